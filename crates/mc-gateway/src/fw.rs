//! The firmware directory (`--fw-dir`): an `fw_update` that names no uploaded image names an
//! image file in it, and the shell reads it for the core (which reads no files). Only plain names
//! reach here (the command parser refuses paths), and a file larger than a transfer can carry is
//! not read.

use std::path::Path;

use ihex_proto::FW_MAX_LEN;

/// Reads `name` from `dir`; `Err` is the reason `command_result` gives.
pub fn read_image(dir: Option<&Path>, name: &str) -> Result<Vec<u8>, String> {
    let dir = dir.ok_or_else(|| {
        "no image of that name was uploaded (ihex/fw/upload/NAME), and the gateway serves no \
         firmware directory (--fw-dir DIR)"
            .to_string()
    })?;
    let path = dir.join(name);
    let len = std::fs::metadata(&path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?
        .len();
    if len > u64::from(FW_MAX_LEN) {
        return Err(format!(
            "{} is {len} bytes; a transfer carries at most {FW_MAX_LEN}",
            path.display()
        ));
    }
    // One local file of at most 384 KiB per update: read in place rather than on a blocking
    // thread.
    std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_from_the_directory_or_says_why_not() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("a.ihex"), b"bytes").unwrap();
        assert_eq!(read_image(Some(dir.path()), "a.ihex").unwrap(), b"bytes");
        let e = read_image(Some(dir.path()), "b.ihex").unwrap_err();
        assert!(e.starts_with("cannot read") && e.contains("b.ihex"), "{e}");
        let e = read_image(None, "a.ihex").unwrap_err();
        assert!(e.contains("--fw-dir") && e.contains("uploaded"), "{e}");
        let big = std::fs::File::create(dir.path().join("big")).unwrap();
        big.set_len(u64::from(FW_MAX_LEN) + 1).unwrap();
        assert!(read_image(Some(dir.path()), "big")
            .unwrap_err()
            .contains("at most"));
    }
}
