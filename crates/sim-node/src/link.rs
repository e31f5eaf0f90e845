//! Where a virtual node's frames go: one endpoint per node on a SocketCAN interface or a [`MemBus`].
//!
//! A [`Link`] names the bus; [`Link::open`] gives a node its own endpoint as a sending half
//! ([`LinkTx`], which also sets the acceptance filters) and a receiving half ([`LinkRx`]), so one task
//! can wait for frames while another sends. On SocketCAN each endpoint is its own raw socket: the
//! kernel carries frames between the virtual nodes and any other program on the interface, and a
//! socket never receives its own frames, exactly like a controller on a real bus.
//!
//! A SocketCAN endpoint survives its interface going down and up (or being deleted and created
//! again): when a read fails, or a write fails with a link error, the receiving half reopens the
//! socket with a back-off ([`REOPEN_MIN`] doubling up to [`REOPEN_MAX`], reset by the next frame
//! received), reinstalls the filters in force and carries on; the sending half writes on the
//! socket of the moment. Frames sent while the interface is down are lost (the send fails), as
//! on a controller whose bus is gone.

use std::{
    sync::{Arc, Mutex},
    time::Duration,
};

use ihex_proto::filter::{self, Filter, FilterError};
use socketcan::{CanFilter, CanFrame, SocketOptions};
use tokio::sync::Notify;

use crate::bus::{BusError, MemBus, MemEndpoint, MemFilterHandle, MemSender};

/// Why a link operation failed.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// Opening, configuring, reading or writing the SocketCAN socket failed.
    // The OS error is in the message rather than `source()`, so that `%err` in a log line says it all.
    #[error("SocketCAN interface {iface}: {error}")]
    Io {
        /// Interface name.
        iface: String,
        /// The OS error.
        error: std::io::Error,
    },
    /// The in-memory bus is gone.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// The filters cannot be installed on a kernel socket.
    #[error("filters cannot be installed: {0}")]
    Filter(FilterError),
}

/// First reopen delay after a SocketCAN endpoint lost its interface; doubles up to [`REOPEN_MAX`].
pub const REOPEN_MIN: Duration = Duration::from_millis(100);
/// Longest reopen delay.
pub const REOPEN_MAX: Duration = Duration::from_secs(5);

/// A bus that virtual nodes (and tests playing the gateway) attach to.
#[derive(Clone, Debug)]
pub enum Link {
    /// A SocketCAN interface such as `vcan0`.
    SocketCan(String),
    /// An in-memory bus.
    Mem(MemBus),
}

impl Link {
    /// A SocketCAN interface by name.
    pub fn socketcan(iface: impl Into<String>) -> Self {
        Link::SocketCan(iface.into())
    }

    /// A short description for logs (`vcan0` or `mem`).
    pub fn name(&self) -> &str {
        match self {
            Link::SocketCan(i) => i,
            Link::Mem(_) => "mem",
        }
    }

    /// A new endpoint on the bus, receiving everything until filters are set.
    pub fn open(&self) -> Result<(LinkTx, LinkRx), LinkError> {
        let filters = Arc::new(Mutex::new(Vec::new()));
        match self {
            Link::SocketCan(iface) => {
                let sock = open_socket(iface, &[])?;
                let can = Arc::new(CanLink {
                    iface: iface.clone(),
                    slot: Mutex::new(Slot {
                        sock: Arc::new(sock),
                        filters: Vec::new(),
                    }),
                    failed: Notify::new(),
                });
                let tx = LinkTx {
                    inner: TxInner::Can(can.clone()),
                    filters: filters.clone(),
                };
                let rx = LinkRx {
                    inner: RxInner::Can {
                        can,
                        backoff: REOPEN_MIN,
                        lost: false,
                    },
                    filters,
                };
                Ok((tx, rx))
            }
            Link::Mem(bus) => {
                let ep = bus.endpoint();
                let tx = LinkTx {
                    inner: TxInner::Mem {
                        tx: ep.sender(),
                        filters: ep.filter_handle(),
                    },
                    filters: filters.clone(),
                };
                Ok((
                    tx,
                    LinkRx {
                        inner: RxInner::Mem(ep),
                        filters,
                    },
                ))
            }
        }
    }
}

