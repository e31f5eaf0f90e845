//! The LED strip's state in the shape Home Assistant's JSON-schema light reads from its state
//! topic (`{"state":"ON","color_mode":"rgb","color":{"r":255,"g":0,"b":0},"brightness":128,
//! "effect":"blink"}`). That schema has no value template, so the gateway publishes this on a topic
//! of its own (retained) instead of pointing Home Assistant at the node's state document.

use std::borrow::Cow;

use ihex_proto::{LedCommand, Rgb};
use serde::{Deserialize, Serialize};

/// The effect that is no effect (Home Assistant's `light.EFFECT_OFF`).
pub const EFFECT_OFF: &str = "off";
/// The effect of a blinking strip.
pub const EFFECT_BLINK: &str = "blink";
/// The light's effects, as its discovery config lists them.
pub const EFFECTS: [&str; 2] = [EFFECT_OFF, EFFECT_BLINK];

/// A colour as Home Assistant's JSON schema writes it for the `rgb` colour mode.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct RgbColor {
    /// Red, 0–255.
    pub r: u8,
    /// Green, 0–255.
    pub g: u8,
    /// Blue, 0–255.
    pub b: u8,
}

impl From<Rgb> for RgbColor {
    fn from(c: Rgb) -> Self {
        RgbColor {
            r: c.r,
            g: c.g,
            b: c.b,
        }
    }
}

/// One state message of the light. Its texts are the constants above as the gateway builds it
/// (built for every state document, so without allocating), any text once read back.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LightState {
    /// `ON`, `OFF`, or `null` while the node has acknowledged no LED command (unknown).
    pub state: Option<Cow<'static, str>>,
    /// `rgb` while on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color_mode: Option<Cow<'static, str>>,
    /// The colour while on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color: Option<RgbColor>,
    /// 0–255 while on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub brightness: Option<u8>,
    /// [`EFFECT_BLINK`] or [`EFFECT_OFF`] while on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub effect: Option<Cow<'static, str>>,
}

impl LightState {
    /// The light as the LED command the node last acknowledged shows it (`None`: none yet, or the
    /// node restarted since).
    pub fn from_led(led: Option<LedCommand>) -> LightState {
        let on = |color: Rgb, brightness: u8, effect: &'static str| LightState {
            state: Some("ON".into()),
            color_mode: Some("rgb".into()),
            color: Some(color.into()),
            brightness: Some(brightness),
            effect: Some(effect.into()),
        };
        match led {
            None => LightState {
                state: None,
                color_mode: None,
                color: None,
                brightness: None,
                effect: None,
            },
            Some(LedCommand::Off) => LightState {
                state: Some("OFF".into()),
                ..LightState::from_led(None)
            },
            Some(LedCommand::Steady { color, brightness }) => on(color, brightness, EFFECT_OFF),
            Some(LedCommand::Blink {
                color, brightness, ..
            }) => on(color, brightness, EFFECT_BLINK),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn json(led: Option<LedCommand>) -> String {
        serde_json::to_string(&LightState::from_led(led)).unwrap()
    }

    #[test]
    fn every_led_state_in_home_assistants_shape() {
        assert_eq!(json(None), r#"{"state":null}"#);
        assert_eq!(json(Some(LedCommand::Off)), r#"{"state":"OFF"}"#);
        assert_eq!(
            json(Some(LedCommand::Steady {
                color: Rgb::new(255, 0, 0),
                brightness: 128
            })),
            r#"{"state":"ON","color_mode":"rgb","color":{"r":255,"g":0,"b":0},"brightness":128,"effect":"off"}"#
        );
        assert_eq!(
            json(Some(LedCommand::Blink {
                color: Rgb::new(0, 1, 2),
                brightness: 255,
                period_10ms: 50,
                duty_pct: 50
            })),
            r#"{"state":"ON","color_mode":"rgb","color":{"r":0,"g":1,"b":2},"brightness":255,"effect":"blink"}"#
        );
    }
}
