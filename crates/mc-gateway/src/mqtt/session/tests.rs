//! The session's rules without a socket: packets, core hand-overs and time in, requests out.

use super::*;

const KEEP_ALIVE: Duration = Duration::from_secs(10);
const BOUND: Duration = Duration::from_secs(4);

fn session() -> Session {
    let timing = Timing {
        keep_alive: KEEP_ALIVE,
        ack_timeout: BOUND,
    };
    Session::new(
        Topics::seed(),
        false,
        "b:1883".into(),
        Arc::default(),
        timing,
    )
}

/// Connected at `now`, its subscriptions, `online` and the `Connected` input taken.
fn connected(now: Instant) -> Session {
    let mut s = session();
    s.handle_connack(now);
    drain(&mut s);
    assert!(matches!(s.poll_publication(now), Some(p) if &p.payload[..] == b"online"));
    s.handle_puback(now);
    assert_eq!(s.poll_input(), Some(MqttInput::Connected));
    s
}

fn drain(s: &mut Session) -> Vec<Request> {
    std::iter::from_fn(|| s.poll_request()).collect()
}

fn command(pkid: u16, qos: QoS, payload: &[u8]) -> Publish {
    let mut p = Publish::new("CommandsTopic", qos, payload.to_vec());
    p.pkid = pkid;
    p
}

fn state(id: &str, retain: bool) -> Publish {
    let mut p = Publish::new(
        format!("ihex/node/{id}/state"),
        QoS::AtMostOnce,
        b"{}".to_vec(),
    );
    p.retain = retain;
    p
}

/// A publication whose payload is `n` (also for the socket tests in `mqtt`).
pub(crate) fn publication(n: u8) -> Outbound {
    Outbound {
        topic: "EventsTopic".into(),
        payload: vec![n].into(),
        retain: false,
    }
}

#[test]
fn every_connack_subscribes_and_announces_online_first() {
    let t0 = Instant::now();
    let mut s = session();
    assert!(s.wants_link());
    assert_eq!(
        s.poll_request(),
        None,
        "nothing is asked of a link that is down"
    );
    s.handle_publication(publication(1));
    assert_eq!(s.poll_publication(t0), None);
    s.handle_connack(t0);
    assert_eq!(
        drain(&mut s),
        [
            Request::Subscribe {
                filter: "CommandsTopic".into(),
                qos: QoS::AtLeastOnce
            },
            Request::Subscribe {
                filter: "ihex/cmd/+".into(),
                qos: QoS::AtLeastOnce
            },
            Request::Subscribe {
                filter: "ihex/fw/upload/+".into(),
                qos: QoS::AtLeastOnce
            },
            Request::Subscribe {
                filter: "ihex/node/+/state".into(),
                qos: QoS::AtMostOnce
            },
        ]
    );
    let online = s.poll_publication(t0).unwrap();
    assert_eq!(
        (online.topic.as_str(), &online.payload[..], online.retain),
        ("ihex/gateway/availability", &b"online"[..], true)
    );
    assert_eq!(s.poll_publication(t0), Some(publication(1)));
    assert_eq!(s.poll_input(), Some(MqttInput::Connected));
}

#[test]
fn a_command_is_acknowledged_only_once_the_core_took_it() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    s.handle_publish(command(7, QoS::AtLeastOnce, b"{}"), t0);
    assert_eq!(drain(&mut s), [], "acknowledged before the core took it");
    assert!(matches!(
        s.poll_input(),
        Some(MqttInput::Command { received, retained: false, .. }) if received == t0
    ));
    assert_eq!(drain(&mut s), [Request::Ack(7)]);
    // QoS 0: nothing to acknowledge.
    s.handle_publish(command(0, QoS::AtMostOnce, b"{}"), t0);
    assert!(s.poll_input().is_some());
    assert_eq!(drain(&mut s), []);
}

#[test]
fn a_per_user_topic_names_its_user_and_the_shared_one_nobody() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    let mut p = Publish::new("ihex/cmd/alice", QoS::AtLeastOnce, b"{}".to_vec());
    p.pkid = 3;
    s.handle_publish(p, t0);
    s.handle_publish(command(4, QoS::AtLeastOnce, b"{}"), t0);
    // Not a command topic: a deeper level under the per-user root.
    s.handle_publish(
        Publish::new("ihex/cmd/alice/x", QoS::AtMostOnce, b"{}".to_vec()),
        t0,
    );
    let origin = |input| match input {
        Some(MqttInput::Command { origin, .. }) => origin,
        other => panic!("{other:?}"),
    };
    let alice = Origin::new(Interface::Mqtt, Some("alice".into()));
    assert_eq!(origin(s.poll_input()), alice);
    assert_eq!(origin(s.poll_input()), Origin::default());
    assert_eq!(s.poll_input(), None);
}