/// Opens a raw socket on `iface` with these acceptance filters (kernel plan of
/// [`ihex_proto::filter::to_kernel`]; an empty set receives everything).
fn open_socket(iface: &str, filters: &[Filter]) -> Result<socketcan::tokio::CanSocket, LinkError> {
    let io = |error| LinkError::Io {
        iface: iface.to_owned(),
        error,
    };
    let sock = socketcan::tokio::CanSocket::open(iface).map_err(io)?;
    if !filters.is_empty() {
        install(&sock, iface, filters)?;
    }
    Ok(sock)
}

/// Installs `filters` on a socket as kernel filters.
fn install(
    sock: &socketcan::tokio::CanSocket,
    iface: &str,
    filters: &[Filter],
) -> Result<(), LinkError> {
    let plan = filter::to_kernel(filters).map_err(LinkError::Filter)?;
    let io = |error| LinkError::Io {
        iface: iface.to_owned(),
        error,
    };
    let kf: Vec<CanFilter> = plan
        .filters
        .iter()
        .map(|k| CanFilter::new(k.can_id, k.can_mask))
        .collect();
    sock.set_join_filters(plan.join).map_err(io)?;
    sock.set_filters(&kf).map_err(io)
}

/// One SocketCAN endpoint, shared by its two halves.
#[derive(Debug)]
struct CanLink {
    iface: String,
    /// The socket of the moment and the filters installed on it: swapped together, so a reopen
    /// and a change of filters cannot cross.
    slot: Mutex<Slot>,
    /// A write failed with a link error: the receiving half should reopen.
    failed: Notify,
}

#[derive(Debug)]
struct Slot {
    sock: Arc<socketcan::tokio::CanSocket>,
    filters: Vec<Filter>,
}

impl CanLink {
    fn slot(&self) -> std::sync::MutexGuard<'_, Slot> {
        self.slot.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn socket(&self) -> Arc<socketcan::tokio::CanSocket> {
        self.slot().sock.clone()
    }

    /// A fresh socket with the filters in force replaces the current one.
    fn reopen(&self) -> Result<(), LinkError> {
        let mut slot = self.slot();
        let sock = open_socket(&self.iface, &slot.filters)?;
        slot.sock = Arc::new(sock);
        Ok(())
    }
}

/// True for write errors that mean the interface is down or gone, not a full queue.
fn is_link_error(e: &std::io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::ENETDOWN | libc::ENODEV | libc::ENXIO | libc::EBADF)
    )
}

#[derive(Debug)]
enum TxInner {
    Can(Arc<CanLink>),
    Mem {
        tx: MemSender,
        filters: MemFilterHandle,
    },
}

/// Sending half of an endpoint; also owns its acceptance filters.
#[derive(Debug)]
pub struct LinkTx {
    inner: TxInner,
    // The filter set in force, checked in software too: a kernel plan may be a superset.
    filters: Arc<Mutex<Vec<Filter>>>,
}

impl LinkTx {
    /// Transmits a frame.
    pub async fn send(&self, frame: CanFrame) -> Result<(), LinkError> {
        match &self.inner {
            TxInner::Can(can) => {
                let sock = can.socket();
                sock.write_frame(frame).await.map_err(|error| {
                    if is_link_error(&error) {
                        can.failed.notify_one();
                    }
                    LinkError::Io {
                        iface: can.iface.clone(),
                        error,
                    }
                })
            }
            TxInner::Mem { tx, .. } => Ok(tx.send(frame).await?),
        }
    }

    /// Installs acceptance filters (seed semantics, [`ihex_proto::filter::accepts`]); on SocketCAN
    /// as kernel filters via [`ihex_proto::filter::to_kernel`].
    pub fn set_filters(&self, filters: &[Filter]) -> Result<(), LinkError> {
        match &self.inner {
            TxInner::Can(can) => {
                let mut slot = can.slot();
                install(&slot.sock, &can.iface, filters)?;
                slot.filters = filters.to_vec();
            }
            TxInner::Mem { filters: f, .. } => f.set(filters),
        }
        let mut f = self.filters.lock().unwrap_or_else(|e| e.into_inner());
        f.clear();
        f.extend_from_slice(filters);
        Ok(())
    }
}

