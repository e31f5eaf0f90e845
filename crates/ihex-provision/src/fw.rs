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
use ihex_image::sim::{sim_image_with_notes, SimFirmware};
use ihex_image::{
    load_public, pack_elf_with_notes, pack_with_notes, Board, FirmwareVersion, Inspection,
    PackOverrides, PublicKey, SigningKey,
};
use std::collections::BTreeMap;

use ihex_gateway_core::event::{NodeState, Role};
use ihex_proto::NodeId;
use ihex_provision::api::{self, GatewayEvent};
use ihex_provision::can::Topics;
use ihex_provision::mqtt::Session;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
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
    /// Release notes the image carries (at most 320 bytes; shown before an update).
    #[arg(long, default_value = "")]
    notes: String,
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
    /// Let the nodes take an older version (a downgrade), and update nodes that already run
    /// this version too.
    #[arg(long)]
    force: bool,
    /// One element at a time (a queue), instead of all at once.
    #[arg(long, conflicts_with = "canary")]
    one_at_a_time: bool,
    /// Update N elements first; only if all of them end `updated`, the rest.
    #[arg(long, value_name = "N")]
    canary: Option<usize>,
    /// Several islands in turn, comma-separated (the first is the canary island: the others
    /// are updated only if every element of it ended `updated`).
    #[arg(long, value_delimiter = ',', conflicts_with = "island")]
    islands: Vec<String>,
    /// Give up waiting for a report after this many seconds.
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
    /// Release notes the image carries (at most 320 bytes of UTF-8; `fw update` and the island
    /// view show them before the update). An image with notes needs nodes that read header
    /// format 2.
    #[arg(long, conflicts_with = "notes_file")]
    notes: Option<String>,
    /// Release notes from a file (see --notes).
    #[arg(long)]
    notes_file: Option<PathBuf>,
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
    let image = sim_image_with_notes(a.version, firmware, a.size as usize, &a.notes, &key)?;
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

/// `fw update`: `Ok(true)` when every node ended `updated` (or already ran the version).
async fn update(a: UpdateArgs) -> Result<bool> {
    let name = a
        .image
        .file_name()
        .and_then(|n| n.to_str())
        .context("IMAGE must end in a file name")?
        .to_owned();
    // A local file is checked here and uploaded; any other name is one in the gateway's
    // firmware directory.
    let (upload, version) = if a.image.is_file() {
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
        if let Some(notes) = image.notes() {
            say!("release notes:");
            for line in notes.lines() {
                say!("  {line}");
            }
        }
        (Some(bytes), Some(image.version().to_string()))
    } else {
        say!("{name}: no such local file; asking the gateway for its own copy (--fw-dir)");
        (None, None)
    };
    let broker = a.broker.broker()?;
    let islands: Vec<Option<String>> = if a.islands.is_empty() {
        vec![a.broker.island.clone()]
    } else {
        a.islands
            .iter()
            .map(|i| Some(i.trim().to_owned()))
            .collect()
    };
    let mut all = true;
    for (n, island) in islands.iter().enumerate() {
        let topics = a.broker.topics_of(island.as_deref());
        if let Some(i) = island.as_deref().filter(|_| islands.len() > 1) {
            say!("== island {i} ({} of {})", n + 1, islands.len());
        }
        let state_topic = format!("{}/+/state", topics.node_state_root);
        let mut session = Session::connect(
            &broker,
            &[
                topics.events.clone(),
                topics.availability.clone(),
                state_topic,
            ],
            GATEWAY_WAIT,
        )
        .await?;
        let job = Job {
            a: &a,
            topics: &topics,
            name: &name,
            version: version.as_deref(),
        };
        let outcome = job.run(&mut session, upload.clone()).await;
        session.close().await;
        if !outcome? {
            all = false;
            if n + 1 < islands.len() {
                say!(
                    "stopping: not every element of this island ended updated; {} not touched",
                    islands[n + 1..]
                        .iter()
                        .flatten()
                        .cloned()
                        .collect::<Vec<_>>()
                        .join(", ")
                );
                break;
            }
        }
    }
    Ok(all)
}

/// One island's rollout.
struct Job<'a> {
    a: &'a UpdateArgs,
    topics: &'a Topics,
    name: &'a str,
    /// The image's version, when the file is local (else the gateway's copy decides).
    version: Option<&'a str>,
}

