//! Tidy tests (rust-analyzer's `xtask/src/tidy.rs` idea): facts the compiler cannot check — docs
//! that must name every stage, verb and step, every script's and binary's `--help`, comments that
//! restate data — checked as plain `#[test]`s, so `cargo test` (the `host` stage) catches the drift.

use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use clap::CommandFactory;

use crate::{cmd, fuzz, lint, Cli, Stage, FIRMWARE_CHECKS};

fn read(rel: &str) -> String {
    let path = cmd::root().join(rel);
    fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Repository files tracked by git, relative to the root.
fn tracked_files() -> Vec<String> {
    let out = Command::new("git")
        .arg("-C")
        .arg(cmd::root())
        .args(["ls-files", "-z"])
        .output()
        .expect("git ls-files (the tidy tests need the repository's git metadata)");
    assert!(out.status.success(), "git ls-files failed");
    String::from_utf8_lossy(&out.stdout)
        .split('\0')
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect()
}

/// The first cells (without backticks) of the markdown table whose header's first cell is `header`.
fn table_keys(doc: &str, header: &str) -> Vec<String> {
    let mut keys = Vec::new();
    let mut inside = false;
    for line in doc.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if !line.trim_start().starts_with('|') || cells.len() < 3 {
            if inside {
                break;
            }
            continue;
        }
        if !inside {
            inside = cells[1] == header;
            continue;
        }
        if cells[1].starts_with("---") {
            continue;
        }
        keys.push(cells[1].trim_matches('`').to_string());
    }
    keys
}

#[test]
fn cli_is_well_formed() {
    Cli::command().debug_assert();
}

#[test]
fn testing_md_lists_every_stage_in_run_order() {
    let doc = read("docs/testing.md");
    let documented = table_keys(&doc, "stage");
    let stages: Vec<String> = Stage::all().iter().map(|s| s.name()).collect();
    assert_eq!(
        documented, stages,
        "docs/testing.md's stage table must list exactly the stages of `cargo xtask test`, in order"
    );
}

#[test]
fn testing_md_lists_every_verb() {
    let doc = read("docs/testing.md");
    let documented = table_keys(&doc, "verb");
    let verbs: Vec<String> = Cli::command()
        .get_subcommands()
        .map(|c| format!("cargo xtask {}", c.get_name()))
        .collect();
    for verb in &verbs {
        assert!(
            documented.iter().any(|d| d.starts_with(verb.as_str())),
            "docs/testing.md's verb table lacks `{verb}`"
        );
    }
    for d in &documented {
        assert!(
            verbs.iter().any(|v| d.starts_with(v.as_str())),
            "docs/testing.md documents `{d}`, which xtask does not have"
        );
    }
}

#[test]
fn testing_md_shows_every_lint_command_and_firmware_check() {
    let doc = read("docs/testing.md");
    for step in lint::STEPS {
        let line = format!("cargo {}", step.args.join(" "));
        assert!(
            doc.contains(&format!("`{line}`")),
            "docs/testing.md lacks the lint step `{line}` ({})",
            step.what
        );
        if step.dir != "." {
            assert!(
                doc.contains(&format!("`{}`", step.dir)),
                "docs/testing.md does not say where `{line}` runs (`{}`)",
                step.dir
            );
        }
    }
    for (what, dir, prog, _) in FIRMWARE_CHECKS {
        let path = Path::new(cmd::FIRMWARE).join(dir);
        let shown = match prog.strip_prefix("./") {
            Some(script) => path.join(script),
            None => path,
        };
        let shown = shown.to_string_lossy().replace("/./", "/");
        assert!(
            doc.contains(&format!("`{shown}")),
            "docs/testing.md's firmware stage does not name `{shown}` ({what})"
        );
    }
}

#[test]
fn every_fuzz_workspace_is_built_and_formatted() {
    let found: Vec<String> = tracked_files()
        .into_iter()
        .filter(|f| f.ends_with("/fuzz/Cargo.toml") && read(f).contains("cargo-fuzz = true"))
        .map(|f| f.trim_end_matches("/Cargo.toml").to_string())
        .collect();
    assert!(
        found.iter().any(|f| f == "crates/ihex-proto/fuzz"),
        "{found:?}"
    );
    for ws in &found {
        assert!(
            fuzz::WORKSPACES.contains(&ws.as_str()),
            "{ws} is a cargo-fuzz workspace missing from xtask's fuzz::WORKSPACES (built by the lint stage)"
        );
        assert!(
            lint::STEPS
                .iter()
                .any(|s| s.dir == ws && s.args.first() == Some(&"fmt")),
            "{ws} has no fmt step in lint::STEPS"
        );
    }
    for ws in fuzz::WORKSPACES {
        assert!(
            found.iter().any(|f| f == ws),
            "fuzz::WORKSPACES names {ws}, which is no tracked cargo-fuzz workspace"
        );
    }
}

