//! The checker: reads a [`Trace`] and lists every way the gateway broke its delivery contract
//! (`docs/gateway.md`, "Delivery contract").
//!
//! Rules, each a [`Rule`]:
//! - **one answer**: every command gets exactly one terminal answer (`command_result`,
//!   `command_rejected`, `node_list`). A command sent while no fault could keep it from the gateway
//!   or its answer from the recorder must be answered within the command timeout (plus slack);
//!   one sent around a fault that breaks the MQTT session may go unanswered, never answered twice
//!   (an identical copy after the session broke is QoS 1 redelivery and is only counted). An answer
//!   to a `request_id` never sent is a violation too.
//! - **no late execution**: a command frame on the bus must belong to a command that may still
//!   run: sent before it, not retained, not past its `ttl_ms`, not already answered with anything
//!   but `ok` (`timeout`, `failed`, `refused`, `expired`, `command_rejected`). A command answered
//!   `failed` ("not sent") has no frame at all. Frames are matched by destination and content (the
//!   harness makes LED and buzzer commands unique; a frame several commands could have produced
//!   is fine when any of them may run).
//! - **retained never runs**: a retained command (the harness sends them only while the gateway is
//!   away, so every delivery is a replay) has no frame and no `ok` answer.
//! - **convergence**: at each checkpoint (2 health periods after a recovery) the retained state
//!   documents equal the island's truth: presence, LED, buzzer, relay, dockings; `online` may lag
//!   only for a node that vanished less than `lost_after + 1` health periods before (counted from
//!   the recovery when it vanished while the gateway's CAN interface was down or it was killed).
//! - **availability**: around a fault that breaks the session, `offline` (the last will, or the
//!   broker itself gone) and then `online`; `online` at every checkpoint; every fault recovered.
//! - **knowledge kept**: no state document shows a field `null` that an earlier document of the
//!   node showed known — a restart, a cut or a read-back never turns a known value into `null`.
//!   What a node is (`role`, `ports`, `version`, `firmware`, `uid`) stays known for good; its
//!   actuators (`led`, `buzzer`, `relay`) may be unknown again only after the node itself restarted
//!   (`node_rebooted`, a power cycle, a mobile element without power) or was forgotten.
//! - **no false fault**: no `unexpected_handshake` fault for a mobile element whose docking
//!   completed (`new_connection` naming it) within the docking timeout after it: a handshake that
//!   overtook its dock report is part of a normal docking.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;

use ihex_gateway_core::command::{self, Command, NodeAction};
use ihex_gateway_core::event::{BuzzerState, Event, NodeState, Outcome};
use ihex_proto::{Message, NodeId, Packet};

use super::trace::{Element, Entry, Fault, Ms, Sent, Trace};

/// Which part of the contract a violation breaks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Rule {
    /// Exactly one terminal answer per command.
    OneAnswer,
    /// No command executes after its answer said it did not, or after it expired.
    NoLateExecution,
    /// A retained command never executes.
    RetainedNeverRuns,
    /// Retained state equals the truth after each fault.
    Convergence,
    /// Availability went offline and back; every fault recovered.
    Availability,
    /// No state document knows less of a node than an earlier one did.
    KnowledgeKept,
    /// No fault event for a docking that completed.
    NoFalseFault,
}

impl fmt::Display for Rule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Rule::OneAnswer => "one answer per command",
            Rule::NoLateExecution => "no execution after a negative answer or expiry",
            Rule::RetainedNeverRuns => "retained commands never run",
            Rule::Convergence => "retained state equals the truth",
            Rule::Availability => "availability offline and back",
            Rule::KnowledgeKept => "no state document less known than before",
            Rule::NoFalseFault => "no fault event for a docking that completed",
        })
    }
}

/// One broken promise.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Violation {
    /// When (the record that shows it).
    pub at: Ms,
    /// Which rule.
    pub rule: Rule,
    /// What happened, in words.
    pub message: String,
}

/// The checker's verdict.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Every violation, by time.
    pub violations: Vec<Violation>,
    /// Commands sent.
    pub commands: usize,
    /// Commands answered exactly once.
    pub answered: usize,
    /// Commands sent around a session-breaking fault that got no answer (allowed).
    pub lost_in_faults: usize,
    /// Identical answers delivered again after a session broke (QoS 1, allowed).
    pub redelivered: usize,
    /// Command frames seen on the bus.
    pub frames: usize,
    /// Checkpoints compared.
    pub checkpoints: usize,
    /// Faults injected.
    pub faults: usize,
}

impl Report {
    /// True when nothing was violated.
    pub fn ok(&self) -> bool {
        self.violations.is_empty()
    }

    /// The violations of one rule.
    pub fn of(&self, rule: Rule) -> Vec<&Violation> {
        self.violations.iter().filter(|v| v.rule == rule).collect()
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{} faults, {} commands ({} answered once, {} lost in faults, {} answers redelivered), \
             {} command frames, {} checkpoints: {} violations",
            self.faults,
            self.commands,
            self.answered,
            self.lost_in_faults,
            self.redelivered,
            self.frames,
            self.checkpoints,
            self.violations.len()
        )?;
        for v in &self.violations {
            writeln!(f, "  at {:>7} ms [{}] {}", v.at, v.rule, v.message)?;
        }
        Ok(())
    }
}