/// What the island's retained state documents say about an element.
#[derive(Clone, Debug)]
struct Element {
    id: NodeId,
    mobile: bool,
    online: bool,
    /// Firmware version and trial flag, once read back.
    firmware: Option<(String, bool)>,
    /// Mobile elements docked on it.
    docked: Vec<NodeId>,
}

impl Job<'_> {
    async fn run(&self, session: &mut Session, upload: Option<Vec<u8>>) -> Result<bool> {
        wait_online(session, self.topics).await?;
        let elements = read_states(session, self.topics).await?;
        let targets = self.targets(&elements)?;
        if targets.is_empty() {
            say!("nothing to update");
            return Ok(true);
        }
        if let Some(bytes) = upload {
            self.upload(session, bytes).await?;
        }
        let waves = plan(&targets, &elements, self.a.one_at_a_time, self.a.canary);
        let mut reports: BTreeMap<NodeId, (NodeOutcome, Option<String>)> = BTreeMap::new();
        let mut stopped = false;
        for (n, wave) in waves.iter().enumerate() {
            if waves.len() > 1 {
                let ids: Vec<String> = wave.nodes.iter().map(|id| id.to_string()).collect();
                say!("-- {} {}: {}", wave.what, n + 1, ids.join(","));
            }
            let report = self.send(session, &wave.nodes).await?;
            let ok = report.iter().all(|(_, (o, _))| *o == NodeOutcome::Updated);
            reports.extend(report);
            if !ok && wave.stop_on_failure {
                say!(
                    "stopping: the {} did not end all updated; the rest is left as it is",
                    wave.what
                );
                stopped = true;
                break;
            }
        }
        let updated = reports
            .values()
            .filter(|(o, _)| *o == NodeOutcome::Updated)
            .count();
        if waves.len() > 1 {
            for (id, (o, why)) in &reports {
                let o = outcome_name(*o);
                match why {
                    Some(why) => say!("{id:>4} {o}: {why}"),
                    None => say!("{id:>4} {o}"),
                }
            }
        }
        say!(
            "{updated} of {} nodes updated{}",
            targets.len(),
            if stopped { " (stopped early)" } else { "" }
        );
        Ok(updated == targets.len())
    }

    /// The elements to update: those named (or all online), minus those already on the version.
    fn targets(&self, elements: &BTreeMap<NodeId, Element>) -> Result<Vec<NodeId>> {
        let named: Vec<NodeId> = if self.a.nodes.trim() == "all" {
            elements
                .values()
                .filter(|e| e.online)
                .map(|e| e.id)
                .collect()
        } else {
            self.a
                .nodes
                .split(',')
                .map(|t| ihex_provision::id::parse_sc_id(t).map_err(anyhow::Error::from))
                .collect::<Result<_>>()?
        };
        let mut out = Vec::new();
        for id in named {
            // Hook for leases (issue 28): an element leased to someone else is to be skipped
            // here, with the lease named as the reason. Leases do not exist yet.
            let current = elements.get(&id).and_then(|e| e.firmware.clone());
            match (self.version, current) {
                (Some(want), Some((have, false))) if have == want && !self.a.force => {
                    say!("{id:>4} already runs {have}: skipped (--force updates it anyway)");
                }
                _ => out.push(id),
            }
        }
        Ok(out)
    }

    async fn upload(&self, session: &mut Session, bytes: Vec<u8>) -> Result<()> {
        let (topics, name) = (self.topics, self.name);
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
        Ok(())
    }

    /// One `fw_update` to `nodes`, followed to its report.
    async fn send(
        &self,
        session: &mut Session,
        nodes: &[NodeId],
    ) -> Result<BTreeMap<NodeId, (NodeOutcome, Option<String>)>> {
        let (a, topics) = (self.a, self.topics);
        let deadline = Instant::now() + Duration::from_secs(a.timeout_secs);
        let request_id = api::new_request_id("fw");
        let list: Vec<String> = nodes.iter().map(|id| id.to_string()).collect();
        let cmd = api::fw_update_command(self.name, &list.join(","), a.force, &request_id);
        session.publish(&topics.commands, cmd).await?;
        let mut progress = Progress::new();
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
                    progress.show(&p.node.to_string(), &p.phase, p.percent);
                }
                GatewayEvent::FwCorrection(c) if c.request_id.as_deref() == Some(&request_id) => {
                    say!(
                        "{:>4} {} (was {}): {}",
                        c.node.to_string(),
                        outcome_name(c.outcome),
                        outcome_name(c.was),
                        c.reason
                    );
                }
                GatewayEvent::FwReport(r) if r.request_id.as_deref() == Some(&request_id) => {
                    progress.finish();
                    say!(
                        "image {} version {}: {} data frames in {:.1} s at a {} % bus share",
                        r.image_id,
                        r.version,
                        r.frames_sent,
                        r.duration_ms as f64 / 1000.0,
                        r.bus_share
                    );
                    let mut out = BTreeMap::new();
                    for n in &r.nodes {
                        let o = outcome_name(n.outcome);
                        match &n.reason {
                            Some(why) => say!("{:>4} {o}: {why}", n.node.to_string()),
                            None => say!("{:>4} {o}", n.node.to_string()),
                        }
                        out.insert(n.node.0, (n.outcome, n.reason.clone()));
                    }
                    return Ok(out);
                }
                _ => {}
            }
        }
        progress.finish();
        bail!(
            "no fw_report within {} s (--timeout-secs); the update may still run: watch {}",
            a.timeout_secs,
            topics.events
        )
    }
}

