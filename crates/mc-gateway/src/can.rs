//! The CAN side: a receive task and a transmit path around one link, turning frames into
//! [`CanInput`]s for the core and the core's packets into frames. The link is SocketCAN
//! ([`CanLink::socketcan`]) or anything implementing [`FrameLink`] ([`CanLink::frames`]; the demo
//! plugs its in-memory bus in that way).
//!
//! The core hands frames to a [`Transmitter`]: a frame the link takes without waiting is written
//! there and then, in the core's turn, when no frame waits before it; the others go to the
//! transmit task, which waits for room. So the usual frame costs one system call and no task hop.
//!
//! On SocketCAN the receive task owns the socket's life: it installs the gateway's kernel filters,
//! enables error frames and the echo of the gateway's own frames (`CAN_RAW_RECV_OWN_MSGS`: a frame
//! comes back once the interface sent it, which confirms it to the core), sizes the receive buffer,
//! and when a read fails (interface down or gone) reports [`BusEvent::InterfaceDown`], reopens with
//! a capped back-off once the interface is up again, and reports [`BusEvent::Recovered`]. The
//! transmit task always writes on the socket of the moment (shared through a `watch`), never writes
//! a frame after its [`Transmit::not_after`] (reported as [`CanInput::Withdrawn`]), and reports every
//! frame it cannot send. The core hands the link at most `ihex_gateway_core::bridge::TRANSMIT_WINDOW`
//! frames not yet confirmed, so few frames are ever beyond recall.

use std::{
    future::Future,
    io,
    os::fd::AsRawFd,
    sync::{
        atomic::{AtomicUsize, Ordering},
        Arc,
    },
    time::{Duration, Instant},
};

use embedded_can::{Frame as _, Id};
use ihex_gateway_core::{BusEvent, Transmit};
use ihex_proto::{
    filter::{self, Filter},
    DecodeError, NodeId, Packet,
};
use socketcan::{CanFilter, CanFrame, Socket as _, SocketOptions};
use tokio::{
    io::{unix::AsyncFd, Interest},
    sync::{mpsc, watch, Notify},
    task::JoinSet,
};
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::{error::CanError, sys};

/// The gateway's SocketCAN socket: non-blocking, in tokio's reactor. The receive task reads it a
/// batch at a time ([`sys::recv_can_frames`]), the transmit task writes it a frame at a time.
type Socket = AsyncFd<socketcan::CanSocket>;

/// `CAN_ERR_BUSOFF` (linux/can/error.h): the controller went bus-off.
pub const CAN_ERR_BUSOFF: u32 = 0x0000_0040;
/// `CAN_ERR_RESTARTED`: the controller restarted after bus-off.
pub const CAN_ERR_RESTARTED: u32 = 0x0000_0100;
/// First reopen delay after the interface is lost; doubles up to [`REOPEN_MAX`].
pub const REOPEN_MIN: Duration = Duration::from_millis(100);
/// Longest reopen delay.
pub const REOPEN_MAX: Duration = Duration::from_secs(5);
/// A write that cannot get into the kernel's queue within this time fails (the bus is stuck).
const WRITE_TIMEOUT: Duration = Duration::from_millis(200);
/// Pause before a write the interface's full queue refused (ENOBUFS) is tried again.
const ENOBUFS_RETRY: Duration = Duration::from_millis(1);
/// How often the receive task looks at the interface's flags while the socket is quiet.
const LINK_CHECK: Duration = Duration::from_secs(1);

/// What the CAN tasks report to the core.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CanInput {
    /// A valid iHEX packet.
    Packet(Packet),
    /// A frame that passed the filters but does not decode.
    Undecodable {
        /// Raw identifier (29 or 11 bits, no flags).
        raw_id: u32,
        /// Its data.
        data: Vec<u8>,
        /// Why it does not decode.
        err: DecodeError,
    },
    /// A bus condition.
    Bus(BusEvent),
    /// A packet could not be transmitted.
    SendFailed(Packet, String),
    /// A packet was written on a link that does not echo frames: as sent as it will ever be known.
    Transmitted(Packet),
    /// A packet was not written because its `not_after` had passed.
    Withdrawn(Packet),
}

/// A frame link other than SocketCAN that the CAN tasks can run on (the demo's in-memory bus).
pub trait FrameLink: Send + 'static {
    /// The transmit half, used by the transmit task.
    type Sender: FrameSender;
    /// A transmit half for this link.
    fn sender(&self) -> Self::Sender;
    /// The next frame that passes the gateway's filters (the link applies
    /// `ihex_proto::filter::gateway_filters()` itself); `None` once the link is gone for good.
    fn recv(&mut self) -> impl Future<Output = Option<CanFrame>> + Send;
}

/// Transmits frames on a [`FrameLink`].
pub trait FrameSender: Send + Sync + 'static {
    /// Writes one frame without waiting (the link has no queue to wait for); the error text is
    /// the reason the core reports.
    fn send(&self, frame: CanFrame) -> Result<(), String>;

    /// `None` when the link takes a frame now; otherwise how long to wait before asking again. A
    /// link says so when nothing else paces its senders (an in-memory bus: no arbitration, no bit
    /// rate, receivers that lose what they fall behind on). Frames then wait in the transmit queue,
    /// whose filling holds commands back as a busy bus does, up to [`BUSY_WAIT_MAX`] each. Never
    /// busy unless a link says so.
    fn busy_for(&self) -> Option<Duration> {
        None
    }
}

