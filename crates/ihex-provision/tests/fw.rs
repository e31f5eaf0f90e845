//! `ihex-provision fw keygen | pack | inspect`, run as the lab would run them.

use std::fs;
use std::path::PathBuf;
use std::process::{Command, Output};

fn tool(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ihex-provision"))
        .args(args)
        .output()
        .expect("runs")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

struct Dir(PathBuf);

impl Dir {
    fn new(name: &str) -> Dir {
        let d = std::env::temp_dir().join(format!("ihex-fw-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        fs::create_dir_all(&d).unwrap();
        Dir(d)
    }
    fn path(&self, f: &str) -> String {
        self.0.join(f).display().to_string()
    }
}

impl Drop for Dir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

#[test]
fn keygen_pack_inspect() {
    let d = Dir::new("cycle");
    let out = tool(&["fw", "keygen", "--out", &d.path("lab")]);
    assert!(out.status.success(), "{}", text(&out));
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = fs::metadata(d.path("lab.secret"))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "the secret key is private");
    }
    let again = tool(&["fw", "keygen", "--out", &d.path("lab")]);
    assert!(!again.status.success() && text(&again).contains("refusing to overwrite"));

    let payload: Vec<u8> = (0..3000u32).map(|i| (i * 13) as u8).collect();
    fs::write(d.path("app.bin"), &payload).unwrap();
    let img = d.path("app.img");
    let out = tool(&[
        "fw",
        "pack",
        "--raw",
        &d.path("app.bin"),
        "--board",
        "nucleo-f303re",
        "--version",
        "1.4.2",
        "--protocol",
        "1.0",
        "--key",
        &d.path("lab.secret"),
        "-o",
        &img,
    ]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("version       1.4.2"), "{}", text(&out));
    let bytes = fs::read(&img).unwrap();
    assert_eq!(bytes.len(), 512 + payload.len());
    assert_eq!(&bytes[512..], &payload[..]);

    let ok = tool(&["fw", "inspect", &img, "--key", &d.path("lab.pub")]);
    assert!(ok.status.success(), "{}", text(&ok));
    assert!(text(&ok).contains("signature     ok"));
    // The test key does not verify the lab's image.
    let other = tool(&["fw", "inspect", &img, "--test-key"]);
    assert!(!other.status.success());
    assert!(
        text(&other).contains("signature     BAD"),
        "{}",
        text(&other)
    );
    // A changed payload byte is caught.
    let mut bad = bytes;
    bad[2000] ^= 1;
    fs::write(&img, &bad).unwrap();
    let corrupt = tool(&["fw", "inspect", &img]);
    assert!(!corrupt.status.success());
    assert!(text(&corrupt).contains("payload hash  BAD"));
}

#[test]
fn pack_refuses_without_a_key_or_the_header_fields() {
    let d = Dir::new("refuse");
    fs::write(d.path("app.bin"), [1u8; 64]).unwrap();
    let no_key = tool(&[
        "fw",
        "pack",
        "--raw",
        &d.path("app.bin"),
        "--board",
        "sim",
        "--version",
        "1.0.0",
        "--protocol",
        "1.0",
    ]);
    assert!(!no_key.status.success());
    assert!(text(&no_key).contains("--key"), "{}", text(&no_key));
    let no_version = tool(&["fw", "pack", "--raw", &d.path("app.bin"), "--test-key"]);
    assert!(!no_version.status.success());
    assert!(text(&no_version).contains("--raw needs"));
    let not_elf = tool(&["fw", "pack", &d.path("app.bin"), "--test-key"]);
    assert!(!not_elf.status.success());
    assert!(text(&not_elf).contains("ELF"), "{}", text(&not_elf));
}

#[test]
fn update_checks_the_image_and_needs_a_gateway() {
    let d = Dir::new("update");
    // Not an image: refused before any broker is asked.
    fs::write(d.path("junk.img"), b"not an image").unwrap();
    let out = tool(&[
        "fw",
        "update",
        &d.path("junk.img"),
        "--broker",
        "127.0.0.1:1",
    ]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("is not an image to send"),
        "{}",
        text(&out)
    );
    // Larger than a slot: refused before reading it as an image.
    fs::write(d.path("big.img"), vec![0u8; 128 * 1024 + 1]).unwrap();
    let out = tool(&[
        "fw",
        "update",
        &d.path("big.img"),
        "--broker",
        "127.0.0.1:1",
    ]);
    assert!(!out.status.success());
    assert!(text(&out).contains("at most 131072"), "{}", text(&out));
    // A good image, but no broker: a clear error, not a hang.
    fs::write(d.path("app.bin"), [7u8; 100]).unwrap();
    let img = d.path("app.img");
    let packed = tool(&[
        "fw",
        "pack",
        "--raw",
        &d.path("app.bin"),
        "--board",
        "sim",
        "--version",
        "1.0.0",
        "--protocol",
        "1.2",
        "--test-key",
        "-o",
        &img,
    ]);
    assert!(packed.status.success(), "{}", text(&packed));
    let out = tool(&["fw", "update", &img, "--broker", "127.0.0.1:1"]);
    assert!(!out.status.success());
    assert!(text(&out).contains("MQTT"), "{}", text(&out));
}

#[test]
fn demo_image_is_a_simulated_firmware_signed_with_the_test_key() {
    use ihex_image::sim::SimFirmware;
    let d = Dir::new("demo");
    for (reverts, file) in [(false, "good.img"), (true, "bad.img")] {
        let path = d.path(file);
        let mut args = vec!["fw", "demo-image", "--version", "0.2.0", "--size", "4000"];
        args.extend(["--out", &path]);
        if reverts {
            args.push("--reverts");
        }
        let out = tool(&args);
        assert!(out.status.success(), "{}", text(&out));
        let image = fs::read(d.path(file)).unwrap();
        let check =
            ihex_image::Inspection::of(&image, Some(&ihex_image::test_key::PUBLIC)).unwrap();
        assert!(check.is_good(), "{check}");
        assert_eq!(check.header.board, ihex_image::Board::SIM);
        assert_eq!(check.header.version.to_string(), "0.2.0");
        // What the simulated board reads from the payload to decide whether it confirms.
        let payload = &image[ihex_image::HEADER_BLOCK..];
        assert_eq!(
            SimFirmware::parse(payload),
            Some(SimFirmware { confirms: !reverts })
        );
    }
}

/// Release notes given to `pack` travel in the image (format 2) and `inspect` shows them; `fw
/// update` shows them before it connects (here: to no broker).
#[test]
fn release_notes_are_packed_and_shown() {
    let d = Dir::new("notes");
    fs::write(d.path("app.bin"), [7u8; 100]).unwrap();
    let img = d.path("app.img");
    let packed = tool(&[
        "fw",
        "pack",
        "--raw",
        &d.path("app.bin"),
        "--board",
        "sim",
        "--version",
        "1.0.0",
        "--protocol",
        "1.2",
        "--test-key",
        "--notes",
        "first line\nsecond line",
        "-o",
        &img,
    ]);
    assert!(packed.status.success(), "{}", text(&packed));
    assert_eq!(fs::read(&img).unwrap()[4], 2, "format 2");
    let out = tool(&["fw", "inspect", &img, "--test-key"]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(
        text(&out).contains("release notes first line"),
        "{}",
        text(&out)
    );
    let out = tool(&["fw", "update", &img, "--broker", "127.0.0.1:1"]);
    let t = text(&out);
    assert!(
        t.contains("release notes:\n  first line\n  second line"),
        "{t}"
    );
    // The demo image takes them too.
    let demo = d.path("demo.img");
    let out = tool(&[
        "fw",
        "demo-image",
        "--version",
        "0.2.0",
        "--notes",
        "demo notes",
        "--out",
        &demo,
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let image = fs::read(&demo).unwrap();
    let check = ihex_image::Inspection::of(&image, Some(&ihex_image::test_key::PUBLIC)).unwrap();
    assert_eq!(check.notes.as_deref(), Some("demo notes"));
}

#[test]
fn a_closed_pipe_ends_the_output_not_the_program() {
    use std::process::Stdio;
    let d = Dir::new("pipe");
    let mut child = Command::new(env!("CARGO_BIN_EXE_ihex-provision"))
        .args([
            "fw",
            "demo-image",
            "--version",
            "1.0.0",
            "--out",
            &d.path("x.img"),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("runs");
    // The reader goes away before the first line, as `| head -0` would.
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{:?} {}", out.status, text(&out));
    assert!(fs::metadata(d.path("x.img")).is_ok(), "the work was done");
}
