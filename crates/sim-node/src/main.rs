//! `sim-node`: run an island of virtual sub-controllers on a SocketCAN interface.
fn main() {}
