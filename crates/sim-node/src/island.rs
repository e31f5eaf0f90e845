//! A running island: one [`ihex_sc_core::Node`] per element, wired to a [`Link`], with the physical
//! world (power through dock relays, signal loops, cables) simulated around them.
//!
//! One task owns every node and the topology, so a dock, a relay edge and the power it switches are
//! handled in a consistent order. Per powered node a small reader task forwards received frames to it.
//! The rules of the physical world:
//! - static elements are powered from the start (and after [`IslandHandle::power_cycle`]);
//! - a mobile element is powered exactly while it is docked on a powered static element whose relay is
//!   on; power-up is a fresh `Node` (reset `PowerOn`, the ID it last stored), power loss drops it;
//! - docking closes the static element's signal loop on that port and the mobile's own loop on its
//!   port; undocking opens both (with optional contact bounce);
//! - a node taken off the bus keeps running but neither sends nor receives frames; a frame it tries
//!   to send goes unacknowledged, so its controller turns error passive (TEC 128, reported to the
//!   core) and recovers one count per frame sent once it is back.
//!
//! Time is tokio's clock, so tests may run with a paused clock.

use std::collections::BTreeMap;

use embedded_can::Frame as EmbeddedFrame;
use ihex_proto::{filter::sc_filters, BootRole, FirmwareVersion, NodeId, Port, ResetReason, Uid};
use ihex_sc_core::{
    Actuators, BuzzerOutput, Config, FirmwareIdentity, Millis, Node, Output, Retained,
};
use socketcan::CanFrame;
use tokio::{
    sync::{broadcast, mpsc, oneshot},
    task::JoinHandle,
    time::{Duration, Instant},
};

use crate::{
    board::{self, Board, Carried},
    desc::IslandDesc,
    link::{Link, LinkError, LinkTx},
};

/// Offsets (ms) and levels (relative to the final level) of a bouncing contact: four short glitches,
/// all well inside the core's debounce window.
const BOUNCE: [(u64, bool); 5] = [(0, true), (2, false), (4, true), (6, false), (9, true)];

/// Transmit error count at which a CAN controller turns error passive.
const ERROR_PASSIVE_TEC: u8 = 128;

/// Capacity of the event stream ([`IslandHandle::subscribe`]).
pub const EVENT_CAPACITY: usize = 256;

/// Why an island operation was refused.
#[derive(Debug, thiserror::Error)]
pub enum IslandError {
    /// No element with this ID in the island.
    #[error("no element \"{0}\" in this island")]
    UnknownNode(NodeId),
    /// The element is static where a mobile one is needed.
    #[error("\"{0}\" is not a mobile element")]
    NotMobile(NodeId),
    /// The element is mobile where a static one is needed.
    #[error("\"{0}\" is not a static element")]
    NotStatic(NodeId),
    /// The element has no such port.
    #[error("\"{node}\" has no port {port}")]
    NoSuchPort {
        /// Element.
        node: NodeId,
        /// Requested port.
        port: u8,
    },
    /// Another mobile element is docked on that port.
    #[error("port {port} of \"{static_id}\" is taken by \"{by}\"")]
    PortTaken {
        /// Static element.
        static_id: NodeId,
        /// Port.
        port: Port,
        /// The mobile element there.
        by: NodeId,
    },
    /// The mobile element is already docked somewhere.
    #[error("\"{mobile}\" is already docked on \"{static_id}\" port {port}")]
    AlreadyDocked {
        /// Mobile element.
        mobile: NodeId,
        /// Where.
        static_id: NodeId,
        /// Port.
        port: Port,
    },
    /// The mobile element is not docked.
    #[error("\"{0}\" is not docked")]
    NotDocked(NodeId),
    /// The element has no power (a mobile element not powered through a dock).
    #[error("\"{0}\" has no power")]
    NotPowered(NodeId),
    /// The bus could not be opened or configured.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// A hand-built [`IslandDesc`] is inconsistent ([`IslandDesc::parse`] never yields one).
    #[error("invalid island description: {0}")]
    InvalidDesc(String),
    /// The island task has stopped.
    #[error("the island is not running")]
    Stopped,
    /// The element's board does not start (its bootloader failed, or its slot holds no image).
    #[error("\"{0}\" does not boot: {1}")]
    Boot(NodeId, board::BootFailure),
    /// A simulated image could not be made.
    #[error("simulated image: {0}")]
    Image(String),
}

/// The images boards start with, made once per version.
#[derive(Default)]
struct Images(BTreeMap<(u8, u8, u8), Vec<u8>>);

