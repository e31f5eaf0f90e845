//! Island scenarios shared by the in-memory tests (`crates/sim-node/tests/island.rs`) and the
//! SocketCAN tests (`tests/tests/sim_island.rs`, included there by path): the same code runs on a
//! `MemBus` and on a real vcan interface. The test plays the gateway on its own endpoint.
#![allow(dead_code)]

use std::time::Duration;

use ihex_proto::test_util::port;
pub use ihex_proto::test_util::sc_id as id;
use ihex_proto::{
    filter::gateway_filters, AckResult, BootRole, BuzzerCommand, DockPartner, DockState,
    FirmwareVersion, Kind, LedCommand, Message, NodeId, Packet, PowerState, ResetReason, Rgb,
    StateParts, StateReport,
};
use ihex_sc_core::{BuzzerOutput, LedOutput};
use sim_node::{
    link::{LinkRx, LinkTx},
    Island, IslandDesc, IslandEvent, IslandHandle, Link, NodeView,
};

/// Longest wait for one expected frame or state (multiplied by `IHEX_TEST_TIME_SCALE`).
const WAIT: Duration = Duration::from_secs(5);
/// How long "nothing more arrives" is watched for.
const QUIET: Duration = Duration::from_millis(300);

fn scaled(d: Duration) -> Duration {
    let f = std::env::var("IHEX_TEST_TIME_SCALE")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .filter(|f| f.is_finite() && *f > 0.0)
        .unwrap_or(1.0);
    d.mul_f64(f)
}

/// The island every scenario uses: two static hexagons (111 with 6 ports, 112 with 4 and a
/// firmware of its own), a mobile element 2 that docks by its own port 1, a mobile 3, and a
/// factory-fresh static 120.
pub const ISLAND: &str = r#"
[[static]]
id = "111"
ports = 6

[[static]]
id = "112"
ports = 4
firmware = "2.3.4"

[[static]]
id = "120"
unconfigured = true

[[mobile]]
id = "2"
port = 1

[[mobile]]
id = "3"
"#;

/// The test's gateway: an endpoint with the gateway's filters.
pub struct Gateway {
    tx: LinkTx,
    rx: LinkRx,
    /// Frames received but not yet consumed by an expectation.
    backlog: Vec<Packet>,
}

impl Gateway {
    /// Opens the gateway's endpoint (before the island starts, to see the boot-up frames).
    pub fn open(link: &Link) -> Self {
        let (tx, rx) = link.open().expect("open gateway endpoint");
        tx.set_filters(&gateway_filters()).expect("gateway filters");
        Gateway {
            tx,
            rx,
            backlog: Vec::new(),
        }
    }

    /// Sends a command from the gateway.
    pub async fn send(&self, dest: NodeId, msg: Message) {
        self.try_send(dest, msg).await.expect("gateway send");
    }

    /// Sends a command from the gateway; the send may fail (an interface that is down).
    pub async fn try_send(&self, dest: NodeId, msg: Message) -> Result<(), sim_node::LinkError> {
        let frame = Packet::command(dest, msg).to_frame().expect("frame");
        self.tx.send(frame).await
    }

    /// The next packet matching `pred` within `wait` (unscaled), if any; others go to the backlog.
    pub async fn within(
        &mut self,
        wait: Duration,
        mut pred: impl FnMut(&Packet) -> bool,
    ) -> Option<Packet> {
        if let Some(i) = self.backlog.iter().position(&mut pred) {
            return Some(self.backlog.remove(i));
        }
        let until = tokio::time::Instant::now() + wait;
        while let Some(p) = self.next(until).await {
            if pred(&p) {
                return Some(p);
            }
            self.backlog.push(p);
        }
        None
    }

    async fn next(&mut self, until: tokio::time::Instant) -> Option<Packet> {
        let frame = tokio::time::timeout_at(until, self.rx.recv()).await.ok()?;
        let frame = frame.expect("gateway receive");
        match Packet::from_frame(&frame) {
            Ok(p) => Some(p),
            Err(e) => panic!("a virtual node sent an undecodable frame: {e:?} ({frame:?})"),
        }
    }

