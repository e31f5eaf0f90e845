//! The checker on hand-made traces: a clean run passes, and each kind of violation is found.

use ihex_proto::{LedCommand, Message, NodeId, Packet, Rgb};

use super::*;
use crate::fault::trace::{Params, Record};
use crate::id;

const EVENTS: &str = "t/EventsTopic";
const AVAIL: &str = "t/ihex/gateway/availability";

/// A trace under construction.
#[derive(Default)]
struct T {
    trace: Trace,
}

impl T {
    fn new() -> T {
        let mut t = T::default();
        t.trace.params = Params {
            health_period_ms: 500,
            lost_after: 3,
            command_timeout_ms: 1000,
            slack_ms: 500,
            dock_timeout_ms: 3000,
        };
        t
    }

    fn at(&mut self, at: Ms, entry: Entry) -> &mut T {
        self.trace.records.push(Record { at, entry });
        self
    }

    fn received(&mut self, at: Ms, topic: &str, payload: &str) -> &mut T {
        self.at(
            at,
            Entry::Received {
                topic: topic.into(),
                payload: payload.into(),
                retain: false,
            },
        )
    }

    /// An LED command to 111 (red, or `rgb`), with `rid` if given.
    fn led(&mut self, at: Ms, n: u32, rgb: [u8; 3], rid: Option<&str>) -> &mut T {
        self.send(at, n, rgb, rid, false, None)
    }

