//! Home Assistant over vcan + Mosquitto: messages shaped as Home Assistant sends them, on the
//! entities' command topics, change the simulated elements and get a `command_result`; the
//! discovery configs on the broker use only keys Home Assistant documents, and come back after a
//! broker restart and when Home Assistant announces itself (`homeassistant/status` = `online`).
#![cfg(feature = "vcan")]

mod gateway_support;

use gateway_support::{id, Client, Rig, Seen};
use ihex_proto::Rgb;
use ihex_sc_core::BuzzerOutput;
use mc_gateway::core::ha::schema::check_device_config;
use mc_gateway::core::ha::{Entity, HaTopic};
use mc_gateway::core::Topic;
use serde_json::{json, Value};

/// Publishes `payload` on `<island>/ihex/ha/<node>/<entity>/set` and waits for the
/// `command_result` of command `cmd` to `node` (Home Assistant's commands carry the request id
/// `homeassistant`).
async fn ha_command(rig: &mut Rig, node: &str, entity: &str, payload: &str, cmd: &str) -> Value {
    let topic = rig
        .gateway
        .config
        .topics
        .ha
        .command(id(node), entity_of(entity));
    rig.client.publish(&topic, payload).await;
    let events = rig.events();
    let r = rig
        .client
        .expect_event(&events, "command_result", |p| {
            p["request_id"] == "homeassistant" && p["cmd"] == cmd && p["node"] == node
        })
        .await;
    assert_eq!(r["payload"]["result"], "ok", "{r}");
    r
}

