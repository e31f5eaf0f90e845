//! The bridge's glue for guided procedures: the `procedure` and `procedure_cancel` commands, the
//! lease a procedure holds on its static elements while it runs, the docking sequence's
//! connections and lost elements fed to the runs (after every input), their step timer, and their
//! actions carried out as frames (LED, buzzer) and events, with the retained procedures document.

use std::time::{Duration, Instant};

use ihex_proto::{BuzzerCommand, Kind, LedCommand, Message, NodeId, Seq};
use serde::{Deserialize, Serialize};

use super::{Action, Run, Spec, StepOutcome, BEEP};
use crate::bridge::{Bridge, FrameOwner, Publication};
use crate::command::CommandError;
use crate::event::{Event, HexId};
use crate::lease::Scope;

/// How long a procedure's own lease outlasts the sum of its steps' timeouts: the lease never ends
/// before the procedure does, whatever the order of their timers.
pub const LEASE_MARGIN: Duration = Duration::from_secs(10);

/// Payload of `procedure_started`: the answer to `procedure`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct ProcedureStarted {
    /// The command's `request_id`.
    pub request_id: Option<String>,
    /// The procedure's id (what `procedure_cancel` names).
    pub id: u32,
    /// Its name.
    pub name: String,
    /// How many steps it has.
    pub steps: usize,
    /// The static elements it holds while it runs.
    pub nodes: Vec<HexId>,
    /// The id of the lease it took on those of them no lease of the sender's already held
    /// (`null`: it took none).
    pub lease: Option<u32>,
}

impl Bridge {
    /// The procedures running now (what the retained `<root>/procedures` topic holds).
    pub fn procedures(&self, now: Instant) -> super::ProceduresDocument {
        self.procedures.document(now)
    }

    /// `procedure`: admitted when fewer than `max_procedures` run and every static element it
    /// lights or waits on is known (a mobile element it waits for may not be: it is heard only
    /// once docked); its static elements are leased (those the sender's own lease does not hold
    /// already), `procedure_started` answers, and its first step starts.
    pub(crate) fn procedure_command(
        &mut self,
        request_id: Option<String>,
        spec: Spec,
        now: Instant,
    ) {
        let id = match self.procedures.admit() {
            Ok(id) => id,
            Err(e) => return self.reject(request_id, e.into()),
        };
        let statics = spec.static_elements();
        if let Some(&unknown) = statics.iter().find(|&&n| self.registry.get(n).is_none()) {
            let error = CommandError::UnknownNode {
                id: HexId(unknown),
                known: self.registry.known_list(),
            };
            return self.reject(request_id, error);
        }
        // `lease_refusal` let it through: each element is free or held by the sender's lease.
        let free: Vec<NodeId> = statics
            .iter()
            .copied()
            .filter(|&n| self.lease_table.holder(n, None, now).is_none())
            .collect();
        let lease = if free.is_empty() {
            None
        } else {
            let owner = format!("procedure {id} ({})", spec.name);
            let note = Some("a guided procedure runs; procedure_cancel ends it".to_owned());
            let ttl = spec.longest() + LEASE_MARGIN;
            match self
                .lease_table
                .take(owner, note, Scope::Nodes(free), ttl, &self.clock, now)
            {
                Ok(l) => Some((l.id, l.token.clone())),
                Err(e) => return self.reject(request_id, e.into()),
            }
        };
        tracing::info!(id, name = %spec.name, steps = spec.steps.len(), "procedure started");
        self.out
            .emit(Event::ProcedureStarted(Box::new(ProcedureStarted {
                request_id: request_id.clone(),
                id,
                name: spec.name.clone(),
                steps: spec.steps.len(),
                nodes: statics.iter().map(|&n| HexId(n)).collect(),
                lease: lease.as_ref().map(|l| l.0),
            })));
        if lease.is_some() {
            self.publish_leases(now);
        }
        let connections = self.docking().connections();
        let (mut run, actions) = Run::start(id, spec, request_id, &connections, &self.clock, now);
        run.lease = lease;
        self.carry_out(&run, actions);
        if run.ended() {
            self.release_procedure_lease(&run, now);
        }
        self.procedures.add(run);
        self.publish_procedures(now);
    }

    /// `procedure_cancel`: the procedure ends `cancelled`; its `procedure_ended` is the answer.
    pub(crate) fn procedure_cancel(&mut self, request_id: Option<String>, id: u32, now: Instant) {
        let run = match self.procedures.get_mut(id) {
            Ok(run) => run,
            Err(e) => return self.reject(request_id, e.into()),
        };
        let reason = "cancelled by procedure_cancel".to_owned();
        let actions = run.stop(StepOutcome::Cancelled, reason, request_id, now);
        self.after(id, actions, now);
    }

    /// True while a guided procedure runs.
    pub fn procedures_running(&self) -> bool {
        !self.procedures.runs().is_empty()
    }

    /// Ends every running procedure `cancelled` with `reason` (the gateway is stopping): their
    /// lights are switched off and each publishes its `procedure_ended`.
    pub fn cancel_procedures(&mut self, reason: &str, now: Instant) {
        self.set_now(now);
        let ids: Vec<u32> = self.procedures.runs().iter().map(Run::id).collect();
        for id in ids {
            if let Ok(run) = self.procedures.get_mut(id) {
                let actions = run.stop(StepOutcome::Cancelled, reason.to_owned(), None, now);
                self.after(id, actions, now);
            }
        }
    }

