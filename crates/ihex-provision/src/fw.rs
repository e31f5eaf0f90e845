//! `ihex-provision fw …`: the lab PC's firmware-image verbs — make a signing key, pack and sign the
//! firmware ELF into an update image, inspect an image, and update nodes through the gateway
//! (`fw update`: the image uploaded over MQTT — or named in the gateway's firmware directory —
//! then the `fw_update` command; progress and the report printed).

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use ihex_gateway_core::fwupdate::{FwImage, NodeOutcome, UploadResult, MAX_UPLOAD};
use ihex_image::sim::{sim_image, SimFirmware};
use ihex_image::{
    load_public, pack, pack_elf, Board, FirmwareVersion, Inspection, PackOverrides, PublicKey,
    SigningKey,
};
use ihex_provision::api::{self, GatewayEvent};
use ihex_provision::can::Topics;
use ihex_provision::mqtt::Session;
use tokio::time::Instant;

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
    /// Update nodes through the gateway (MQTT): upload the image, send `fw_update`, print
    /// progress and the report; exit 1 unless every node was updated.
    Update(UpdateArgs),
    /// Make an image the simulated boards (sim-node, the demo gateway) accept: a simulated
    /// firmware of that version, signed with the test key; with --reverts one that installs and
    /// then fails its self-test, so the boards go back to their old image.
    DemoImage(DemoImageArgs),
}

/// `fw demo-image`.
#[derive(Args)]
pub struct DemoImageArgs {
    /// The version it claims, MAJOR.MINOR.PATCH (newer than the island's to be taken without --force).
    #[arg(long)]
    version: FirmwareVersion,
    /// Make an image that does not confirm itself after the update (the boards revert it).
    #[arg(long)]
    reverts: bool,
    /// Payload size in bytes (a real firmware is about 50 KiB; smaller transfers faster).
    #[arg(long, default_value_t = 16 * 1024, value_parser = clap::value_parser!(u32).range(12..=(128 * 1024 - 512)))]
    size: u32,
    /// The image file to write (default: sim-fw-<version>.img, or sim-fw-<version>-reverts.img).
    #[arg(long, short)]
    out: Option<PathBuf>,
}

/// `fw update`.
#[derive(Args)]
pub struct UpdateArgs {
    #[command(flatten)]
    broker: crate::BrokerArgs,
    /// The image file: checked here, uploaded to the gateway over MQTT under its file name. A
    /// name that is no local file is asked of the gateway's firmware directory (--fw-dir).
    image: PathBuf,
    /// Which nodes: `all` (every node online) or node IDs in hex, comma-separated (`111,112`).
    #[arg(long, default_value = "all")]
    nodes: String,
    /// Let the nodes take an older version (a downgrade).
    #[arg(long)]
    force: bool,
    /// Give up waiting for the report after this many seconds.
    #[arg(long, default_value_t = 600)]
    timeout_secs: u64,
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
        FwCmd::Update(a) => crate::tokio_main(update(a)),
        FwCmd::DemoImage(a) => demo_image(a).map(|()| true),
    }
}

/// `fw demo-image`: a simulated firmware signed with the test key, which is what every
/// simulated board trusts.
fn demo_image(a: DemoImageArgs) -> Result<()> {
    let firmware = SimFirmware {
        confirms: !a.reverts,
    };
    let key = SigningKey::test_key();
    let image = sim_image(a.version, firmware, a.size as usize, &key)?;
    let out = a.out.unwrap_or_else(|| {
        let tail = if a.reverts { "-reverts" } else { "" };
        PathBuf::from(format!("sim-fw-{}{tail}.img", a.version))
    });
    fs::write(&out, &image).with_context(|| format!("writing {}", out.display()))?;
    let inspection = Inspection::of(&image, Some(&key.public()))?;
    say!("{}", inspection.to_string().trim_end());
    if a.reverts {
        say!("simulated firmware that fails its self-test: the boards take it, then revert to their old image");
    } else {
        say!("simulated firmware: the simulated boards take it and confirm it");
    }
    say!("wrote {} ({} bytes)", out.display(), image.len());
    Ok(())
}

/// How long the gateway has to show itself (its retained `online`) and to answer an upload.
const GATEWAY_WAIT: Duration = Duration::from_secs(10);

/// `fw update`: `Ok(true)` when every node ended `updated`.
async fn update(a: UpdateArgs) -> Result<bool> {
    let name = a
        .image
        .file_name()
        .and_then(|n| n.to_str())
        .context("IMAGE must end in a file name")?
        .to_owned();
    // A local file is checked here and uploaded; any other name is one in the gateway's
    // firmware directory.
    let upload = if a.image.is_file() {
        if !ihex_gateway_core::command::is_image_name(&name) {
            bail!("{name:?}: an image name is 1 to 128 of A-Z a-z 0-9 . - _ (rename the file)");
        }
        let bytes = fs::read(&a.image).with_context(|| format!("reading {}", a.image.display()))?;
        if bytes.len() > MAX_UPLOAD {
            bail!(
                "{} is {} bytes; an image slot takes at most {MAX_UPLOAD}",
                a.image.display(),
                bytes.len()
            );
        }
        let image = FwImage::check(bytes.clone())
            .with_context(|| format!("{} is not an image to send", a.image.display()))?;
        say!(
            "{name}: version {}, board {}, {} bytes",
            image.version(),
            image.header().board,
            image.len()
        );
        Some(bytes)
    } else {
        say!("{name}: no such local file; asking the gateway for its own copy (--fw-dir)");
        None
    };
    let broker = a.broker.broker()?;
    let topics = a.broker.topics();
    let mut session = Session::connect(
        &broker,
        &[topics.events.clone(), topics.availability.clone()],
        GATEWAY_WAIT,
    )
    .await?;
    let outcome = drive(&mut session, &topics, &a, &name, upload).await;
    session.close().await;
    outcome
}

