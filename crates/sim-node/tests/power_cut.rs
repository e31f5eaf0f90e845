//! The power-cut suite: island-wide updates by the gateway's real sender (`ihex-gateway-core`'s
//! `FwSender`) to simulated sub-controllers (node core + board: flash with embassy-boot's swap),
//! each run with one power cut at a seeded random point — during the transfer, at a flash
//! operation after the commit (the bootloader's swap, `mark_booted`), or at a random moment
//! (after the last frame, during the commit, on trial before or after the confirmation).
//!
//! Every run must end with every element booted on the old or the new image (byte for byte in
//! its active slot), running and confirmed, and its outcome in the report true to what it runs:
//! `updated` only on the new image confirmed; never `reverted` (every image here confirms itself,
//! so a revert is a cut's doing: the gateway, told of the power-on by the boot-up, begins such an
//! element again, or reports `lost_power`).
//!
//! The test command runs a fixed seed ([`CI_SEED`], [`CI_CUTS`] cuts). `cargo xtask soak
//! --fw-power-cuts N` runs N cuts with a fresh seed (`IHEX_FW_CUT_SEED`, `IHEX_FW_CUTS`); every
//! run prints its seed, and a failure names its cut, so a plan can be replayed.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use ihex_gateway_core::event::Event;
use ihex_gateway_core::fwupdate::{FwConfig, FwImage, FwReport, FwSender, NodeOutcome};
use ihex_image::board::F303RE;
use ihex_image::{FirmwareVersion, Header, SigningKey};
use ihex_proto::{BootRole, Message, NodeId, Packet, ResetReason, Uid};
use ihex_sc_core::{Config, Millis, Node, Output};
use sim_node::board::{self, Board, BootFailure, Carried, SimFirmware};

const OLD: FirmwareVersion = FirmwareVersion::new(1, 0, 0);
const NEW: FirmwareVersion = FirmwareVersion::new(1, 1, 0);
const IDS: [u16; 3] = [0x111, 0x112, 0x113];
/// The seed and number of cuts of the test command.
const CI_SEED: u64 = 0x5EED_F1A5_4C07;
const CI_CUTS: usize = 100;
const SEED_ENV: &str = "IHEX_FW_CUT_SEED";
const CUTS_ENV: &str = "IHEX_FW_CUTS";
/// The virtual clock's step.
const STEP_MS: u64 = 1;

fn nid(raw: u16) -> NodeId {
    NodeId::new_sc(raw).unwrap()
}

fn sim(version: FirmwareVersion, len: usize) -> Vec<u8> {
    board::sim_image(
        version,
        SimFirmware { confirms: true },
        len,
        &SigningKey::test_key(),
    )
    .unwrap()
}

/// Where one run cuts the power of one element.
#[derive(Clone, Copy, Debug)]
enum Cut {
    /// At the flash operation this many operations after power-on (the transfer's erase and
    /// writes, the commit's mark).
    Op(u64),
    /// At the flash operation this many operations after the restart that follows the commit
    /// (the bootloader's swap, the confirmation's `mark_booted`).
    OpAfterCommit(u64),
    /// At this moment of the update, ms from its start.
    At(u64),
}

/// One simulated element: board and node, its frames to the gateway collected.
struct Sc {
    id: NodeId,
    board: Board,
    node: Option<Node>,
    /// Frames it sent (source, message), for the gateway.
    sent: Vec<(NodeId, Message)>,
    /// Arm the cut at the next power-on (after the commit's restart).
    arm_on_boot: Option<u64>,
    /// Power comes back at this time (ms) after a cut.
    back_at: Option<u64>,
    /// A cut happened.
    was_cut: bool,
    /// Flash operations counted before each power-on (the counter restarts at power-on).
    ops_log: Vec<u64>,
    /// How it starts next: a reset it asked for, or power-on after a cut.
    reset: ResetReason,
}

