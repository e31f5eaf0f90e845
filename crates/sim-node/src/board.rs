//! A simulated sub-controller's flash and bootloader: the F303RE's flash in memory, laid out by
//! `ihex_image::board::F303RE`, with embassy-boot's own swap and revert code running over it — so a
//! simulated update goes through the real A/B logic, not a model of it.
//!
//! [`SimFlash`] is a NOR flash as embassy-boot sees the STM32F303's (`embedded_storage` traits, 2 KiB
//! erase pages, 8-byte program units, programming only erased bytes) that can lose power at any
//! operation: [`SimFlash::cut_after`] arms a cut, the operation it hits is left half done (an
//! interrupted erase leaves a mix of erased and old bytes, an interrupted 8-byte program the
//! half-words written so far — the F303 programs 16 bits at a time), and every operation after it
//! fails until [`SimFlash::power_on`]. Like the F303, a half-word can only be programmed when
//! erased, or to `0x0000` (RM0316, "Flash memory programming": the one exception to `PGERR`).
//!
//! [`Board`] is what the node's adapter and the bootloader do with it: run the bootloader at reset
//! ([`Board::boot`]), read the running image ([`Board::active_image`]), and the update's flash
//! work (erase, write and hash the DFU slot, mark updated, mark booted).
//!
//! A simulated image is a signed `ihex-image` for [`ihex_image::Board::SIM`] whose payload is a
//! [`SimFirmware`]: what the simulated firmware does (for now: whether it passes its self-test,
//! and so confirms itself after an update), padded to a realistic size ([`sim_image`]).
//!
//! [`boot`] and [`carry_out`] are the update half of a simulated SC's adapter, the counterpart of
//! the firmware's `src/update.rs`: the bootloader at reset, the node's identity from the image it
//! starts, and the node's flash outputs carried out on the board.

use core::cell::RefCell;

use embassy_boot::{BlockingFirmwareState, BootLoader, BootLoaderConfig, State};
use embassy_embedded_hal::flash::partition::BlockingPartition;
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use ihex_image::board::{Layout, Region, F303RE};
use ihex_image::{Digest, FirmwareVersion, Hasher, Header, SigningKey, HEADER_BLOCK, HEADER_LEN};
use ihex_sc_core::{FirmwareIdentity, FlashError, Millis, Node, Output, UpdateConfig};

const PAGE: usize = F303RE.page as usize;
const UNIT: usize = F303RE.write_unit as usize;
const ERASED: u8 = 0xFF;

/// Why a flash operation failed.
#[derive(Clone, Copy, PartialEq, Eq, Debug, thiserror::Error)]
pub enum SimFlashError {
    /// The power was cut (this operation was left half done, or it came after the cut).
    #[error("power cut")]
    PowerCut,
    /// Outside the flash.
    #[error("out of bounds")]
    OutOfBounds,
    /// Not aligned to the erase page or the program unit.
    #[error("not aligned")]
    NotAligned,
    /// Programming bytes that are not erased (the F303 refuses it: PGERR).
    #[error("programming a location that is not erased")]
    NotErased,
}

impl NorFlashError for SimFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            SimFlashError::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            SimFlashError::NotAligned => NorFlashErrorKind::NotAligned,
            SimFlashError::PowerCut | SimFlashError::NotErased => NorFlashErrorKind::Other,
        }
    }
}

/// The flash of one simulated board (see the module docs). Pages are kept only once written
/// (an erased page is `None`), so an island of boards costs what their images take.
pub struct SimFlash {
    pages: Vec<Option<Box<[u8; PAGE]>>>,
    /// Page erases and 8-byte program units done since power-on.
    ops: u64,
    /// The operation (counted like `ops`) at which the power fails.
    cut_at: Option<u64>,
    /// Powered off by a cut: every operation fails.
    dead: bool,
    /// Drives the pattern a cut leaves behind (xorshift64).
    rng: u64,
}

impl SimFlash {
    /// An erased flash of `layout`'s size.
    pub fn new(layout: &Layout) -> Self {
        SimFlash {
            pages: (0..layout.flash.len as usize / PAGE)
                .map(|_| None)
                .collect(),
            ops: 0,
            cut_at: None,
            dead: false,
            rng: 0x9E37_79B9_7F4A_7C15,
        }
    }

    /// Operations (page erases and 8-byte program units) done since power-on.
    pub fn ops(&self) -> u64 {
        self.ops
    }

    /// The power fails at the operation `n` operations from now (0 = the next one); `seed` picks
    /// how much of it gets done.
    pub fn cut_after(&mut self, n: u64, seed: u64) {
        self.cut_at = Some(self.ops + n);
        self.rng = seed | 1;
    }

