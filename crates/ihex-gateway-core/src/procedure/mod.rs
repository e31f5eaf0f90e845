//! Guided procedures, sans-IO: an ordered list of [`Step`]s, each lighting elements (and optionally
//! beeping) until a physical condition holds — a mobile element (a given one or any) docked on a
//! given static element (and port), or undocked from it — or its timeout passes, or the procedure
//! is cancelled, or one of its elements is lost. A [`Run`] is one procedure in progress: a pure
//! state machine (time passed in) whose `handle_*` methods return the [`Action`]s to carry out, in
//! order: light, progress events, clear. Every step that starts has exactly one outcome
//! ([`StepOutcome`]), every run exactly one [`ProcedureEnded`], and every light it switched on is
//! switched off again.
//!
//! The bridge's glue (`glue`) parses nothing: it admits a `procedure` command (at most
//! `max_procedures` at once, its elements leased for its duration), feeds the runs the docking
//! sequence's connections, lost elements and its timer, and carries out their actions as frames
//! and events.

pub(crate) mod glue;

use std::time::{Duration, Instant};

use ihex_proto::{BuzzerCommand, LedCommand, NodeId, Port};
use serde::{Deserialize, Serialize};

use crate::event::{Connection, HexId};
use crate::lease::WallClock;
use crate::registry::millis;

/// Most steps in one procedure.
pub const MAX_STEPS: usize = 64;
/// Longest step timeout, seconds (an hour: a step that waits longer is not a guided step).
pub const MAX_STEP_TIMEOUT_S: u32 = 3600;
/// Default step timeout, seconds.
pub const DEFAULT_STEP_TIMEOUT_S: u32 = 300;
/// Default of `max_procedures`: procedures running at once.
pub const DEFAULT_MAX_PROCEDURES: usize = 4;
/// The beep of a step with `"beep": true`: three short 2 kHz beeps.
pub const BEEP: BuzzerCommand = BuzzerCommand::Pattern {
    freq_hz: 2000,
    on_10ms: 10,
    off_10ms: 10,
    count: 3,
};

/// What ends a step as `done`.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Wait {
    /// A mobile element (`mobile`, or any) docks on static element `node` (on `port`, or any).
    Docked {
        /// The static element.
        node: NodeId,
        /// Its dock port (`None`: any).
        port: Option<Port>,
        /// The mobile element (`None`: any).
        mobile: Option<NodeId>,
    },
    /// The mobile element (`mobile`, or any) on static element `node` (on `port`, or any) undocks.
    Undocked {
        /// The static element.
        node: NodeId,
        /// Its dock port (`None`: any).
        port: Option<Port>,
        /// The mobile element (`None`: any).
        mobile: Option<NodeId>,
    },
}

impl Wait {
    fn parts(&self) -> (NodeId, Option<Port>, Option<NodeId>) {
        match *self {
            Wait::Docked { node, port, mobile } | Wait::Undocked { node, port, mobile } => {
                (node, port, mobile)
            }
        }
    }

    /// True when connection `c` is the one this wait names.
    fn covers(&self, c: &Connection) -> bool {
        let (node, port, mobile) = self.parts();
        c.n_1.id.0 == node
            && port.is_none_or(|p| p.get() == c.n_1.port)
            && mobile.is_none_or(|m| m == c.n.id.0)
    }

    /// Its public form.
    fn view(&self) -> WaitView {
        let (node, port, mobile) = self.parts();
        WaitView {
            condition: match self {
                Wait::Docked { .. } => "docked",
                Wait::Undocked { .. } => "undocked",
            }
            .to_owned(),
            node: HexId(node),
            port: port.map(Port::get),
            mobile: mobile.map(HexId),
        }
    }
}

