//! Firmware updates of a simulated sub-controller, without a bus: the node core, its board (flash +
//! embassy-boot's real swap and revert) and a gateway that drives the transfer the way the update
//! protocol allows (begin, header, data, query, resend the gaps, commit, confirm).
//!
//! * power cuts at ≥ 100 random points of the transfer and ≥ 100 of the swap and confirmation:
//!   the board always comes back running the old or the new image, never neither, and the update
//!   then completes;
//! * every refusal (bad signature, unknown key, wrong board, truncated, corrupted, downgrade,
//!   incompatible protocol, too large) is reported with its reason and the node keeps its image;
//! * an image that never confirms itself is reverted at the next reset.

use ihex_image::board::F303RE;
use ihex_image::{Board as BoardId, FirmwareVersion, Hasher, Header, SigningKey, HEADER_BLOCK};
use ihex_proto::{
    BootRole, FwAction, FwPhase, FwRefusal, FwStatus, Message, NodeId, Packet, ResetReason, Uid,
    FW_DATA_LEN, PROTOCOL_VERSION,
};
use ihex_sc_core::{Config, Millis, Node, Output, RESET_DELAY_MS};
use sim_node::board::{self, Board, BootFailure, Carried, SimFirmware};

const OLD: FirmwareVersion = FirmwareVersion::new(1, 0, 0);
const NEW: FirmwareVersion = FirmwareVersion::new(1, 1, 0);
const ID: u16 = 0x111;

fn id() -> NodeId {
    NodeId::new_sc(ID).unwrap()
}

fn sim(version: FirmwareVersion, confirms: bool, len: usize) -> Vec<u8> {
    board::sim_image(
        version,
        SimFirmware { confirms },
        len,
        &SigningKey::test_key(),
    )
    .unwrap()
}

fn image_id(img: &[u8]) -> u32 {
    Header::parse(img).unwrap().image_id()
}

/// One simulated SC as the island runs it: node + board, with its own clock; the gateway's
/// frames go straight in, the node's frames are collected.
struct Sc {
    board: Board,
    node: Option<Node>,
    now: u64,
    sent: Vec<Message>,
    boots: u32,
}

impl Sc {
    fn new(image: &[u8]) -> Sc {
        let mut sc = Sc {
            board: Board::with_image(image),
            node: None,
            now: 0,
            sent: Vec::new(),
            boots: 0,
        };
        sc.power_on();
        sc
    }

    /// Reset or power-on: the bootloader runs (resuming a swap a cut interrupted), then the node.
    fn power_on(&mut self) {
        self.node = None;
        loop {
            self.board.flash.power_on();
            match board::boot(&mut self.board, ihex_image::test_key::PUBLIC) {
                Ok(b) => {
                    self.boots += 1;
                    let config = Config {
                        role: BootRole::Static,
                        ports: 6,
                        uid: Uid([7; 12]),
                        node_id: Some(id()),
                        reset: ResetReason::Software,
                        firmware: b.firmware,
                        update: b.update,
                    };
                    let mut node = Node::new(config, Millis(self.now));
                    node.handle_self_test(b.self_test(), Millis(self.now));
                    self.node = Some(node);
                    self.drain();
                    return;
                }
                Err(BootFailure::Flash(_)) if !self.board.flash.is_dead() => {
                    panic!("the bootloader failed without a power cut")
                }
                Err(BootFailure::Flash(_)) => continue, // cut during the swap: power back, retry
                Err(BootFailure::NoImage) => panic!("neither image in the active slot"),
            }
        }
    }

    /// Carries out the node's outputs like the island's adapter. A power cut kills the node on
    /// the spot; a reset restarts it.
    fn drain(&mut self) {
        loop {
            let Some(node) = self.node.as_mut() else {
                return;
            };
            let Some(out) = node.poll_output() else {
                return;
            };
            let carried = board::carry_out(&mut self.board, node, out, Millis(self.now));
            if self.board.flash.is_dead() {
                self.node = None;
                return;
            }
            match carried {
                Carried::Done => {}
                Carried::Reset => return self.power_on(),
                Carried::Other(Output::Frame(p)) => self.sent.push(p.msg),
                Carried::Other(_) => {}
            }
        }
    }