    /// True once a cut happened (until [`SimFlash::power_on`]).
    pub fn is_dead(&self) -> bool {
        self.dead
    }

    /// Power back: operations work again, no cut armed, the counter restarts.
    pub fn power_on(&mut self) {
        self.dead = false;
        self.cut_at = None;
        self.ops = 0;
    }

    /// A copy of the bytes of `r` (absolute addresses).
    pub fn region(&self, r: Region) -> Vec<u8> {
        let start = (r.start - F303RE.flash.start) as usize;
        let mut out = Vec::with_capacity(r.len as usize);
        for a in (start..start + r.len as usize).step_by(PAGE) {
            match &self.pages[a / PAGE] {
                Some(p) => out.extend_from_slice(&p[..]),
                None => out.resize(out.len() + PAGE, ERASED),
            }
        }
        out
    }

    fn byte(&self, at: usize) -> u8 {
        self.pages[at / PAGE]
            .as_ref()
            .map_or(ERASED, |p| p[at % PAGE])
    }

    fn set(&mut self, at: usize, v: u8) {
        let page = self.pages[at / PAGE].get_or_insert_with(|| Box::new([ERASED; PAGE]));
        page[at % PAGE] = v;
    }

    fn random(&mut self) -> u64 {
        let mut x = self.rng;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.rng = x;
        x
    }

    /// Counts one operation; `Err` if the power is off, `Ok(true)` if this one is cut short.
    fn step(&mut self) -> Result<bool, SimFlashError> {
        if self.dead {
            return Err(SimFlashError::PowerCut);
        }
        let cut = self.cut_at == Some(self.ops);
        self.ops += 1;
        if cut {
            self.dead = true;
        }
        Ok(cut)
    }

    fn check(&self, offset: u32, len: usize, align: usize) -> Result<usize, SimFlashError> {
        let start = offset as usize;
        if !start.is_multiple_of(align) || !len.is_multiple_of(align) {
            return Err(SimFlashError::NotAligned);
        }
        if start + len > self.capacity() {
            return Err(SimFlashError::OutOfBounds);
        }
        Ok(start)
    }
}

impl ErrorType for SimFlash {
    type Error = SimFlashError;
}

impl ReadNorFlash for SimFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        if self.dead {
            return Err(SimFlashError::PowerCut);
        }
        let start = self.check(offset, bytes.len(), 1)?;
        let mut done = 0;
        while done < bytes.len() {
            let at = start + done;
            let n = (PAGE - at % PAGE).min(bytes.len() - done);
            let out = &mut bytes[done..done + n];
            match &self.pages[at / PAGE] {
                Some(p) => out.copy_from_slice(&p[at % PAGE..at % PAGE + n]),
                None => out.fill(ERASED),
            }
            done += n;
        }
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.pages.len() * PAGE
    }
}

impl NorFlash for SimFlash {
    const WRITE_SIZE: usize = UNIT;
    const ERASE_SIZE: usize = PAGE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let start = self.check(from, to.saturating_sub(from) as usize, PAGE)?;
        for page in (start..to as usize).step_by(PAGE) {
            if self.step()? {
                // An interrupted erase: some bytes erased, the others as they were.
                for i in page..page + PAGE {
                    if self.random() & 1 == 1 {
                        self.set(i, ERASED);
                    }
                }
                return Err(SimFlashError::PowerCut);
            }
            self.pages[page / PAGE] = None;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let start = self.check(offset, bytes.len(), UNIT)?;
        for (i, unit) in bytes.chunks(UNIT).enumerate() {
            let at = start + i * UNIT;
            // The half-words of this unit that get programmed: all, or up to the cut.
            let halves = if self.step()? {
                (self.random() % (UNIT as u64 / 2)) as usize
            } else {
                UNIT / 2
            };
            for h in 0..halves {
                let a = at + 2 * h;
                let old = [self.byte(a), self.byte(a + 1)];
                let new = [unit[2 * h], unit[2 * h + 1]];
                // Like the F303: only an erased half-word can be programmed — except to 0x0000,
                // which embassy-boot relies on to redo a progress mark a cut left half written.
                if old != [ERASED; 2] && new != [0; 2] {
                    return Err(SimFlashError::NotErased);
                }
                self.set(a, new[0]);
                self.set(a + 1, new[1]);
            }
            if self.dead {
                return Err(SimFlashError::PowerCut);
            }
        }
        Ok(())
    }
}

type Part<'a> = BlockingPartition<'a, NoopRawMutex, &'a mut SimFlash>;

/// What the bootloader did at the last [`Board::boot`].
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum BootState {
    /// Nothing to do: a confirmed image (or no update ever).
    Confirmed,
    /// A new image was swapped in and runs on trial.
    Trial,
    /// The image on trial did not confirm itself: the old one was swapped back.
    Reverted,
}

