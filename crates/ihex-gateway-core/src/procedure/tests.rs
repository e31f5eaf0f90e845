//! Procedures: the run's state machine against every ordering of dock, undock, timeout, cancel and
//! lost (unit and property tests), and the bridge's glue from the `procedure` command to frames,
//! events, the lease and the procedures document.

use std::time::{Duration, Instant};

use ihex_proto::{LedCommand, Message, Packet, Rgb};
use proptest::prelude::*;
use serde_json::{json, Value};

use super::*;
use crate::bridge::test_support::*;
use crate::bridge::Bridge;
use crate::event::End;

const GREEN: LedCommand = LedCommand::Steady {
    color: Rgb::new(0, 255, 0),
    brightness: 255,
};

fn conn(mobile: u16, node: u16, p: u8) -> Connection {
    Connection {
        n: End {
            id: HexId(id(mobile)),
            port: 0,
        },
        n_1: End {
            id: HexId(id(node)),
            port: p,
        },
    }
}

fn docked_step(node: u16, p: Option<u8>, mobile: Option<u16>, secs: u64) -> Step {
    Step {
        text: Some(format!("dock on {node:x}")),
        light: vec![id(node)],
        led: GREEN,
        beep: false,
        wait: Wait::Docked {
            node: id(node),
            port: p.map(port),
            mobile: mobile.map(id),
        },
        timeout: Duration::from_secs(secs),
    }
}

fn undocked_step(node: u16, p: Option<u8>, secs: u64) -> Step {
    Step {
        wait: Wait::Undocked {
            node: id(node),
            port: p.map(port),
            mobile: None,
        },
        ..docked_step(node, p, None, secs)
    }
}

/// The sample handover: dock 2 on 111 port 3, take it off again, dock it on 112 (any port).
fn handover() -> Spec {
    Spec {
        name: "handover".into(),
        steps: vec![
            docked_step(0x111, Some(3), Some(2), 60),
            undocked_step(0x111, Some(3), 60),
            docked_step(0x112, None, Some(2), 60),
        ],
    }
}

fn events(actions: &[Action]) -> Vec<String> {
    actions
        .iter()
        .map(|a| match a {
            Action::Light { nodes, .. } => format!("light {}", nodes[0]),
            Action::Clear { nodes, .. } => format!("clear {}", nodes[0]),
            Action::Step(s) => format!("step {} {:?}", s.step, s.state),
            Action::Mismatch(m) => format!("mismatch {} {}", m.step, m.got),
            Action::Ended(e) => format!("ended {:?}", e.outcome),
        })
        .collect()
}

#[test]
fn three_steps_confirmed_by_dockings_in_order() {
    let t0 = Instant::now();
    let clock = WallClock::default();
    let (mut run, a) = Run::start(1, handover(), Some("p".into()), &[], &clock, t0);
    assert_eq!(events(&a), ["light 111", "step 1 Started"]);
    let c = conn(2, 0x111, 3);
    let a = run.handle_docked(&c, &[c], &clock, t0 + S);
    assert_eq!(
        events(&a),
        ["clear 111", "step 1 Done", "light 111", "step 2 Started"]
    );
    let Action::Step(done) = &a[1] else { panic!() };
    let ev = done.evidence.as_ref().unwrap();
    assert_eq!(
        (ev.connection, ev.after_ms, ev.already),
        (Some(c), 1000, false)
    );
    let a = run.handle_undocked(&c, &[], &clock, t0 + 2 * S);
    assert_eq!(
        events(&a),
        ["clear 111", "step 2 Done", "light 112", "step 3 Started"]
    );
    let c2 = conn(2, 0x112, 5);
    let a = run.handle_docked(&c2, &[c2], &clock, t0 + 3 * S);
    assert_eq!(events(&a), ["clear 112", "step 3 Done", "ended Done"]);
    let Action::Ended(e) = &a[2] else { panic!() };
    assert_eq!(
        (e.steps_done, e.of, e.duration_ms, e.request_id.as_deref()),
        (3, 3, 3000, Some("p"))
    );
    assert!(run.ended() && run.deadline().is_none());
    assert!(run.handle_timeout(t0 + 100 * S).is_empty());
}

