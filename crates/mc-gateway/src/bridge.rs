//! The gateway's logic, sans-IO: JSON commands and CAN packets in, frames to send and MQTT publications
//! out. No sockets, no clocks of its own: the async adapters (`can`, `mqtt`) feed it and carry out its
//! [`Action`]s, so every behaviour — command validation, acknowledgement tracking, health and lost-node
//! detection, the one-at-a-time docking sequence — is tested without a bus or a broker.

use std::time::{Duration, Instant};

use ihex_proto::{DecodeError, NodeId, Packet};

/// Tunables of the bridge (the CLI/TOML configuration fills these in).
#[derive(Clone, Debug)]
pub struct BridgeConfig {
    /// Period of the broadcast health check (seed: 1 s).
    pub health_period: Duration,
    /// Consecutive missed health replies after which a node is `node_lost` (default 3).
    pub lost_after_misses: u32,
    /// How long to wait for the mobile element's handshake after confirming a docking.
    pub dock_timeout: Duration,
    /// How long to wait for a node's ack before a `command_result` with `"timeout"`.
    pub command_timeout: Duration,
    /// Largest accepted command payload in bytes; larger ones are `command_rejected`.
    pub max_command_bytes: usize,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        BridgeConfig {
            health_period: Duration::from_secs(1),
            lost_after_misses: 3,
            dock_timeout: Duration::from_secs(5),
            command_timeout: Duration::from_millis(500),
            max_command_bytes: 4096,
        }
    }
}

/// Logical MQTT topics; the `mqtt` adapter maps them to names under the island prefix.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum Topic {
    /// `EventsTopic`: every JSON event.
    Events,
    /// The retained state document of one node.
    NodeState(NodeId),
}

/// What the adapters must do for the bridge.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Action {
    /// Transmit on the CAN bus.
    Send(Packet),
    /// Publish `payload` (JSON) on `topic`, QoS 1.
    Publish {
        /// Where.
        topic: Topic,
        /// JSON text.
        payload: String,
        /// Retained (node state) or not (events).
        retain: bool,
    },
}

/// Bus conditions the CAN adapter observes besides frames.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum BusEvent {
    /// An error frame arrived (`can_id` with the error class bits, `data` as received).
    ErrorFrame {
        /// Error class bits (`CAN_ERR_*` of linux/can/error.h).
        class: u32,
        /// The error frame's 8 data bytes.
        data: [u8; 8],
    },
    /// The controller went bus-off.
    BusOff,
    /// The interface went down or vanished (the adapter retries opening it).
    InterfaceDown,
    /// The interface is back up after `BusOff` or `InterfaceDown`.
    Recovered,
    /// The kernel dropped received frames (count since the last report).
    RxDropped(u32),
}

/// The gateway state machine.
#[derive(Debug)]
pub struct Bridge {
    // The implementation fills this in.
}

impl Bridge {
    /// A bridge started at `now`; the first health check is due at once.
    pub fn new(config: BridgeConfig, now: Instant) -> Self {
        let _ = (config, now);
        todo!("mc-gateway: Bridge::new")
    }

    /// A message arrived on `CommandsTopic` (raw bytes: the bridge parses and validates them and answers
    /// bad input with a `command_rejected` event).
    pub fn on_command(&mut self, payload: &[u8], now: Instant) {
        let _ = (payload, now);
        todo!()
    }

    /// A valid iHEX packet arrived on the bus.
    pub fn on_packet(&mut self, packet: Packet, now: Instant) {
        let _ = (packet, now);
        todo!()
    }

    /// A frame arrived that passed the filters but is not a valid iHEX packet.
    pub fn on_undecodable(&mut self, raw_id: u32, data: &[u8], err: DecodeError, now: Instant) {
        let _ = (raw_id, data, err, now);
        todo!()
    }

    /// A bus condition (error frame, bus-off, interface down/up, drops).
    pub fn on_bus_event(&mut self, event: BusEvent, now: Instant) {
        let _ = (event, now);
        todo!()
    }

    /// A frame from [`Action::Send`] could not be transmitted.
    pub fn on_send_failed(&mut self, packet: Packet, reason: &str, now: Instant) {
        let _ = (packet, reason, now);
        todo!()
    }

    /// The MQTT session is (re)established: queue the retained node states again (a restarted broker
    /// may have lost them).
    pub fn on_mqtt_connected(&mut self, now: Instant) {
        let _ = now;
        todo!()
    }

    /// Advances timers: health broadcast, lost nodes, ack and docking timeouts.
    pub fn tick(&mut self, now: Instant) {
        let _ = now;
        todo!()
    }

    /// When [`Bridge::tick`] must run next.
    pub fn next_deadline(&self) -> Instant {
        todo!()
    }

    /// Next action for the adapters, `None` when drained.
    pub fn poll_action(&mut self) -> Option<Action> {
        todo!()
    }
}