/// A flash operation of the update failed.
#[derive(Clone, Copy, PartialEq, Eq, Debug, thiserror::Error)]
#[error("flash: {0:?}")]
pub struct BoardError(pub NorFlashErrorKind);

impl<E: NorFlashError> From<E> for BoardError {
    fn from(e: E) -> Self {
        BoardError(e.kind())
    }
}

fn updater_error(e: embassy_boot::FirmwareUpdaterError) -> BoardError {
    match e {
        embassy_boot::FirmwareUpdaterError::Flash(k) => BoardError(k),
        _ => BoardError(NorFlashErrorKind::Other),
    }
}

/// A simulated board: its flash, partitioned by the F303RE layout.
pub struct Board {
    /// The flash (tests arm power cuts on it).
    pub flash: SimFlash,
}

impl Board {
    /// A board whose active slot holds `image` (as a first flash with a probe would leave it).
    pub fn with_image(image: &[u8]) -> Self {
        let mut flash = SimFlash::new(&F303RE);
        let at = (F303RE.active.start - F303RE.flash.start) as usize;
        for (i, &b) in image.iter().enumerate() {
            flash.set(at + i, b);
        }
        Board { flash }
    }

    /// Runs the partitions through `f` (embassy-boot wants each as its own `NorFlash`).
    fn with_parts<R>(&mut self, f: impl FnOnce(Part<'_>, Part<'_>, Part<'_>) -> R) -> R {
        let shared = Mutex::<NoopRawMutex, _>::new(RefCell::new(&mut self.flash));
        let part = |r: Region| Part::new(&shared, r.start - F303RE.flash.start, r.len);
        f(part(F303RE.active), part(F303RE.dfu), part(F303RE.state))
    }

    /// The bootloader at reset: embassy-boot's `prepare_boot` (swap, revert or nothing). A flash
    /// error (a power cut) leaves the swap to be resumed at the next boot, as on the chip.
    pub fn boot(&mut self) -> Result<BootState, BoardError> {
        self.with_parts(|active, dfu, state| {
            let mut bl = BootLoader::new(BootLoaderConfig { active, dfu, state });
            let mut buf = [0u8; PAGE];
            let boot_error = |e| match e {
                embassy_boot::BootError::Flash(k) => BoardError(k),
                _ => BoardError(NorFlashErrorKind::Other),
            };
            bl.prepare_boot(&mut buf).map_err(boot_error)?;
            // `prepare_boot` returns the state it found; what it left is what the image sees.
            match bl.read_state(&mut buf).map_err(boot_error)? {
                State::Swap => Ok(BootState::Trial),
                State::Revert => Ok(BootState::Reverted),
                _ => Ok(BootState::Confirmed),
            }
        })
    }

    /// The image in the active slot: its header and payload, `None` if there is no readable header.
    pub fn active_image(&self) -> Option<(Header, Vec<u8>)> {
        let mut slot = self.flash.region(F303RE.active);
        let header = Header::parse(&slot[..HEADER_LEN]).ok()?;
        let end = HEADER_BLOCK + header.payload_len as usize;
        if end > slot.len() {
            return None;
        }
        slot.truncate(end);
        slot.drain(..HEADER_BLOCK);
        Some((header, slot))
    }

    /// Erases the DFU pages `len` image bytes occupy.
    pub fn erase_dfu(&mut self, len: u32) -> Result<(), BoardError> {
        let end = len.div_ceil(F303RE.page) * F303RE.page;
        self.with_parts(|_, mut dfu, _| dfu.erase(0, end.min(F303RE.dfu.len)))?;
        Ok(())
    }

    /// Programs `data` at `offset` of the DFU slot.
    pub fn write_dfu(&mut self, offset: u32, data: &[u8]) -> Result<(), BoardError> {
        self.with_parts(|_, mut dfu, _| dfu.write(offset, data))?;
        Ok(())
    }

    /// SHA-512 of `len` DFU bytes from `offset`, as the node re-reads them.
    pub fn hash_dfu(&mut self, offset: u32, len: u32) -> Result<Digest, BoardError> {
        self.with_parts(|_, mut dfu, _| {
            let mut h = Hasher::new();
            let mut buf = [0u8; 256];
            let mut done = 0;
            while done < len {
                let n = (len - done).min(buf.len() as u32) as usize;
                dfu.read(offset + done, &mut buf[..n])?;
                h.update(&buf[..n]);
                done += n as u32;
            }
            Ok(h.finish())
        })
    }

    fn with_state<R>(
        &mut self,
        f: impl FnOnce(
            &mut BlockingFirmwareState<'_, Part<'_>>,
        ) -> Result<R, embassy_boot::FirmwareUpdaterError>,
    ) -> Result<R, BoardError> {
        self.with_parts(|_, _, state| {
            let mut aligned = [0u8; UNIT];
            let mut s = BlockingFirmwareState::new(state, &mut aligned);
            f(&mut s).map_err(updater_error)
        })
    }

    /// Asks the bootloader to swap the DFU image in at the next boot.
    pub fn mark_updated(&mut self) -> Result<(), BoardError> {
        self.with_state(|s| s.mark_updated())
    }

    /// Confirms the running image.
    pub fn mark_booted(&mut self) -> Result<(), BoardError> {
        self.with_state(|s| s.mark_booted())
    }
}

pub use ihex_image::sim::{sim_image, SimFirmware, SIM_PAYLOAD_LEN};

/// The image a simulated board is first flashed with: a confirming firmware of `version`,
/// [`SIM_PAYLOAD_LEN`] bytes, signed with the test key.
pub fn factory_image(version: FirmwareVersion) -> Result<Vec<u8>, ihex_image::ToolError> {
    sim_image(
        version,
        SimFirmware { confirms: true },
        SIM_PAYLOAD_LEN,
        &SigningKey::test_key(),
    )
}

/// The image hash (first 7 bytes) a freshly flashed simulated board of `version` reports: that
/// of [`factory_image`]'s payload.
pub fn factory_image_hash(version: FirmwareVersion) -> [u8; 7] {
    Hasher::digest(&SimFirmware { confirms: true }.payload(version, SIM_PAYLOAD_LEN)).prefix::<7>()
}

/// What a simulated board starts at reset: the node's firmware identity and update configuration,
/// and how the simulated firmware behaves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Booted {
    /// For `Config::firmware`.
    pub firmware: FirmwareIdentity,
    /// For `Config::update`.
    pub update: UpdateConfig,
    /// The simulated firmware; `None` when the payload is not one (a real firmware flashed into a
    /// simulated board): it then fails its self-test.
    pub sim: Option<SimFirmware>,
}

