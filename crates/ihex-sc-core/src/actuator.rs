//! What the hardware must show: the effective LED, buzzer and relay settings.

use ihex_proto::Rgb;

/// LED strip drive: per-channel PWM duty (brightness already applied) and an optional blink gate.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LedOutput {
    /// Duty of the R, G, B channels, 0–255 (0 = off), i.e. colour × brightness / 255.
    pub duty: Rgb,
    /// `Some((period_ms, on_pct))` to gate the strip on and off (TIM3 CH1 on the board); `None` = steady.
    pub blink: Option<(u16, u8)>,
}

/// Buzzer drive.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BuzzerOutput {
    /// Silent.
    #[default]
    Off,
    /// Sound `freq_hz` continuously.
    Tone {
        /// Tone frequency.
        freq_hz: u16,
    },
    /// Beep `count` times (0 = forever): on `on_ms`, off `off_ms`. The adapter times the pattern and
    /// reports its end with [`crate::Node::handle_buzzer_done`] (or the core ends it at its own tick).
    Pattern {
        /// Tone frequency.
        freq_hz: u16,
        /// Beep length.
        on_ms: u16,
        /// Pause length.
        off_ms: u16,
        /// Beeps (0 = until changed).
        count: u8,
    },
}

/// The complete actuator state of a node.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Actuators {
    /// LED strip.
    pub led: LedOutput,
    /// Buzzer.
    pub buzzer: BuzzerOutput,
    /// Power relay to the dock (true = on).
    pub relay: bool,
}