/// Longest a frame waits for a [`FrameSender::busy_for`] link: after that it is written all the
/// same (a receiver that stopped reading must not stop the gateway's transmissions for good).
pub const BUSY_WAIT_MAX: Duration = Duration::from_secs(1);

/// Writes a frame at once if the link takes it without waiting: what became of it, or `None` when
/// it was not written (the transmit task then tries, waits and reports).
type WriteNow = Box<dyn Fn(&CanFrame) -> Option<Handed> + Send>;

type Start = Box<
    dyn FnOnce(
            mpsc::Receiver<Transmit>,
            Arc<AtomicUsize>,
            mpsc::Sender<CanInput>,
            &mut JoinSet<()>,
            CancellationToken,
        ) -> WriteNow
        + Send,
>;

/// What [`Transmitter::send`] did with a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Handed {
    /// Written on a link that echoes its frames: the echo confirms it.
    Written,
    /// Written on a link without echo: as sent as it will ever be known (the core reports it
    /// transmitted itself).
    Transmitted,
    /// Queued for the transmit task, which reports what becomes of it.
    Queued,
}

/// The core's end of the transmit path (see the module's documentation).
pub struct Transmitter {
    queue: mpsc::Sender<Transmit>,
    /// Frames queued for the transmit task that it has not finished writing: a frame is written
    /// at once only while this is 0, so frames leave in the order the core hands them over.
    queued: Arc<AtomicUsize>,
    write_now: Option<WriteNow>,
}

impl std::fmt::Debug for Transmitter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Transmitter")
            .field("queued", &self.queued.load(Ordering::Relaxed))
            .field("writes_at_once", &self.write_now.is_some())
            .finish()
    }
}

impl Transmitter {
    /// Hands `t` to the link, never waiting: written at once when nothing waits before it, the
    /// link takes it and its `not_after` has not passed at `now`; queued otherwise. An error when
    /// the queue (a transmit window's room) is full or the transmit task has stopped.
    pub fn send(
        &self,
        t: Transmit,
        now: Instant,
    ) -> Result<Handed, mpsc::error::TrySendError<Transmit>> {
        if let Some(write) = &self.write_now {
            let in_time = t.not_after.is_none_or(|d| now < d);
            if in_time && self.queued.load(Ordering::Acquire) == 0 {
                if let Some(handed) = t.packet.to_frame::<CanFrame>().and_then(|f| write(&f)) {
                    return Ok(handed);
                }
            }
        }
        self.queued.fetch_add(1, Ordering::AcqRel);
        self.queue
            .try_send(t)
            .map(|()| Handed::Queued)
            .inspect_err(|_| {
                self.queued.fetch_sub(1, Ordering::AcqRel);
            })
    }

    /// A transmitter that only queues, on `queue` (tests of the core).
    #[cfg(test)]
    pub(crate) fn queue_only(queue: mpsc::Sender<Transmit>) -> Transmitter {
        Transmitter {
            queue,
            queued: Arc::default(),
            write_now: None,
        }
    }
}

/// What the gateway's socket receives: frames addressed to the gateway, and the echo of its own.
pub fn receive_filters() -> [Filter; 2] {
    let [to_gateway] = filter::gateway_filters();
    [to_gateway, Filter::from_node(NodeId::GATEWAY)]
}

/// How the CAN tasks reach the bus: built (and, for SocketCAN, first opened) before they run.
pub struct CanLink {
    name: String,
    start: Start,
}

impl std::fmt::Debug for CanLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CanLink").field("name", &self.name).finish()
    }
}

impl CanLink {
    /// A SocketCAN interface with `rx_buffer` bytes of receive buffer. The first open happens here,
    /// so the core's first frames find a socket; an interface that is not there yet is waited for
    /// by the receive task. Fails only when the gateway's filters cannot be expressed for the kernel
    /// or the socket refuses them.
    pub fn socketcan(iface: &str, rx_buffer: usize) -> Result<CanLink, CanError> {
        let filters = receive_filters();
        let setup = SocketSetup {
            iface: iface.to_owned(),
            rx_buffer,
            plan: filter::to_kernel(&filters)?,
            filters: filters.to_vec(),
        };
        let first = setup.open()?.map(Arc::new);
        let start: Start = Box::new(move |packets, queued, inputs, tasks, cancel| {
            let (link_tx, link_rx) = watch::channel(first.clone());
            let failed = Arc::new(Notify::new());
            tasks.spawn(receive_socket(
                setup,
                first,
                inputs.clone(),
                link_tx,
                failed.clone(),
                cancel.clone(),
            ));
            let link = link_rx.clone();
            let writer = SocketWriter { link: link_rx };
            tasks.spawn(transmit(
                packets,
                queued,
                writer,
                inputs,
                Some(failed),
                cancel,
            ));
            // The socket is non-blocking: a full queue (ENOBUFS, EAGAIN) or a link error leaves
            // the frame to the transmit task, which waits for room or reports the error.
            Box::new(move |frame: &CanFrame| {
                let sock = link.borrow().clone()?;
                sock.get_ref()
                    .write_frame(frame)
                    .ok()
                    .map(|()| Handed::Written)
            })
        });
        Ok(CanLink {
            name: iface.to_owned(),
            start,
        })
    }