    /// Waits for a packet matching `pred` (earlier non-matching packets stay in the backlog).
    pub async fn expect(&mut self, what: &str, mut pred: impl FnMut(&Packet) -> bool) -> Packet {
        if let Some(i) = self.backlog.iter().position(&mut pred) {
            return self.backlog.remove(i);
        }
        let until = tokio::time::Instant::now() + scaled(WAIT);
        while let Some(p) = self.next(until).await {
            if pred(&p) {
                return p;
            }
            self.backlog.push(p);
        }
        panic!(
            "gateway did not receive {what} within {:?}; other frames: {:#?}",
            scaled(WAIT),
            self.backlog
        )
    }

    /// Waits for the report `msg` from `src`.
    pub async fn expect_from(&mut self, src: NodeId, msg: Message) -> Packet {
        self.expect(&format!("{msg:?} from {src}"), |p| {
            p.src == src && p.msg == msg
        })
        .await
    }

    /// Asserts that nothing matching `pred` arrives for a while (and nothing is in the backlog).
    pub async fn expect_none(&mut self, what: &str, mut pred: impl FnMut(&Packet) -> bool) {
        if let Some(p) = self.backlog.iter().find(|p| pred(p)) {
            panic!("unexpected {what}: {p:?}");
        }
        let until = tokio::time::Instant::now() + scaled(QUIET);
        while let Some(p) = self.next(until).await {
            assert!(!pred(&p), "unexpected {what}: {p:?}");
            self.backlog.push(p);
        }
    }
}

fn boot_up(role: BootRole, ports: u8) -> Message {
    Message::BootUp {
        version: ihex_proto::PROTOCOL_VERSION,
        role,
        ports,
        reset: ResetReason::PowerOn,
    }
}

fn ack(kind: Kind, seq: u8) -> Message {
    Message::Ack {
        kind,
        seq,
        result: AckResult::Ok,
        detail: 0,
    }
}