impl Images {
    /// A board whose active slot holds the factory image of `version`.
    fn factory(&mut self, version: FirmwareVersion) -> Result<Board, IslandError> {
        let key = (version.major, version.minor, version.patch);
        let img = match self.0.entry(key) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(e) => e.insert(
                board::factory_image(version).map_err(|e| IslandError::Image(e.to_string()))?,
            ),
        };
        Ok(Board::with_image(img))
    }
}

/// Something that changed in the island (see [`IslandHandle::subscribe`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IslandEvent {
    /// A powered node's actuators changed (also sent at power-up).
    Actuators {
        /// Element.
        node: NodeId,
        /// The new setting.
        actuators: Actuators,
    },
    /// An element gained or lost power.
    Power {
        /// Element.
        node: NodeId,
        /// Powered now.
        on: bool,
    },
    /// An element was put on or taken off the bus.
    Bus {
        /// Element.
        node: NodeId,
        /// Connected now.
        on: bool,
    },
    /// A mobile element was docked.
    Docked {
        /// Mobile element.
        mobile: NodeId,
        /// Static element.
        static_id: NodeId,
        /// Static element's port.
        port: Port,
    },
    /// A mobile element was undocked.
    Undocked {
        /// Mobile element.
        mobile: NodeId,
        /// Static element it left.
        static_id: NodeId,
        /// Port it left.
        port: Port,
    },
    /// A node asked to persist a new node ID ("flash" write; used at its next power-up).
    IdStored {
        /// Element.
        node: NodeId,
        /// The stored ID.
        id: NodeId,
    },
}

/// What one element looks like right now (see [`IslandHandle::snapshot`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NodeView {
    /// The element's name in the island (its ID in the island file).
    pub name: NodeId,
    /// Static or mobile.
    pub role: BootRole,
    /// The ID the node uses now (powered) or would boot with (unpowered); `None` = unconfigured.
    pub node_id: Option<NodeId>,
    /// Its unique ID.
    pub uid: Uid,
    /// Has power (a `Node` is running).
    pub powered: bool,
    /// Connected to the bus.
    pub on_bus: bool,
    /// Actuators (all off when unpowered).
    pub actuators: Actuators,
    /// Signal-loop levels as its pins read them: bit n = port n closed.
    pub loops: u8,
    /// Mobile: where it is docked.
    pub docked: Option<(NodeId, Port)>,
    /// The firmware it runs (reported on a state query).
    pub firmware: FirmwareIdentity,
}

enum Command {
    Dock(NodeId, NodeId, u8, oneshot::Sender<Result<(), IslandError>>),
    Undock(NodeId, oneshot::Sender<Result<(), IslandError>>),
    PowerCycle(NodeId, oneshot::Sender<Result<(), IslandError>>),
    SetOnBus(NodeId, bool, oneshot::Sender<Result<(), IslandError>>),
    Uart(
        NodeId,
        Vec<u8>,
        oneshot::Sender<Result<Vec<u8>, IslandError>>,
    ),
    Snapshot(oneshot::Sender<Vec<NodeView>>),
    Shutdown(oneshot::Sender<()>),
}

/// Controls a running island. Cheap to clone; the island stops when every handle is dropped or
/// [`IslandHandle::shutdown`] is called.
#[derive(Clone, Debug)]
pub struct IslandHandle {
    cmd: mpsc::Sender<Command>,
    events: broadcast::Sender<IslandEvent>,
}

