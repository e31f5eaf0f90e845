//! An in-memory CAN bus: every frame one endpoint sends reaches every *other* endpoint, as on a wire.
//!
//! For the gateway's embedded demo and fast unit tests only; the SocketCAN tests use a real (v)can
//! interface. The bus is a bounded tokio broadcast channel: sending never blocks, and an endpoint that
//! falls more than [`MemBus::DEFAULT_CAPACITY`] frames behind loses the oldest ones (like a CAN
//! controller's receive FIFO overrun); [`MemEndpoint::lost`] counts them.
//!
//! ```
//! # tokio::runtime::Runtime::new().unwrap().block_on(async {
//! use embedded_can::{ExtendedId, Frame};
//! use sim_node::bus::MemBus;
//! use socketcan::CanFrame;
//!
//! let bus = MemBus::new();
//! let a = bus.endpoint();
//! let mut b = bus.endpoint();
//! let frame = CanFrame::new(ExtendedId::new(0x123).unwrap(), &[1, 2]).unwrap();
//! a.send(frame).await.unwrap();
//! assert_eq!(b.recv().await.unwrap().data(), &[1, 2]);
//! # });
//! ```

use std::sync::{
    atomic::{AtomicU64, Ordering},
    Arc, Mutex,
};

use ihex_proto::filter::{self, Filter};
use socketcan::CanFrame;
use tokio::sync::broadcast;

/// Why an in-memory bus operation failed.
#[derive(Debug, thiserror::Error, Clone, Copy, PartialEq, Eq)]
pub enum BusError {
    /// Every [`MemBus`] handle was dropped: the bus no longer exists.
    #[error("the in-memory bus was dropped")]
    Closed,
}

#[derive(Clone, Debug)]
struct Wire {
    from: u64,
    frame: CanFrame,
}

/// The bus itself. Cheap to clone (all clones are the same bus); the bus lives while a clone does.
#[derive(Clone, Debug)]
pub struct MemBus {
    tx: broadcast::Sender<Wire>,
    next_endpoint: Arc<AtomicU64>,
}

impl Default for MemBus {
    fn default() -> Self {
        Self::new()
    }
}

impl MemBus {
    /// Frames an endpoint may fall behind before it loses the oldest.
    pub const DEFAULT_CAPACITY: usize = 1024;

    /// A bus with [`MemBus::DEFAULT_CAPACITY`].
    pub fn new() -> Self {
        Self::with_capacity(Self::DEFAULT_CAPACITY)
    }

    /// A bus on which an endpoint may fall `capacity` frames behind (at least 1).
    pub fn with_capacity(capacity: usize) -> Self {
        let (tx, _) = broadcast::channel(capacity.max(1));
        MemBus {
            tx,
            next_endpoint: Arc::new(AtomicU64::new(0)),
        }
    }

    /// A new node on the bus. It receives every frame sent by other endpoints after this call (and
    /// passing its filters), never its own.
    pub fn endpoint(&self) -> MemEndpoint {
        let id = self.next_endpoint.fetch_add(1, Ordering::Relaxed);
        MemEndpoint {
            tx: MemSender {
                id,
                tx: self.tx.downgrade(),
            },
            rx: self.tx.subscribe(),
            filters: Arc::new(Mutex::new(Vec::new())),
            lost: 0,
        }
    }
}

/// The sending half of an endpoint (cloneable), see [`MemEndpoint::sender`].
#[derive(Clone, Debug)]
pub struct MemSender {
    id: u64,
    // Weak, so that the bus closes once every `MemBus` handle is gone even while endpoints live.
    tx: broadcast::WeakSender<Wire>,
}

impl MemSender {
    /// Puts a frame on the bus. Never waits (it is `async` to look like a socket write); it fails only
    /// when the bus is gone. A frame nobody else listens to is simply lost, as on a real bus.
    pub async fn send(&self, frame: CanFrame) -> Result<(), BusError> {
        self.try_send(frame)
    }

    /// Frames on the bus that an endpoint has not read yet (its slowest endpoint's backlog; 0 once
    /// the bus is gone). Nothing on an in-memory bus paces a sender as arbitration and the bit rate
    /// pace a real one, so a sender that must not overrun slow endpoints (the gateway's transmit
    /// side, in the demo) waits while this is high.
    pub fn backlog(&self) -> usize {
        self.tx.upgrade().map_or(0, |tx| tx.len())
    }

    /// [`MemSender::send`] without the `async`.
    pub fn try_send(&self, frame: CanFrame) -> Result<(), BusError> {
        let tx = self.tx.upgrade().ok_or(BusError::Closed)?;
        // Err only means "no receiver right now": not an error on a bus.
        let _ = tx.send(Wire {
            from: self.id,
            frame,
        });
        Ok(())
    }
}

/// One node's connection to a [`MemBus`]: send with [`MemEndpoint::send`], receive with
/// [`MemEndpoint::recv`]. Acceptance filters ([`MemEndpoint::set_filters`]) follow
/// [`ihex_proto::filter::accepts`], the same rule the kernel and bxCAN filters implement.
#[derive(Debug)]
pub struct MemEndpoint {
    tx: MemSender,
    rx: broadcast::Receiver<Wire>,
    filters: Arc<Mutex<Vec<Filter>>>,
    lost: u64,
}

impl MemEndpoint {
    /// Puts a frame on the bus (every other endpoint receives it). See [`MemSender::send`].
    pub async fn send(&self, frame: CanFrame) -> Result<(), BusError> {
        self.tx.try_send(frame)
    }

    /// [`MemEndpoint::send`] without the `async`.
    pub fn try_send(&self, frame: CanFrame) -> Result<(), BusError> {
        self.tx.try_send(frame)
    }

