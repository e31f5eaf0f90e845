//! Firmware update, node side: the transfer, every refusal, resends, resume, abort, verification,
//! trial boot and its confirmation or revert — driven by frames as the gateway would send them,
//! with the adapter's flash work played by [`Flash`].

mod common;

use common::{cmd, config, id, UPDATE};
use ihex_image::board::F303RE;
use ihex_image::{pack, Board, Hasher, SigningKey, HEADER_BLOCK};
use ihex_proto::{
    BootRole, FirmwareVersion, FwAction, FwPhase, FwRefusal, FwStatus, Message, NodeId, Packet,
    StateParts, StateReport, FW_DATA_LEN, PROTOCOL_VERSION,
};
use ihex_sc_core::{
    Config, FlashError, Millis, Node, Output, CHUNK_LEN, RESET_DELAY_MS, TRIAL_CONFIRM_MS,
};

/// The version the test nodes run (`common::FIRMWARE`).
const RUNNING: FirmwareVersion = FirmwareVersion::new(1, 4, 2);
const NEWER: FirmwareVersion = FirmwareVersion::new(1, 5, 0);

struct Image {
    bytes: Vec<u8>,
    id: u32,
}

impl Image {
    fn frames(&self) -> u16 {
        self.bytes.len().div_ceil(FW_DATA_LEN) as u16
    }

    fn data(&self, index: u16) -> Message {
        let mut data = [0xEE; FW_DATA_LEN];
        let at = index as usize * FW_DATA_LEN;
        let end = (at + FW_DATA_LEN).min(self.bytes.len());
        data[..end - at].copy_from_slice(&self.bytes[at..end]);
        Message::FwData { index, data }
    }

    fn begin(&self) -> Message {
        Message::FwBegin {
            image_id: self.id,
            len: self.bytes.len() as u32,
            force: false,
        }
    }
}

fn signed(
    board: Board,
    protocol: (u8, u8),
    v: FirmwareVersion,
    len: usize,
    key: &SigningKey,
) -> Image {
    let payload: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
    let bytes = pack(board, protocol, v, &payload, key).unwrap();
    let id = ihex_image::Header::parse(&bytes).unwrap().image_id();
    Image { bytes, id }
}

/// A good image for the test node, `len` payload bytes.
fn image(v: FirmwareVersion, len: usize) -> Image {
    signed(
        Board::NUCLEO_F303RE,
        PROTOCOL_VERSION,
        v,
        len,
        &SigningKey::test_key(),
    )
}

/// The adapter's side: the DFU slot and the bootloader state, carrying out the node's flash
/// outputs and reporting back; frames are collected.
struct Flash {
    dfu: Vec<u8>,
    marked: bool,
    confirmed: bool,
    reset: bool,
    erases: u32,
    writes: u32,
    fail_erase: bool,
    fail_write: bool,
    fail_hash: bool,
    fail_mark: bool,
    /// Flip this DFU byte right after it is written (a bad flash cell).
    corrupt_at: Option<usize>,
}

impl Flash {
    fn new() -> Self {
        Flash {
            // Not erased: whatever a previous update left.
            dfu: vec![0x5A; F303RE.dfu.len as usize],
            marked: false,
            confirmed: false,
            reset: false,
            erases: 0,
            writes: 0,
            fail_erase: false,
            fail_write: false,
            fail_hash: false,
            fail_mark: false,
            corrupt_at: None,
        }
    }