impl IslandHandle {
    async fn call<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<T>) -> Command,
    ) -> Result<T, IslandError> {
        let (tx, rx) = oneshot::channel();
        self.cmd
            .send(make(tx))
            .await
            .map_err(|_| IslandError::Stopped)?;
        rx.await.map_err(|_| IslandError::Stopped)
    }

    /// Docks `mobile` on `port` of `static_id`: closes both signal loops. The mobile gets power when
    /// the static element's relay is (or turns) on.
    pub async fn dock(
        &self,
        mobile: NodeId,
        static_id: NodeId,
        port: u8,
    ) -> Result<(), IslandError> {
        self.call(|r| Command::Dock(mobile, static_id, port, r))
            .await?
    }

    /// Undocks `mobile`: it loses power at once and both signal loops open.
    pub async fn undock(&self, mobile: NodeId) -> Result<(), IslandError> {
        self.call(|r| Command::Undock(mobile, r)).await?
    }

    /// Removes and restores an element's power: a fresh boot (reset `PowerOn`) with its stored ID.
    /// A static element's mobiles lose power with it. A mobile element must be powered.
    pub async fn power_cycle(&self, node: NodeId) -> Result<(), IslandError> {
        self.call(|r| Command::PowerCycle(node, r)).await?
    }

    /// Connects an element to the bus or disconnects it (it keeps running).
    pub async fn set_on_bus(&self, node: NodeId, on: bool) -> Result<(), IslandError> {
        self.call(|r| Command::SetOnBus(node, on, r)).await?
    }

    /// Writes `bytes` to the element's configuration UART and returns what it answered meanwhile
    /// (2 bytes per complete request, see `ihex_proto::uart`). The element must be powered.
    pub async fn uart(&self, node: NodeId, bytes: &[u8]) -> Result<Vec<u8>, IslandError> {
        let bytes = bytes.to_vec();
        self.call(|r| Command::Uart(node, bytes, r)).await?
    }

    /// One element's actuators (all off when unpowered).
    pub async fn actuators(&self, node: NodeId) -> Result<Actuators, IslandError> {
        self.view(node).await.map(|v| v.actuators)
    }

    /// One element's state.
    pub async fn view(&self, node: NodeId) -> Result<NodeView, IslandError> {
        let all = self.snapshot().await?;
        all.into_iter()
            .find(|v| v.name == node)
            .ok_or(IslandError::UnknownNode(node))
    }

    /// Every element's state, static elements first, in file order.
    pub async fn snapshot(&self) -> Result<Vec<NodeView>, IslandError> {
        self.call(Command::Snapshot).await
    }

    /// A stream of changes from now on. A receiver that lags more than [`EVENT_CAPACITY`] events
    /// behind gets `RecvError::Lagged` and continues with the newest.
    pub fn subscribe(&self) -> broadcast::Receiver<IslandEvent> {
        self.events.subscribe()
    }

    /// Stops the island: every node loses power and leaves the bus.
    pub async fn shutdown(&self) {
        let _ = self.call(Command::Shutdown).await;
    }
}

struct Live {
    node: Node,
    tx: LinkTx,
    reader: JoinHandle<()>,
    epoch: u64,
    actuators: Actuators,
    buzzer_done_at: Option<Millis>,
    /// Simulated transmit error counter of the node's CAN controller.
    tec: u8,
}

impl Drop for Live {
    fn drop(&mut self) {
        self.reader.abort();
    }
}

struct Element {
    name: NodeId,
    role: BootRole,
    ports: u8,
    uid: Uid,
    /// The "flash": the ID the board boots with.
    stored_id: Option<NodeId>,
    /// Mobile: its own port it docks by.
    own_port: Port,
    /// Mobile: where it is docked.
    docked: Option<(NodeId, Port)>,
    /// Pin levels of the signal loops (bit n = port n closed).
    loops: u8,
    on_bus: bool,
    live: Option<Live>,
    /// Its flash and bootloader: the images it runs.
    board: Board,
    /// The identity of the image it last booted (reported while powered off too).
    firmware: FirmwareIdentity,
    /// Why it starts next time (a reset the node asked for is a software reset).
    next_reset: ResetReason,
    /// What its kept RAM block holds across the reset it asked for (relay, confirmed docks):
    /// restored at the next boot if that is the software reset, lost with a power cut.
    retained: Option<Retained>,
}

type Received = (NodeId, u64, CanFrame);

/// The island's state, owned by its task. Start one with [`Island::start`].
pub struct Island {
    link: Link,
    origin: Instant,
    bounce: bool,
    elements: BTreeMap<NodeId, Element>,
    /// Element names in display order (statics first, file order).
    order: Vec<NodeId>,
    events: broadcast::Sender<IslandEvent>,
    frames_tx: mpsc::Sender<Received>,
    next_epoch: u64,
    /// Pending loop-level changes (bounce): (due, element, port, closed).
    levels: Vec<(Millis, NodeId, Port, bool)>,
}

