//! iHEX sub-controller bootloader: embassy-boot over the F303RE layout of `ihex_image::board`.
//!
//! At every reset it asks embassy-boot to prepare the boot:
//!
//! * state `Boot` (nothing to do) → start the application;
//! * an image was marked for update → swap it into ACTIVE page by page, the old one into DFU, with
//!   a progress index in the state partition (a power cut resumes the swap where it stopped), then
//!   start the new image *on trial*;
//! * the image started on trial did not confirm itself (`mark_booted`) before this reset → swap
//!   the old image back (revert) and start it.
//!
//! The application starts at the active slot + `HEADER_BLOCK` (the signed image header sits in
//! front of it). Before anything else it reads the block the application may have left in the kept
//! top of SRAM (`ihex_sc_core::Retained`): after a software reset, if the block is valid and says
//! the relay was on, it drives the dock relay (PB5, active high; the firmware's build checks the pin
//! map says so) on again, so a docked mobile element keeps its power through the swap. It leaves the
//! block for the application. Apart from that pin and its port's clock nothing is touched: no clocks (the chip runs on its reset HSI clock), no
//! interrupts, no time driver, so the application starts from a reset-like state. A flash error
//! panics, and a panic resets the chip, which retries the same step.
//!
//! Images are verified by the application before it marks them for update; the bootloader only
//! refuses to jump into an active slot that holds no plausible vector table (a board flashed with
//! the bootloader alone), and then waits, logging why.
#![no_std]
#![no_main]

use core::cell::RefCell;

use cortex_m_rt::{entry, exception};
use defmt::{error, info};
use defmt_rtt as _;
use embassy_boot_stm32::{BootLoader, BootLoaderConfig, State};
use embassy_embedded_hal::flash::partition::BlockingPartition;
use embassy_stm32::flash::Flash;
use embassy_stm32::pac::gpio::vals::Moder;
use embassy_stm32::pac::{GPIOB, RCC};
use embassy_sync::blocking_mutex::raw::NoopRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use ihex_image::board::{Region, F303RE, KEPT_RAM_LEN};
use ihex_sc_core::{Retained, RETAINED_WORDS};

/// Copy buffer of the swap: one page.
const PAGE: usize = 2048;
const _: () = assert!(PAGE as u32 == F303RE.page);
const _: () = assert!(RETAINED_WORDS * 4 <= KEPT_RAM_LEN as usize);

/// The dock relay's pin on port B (hw/pinmap.toml `relay`; sc-fw's build script fails if it moves).
const RELAY_PIN: usize = 5;

#[entry]
fn main() -> ! {
    // First: a few µs after the reset pulse, well inside the relay's drop-out time.
    keep_relay();
    // Only the flash is used, and it needs no set-up: no `embassy_stm32::init`, so the application
    // finds the chip as after a reset.
    let p = unsafe { embassy_stm32::Peripherals::steal() };
    let flash = Mutex::<NoopRawMutex, _>::new(RefCell::new(
        Flash::new_blocking(p.FLASH)
            .into_blocking_regions()
            .bank1_region,
    ));
    let part = |r: Region| BlockingPartition::new(&flash, r.start - F303RE.flash.start, r.len);
    let config = BootLoaderConfig {
        active: part(F303RE.active),
        dfu: part(F303RE.dfu),
        state: part(F303RE.state),
    };
    let bl = BootLoader::prepare::<_, _, _, PAGE>(config);
    // `state` is what the bootloader found: `Swap` means it has just swapped, either a new image in
    // (now on trial) or, after a trial that did not confirm itself, the previous one back.
    match bl.state {
        State::Swap => {
            info!("bootloader: images swapped (a new image on trial, or the previous one back)")
        }
        State::Revert => {
            info!("bootloader: starting the application (its last update was reverted)")
        }
        _ => info!("bootloader: starting the application"),
    }
    let app = F303RE.app_start();
    if !plausible(app) {
        error!(
            "bootloader: no application at {=u32:#010x} (flash one with probe-rs, see docs/firmware-update.md)",
            app
        );
        loop {
            cortex_m::asm::wfi();
        }
    }
    // SAFETY: `app` holds a vector table whose stack pointer lies in RAM and whose reset vector
    // points into the active slot; `load` sets VTOR to it and jumps.
    unsafe { bl.load(app) }
}

/// Drives the relay on again if the application asked for this reset with the relay on.
fn keep_relay() {
    let csr = RCC.csr().read();
    // Only a software reset: the application clears these flags at every start, so after its
    // `SYSRESETREQ` only SFTRSTF is set (a power-on or watchdog reset also raises others).
    if !csr.sftrstf() || csr.porrstf() || csr.iwdgrstf() || csr.wwdgrstf() || csr.lpwrrstf() {
        return;
    }
    let mut block = [0u32; RETAINED_WORDS];
    for (i, w) in block.iter_mut().enumerate() {
        // SAFETY: the kept RAM is word-aligned SRAM outside this program's `.data`/`.bss`/stack
        // (build.rs leaves it out of RAM); any bit pattern is a valid `u32`.
        *w = unsafe {
            core::ptr::read_volatile((F303RE.kept_ram().start as usize + 4 * i) as *const u32)
        };
    }
    if Retained::decode(&block).is_some_and(|r| r.relay) {
        RCC.ahbenr().modify(|w| w.set_gpioben(true));
        // Level first, then output mode: the pin goes from floating straight to high.
        GPIOB.bsrr().write(|w| w.set_bs(RELAY_PIN, true));
        GPIOB
            .moder()
            .modify(|w| w.set_moder(RELAY_PIN, Moder::OUTPUT));
        info!("bootloader: relay kept on across the software reset");
    }
}

/// A vector table at `app`: initial stack pointer inside RAM, reset handler (Thumb) inside the slot.
fn plausible(app: u32) -> bool {
    // SAFETY: both words lie in the active slot of the internal flash, which is always readable.
    let (sp, reset) = unsafe {
        (
            core::ptr::read_volatile(app as *const u32),
            core::ptr::read_volatile((app + 4) as *const u32),
        )
    };
    let ram = F303RE.ram;
    sp > ram.start
        && sp <= ram.end()
        && reset & 1 == 1
        && reset > app
        && reset < F303RE.active.end()
}

#[exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    error!("bootloader: {}, resetting", defmt::Display2Format(info));
    cortex_m::peripheral::SCB::sys_reset()
}
