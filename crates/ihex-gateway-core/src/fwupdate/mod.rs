//! The firmware-update sender, sans-IO: one checked image to many nodes at once (protocol 1.2,
//! `docs/protocol.md` "Firmware transfer"), under a bus-share cap, with a per-node outcome.
//!
//! The sender works in rounds. Each round it looks at what every node last said and queues, in
//! order: a `FwBegin` to each node without a transfer (a new one, or one that reset), a `FwQuery`
//! to each node that did not answer the last round, the frames the other nodes miss (broadcast
//! when several miss a frame, else to the one node), a `FwEnd commit` to each node that has
//! everything, and a `FwQuery` to each node still receiving. A node that did not answer gets no
//! data until it does: what it last said is stale, so resending from it repeats what it may
//! already have, and a node swamped by a burst drops the query at the burst's tail again (the
//! vicious circle that left a node `unreachable`). When the
//! queue has drained and every node asked has answered (or the reply time is up: a miss), the
//! next round starts. A node's first answer after the header says it misses the whole image,
//! so the first data round is one broadcast of the image; later rounds resend only the gaps.
//! A static element whose docked mobile elements are in the same update installs only once
//! they have their outcome ([`FwSender::set_docked`]).
//! After the commit, each node is followed alone: `rebooting`, its `BootUp`, then queries until
//! its new image has confirmed itself (`idle`: `updated`) or was put back (`reverted`). Where
//! `idle` is ambiguous — a restart before the node said `rebooting`, or a mobile element whose
//! power was cut — only the version in its state report ([`FwSender::handle_firmware`]) makes it
//! `updated`; its old version begins it again.
//!
//! A mobile element docked on a static element that restarts (in the update or not) loses its
//! power: it gets a restart's time before a missed answer counts, is begun again if the cut cost
//! it its transfer or its trial image (up to [`POWER_RETRIES`] times), and otherwise ends
//! `lost_power` naming the static element — never `reverted` or `unreachable`. A node given up
//! that later reports the new version confirmed is corrected with an `fw_correction` event.
//!
//! Progress (`fw_progress`) is published at every [`PROGRESS_STEP`] % of a node's transfer, from
//! what it last said it has plus the frames sent to it since: no query is added for it.
//!
//! Every frame the sender emits goes through a [`BitBucket`] (worst-case bits on the wire), so
//! an update never takes more than its share of the bus; the bridge hands these frames out only
//! when it has nothing else to send. Time comes in through the `handle_*` calls; the sender
//! remembers the latest `now` for [`FwSender::poll_transmit`].

mod bucket;
mod glue;
mod image;
mod report;
#[cfg(test)]
mod tests;
mod upload;

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use ihex_proto::{FwAction, FwPhase, FwStatus, Message, NodeId, Packet};

pub use bucket::BitBucket;
pub use glue::FwLoad;
pub(crate) use glue::FwUpdates;
pub use image::{FwImage, FwImageError};
pub use report::{FwCorrection, FwProgress, FwReport, NodeOutcome, NodeReport};
pub use upload::{FwUpload, UploadResult, Uploads, MAX_UPLOAD, UPLOADS_KEPT};

use crate::event::{Event, HexId};

/// Default bus share of an update, %.
pub const DEFAULT_BUS_SHARE: u8 = 50;
/// The iHEX bus bitrate.
pub const BUS_BITRATE: u32 = 500_000;
/// How many times an element that lost its power mid-update (its static element restarted) is
/// begun again before its outcome is `lost_power`.
pub const POWER_RETRIES: u32 = 2;
/// `fw_progress` is published at least at every multiple of this many percent of a node's
/// transfer.
pub const PROGRESS_STEP: u8 = 5;

/// Tunables of an update.
#[derive(Clone, Debug)]
pub struct FwConfig {
    /// Bus bitrate, bit/s.
    pub bitrate: u32,
    /// Largest share of the bus the update's frames take, % (1–100).
    pub bus_share: u8,
    /// How long a node has to answer a begin, a query or a commit once the queue has drained
    /// (the gateway uses its command timeout).
    pub reply_timeout: Duration,
    /// Unanswered requests in a row a node may have; one more and it is `unreachable`.
    pub max_misses: u32,
    /// How long a node may erase before the others get data anyway.
    pub erase_timeout: Duration,
    /// How long a node may take from `rebooting` to its `BootUp` (the bootloader's swap).
    pub reboot_timeout: Duration,
    /// How long a new image may stay on trial before the node is `unreachable` (the node's own
    /// trial limit is 60 s, after which it reverts and says so).
    pub confirm_timeout: Duration,
    /// Period of the queries to a node on trial.
    pub confirm_poll: Duration,
    /// Shortest interval between two `fw_progress` events of a node in the same phase.
    pub progress_interval: Duration,
    /// The lab's public key: an image uploaded over MQTT must be signed with it. `None`: the
    /// gateway checks everything of an upload but its signature (the nodes check that).
    pub trusted_key: Option<ihex_image::PublicKey>,
}

