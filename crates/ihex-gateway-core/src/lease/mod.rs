//! Leases, sans-IO: who holds which elements of the island, until when. The [`LeaseTable`] is a
//! pure state machine (time passed in): [`LeaseTable::take`], [`LeaseTable::renew`],
//! [`LeaseTable::release`] (by the token only), [`LeaseTable::break_lease`] (by the lease's public
//! id, an administrative privilege), [`LeaseTable::check`] (may a command reach these elements?)
//! and [`LeaseTable::expire`] at [`LeaseTable::next_deadline`]. A lease is held while
//! `now < expires`: at the exact instant of its end, commands without its token are accepted
//! again, whether or not the expiry timer has run yet.
//!
//! The bridge's glue (`glue`) turns the `lease`, `renew`, `release` and `break_lease` commands into
//! calls on the table, refuses commands to leased elements, runs the expiry from the bridge's one
//! timer table and publishes the retained leases document and the `lease_ended` events.
//!
//! The token is the owner's proof for its own commands; it is answered on the events topic, so
//! it guards against accidents, not against a client that reads every answer — that is the
//! broker's ACLs' job (docs/mqtt-api.md).

pub(crate) mod glue;

use std::collections::hash_map::RandomState;
use std::fmt;
use std::hash::BuildHasher;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use ihex_proto::NodeId;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::event::HexId;

/// Longest lease, seconds (a day: a run that needs longer renews).
pub const MAX_LEASE_S: u32 = 86_400;
/// Longest owner name, characters.
pub const MAX_OWNER_CHARS: usize = 64;
/// Longest note, characters.
pub const MAX_NOTE_CHARS: usize = 200;

/// What a lease covers.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Scope {
    /// Every element of the island, present and future (`"all"`).
    Island,
    /// These elements (at least one, no repeats).
    Nodes(Vec<NodeId>),
}

impl Scope {
    /// True when the scope covers `id`.
    pub fn covers(&self, id: NodeId) -> bool {
        match self {
            Scope::Island => true,
            Scope::Nodes(ids) => ids.contains(&id),
        }
    }

    /// An element both scopes cover (`None`: they are disjoint); with the island, the other
    /// scope's first element, or `None` for island against island.
    fn overlap(&self, other: &Scope) -> Option<Option<NodeId>> {
        match (self, other) {
            (Scope::Island, Scope::Island) => Some(None),
            (Scope::Island, Scope::Nodes(ids)) | (Scope::Nodes(ids), Scope::Island) => {
                ids.first().map(|&id| Some(id))
            }
            (Scope::Nodes(a), Scope::Nodes(b)) => {
                a.iter().find(|id| b.contains(id)).map(|&id| Some(id))
            }
        }
    }
}

impl Serialize for Scope {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Scope::Island => s.serialize_str("all"),
            Scope::Nodes(ids) => s.collect_seq(ids.iter().map(|&id| HexId(id))),
        }
    }
}

impl<'de> Deserialize<'de> for Scope {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Form {
            All(String),
            Nodes(Vec<HexId>),
        }
        match Form::deserialize(d)? {
            Form::All(s) if s == "all" => Ok(Scope::Island),
            Form::All(s) => Err(serde::de::Error::custom(format!(
                "expected \"all\" or a list of node ids; got {s:?}"
            ))),
            Form::Nodes(ids) => Ok(Scope::Nodes(ids.into_iter().map(|h| h.0).collect())),
        }
    }
}

/// The wall clock as the adapter told it, to show a lease's end as a time of day: the core has no
/// clock of its own, and an [`Instant`] has no date.
#[derive(Clone, Copy, Debug, Default)]
pub struct WallClock {
    anchor: Option<(SystemTime, Instant)>,
}

impl WallClock {
    /// `wall` was the time of day at `now`.
    pub fn set(&mut self, wall: SystemTime, now: Instant) {
        self.anchor = Some((wall, now));
    }

    /// Seconds since the Unix epoch at `t`, if the adapter told the wall clock.
    fn unix(&self, t: Instant) -> Option<u64> {
        let (wall, at) = self.anchor?;
        let wall_t = match t.checked_duration_since(at) {
            Some(d) => wall.checked_add(d)?,
            None => wall.checked_sub(at.saturating_duration_since(t))?,
        };
        Some(wall_t.duration_since(UNIX_EPOCH).ok()?.as_secs())
    }

