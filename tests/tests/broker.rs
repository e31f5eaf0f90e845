//! The Mosquitto helper starts a real broker, survives a restart on the same port, and stops.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

use ihex_tests::broker::Mosquitto;

/// An MQTT 3.1.1 CONNECT (clean session, keep-alive 20 s, client id "t") must get a CONNACK with
/// return code 0: proof that a real broker, not just a socket, is listening.
fn connack(addr: std::net::SocketAddr) -> std::io::Result<[u8; 4]> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(ihex_tests::time::scaled(Duration::from_secs(10))))?;
    let connect = [
        0x10, 13, 0x00, 0x04, b'M', b'Q', b'T', b'T', 0x04, 0x02, 0x00, 20, 0x00, 0x01, b't',
    ];
    s.write_all(&connect)?;
    let mut reply = [0u8; 4];
    s.read_exact(&mut reply)?;
    Ok(reply)
}

#[test]
fn mosquitto_starts_restarts_and_stops() {
    let mut broker = Mosquitto::start().expect("start mosquitto");
    let addr = broker.addr();
    assert!(addr.ip().is_loopback());
    assert_eq!(connack(addr).expect("CONNACK"), [0x20, 0x02, 0x00, 0x00]);

    broker.restart().expect("restart mosquitto");
    assert_eq!(broker.addr(), addr, "a restart keeps the port");
    assert_eq!(
        connack(addr).expect("CONNACK after restart"),
        [0x20, 0x02, 0x00, 0x00]
    );

    broker.stop();
    assert!(!broker.is_running());
    assert!(
        TcpStream::connect(addr).is_err(),
        "nothing listens after stop"
    );
}

#[test]
fn two_brokers_get_distinct_ports() {
    let a = Mosquitto::start().expect("start first");
    let b = Mosquitto::start().expect("start second");
    assert_ne!(a.addr(), b.addr());
}