impl Default for FwConfig {
    fn default() -> Self {
        FwConfig {
            bitrate: BUS_BITRATE,
            bus_share: DEFAULT_BUS_SHARE,
            reply_timeout: Duration::from_millis(500),
            max_misses: 5,
            erase_timeout: Duration::from_secs(20),
            reboot_timeout: Duration::from_secs(30),
            confirm_timeout: Duration::from_secs(90),
            confirm_poll: Duration::from_secs(1),
            progress_interval: Duration::from_secs(1),
            trusted_key: None,
        }
    }
}

/// Where the sender has one node.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Stage {
    /// Begin, header, data and resends.
    Transfer,
    /// Commit sent: waiting for `rebooting` (or a refusal, e.g. `corrupted`).
    Committing,
    /// Waiting for its `BootUp`.
    Rebooting,
    /// Its new image runs: waiting for it to confirm itself.
    Confirming,
    /// Has an outcome.
    Done,
}

#[derive(Clone, Debug)]
struct NodeTx {
    stage: Stage,
    /// What it last said about this image (`None`: nothing yet, or it reset).
    status: Option<FwStatus>,
    /// A begin, query or commit went out that it has not answered yet.
    awaiting: bool,
    misses: u32,
    /// Post-commit stages: when to act next.
    due: Option<Instant>,
    /// Confirming: when to give up.
    give_up: Option<Instant>,
    /// When it was first seen erasing in the current attempt.
    erasing_since: Option<Instant>,
    outcome: Option<(NodeOutcome, Option<String>, Instant)>,
    /// Last progress published: phase name, percent, when.
    progress: Option<(&'static str, u8, Instant)>,
    /// The frames planned for it in this round (its first missing run), `start..end`.
    planned: Option<(u32, u32)>,
    /// The static element whose restart cut its power in the middle of its update: it gets time
    /// to come back, and its outcome names the cause.
    power_cut_by: Option<NodeId>,
    /// Times it was begun again after losing power.
    power_retries: u32,
    /// After a power cut: no unanswered request counts as a miss before this (its host restarts,
    /// then it starts and docks again).
    grace_until: Option<Instant>,
    /// It was sent a commit: an image it later reports confirmed came from this update.
    committed: bool,
    /// It restarted after the commit without having said `rebooting`: whether it installed the
    /// image is known only from the version it reports.
    unsure: bool,
    /// Its state report named the image's version (on trial or not) since the commit.
    seen_new: bool,
    /// Data frames of `planned` that went out (to it or broadcast) since its last status: its
    /// progress between two statuses, without asking it (a query per node per step would cost
    /// the bus what the update needs).
    sent_since_status: u32,
}

impl NodeTx {
    fn new() -> Self {
        NodeTx {
            stage: Stage::Transfer,
            status: None,
            awaiting: false,
            misses: 0,
            due: None,
            give_up: None,
            erasing_since: None,
            outcome: None,
            progress: None,
            planned: None,
            sent_since_status: 0,
            power_cut_by: None,
            power_retries: 0,
            grace_until: None,
            committed: false,
            unsure: false,
            seen_new: false,
        }
    }
}

/// One update in progress: an image, the nodes it goes to, and where each one is.
#[derive(Debug)]
pub struct FwSender {
    config: FwConfig,
    image: FwImage,
    force: bool,
    request_id: Option<String>,
    nodes: BTreeMap<NodeId, NodeTx>,
    queue: VecDeque<Packet>,
    bucket: BitBucket,
    /// End of the current wait for answers (set when the queue drains).
    round_deadline: Option<Instant>,
    bus_down: bool,
    started: Instant,
    now: Instant,
    frames_sent: u64,
    events: VecDeque<Event>,
    finished: bool,
    /// Mobile element → the static element whose relay powers it (docked on it).
    powered_by: BTreeMap<NodeId, NodeId>,
    /// Elements left out because a lease holds them, with the reason: in the report as `skipped`.
    skipped: Vec<(NodeId, String)>,
}

impl FwSender {
    /// Starts updating `nodes` with `image` at `now` (`force`: allow a downgrade). The first
    /// frames are ready at once.
    pub fn new(
        image: FwImage,
        nodes: impl IntoIterator<Item = NodeId>,
        force: bool,
        request_id: Option<String>,
        config: FwConfig,
        now: Instant,
    ) -> Self {
        let mut s = FwSender {
            bucket: BitBucket::new(config.bitrate, config.bus_share, now),
            config,
            image,
            force,
            request_id,
            nodes: nodes.into_iter().map(|id| (id, NodeTx::new())).collect(),
            queue: VecDeque::new(),
            round_deadline: None,
            bus_down: false,
            started: now,
            now,
            frames_sent: 0,
            events: VecDeque::new(),
            finished: false,
            powered_by: BTreeMap::new(),
            skipped: Vec::new(),
        };
        s.advance(now);
        s
    }