    /// Drains the node like an adapter, carrying out every output; returns the messages sent.
    fn run(&mut self, n: &mut Node, now: u64) -> Vec<Message> {
        let t = Millis(now);
        let mut sent = Vec::new();
        while let Some(o) = n.poll_output() {
            match o {
                Output::Frame(p) => {
                    p.validate().expect("valid frames only");
                    sent.push(p.msg);
                }
                Output::EraseDfu { len } => {
                    self.erases += 1;
                    assert_eq!(len % CHUNK_LEN as u32, 0);
                    let end = (len.div_ceil(F303RE.page) * F303RE.page) as usize;
                    self.dfu[..end].fill(0xFF);
                    let r = if self.fail_erase {
                        Err(FlashError)
                    } else {
                        Ok(())
                    };
                    n.handle_fw_erased(r, t);
                }
                Output::WriteDfu { offset, data } => {
                    self.writes += 1;
                    let at = offset as usize;
                    assert!(
                        self.dfu[at..at + CHUNK_LEN].iter().all(|&b| b == 0xFF),
                        "write at {at} to flash that is not erased"
                    );
                    self.dfu[at..at + CHUNK_LEN].copy_from_slice(&data);
                    if let Some(c) = self.corrupt_at.filter(|c| (at..at + CHUNK_LEN).contains(c)) {
                        self.dfu[c] ^= 0x01;
                    }
                    if self.fail_write {
                        n.handle_fw_write_failed(t);
                    }
                }
                Output::HashDfu { offset, len } => {
                    let r = if self.fail_hash {
                        Err(FlashError)
                    } else {
                        let (a, b) = (offset as usize, (offset + len) as usize);
                        Ok(Hasher::digest(&self.dfu[a..b]))
                    };
                    n.handle_fw_hashed(r, t);
                }
                Output::MarkUpdated => {
                    let r = if self.fail_mark {
                        Err(FlashError)
                    } else {
                        Ok(())
                    };
                    self.marked = r.is_ok();
                    n.handle_fw_marked(r, t);
                }
                Output::MarkBooted => {
                    self.confirmed = true;
                    n.handle_fw_confirmed(Ok(()), t);
                }
                Output::Reset => self.reset = true,
                other => panic!("unexpected output {other:?}"),
            }
        }
        sent
    }
}

fn status(msgs: &[Message]) -> Vec<FwStatus> {
    msgs.iter()
        .filter_map(|m| match m {
            Message::FwStatus(s) => Some(*s),
            _ => None,
        })
        .collect()
}

fn st(phase: FwPhase, reason: FwRefusal) -> FwStatus {
    FwStatus::phase(phase, reason)
}

fn node_with(trial: bool, reverted: bool) -> Node {
    let mut c: Config = config(BootRole::Static, 6, Some(id()));
    c.firmware.trial = trial;
    c.update.reverted = reverted;
    let mut n = Node::new(c, Millis(0));
    while n.poll_output().is_some() {}
    n
}

fn node() -> Node {
    node_with(false, false)
}

/// Sends a broadcast command (as the gateway does for a whole island).
fn all(n: &mut Node, msg: Message, now: u64) {
    common::feed(n, Packet::command(NodeId::BROADCAST, msg), now);
}

/// Begin, header frames and the erase: the node is ready for the payload.
fn start(n: &mut Node, f: &mut Flash, img: &Image) -> Vec<FwStatus> {
    all(n, img.begin(), 10);
    let mut seen = status(&f.run(n, 10));
    for i in 0..32 {
        all(n, img.data(i), 11);
        seen.extend(status(&f.run(n, 11)));
    }
    seen
}

fn send(
    n: &mut Node,
    f: &mut Flash,
    img: &Image,
    range: impl Iterator<Item = u16>,
) -> Vec<FwStatus> {
    let mut seen = Vec::new();
    for i in range {
        all(n, img.data(i), 20);
        seen.extend(status(&f.run(n, 20)));
    }
    seen
}

fn query(n: &mut Node, f: &mut Flash, img: &Image) -> FwStatus {
    all(n, Message::FwQuery { image_id: img.id }, 30);
    let s = status(&f.run(n, 30));
    assert_eq!(s.len(), 1, "one status per query: {s:?}");
    s[0]
}

fn commit(n: &mut Node, f: &mut Flash, img: &Image, now: u64) -> Vec<FwStatus> {
    all(
        n,
        Message::FwEnd {
            image_id: img.id,
            action: FwAction::Commit,
        },
        now,
    );
    status(&f.run(n, now))
}