#[test]
fn an_ack_from_an_older_connection_is_never_sent_on_a_newer_one() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    s.handle_publish(command(7, QoS::AtLeastOnce, b"{}"), t0);
    s.handle_connection_lost("reset", "reset".into(), Vec::new(), t0);
    // Taken while down: no ack (there is no connection).
    s.handle_publish(command(8, QoS::AtLeastOnce, b"{}"), t0);
    s.handle_timeout(t0 + RECONNECT_MIN);
    s.handle_connack(t0 + RECONNECT_MIN);
    drain(&mut s);
    // Both taken by the core on the new connection: packet ids 7 and 8 were the old
    // connection's (the broker sends them again), never acknowledged on this one.
    assert!(matches!(s.poll_input(), Some(MqttInput::Command { .. })));
    assert!(matches!(s.poll_input(), Some(MqttInput::Command { .. })));
    assert_eq!(s.poll_input(), Some(MqttInput::Connected));
    assert_eq!(drain(&mut s), []);
    // One of this connection is.
    s.handle_publish(command(7, QoS::AtLeastOnce, b"{}"), t0);
    assert!(s.poll_input().is_some());
    assert_eq!(drain(&mut s), [Request::Ack(7)]);
}

#[test]
fn commands_wait_for_the_core_and_only_qos0_floods_are_shed() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    for n in 0..HELD_MAX as u16 {
        s.handle_publish(command(n + 1, QoS::AtLeastOnce, b"{}"), t0);
    }
    assert_eq!(s.held(), HELD_MAX);
    assert_eq!(drain(&mut s), [], "held commands are not acknowledged");
    // Beyond the limit a QoS 0 command is shed and counted; a QoS 1 command is still held (the
    // broker's window bounds those), unacknowledged.
    s.handle_publish(command(0, QoS::AtMostOnce, b"{}"), t0);
    s.handle_publish(command(5000, QoS::AtLeastOnce, b"{}"), t0);
    assert_eq!(s.stats.commands_shed.load(Ordering::Relaxed), 1);
    assert_eq!(s.held(), HELD_MAX + 1);
    assert_eq!(drain(&mut s), []);
    assert_eq!(
        s.stats.commands.load(Ordering::Relaxed),
        HELD_MAX as u64 + 2
    );
    // `Connected` is never shed.
    s.handle_connection_lost("reset", "reset".into(), Vec::new(), t0);
    s.handle_timeout(t0 + RECONNECT_MIN);
    s.handle_connack(t0 + RECONNECT_MIN);
    assert_eq!(s.held(), HELD_MAX + 2);
}

#[test]
fn a_burst_s_queues_give_their_memory_back_once_empty() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    for n in 1..=5000 {
        s.handle_publish(command(n, QoS::AtLeastOnce, b"{}"), t0);
    }
    assert!(s.held.capacity() >= 5000);
    while s.poll_input().is_some() {}
    assert!(s.held.capacity() <= KEPT, "{}", s.held.capacity());
    assert!(s.requests.capacity() >= 5000, "an ack per command taken");
    assert_eq!(drain(&mut s).len(), 5000);
    assert!(s.requests.capacity() <= KEPT, "{}", s.requests.capacity());
}

#[test]
fn qos1_commands_are_held_up_to_what_packet_identifiers_allow() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    // A broker with an unlimited in-flight window (Mosquitto's `max_inflight_messages 0`) sends a
    // burst whole: every command waits for the core, none is shed.
    for n in 1..=u16::MAX {
        s.handle_publish(command(n, QoS::AtLeastOnce, b"{}"), t0);
    }
    assert_eq!(s.held(), u16::MAX as usize);
    assert_eq!(s.stats.commands_shed.load(Ordering::Relaxed), 0);
    assert_eq!(drain(&mut s), []);
    // Only a broker reusing identifiers it was never given back gets past that: shed, acknowledged.
    for n in 0..HELD_MAX as u16 {
        s.handle_publish(command(n + 1, QoS::AtLeastOnce, b"{}"), t0);
    }
    assert_eq!(s.held(), HELD_MAX_ACKED);
    assert_eq!(s.stats.commands_shed.load(Ordering::Relaxed), 0);
    s.handle_publish(command(1, QoS::AtLeastOnce, b"{}"), t0);
    assert_eq!(s.stats.commands_shed.load(Ordering::Relaxed), 1);
    assert_eq!(drain(&mut s), [Request::Ack(1)]);
    // Taken by the core, each is acknowledged.
    assert_eq!(s.poll_input().map(|_| ()), Some(()));
    assert_eq!(drain(&mut s), [Request::Ack(1)]);
}

