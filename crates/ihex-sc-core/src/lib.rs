//! The sub-controller's behaviour, written once as a sans-IO state machine.
//!
//! A [`Node`] takes inputs — received frames, signal-loop levels per dock port, UART bytes, the passage
//! of time — and produces outputs: frames to send, UART replies, a node ID to persist, and the
//! [`Actuators`] setting (LED PWM and blink, buzzer tone and pattern, relay) the hardware must show.
//! It does no I/O and never blocks: the firmware (`sc-fw`) and the simulator (`sim-node`) are thin
//! adapters that feed it and carry out what it asks, so they behave identically by construction.
//!
//! Driving it: call the `handle_*` methods as inputs arrive and [`Node::tick`] at least at
//! [`Node::poll_at`]; after every call drain [`Node::poll_output`] until `None`, and apply
//! [`Node::actuators`] whenever [`Node::actuators_changed`] says so.
#![cfg_attr(not(test), no_std)]
#![warn(missing_docs)]
#![forbid(unsafe_code)]

mod actuator;
mod debounce;
mod node;
mod queue;
mod time;

pub use actuator::{Actuators, BuzzerOutput, LedOutput};
pub use node::{
    Config, Node, Output, DEBOUNCE_MS, HANDSHAKE_SETTLE_MS, IDENTIFY_BUZZER, IDENTIFY_LED,
    UART_IDLE_RESET_MS,
};
pub use queue::OUTPUT_QUEUE_LEN;
pub use time::Millis;
