//! Firmware update, node side: a signed image received into the DFU slot, checked, handed to the
//! bootloader; and a new image on trial confirmed — or left to be reverted. The contract is in the
//! crate docs (*Firmware update*).

use ihex_image::board::Layout;
use ihex_image::{
    check_len, check_signed, header_block_digest, Board, Digest, Hasher, Header, ImageError,
    Policy, PublicKey, HEADER_BLOCK, NOTES_LEN, SIGNED_LEN,
};
use ihex_proto::{FwAction, FwPhase, FwRefusal, FwStatus, Message, FW_DATA_LEN, PROTOCOL_VERSION};

use super::Node;
use crate::{Millis, Output};

/// Bytes the core hands to the adapter per [`Output::WriteDfu`]: four data frames, three of the
/// F303's 8-byte program units (the least common multiple of 6 and 8).
pub const CHUNK_LEN: usize = 24;
/// The largest image a node takes, whatever its slot: the F303RE's active slot (it sizes the
/// received-chunks bitmap, 683 bytes).
pub const MAX_IMAGE_LEN: u32 = 128 * 1024;
/// After the `Rebooting` status, the node waits this long (for the frame to leave) before it
/// asks for the reset.
pub const RESET_DELAY_MS: u64 = 100;
/// A new image on trial that has not confirmed itself this long after boot asks for a reset, and
/// the bootloader reverts it. The gateway checks health every second, so a healthy image has
/// heard it long before.
pub const TRIAL_CONFIRM_MS: u64 = 60_000;

const CHUNK_FRAMES: u32 = (CHUNK_LEN / FW_DATA_LEN) as u32;
/// The signed header is exactly the first frames and chunks.
const HEADER_FRAMES: u32 = (SIGNED_LEN / FW_DATA_LEN) as u32;
const HEADER_CHUNKS: u32 = (SIGNED_LEN / CHUNK_LEN) as u32;
const MAX_CHUNKS: usize = (MAX_IMAGE_LEN as usize).div_ceil(CHUNK_LEN);
/// Chunks being assembled at once; a partial chunk pushed out forgets its frames (they are asked
/// for again), which only costs resends after losses.
const CACHE: usize = 4;
const _: () = assert!(
    SIGNED_LEN.is_multiple_of(CHUNK_LEN)
        && CHUNK_LEN.is_multiple_of(FW_DATA_LEN)
        && CHUNK_LEN.is_multiple_of(8)
        && HEADER_FRAMES == 32
);

/// What a node needs to take updates: its board, the key images must be signed with, its flash
/// layout, and whether the bootloader reverted an update at this boot.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct UpdateConfig {
    /// The board images must be built for.
    pub board: Board,
    /// The key images must be signed with.
    pub key: PublicKey,
    /// The flash layout (slot size, load address).
    pub layout: &'static Layout,
    /// The bootloader put the previous image back at this boot (a new one never confirmed itself).
    pub reverted: bool,
}

/// A flash operation the adapter carried out failed.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FlashError;

/// The update state of a node.
#[derive(Debug)]
pub(super) struct Update {
    session: Option<Session>,
    trial: Option<Trial>,
    /// When to ask for the reset (after the `Rebooting` status, or to revert a trial).
    reset_at: Option<Millis>,
    /// A reset was asked for: nothing more is done until it happens.
    resetting: bool,
}

impl Update {
    pub(super) fn new(trial: bool, now: Millis) -> Self {
        Update {
            session: None,
            trial: trial.then(|| Trial {
                heard_gateway: false,
                self_test: None,
                requested: false,
                deadline: now.add_ms(TRIAL_CONFIRM_MS),
            }),
            reset_at: None,
            resetting: false,
        }
    }

    pub(super) fn deadline(&self) -> Option<Millis> {
        if self.resetting {
            return None;
        }
        // Once the confirmation is asked for, the deadline no longer applies.
        let trial = self
            .trial
            .as_ref()
            .filter(|t| !t.requested)
            .map(|t| t.deadline);
        [self.reset_at, trial].into_iter().flatten().min()
    }
}