fn entity_of(name: &str) -> Entity {
    Entity::ALL
        .into_iter()
        .find(|e| e.name() == name)
        .expect("entity")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn home_assistant_commands_change_the_elements() {
    let mut rig = Rig::start("hass").await;

    // The light: red at half brightness, as Home Assistant's JSON schema sends it.
    let start = rig.client.log.len();
    ha_command(
        &mut rig,
        "111",
        "led",
        r#"{"state":"ON","color":{"r":255,"g":0,"b":0},"brightness":128}"#,
        "led",
    )
    .await;
    let a = rig.island.actuators(id("111")).await.unwrap();
    assert_eq!(a.led.duty, Rgb::new(128, 0, 0), "red at half brightness");
    assert_eq!(a.led.blink, None);
    // Its state, in the shape Home Assistant reads, retained on the light's state topic.
    let light = rig
        .gateway
        .config
        .topics
        .resolve(Topic::Ha(HaTopic::LightState(id("111"))));
    // Before or after the command's result: the state and the answer are separate publications.
    let red = |m: &Seen| {
        m.topic == light
            && m.json()
                == json!({"state": "ON", "color_mode": "rgb", "color": {"r": 255, "g": 0, "b": 0},
                          "brightness": 128, "effect": "off"})
    };
    if !rig.client.log[start..].iter().any(&red) {
        rig.client.expect("the light's state", red).await;
    }

    // The switch (relay of a static element).
    ha_command(&mut rig, "112", "relay", "ON", "power").await;
    assert!(rig.island.actuators(id("112")).await.unwrap().relay);
    ha_command(&mut rig, "112", "relay", "OFF", "power").await;
    assert!(!rig.island.actuators(id("112")).await.unwrap().relay);

    // The siren: a beeping tone for 3 s is a pattern of 3 beeps.
    ha_command(
        &mut rig,
        "2",
        "buzzer",
        r#"{"state":"ON","tone":"beep","duration":3}"#,
        "buzzer",
    )
    .await;
    assert!(matches!(
        rig.island.actuators(id("2")).await.unwrap().buzzer,
        BuzzerOutput::Pattern { freq_hz: 2000, .. }
    ));
    ha_command(&mut rig, "2", "buzzer", r#"{"state":"OFF"}"#, "buzzer").await;
    assert_eq!(
        rig.island.actuators(id("2")).await.unwrap().buzzer,
        BuzzerOutput::Off
    );

    // The identify button: the dark element 112 blinks.
    ha_command(&mut rig, "112", "identify", "PRESS", "identify").await;
    let a = rig.island.actuators(id("112")).await.unwrap();
    assert!(
        a.led.blink.is_some() && a.led.duty != Rgb::new(0, 0, 0),
        "{a:?}"
    );

    // A bad one is refused like a JSON command, and nothing changes.
    let topic = rig
        .gateway
        .config
        .topics
        .ha
        .command(id("111"), entity_of("led"));
    rig.client
        .publish(&topic, r#"{"state":"ON","brightness":300}"#)
        .await;
    let events = rig.events();
    let r = rig
        .client
        .expect_event(&events, "command_rejected", |p| {
            p["request_id"] == "homeassistant"
        })
        .await;
    assert_eq!(
        r["payload"]["reason"],
        "light: `brightness` must be an integer 0 to 255; got 300"
    );
    assert_eq!(
        rig.island.actuators(id("111")).await.unwrap().led.duty,
        Rgb::new(128, 0, 0)
    );
    rig.shutdown().await;
}

/// Waits for the discovery config of every device of the demo island on `client` (the gateway,
/// 111, 112 and 2; the free mobile element 3 is not powered, so not on the bus) (`live`: sent
/// while subscribed, not a retained copy), checks each against Home Assistant's documented keys,
/// and returns them by topic.
async fn expect_configs(
    client: &mut Client,
    rig: &Rig,
    live: bool,
    what: &str,
) -> Vec<(String, Value)> {
    let topics = &rig.gateway.config.topics;
    let mut wanted = vec![topics.resolve(Topic::Ha(HaTopic::GatewayConfig))];
    for n in ["111", "112", "2"] {
        wanted.push(topics.resolve(Topic::Ha(HaTopic::DeviceConfig(id(n)))));
    }
    let mut got: Vec<(String, Value)> = Vec::new();
    while got.len() < wanted.len() {
        let m = client
            .expect(&format!("{what}: {wanted:?}"), |m| {
                wanted.contains(&m.topic)
                    && !got.iter().any(|(t, _)| *t == m.topic)
                    && (!live || !m.retain)
            })
            .await;
        let config = m.json();
        let problems = check_device_config(&config);
        assert!(
            problems.is_empty(),
            "{}: {problems:#?}\n{config:#}",
            m.topic
        );
        got.push((m.topic, config));
    }
    // In the order asked for.
    got.sort_by_key(|(t, _)| wanted.iter().position(|w| w == t));
    got
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn discovery_comes_back_after_a_broker_restart_and_when_home_assistant_starts() {
    let mut rig = Rig::start("hass-restart").await;
    let prefix = format!("{}/#", rig.gateway.config.topics.ha.discovery_prefix);
    let mut hass = Client::connect(rig.addr, "home-assistant", std::slice::from_ref(&prefix));
    let configs = expect_configs(&mut hass, &rig, false, "configs").await;
    let static_111 = &configs[1].1;
    assert!(static_111["components"]["relay"].is_object());
    assert!(
        configs[3].1["components"]["relay"].is_null(),
        "mobile 2 has no relay"
    );

    // Home Assistant restarts and announces itself: every config again.
    let status = rig.gateway.config.topics.ha.status.clone();
    hass.publish(&status, "online").await;
    expect_configs(
        &mut hass,
        &rig,
        true,
        "configs after homeassistant/status online",
    )
    .await;

    // The broker restarts and forgets every retained message: the gateway publishes them again.
    rig.broker().stop();
    rig.broker().restart().expect("restart mosquitto");
    let mut fresh = Client::connect(rig.addr, "home-assistant-2", &[prefix]);
    expect_configs(
        &mut fresh,
        &rig,
        false,
        "configs after the broker restarted",
    )
    .await;
    rig.shutdown().await;
}
