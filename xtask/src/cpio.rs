//! A minimal writer of `newc` cpio archives, the format the Linux kernel unpacks as an initramfs.
//!
//! Every entry is owned by root; parent directories are emitted before their contents because the
//! kernel's unpacker does not create them. Several archives may be concatenated into one initrd.

use std::collections::BTreeSet;
use std::fs::File;
use std::io::{self, BufWriter, Read, Write};
use std::path::Path;

const S_IFDIR: u32 = 0o040000;
const S_IFREG: u32 = 0o100000;
const S_IFLNK: u32 = 0o120000;
const S_IFCHR: u32 = 0o020000;

/// Writes a newc archive entry by entry; call [`Cpio::finish`] to write the trailer.
pub struct Cpio<W: Write> {
    out: W,
    written: u64,
    ino: u32,
    dirs: BTreeSet<String>,
}

/// Archive paths are relative (`bin/sh`); leading slashes are dropped.
fn clean(path: &str) -> &str {
    path.trim_start_matches('/')
}

impl Cpio<BufWriter<File>> {
    /// Creates (truncates) the archive file at `path`.
    pub fn create(path: &Path) -> io::Result<Self> {
        Ok(Cpio::new(BufWriter::with_capacity(
            1 << 20,
            File::create(path)?,
        )))
    }
}

impl<W: Write> Cpio<W> {
    /// An archive written to `out`.
    pub fn new(out: W) -> Self {
        Cpio {
            out,
            written: 0,
            ino: 1,
            dirs: BTreeSet::new(),
        }
    }

    /// Marks directories that an earlier archive of the same initrd already created.
    pub fn assume_dirs<'a>(&mut self, dirs: impl IntoIterator<Item = &'a str>) {
        self.dirs
            .extend(dirs.into_iter().map(|d| clean(d).to_string()));
    }

    fn write_all(&mut self, b: &[u8]) -> io::Result<()> {
        self.out.write_all(b)?;
        self.written += b.len() as u64;
        Ok(())
    }

    fn pad(&mut self) -> io::Result<()> {
        let n = ((4 - self.written % 4) % 4) as usize;
        self.write_all(&[0u8; 3][..n])
    }

    fn header(&mut self, name: &str, mode: u32, size: u64, rdev: (u32, u32)) -> io::Result<()> {
        let size = u32::try_from(size).map_err(|_| {
            io::Error::new(io::ErrorKind::InvalidInput, format!("{name}: over 4 GiB"))
        })?;
        let nlink = if mode & S_IFDIR != 0 { 2 } else { 1 };
        let ino = self.ino;
        self.ino += 1;
        let fields = [
            ino,
            mode,
            0,
            0,
            nlink,
            0,
            size,
            0,
            0,
            rdev.0,
            rdev.1,
            name.len() as u32 + 1,
            0,
        ];
        let mut h = String::with_capacity(110);
        h.push_str("070701");
        for f in fields {
            h.push_str(&format!("{f:08x}"));
        }
        self.write_all(h.as_bytes())?;
        self.write_all(name.as_bytes())?;
        self.write_all(&[0])?;
        self.pad()
    }

    /// Adds a directory and any missing parents.
    pub fn dir(&mut self, path: &str) -> io::Result<()> {
        let path = clean(path).trim_end_matches('/');
        if path.is_empty() || self.dirs.contains(path) {
            return Ok(());
        }
        if let Some((parent, _)) = path.rsplit_once('/') {
            self.dir(parent)?;
        }
        self.header(path, S_IFDIR | 0o755, 0, (0, 0))?;
        self.dirs.insert(path.to_string());
        Ok(())
    }

    fn parent(&mut self, path: &str) -> io::Result<()> {
        match clean(path).rsplit_once('/') {
            Some((parent, _)) => self.dir(parent),
            None => Ok(()),
        }
    }

    /// Adds a regular file with the given contents.
    pub fn bytes(&mut self, path: &str, mode: u32, data: &[u8]) -> io::Result<()> {
        self.parent(path)?;
        self.header(
            clean(path),
            S_IFREG | (mode & 0o7777),
            data.len() as u64,
            (0, 0),
        )?;
        self.write_all(data)?;
        self.pad()
    }

    /// Adds a regular file copied from the host (symlinks followed), keeping its permission bits.
    pub fn file(&mut self, path: &str, src: &Path) -> io::Result<()> {
        use std::os::unix::fs::PermissionsExt;
        let mut f = File::open(src)
            .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", src.display())))?;
        let meta = f.metadata()?;
        self.parent(path)?;
        self.header(
            clean(path),
            S_IFREG | (meta.permissions().mode() & 0o7777),
            meta.len(),
            (0, 0),
        )?;
        let copied = io::copy(&mut (&mut f).take(meta.len()), &mut self.out)?;
        if copied != meta.len() {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!("{} shrank while being archived", src.display()),
            ));
        }
        self.written += copied;
        self.pad()
    }

    /// Adds a symbolic link.
    pub fn symlink(&mut self, path: &str, target: &str) -> io::Result<()> {
        self.parent(path)?;
        self.header(clean(path), S_IFLNK | 0o777, target.len() as u64, (0, 0))?;
        self.write_all(target.as_bytes())?;
        self.pad()
    }

    /// Adds a character device node.
    pub fn char_dev(&mut self, path: &str, major: u32, minor: u32) -> io::Result<()> {
        self.parent(path)?;
        self.header(clean(path), S_IFCHR | 0o600, 0, (major, minor))
    }

    /// Writes the trailer and returns the writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.header("TRAILER!!!", 0, 0, (0, 0))?;
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_are_aligned_and_parents_come_first() {
        let mut c = Cpio::new(Vec::new());
        c.bytes("/a/b/file", 0o644, b"hello").unwrap();
        let out = c.finish().unwrap();
        let text = String::from_utf8_lossy(&out);
        let a = text.find("a\0").unwrap();
        let ab = text.find("a/b\0").unwrap();
        let f = text.find("a/b/file\0").unwrap();
        assert!(a < ab && ab < f);
        assert_eq!(out.len() % 4, 0);
        // The file's header: magic, then its mode field (8th..16th hex digit after the inode).
        let hdr = &text[f - 110..f];
        assert!(hdr.starts_with("070701"));
        assert_eq!(&hdr[14..22], "000081a4");
        assert_eq!(&hdr[54..62], "00000005");
        assert!(text.contains("hello"));
        // 110-byte header + 11-byte name, padded to a multiple of 4.
        assert!(text.ends_with("TRAILER!!!\0\0\0\0"));
    }

    #[test]
    fn directories_are_written_once() {
        let mut c = Cpio::new(Vec::new());
        c.assume_dirs(["x"]);
        c.bytes("x/y/1", 0o644, b"").unwrap();
        c.bytes("x/y/2", 0o644, b"").unwrap();
        let text = String::from_utf8_lossy(&c.finish().unwrap()).into_owned();
        assert_eq!(text.matches("x/y\0").count(), 1);
        assert!(!text.contains("x\0"), "x was assumed present");
    }
}