    fn send(
        &mut self,
        at: Ms,
        n: u32,
        rgb: [u8; 3],
        rid: Option<&str>,
        retained: bool,
        ttl_ms: Option<u64>,
    ) -> &mut T {
        let action = format!(
            r#"{{"cmd":"led","node":"111","color":[{},{},{}]}}"#,
            rgb[0], rgb[1], rgb[2]
        );
        let mut payload = action.strip_suffix('}').unwrap_or(&action).to_string();
        if let Some(r) = rid {
            payload.push_str(&format!(r#","request_id":"{r}""#));
        }
        if let Some(t) = ttl_ms {
            payload.push_str(&format!(r#","ttl_ms":{t}"#));
        }
        payload.push('}');
        self.at(
            at,
            Entry::Sent(Sent {
                n,
                payload,
                request_id: rid.map(String::from),
                retained,
                ttl_ms,
                action,
            }),
        )
    }

    fn result(&mut self, at: Ms, rid: Option<&str>, result: &str) -> &mut T {
        let rid = rid.map_or("null".to_string(), |r| format!("\"{r}\""));
        let reason = if result == "ok" { "null" } else { "\"why\"" };
        self.received(
            at,
            EVENTS,
            &format!(
                r#"{{"event":"command_result","payload":{{"request_id":{rid},"cmd":"led","node":"111","result":"{result}","reason":{reason}}}}}"#
            ),
        )
    }

    fn rejected(&mut self, at: Ms, rid: &str) -> &mut T {
        self.received(
            at,
            EVENTS,
            &format!(
                r#"{{"event":"command_rejected","payload":{{"request_id":"{rid}","reason":"retained"}}}}"#
            ),
        )
    }

    /// The LED frame the gateway sends for `rgb` to 111.
    fn frame(&mut self, at: Ms, rgb: [u8; 3], seq: u8) -> &mut T {
        let p = Packet {
            src: NodeId::GATEWAY,
            dest: id(0x111),
            msg: Message::LedSet {
                seq,
                cmd: LedCommand::Steady {
                    color: Rgb::new(rgb[0], rgb[1], rgb[2]),
                    brightness: 255,
                },
            },
        };
        let (raw, data) = p.encode();
        self.at(
            at,
            Entry::Frame {
                id: raw,
                data: data.to_vec(),
            },
        )
    }

    fn fault(&mut self, begin: Ms, n: u32, what: Fault, recovered: Ms) -> &mut T {
        self.at(begin, Entry::FaultBegin { fault: n, what })
            .at(recovered, Entry::FaultEnd { fault: n })
            .at(
                recovered,
                Entry::Recovered {
                    fault: n,
                    how: "test".into(),
                },
            )
    }

    fn check(&self) -> Report {
        check(&self.trace)
    }
}

fn element(id: &str, led: [u8; 3]) -> Element {
    Element {
        id: id.into(),
        mobile: false,
        own_port: 0,
        powered: true,
        on_bus: true,
        led,
        blink: None,
        buzzer: "off".into(),
        relay: true,
        docked: None,
    }
}

fn mobile(id: &str, docked: Option<(&str, u8)>) -> Element {
    Element {
        mobile: true,
        own_port: 0,
        relay: false,
        docked: docked.map(|(s, p)| (s.to_string(), p)),
        ..element(id, [0, 0, 0])
    }
}

fn doc(id: &str, online: bool, led: [u8; 3], relay: bool, links: &str) -> (String, String) {
    (
        format!("t/ihex/node/{id}/state"),
        format!(
            r##"{{"id":"{id}","online":{online},"role":null,"ports":null,"version":null,"led":{{"mode":"steady","color":"#{:02x}{:02x}{:02x}","brightness":255}},"buzzer":{{"mode":"off"}},"relay":{relay},"loops":[],"connections":[{links}],"reported":null,"last_seen_ms":0,"first_seen_ms":0}}"##,
            led[0], led[1], led[2]
        ),
    )
}

fn online() -> (String, String) {
    (AVAIL.into(), "online".into())
}

fn rules(r: &Report) -> Vec<Rule> {
    r.violations.iter().map(|v| v.rule).collect()
}

#[test]
fn a_clean_run_passes() {
    let mut t = T::new();
    t.received(0, AVAIL, "online")
        .led(100, 1, [255, 0, 0], Some("a"))
        .frame(110, [255, 0, 0], 1)
        .result(120, Some("a"), "ok")
        .led(200, 2, [0, 255, 0], None)
        .frame(210, [0, 255, 0], 2)
        .result(220, None, "ok")
        .fault(300, 1, Fault::GatewayKill { down_ms: 100 }, 800);
    t.received(350, AVAIL, "offline");
    // Records must be in time order: rebuild sorted.
    t.trace.records.sort_by_key(|r| r.at);
    t.received(800, AVAIL, "online");
    t.trace.records.sort_by_key(|r| r.at);
    t.at(
        1900,
        Entry::Checkpoint {
            fault: Some(1),
            truth: vec![element("111", [0, 255, 0])],
            retained: vec![online(), doc("111", true, [0, 255, 0], true, "")],
        },
    );
    let r = t.check();
    assert!(r.ok(), "{r}");
    assert_eq!(
        (r.commands, r.answered, r.frames, r.checkpoints),
        (2, 2, 2, 1)
    );
}

#[test]
fn a_missing_answer_is_found_but_not_around_a_fault() {
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], Some("a"))
        .at(5000, Entry::Note("end".into()));
    let r = t.check();
    assert_eq!(rules(&r), [Rule::OneAnswer], "{r}");
    assert!(r.violations[0].message.contains("no answer"), "{r}");

    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], Some("a"))
        .fault(
            500,
            1,
            Fault::ProxyHalfOpen {
                ms: 100,
                noticed: false,
            },
            900,
        )
        .at(5000, Entry::Note("end".into()));
    let r = t.check();
    assert!(r.ok(), "{r}");
    assert_eq!(r.lost_in_faults, 1);
}

#[test]
fn a_second_answer_is_found_and_a_redelivered_copy_is_not() {
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], Some("a"))
        .result(200, Some("a"), "ok")
        .result(300, Some("a"), "ok");
    assert_eq!(rules(&t.check()), [Rule::OneAnswer]);

    // Two different outcomes are never a redelivery, fault or not.
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], Some("a"))
        .result(200, Some("a"), "timeout")
        .fault(250, 1, Fault::BrokerKill { down_ms: 10 }, 400)
        .result(300, Some("a"), "ok");
    t.trace.records.sort_by_key(|r| r.at);
    assert!(rules(&t.check()).contains(&Rule::OneAnswer));

    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], Some("a"))
        .result(200, Some("a"), "ok")
        .fault(250, 1, Fault::ProxyCut { ms: 10 }, 400)
        .result(300, Some("a"), "ok");
    t.trace.records.sort_by_key(|r| r.at);
    let r = t.check();
    assert!(!rules(&r).contains(&Rule::OneAnswer), "{r}");
    assert_eq!(r.redelivered, 1);
}