    fn send(&mut self, msg: Message) {
        self.now += 1;
        let Some(node) = self.node.as_mut() else {
            return;
        };
        let (raw, data) = Packet::command(NodeId::BROADCAST, msg).encode();
        node.handle_frame(raw, true, false, &data, Millis(self.now));
        self.drain();
    }

    fn wait(&mut self, ms: u64) {
        self.now += ms;
        if let Some(node) = self.node.as_mut() {
            node.tick(Millis(self.now));
        }
        self.drain();
    }

    /// The node's answer to a status query (`None` when it is dead or silent).
    fn status(&mut self, image_id: u32) -> Option<FwStatus> {
        self.sent.clear();
        self.send(Message::FwQuery { image_id });
        self.sent.iter().rev().find_map(|m| match m {
            Message::FwStatus(s) => Some(*s),
            _ => None,
        })
    }

    /// The running image (version, payload hash) and whether it is on trial.
    fn running(&self) -> (FirmwareVersion, [u8; 7], bool) {
        let c = self.node.as_ref().expect("running").config();
        (c.firmware.version, c.firmware.image_hash, c.firmware.trial)
    }
}

fn hash7(img: &[u8]) -> [u8; 7] {
    Hasher::digest(&img[HEADER_BLOCK..]).prefix::<7>()
}

fn data(img: &[u8], index: usize) -> Message {
    let mut d = [0xFF; FW_DATA_LEN];
    let at = index * FW_DATA_LEN;
    let end = (at + FW_DATA_LEN).min(img.len());
    d[..end - at].copy_from_slice(&img[at..end]);
    Message::FwData {
        index: index as u16,
        data: d,
    }
}

/// How an update ended, if not with the new image confirmed.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Outcome {
    Refused(FwRefusal),
    Reverted,
}

/// The gateway's side of one update, as the protocol allows it to recover from anything: it asks
/// for the status and does what it says, until the node runs the new image confirmed. A revert
/// (the node came back on the old image after it installed this one) ends it, unless `retry`
/// (power cuts may cause one). `check` runs at every boot of the node.
fn update(
    sc: &mut Sc,
    img: &[u8],
    force: bool,
    retry: bool,
    mut check: impl FnMut(&Sc),
) -> Result<(), Outcome> {
    let id = image_id(img);
    let frames = img.len().div_ceil(FW_DATA_LEN);
    let want = hash7(img);
    let mut boots = sc.boots;
    let begin = Message::FwBegin {
        image_id: id,
        len: img.len() as u32,
        force,
    };
    // A `reverted` node only means this image was reverted once it was committed and installed.
    let mut installed = false;
    for _ in 0..500 {
        if sc.node.is_none() {
            sc.power_on(); // power back after a cut
        }
        if sc.boots != boots {
            boots = sc.boots;
            check(sc);
        }
        let (_, running, trial) = sc.running();
        if running == want && !trial {
            return Ok(());
        }
        let Some(st) = sc.status(id) else { continue };
        match st.phase {
            FwPhase::Reverted if installed && !retry => return Err(Outcome::Reverted),
            FwPhase::Idle | FwPhase::Reverted => sc.send(begin),
            FwPhase::Header | FwPhase::Receiving => {
                let from = st.first_missing as usize;
                for i in from..(from + st.run as usize).min(frames) {
                    sc.send(data(img, i));
                }
            }
            FwPhase::Complete => sc.send(Message::FwEnd {
                image_id: id,
                action: FwAction::Commit,
            }),
            // Resetting soon (after the commit, or a trial image that failed its self-test), or
            // a trial image that confirms once it hears the gateway (this query was heard).
            FwPhase::Rebooting | FwPhase::Verifying | FwPhase::Erasing | FwPhase::Trial => {
                installed |= st.phase == FwPhase::Rebooting;
                sc.wait(RESET_DELAY_MS)
            }
            // A flash operation failed (a cut the node did not survive looks the same): again.
            FwPhase::Refused if st.reason == FwRefusal::FlashError => sc.send(begin),
            FwPhase::Refused => return Err(Outcome::Refused(st.reason)),
            other => panic!("unexpected phase {other:?}"),
        }
    }
    panic!("the update did not finish")
}

