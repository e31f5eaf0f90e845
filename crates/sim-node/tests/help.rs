//! `sim-node --help` runs and names its options and where the island format is described.

use std::process::Command;

#[test]
fn help_names_the_options_and_the_island_format() {
    let out = Command::new(env!("CARGO_BIN_EXE_sim-node"))
        .arg("--help")
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    for needle in ["--iface", "--island", "SIM_NODE_IFACE", "docs/sim-node.md"] {
        assert!(text.contains(needle), "--help lacks {needle}:\n{text}");
    }
}
