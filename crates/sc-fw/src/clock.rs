//! The chip configuration shared by the firmware and the bring-up binaries.

use embassy_stm32::rcc::{
    AHBPrescaler, APBPrescaler, Hse, HseMode, Pll, PllMul, PllPreDiv, PllSource, Sysclk,
};
use embassy_stm32::time::Hertz;

/// HSE 8 MHz in bypass (the ST-Link's MCO drives OSC_IN on the NUCLEO) → PLL ×9 = 72 MHz SYSCLK;
/// AHB 72 MHz, APB1 /2 = 36 MHz (bxCAN, `board::APB1_HZ`), APB2 72 MHz. Without the HSE signal
/// `embassy_stm32::init` waits forever: check the NUCLEO's SB55/MCO jumper if a board hangs at boot.
pub fn config() -> embassy_stm32::Config {
    let mut c = embassy_stm32::Config::default();
    c.rcc.hse = Some(Hse {
        freq: Hertz(8_000_000),
        mode: HseMode::Bypass,
    });
    c.rcc.pll = Some(Pll {
        src: PllSource::HSE,
        prediv: PllPreDiv::DIV1,
        mul: PllMul::MUL9,
    });
    c.rcc.sys = Sysclk::PLL1_P;
    c.rcc.ahb_pre = AHBPrescaler::DIV1;
    c.rcc.apb1_pre = APBPrescaler::DIV2;
    c.rcc.apb2_pre = APBPrescaler::DIV1;
    c
}

/// Resets the chip on a hard fault (which is also where panic-probe ends up after logging a panic):
/// without a debugger attached this restarts the node with the relay off instead of hanging until the
/// watchdog bites. With probe-rs attached, its vector catch halts first so the backtrace is shown.
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    cortex_m::peripheral::SCB::sys_reset()
}
