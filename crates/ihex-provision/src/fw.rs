//! `ihex-provision fw …`: the lab PC's firmware-image verbs — make a signing key, pack and sign the
//! firmware ELF into an update image, inspect an image. (Sending an image to the island through the
//! gateway, `fw update`, comes with the gateway's side of the update.)

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use ihex_image::{
    load_public, pack, pack_elf, Board, FirmwareVersion, Inspection, PackOverrides, PublicKey,
    SigningKey,
};

/// The `fw` verbs.
#[derive(Subcommand)]
pub enum FwCmd {
    /// Generate a signing key pair: OUT.secret (keep it off the bench) and OUT.pub (build the
    /// firmware with IHEX_FW_PUBKEY=OUT.pub).
    Keygen(KeygenArgs),
    /// Pack and sign a firmware ELF (or a flat binary with --raw) into an update image.
    Pack(PackArgs),
    /// Show what an image says about itself and check it (signature with --key or --test-key).
    Inspect(InspectArgs),
}

/// `fw keygen`.
#[derive(Args)]
pub struct KeygenArgs {
    /// Path stem of the two key files (OUT.secret, OUT.pub); neither may exist.
    #[arg(long)]
    out: PathBuf,
}

/// Which key signs (`pack`) or verifies (`inspect`).
#[derive(Args)]
#[group(required = false, multiple = false)]
pub struct KeyArgs {
    /// The key file: the secret key for `pack`, the public key for `inspect`.
    #[arg(long)]
    key: Option<PathBuf>,
    /// Use the committed TEST key (tests and the simulator only: anybody can sign with it).
    #[arg(long)]
    test_key: bool,
}

/// `fw pack`.
#[derive(Args)]
pub struct PackArgs {
    /// The firmware ELF (crates/sc-fw/target/thumbv7em-none-eabihf/release/ihex-sc-fw).
    input: PathBuf,
    #[command(flatten)]
    key: KeyArgs,
    /// The image file to write (default: <input name>-<version>.img in the current folder).
    #[arg(long, short)]
    out: Option<PathBuf>,
    /// INPUT is a flat binary that runs at the board's load address, not an ELF (then --board,
    /// --version and --protocol are required).
    #[arg(long)]
    raw: bool,
    /// The board (nucleo-f303re, sim, or a number); from the ELF's IHEX_FW_INFO when it has one.
    #[arg(long)]
    board: Option<Board>,
    /// The firmware version MAJOR.MINOR.PATCH; from the ELF's IHEX_FW_INFO when it has one.
    #[arg(long)]
    version: Option<FirmwareVersion>,
    /// The CAN protocol version MAJOR.MINOR; from the ELF's IHEX_FW_INFO when it has one.
    #[arg(long, value_parser = parse_protocol)]
    protocol: Option<(u8, u8)>,
}

/// `fw inspect`.
#[derive(Args)]
pub struct InspectArgs {
    /// The image file.
    image: PathBuf,
    #[command(flatten)]
    key: KeyArgs,
}

/// `1.0` → `(1, 0)`.
fn parse_protocol(s: &str) -> Result<(u8, u8), String> {
    let bad = || format!("{s:?} is not a protocol version MAJOR.MINOR");
    let (major, minor) = s.trim().split_once('.').ok_or_else(bad)?;
    Ok((
        major.parse().map_err(|_| bad())?,
        minor.parse().map_err(|_| bad())?,
    ))
}

/// Runs a `fw` verb; `Ok(false)` when `inspect` found a problem (exit status 1).
pub fn run(cmd: FwCmd) -> Result<bool> {
    match cmd {
        FwCmd::Keygen(a) => keygen(&a.out).map(|()| true),
        FwCmd::Pack(a) => pack_cmd(a).map(|()| true),
        FwCmd::Inspect(a) => inspect(a),
    }
}

fn keygen(out: &Path) -> Result<()> {
    let secret = with_suffix(out, "secret");
    let public = with_suffix(out, "pub");
    let key = SigningKey::generate()?;
    key.save(&secret, &public)?;
    println!("key ID {}", key.public().id());
    println!(
        "secret key: {} (signs images: keep it off the bench, back it up)",
        secret.display()
    );
    println!(
        "public key: {} (build the firmware with IHEX_FW_PUBKEY={0})",
        public.display()
    );
    Ok(())
}

/// `stem.suffix`, keeping any dots already in the stem's name.
fn with_suffix(stem: &Path, suffix: &str) -> PathBuf {
    let mut name = stem.as_os_str().to_owned();
    name.push(".");
    name.push(suffix);
    PathBuf::from(name)
}

fn pack_cmd(a: PackArgs) -> Result<()> {
    let key = match (&a.key.key, a.key.test_key) {
        (Some(path), _) => SigningKey::load(path)?,
        (None, true) => SigningKey::test_key(),
        (None, false) => bail!("give the signing key: --key LAB.secret (or --test-key)"),
    };
    let input = fs::read(&a.input).with_context(|| format!("reading {}", a.input.display()))?;
    let overrides = PackOverrides {
        board: a.board,
        protocol: a.protocol,
        version: a.version,
    };
    let image = if a.raw {
        let (Some(board), Some(protocol), Some(version)) = (a.board, a.protocol, a.version) else {
            bail!("--raw needs --board, --version and --protocol");
        };
        pack(board, protocol, version, &input, &key)?
    } else {
        pack_elf(&input, overrides, &key)?
    };
    let inspection = Inspection::of(&image, Some(&key.public()))?;
    let out = a.out.unwrap_or_else(|| {
        let name = a.input.file_stem().unwrap_or_default().to_string_lossy();
        PathBuf::from(format!("{name}-{}.img", inspection.header.version))
    });
    fs::write(&out, &image).with_context(|| format!("writing {}", out.display()))?;
    print!("{inspection}");
    if key.public() == ihex_image::test_key::PUBLIC {
        println!("signed with the TEST key: only boards built with the test key accept it");
    }
    println!("wrote {} ({} bytes)", out.display(), image.len());
    Ok(())
}

fn inspect(a: InspectArgs) -> Result<bool> {
    let key: Option<PublicKey> = match (&a.key.key, a.key.test_key) {
        (Some(path), _) => Some(load_public(path)?),
        (None, true) => Some(ihex_image::test_key::PUBLIC),
        (None, false) => None,
    };
    let image = fs::read(&a.image).with_context(|| format!("reading {}", a.image.display()))?;
    let inspection = Inspection::of(&image, key.as_ref())?;
    print!("{inspection}");
    Ok(inspection.is_good())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn protocol_versions() {
        assert_eq!(parse_protocol("1.0"), Ok((1, 0)));
        assert_eq!(parse_protocol(" 2.13 "), Ok((2, 13)));
        for bad in ["1", "1.", ".1", "1.2.3", "256.0", "a.b"] {
            assert!(parse_protocol(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn key_file_names_keep_dots_in_the_stem() {
        assert_eq!(
            with_suffix(Path::new("keys/lab.2026"), "pub"),
            PathBuf::from("keys/lab.2026.pub")
        );
    }
}
