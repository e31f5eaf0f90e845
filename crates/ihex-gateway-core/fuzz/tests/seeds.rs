//! The seed corpus as a regression test on stable: every file of `seeds/<target>/` through the
//! target's check, so a change that breaks one fails `cargo test` here without nightly.

use std::fs;
use std::path::Path;

fn seeds(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("seeds")
        .join(target);
    let mut files: Vec<_> = fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("a readable seed folder").path())
        .collect();
    files.sort();
    files
        .into_iter()
        .map(|p| {
            let name = p
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            let bytes = fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            (name, bytes)
        })
        .collect()
}

#[test]
fn every_command_seed_gets_exactly_one_answer() {
    let seeds = seeds("command");
    assert!(seeds.len() >= 10, "only {} seeds", seeds.len());
    for (name, bytes) in seeds {
        eprintln!("seed {name}");
        ihex_gateway_core_fuzz::command(&bytes);
    }
}