/// `(Type, NAME N)` labels of a diagram: (type, constant, value).
fn channel_labels(diagram: &str) -> Vec<(String, String, usize)> {
    let mut out = Vec::new();
    for part in diagram.split('(').skip(1) {
        let Some((inside, _)) = part.split_once(')') else {
            continue;
        };
        let Some((ty, size)) = inside.split_once(", ") else {
            continue;
        };
        let mut words = size.split_whitespace();
        let (Some(name), Some(value), None) = (words.next(), words.next(), words.next()) else {
            continue;
        };
        let is_const = name.chars().all(|c| c.is_ascii_uppercase() || c == '_');
        if let (true, Ok(value)) = (is_const, value.parse()) {
            out.push((ty.trim().to_string(), name.to_string(), value));
        }
    }
    out
}

/// `const NAME: usize = VALUE;` definitions (with or without `pub`) in the Rust files under `dirs`,
/// test modules included (a name defined twice is reported by the caller).
fn usize_consts(dirs: &[&str]) -> Vec<(String, String, PathBuf)> {
    let mut files = Vec::new();
    for dir in dirs {
        rust_files(&cmd::root().join(dir), &mut files);
    }
    let mut out = Vec::new();
    for f in files {
        for line in fs::read_to_string(&f).unwrap_or_default().lines() {
            let line = line.trim();
            let rest = line.strip_prefix("pub ").unwrap_or(line);
            let Some(rest) = rest.strip_prefix("const ") else {
                continue;
            };
            if let Some((name, value)) = rest.split_once(": usize = ") {
                let value = value.trim_end_matches(';').replace('_', "");
                out.push((name.to_string(), value, f.clone()));
            }
        }
    }
    out
}

#[test]
fn gateway_diagram_names_the_channels_the_code_sizes() {
    let doc = read("docs/gateway.md");
    let inside = doc
        .split("## Inside")
        .nth(1)
        .and_then(|s| s.split("```").nth(1))
        .expect("docs/gateway.md has a diagram under `## Inside`");
    let labels = channel_labels(inside);
    assert!(labels.len() >= 5, "{labels:?}");
    let consts = usize_consts(&["crates/mc-gateway/src", "crates/ihex-gateway-core/src"]);
    let gateway_src = {
        let mut files = Vec::new();
        rust_files(&cmd::root().join("crates/mc-gateway/src"), &mut files);
        files
            .iter()
            .map(|f| fs::read_to_string(f).unwrap_or_default())
            .collect::<Vec<_>>()
            .join("\n")
    };
    for (ty, name, value) in &labels {
        let defs: Vec<_> = consts.iter().filter(|(n, _, _)| n == name).collect();
        assert_eq!(
            defs.len(),
            1,
            "docs/gateway.md's diagram names `{name}`: the code should define it once, found {defs:?}"
        );
        assert_eq!(
            defs[0].1,
            value.to_string(),
            "docs/gateway.md's diagram says {name} is {value}; {} says {}",
            defs[0].2.display(),
            defs[0].1
        );
        assert!(
            gateway_src.contains(&format!("Sender<{ty}>"))
                || gateway_src.contains(&format!("Sender<Arc<{ty}>>")),
            "docs/gateway.md's diagram says a channel carries `{ty}`: no `Sender<{ty}>` in mc-gateway"
        );
    }
    // The other way: every channel the gateway sizes by a constant is in the diagram.
    for kind in ["mpsc::channel(", "broadcast::channel(", "link.spawn("] {
        for part in gateway_src.split(kind).skip(1) {
            let arg: String = part
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if arg.len() > 1 && arg.chars().all(|c| c.is_ascii_uppercase() || c == '_') {
                assert!(
                    labels.iter().any(|(_, n, _)| *n == arg),
                    "mc-gateway sizes a channel by `{arg}` ({kind}...), which docs/gateway.md's \
                     `## Inside` diagram does not name"
                );
            }
        }
    }
}

#[test]
fn channel_labels_read_type_constant_and_value() {
    assert_eq!(
        channel_labels("a ──(CanInput, CAN_INPUTS 1024)──► (demo: x, y) (Transmit, same channel)"),
        [("CanInput".to_string(), "CAN_INPUTS".to_string(), 1024)]
    );
}

/// The comment block at the top of a script (after the shebang and an optional re-exec line), without
/// its `# `: what `--help` must print. Mirrors the scripts'
/// `sed -n '/^# /,/^[^#]/{/^[^#]/q;s/^# \{0,1\}//p}' "$0"`.
fn header(script: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in script.lines() {
        if !inside {
            inside = line.starts_with("# ");
            if !inside {
                continue;
            }
        }
        if !line.is_empty() && !line.starts_with('#') {
            break;
        }
        if let Some(rest) = line.strip_prefix('#') {
            out.push(rest.strip_prefix(' ').unwrap_or(rest).to_string());
        }
    }
    out
}