impl Island {
    /// Builds the island on `link`, powers the static elements (and mobiles docked on a static whose
    /// relay comes on) and runs it on a tokio task. Must be called inside a tokio runtime.
    pub fn start(desc: &IslandDesc, link: Link) -> Result<IslandHandle, IslandError> {
        let (events, _) = broadcast::channel(EVENT_CAPACITY);
        let (frames_tx, frames_rx) = mpsc::channel(256);
        check(desc)?;
        let (cmd_tx, cmd_rx) = mpsc::channel(32);
        let mut island = Island {
            link,
            origin: Instant::now(),
            bounce: desc.bounce,
            elements: BTreeMap::new(),
            order: Vec::new(),
            events: events.clone(),
            frames_tx,
            next_epoch: 0,
            levels: Vec::new(),
        };
        let zero = Port::new(0).expect("port 0 exists");
        // Every board starts with a confirmed image of its version, as flashed with a probe.
        let mut images = Images::default();
        for s in &desc.statics {
            let board = images.factory(s.firmware.version)?;
            island.add(Element {
                name: s.id,
                role: BootRole::Static,
                ports: s.ports,
                uid: s.uid,
                stored_id: s.configured.then_some(s.id),
                own_port: zero,
                docked: None,
                loops: 0,
                on_bus: true,
                live: None,
                board,
                firmware: s.firmware,
                next_reset: ResetReason::PowerOn,
                retained: None,
            });
        }
        for m in &desc.mobiles {
            let board = images.factory(m.firmware.version)?;
            island.add(Element {
                name: m.id,
                role: BootRole::Mobile,
                ports: m.ports,
                uid: m.uid,
                stored_id: m.configured.then_some(m.id),
                own_port: m.port,
                docked: m.dock,
                loops: if m.dock.is_some() { m.port.mask() } else { 0 },
                on_bus: true,
                live: None,
                board,
                firmware: m.firmware,
                next_reset: ResetReason::PowerOn,
                retained: None,
            });
            if let Some((s, p)) = m.dock {
                if let Some(st) = island.elements.get_mut(&s) {
                    st.loops |= p.mask();
                }
            }
        }
        let statics: Vec<NodeId> = desc.statics.iter().map(|s| s.id).collect();
        let now = island.now();
        for s in statics {
            island.boot(s, now)?;
        }
        tokio::spawn(island.run(cmd_rx, frames_rx));
        Ok(IslandHandle {
            cmd: cmd_tx,
            events,
        })
    }

    fn add(&mut self, e: Element) {
        self.order.push(e.name);
        self.elements.insert(e.name, e);
    }

    fn now(&self) -> Millis {
        Millis(self.origin.elapsed().as_millis() as u64)
    }

    fn instant(&self, m: Millis) -> Instant {
        self.origin + Duration::from_millis(m.0)
    }

    fn emit(&self, e: IslandEvent) {
        tracing::debug!(event = ?e, "island");
        let _ = self.events.send(e);
    }

    async fn run(
        mut self,
        mut cmd_rx: mpsc::Receiver<Command>,
        mut frames_rx: mpsc::Receiver<Received>,
    ) {
        // Send the boot announcements queued by `start` before serving anything.
        self.settle().await;
        let mut last_timer: Option<Instant> = None;
        loop {
            // A deadline that is still due right after its timers ran (a core that does not move
            // it on) is retried 1 ms later rather than in a busy loop.
            let deadline = self.next_deadline().map(|d| match last_timer {
                Some(t) if d <= t => t + Duration::from_millis(1),
                _ => d,
            });
            tokio::select! {
                cmd = cmd_rx.recv() => match cmd {
                    None => break,
                    Some(Command::Shutdown(done)) => {
                        self.power_off_all();
                        let _ = done.send(());
                        return;
                    }
                    Some(c) => self.command(c).await,
                },
                Some((name, epoch, frame)) = frames_rx.recv() => {
                    self.frame(name, epoch, frame);
                    // Only the node that heard the frame can have new outputs: settling every
                    // node per frame made a broadcast cost nodes² (20 nodes starved the task).
                    self.settle_one(name).await;
                    continue;
                }
                _ = tokio::time::sleep_until(deadline.unwrap_or_else(Instant::now)), if deadline.is_some() => {
                    self.timers();
                    last_timer = Some(Instant::now());
                }
            }
            self.settle().await;
        }
        self.power_off_all();
    }

    fn power_off_all(&mut self) {
        for e in self.elements.values_mut() {
            e.live = None;
        }
    }

    fn next_deadline(&self) -> Option<Instant> {
        let nodes = self
            .elements
            .values()
            .filter_map(|e| e.live.as_ref())
            .flat_map(|l| [l.node.poll_at(), l.buzzer_done_at].into_iter().flatten());
        let levels = self.levels.iter().map(|l| l.0);
        nodes.chain(levels).min().map(|m| self.instant(m))
    }

    fn timers(&mut self) {
        let now = self.now();
        let mut due: Vec<_> = Vec::new();
        self.levels.retain(|l| {
            if l.0 <= now {
                due.push(*l);
                false
            } else {
                true
            }
        });
        due.sort_by_key(|l| l.0);
        // Several toggles of one contact due at once mean this task was late (a loaded machine):
        // they all reach the node at the same `now`, so only the last one matters. Feeding the
        // others would make a glitch look like a level held for the whole delay, i.e. a real edge.
        let mut last: Vec<(NodeId, Port, bool)> = Vec::new();
        for (_, name, port, closed) in due {
            match last.iter_mut().find(|l| l.0 == name && l.1 == port) {
                Some(l) => l.2 = closed,
                None => last.push((name, port, closed)),
            }
        }
        for (name, port, closed) in last {
            self.set_level(name, port, closed, now);
        }
        for e in self.elements.values_mut() {
            if let Some(l) = e.live.as_mut() {
                if l.buzzer_done_at.is_some_and(|t| t <= now) {
                    l.buzzer_done_at = None;
                    l.node.handle_buzzer_done(now);
                }
                if l.node.poll_at().is_some_and(|t| t <= now) {
                    l.node.tick(now);
                }
            }
        }
    }

