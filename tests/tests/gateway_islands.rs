//! Two gateways on two buses with different island names share one broker and never act on each
//! other's commands.
#![cfg(feature = "vcan")]

mod gateway_support;

use gateway_support::{id, Rig};
use ihex_proto::Rgb;
use ihex_sc_core::BuzzerOutput;
use ihex_tests::broker::Mosquitto;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_islands_share_one_broker_without_crosstalk() {
    let broker = Mosquitto::start().expect("mosquitto");
    let addr = broker.addr();
    let mut a = Rig::start_on(broker, "island-a").await;
    let mut b = Rig::start_at(addr, "island-b").await;

    let off = Rgb::new(0, 0, 0);
    a.command_ok(r#"{"cmd":"led","node":"111","color":"red""#, "a1")
        .await;
    assert_eq!(
        a.island.actuators(id("111")).await.unwrap().led.duty,
        Rgb::new(255, 0, 0)
    );
    assert_eq!(
        b.island.actuators(id("111")).await.unwrap().led.duty,
        off,
        "b acted on a's command"
    );
    b.command_ok(r#"{"cmd":"buzzer","node":"111","mode":"on""#, "b1")
        .await;
    assert_ne!(
        b.island.actuators(id("111")).await.unwrap().buzzer,
        BuzzerOutput::Off
    );
    assert_eq!(
        a.island.actuators(id("111")).await.unwrap().buzzer,
        BuzzerOutput::Off,
        "a acted on b's command"
    );
    // Commands to "all" stay on their island too.
    b.command_ok(r#"{"cmd":"led","node":"all","color":"blue""#, "b2")
        .await;
    assert_eq!(
        a.island.actuators(id("111")).await.unwrap().led.duty,
        Rgb::new(255, 0, 0)
    );

    // Each client subscribed to its own island's `#` only saw its own island.
    for (rig, own, other) in [
        (&mut a, "island-a/", "island-b/"),
        (&mut b, "island-b/", "island-a/"),
    ] {
        let seen = rig.client.drain();
        assert!(
            seen.iter().all(|m| m.topic.starts_with(own)),
            "foreign topic under {own}"
        );
        let answered_other = seen.iter().any(|m| {
            let r = &m.json()["payload"]["request_id"];
            if own == "island-a/" {
                r == "b1" || r == "b2"
            } else {
                r == "a1"
            }
        });
        assert!(!answered_other, "{own} answered a command of {other}");
    }
    b.shutdown().await;
    a.shutdown().await;
}
