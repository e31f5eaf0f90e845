//! Leases: the table's arithmetic (exact expiry, renew, release, break, overlaps), and every
//! command path of the bridge refusing without the token and accepting with it.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use ihex_proto::{Kind, Packet};
use proptest::prelude::*;
use serde_json::{json, Value};

use super::*;
use crate::bridge::test_support::*;
use crate::bridge::{Bridge, Delivery};
use crate::ha::HaConfig;
use crate::topic::Topics;

const NS: Duration = Duration::from_nanos(1);

fn nodes(ids: &[u16]) -> Scope {
    Scope::Nodes(ids.iter().map(|&n| id(n)).collect())
}

fn take(t: &mut LeaseTable, owner: &str, scope: Scope, secs: u64, now: Instant) -> Lease {
    t.take(
        owner.into(),
        None,
        scope,
        Duration::from_secs(secs),
        &WallClock::default(),
        now,
    )
    .unwrap()
    .clone()
}

#[test]
fn a_lease_ends_at_the_exact_instant() {
    let t0 = Instant::now();
    let clock = WallClock::default();
    let mut t = LeaseTable::new();
    let l = take(&mut t, "run-42", nodes(&[0x111]), 60, t0);
    let end = t0 + 60 * S;
    assert!(t.check(id(0x111), None, &clock, end - NS).is_err());
    assert!(t.check(id(0x111), Some(&l.token), &clock, end - NS).is_ok());
    // At the end itself, before the timer has run: accepted.
    assert!(t.check(id(0x111), None, &clock, end).is_ok());
    assert_eq!(t.next_deadline(), Some(end));
    assert!(t.expire(end - NS).is_empty());
    assert_eq!(t.expire(end), vec![l]);
    assert_eq!(t.next_deadline(), None);
    // Other elements were never held.
    assert!(t.check(id(0x112), None, &clock, t0).is_ok());
}

#[test]
fn renew_extends_from_now_and_release_takes_the_token_only() {
    let t0 = Instant::now();
    let mut t = LeaseTable::new();
    let l = take(&mut t, "run-42", nodes(&[0x111]), 60, t0);
    let renewed = t.renew(&l.token, 10 * S, t0 + 30 * S).unwrap().expires;
    assert_eq!(renewed, t0 + 40 * S, "from now, not from the old end");
    assert!(matches!(
        t.renew("wrong", 10 * S, t0),
        Err(LeaseError::UnknownToken { cmd: "renew" })
    ));
    assert!(t.release("wrong", t0).is_err());
    assert!(
        t.release(&l.id.to_string(), t0).is_err(),
        "the id is not the token"
    );
    // An ended lease cannot be renewed, even before its timer has run.
    assert!(t.renew(&l.token, 10 * S, t0 + 40 * S).is_err());
    let l2 = take(&mut t, "run-43", nodes(&[0x112]), 60, t0 + 41 * S);
    assert_eq!(t.release(&l2.token, t0 + 41 * S).unwrap().id, l2.id);
    assert!(t.release(&l2.token, t0 + 41 * S).is_err(), "released once");
}

#[test]
fn break_names_the_lease_by_its_id() {
    let t0 = Instant::now();
    let mut t = LeaseTable::new();
    let l = take(&mut t, "run-42", Scope::Island, 60, t0);
    assert!(matches!(
        t.break_lease(l.id + 1, t0),
        Err(LeaseError::UnknownId { .. })
    ));
    assert_eq!(t.break_lease(l.id, t0).unwrap().owner, "run-42");
    assert!(t.check_all(None, &WallClock::default(), t0).is_ok());
}

