//! Test harness shared by the behaviour tests: build nodes, send commands, collect outputs.
#![allow(dead_code)]

use ihex_image::board::F303RE;
use ihex_proto::{BootRole, FirmwareVersion, Message, NodeId, Packet, Port, ResetReason, Uid};
use ihex_sc_core::{Config, FirmwareIdentity, Millis, Node, Output, UpdateConfig};

pub const ID: u16 = 0x111;
pub const UID: [u8; 12] = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12];
/// The firmware every test node runs.
pub const FIRMWARE: FirmwareIdentity = FirmwareIdentity {
    version: FirmwareVersion::new(1, 4, 2),
    image_hash: [0xA1, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7],
    trial: false,
};

/// Every test node takes F303RE images signed with the test key.
pub const UPDATE: UpdateConfig = UpdateConfig {
    board: ihex_image::Board::NUCLEO_F303RE,
    key: ihex_image::test_key::PUBLIC,
    layout: &F303RE,
    reverted: false,
};

pub fn id() -> NodeId {
    NodeId::new_sc(ID).unwrap()
}

pub fn port(p: u8) -> Port {
    Port::new(p).unwrap()
}

pub fn config(role: BootRole, ports: u8, node_id: Option<NodeId>) -> Config {
    Config {
        role,
        ports,
        uid: Uid(UID),
        node_id,
        reset: ResetReason::PowerOn,
        firmware: FIRMWARE,
        update: UPDATE,
    }
}

/// A static node with 6 ports and ID 0x111, boot output drained.
pub fn static_node() -> Node {
    let mut n = Node::new(config(BootRole::Static, 6, Some(id())), Millis(0));
    drain(&mut n);
    n
}

/// Every queued output.
pub fn drain(n: &mut Node) -> Vec<Output> {
    let mut v = Vec::new();
    while let Some(o) = n.poll_output() {
        if let Output::Frame(p) = o {
            p.validate().expect("the core only emits valid frames");
        }
        v.push(o);
    }
    v
}

/// The queued frames' messages (non-frame outputs dropped).
pub fn msgs(n: &mut Node) -> Vec<Message> {
    drain(n)
        .into_iter()
        .filter_map(|o| match o {
            Output::Frame(p) => Some(p.msg),
            _ => None,
        })
        .collect()
}

/// Feeds an encoded packet to the node as a received extended data frame.
pub fn feed(n: &mut Node, p: Packet, now: u64) {
    let (raw, data) = p.encode();
    n.handle_frame(raw, true, false, &data, Millis(now));
}

/// Sends a gateway command to the node's own ID.
pub fn cmd(n: &mut Node, msg: Message, now: u64) {
    let dest = n.node_id().unwrap_or(NodeId::BROADCAST);
    feed(n, Packet::command(dest, msg), now);
}

/// Holds a loop level steady past the debounce time.
pub fn settle_loop(n: &mut Node, p: u8, closed: bool, now: u64) -> u64 {
    n.handle_loop_level(port(p), closed, Millis(now));
    let t = now + ihex_sc_core::DEBOUNCE_MS;
    n.tick(Millis(t));
    t
}