/// The trace lines around `at` (± `window_ms`), for a failure message.
pub fn excerpt(trace: &Trace, at: Ms, window_ms: Ms) -> String {
    trace
        .records
        .iter()
        .filter(|r| r.at + window_ms >= at && r.at <= at + window_ms)
        .filter(|r| !matches!(r.entry, Entry::Truth(_)))
        .map(|r| {
            let line = serde_json::to_string(r).unwrap_or_default();
            if line.chars().count() > 300 {
                format!("  {}…", line.chars().take(300).collect::<String>())
            } else {
                format!("  {line}")
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// The island's story in a run, one line per record: faults and recoveries, island actions,
/// harness notes, availability and the lifecycle and docking events — what a convergence
/// violation is read against (the excerpts around it rarely reach back to the cause).
pub fn story(trace: &Trace) -> String {
    const EVENTS: [&str; 8] = [
        "new_connection",
        "connection_removed",
        "dock_failed",
        "fault",
        "node_lost",
        "node_online",
        "node_rebooted",
        "bus_error",
    ];
    trace
        .records
        .iter()
        .filter_map(|r| {
            let what = match &r.entry {
                Entry::FaultBegin { .. }
                | Entry::FaultEnd { .. }
                | Entry::Recovered { .. }
                | Entry::Island(_)
                | Entry::Note(_) => serde_json::to_string(&r.entry).unwrap_or_default(),
                Entry::Received { topic, payload, .. }
                    if topic.ends_with("availability")
                        || EVENTS
                            .iter()
                            .any(|e| payload.starts_with(&format!(r#"{{"event":"{e}""#))) =>
                {
                    payload.clone()
                }
                _ => return None,
            };
            Some(format!(
                "  {:>7} {}",
                r.at,
                what.chars().take(240).collect::<String>()
            ))
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// How a command was answered.
#[derive(Clone, Debug, PartialEq)]
enum Answer {
    /// `command_result` with this outcome (and its payload for comparing copies).
    Result(Outcome, String),
    /// `command_rejected`.
    Rejected(String),
    /// `node_list`.
    List,
}

impl Answer {
    /// The answer says the command did not (and will not) run.
    fn negative(&self) -> bool {
        match self {
            Answer::Result(o, _) => *o != Outcome::Ok,
            Answer::Rejected(_) => true,
            Answer::List => false,
        }
    }

    fn text(&self) -> String {
        match self {
            Answer::Result(o, reason) => format!("command_result {o:?} {reason}"),
            Answer::Rejected(reason) => format!("command_rejected \"{reason}\""),
            Answer::List => "node_list".into(),
        }
    }
}

struct Answered {
    at: Ms,
    request_id: Option<String>,
    /// `(cmd, node)` of a `command_result`, for answers without `request_id`.
    what: Option<(String, String)>,
    answer: Answer,
    raw: String,
}

/// The faults' windows, from their start to their recovery (or the end of the run).
struct Windows {
    /// Faults that may break the MQTT session.
    breaking: Vec<(Ms, Ms)>,
    /// Proxy delays: (from, to, delay).
    delays: Vec<(Ms, Ms, Ms)>,
}

impl Windows {
    fn new(faults: &BTreeMap<u32, (Ms, Fault)>, recovered: &BTreeMap<u32, Ms>, end: Ms) -> Windows {
        let mut w = Windows {
            breaking: Vec::new(),
            delays: Vec::new(),
        };
        for (n, (begin, f)) in faults {
            let until = recovered.get(n).copied().unwrap_or(end);
            if f.breaks_mqtt() {
                w.breaking.push((*begin, until));
            }
            if let Fault::ProxyDelay { delay_ms, .. } = f {
                w.delays.push((*begin, until, *delay_ms));
            }
        }
        w
    }

    /// A session-breaking fault overlaps `[from, to]`.
    fn breaking(&self, from: Ms, to: Ms) -> bool {
        self.breaking.iter().any(|(b, e)| *b <= to && from <= *e)
    }

    /// The proxy's delay at `at` (0 when none).
    fn delay_at(&self, at: Ms) -> Ms {
        self.delays
            .iter()
            .filter(|(b, e, _)| *b <= at && at <= *e)
            .map(|(_, _, d)| *d)
            .max()
            .unwrap_or(0)
    }

    /// The latest a command published at `at` can have reached the gateway, less the machine's
    /// slack: held by a session-breaking fault until its recovery, or delayed by the proxy.
    fn reached_gateway_by(&self, at: Ms) -> Ms {
        let held = self
            .breaking
            .iter()
            .filter(|(b, e)| *b <= at && at <= *e)
            .map(|(_, e)| *e)
            .max()
            .unwrap_or(at);
        held + self.delay_at(at)
    }
}

/// Checks a trace against the contract.
pub fn check(trace: &Trace) -> Report {
    let mut report = Report::default();
    let p = trace.params;
    let events_suffix = "EventsTopic";
    let end_of_run = trace.records.last().map_or(0, |r| r.at);

    let sent: Vec<(Ms, &Sent)> = trace
        .records
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::Sent(s) => Some((r.at, s)),
            _ => None,
        })
        .collect();
    report.commands = sent.len();

    // Answers, in order; and the failed dockings (the gateway then turns the relay off itself).
    let mut answers: Vec<Answered> = Vec::new();
    let mut dock_failed: Vec<(Ms, NodeId)> = Vec::new();
    for r in &trace.records {
        let Entry::Received { topic, payload, .. } = &r.entry else {
            continue;
        };
        if !topic.ends_with(events_suffix) {
            continue;
        }
        let Ok(event) = serde_json::from_str::<Event>(payload) else {
            continue;
        };
        let (request_id, what, answer) = match event {
            Event::CommandResult(c) => (
                c.request_id,
                Some((c.cmd.into_owned(), c.node.to_string())),
                Answer::Result(c.result, c.reason.unwrap_or_default()),
            ),
            Event::CommandRejected(c) => (c.request_id, None, Answer::Rejected(c.reason)),
            Event::NodeList(l) => (l.request_id, None, Answer::List),
            Event::DockFailed(d) => {
                dock_failed.push((r.at, d.node.0));
                continue;
            }
            _ => continue,
        };
        answers.push(Answered {
            at: r.at,
            request_id,
            what,
            answer,
            raw: payload.clone(),
        });
    }

    // Faults and their windows.
    let mut faults: BTreeMap<u32, (Ms, Fault)> = BTreeMap::new();
    let mut recovered: BTreeMap<u32, Ms> = BTreeMap::new();
    for r in &trace.records {
        match &r.entry {
            Entry::FaultBegin { fault, what } => {
                faults.insert(*fault, (r.at, what.clone()));
            }
            Entry::Recovered { fault, .. } => {
                recovered.insert(*fault, r.at);
            }
            _ => {}
        }
    }
    report.faults = faults.len();
    let windows = Windows::new(&faults, &recovered, end_of_run);
    let in_fault = |from: Ms, to: Ms| windows.breaking(from, to);

    // Each command's answers.
    let mut answer_of: BTreeMap<u32, Vec<&Answered>> = BTreeMap::new();
    let mut by_rid: BTreeMap<&str, u32> = BTreeMap::new();
    for (_, s) in &sent {
        if let Some(rid) = &s.request_id {
            by_rid.insert(rid, s.n);
        }
    }
    // Answers without a request_id cannot tell which of the commands they could answer is theirs:
    // a `command_result` names its cmd and node, a rejection nothing. First a guess — a result goes
    // to the oldest open command of its cmd and node, a rejection (it comes at once) to the newest
    // open one — then the guess is corrected where it left a command unanswered that needed an
    // answer while another assignment answers it (an answer given to a command lost in a fault
    // may belong to a later one): augmenting paths, commands that must be answered first. Only
    // what no assignment explains is a violation.
    let answerable = |at: Ms, s: &Sent, answer_at: Ms| {
        s.request_id.is_none()
            && at <= answer_at
            && answer_at
                <= windows.reached_gateway_by(at)
                    + p.command_timeout_ms
                    + 2 * p.slack_ms
                    + 2 * windows.delay_at(at)
    };
    let deadline_of = |at: Ms| p.command_timeout_ms + p.slack_ms + 2 * windows.delay_at(at);
    let mut null_answers: Vec<&Answered> = Vec::new();
    for a in &answers {
        match &a.request_id {
            Some(rid) => match by_rid.get(rid.as_str()) {
                Some(n) => answer_of.entry(*n).or_default().push(a),
                None => report.violations.push(Violation {
                    at: a.at,
                    rule: Rule::OneAnswer,
                    message: format!(
                        "an answer to request_id {rid:?}, which was never sent: {}",
                        a.raw
                    ),
                }),
            },
            None => null_answers.push(a),
        }
    }
    // Which answers each command could own (indices into `null_answers`), in time order.
    let can_own: Vec<Vec<usize>> = sent
        .iter()
        .map(|(at, s)| {
            let what = cmd_and_node(s);
            null_answers
                .iter()
                .enumerate()
                .filter(|(_, a)| {
                    answerable(*at, s, a.at)
                        && a.what.as_ref().is_none_or(|w| Some(w) == what.as_ref())
                })
                .map(|(i, _)| i)
                .collect()
        })
        .collect();
    // owner[answer] = index into `sent`.
    let mut owner: Vec<Option<usize>> = vec![None; null_answers.len()];
    let mut owned = vec![false; sent.len()];
    for (i, a) in null_answers.iter().enumerate() {
        let open = |c: &usize| !owned[*c] && can_own[*c].contains(&i);
        let mut candidates = 0..sent.len();
        let target = match a.what {
            Some(_) => candidates.find(open),
            None => candidates.rfind(open),
        };
        if let Some(c) = target {
            owner[i] = Some(c);
            owned[c] = true;
        }
    }
    let must_answer: Vec<bool> = sent
        .iter()
        .map(|(at, s)| {
            let deadline = deadline_of(*at);
            !s.retained && !in_fault(*at, at + deadline) && at + deadline <= end_of_run
        })
        .collect();
    // A command that needs its answer takes one another command could do without: by moving
    // answers along, or else from a command that may go unanswered (lost in a fault).
    for c in 0..sent.len() {
        if !must_answer[c] || owned[c] {
            continue;
        }
        let mut seen = vec![false; null_answers.len()];
        if augment(c, &can_own, &mut owner, &mut seen) {
            owned[c] = true;
        } else if let Some(a) = can_own[c]
            .iter()
            .copied()
            .find(|&a| owner[a].is_some_and(|o| !must_answer[o]))
        {
            if let Some(o) = owner[a].replace(c) {
                owned[o] = false;
            }
            owned[c] = true;
        }
    }
    // Answers still without an owner go to commands that may take them.
    for (c, owns) in owned.iter_mut().enumerate() {
        if !*owns {
            let mut seen = vec![false; null_answers.len()];
            *owns = augment(c, &can_own, &mut owner, &mut seen);
        }
    }
    for (i, a) in null_answers.iter().enumerate() {
        match owner[i] {
            Some(c) => answer_of.entry(sent[c].1.n).or_default().push(a),
            None => report.violations.push(Violation {
                at: a.at,
                rule: Rule::OneAnswer,
                message: format!(
                    "an answer without request_id that no command left unanswered can own (a second answer?): {}",
                    a.raw
                ),
            }),
        }
    }
    for (at, s) in &sent {
        // A delayed link delays the command and its answer.
        let deadline = deadline_of(*at);
        let got = answer_of.get(&s.n).map(Vec::as_slice).unwrap_or_default();
        if s.retained {
            // Every replay may be answered (a rejection each time); none may say `ok`.
            for a in got {
                if !a.answer.negative() {
                    report.violations.push(Violation {
                        at: a.at,
                        rule: Rule::RetainedNeverRuns,
                        message: format!("retained command #{} answered {}", s.n, a.answer.text()),
                    });
                }
            }
            continue;
        }
        match got {
            [] => {
                if in_fault(*at, at + deadline) {
                    report.lost_in_faults += 1;
                } else if at + deadline <= end_of_run {
                    // Dated when it was sent: the excerpt then shows the command, its way to the
                    // gateway and what the gateway answered around it.
                    report.violations.push(Violation {
                        at: *at,
                        rule: Rule::OneAnswer,
                        message: format!(
                            "command #{} {} got no answer within {deadline} ms (no fault in the way)",
                            s.n, s.payload
                        ),
                    });
                }
            }
            [_] => report.answered += 1,
            [first, rest @ ..] => {
                report.answered += 1;
                for again in rest {
                    let same = again.raw == first.raw;
                    if same && in_fault(first.at, again.at) {
                        report.redelivered += 1;
                    } else {
                        report.violations.push(Violation {
                            at: again.at,
                            rule: Rule::OneAnswer,
                            message: format!(
                                "command #{} {} answered twice: {} at {} ms, then {}",
                                s.n,
                                s.payload,
                                first.answer.text(),
                                first.at,
                                again.answer.text()
                            ),
                        });
                    }
                }
            }
        }
    }

    check_frames(
        trace,
        &sent,
        &answer_of,
        &windows,
        &dock_failed,
        &mut report,
    );
    check_availability(trace, &faults, &recovered, &mut report);
    check_checkpoints(trace, &mut report);
    check_knowledge(trace, &mut report);
    check_false_faults(trace, &mut report);
    report.violations.sort_by_key(|v| (v.at, v.rule));
    report
}

/// Kuhn's augmenting path from command `c`: gives it one of the answers it can own, moving the
/// answer's present owner to another of its own if need be. True when it found one.
fn augment(
    c: usize,
    can_own: &[Vec<usize>],
    owner: &mut [Option<usize>],
    seen: &mut [bool],
) -> bool {
    for &a in &can_own[c] {
        if seen[a] {
            continue;
        }
        seen[a] = true;
        let free = match owner[a] {
            None => true,
            Some(o) => augment(o, can_own, owner, seen),
        };
        if free {
            owner[a] = Some(c);
            return true;
        }
    }
    false
}

/// `(cmd, node)` of a command as its `command_result` names them.
fn cmd_and_node(s: &Sent) -> Option<(String, String)> {
    match command::parse(s.action.as_bytes(), usize::MAX)
        .ok()?
        .command
    {
        Command::Node { target, action } => Some((action.name().to_string(), target.to_string())),
        Command::Assign { new_id, .. } => Some(("assign".into(), new_id.to_string())),
        Command::Forget { id } => Some(("forget".into(), id.to_string())),
        Command::List
        | Command::FwUpdate { .. }
        | Command::FwCancel
        | Command::Lease { .. }
        | Command::Renew { .. }
        | Command::Release
        | Command::BreakLease { .. }
        | Command::Procedure(_)
        | Command::ProcedureCancel { .. } => None,
    }
}

/// The frame a command turns into: destination and action.
fn frame_of(s: &Sent) -> Option<(NodeId, NodeAction)> {
    match command::parse(s.action.as_bytes(), usize::MAX)
        .ok()?
        .command
    {
        Command::Node { target, action } => Some((target.dest(), action)),
        _ => None,
    }
}

fn check_frames(
    trace: &Trace,
    sent: &[(Ms, &Sent)],
    answer_of: &BTreeMap<u32, Vec<&Answered>>,
    windows: &Windows,
    dock_failed: &[(Ms, NodeId)],
    report: &mut Report,
) {
    let slack = trace.params.slack_ms;
    let actions: Vec<(Ms, &Sent, NodeId, NodeAction)> = sent
        .iter()
        .filter_map(|(at, s)| frame_of(s).map(|(dest, a)| (*at, *s, dest, a)))
        .collect();
    let mut framed: BTreeSet<u32> = BTreeSet::new();
    for r in &trace.records {
        let Entry::Frame { id, data } = &r.entry else {
            continue;
        };
        let Ok(packet) = decode(*id, data) else {
            continue;
        };
        if packet.src != NodeId::GATEWAY {
            continue;
        }
        let seq = match packet.msg {
            Message::LedSet { seq, .. }
            | Message::BuzzerSet { seq, .. }
            | Message::PowerSet { seq, .. }
            | Message::Identify { seq, .. } => seq,
            _ => continue,
        };
        report.frames += 1;
        // A failed docking: the gateway turns the static element's relay off on its own and
        // publishes `dock_failed` with it (delayed, like any event, while the session is broken).
        if matches!(packet.msg, Message::PowerSet { on: false, .. })
            && dock_failed.iter().any(|(at, node)| {
                *node == packet.dest
                    && r.at <= at + slack
                    && *at <= windows.reached_gateway_by(r.at) + slack
            })
        {
            continue;
        }
        let candidates: Vec<&(Ms, &Sent, NodeId, NodeAction)> = actions
            .iter()
            .filter(|(at, _, dest, a)| {
                *at <= r.at && *dest == packet.dest && a.to_message(seq) == packet.msg
            })
            .collect();
        let mut why_not = Vec::new();
        let mut may_run = false;
        for (at, s, _, _) in &candidates {
            framed.insert(s.n);
            if s.retained {
                why_not.push(format!("#{} is retained", s.n));
                continue;
            }
            // The ttl runs from when the gateway received the command: at the latest, when a
            // fault holding it ended (plus the machine's slack).
            if let Some(ttl) = s.ttl_ms {
                let expired = windows.reached_gateway_by(*at) + slack + ttl;
                if r.at > expired {
                    why_not.push(format!(
                        "#{} (ttl_ms {ttl}) expired by {expired} ms at the latest",
                        s.n
                    ));
                    continue;
                }
            }
            let negative = answer_of
                .get(&s.n)
                .and_then(|v| v.iter().find(|a| a.at <= r.at && a.answer.negative()));
            if let Some(a) = negative {
                why_not.push(format!(
                    "#{} was answered {} at {} ms",
                    s.n,
                    a.answer.text(),
                    a.at
                ));
                continue;
            }
            may_run = true;
        }
        if may_run {
            continue;
        }
        let rule = if candidates.iter().any(|(_, s, _, _)| s.retained) {
            Rule::RetainedNeverRuns
        } else {
            Rule::NoLateExecution
        };
        let message = if candidates.is_empty() {
            format!("frame {packet:?} belongs to no command sent before it")
        } else {
            format!(
                "frame {packet:?} executes a command that may not run: {}",
                why_not.join("; ")
            )
        };
        report.violations.push(Violation {
            at: r.at,
            rule,
            message,
        });
    }
    // `failed` means "not sent": such a command has no frame at all, not even before its answer
    // (checked for commands whose frame no other command could have produced).
    for (_, s, dest, action) in &actions {
        if !framed.contains(&s.n) {
            continue;
        }
        let twins = actions
            .iter()
            .filter(|(_, o, d, a)| {
                o.n != s.n && d == dest && a.to_message(0) == action.to_message(0)
            })
            .count();
        if twins > 0 {
            continue;
        }
        if let Some(a) = answer_of.get(&s.n).and_then(|v| {
            v.iter()
                .find(|a| matches!(a.answer, Answer::Result(Outcome::Failed, _)))
        }) {
            report.violations.push(Violation {
                at: a.at,
                rule: Rule::NoLateExecution,
                message: format!(
                    "command #{} {} answered {} but its frame was on the bus",
                    s.n,
                    s.payload,
                    a.answer.text()
                ),
            });
        }
    }
}

fn decode(id: u32, data: &[u8]) -> Result<Packet, ihex_proto::DecodeError> {
    Packet::decode(id, data)
}

fn check_availability(
    trace: &Trace,
    faults: &BTreeMap<u32, (Ms, Fault)>,
    recovered: &BTreeMap<u32, Ms>,
    report: &mut Report,
) {
    for (n, (begin, fault)) in faults {
        let Some(&back) = recovered.get(n) else {
            report.violations.push(Violation {
                at: *begin,
                rule: Rule::Availability,
                message: format!("fault {n} ({}) never recovered", fault.name()),
            });
            continue;
        };
        if !fault.expects_offline() {
            continue;
        }
        let between = trace
            .records
            .iter()
            .filter(|r| r.at >= *begin && r.at <= back);
        let mut offline_at = None;
        let mut online_after = false;
        for r in between {
            match &r.entry {
                Entry::Received { topic, payload, .. } if is_availability(topic) => {
                    if payload == "offline" && offline_at.is_none() {
                        offline_at = Some(r.at);
                    } else if payload == "online" && offline_at.is_some() {
                        online_after = true;
                    }
                }
                // The broker itself was gone: that is the offline a dashboard sees.
                Entry::RecorderConnected if matches!(fault, Fault::BrokerKill { .. }) => {
                    offline_at.get_or_insert(r.at);
                }
                _ => {}
            }
        }
        if offline_at.is_none() || !online_after {
            report.violations.push(Violation {
                at: back,
                rule: Rule::Availability,
                message: format!(
                    "fault {n} ({}): availability did not go {} between {begin} and {back} ms",
                    fault.name(),
                    if offline_at.is_none() {
                        "offline"
                    } else {
                        "online again"
                    }
                ),
            });
        }
    }
}

fn is_availability(topic: &str) -> bool {
    topic.ends_with("ihex/gateway/availability")
}

/// The retained state documents, by node id.
fn documents(retained: &[(String, String)]) -> (BTreeMap<String, NodeState>, Option<String>) {
    let mut docs = BTreeMap::new();
    let mut availability = None;
    for (topic, payload) in retained {
        if is_availability(topic) {
            availability = Some(payload.clone());
        } else if topic.ends_with("/state") {
            if let Ok(doc) = serde_json::from_str::<NodeState>(payload) {
                docs.insert(doc.id.to_string(), doc);
            }
        }
    }
    (docs, availability)
}

/// Each element's presence (powered and on the bus) as of a time: since when it has been present
/// without a break, or since when it has been absent (from the start of the run if it never was
/// present).
struct Presence {
    since: BTreeMap<String, Ms>,
    gone: BTreeMap<String, Ms>,
}

impl Presence {
    /// Presence as of `until`. A change the gateway could not see when it happened — while its
    /// CAN interface was down or it was not running (a CAN outage or a gateway kill, from its
    /// begin to its recovery), or shortly before, while the lost detection of `lost_grace` was
    /// still counting — counts from that recovery: the gateway pauses lost detection while its
    /// own bus is down (else every node would be declared lost) and a restarted one starts it
    /// afresh, so `lost_after` health periods only start then.
    fn at(trace: &Trace, until: Ms, lost_grace: Ms) -> Presence {
        let mut p = Presence {
            since: BTreeMap::new(),
            gone: BTreeMap::new(),
        };
        let mut blind: Vec<(Ms, Ms)> = Vec::new();
        let mut begun: BTreeMap<u32, Ms> = BTreeMap::new();
        for r in trace.records.iter().take_while(|r| r.at <= until) {
            match &r.entry {
                Entry::FaultBegin {
                    fault,
                    what: Fault::CanDown { .. } | Fault::GatewayKill { .. },
                } => {
                    begun.insert(*fault, r.at);
                }
                Entry::Recovered { fault, .. } => {
                    if let Some(b) = begun.remove(fault) {
                        blind.push((b, r.at));
                    }
                }
                _ => {}
            }
        }
        // Still blind at `until`: nothing counts yet.
        blind.extend(begun.values().map(|&b| (b, until)));
        let seen_at = |t: Ms, grace: Ms| {
            blind
                .iter()
                .filter(|&&(b, e)| b <= t + grace && t < e)
                .map(|&(_, e)| e)
                .fold(t, Ms::max)
        };
        for r in trace.records.iter().take_while(|r| r.at <= until) {
            let truth = match &r.entry {
                Entry::Truth(t) => t,
                Entry::Checkpoint { truth, .. } => truth,
                _ => continue,
            };
            for e in truth {
                if e.powered && e.on_bus {
                    p.gone.remove(&e.id);
                    p.since.entry(e.id.clone()).or_insert(seen_at(r.at, 0));
                } else if p.since.remove(&e.id).is_some() {
                    p.gone.insert(e.id.clone(), seen_at(r.at, lost_grace));
                } else {
                    p.gone.entry(e.id.clone()).or_insert(0);
                }
            }
        }
        p
    }

    /// How long it has been absent at `at` (`None` when present or never recorded).
    fn gone_for(&self, id: &str, at: Ms) -> Option<Ms> {
        self.gone.get(id).map(|t| at.saturating_sub(*t))
    }

    /// Its presence changed within `window` before `at` (it appeared, or vanished).
    fn changed_within(&self, id: &str, at: Ms, window: Ms) -> bool {
        let t = self.since.get(id).or_else(|| self.gone.get(id));
        t.is_some_and(|t| at.saturating_sub(*t) <= window)
    }
}

/// An identify frame (seconds > 0) sent to `id` or to all within `window` before `at`.
fn identified_recently(trace: &Trace, id: &str, at: Ms, window: Ms) -> bool {
    trace
        .records
        .iter()
        .filter(|r| r.at <= at && r.at + window >= at)
        .any(|r| match &r.entry {
            Entry::Frame { id: raw, data } => decode(*raw, data).is_ok_and(|p| {
                matches!(p.msg, Message::Identify { seconds, .. } if seconds > 0)
                    && (p.dest == NodeId::BROADCAST || p.dest.to_string() == id)
            }),
            _ => false,
        })
}

fn check_checkpoints(trace: &Trace, report: &mut Report) {
    let p = trace.params;
    let lost_grace = (u64::from(p.lost_after) + 1) * p.health_period_ms + p.slack_ms;
    // Identify lasts at most the 1 s the harness asks for, plus a health period to be reported.
    let identify_grace = 1000 + p.health_period_ms + p.slack_ms;
    // A node that appeared (booted, came back) converges from its own appearance.
    let settle = 2 * p.health_period_ms + p.slack_ms;
    for r in &trace.records {
        let Entry::Checkpoint {
            fault,
            truth,
            retained,
        } = &r.entry
        else {
            continue;
        };
        report.checkpoints += 1;
        let after = match fault {
            Some(n) => format!("after fault {n}"),
            None => "at the end".to_string(),
        };
        let mut wrong = Vec::new();
        let (docs, availability) = documents(retained);
        if availability.as_deref() != Some("online") {
            report.violations.push(Violation {
                at: r.at,
                rule: Rule::Availability,
                message: format!("{after}: availability is {availability:?}, not online"),
            });
        }
        let presence = Presence::at(trace, r.at, lost_grace);
        let by_id: BTreeMap<&str, &Element> = truth.iter().map(|e| (e.id.as_str(), e)).collect();
        for e in truth {
            let doc = docs.get(&e.id);
            let live = e.powered && e.on_bus;
            if !live {
                match doc {
                    Some(d) if d.online => {
                        let gone_for = presence.gone_for(&e.id, r.at);
                        if gone_for.is_some_and(|g| g > lost_grace) {
                            wrong.push(format!(
                                "{}: document says online, but the node has been {} for {} ms",
                                e.id,
                                if e.powered {
                                    "off the bus"
                                } else {
                                    "without power"
                                },
                                gone_for.unwrap_or_default()
                            ));
                        }
                    }
                    _ => {}
                }
                continue;
            }
            if presence.changed_within(&e.id, r.at, settle) {
                continue;
            }
            let Some(d) = doc else {
                wrong.push(format!(
                    "{}: no retained document for a node on the bus",
                    e.id
                ));
                continue;
            };
            if !d.online {
                wrong.push(format!(
                    "{}: document says offline, the node is on the bus",
                    e.id
                ));
                continue;
            }
            if !identified_recently(trace, &e.id, r.at, identify_grace) {
                let led = led_of(d);
                if led != Some((e.led, e.blink)) {
                    wrong.push(format!(
                        "{}: LED {} in the document, {:?}{} on the node",
                        e.id,
                        serde_json::to_string(&d.led).unwrap_or_default(),
                        e.led,
                        match e.blink {
                            Some((period, duty)) => format!(" blinking {period} ms {duty} %"),
                            None => String::new(),
                        }
                    ));
                }
                let buzzer = d.buzzer.as_ref().map(buzzer_text);
                if buzzer.as_deref() != Some(e.buzzer.as_str()) {
                    wrong.push(format!(
                        "{}: buzzer {:?} in the document, {:?} on the node",
                        e.id, buzzer, e.buzzer
                    ));
                }
            }
            if d.relay != Some(e.relay) {
                wrong.push(format!(
                    "{}: relay {:?} in the document, {} on the node",
                    e.id, d.relay, e.relay
                ));
            }
            let expected = links_of(e, truth, &by_id);
            let got: BTreeSet<(u8, String, u8)> = d
                .connections
                .iter()
                .map(|l| (l.port, l.peer.to_string(), l.peer_port))
                .collect();
            if expected != got {
                // A peer that came or went recently may be missing or still listed.
                let unsettled = |(_, peer, _): &(u8, String, u8)| {
                    presence.changed_within(peer, r.at, lost_grace)
                };
                let excused = got.symmetric_difference(&expected).all(unsettled);
                if !excused {
                    wrong.push(format!(
                        "{}: connections {:?} in the document, {:?} on the island",
                        e.id, got, expected
                    ));
                }
            }
        }
        for w in wrong {
            report.violations.push(Violation {
                at: r.at,
                rule: Rule::Convergence,
                message: format!("{after}: {w}"),
            });
        }
    }
}

/// An LED drive: per-channel duty and blink gate, as [`Element`] has them.
type Led = ([u8; 3], Option<(u16, u8)>);

/// The LED drive a document describes, when it can be compared (brightness 255, as the harness
/// sends).
fn led_of(d: &NodeState) -> Option<Led> {
    let led = d.led.as_ref()?;
    let color = |c: &Option<String>| -> Option<[u8; 3]> {
        let hex = c.as_deref()?.strip_prefix('#')?;
        let v = u32::from_str_radix(hex, 16).ok()?;
        Some([(v >> 16) as u8, (v >> 8) as u8, v as u8])
    };
    match &*led.mode {
        "off" => Some(([0, 0, 0], None)),
        "steady" if led.brightness == Some(255) => Some((color(&led.color)?, None)),
        "blink" if led.brightness == Some(255) => {
            Some((color(&led.color)?, Some((led.period_ms?, led.duty?))))
        }
        _ => None,
    }
}

/// A buzzer state in the words [`Element::buzzer`] uses.
pub fn buzzer_text(b: &BuzzerState) -> String {
    match &*b.mode {
        "on" => format!("on {}", b.freq_hz.unwrap_or_default()),
        "pattern" => format!(
            "pattern {} {} {} {}",
            b.freq_hz.unwrap_or_default(),
            b.on_ms.unwrap_or_default(),
            b.off_ms.unwrap_or_default(),
            b.count.unwrap_or_default()
        ),
        other => other.to_string(),
    }
}

/// The dockings a live element must list: (its port, peer, peer's port). A docking exists while the
/// mobile element is powered and on the bus (otherwise the gateway reports it lost, which ends it).
fn links_of(
    e: &Element,
    truth: &[Element],
    by_id: &BTreeMap<&str, &Element>,
) -> BTreeSet<(u8, String, u8)> {
    let live = |m: &Element| m.powered && m.on_bus;
    if e.mobile {
        match &e.docked {
            Some((at, port)) if live(e) && by_id.contains_key(at.as_str()) => {
                BTreeSet::from([(e.own_port, at.clone(), *port)])
            }
            _ => BTreeSet::new(),
        }
    } else {
        truth
            .iter()
            .filter(|m| m.mobile && live(m))
            .filter_map(|m| match &m.docked {
                Some((at, port)) if *at == e.id => Some((*port, m.id.clone(), m.own_port)),
                _ => None,
            })
            .collect()
    }
}

/// Fields of a state document that say what a node is: once known, known for good.
const IDENTITY_FIELDS: [&str; 5] = ["role", "ports", "version", "firmware", "uid"];
/// Fields of a state document that say what a node's actuators do: unknown again only once the
/// node restarted (it starts with everything off, and the gateway reads it back).
const ACTUATOR_FIELDS: [&str; 3] = ["led", "buzzer", "relay"];

/// The node a state topic (`…/<id>/state`) is about.
fn state_topic_node(topic: &str) -> Option<&str> {
    let rest = topic.strip_suffix("/state")?;
    rest.rsplit('/').next()
}

/// The rule **knowledge kept**: every state document received is compared with what the earlier
/// documents of its node showed known.
fn check_knowledge(trace: &Trace, report: &mut Report) {
    let mut known: BTreeMap<String, BTreeSet<&'static str>> = BTreeMap::new();
    let forget_actuators = |known: &mut BTreeMap<String, BTreeSet<&'static str>>, id: &str| {
        if let Some(k) = known.get_mut(id) {
            k.retain(|f| !ACTUATOR_FIELDS.contains(f));
        }
    };
    for r in &trace.records {
        match &r.entry {
            Entry::Received { topic, payload, .. } => {
                if let Some(id) = state_topic_node(topic) {
                    let Ok(doc) = serde_json::from_str::<serde_json::Value>(payload) else {
                        // Emptied (the node was forgotten): it claims nothing any more.
                        known.remove(id);
                        continue;
                    };
                    let shown: BTreeSet<&'static str> = IDENTITY_FIELDS
                        .iter()
                        .chain(ACTUATOR_FIELDS.iter())
                        .copied()
                        .filter(|f| doc.get(f).is_some_and(|v| !v.is_null()))
                        .collect();
                    let before = known.entry(id.to_string()).or_default();
                    let lost: Vec<&str> = before.difference(&shown).copied().collect();
                    if !lost.is_empty() {
                        report.violations.push(Violation {
                            at: r.at,
                            rule: Rule::KnowledgeKept,
                            message: format!(
                                "{id}: the state document shows {} null, known before: {payload}",
                                lost.join(", ")
                            ),
                        });
                    }
                    *before = shown;
                } else if let Ok(event) = serde_json::from_str::<serde_json::Value>(payload) {
                    let node = event["payload"]["id"].as_str().unwrap_or_default();
                    match event["event"].as_str() {
                        Some("node_rebooted") => forget_actuators(&mut known, node),
                        Some("node_forgotten") => {
                            known.remove(node);
                        }
                        _ => {}
                    }
                }
            }
            Entry::FaultBegin {
                what: Fault::NodeReset { node },
                ..
            } => forget_actuators(&mut known, node),
            Entry::Truth(truth) | Entry::Checkpoint { truth, .. } => {
                for e in truth.iter().filter(|e| !e.powered) {
                    forget_actuators(&mut known, &e.id);
                }
            }
            _ => {}
        }
    }
}

/// The rule **no false fault**: an `unexpected_handshake` fault of a mobile element whose
/// `new_connection` follows within the docking timeout (plus slack) belonged to that docking.
fn check_false_faults(trace: &Trace, report: &mut Report) {
    let window = trace.params.dock_timeout_ms + trace.params.slack_ms;
    let events: Vec<(Ms, serde_json::Value, &str)> = trace
        .records
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::Received { topic, payload, .. } if topic.ends_with("EventsTopic") => {
                serde_json::from_str(payload)
                    .ok()
                    .map(|v| (r.at, v, payload.as_str()))
            }
            _ => None,
        })
        .collect();
    for (at, v, raw) in &events {
        if v["event"] != "fault" || v["payload"]["code"] != "unexpected_handshake" {
            continue;
        }
        let node = &v["payload"]["node"];
        let docked = events.iter().find(|(t, e, _)| {
            *t >= *at
                && *t <= at + window
                && e["event"] == "new_connection"
                && e["payload"]["n"]["id"] == *node
        });
        if let Some((t, _, connection)) = docked {
            report.violations.push(Violation {
                at: *at,
                rule: Rule::NoFalseFault,
                message: format!(
                    "a fault for a handshake whose docking completed {} ms later: {raw}, then {connection}",
                    t - at
                ),
            });
        }
    }
}

/// Runs the checker and turns violations into a failure message with trace excerpts.
pub fn assert_contract(trace: &Trace) -> Result<Report, String> {
    let report = check(trace);
    if report.ok() {
        return Ok(report);
    }
    let mut text = report.to_string();
    for v in report.violations.iter().take(5) {
        text.push_str(&format!(
            "\ntrace around {} ms ({}):\n{}\n",
            v.at,
            v.rule,
            excerpt(trace, v.at, 2 * trace.params.health_period_ms)
        ));
    }
    text.push_str(&format!("\nthe island's story:\n{}\n", story(trace)));
    Err(text)
}

#[cfg(test)]
mod tests;