/// One step.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Step {
    /// What the person must do, shown in the island view and Home Assistant.
    pub text: Option<String>,
    /// The elements lit while the step waits (at least one).
    pub light: Vec<NodeId>,
    /// Their pattern.
    pub led: LedCommand,
    /// Beep on the lit elements when the step starts.
    pub beep: bool,
    /// What ends it as `done`.
    pub wait: Wait,
    /// How long it may wait.
    pub timeout: Duration,
}

impl Step {
    /// The elements the step needs online: the lit ones and the static element of its wait. A
    /// mobile element is not among them: it has no power (and is not heard) until it docks.
    fn elements(&self) -> impl Iterator<Item = NodeId> + '_ {
        let (node, _, _) = self.wait.parts();
        self.light.iter().copied().chain(std::iter::once(node))
    }
}

/// A procedure as the `procedure` command gave it.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Spec {
    /// Its name (for people and the lease's owner).
    pub name: String,
    /// Its steps, in order (1 to [`MAX_STEPS`]).
    pub steps: Vec<Step>,
}

impl Spec {
    /// The static elements it lights or waits on (what its lease covers), without repeats.
    pub fn static_elements(&self) -> Vec<NodeId> {
        let mut ids = Vec::new();
        for s in &self.steps {
            for id in s.light.iter().copied().chain([s.wait.parts().0]) {
                if !ids.contains(&id) {
                    ids.push(id);
                }
            }
        }
        ids
    }

    /// The longest it can run: the sum of its steps' timeouts.
    pub fn longest(&self) -> Duration {
        self.steps.iter().map(|s| s.timeout).sum()
    }
}

/// How a step (and a procedure) ended.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StepOutcome {
    /// Its condition held.
    Done,
    /// Its timeout passed first.
    TimedOut,
    /// `procedure_cancel`, or the gateway stopping.
    Cancelled,
    /// It could not go on (`reason` says why: an element lost, its lease ended).
    Failed,
}

/// The condition a step waits for, as published.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct WaitView {
    /// `docked` or `undocked`.
    pub condition: String,
    /// The static element.
    pub node: HexId,
    /// Its dock port (`null`: any).
    pub port: Option<u8>,
    /// The mobile element (`null`: any).
    pub mobile: Option<HexId>,
}

/// What confirmed a step: the connection, and when.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct Evidence {
    /// The docking that was made or ended (`new_connection`'s shape); `null` for an undocking
    /// step whose element had nothing docked as it started.
    pub connection: Option<Connection>,
    /// When, RFC 3339 UTC (`null` when the gateway does not know the time of day).
    pub at: Option<String>,
    /// How long after the step started, ms.
    pub after_ms: u64,
    /// True when the condition already held as the step started (no docking was needed).
    pub already: bool,
}

/// Payload of `procedure_step`: step `step` of `of` started, or ended with `outcome`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct ProcedureStep {
    /// The procedure's id.
    pub id: u32,
    /// Its name.
    pub name: String,
    /// The step, from 1.
    pub step: usize,
    /// How many steps it has.
    pub of: usize,
    /// `started`, or the step's outcome.
    pub state: StepState,
    /// What the person must do.
    pub text: Option<String>,
    /// The elements lit.
    pub light: Vec<HexId>,
    /// What it waits for.
    pub wait: WaitView,
    /// When it times out, ms from now (`started` only).
    pub timeout_ms: Option<u64>,
    /// What confirmed it (`done` only).
    pub evidence: Option<Evidence>,
    /// Why it failed or was cancelled.
    pub reason: Option<String>,
}

/// A step's state in `procedure_step`.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StepState {
    /// It lights its elements and waits.
    Started,
    /// Its condition held.
    Done,
    /// Its timeout passed.
    TimedOut,
    /// Cancelled.
    Cancelled,
    /// Failed.
    Failed,
}

impl From<StepOutcome> for StepState {
    fn from(o: StepOutcome) -> Self {
        match o {
            StepOutcome::Done => StepState::Done,
            StepOutcome::TimedOut => StepState::TimedOut,
            StepOutcome::Cancelled => StepState::Cancelled,
            StepOutcome::Failed => StepState::Failed,
        }
    }
}