#[test]
fn a_wrong_docking_is_reported_not_taken() {
    let t0 = Instant::now();
    let clock = WallClock::default();
    let (mut run, _) = Run::start(1, handover(), None, &[], &clock, t0);
    for wrong in [conn(2, 0x111, 4), conn(3, 0x111, 3), conn(2, 0x112, 3)] {
        let a = run.handle_docked(&wrong, &[wrong], &clock, t0 + S);
        assert_eq!(events(&a), ["mismatch 1 docked"], "{wrong:?}");
    }
    assert_eq!(run.view(t0 + S).unwrap().step, 1);
    // Undocking elsewhere is nobody's business; from the element waited on, it is reported.
    assert!(run
        .handle_undocked(&conn(2, 0x112, 3), &[], &clock, t0 + S)
        .is_empty());
    let a = run.handle_undocked(&conn(3, 0x111, 2), &[], &clock, t0 + S);
    assert_eq!(events(&a), ["mismatch 1 undocked"]);
}

#[test]
fn a_step_times_out_at_its_deadline_exactly() {
    let t0 = Instant::now();
    let clock = WallClock::default();
    let (mut run, _) = Run::start(1, handover(), None, &[], &clock, t0);
    assert_eq!(run.deadline(), Some(t0 + 60 * S));
    assert!(run.handle_timeout(t0 + 60 * S - MS).is_empty());
    let a = run.handle_timeout(t0 + 60 * S);
    assert_eq!(
        events(&a),
        ["clear 111", "step 1 TimedOut", "ended TimedOut"]
    );
    let Action::Ended(e) = &a[2] else { panic!() };
    assert_eq!(e.steps_done, 0);
    assert_eq!(
        e.reason.as_deref(),
        Some("nothing confirmed the step within 60 s")
    );
}

#[test]
fn cancel_and_lost_end_the_procedure_once() {
    let t0 = Instant::now();
    let clock = WallClock::default();
    let (mut run, _) = Run::start(1, handover(), Some("p".into()), &[], &clock, t0);
    let a = run.stop(
        StepOutcome::Cancelled,
        "cancelled by procedure_cancel".into(),
        Some("c".into()),
        t0 + S,
    );
    assert_eq!(
        events(&a),
        ["clear 111", "step 1 Cancelled", "ended Cancelled"]
    );
    let Action::Ended(e) = &a[2] else { panic!() };
    assert_eq!(e.request_id.as_deref(), Some("c"), "the cancel's answer");
    assert!(run
        .stop(StepOutcome::Cancelled, "again".into(), None, t0 + S)
        .is_empty());

    let (mut run, _) = Run::start(2, handover(), None, &[], &clock, t0);
    // Not an element of step 1 (112 is step 3's; the mobile element is heard only once docked):
    // nothing.
    assert!(run.handle_lost(id(0x112), t0 + S).is_empty());
    assert!(run.handle_lost(id(2), t0 + S).is_empty());
    let a = run.handle_lost(id(0x111), t0 + S);
    assert_eq!(events(&a), ["clear 111", "step 1 Failed", "ended Failed"]);
    let Action::Ended(e) = &a[2] else { panic!() };
    assert_eq!(
        e.reason.as_deref(),
        Some("element 111 was lost (it stopped answering health checks)")
    );
}

#[test]
fn a_condition_that_already_holds_completes_its_step_at_once() {
    let t0 = Instant::now();
    let clock = WallClock::default();
    let c = conn(2, 0x111, 3);
    let spec = Spec {
        name: "x".into(),
        steps: vec![
            docked_step(0x111, Some(3), None, 60),
            undocked_step(0x112, None, 60),
        ],
    };
    let (run, a) = Run::start(1, spec, None, &[c], &clock, t0);
    assert_eq!(
        events(&a),
        [
            "light 111",
            "step 1 Started",
            "clear 111",
            "step 1 Done",
            "light 112",
            "step 2 Started",
            "clear 112",
            "step 2 Done",
            "ended Done"
        ]
    );
    let Action::Step(s) = &a[3] else { panic!() };
    let ev = s.evidence.as_ref().unwrap();
    assert!(ev.already && ev.connection == Some(c));
    let Action::Step(s) = &a[7] else { panic!() };
    assert_eq!(s.evidence.as_ref().unwrap().connection, None);
    assert!(run.ended());
}

