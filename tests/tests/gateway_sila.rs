//! Gateway end to end over vcan with a SiLA client: one `IslandControl.SetLight` call becomes the
//! `LedSet` frame docs/protocol.md specifies, byte for byte, the node's `Ack` comes back, and only
//! then does the SiLA call return; the element's state shows the new light.
#![cfg(feature = "vcan")]

mod gateway_support;

use embedded_can::{Frame as _, Id};
use gateway_support::{id, Rig, WAIT};
use ihex_proto::Rgb;
use ihex_tests::broker::Mosquitto;
use mc_gateway::sila::proto::{
    framework,
    island_control::{self as pb, island_control_client::IslandControlClient},
};
use socketcan::tokio::CanSocket;

/// The raw 29-bit identifier of a frame (`None` for a standard one).
fn raw_id(f: &socketcan::CanFrame) -> Option<u32> {
    match f.id() {
        Id::Extended(e) => Some(e.as_raw()),
        Id::Standard(_) => None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sila_command_is_one_frame_its_ack_and_the_answer() {
    let sila = ihex_tests::free_port();
    let broker = Mosquitto::start().expect("start mosquitto");
    let mut rig = Rig::start_at_with(broker.addr(), "sila", |o| {
        o.sila = Some(format!("127.0.0.1:{sila}"));
        o.sila_insecure = Some(true);
        o.sila_announce = Some("off".into());
    })
    .await;
    rig.broker = Some(broker);
    // Everything on the bus from now on, as a second socket on the same interface sees it.
    let sock = CanSocket::open(&rig.iface).expect("open a test socket");
    let ch = tonic::transport::Channel::from_shared(format!("http://127.0.0.1:{sila}"))
        .unwrap()
        .connect()
        .await
        .expect("the SiLA server listens");
    let mut c = IslandControlClient::new(ch);
    let text = |v: &str| Some(framework::String { value: v.into() });
    let int = |value| Some(framework::Integer { value });
    let call = c.set_light(pb::SetLightParameters {
        element_id: text("111"),
        color: text("red"),
        brightness: int(50),
        blink_period: int(0),
        blink_duty: int(50),
    });
    let frames = async {
        // LedSet (0x0D) from the gateway (0x000) to 0x111, then its Ack (0x07) from 0x111.
        let mut seen = Vec::new();
        loop {
            let f = sock.read_frame().await.expect("read a frame");
            let Some(raw) = raw_id(&f) else { continue };
            // Only Acks of a LedSet: 111 also acknowledges the gateway's own frames of the
            // island's start (its dock link), which may still be on the bus.
            let led_ack = raw == 0x0700_0111 && f.data().first() == Some(&0x0D);
            if raw == 0x0D11_1000 || led_ack {
                seen.push((raw, f.data().to_vec()));
            }
            if led_ack {
                return seen;
            }
        }
    };
    let (answer, seen) = ihex_tests::within_or_panic(WAIT, "the SiLA call and its frames", async {
        tokio::join!(call, frames)
    })
    .await;
    answer.expect("SetLight succeeds once the node acknowledged");
    let (led_id, led) = &seen[0];
    assert_eq!(*led_id, 0x0D11_1000, "{seen:02x?}");
    let seq = led[0];
    // seq, mode steady, r g b, brightness 50 % of 255 = 128, period 0, duty 0.
    assert_eq!(led[..], [seq, 1, 255, 0, 0, 128, 0, 0], "{seen:02x?}");
    let (ack_id, ack) = seen.last().unwrap();
    assert_eq!(*ack_id, 0x0700_0111);
    assert_eq!(
        ack[..],
        [0x0D, seq, 0, 0],
        "Ack of that LedSet, Ok: {seen:02x?}"
    );
    assert_eq!(seen.len(), 2, "one LedSet, one Ack: {seen:02x?}");
    let a = rig.island.actuators(id("111")).await.unwrap();
    assert_eq!(a.led.duty, Rgb::new(128, 0, 0), "{a:?}");
    rig.shutdown().await;
}
