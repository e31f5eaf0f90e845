//! Loopback TCP ports for tests: the kernel picks a free one (tests never use fixed ports).

use std::io;
use std::net::{Ipv4Addr, TcpListener};

/// A loopback port nobody listens on right now (the kernel picks it; it is released for the
/// caller's server, which binds it next).
pub fn try_free_port() -> io::Result<u16> {
    Ok(TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?
        .local_addr()?
        .port())
}

/// [`try_free_port`] for a test: panics when the loopback interface cannot be bound.
pub fn free_port() -> u16 {
    try_free_port().expect("binding a free loopback port")
}
