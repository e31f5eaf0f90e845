//! `sim-node` over real SocketCAN: the island scenarios of `crates/sim-node/tests/scenario`, the same
//! code the in-memory tests run, on a leased vcan interface. Every virtual node has its own raw socket
//! with its kernel acceptance filters; the test plays the gateway on another socket.
#![cfg(feature = "vcan")]

#[path = "../../crates/sim-node/tests/scenario/mod.rs"]
mod scenario;

use ihex_tests::can;
use sim_node::Link;

fn vcan() -> Link {
    Link::socketcan(can::lease())
}

#[tokio::test]
async fn boot() {
    scenario::boot(vcan()).await;
}

#[tokio::test]
async fn dock_and_undock() {
    scenario::dock_and_undock(vcan()).await;
}

#[tokio::test]
async fn bad_requests() {
    scenario::bad_requests(vcan()).await;
}

#[tokio::test]
async fn power_cycle() {
    scenario::power_cycle(vcan()).await;
}

#[tokio::test]
async fn off_bus() {
    scenario::off_bus(vcan()).await;
}

#[tokio::test]
async fn actuators() {
    scenario::actuators(vcan()).await;
}

#[tokio::test]
async fn bounce() {
    scenario::bounce(vcan()).await;
}

#[tokio::test]
async fn uart_id() {
    scenario::uart_id(vcan()).await;
}

#[tokio::test]
async fn docked_at_start() {
    scenario::docked_at_start(vcan()).await;
}

#[tokio::test]
async fn can_assignment() {
    scenario::can_assignment(vcan()).await;
}

#[tokio::test]
async fn state_query() {
    scenario::state_query(vcan()).await;
}