#[test]
fn an_empty_command_clears_a_retained_one_and_is_not_answered() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    let mut clear = command(3, QoS::AtLeastOnce, b"");
    clear.retain = true;
    s.handle_publish(clear, t0);
    s.handle_publish(command(4, QoS::AtMostOnce, b""), t0);
    assert_eq!(s.poll_input(), None, "nothing for the core");
    assert_eq!(drain(&mut s), [Request::Ack(3)]);
    assert_eq!(s.stats.commands.load(Ordering::Relaxed), 0);
}

#[test]
fn the_retained_state_window_opens_on_connack_and_ends_at_the_first_live_message() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    s.handle_publish(state("111", true), t0);
    assert!(matches!(
        s.poll_input(),
        Some(MqttInput::RetainedState { id, .. }) if id.to_string() == "111"
    ));
    s.handle_publish(state("111", false), t0);
    s.handle_publish(state("112", false), t0);
    assert_eq!(s.poll_input(), None, "live documents are our own");
    assert_eq!(
        drain(&mut s),
        [Request::Unsubscribe("ihex/node/+/state".into())],
        "unsubscribed once"
    );
    // The next connection opens it again.
    s.handle_connection_lost("reset", "reset".into(), Vec::new(), t0);
    s.handle_timeout(t0 + RECONNECT_MIN);
    s.handle_connack(t0 + RECONNECT_MIN);
    drain(&mut s);
    s.handle_publish(state("112", false), t0);
    assert_eq!(
        drain(&mut s),
        [Request::Unsubscribe("ihex/node/+/state".into())]
    );
}

#[test]
fn reconnects_back_off_from_100_ms_doubling_to_5_s_and_reset_on_success() {
    let t0 = Instant::now();
    let mut s = session();
    let mut now = t0;
    let mut delays = Vec::new();
    for _ in 0..8 {
        assert!(s.wants_link());
        s.handle_connection_lost("refused", "refused".into(), Vec::new(), now);
        assert!(!s.wants_link(), "no attempt during the back-off");
        let at = s.poll_timeout().unwrap();
        delays.push((at - now).as_millis());
        s.handle_timeout(at - Duration::from_millis(1));
        assert!(!s.wants_link());
        s.handle_timeout(at);
        now = at;
    }
    assert_eq!(delays, [100, 200, 400, 800, 1600, 3200, 5000, 5000]);
    assert_eq!(s.stats.failed_attempts.load(Ordering::Relaxed), 8);
    assert_eq!(s.stats.broker_link().last_error.as_deref(), Some("refused"));
    s.handle_connack(now);
    assert!(s.stats.broker_link().connected);
    assert_eq!(s.stats.broker_link().last_error, None);
    s.handle_connection_lost("reset", "reset".into(), Vec::new(), now);
    assert_eq!(s.poll_timeout(), Some(now + RECONNECT_MIN));
}

#[test]
fn warnings_about_an_unreachable_broker_follow_a_growing_interval() {
    let t0 = Instant::now();
    let mut w = WarnSchedule::new();
    // Attempts every 100 ms doubling to 5 s, for ten minutes: when is there a warning?
    let mut at = Duration::ZERO;
    let mut delay = RECONNECT_MIN;
    let mut warned = Vec::new();
    while at < Duration::from_secs(600) {
        if w.due(t0 + at) {
            warned.push(at.as_secs());
        }
        at += delay;
        delay = (delay * 2).min(RECONNECT_MAX);
    }
    assert_eq!(warned, [0, 6, 16, 36, 76, 156, 316]);
    // A connection resets the schedule: the next failure warns at once.
    let mut s = session();
    s.warn_at = w;
    s.handle_connack(t0 + at);
    assert!(s.warn_at.due(t0 + at));
}

#[test]
fn publications_of_a_broken_connection_go_first_and_online_is_not_taken_back() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    for n in 1..=3 {
        s.handle_publication(publication(n));
    }
    let sent: Vec<Outbound> = std::iter::from_fn(|| s.poll_publication(t0)).collect();
    assert_eq!(sent.len(), 3);
    assert_eq!(s.stats.published.load(Ordering::Relaxed), 3);
    s.handle_publication(publication(4));
    let mut online = sent[0].clone();
    online.topic = "ihex/gateway/availability".into();
    let back = vec![online, sent[1].clone(), sent[2].clone()];
    s.handle_connection_lost("reset", "reset".into(), back, t0);
    assert_eq!(s.stats.published.load(Ordering::Relaxed), 1);
    s.handle_timeout(t0 + RECONNECT_MIN);
    s.handle_connack(t0);
    let order: Vec<u8> = std::iter::from_fn(|| s.poll_publication(t0))
        .map(|p| p.payload[0])
        .collect();
    assert_eq!(order, [b'o', 2, 3, 4]);
}

