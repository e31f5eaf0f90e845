//! `mc-gateway doctor` on real SocketCAN (vcan in the microVM): an interface that is down, a bus
//! with no node, error frames on the bus, a node on an older protocol (a test node written with
//! `ihex-proto` that knows only 1.1's messages), and a healthy island (sim-node) — each through
//! `doctor::run`, the function the command runs. The healthy island is checked with a Mosquitto
//! started in the VM, so its report is complete (broker checks included) and passes.
#![cfg(feature = "vcan")]

use std::{net::SocketAddr, time::Duration};

use ihex_proto::{
    FirmwareVersion, HealthFlags, HealthReply, Message, NodeId, Packet, StateParts, StateReport,
};
use ihex_tests::{broker::Mosquitto, can, time::scaled};
use mc_gateway::{
    config::Broker,
    doctor::{self, DoctorOptions, Report, Status},
    Config,
};
use sim_node::{Island, IslandDesc, Link};
use socketcan::{CanErrorFrame, CanFrame};

/// The gateway's configuration on `iface`: with `broker` when given, else the embedded broker
/// (whose check the doctor skips).
fn config(iface: &str, broker: Option<SocketAddr>) -> Config {
    let mut c = Config::lab(
        &broker.map_or("127.0.0.1:1".into(), |a| a.to_string()),
        iface,
    )
    .expect("config");
    if broker.is_none() {
        c.mqtt.broker = Broker::Embedded {
            listen: "127.0.0.1:1".parse().unwrap(),
        };
    }
    c
}

fn options() -> DoctorOptions {
    DoctorOptions {
        listen: scaled(Duration::from_millis(1500)),
        ..DoctorOptions::default()
    }
}

async fn doctor(iface: &str) -> Report {
    doctor::run(&config(iface, None), &options()).await
}

fn status(r: &Report, check: &str) -> Status {
    r.get(check)
        .unwrap_or_else(|| panic!("no {check} in {r:#?}"))
        .status
}

#[tokio::test]
async fn interface_down_fails_and_the_bus_checks_are_skipped() {
    let iface = can::lease();
    can::set_link(&iface, false);
    let r = doctor(&iface).await;
    can::set_link(&iface, true);
    let v = r.get("can.interface").unwrap();
    assert_eq!(v.status, Status::Fail, "{r:#?}");
    assert!(v.found.contains("is down"), "{}", v.found);
    assert!(
        v.action.as_deref().unwrap().contains("ip link set"),
        "{v:?}"
    );
    assert_eq!(status(&r, "bus.traffic"), Status::Skip);
    assert_eq!(status(&r, "island.nodes"), Status::Skip);
    assert!(!r.ok);
}

#[tokio::test]
async fn a_missing_interface_fails() {
    let r = doctor("vcan-nosuch").await;
    let v = r.get("can.interface").unwrap();
    assert_eq!(v.status, Status::Fail, "{r:#?}");
    assert!(v.found.contains("no interface vcan-nosuch"), "{}", v.found);
}

#[tokio::test]
async fn no_nodes_fails_traffic_and_island_but_vcan_has_no_bitrate_to_fail() {
    let iface = can::lease();
    let r = doctor(&iface).await;
    assert_eq!(status(&r, "can.interface"), Status::Pass, "{r:#?}");
    let bitrate = r.get("can.bitrate").unwrap();
    assert_eq!(bitrate.status, Status::Skip);
    assert_eq!(bitrate.found, "virtual CAN: no bitrate");
    let traffic = r.get("bus.traffic").unwrap();
    assert_eq!(traffic.status, Status::Fail, "{r:#?}");
    assert!(traffic.found.starts_with("no frame"), "{}", traffic.found);
    let island = r.get("island.nodes").unwrap();
    assert_eq!(island.status, Status::Fail, "{r:#?}");
    assert!(
        island.found.starts_with("no node answered"),
        "{}",
        island.found
    );
    assert!(!r.ok);
}