/// An outcome's published name.
fn outcome_name(o: NodeOutcome) -> String {
    serde_json::to_value(o)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| "?".into())
}

/// How long the retained state documents may keep coming after the last one.
const STATES_QUIET: Duration = Duration::from_millis(500);

/// The island's elements from their retained state documents (they arrive right after the
/// subscription; the read stops at the first quiet half-second).
async fn read_states(session: &mut Session, topics: &Topics) -> Result<BTreeMap<NodeId, Element>> {
    let mut out = BTreeMap::new();
    let prefix = format!("{}/", topics.node_state_root);
    let end = Instant::now() + GATEWAY_WAIT;
    loop {
        let deadline = (Instant::now() + STATES_QUIET).min(end);
        let Some(msg) = session.recv_until(deadline).await? else {
            break;
        };
        if !(msg.topic.starts_with(&prefix) && msg.topic.ends_with("/state")) {
            continue;
        }
        let Ok(doc) = serde_json::from_slice::<NodeState>(&msg.payload) else {
            continue;
        };
        let mobile = doc.role == Some(Role::Mobile);
        let docked = if mobile {
            Vec::new()
        } else {
            doc.connections.iter().map(|l| l.peer.0).collect()
        };
        out.insert(
            doc.id.0,
            Element {
                id: doc.id.0,
                mobile,
                online: doc.online,
                firmware: doc.firmware.map(|f| (f.version, f.trial)),
                docked,
            },
        );
    }
    Ok(out)
}

/// One `fw_update` of a rollout.
#[derive(Debug, PartialEq, Eq)]
struct Wave {
    what: &'static str,
    nodes: Vec<NodeId>,
    /// A failure here ends the rollout.
    stop_on_failure: bool,
}

/// The order of an update: mobile elements before the static elements that power them (a
/// static element restarts into its new image; where its relay cannot be held through that, a
/// mobile element docked on it would lose power mid-update), in waves: the canaries first, or
/// one element at a time.
fn plan(
    targets: &[NodeId],
    elements: &BTreeMap<NodeId, Element>,
    one_at_a_time: bool,
    canary: Option<usize>,
) -> Vec<Wave> {
    let powers = |id: &NodeId| {
        elements
            .get(id)
            .is_some_and(|e| !e.mobile && !e.docked.is_empty())
    };
    // Mobiles and free statics first, statics with docked elements last, each by ID.
    let mut order: Vec<NodeId> = targets.to_vec();
    order.sort_by_key(|id| (powers(id), elements.get(id).is_none_or(|e| !e.mobile), *id));
    if one_at_a_time {
        return order
            .into_iter()
            .map(|id| Wave {
                what: "element",
                nodes: vec![id],
                stop_on_failure: false,
            })
            .collect();
    }
    let mut waves = Vec::new();
    let mut rest = order;
    if let Some(n) = canary.filter(|&n| n > 0 && n < rest.len()) {
        let canaries: Vec<NodeId> = rest.drain(..n).collect();
        waves.push(Wave {
            what: "canary wave",
            nodes: canaries,
            stop_on_failure: true,
        });
    }
    // The statics that power docked elements go after the others (their restart would cut them).
    let split = rest.iter().position(powers).unwrap_or(rest.len());
    let last: Vec<NodeId> = rest.drain(split..).collect();
    if !rest.is_empty() {
        waves.push(Wave {
            what: "wave",
            nodes: rest,
            stop_on_failure: canary.is_some(),
        });
    }
    if !last.is_empty() {
        waves.push(Wave {
            what: "wave (elements powering docked ones)",
            nodes: last,
            stop_on_failure: false,
        });
    }
    waves
}