#[derive(Debug)]
struct Trial {
    heard_gateway: bool,
    self_test: Option<bool>,
    /// `MarkBooted` was asked for.
    requested: bool,
    deadline: Millis,
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Phase {
    Header,
    Erasing,
    Receiving,
    Complete,
    Verifying(Step),
    Rebooting,
    Refused(FwRefusal),
}

/// What the verification waits for.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Step {
    /// The hash of the header block as written (format 2: of its signed part).
    HeaderBlock,
    /// Format 2: the hash of the release notes area as written.
    Notes,
    /// The hash of the payload as written.
    Payload,
    /// `MarkUpdated` carried out.
    Mark,
}

#[derive(Debug)]
struct Session {
    image_id: u32,
    len: u32,
    force: bool,
    frames: u32,
    chunks: u32,
    phase: Phase,
    /// The signed header, filled from frames `0..HEADER_FRAMES` (then written from here).
    signed: [u8; SIGNED_LEN],
    /// Bit `i`: header frame `i` is in `signed`.
    header_have: u32,
    /// The checked header.
    header: Option<Header>,
    /// Chunks written.
    done: Bitmap,
    done_chunks: u32,
    cache: [Partial; CACHE],
    /// Age stamp for the cache's least recently started chunk.
    stamp: u32,
}

#[derive(Clone, Copy, Debug)]
struct Partial {
    /// `None` = a free slot.
    chunk: Option<u32>,
    have: u8,
    stamp: u32,
    data: [u8; CHUNK_LEN],
}

const FREE: Partial = Partial {
    chunk: None,
    have: 0,
    stamp: 0,
    data: [0xFF; CHUNK_LEN],
};

#[derive(Debug)]
struct Bitmap([u32; MAX_CHUNKS.div_ceil(32)]);

impl Bitmap {
    fn get(&self, i: u32) -> bool {
        self.0[(i / 32) as usize] & (1 << (i % 32)) != 0
    }

    fn set(&mut self, i: u32) {
        self.0[(i / 32) as usize] |= 1 << (i % 32);
    }

    /// The first clear bit below `n`.
    fn first_clear(&self, n: u32) -> Option<u32> {
        (0..n.div_ceil(32)).find_map(|w| {
            let free = !self.0[w as usize];
            (free != 0)
                .then(|| w * 32 + free.trailing_zeros())
                .filter(|&i| i < n)
        })
    }
}

impl Session {
    fn new(image_id: u32, len: u32, force: bool) -> Self {
        let frames = len.div_ceil(FW_DATA_LEN as u32);
        Session {
            image_id,
            len,
            force,
            frames,
            chunks: frames.div_ceil(CHUNK_FRAMES),
            phase: Phase::Header,
            signed: [0; SIGNED_LEN],
            header_have: 0,
            header: None,
            done: Bitmap([0; MAX_CHUNKS.div_ceil(32)]),
            done_chunks: 0,
            cache: [FREE; CACHE],
            stamp: 0,
        }
    }

    /// Frames in chunk `c` (the last one may have fewer).
    fn frames_in(&self, c: u32) -> u32 {
        (self.frames - c * CHUNK_FRAMES).min(CHUNK_FRAMES)
    }