/// One input to a run, for the property test.
#[derive(Clone, Debug)]
enum Input {
    /// The docking the current step waits for (or a wrong one when it waits for an undocking).
    DockRight,
    /// A docking on the right element with the wrong mobile element.
    DockWrong,
    /// The undocking the current step waits for, when it waits for one.
    UndockRight,
    /// Time passes by this many seconds.
    Wait(u64),
    /// `procedure_cancel`.
    Cancel,
    /// An element of the procedure is lost (index into its elements).
    Lost(usize),
}

fn input() -> impl Strategy<Value = Input> {
    prop_oneof![
        3 => Just(Input::DockRight),
        1 => Just(Input::DockWrong),
        3 => Just(Input::UndockRight),
        2 => (1u64..40).prop_map(Input::Wait),
        1 => Just(Input::Cancel),
        1 => (0usize..4).prop_map(Input::Lost),
    ]
}

fn spec_of(kinds: &[bool]) -> Spec {
    Spec {
        name: "p".into(),
        steps: kinds
            .iter()
            .enumerate()
            .map(|(i, &dock)| {
                let node = if i % 2 == 0 { 0x111 } else { 0x112 };
                if dock {
                    docked_step(node, Some(3), Some(2), 30)
                } else {
                    undocked_step(node, Some(3), 30)
                }
            })
            .collect(),
    }
}

proptest! {
    /// Whatever the order of dockings, undockings, timeouts, cancels and lost elements: every step
    /// that starts has exactly one outcome before the next starts, every light is cleared, the
    /// procedure ends exactly once and says nothing after, a step is done only by its own
    /// condition, and the procedure is `done` only when all its steps are.
    #[test]
    fn every_ordering_has_one_outcome_per_step_and_one_end(
        kinds in proptest::collection::vec(any::<bool>(), 1..5),
        inputs in proptest::collection::vec(input(), 0..30),
    ) {
        let t0 = Instant::now();
        let clock = WallClock::default();
        let spec = spec_of(&kinds);
        let elements = spec.static_elements();
        let mut now = t0;
        let mut connections: Vec<Connection> = Vec::new();
        let (mut run, first) = Run::start(1, spec, None, &connections, &clock, now);
        let mut all = first;
        for i in inputs {
            let ended_before = run.ended();
            let a = match i {
                Input::DockRight | Input::DockWrong => {
                    let (node, mobile) = match run.current().map(|s| s.wait.parts()) {
                        Some((n, _, _)) => (n, if matches!(i, Input::DockRight) { 2 } else { 7 }),
                        None => (id(0x111), 2),
                    };
                    let c = conn(mobile, node.get(), 3);
                    if connections.iter().any(|x| x.n_1 == c.n_1 || x.n == c.n) {
                        continue;
                    }
                    connections.push(c);
                    let right = run.matches_docked(&c);
                    let a = run.handle_docked(&c, &connections, &clock, now);
                    if !right {
                        prop_assert!(a.iter().all(|x| !matches!(x, Action::Step(s) if s.state == StepState::Done)));
                    }
                    a
                }
                Input::UndockRight => {
                    let Some(k) = (0..connections.len()).find(|&k| run.matches_undocked(&connections[k])) else {
                        continue;
                    };
                    let c = connections.remove(k);
                    run.handle_undocked(&c, &connections, &clock, now)
                }
                Input::Wait(s) => {
                    now += Duration::from_secs(s);
                    run.handle_timeout(now)
                }
                Input::Cancel => run.stop(StepOutcome::Cancelled, "cancel".into(), None, now),
                Input::Lost(k) => run.handle_lost(elements[k % elements.len()], now),
            };
            if ended_before {
                prop_assert!(a.is_empty(), "actions after the end: {:?}", events(&a));
            }
            all.extend(a);
        }
        let a = run.stop(StepOutcome::Cancelled, "end of test".into(), None, now);
        all.extend(a);
        let log = events(&all);
        // Started / outcome alternate, step numbers ascending by one.
        let mut open: Option<usize> = None;
        let mut last_done = 0;
        let mut lit = 0i32;
        let mut ends = Vec::new();
        for a in &all {
            match a {
                Action::Light { .. } => { prop_assert_eq!(lit, 0, "{:?}", log); lit += 1; }
                Action::Clear { .. } => { prop_assert_eq!(lit, 1, "{:?}", log); lit -= 1; }
                Action::Step(s) if s.state == StepState::Started => {
                    prop_assert!(open.is_none(), "{:?}", log);
                    prop_assert_eq!(s.step, last_done + 1, "{:?}", log);
                    open = Some(s.step);
                }
                Action::Step(s) => {
                    prop_assert_eq!(open, Some(s.step), "{:?}", log);
                    open = None;
                    if s.state == StepState::Done {
                        prop_assert!(s.evidence.is_some());
                        last_done = s.step;
                    }
                }
                Action::Mismatch(_) => {}
                Action::Ended(e) => {
                    prop_assert!(open.is_none(), "{:?}", log);
                    ends.push(e.clone());
                }
            }
        }
        prop_assert_eq!(lit, 0, "a light left on: {:?}", log);
        prop_assert_eq!(ends.len(), 1, "{:?}", log);
        let e = &ends[0];
        prop_assert_eq!(e.steps_done, last_done);
        prop_assert_eq!(e.outcome == StepOutcome::Done, last_done == kinds.len(), "{:?}", log);
        prop_assert!(matches!(all.last(), Some(Action::Ended(_))));
    }
}