#[test]
fn a_whole_update_from_begin_to_reset() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 3000);
    let frames = u32::from(img.frames());
    all(&mut n, img.begin(), 10);
    assert_eq!(
        status(&f.run(&mut n, 10)),
        vec![FwStatus {
            phase: FwPhase::Header,
            reason: FwRefusal::None,
            first_missing: 0,
            run: 32,
            missing: 32
        }]
    );
    // Nothing is erased before the header is checked.
    let seen = send(&mut n, &mut f, &img, 0..31);
    assert!(seen.is_empty() && f.erases == 0);
    let seen = send(&mut n, &mut f, &img, 31..32);
    assert_eq!(f.erases, 1);
    assert_eq!(f.writes, 8, "the header's chunks go to flash from RAM");
    // Ready: receiving, everything after the header missing.
    assert_eq!(
        seen,
        vec![FwStatus {
            phase: FwPhase::Receiving,
            reason: FwRefusal::None,
            first_missing: 32,
            run: (frames - 32) as u16,
            missing: (frames - 32) as u16
        }]
    );
    let seen = send(&mut n, &mut f, &img, 32..img.frames());
    assert_eq!(seen, vec![st(FwPhase::Complete, FwRefusal::None)]);
    assert_eq!(&f.dfu[..img.bytes.len()], &img.bytes[..]);
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Complete);

    let seen = commit(&mut n, &mut f, &img, 40);
    assert_eq!(
        seen,
        vec![
            st(FwPhase::Verifying, FwRefusal::None),
            st(FwPhase::Rebooting, FwRefusal::None)
        ]
    );
    assert!(f.marked && !f.reset);
    n.tick(Millis(40 + RESET_DELAY_MS - 1));
    f.run(&mut n, 40 + RESET_DELAY_MS - 1);
    assert!(!f.reset, "the reset waits for the status to leave");
    n.tick(Millis(40 + RESET_DELAY_MS));
    f.run(&mut n, 40 + RESET_DELAY_MS);
    assert!(f.reset);
    assert_eq!(n.poll_at(), None, "nothing more after the reset");
}

#[test]
fn lost_frames_are_reported_and_resent_only_to_fill_the_gaps() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 6000);
    let frames = img.frames();
    start(&mut n, &mut f, &img);
    // Frames 100..=109 and 500 are lost on the way.
    let lost: Vec<u16> = (100..110).chain([500]).collect();
    send(
        &mut n,
        &mut f,
        &img,
        (32..frames).filter(|i| !lost.contains(i)),
    );
    // Missing is reported by whole chunks of 4 frames: 100..112 (3 chunks), then 500..504.
    assert_eq!(
        query(&mut n, &mut f, &img),
        FwStatus {
            phase: FwPhase::Receiving,
            reason: FwRefusal::None,
            first_missing: 100,
            run: 12,
            missing: 16
        }
    );
    send(&mut n, &mut f, &img, 100..112);
    assert_eq!(
        query(&mut n, &mut f, &img),
        FwStatus {
            phase: FwPhase::Receiving,
            reason: FwRefusal::None,
            first_missing: 500,
            run: 4,
            missing: 4
        }
    );
    let seen = send(&mut n, &mut f, &img, 500..504);
    assert_eq!(seen, vec![st(FwPhase::Complete, FwRefusal::None)]);
    assert_eq!(&f.dfu[..img.bytes.len()], &img.bytes[..]);
}

#[test]
fn a_chunk_pushed_out_of_the_assembly_is_asked_for_again() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 2000);
    start(&mut n, &mut f, &img);
    send(
        &mut n,
        &mut f,
        &img,
        (32..img.frames()).filter(|i| !(40..60).contains(i)),
    );
    // One frame each of chunks 10..=14: five chunks started, four slots — chunk 10's frame 40
    // goes. Its other frames then complete nothing.
    send(&mut n, &mut f, &img, [40, 44, 48, 52, 56].into_iter());
    send(&mut n, &mut f, &img, [41, 42, 43].into_iter());
    let q = query(&mut n, &mut f, &img);
    assert_eq!((q.first_missing, q.run, q.missing), (40, 20, 20), "{q:?}");
    let seen = send(&mut n, &mut f, &img, 40..60);
    assert_eq!(seen, vec![st(FwPhase::Complete, FwRefusal::None)]);
    assert_eq!(&f.dfu[..img.bytes.len()], &img.bytes[..]);
}