/// Polls the island until `node`'s view satisfies `pred`.
pub async fn wait_view(
    island: &IslandHandle,
    node: NodeId,
    what: &str,
    pred: impl Fn(&NodeView) -> bool,
) {
    let until = tokio::time::Instant::now() + scaled(WAIT);
    loop {
        let v = island.view(node).await.expect("view");
        if pred(&v) {
            return;
        }
        if tokio::time::Instant::now() >= until {
            panic!(
                "{node}: {what} did not happen within {:?}; now {v:?}",
                scaled(WAIT)
            );
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Starts the scenario island on `link` with the gateway already listening; waits for the three
/// configured static elements to announce themselves.
pub async fn start(link: &Link, text: &str) -> (Gateway, IslandHandle) {
    let mut gw = Gateway::open(link);
    let desc = IslandDesc::parse(text).expect("island");
    let island = Island::start(&desc, link.clone()).expect("island starts");
    for s in desc.statics.iter().filter(|s| s.configured) {
        gw.expect_from(s.id, boot_up(BootRole::Static, s.ports))
            .await;
    }
    (gw, island)
}

/// Docks 2 on port 3 of 111 and plays the gateway's part until 2 has shaken hands.
pub async fn dock_and_confirm(gw: &mut Gateway, island: &IslandHandle, seq: u8) {
    island.dock(id(2), id(0x111), 3).await.expect("dock");
    gw.expect_from(id(0x111), Message::DockDetected { port: port(3) })
        .await;
    assert!(
        !island.actuators(id(0x111)).await.unwrap().relay,
        "relay waits for the confirmation"
    );
    assert!(
        !island.view(id(2)).await.unwrap().powered,
        "no power before the confirmation"
    );
    gw.send(id(0x111), Message::DockConfirm { seq, port: port(3) })
        .await;
    gw.expect_from(id(0x111), ack(Kind::DockConfirm, seq)).await;
    gw.expect_from(id(2), boot_up(BootRole::Mobile, 6)).await;
    // The mobile docks by its own port 1, which is what it must report.
    gw.expect_from(id(2), Message::Handshake { port: port(1) })
        .await;
}

/// Static elements boot and announce themselves; the unconfigured one and the undocked mobiles
/// stay silent.
pub async fn boot(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    let snap = island.snapshot().await.unwrap();
    let names: Vec<_> = snap.iter().map(|v| v.name).collect();
    assert_eq!(names, [id(0x111), id(0x112), id(0x120), id(2), id(3)]);
    assert!(snap[..3].iter().all(|v| v.powered && v.on_bus));
    assert!(snap[3..].iter().all(|v| !v.powered && v.docked.is_none()));
    assert_eq!(snap[2].node_id, None, "120 is factory-fresh");
    gw.expect_none("a frame from an unconfigured or unpowered node", |p| {
        p.src == NodeId::UNCONFIGURED || p.src == id(2) || p.src == id(3)
    })
    .await;
    island.shutdown().await;
}

/// Dock → DockDetected → (gateway) DockConfirm → relay on → mobile BootUp + Handshake; undock →
/// DockRemoved, relay off, the mobile loses power.
pub async fn dock_and_undock(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    let mut events = island.subscribe();
    dock_and_confirm(&mut gw, &island, 7).await;
    assert!(island.actuators(id(0x111)).await.unwrap().relay);
    let v = island.view(id(2)).await.unwrap();
    assert!(v.powered);
    assert_eq!(v.docked, Some((id(0x111), port(3))));
    assert_eq!(
        v.loops,
        port(1).mask(),
        "the mobile's own loop on port 1 is closed"
    );
    assert_eq!(island.view(id(0x111)).await.unwrap().loops, port(3).mask());

    island.undock(id(2)).await.expect("undock");
    assert!(
        !island.view(id(2)).await.unwrap().powered,
        "power is gone at once"
    );
    gw.expect_from(id(0x111), Message::DockRemoved { port: port(3) })
        .await;
    wait_view(&island, id(0x111), "relay off", |v| !v.actuators.relay).await;
    let v = island.view(id(2)).await.unwrap();
    assert_eq!((v.docked, v.loops), (None, 0));
    assert!(
        island.undock(id(2)).await.is_err(),
        "undocking twice is an error"
    );

    // The event stream told the same story, in order.
    let mut seen = Vec::new();
    while let Ok(e) = events.try_recv() {
        seen.push(e);
    }
    let pos = |want: &IslandEvent| {
        seen.iter()
            .position(|e| e == want)
            .unwrap_or_else(|| panic!("{want:?} not in {seen:#?}"))
    };
    let docked = pos(&IslandEvent::Docked {
        mobile: id(2),
        static_id: id(0x111),
        port: port(3),
    });
    let on = pos(&IslandEvent::Power {
        node: id(2),
        on: true,
    });
    let off = pos(&IslandEvent::Power {
        node: id(2),
        on: false,
    });
    let undocked = pos(&IslandEvent::Undocked {
        mobile: id(2),
        static_id: id(0x111),
        port: port(3),
    });
    assert!(docked < on && on < off && off < undocked, "{seen:#?}");
    island.shutdown().await;
}

/// Docking refusals and impossible requests are errors, not panics.
pub async fn bad_requests(link: Link) {
    let (_gw, island) = start(&link, ISLAND).await;
    assert!(
        island.dock(id(0x111), id(0x112), 0).await.is_err(),
        "a static element cannot dock"
    );
    assert!(
        island.dock(id(2), id(3), 0).await.is_err(),
        "cannot dock on a mobile"
    );
    assert!(
        island.dock(id(2), id(0x112), 4).await.is_err(),
        "112 has ports 0..=3"
    );
    assert!(
        island.dock(id(2), id(0x999), 0).await.is_err(),
        "no such element"
    );
    island.dock(id(2), id(0x112), 0).await.unwrap();
    assert!(
        island.dock(id(3), id(0x112), 0).await.is_err(),
        "port taken"
    );
    assert!(
        island.dock(id(2), id(0x111), 0).await.is_err(),
        "already docked"
    );
    assert!(island.power_cycle(id(3)).await.is_err(), "3 has no power");
    assert!(
        island.uart(id(3), &[0xB0, 0]).await.is_err(),
        "3 has no power"
    );
    // A hand-built description is checked like a parsed one.
    let mut desc = IslandDesc::parse(ISLAND).unwrap();
    desc.mobiles[0].dock = Some((id(0x999), port(0)));
    assert!(
        Island::start(&desc, link.clone()).is_err(),
        "dock on a missing element"
    );
    island.shutdown().await;
}

/// A power cycle is a fresh boot; the static element's mobile loses power with the relay, and the
/// rebooted static element reports the still-closed loop again.
pub async fn power_cycle(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    dock_and_confirm(&mut gw, &island, 1).await;

    island.power_cycle(id(2)).await.expect("cycle the mobile");
    gw.expect_from(id(2), boot_up(BootRole::Mobile, 6)).await;
    gw.expect_from(id(2), Message::Handshake { port: port(1) })
        .await;

    island
        .power_cycle(id(0x111))
        .await
        .expect("cycle the static");
    assert!(
        !island.view(id(2)).await.unwrap().powered,
        "the relay went off with the power"
    );
    gw.expect_from(id(0x111), boot_up(BootRole::Static, 6))
        .await;
    assert!(!island.actuators(id(0x111)).await.unwrap().relay);
    gw.expect_from(id(0x111), Message::DockDetected { port: port(3) })
        .await;
    gw.send(
        id(0x111),
        Message::DockConfirm {
            seq: 2,
            port: port(3),
        },
    )
    .await;
    gw.expect_from(id(0x111), ack(Kind::DockConfirm, 2)).await;
    gw.expect_from(id(2), boot_up(BootRole::Mobile, 6)).await;
    island.shutdown().await;
}

/// A node off the bus keeps running but neither hears nor answers health checks; back on the bus
/// it answers again.
pub async fn off_bus(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    let reply_from = |src: NodeId, seq: u8| {
        move |p: &Packet| p.src == src && matches!(p.msg, Message::HealthReply(h) if h.seq == seq)
    };
    island.set_on_bus(id(0x112), false).await.unwrap();
    assert!(!island.view(id(0x112)).await.unwrap().on_bus);
    gw.send(NodeId::BROADCAST, Message::HealthCheck { seq: 1 })
        .await;
    gw.expect("health reply 1 from 111", reply_from(id(0x111), 1))
        .await;
    gw.send(id(0x112), Message::HealthCheck { seq: 2 }).await;
    gw.expect_none("a health reply from 112 while off the bus", |p| {
        p.src == id(0x112)
    })
    .await;
    assert!(
        island.view(id(0x112)).await.unwrap().powered,
        "it is still running"
    );
    // Nor does it hear commands: this LED command is lost on the way in.
    let red = LedCommand::Steady {
        color: Rgb::new(255, 0, 0),
        brightness: 255,
    };
    gw.send(id(0x112), Message::LedSet { seq: 4, cmd: red })
        .await;
    gw.expect_none("an ack from 112 while off the bus", |p| p.src == id(0x112))
        .await;
    assert_eq!(
        island.actuators(id(0x112)).await.unwrap().led,
        LedOutput::default()
    );

    // Something to say while nobody listens: the dock report goes unacknowledged.
    island.dock(id(3), id(0x112), 1).await.unwrap();
    wait_view(&island, id(0x112), "the dock noticed", |v| {
        v.loops == port(1).mask()
    })
    .await;
    gw.expect_none("a dock report from 112 while off the bus", |p| {
        p.src == id(0x112)
    })
    .await;

    island.set_on_bus(id(0x112), true).await.unwrap();
    gw.send(NodeId::BROADCAST, Message::HealthCheck { seq: 3 })
        .await;
    gw.expect("health reply 3 from 111", reply_from(id(0x111), 3))
        .await;
    let p = gw
        .expect("health reply 3 from 112", reply_from(id(0x112), 3))
        .await;
    let Message::HealthReply(h) = p.msg else {
        unreachable!()
    };
    assert_eq!(
        h.loops,
        port(1).mask(),
        "the debounced dock is in the health reply"
    );
    assert_eq!(
        h.tec, 128,
        "the unacknowledged report made its controller error passive"
    );
    assert!(h.flags.contains(ihex_proto::HealthFlags::ERROR_PASSIVE));
    // Every frame sent since lowers the counter: the next reply shows fewer errors.
    gw.send(id(0x112), Message::HealthCheck { seq: 5 }).await;
    let p = gw
        .expect("health reply 5 from 112", reply_from(id(0x112), 5))
        .await;
    let Message::HealthReply(h) = p.msg else {
        unreachable!()
    };
    assert_eq!(h.tec, 127);
    assert!(!h.flags.contains(ihex_proto::HealthFlags::ERROR_PASSIVE));
    island.shutdown().await;
}

/// LED, buzzer and relay commands show up as virtual actuator state and as events.
pub async fn actuators(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    let mut events = island.subscribe();
    let color = Rgb::new(255, 0, 0);
    let blink = LedCommand::Blink {
        color,
        brightness: 255,
        period_10ms: 50,
        duty_pct: 50,
    };
    gw.send(id(0x111), Message::LedSet { seq: 5, cmd: blink })
        .await;
    gw.expect_from(id(0x111), ack(Kind::LedSet, 5)).await;
    let a = island.actuators(id(0x111)).await.unwrap();
    assert_eq!(
        a.led,
        LedOutput {
            duty: color,
            blink: Some((500, 50))
        }
    );
    let tone = BuzzerCommand::Continuous { freq_hz: 440 };
    gw.send(id(0x112), Message::BuzzerSet { seq: 6, cmd: tone })
        .await;
    gw.expect_from(id(0x112), ack(Kind::BuzzerSet, 6)).await;
    assert_eq!(
        island.actuators(id(0x112)).await.unwrap().buzzer,
        BuzzerOutput::Tone { freq_hz: 440 }
    );
    assert_eq!(
        island.actuators(id(0x111)).await.unwrap().buzzer,
        BuzzerOutput::Off,
        "only 112 beeps"
    );

    // Relay on by command powers a docked mobile too (no confirmation needed for PowerSet).
    island.dock(id(3), id(0x112), 2).await.unwrap();
    gw.expect_from(id(0x112), Message::DockDetected { port: port(2) })
        .await;
    gw.send(id(0x112), Message::PowerSet { seq: 7, on: true })
        .await;
    gw.expect_from(id(0x112), ack(Kind::PowerSet, 7)).await;
    gw.expect_from(id(3), boot_up(BootRole::Mobile, 6)).await;
    gw.send(id(0x112), Message::PowerSet { seq: 8, on: false })
        .await;
    gw.expect_from(id(0x112), ack(Kind::PowerSet, 8)).await;
    wait_view(&island, id(3), "power off with the relay", |v| !v.powered).await;

    let mut led_event = false;
    while let Ok(e) = events.try_recv() {
        if let IslandEvent::Actuators { node, actuators } = e {
            led_event |= node == id(0x111) && actuators.led.blink == Some((500, 50));
        }
    }
    assert!(led_event, "the LED change was published");
    island.shutdown().await;
}

/// With contact bounce on, one dock and one undock still produce exactly one report each.
pub async fn bounce(link: Link) {
    let text = format!("bounce = true\n{ISLAND}");
    let (mut gw, island) = start(&link, &text).await;
    let dock_report = |p: &Packet| {
        p.src == id(0x111)
            && matches!(
                p.msg,
                Message::DockDetected { .. } | Message::DockRemoved { .. }
            )
    };
    island.dock(id(2), id(0x111), 5).await.unwrap();
    gw.expect_from(id(0x111), Message::DockDetected { port: port(5) })
        .await;
    gw.expect_none("a second dock report", dock_report).await;
    island.undock(id(2)).await.unwrap();
    gw.expect_from(id(0x111), Message::DockRemoved { port: port(5) })
        .await;
    gw.expect_none("a second dock report", dock_report).await;
    island.shutdown().await;
}

/// The UART ID message configures a factory-fresh board; the stored ID survives a power cycle.
pub async fn uart_id(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    let fresh = id(0x120);
    assert_eq!(
        island.uart(fresh, &[0xB0, 0x00]).await.unwrap(),
        [0x5F, 0xFE],
        "no ID yet"
    );
    assert_eq!(
        island.uart(fresh, &[0xA0, 0x00]).await.unwrap(),
        [0xE0, 0x01],
        "reserved ID refused"
    );
    assert_eq!(
        island.uart(fresh, &[0xA1, 0x23]).await.unwrap(),
        [0x51, 0x23]
    );
    gw.expect_from(id(0x123), boot_up(BootRole::Static, 6))
        .await;
    assert_eq!(island.view(fresh).await.unwrap().node_id, Some(id(0x123)));
    gw.send(id(0x123), Message::HealthCheck { seq: 9 }).await;
    gw.expect("health reply from 123", |p| {
        p.src == id(0x123) && matches!(p.msg, Message::HealthReply(h) if h.seq == 9)
    })
    .await;

    island.power_cycle(fresh).await.unwrap();
    gw.expect_from(id(0x123), boot_up(BootRole::Static, 6))
        .await;
    assert_eq!(
        island.uart(fresh, &[0xB0, 0x00]).await.unwrap(),
        [0x51, 0x23]
    );
    island.shutdown().await;
}

/// A mobile docked in the island file: its static element reports the closed loop after booting,
/// and the mobile powers up once the gateway confirms.
pub async fn docked_at_start(link: Link) {
    let text = ISLAND.replace(
        "id = \"2\"\nport = 1",
        "id = \"2\"\nport = 1\ndock = { static = \"112\", port = 0 }",
    );
    assert_ne!(text, ISLAND, "the island text changed");
    let (mut gw, island) = start(&link, &text).await;
    gw.expect_from(id(0x112), Message::DockDetected { port: port(0) })
        .await;
    assert!(!island.view(id(2)).await.unwrap().powered);
    gw.send(
        id(0x112),
        Message::DockConfirm {
            seq: 3,
            port: port(0),
        },
    )
    .await;
    gw.expect_from(id(0x112), ack(Kind::DockConfirm, 3)).await;
    gw.expect_from(id(2), boot_up(BootRole::Mobile, 6)).await;
    gw.expect_from(id(2), Message::Handshake { port: port(1) })
        .await;
    island.shutdown().await;
}

/// CAN node-ID assignment by unique ID reaches a factory-fresh board, which then answers under
/// its new ID (its acceptance filters followed the change).
pub async fn can_assignment(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    let fresh = island.view(id(0x120)).await.unwrap();
    assert_eq!(fresh.node_id, None);
    // A UID no board of this island has selects nobody.
    let other = ihex_proto::Uid([0xEE; 12]);
    gw.send(
        NodeId::BROADCAST,
        Message::AssignSelect {
            uid_head: other.head(),
        },
    )
    .await;
    let commit = |uid: ihex_proto::Uid, seq| Message::AssignCommit {
        uid_tail: uid.tail(),
        new_id: id(0x456),
        seq,
    };
    gw.send(NodeId::BROADCAST, commit(other, 1)).await;
    gw.expect_none("an assignment reply to a foreign UID", |p| {
        matches!(p.msg, Message::AssignReply { .. })
    })
    .await;

    gw.send(
        NodeId::BROADCAST,
        Message::AssignSelect {
            uid_head: fresh.uid.head(),
        },
    )
    .await;
    gw.send(NodeId::BROADCAST, commit(fresh.uid, 2)).await;
    let reply = Message::AssignReply {
        seq: 2,
        result: AckResult::Ok,
        new_id: id(0x456),
        uid_tail: fresh.uid.tail(),
    };
    gw.expect_from(id(0x456), reply).await;
    gw.expect_from(id(0x456), boot_up(BootRole::Static, 6))
        .await;
    gw.send(id(0x456), Message::HealthCheck { seq: 4 }).await;
    gw.expect("health reply from 456", |p| {
        p.src == id(0x456) && matches!(p.msg, Message::HealthReply(h) if h.seq == 4)
    })
    .await;
    assert_eq!(
        island.view(id(0x120)).await.unwrap().node_id,
        Some(id(0x456))
    );
    island.shutdown().await;
}

/// The reply of `src` to the state query `seq`: its reports up to and including `End`.
pub async fn state_reply(gw: &mut Gateway, src: NodeId, seq: u8) -> Vec<StateReport> {
    let mut out = Vec::new();
    loop {
        let p = gw
            .expect(&format!("state report {} of {src}", out.len()), |p| {
                p.src == src && matches!(p.msg, Message::StateReport(_))
            })
            .await;
        let Message::StateReport(r) = p.msg else {
            unreachable!("matched above")
        };
        out.push(r);
        if let StateReport::End { seq: s, count, .. } = r {
            assert_eq!(s, seq, "{src} answered another query: {out:?}");
            assert_eq!(usize::from(count), out.len() - 1, "{src}: {out:?}");
            return out;
        }
    }
}

/// A (restarted) gateway reads the island back: the commanded LED, the relay, the docking with
/// the link it set, and every node's firmware and UID from the island file (or their defaults);
/// the link goes with the undocking.
pub async fn state_query(link: Link) {
    let (mut gw, island) = start(&link, ISLAND).await;
    dock_and_confirm(&mut gw, &island, 7).await;
    let partner = DockPartner {
        node: id(2),
        port: port(1),
    };
    gw.send(
        id(0x111),
        Message::DockLink {
            seq: 8,
            port: port(3),
            partner: Some(partner),
        },
    )
    .await;
    gw.expect_from(id(0x111), ack(Kind::DockLink, 8)).await;
    let red = LedCommand::Steady {
        color: Rgb::new(255, 0, 0),
        brightness: 200,
    };
    gw.send(id(0x111), Message::LedSet { seq: 9, cmd: red })
        .await;
    gw.expect_from(id(0x111), ack(Kind::LedSet, 9)).await;

    // One broadcast query: every configured, powered node answers in full.
    gw.send(
        NodeId::BROADCAST,
        Message::StateQuery {
            seq: 0x40,
            parts: StateParts::ALL,
        },
    )
    .await;
    let desc = IslandDesc::parse(ISLAND).unwrap();
    let default_fw = sim_node::desc::DEFAULT_FIRMWARE;
    let identity = |node: u16, version: FirmwareVersion, hash: [u8; 7]| {
        let uid = sim_node::desc::derived_uid(id(node));
        [
            StateReport::Firmware {
                version,
                trial: false,
            },
            StateReport::ImageHash(hash),
            StateReport::UidLow(uid.low()),
            StateReport::UidHigh(uid.high()),
            StateReport::Protocol {
                version: ihex_proto::PROTOCOL_VERSION,
            },
        ]
    };
    let mut want = vec![
        StateReport::Led(red),
        StateReport::Buzzer(BuzzerCommand::Off),
        StateReport::Power(PowerState {
            relay: true,
            loops: port(3).mask(),
            confirmed: port(3).mask(),
            identify_s: 0,
            role: BootRole::Static,
            ports: 6,
        }),
        StateReport::Dock {
            port: port(3),
            state: DockState {
                closed: true,
                confirmed: true,
                partner: Some(partner),
            },
        },
    ];
    want.extend(identity(
        0x111,
        default_fw,
        sim_node::desc::simulated_image_hash(default_fw),
    ));
    want.push(StateReport::End {
        seq: 0x40,
        parts: StateParts::ALL,
        count: 9,
    });
    assert_eq!(state_reply(&mut gw, id(0x111), 0x40).await, want);
    assert_eq!(desc.statics[0].firmware.version, default_fw);

    let r112 = state_reply(&mut gw, id(0x112), 0x40).await;
    assert_eq!(
        r112[3..8],
        identity(
            0x112,
            FirmwareVersion::new(2, 3, 4),
            sim_node::desc::simulated_image_hash(FirmwareVersion::new(2, 3, 4))
        )
    );
    let r2 = state_reply(&mut gw, id(2), 0x40).await;
    assert_eq!(
        r2[2],
        StateReport::Power(PowerState {
            relay: false,
            loops: port(1).mask(),
            confirmed: 0,
            identify_s: 0,
            role: BootRole::Mobile,
            ports: 6,
        })
    );
    assert_eq!(r2.len(), 9, "a mobile has no dock parts: {r2:?}");
    gw.expect_none("a state report from a silent node", |p| {
        matches!(p.msg, Message::StateReport(_)) && (p.src == id(3) || !p.src.is_sc())
    })
    .await;

    // Undocked: the loop opens and the link goes with it.
    island.undock(id(2)).await.expect("undock");
    gw.expect_from(id(0x111), Message::DockRemoved { port: port(3) })
        .await;
    gw.send(
        id(0x111),
        Message::StateQuery {
            seq: 0x41,
            parts: StateParts(StateParts::DOCKING),
        },
    )
    .await;
    assert_eq!(
        state_reply(&mut gw, id(0x111), 0x41).await,
        [StateReport::End {
            seq: 0x41,
            parts: StateParts(StateParts::DOCKING),
            count: 0
        }]
    );
    island.shutdown().await;
}

/// A firmware update of one element through the bus: the transfer, the commit, the reset into
/// the new image on trial, its confirmation once it hears the gateway — and the new version and
/// image hash reported, while the other elements keep theirs.
pub async fn firmware_update(link: Link) {
    use ihex_proto::{FwAction, FwPhase, FwStatus, FW_DATA_LEN};
    use sim_node::board::{sim_image, SimFirmware};

    let (mut gw, island) = start(&link, ISLAND).await;
    // 2 docked and confirmed on 111: 111's relay powers it through the whole update.
    dock_and_confirm(&mut gw, &island, 0x40).await;
    let mut power = island.subscribe();
    let new_version = FirmwareVersion::new(9, 0, 1);
    let img = sim_image(
        new_version,
        SimFirmware { confirms: true },
        3000,
        &ihex_image::SigningKey::test_key(),
    )
    .expect("image");
    let header = ihex_image::Header::parse(&img).expect("header");
    let image_id = header.image_id();
    let status = |phase| {
        move |p: &Packet| {
            p.src == id(0x111)
                && matches!(p.msg, Message::FwStatus(FwStatus { phase: ph, .. }) if ph == phase)
        }
    };

    gw.send(
        id(0x111),
        Message::FwBegin {
            image_id,
            len: img.len() as u32,
            force: false,
        },
    )
    .await;
    gw.expect("header phase", status(FwPhase::Header)).await;
    // The data go to everybody: the other nodes have no transfer and ignore them.
    for (i, chunk) in img.chunks(FW_DATA_LEN).enumerate() {
        let mut data = [0xFF; FW_DATA_LEN];
        data[..chunk.len()].copy_from_slice(chunk);
        gw.send(
            NodeId::BROADCAST,
            Message::FwData {
                index: i as u16,
                data,
            },
        )
        .await;
    }
    gw.expect("ready after the erase", status(FwPhase::Receiving))
        .await;
    // A burst can lose frames on a loaded machine (a socket's receive buffer overflows): like the
    // gateway's sender, ask what is missing and send only that until the node has it all.
    let mut complete = gw
        .within(scaled(Duration::from_secs(2)), status(FwPhase::Complete))
        .await;
    for _ in 0..50 {
        if complete.is_some() {
            break;
        }
        gw.send(id(0x111), Message::FwQuery { image_id }).await;
        let answer = gw
            .within(scaled(Duration::from_secs(2)), |p| {
                p.src == id(0x111) && matches!(p.msg, Message::FwStatus(_))
            })
            .await;
        let Some(Packet {
            msg: Message::FwStatus(st),
            ..
        }) = answer
        else {
            continue;
        };
        if st.phase == FwPhase::Complete {
            complete = answer;
            break;
        }
        let first = usize::from(st.first_missing);
        for i in first..first + usize::from(st.run.max(1)) {
            let Some(chunk) = img.chunks(FW_DATA_LEN).nth(i) else {
                break;
            };
            let mut data = [0xFF; FW_DATA_LEN];
            data[..chunk.len()].copy_from_slice(chunk);
            gw.send(
                NodeId::BROADCAST,
                Message::FwData {
                    index: i as u16,
                    data,
                },
            )
            .await;
        }
    }
    assert!(complete.is_some(), "the transfer never completed");
    gw.send(
        id(0x111),
        Message::FwEnd {
            image_id,
            action: FwAction::Commit,
        },
    )
    .await;
    gw.expect("installed", status(FwPhase::Rebooting)).await;
    // The reset: the bootloader swaps the image in, the node announces itself again.
    gw.expect("boot-up after the update", |p| {
        p.src == id(0x111)
            && matches!(
                p.msg,
                Message::BootUp {
                    reset: ResetReason::Software,
                    ..
                }
            )
    })
    .await;
    let firmware = |reports: &[StateReport]| {
        reports.iter().find_map(|r| match *r {
            StateReport::Firmware { version, trial } => Some((version, trial)),
            _ => None,
        })
    };
    let ask = |seq| Message::StateQuery {
        seq,
        parts: StateParts(StateParts::IDENTITY),
    };
    // The query is the gateway heard, and the simulated firmware passed its self-test: the node
    // confirms its image right after answering (still on trial in this answer).
    gw.send(id(0x111), ask(0x51)).await;
    let r = state_reply(&mut gw, id(0x111), 0x51).await;
    assert_eq!(firmware(&r), Some((new_version, true)), "{r:?}");
    gw.send(id(0x111), ask(0x52)).await;
    let r = state_reply(&mut gw, id(0x111), 0x52).await;
    assert_eq!(firmware(&r), Some((new_version, false)), "{r:?}");
    assert!(
        r.contains(&StateReport::ImageHash(header.payload_hash.prefix::<7>())),
        "{r:?}"
    );
    assert_eq!(
        island.view(id(0x111)).await.unwrap().firmware.version,
        new_version
    );
    // 111's relay held through its reset (the bootloader keeps it), so 2 never lost power, and
    // 111 neither forgot nor re-announced the docking.
    while let Ok(ev) = power.try_recv() {
        assert!(
            !matches!(ev, IslandEvent::Power { node, on: false } if node == id(2)),
            "2 lost power during 111's update"
        );
    }
    assert!(island.view(id(2)).await.unwrap().powered);
    assert!(island.actuators(id(0x111)).await.unwrap().relay);
    gw.expect_none("a docking reported again", |p| {
        matches!(
            p.msg,
            Message::DockDetected { .. } | Message::DockRemoved { .. }
        )
    })
    .await;
    // Another element still runs what it was flashed with.
    gw.send(id(0x112), ask(0x53)).await;
    let r = state_reply(&mut gw, id(0x112), 0x53).await;
    assert_eq!(firmware(&r), Some((FirmwareVersion::new(2, 3, 4), false)));
    island.shutdown().await;
}