#[test]
fn overlapping_requests_are_refused_naming_the_holder() {
    let t0 = Instant::now();
    let mut clock = WallClock::default();
    clock.set(
        UNIX_EPOCH + Duration::from_secs(14 * 3600 + 5 * 60 + 10 - 60),
        t0,
    );
    let mut t = LeaseTable::new();
    t.take(
        "run-42".into(),
        Some("sample prep".into()),
        nodes(&[0x111, 2]),
        60 * S,
        &clock,
        t0,
    )
    .unwrap();
    let refused = |t: &mut LeaseTable, scope| {
        t.take("other".into(), None, scope, S, &clock, t0)
            .unwrap_err()
            .to_string()
    };
    assert_eq!(
        refused(&mut t, nodes(&[0x112, 2])),
        "lease: 2 is leased by run-42 until 14:05:10 UTC (note: sample prep); wait for its end or \
         ask its owner to release it"
    );
    assert!(refused(&mut t, Scope::Island).contains("111 is leased by run-42"));
    assert!(t
        .take("other".into(), None, nodes(&[0x112]), S, &clock, t0)
        .is_ok());
    assert_eq!(
        t.check(id(0x111), None, &clock, t0).unwrap_err().to_string(),
        "111 is leased by run-42 until 14:05:10 UTC (note: sample prep); send the lease's token in \
         `lease`, wait for its end, or ask whoever may send `break_lease`"
    );
    // Once the lease ended, the same request is granted.
    assert!(t
        .take("other".into(), None, nodes(&[2]), S, &clock, t0 + 60 * S)
        .is_ok());
}

#[test]
fn wall_clock_formats_and_tokens_differ() {
    let t0 = Instant::now();
    let mut clock = WallClock::default();
    clock.set(UNIX_EPOCH + Duration::from_secs(1_795_615_510), t0);
    assert_eq!(clock.rfc3339(t0).as_deref(), Some("2026-11-25T14:05:10Z"));
    clock.set(UNIX_EPOCH + Duration::from_secs(951_782_400), t0);
    assert_eq!(
        clock.rfc3339(t0 + S).as_deref(),
        Some("2000-02-29T00:00:01Z")
    );
    assert_eq!(WallClock::default().rfc3339(t0), None);
    let mut t = LeaseTable::new();
    let a = take(&mut t, "a", nodes(&[1]), 1, t0);
    let b = take(&mut t, "a", nodes(&[3]), 1, t0);
    assert_ne!(a.token, b.token);
    assert_ne!(a.id, b.id);
    assert_eq!(a.token.len(), 32);
}

proptest! {
    /// Whatever leases are taken, renewed, released, broken and expired, an element is refused to a
    /// command without a token exactly when a lease whose end is after `now` covers it, and each
    /// lease's own token always passes its elements.
    #[test]
    fn refusal_is_exactly_a_held_cover(
        ops in prop::collection::vec((0u8..5, 1u16..6, 1u64..50, 0u64..40), 1..30),
        probe in 0u64..200,
    ) {
        let t0 = Instant::now();
        let clock = WallClock::default();
        let mut t = LeaseTable::new();
        let mut model: Vec<Lease> = Vec::new();
        let mut now = t0;
        for (op, n, secs, step) in ops {
            now += Duration::from_secs(step);
            model.retain(|l| l.held(now));
            match op {
                0 => {
                    let scope = if n == 5 { Scope::Island } else { nodes(&[n, n + 1]) };
                    let overlaps = model.iter().any(|l| match (&l.scope, &scope) {
                        (Scope::Island, _) | (_, Scope::Island) => true,
                        (Scope::Nodes(a), Scope::Nodes(b)) => a.iter().any(|x| b.contains(x)),
                    });
                    let got = t.take("o".into(), None, scope, Duration::from_secs(secs), &clock, now);
                    prop_assert_eq!(got.is_err(), overlaps);
                    if let Ok(l) = got {
                        model.push(l.clone());
                    }
                }
                1 if !model.is_empty() => {
                    let i = usize::from(n) % model.len();
                    let l = t.renew(&model[i].token, Duration::from_secs(secs), now).unwrap();
                    prop_assert_eq!(l.expires, now + Duration::from_secs(secs));
                    model[i].expires = l.expires;
                }
                2 if !model.is_empty() => {
                    let i = usize::from(n) % model.len();
                    let token = model.remove(i).token;
                    prop_assert!(t.release(&token, now).is_ok());
                }
                3 if !model.is_empty() => {
                    let i = usize::from(n) % model.len();
                    let lease_id = model.remove(i).id;
                    prop_assert!(t.break_lease(lease_id, now).is_ok());
                }
                // The leases' timer: those ended by now leave the table.
                4 => {
                    for l in t.expire(now) {
                        prop_assert!(!model.iter().any(|m| m.id == l.id));
                    }
                }
                _ => {}
            }
        }
        let at = now + Duration::from_secs(probe);
        for n in 1u16..7 {
            let holder = model.iter().find(|l| l.held(at) && l.scope.covers(id(n)));
            prop_assert_eq!(t.check(id(n), None, &clock, at).is_err(), holder.is_some());
            if let Some(l) = holder {
                prop_assert!(t.check(id(n), Some(&l.token), &clock, at).is_ok());
            }
        }
    }
}

