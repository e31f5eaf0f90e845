//! Traffic on the bus while the doctor listened (its own probes included): frames seen, error
//! frames and what they usually mean physically.

use std::{collections::BTreeMap, time::Duration};

use ihex_gateway_core::error_frame;

use super::Verdict;

/// Identifier of the traffic check.
pub const CHECK: &str = "bus.traffic";

/// What was seen on the bus.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Facts {
    /// Data frames received from other senders.
    pub frames: u64,
    /// Frames that are not iHEX frames (another protocol on the bus, or a corrupted sender).
    pub foreign: u64,
    /// Error frames, by class name (`no_ack`, `bus_off`, …; `error_frame::CLASSES`), counted.
    pub errors: BTreeMap<String, u64>,
    /// Probes the doctor could not send, and the last reason.
    pub send_failures: Option<(u32, String)>,
}

impl Facts {
    /// Counts one error frame (`class` is the error frame's identifier, `data` its payload).
    pub fn observe_error(&mut self, class: u32, data: [u8; 8]) {
        let decoded = error_frame::decode(class, data);
        for c in decoded.classes.unwrap_or_default() {
            *self.errors.entry(c).or_default() += 1;
        }
    }

    /// Counts one probe that could not be sent.
    pub fn send_failed(&mut self, why: String) {
        let n = self.send_failures.as_ref().map_or(0, |(n, _)| *n);
        self.send_failures = Some((n + 1, why));
    }
}

/// What an error class usually means on an iHEX bench, most telling first.
const MEANINGS: [(&str, &str); 6] = [
    (
        "bus_off",
        "bus-off: the controller stopped after too many errors: check termination (120 Ω at both ends) \
         and that every node runs at 500 kbit/s",
    ),
    (
        "no_ack",
        "nobody acknowledged the frames: no other node powered on the bus, or no termination \
         (120 Ω at both ends: CANH–CANL ≈ 60 Ω with power off), or CANH/CANL swapped",
    ),
    (
        "protocol",
        "bit/stuff/form errors: a node at another bitrate (every node 500 kbit/s), a missing \
         termination or CAN_GND, long stubs, or CANH/CANL swapped",
    ),
    (
        "bus_error",
        "bus errors: a node at another bitrate, a missing termination or CAN_GND, or long stubs",
    ),
    (
        "controller",
        "controller warnings (error counters rising or receive overflow): errors on the bus, or \
         the Pi reads frames too slowly",
    ),
    (
        "transceiver",
        "transceiver errors: CANH or CANL shorted or open: check the wiring to the HAT",
    ),
];

/// Judges what was seen during `listen`.
pub fn check(f: &Facts, listen: Duration) -> Verdict {
    let secs = listen.as_secs_f32();
    let counted: Vec<String> = f.errors.iter().map(|(c, n)| format!("{c} ×{n}")).collect();
    if let Some((_, meaning)) = MEANINGS.iter().find(|(c, _)| f.errors.contains_key(*c)) {
        return Verdict::fail(
            CHECK,
            format!(
                "{} frames and error frames ({}) in {secs:.1} s",
                f.frames,
                counted.join(", ")
            ),
            meaning.to_string(),
        );
    }
    if let Some((n, why)) = &f.send_failures {
        return Verdict::fail(
            CHECK,
            format!("{n} probe frame(s) could not be sent ({why})"),
            "the controller does not get frames out: nobody acknowledges (no other node, no \
             termination) or the transmit queue is full; see can.controller above",
        );
    }
    if f.frames == 0 {
        return Verdict::fail(
            CHECK,
            format!("no frame in {secs:.1} s, not even an answer to the doctor's health check"),
            "power the boards and check CANH/CANL reach every board; on a board, the firmware's \
             `loopback` binary proves its CAN transceiver (docs/firmware.md)",
        );
    }
    let foreign = if f.foreign > 0 {
        format!(
            " ({} not iHEX frames: another device on the bus?)",
            f.foreign
        )
    } else {
        String::new()
    };
    let others = if counted.is_empty() {
        String::new()
    } else {
        format!(", error frames: {}", counted.join(", "))
    };
    Verdict::pass(
        CHECK,
        format!(
            "{} frames in {secs:.1} s, no bus errors{others}{foreign}",
            f.frames
        ),
    )
}