    /// A cloneable sending half, for when one task receives and others send.
    pub fn sender(&self) -> MemSender {
        self.tx.clone()
    }

    /// A handle to change this endpoint's filters from another task while it receives.
    pub fn filter_handle(&self) -> MemFilterHandle {
        MemFilterHandle(self.filters.clone())
    }

    /// Replaces the acceptance filters (empty = receive everything, the default).
    pub fn set_filters(&self, filters: &[Filter]) {
        self.filter_handle().set(filters);
    }

    /// The next frame from another endpoint that passes the filters; `None` once the bus is gone.
    /// Cancel-safe (usable in `tokio::select!`).
    pub async fn recv(&mut self) -> Option<CanFrame> {
        loop {
            match self.rx.recv().await {
                Ok(w) if w.from == self.tx.id => {}
                Ok(w) => {
                    if self.accepts(&w.frame) {
                        return Some(w.frame);
                    }
                }
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    self.lost += n;
                    tracing::warn!(lost = n, "in-memory bus endpoint fell behind; frames lost");
                }
                Err(broadcast::error::RecvError::Closed) => return None,
            }
        }
    }

    /// Frames lost because this endpoint fell too far behind.
    pub fn lost(&self) -> u64 {
        self.lost
    }

    fn accepts(&self, frame: &CanFrame) -> bool {
        let filters = self.filters.lock().unwrap_or_else(|e| e.into_inner());
        filter::accepts(&filters, filter::word_of(frame))
    }
}

/// Changes a [`MemEndpoint`]'s filters from elsewhere (see [`MemEndpoint::filter_handle`]).
#[derive(Clone, Debug)]
pub struct MemFilterHandle(Arc<Mutex<Vec<Filter>>>);

impl MemFilterHandle {
    /// Replaces the endpoint's acceptance filters.
    pub fn set(&self, filters: &[Filter]) {
        let mut f = self.0.lock().unwrap_or_else(|e| e.into_inner());
        f.clear();
        f.extend_from_slice(filters);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::{ExtendedId, Frame};
    use ihex_proto::{filter::sc_filters, Message, NodeId, Packet};

    fn frame(id: u32, data: &[u8]) -> CanFrame {
        CanFrame::new(ExtendedId::new(id).unwrap(), data).unwrap()
    }

    #[tokio::test]
    async fn frames_reach_every_other_endpoint_but_not_the_sender() {
        let bus = MemBus::new();
        let mut a = bus.endpoint();
        let mut b = bus.endpoint();
        let mut c = bus.endpoint();
        a.send(frame(0x100, &[1])).await.unwrap();
        b.send(frame(0x200, &[2])).await.unwrap();
        assert_eq!(b.recv().await.unwrap().data(), &[1]);
        assert_eq!(c.recv().await.unwrap().data(), &[1]);
        assert_eq!(c.recv().await.unwrap().data(), &[2]);
        // a must see b's frame first: its own is skipped.
        assert_eq!(a.recv().await.unwrap().data(), &[2]);
    }

    #[tokio::test]
    async fn filters_select_frames_like_the_node_would() {
        let bus = MemBus::new();
        let gw = bus.endpoint();
        let mut node = bus.endpoint();
        let me = NodeId::new_sc(0x111).unwrap();
        node.set_filters(&sc_filters(Some(me)));
        let other = Packet::command(
            NodeId::new_sc(0x222).unwrap(),
            Message::HealthCheck { seq: 1 },
        );
        let mine = Packet::command(me, Message::HealthCheck { seq: 2 });
        let all = Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 3 });
        for p in [other, mine, all] {
            gw.send(p.to_frame().unwrap()).await.unwrap();
        }
        assert_eq!(
            Packet::from_frame(&node.recv().await.unwrap()).unwrap(),
            mine
        );
        assert_eq!(
            Packet::from_frame(&node.recv().await.unwrap()).unwrap(),
            all
        );
    }

    #[tokio::test]
    async fn the_backlog_is_what_the_slowest_endpoint_has_not_read() {
        let bus = MemBus::new();
        let mut fast = bus.endpoint();
        let mut slow = bus.endpoint();
        let tx = bus.endpoint().sender();
        assert_eq!(tx.backlog(), 0);
        for i in 0..3 {
            tx.send(frame(0x100, &[i])).await.unwrap();
        }
        for _ in 0..3 {
            fast.recv().await.unwrap();
        }
        assert_eq!(tx.backlog(), 3, "the slow endpoint read nothing");
        slow.recv().await.unwrap();
        assert_eq!(tx.backlog(), 2);
        drop(slow);
        assert_eq!(tx.backlog(), 0, "a dropped endpoint holds nothing back");
        drop(bus);
        drop(fast);
        assert_eq!(tx.backlog(), 0, "no bus, no backlog");
    }

    #[tokio::test]
    async fn dropping_the_bus_closes_endpoints() {
        let bus = MemBus::new();
        let mut a = bus.endpoint();
        let b = bus.endpoint();
        b.send(frame(1, &[])).await.unwrap();
        drop(bus);
        assert!(
            a.recv().await.is_some(),
            "frames already sent are still delivered"
        );
        assert!(a.recv().await.is_none());
        assert_eq!(b.send(frame(1, &[])).await, Err(BusError::Closed));
    }

    #[tokio::test]
    async fn a_slow_endpoint_loses_the_oldest_frames_and_counts_them() {
        let bus = MemBus::with_capacity(4);
        let tx = bus.endpoint();
        let mut rx = bus.endpoint();
        for i in 0..10u8 {
            tx.send(frame(0x10, &[i])).await.unwrap();
        }
        assert_eq!(rx.recv().await.unwrap().data(), &[6]);
        assert_eq!(rx.lost(), 6);
    }
}