    fn status(&self) -> FwStatus {
        let (phase, reason) = match self.phase {
            Phase::Header => (FwPhase::Header, FwRefusal::None),
            Phase::Erasing => (FwPhase::Erasing, FwRefusal::None),
            Phase::Receiving => (FwPhase::Receiving, FwRefusal::None),
            Phase::Complete => (FwPhase::Complete, FwRefusal::None),
            Phase::Verifying(_) => (FwPhase::Verifying, FwRefusal::None),
            Phase::Rebooting => (FwPhase::Rebooting, FwRefusal::None),
            Phase::Refused(r) => (FwPhase::Refused, r),
        };
        let mut st = FwStatus::phase(phase, reason);
        match self.phase {
            Phase::Header => {
                let missing = !self.header_have;
                if missing != 0 {
                    let first = missing.trailing_zeros();
                    st.first_missing = first as u16;
                    st.run = (!(self.header_have >> first))
                        .trailing_ones()
                        .min(32 - first) as u16;
                    st.missing = missing.count_ones() as u16;
                }
            }
            Phase::Receiving => {
                if let Some(c) = self.done.first_clear(self.chunks) {
                    let run = (c..self.chunks)
                        .take_while(|&i| !self.done.get(i))
                        .map(|i| self.frames_in(i))
                        .sum::<u32>();
                    let done_frames: u32 = (0..self.chunks)
                        .filter(|&i| self.done.get(i))
                        .map(|i| self.frames_in(i))
                        .sum();
                    st.first_missing = sat16(c * CHUNK_FRAMES);
                    st.run = sat16(run);
                    st.missing = sat16(self.frames - done_frames);
                }
            }
            _ => {}
        }
        st
    }
}

fn sat16(v: u32) -> u16 {
    u16::try_from(v).unwrap_or(u16::MAX)
}

/// The wire reason for an image the node refuses.
fn refusal(e: ImageError) -> FwRefusal {
    match e {
        ImageError::Truncated { .. } => FwRefusal::Truncated,
        ImageError::UnknownKey => FwRefusal::UnknownKey,
        ImageError::BadSignature => FwRefusal::BadSignature,
        ImageError::WrongBoard { .. } => FwRefusal::WrongBoard,
        ImageError::IncompatibleProtocol { .. } => FwRefusal::IncompatibleProtocol,
        ImageError::TooLarge { .. } => FwRefusal::TooLarge,
        ImageError::Downgrade { .. } => FwRefusal::Downgrade,
        ImageError::Corrupted => FwRefusal::Corrupted,
        ImageError::TrailingData { .. }
        | ImageError::BadMagic
        | ImageError::UnsupportedFormat(_)
        | ImageError::Reserved { .. }
        | ImageError::UnknownFlags(_)
        | ImageError::EmptyPayload
        | ImageError::WrongAddress { .. } => FwRefusal::BadImage,
    }
}

impl Node {
    /// The largest image this node takes.
    fn capacity(&self) -> u32 {
        self.config.update.layout.max_image_len().min(MAX_IMAGE_LEN)
    }

    fn policy(&self, force: bool) -> Policy {
        let u = &self.config.update;
        let mut p = Policy::new(
            u.board,
            u.layout,
            PROTOCOL_VERSION.0,
            self.config.firmware.version,
        );
        p.max_image_len = self.capacity();
        p.allow_downgrade = force;
        p
    }

    fn send_status(&mut self, st: FwStatus) {
        self.report(Message::FwStatus(st));
    }

    /// The status about `image_id`: the session's if it is that image, else what the node is.
    fn status_of(&self, image_id: u32) -> FwStatus {
        match &self.update.session {
            Some(s) if s.image_id == image_id => s.status(),
            _ => FwStatus::phase(self.idle_phase(), FwRefusal::None),
        }
    }

    fn idle_phase(&self) -> FwPhase {
        if self.update.trial.is_some() {
            FwPhase::Trial
        } else if self.config.update.reverted {
            FwPhase::Reverted
        } else {
            FwPhase::Idle
        }
    }

    /// Ends the session with a refusal, and says so.
    fn refuse(&mut self, reason: FwRefusal) {
        if let Some(s) = self.update.session.as_mut() {
            s.phase = Phase::Refused(reason);
            let st = s.status();
            self.send_status(st);
        }
    }