    fn frame(&mut self, name: NodeId, epoch: u64, frame: CanFrame) {
        let now = self.now();
        let Some(e) = self.elements.get_mut(&name) else {
            return;
        };
        if !e.on_bus {
            return;
        }
        let Some(l) = e.live.as_mut().filter(|l| l.epoch == epoch) else {
            return;
        };
        if let CanFrame::Error(_) = frame {
            // Error frames carry no message; the core learns about bus trouble from counters only.
            return;
        }
        let raw = match frame.id() {
            embedded_can::Id::Standard(s) => s.as_raw() as u32,
            embedded_can::Id::Extended(x) => x.as_raw(),
        };
        l.node.handle_frame(
            raw,
            frame.is_extended(),
            frame.is_remote_frame(),
            frame.data(),
            now,
        );
    }

    /// Sets a loop's pin level and tells the node (if powered).
    fn set_level(&mut self, name: NodeId, port: Port, closed: bool, now: Millis) {
        let Some(e) = self.elements.get_mut(&name) else {
            return;
        };
        if closed {
            e.loops |= port.mask();
        } else {
            e.loops &= !port.mask();
        }
        if let Some(l) = e.live.as_mut() {
            l.node.handle_loop_level(port, closed, now);
        }
    }

    /// Changes a loop level, through a bouncing contact if enabled.
    fn change_level(&mut self, name: NodeId, port: Port, closed: bool) {
        let now = self.now();
        // A newer change supersedes any bounce still pending on the same contact.
        self.levels.retain(|l| !(l.1 == name && l.2 == port));
        if self.bounce {
            for (dt, same) in BOUNCE {
                let level = if same { closed } else { !closed };
                if dt == 0 {
                    self.set_level(name, port, level, now);
                } else {
                    self.levels.push((now.add_ms(dt), name, port, level));
                }
            }
        } else {
            self.set_level(name, port, closed, now);
        }
    }

    /// Powers an element up: a fresh node, its own endpoint and reader.
    fn boot(&mut self, name: NodeId, now: Millis) -> Result<(), IslandError> {
        let (tx, mut rx) = self.link.open()?;
        let epoch = self.next_epoch;
        self.next_epoch += 1;
        let e = self
            .elements
            .get_mut(&name)
            .ok_or(IslandError::UnknownNode(name))?;
        // The bootloader first: it may swap in an update, or revert one that never confirmed.
        let booted = board::boot(&mut e.board, ihex_image::test_key::PUBLIC)
            .map_err(|err| IslandError::Boot(name, err))?;
        tx.set_filters(&sc_filters(e.stored_id))?;
        e.firmware = booted.firmware;
        let reset = std::mem::replace(&mut e.next_reset, ResetReason::PowerOn);
        let retained = e.retained.take().filter(|_| reset == ResetReason::Software);
        let config = Config {
            role: e.role,
            ports: e.ports,
            uid: e.uid,
            node_id: e.stored_id,
            reset,
            firmware: booted.firmware,
            update: booted.update,
        };
        let mut node = Node::new(config, now);
        node.handle_self_test(booted.self_test(), now);
        for p in 0..e.ports.min(Port::COUNT) {
            let port = Port::new(p).expect("p < Port::COUNT");
            let closed = e.loops & port.mask() != 0;
            // Pins start open (pulled up): only closed loops are an edge worth reporting.
            if closed {
                node.handle_loop_level(port, closed, now);
            }
        }
        // The bootloader drove the relay from the kept RAM block before the swap, so the
        // docked mobile element never lost its power (docs/firmware.md, "Reset and the relay").
        if let Some(r) = retained {
            node.restore(r, now);
        }
        let actuators = node.actuators();
        let frames = self.frames_tx.clone();
        let reader = tokio::spawn(async move {
            loop {
                match rx.recv().await {
                    Ok(f) => {
                        if frames.send((name, epoch, f)).await.is_err() {
                            return;
                        }
                    }
                    Err(err) => {
                        tracing::warn!(node = %name, %err, "receive failed; node no longer hears the bus");
                        return;
                    }
                }
            }
        });
        e.live = Some(Live {
            node,
            tx,
            reader,
            epoch,
            actuators,
            buzzer_done_at: None,
            tec: 0,
        });
        // The stored ID in the API's hex form, "none" for a factory-fresh board.
        let id = e
            .stored_id
            .map_or_else(|| "none".to_string(), |id| id.to_string());
        tracing::info!(node = %name, role = ?e.role, %id, "power on");
        // The core flags its initial actuators as changed: the next drain reports them.
        self.emit(IslandEvent::Power {
            node: name,
            on: true,
        });
        Ok(())
    }