#[test]
fn frames_before_the_node_is_ready_are_not_taken() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 2000);
    all(&mut n, img.begin(), 10);
    f.run(&mut n, 10);
    // Payload frames during the header phase (nothing is erased yet) are dropped.
    send(&mut n, &mut f, &img, 32..img.frames());
    assert_eq!(f.writes, 0);
    send(&mut n, &mut f, &img, 0..32);
    let q = query(&mut n, &mut f, &img);
    assert_eq!((q.phase, q.first_missing), (FwPhase::Receiving, 32));
}

#[test]
fn a_restarted_gateway_resumes_and_a_new_image_starts_over() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 3000);
    start(&mut n, &mut f, &img);
    send(&mut n, &mut f, &img, 32..300);
    let before = query(&mut n, &mut f, &img);
    let erases = f.erases;
    // The same begin again: nothing lost, nothing erased again.
    all(&mut n, img.begin(), 50);
    assert_eq!(status(&f.run(&mut n, 50)), vec![before]);
    assert_eq!(f.erases, erases);
    send(&mut n, &mut f, &img, 300..img.frames());
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Complete);
    // Another image: a new transfer from the header on.
    let other = image(FirmwareVersion::new(1, 6, 0), 1000);
    all(&mut n, other.begin(), 60);
    assert_eq!(status(&f.run(&mut n, 60))[0].phase, FwPhase::Header);
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Idle);
}

#[test]
fn a_node_reset_mid_transfer_has_to_start_over() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 3000);
    start(&mut n, &mut f, &img);
    send(&mut n, &mut f, &img, 32..200);
    let mut n = node(); // power cycle: the session lived in RAM
    assert_eq!(
        query(&mut n, &mut f, &img),
        st(FwPhase::Idle, FwRefusal::None)
    );
    let seen = start(&mut n, &mut f, &img);
    assert_eq!(seen.last().unwrap().first_missing, 32);
    assert_eq!(
        f.erases, 2,
        "erased again: the slot's content is not trusted"
    );
}

#[test]
fn abort_and_commit_too_early() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 3000);
    start(&mut n, &mut f, &img);
    send(&mut n, &mut f, &img, 32..100);
    // A commit before everything arrived changes nothing: the status says what is missing.
    let seen = commit(&mut n, &mut f, &img, 40);
    assert_eq!(seen[0].phase, FwPhase::Receiving);
    assert!(!f.marked);
    all(
        &mut n,
        Message::FwEnd {
            image_id: img.id,
            action: FwAction::Abort,
        },
        41,
    );
    assert_eq!(
        status(&f.run(&mut n, 41)),
        vec![st(FwPhase::Idle, FwRefusal::None)]
    );
    send(&mut n, &mut f, &img, 100..img.frames());
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Idle);
}

/// Sends `img` completely and returns every status seen, without committing.
fn transfer(n: &mut Node, f: &mut Flash, img: &Image) -> Vec<FwStatus> {
    let mut seen = start(n, f, img);
    if f.erases > 0 {
        seen.extend(send(n, f, img, 32..img.frames()));
    }
    seen
}

/// The header is refused with `reason`: nothing erased, the running image untouched.
#[track_caller]
fn refused_at_header(img: &Image, reason: FwRefusal) {
    let mut n = node();
    let mut f = Flash::new();
    let seen = transfer(&mut n, &mut f, img);
    assert_eq!(seen.last(), Some(&st(FwPhase::Refused, reason)), "{seen:?}");
    assert_eq!((f.erases, f.writes, f.marked), (0, 0, false));
    assert_eq!(query(&mut n, &mut f, img), st(FwPhase::Refused, reason));
    // A commit cannot override a refusal.
    commit(&mut n, &mut f, img, 99);
    assert!(!f.marked && !f.reset);
}

#[test]
fn refusals_bad_signature_and_unknown_key() {
    let mut img = image(NEWER, 1000);
    img.bytes[140] ^= 0x20; // in the signature
    refused_at_header(&img, FwRefusal::BadSignature);
    let other = SigningKey::from_seed([9; 32]);
    let img = signed(Board::NUCLEO_F303RE, PROTOCOL_VERSION, NEWER, 1000, &other);
    refused_at_header(&img, FwRefusal::UnknownKey);
}

