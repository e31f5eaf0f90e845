//! What the core task shares with adapters other than MQTT (the island view, [`crate::web`]): every
//! publication as it was serialised for MQTT, numbered, kept for late readers and fanned out to live
//! ones ([`Feed`]); and views of the bridge's read accessors, asked for through a bounded channel
//! and answered by the core task between two inputs ([`ViewRequest`]).
//!
//! Publications and views share one sequence: a view answered after publication `n` reflects every
//! publication up to `n` and none after it, so a reader that combines a view with the live stream
//! knows which messages the view already contains.

use std::{
    collections::VecDeque,
    sync::{
        atomic::{AtomicU64, Ordering},
        Arc, Mutex,
    },
    time::{Instant, SystemTime, UNIX_EPOCH},
};

use ihex_gateway_core::{
    bridge::{BusHealth, CommandCounters},
    event::NodeState,
    lease::LeasesDocument,
    procedure::ProceduresDocument,
    Bridge, Publication,
};
use tokio::sync::{broadcast, mpsc, oneshot};

/// Events kept for readers that arrive late (the island view's timeline).
pub const RECENT_EVENTS: usize = 300;
/// Publications a slow live reader may fall behind before it is told it lost some.
pub const LIVE_QUEUE: usize = 1024;
/// View requests waiting for the core task.
pub const VIEW_REQUESTS: usize = 16;

/// What a publication was.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// An event on the events topic, by name (`new_connection`, ...).
    Event(&'static str),
    /// A node's retained state document (which node: [`Published::state`]).
    State,
    /// The retained leases document.
    Leases,
    /// The retained document of the running procedures.
    Procedures,
}

/// One publication as it left the core.
#[derive(Debug)]
pub struct Published {
    /// Its number: 1 for the first publication of this gateway, then consecutive.
    pub seq: u64,
    /// When it was published, milliseconds since the Unix epoch.
    pub time_ms: u64,
    /// What it is.
    pub kind: Kind,
    /// The JSON text exactly as published on MQTT.
    pub json: Arc<str>,
    /// A state document as the core built it (`Kind::State`), for readers that show parts of it
    /// without reading the text again.
    pub state: Option<NodeState>,
}

/// The publications of one gateway, for readers other than MQTT.
#[derive(Debug)]
pub struct Feed {
    seq: AtomicU64,
    recent: Mutex<VecDeque<Arc<Published>>>,
    live: broadcast::Sender<Arc<Published>>,
}

impl Default for Feed {
    fn default() -> Self {
        Feed {
            seq: AtomicU64::new(0),
            recent: Mutex::new(VecDeque::with_capacity(RECENT_EVENTS)),
            live: broadcast::channel(LIVE_QUEUE).0,
        }
    }
}

impl Feed {
    /// Called by the core task for every publication, with the JSON it serialised for MQTT: numbers
    /// it, keeps it when it is an event, and hands it to every live reader (never waiting: a reader
    /// that falls [`LIVE_QUEUE`] behind is told how many it lost).
    pub fn publish(&self, publication: Publication, json: &str) {
        let (kind, state) = match publication {
            Publication::Event(e) => (Kind::Event(e.name()), None),
            Publication::State(s) => (Kind::State, Some(s)),
            Publication::Leases(_) => (Kind::Leases, None),
            Publication::Procedures(_) => (Kind::Procedures, None),
            // Home Assistant's topics are not the page's; a forgotten node's emptied state document
            // reaches it as the `node_forgotten` event.
            Publication::Ha(_) | Publication::Cleared(_) => return,
        };
        let p = Arc::new(Published {
            seq: self.seq.fetch_add(1, Ordering::Relaxed) + 1,
            time_ms: unix_ms(SystemTime::now()),
            kind,
            json: Arc::from(json),
            state,
        });
        // A firmware update's progress (a step per element every 5 %) would push every other
        // event out of the timeline a new page starts from; the live stream carries it.
        if matches!(kind, Kind::Event(name) if name != "fw_progress") {
            let mut recent = self.recent.lock().unwrap_or_else(|e| e.into_inner());
            if recent.len() == RECENT_EVENTS {
                recent.pop_front();
            }
            recent.push_back(p.clone());
        }
        // No live reader is not an error.
        let _ = self.live.send(p);
    }

    /// The number of the last publication (0 before the first).
    pub fn seq(&self) -> u64 {
        self.seq.load(Ordering::Relaxed)
    }

    /// The kept events numbered up to `seq`, oldest first.
    pub fn recent_events(&self, seq: u64) -> Vec<Arc<Published>> {
        let recent = self.recent.lock().unwrap_or_else(|e| e.into_inner());
        recent.iter().filter(|p| p.seq <= seq).cloned().collect()
    }

    /// A live reader: every publication from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<Published>> {
        self.live.subscribe()
    }

    /// Live readers right now.
    pub fn readers(&self) -> usize {
        self.live.receiver_count()
    }
}