#[test]
fn answers_without_request_id_are_counted_per_command() {
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], None)
        .result(200, None, "ok")
        .result(300, None, "ok");
    let r = t.check();
    assert_eq!(rules(&r), [Rule::OneAnswer], "{r}");
    assert!(r.violations[0].message.contains("without request_id"));

    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], None)
        .led(110, 2, [2, 0, 0], None)
        .result(200, None, "ok")
        .result(300, None, "timeout");
    assert!(t.check().ok());
}

#[test]
fn a_rejection_without_request_id_goes_to_the_newest_open_command() {
    let reject =
        r#"{"event":"command_rejected","payload":{"request_id":null,"reason":"unknown node 2"}}"#;
    // #1 is still waiting for its result when #2 is rejected: each gets one answer.
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], None)
        .led(200, 2, [2, 0, 0], None)
        .received(220, EVENTS, reject)
        .result(900, None, "timeout");
    assert!(t.check().ok(), "{}", t.check());
    // A second rejection has no command left to own it.
    t.received(230, EVENTS, reject);
    t.trace.records.sort_by_key(|r| r.at);
    assert_eq!(rules(&t.check()), [Rule::OneAnswer]);
}

#[test]
fn an_answer_without_request_id_goes_to_the_command_that_needs_it() {
    // #1 is published during a cut (it never reached the gateway: no answer needed), #2 after the
    // recovery; the one answer fits both windows and is #2's. (The first guess, the oldest open
    // command, gave it to #1 and found #2 unanswered: a soak run's false violation.)
    let mut t = T::new();
    t.fault(100, 1, Fault::ProxyCut { ms: 100 }, 400)
        .received(150, AVAIL, "offline")
        .received(390, AVAIL, "online")
        .led(200, 1, [1, 0, 0], None)
        .led(500, 2, [2, 0, 0], None)
        .result(600, None, "ok")
        .at(5000, Entry::Note("end".into()));
    t.trace.records.sort_by_key(|r| r.at);
    let r = t.check();
    assert!(r.ok(), "{r}");
    assert_eq!((r.answered, r.lost_in_faults), (1, 1), "{r}");
    // Answers are moved along when that answers everyone: #1's rejection (guessed for #2, the
    // newest) and #2's result, which only #2 can own... here any result can be either's.
    let reject =
        r#"{"event":"command_rejected","payload":{"request_id":null,"reason":"unknown node 2"}}"#;
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], None)
        .led(200, 2, [2, 0, 0], None)
        .received(300, EVENTS, reject)
        .result(400, None, "ok")
        .at(5000, Entry::Note("end".into()));
    let r = t.check();
    assert!(r.ok(), "{r}");
    assert_eq!(r.answered, 2);
    // Still one answer too few for two commands that both need one.
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], None)
        .led(200, 2, [2, 0, 0], None)
        .result(400, None, "ok")
        .at(5000, Entry::Note("end".into()));
    assert_eq!(rules(&t.check()), [Rule::OneAnswer]);
}

#[test]
fn a_late_answer_is_not_given_to_a_command_long_past_its_deadline() {
    // #1 (lost: sent at 100, deadline 100 + 1000 + 2 × 500) cannot own an answer at 5000; #2 does.
    let mut t = T::new();
    t.led(100, 1, [1, 0, 0], None)
        .led(4500, 2, [2, 0, 0], None)
        .result(5000, None, "ok");
    let r = t.check();
    assert_eq!(rules(&r), [Rule::OneAnswer], "{r}");
    assert!(r.violations[0].message.contains("#1"), "{r}");
}