    /// Any other frame link, named `name` in logs.
    pub fn frames<L: FrameLink>(name: &str, link: L) -> CanLink {
        let start: Start = Box::new(move |packets, queued, inputs, tasks, cancel| {
            let sender = link.sender();
            let writer = LinkWriter(link.sender());
            tasks.spawn(receive_link(link, inputs.clone(), cancel.clone()));
            tasks.spawn(transmit(packets, queued, writer, inputs, None, cancel));
            Box::new(move |frame: &CanFrame| {
                if sender.busy_for().is_some() {
                    return None;
                }
                sender.send(*frame).ok().map(|()| Handed::Transmitted)
            })
        });
        CanLink {
            name: name.to_owned(),
            start,
        }
    }

    /// The link's name (interface name, or what [`CanLink::frames`] was given).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Spawns the receive and transmit tasks into `tasks`; returns the core's end of the transmit
    /// path, whose queue holds `capacity` frames (the core's transmit window).
    pub fn spawn(
        self,
        capacity: usize,
        inputs: mpsc::Sender<CanInput>,
        tasks: &mut JoinSet<()>,
        cancel: CancellationToken,
    ) -> Transmitter {
        let (queue, rx_packets) = mpsc::channel(capacity.max(1));
        let queued = Arc::new(AtomicUsize::new(0));
        let write_now = (self.start)(rx_packets, queued.clone(), inputs, tasks, cancel);
        Transmitter {
            queue,
            queued,
            write_now: Some(write_now),
        }
    }
}

struct SocketSetup {
    iface: String,
    rx_buffer: usize,
    plan: filter::KernelPlan,
    filters: Vec<Filter>,
}

impl SocketSetup {
    /// Opens and configures the socket. `Ok(None)` means "not now" (interface missing or down).
    fn open(&self) -> Result<Option<Socket>, CanError> {
        if !interface_up(&self.iface) {
            return Ok(None);
        }
        let sock = match socketcan::CanSocket::open(&self.iface) {
            Ok(s) => s,
            Err(e) => {
                debug!(iface = %self.iface, error = %e, "cannot open CAN interface yet");
                return Ok(None);
            }
        };
        let opt = |option: &'static str| move |source| CanError::SocketOption { option, source };
        let kf: Vec<CanFilter> = self
            .plan
            .filters
            .iter()
            .map(|k| CanFilter::new(k.can_id, k.can_mask))
            .collect();
        sock.set_filters(&kf).map_err(opt("CAN_RAW_FILTER"))?;
        sock.set_join_filters(self.plan.join)
            .map_err(opt("CAN_RAW_JOIN_FILTERS"))?;
        sock.set_error_filter_accept_all()
            .map_err(opt("CAN_RAW_ERR_FILTER"))?;
        sock.set_recv_own_msgs(true)
            .map_err(opt("CAN_RAW_RECV_OWN_MSGS"))?;
        let got = set_receive_buffer(&sock, self.rx_buffer);
        sock.set_nonblocking(true).map_err(opt("O_NONBLOCK"))?;
        let sock = sys::register_can(sock).map_err(opt("the reactor's registration (epoll)"))?;
        info!(iface = %self.iface, rx_buffer = got, asked = self.rx_buffer, join = self.plan.join,
              software_check = self.plan.software_check, "CAN interface open");
        Ok(Some(sock))
    }
}

/// Asks for `bytes` of receive buffer: `SO_RCVBUFFORCE` (needs CAP_NET_ADMIN, ignores
/// `net.core.rmem_max`) first, `SO_RCVBUF` (capped by rmem_max) otherwise. The default buffer loses
/// frames at high rates. Returns what the kernel granted (it doubles the value for bookkeeping).
fn set_receive_buffer(sock: &socketcan::CanSocket, bytes: usize) -> usize {
    let val = bytes.min(i32::MAX as usize) as i32;
    if sock
        .set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUFFORCE, val)
        .is_err()
    {
        if let Err(e) = sock.set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUF, val) {
            warn!(error = %e, "cannot set SO_RCVBUF on the CAN socket");
        }
    }
    let mut buf = [0u8; 4];
    match sock.get_socket_option_bytes(libc::SOL_SOCKET, libc::SO_RCVBUF, &mut buf) {
        Ok(4) => i32::from_ne_bytes(buf).max(0) as usize,
        _ => 0,
    }
}

/// True when the interface exists and is administratively up (`/sys/class/net/IF/flags` & IFF_UP).
/// Without sysfs the answer is "up" and opening the socket decides.
fn interface_up(iface: &str) -> bool {
    match std::fs::read_to_string(format!("/sys/class/net/{iface}/flags")) {
        Ok(s) => u32::from_str_radix(s.trim().trim_start_matches("0x"), 16)
            .map(|f| f & libc::IFF_UP as u32 != 0)
            .unwrap_or(true),
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            // No such interface, or no sysfs at all.
            !std::path::Path::new("/sys/class/net").exists()
        }
        Err(_) => true,
    }
}

/// Frames the interface (driver/controller) lost on reception so far: `rx_dropped` +
/// `rx_over_errors` + `rx_fifo_errors` from sysfs (an MCP2515 overflowing counts here); 0 without
/// sysfs. Drops in our own socket's buffer are not visible this way (that needs `SO_RXQ_OVFL`).
fn interface_drops(iface: &str) -> u64 {
    ["rx_dropped", "rx_over_errors", "rx_fifo_errors"]
        .iter()
        .filter_map(|c| {
            std::fs::read_to_string(format!("/sys/class/net/{iface}/statistics/{c}")).ok()
        })
        .filter_map(|s| s.trim().parse::<u64>().ok())
        .sum()
}

