//! Buzzer on TIM15 CH2: a 50 % square wave at the tone frequency, switched on and off for patterns.

use embassy_futures::select::{select, Either};
use embassy_stm32::peripherals::TIM15;
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::simple_pwm::SimplePwm;
use embassy_time::Timer;
use ihex_proto::BuzzerCommand;
use ihex_sc_core::BuzzerOutput;

use crate::event::{Event, BUZZER, EVENTS};

fn sound(pwm: &mut SimplePwm<'static, TIM15>, freq_hz: u16) {
    let f = freq_hz.clamp(BuzzerCommand::MIN_FREQ_HZ, BuzzerCommand::MAX_FREQ_HZ);
    pwm.set_frequency(Hertz(f as u32));
    let mut ch = pwm.ch2();
    ch.set_duty_cycle_percent(50);
    ch.enable();
}

fn silence(pwm: &mut SimplePwm<'static, TIM15>) {
    let mut ch = pwm.ch2();
    ch.set_duty_cycle_fully_off();
    ch.disable();
}

/// Plays what the node asks; reports the end of a finite pattern.
#[embassy_executor::task]
pub async fn buzzer(mut pwm: SimplePwm<'static, TIM15>) {
    silence(&mut pwm);
    let mut current = BuzzerOutput::Off;
    loop {
        current = match current {
            BuzzerOutput::Off => {
                silence(&mut pwm);
                BUZZER.wait().await
            }
            BuzzerOutput::Tone { freq_hz } => {
                sound(&mut pwm, freq_hz);
                BUZZER.wait().await
            }
            BuzzerOutput::Pattern {
                freq_hz,
                on_ms,
                off_ms,
                count,
            } => {
                match play(&mut pwm, freq_hz, on_ms, off_ms, count).await {
                    // Replaced before it ended: start the new setting at once.
                    Some(next) => next,
                    None => {
                        silence(&mut pwm);
                        EVENTS.send(Event::BuzzerDone).await;
                        BUZZER.wait().await
                    }
                }
            }
        };
    }
}

/// Plays a pattern; `Some(new)` if a new setting arrived first, `None` when `count` beeps are done.
async fn play(
    pwm: &mut SimplePwm<'static, TIM15>,
    freq_hz: u16,
    on_ms: u16,
    off_ms: u16,
    count: u8,
) -> Option<BuzzerOutput> {
    let mut done = 0u8;
    loop {
        sound(pwm, freq_hz);
        if let Either::First(next) =
            select(BUZZER.wait(), Timer::after_millis(on_ms.max(1) as u64)).await
        {
            return Some(next);
        }
        silence(pwm);
        done = done.saturating_add(1);
        if count != 0 && done >= count {
            return None;
        }
        if let Either::First(next) =
            select(BUZZER.wait(), Timer::after_millis(off_ms.max(1) as u64)).await
        {
            return Some(next);
        }
    }
}
