//! Virtual iHEX sub-controllers: each one is the real [`ihex_sc_core::Node`], wired to a bus.
//!
//! * [`board`] — a simulated SC's flash and bootloader (embassy-boot's own swap over an in-memory
//!   NOR flash, with power cuts on demand) and the update half of its adapter.
//! * [`bus`] — an in-memory CAN bus ([`bus::MemBus`]) for demos and fast tests.
//! * [`link`] — one endpoint per node on SocketCAN (`vcan0`, `can0`) or a [`bus::MemBus`].
//! * [`desc`] — the island description file (TOML).
//! * [`console`] — the binary's control commands and change lines.
//! * [`island`] — a running island ([`Island::start`] → [`IslandHandle`]): power through dock relays,
//!   signal loops, docking, power cycles, nodes on and off the bus, UART, actuator state and events.
//!
//! ```no_run
//! # async fn demo() -> Result<(), Box<dyn std::error::Error>> {
//! use ihex_proto::NodeId;
//! use sim_node::{bus::MemBus, link::Link, Island, IslandDesc};
//!
//! let desc = IslandDesc::parse("[[static]]\nid = \"111\"\n[[mobile]]\nid = \"2\"\n")?;
//! let bus = MemBus::new();
//! let mut gateway = bus.endpoint(); // play the gateway on the same bus
//! let island = Island::start(&desc, Link::Mem(bus.clone()))?;
//! let (mobile, host) = (NodeId::new_sc(0x2).unwrap(), NodeId::new_sc(0x111).unwrap());
//! island.dock(mobile, host, 3).await?; // the static SC reports DockDetected to the gateway
//! let frame = gateway.recv().await;
//! # drop(frame); Ok(()) }
//! ```
#![warn(missing_docs)]
#![forbid(unsafe_code)]

pub mod board;
pub mod bus;
pub mod console;
pub mod desc;
pub mod island;
pub mod link;

pub use desc::IslandDesc;
pub use island::{Island, IslandError, IslandEvent, IslandHandle, NodeView};
pub use link::{Link, LinkError};