#[test]
fn refusals_wrong_board_and_incompatible_protocol() {
    let key = SigningKey::test_key();
    let img = signed(Board::SIM, PROTOCOL_VERSION, NEWER, 1000, &key);
    refused_at_header(&img, FwRefusal::WrongBoard);
    let img = signed(
        Board::NUCLEO_F303RE,
        (PROTOCOL_VERSION.0 + 1, 0),
        NEWER,
        1000,
        &key,
    );
    refused_at_header(&img, FwRefusal::IncompatibleProtocol);
}

#[test]
fn refusals_downgrade_unless_forced() {
    let img = image(FirmwareVersion::new(1, 4, 1), 1000);
    refused_at_header(&img, FwRefusal::Downgrade);
    let mut n = node();
    let mut f = Flash::new();
    all(
        &mut n,
        Message::FwBegin {
            image_id: img.id,
            len: img.bytes.len() as u32,
            force: true,
        },
        10,
    );
    f.run(&mut n, 10);
    send(&mut n, &mut f, &img, 0..img.frames());
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Complete);
    // The same version is a re-install, no downgrade.
    let mut n = node();
    let same = image(RUNNING, 1000);
    transfer(&mut n, &mut f, &same);
    assert_eq!(query(&mut n, &mut f, &same).phase, FwPhase::Complete);
}

#[test]
fn refusals_truncated_too_large_and_not_the_announced_image() {
    let img = image(NEWER, 1000);
    // The gateway announces fewer bytes than the header says (a cut file).
    let mut cut = Image {
        bytes: img.bytes.clone(),
        id: img.id,
    };
    cut.bytes.truncate(900);
    refused_at_header(&cut, FwRefusal::Truncated);
    // Refused at the begin already: no header frames needed.
    let mut n = node();
    let mut f = Flash::new();
    for (len, reason) in [
        (F303RE.active.len + 1, FwRefusal::TooLarge),
        (HEADER_BLOCK as u32, FwRefusal::Truncated),
    ] {
        all(
            &mut n,
            Message::FwBegin {
                image_id: 7,
                len,
                force: false,
            },
            10,
        );
        assert_eq!(
            status(&f.run(&mut n, 10)),
            vec![st(FwPhase::Refused, reason)]
        );
    }
    // A header of another image than the begin named.
    let wrong_id = Image {
        bytes: img.bytes.clone(),
        id: img.id ^ 1,
    };
    refused_at_header(&wrong_id, FwRefusal::BadImage);
}

#[test]
fn refusal_corrupted_payload_is_found_on_commit() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 3000);
    f.corrupt_at = Some(HEADER_BLOCK + 1234);
    transfer(&mut n, &mut f, &img);
    let seen = commit(&mut n, &mut f, &img, 40);
    assert_eq!(
        seen,
        vec![
            st(FwPhase::Verifying, FwRefusal::None),
            st(FwPhase::Refused, FwRefusal::Corrupted)
        ]
    );
    assert!(!f.marked && !f.reset);
    // So is a corrupted header block (the signature was checked in RAM, the flash copy differs).
    let mut n = node();
    let mut f = Flash::new();
    f.corrupt_at = Some(300);
    transfer(&mut n, &mut f, &img);
    let seen = commit(&mut n, &mut f, &img, 40);
    assert_eq!(
        seen.last(),
        Some(&st(FwPhase::Refused, FwRefusal::Corrupted))
    );
    assert!(!f.marked);
    // The gateway can simply start over.
    let mut f2 = Flash::new();
    all(&mut n, img.begin(), 50);
    f2.run(&mut n, 50);
    send(&mut n, &mut f2, &img, 0..img.frames());
    let seen = commit(&mut n, &mut f2, &img, 60);
    assert_eq!(seen.last(), Some(&st(FwPhase::Rebooting, FwRefusal::None)));
}