/// Payload of `procedure_mismatch`: a docking or undocking during a step that is not what it
/// waits for (reported, never taken as confirmation).
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct ProcedureMismatch {
    /// The procedure's id.
    pub id: u32,
    /// The step, from 1.
    pub step: usize,
    /// What it waits for.
    pub expected: WaitView,
    /// `docked` or `undocked`: what happened instead.
    pub got: String,
    /// The connection.
    pub connection: Connection,
}

/// Payload of `procedure_ended`: the procedure's one final outcome (also the answer to
/// `procedure_cancel`, whose `request_id` it then carries).
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct ProcedureEnded {
    /// `request_id` of the `procedure` command, or of the `procedure_cancel` that ended it.
    pub request_id: Option<String>,
    /// The procedure's id.
    pub id: u32,
    /// Its name.
    pub name: String,
    /// `done` when every step was; else the outcome of the step it stopped at.
    pub outcome: StepOutcome,
    /// Steps done.
    pub steps_done: usize,
    /// How many steps it has.
    pub of: usize,
    /// Why it did not complete.
    pub reason: Option<String>,
    /// How long it ran, ms.
    pub duration_ms: u64,
}

/// What a [`Run`] asks the glue to do, in this order.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Action {
    /// Set the LEDs of `nodes` to `led`, and beep if `beep`.
    Light {
        /// The elements.
        nodes: Vec<NodeId>,
        /// The pattern.
        led: LedCommand,
        /// Beep too.
        beep: bool,
    },
    /// Switch the LEDs of `nodes` off (and their buzzer, if the step beeped).
    Clear {
        /// The elements.
        nodes: Vec<NodeId>,
        /// The step beeped.
        beep: bool,
    },
    /// Publish `procedure_step`.
    Step(Box<ProcedureStep>),
    /// Publish `procedure_mismatch`.
    Mismatch(Box<ProcedureMismatch>),
    /// Publish `procedure_ended`: the run is over.
    Ended(Box<ProcedureEnded>),
}

/// One procedure in progress.
#[derive(Clone, Debug)]
pub struct Run {
    id: u32,
    spec: Spec,
    request_id: Option<String>,
    started: Instant,
    /// The current step (index), when it started, when it times out.
    step: usize,
    step_started: Instant,
    deadline: Instant,
    ended: bool,
    /// The lease the glue took for it (id, token), if any.
    pub(crate) lease: Option<(u32, String)>,
}

/// Its public form: the running procedures document's entries.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct RunView {
    /// The procedure's id (what `procedure_cancel` names).
    pub id: u32,
    /// Its name.
    pub name: String,
    /// The current step, from 1.
    pub step: usize,
    /// How many steps it has.
    pub of: usize,
    /// What the person must do now.
    pub text: Option<String>,
    /// The elements lit now.
    pub light: Vec<HexId>,
    /// What the step waits for.
    pub wait: WaitView,
    /// When the step times out, ms after the document was made.
    pub remaining_ms: u64,
}

/// The retained document of the procedures running now (`<root>/procedures`).
#[derive(Clone, PartialEq, Eq, Debug, Default, Serialize, Deserialize)]
pub struct ProceduresDocument {
    /// By id.
    pub procedures: Vec<RunView>,
}

impl Run {
    /// Starts procedure `id` at `now`: its first step lights and waits (or is done at once when
    /// its condition already holds in `connections`).
    pub fn start(
        id: u32,
        spec: Spec,
        request_id: Option<String>,
        connections: &[Connection],
        clock: &WallClock,
        now: Instant,
    ) -> (Run, Vec<Action>) {
        let mut run = Run {
            id,
            spec,
            request_id,
            started: now,
            step: 0,
            step_started: now,
            deadline: now,
            ended: false,
            lease: None,
        };
        let mut actions = Vec::new();
        run.begin(0, connections, clock, now, &mut actions);
        (run, actions)
    }