/// Per-element progress: a bar each on a terminal, plain lines when piped.
struct Progress {
    bars: Option<(MultiProgress, BTreeMap<String, ProgressBar>)>,
}

impl Progress {
    fn new() -> Self {
        Progress {
            bars: crate::out::is_terminal().then(|| (MultiProgress::new(), BTreeMap::new())),
        }
    }

    fn show(&mut self, node: &str, phase: &str, percent: u8) {
        let Some((multi, bars)) = self.bars.as_mut() else {
            say!("{node:>4} {phase:<10} {percent:>3} %");
            return;
        };
        let bar = bars.entry(node.to_owned()).or_insert_with(|| {
            let style = ProgressStyle::with_template("{prefix:>4} [{bar:30}] {pos:>3} % {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
            multi.add(
                ProgressBar::new(100)
                    .with_style(style)
                    .with_prefix(node.to_owned()),
            )
        });
        bar.set_position(u64::from(percent));
        bar.set_message(phase.to_owned());
    }

    fn finish(&mut self) {
        if let Some((_, bars)) = self.bars.take() {
            for bar in bars.values() {
                bar.finish();
            }
        }
    }
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
    let notes = match (&a.notes, &a.notes_file) {
        (Some(n), _) => n.clone(),
        (None, Some(p)) => {
            fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?
        }
        (None, None) => String::new(),
    };
    let notes = notes.trim_end();
    let image = if a.raw {
        let (Some(board), Some(protocol), Some(version)) = (a.board, a.protocol, a.version) else {
            bail!("--raw needs --board, --version and --protocol");
        };
        pack_with_notes(board, protocol, version, &input, notes, &key)?
    } else {
        pack_elf_with_notes(&input, overrides, notes, &key)?
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

    fn id(raw: u16) -> NodeId {
        NodeId::new_sc(raw).unwrap()
    }

    /// The demo island: 2 docked on 111, 3 free, 112 powering nothing.
    fn island() -> BTreeMap<NodeId, Element> {
        let e = |raw, mobile, docked: &[u16]| {
            (
                id(raw),
                Element {
                    id: id(raw),
                    mobile,
                    online: true,
                    firmware: None,
                    docked: docked.iter().map(|&d| id(d)).collect(),
                },
            )
        };
        [
            e(0x111, false, &[2]),
            e(0x112, false, &[]),
            e(2, true, &[]),
            e(3, true, &[]),
        ]
        .into_iter()
        .collect()
    }

    fn ids(w: &Wave) -> Vec<u16> {
        w.nodes.iter().map(|n| n.get()).collect()
    }

    #[test]
    fn statics_powering_docked_elements_go_last() {
        let all = [id(0x111), id(0x112), id(2), id(3)];
        let waves = plan(&all, &island(), false, None);
        let got: Vec<Vec<u16>> = waves.iter().map(ids).collect();
        assert_eq!(got, vec![vec![2, 3, 0x112], vec![0x111]]);
        assert!(waves.iter().all(|w| !w.stop_on_failure));
    }

    #[test]
    fn a_canary_wave_comes_first_and_stops_the_rollout_when_it_fails() {
        let all = [id(0x111), id(0x112), id(2), id(3)];
        let waves = plan(&all, &island(), false, Some(1));
        let got: Vec<Vec<u16>> = waves.iter().map(ids).collect();
        assert_eq!(got, vec![vec![2], vec![3, 0x112], vec![0x111]]);
        assert!(waves[0].stop_on_failure && waves[1].stop_on_failure);
    }

    #[test]
    fn one_at_a_time_is_a_queue_in_the_same_order() {
        let all = [id(0x111), id(0x112), id(2)];
        let waves = plan(&all, &island(), true, None);
        let got: Vec<Vec<u16>> = waves.iter().map(ids).collect();
        assert_eq!(got, vec![vec![2], vec![0x112], vec![0x111]]);
    }

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