#[test]
fn flash_failures_end_the_transfer() {
    let img = image(NEWER, 2000);
    type Arm = fn(&mut Flash);
    let cases: [(&str, Arm); 4] = [
        ("erase", |f| f.fail_erase = true),
        ("write", |f| f.fail_write = true),
        ("hash", |f| f.fail_hash = true),
        ("mark", |f| f.fail_mark = true),
    ];
    for (what, arm) in cases {
        let mut n = node();
        let mut f = Flash::new();
        arm(&mut f);
        let mut seen = transfer(&mut n, &mut f, &img);
        seen.extend(commit(&mut n, &mut f, &img, 40));
        assert_eq!(
            seen.last(),
            Some(&st(FwPhase::Refused, FwRefusal::FlashError)),
            "{what}: {seen:?}"
        );
        assert!(!f.marked && !f.reset, "{what}");
    }
}

#[test]
fn busy_while_verifying_another_image() {
    let mut n = node();
    let img = image(NEWER, 1000);
    let mut f = Flash::new();
    transfer(&mut n, &mut f, &img);
    // Commit, but do not carry out the hash yet: the node is verifying.
    all(
        &mut n,
        Message::FwEnd {
            image_id: img.id,
            action: FwAction::Commit,
        },
        40,
    );
    let mut pending = Vec::new();
    while let Some(o) = n.poll_output() {
        pending.push(o);
    }
    assert!(pending.iter().any(|o| matches!(o, Output::HashDfu { .. })));
    let other = image(FirmwareVersion::new(2, 0, 0), 500);
    all(&mut n, other.begin(), 41);
    assert_eq!(
        status(&f.run(&mut n, 41)),
        vec![st(FwPhase::Refused, FwRefusal::Busy)]
    );
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Verifying);
}

#[test]
fn an_unconfigured_node_takes_no_part() {
    let mut n = Node::new(config(BootRole::Static, 6, None), Millis(0));
    let mut f = Flash::new();
    let img = image(NEWER, 1000);
    all(&mut n, img.begin(), 1);
    send(&mut n, &mut f, &img, 0..img.frames());
    assert!(f.run(&mut n, 2).is_empty());
    assert_eq!(f.erases, 0);
}

#[test]
fn frames_for_another_node_are_ignored() {
    let mut n = node();
    let mut f = Flash::new();
    let img = image(NEWER, 1000);
    let other = NodeId::new_sc(0x222).unwrap();
    common::feed(&mut n, Packet::command(other, img.begin()), 1);
    assert!(f.run(&mut n, 1).is_empty());
    // To the node itself works as well as broadcast.
    cmd(&mut n, img.begin(), 2);
    assert_eq!(status(&f.run(&mut n, 2))[0].phase, FwPhase::Header);
}

// ---- trial boot ----

fn on_trial(n: &mut Node, f: &mut Flash) -> bool {
    cmd(
        n,
        Message::StateQuery {
            seq: 1,
            parts: StateParts(StateParts::IDENTITY),
        },
        500,
    );
    f.run(n, 500)
        .into_iter()
        .find_map(|m| match m {
            Message::StateReport(StateReport::Firmware { trial, .. }) => Some(trial),
            _ => None,
        })
        .expect("a Firmware part")
}

#[test]
fn a_trial_image_confirms_itself_once_on_the_bus_and_self_tested() {
    let mut n = node_with(true, false);
    let mut f = Flash::new();
    let img = image(NEWER, 1000);
    // Self-tested, but the gateway not heard yet: not confirmed.
    n.handle_self_test(true, Millis(1));
    f.run(&mut n, 1);
    assert!(!f.confirmed && n.config().firmware.trial);
    // Any gateway command is the gateway heard. This one, an update, is refused while on trial:
    // the DFU slot holds the way back.
    all(&mut n, img.begin(), 2);
    assert_eq!(
        status(&f.run(&mut n, 2)),
        vec![st(FwPhase::Refused, FwRefusal::Unconfirmed)]
    );
    assert!(f.confirmed);
    assert!(!on_trial(&mut n, &mut f), "no longer on trial");
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Idle);
    // The deadline is gone: no reset later.
    n.tick(Millis(TRIAL_CONFIRM_MS + 1));
    f.run(&mut n, TRIAL_CONFIRM_MS + 1);
    assert!(!f.reset);
    // And updates are taken again.
    let seen = transfer(&mut n, &mut f, &img);
    assert_eq!(seen.last().unwrap().phase, FwPhase::Complete);
}

