//! The workspace's own programs for tests that run them as a user would: found through an
//! environment variable (the vcan stage sets it to the copy it carries into the microVM), else
//! beside the test binary's `deps/` folder, where `cargo test --workspace` builds them.

use std::path::{Path, PathBuf};

/// Environment variable naming the `ihex-provision` binary.
pub const PROVISION_BIN_ENV: &str = "IHEX_PROVISION_BIN";

/// The program `name`: the path in `env` when set, else `name` in the target folder of the
/// running test binary.
pub fn workspace_binary(name: &str, env: &str) -> Result<PathBuf, String> {
    if let Some(p) = std::env::var_os(env) {
        return Ok(p.into());
    }
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    match exe.parent().and_then(Path::parent).map(|d| d.join(name)) {
        Some(p) if p.is_file() => Ok(p),
        _ => Err(format!(
            "no {name} binary: build it (`cargo build -p {name}`, next to this test's target \
             folder) or set {env}; `cargo xtask test --stage vcan` does both"
        )),
    }
}