#[tracing::instrument(name = "can_rx", skip_all, fields(iface = %setup.iface))]
async fn receive_socket(
    setup: SocketSetup,
    mut first: Option<Arc<Socket>>,
    inputs: mpsc::Sender<CanInput>,
    link: watch::Sender<Option<Arc<Socket>>>,
    failed: Arc<Notify>,
    cancel: CancellationToken,
) {
    let mut cancelled = crate::shutdown::stopped(&cancel);
    let mut delay = REOPEN_MIN;
    let mut down = false;
    loop {
        let opened = match first.take() {
            Some(s) => Ok(Some(s)),
            None => setup.open().map(|o| o.map(Arc::new)),
        };
        let sock = match opened {
            Ok(Some(s)) => s,
            Ok(None) => {
                if !down {
                    warn!("CAN interface missing or down; retrying");
                    down = true;
                    link.send_replace(None);
                    let _ = inputs.send(CanInput::Bus(BusEvent::InterfaceDown)).await;
                }
                tokio::select! {
                    _ = &mut cancelled => return,
                    _ = tokio::time::sleep(delay) => {}
                }
                delay = (delay * 2).min(REOPEN_MAX);
                continue;
            }
            Err(e) => {
                // A socket that refuses our filters will never work: say so loudly, keep retrying
                // in case the interface is replaced, but slowly.
                tracing::error!(error = %e, "CAN socket set-up failed");
                tokio::select! {
                    _ = &mut cancelled => return,
                    _ = tokio::time::sleep(REOPEN_MAX) => {}
                }
                continue;
            }
        };
        if down {
            info!("CAN interface back");
            link.send_replace(Some(sock.clone()));
            let _ = inputs.send(CanInput::Bus(BusEvent::Recovered)).await;
        }
        delay = REOPEN_MIN;
        let mut check = tokio::time::interval(LINK_CHECK);
        check.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut drops = interface_drops(&setup.iface);
        // The socket's pending error (ENETDOWN on link down) goes to whichever call sees it
        // first, often a write in the transmit task: so a failed write, a failed read and a
        // periodic look at the interface flags all lead here.
        let mut batch = [socketcan::frame::can_frame_default(); sys::CAN_BATCH];
        // Made once per socket: a fresh one per read would join and leave its waiter list per
        // read. It is used up when it fires, which ends this socket's loop.
        let write_failed = failed.notified();
        tokio::pin!(write_failed);
        let why = loop {
            let read = tokio::select! {
                _ = &mut cancelled => return,
                _ = &mut write_failed => break "a write failed with a link error".to_owned(),
                _ = check.tick() => {
                    if !interface_up(&setup.iface) {
                        break "interface down".to_owned();
                    }
                    let now = interface_drops(&setup.iface);
                    let lost = now.saturating_sub(drops);
                    drops = now;
                    if lost > 0 {
                        let n = u32::try_from(lost).unwrap_or(u32::MAX);
                        if inputs.send(CanInput::Bus(BusEvent::RxDropped(n))).await.is_err() {
                            return;
                        }
                    }
                    continue;
                }
                r = read_batch(&sock, &mut batch) => r,
            };
            let n = match read {
                Ok(n) => n,
                Err(e) => break e.to_string(),
            };
            for raw in &batch[..n] {
                let frame = CanFrame::from(*raw);
                let Some(input) = classify(&frame, &setup.filters, setup.plan.software_check)
                else {
                    continue;
                };
                if inputs.send(input).await.is_err() {
                    return;
                }
            }
        };
        warn!(%why, "CAN interface lost; reopening");
        link.send_replace(None);
        // Reported here, so the reopen loop must not report it again.
        down = true;
        let _ = inputs.send(CanInput::Bus(BusEvent::InterfaceDown)).await;
    }
}

/// Waits until `sock` is readable and reads the frames waiting, one system call for up to `batch`
/// of them (a busy bus costs one call per batch, not per frame): how many are at the front of
/// `batch`. Cancel-safe: the frames are read in the same poll that returns them.
async fn read_batch(sock: &Socket, batch: &mut [libc::can_frame]) -> io::Result<usize> {
    loop {
        let mut ready = sock.readable().await?;
        match ready.try_io(|s| sys::recv_can_frames(s.as_raw_fd(), batch)) {
            Ok(Ok((n, filled))) => {
                // A batch with room left emptied the queue: the reactor's next edge says when
                // more came, without a read that would only answer EAGAIN first.
                if !filled {
                    ready.clear_ready();
                }
                return Ok(n);
            }
            Ok(Err(e)) => return Err(e),
            Err(_would_block) => {}
        }
    }
}

#[tracing::instrument(name = "can_rx", skip_all)]
async fn receive_link<L: FrameLink>(
    mut link: L,
    inputs: mpsc::Sender<CanInput>,
    cancel: CancellationToken,
) {
    let mut cancelled = crate::shutdown::stopped(&cancel);
    // The link already filters with the same rule as the kernel.
    loop {
        let frame = tokio::select! {
            _ = &mut cancelled => return,
            f = link.recv() => f,
        };
        let Some(frame) = frame else {
            warn!("CAN link closed");
            let _ = inputs.send(CanInput::Bus(BusEvent::InterfaceDown)).await;
            cancelled.await;
            return;
        };
        if let Some(input) = classify(&frame, &[], false) {
            if inputs.send(input).await.is_err() {
                return;
            }
        }
    }
}

