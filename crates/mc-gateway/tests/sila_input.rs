//! The SiLA server against bad and heavy input, with a gRPC client from Rust (tonic) on the demo
//! gateway in-process: a malformed message, an unknown method, a thousand concurrent subscriptions,
//! and clients vanishing mid-stream — each answered or dropped cleanly while the server keeps serving
//! everyone else. (The reference client's tour is `tests/sila.rs`.)
#![cfg(all(feature = "demo", feature = "sila"))]

use std::time::Duration;

use ihex_tests::free_port;
use mc_gateway::{
    config::Options,
    sila::proto::{
        cancel_controller::{self as cancel_pb, cancel_controller_client::CancelControllerClient},
        firmware_update::{self as fw_pb, firmware_update_client::FirmwareUpdateClient},
        framework,
        island_control::{self as pb, island_control_client::IslandControlClient},
    },
    CancellationToken, Config,
};
use tonic::{codegen::http::uri::PathAndQuery, transport::Channel};

const WAIT: Duration = Duration::from_secs(20);

/// The demo gateway with a plaintext SiLA server on loopback (not announced); its SiLA port.
async fn demo(stop: &CancellationToken) -> u16 {
    let sila = free_port();
    let cli = Options {
        broker_listen: Some(format!("127.0.0.1:{}", free_port()).parse().unwrap()),
        http: Some("off".into()),
        sila: Some(format!("127.0.0.1:{sila}")),
        sila_insecure: Some(true),
        sila_announce: Some("off".into()),
        health_period_ms: Some(200),
        log_dir: Some("-".into()),
        ..Options::default()
    };
    let config = Config::resolve(cli, Options::default()).unwrap();
    tokio::spawn(mc_gateway::run(config, stop.clone()));
    sila
}