    pub(super) fn on_fw_begin(&mut self, image_id: u32, len: u32, force: bool) {
        if self.update.resetting {
            return;
        }
        if let Some(s) = self.update.session.as_mut() {
            match s.phase {
                Phase::Verifying(_) | Phase::Rebooting if s.image_id == image_id => {
                    let st = s.status();
                    self.send_status(st);
                    return;
                }
                Phase::Verifying(_) | Phase::Rebooting => {
                    self.send_status(FwStatus::phase(FwPhase::Refused, FwRefusal::Busy));
                    return;
                }
                Phase::Refused(_) => {}
                // The same transfer again (a restarted gateway): keep what is there.
                _ if s.image_id == image_id && s.len == len => {
                    s.force = force;
                    let st = s.status();
                    self.send_status(st);
                    return;
                }
                _ => {}
            }
        }
        if self.update.trial.is_some() {
            // The DFU slot holds the image to go back to: it must not be overwritten.
            self.update.session = None;
            self.send_status(FwStatus::phase(FwPhase::Refused, FwRefusal::Unconfirmed));
            return;
        }
        let mut s = Session::new(image_id, len, force);
        let early = if len > self.capacity() {
            Some(FwRefusal::TooLarge)
        } else if len <= HEADER_BLOCK as u32 {
            Some(FwRefusal::Truncated)
        } else {
            None
        };
        if let Some(r) = early {
            s.phase = Phase::Refused(r);
        }
        let st = s.status();
        self.update.session = Some(s);
        self.send_status(st);
    }

    pub(super) fn on_fw_data(&mut self, index: u16, data: [u8; FW_DATA_LEN]) {
        let index = u32::from(index);
        let Some(s) = self.update.session.as_mut() else {
            return;
        };
        if index >= s.frames {
            return;
        }
        match s.phase {
            Phase::Header if index < HEADER_FRAMES => {
                let at = index as usize * FW_DATA_LEN;
                s.signed[at..at + FW_DATA_LEN].copy_from_slice(&data);
                s.header_have |= 1 << index;
                if s.header_have == u32::MAX {
                    self.check_header();
                }
            }
            Phase::Receiving if index >= HEADER_FRAMES => self.take_frame(index, data),
            _ => {}
        }
    }

    /// The whole signed header is in: check it, then erase (or refuse).
    fn check_header(&mut self) {
        let Some(s) = self.update.session.as_ref() else {
            return;
        };
        let policy = self.policy(s.force);
        let checked = check_signed(&s.signed, &self.config.update.key, &policy)
            .and_then(|h| check_len(&h, s.len).map(|()| h));
        let (image_id, chunks) = (s.image_id, s.chunks);
        match checked {
            Ok(h) if h.image_id() != image_id => self.refuse(FwRefusal::BadImage),
            Ok(h) => {
                if let Some(s) = self.update.session.as_mut() {
                    s.header = Some(h);
                    s.phase = Phase::Erasing;
                }
                self.queue.push(Output::EraseDfu {
                    len: chunks * CHUNK_LEN as u32,
                });
            }
            Err(e) => self.refuse(refusal(e)),
        }
    }

    /// A payload frame while receiving: into its chunk; a full chunk goes to flash.
    fn take_frame(&mut self, index: u32, data: [u8; FW_DATA_LEN]) {
        // An adapter that does not drain (against the contract) must not lose a write the core
        // counts as done: the frame is not taken, and stays missing.
        if !self.queue.has_room() {
            return;
        }
        let Some(s) = self.update.session.as_mut() else {
            return;
        };
        let chunk = index / CHUNK_FRAMES;
        if s.done.get(chunk) {
            return;
        }
        let slot = match s.cache.iter().position(|p| p.chunk == Some(chunk)) {
            Some(i) => i,
            None => {
                // A free slot, else the chunk started longest ago (its frames are asked again).
                let i = s
                    .cache
                    .iter()
                    .enumerate()
                    .min_by_key(|(_, p)| (p.chunk.is_some(), p.stamp))
                    .map_or(0, |(i, _)| i);
                s.stamp = s.stamp.wrapping_add(1);
                s.cache[i] = Partial {
                    chunk: Some(chunk),
                    stamp: s.stamp,
                    ..FREE
                };
                i
            }
        };
        let within = (index % CHUNK_FRAMES) as usize;
        let need = s.frames_in(chunk);
        let p = &mut s.cache[slot];
        p.data[within * FW_DATA_LEN..(within + 1) * FW_DATA_LEN].copy_from_slice(&data);
        p.have |= 1 << within;
        if p.have.count_ones() < need {
            return;
        }
        let bytes = p.data;
        *p = FREE;
        s.done.set(chunk);
        s.done_chunks += 1;
        self.queue.push(Output::WriteDfu {
            offset: chunk * CHUNK_LEN as u32,
            data: bytes,
        });
        if s.done_chunks == s.chunks {
            s.phase = Phase::Complete;
            let st = s.status();
            self.send_status(st);
        }
    }