impl Sc {
    fn new(raw: u16, image: &[u8], now: u64) -> Sc {
        let mut sc = Sc {
            id: nid(raw),
            board: Board::with_image(image),
            node: None,
            sent: Vec::new(),
            arm_on_boot: None,
            back_at: None,
            was_cut: false,
            ops_log: Vec::new(),
            reset: ResetReason::PowerOn,
        };
        sc.power_on(now);
        sc
    }

    /// Reset or power-on: the bootloader runs (resuming a swap a cut interrupted), then the node
    /// (which announces itself).
    fn power_on(&mut self, now: u64) {
        self.node = None;
        self.ops_log.push(self.board.flash.ops());
        self.board.flash.power_on();
        if let Some(k) = self.arm_on_boot.take() {
            self.board.flash.cut_after(k, k + 1);
        }
        match board::boot(&mut self.board, ihex_image::test_key::PUBLIC) {
            Ok(b) => {
                let config = Config {
                    role: BootRole::Static,
                    ports: 6,
                    uid: Uid([self.id.get() as u8; 12]),
                    node_id: Some(self.id),
                    reset: std::mem::replace(&mut self.reset, ResetReason::Software),
                    firmware: b.firmware,
                    update: b.update,
                };
                let mut node = Node::new(config, Millis(now));
                node.handle_self_test(b.self_test(), Millis(now));
                self.node = Some(node);
                self.drain(now);
            }
            // Cut during the swap: dead until the power comes back (the next boot resumes it).
            Err(BootFailure::Flash(_)) if self.board.flash.is_dead() => self.cut(),
            Err(e) => panic!(
                "{}: the bootloader failed without a power cut: {e}",
                self.id
            ),
        }
    }

    fn drain(&mut self, now: u64) {
        loop {
            let Some(node) = self.node.as_mut() else {
                return;
            };
            let Some(out) = node.poll_output() else {
                return;
            };
            let carried = board::carry_out(&mut self.board, node, out, Millis(now));
            if self.board.flash.is_dead() {
                self.cut();
                return;
            }
            match carried {
                Carried::Done => {}
                Carried::Reset => return self.power_on(now),
                Carried::Other(Output::Frame(p)) => self.sent.push((self.id, p.msg)),
                Carried::Other(_) => {}
            }
        }
    }

    /// The power fails now (the run decides when it comes back: `back_at`).
    fn cut(&mut self) {
        self.node = None;
        self.was_cut = true;
        self.reset = ResetReason::PowerOn;
    }

    fn frame(&mut self, p: &Packet, now: u64) {
        let Some(node) = self.node.as_mut() else {
            return;
        };
        let (raw, data) = p.encode();
        node.handle_frame(raw, true, false, &data, Millis(now));
        self.drain(now);
    }

    fn tick(&mut self, now: u64) {
        if self.node.is_none() {
            if self.back_at.is_some_and(|t| now >= t) {
                self.back_at = None;
                self.power_on(now);
            }
            return;
        }
        let node = self.node.as_mut().unwrap();
        if node.poll_at().is_some_and(|t| t.0 <= now) {
            node.tick(Millis(now));
            self.drain(now);
        }
    }

    /// The running image's version and whether it is on trial (`None`: not running).
    fn running(&self) -> Option<(FirmwareVersion, bool)> {
        let c = self.node.as_ref()?.config();
        Some((c.firmware.version, c.firmware.trial))
    }

    /// The active slot holds exactly `old` or `new`.
    fn old_or_new(&self, old: &[u8], new: &[u8]) -> bool {
        let slot = self.board.flash.region(F303RE.active);
        [old, new].iter().any(|img| slot[..img.len()] == **img)
    }
}

/// A deterministic pseudo-random sequence (no dependency for a test's seeds).
fn lcg(seed: &mut u64) -> u64 {
    *seed = seed
        .wrapping_mul(6_364_136_223_846_793_005)
        .wrapping_add(1_442_695_040_888_963_407);
    *seed >> 33
}

/// What one run measured: the report, the elements, the time it took.
struct Run {
    report: FwReport,
    scs: Vec<Sc>,
    ms: u64,
}

