//! Hands out the SocketCAN interfaces named in `IHEX_TEST_CAN`, one distinct interface per call.
//!
//! Tests of one binary run on parallel threads and a vcan interface is a shared bus, so every test
//! leases its own interface(s) and never sees another test's frames.

use std::sync::atomic::{AtomicUsize, Ordering};

/// Environment variable listing the interfaces tests may use, comma separated (`vcan0,vcan1,...`).
pub const ENV: &str = "IHEX_TEST_CAN";

static NEXT: AtomicUsize = AtomicUsize::new(0);

/// The interfaces listed in [`ENV`], or `None` when the variable is unset or empty.
pub fn interfaces() -> Option<Vec<String>> {
    let raw = std::env::var(ENV).ok()?;
    let list: Vec<String> = raw
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect();
    (!list.is_empty()).then_some(list)
}

/// Leases a SocketCAN interface no other caller in this process gets.
///
/// # Panics
/// When [`ENV`] is missing (the test was not started by the harness) or every interface has
/// already been leased; the message says what to do.
pub fn lease() -> String {
    let Some(list) = interfaces() else {
        panic!(
            "{ENV} is not set: run the SocketCAN tests through `cargo xtask test --stage vcan` \
             (or set {ENV}=vcan0,vcan1,... to interfaces that exist and are up; see docs/testing.md)"
        );
    };
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    match list.get(n) {
        Some(name) => name.clone(),
        None => panic!(
            "all {} interfaces in {ENV} are leased ({}): add more vcan interfaces or split the \
             tests into several test files",
            list.len(),
            list.join(",")
        ),
    }
}

/// Takes a (leased) interface down or brings it up with `ip link set IFACE down|up`, as an
/// unplugged cable or a driver restart would.
///
/// # Panics
/// When `ip` cannot be run or fails (the harness runs the SocketCAN tests as root).
pub fn set_link(iface: &str, up: bool) {
    let state = if up { "up" } else { "down" };
    let st = std::process::Command::new("ip")
        .args(["link", "set", iface, state])
        .status()
        .expect("run ip");
    assert!(st.success(), "ip link set {iface} {state}: {st}");
}
