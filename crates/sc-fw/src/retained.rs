//! The [`Retained`] block in the kept top of SRAM (`ihex_image::board::Layout::kept_ram`, outside
//! `.data`/`.bss`/stack in both linker scripts): written just before a reset the application asks
//! for, read by the bootloader (which drives the relay on again before it swaps) and taken back by
//! the application after that reset only. SRAM keeps it through a system reset, not a power cut,
//! and [`Retained::decode`] refuses whatever else the RAM holds.

use ihex_image::board::{F303RE, KEPT_RAM_LEN};
use ihex_proto::ResetReason;
use ihex_sc_core::{Retained, RETAINED_WORDS};

const _: () = assert!(RETAINED_WORDS * 4 <= KEPT_RAM_LEN as usize);

fn word(i: usize) -> *mut u32 {
    debug_assert!(i < RETAINED_WORDS);
    (F303RE.kept_ram().start as usize + 4 * i) as *mut u32
}

/// Leaves `retained` for the bootloader and the next start; call right before `SYSRESETREQ`.
pub fn write(retained: &Retained) {
    for (i, w) in retained.encode().into_iter().enumerate() {
        // SAFETY: the kept RAM is word-aligned SRAM that no Rust object and no stack occupy
        // (neither linker script places anything there); volatile so the store is not elided
        // before the reset.
        unsafe { word(i).write_volatile(w) };
    }
}

/// What the previous run left, if this start follows a software reset; the block is cleared
/// either way, so a later power cut, watchdog or pin reset never restores it.
pub fn take(reset: ResetReason) -> Option<Retained> {
    let mut block = [0u32; RETAINED_WORDS];
    for (i, w) in block.iter_mut().enumerate() {
        // SAFETY: as in `write`; any bit pattern is a valid `u32`.
        *w = unsafe { word(i).read_volatile() };
        // SAFETY: as in `write`.
        unsafe { word(i).write_volatile(0) };
    }
    if matches!(reset, ResetReason::Software) {
        Retained::decode(&block)
    } else {
        None
    }
}