    fn power_off(&mut self, name: NodeId) {
        let Some(e) = self.elements.get_mut(&name) else {
            return;
        };
        if e.live.take().is_some() {
            tracing::info!(node = %name, "power off");
            self.emit(IslandEvent::Power {
                node: name,
                on: false,
            });
            self.emit(IslandEvent::Actuators {
                node: name,
                actuators: Actuators::default(),
            });
        }
    }

    /// Carries out every node's outputs, then brings mobile power in line with the relays, until
    /// nothing changes any more.
    async fn settle(&mut self) {
        // Mobiles cannot power other elements, so this converges in two rounds (a node's reset adds
        // one: it boots again with outputs of its own); the bound is a guard.
        for _ in 0..6 {
            let reset = self.drain_all().await;
            if !self.reconcile_power() && !reset {
                break;
            }
        }
    }

    /// [`Island::settle`] after an input to `name` alone: carries out its outputs; the whole
    /// island settles only when that changed more (a reset, mobile power).
    async fn settle_one(&mut self, name: NodeId) {
        let now = self.now();
        let mut events = Vec::new();
        let reset = match self.elements.get_mut(&name) {
            Some(e) => drain(e, now, &mut events, None).await,
            None => false,
        };
        for ev in events {
            self.emit(ev);
        }
        if reset {
            self.reset(name);
        }
        if reset || self.reconcile_power() {
            self.settle().await;
        }
    }

    /// Carries out every node's outputs; true when a node reset (and has new outputs).
    async fn drain_all(&mut self) -> bool {
        let now = self.now();
        let mut events = Vec::new();
        let mut resets = Vec::new();
        for e in self.elements.values_mut() {
            if drain(e, now, &mut events, None).await {
                resets.push(e.name);
            }
        }
        for ev in events {
            self.emit(ev);
        }
        let reset = !resets.is_empty();
        for name in resets {
            self.reset(name);
        }
        reset
    }

    /// The node asked for a reset (to swap an update in, or to revert one on trial): it starts
    /// again through its bootloader, as after a software reset. Its relay and confirmed docks are
    /// kept across it ([`Retained`]), as the firmware keeps them in its kept RAM block.
    fn reset(&mut self, name: NodeId) {
        let Some(e) = self.elements.get_mut(&name) else {
            return;
        };
        e.next_reset = ResetReason::Software;
        e.retained = e.live.as_ref().map(|l| l.node.retained());
        tracing::info!(node = %name, "reset");
        self.power_off(name);
        let now = self.now();
        if let Err(err) = self.boot(name, now) {
            tracing::error!(node = %name, %err, "does not come back after its reset");
        }
    }

    /// Powers mobiles up or down to match their static element's relay; true if anything changed.
    fn reconcile_power(&mut self) -> bool {
        let mut changes = Vec::new();
        for e in self.elements.values() {
            if e.role != BootRole::Mobile {
                continue;
            }
            let want = e.docked.is_some_and(|(s, _)| {
                self.elements
                    .get(&s)
                    .and_then(|st| st.live.as_ref())
                    .is_some_and(|l| l.actuators.relay)
            });
            if want != e.live.is_some() {
                changes.push((e.name, want));
            }
        }
        let now = self.now();
        for (name, on) in &changes {
            if *on {
                if let Err(err) = self.boot(*name, now) {
                    tracing::error!(node = %name, %err, "cannot power up");
                }
            } else {
                self.power_off(*name);
            }
        }
        !changes.is_empty()
    }

    async fn command(&mut self, c: Command) {
        match c {
            Command::Dock(m, s, p, r) => {
                let _ = r.send(self.dock(m, s, p));
            }
            Command::Undock(m, r) => {
                let _ = r.send(self.undock(m));
            }
            Command::PowerCycle(n, r) => {
                let res = self.power_cycle(n).await;
                let _ = r.send(res);
            }
            Command::SetOnBus(n, on, r) => {
                let res = match self.elements.get_mut(&n) {
                    None => Err(IslandError::UnknownNode(n)),
                    Some(e) => {
                        let changed = e.on_bus != on;
                        e.on_bus = on;
                        if changed {
                            self.emit(IslandEvent::Bus { node: n, on });
                        }
                        Ok(())
                    }
                };
                let _ = r.send(res);
            }
            Command::Uart(n, bytes, r) => {
                let res = self.uart(n, &bytes).await;
                let _ = r.send(res);
            }
            Command::Snapshot(r) => {
                let _ = r.send(self.snapshot());
            }
            Command::Shutdown(_) => unreachable!("handled in run"),
        }
    }

