//! The sender against model nodes that follow the node side of the protocol (phases, unasked
//! statuses, first missing run, reset on commit, trial and confirmation), on a virtual clock:
//! every frame the sender hands out is delivered at once, time moves in 1 ms steps.

use std::collections::{BTreeSet, VecDeque};
use std::time::{Duration, Instant};

use ihex_image::{pack, Board, SigningKey};
use ihex_proto::{
    FirmwareVersion, FwAction, FwPhase, FwRefusal, FwStatus, Message, NodeId, Packet,
};

use super::*;

fn nid(raw: u16) -> NodeId {
    NodeId::new_sc(raw).unwrap()
}

const HEADER_FRAMES: u32 = 32;
const STEP: Duration = Duration::from_millis(1);

fn image(payload_len: usize) -> FwImage {
    let key = SigningKey::from_text(ihex_image::test_key::SECRET_TEXT).unwrap();
    let payload: Vec<u8> = (0..payload_len).map(|i| (i * 7 + 3) as u8).collect();
    let bytes = pack(
        Board::SIM,
        ihex_proto::PROTOCOL_VERSION,
        FirmwareVersion {
            major: 1,
            minor: 3,
            patch: 0,
        },
        &payload,
        &key,
    )
    .unwrap();
    FwImage::check(bytes).unwrap()
}

/// What a model node does besides following the protocol.
#[derive(Clone, Default)]
struct Quirks {
    /// Refuse the header with this reason.
    refuse: Option<FwRefusal>,
    /// Lose these data frames the first time they are sent.
    lose: BTreeSet<u32>,
    /// Reset (losing the transfer) when this data frame arrives, once.
    reset_at: Option<u32>,
    /// The new image never confirms itself: it reverts.
    never_confirms: bool,
    /// Never answers anything.
    dead: bool,
    /// Leave this many queries unanswered once data has come (a receive queue still full of the
    /// burst drops them).
    deaf_after_data: u32,
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum NPhase {
    Idle,
    Header,
    Erasing(Instant),
    Receiving,
    Complete,
    Rebooting(Instant),
    Trial(Instant),
    Confirmed,
    Reverted,
    Refused(FwRefusal),
}

struct Model {
    id: NodeId,
    quirks: Quirks,
    frames: u32,
    have: Vec<bool>,
    phase: NPhase,
    /// Data frames taken (to check only the missing ones were resent).
    received: Vec<u32>,
    boots: u32,
}

const ERASE: Duration = Duration::from_millis(400);
const REBOOT: Duration = Duration::from_millis(800);
const CONFIRM: Duration = Duration::from_millis(1500);

impl Model {
    fn new(id: u16, frames: u32, quirks: Quirks) -> Self {
        Model {
            id: nid(id),
            quirks,
            frames,
            have: vec![false; frames as usize],
            phase: NPhase::Idle,
            received: Vec::new(),
            boots: 0,
        }
    }

    fn missing_from(&self, from: u32, to: u32) -> (u16, u16, u16) {
        let miss: Vec<u32> = (from..to).filter(|&i| !self.have[i as usize]).collect();
        let Some(&first) = miss.first() else {
            return (0, 0, 0);
        };
        let run = miss
            .iter()
            .enumerate()
            .take_while(|&(k, &i)| i == first + k as u32)
            .count();
        (first as u16, run as u16, miss.len() as u16)
    }

    fn status(&self) -> FwStatus {
        let ph = |p| FwStatus::phase(p, FwRefusal::None);
        match self.phase {
            NPhase::Idle | NPhase::Confirmed => ph(FwPhase::Idle),
            NPhase::Header => {
                let (first_missing, run, missing) = self.missing_from(0, HEADER_FRAMES);
                FwStatus {
                    first_missing,
                    run,
                    missing,
                    ..ph(FwPhase::Header)
                }
            }
            NPhase::Erasing(_) => ph(FwPhase::Erasing),
            NPhase::Receiving => {
                let (first_missing, run, missing) = self.missing_from(HEADER_FRAMES, self.frames);
                FwStatus {
                    first_missing,
                    run,
                    missing,
                    ..ph(FwPhase::Receiving)
                }
            }
            NPhase::Complete => ph(FwPhase::Complete),
            NPhase::Rebooting(_) => ph(FwPhase::Rebooting),
            NPhase::Trial(_) => ph(FwPhase::Trial),
            NPhase::Reverted => ph(FwPhase::Reverted),
            NPhase::Refused(r) => FwStatus::phase(FwPhase::Refused, r),
        }
    }

