//! The Pi build (`--no-default-features`, with or without `web` and `sila`) links neither the embedded broker (rumqttd) nor the
//! simulator (sim-node): checked on cargo's own dependency tree, so a new dependency path that drags
//! either in fails here.

use std::process::Command;

fn normal_deps(features: &[&str]) -> String {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let manifest = concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml");
    let out = Command::new(cargo)
        .args([
            "tree",
            "--offline",
            "--manifest-path",
            manifest,
            "-p",
            "mc-gateway",
        ])
        .args(["-e", "normal", "--prefix", "none"])
        .args(features)
        .output()
        .expect("run cargo tree");
    assert!(
        out.status.success(),
        "cargo tree failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("cargo tree prints UTF-8")
}

fn has(tree: &str, krate: &str) -> bool {
    tree.lines()
        .any(|l| l.split_whitespace().next() == Some(krate))
}

#[test]
fn the_pi_build_links_neither_the_broker_nor_the_simulator() {
    // As deploy/build-pi.sh builds it (with the island view and the SiLA server), and with
    // --no-web --no-sila.
    for features in [
        &["--no-default-features", "--features", "web,sila"][..],
        &["--no-default-features"][..],
    ] {
        let pi = normal_deps(features);
        let full = features.contains(&"web,sila");
        assert!(has(&pi, "ihex-gateway-core"), "{pi}");
        assert_eq!(has(&pi, "axum"), full, "{pi}");
        assert_eq!(has(&pi, "tonic"), full, "{pi}");
        // protox and the code generator run in the build script only.
        assert!(!has(&pi, "protox"), "{pi}");
        for demo_only in ["rumqttd", "sim-node"] {
            assert!(
                !has(&pi, demo_only),
                "{demo_only} is in the Pi build ({features:?}):\n{pi}"
            );
        }
    }
    // The check can fail: the default build does have them.
    let default = normal_deps(&[]);
    assert!(
        has(&default, "rumqttd") && has(&default, "sim-node"),
        "{default}"
    );
}

/// The core stays sans-IO: no runtime, socket or MQTT crate anywhere in its tree.
#[test]
fn the_core_depends_on_no_io_crate() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let manifest = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../ihex-gateway-core/Cargo.toml"
    );
    let out = Command::new(cargo)
        .args([
            "tree",
            "--offline",
            "--manifest-path",
            manifest,
            "-p",
            "ihex-gateway-core",
        ])
        .args(["-e", "normal", "--prefix", "none"])
        .output()
        .expect("run cargo tree");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let tree = String::from_utf8_lossy(&out.stdout);
    for io in [
        "tokio",
        "rumqttc",
        "rumqttd",
        "socketcan",
        "sim-node",
        "mio",
    ] {
        assert!(!has(&tree, io), "{io} is in the core's tree:\n{tree}");
    }
}
