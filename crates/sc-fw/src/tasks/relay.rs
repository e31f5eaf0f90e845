//! The dock power relay: a plain GPIO, off at reset (external pull-down) and driven low at boot.

use defmt::info;
use embassy_stm32::gpio::Output;

use crate::event::RELAY;

/// Applies every relay setting the node publishes. `active_low` comes from the pin map.
#[embassy_executor::task]
pub async fn relay(mut pin: Output<'static>, active_low: bool) {
    loop {
        let on = RELAY.wait().await;
        info!("relay {}", if on { "ON" } else { "off" });
        if on != active_low {
            pin.set_high();
        } else {
            pin.set_low();
        }
    }
}