/// One island-wide update, with `cut` on element `victim` (none: a clean run); power comes back
/// `back_ms` after the cut.
fn run(old: &[u8], new: &[u8], cut: Option<(usize, Cut)>, back_ms: u64) -> Run {
    let t0 = Instant::now();
    let mut now = 0u64;
    let mut scs: Vec<Sc> = IDS.iter().map(|&id| Sc::new(id, old, now)).collect();
    for sc in &mut scs {
        sc.sent.clear();
    }
    let config = FwConfig {
        reboot_timeout: Duration::from_secs(10),
        ..FwConfig::default()
    };
    let image = FwImage::check(new.to_vec()).unwrap();
    let mut s = FwSender::new(image, IDS.map(nid), false, None, config, t0);
    let mut at_cut = None;
    match cut {
        Some((v, Cut::Op(k))) => scs[v].board.flash.cut_after(k, k + 1),
        Some((v, Cut::OpAfterCommit(k))) => scs[v].arm_on_boot = Some(k),
        Some((v, Cut::At(t))) => at_cut = Some((v, t)),
        None => {}
    }
    loop {
        let at = t0 + Duration::from_millis(now);
        while let Some(p) = s.poll_transmit() {
            for sc in &mut scs {
                sc.frame(&p, now);
            }
        }
        if let Some((v, _)) = at_cut.filter(|&(_, t)| now >= t) {
            at_cut = None;
            if scs[v].node.is_some() {
                scs[v].cut();
            }
        }
        for sc in &mut scs {
            if sc.was_cut && sc.node.is_none() && sc.back_at.is_none() {
                sc.back_at = Some(now + back_ms);
            }
            sc.tick(now);
        }
        for sc in &mut scs {
            for (src, msg) in std::mem::take(&mut sc.sent) {
                match msg {
                    Message::FwStatus(st) => s.handle_status(src, st, at),
                    // As the bridge does: a power-on is told first, and the state read-back
                    // after a boot-up names the running firmware.
                    Message::BootUp { reset, .. } => {
                        if reset == ResetReason::PowerOn {
                            s.handle_power_on(src, at);
                        }
                        s.handle_boot_up(src, at);
                        if let Some((version, trial)) = sc.running() {
                            s.handle_firmware(src, version, trial, at);
                        }
                    }
                    _ => {}
                }
            }
        }
        while let Some(e) = s.poll_event() {
            if let Event::FwReport(report) = e {
                return Run {
                    report: *report,
                    ms: now,
                    scs,
                };
            }
        }
        now += STEP_MS;
        s.handle_timeout(t0 + Duration::from_millis(now));
        assert!(now < 600_000, "no report within 600 s of virtual time");
    }
}

/// Counts the flash operations of a clean update of one element: before the commit's restart, and
/// from it to the confirmation.
fn clean_ops(old: &[u8], new: &[u8]) -> (u64, u64) {
    let mut sc = Sc::new(IDS[0], old, 0);
    let image = FwImage::check(new.to_vec()).unwrap();
    let t0 = Instant::now();
    let mut s = FwSender::new(image, [sc.id], false, None, FwConfig::default(), t0);
    let mut now = 0;
    loop {
        let at = t0 + Duration::from_millis(now);
        while let Some(p) = s.poll_transmit() {
            sc.frame(&p, now);
        }
        sc.tick(now);
        for (src, msg) in std::mem::take(&mut sc.sent) {
            match msg {
                Message::FwStatus(st) => s.handle_status(src, st, at),
                // As the bridge does: a power-on is told first.
                Message::BootUp { reset, .. } => {
                    if reset == ResetReason::PowerOn {
                        s.handle_power_on(src, at);
                    }
                    s.handle_boot_up(src, at)
                }
                _ => {}
            }
        }
        while let Some(e) = s.poll_event() {
            if let Event::FwReport(r) = e {
                assert!(r.all_updated(), "a clean update: {r:?}");
                // Power-on at the start, then the commit's restart.
                assert_eq!(sc.ops_log.len(), 2, "{:?}", sc.ops_log);
                return (sc.ops_log[1], sc.board.flash.ops());
            }
        }
        now += STEP_MS;
        s.handle_timeout(t0 + Duration::from_millis(now));
    }
}