    fn element(&self, name: NodeId) -> Result<&Element, IslandError> {
        self.elements
            .get(&name)
            .ok_or(IslandError::UnknownNode(name))
    }

    fn dock(&mut self, mobile: NodeId, static_id: NodeId, port: u8) -> Result<(), IslandError> {
        let m = self.element(mobile)?;
        if m.role != BootRole::Mobile {
            return Err(IslandError::NotMobile(mobile));
        }
        if let Some((s, p)) = m.docked {
            return Err(IslandError::AlreadyDocked {
                mobile,
                static_id: s,
                port: p,
            });
        }
        let own = m.own_port;
        let s = self.element(static_id)?;
        if s.role != BootRole::Static {
            return Err(IslandError::NotStatic(static_id));
        }
        let port =
            Port::new(port)
                .filter(|p| p.get() < s.ports)
                .ok_or(IslandError::NoSuchPort {
                    node: static_id,
                    port,
                })?;
        if let Some(by) = self
            .elements
            .values()
            .find(|e| e.docked == Some((static_id, port)))
        {
            return Err(IslandError::PortTaken {
                static_id,
                port,
                by: by.name,
            });
        }
        if let Some(m) = self.elements.get_mut(&mobile) {
            m.docked = Some((static_id, port));
        }
        // The mobile's own loop is closed by the contact itself; it reads it when it powers up.
        self.set_level(mobile, own, true, self.now());
        self.change_level(static_id, port, true);
        self.emit(IslandEvent::Docked {
            mobile,
            static_id,
            port,
        });
        Ok(())
    }

    fn undock(&mut self, mobile: NodeId) -> Result<(), IslandError> {
        let m = self.element(mobile)?;
        if m.role != BootRole::Mobile {
            return Err(IslandError::NotMobile(mobile));
        }
        let (static_id, port) = m.docked.ok_or(IslandError::NotDocked(mobile))?;
        let own = m.own_port;
        if let Some(m) = self.elements.get_mut(&mobile) {
            m.docked = None;
        }
        // Pulled away: power is gone before the loop contact settles.
        self.power_off(mobile);
        self.set_level(mobile, own, false, self.now());
        self.change_level(static_id, port, false);
        self.emit(IslandEvent::Undocked {
            mobile,
            static_id,
            port,
        });
        Ok(())
    }

    async fn power_cycle(&mut self, name: NodeId) -> Result<(), IslandError> {
        let e = self.element(name)?;
        if e.live.is_none() {
            return Err(IslandError::NotPowered(name));
        }
        let role = e.role;
        self.power_off(name);
        // Let the loss of power propagate: a static element's mobiles go dark, and a mobile whose
        // dock is still powered comes straight back (that is its fresh boot).
        self.settle().await;
        if role == BootRole::Static {
            self.boot(name, self.now())?;
        }
        Ok(())
    }

    async fn uart(&mut self, name: NodeId, bytes: &[u8]) -> Result<Vec<u8>, IslandError> {
        let now = self.now();
        let e = self
            .elements
            .get_mut(&name)
            .ok_or(IslandError::UnknownNode(name))?;
        let l = e.live.as_mut().ok_or(IslandError::NotPowered(name))?;
        for b in bytes {
            l.node.handle_uart_byte(*b, now);
        }
        let mut reply = Vec::new();
        let mut events = Vec::new();
        let reset = drain(e, now, &mut events, Some(&mut reply)).await;
        for ev in events {
            self.emit(ev);
        }
        if reset {
            self.reset(name);
        }
        Ok(reply)
    }

    fn snapshot(&self) -> Vec<NodeView> {
        self.order
            .iter()
            .filter_map(|n| self.elements.get(n))
            .map(|e| NodeView {
                name: e.name,
                role: e.role,
                node_id: e.live.as_ref().map_or(e.stored_id, |l| l.node.node_id()),
                uid: e.uid,
                powered: e.live.is_some(),
                on_bus: e.on_bus,
                actuators: e
                    .live
                    .as_ref()
                    .map_or(Actuators::default(), |l| l.actuators),
                loops: e.loops,
                docked: e.docked,
                firmware: e.firmware,
            })
            .collect()
    }
}