#[test]
fn a_relay_off_after_a_failed_docking_is_the_gateways_own() {
    let off = |t: &mut T, at: Ms| {
        let p = Packet {
            src: NodeId::GATEWAY,
            dest: id(0x111),
            msg: Message::PowerSet { seq: 7, on: false },
        };
        let (raw, data) = p.encode();
        t.at(
            at,
            Entry::Frame {
                id: raw,
                data: data.to_vec(),
            },
        );
    };
    let mut t = T::new();
    off(&mut t, 1000);
    assert_eq!(rules(&t.check()), [Rule::NoLateExecution]);
    t.received(
        1010,
        EVENTS,
        r#"{"event":"dock_failed","payload":{"node":"111","port":3,"reason":"handshake timeout"}}"#,
    );
    assert!(t.check().ok(), "{}", t.check());
    // Not to another node, and not long after.
    off(&mut t, 5000);
    assert_eq!(rules(&t.check()), [Rule::NoLateExecution]);
}

#[test]
fn an_answer_to_an_unknown_request_id_is_found() {
    let mut t = T::new();
    t.result(200, Some("ghost"), "ok");
    let r = t.check();
    assert_eq!(rules(&r), [Rule::OneAnswer]);
    assert!(r.violations[0].message.contains("never sent"), "{r}");
}

#[test]
fn a_frame_after_a_timeout_is_late_execution() {
    let mut t = T::new();
    t.led(100, 1, [9, 9, 9], Some("a"))
        .result(1100, Some("a"), "timeout")
        .frame(1200, [9, 9, 9], 1);
    let r = t.check();
    assert_eq!(rules(&r), [Rule::NoLateExecution], "{r}");
    assert!(
        r.violations[0]
            .message
            .contains("answered command_result Timeout"),
        "{r}"
    );

    // Before its timeout answer the frame was allowed (the answer says "no ack", not "not sent").
    let mut t = T::new();
    t.led(100, 1, [9, 9, 9], Some("a"))
        .frame(200, [9, 9, 9], 1)
        .result(1100, Some("a"), "timeout");
    assert!(t.check().ok());
}

#[test]
fn a_failed_command_has_no_frame_at_all() {
    let mut t = T::new();
    t.led(100, 1, [9, 9, 9], Some("a"))
        .frame(200, [9, 9, 9], 1)
        .result(300, Some("a"), "failed");
    let r = t.check();
    assert_eq!(rules(&r), [Rule::NoLateExecution], "{r}");
    assert!(
        r.violations[0].message.contains("its frame was on the bus"),
        "{r}"
    );
}

#[test]
fn a_frame_no_command_asked_for_is_found() {
    let mut t = T::new();
    t.led(100, 1, [1, 2, 3], Some("a"))
        .result(200, Some("a"), "ok")
        .frame(300, [3, 2, 1], 7);
    let r = t.check();
    assert_eq!(rules(&r), [Rule::NoLateExecution], "{r}");
    assert!(r.violations[0]
        .message
        .contains("no command sent before it"));
}

#[test]
fn an_expired_command_must_not_run() {
    // slack 500: a ttl of 200 from 100 is over by 800 at the latest.
    let mut t = T::new();
    t.send(100, 1, [5, 5, 5], Some("a"), false, Some(200))
        .frame(900, [5, 5, 5], 1)
        .result(910, Some("a"), "ok");
    let r = t.check();
    assert_eq!(rules(&r), [Rule::NoLateExecution], "{r}");
    assert!(r.violations[0].message.contains("expired"));

    let mut t = T::new();
    t.send(100, 1, [5, 5, 5], Some("a"), false, Some(200))
        .frame(750, [5, 5, 5], 1)
        .result(760, Some("a"), "ok");
    assert!(t.check().ok());

    // The ttl runs from the gateway's receipt: a command held by a half-open link until 3000 may
    // run until 3000 + slack + ttl.
    let mut t = T::new();
    t.fault(
        50,
        1,
        Fault::ProxyHalfOpen {
            ms: 2950,
            noticed: false,
        },
        3000,
    );
    t.send(100, 1, [5, 5, 5], Some("a"), false, Some(200));
    t.trace.records.sort_by_key(|r| r.at);
    t.frame(3600, [5, 5, 5], 1).result(3610, Some("a"), "ok");
    assert!(t.check().ok(), "{}", t.check());
    t.frame(3800, [5, 5, 5], 2);
    assert_eq!(rules(&t.check()), [Rule::NoLateExecution]);
}