/// After the report: the island runs on alone for longer than a trial may last, the gateway
/// silent, then every element must run the old or the new image, answer, and match its outcome.
fn check(r: &mut Run, old: &[u8], new: &[u8]) -> Result<(), String> {
    let mut now = r.ms;
    for _ in 0..70_000 {
        now += STEP_MS;
        for sc in &mut r.scs {
            if sc.node.is_none() && sc.back_at.is_none() {
                sc.back_at = Some(now);
            }
            sc.tick(now);
            sc.sent.clear();
        }
    }
    let outcomes: BTreeMap<NodeId, (NodeOutcome, Option<String>)> = r
        .report
        .nodes
        .iter()
        .map(|n| (n.node.0, (n.outcome, n.reason.clone())))
        .collect();
    for sc in &r.scs {
        let Some((version, trial)) = sc.running() else {
            return Err(format!("{} is not running", sc.id));
        };
        if !sc.old_or_new(old, new) {
            return Err(format!("{}: neither image in its active slot", sc.id));
        }
        if trial {
            return Err(format!("{} still on trial after 70 s", sc.id));
        }
        let (outcome, why) = &outcomes[&sc.id];
        let truthful = match outcome {
            NodeOutcome::Updated => version == NEW,
            // Every image here confirms itself: a revert is the cut's doing, and reporting it
            // as the image's would blame the image.
            NodeOutcome::Reverted => false,
            NodeOutcome::Refused => version == OLD,
            // The gateway stopped hearing it: it may run either.
            NodeOutcome::Unreachable | NodeOutcome::LostPower => true,
            NodeOutcome::Failed | NodeOutcome::Skipped => false,
        };
        if !truthful {
            return Err(format!(
                "{} reported {} ({why:?}) but runs {version}",
                sc.id,
                outcome.as_str()
            ));
        }
    }
    Ok(())
}

#[test]
fn power_cuts_during_island_updates_strand_no_element() {
    let seed: u64 = std::env::var(SEED_ENV)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(CI_SEED);
    let cuts: usize = std::env::var(CUTS_ENV)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(CI_CUTS);
    println!("power-cut suite: seed {seed}, {cuts} cuts ({SEED_ENV}, {CUTS_ENV})");
    let old = sim(OLD, 3_000);
    let new = sim(NEW, 4_000);
    assert_ne!(
        Header::parse(&old).unwrap().image_id(),
        Header::parse(&new).unwrap().image_id()
    );
    let (before, after) = clean_ops(&old, &new);
    let clean = run(&old, &new, None, 0);
    assert!(clean.report.all_updated(), "{:?}", clean.report);
    let clean_ms = clean.ms;
    let mut rng = seed;
    let mut done = 0;
    let mut tally: BTreeMap<&'static str, usize> = BTreeMap::new();
    let mut runs = 0;
    while done < cuts {
        runs += 1;
        assert!(runs <= cuts * 3, "too few cuts took effect");
        let victim = (lcg(&mut rng) % IDS.len() as u64) as usize;
        let cut = match lcg(&mut rng) % 3 {
            0 => Cut::Op(lcg(&mut rng) % before),
            1 => Cut::OpAfterCommit(lcg(&mut rng) % after.max(1)),
            _ => Cut::At(lcg(&mut rng) % (clean_ms + 2_000)),
        };
        let back_ms = 5 + lcg(&mut rng) % 3_000;
        let mut r = run(&old, &new, Some((victim, cut)), back_ms);
        if !r.scs[victim].was_cut {
            continue;
        }
        done += 1;
        if let Err(e) = check(&mut r, &old, &new) {
            panic!(
                "seed {seed}, cut {done} ({cut:?} on {}, power back after {back_ms} ms): {e}; report {:?}",
                IDS[victim], r.report.nodes
            );
        }
        for n in &r.report.nodes {
            *tally.entry(n.outcome.as_str()).or_default() += 1;
        }
    }
    println!("outcomes over {cuts} cut runs: {tally:?}");
}
