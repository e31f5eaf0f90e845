//! The bridge's glue for leases: the `lease`, `renew`, `release` and `break_lease` commands, the
//! check every other command passes before it is queued (whatever interface it came from: the
//! JSON API, the island view, Home Assistant), the expiry timer, and the retained leases document.

use std::time::{Instant, SystemTime};

use ihex_proto::NodeId;

use super::{Ended, Lease, LeaseEnded, LeaseGranted, LeasesDocument, LeasesReset};
use crate::bridge::{Bridge, Publication};
use crate::command::{Command, CommandError};
use crate::event::{Event, Target};

impl Bridge {
    /// The adapter tells the time of day `wall` at `now` (once at start is enough): leases' ends
    /// are then shown as times of day (`until 14:05:10 UTC`, `expires_at`) rather than as
    /// remaining seconds.
    pub fn handle_wall_clock(&mut self, wall: SystemTime, now: Instant) {
        self.set_now(now);
        self.clock.set(wall, now);
    }

    /// The leases document as of `now` (what the retained `<root>/leases` topic holds).
    pub fn leases(&self, now: Instant) -> LeasesDocument {
        LeasesDocument {
            leases: self
                .lease_table
                .held(now)
                .map(|l| l.view(&self.clock, now))
                .collect(),
        }
    }

    /// Why a command carrying `token` may not reach `target` now (`None`: it may). Reading
    /// (`list`) never comes here.
    pub(crate) fn lease_refusal(
        &self,
        cmd: &Command,
        token: Option<&str>,
        now: Instant,
    ) -> Option<CommandError> {
        let (t, c) = (&self.lease_table, &self.clock);
        let checked = match cmd {
            Command::Node {
                target: Target::Node(id),
                ..
            } => t.check(*id, token, c, now),
            Command::Node {
                target: Target::All,
                ..
            } => t.check_all(token, c, now),
            // A procedure lights and waits on its static elements: they must be free, or held by
            // the lease whose token it carries.
            Command::Procedure(spec) => spec
                .static_elements()
                .into_iter()
                .try_for_each(|id| t.check(id, token, c, now)),
            Command::Assign { new_id: id, .. } | Command::Forget { id } => {
                t.check(*id, token, c, now)
            }
            // `fw_update` skips leased elements one by one (`lease_skips`), `fw_cancel` checks
            // the running update's elements (`fw_cancel`); the lease commands act on leases
            // themselves.
            Command::List
            | Command::FwUpdate { .. }
            | Command::FwCancel
            | Command::Lease { .. }
            | Command::Renew { .. }
            | Command::Release
            | Command::BreakLease { .. }
            | Command::ProcedureCancel { .. } => Ok(()),
        };
        checked.err().map(CommandError::from)
    }

    /// `fw_update`'s elements a lease keeps from it, each with the reason (the update carries on
    /// without them): a leased element is updated only by a command carrying its lease's token.
    pub(crate) fn lease_skips(
        &self,
        nodes: &[NodeId],
        token: Option<&str>,
        now: Instant,
    ) -> Vec<(NodeId, String)> {
        nodes
            .iter()
            .filter_map(|&id| {
                let e = self.lease_table.check(id, token, &self.clock, now).err()?;
                Some((id, e.to_string()))
            })
            .collect()
    }

    /// Carries out `lease`, `renew`, `release` or `break_lease`: one answer each
    /// (`lease_granted`, `lease_ended` or `command_rejected`), and the leases document again when
    /// it changed.
    pub(crate) fn lease_command(
        &mut self,
        request_id: Option<String>,
        cmd: Command,
        token: Option<String>,
        now: Instant,
    ) {
        let token = token.as_deref().unwrap_or("");
        let name = cmd.name();
        let answer = match cmd {
            Command::Lease {
                owner,
                note,
                scope,
                ttl,
            } => self
                .lease_table
                .take(owner, note, scope, ttl, &self.clock, now)
                .map(|l| granted(request_id.clone(), name, l, &self.clock, now)),
            Command::Renew { ttl } => self
                .lease_table
                .renew(token, ttl, now)
                .map(|l| granted(request_id.clone(), name, l, &self.clock, now)),
            Command::Release => self.lease_table.release(token, now).map(|l| {
                tracing::info!(id = l.id, owner = %l.owner, "lease released");
                self.ended(request_id.clone(), Ended::Released, None, &l, now)
            }),
            Command::BreakLease { id, reason } => self.lease_table.break_lease(id, now).map(|l| {
                tracing::warn!(id, owner = %l.owner, %reason, "lease broken");
                self.procedures_on_lease_ended(id, "broken (break_lease)", now);
                self.ended(request_id.clone(), Ended::Broken, Some(reason), &l, now)
            }),
            _ => return,
        };
        match answer {
            Ok(event) => {
                self.out.emit(event);
                self.publish_leases(now);
            }
            Err(e) => self.reject(request_id, e.into()),
        }
    }

    fn ended(
        &self,
        request_id: Option<String>,
        why: Ended,
        reason: Option<String>,
        lease: &Lease,
        now: Instant,
    ) -> Event {
        Event::LeaseEnded(Box::new(LeaseEnded {
            request_id,
            why,
            reason,
            lease: lease.view(&self.clock, now),
        }))
    }

    /// Queues the leases document as of `now` (retained: never dropped).
    pub(crate) fn publish_leases(&mut self, now: Instant) {
        let doc = self.leases(now);
        self.out.publish.push_kept(Publication::Leases(doc));
    }

    /// The lease timer: every lease whose end is due is `lease_ended` (`expired`).
    pub(crate) fn expire_leases(&mut self, now: Instant) {
        let ended = self.lease_table.expire(now);
        if ended.is_empty() {
            return;
        }
        for l in &ended {
            tracing::info!(id = l.id, owner = %l.owner, "lease expired");
            self.procedures_on_lease_ended(l.id, "expired", now);
            let event = self.ended(None, Ended::Expired, None, l, now);
            self.out.emit(event);
        }
        self.publish_leases(now);
    }

    /// The MQTT session is up: the leases document again (a restarted broker may have lost it);
    /// at the first connection of this run, `leases_reset`, since an earlier run's leases ended
    /// with it and its retained document is replaced.
    pub(crate) fn leases_on_connected(&mut self, now: Instant) {
        if !self.leases_announced {
            self.leases_announced = true;
            self.out.emit(Event::LeasesReset(LeasesReset {
                reason: "the gateway started: leases held before, if any, ended with the restart; \
                         take them again"
                    .into(),
            }));
        }
        self.publish_leases(now);
    }
}

fn granted(
    request_id: Option<String>,
    cmd: &str,
    l: &Lease,
    clock: &super::WallClock,
    now: Instant,
) -> Event {
    tracing::info!(id = l.id, owner = %l.owner, cmd, "lease granted");
    Event::LeaseGranted(Box::new(LeaseGranted {
        request_id,
        cmd: cmd.into(),
        token: l.token.clone(),
        lease: l.view(clock, now),
    }))
}