#[derive(Debug)]
enum RxInner {
    Can {
        can: Arc<CanLink>,
        /// Wait before the next reopen; back to [`REOPEN_MIN`] once a frame arrives.
        backoff: Duration,
        /// The interface was lost and no frame has arrived since (for logging once per outage).
        lost: bool,
    },
    Mem(MemEndpoint),
}

/// Receiving half of an endpoint.
#[derive(Debug)]
pub struct LinkRx {
    inner: RxInner,
    filters: Arc<Mutex<Vec<Filter>>>,
}

impl LinkRx {
    /// The next frame that passes the endpoint's filters. Error frames are passed on (the caller
    /// decides). On SocketCAN it waits through interface outages, reopening the socket (see the
    /// module docs); `Err` only when the in-memory bus is gone. Cancel-safe.
    pub async fn recv(&mut self) -> Result<CanFrame, LinkError> {
        loop {
            let frame = match &mut self.inner {
                RxInner::Can { can, backoff, lost } => {
                    let sock = can.socket();
                    let got = tokio::select! {
                        r = sock.read_frame() => r.map_err(|e| e.to_string()),
                        _ = can.failed.notified() => Err("a write failed with a link error".to_owned()),
                    };
                    match got {
                        Ok(frame) => {
                            if std::mem::take(lost) {
                                tracing::info!(iface = %can.iface, "CAN endpoint hears the bus again");
                            }
                            *backoff = REOPEN_MIN;
                            frame
                        }
                        Err(why) => {
                            reopen_after(can, backoff, lost, &why).await;
                            continue;
                        }
                    }
                }
                RxInner::Mem(ep) => ep.recv().await.ok_or(BusError::Closed)?,
            };
            let pass = matches!(frame, CanFrame::Error(_)) || {
                let f = self.filters.lock().unwrap_or_else(|e| e.into_inner());
                filter::accepts(&f, filter::word_of(&frame))
            };
            if pass {
                return Ok(frame);
            }
        }
    }
}

/// Waits out the back-off, then puts a fresh socket in place (if the interface lets us).
async fn reopen_after(can: &CanLink, backoff: &mut Duration, lost: &mut bool, why: &str) {
    if *lost {
        tracing::debug!(iface = %can.iface, %why, "CAN endpoint still without its interface");
    } else {
        tracing::warn!(iface = %can.iface, %why, "CAN endpoint lost its interface; reopening");
        *lost = true;
    }
    tokio::time::sleep(*backoff).await;
    *backoff = (*backoff * 2).min(REOPEN_MAX);
    if let Err(err) = can.reopen() {
        tracing::debug!(%err, "reopening failed; retrying");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::{filter::sc_filters, Message, NodeId, Packet};

    #[tokio::test]
    async fn mem_link_endpoints_talk_and_filter() {
        let link = Link::Mem(MemBus::new());
        let (gw_tx, mut gw_rx) = link.open().unwrap();
        let (node_tx, mut node_rx) = link.open().unwrap();
        let me = NodeId::new_sc(0x2).unwrap();
        node_tx.set_filters(&sc_filters(Some(me))).unwrap();
        let not_me = Packet::command(
            NodeId::new_sc(0x3).unwrap(),
            Message::HealthCheck { seq: 9 },
        );
        let to_me = Packet::command(me, Message::HealthCheck { seq: 7 });
        gw_tx.send(not_me.to_frame().unwrap()).await.unwrap();
        gw_tx.send(to_me.to_frame().unwrap()).await.unwrap();
        assert_eq!(
            Packet::from_frame(&node_rx.recv().await.unwrap()).unwrap(),
            to_me
        );
        let reply = Packet::report(
            me,
            Message::DockDetected {
                port: ihex_proto::Port::new(1).unwrap(),
            },
        );
        node_tx.send(reply.to_frame().unwrap()).await.unwrap();
        assert_eq!(
            Packet::from_frame(&gw_rx.recv().await.unwrap()).unwrap(),
            reply
        );
    }
}