// The bridge: every command path.

fn lease_cmd(b: &mut Bridge, nodes: &str, now: Instant) -> (String, Value) {
    let out = command(
        b,
        json!({"cmd": "lease", "request_id": "L", "owner": "run-42", "note": "sample prep",
               "nodes": nodes, "seconds": 60}),
        now,
    );
    let granted = out.one("lease_granted").clone();
    assert_eq!(out.leases.len(), 1, "the leases document follows");
    (granted["token"].as_str().unwrap().to_owned(), granted)
}

fn rejected(out: &Out) -> String {
    out.one("command_rejected")["reason"]
        .as_str()
        .unwrap()
        .to_owned()
}

#[test]
fn the_json_path_refuses_without_the_token_and_accepts_with_it() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112]);
    let now = t0 + S;
    let (token, granted) = lease_cmd(&mut b, "111", now);
    assert_eq!(granted["request_id"], "L");
    assert_eq!(granted["lease"]["owner"], "run-42");
    assert_eq!(granted["lease"]["nodes"], json!(["111"]));
    assert_eq!(granted["lease"]["remaining_ms"], 60_000);

    let led = json!({"cmd": "led", "node": "111", "color": "red"});
    let out = command(&mut b, led.clone(), now);
    assert!(out.sent.is_empty());
    assert!(
        rejected(&out).starts_with("111 is leased by run-42 for another 60 s (note: sample prep)"),
        "{}",
        rejected(&out)
    );
    // A broadcast would reach 111 as well.
    let out = command(
        &mut b,
        json!({"cmd": "power", "node": "all", "on": true}),
        now,
    );
    assert!(rejected(&out).contains("\"all\" includes 111, which is leased by run-42"));
    // Another element, and reading, are not held.
    let out = command(
        &mut b,
        json!({"cmd": "led", "node": "112", "color": "red"}),
        now,
    );
    assert_eq!(out.sent.len(), 1);
    let out = command(&mut b, json!({"cmd": "list", "request_id": "r"}), now);
    assert_eq!(out.one("node_list")["nodes"].as_array().unwrap().len(), 2);
    assert!(b.node_state(id(0x111), now).is_some());
    // The owner's command carries the token.
    let mut with = led.clone();
    with["lease"] = json!(token);
    let out = command(&mut b, with.clone(), now);
    assert_eq!(out.sent.len(), 1);
    assert_eq!(out.sent[0].dest, id(0x111));
    // A wrong token is no token.
    let mut wrong = led.clone();
    wrong["lease"] = json!("0123");
    assert!(rejected(&command(&mut b, wrong, now)).contains("leased by run-42"));
    // The same JSON through the island view (its POST goes to this input unchanged).
    b.handle_delivered_command(led.to_string().as_bytes(), Delivery::live(now), now);
    assert!(rejected(&drain(&mut b)).contains("leased by run-42"));
    b.handle_delivered_command(with.to_string().as_bytes(), Delivery::live(now), now);
    assert_eq!(drain(&mut b).sent.len(), 1);
}