    fn on_packet(&mut self, p: &Packet, now: Instant, out: &mut Vec<(NodeId, Message)>) {
        if self.quirks.dead || !(p.dest == self.id || p.dest == NodeId::BROADCAST) {
            return;
        }
        let mut say = |m: &Model| out.push((m.id, Message::FwStatus(m.status())));
        match p.msg {
            Message::FwBegin { .. } => {
                if matches!(
                    self.phase,
                    NPhase::Idle | NPhase::Refused(_) | NPhase::Reverted
                ) {
                    self.have.iter_mut().for_each(|h| *h = false);
                    self.phase = NPhase::Header;
                }
                say(self);
            }
            Message::FwQuery { .. }
                if !self.received.is_empty() && self.quirks.deaf_after_data > 0 =>
            {
                self.quirks.deaf_after_data -= 1;
            }
            Message::FwQuery { .. } => say(self),
            Message::FwEnd {
                action: FwAction::Commit,
                ..
            } if self.phase == NPhase::Complete => {
                self.phase = NPhase::Rebooting(now + REBOOT);
                say(self);
            }
            Message::FwData { index, .. } => {
                let i = u32::from(index);
                if self.quirks.lose.remove(&i) {
                    return;
                }
                if self.quirks.reset_at == Some(i) {
                    self.quirks.reset_at = None;
                    self.phase = NPhase::Idle;
                    self.boots += 1;
                    out.push((self.id, boot_up()));
                    return;
                }
                match self.phase {
                    NPhase::Header if i < HEADER_FRAMES => {
                        self.have[i as usize] = true;
                        if self.missing_from(0, HEADER_FRAMES).2 == 0 {
                            self.phase = match self.quirks.refuse {
                                Some(r) => NPhase::Refused(r),
                                None => NPhase::Erasing(now + ERASE),
                            };
                            say(self);
                        }
                    }
                    NPhase::Receiving if i >= HEADER_FRAMES => {
                        self.received.push(i);
                        self.have[i as usize] = true;
                        if self.missing_from(HEADER_FRAMES, self.frames).2 == 0 {
                            self.phase = NPhase::Complete;
                            say(self);
                        }
                    }
                    _ => {}
                }
            }
            _ => {}
        }
    }

