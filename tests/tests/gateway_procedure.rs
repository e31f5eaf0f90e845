//! Guided procedures end to end over vcan + Mosquitto with the real gateway and `sim-node`: the
//! sample procedure file, run as `ihex-provision procedure run` runs it, completed by three
//! dockings and undockings of the simulated island (a wrong docking reported and ignored, the
//! steps' elements lit and cleared, a second client refused meanwhile); a step that times out; a
//! cancel; an element lost mid-step.
#![cfg(feature = "vcan")]

mod gateway_support;

use std::time::Duration;

use gateway_support::{id, Client, Rig, WAIT};
use ihex_proto::Rgb;
use ihex_provision::{can::Topics, mqtt::Broker, procedure};
use serde_json::Value;

const SAMPLE: &str = include_str!("../../examples/procedures/sample-handover.toml");

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_sample_handover_is_confirmed_by_the_bench() {
    // A step fails when its element is lost: under emulation a stalled VM must not look like that
    // (10 s of missed health checks before `node_lost`).
    let mut rig = Rig::start_with("proc", |o| o.lost_after = Some(50)).await;
    let events = rig.events();
    let commands = rig.gateway.commands();
    let procedures_topic = rig.gateway.config.topics.procedures.clone();
    let mut other = Client::connect(rig.addr, "test-proc-other", std::slice::from_ref(&events));

    // The file, run as the tool runs it: its command is the gateway's, its events followed.
    let request_id = "proc-sample";
    let command = procedure::command_from_toml(SAMPLE, request_id).expect("sample file");
    let broker = Broker::parse(&rig.addr.to_string()).expect("broker address");
    let topics = Topics::new(Some("proc"), "CommandsTopic", "EventsTopic", "ihex/node");
    let runner = tokio::spawn(async move {
        let mut seen = Vec::new();
        let ended = procedure::run(
            &broker,
            &topics,
            &command,
            request_id,
            ihex_tests::time::scaled(Duration::from_secs(120)),
            |e| seen.push(e.name.clone()),
        )
        .await;
        (ended, seen)
    });

    let step = |n: u64, state: &'static str| move |p: &Value| p["step"] == n && p["state"] == state;
    rig.client
        .expect_event(&events, "procedure_started", |p| {
            p["request_id"] == request_id
        })
        .await;
    rig.client
        .expect_event(&events, "procedure_step", step(1, "started"))
        .await;
    rig.client
        .expect("the procedures document at step 1", |m| {
            m.topic == procedures_topic && m.json()["procedures"][0]["step"] == 1
        })
        .await;
    // Step 1 lights 112 (green, blinking).
    let lit = wait_for_led(&rig, "112", Rgb::new(0, 255, 0)).await;
    assert!(lit, "112 lit for step 1");

    // A second client cannot recolour the element the procedure holds.
    other
        .publish(
            &commands,
            r#"{"cmd":"led","node":"112","color":"red","request_id":"o1"}"#,
        )
        .await;
    let refused = other
        .expect_event(&events, "command_rejected", |p| p["request_id"] == "o1")
        .await;
    assert!(
        refused["payload"]["reason"]
            .as_str()
            .unwrap()
            .starts_with("112 is leased by procedure 1 (sample-handover)"),
        "{refused}"
    );

    // The wrong docking (111 instead of 112): reported, not taken.
    rig.island.dock(id("3"), id("111"), 1).await.expect("dock");
    rig.client
        .expect_event(&events, "new_connection", |p| {
            p["n-1"]["id"] == "111" && p["n"]["id"] == "3"
        })
        .await;
    let mismatch = rig
        .client
        .expect_event(&events, "procedure_mismatch", |p| p["step"] == 1)
        .await;
    assert_eq!(mismatch["payload"]["connection"]["n-1"]["id"], "111");
    rig.island.undock(id("3")).await.expect("undock");
    rig.client
        .expect_event(&events, "connection_removed", |p| p["n"]["id"] == "3")
        .await;

    // The right one: step 1 done with the docking as evidence; step 2 waits for the undocking.
    rig.island.dock(id("3"), id("112"), 2).await.expect("dock");
    let done = rig
        .client
        .expect_event(&events, "procedure_step", step(1, "done"))
        .await;
    assert_eq!(
        done["payload"]["evidence"]["connection"],
        serde_json::json!({"n": {"id": "3", "port": 1}, "n-1": {"id": "112", "port": 2}})
    );
    rig.client
        .expect_event(&events, "procedure_step", step(2, "started"))
        .await;
    rig.island.undock(id("3")).await.expect("undock");
    rig.client
        .expect_event(&events, "procedure_step", step(2, "done"))
        .await;
    rig.client
        .expect_event(&events, "procedure_step", step(3, "started"))
        .await;
    rig.island.dock(id("3"), id("111"), 1).await.expect("dock");
    let ended = rig
        .client
        .expect_event(&events, "procedure_ended", |p| {
            p["request_id"] == request_id
        })
        .await;
    assert_eq!(ended["payload"]["outcome"], "done", "{ended}");
    assert_eq!(ended["payload"]["steps_done"], 3);

    let (answer, seen) = ihex_tests::within_or_panic(WAIT, "procedure run", runner)
        .await
        .expect("runner task");
    let answer = answer.expect("procedure run");
    assert_eq!(answer.payload["outcome"], "done");
    assert_eq!(seen.first().map(String::as_str), Some("procedure_started"));
    assert_eq!(seen.last().map(String::as_str), Some("procedure_ended"));
    assert_eq!(
        seen.iter().filter(|n| *n == "procedure_mismatch").count(),
        1
    );

    // Lights off, lease and document cleared, the element free again.
    assert!(
        wait_for_led(&rig, "111", Rgb::new(0, 0, 0)).await,
        "111 cleared"
    );
    rig.client
        .expect("the emptied procedures document", |m| {
            m.topic == procedures_topic && m.json()["procedures"] == serde_json::json!([])
        })
        .await;
    other
        .publish(
            &commands,
            r#"{"cmd":"led","node":"112","color":"red","request_id":"o2"}"#,
        )
        .await;
    let r = other
        .expect_event(&events, "command_result", |p| p["request_id"] == "o2")
        .await;
    assert_eq!(r["payload"]["result"], "ok", "{r}");
    rig.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_times_out_is_cancelled_or_fails_when_its_element_is_lost() {
    // Tolerant of a stalled VM (2 s of missed health checks), quick enough for the lost step.
    let mut rig = Rig::start_with("proc2", |o| o.lost_after = Some(10)).await;
    let events = rig.events();

    // A timeout.
    rig.command(
        r#"{"cmd":"procedure","name":"t","request_id":"t1","steps":[{"node":"112","wait":"docked","color":"blue","timeout_s":1}]}"#,
    )
    .await;
    rig.client
        .expect_event(&events, "procedure_started", |p| p["request_id"] == "t1")
        .await;
    let ended = rig
        .client
        .expect_event(&events, "procedure_ended", |p| p["request_id"] == "t1")
        .await;
    assert_eq!(ended["payload"]["outcome"], "timed_out", "{ended}");
    assert!(
        wait_for_led(&rig, "112", Rgb::new(0, 0, 0)).await,
        "112 cleared"
    );

    // A cancel: answered by procedure_ended with the cancel's request id.
    rig.command(
        r#"{"cmd":"procedure","name":"c","request_id":"c1","steps":[{"node":"112","wait":"docked","color":"blue","timeout_s":600}]}"#,
    )
    .await;
    let started = rig
        .client
        .expect_event(&events, "procedure_started", |p| p["request_id"] == "c1")
        .await;
    let pid = started["payload"]["id"].as_u64().unwrap();
    assert!(
        wait_for_led(&rig, "112", Rgb::new(0, 0, 255)).await,
        "112 lit"
    );
    rig.command(&format!(
        r#"{{"cmd":"procedure_cancel","id":{pid},"request_id":"c2"}}"#
    ))
    .await;
    let ended = rig
        .client
        .expect_event(&events, "procedure_ended", |p| p["request_id"] == "c2")
        .await;
    assert_eq!(ended["payload"]["outcome"], "cancelled", "{ended}");
    assert!(
        wait_for_led(&rig, "112", Rgb::new(0, 0, 0)).await,
        "112 cleared"
    );

    // The element waited on goes off the bus mid-step: the step and the procedure fail.
    rig.command(
        r#"{"cmd":"procedure","name":"l","request_id":"l1","steps":[{"node":"112","wait":"docked","color":"blue","timeout_s":600}]}"#,
    )
    .await;
    rig.client
        .expect_event(&events, "procedure_step", |p| {
            p["state"] == "started" && p["name"] == "l"
        })
        .await;
    rig.island
        .set_on_bus(id("112"), false)
        .await
        .expect("off bus");
    let failed = rig
        .client
        .expect_event(&events, "procedure_step", |p| p["state"] == "failed")
        .await;
    assert_eq!(
        failed["payload"]["reason"],
        "element 112 was lost (it stopped answering health checks)"
    );
    let ended = rig
        .client
        .expect_event(&events, "procedure_ended", |p| p["request_id"] == "l1")
        .await;
    assert_eq!(ended["payload"]["outcome"], "failed", "{ended}");
    rig.island
        .set_on_bus(id("112"), true)
        .await
        .expect("on bus");
    rig.shutdown().await;
}

/// Waits (a while) until `node`'s LED shows `color` (black: off); false if it never does.
async fn wait_for_led(rig: &Rig, node: &str, color: Rgb) -> bool {
    let deadline = tokio::time::Instant::now() + ihex_tests::time::scaled(Duration::from_secs(5));
    loop {
        let a = rig.island.actuators(id(node)).await.expect("actuators");
        if a.led.duty == color {
            return true;
        }
        if tokio::time::Instant::now() > deadline {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