/// Turns a received frame into the bridge's input; `None` when the software filter check drops it.
pub fn classify(frame: &CanFrame, filters: &[Filter], software_check: bool) -> Option<CanInput> {
    if let CanFrame::Error(ef) = frame {
        let class = ef.error_bits();
        let mut data = [0u8; 8];
        let d = frame.data();
        data[..d.len().min(8)].copy_from_slice(&d[..d.len().min(8)]);
        let event = if class & CAN_ERR_BUSOFF != 0 {
            BusEvent::BusOff
        } else if class & CAN_ERR_RESTARTED != 0 {
            BusEvent::Recovered
        } else {
            BusEvent::ErrorFrame { class, data }
        };
        return Some(CanInput::Bus(event));
    }
    if software_check && !filter::accepts(filters, filter::word_of(frame)) {
        return None;
    }
    Some(match Packet::from_frame(frame) {
        Ok(p) => CanInput::Packet(p),
        Err(err) => CanInput::Undecodable {
            raw_id: match frame.id() {
                Id::Standard(s) => s.as_raw() as u32,
                Id::Extended(e) => e.as_raw(),
            },
            data: frame.data().to_vec(),
            err,
        },
    })
}

/// Why a frame was not written.
enum WriteError {
    /// It could not be written; true when that means the link itself is gone.
    Failed(String, bool),
    /// Its `not_after` passed before the interface took it.
    Late,
}

/// Writes frames.
trait Writer: Send + 'static {
    /// Writes `frame` unless that cannot happen by `not_after`.
    fn write(
        &self,
        frame: CanFrame,
        not_after: Option<tokio::time::Instant>,
    ) -> impl Future<Output = Result<(), WriteError>> + Send;
    /// True when the link echoes written frames back through the receive task (the echo confirms
    /// them); otherwise the transmit task reports a written frame as transmitted itself.
    fn echoes(&self) -> bool;
}

/// Writes on the SocketCAN socket of the moment.
struct SocketWriter {
    link: watch::Receiver<Option<Arc<Socket>>>,
}

impl Writer for SocketWriter {
    async fn write(
        &self,
        frame: CanFrame,
        not_after: Option<tokio::time::Instant>,
    ) -> Result<(), WriteError> {
        let Some(sock) = self.link.borrow().clone() else {
            return Err(WriteError::Failed("CAN interface down".into(), false));
        };
        write_retrying(
            || sock.async_io(Interest::WRITABLE, |s| s.write_frame(&frame)),
            not_after,
        )
        .await
    }

    fn echoes(&self) -> bool {
        true
    }
}

/// Writes with `attempt`, retrying while the kernel answers ENOBUFS: the interface's queue
/// (`txqueuelen`, 10 frames on most CAN drivers) is full, and a raw CAN socket does not wait for
/// room on its own nor signal it through readiness. The retry comes after [`ENOBUFS_RETRY`], the
/// timer's resolution, because ten of the shortest frames leave a 500 kbit/s bus in about 1.1 ms:
/// a longer pause lets the queue run dry and the bus idle while frames wait here. Gives up after
/// [`WRITE_TIMEOUT`] so one stuck bus cannot stall the gateway, and never retries past the frame's
/// own deadline (then [`WriteError::Late`]).
async fn write_retrying<F, Fut>(
    mut attempt: F,
    not_after: Option<tokio::time::Instant>,
) -> Result<(), WriteError>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = io::Result<()>>,
{
    let give_up = tokio::time::Instant::now() + WRITE_TIMEOUT;
    let deadline = not_after.map_or(give_up, |d| d.min(give_up));
    loop {
        if not_after.is_some_and(|d| tokio::time::Instant::now() >= d) {
            return Err(WriteError::Late);
        }
        match tokio::time::timeout_at(deadline, attempt()).await {
            Ok(Ok(())) => return Ok(()),
            Ok(Err(e)) if e.raw_os_error() == Some(libc::ENOBUFS) => {
                if tokio::time::Instant::now() >= deadline {
                    if deadline < give_up {
                        return Err(WriteError::Late);
                    }
                    let why = "transmit queue full (ENOBUFS)".into();
                    return Err(WriteError::Failed(why, false));
                }
                tokio::time::sleep(ENOBUFS_RETRY).await;
            }
            Ok(Err(e)) => {
                let link_error = matches!(
                    e.raw_os_error(),
                    Some(libc::ENETDOWN | libc::ENODEV | libc::ENXIO | libc::EBADF)
                );
                return Err(WriteError::Failed(e.to_string(), link_error));
            }
            Err(_) if deadline < give_up => return Err(WriteError::Late),
            Err(_) => return Err(WriteError::Failed("transmit timed out".into(), false)),
        }
    }
}

/// Writes on a [`FrameLink`]'s sender.
struct LinkWriter<S>(S);

