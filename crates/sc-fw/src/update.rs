//! The flash side of a firmware update: the partitions of `ihex_image::board::F303RE` on the chip's
//! one flash bank (shared with the configuration page), the DFU slot a new image is written to,
//! and embassy-boot's state (mark updated, mark booted, what the bootloader did at this boot).
//!
//! The F303 has a single flash bank and runs from it: an erase stalls the CPU for 20–40 ms per
//! 2 KiB page (interrupts included). So the DFU slot is erased one page at a time, and between
//! pages (and between the pages of a re-read for the hash) the node task yields to the other tasks
//! and shows its heartbeat, so the watchdog keeps being fed. Programming is 8 bytes at a time
//! (a few hundred µs per 24-byte chunk the core hands over), which needs no yielding.

use core::cell::RefCell;

use defmt::warn;
use embassy_boot_stm32::{AlignedBuffer, BlockingFirmwareState, State};
use embassy_embedded_hal::flash::partition::BlockingPartition;
use embassy_stm32::flash::{Blocking, Flash, WRITE_SIZE};
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embedded_storage::nor_flash::{NorFlash, ReadNorFlash};
use ihex_image::board::{Region, F303RE};
use ihex_image::{Digest, Hasher, Header, HEADER_LEN};
use static_cell::StaticCell;

use crate::tasks::watchdog::{beat, Beat};

/// The whole flash, shared by the partitions.
pub type SharedFlash = Mutex<NoopRawMutex, RefCell<Flash<'static, Blocking>>>;
/// A partition of the flash (offsets from its start).
pub type Part = BlockingPartition<'static, NoopRawMutex, Flash<'static, Blocking>>;

static FLASH: StaticCell<SharedFlash> = StaticCell::new();
static STATE_BUF: StaticCell<AlignedBuffer<WRITE_SIZE>> = StaticCell::new();

/// Bytes read per step when hashing the DFU slot.
const READ_CHUNK: usize = 256;

/// The partitions the application uses (the bootloader's own is never touched).
pub struct Partitions {
    /// The node configuration record's page.
    pub config: Part,
    /// The running image (read only: its header is the node's identity).
    pub active: Part,
    /// The incoming image.
    pub dfu: Part,
    /// embassy-boot's state.
    pub state: Part,
}

/// Splits the flash into the layout's partitions. Call once.
pub fn split(flash: Flash<'static, Blocking>) -> Partitions {
    let shared: &'static SharedFlash = FLASH.init(Mutex::new(RefCell::new(flash)));
    let part = |r: Region| Part::new(shared, r.start - F303RE.flash.start, r.len);
    Partitions {
        config: part(F303RE.config),
        active: part(F303RE.active),
        dfu: part(F303RE.dfu),
        state: part(F303RE.state),
    }
}

/// The header in front of the running application; `None` when the slot holds none (an
/// application flashed directly with probe-rs: its first page, header included, was erased).
pub fn running_header(active: &mut Part) -> Option<Header> {
    let mut b = [0u8; HEADER_LEN];
    active.read(0, &mut b).ok()?;
    Header::parse(&b).ok()
}

/// What the bootloader did before starting this image.
#[derive(Clone, Copy, PartialEq, Eq, Debug, defmt::Format)]
pub enum BootState {
    /// A confirmed image (or no update ever).
    Confirmed,
    /// A freshly swapped-in image on trial: it must confirm itself (`mark_booted`) or the next
    /// reset reverts it.
    Trial,
    /// The previous update was reverted: this is the old image again.
    Reverted,
}

/// A flash operation failed (logged where it happened).
#[derive(Clone, Copy, PartialEq, Eq, Debug, defmt::Format)]
pub struct FlashFailed;

/// The DFU slot and the bootloader state.
pub struct Updater {
    dfu: Part,
    state: BlockingFirmwareState<'static, Part>,
}

impl Updater {
    /// The updater over `dfu` and `state`. Call once (it owns the state's aligned buffer).
    pub fn new(dfu: Part, state: Part) -> Self {
        let buf = STATE_BUF.init(AlignedBuffer([0; WRITE_SIZE]));
        Updater {
            dfu,
            state: BlockingFirmwareState::new(state, &mut buf.0),
        }
    }

    /// What the bootloader did at this boot; a state that cannot be read counts as confirmed
    /// (logged): the core then never asks to confirm, and updates stay possible.
    pub fn boot_state(&mut self) -> BootState {
        match self.state.get_state() {
            Ok(State::Swap) => BootState::Trial,
            Ok(State::Revert) => BootState::Reverted,
            Ok(_) => BootState::Confirmed,
            Err(e) => {
                warn!("update: bootloader state unreadable: {}", e);
                BootState::Confirmed
            }
        }
    }

    /// Erases the DFU pages that `len` image bytes occupy, a page at a time, yielding between pages.
    pub async fn erase_dfu(&mut self, len: u32) -> Result<(), FlashFailed> {
        let page = F303RE.page;
        let end = len.div_ceil(page).saturating_mul(page).min(F303RE.dfu.len);
        let mut at = 0;
        while at < end {
            if let Err(e) = self.dfu.erase(at, at + page) {
                warn!("update: erasing DFU at {=u32:#x} failed: {}", at, e);
                return Err(FlashFailed);
            }
            at += page;
            beat(Beat::Node as usize);
            embassy_futures::yield_now().await;
        }
        Ok(())
    }

    /// Programs `data` (a multiple of 8 bytes) at `offset` of the erased DFU slot.
    pub fn write_dfu(&mut self, offset: u32, data: &[u8]) -> Result<(), FlashFailed> {
        self.dfu.write(offset, data).map_err(|e| {
            warn!("update: writing DFU at {=u32:#x} failed: {}", offset, e);
            FlashFailed
        })
    }

    /// SHA-512 of `len` bytes of the DFU slot from `offset`, yielding every page.
    pub async fn hash_dfu(&mut self, offset: u32, len: u32) -> Result<Digest, FlashFailed> {
        let mut h = Hasher::new();
        let mut buf = [0u8; READ_CHUNK];
        let mut done = 0u32;
        while done < len {
            let n = (len - done).min(READ_CHUNK as u32) as usize;
            if let Err(e) = self.dfu.read(offset + done, &mut buf[..n]) {
                warn!(
                    "update: reading DFU at {=u32:#x} failed: {}",
                    offset + done,
                    e
                );
                return Err(FlashFailed);
            }
            h.update(&buf[..n]);
            done += n as u32;
            if done.is_multiple_of(F303RE.page) {
                beat(Beat::Node as usize);
                embassy_futures::yield_now().await;
            }
        }
        Ok(h.finish())
    }

    /// Asks the bootloader to swap the DFU image in at the next reset.
    pub fn mark_updated(&mut self) -> Result<(), FlashFailed> {
        self.state.mark_updated().map_err(|e| {
            warn!("update: marking the update failed: {}", e);
            FlashFailed
        })
    }

    /// Confirms the running image: the bootloader will not revert it.
    pub fn mark_booted(&mut self) -> Result<(), FlashFailed> {
        self.state.mark_booted().map_err(|e| {
            warn!("update: confirming the image failed: {}", e);
            FlashFailed
        })
    }
}