#[test]
fn a_retained_command_never_runs() {
    let mut t = T::new();
    t.send(100, 1, [7, 7, 7], Some("r"), true, None)
        .rejected(600, "r")
        .rejected(900, "r");
    assert!(t.check().ok(), "a rejection per replay is fine");

    let mut t = T::new();
    t.send(100, 1, [7, 7, 7], Some("r"), true, None)
        .frame(600, [7, 7, 7], 3)
        .result(610, Some("r"), "ok");
    let r = t.check();
    assert_eq!(
        rules(&r),
        [Rule::RetainedNeverRuns, Rule::RetainedNeverRuns],
        "{r}"
    );
}

#[test]
fn availability_must_go_offline_and_back() {
    let mut t = T::new();
    t.fault(100, 1, Fault::GatewayKill { down_ms: 100 }, 900)
        .received(950, AVAIL, "online");
    let r = t.check();
    assert_eq!(rules(&r), [Rule::Availability], "{r}");
    assert!(r.violations[0].message.contains("did not go offline"));

    let mut t = T::new();
    t.at(
        100,
        Entry::FaultBegin {
            fault: 1,
            what: Fault::BrokerKill { down_ms: 100 },
        },
    )
    .at(300, Entry::RecorderConnected)
    .received(400, AVAIL, "online")
    .at(
        400,
        Entry::Recovered {
            fault: 1,
            how: "online".into(),
        },
    );
    assert!(t.check().ok(), "{}", t.check());

    let mut t = T::new();
    t.at(
        100,
        Entry::FaultBegin {
            fault: 1,
            what: Fault::CanDown { ms: 100 },
        },
    );
    let r = t.check();
    assert_eq!(rules(&r), [Rule::Availability]);
    assert!(r.violations[0].message.contains("never recovered"));
}

#[test]
fn a_checkpoint_finds_every_difference() {
    let truth = vec![element("111", [255, 0, 0]), mobile("2", Some(("111", 3)))];
    let good = vec![
        online(),
        doc(
            "111",
            true,
            [255, 0, 0],
            true,
            r#"{"port":3,"peer":"2","peer_port":0}"#,
        ),
        doc(
            "2",
            true,
            [0, 0, 0],
            false,
            r#"{"port":0,"peer":"111","peer_port":3}"#,
        ),
    ];
    let run = |retained: Vec<(String, String)>, truth: Vec<Element>| {
        let mut t = T::new();
        t.at(0, Entry::Truth(truth.clone())).at(
            5000,
            Entry::Checkpoint {
                fault: None,
                truth,
                retained,
            },
        );
        t.check()
    };
    let r = run(good.clone(), truth.clone());
    assert!(r.ok(), "{r}");

    let mut wrong_led = good.clone();
    wrong_led[1] = doc(
        "111",
        true,
        [0, 0, 255],
        true,
        r#"{"port":3,"peer":"2","peer_port":0}"#,
    );
    let r = run(wrong_led, truth.clone());
    assert_eq!(rules(&r), [Rule::Convergence], "{r}");
    assert!(r.violations[0].message.contains("LED"));

    let mut no_link = good.clone();
    no_link[1] = doc("111", true, [255, 0, 0], true, "");
    let r = run(no_link, truth.clone());
    assert_eq!(rules(&r), [Rule::Convergence], "{r}");
    assert!(r.violations[0].message.contains("connections"));

    let mut relay = good.clone();
    relay[1] = doc(
        "111",
        true,
        [255, 0, 0],
        false,
        r#"{"port":3,"peer":"2","peer_port":0}"#,
    );
    assert_eq!(rules(&run(relay, truth.clone())), [Rule::Convergence]);

    let missing = vec![good[0].clone(), good[1].clone()];
    let r = run(missing, truth.clone());
    assert_eq!(rules(&r), [Rule::Convergence], "{r}");
    assert!(r.violations[0].message.contains("no retained document"));

    let offline = vec![
        (AVAIL.to_string(), "offline".to_string()),
        good[1].clone(),
        good[2].clone(),
    ];
    assert_eq!(rules(&run(offline, truth.clone())), [Rule::Availability]);

    // A node gone long ago must not be online in its document.
    let mut gone = truth.clone();
    gone[1] = Element {
        powered: false,
        ..gone[1].clone()
    };
    gone[0].relay = true;
    let stale = vec![
        online(),
        doc("111", true, [255, 0, 0], true, ""),
        doc("2", true, [0, 0, 0], false, ""),
    ];
    let r = run(stale, gone);
    assert_eq!(rules(&r), [Rule::Convergence], "{r}");
    assert!(r.violations[0].message.contains("without power"), "{r}");
}