impl Booted {
    /// The self-test result the simulated firmware reports after boot.
    pub fn self_test(&self) -> bool {
        self.sim.is_some_and(|s| s.confirms)
    }
}

/// Why a simulated board does not start.
#[derive(Clone, Copy, PartialEq, Eq, Debug, thiserror::Error)]
pub enum BootFailure {
    /// The bootloader stopped on a flash error (a power cut: the next boot resumes).
    #[error("bootloader: {0}")]
    Flash(#[from] BoardError),
    /// The active slot holds no image header: nothing to start.
    #[error("no image in the active slot")]
    NoImage,
}

/// Reset: runs the bootloader, then reads the identity of the image it starts. Images are trusted
/// (by `key`) only when they arrive over the bus; at boot the header is read as the firmware does.
pub fn boot(board: &mut Board, key: ihex_image::PublicKey) -> Result<Booted, BootFailure> {
    let state = board.boot()?;
    let (header, payload) = board.active_image().ok_or(BootFailure::NoImage)?;
    Ok(Booted {
        firmware: FirmwareIdentity {
            version: header.version,
            image_hash: header.payload_hash.prefix::<7>(),
            trial: state == BootState::Trial,
        },
        update: UpdateConfig {
            board: ihex_image::Board::SIM,
            key,
            layout: &F303RE,
            reverted: state == BootState::Reverted,
        },
        sim: SimFirmware::parse(&payload),
    })
}

/// What [`carry_out`] did with an output.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Carried {
    /// A firmware-update output, carried out and reported to the node.
    Done,
    /// [`Output::Reset`]: the adapter must reset the node.
    Reset,
    /// Not an update output: the adapter's other half handles it.
    Other(Output),
}

/// Carries out one of the node's firmware-update outputs on the board and reports the result
/// back, as the firmware's node task does on the chip.
pub fn carry_out(board: &mut Board, node: &mut Node, out: Output, now: Millis) -> Carried {
    let flash = |r: Result<(), BoardError>| r.map_err(|_| FlashError);
    match out {
        Output::EraseDfu { len } => node.handle_fw_erased(flash(board.erase_dfu(len)), now),
        Output::WriteDfu { offset, data } => {
            if board.write_dfu(offset, &data).is_err() {
                node.handle_fw_write_failed(now);
            }
        }
        Output::HashDfu { offset, len } => {
            let r = board.hash_dfu(offset, len).map_err(|_| FlashError);
            node.handle_fw_hashed(r, now)
        }
        Output::MarkUpdated => node.handle_fw_marked(flash(board.mark_updated()), now),
        Output::MarkBooted => node.handle_fw_confirmed(flash(board.mark_booted()), now),
        Output::Reset => return Carried::Reset,
        other => return Carried::Other(other),
    }
    Carried::Done
}