    /// The procedure's id.
    pub fn id(&self) -> u32 {
        self.id
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.spec.name
    }

    /// Its spec.
    pub fn spec(&self) -> &Spec {
        &self.spec
    }

    /// True once its `procedure_ended` was returned.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// When its current step times out (`None` once it ended).
    pub fn deadline(&self) -> Option<Instant> {
        (!self.ended).then_some(self.deadline)
    }

    /// The current step (`None` once it ended).
    pub fn current(&self) -> Option<&Step> {
        (!self.ended).then(|| &self.spec.steps[self.step])
    }

    /// The elements the current step needs online.
    pub fn needs(&self) -> Vec<NodeId> {
        self.current()
            .map(|s| s.elements().collect())
            .unwrap_or_default()
    }

    /// True when the current step waits for a docking and `c` is it.
    pub fn matches_docked(&self, c: &Connection) -> bool {
        matches!(self.current().map(|s| s.wait), Some(w @ Wait::Docked { .. }) if w.covers(c))
    }

    /// True when the current step waits for an undocking and `c` is it.
    pub fn matches_undocked(&self, c: &Connection) -> bool {
        matches!(self.current().map(|s| s.wait), Some(w @ Wait::Undocked { .. }) if w.covers(c))
    }

    /// Its public form as of `now`.
    pub fn view(&self, now: Instant) -> Option<RunView> {
        let s = self.current()?;
        Some(RunView {
            id: self.id,
            name: self.spec.name.clone(),
            step: self.step + 1,
            of: self.spec.steps.len(),
            text: s.text.clone(),
            light: s.light.iter().map(|&id| HexId(id)).collect(),
            wait: s.wait.view(),
            remaining_ms: millis(self.deadline.saturating_duration_since(now)),
        })
    }

    /// A docking completed: the current step is `done` when it is what it waits for; a docking
    /// during a step that waits for one, but not this one, is a `procedure_mismatch`.
    pub fn handle_docked(
        &mut self,
        c: &Connection,
        connections: &[Connection],
        clock: &WallClock,
        now: Instant,
    ) -> Vec<Action> {
        let mut actions = Vec::new();
        let Some(step) = self.current() else {
            return actions;
        };
        if self.matches_docked(c) {
            let evidence = self.evidence(Some(c), false, clock, now);
            self.finish(StepOutcome::Done, Some(evidence), None, now, &mut actions);
            self.next(connections, clock, now, &mut actions);
        } else if matches!(step.wait, Wait::Docked { .. }) {
            actions.push(self.mismatch(c, "docked"));
        }
        actions
    }

    /// A connection ended: the current step is `done` when it waits for this undocking; an
    /// undocking of the element a docking step waits on is a `procedure_mismatch`.
    pub fn handle_undocked(
        &mut self,
        c: &Connection,
        connections: &[Connection],
        clock: &WallClock,
        now: Instant,
    ) -> Vec<Action> {
        let mut actions = Vec::new();
        let Some(step) = self.current() else {
            return actions;
        };
        if self.matches_undocked(c) {
            let evidence = self.evidence(Some(c), false, clock, now);
            self.finish(StepOutcome::Done, Some(evidence), None, now, &mut actions);
            self.next(connections, clock, now, &mut actions);
        } else if step.wait.parts().0 == c.n_1.id.0 {
            actions.push(self.mismatch(c, "undocked"));
        }
        actions
    }

    /// Element `id` was lost: the current step fails when it needs it.
    pub fn handle_lost(&mut self, id: NodeId, now: Instant) -> Vec<Action> {
        let mut actions = Vec::new();
        if self
            .current()
            .is_some_and(|s| s.elements().any(|e| e == id))
        {
            let reason = format!("element {id} was lost (it stopped answering health checks)");
            self.finish(StepOutcome::Failed, None, Some(reason), now, &mut actions);
        }
        actions
    }