#[test]
fn a_node_that_just_vanished_may_still_be_online() {
    let truth = vec![element("111", [255, 0, 0]), mobile("2", Some(("111", 3)))];
    let mut gone = truth.clone();
    gone[1].powered = false;
    let mut t = T::new();
    t.at(0, Entry::Truth(truth))
        .at(4000, Entry::Truth(gone.clone()))
        .at(
            5000,
            Entry::Checkpoint {
                fault: None,
                truth: gone,
                retained: vec![
                    online(),
                    doc(
                        "111",
                        true,
                        [255, 0, 0],
                        true,
                        r#"{"port":3,"peer":"2","peer_port":0}"#,
                    ),
                    doc(
                        "2",
                        true,
                        [0, 0, 0],
                        false,
                        r#"{"port":0,"peer":"111","peer_port":3}"#,
                    ),
                ],
            },
        );
    let r = t.check();
    assert!(
        r.ok(),
        "lost detection takes lost_after health periods: {r}"
    );
}

#[test]
fn a_node_that_vanished_while_the_gateway_was_blind_is_given_the_lost_time_after() {
    // 2 loses power during a CAN outage (1000..8000): the gateway cannot count its misses until
    // 8000, so at 9000 it may still show it online; at 8000 + the lost time it may not.
    let truth = vec![element("111", [255, 0, 0]), mobile("2", Some(("111", 3)))];
    let mut gone = truth.clone();
    gone[1].powered = false;
    let checkpoint = |t: &mut T, at: Ms| {
        t.at(
            at,
            Entry::Checkpoint {
                fault: Some(1),
                truth: gone.clone(),
                retained: vec![
                    online(),
                    doc(
                        "111",
                        true,
                        [255, 0, 0],
                        true,
                        r#"{"port":3,"peer":"2","peer_port":0}"#,
                    ),
                    doc(
                        "2",
                        true,
                        [0, 0, 0],
                        false,
                        r#"{"port":0,"peer":"111","peer_port":3}"#,
                    ),
                ],
            },
        );
    };
    let mut t = T::new();
    t.at(0, Entry::Truth(truth))
        .fault(1000, 1, Fault::CanDown { ms: 6000 }, 8000)
        .at(2000, Entry::Truth(gone.clone()));
    t.trace.records.sort_by_key(|r| r.at);
    checkpoint(&mut t, 9000);
    let r = t.check();
    assert!(r.ok(), "{r}");
    checkpoint(&mut t, 8000 + 4 * 500 + 500 + 1);
    let r = t.check();
    assert_eq!(rules(&r), [Rule::Convergence, Rule::Convergence], "{r}");
}

