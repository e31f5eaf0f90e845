//! LED strip: R, G, B duty on TIM1 CH1–3 at 1 kHz, gated by the blink signal on TIM3 CH1.
//!
//! The blink output switches the strip's supply (see `hw/pinmap.toml`, `led_blink`): steady light is a
//! gate held constantly high (100 % duty), blinking is a TIM3 PWM whose period is the blink period and
//! whose duty is the on-percentage. A dark strip also drops the gate.

use embassy_stm32::peripherals::{TIM1, TIM3};
use embassy_stm32::timer::simple_pwm::SimplePwm;
use ihex_sc_core::LedOutput;

use crate::event::LED;

/// The strip's PWM frequency.
pub const PWM_HZ: u32 = 1_000;
/// Longest blink period TIM3 can make at 72 MHz with 16-bit prescaler and reload (≈ 59.6 s).
pub const MAX_BLINK_MS: u16 = 59_000;
/// Shortest blink period (a 2 ms gate is already a dimmer, not a blink).
pub const MIN_BLINK_MS: u16 = 2;

/// Drives the strip from the node's LED output.
#[embassy_executor::task]
pub async fn led(mut rgb: SimplePwm<'static, TIM1>, mut gate: SimplePwm<'static, TIM3>) {
    apply(&mut rgb, &mut gate, LedOutput::default());
    loop {
        let out = LED.wait().await;
        defmt::debug!("led {}", out);
        apply(&mut rgb, &mut gate, out);
    }
}

fn apply(rgb: &mut SimplePwm<'static, TIM1>, gate: &mut SimplePwm<'static, TIM3>, out: LedOutput) {
    let d = out.duty;
    rgb.ch1().set_duty_cycle_fraction(d.r as u32, 255);
    rgb.ch2().set_duty_cycle_fraction(d.g as u32, 255);
    rgb.ch3().set_duty_cycle_fraction(d.b as u32, 255);
    rgb.ch1().enable();
    rgb.ch2().enable();
    rgb.ch3().enable();
    let dark = d.r == 0 && d.g == 0 && d.b == 0;
    match out.blink {
        _ if dark => gate.ch1().set_duty_cycle_fully_off(),
        None => gate.ch1().set_duty_cycle_fully_on(),
        Some((period_ms, on_pct)) => {
            gate.set_period_ms(period_ms.clamp(MIN_BLINK_MS, MAX_BLINK_MS) as u32);
            gate.ch1().set_duty_cycle_percent(on_pct.min(100));
        }
    }
    // Reload and compare registers are preloaded: the update event loads the new period and duty at
    // once, instead of after the old blink period ran out (up to a minute).
    embassy_stm32::pac::TIM3.egr().write(|w| w.set_ug(true));
    gate.ch1().enable();
}
