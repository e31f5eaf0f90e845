//! Where a virtual node's frames go: one endpoint per node on a SocketCAN interface or a [`MemBus`].
//!
//! A [`Link`] names the bus; [`Link::open`] gives a node its own endpoint as a sending half
//! ([`LinkTx`], which also sets the acceptance filters) and a receiving half ([`LinkRx`]), so one task
//! can wait for frames while another sends. On SocketCAN each endpoint is its own raw socket: the
//! kernel carries frames between the virtual nodes and any other program on the interface, and a
//! socket never receives its own frames, exactly like a controller on a real bus.

use std::sync::{Arc, Mutex};

use ihex_proto::filter::{self, Filter, FilterError};
use socketcan::{CanFilter, CanFrame, SocketOptions};

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
                let io = |error| LinkError::Io {
                    iface: iface.clone(),
                    error,
                };
                let sock = Arc::new(socketcan::tokio::CanSocket::open(iface).map_err(io)?);
                let tx = LinkTx {
                    inner: TxInner::Can {
                        sock: sock.clone(),
                        iface: iface.clone(),
                    },
                    filters: filters.clone(),
                };
                let rx = LinkRx {
                    inner: RxInner::Can {
                        sock,
                        iface: iface.clone(),
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

#[derive(Debug)]
enum TxInner {
    Can {
        sock: Arc<socketcan::tokio::CanSocket>,
        iface: String,
    },
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
            TxInner::Can { sock, iface } => {
                sock.write_frame(frame)
                    .await
                    .map_err(|error| LinkError::Io {
                        iface: iface.clone(),
                        error,
                    })
            }
            TxInner::Mem { tx, .. } => Ok(tx.send(frame).await?),
        }
    }

    /// Installs acceptance filters (seed semantics, [`ihex_proto::filter::accepts`]); on SocketCAN
    /// as kernel filters via [`ihex_proto::filter::to_kernel`].
    pub fn set_filters(&self, filters: &[Filter]) -> Result<(), LinkError> {
        match &self.inner {
            TxInner::Can { sock, iface } => {
                let plan = filter::to_kernel(filters).map_err(LinkError::Filter)?;
                let io = |error| LinkError::Io {
                    iface: iface.clone(),
                    error,
                };
                let kf: Vec<CanFilter> = plan
                    .filters
                    .iter()
                    .map(|k| CanFilter::new(k.can_id, k.can_mask))
                    .collect();
                sock.set_join_filters(plan.join).map_err(io)?;
                sock.set_filters(&kf).map_err(io)?;
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
        sock: Arc<socketcan::tokio::CanSocket>,
        iface: String,
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
    /// decides); `Err` on I/O failure or when the in-memory bus is gone. Cancel-safe.
    pub async fn recv(&mut self) -> Result<CanFrame, LinkError> {
        loop {
            let frame = match &mut self.inner {
                RxInner::Can { sock, iface } => {
                    sock.read_frame().await.map_err(|error| LinkError::Io {
                        iface: iface.clone(),
                        error,
                    })?
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