/// Runs `c` with a deadline (a script that ignores `--help` must not run its real job for long).
fn output_within(mut c: Command, limit: Duration) -> (Option<i32>, String, String) {
    let mut child = c
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let pipe = |r: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut s = String::new();
            if let Some(mut r) = r {
                let _ = r.read_to_string(&mut s);
            }
            s
        })
    };
    let out = pipe(child.stdout.take().map(|p| Box::new(p) as _));
    let err = pipe(child.stderr.take().map(|p| Box::new(p) as _));
    let deadline = Instant::now() + limit;
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break Some(status);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    (
        status.and_then(|s| s.code()),
        out.join().unwrap_or_default(),
        err.join().unwrap_or_default(),
    )
}

/// Tracked files that start with a shell shebang.
fn scripts() -> Vec<String> {
    tracked_files()
        .into_iter()
        .filter(|f| {
            let mut head = [0u8; 32];
            let n = fs::File::open(cmd::root().join(f))
                .and_then(|mut file| file.read(&mut head))
                .unwrap_or(0);
            let head = String::from_utf8_lossy(&head[..n]);
            head.starts_with("#!") && (head.contains("sh\n") || head.contains("bash"))
        })
        .collect()
}

#[test]
fn every_script_prints_its_usage() {
    let scripts = scripts();
    assert!(
        scripts.iter().any(|s| s == "deploy/build-pi.sh"),
        "script discovery found {scripts:?}"
    );
    for rel in scripts {
        let text = read(&rel);
        // Never start a script that would do its real job instead of printing help.
        assert!(
            text.contains("--help)"),
            "{rel} does not handle --help (add the usage one-liner of deploy/build-pi.sh)"
        );
        let usage = header(&text);
        assert!(
            usage.iter().any(|l| l.contains(&rel)),
            "{rel}: its header comment (the usage) should show how to call it, by its path {rel}"
        );
        let mut c = Command::new("bash");
        c.arg(cmd::root().join(&rel)).arg("--help");
        let (code, out, err) = output_within(c, Duration::from_secs(30));
        assert_eq!(code, Some(0), "{rel} --help: exit {code:?}; stderr: {err}");
        let printed: Vec<&str> = out.lines().collect();
        assert_eq!(
            printed, usage,
            "{rel} --help must print exactly its header comment"
        );
    }
}

/// Workspace binaries (package folder, binary name) from `cargo metadata`.
fn workspace_binaries() -> Vec<(PathBuf, String)> {
    let out = cmd::output(cmd::cargo().current_dir(cmd::root()).args([
        "metadata",
        "--no-deps",
        "--format-version",
        "1",
    ]))
    .expect("cargo metadata");
    let meta: serde_json::Value = serde_json::from_str(&out).expect("metadata JSON");
    let mut bins = Vec::new();
    for p in meta["packages"].as_array().expect("packages") {
        let dir = PathBuf::from(p["manifest_path"].as_str().expect("manifest_path"))
            .parent()
            .expect("package folder")
            .to_path_buf();
        for t in p["targets"].as_array().expect("targets") {
            if t["kind"]
                .as_array()
                .is_some_and(|k| k.iter().any(|k| k == "bin"))
            {
                bins.push((dir.clone(), t["name"].as_str().expect("name").to_string()));
            }
        }
    }
    bins
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = entry.path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
}

#[test]
fn every_binary_has_a_test_of_its_help() {
    let bins = workspace_binaries();
    assert!(bins.iter().any(|(_, b)| b == "mc-gateway"), "{bins:?}");
    for (dir, bin) in bins {
        if bin == "xtask" {
            continue; // `cli_is_well_formed` and this file test it.
        }
        let mut files = Vec::new();
        rust_files(&dir.join("tests"), &mut files);
        let exe = format!("CARGO_BIN_EXE_{bin}");
        let tested = files.iter().any(|f| {
            let text = fs::read_to_string(f).unwrap_or_default();
            text.contains(&exe) && text.contains("\"--help\"")
        });
        assert!(
            tested,
            "no test under {}/tests runs `{bin} --help` (env!(\"{exe}\"))",
            dir.display()
        );
    }
}