/// Milliseconds since the Unix epoch (0 for a clock set before it).
pub fn unix_ms(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// The bridge as the core task saw it between two inputs.
#[derive(Clone, Debug)]
pub struct CoreView {
    /// The last publication reflected in this view (see the module docs).
    pub seq: u64,
    /// When the view was taken.
    pub at: Instant,
    /// Every known node's state document (ages as of `at`), when asked for.
    pub nodes: Option<Vec<NodeState>>,
    /// What the bus has done since start.
    pub bus: BusHealth,
    /// Commands in flight and how the others ended.
    pub commands: CommandCounters,
    /// The leases held now.
    pub leases: LeasesDocument,
    /// The procedures running now.
    pub procedures: ProceduresDocument,
}

/// A request for a [`CoreView`], answered by the core task.
#[derive(Debug)]
pub struct ViewRequest {
    /// Include every node's state document (costs a document per node).
    pub nodes: bool,
    /// Where the view goes.
    pub reply: oneshot::Sender<CoreView>,
}

impl ViewRequest {
    /// Answers from `bridge` at `now`; `seq` is the feed's last publication.
    pub fn answer(self, bridge: &Bridge, seq: u64, now: Instant) {
        let view = CoreView {
            seq,
            at: now,
            nodes: self.nodes.then(|| bridge.node_states(now)),
            bus: bridge.bus_health(),
            commands: bridge.command_counters(),
            leases: bridge.leases(now),
            procedures: bridge.procedures(now),
        };
        // The asker may have given up waiting.
        let _ = self.reply.send(view);
    }
}

/// The core task's end of the view requests: pending forever when nobody can ask.
#[derive(Debug, Default)]
pub struct ViewRequests(Option<mpsc::Receiver<ViewRequest>>);

impl ViewRequests {
    /// A channel for view requests: the askers' end and the core task's end.
    pub fn channel() -> (mpsc::Sender<ViewRequest>, ViewRequests) {
        let (tx, rx) = mpsc::channel(VIEW_REQUESTS);
        (tx, ViewRequests(Some(rx)))
    }

    /// The next request; never resolves once every asker is gone (or when there were none).
    pub async fn next(&mut self) -> ViewRequest {
        if let Some(rx) = &mut self.0 {
            if let Some(req) = rx.recv().await {
                return req;
            }
            self.0 = None;
        }
        std::future::pending().await
    }
}

/// Asks the core task for a view; `None` when the core is gone.
pub async fn ask(views: &mpsc::Sender<ViewRequest>, nodes: bool) -> Option<CoreView> {
    let (reply, answer) = oneshot::channel();
    views.send(ViewRequest { nodes, reply }).await.ok()?;
    answer.await.ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_gateway_core::event::{CommandRejected, Event};

    fn rejected(n: usize) -> Publication {
        Publication::Event(Event::CommandRejected(CommandRejected {
            request_id: Some(n.to_string()),
            reason: "r".into(),
            origin: None,
        }))
    }

    /// A firmware update's progress reaches the live readers but is not kept for the timeline of a
    /// page that starts later (it would push every other event out).
    #[test]
    fn firmware_progress_is_streamed_not_kept() {
        use ihex_gateway_core::fwupdate::FwProgress;
        let feed = Feed::default();
        let mut live = feed.subscribe();
        let p = Publication::Event(Event::FwProgress(FwProgress {
            request_id: None,
            node: ihex_gateway_core::event::HexId("111".parse().unwrap()),
            phase: "receiving".into(),
            percent: 5,
        }));
        let json = p.to_json();
        feed.publish(p, &json);
        let r = rejected(1);
        let json = r.to_json();
        feed.publish(r, &json);
        assert_eq!(live.try_recv().unwrap().kind, Kind::Event("fw_progress"));
        let kept = feed.recent_events(u64::MAX);
        assert_eq!(kept.len(), 1);
        assert_eq!(kept[0].kind, Kind::Event("command_rejected"));
    }

    #[test]
    fn publications_are_numbered_kept_and_fanned_out() {
        let feed = Feed::default();
        let mut live = feed.subscribe();
        for n in 0..RECENT_EVENTS + 5 {
            let p = rejected(n);
            let json = p.to_json();
            feed.publish(p, &json);
        }
        assert_eq!(feed.seq(), (RECENT_EVENTS + 5) as u64);
        let kept = feed.recent_events(u64::MAX);
        assert_eq!(kept.len(), RECENT_EVENTS, "the oldest are dropped");
        assert_eq!(kept[0].seq, 6);
        assert_eq!(
            feed.recent_events(10).len(),
            5,
            "only up to the asked number"
        );
        let first = live.try_recv().unwrap();
        assert_eq!(
            (first.seq, first.kind),
            (1, Kind::Event("command_rejected"))
        );
        assert_eq!(
            &*first.json,
            r#"{"event":"command_rejected","payload":{"request_id":"0","reason":"r"}}"#
        );
    }

    #[tokio::test]
    async fn views_are_answered_from_the_bridge_and_absent_askers_never_wake_the_core() {
        let (tx, mut rx) = ViewRequests::channel();
        let bridge = Bridge::new(Default::default(), Instant::now());
        let ask = tokio::spawn(async move { ask(&tx, true).await });
        let req = rx.next().await;
        req.answer(&bridge, 7, Instant::now());
        let view = ask.await.unwrap().expect("answered");
        assert_eq!(view.seq, 7);
        assert_eq!(view.nodes, Some(vec![]));
        // The sender is gone: `next` pends instead of spinning.
        let idle = tokio::time::timeout(std::time::Duration::from_millis(20), rx.next()).await;
        assert!(idle.is_err());
        let mut none = ViewRequests::default();
        let idle = tokio::time::timeout(std::time::Duration::from_millis(20), none.next()).await;
        assert!(idle.is_err());
    }
}