/// Waits for the gateway, uploads, sends `fw_update` and follows it to the report.
async fn drive(
    session: &mut Session,
    topics: &Topics,
    a: &UpdateArgs,
    name: &str,
    upload: Option<Vec<u8>>,
) -> Result<bool> {
    wait_online(session, topics).await?;
    if let Some(bytes) = upload {
        session
            .publish(&format!("{}/{name}", topics.fw_upload), bytes)
            .await?;
        let deadline = Instant::now() + GATEWAY_WAIT;
        let answer = loop {
            let Some(msg) = session.recv_until(deadline).await? else {
                bail!(
                    "the gateway did not answer the upload on {}/{name} within {} s (a gateway \
                     older than image uploads? then copy the file into its --fw-dir)",
                    topics.fw_upload,
                    GATEWAY_WAIT.as_secs()
                );
            };
            match serde_json::from_slice::<GatewayEvent>(&msg.payload) {
                Ok(GatewayEvent::FwUpload(u)) if u.name == name => break u,
                _ => {}
            }
        };
        if answer.result != UploadResult::Stored {
            bail!(
                "the gateway rejected the image: {}",
                answer.reason.as_deref().unwrap_or("no reason given")
            );
        }
        say!(
            "uploaded: image {} version {} (signature {} by the gateway)",
            answer.image_id.as_deref().unwrap_or("?"),
            answer.version.as_deref().unwrap_or("?"),
            answer.signature.as_deref().unwrap_or("?")
        );
    }
    let deadline = Instant::now() + Duration::from_secs(a.timeout_secs);
    let request_id = api::new_request_id("fw");
    let cmd = api::fw_update_command(name, &a.nodes, a.force, &request_id);
    session.publish(&topics.commands, cmd).await?;
    while let Some(msg) = session.recv_until(deadline).await? {
        if msg.topic == topics.availability {
            if msg.payload == b"offline" {
                bail!("the gateway went offline during the update");
            }
            continue;
        }
        let Ok(event) = serde_json::from_slice::<GatewayEvent>(&msg.payload) else {
            continue;
        };
        if let Some(api::Outcome::Failed { reason, .. }) = api::outcome(&event, &request_id) {
            bail!("the gateway did not start the update: {reason}");
        }
        match event {
            GatewayEvent::FwProgress(p) if p.request_id.as_deref() == Some(&request_id) => {
                say!("{:>4} {:<10} {:>3} %", p.node, p.phase, p.percent);
            }
            GatewayEvent::FwReport(r) if r.request_id.as_deref() == Some(&request_id) => {
                say!(
                    "image {} version {}: {} data frames in {:.1} s at a {} % bus share",
                    r.image_id,
                    r.version,
                    r.frames_sent,
                    r.duration_ms as f64 / 1000.0,
                    r.bus_share
                );
                for n in &r.nodes {
                    let outcome = serde_json::to_value(n.outcome)?;
                    let outcome = outcome.as_str().unwrap_or("?");
                    match &n.reason {
                        Some(why) => say!("{:>4} {outcome}: {why}", n.node),
                        None => say!("{:>4} {outcome}", n.node),
                    }
                }
                let updated = r
                    .nodes
                    .iter()
                    .filter(|n| n.outcome == NodeOutcome::Updated)
                    .count();
                say!("{updated} of {} nodes updated", r.nodes.len());
                return Ok(r.all_updated());
            }
            _ => {}
        }
    }
    bail!(
        "no fw_report within {} s (--timeout-secs); the update may still run: watch {}",
        a.timeout_secs,
        topics.events
    )
}

/// Fails unless the gateway's retained availability says `online`.
async fn wait_online(session: &mut Session, topics: &Topics) -> Result<()> {
    let deadline = Instant::now() + GATEWAY_WAIT;
    while let Some(msg) = session.recv_until(deadline).await? {
        if msg.topic == topics.availability {
            if msg.payload == b"online" {
                return Ok(());
            }
            bail!(
                "the gateway is {} ({} says so): start it, or check --island",
                String::from_utf8_lossy(&msg.payload),
                topics.availability
            );
        }
    }
    bail!(
        "no gateway: nothing on {} within {} s (is it running, on this broker, with this --island?)",
        topics.availability,
        GATEWAY_WAIT.as_secs()
    )
}

fn keygen(out: &Path) -> Result<()> {
    let secret = with_suffix(out, "secret");
    let public = with_suffix(out, "pub");
    let key = SigningKey::generate()?;
    key.save(&secret, &public)?;
    say!("key ID {}", key.public().id());
    say!(
        "secret key: {} (signs images: keep it off the bench, back it up)",
        secret.display()
    );
    say!(
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
    say!("{}", inspection.to_string().trim_end());
    if key.public() == ihex_image::test_key::PUBLIC {
        say!("signed with the TEST key: only boards built with the test key accept it");
    }
    say!("wrote {} ({} bytes)", out.display(), image.len());
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
    say!("{}", inspection.to_string().trim_end());
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