    /// A procedure's own lease ended without it (broken or expired): the procedure fails.
    pub(crate) fn procedures_on_lease_ended(&mut self, lease_id: u32, how: &str, now: Instant) {
        let ids: Vec<u32> = self
            .procedures
            .runs()
            .iter()
            .filter(|r| r.lease.as_ref().is_some_and(|l| l.0 == lease_id))
            .map(Run::id)
            .collect();
        for id in ids {
            if let Ok(run) = self.procedures.get_mut(id) {
                run.lease = None;
                let reason = format!("its lease {lease_id} was {how}");
                let actions = run.stop(StepOutcome::Failed, reason, None, now);
                self.after(id, actions, now);
            }
        }
    }

    /// The step timer: every step whose timeout is due.
    pub(crate) fn expire_procedures(&mut self, now: Instant) {
        let ids: Vec<u32> = self.procedures.runs().iter().map(Run::id).collect();
        for id in ids {
            if let Ok(run) = self.procedures.get_mut(id) {
                let actions = run.handle_timeout(now);
                self.after(id, actions, now);
            }
        }
    }

    /// After every input: the connections made and ended go to the runs (a docking one run waits
    /// for is that run's alone; one none waits for is a mismatch to every run waiting for a
    /// docking), then the runs whose step needs an element that is not online fail.
    pub(crate) fn procedures_on_input(&mut self, now: Instant) {
        let changes = std::mem::take(&mut self.out.dock_changes);
        if self.procedures.runs().is_empty() {
            return;
        }
        for (docked, c) in changes {
            let connections = self.docking().connections();
            let matching: Vec<u32> = self
                .procedures
                .runs()
                .iter()
                .filter(|r| {
                    if docked {
                        r.matches_docked(&c)
                    } else {
                        r.matches_undocked(&c)
                    }
                })
                .map(Run::id)
                .collect();
            let ids: Vec<u32> = if matching.is_empty() {
                self.procedures.runs().iter().map(Run::id).collect()
            } else {
                matching
            };
            for id in ids {
                let clock = self.clock;
                if let Ok(run) = self.procedures.get_mut(id) {
                    let actions = if docked {
                        run.handle_docked(&c, &connections, &clock, now)
                    } else {
                        run.handle_undocked(&c, &connections, &clock, now)
                    };
                    self.after(id, actions, now);
                }
            }
        }
        let lost: Vec<(u32, NodeId)> = self
            .procedures
            .runs()
            .iter()
            .flat_map(|r| r.needs().into_iter().map(move |n| (r.id(), n)))
            .filter(|&(_, n)| !self.registry.get(n).is_some_and(|e| e.online))
            .collect();
        for (id, n) in lost {
            if let Ok(run) = self.procedures.get_mut(id) {
                let actions = run.handle_lost(n, now);
                self.after(id, actions, now);
            }
        }
    }

    /// Carries out run `id`'s actions; once it ended, its lease is released and it is dropped.
    fn after(&mut self, id: u32, actions: Vec<Action>, now: Instant) {
        if actions.is_empty() {
            return;
        }
        let Ok(run) = self.procedures.get_mut(id) else {
            return;
        };
        let run = run.clone();
        self.carry_out(&run, actions);
        if run.ended() {
            self.release_procedure_lease(&run, now);
            self.procedures.sweep();
        }
        self.publish_procedures(now);
    }

    /// Lights, clears and events of `run`, in their order.
    fn carry_out(&mut self, run: &Run, actions: Vec<Action>) {
        for a in actions {
            match a {
                Action::Light { nodes, led, beep } => {
                    for n in nodes {
                        self.procedure_frame(n, Kind::LedSet, move |seq| Message::LedSet {
                            seq,
                            cmd: led,
                        });
                        if beep {
                            self.procedure_frame(n, Kind::BuzzerSet, |seq| Message::BuzzerSet {
                                seq,
                                cmd: BEEP,
                            });
                        }
                    }
                }
                Action::Clear { nodes, beep } => {
                    for n in nodes {
                        self.procedure_frame(n, Kind::LedSet, |seq| Message::LedSet {
                            seq,
                            cmd: LedCommand::Off,
                        });
                        if beep {
                            self.procedure_frame(n, Kind::BuzzerSet, |seq| Message::BuzzerSet {
                                seq,
                                cmd: BuzzerCommand::Off,
                            });
                        }
                    }
                }
                Action::Step(s) => self.out.emit(Event::ProcedureStep(s)),
                Action::Mismatch(m) => self.out.emit(Event::ProcedureMismatch(m)),
                Action::Ended(e) => {
                    tracing::info!(id = run.id(), outcome = ?e.outcome, "procedure ended");
                    self.out.emit(Event::ProcedureEnded(e));
                }
            }
        }
    }

    /// Queues one of a procedure's frames (it holds the element: no lease check).
    fn procedure_frame(&mut self, node: NodeId, kind: Kind, msg: impl FnOnce(Seq) -> Message) {
        if !self.send_own(FrameOwner::Procedure, node, kind, msg) {
            tracing::warn!(%node, ?kind, "procedure frame not sent: no free sequence number");
        }
    }

    /// Ends the lease `run` took, if it still holds it.
    fn release_procedure_lease(&mut self, run: &Run, now: Instant) {
        if let Some((_, token)) = &run.lease {
            if self.lease_table.release(token, now).is_ok() {
                self.publish_leases(now);
            }
        }
    }

    /// Queues the procedures document as of `now` (retained: never dropped).
    pub(crate) fn publish_procedures(&mut self, now: Instant) {
        let doc = self.procedures.document(now);
        self.out.publish.push_kept(Publication::Procedures(doc));
    }
}