    /// `t` as an RFC 3339 UTC time (`2026-11-25T14:05:10Z`), if the wall clock is known.
    pub fn rfc3339(&self, t: Instant) -> Option<String> {
        let secs = self.unix(t)?;
        let (y, m, d) = civil_from_days(secs / 86_400);
        let s = secs % 86_400;
        Some(format!(
            "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
            s / 3600,
            s / 60 % 60,
            s % 60
        ))
    }

    /// `until 14:05:10 UTC`, or `for another 42 s` when the wall clock is not known.
    fn until(&self, t: Instant, now: Instant) -> String {
        match self.unix(t) {
            Some(secs) => {
                let s = secs % 86_400;
                format!("until {:02}:{:02}:{:02} UTC", s / 3600, s / 60 % 60, s % 60)
            }
            None => format!(
                "for another {} s",
                t.saturating_duration_since(now).as_secs_f64().ceil()
            ),
        }
    }
}

/// Year, month, day of a day count since 1970-01-01 (Howard Hinnant's `civil_from_days`).
fn civil_from_days(days: u64) -> (u64, u64, u64) {
    let z = days + 719_468;
    let era = z / 146_097;
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + u64::from(m <= 2);
    (y, m, d)
}

/// One lease.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Lease {
    /// Public number, unique within this gateway run (what `break_lease` names).
    pub id: u32,
    /// The owner's proof, carried in its commands' `lease` field.
    pub token: String,
    /// Who holds it.
    pub owner: String,
    /// Why, for the people it keeps out.
    pub note: Option<String>,
    /// What it covers.
    pub scope: Scope,
    /// Its end: held while `now < expires`.
    pub expires: Instant,
}

impl Lease {
    /// True while it is held at `now`.
    pub fn held(&self, now: Instant) -> bool {
        now < self.expires
    }

    /// Its public form (without the token) for the leases document and events.
    pub fn view(&self, clock: &WallClock, now: Instant) -> LeaseView {
        LeaseView {
            id: self.id,
            owner: self.owner.clone(),
            note: self.note.clone(),
            nodes: self.scope.clone(),
            expires_at: clock.rfc3339(self.expires),
            remaining_ms: crate::registry::millis(self.expires.saturating_duration_since(now)),
        }
    }

    /// `111 is leased by run-42 until 14:05:10 UTC (note: sample prep)`.
    fn held_by(&self, what: &str, clock: &WallClock, now: Instant) -> String {
        let note = match &self.note {
            Some(n) => format!(" (note: {n})"),
            None => String::new(),
        };
        format!(
            "{what} is leased by {} {}{note}",
            self.owner,
            clock.until(self.expires, now)
        )
    }
}

/// A lease's public form: the leases document's entries and the lease events' `lease`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LeaseView {
    /// Public number (what `break_lease` names).
    pub id: u32,
    /// Who holds it.
    pub owner: String,
    /// Why, if the owner said.
    pub note: Option<String>,
    /// `"all"` or the element IDs.
    pub nodes: Scope,
    /// Its end, RFC 3339 UTC (`null` when the gateway does not know the time of day).
    pub expires_at: Option<String>,
    /// Its end, ms after the document or event was made.
    pub remaining_ms: u64,
}

/// Why a lease request or a command was refused: the reason a person can act on.
#[derive(Clone, PartialEq, Eq, Debug, thiserror::Error)]
pub enum LeaseError {
    /// A command without the token of a lease on its element.
    #[error("{0}; send the lease's token in `lease`, wait for its end, or ask whoever may send `break_lease`")]
    Leased(String),
    /// `lease` overlapping a lease held now.
    #[error("lease: {0}; wait for its end or ask its owner to release it")]
    Overlap(String),
    /// `renew` or `release` with a token no lease held now has.
    #[error("{cmd}: no lease held now has this token (it ended, was broken or released, or the gateway restarted); take a new lease")]
    UnknownToken {
        /// The command name.
        cmd: &'static str,
    },
    /// `break_lease` of an id no lease held now has.
    #[error("break_lease: no lease {id} is held now; see the retained leases document for the ones that are")]
    UnknownId {
        /// The id asked for.
        id: u32,
    },
}

