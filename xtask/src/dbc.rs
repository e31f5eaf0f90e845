//! `cargo xtask dbc`: writes `docs/ihex.dbc` from `ihex_proto::schema` (one message per kind), checks
//! that the committed file is what the generator writes (`--check`, part of the host stage), and
//! prints a DBC with exact IDs for one island's nodes (`--island 111,112,2`).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use ihex_proto::dbc::{self, Layout};
use ihex_proto::NodeId;

use crate::cmd;

/// The committed DBC file, relative to the workspace root.
pub const PATH: &str = "docs/ihex.dbc";

/// The DBC text of `layout`.
pub fn generate(layout: Layout<'_>) -> Result<String> {
    let mut text = String::new();
    dbc::write(&mut text, layout).context("generating the DBC")?;
    Ok(text)
}

fn committed() -> PathBuf {
    cmd::root().join(PATH)
}

/// Writes `docs/ihex.dbc`.
pub fn write() -> Result<()> {
    let path = committed();
    let text = generate(Layout::ByKind)?;
    std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    println!("xtask: wrote {PATH}");
    Ok(())
}

/// Fails when `docs/ihex.dbc` differs from what [`write()`] would write.
pub fn check() -> Result<()> {
    let path = committed();
    let on_disk =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    if on_disk != generate(Layout::ByKind)? {
        bail!(
            "{PATH} differs from what ihex-proto's schema generates: run `cargo xtask dbc` and \
             commit the result"
        );
    }
    println!("xtask: {PATH} is up to date");
    Ok(())
}

/// Prints the DBC of an island (exact IDs) to stdout.
pub fn island(nodes: &[NodeId]) -> Result<()> {
    let mut nodes = nodes.to_vec();
    nodes.sort();
    nodes.dedup();
    print!("{}", generate(Layout::Island(&nodes))?);
    Ok(())
}