// The bridge's glue.

fn led_to(out: &Out, n: u16) -> Vec<LedCommand> {
    out.sent
        .iter()
        .filter(|p| p.dest == id(n))
        .filter_map(|p| match p.msg {
            Message::LedSet { cmd, .. } => Some(cmd),
            _ => None,
        })
        .collect()
}

fn handover_json() -> Value {
    json!({"cmd": "procedure", "request_id": "p1", "name": "sample-handover", "steps": [
        {"text": "Place the carrier on 111", "node": "111", "port": 3, "mobile": "2",
         "wait": "docked", "color": "green", "blink": {"period_ms": 500}, "beep": true,
         "timeout_s": 60},
        {"text": "Take it off", "node": "111", "port": 3, "wait": "undocked", "color": "yellow"},
        {"text": "Place it on 112", "node": "112", "mobile": "2", "wait": "docked",
         "color": "green", "timeout_s": 60}
    ]})
}

fn undock(b: &mut Bridge, node: u16, p: u8, now: Instant) -> Out {
    b.handle_packet(
        Packet::report(id(node), Message::DockRemoved { port: port(p) }),
        now,
    );
    drain(b)
}

#[test]
fn a_procedure_command_runs_lights_leases_and_is_confirmed_by_dockings() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112, 2]);
    let out = command(&mut b, handover_json(), t0 + MS);
    let started = out.one("procedure_started");
    assert_eq!(
        started,
        &json!({"request_id": "p1", "id": 1, "name": "sample-handover", "steps": 3,
                "nodes": ["111", "112"], "lease": 1})
    );
    assert_eq!(out.one("procedure_step")["state"], "started");
    assert!(matches!(
        led_to(&out, 0x111)[..],
        [LedCommand::Blink { .. }]
    ));
    assert!(out
        .sent
        .iter()
        .any(|p| p.dest == id(0x111) && matches!(p.msg, Message::BuzzerSet { .. })));
    assert_eq!(
        out.leases.last().unwrap()["leases"][0]["owner"],
        "procedure 1 (sample-handover)"
    );
    let doc = out.procedures.last().unwrap();
    assert_eq!(doc["procedures"][0]["step"], 1);
    assert_eq!(doc["procedures"][0]["text"], "Place the carrier on 111");
    // Another client's command to a held element is refused, naming the procedure.
    let out = command(
        &mut b,
        json!({"cmd": "led", "node": "111", "color": "red"}),
        t0 + MS,
    );
    let reason = out.one("command_rejected")["reason"]
        .as_str()
        .unwrap()
        .to_owned();
    assert!(
        reason.starts_with("111 is leased by procedure 1 (sample-handover)"),
        "{reason}"
    );
    // A wrong docking: reported, not taken.
    let out = dock(&mut b, 0x112, 1, 2, t0 + 2 * MS);
    assert_eq!(out.named("new_connection").len(), 1);
    assert_eq!(out.one("procedure_mismatch")["got"], "docked");
    assert!(out.named("procedure_step").is_empty());
    undock(&mut b, 0x112, 1, t0 + 3 * MS);
    // The right one: step 1 done with evidence, step 2 lights.
    let out = dock(&mut b, 0x111, 3, 2, t0 + 4 * MS);
    assert_eq!(
        out.raw_named("new_connection"),
        [
            r#"{"event":"new_connection","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
        ],
        "the docking events' shape is the seed's"
    );
    let steps = out.named("procedure_step");
    assert_eq!(steps.len(), 2);
    assert_eq!(steps[0]["payload"]["state"], "done");
    assert_eq!(
        steps[0]["payload"]["evidence"]["connection"],
        json!({"n": {"id": "2", "port": 0}, "n-1": {"id": "111", "port": 3}})
    );
    assert_eq!(
        (
            steps[1]["payload"]["step"].clone(),
            steps[1]["payload"]["state"].clone()
        ),
        (json!(2), json!("started"))
    );
    assert_eq!(led_to(&out, 0x111).len(), 2, "off, then step 2's colour");
    let out = undock(&mut b, 0x111, 3, t0 + 5 * MS);
    assert_eq!(out.named("procedure_step").len(), 2);
    let out = dock(&mut b, 0x112, 4, 2, t0 + 6 * MS);
    let ended = out.one("procedure_ended");
    assert_eq!(
        (
            ended["outcome"].clone(),
            ended["steps_done"].clone(),
            ended["request_id"].clone()
        ),
        (json!("done"), json!(3), json!("p1"))
    );
    assert_eq!(led_to(&out, 0x112), [LedCommand::Off]);
    assert_eq!(
        out.leases.last().unwrap(),
        &json!({"leases": []}),
        "its lease released"
    );
    assert_eq!(out.procedures.last().unwrap(), &json!({"procedures": []}));
    assert_eq!(b.timers().next_timeout(), Some(b.poll_timeout()));
}