/// A new connection to the server (retried until it listens).
async fn channel(port: u16) -> Channel {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let c = Channel::from_shared(format!("http://127.0.0.1:{port}"))
            .unwrap()
            .connect()
            .await;
        match c {
            Ok(c) => return c,
            Err(e) if tokio::time::Instant::now() > deadline => panic!("no SiLA server: {e}"),
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}

/// The elements, once the island has booted (111 online).
async fn elements(c: &mut IslandControlClient<Channel>) -> Vec<String> {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let r = c.get_elements(pb::GetElementsParameters {}).await.unwrap();
        let ids: Vec<String> = r
            .into_inner()
            .elements
            .into_iter()
            .filter_map(|e| e.element_id.map(|s| s.value))
            .collect();
        if ids.iter().any(|i| i == "111") {
            return ids;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the island never booted"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn text(v: &str) -> Option<framework::String> {
    Some(framework::String { value: v.into() })
}

fn int(value: i64) -> Option<framework::Integer> {
    Some(framework::Integer { value })
}

fn light(element: &str, brightness: i64) -> pb::SetLightParameters {
    pb::SetLightParameters {
        element_id: text(element),
        color: text("blue"),
        brightness: int(brightness),
        blink_period: int(0),
        blink_duty: int(50),
    }
}

/// The `SiLAError` a failed call carries (base64 in the status message).
fn sila_error(status: &tonic::Status) -> framework::si_la_error::Error {
    use base64::Engine as _;
    use prost::Message as _;
    assert_eq!(status.code(), tonic::Code::Aborted, "{status:?}");
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(status.message())
        .expect("base64");
    framework::SiLaError::decode(&bytes[..])
        .expect("a SiLAError")
        .error
        .expect("with an error")
}

/// Calls `path` with `msg` (any message: the server decodes it as its own type).
async fn raw_call<M: prost::Message + Default + 'static>(
    ch: Channel,
    path: &'static str,
    msg: M,
) -> Result<pb::SetLightResponses, tonic::Status> {
    let mut grpc = tonic::client::Grpc::new(ch);
    grpc.ready().await.unwrap();
    grpc.unary(
        tonic::Request::new(msg),
        PathAndQuery::from_static(path),
        tonic_prost::ProstCodec::<M, pb::SetLightResponses>::default(),
    )
    .await
    .map(tonic::Response::into_inner)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_is_answered_and_the_server_keeps_serving() {
    let stop = CancellationToken::new();
    let port = demo(&stop).await;
    let ch = channel(port).await;
    let mut c = IslandControlClient::new(ch.clone());
    elements(&mut c).await;

    // A message that is not the method's: the bytes of a SiLA String where SetLight's parameters
    // are expected do not decode.
    let garbage = framework::String {
        value: "\u{7f}not a SetLight".into(),
    };
    let e = raw_call(
        ch.clone(),
        "/sila2.de.ihex.bench.islandcontrol.v1.IslandControl/SetLight",
        garbage,
    )
    .await
    .unwrap_err();
    assert_eq!(e.code(), tonic::Code::Internal, "{e:?}");
    // Unknown command and unknown feature.
    for path in [
        "/sila2.de.ihex.bench.islandcontrol.v1.IslandControl/Explode",
        "/sila2.de.ihex.bench.nothing.v1.Nothing/SetLight",
    ] {
        let e = raw_call(ch.clone(), path, light("111", 50))
            .await
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unimplemented, "{path}: {e:?}");
    }
    // A missing parameter and an out-of-range one: validation errors naming them.
    let mut missing = light("111", 50);
    missing.color = None;
    let e = c.set_light(missing).await.unwrap_err();
    match sila_error(&e) {
        framework::si_la_error::Error::ValidationError(v) => assert_eq!(
            v.parameter,
            "de.ihex/bench/IslandControl/v1/Command/SetLight/Parameter/Color"
        ),
        other => panic!("{other:?}"),
    }
    let e = c.set_light(light("111", -1)).await.unwrap_err();
    match sila_error(&e) {
        framework::si_la_error::Error::ValidationError(v) => {
            assert!(v.parameter.ends_with("/Parameter/Brightness"), "{v:?}");
            assert_eq!(v.message, "Brightness must be 0 to 100 percent; got -1");
        }
        other => panic!("{other:?}"),
    }
    // An unknown element: the defined execution error.
    let e = c.set_light(light("5", 50)).await.unwrap_err();
    match sila_error(&e) {
        framework::si_la_error::Error::DefinedExecutionError(d) => assert_eq!(
            d.error_identifier,
            "de.ihex/bench/IslandControl/v1/DefinedExecutionError/UnknownElement"
        ),
        other => panic!("{other:?}"),
    }
    // FirmwareUpdate: a missing parameter and an image name that is a path (the reference client
    // checks the pattern itself; the server does too), then executions that do not exist.
    let mut fw = FirmwareUpdateClient::new(ch.clone());
    let update = |image: &str, elements: Option<&str>| fw_pb::UpdateFirmwareParameters {
        image: text(image),
        elements: elements.and_then(text),
    };
    for (params, parameter) in [
        (update("a.img", None), "Elements"),
        (update("../a.img", Some("111")), "Image"),
    ] {
        let e = fw.update_firmware(params).await.unwrap_err();
        match sila_error(&e) {
            framework::si_la_error::Error::ValidationError(v) => assert_eq!(
                v.parameter,
                format!(
                    "de.ihex/bench/FirmwareUpdate/v1/Command/UpdateFirmware/Parameter/{parameter}"
                )
            ),
            other => panic!("{other:?}"),
        }
    }
    let nobody = framework::CommandExecutionUuid {
        value: "00000000-0000-4000-8000-000000000000".into(),
    };
    let invalid_uuid = |e: &tonic::Status| match sila_error(e) {
        framework::si_la_error::Error::FrameworkError(f) => assert_eq!(
            f.error_type,
            framework::framework_error::ErrorType::InvalidCommandExecutionUuid as i32
        ),
        other => panic!("{other:?}"),
    };
    invalid_uuid(&fw.update_firmware_result(nobody.clone()).await.unwrap_err());
    invalid_uuid(&fw.update_firmware_info(nobody.clone()).await.unwrap_err());
    invalid_uuid(
        &fw.update_firmware_intermediate(nobody.clone())
            .await
            .unwrap_err(),
    );
    let e = CancelControllerClient::new(ch.clone())
        .cancel_command(cancel_pb::CancelCommandParameters {
            command_execution_uuid: Some(cancel_pb::DataTypeUuid {
                uuid: text(&nobody.value),
            }),
        })
        .await
        .unwrap_err();
    match sila_error(&e) {
        framework::si_la_error::Error::DefinedExecutionError(d) => assert_eq!(
            d.error_identifier,
            "org.silastandard/core.commands/CancelController/v1/DefinedExecutionError/InvalidCommandExecutionUUID"
        ),
        other => panic!("{other:?}"),
    }
    // After all that, a good command still works.
    c.set_light(light("111", 50)).await.expect("served");
    stop.cancel();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thousand_subscriptions_and_vanishing_clients_disturb_no_one() {
    let stop = CancellationToken::new();
    let port = demo(&stop).await;
    let mut c = IslandControlClient::new(channel(port).await);
    elements(&mut c).await;

    // 1,000 subscriptions on 10 connections, each of which gets its first value.
    let mut streams = Vec::new();
    for _ in 0..10 {
        let ch = channel(port).await;
        for _ in 0..100 {
            let mut sc = IslandControlClient::new(ch.clone());
            let mut s = sc
                .subscribe_element_states(pb::SubscribeElementStatesParameters {})
                .await
                .expect("subscribed")
                .into_inner();
            let first = tokio::time::timeout(WAIT, s.message())
                .await
                .expect("a first value in time")
                .unwrap()
                .expect("a value");
            assert!(!first.element_states.is_empty());
            streams.push(s);
        }
    }
    // None of them reads on: the gateway still answers another client at once.
    let t = tokio::time::Instant::now();
    c.set_light(light("111", 20)).await.expect("served");
    assert!(t.elapsed() < WAIT);
    // Every subscriber is dropped mid-stream (the clients vanish); the server carries on.
    drop(streams);
    let mut docks = c
        .subscribe_dockings(pb::SubscribeDockingsParameters {})
        .await
        .unwrap()
        .into_inner();
    let now = tokio::time::timeout(WAIT, docks.message())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(!now.dockings.is_empty(), "2 is docked on 111 in the demo");
    c.set_light(light("111", 80)).await.expect("still served");
    stop.cancel();
}