impl<S: FrameSender> Writer for LinkWriter<S> {
    async fn write(
        &self,
        frame: CanFrame,
        not_after: Option<tokio::time::Instant>,
    ) -> Result<(), WriteError> {
        let late = || not_after.is_some_and(|d| tokio::time::Instant::now() >= d);
        let give_up = tokio::time::Instant::now() + BUSY_WAIT_MAX;
        while let Some(wait) = self.0.busy_for() {
            let now = tokio::time::Instant::now();
            if now >= give_up || late() {
                break;
            }
            let until = (now + wait).min(give_up);
            tokio::time::sleep_until(not_after.map_or(until, |d| until.min(d))).await;
        }
        if late() {
            return Err(WriteError::Late);
        }
        self.0.send(frame).map_err(|e| WriteError::Failed(e, true))
    }

    fn echoes(&self) -> bool {
        false
    }
}

/// Writes the frames the core queued (`queued` counts those not yet written), waiting for room
/// and reporting what it could not write.
#[tracing::instrument(name = "can_tx", skip_all)]
async fn transmit<W: Writer>(
    mut packets: mpsc::Receiver<Transmit>,
    queued: Arc<AtomicUsize>,
    writer: W,
    inputs: mpsc::Sender<CanInput>,
    failed: Option<Arc<Notify>>,
    cancel: CancellationToken,
) {
    let mut cancelled = crate::shutdown::stopped(&cancel);
    loop {
        let t = tokio::select! {
            _ = &mut cancelled => return,
            p = packets.recv() => match p { Some(p) => p, None => return },
        };
        let packet = t.packet;
        let not_after = t.not_after.map(tokio::time::Instant::from_std);
        let written = match packet.to_frame::<CanFrame>() {
            Some(frame) => writer.write(frame, not_after).await,
            None => Err(WriteError::Failed(
                "packet cannot be encoded".to_owned(),
                false,
            )),
        };
        // Done with it: the core may write the next frame itself.
        queued.fetch_sub(1, Ordering::AcqRel);
        let report = match written {
            Ok(()) if writer.echoes() => continue,
            Ok(()) => CanInput::Transmitted(packet),
            Err(WriteError::Late) => {
                debug!(?packet, "not written: its deadline passed");
                CanInput::Withdrawn(packet)
            }
            Err(WriteError::Failed(reason, link_error)) => {
                debug!(?packet, %reason, "send failed");
                if let (true, Some(failed)) = (link_error, &failed) {
                    failed.notify_one();
                }
                CanInput::SendFailed(packet, reason)
            }
        };
        if inputs.send(report).await.is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::ExtendedId;
    use ihex_proto::{Message, NodeId};
    use socketcan::CanErrorFrame;

    #[test]
    fn error_frames_become_bus_events() {
        let f = |class| CanFrame::Error(CanErrorFrame::new_error(class, &[1, 2, 3]).unwrap());
        assert_eq!(
            classify(&f(CAN_ERR_BUSOFF), &[], false),
            Some(CanInput::Bus(BusEvent::BusOff))
        );
        assert_eq!(
            classify(&f(CAN_ERR_RESTARTED), &[], false),
            Some(CanInput::Bus(BusEvent::Recovered))
        );
        assert_eq!(
            classify(&f(0x04), &[], false),
            Some(CanInput::Bus(BusEvent::ErrorFrame {
                class: 0x04,
                data: [1, 2, 3, 0, 0, 0, 0, 0]
            }))
        );
    }

    #[test]
    fn packets_and_garbage_are_told_apart() {
        let port = ihex_proto::Port::new(3).unwrap();
        let p = Packet::report(
            NodeId::new_sc(0x111).unwrap(),
            Message::DockDetected { port },
        );
        let frame: CanFrame = p.to_frame().unwrap();
        let filters = filter::gateway_filters();
        assert_eq!(classify(&frame, &filters, true), Some(CanInput::Packet(p)));
        // Kind 31 is unassigned: passes the filters, fails to decode.
        let raw = (31 << 24) | 0x111;
        let junk = CanFrame::new(ExtendedId::new(raw).unwrap(), &[0xde, 0xad]).unwrap();
        match classify(&junk, &[], false) {
            Some(CanInput::Undecodable { raw_id, data, .. }) => {
                assert_eq!(raw_id, raw);
                assert_eq!(data, vec![0xde, 0xad]);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn software_check_drops_what_the_filters_refuse() {
        // A frame addressed to another node, which the gateway filters do not accept.
        let p = Packet::command(
            NodeId::new_sc(0x222).unwrap(),
            Message::HealthCheck { seq: 1 },
        );
        let frame: CanFrame = p.to_frame().unwrap();
        let filters = filter::gateway_filters();
        assert!(
            !filter::accepts(&filters, filter::word_of(&frame)),
            "test premise"
        );
        assert_eq!(classify(&frame, &filters, true), None);
    }

    /// A link whose interface queue is full for its first `full_for` attempts: the kernel answers
    /// ENOBUFS, as a CAN driver's 10-frame `txqueuelen` does while the bus is saturated.
    struct QueueFull {
        full_for: usize,
        attempts: Arc<std::sync::atomic::AtomicUsize>,
    }

    impl Writer for QueueFull {
        async fn write(
            &self,
            _frame: CanFrame,
            not_after: Option<tokio::time::Instant>,
        ) -> Result<(), WriteError> {
            let attempt = || {
                let n = self
                    .attempts
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let r = if n < self.full_for {
                    Err(io::Error::from_raw_os_error(libc::ENOBUFS))
                } else {
                    Ok(())
                };
                std::future::ready(r)
            };
            write_retrying(attempt, not_after).await
        }

        fn echoes(&self) -> bool {
            false
        }
    }

    /// Runs the transmit task on `writer` for one frame with `not_after`; what it reported.
    async fn transmit_one(writer: QueueFull, not_after: Option<std::time::Instant>) -> CanInput {
        let (tx, rx) = mpsc::channel(1);
        let (in_tx, mut in_rx) = mpsc::channel(1);
        let cancel = CancellationToken::new();
        let queued = Arc::new(AtomicUsize::new(1));
        let task = tokio::spawn(transmit(
            rx,
            queued.clone(),
            writer,
            in_tx,
            None,
            cancel.clone(),
        ));
        let packet = Packet::command(
            NodeId::new_sc(0x111).unwrap(),
            Message::Identify { seq: 1, seconds: 1 },
        );
        let owner = ihex_gateway_core::bridge::FrameOwner::Command;
        tx.send(Transmit {
            packet,
            not_after,
            owner,
        })
        .await
        .unwrap();
        let report = in_rx.recv().await.unwrap();
        assert_eq!(
            queued.load(Ordering::Relaxed),
            0,
            "the task is done with it"
        );
        cancel.cancel();
        task.await.unwrap();
        report
    }

    #[tokio::test]
    async fn a_full_interface_queue_is_retried_until_it_has_room() {
        let attempts = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let writer = QueueFull {
            full_for: 3,
            attempts: attempts.clone(),
        };
        let later = std::time::Instant::now() + Duration::from_secs(10);
        match transmit_one(writer, Some(later)).await {
            CanInput::Transmitted(p) => assert_eq!(p.dest, NodeId::new_sc(0x111).unwrap()),
            other => panic!("{other:?}"),
        }
        assert_eq!(attempts.load(std::sync::atomic::Ordering::Relaxed), 4);
    }

    #[tokio::test]
    async fn a_frame_is_withdrawn_when_its_deadline_passes_in_a_full_queue() {
        let attempts = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let writer = QueueFull {
            full_for: usize::MAX,
            attempts: attempts.clone(),
        };
        let soon = std::time::Instant::now() + Duration::from_millis(20);
        assert!(matches!(
            transmit_one(writer, Some(soon)).await,
            CanInput::Withdrawn(_)
        ));
        assert!(
            attempts.load(std::sync::atomic::Ordering::Relaxed) > 1,
            "retried"
        );
    }

    #[tokio::test]
    async fn a_queue_that_stays_full_fails_the_frame() {
        let writer = QueueFull {
            full_for: usize::MAX,
            attempts: Arc::default(),
        };
        match transmit_one(writer, None).await {
            CanInput::SendFailed(_, why) => assert_eq!(why, "transmit queue full (ENOBUFS)"),
            other => panic!("{other:?}"),
        }
    }

    /// A transmitter whose link takes frames at once while `open` says so, recording them.
    fn recording(
        open: Arc<std::sync::atomic::AtomicBool>,
    ) -> (
        Transmitter,
        mpsc::Receiver<Transmit>,
        Arc<std::sync::Mutex<Vec<CanFrame>>>,
    ) {
        let (queue, rx) = mpsc::channel(2);
        let written = Arc::new(std::sync::Mutex::new(Vec::new()));
        let w = written.clone();
        let write_now: WriteNow = Box::new(move |f: &CanFrame| {
            open.load(Ordering::Relaxed).then(|| {
                w.lock().unwrap().push(*f);
                Handed::Written
            })
        });
        let t = Transmitter {
            queue,
            queued: Arc::default(),
            write_now: Some(write_now),
        };
        (t, rx, written)
    }

    fn led(seq: u8, not_after: Option<Instant>) -> Transmit {
        let packet = Packet::command(
            NodeId::new_sc(0x111).unwrap(),
            Message::Identify { seq, seconds: 1 },
        );
        let owner = ihex_gateway_core::bridge::FrameOwner::Command;
        Transmit {
            packet,
            not_after,
            owner,
        }
    }

    /// A link that is busy while `busy` says so, recording what it was sent.
    #[derive(Clone, Default)]
    struct Jammed {
        busy: Arc<std::sync::atomic::AtomicBool>,
        sent: Arc<std::sync::Mutex<Vec<CanFrame>>>,
    }

    impl FrameSender for Jammed {
        fn send(&self, frame: CanFrame) -> Result<(), String> {
            self.sent.lock().unwrap().push(frame);
            Ok(())
        }

        fn busy_for(&self) -> Option<Duration> {
            self.busy
                .load(Ordering::Relaxed)
                .then_some(Duration::from_millis(1))
        }
    }

    fn jammed() -> (LinkWriter<Jammed>, Jammed, CanFrame) {
        let link = Jammed::default();
        link.busy.store(true, Ordering::Relaxed);
        let frame = led(1, None).packet.to_frame::<CanFrame>().unwrap();
        (LinkWriter(link.clone()), link, frame)
    }

    #[tokio::test]
    async fn a_busy_link_gets_the_frame_once_it_is_free() {
        let (writer, link, frame) = jammed();
        let busy = link.busy.clone();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(30)).await;
            busy.store(false, Ordering::Relaxed);
        });
        let start = Instant::now();
        assert!(writer.write(frame, None).await.is_ok());
        assert!(start.elapsed() >= Duration::from_millis(30), "did not wait");
        assert_eq!(*link.sent.lock().unwrap(), [frame]);
    }

    #[tokio::test]
    async fn a_frame_whose_time_ends_while_the_link_is_busy_is_late_and_not_written() {
        let (writer, link, frame) = jammed();
        let soon = tokio::time::Instant::now() + Duration::from_millis(20);
        assert!(matches!(
            writer.write(frame, Some(soon)).await,
            Err(WriteError::Late)
        ));
        assert!(link.sent.lock().unwrap().is_empty());
    }

    #[tokio::test]
    async fn a_link_busy_for_good_gets_the_frame_after_the_longest_wait() {
        let (writer, link, frame) = jammed();
        let start = Instant::now();
        assert!(writer.write(frame, None).await.is_ok());
        assert!(start.elapsed() >= BUSY_WAIT_MAX);
        assert_eq!(link.sent.lock().unwrap().len(), 1);
    }

    #[tokio::test]
    async fn a_busy_link_takes_no_frame_at_once_the_transmit_task_writes_it_when_free() {
        struct Link(Jammed);
        impl FrameLink for Link {
            type Sender = Jammed;
            fn sender(&self) -> Jammed {
                self.0.clone()
            }
            async fn recv(&mut self) -> Option<CanFrame> {
                std::future::pending().await
            }
        }
        let (_, link, _) = jammed();
        let (queue, rx) = mpsc::channel(4);
        let queued = Arc::new(AtomicUsize::new(0));
        let (in_tx, mut in_rx) = mpsc::channel(4);
        let mut tasks = JoinSet::new();
        let cancel = CancellationToken::new();
        let start = CanLink::frames("jammed", Link(link.clone())).start;
        let write_now = start(rx, queued.clone(), in_tx, &mut tasks, cancel.clone());
        let tx = Transmitter {
            queue,
            queued,
            write_now: Some(write_now),
        };
        assert_eq!(
            tx.send(led(1, None), Instant::now()).unwrap(),
            Handed::Queued
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(link.sent.lock().unwrap().is_empty(), "written while busy");
        link.busy.store(false, Ordering::Relaxed);
        let report = tokio::time::timeout(Duration::from_secs(1), in_rx.recv())
            .await
            .expect("no report");
        assert!(
            matches!(report, Some(CanInput::Transmitted(_))),
            "{report:?}"
        );
        assert_eq!(link.sent.lock().unwrap().len(), 1);
        assert_eq!(
            tx.send(led(2, None), Instant::now()).unwrap(),
            Handed::Transmitted
        );
        cancel.cancel();
    }

    #[test]
    fn frames_are_written_at_once_until_one_has_to_wait_then_queued_in_order() {
        let open = Arc::new(std::sync::atomic::AtomicBool::new(true));
        let (tx, mut rx, written) = recording(open.clone());
        let now = Instant::now();
        assert_eq!(tx.send(led(1, None), now).unwrap(), Handed::Written);
        assert_eq!(written.lock().unwrap().len(), 1);
        // The link refuses one (its queue is full): it and every later frame wait their turn
        // behind it, even once the link would take them again.
        open.store(false, Ordering::Relaxed);
        assert_eq!(tx.send(led(2, None), now).unwrap(), Handed::Queued);
        open.store(true, Ordering::Relaxed);
        assert_eq!(tx.send(led(3, None), now).unwrap(), Handed::Queued);
        assert_eq!(written.lock().unwrap().len(), 1, "nothing overtook frame 2");
        // The queue (the window's room) is full: an error, and the count stays true.
        assert!(matches!(
            tx.send(led(4, None), now),
            Err(mpsc::error::TrySendError::Full(_))
        ));
        assert_eq!(tx.queued.load(Ordering::Relaxed), 2);
        for seq in [2, 3] {
            let t = rx.try_recv().unwrap();
            assert_eq!(t.packet, led(seq, None).packet);
            // What the transmit task does once it wrote it.
            tx.queued.fetch_sub(1, Ordering::AcqRel);
        }
        assert_eq!(tx.send(led(5, None), now).unwrap(), Handed::Written);
        assert_eq!(written.lock().unwrap().len(), 2);
    }

    #[test]
    fn a_frame_past_its_deadline_goes_to_the_task_to_be_withdrawn() {
        let open = Arc::new(std::sync::atomic::AtomicBool::new(true));
        let (tx, mut rx, written) = recording(open);
        let now = Instant::now();
        assert_eq!(tx.send(led(1, Some(now)), now).unwrap(), Handed::Queued);
        assert!(written.lock().unwrap().is_empty());
        assert!(rx.try_recv().is_ok());
    }

    #[test]
    fn drop_counters_are_read_from_sysfs() {
        assert_eq!(interface_drops("ihexnone0"), 0);
        if let Ok(s) = std::fs::read_to_string("/sys/class/net/lo/statistics/rx_dropped") {
            let dropped: u64 = s.trim().parse().unwrap();
            assert!(interface_drops("lo") >= dropped);
        }
    }

    #[test]
    fn missing_interfaces_are_not_up() {
        if std::path::Path::new("/sys/class/net/lo/flags").exists() {
            assert!(interface_up("lo"));
            assert!(!interface_up("ihexnone0"));
        }
    }
}
