//! The dock power relay: a plain GPIO, off through reset (external pull-down) and driven off at boot.
//!
//! Not a task of its own: the core requires the relay to be switched *before* the frame that goes
//! with it leaves (relay off before `DockRemoved`), and a separate task could be scheduled after the
//! CAN transmitter. The node task therefore owns the relay and switches it synchronously.

use defmt::info;
use embassy_stm32::gpio::Output;

/// The relay output with its active level from the pin map.
pub struct Relay {
    pin: Output<'static>,
    active_low: bool,
    on: bool,
}

impl Relay {
    /// Takes the pin (already driven to the off level) and the pin map's `RELAY_ACTIVE_LOW`.
    pub fn new(pin: Output<'static>, active_low: bool) -> Self {
        let mut r = Relay {
            pin,
            active_low,
            on: true,
        };
        r.set(false);
        r
    }

    /// Switches the relay; logs changes.
    pub fn set(&mut self, on: bool) {
        if on != self.on {
            info!("relay {}", if on { "ON" } else { "off" });
        }
        self.on = on;
        if on != self.active_low {
            self.pin.set_high();
        } else {
            self.pin.set_low();
        }
    }
}