#[test]
fn a_refused_publication_comes_back_first() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    s.handle_publication(publication(1));
    s.handle_publication(publication(2));
    let p = s.poll_publication(t0).unwrap();
    s.handle_publication_refused(p);
    assert_eq!(s.stats.published.load(Ordering::Relaxed), 0);
    assert_eq!(s.poll_publication(t0), Some(publication(1)));
    // `online` refused is announced again, not staged.
    s.handle_connack(t0);
    let online = s.poll_publication(t0).unwrap();
    s.handle_publication_refused(online.clone());
    assert_eq!(s.poll_publication(t0), Some(online));
    assert_eq!(s.poll_publication(t0), Some(publication(2)));
}

#[test]
fn only_staging_publications_wait_here() {
    let mut s = session();
    for n in 0..STAGING {
        assert!(s.wants_publications());
        s.handle_publication(publication(n as u8));
    }
    assert!(!s.wants_publications(), "the core keeps the rest");
}

#[test]
fn a_ping_goes_out_at_every_keep_alive_and_its_answer_keeps_the_link() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    assert_eq!(s.poll_timeout(), Some(t0 + KEEP_ALIVE));
    s.handle_timeout(t0 + KEEP_ALIVE);
    assert_eq!(drain(&mut s), [Request::Ping]);
    s.handle_pingresp(t0 + KEEP_ALIVE + Duration::from_millis(30));
    assert_eq!(s.poll_timeout(), Some(t0 + 2 * KEEP_ALIVE));
    s.handle_timeout(t0 + 2 * KEEP_ALIVE);
    assert_eq!(drain(&mut s), [Request::Ping]);
}

#[test]
fn a_ping_without_answer_for_the_bound_closes_the_link() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    let ping = t0 + KEEP_ALIVE;
    s.handle_timeout(ping);
    assert_eq!(drain(&mut s), [Request::Ping]);
    assert_eq!(s.poll_timeout(), Some(ping + BOUND));
    s.handle_timeout(ping + BOUND - Duration::from_millis(1));
    assert_eq!(drain(&mut s), []);
    s.handle_timeout(ping + BOUND);
    let asked = drain(&mut s);
    assert!(
        matches!(&asked[..], [Request::Close(why)] if why.contains("PINGREQ without PINGRESP")),
        "{asked:?}"
    );
    assert_eq!(s.poll_timeout(), None, "closed once");
    assert_eq!(s.poll_publication(ping + BOUND), None);
    s.handle_connection_lost("dead", "dead".into(), Vec::new(), ping + BOUND);
    assert!(!s.wants_link());
}

#[test]
fn an_unacknowledged_publication_is_probed_at_half_the_bound_and_closes_at_the_bound() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    let t1 = t0 + Duration::from_secs(1);
    s.handle_publication(publication(1));
    assert!(s.poll_publication(t1).is_some());
    // PUBACKs may wait in the kernel under the low-water mark: a PINGREQ first.
    assert_eq!(s.poll_timeout(), Some(t1 + BOUND / 2));
    s.handle_timeout(t1 + BOUND / 2);
    assert_eq!(drain(&mut s), [Request::Ping]);
    s.handle_timeout(t1 + BOUND);
    assert!(matches!(&drain(&mut s)[..], [Request::Close(why)] if why.contains("1 publication")));
}

#[test]
fn acknowledgements_keep_a_busy_link_alive() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    let step = BOUND / 4;
    let mut now = t0;
    // Publications all along, each acknowledged within a quarter of the bound, for three bounds.
    for n in 0..12 {
        now += step;
        s.handle_publication(publication(n));
        assert!(s.poll_publication(now).is_some());
        if n > 0 {
            s.handle_puback(now);
        }
        s.handle_timeout(now);
        for r in drain(&mut s) {
            assert_eq!(r, Request::Ping, "only keep-alive pings");
            s.handle_pingresp(now);
        }
    }
    // The probe's answer brings the PUBACKs the kernel held: nothing owed, no deadline.
    s.handle_puback(now);
    assert_eq!(s.liveness.owed_since, None);
    assert_eq!(s.poll_timeout(), s.liveness.ping_at);
}

#[test]
fn the_probe_answered_keeps_the_link_and_the_late_pubacks_clear_the_debt() {
    let t0 = Instant::now();
    let mut s = connected(t0);
    s.handle_publication(publication(1));
    assert!(s.poll_publication(t0).is_some());
    s.handle_timeout(t0 + BOUND / 2);
    assert_eq!(drain(&mut s), [Request::Ping]);
    // The PUBACK the kernel held, then the PINGRESP.
    let t1 = t0 + BOUND / 2 + Duration::from_millis(5);
    s.handle_puback(t1);
    s.handle_pingresp(t1);
    s.handle_timeout(t0 + BOUND);
    assert_eq!(drain(&mut s), [], "alive");
    assert_eq!(s.poll_timeout(), Some(t0 + KEEP_ALIVE));
}