    fn tick(&mut self, now: Instant, out: &mut Vec<(NodeId, Message)>) {
        match self.phase {
            NPhase::Erasing(t) if now >= t => {
                self.phase = NPhase::Receiving;
                out.push((self.id, Message::FwStatus(self.status())));
            }
            NPhase::Rebooting(t) if now >= t => {
                self.boots += 1;
                self.phase = NPhase::Trial(now + CONFIRM);
                out.push((self.id, boot_up()));
            }
            NPhase::Trial(t) if now >= t => {
                if self.quirks.never_confirms {
                    self.boots += 1;
                    self.phase = NPhase::Reverted;
                    out.push((self.id, boot_up()));
                } else {
                    self.phase = NPhase::Confirmed;
                }
            }
            _ => {}
        }
    }
}

fn boot_up() -> Message {
    Message::BootUp {
        version: ihex_proto::PROTOCOL_VERSION,
        role: ihex_proto::BootRole::Static,
        ports: 6,
        reset: ihex_proto::ResetReason::Software,
    }
}

struct Run {
    report: FwReport,
    progress: Vec<FwProgress>,
    /// (when, bits) of every frame the sender handed out.
    sent: Vec<(Instant, u32)>,
    /// Every packet the sender handed out, in order.
    packets: Vec<Packet>,
    models: Vec<Model>,
    t0: Instant,
}

fn run(models: Vec<Model>, image: FwImage, config: FwConfig) -> Run {
    run_docked(models, image, config, &[])
}

/// [`run`] on an island with these dockings, `(static element, mobile element)`.
fn run_docked(models: Vec<Model>, image: FwImage, config: FwConfig, docked: &[(u16, u16)]) -> Run {
    run_full(models, image, config, docked, None)
}

/// A static element that restarts on its own (it is not in the update) each time its docked
/// mobile element starts a new image on trial, `times` times: the mobile element loses power
/// with it, and its trial image is reverted by that reset.
#[derive(Clone, Copy)]
struct HostCut {
    host: u16,
    mobile: u16,
    times: u32,
    /// The mobile element comes back on its old image, confirmed (`idle`, and its state report
    /// says the old version) instead of answering `reverted`.
    old_idle: bool,
}

fn run_full(
    mut models: Vec<Model>,
    image: FwImage,
    config: FwConfig,
    docked: &[(u16, u16)],
    mut cut: Option<HostCut>,
) -> Run {
    let t0 = Instant::now();
    let hosts: Vec<NodeId> = cut.iter().map(|c| nid(c.host)).collect();
    let ids: Vec<NodeId> = models
        .iter()
        .map(|m| m.id)
        .filter(|id| !hosts.contains(id))
        .collect();
    let mut s = FwSender::new(image, ids, false, Some("r1".into()), config, t0);
    s.set_docked(docked.iter().map(|&(st, m)| (nid(st), nid(m))));
    let mut now = t0;
    let mut sent = Vec::new();
    let mut packets = Vec::new();
    let mut progress = Vec::new();
    let mut replies: VecDeque<(NodeId, Message)> = VecDeque::new();
    for _ in 0..600_000 {
        let mut out = Vec::new();
        while let Some(p) = s.poll_transmit() {
            sent.push((now, cost(&p)));
            packets.push(p);
            for m in models.iter_mut() {
                m.on_packet(&p, now, &mut out);
            }
        }
        for m in models.iter_mut() {
            m.tick(now, &mut out);
        }
        let mut read_back = None;
        if let Some(c) = cut.as_mut().filter(|c| c.times > 0) {
            let on_trial = models
                .iter()
                .any(|m| m.id == nid(c.mobile) && matches!(m.phase, NPhase::Trial(_)));
            if on_trial {
                c.times -= 1;
                // The host restarts (it says so), the mobile element starts again unconfirmed:
                // the bootloader puts its old image back.
                out.push((nid(c.host), boot_up()));
                let m = models.iter_mut().find(|m| m.id == nid(c.mobile)).unwrap();
                m.boots += 1;
                m.phase = if c.old_idle {
                    NPhase::Idle
                } else {
                    NPhase::Reverted
                };
                out.push((m.id, boot_up()));
                if c.old_idle {
                    read_back = Some(nid(c.mobile));
                }
            }
        }
        replies.extend(out);
        while let Some((src, msg)) = replies.pop_front() {
            match msg {
                Message::FwStatus(st) => s.handle_status(src, st, now),
                Message::BootUp { .. } => s.handle_boot_up(src, now),
                _ => {}
            }
        }
        if let Some(m) = read_back {
            // Its state read-back after the boot-up: the old version, confirmed.
            s.handle_firmware(m, ihex_proto::FirmwareVersion::new(1, 0, 0), false, now);
        }
        while let Some(e) = s.poll_event() {
            match e {
                Event::FwProgress(p) => progress.push(p),
                Event::FwReport(report) => {
                    return Run {
                        report: *report,
                        progress,
                        sent,
                        packets,
                        models,
                        t0,
                    }
                }
                other => panic!("unexpected {other:?}"),
            }
        }
        now += STEP;
        s.handle_timeout(now);
    }
    panic!("the update did not end within 600 s of virtual time");
}

/// The first time a mobile element loses power on trial because its static element restarted, it
/// is begun again and ends `updated`; a power cut is never blamed on the image.
#[test]
fn a_mobile_element_that_lost_power_is_retried_and_updated() {
    let img = image(2000);
    let frames = img.frames();
    let models = [0x101, 2]
        .into_iter()
        .map(|id| Model::new(id, frames, Quirks::default()))
        .collect();
    let cut = HostCut {
        host: 0x101,
        mobile: 2,
        times: 1,
        old_idle: false,
    };
    let r = run_full(models, img, FwConfig::default(), &[(0x101, 2)], Some(cut));
    assert_eq!(outcomes(&r.report), vec![(2, NodeOutcome::Updated, None)]);
    // Trial, revert by the power cut, trial again.
    assert_eq!(r.models[1].boots, 3);
    assert_eq!(r.models[1].phase, NPhase::Confirmed);
}

/// After a power cut a mobile element answers `idle` on its old image: not `updated` — its
/// state report's old version shows the new image never ran, so it is begun again.
#[test]
fn a_mobile_element_back_on_its_old_image_after_a_power_cut_is_not_updated_but_retried() {
    let img = image(2000);
    let frames = img.frames();
    let models = [0x101, 2]
        .into_iter()
        .map(|id| Model::new(id, frames, Quirks::default()))
        .collect();
    let cut = HostCut {
        host: 0x101,
        mobile: 2,
        times: 1,
        old_idle: true,
    };
    let r = run_full(models, img, FwConfig::default(), &[(0x101, 2)], Some(cut));
    assert_eq!(outcomes(&r.report), vec![(2, NodeOutcome::Updated, None)]);
    // Its transfer ran twice: the header went out twice.
    assert!(
        r.report.frames_sent > u64::from(frames),
        "{}",
        r.report.frames_sent
    );
    assert_eq!(r.models[1].phase, NPhase::Confirmed);
}

/// A mobile element whose power is cut at every try ends `lost_power`, naming its host, after
/// the retries: not `reverted`.
#[test]
fn a_mobile_element_that_keeps_losing_power_ends_lost_power() {
    let img = image(2000);
    let frames = img.frames();
    let models = [0x101, 2]
        .into_iter()
        .map(|id| Model::new(id, frames, Quirks::default()))
        .collect();
    let cut = HostCut {
        host: 0x101,
        mobile: 2,
        times: u32::MAX,
        old_idle: false,
    };
    let r = run_full(models, img, FwConfig::default(), &[(0x101, 2)], Some(cut));
    assert_eq!(
        outcomes(&r.report),
        vec![(
            2,
            NodeOutcome::LostPower,
            Some("lost power when 101 restarted".into())
        )]
    );
    assert_eq!(r.models[1].boots, 2 * (POWER_RETRIES + 1));
}

/// A node given up as `unreachable` that then reports the new image confirmed: the outcome is
/// corrected and an `fw_correction` says so; the other firmware reports change nothing.
#[test]
fn a_late_confirmation_is_a_correction_event() {
    let img = image(1000);
    let version = img.version();
    let t0 = Instant::now();
    let config = FwConfig {
        reboot_timeout: Duration::from_secs(2),
        ..FwConfig::default()
    };
    let mut s = FwSender::new(
        img.clone(),
        [nid(0x191)],
        false,
        Some("r9".into()),
        config,
        t0,
    );
    let mut model = Model::new(0x191, img.frames(), Quirks::default());
    let mut now = t0;
    let mut report = None;
    // Drive it to `rebooting`, then the node stays silent: `unreachable`.
    for _ in 0..60_000 {
        let mut out = Vec::new();
        while let Some(p) = s.poll_transmit() {
            model.on_packet(&p, now, &mut out);
        }
        if !matches!(model.phase, NPhase::Rebooting(_)) {
            model.tick(now, &mut out);
        }
        for (src, msg) in out {
            if let Message::FwStatus(st) = msg {
                s.handle_status(src, st, now);
            }
        }
        while let Some(e) = s.poll_event() {
            if let Event::FwReport(r) = e {
                report = Some(r);
            }
        }
        if report.is_some() {
            break;
        }
        now += STEP;
        s.handle_timeout(now);
    }
    let report = report.expect("a report");
    assert_eq!(report.nodes[0].outcome, NodeOutcome::Unreachable);
    let older = ihex_proto::FirmwareVersion::new(1, 2, 0);
    s.handle_firmware(nid(0x191), older, false, now);
    s.handle_firmware(nid(0x191), version, true, now);
    assert!(
        s.poll_event().is_none(),
        "neither the old nor a trial image corrects"
    );
    s.handle_firmware(nid(0x191), version, false, now);
    let Some(Event::FwCorrection(c)) = s.poll_event() else {
        panic!("a correction");
    };
    assert_eq!(c.node.0, nid(0x191));
    assert_eq!(c.was, NodeOutcome::Unreachable);
    assert_eq!(c.outcome, NodeOutcome::Updated);
    assert_eq!(c.request_id.as_deref(), Some("r9"));
    // Once.
    s.handle_firmware(nid(0x191), version, false, now);
    assert!(s.poll_event().is_none());
}

fn outcomes(r: &FwReport) -> Vec<(u16, NodeOutcome, Option<String>)> {
    r.nodes
        .iter()
        .map(|n| (n.node.0.get(), n.outcome, n.reason.clone()))
        .collect()
}

#[test]
fn happy_path_to_many_nodes_sends_the_image_once() {
    let img = image(6000);
    let frames = img.frames();
    let models = (0x101..0x10B)
        .map(|id| Model::new(id, frames, Quirks::default()))
        .collect();
    let r = run(models, img, FwConfig::default());
    assert!(r.report.all_updated(), "{:?}", outcomes(&r.report));
    assert_eq!(r.report.nodes.len(), 10);
    assert_eq!(r.report.version, "1.3.0");
    // One broadcast of the header and of the data: ten nodes, one copy of each frame.
    assert_eq!(r.report.frames_sent, u64::from(frames));
    for m in &r.models {
        assert_eq!(m.phase, NPhase::Confirmed);
        assert_eq!(m.boots, 1);
    }
    // Progress: every node went through these phases, in this order, each reported once.
    let phases: Vec<&str> = r
        .progress
        .iter()
        .filter(|p| p.node.0 == nid(0x105))
        .map(|p| p.phase.as_str())
        .collect();
    let mut want = vec![
        "begin",
        "header",
        "erasing",
        "receiving",
        "complete",
        "rebooting",
        "confirming",
    ];
    want.retain(|w| phases.contains(w));
    assert_eq!(phases.iter().filter(|p| **p == "confirming").count(), 1);
    assert!(want.len() >= 5, "{phases:?}");
    assert!(r
        .progress
        .iter()
        .all(|p| p.request_id.as_deref() == Some("r1")));
}

/// Each node's transfer is published in steps of at most `PROGRESS_STEP` % from 0 to 100,
/// derived from the frames sent: no query more than the rounds need.
#[test]
fn progress_moves_in_small_steps_without_extra_queries() {
    let img = image(20_000);
    let frames = img.frames();
    let models = (0x101..0x115)
        .map(|id| Model::new(id, frames, Quirks::default()))
        .collect();
    let r = run(models, img, FwConfig::default());
    assert!(r.report.all_updated(), "{:?}", outcomes(&r.report));
    for raw in 0x101..0x115 {
        let percents: Vec<u8> = r
            .progress
            .iter()
            .filter(|p| p.node.0 == nid(raw))
            .filter(|p| matches!(p.phase.as_str(), "receiving" | "complete"))
            .map(|p| p.percent)
            .collect();
        assert!(
            percents.len() >= 100 / usize::from(PROGRESS_STEP),
            "{percents:?}"
        );
        assert_eq!(percents.last(), Some(&100));
        for w in percents.windows(2) {
            assert!(
                w[1] >= w[0] && w[1] - w[0] <= PROGRESS_STEP,
                "{raw:x}: a step from {} to {}: {percents:?}",
                w[0],
                w[1]
            );
        }
    }
    // No query went out while the image's data was broadcast: the progress came from the frames.
    let data_at = |i: &Packet| matches!(i.msg, Message::FwData { index, .. } if u32::from(index) >= HEADER_FRAMES);
    let first = r.packets.iter().position(data_at).unwrap();
    let last = r.packets.iter().rposition(data_at).unwrap();
    let during = r.packets[first..last]
        .iter()
        .filter(|p| matches!(p.msg, Message::FwQuery { .. }))
        .count();
    assert_eq!(during, 0);
    assert_eq!(r.report.frames_sent, u64::from(frames));
}

#[test]
fn a_node_missing_frames_gets_only_those() {
    let img = image(3000);
    let frames = img.frames();
    let lose: BTreeSet<u32> = (100..110).chain([frames - 1]).collect();
    let lossy = Quirks {
        lose: lose.clone(),
        ..Quirks::default()
    };
    let models = vec![
        Model::new(0x111, frames, lossy),
        Model::new(0x112, frames, Quirks::default()),
    ];
    let r = run(models, img, FwConfig::default());
    assert!(r.report.all_updated(), "{:?}", outcomes(&r.report));
    let data = frames - HEADER_FRAMES;
    // The lossy node took every data frame once; the other never got a resend.
    let lossy = &r.models[0];
    assert_eq!(lossy.received.len() as u32, data);
    assert_eq!(r.models[1].received.len() as u32, data);
    assert_eq!(r.report.frames_sent, u64::from(frames) + lose.len() as u64);
}

/// A node whose answer was lost is asked again before it is sent anything: the sender does not
/// resend from what it last said (stale), which would repeat frames it has and bury its next
/// query behind them.
#[test]
fn a_node_that_did_not_answer_is_asked_before_it_is_sent_more() {
    let img = image(3000);
    let frames = img.frames();
    let lose: BTreeSet<u32> = (200..204).collect();
    let models = vec![
        // The query right after the image's broadcast goes unanswered.
        Model::new(
            0x161,
            frames,
            Quirks {
                lose: lose.clone(),
                deaf_after_data: 1,
                ..Quirks::default()
            },
        ),
        Model::new(0x162, frames, Quirks::default()),
    ];
    let r = run(models, img, FwConfig::default());
    assert!(r.report.all_updated(), "{:?}", outcomes(&r.report));
    // Each data frame reached it once: nothing was resent from its stale status.
    let quiet = &r.models[0];
    let mut distinct = quiet.received.clone();
    distinct.sort_unstable();
    distinct.dedup();
    let resent = quiet.received.len() - distinct.len();
    assert_eq!(resent, 0, "data frames it got twice");
    assert_eq!(distinct.len() as u32, frames - HEADER_FRAMES);
    assert_eq!(r.report.frames_sent, u64::from(frames) + lose.len() as u64);
}

#[test]
fn a_refusal_is_reported_with_the_nodes_reason_and_the_others_update() {
    let img = image(2000);
    let frames = img.frames();
    let refuse = Quirks {
        refuse: Some(FwRefusal::Downgrade),
        ..Quirks::default()
    };
    let models = vec![
        Model::new(0x121, frames, Quirks::default()),
        Model::new(0x122, frames, refuse),
    ];
    let r = run(models, img, FwConfig::default());
    assert_eq!(
        outcomes(&r.report),
        vec![
            (0x121, NodeOutcome::Updated, None),
            (0x122, NodeOutcome::Refused, Some("downgrade".into())),
        ]
    );
    assert_eq!(r.models[1].boots, 0);
    assert!(r.models[1].received.is_empty());
}

#[test]
fn a_node_that_resets_mid_transfer_starts_again_and_updates() {
    let img = image(4000);
    let frames = img.frames();
    let resets = Quirks {
        reset_at: Some(300),
        ..Quirks::default()
    };
    let models = vec![
        Model::new(0x131, frames, resets),
        Model::new(0x132, frames, Quirks::default()),
    ];
    let r = run(models, img, FwConfig::default());
    assert!(r.report.all_updated(), "{:?}", outcomes(&r.report));
    // Reset once mid-transfer, once to swap the image in.
    assert_eq!(r.models[0].boots, 2);
    // It began again: the header went out again (to it alone) and then the data it lacked.
    assert!(r.report.frames_sent > u64::from(frames));
    assert!(r.report.frames_sent < 2 * u64::from(frames) + 64);
}

#[test]
fn a_never_confirming_image_is_reported_reverted() {
    let img = image(1000);
    let frames = img.frames();
    let q = Quirks {
        never_confirms: true,
        ..Quirks::default()
    };
    let r = run(vec![Model::new(0x141, frames, q)], img, FwConfig::default());
    assert_eq!(outcomes(&r.report)[0].1, NodeOutcome::Reverted);
}

#[test]
fn a_silent_node_is_unreachable_and_does_not_hold_up_the_others() {
    let img = image(1000);
    let frames = img.frames();
    let dead = Quirks {
        dead: true,
        ..Quirks::default()
    };
    let models = vec![
        Model::new(0x151, frames, Quirks::default()),
        Model::new(0x152, frames, dead),
    ];
    let r = run(models, img, FwConfig::default());
    let o = outcomes(&r.report);
    assert_eq!(o[0].1, NodeOutcome::Updated);
    assert_eq!(o[1].1, NodeOutcome::Unreachable);
}

#[test]
fn the_bus_share_is_respected_over_every_window() {
    let img = image(30_000);
    let frames = img.frames();
    for share in [50u8, 20] {
        let config = FwConfig {
            bus_share: share,
            ..FwConfig::default()
        };
        let models = (0x161..0x165)
            .map(|id| Model::new(id, frames, Quirks::default()))
            .collect();
        let r = run(models, img.clone(), config);
        assert!(r.report.all_updated());
        // Bits in every 100 ms window starting at a frame: at most the share of 100 ms plus the
        // 10 ms burst.
        let window = Duration::from_millis(100);
        let allowed = u64::from(BUS_BITRATE) * u64::from(share) / 100 * 110 / 1000;
        let mut busiest = 0;
        for (i, &(t, _)) in r.sent.iter().enumerate() {
            let bits: u64 = r.sent[i..]
                .iter()
                .take_while(|(u, _)| *u < t + window)
                .map(|&(_, b)| u64::from(b))
                .sum();
            busiest = busiest.max(bits);
        }
        assert!(
            busiest <= allowed,
            "share {share}%: {busiest} bits in 100 ms > {allowed}"
        );
        // And the share is used: the data went out near the cap (not throttled to nothing).
        let data_bits = u64::from(frames) * u64::from(ihex_proto::bus::frame_bits_worst(8));
        let rate = u64::from(BUS_BITRATE) * u64::from(share) / 100;
        let floor = Duration::from_millis(data_bits * 1000 / rate);
        let last = r.sent.last().map(|&(t, _)| t - r.t0).unwrap();
        assert!(
            last >= floor,
            "share {share}%: all sent in {last:?} < {floor:?}"
        );
    }
}

#[test]
fn bus_down_pauses_without_counting_misses() {
    let img = image(2000);
    let t0 = Instant::now();
    let mut s = FwSender::new(img, [nid(0x171)], false, None, FwConfig::default(), t0);
    assert!(s.poll_transmit().is_some(), "the begin goes out");
    s.handle_bus_down(t0);
    assert_eq!(s.poll_timeout(), None);
    // A minute of silence while the bus is down: nobody is declared lost.
    let later = t0 + Duration::from_secs(60);
    s.handle_timeout(later);
    assert!(s.poll_transmit().is_none());
    assert!(s.poll_event().is_none());
    s.handle_bus_recovered(later);
    let p = s.poll_transmit().expect("asked again after recovery");
    assert_eq!(p.dest, nid(0x171));
    assert!(matches!(p.msg, Message::FwBegin { .. }));
}

#[test]
fn cancel_aborts_the_transfer_and_reports_failed() {
    let img = image(2000);
    let t0 = Instant::now();
    let mut s = FwSender::new(img, [nid(0x181)], false, None, FwConfig::default(), t0);
    s.cancel("gateway stopped", t0);
    let mut aborted = false;
    while let Some(p) = s.poll_transmit() {
        aborted |= matches!(
            p.msg,
            Message::FwEnd {
                action: FwAction::Abort,
                ..
            }
        );
    }
    assert!(aborted);
    s.handle_timeout(t0);
    let report = std::iter::from_fn(|| s.poll_event())
        .find_map(|e| match e {
            Event::FwReport(r) => Some(r),
            _ => None,
        })
        .expect("a report");
    assert_eq!(report.nodes[0].outcome, NodeOutcome::Failed);
    assert_eq!(report.nodes[0].reason.as_deref(), Some("gateway stopped"));
}

#[test]
fn a_bad_image_is_refused_before_anything_is_sent() {
    let good = image(500);
    let mut bytes = Vec::new();
    for i in 0..good.frames() {
        bytes.extend_from_slice(&good.frame(i as u16));
    }
    bytes.truncate(good.len() as usize);
    let mut corrupted = bytes.clone();
    *corrupted.last_mut().unwrap() ^= 1;
    let e = FwImage::check(corrupted).unwrap_err();
    assert!(e.to_string().contains("corrupted"), "{e}");
    let e = FwImage::check(bytes[..bytes.len() - 1].to_vec()).unwrap_err();
    assert!(e.to_string().contains("truncated"), "{e}");
    let e = FwImage::check(b"not an image".to_vec()).unwrap_err();
    assert!(e.to_string().starts_with("bad image"), "{e}");
}

#[test]
fn a_static_element_installs_only_after_the_mobile_elements_docked_on_it() {
    let img = image(3000);
    let frames = img.frames();
    let models = [0x101, 0x102, 2]
        .into_iter()
        .map(|id| Model::new(id, frames, Quirks::default()))
        .collect();
    // 2 is docked on 101; 102 powers nothing.
    let r = run_docked(models, img, FwConfig::default(), &[(0x101, 2)]);
    assert!(r.report.all_updated(), "{:?}", outcomes(&r.report));
    let done = |raw| {
        r.report
            .nodes
            .iter()
            .find(|n| n.node.0 == nid(raw))
            .map(|n| n.duration_ms)
            .unwrap()
    };
    // 101 restarts only once 2 has its outcome: at least a restart later.
    assert!(
        done(0x101) >= done(2) + REBOOT.as_millis() as u64,
        "101 at {} ms, 2 at {} ms",
        done(0x101),
        done(2)
    );
    // A static element powering nothing does not wait.
    assert!(done(0x102) < done(0x101), "{:?}", outcomes(&r.report));
    // The image went out once all the same.
    assert_eq!(r.report.frames_sent, u64::from(frames));
}

/// The release notes an image carries (header format 2) are in its report; an image without
/// them (format 1) has none.
#[test]
fn the_report_carries_the_release_notes() {
    let key = SigningKey::from_text(ihex_image::test_key::SECRET_TEXT).unwrap();
    let v = FirmwareVersion::new(1, 3, 0);
    let bytes = ihex_image::pack_with_notes(
        Board::SIM,
        ihex_proto::PROTOCOL_VERSION,
        v,
        &[9; 700],
        "faster docking",
        &key,
    )
    .unwrap();
    let img = FwImage::check(bytes).unwrap();
    assert_eq!(img.notes(), Some("faster docking"));
    let frames = img.frames();
    let r = run(
        vec![Model::new(0x1a1, frames, Quirks::default())],
        img,
        FwConfig::default(),
    );
    assert!(r.report.all_updated());
    assert_eq!(r.report.notes.as_deref(), Some("faster docking"));
    assert_eq!(image(700).notes(), None);
}