#[test]
fn the_lease_commands_answer_once_each() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112]);
    let now = t0 + S;
    let (token, granted) = lease_cmd(&mut b, "111,112", now);
    let lease_id = granted["lease"]["id"].clone();
    // Overlap: refused naming the holder.
    let out = command(
        &mut b,
        json!({"cmd": "lease", "owner": "x", "nodes": "112", "seconds": 5}),
        now,
    );
    assert!(rejected(&out).starts_with("lease: 112 is leased by run-42"));
    assert!(out.leases.is_empty());
    // Renew from now.
    let later = now + 50 * S;
    let out = command(
        &mut b,
        json!({"cmd": "renew", "lease": token, "seconds": 30}),
        later,
    );
    assert_eq!(out.one("lease_granted")["lease"]["remaining_ms"], 30_000);
    assert_eq!(b.leases(later + 10 * S).leases[0].remaining_ms, 20_000);
    // Release needs the token.
    let out = command(&mut b, json!({"cmd": "release"}), later);
    assert_eq!(
        rejected(&out),
        "release: missing `lease`: the token `lease_granted` answered"
    );
    let out = command(&mut b, json!({"cmd": "release", "lease": "x"}), later);
    assert!(rejected(&out).starts_with("release: no lease held now has this token"));
    let out = command(
        &mut b,
        json!({"cmd": "release", "lease": token, "request_id": "R"}),
        later,
    );
    let ended = out.one("lease_ended");
    assert_eq!(
        (&ended["request_id"], &ended["why"], &ended["lease"]["id"]),
        (&json!("R"), &json!("released"), &lease_id)
    );
    assert_eq!(out.leases, vec![json!({"leases": []})]);
    let out = command(
        &mut b,
        json!({"cmd": "led", "node": "111", "color": "red"}),
        later,
    );
    assert_eq!(out.sent.len(), 1);
}

#[test]
fn break_and_expiry_are_events_and_clear_the_document() {
    let (mut b, t0) = with_nodes(&[0x111]);
    let now = t0 + S;
    let (_, granted) = lease_cmd(&mut b, "all", now);
    let lease_id = granted["lease"]["id"].as_u64().unwrap();
    let out = command(&mut b, json!({"cmd": "break_lease", "id": lease_id}), now);
    assert_eq!(
        rejected(&out),
        "break_lease: missing `reason`: why it is broken (text)"
    );
    let out = command(
        &mut b,
        json!({"cmd": "break_lease", "id": lease_id, "reason": "run-42 crashed"}),
        now,
    );
    let ended = out.one("lease_ended");
    assert_eq!(ended["why"], "broken");
    assert_eq!(ended["reason"], "run-42 crashed");
    assert_eq!(out.leases, vec![json!({"leases": []})]);

    // Expiry through the bridge's timer table, at the exact instant.
    let (token, _) = lease_cmd(&mut b, "111", now);
    let end = now + 60 * S;
    assert!(b.poll_timeout() <= end);
    let led = json!({"cmd": "identify", "node": "111", "seconds": 1});
    b.handle_timeout(end - NS);
    let out = command(&mut b, led.clone(), end - NS);
    assert!(out.named("lease_ended").is_empty());
    assert!(rejected(&out).contains("leased by run-42"));
    let out = command(&mut b, led, end);
    assert_eq!(
        out.sent.len(),
        1,
        "accepted at the end even before the timer ran"
    );
    b.handle_timeout(end);
    let out = drain(&mut b);
    let ended = out.one("lease_ended");
    assert_eq!(
        (&ended["why"], &ended["request_id"]),
        (&json!("expired"), &Value::Null)
    );
    assert_eq!(out.leases, vec![json!({"leases": []})]);
    // The old token is worth nothing now.
    let out = command(
        &mut b,
        json!({"cmd": "renew", "lease": token, "seconds": 1}),
        end,
    );
    assert!(rejected(&out).starts_with("renew: no lease held now"));
}