/// Why a lease ended.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Ended {
    /// Its owner released it.
    Released,
    /// Its time ran out.
    Expired,
    /// `break_lease`.
    Broken,
}

/// Payload of `lease_granted`: the answer to `lease` and `renew`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LeaseGranted {
    /// The command's `request_id`.
    pub request_id: Option<String>,
    /// `lease` or `renew`.
    pub cmd: String,
    /// The token the owner's commands carry in their `lease` field.
    pub token: String,
    /// The lease as it is now.
    pub lease: LeaseView,
}

/// Payload of `lease_ended`: the answer to `release` and `break_lease`, and the event of an
/// expiry (`request_id` `null`).
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LeaseEnded {
    /// The `release` or `break_lease` command's `request_id`; `null` for an expiry.
    pub request_id: Option<String>,
    /// How it ended.
    pub why: Ended,
    /// The reason `break_lease` gave.
    pub reason: Option<String>,
    /// The lease as it was.
    pub lease: LeaseView,
}

/// Payload of `leases_reset`: at its first connection after a start, the gateway holds no lease,
/// whatever an earlier run held (leases end with the gateway's restart).
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LeasesReset {
    /// What it means.
    pub reason: String,
}

/// The retained leases document (`<root>/leases`): every lease held when it was made.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LeasesDocument {
    /// By id.
    pub leases: Vec<LeaseView>,
}

/// Every lease held now.
#[derive(Debug)]
pub struct LeaseTable {
    leases: Vec<Lease>,
    /// One bit per raw node id that a lease in `leases` names: a command to an element without
    /// its bit, with no island lease in `leases`, passes without a scan (the common case).
    named: [u64; NAMED_WORDS],
    /// Island leases in `leases`.
    islands: usize,
    next_id: u32,
    /// Keys the tokens: another run's tokens (or a guessed counter) never match this run's.
    keys: RandomState,
}

impl Default for LeaseTable {
    fn default() -> Self {
        LeaseTable::new()
    }
}

/// Words of [`LeaseTable::named`]: a bit for every raw node id.
const NAMED_WORDS: usize = (NodeId::MAX_RAW as usize + 1).div_ceil(64);

/// `id`'s word in [`LeaseTable::named`] and its bit there.
fn named_bit(id: NodeId) -> (usize, u64) {
    let raw = usize::from(id.get());
    (raw / 64, 1 << (raw % 64))
}

impl LeaseTable {
    /// No leases.
    pub fn new() -> Self {
        LeaseTable {
            leases: Vec::new(),
            named: [0; NAMED_WORDS],
            islands: 0,
            next_id: 1,
            keys: RandomState::new(),
        }
    }

    /// The leases held at `now` (some may wait for [`LeaseTable::expire`]), by id.
    pub fn held(&self, now: Instant) -> impl Iterator<Item = &Lease> {
        self.leases.iter().filter(move |l| l.held(now))
    }

