//! `ihex-bench --help` and each subcommand's `--help` run and name what they do.

use std::process::Command;

fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_ihex-bench"))
        .args(args)
        .arg("--help")
        .output()
        .unwrap();
    assert!(out.status.success(), "{args:?} --help failed: {out:?}");
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn help_lists_every_subcommand_and_each_has_its_own() {
    let text = help(&[]);
    for (cmd, option) in [
        ("live", "--gateway"),
        ("workload", "--path"),
        ("callgrind", "--out"),
        ("report", "--dir"),
    ] {
        assert!(text.contains(cmd), "--help lacks {cmd}:\n{text}");
        let sub = help(&[cmd]);
        assert!(sub.contains(option), "{cmd} --help lacks {option}:\n{sub}");
    }
}