#[test]
fn cancel_timeout_and_limits() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112, 2]);
    // As `max_procedures = 1` configures it.
    b.procedures = Procedures::new(1);
    command(&mut b, handover_json(), t0);
    let other =
        json!({"cmd": "procedure", "steps": [{"node": "2", "wait": "docked", "color": "red"}]});
    let out = command(&mut b, other, t0);
    assert!(out.one("command_rejected")["reason"]
        .as_str()
        .unwrap()
        .starts_with("procedure: 1 procedures are running"));
    let out = command(
        &mut b,
        json!({"cmd": "procedure_cancel", "id": 9, "request_id": "c0"}),
        t0,
    );
    assert_eq!(
        out.one("command_rejected")["reason"],
        "procedure_cancel: no procedure 9 is running; see the retained procedures document for the ones that are"
    );
    let out = command(
        &mut b,
        json!({"cmd": "procedure_cancel", "id": 1, "request_id": "c1"}),
        t0 + S,
    );
    let ended = out.one("procedure_ended");
    assert_eq!(
        (ended["outcome"].clone(), ended["request_id"].clone()),
        (json!("cancelled"), json!("c1"))
    );
    assert_eq!(led_to(&out, 0x111), [LedCommand::Off]);
    // The next one times out at its step's deadline.
    let out = command(&mut b, handover_json(), t0 + S);
    assert_eq!(out.one("procedure_started")["id"], 2);
    assert!(b.poll_timeout() <= t0 + 61 * S);
    // Keep the elements online meanwhile.
    let mut k = 2u32;
    while t0 + S * k < t0 + 61 * S {
        b.handle_timeout(t0 + S * k);
        for n in [0x111, 0x112, 2] {
            b.handle_packet(Packet::report(id(n), reply(k as u8, 0)), t0 + S * k);
        }
        assert!(drain(&mut b).named("procedure_ended").is_empty());
        k += 1;
    }
    b.handle_timeout(t0 + 61 * S);
    let out = drain(&mut b);
    assert_eq!(out.one("procedure_ended")["outcome"], "timed_out");
}

