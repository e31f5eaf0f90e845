//! The node state machine: commands, health, signal-loop debounce, docking, mobile handshake, ID set-up.

use ihex_proto::{uart::UartDecoder, BootRole, NodeId, Packet, Port, ResetReason, Uid};

use crate::{Actuators, Millis};

/// A signal-loop level must stay unchanged this long before it counts (a bouncing contact = one event).
pub const DEBOUNCE_MS: u64 = 50;
/// A half-received UART request is dropped after this idle gap.
pub const UART_IDLE_RESET_MS: u64 = 100;

/// How a node is built and what it remembers across resets.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Config {
    /// Static element (on the bus, has dock ports) or mobile element (docks onto one).
    pub role: BootRole,
    /// Number of dock ports with a signal loop (`0..=8`).
    pub ports: u8,
    /// The MCU's 96-bit unique ID (CAN node-ID assignment selects by it).
    pub uid: Uid,
    /// The stored node ID; `None` for a factory-fresh board, which stays quiet until given one.
    pub node_id: Option<NodeId>,
    /// Why the node started (reported in the boot-up announcement).
    pub reset: ResetReason,
}

/// Something the adapter must do.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Output {
    /// Transmit this frame.
    Frame(Packet),
    /// Write these two bytes to the configuration UART.
    Uart([u8; 2]),
    /// Persist this node ID (flash); report a failure with [`Node::handle_store_failed`].
    StoreId(NodeId),
    /// Reconfigure the CAN acceptance filters: the node ID changed
    /// (use `ihex_proto::filter::sc_filters(node.node_id())`).
    FiltersChanged,
}

/// One sub-controller's complete behaviour.
#[derive(Debug)]
pub struct Node {
    #[allow(dead_code)]
    config: Config,
    #[allow(dead_code)]
    uart: UartDecoder,
    // The implementation fills this in.
}

impl Node {
    /// A node that has just reset at `now`. Queues the boot-up announcement (and, for a mobile
    /// element, schedules its handshake) unless it has no ID yet.
    pub fn new(config: Config, now: Millis) -> Self {
        let _ = now;
        todo!("ihex-sc-core: Node::new")
    }

    /// The node ID in force, `None` while unconfigured.
    pub fn node_id(&self) -> Option<NodeId> {
        todo!()
    }

    /// The node's configuration (role, ports, UID, ID).
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// A frame arrived (raw 29-bit ID and data, as received: the core decodes and validates it).
    /// `extended`/`remote` describe the frame's flags.
    pub fn handle_frame(&mut self, raw_id: u32, extended: bool, remote: bool, data: &[u8], now: Millis) {
        let _ = (raw_id, extended, remote, data, now);
        todo!()
    }

    /// The current level of a dock port's signal loop (`closed` = pulled low = something docked).
    /// Call on every edge and/or periodically; the core debounces.
    pub fn handle_loop_level(&mut self, port: Port, closed: bool, now: Millis) {
        let _ = (port, closed, now);
        todo!()
    }

    /// One byte from the configuration UART.
    pub fn handle_uart_byte(&mut self, byte: u8, now: Millis) {
        let _ = (byte, now);
        todo!()
    }

    /// The CAN controller's error counters and state, for health replies and fault reports.
    pub fn handle_can_status(&mut self, tec: u8, rec: u8, bus_off: bool, now: Millis) {
        let _ = (tec, rec, bus_off, now);
        todo!()
    }

    /// Persisting the node ID failed: the core reports a fault (and answers UART with an error).
    pub fn handle_store_failed(&mut self, now: Millis) {
        let _ = now;
        todo!()
    }

    /// The adapter finished a finite buzzer pattern.
    pub fn handle_buzzer_done(&mut self, now: Millis) {
        let _ = now;
        todo!()
    }

    /// Advances timers (debounce, identify, UART idle, handshake) to `now`.
    pub fn tick(&mut self, now: Millis) {
        let _ = now;
        todo!()
    }

    /// The latest time by which [`Node::tick`] must be called again, `None` if nothing is pending.
    pub fn poll_at(&self) -> Option<Millis> {
        todo!()
    }

    /// Next queued output, `None` when drained.
    pub fn poll_output(&mut self) -> Option<Output> {
        todo!()
    }

    /// The effective actuator setting (identify overrides LED and buzzer while it runs).
    pub fn actuators(&self) -> Actuators {
        todo!()
    }

    /// True once after every change of [`Node::actuators`] (reading it clears the flag).
    pub fn actuators_changed(&mut self) -> bool {
        todo!()
    }
}