    /// The timer: the current step times out when its deadline is due by `now`.
    pub fn handle_timeout(&mut self, now: Instant) -> Vec<Action> {
        let mut actions = Vec::new();
        if let Some(s) = self.current() {
            if now >= self.deadline {
                let reason = format!(
                    "nothing confirmed the step within {} s",
                    s.timeout.as_secs_f64()
                );
                self.finish(StepOutcome::TimedOut, None, Some(reason), now, &mut actions);
            }
        }
        actions
    }

    /// `procedure_cancel` (its `request_id` goes with `procedure_ended`), or the end of the
    /// procedure's lease: the current step and the procedure end `outcome` with `reason`.
    pub fn stop(
        &mut self,
        outcome: StepOutcome,
        reason: String,
        request_id: Option<String>,
        now: Instant,
    ) -> Vec<Action> {
        let mut actions = Vec::new();
        if self.current().is_some() {
            if request_id.is_some() {
                self.request_id = request_id;
            }
            self.finish(outcome, None, Some(reason), now, &mut actions);
        }
        actions
    }

    /// Starts step `i` at `now`, done at once when its condition already holds.
    fn begin(
        &mut self,
        i: usize,
        connections: &[Connection],
        clock: &WallClock,
        now: Instant,
        actions: &mut Vec<Action>,
    ) {
        self.step = i;
        self.step_started = now;
        let s = &self.spec.steps[i];
        self.deadline = now + s.timeout;
        actions.push(Action::Light {
            nodes: s.light.clone(),
            led: s.led,
            beep: s.beep,
        });
        actions.push(self.progress(StepState::Started, None, None, now));
        // Already true as the step starts: docked there now, or (undocking) nothing it names is.
        let docked = connections.iter().find(|c| s.wait.covers(c)).copied();
        let held = match s.wait {
            Wait::Docked { .. } => docked.map(Some),
            Wait::Undocked { .. } => docked.is_none().then_some(None),
        };
        if let Some(c) = held {
            let evidence = self.evidence(c.as_ref(), true, clock, now);
            self.finish(StepOutcome::Done, Some(evidence), None, now, actions);
            self.next(connections, clock, now, actions);
        }
    }

    /// After a step `done`: the next step, or the procedure's end.
    fn next(
        &mut self,
        connections: &[Connection],
        clock: &WallClock,
        now: Instant,
        actions: &mut Vec<Action>,
    ) {
        if self.ended {
            return;
        }
        if self.step + 1 < self.spec.steps.len() {
            self.begin(self.step + 1, connections, clock, now, actions);
        } else {
            self.end(StepOutcome::Done, None, now, actions);
        }
    }

    /// Ends the current step with `outcome`: its light off, its event; anything but `done` ends
    /// the procedure too.
    fn finish(
        &mut self,
        outcome: StepOutcome,
        evidence: Option<Evidence>,
        reason: Option<String>,
        now: Instant,
        actions: &mut Vec<Action>,
    ) {
        let s = &self.spec.steps[self.step];
        actions.push(Action::Clear {
            nodes: s.light.clone(),
            beep: s.beep,
        });
        actions.push(self.progress(outcome.into(), evidence, reason.clone(), now));
        if outcome != StepOutcome::Done {
            self.end(outcome, reason, now, actions);
        }
    }

    fn end(
        &mut self,
        outcome: StepOutcome,
        reason: Option<String>,
        now: Instant,
        actions: &mut Vec<Action>,
    ) {
        self.ended = true;
        let steps_done = match outcome {
            StepOutcome::Done => self.spec.steps.len(),
            _ => self.step,
        };
        actions.push(Action::Ended(Box::new(ProcedureEnded {
            request_id: self.request_id.clone(),
            id: self.id,
            name: self.spec.name.clone(),
            outcome,
            steps_done,
            of: self.spec.steps.len(),
            reason,
            duration_ms: millis(now.saturating_duration_since(self.started)),
        })));
    }