/// The consistency [`IslandDesc::parse`] guarantees, for descriptions built by hand.
fn check(desc: &IslandDesc) -> Result<(), IslandError> {
    let bad = |m: String| Err(IslandError::InvalidDesc(m));
    let mut names: Vec<NodeId> = desc.statics.iter().map(|s| s.id).collect();
    names.extend(desc.mobiles.iter().map(|m| m.id));
    let mut sorted = names.clone();
    sorted.sort();
    sorted.dedup();
    if sorted.len() != names.len() {
        return bad("an element ID is used twice".into());
    }
    let mut taken = Vec::new();
    for m in &desc.mobiles {
        if m.port.get() >= m.ports.max(1) {
            return bad(format!(
                "\"{}\" docks by port {} of {}",
                m.id, m.port, m.ports
            ));
        }
        let Some((s, p)) = m.dock else { continue };
        match desc.statics.iter().find(|st| st.id == s) {
            Some(st) if p.get() < st.ports => {}
            _ => {
                return bad(format!(
                    "\"{}\" is docked on a missing static element or port",
                    m.id
                ))
            }
        }
        if taken.contains(&(s, p)) {
            return bad(format!("two mobiles are docked on \"{s}\" port {p}"));
        }
        taken.push((s, p));
    }
    Ok(())
}

/// Carries out one node's queued outputs; UART bytes go to `uart` when given (else they are logged).
/// Returns true when the node asked for a reset.
async fn drain(
    e: &mut Element,
    now: Millis,
    events: &mut Vec<IslandEvent>,
    mut uart: Option<&mut Vec<u8>>,
) -> bool {
    let Some(l) = e.live.as_mut() else {
        return false;
    };
    let mut reset = false;
    while let Some(out) = l.node.poll_output() {
        let out = match board::carry_out(&mut e.board, &mut l.node, out, now) {
            Carried::Done => continue,
            Carried::Reset => {
                // Whatever else it asked for is moot: the chip resets now.
                reset = true;
                break;
            }
            Carried::Other(out) => out,
        };
        match out {
            Output::Frame(p) => {
                if !e.on_bus {
                    // Alone on its cable, nobody acknowledges: the controller retransmits until
                    // it is error passive (TEC 128). The frame itself is dropped here.
                    tracing::trace!(node = %e.name, packet = ?p, "off the bus: frame lost");
                    if l.tec < ERROR_PASSIVE_TEC {
                        l.tec = ERROR_PASSIVE_TEC;
                        l.node.handle_can_status(l.tec, 0, false, now);
                    }
                    continue;
                }
                let Some(frame) = p.to_frame::<CanFrame>() else {
                    continue;
                };
                match l.tx.send(frame).await {
                    // A successful transmission lowers the counter by one (ISO 11898-1).
                    Ok(()) if l.tec > 0 => {
                        l.tec -= 1;
                        l.node.handle_can_status(l.tec, 0, false, now);
                    }
                    Ok(()) => {}
                    Err(err) => tracing::warn!(node = %e.name, %err, "send failed"),
                }
            }
            Output::Uart(b) => match uart.as_deref_mut() {
                Some(buf) => buf.extend_from_slice(&b),
                None => tracing::info!(node = %e.name, bytes = ?b, "unsolicited UART output"),
            },
            Output::StoreId(id) => {
                e.stored_id = Some(id);
                events.push(IslandEvent::IdStored { node: e.name, id });
            }
            Output::FiltersChanged => {
                if let Err(err) = l.tx.set_filters(&sc_filters(l.node.node_id())) {
                    tracing::error!(node = %e.name, %err, "cannot install filters");
                }
            }
            // `carry_out` has done these.
            Output::EraseDfu { .. }
            | Output::WriteDfu { .. }
            | Output::HashDfu { .. }
            | Output::MarkUpdated
            | Output::MarkBooted
            | Output::Reset => {}
        }
    }
    if reset {
        return true;
    }
    if l.node.actuators_changed() {
        let a = l.node.actuators();
        if a.buzzer != l.actuators.buzzer {
            l.buzzer_done_at = pattern_len(a.buzzer).map(|ms| now.add_ms(ms));
        }
        l.actuators = a;
        events.push(IslandEvent::Actuators {
            node: e.name,
            actuators: a,
        });
    }
    false
}

/// How long a finite buzzer pattern sounds (the last beep has no pause after it).
fn pattern_len(b: BuzzerOutput) -> Option<u64> {
    match b {
        BuzzerOutput::Pattern {
            on_ms,
            off_ms,
            count,
            ..
        } if count > 0 => {
            let n = count as u64;
            Some(n * on_ms as u64 + (n - 1) * off_ms as u64)
        }
        _ => None,
    }
}
