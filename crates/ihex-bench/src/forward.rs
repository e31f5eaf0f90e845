//! A plain MQTT → CAN forwarder, the yardstick for what a command costs the gateway: what a bridge
//! without a protocol of its own does per frame, as can2mqtt does — read one QoS 1 message,
//! acknowledge it, write its frame — with nothing parsed beyond the frame, nothing tracked and
//! nothing answered. `ihex-bench forward` runs it in the live part's place (the microVM) against
//! the same broker, fed by the same load generator.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result};
use rumqttc::{Client, Event, MqttOptions, Packet, QoS};
use socketcan::{CanFrame, CanSocket, EmbeddedFrame, ExtendedId, Frame, Socket};

use crate::live::write;

/// The topic it forwards from.
pub(crate) const TOPIC: &str = "ihex-bench/raw";

/// The message for frame `f`: `ID#DATA` in hex, cansend's notation for an extended frame.
pub(crate) fn message(f: &CanFrame) -> String {
    let mut m = format!("{:08X}#", f.raw_id());
    for b in f.data() {
        m.push_str(&format!("{b:02X}"));
    }
    m
}

/// The frame of a [`message`] (`None`: not one).
fn parse(m: &[u8]) -> Option<CanFrame> {
    let m = std::str::from_utf8(m).ok()?;
    let (id, data) = m.split_once('#')?;
    let id = ExtendedId::new(u32::from_str_radix(id, 16).ok()?)?;
    if data.len() % 2 != 0 || data.len() > 16 {
        return None;
    }
    let bytes: Option<Vec<u8>> = (0..data.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(data.get(i..i + 2)?, 16).ok())
        .collect();
    CanFrame::new(id, &bytes?)
}

/// `ihex-bench forward`: forwards until the process is killed.
pub(crate) fn serve(iface: &str, broker: SocketAddr) -> Result<()> {
    let sock = CanSocket::open(iface).with_context(|| format!("opening {iface}"))?;
    let mut o = MqttOptions::new(
        format!("ihex-bench-forward-{}", std::process::id()),
        broker.ip().to_string(),
        broker.port(),
    );
    o.set_keep_alive(Duration::from_secs(30))
        .set_clean_session(true);
    let (client, mut conn) = Client::new(o, 64);
    let mut net = conn.eventloop.network_options();
    net.set_tcp_nodelay(true);
    conn.eventloop.set_network_options(net);
    client.subscribe(TOPIC, QoS::AtLeastOnce)?;
    let mut malformed = 0u64;
    for ev in conn.iter() {
        match ev {
            Ok(Event::Incoming(Packet::Publish(p))) => match parse(&p.payload) {
                Some(f) => write(&sock, &f)?,
                None => {
                    malformed += 1;
                    eprintln!("forward: not ID#DATA ({malformed} so far): {:?}", p.payload);
                }
            },
            Ok(_) => {}
            Err(e) => {
                eprintln!("forward: {e}");
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_message_reads_back_as_its_frame() {
        let id = ExtendedId::new(0x1abc_def0).unwrap();
        for data in [&[][..], &[0x00], &[1, 2, 3, 4, 5, 6, 7, 0xff]] {
            let f = CanFrame::new(id, data).unwrap();
            let back = parse(message(&f).as_bytes()).unwrap();
            assert_eq!((back.raw_id(), back.data()), (f.raw_id(), f.data()));
        }
    }

    #[test]
    fn anything_else_is_refused() {
        for m in [
            &b""[..],
            b"1FFFFFFFF#00",
            b"123#0",
            b"123#000102030405060708",
            b"123#zz",
            b"\xff#00",
            b"no hash",
        ] {
            assert!(parse(m).is_none(), "{m:?}");
        }
    }
}