    /// The island's dockings, `(static element, mobile element)`: a static element of the update
    /// is told to install (and so to restart) only once every mobile element of the update docked
    /// on it has its outcome, so that none of them loses power in the middle of its own update
    /// where the static element's relay cannot be held through its restart.
    pub fn set_docked(&mut self, docked: impl IntoIterator<Item = (NodeId, NodeId)>) {
        self.powered_by = docked.into_iter().map(|(s, m)| (m, s)).collect();
    }

    /// `host` restarted (into its new image, or because it lost power itself): every mobile
    /// element of the update docked on it and not done lost its power with it. Each gets the time
    /// a restart takes to come back, and its outcome will say why if it does not.
    fn host_restarted(&mut self, host: NodeId, now: Instant) {
        let (reboot, confirm) = (self.config.reboot_timeout, self.config.confirm_timeout);
        let mobiles: Vec<NodeId> = self
            .powered_by
            .iter()
            .filter(|(_, s)| **s == host)
            .map(|(m, _)| *m)
            .collect();
        for m in mobiles {
            let Some(n) = self.nodes.get_mut(&m) else {
                continue;
            };
            if n.stage == Stage::Done {
                continue;
            }
            tracing::info!(node = %m, %host, "the element powering it restarted");
            n.power_cut_by = Some(host);
            n.misses = 0;
            n.grace_until = Some(now + reboot);
            if let Some(d) = n.due.as_mut() {
                *d = (*d).max(now + reboot);
            }
            if let Some(g) = n.give_up.as_mut() {
                *g = (*g).max(now + confirm);
            }
            // In the transfer its RAM is gone: begin again, without waiting for its boot-up
            // (a mobile element re-docks before it may say anything).
            if n.stage == Stage::Transfer {
                n.status = None;
                n.awaiting = false;
                n.erasing_since = None;
            }
        }
    }

    /// A node of the update started from a power-on (its boot-up says so), not from a reset it
    /// asked for: whatever it does next — come back on its old image, revert a trial image the
    /// cut interrupted — is the cut's doing, not the image's. Call before
    /// [`FwSender::handle_boot_up`].
    pub fn handle_power_on(&mut self, src: NodeId, now: Instant) {
        self.tick(now);
        if let Some(n) = self.nodes.get_mut(&src) {
            // In the transfer a restart only costs the transfer, which starts again anyway.
            let installing = matches!(
                n.stage,
                Stage::Committing | Stage::Rebooting | Stage::Confirming
            );
            if installing && n.power_cut_by.is_none() {
                tracing::info!(node = %src, "powered on in the middle of its update");
                n.power_cut_by = Some(src);
            }
        }
    }

    /// A node's state report names the firmware it runs (`trial`: not confirmed yet). The new
    /// version, confirmed, ends a node still being followed as `updated`; for a node already
    /// given up (`unreachable`, `lost_power`) it corrects its outcome and says so
    /// (`fw_correction`).
    pub fn handle_firmware(
        &mut self,
        src: NodeId,
        version: ihex_proto::FirmwareVersion,
        trial: bool,
        now: Instant,
    ) {
        self.tick(now);
        let Some(n) = self.nodes.get_mut(&src) else {
            return;
        };
        if !n.committed {
            return;
        }
        if version == self.image.version() {
            n.seen_new = true;
        }
        if trial {
            return;
        }
        if version != self.image.version() {
            // Its old image, confirmed, after a power cut: the new one never got to run, or was
            // put back by the cut.
            if n.stage == Stage::Confirming && n.power_cut_by.is_some() {
                self.power_retry(src, now);
                self.advance(now);
            }
            return;
        }
        match (n.stage, n.outcome.as_ref().map(|o| o.0)) {
            (Stage::Committing | Stage::Rebooting | Stage::Confirming, _) => {
                self.finish_node(src, NodeOutcome::Updated, None, now);
            }
            (Stage::Done, Some(was @ (NodeOutcome::Unreachable | NodeOutcome::LostPower))) => {
                let why = n
                    .outcome
                    .as_ref()
                    .and_then(|o| o.1.clone())
                    .unwrap_or_default();
                n.outcome = Some((NodeOutcome::Updated, None, now));
                tracing::info!(node = %src, ?was, "a node reported the new image confirmed after all");
                self.events
                    .push_back(Event::FwCorrection(Box::new(FwCorrection {
                        request_id: self.request_id.clone(),
                        image_id: format!("{:08x}", self.image.image_id()),
                        version: self.image.version().to_string(),
                        node: HexId(src),
                        was,
                        outcome: NodeOutcome::Updated,
                        reason: format!(
                            "reported {version} confirmed after it was given `{}` ({why})",
                            was.as_str()
                        ),
                    })));
            }
            _ => {}
        }
        self.advance(now);
    }