#[tokio::test]
async fn error_frames_on_the_bus_are_named_with_their_usual_cause() {
    let iface = can::lease();
    let sock = socketcan::tokio::CanSocket::open(&iface).expect("open");
    let stop = mc_gateway::CancellationToken::new();
    // Another station's controller reporting "no ACK" every 50 ms while the doctor listens.
    let writer = {
        let stop = stop.clone();
        tokio::spawn(async move {
            while !stop.is_cancelled() {
                let f = CanFrame::Error(CanErrorFrame::new_error(0x20, &[0; 8]).unwrap());
                let _ = sock.write_frame(f).await;
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        })
    };
    let r = doctor(&iface).await;
    stop.cancel();
    writer.await.unwrap();
    let v = r.get("bus.traffic").unwrap();
    assert_eq!(v.status, Status::Fail, "{r:#?}");
    assert!(v.found.contains("no_ack"), "{}", v.found);
    let action = v.action.as_deref().unwrap();
    assert!(
        action.contains("no other node") && action.contains("termination"),
        "{action}"
    );
}

/// A node of protocol 1.1 at `id`: answers health checks and state queries (firmware, UID), and
/// ignores `FwQuery`, which 1.1 does not know.
fn old_node(
    iface: &str,
    id: NodeId,
    stop: mc_gateway::CancellationToken,
) -> tokio::task::JoinHandle<()> {
    let sock = socketcan::tokio::CanSocket::open(iface).expect("open");
    tokio::spawn(async move {
        loop {
            let frame = tokio::select! {
                _ = stop.cancelled() => return,
                f = sock.read_frame() => f.expect("read"),
            };
            let Ok(p) = Packet::from_frame(&frame) else {
                continue;
            };
            if p.src != NodeId::GATEWAY || !(p.dest == id || p.dest == NodeId::BROADCAST) {
                continue;
            }
            let replies: Vec<Message> = match p.msg {
                Message::HealthCheck { seq } => vec![Message::HealthReply(HealthReply {
                    seq,
                    flags: HealthFlags(0),
                    loops: 0,
                    tec: 0,
                    rec: 0,
                    uptime_s: 42,
                })],
                Message::StateQuery { seq, parts } if parts.0 & StateParts::IDENTITY != 0 => vec![
                    Message::StateReport(StateReport::Firmware {
                        version: FirmwareVersion::new(0, 1, 0),
                        trial: false,
                    }),
                    Message::StateReport(StateReport::End {
                        seq,
                        parts: StateParts(StateParts::IDENTITY),
                        count: 1,
                    }),
                ],
                _ => vec![],
            };
            for m in replies {
                let f: CanFrame = Packet::report(id, m).to_frame().expect("frame");
                sock.write_frame(f).await.expect("write");
            }
        }
    })
}

#[tokio::test]
async fn a_node_on_an_older_protocol_is_named() {
    let iface = can::lease();
    let stop = mc_gateway::CancellationToken::new();
    let node = old_node(&iface, NodeId::new(0x123).unwrap(), stop.clone());
    let r = doctor(&iface).await;
    stop.cancel();
    node.await.unwrap();
    assert_eq!(status(&r, "bus.traffic"), Status::Pass, "{r:#?}");
    let v = r.get("island.nodes").unwrap();
    assert_eq!(v.status, Status::Fail, "{r:#?}");
    assert!(
        v.found.contains("123 (firmware 0.1.0, protocol 1.1"),
        "{}",
        v.found
    );
    let action = v.action.as_deref().unwrap();
    assert!(
        action.contains("123 (1.1") && action.contains("flash"),
        "{action}"
    );
}

#[tokio::test]
async fn a_healthy_island_passes() {
    let iface = can::lease();
    let desc = IslandDesc::parse(
        "[[static]]\nid = \"111\"\nuid = \"300047001251333933383437\"\nfirmware = \"0.4.2\"\n\
         [[static]]\nid = \"112\"\n",
    )
    .expect("island");
    let island = Island::start(&desc, Link::socketcan(&iface)).expect("sim-node island");
    // Let every virtual node open its socket before the doctor asks.
    tokio::time::sleep(scaled(Duration::from_millis(300))).await;
    let broker = Mosquitto::start().expect("mosquitto");
    let r = doctor::run(&config(&iface, Some(broker.addr())), &options()).await;
    drop(island);
    let v = r.get("island.nodes").unwrap();
    assert_eq!(v.status, Status::Pass, "{r:#?}");
    assert!(v.found.starts_with("2 node(s) answered"), "{}", v.found);
    assert!(
        v.found.contains("111 (firmware 0.4.2, ")
            && v.found
                .contains("protocol 1.3, uid 300047001251333933383437"),
        "{}",
        v.found
    );
    assert_eq!(status(&r, "bus.traffic"), Status::Pass, "{r:#?}");
    assert_eq!(status(&r, "can.interface"), Status::Pass);
    assert_eq!(status(&r, "broker.connect"), Status::Pass, "{r:#?}");
    assert_eq!(status(&r, "broker.topics"), Status::Pass, "{r:#?}");
    // Nothing failed: the boot file is absent in the VM (skipped), vcan has no bitrate (skipped).
    assert!(r.ok, "{}", r.text());
}