/// The active slot holds exactly `old` or `new`: header and payload, byte for byte.
fn old_or_new(sc: &Sc, old: &[u8], new: &[u8]) -> Result<(), String> {
    let slot = sc.board.flash.region(F303RE.active);
    for img in [old, new] {
        if slot[..img.len()] == *img {
            return Ok(());
        }
    }
    Err("the active slot holds neither the old nor the new image".into())
}

/// A deterministic pseudo-random sequence (no dependency for a test's seeds).
fn lcg(seed: &mut u64) -> u64 {
    *seed = seed
        .wrapping_mul(6_364_136_223_846_793_005)
        .wrapping_add(1_442_695_040_888_963_407);
    *seed >> 33
}

#[test]
fn an_update_swaps_the_new_image_in_and_confirms_it() {
    let old = sim(OLD, true, 20_000);
    let new = sim(NEW, true, 24_000);
    let mut sc = Sc::new(&old);
    assert_eq!(sc.running(), (OLD, hash7(&old), false));
    update(&mut sc, &new, false, false, |_| {}).unwrap();
    assert_eq!(sc.running(), (NEW, hash7(&new), false));
    // Confirmed for good: another reset keeps it.
    sc.power_on();
    assert_eq!(sc.running(), (NEW, hash7(&new), false));
    assert_eq!(sc.status(image_id(&new)).unwrap().phase, FwPhase::Idle);
}

#[test]
fn an_image_that_never_confirms_itself_is_reverted_at_the_next_reset() {
    let old = sim(OLD, true, 20_000);
    let bad = sim(NEW, false, 24_000);
    let mut sc = Sc::new(&old);
    let id = image_id(&bad);
    let mut seen_trial_of_new = false;
    // The transfer succeeds; the new image starts on trial, fails its self-test, resets, and the
    // bootloader puts the old one back.
    let r = update(&mut sc, &bad, false, false, |sc| {
        let (v, _, trial) = sc.running();
        seen_trial_of_new |= v == NEW && trial;
    });
    assert_eq!(r, Err(Outcome::Reverted));
    assert!(seen_trial_of_new, "the new image did start, on trial");
    assert_eq!(sc.running(), (OLD, hash7(&old), false));
    assert_eq!(sc.status(id).unwrap().phase, FwPhase::Reverted);
    // And the node takes the next (good) update.
    let good = sim(FirmwareVersion::new(1, 2, 0), true, 10_000);
    update(&mut sc, &good, false, false, |_| {}).unwrap();
    assert_eq!(sc.running().0, FirmwareVersion::new(1, 2, 0));
}

#[test]
fn power_cuts_anywhere_leave_the_old_or_the_new_image_never_neither() {
    let old = sim(OLD, true, 20_000);
    let new = sim(NEW, true, 30_000);
    // A clean run, to count the flash operations of the transfer and of the whole update.
    let mut sc = Sc::new(&old);
    let mut transfer_ops = None;
    let new_id = image_id(&new);
    {
        let sc = &mut sc;
        // Phase 1: up to the commit (the transfer); phase 2: commit, swap, confirm.
        let frames = new.len().div_ceil(FW_DATA_LEN);
        sc.send(Message::FwBegin {
            image_id: new_id,
            len: new.len() as u32,
            force: false,
        });
        for i in 0..frames {
            sc.send(data(&new, i));
        }
        assert_eq!(sc.status(new_id).unwrap().phase, FwPhase::Complete);
        transfer_ops = transfer_ops.or(Some(sc.board.flash.ops()));
        update(sc, &new, false, false, |_| {}).unwrap();
    }
    let transfer_ops = transfer_ops.unwrap();
    let total_ops = sc.board.flash.ops();
    assert!(
        total_ops > transfer_ops * 2,
        "the swap is counted: {total_ops} > {transfer_ops}"
    );

    let mut seed = 0x1EC5_F00D;
    let mut cuts = Vec::new();
    for _ in 0..110 {
        cuts.push(lcg(&mut seed) % transfer_ops);
    }
    for _ in 0..110 {
        cuts.push(transfer_ops + lcg(&mut seed) % (total_ops - transfer_ops));
    }
    for (n, at) in cuts.into_iter().enumerate() {
        let mut sc = Sc::new(&old);
        sc.board.flash.cut_after(at, n as u64 + 1);
        let mut problem = None;
        update(&mut sc, &new, false, true, |sc| {
            if let Err(e) = old_or_new(sc, &old, &new) {
                problem.get_or_insert(e);
            }
        })
        .unwrap_or_else(|r| panic!("cut at op {at}: refused {r:?}"));
        assert_eq!(problem, None, "cut at op {at}");
        assert_eq!(sc.running(), (NEW, hash7(&new), false), "cut at op {at}");
        assert!(!sc.board.flash.is_dead());
    }
}