    /// A node whose power was cut runs its old image again: begun again, up to
    /// [`POWER_RETRIES`] times; then its outcome is `lost_power`.
    fn power_retry(&mut self, id: NodeId, now: Instant) {
        let Some(n) = self.nodes.get_mut(&id) else {
            return;
        };
        if n.power_retries >= POWER_RETRIES {
            // `finish_node` names the cause.
            self.finish_node(id, NodeOutcome::Reverted, None, now);
            return;
        }
        tracing::info!(node = %id, host = ?n.power_cut_by, "lost power mid-update: updating it again");
        n.power_retries += 1;
        n.power_cut_by = None;
        n.stage = Stage::Transfer;
        n.status = None;
        n.awaiting = false;
        n.due = None;
        n.give_up = None;
        n.committed = false;
    }

    /// True while a mobile element of the update docked on `id` has no outcome yet.
    fn powers_one_in_update(&self, id: NodeId) -> bool {
        self.powered_by
            .iter()
            .any(|(m, s)| *s == id && self.nodes.get(m).is_some_and(|n| n.stage != Stage::Done))
    }

    /// Names elements the update leaves out (a lease holds them): its report lists each as
    /// `skipped` with the reason.
    pub fn with_skipped(mut self, skipped: Vec<(NodeId, String)>) -> Self {
        self.skipped = skipped;
        self
    }

    /// When the update started.
    pub fn started_at(&self) -> Instant {
        self.started
    }

    /// When its report was emitted.
    pub fn finished_at(&self) -> Option<Instant> {
        self.finished.then_some(self.now)
    }

    /// The image being sent.
    pub fn image(&self) -> &FwImage {
        &self.image
    }

    /// The nodes being updated.
    pub fn nodes(&self) -> impl Iterator<Item = NodeId> + '_ {
        self.nodes.keys().copied()
    }