#[test]
fn every_package_declares_the_msrv() {
    let out = cmd::output(cmd::cargo().current_dir(cmd::root()).args([
        "metadata",
        "--no-deps",
        "--format-version",
        "1",
    ]))
    .expect("cargo metadata");
    let meta: serde_json::Value = serde_json::from_str(&out).expect("metadata JSON");
    let msrv = lint::declared_msrv().expect("declared MSRV");
    for p in meta["packages"].as_array().expect("packages") {
        assert_eq!(
            p["rust_version"].as_str(),
            Some(msrv.as_str()),
            "{} should inherit the workspace's rust-version (`rust-version.workspace = true`): \
             the lint's MSRV check covers that version only",
            p["name"]
        );
    }
    let fw = read(&format!("{}/Cargo.toml", cmd::FIRMWARE));
    assert!(
        fw.lines()
            .any(|l| l.replace(' ', "") == format!("rust-version=\"{msrv}\"")),
        "{}/Cargo.toml should declare rust-version = \"{msrv}\", the version the lint checks it with",
        cmd::FIRMWARE
    );
}

/// An island file's elements: (id, unconfigured).
fn island_elements(text: &str) -> Vec<(String, bool)> {
    let mut elements: Vec<(String, bool)> = Vec::new();
    for line in text.lines().map(str::trim) {
        if line.starts_with("[[") {
            elements.push((String::new(), false));
        } else if let (Some(last), Some(v)) = (elements.last_mut(), line.strip_prefix("id")) {
            if let Some(v) = v.trim_start().strip_prefix('=') {
                last.0 = v.trim().trim_matches('"').to_string();
            }
        } else if let Some(last) = elements.last_mut() {
            if line.replace(' ', "") == "unconfigured=true" {
                last.1 = true;
            }
        }
    }
    elements
}

/// Words of a comment that look like node IDs as the API writes them: 3 hex digits, at least one a
/// decimal digit (so `add` or `bad` are words, `7f0` and `111` are IDs).
fn node_id_words(comment: &str) -> Vec<String> {
    comment
        .split(|c: char| !c.is_ascii_alphanumeric())
        .filter(|w| {
            w.len() == 3
                && w.chars().all(|c| c.is_ascii_hexdigit())
                && w.chars().any(|c| c.is_ascii_digit())
        })
        .map(|w| w.to_ascii_lowercase())
        .collect()
}

#[test]
fn island_comments_name_their_own_elements() {
    let islands: Vec<String> = tracked_files()
        .into_iter()
        .filter(|f| f.ends_with(".toml") && read(f).contains("[[static]]"))
        .collect();
    assert!(islands.iter().any(|f| f == "deploy/arm64-island.toml"));
    for rel in islands {
        let text = read(&rel);
        let elements = island_elements(&text);
        let comments = text.lines().filter_map(|l| l.trim().strip_prefix('#'));
        for comment in comments {
            // "X is factory-fresh": X must be an element that boots without a node ID.
            for clause in comment.split([';', '.', ',']) {
                if !clause.contains("factory-fresh") {
                    continue;
                }
                for id in node_id_words(clause) {
                    assert!(
                        elements.iter().any(|(e, un)| *e == id && *un),
                        "{rel}: the comment calls {id} factory-fresh, but no element {id} has \
                         `unconfigured = true`: {comment}"
                    );
                }
            }
            // deploy/check-arm64.sh's island: its comment tells the roles, each by its element.
            if rel == "deploy/arm64-island.toml" {
                for id in node_id_words(comment) {
                    assert!(
                        elements.iter().any(|(e, _)| *e == id),
                        "{rel}: the comment names {id}, which is no element of the island: {comment}"
                    );
                }
            }
        }
    }
}

#[test]
fn changelog_and_protocol_doc_carry_the_protocol_version() {
    let (major, minor) = ihex_proto::PROTOCOL_VERSION;
    let version = format!("{major}.{minor}");
    let changelog = read("CHANGELOG.md");
    let can = changelog
        .split("\n## ")
        .find(|s| s.starts_with("CAN protocol"))
        .expect("CHANGELOG.md has a `## CAN protocol` section");
    let newest = can
        .lines()
        .filter_map(|l| l.strip_prefix("### ["))
        .find(|l| !l.starts_with("Unreleased"))
        .and_then(|l| l.split(']').next())
        .expect("a released CAN protocol version in CHANGELOG.md");
    assert_eq!(
        newest, version,
        "ihex_proto::PROTOCOL_VERSION is {version} but CHANGELOG.md's newest CAN protocol release is {newest}"
    );
    assert!(
        read("docs/protocol.md").contains(&format!("Protocol version: **{version}**")),
        "docs/protocol.md does not state protocol version {version}"
    );
}

#[test]
fn header_stops_at_the_first_line_of_code() {
    let script = "#!/bin/sh\n[ -n x ] || exec bash\n# Does it.\n#\n#   run.sh --x\nset -e\n# --- later ---\n";
    assert_eq!(header(script), ["Does it.", "", "  run.sh --x"]);
}

#[test]
fn node_id_words_skip_plain_words_and_numbers_of_other_lengths() {
    assert_eq!(
        node_id_words("111 answers; 7f0 is factory-fresh, add 2 or 1234"),
        ["111", "7f0"]
    );
}