    pub(super) fn on_fw_query(&mut self, image_id: u32) {
        if self.update.resetting {
            return;
        }
        let st = self.status_of(image_id);
        self.send_status(st);
    }

    pub(super) fn on_fw_end(&mut self, image_id: u32, action: FwAction) {
        if self.update.resetting {
            return;
        }
        let Some(s) = self
            .update
            .session
            .as_mut()
            .filter(|s| s.image_id == image_id)
        else {
            let st = self.status_of(image_id);
            self.send_status(st);
            return;
        };
        match (action, s.phase) {
            (FwAction::Commit, Phase::Complete) => {
                s.phase = Phase::Verifying(Step::HeaderBlock);
                // A format-2 header block holds release notes the node never had in RAM: the
                // signed part and the notes are checked apart.
                let notes = s.header.is_some_and(|h| h.notes_hash.is_some());
                let st = s.status();
                self.send_status(st);
                self.queue.push(Output::HashDfu {
                    offset: 0,
                    len: if notes { SIGNED_LEN } else { HEADER_BLOCK } as u32,
                });
            }
            (FwAction::Abort, phase) if phase != Phase::Rebooting => {
                self.update.session = None;
                let st = self.status_of(image_id);
                self.send_status(st);
            }
            _ => {
                let st = s.status();
                self.send_status(st);
            }
        }
    }

    /// The adapter erased the DFU pages of [`Output::EraseDfu`].
    pub fn handle_fw_erased(&mut self, result: Result<(), FlashError>, now: Millis) {
        self.advance(now);
        let Some(s) = self
            .update
            .session
            .as_mut()
            .filter(|s| s.phase == Phase::Erasing)
        else {
            return;
        };
        if result.is_err() {
            self.refuse(FwRefusal::FlashError);
            return;
        }
        // The header chunks come from RAM; the rest from the data frames that follow.
        let signed = s.signed;
        for c in 0..HEADER_CHUNKS {
            s.done.set(c);
        }
        s.done_chunks = HEADER_CHUNKS;
        s.phase = Phase::Receiving;
        let st = s.status();
        for (c, bytes) in signed.chunks_exact(CHUNK_LEN).enumerate() {
            let mut data = [0; CHUNK_LEN];
            data.copy_from_slice(bytes);
            self.queue.push(Output::WriteDfu {
                offset: (c * CHUNK_LEN) as u32,
                data,
            });
        }
        self.send_status(st);
    }

    /// Writing a chunk ([`Output::WriteDfu`]) failed: the transfer is refused.
    pub fn handle_fw_write_failed(&mut self, now: Millis) {
        self.advance(now);
        if self
            .update
            .session
            .as_ref()
            .is_some_and(|s| matches!(s.phase, Phase::Receiving | Phase::Complete))
        {
            self.refuse(FwRefusal::FlashError);
        }
    }