#[test]
fn home_assistant_commands_are_refused_on_leased_elements() {
    let t0 = Instant::now();
    let ha = HaConfig {
        topics: Topics::seed(),
        island: None,
        configuration_url: None,
        sw_version: "0".into(),
    };
    let mut b = Bridge::new(crate::bridge::BridgeConfig::default(), t0).with_home_assistant(ha);
    b.handle_timeout(t0);
    drain(&mut b);
    b.handle_packet(Packet::report(id(0x111), reply(0, 0)), t0);
    b.handle_packet(Packet::report(id(0x112), reply(0, 0)), t0);
    drain(&mut b);
    let now = t0 + S;
    lease_cmd(&mut b, "111", now);
    b.handle_ha_command("ihex/ha/111/relay/set", b"ON", now);
    let out = drain(&mut b);
    assert!(out.sent.iter().all(|p| p.msg.kind() != Kind::PowerSet));
    assert_eq!(out.one("command_rejected")["request_id"], "homeassistant");
    assert!(rejected(&out).starts_with("111 is leased by run-42"));
    // Another element still takes Home Assistant's commands.
    b.handle_ha_command("ihex/ha/112/relay/set", b"ON", now);
    let out = drain(&mut b);
    assert!(out.sent.iter().any(|p| p.msg.kind() == Kind::PowerSet));
}

#[test]
fn assign_forget_and_fw_update_respect_leases() {
    let (mut b, t0) = with_nodes(&[0x111, 0x112]);
    let now = t0 + S;
    let (token, _) = lease_cmd(&mut b, "111", now);
    let out = command(&mut b, json!({"cmd": "forget", "node": "111"}), now);
    assert!(rejected(&out).starts_with("111 is leased"));
    let out = command(
        &mut b,
        json!({"cmd": "assign", "uid": "0123456789abcdef01234567", "new_id": "111", "force": true}),
        now,
    );
    assert!(rejected(&out).starts_with("111 is leased"));
    // fw_update: the leased element is left out, and said so; one leased element alone is refused.
    let out = command(
        &mut b,
        json!({"cmd": "fw_update", "image": "a.ihex", "nodes": "111"}),
        now,
    );
    assert!(rejected(&out).starts_with("fw_update: every element is leased: 111 is leased"));
    b.handle_command(
        json!({"cmd": "fw_update", "image": "a.ihex", "nodes": "all"})
            .to_string()
            .as_bytes(),
        now,
    );
    let load = b.poll_fw_load().expect("an image to load");
    assert_eq!(load.nodes, vec![id(0x112)]);
    assert_eq!(load.skipped.len(), 1);
    assert_eq!(load.skipped[0].0, id(0x111));
    assert!(load.skipped[0].1.starts_with("111 is leased by run-42"));
    b.handle_fw_image(load, Err("no such file".into()), now);
    drain(&mut b);
    // With the token, the holder updates its own element.
    b.handle_command(
        json!({"cmd": "fw_update", "image": "a.ihex", "nodes": "111", "lease": token})
            .to_string()
            .as_bytes(),
        now,
    );
    let load = b.poll_fw_load().expect("an image to load");
    assert_eq!(
        (load.nodes.as_slice(), load.skipped.len()),
        ([id(0x111)].as_slice(), 0)
    );
}

#[test]
fn a_start_publishes_no_leases_and_says_so_once() {
    let t0 = Instant::now();
    let mut b = Bridge::new(crate::bridge::BridgeConfig::default(), t0);
    b.handle_wall_clock(SystemTime::now(), t0);
    b.handle_mqtt_connected(t0);
    let out = drain(&mut b);
    assert!(out.one("leases_reset")["reason"]
        .as_str()
        .unwrap()
        .contains("ended with the restart"));
    assert_eq!(out.leases, vec![json!({"leases": []})]);
    // A reconnection republishes the document (a restarted broker may have lost it), without
    // announcing a restart again.
    b.handle_packet(Packet::report(id(0x111), reply(0, 0)), t0);
    drain(&mut b);
    lease_cmd(&mut b, "111", t0);
    b.handle_mqtt_connected(t0 + S);
    let out = drain(&mut b);
    assert!(out.named("leases_reset").is_empty());
    assert_eq!(out.leases.len(), 1);
    assert_eq!(out.leases[0]["leases"][0]["owner"], "run-42");
    assert_eq!(out.leases[0]["leases"][0]["remaining_ms"], 59_000);
    assert!(out.leases[0]["leases"][0]["expires_at"].is_string());
}