    /// Takes a lease of `scope` for `ttl` from `now`; refused, naming the holder, when a lease
    /// held now covers one of its elements.
    pub fn take(
        &mut self,
        owner: String,
        note: Option<String>,
        scope: Scope,
        ttl: Duration,
        clock: &WallClock,
        now: Instant,
    ) -> Result<&Lease, LeaseError> {
        for l in self.held(now) {
            if let Some(id) = l.scope.overlap(&scope) {
                let what = id.map_or_else(|| "the island".to_owned(), |id| id.to_string());
                return Err(LeaseError::Overlap(l.held_by(&what, clock, now)));
            }
        }
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1).max(1);
        let token = format!(
            "{:016x}{:016x}",
            self.keys.hash_one((id, &owner)),
            self.keys.hash_one((&owner, id, now))
        );
        self.leases.push(Lease {
            id,
            token,
            owner,
            note,
            scope,
            expires: now + ttl,
        });
        self.index();
        self.leases.last().ok_or(LeaseError::UnknownId { id })
    }

    /// The lease held now whose token is `token`.
    fn by_token(&mut self, token: &str, now: Instant) -> Option<usize> {
        self.leases
            .iter()
            .position(|l| l.held(now) && l.token == token)
    }

    /// Extends the lease with `token` to `ttl` from `now`.
    pub fn renew(
        &mut self,
        token: &str,
        ttl: Duration,
        now: Instant,
    ) -> Result<&Lease, LeaseError> {
        let i = self
            .by_token(token, now)
            .ok_or(LeaseError::UnknownToken { cmd: "renew" })?;
        self.leases[i].expires = now + ttl;
        Ok(&self.leases[i])
    }

    /// Ends the lease with `token`.
    pub fn release(&mut self, token: &str, now: Instant) -> Result<Lease, LeaseError> {
        let i = self
            .by_token(token, now)
            .ok_or(LeaseError::UnknownToken { cmd: "release" })?;
        Ok(self.remove(i))
    }

    /// Ends lease `id` without its token (the administrative break).
    pub fn break_lease(&mut self, id: u32, now: Instant) -> Result<Lease, LeaseError> {
        let i = self
            .leases
            .iter()
            .position(|l| l.held(now) && l.id == id)
            .ok_or(LeaseError::UnknownId { id })?;
        Ok(self.remove(i))
    }

    /// May a command carrying `token` reach `id` at `now`? Refused, naming the holder, when a
    /// lease held now covers `id` and `token` is not its token.
    pub fn check(
        &self,
        id: NodeId,
        token: Option<&str>,
        clock: &WallClock,
        now: Instant,
    ) -> Result<(), LeaseError> {
        match self.holder(id, token, now) {
            Some(l) => Err(LeaseError::Leased(l.held_by(&id.to_string(), clock, now))),
            None => Ok(()),
        }
    }

    /// May a command carrying `token` reach every element (a broadcast)? Refused when any lease
    /// held now is not the token's.
    pub fn check_all(
        &self,
        token: Option<&str>,
        clock: &WallClock,
        now: Instant,
    ) -> Result<(), LeaseError> {
        match self.held(now).find(|l| Some(l.token.as_str()) != token) {
            Some(l) => {
                let what = match &l.scope {
                    Scope::Island => "the island".to_owned(),
                    Scope::Nodes(ids) => format!("\"all\" includes {}, which", HexList(ids)),
                };
                Err(LeaseError::Leased(l.held_by(&what, clock, now)))
            }
            None => Ok(()),
        }
    }

    /// The lease held now that keeps a command carrying `token` from `id`.
    pub fn holder(&self, id: NodeId, token: Option<&str>, now: Instant) -> Option<&Lease> {
        let (word, bit) = named_bit(id);
        if self.islands == 0 && self.named[word] & bit == 0 {
            return None;
        }
        self.held(now)
            .find(|l| l.scope.covers(id) && Some(l.token.as_str()) != token)
    }

    /// Removes lease `i` (an index into `leases`).
    fn remove(&mut self, i: usize) -> Lease {
        let lease = self.leases.remove(i);
        self.index();
        lease
    }

    /// Sets `named` and `islands` from `leases`, after every change of the set of leases.
    fn index(&mut self) {
        self.named = [0; NAMED_WORDS];
        self.islands = 0;
        for l in &self.leases {
            match &l.scope {
                Scope::Island => self.islands += 1,
                Scope::Nodes(ids) => {
                    for &id in ids {
                        let (word, bit) = named_bit(id);
                        self.named[word] |= bit;
                    }
                }
            }
        }
    }

    /// The earliest end of a lease.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.leases.iter().map(|l| l.expires).min()
    }

    /// Removes and returns the leases whose end is due by `now`, by id.
    pub fn expire(&mut self, now: Instant) -> Vec<Lease> {
        let (ended, held) = std::mem::take(&mut self.leases)
            .into_iter()
            .partition(|l| !l.held(now));
        self.leases = held;
        if !ended.is_empty() {
            self.index();
        }
        ended
    }
}

/// Node IDs as `111, 2`.
struct HexList<'a>(&'a [NodeId]);

impl fmt::Display for HexList<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, id) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(", ")?;
            }
            id.fmt(f)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