#[test]
fn the_report_names_the_trace_around_a_violation() {
    let mut t = T::new();
    t.led(100, 1, [9, 9, 9], Some("a"))
        .result(1100, Some("a"), "timeout")
        .frame(1200, [9, 9, 9], 1)
        .received(
            1300,
            EVENTS,
            r#"{"event":"node_lost","payload":{"id":"111","missed":3,"last_seen_ms":1}}"#,
        );
    let text = assert_contract(&t.trace).unwrap_err();
    assert!(text.contains("1 violations"), "{text}");
    assert!(text.contains("trace around 1200 ms"), "{text}");
    assert!(text.contains(r#""kind":"frame""#), "{text}");
    let story = text.split("the island's story:").nth(1).unwrap_or_default();
    assert!(story.contains("1300 {\"event\":\"node_lost\""), "{text}");
    assert!(!story.contains("command_result"), "{text}");
}

/// A state document of 111 as the gateway publishes it, with `version` and `led` as given.
fn state_111(version: &str, led: &str) -> String {
    format!(
        r#"{{"id":"111","online":true,"role":"static","ports":6,"version":{version},"firmware":{{"version":"0.1.0","trial":false,"image_hash":"00000000000000"}},"uid":"0123456789abcdef01234567","led":{led},"buzzer":{{"mode":"off"}},"relay":false,"loops":[],"connections":[],"reported":null,"last_seen_ms":0,"first_seen_ms":0}}"#
    )
}

const STATE_111: &str = "t/ihex/node/111/state";
const RED: &str = r##"{"mode":"steady","color":"#ff0000","brightness":255}"##;

#[test]
fn a_state_document_that_knows_less_than_before_is_found() {
    let mut t = T::new();
    t.received(100, STATE_111, &state_111("\"1.3\"", RED))
        .fault(200, 1, Fault::GatewayKill { down_ms: 100 }, 600)
        .received(300, AVAIL, "offline")
        .received(600, AVAIL, "online");
    t.trace.records.sort_by_key(|r| r.at);
    // The restarted gateway's first document, before it read 111 back: half-known.
    t.received(700, STATE_111, &state_111("null", "null"));
    let r = t.check();
    assert_eq!(rules(&r), [Rule::KnowledgeKept], "{r}");
    assert!(
        r.violations[0].message.contains("shows led, version null"),
        "{r}"
    );
    // Known again afterwards is no second violation; the same fields known throughout are none.
    t.received(800, STATE_111, &state_111("\"1.3\"", RED));
    assert_eq!(rules(&t.check()), [Rule::KnowledgeKept]);
}

#[test]
fn actuators_may_be_unknown_again_only_after_the_node_restarted() {
    let rebooted = r#"{"event":"node_rebooted","payload":{"id":"111","reset":"power_on","version":"1.3","role":"static"}}"#;
    let mut t = T::new();
    t.received(100, STATE_111, &state_111("\"1.3\"", RED))
        .received(200, EVENTS, rebooted)
        .received(210, STATE_111, &state_111("\"1.3\"", "null"));
    assert!(t.check().ok(), "{}", t.check());
    // A power cycle the harness made counts the same; what a node is stays known even then.
    let mut t = T::new();
    t.received(100, STATE_111, &state_111("\"1.3\"", RED)).at(
        200,
        Entry::FaultBegin {
            fault: 1,
            what: Fault::NodeReset { node: "111".into() },
        },
    );
    t.received(300, STATE_111, &state_111("\"1.3\"", "null"));
    assert!(rules(&t.check()).iter().all(|r| *r != Rule::KnowledgeKept));
    t.received(400, STATE_111, &state_111("null", "null"));
    assert_eq!(
        rules(&t.check())
            .into_iter()
            .filter(|r| *r == Rule::KnowledgeKept)
            .count(),
        1
    );
    // A forgotten node's emptied document, and its next one, claim nothing.
    let mut t = T::new();
    t.received(100, STATE_111, &state_111("\"1.3\"", RED))
        .received(200, STATE_111, "")
        .received(300, STATE_111, &state_111("null", "null"));
    assert!(t.check().ok(), "{}", t.check());
}

#[test]
fn a_fault_for_a_docking_that_completed_is_found() {
    let fault = r#"{"event":"fault","payload":{"node":"3","code":"unexpected_handshake","arg":1,"detail":0,"message":"handshake from 3 (its port 1) ignored: no docking is pending","suppressed":0}}"#;
    let connected = r#"{"event":"new_connection","payload":{"n":{"id":"3","port":1},"n-1":{"id":"112","port":2}}}"#;
    let mut t = T::new();
    t.received(1000, EVENTS, fault)
        .received(1018, EVENTS, connected);
    let r = t.check();
    assert_eq!(rules(&r), [Rule::NoFalseFault], "{r}");
    // A handshake that stayed unmatched past the docking timeout was a real fault.
    let mut t = T::new();
    t.received(1000, EVENTS, fault)
        .received(9000, EVENTS, connected);
    assert!(t.check().ok(), "{}", t.check());
    // Another element's docking does not make it false.
    let mut t = T::new();
    t.received(1000, EVENTS, fault).received(
        1018,
        EVENTS,
        &connected.replace(r#""id":"3""#, r#""id":"2""#),
    );
    assert!(t.check().ok(), "{}", t.check());
}