#[test]
fn an_element_lost_mid_step_fails_the_procedure_and_a_broken_lease_too() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112, 2]);
    command(&mut b, handover_json(), t0 + MS);
    // 111 (step 1's element) stops answering; 112 and 2 answer.
    let mut ended = None;
    for k in 1..=4u32 {
        b.handle_timeout(t0 + S * k);
        for n in [0x112, 2] {
            b.handle_packet(Packet::report(id(n), reply(k as u8, 0)), t0 + S * k + MS);
        }
        let out = drain(&mut b);
        if !out.named("procedure_ended").is_empty() {
            assert_eq!(out.one("node_lost")["id"], "111");
            ended = Some(out);
        }
    }
    let out = ended.expect("procedure ended");
    let e = out.one("procedure_ended");
    assert_eq!(e["outcome"], "failed");
    assert_eq!(
        e["reason"],
        "element 111 was lost (it stopped answering health checks)"
    );
    assert_eq!(out.one("procedure_step")["state"], "failed");

    let (mut b, t0) = with_nodes(&[0x111, 0x112, 2]);
    command(&mut b, handover_json(), t0 + MS);
    let out = command(
        &mut b,
        json!({"cmd": "break_lease", "id": 1, "reason": "stuck"}),
        t0 + MS,
    );
    assert_eq!(
        out.one("procedure_ended")["reason"],
        "its lease 1 was broken (break_lease)"
    );
    assert_eq!(out.one("lease_ended")["why"], "broken");
}

#[test]
fn a_stopping_gateway_cancels_its_procedures_and_clears_their_lights() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112, 2]);
    command(&mut b, handover_json(), t0 + MS);
    assert!(b.procedures_running());
    b.cancel_procedures("the gateway stopped", t0 + S);
    let out = drain(&mut b);
    let e = out.one("procedure_ended");
    assert_eq!(
        (e["outcome"].clone(), e["reason"].clone()),
        (json!("cancelled"), json!("the gateway stopped"))
    );
    assert_eq!(led_to(&out, 0x111), [LedCommand::Off]);
    assert!(!b.procedures_running());
}

#[test]
fn a_procedure_runs_under_the_senders_own_lease() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112, 2]);
    let out = command(
        &mut b,
        json!({"cmd": "lease", "owner": "run-42", "nodes": "111", "seconds": 600}),
        t0 + MS,
    );
    let token = out.one("lease_granted")["token"]
        .as_str()
        .unwrap()
        .to_owned();
    // Without the token: refused, naming the holder.
    let out = command(&mut b, handover_json(), t0 + MS);
    assert!(out.one("command_rejected")["reason"]
        .as_str()
        .unwrap()
        .starts_with("111 is leased by run-42"));
    let mut with = handover_json();
    with["lease"] = json!(token);
    let out = command(&mut b, with, t0 + MS);
    let started = out.one("procedure_started");
    assert_eq!(started["lease"], 2, "its own lease covers only 112");
    assert_eq!(
        out.leases.last().unwrap()["leases"][1]["nodes"],
        json!(["112"])
    );
}

#[test]
fn bad_steps_are_refused_naming_the_step_and_field() {
    let (mut b, t0) = with_nodes(&[0x111]);
    for (cmd, reason) in [
        (json!({"cmd": "procedure", "steps": []}),
         "procedure: `steps` must be an array of 1 to 64 step objects; got []"),
        (json!({"cmd": "procedure", "steps": [{"node": "111", "wait": "docked"}]}),
         "procedure: step 1: missing `color`: a name (red, green, blue, white, yellow, cyan, magenta, orange, purple, pink, warmwhite, black, off), \"#rrggbb\" or [r, g, b] with 0-255 each, or `\"off\": true`"),
        (json!({"cmd": "procedure", "steps": [{"node": "111", "wait": "docked", "color": "red"},
                                                {"node": "111", "wait": "near", "color": "red"}]}),
         "procedure: step 2: `step.wait` must be \"docked\" or \"undocked\"; got \"near\""),
        (json!({"cmd": "procedure", "steps": [{"node": "111", "wait": "docked", "color": "red", "port": 9}]}),
         "procedure: step 1: `step.port` must be an integer 0 to 7; got 9"),
        (json!({"cmd": "procedure", "steps": [{"node": "999", "wait": "docked", "color": "red"}]}),
         "unknown node 999; known: 111"),
    ] {
        let out = command(&mut b, cmd.clone(), t0 + MS);
        assert_eq!(out.one("command_rejected")["reason"], reason, "{cmd}");
    }
}
