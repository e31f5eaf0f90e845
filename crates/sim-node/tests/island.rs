//! The island scenarios on an in-memory bus, with tokio's clock paused (debounce and handshake
//! delays pass instantly). The same scenarios run over real vcan in `tests/tests/sim_island.rs`.

mod scenario;

use sim_node::{bus::MemBus, Link};

fn mem() -> Link {
    Link::Mem(MemBus::new())
}

#[tokio::test(start_paused = true)]
async fn boot() {
    scenario::boot(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn dock_and_undock() {
    scenario::dock_and_undock(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn bad_requests() {
    scenario::bad_requests(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn power_cycle() {
    scenario::power_cycle(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn off_bus() {
    scenario::off_bus(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn actuators() {
    scenario::actuators(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn bounce() {
    scenario::bounce(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn uart_id() {
    scenario::uart_id(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn docked_at_start() {
    scenario::docked_at_start(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn can_assignment() {
    scenario::can_assignment(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn state_query() {
    scenario::state_query(mem()).await;
}

/// The island also runs on a real multi-threaded runtime with a running clock.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dock_and_undock_in_real_time() {
    scenario::dock_and_undock(mem()).await;
}

#[tokio::test(start_paused = true)]
async fn firmware_update() {
    scenario::firmware_update(mem()).await;
}