    /// The nodes without an outcome yet.
    pub fn open_nodes(&self) -> impl Iterator<Item = NodeId> + '_ {
        self.nodes
            .iter()
            .filter(|(_, n)| n.stage != Stage::Done)
            .map(|(id, _)| *id)
    }

    /// True once the report has been emitted: the sender has nothing more to do.
    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// True once the report is out and every frame sent: the sender can be dropped.
    pub fn is_done(&self) -> bool {
        self.finished && self.queue.is_empty()
    }

    /// The next event to publish (`fw_progress`, `fw_report`).
    #[must_use]
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// A node said where it is in a transfer.
    pub fn handle_status(&mut self, src: NodeId, st: FwStatus, now: Instant) {
        self.tick(now);
        let Some(n) = self.nodes.get_mut(&src) else {
            return;
        };
        n.awaiting = false;
        n.misses = 0;
        n.planned = None;
        n.sent_since_status = 0;
        match (n.stage, st.phase) {
            (Stage::Done, _) => return,
            (_, FwPhase::Refused) => {
                let reason = st.reason.to_string();
                self.finish_node(src, NodeOutcome::Refused, Some(reason), now);
            }
            (Stage::Transfer, FwPhase::Erasing) => {
                n.erasing_since.get_or_insert(now);
                n.status = Some(st);
            }
            (Stage::Transfer, FwPhase::Verifying | FwPhase::Rebooting) => {
                // A commit from an earlier round was taken after all.
                n.committed = true;
                n.stage = Stage::Committing;
                n.status = Some(st);
                self.on_commit_status(src, st, now);
            }
            (Stage::Transfer, _) => n.status = Some(st),
            (Stage::Committing | Stage::Rebooting, _) => self.on_commit_status(src, st, now),
            (Stage::Confirming, FwPhase::Trial) => {}
            // Restarted before it said it installed, and no report of the new version: `idle`
            // is its old image. Begin again.
            (Stage::Confirming, FwPhase::Idle) if n.unsure && !n.seen_new => {
                tracing::info!(node = %src, "restarted before installing: starting it again");
                n.stage = Stage::Transfer;
                n.status = None;
                n.due = None;
                n.give_up = None;
                n.committed = false;
                n.unsure = false;
            }
            // After a power cut, `idle` may also be the old image that never got to install:
            // only its state report's version tells (`handle_firmware`).
            (Stage::Confirming, FwPhase::Idle) if n.power_cut_by.is_some() && !n.seen_new => {}
            (Stage::Confirming, FwPhase::Idle) => {
                self.finish_node(src, NodeOutcome::Updated, None, now)
            }
            // Its power was cut while the new image was on trial: that reset put the old image
            // back, through no fault of the image. Begin it again.
            (Stage::Confirming, FwPhase::Reverted) if n.power_cut_by.is_some() => {
                self.power_retry(src, now)
            }
            (Stage::Confirming, FwPhase::Reverted) => {
                let reason = Some("the new image did not confirm itself".to_string());
                self.finish_node(src, NodeOutcome::Reverted, reason, now)
            }
            (Stage::Confirming, _) => {}
        }
        self.progress(src, now);
        self.advance(now);
    }

    /// A node announced a (re)start.
    pub fn handle_boot_up(&mut self, src: NodeId, now: Instant) {
        self.tick(now);
        self.host_restarted(src, now);
        let confirm_poll = self.config.confirm_poll;
        let confirm_timeout = self.config.confirm_timeout;
        let Some(n) = self.nodes.get_mut(&src) else {
            return;
        };
        match n.stage {
            // Its transfer was in RAM: it starts again at the next round.
            Stage::Transfer => {
                tracing::info!(node = %src, "node reset during its transfer: starting it again");
                n.status = None;
                n.awaiting = false;
                n.erasing_since = None;
            }
            Stage::Committing | Stage::Rebooting => {
                // Without its `rebooting`, the restart may have come before it marked the image
                // (a power cut during the commit): then it runs its old image, and `idle` says
                // nothing about which.
                n.unsure = n.stage == Stage::Committing;
                n.stage = Stage::Confirming;
                n.awaiting = false;
                n.due = Some(now + confirm_poll);
                n.give_up = Some(now + confirm_timeout);
            }
            // A trial image that reset: the next query says whether it was reverted.
            Stage::Confirming | Stage::Done => {}
        }
        self.progress(src, now);
        self.advance(now);
    }

    /// The bus went down (bus-off, interface down): nothing is sent and nobody is counted
    /// missing until it is back.
    pub fn handle_bus_down(&mut self, now: Instant) {
        self.tick(now);
        self.bus_down = true;
    }

    /// The bus is back: every node is asked again, deadlines start afresh.
    pub fn handle_bus_recovered(&mut self, now: Instant) {
        self.tick(now);
        if !self.bus_down {
            return;
        }
        self.bus_down = false;
        self.round_deadline = Some(now);
        let (reply, reboot) = (self.config.reply_timeout, self.config.reboot_timeout);
        for n in self.nodes.values_mut() {
            n.awaiting = false;
            n.due = match n.stage {
                Stage::Rebooting => Some(now + reboot),
                Stage::Committing | Stage::Confirming => Some(now + reply),
                _ => n.due,
            };
            if let Some(g) = n.give_up.as_mut() {
                *g = (*g).max(now + reboot);
            }
        }
        self.advance(now);
    }

    /// Stops the update (gateway shutting down, or asked to): the nodes still transferring are
    /// told to drop it, every node without an outcome is `failed` with `reason`, and the report
    /// is emitted.
    pub fn cancel(&mut self, reason: &str, now: Instant) {
        self.tick(now);
        self.queue.clear();
        let image_id = self.image.image_id();
        let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        for id in ids {
            let stage = self.nodes.get(&id).map(|n| n.stage);
            if stage == Some(Stage::Transfer) {
                self.queue.push_back(Packet::command(
                    id,
                    Message::FwEnd {
                        image_id,
                        action: FwAction::Abort,
                    },
                ));
            }
            if stage != Some(Stage::Done) {
                self.finish_node(id, NodeOutcome::Failed, Some(reason.to_string()), now);
            }
        }
        self.advance(now);
    }

    /// Advances timers (reply deadlines, post-commit waits, the bucket).
    pub fn handle_timeout(&mut self, now: Instant) {
        self.tick(now);
        self.advance(now);
    }

    /// When [`FwSender::handle_timeout`] must run next (`None`: only an input moves it on).
    #[must_use]
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.bus_down || self.is_done() {
            return None;
        }
        let mut next = self.round_deadline.filter(|_| !self.finished);
        if let Some(p) = self.queue.front() {
            let at = self.bucket.ready_at(cost(p));
            next = Some(next.map_or(at, |n| n.min(at)));
        }
        for d in self
            .nodes
            .values()
            .filter_map(|n| n.due)
            .filter(|_| !self.finished)
        {
            next = Some(next.map_or(d, |n| n.min(d)));
        }
        next
    }

    /// The next frame, if the bus share allows it now. The caller sends it at the lowest
    /// priority (after every other frame it has).
    #[must_use]
    pub fn poll_transmit(&mut self) -> Option<Packet> {
        if self.bus_down {
            return None;
        }
        let p = *self.queue.front()?;
        if !self.bucket.try_take(cost(&p)) {
            return None;
        }
        self.queue.pop_front();
        if let Message::FwData { index, .. } = p.msg {
            self.frames_sent += 1;
            self.count_delivered(p.dest, u32::from(index));
        }
        if self.queue.is_empty() && self.round_deadline.is_none() {
            self.round_deadline = Some(self.now + self.config.reply_timeout);
        }
        Some(p)
    }

    /// Counts a data frame towards the progress of the nodes it was planned for.
    fn count_delivered(&mut self, dest: NodeId, index: u32) {
        let now = self.now;
        let reached: Vec<NodeId> = self
            .nodes
            .iter_mut()
            .filter(|(id, n)| {
                n.stage == Stage::Transfer
                    && (dest == NodeId::BROADCAST || dest == **id)
                    && n.planned.is_some_and(|(a, b)| (a..b).contains(&index))
            })
            .map(|(id, n)| {
                n.sent_since_status += 1;
                *id
            })
            .collect();
        for id in reached {
            self.progress(id, now);
        }
    }

    fn tick(&mut self, now: Instant) {
        self.now = self.now.max(now);
        self.bucket.refill(self.now);
    }

    /// Moves every node on as far as the inputs so far allow.
    fn advance(&mut self, now: Instant) {
        if self.finished {
            return;
        }
        if !self.bus_down {
            self.post_commit_timers(now);
            self.maybe_next_round(now);
        }
        if self.nodes.values().all(|n| n.stage == Stage::Done) {
            // Nobody needs the rest of the image; only the aborts of a cancel still go out.
            self.queue.retain(|p| {
                matches!(
                    p.msg,
                    Message::FwEnd {
                        action: FwAction::Abort,
                        ..
                    }
                )
            });
            self.report(now);
        }
    }

    fn post_commit_timers(&mut self, now: Instant) {
        let image_id = self.image.image_id();
        let (reply, poll, max) = (
            self.config.reply_timeout,
            self.config.confirm_poll,
            self.config.max_misses,
        );
        let mut lost = Vec::new();
        for (&id, n) in self.nodes.iter_mut() {
            let Some(due) = n.due else { continue };
            if now < due {
                continue;
            }
            match n.stage {
                Stage::Committing => {
                    if n.grace_until.is_none_or(|g| now >= g) {
                        n.misses += 1;
                    }
                    if n.misses > max {
                        lost.push((id, "no answer to the commit"));
                        continue;
                    }
                    // Ask (not commit again): a node still verifying answers so.
                    self.queue
                        .push_back(Packet::command(id, Message::FwQuery { image_id }));
                    n.due = Some(now + reply);
                }
                Stage::Rebooting => lost.push((id, "did not start again after the commit")),
                Stage::Confirming => {
                    if n.give_up.is_some_and(|g| now >= g) {
                        lost.push((id, "the new image did not report as confirmed"));
                        continue;
                    }
                    self.queue
                        .push_back(Packet::command(id, Message::FwQuery { image_id }));
                    n.due = Some(now + poll);
                }
                Stage::Transfer | Stage::Done => n.due = None,
            }
        }
        for (id, why) in lost {
            self.finish_node(id, NodeOutcome::Unreachable, Some(why.to_string()), now);
        }
    }

    fn on_commit_status(&mut self, src: NodeId, st: FwStatus, now: Instant) {
        let (reply, reboot) = (self.config.reply_timeout, self.config.reboot_timeout);
        let image_id = self.image.image_id();
        let Some(n) = self.nodes.get_mut(&src) else {
            return;
        };
        n.status = Some(st);
        match st.phase {
            FwPhase::Verifying => n.due = Some(now + reboot),
            FwPhase::Rebooting => {
                n.stage = Stage::Rebooting;
                n.due = Some(now + reboot);
                self.host_restarted(src, now);
            }
            // The commit was lost: send it again.
            FwPhase::Complete => {
                self.queue.push_back(Packet::command(
                    src,
                    Message::FwEnd {
                        image_id,
                        action: FwAction::Commit,
                    },
                ));
                n.due = Some(now + reply);
            }
            // It reset before it could install: it has lost the transfer.
            FwPhase::Idle => {
                n.stage = Stage::Transfer;
                n.status = None;
                n.due = None;
            }
            _ => {}
        }
    }

    /// Starts the next transfer round when the last one is over.
    fn maybe_next_round(&mut self, now: Instant) {
        if !self.queue.is_empty() {
            return;
        }
        let waiting = self
            .nodes
            .values()
            .any(|n| n.stage == Stage::Transfer && n.awaiting);
        if waiting && self.round_deadline.is_some_and(|d| now < d) {
            return;
        }
        if waiting && self.round_deadline.is_none() {
            return;
        }
        self.round_deadline = None;
        // Misses of the round that ended.
        let max = self.config.max_misses;
        let mut lost = Vec::new();
        for (&id, n) in self.nodes.iter_mut() {
            if n.stage == Stage::Transfer && n.awaiting {
                n.awaiting = false;
                if n.grace_until.is_some_and(|g| now < g) {
                    continue;
                }
                n.misses += 1;
                if n.misses > max {
                    lost.push(id);
                }
            }
        }
        for id in lost {
            let why = Some("no answer during the transfer".to_string());
            self.finish_node(id, NodeOutcome::Unreachable, why, now);
        }
        self.plan_round(now);
    }

    fn plan_round(&mut self, now: Instant) {
        let image_id = self.image.image_id();
        let frames = self.image.frames();
        let erase_timeout = self.config.erase_timeout;
        // Hold data while a node erases (frames sent to it now are lost), up to a limit.
        let hold = self.nodes.values().any(|n| {
            n.stage == Stage::Transfer
                && n.status.is_some_and(|s| s.phase == FwPhase::Erasing)
                && n.erasing_since.is_some_and(|t| now < t + erase_timeout)
        });
        let mut begins = Vec::new();
        let mut commits = Vec::new();
        // Nodes that did not answer the last round, asked before any data (see the module doc).
        let mut asked_first = Vec::new();
        let mut queries = Vec::new();
        // frame index → the nodes missing it
        let mut wanted: BTreeMap<u16, Vec<NodeId>> = BTreeMap::new();
        for (&id, n) in self.nodes.iter_mut() {
            if n.stage != Stage::Transfer {
                continue;
            }
            match n.status {
                None
                | Some(FwStatus {
                    phase: FwPhase::Idle | FwPhase::Trial | FwPhase::Reverted,
                    ..
                }) => {
                    n.erasing_since = None;
                    begins.push(id);
                }
                Some(FwStatus {
                    phase: FwPhase::Complete,
                    ..
                }) => commits.push(id),
                Some(_) if n.misses > 0 => asked_first.push(id),
                Some(FwStatus {
                    phase: FwPhase::Header | FwPhase::Receiving,
                    first_missing,
                    run,
                    ..
                }) if run > 0 && !hold => {
                    let end = (u32::from(first_missing) + u32::from(run)).min(frames);
                    n.planned = Some((u32::from(first_missing), end));
                    n.sent_since_status = 0;
                    for i in u32::from(first_missing)..end {
                        // `frames` ≤ 65 536 (FW_MAX_LEN), so every index fits.
                        wanted.entry(i as u16).or_default().push(id);
                    }
                    queries.push(id);
                }
                Some(_) => queries.push(id),
            }
        }
        // A static element powering a mobile element still being updated waits, complete.
        commits.retain(|&id| !self.powers_one_in_update(id));
        for &id in &begins {
            self.queue.push_back(Packet::command(
                id,
                Message::FwBegin {
                    image_id,
                    len: self.image.len(),
                    force: self.force,
                },
            ));
        }
        let query = |id| Packet::command(id, Message::FwQuery { image_id });
        self.queue.extend(asked_first.iter().map(|&id| query(id)));
        for (index, who) in wanted {
            let dest = match who.as_slice() {
                [one] => *one,
                _ => NodeId::BROADCAST,
            };
            let data = self.image.frame(index);
            self.queue
                .push_back(Packet::command(dest, Message::FwData { index, data }));
        }
        for &id in &commits {
            self.queue.push_back(Packet::command(
                id,
                Message::FwEnd {
                    image_id,
                    action: FwAction::Commit,
                },
            ));
        }
        self.queue.extend(queries.iter().map(|&id| query(id)));
        let reboot = self.config.reboot_timeout;
        for id in begins.iter().chain(&asked_first).chain(&queries) {
            if let Some(n) = self.nodes.get_mut(id) {
                n.awaiting = true;
            }
        }
        for id in &commits {
            if let Some(n) = self.nodes.get_mut(id) {
                n.committed = true;
                n.seen_new = false;
                n.stage = Stage::Committing;
                n.misses = 0;
                n.due = Some(now + reboot);
            }
        }
        for id in commits {
            self.progress(id, now);
        }
    }

    fn finish_node(&mut self, id: NodeId, outcome: NodeOutcome, why: Option<String>, now: Instant) {
        if let Some(n) = self.nodes.get_mut(&id) {
            if n.stage == Stage::Done {
                return;
            }
            let (outcome, why) = match (outcome, n.power_cut_by) {
                (NodeOutcome::Unreachable | NodeOutcome::Reverted, Some(host)) if host == id => (
                    NodeOutcome::LostPower,
                    Some("lost power in the middle of its update".to_string()),
                ),
                (NodeOutcome::Unreachable | NodeOutcome::Reverted, Some(host)) => (
                    NodeOutcome::LostPower,
                    Some(format!("lost power when {host} restarted")),
                ),
                _ => (outcome, why),
            };
            tracing::info!(node = %id, ?outcome, reason = ?why, "firmware update of a node ended");
            n.stage = Stage::Done;
            n.awaiting = false;
            n.due = None;
            n.outcome = Some((outcome, why, now));
        }
    }

    /// Publishes a node's progress when its phase changed, or its percent did and the last
    /// event is older than the progress interval.
    fn progress(&mut self, id: NodeId, now: Instant) {
        let frames = self.image.frames();
        let Some(n) = self.nodes.get_mut(&id) else {
            return;
        };
        let (phase, percent): (&'static str, u8) = match (n.stage, n.status) {
            (Stage::Done, _) => return,
            (Stage::Transfer, None) => ("begin", 0),
            (Stage::Transfer, Some(st)) => {
                let percent = match st.phase {
                    FwPhase::Receiving => {
                        // What it said it has, plus what went out to it since; below 100 until
                        // it says it is complete (a frame it lost shows at its next status).
                        let have =
                            frames.saturating_sub(u32::from(st.missing)) + n.sent_since_status;
                        let have = have.min(frames.saturating_sub(1));
                        u8::try_from(have * 100 / frames.max(1)).unwrap_or(99)
                    }
                    FwPhase::Complete => 100,
                    _ => 0,
                };
                (phase_name(st.phase), percent)
            }
            (Stage::Committing, Some(st)) => (phase_name(st.phase), 100),
            (Stage::Committing, None) => ("complete", 100),
            (Stage::Rebooting, _) => ("rebooting", 100),
            (Stage::Confirming, _) => ("confirming", 100),
        };
        // Every step of `PROGRESS_STEP` is published (the granularity); smaller changes
        // at most once per progress interval.
        let due = match n.progress {
            None => true,
            Some((p, pc, at)) => {
                p != phase
                    || pc / PROGRESS_STEP != percent / PROGRESS_STEP
                    || (pc != percent && now >= at + self.config.progress_interval)
            }
        };
        if due {
            n.progress = Some((phase, percent, now));
            self.events.push_back(Event::FwProgress(FwProgress {
                request_id: self.request_id.clone(),
                node: HexId(id),
                phase: phase.to_string(),
                percent,
            }));
        }
    }

    fn report(&mut self, now: Instant) {
        self.finished = true;
        let started = self.started;
        let ms = |t: Instant| {
            u64::try_from(t.saturating_duration_since(started).as_millis()).unwrap_or(u64::MAX)
        };
        let mut nodes: Vec<NodeReport> = self
            .nodes
            .iter()
            .map(|(&id, n)| {
                let (outcome, reason, at) =
                    n.outcome
                        .clone()
                        .unwrap_or((NodeOutcome::Failed, None, now));
                NodeReport {
                    node: HexId(id),
                    outcome,
                    reason,
                    duration_ms: ms(at),
                }
            })
            .collect();
        nodes.extend(self.skipped.iter().map(|(id, why)| NodeReport {
            node: HexId(*id),
            outcome: NodeOutcome::Skipped,
            reason: Some(why.clone()),
            duration_ms: 0,
        }));
        nodes.sort_by_key(|n| n.node);
        let report = FwReport {
            request_id: self.request_id.clone(),
            image_id: format!("{:08x}", self.image.image_id()),
            version: self.image.version().to_string(),
            notes: self.image.notes().map(str::to_owned),
            duration_ms: ms(now),
            frames_sent: self.frames_sent,
            bus_share: self.config.bus_share,
            nodes,
        };
        tracing::info!(
            image = %report.image_id,
            all_updated = report.all_updated(),
            "firmware update finished"
        );
        self.events.push_back(Event::FwReport(Box::new(report)));
    }
}

/// Bits a packet takes on the wire at worst.
fn cost(p: &Packet) -> u32 {
    ihex_proto::bus::frame_bits_worst(Message::len_of(p.msg.kind()))
}

/// A phase's name as published (the protocol's `FwPhase` name).
fn phase_name(p: FwPhase) -> &'static str {
    p.name().unwrap_or("other")
}