#[test]
fn a_trial_image_reports_trial_until_it_confirms() {
    let mut n = node_with(true, false);
    let mut f = Flash::new();
    let img = image(NEWER, 1000);
    // Heard the gateway (this query), no self-test yet.
    assert_eq!(query(&mut n, &mut f, &img).phase, FwPhase::Trial);
    assert!(on_trial(&mut n, &mut f));
    n.handle_self_test(true, Millis(600));
    f.run(&mut n, 600);
    assert!(f.confirmed && !on_trial(&mut n, &mut f));
}

#[test]
fn a_trial_image_that_never_hears_the_gateway_is_reset_and_reverted() {
    let mut n = node_with(true, false);
    let mut f = Flash::new();
    n.handle_self_test(true, Millis(1));
    assert_eq!(n.poll_at(), Some(Millis(TRIAL_CONFIRM_MS)));
    n.tick(Millis(TRIAL_CONFIRM_MS - 1));
    f.run(&mut n, TRIAL_CONFIRM_MS - 1);
    assert!(!f.reset);
    n.tick(Millis(TRIAL_CONFIRM_MS));
    f.run(&mut n, TRIAL_CONFIRM_MS);
    assert!(f.reset && !f.confirmed);
}

#[test]
fn a_trial_image_failing_its_self_test_resets_at_once() {
    let mut n = node_with(true, false);
    let mut f = Flash::new();
    cmd(&mut n, Message::HealthCheck { seq: 1 }, 2);
    n.handle_self_test(false, Millis(3));
    n.tick(Millis(3 + RESET_DELAY_MS));
    f.run(&mut n, 3 + RESET_DELAY_MS);
    assert!(f.reset && !f.confirmed);
}

#[test]
fn a_confirmed_image_needs_no_confirmation_and_after_a_revert_says_so() {
    let mut n = node();
    let mut f = Flash::new();
    n.handle_self_test(true, Millis(1));
    cmd(&mut n, Message::HealthCheck { seq: 1 }, 2);
    f.run(&mut n, 2);
    assert!(!f.confirmed && n.poll_at().is_none());
    let mut n = node_with(false, true);
    let img = image(NEWER, 1000);
    assert_eq!(
        query(&mut n, &mut f, &img),
        st(FwPhase::Reverted, FwRefusal::None)
    );
    // And it takes the next update.
    let seen = transfer(&mut n, &mut f, &img);
    assert_eq!(seen.last().unwrap().phase, FwPhase::Complete);
}

#[test]
fn update_config_is_the_common_one() {
    // The harness's nodes accept what `image` makes.
    assert_eq!(UPDATE.layout.app_start(), 0x0800_7200);
    assert!(image(NEWER, 10).bytes.len() > HEADER_BLOCK);
}

/// An image with release notes (header format 2) installs; notes changed in flash are found on
/// the commit like any corruption.
#[test]
fn an_image_with_release_notes_installs_and_its_notes_are_checked() {
    let payload: Vec<u8> = (0..3000).map(|i| (i * 37 % 251) as u8).collect();
    let bytes = ihex_image::pack_with_notes(
        Board::NUCLEO_F303RE,
        PROTOCOL_VERSION,
        NEWER,
        &payload,
        "release notes of the new image",
        &SigningKey::test_key(),
    )
    .unwrap();
    assert_eq!(bytes[4], 2, "format 2");
    let id = ihex_image::Header::parse(&bytes).unwrap().image_id();
    let img = Image { bytes, id };
    let mut n = node();
    let mut f = Flash::new();
    transfer(&mut n, &mut f, &img);
    let seen = commit(&mut n, &mut f, &img, 40);
    assert_eq!(seen.last(), Some(&st(FwPhase::Rebooting, FwRefusal::None)));
    assert!(f.marked);
    // A flipped byte in the notes as written: corrupted, nothing marked.
    let mut n = node();
    let mut f = Flash::new();
    f.corrupt_at = Some(ihex_image::SIGNED_LEN + 3);
    transfer(&mut n, &mut f, &img);
    let seen = commit(&mut n, &mut f, &img, 40);
    assert_eq!(
        seen.last(),
        Some(&st(FwPhase::Refused, FwRefusal::Corrupted))
    );
    assert!(!f.marked);
}