    /// The digest of an [`Output::HashDfu`] (SHA-512 of the bytes as read back).
    pub fn handle_fw_hashed(&mut self, result: Result<Digest, FlashError>, now: Millis) {
        self.advance(now);
        let Some(s) = self.update.session.as_mut() else {
            return;
        };
        let (Phase::Verifying(step), Some(header)) = (s.phase, s.header) else {
            return;
        };
        let Ok(digest) = result else {
            self.refuse(FwRefusal::FlashError);
            return;
        };
        match step {
            Step::HeaderBlock
                if header.notes_hash.is_some() && digest == Hasher::digest(&s.signed) =>
            {
                s.phase = Phase::Verifying(Step::Notes);
                self.queue.push(Output::HashDfu {
                    offset: SIGNED_LEN as u32,
                    len: NOTES_LEN as u32,
                });
            }
            Step::Notes if header.notes_hash == Some(digest.prefix::<32>()) => {
                s.phase = Phase::Verifying(Step::Payload);
                self.queue.push(Output::HashDfu {
                    offset: HEADER_BLOCK as u32,
                    len: header.payload_len,
                });
            }
            Step::HeaderBlock
                if header.notes_hash.is_none() && digest == header_block_digest(&s.signed) =>
            {
                s.phase = Phase::Verifying(Step::Payload);
                self.queue.push(Output::HashDfu {
                    offset: HEADER_BLOCK as u32,
                    len: header.payload_len,
                });
            }
            Step::Payload if header.check_payload(&digest).is_ok() => {
                s.phase = Phase::Verifying(Step::Mark);
                self.queue.push(Output::MarkUpdated);
            }
            Step::Mark => {}
            _ => self.refuse(FwRefusal::Corrupted),
        }
    }

    /// [`Output::MarkUpdated`] was carried out (or failed).
    pub fn handle_fw_marked(&mut self, result: Result<(), FlashError>, now: Millis) {
        self.advance(now);
        let Some(s) = self
            .update
            .session
            .as_mut()
            .filter(|s| s.phase == Phase::Verifying(Step::Mark))
        else {
            return;
        };
        if result.is_err() {
            self.refuse(FwRefusal::FlashError);
            return;
        }
        s.phase = Phase::Rebooting;
        let st = s.status();
        self.send_status(st);
        self.update.reset_at = Some(now.add_ms(RESET_DELAY_MS));
    }

    /// The adapter's self-test after boot. On a new image on trial, a pass is one of the two
    /// conditions to confirm it (the other: the gateway was heard); a failure asks for the reset
    /// that reverts it.
    pub fn handle_self_test(&mut self, passed: bool, now: Millis) {
        self.advance(now);
        let Some(t) = self.update.trial.as_mut() else {
            return;
        };
        if t.self_test.is_some() {
            return;
        }
        t.self_test = Some(passed);
        if passed {
            self.try_confirm();
        } else if self.update.reset_at.is_none() {
            self.update.reset_at = Some(now.add_ms(RESET_DELAY_MS));
        }
    }

    /// [`Output::MarkBooted`] was carried out: the image is no longer on trial. A failure leaves it
    /// on trial, so the trial deadline reverts it.
    pub fn handle_fw_confirmed(&mut self, result: Result<(), FlashError>, now: Millis) {
        self.advance(now);
        if result.is_ok() && self.update.trial.as_ref().is_some_and(|t| t.requested) {
            self.update.trial = None;
            self.config.firmware.trial = false;
        }
    }

    /// A valid command from the gateway arrived: the node is on the bus.
    pub(super) fn heard_gateway(&mut self) {
        if let Some(t) = self.update.trial.as_mut() {
            if !t.heard_gateway {
                t.heard_gateway = true;
                self.try_confirm();
            }
        }
    }

    fn try_confirm(&mut self) {
        if let Some(t) = self.update.trial.as_mut() {
            if t.heard_gateway && t.self_test == Some(true) && !t.requested {
                t.requested = true;
                self.queue.push(Output::MarkBooted);
            }
        }
    }

    /// The update's timers: the reset after `Rebooting` or a failed self-test, the trial deadline.
    pub(super) fn advance_update(&mut self, now: Millis) {
        if self.update.resetting {
            return;
        }
        let trial_over = self
            .update
            .trial
            .as_ref()
            .is_some_and(|t| !t.requested && now >= t.deadline);
        if trial_over || self.update.reset_at.is_some_and(|t| now >= t) {
            self.update.resetting = true;
            self.update.reset_at = None;
            self.queue.push(Output::Reset);
        }
    }
}