/// An update that must be refused with `reason`, leaving the running image as it was.
#[track_caller]
fn refused(img: &[u8], force: bool, reason: FwRefusal) {
    let old = sim(OLD, true, 20_000);
    let mut sc = Sc::new(&old);
    let slot_before = sc.board.flash.region(F303RE.active);
    assert_eq!(
        update(&mut sc, img, force, false, |_| {}),
        Err(Outcome::Refused(reason))
    );
    // Nothing was marked for the bootloader: a reset starts the same image.
    sc.power_on();
    assert_eq!(sc.running(), (OLD, hash7(&old), false));
    assert_eq!(sc.board.flash.region(F303RE.active), slot_before);
}

#[test]
fn refusals_leave_the_node_on_its_image() {
    let key = SigningKey::test_key();
    let payload = SimFirmware { confirms: true }.payload(NEW, 5000);
    let pack = |board, protocol, v, key: &SigningKey| {
        ihex_image::pack(board, protocol, v, &payload, key).unwrap()
    };
    // Bad signature: one flipped bit in the signature.
    let mut bad_sig = pack(BoardId::SIM, PROTOCOL_VERSION, NEW, &key);
    bad_sig[130] ^= 0x04;
    refused(&bad_sig, false, FwRefusal::BadSignature);
    // Signed by a key the node does not trust.
    let lab = SigningKey::from_seed([0x42; 32]);
    refused(
        &pack(BoardId::SIM, PROTOCOL_VERSION, NEW, &lab),
        false,
        FwRefusal::UnknownKey,
    );
    // Built for the real board.
    refused(
        &pack(BoardId::NUCLEO_F303RE, PROTOCOL_VERSION, NEW, &key),
        false,
        FwRefusal::WrongBoard,
    );
    // Another protocol major.
    refused(
        &pack(BoardId::SIM, (PROTOCOL_VERSION.0 + 1, 0), NEW, &key),
        false,
        FwRefusal::IncompatibleProtocol,
    );
    // A downgrade, unless forced.
    let older = pack(
        BoardId::SIM,
        PROTOCOL_VERSION,
        FirmwareVersion::new(0, 9, 0),
        &key,
    );
    refused(&older, false, FwRefusal::Downgrade);
    let mut sc = Sc::new(&sim(OLD, true, 20_000));
    update(&mut sc, &older, true, false, |_| {}).unwrap();
    assert_eq!(sc.running().0, FirmwareVersion::new(0, 9, 0));
    // Truncated: the file lost its end.
    let good = pack(BoardId::SIM, PROTOCOL_VERSION, NEW, &key);
    refused(&good[..good.len() - 100], false, FwRefusal::Truncated);
    // Corrupted on the way: the bytes do not hash to the signed hash (found at commit).
    let mut corrupt = good.clone();
    corrupt[HEADER_BLOCK + 2000] ^= 0xFF;
    refused(&corrupt, false, FwRefusal::Corrupted);
    // Too large for the slot.
    let huge = vec![0u8; F303RE.active.len as usize + 6];
    let mut sc = Sc::new(&sim(OLD, true, 20_000));
    sc.send(Message::FwBegin {
        image_id: 1,
        len: huge.len() as u32,
        force: false,
    });
    assert_eq!(
        sc.status(1),
        Some(FwStatus::phase(FwPhase::Refused, FwRefusal::TooLarge))
    );
}