    fn progress(
        &self,
        state: StepState,
        evidence: Option<Evidence>,
        reason: Option<String>,
        now: Instant,
    ) -> Action {
        let s = &self.spec.steps[self.step];
        Action::Step(Box::new(ProcedureStep {
            id: self.id,
            name: self.spec.name.clone(),
            step: self.step + 1,
            of: self.spec.steps.len(),
            state,
            text: s.text.clone(),
            light: s.light.iter().map(|&id| HexId(id)).collect(),
            wait: s.wait.view(),
            timeout_ms: (state == StepState::Started)
                .then(|| millis(self.deadline.saturating_duration_since(now))),
            evidence,
            reason,
        }))
    }

    fn evidence(
        &self,
        c: Option<&Connection>,
        already: bool,
        clock: &WallClock,
        now: Instant,
    ) -> Evidence {
        Evidence {
            connection: c.copied(),
            at: clock.rfc3339(now),
            after_ms: millis(now.saturating_duration_since(self.step_started)),
            already,
        }
    }

    fn mismatch(&self, c: &Connection, got: &'static str) -> Action {
        Action::Mismatch(Box::new(ProcedureMismatch {
            id: self.id,
            step: self.step + 1,
            expected: self.spec.steps[self.step].wait.view(),
            got: got.to_owned(),
            connection: *c,
        }))
    }
}

/// Why a procedure was not started.
#[derive(Clone, PartialEq, Eq, Debug, thiserror::Error)]
pub enum ProcedureError {
    /// `max_procedures` run already.
    #[error("procedure: {0} procedures are running, the most this gateway runs at once (max_procedures); wait for one to end or cancel one")]
    Full(usize),
    /// `procedure_cancel` of an id not running.
    #[error("procedure_cancel: no procedure {0} is running; see the retained procedures document for the ones that are")]
    UnknownId(u32),
}

/// The procedures running now.
#[derive(Debug)]
pub struct Procedures {
    runs: Vec<Run>,
    next_id: u32,
    max: usize,
}

impl Procedures {
    /// None running; at most `max` at once.
    pub fn new(max: usize) -> Self {
        Procedures {
            runs: Vec::new(),
            next_id: 1,
            max,
        }
    }

    /// The id the next procedure gets, or why none may start now.
    pub fn admit(&self) -> Result<u32, ProcedureError> {
        if self.runs.len() >= self.max {
            return Err(ProcedureError::Full(self.runs.len()));
        }
        Ok(self.next_id)
    }

    /// Adds a run started with the id [`Procedures::admit`] gave (one that ended at once is not
    /// kept).
    pub fn add(&mut self, run: Run) {
        self.next_id = self.next_id.wrapping_add(1).max(1);
        if !run.ended() {
            self.runs.push(run);
        }
    }

    /// The runs, by id.
    pub fn runs(&self) -> &[Run] {
        &self.runs
    }

    /// The runs, to feed inputs to; [`Procedures::sweep`] afterwards drops the ended ones.
    pub fn runs_mut(&mut self) -> &mut [Run] {
        &mut self.runs
    }

    /// The run with id `id`.
    pub fn get_mut(&mut self, id: u32) -> Result<&mut Run, ProcedureError> {
        self.runs
            .iter_mut()
            .find(|r| r.id == id)
            .ok_or(ProcedureError::UnknownId(id))
    }

    /// Drops the runs that ended.
    pub fn sweep(&mut self) {
        self.runs.retain(|r| !r.ended());
    }

    /// The earliest step deadline.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.runs.iter().filter_map(Run::deadline).min()
    }

    /// The document of the runs as of `now`.
    pub fn document(&self, now: Instant) -> ProceduresDocument {
        ProceduresDocument {
            procedures: self.runs.iter().filter_map(|r| r.view(now)).collect(),
        }
    }
}

#[cfg(test)]
mod tests;
