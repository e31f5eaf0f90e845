//! The demo (cargo feature `demo`, on by default): the embedded MQTT broker ([`broker`]), the
//! simulated island (the `sim-node` library on an in-memory bus, plugged into the shell's CAN tasks
//! as a [`FrameLink`]), its control client on the `ihex/sim` topic ([`sim`]) and the start-up
//! [`banner`]. None of it is linked into a build with `--no-default-features` (the Pi's).
//!
//! The simulator never blocks the gateway: it runs on its own tasks, and its control messages come
//! through its own MQTT client, not through the gateway's core.

pub mod banner;
pub mod broker;
pub mod sim;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use ihex_proto::filter;
use sim_node::{
    bus::{MemBus, MemEndpoint, MemSender},
    link::Link as SimLink,
    Island, IslandDesc, IslandHandle,
};
use socketcan::CanFrame;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tracing::info;

use crate::{
    can::{CanLink, FrameLink, FrameSender},
    config::{Broker, Config, Link},
    error::GatewayError,
};

/// The island the demo runs when no `--island-file` is given: two static elements, a mobile element
/// docked on `111` port 3 and one waiting to be docked.
pub const BUILTIN_ISLAND: &str = r#"
[[static]]
id = "111"
ports = 6

[[static]]
id = "112"
ports = 6

[[mobile]]
id = "2"
port = 0
dock = { static = "111", port = 3 }

[[mobile]]
id = "3"
port = 1
"#;

/// Loads an island description: the file, or [`BUILTIN_ISLAND`].
pub fn load_island(island_file: Option<&Path>) -> Result<IslandDesc, GatewayError> {
    let desc = match island_file {
        Some(p) => IslandDesc::load(p),
        None => IslandDesc::parse(BUILTIN_ISLAND),
    };
    desc.map_err(|e| GatewayError::Sim(e.to_string()))
}

/// The positions (`hex`) an island description gives its static elements.
pub fn island_layout(desc: &IslandDesc) -> crate::config::web::Layout {
    desc.statics
        .iter()
        .filter_map(|s| s.hex.map(|(q, r)| (s.id, crate::config::web::Hex { q, r })))
        .collect()
}

/// The gateway's endpoint on the simulated island's in-memory bus, with the clock that paces what
/// it sends.
struct MemLink(MemEndpoint, Arc<BusClock>);

/// Transmit half of [`MemLink`].
struct MemLinkSender(MemSender, Arc<BusClock>);

impl FrameLink for MemLink {
    type Sender = MemLinkSender;

    fn sender(&self) -> MemLinkSender {
        MemLinkSender(self.0.sender(), self.1.clone())
    }

    async fn recv(&mut self) -> Option<CanFrame> {
        let frame = self.0.recv().await?;
        // The island's answers share the bus with the gateway's frames.
        self.1.take_frame(&frame, Instant::now());
        Some(frame)
    }
}

impl FrameSender for MemLinkSender {
    fn send(&self, frame: CanFrame) -> Result<(), String> {
        self.1.take_frame(&frame, Instant::now());
        self.0.try_send(frame).map_err(|e| e.to_string())
    }

    fn busy_for(&self) -> Option<Duration> {
        let booked = self.1.booked_beyond(Instant::now());
        if booked > BOOK_AHEAD {
            // Wake with half the window still booked: the bus never idles, and each wake-up writes
            // half a window of frames (about 19 at 500 kbit/s), not one.
            return Some(booked - BOOK_AHEAD / 2);
        }
        (self.0.backlog() >= SIM_BACKLOG).then_some(BACKLOG_POLL)
    }
}

/// Frames the simulated island may have unread before the gateway waits, whatever the clock says:
/// far below what an endpoint of the in-memory bus may fall behind before it loses frames
/// ([`MemBus::DEFAULT_CAPACITY`]).
const SIM_BACKLOG: usize = 64;
/// How often a frame waiting for the island to read its backlog looks again.
const BACKLOG_POLL: Duration = Duration::from_millis(1);

/// Bus time the gateway may have booked ahead of now before its next frame waits, as a kernel's
/// transmit queue takes a few dozen frames at once: about 38 frames at 500 kbit/s. Together with
/// the frames the core keeps queued (half its transmit queue), well below the 256 unanswered
/// commands an element may have.
const BOOK_AHEAD: Duration = Duration::from_millis(10);

/// When the simulated bus is free of the gateway's frames: nothing paces a sender on an in-memory
/// bus, so without this a burst of commands reached the island as fast as the gateway could write
/// them, piled up unread and unanswered, and was refused (256 unanswered commands to one element)
/// or lost (an endpoint that fell 1,024 frames behind). Each frame the gateway writes or reads
/// books its bits (without stuff bits) at the configured bit rate, as arbitration and the bit rate
/// make a real island's gateway wait (frames between elements that the gateway does not read book
/// nothing); the frames behind wait in the transmit queue, and the commands behind those at the
/// broker.
#[derive(Debug)]
struct BusClock {
    origin: Instant,
    /// Nanoseconds from `origin` at which the last booked frame ends.
    free_at: AtomicU64,
    bitrate: u64,
}

impl BusClock {
    fn new(bitrate: u32, now: Instant) -> BusClock {
        BusClock {
            origin: now,
            free_at: AtomicU64::new(0),
            bitrate: u64::from(bitrate.max(1)),
        }
    }

    fn nanos(&self, t: Instant) -> u64 {
        u64::try_from(t.saturating_duration_since(self.origin).as_nanos()).unwrap_or(u64::MAX)
    }

    /// Books `frame`'s bits (without stuff bits) from when the bus is free.
    fn take_frame(&self, frame: &CanFrame, now: Instant) {
        use embedded_can::Frame;
        self.take(ihex_proto::bus::frame_bits(frame.dlc() as u8), now);
    }

    /// Books `bits` on the bus from when it is free (now at the earliest).
    fn take(&self, bits: u32, now: Instant) {
        let now = self.nanos(now);
        let length = u64::from(bits) * 1_000_000_000 / self.bitrate;
        let _ = self
            .free_at
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |free| {
                Some(free.max(now).saturating_add(length))
            });
    }

    /// Bus time booked beyond `now`.
    fn booked_beyond(&self, now: Instant) -> Duration {
        let now = self.nanos(now);
        Duration::from_nanos(self.free_at.load(Ordering::Acquire).saturating_sub(now))
    }
}

/// A running simulated island and its control client (subscribed, not yet running).
struct SimIsland {
    handle: IslandHandle,
    /// Taken when the gateway runs.
    control: Option<sim::Control>,
}

/// What the demo adds to a gateway, built in two steps before the gateway runs: [`Demo::prepare`]
/// (the island file read, the broker accepting) and [`Demo::start_island`] (the island booted, its
/// control client subscribed).
pub struct Demo {
    broker: Option<std::net::SocketAddr>,
    /// The island to simulate, and the file it came from.
    desc: Option<(IslandDesc, Option<PathBuf>)>,
    island: Option<SimIsland>,
}

impl Demo {
    /// Reads the island file and starts the embedded broker, whichever of the two `config` asks
    /// for: the start-up errors a person most often meets (a typo in the file, port 1883 taken)
    /// come before anything else has started or said anything.
    pub async fn prepare(config: &Config) -> Result<Demo, GatewayError> {
        let desc = match &config.can.link {
            Link::Simulated { island_file } => {
                Some((load_island(island_file.as_deref())?, island_file.clone()))
            }
            Link::SocketCan(_) => None,
        };
        let broker = match &config.mqtt.broker {
            Broker::Embedded { listen } => {
                let listen = *listen;
                tokio::task::spawn_blocking(move || broker::start(listen))
                    .await
                    .map_err(|e| GatewayError::Task(e.to_string()))??;
                info!(%listen, "embedded MQTT broker ready");
                Some(listen)
            }
            Broker::External { .. } => None,
        };
        Ok(Demo {
            broker,
            desc,
            island: None,
        })
    }

    /// Boots the simulated island, when there is one, and subscribes its control client; returns
    /// the gateway's CAN link to it.
    pub async fn start_island(&mut self, config: &Config) -> Result<Option<CanLink>, GatewayError> {
        let Some((desc, island_file)) = &self.desc else {
            return Ok(None);
        };
        let bus = MemBus::new();
        // Created before the island starts, so no boot frame is missed.
        let endpoint = bus.endpoint();
        endpoint.set_filters(&filter::gateway_filters());
        let handle =
            Island::start(desc, SimLink::Mem(bus)).map_err(|e| GatewayError::Sim(e.to_string()))?;
        info!(
            statics = desc.statics.len(),
            mobiles = desc.mobiles.len(),
            file = island_file
                .as_ref()
                .map_or("built-in".into(), |f| f.display().to_string()),
            "simulated island started"
        );
        let control = sim::Control::connect(config, handle.clone()).await?;
        self.island = Some(SimIsland {
            handle,
            control: Some(control),
        });
        let clock = Arc::new(BusClock::new(config.can.bitrate, Instant::now()));
        Ok(Some(CanLink::frames(
            "simulated island",
            MemLink(endpoint, clock),
        )))
    }

    /// Positions of static elements the island file gives, for the island view.
    pub fn layout(&self) -> crate::config::web::Layout {
        self.desc
            .as_ref()
            .map(|(desc, _)| island_layout(desc))
            .unwrap_or_default()
    }

    /// Starts the island's control client and prints the banner (embedded broker + island), with
    /// the island view's and the SiLA server's addresses when they run.
    pub fn spawn(
        &mut self,
        config: &Config,
        tasks: &mut JoinSet<()>,
        cancel: CancellationToken,
        view_url: Option<&str>,
        sila_url: Option<&str>,
    ) {
        let (Some(island), Some((desc, file))) = (&mut self.island, &self.desc) else {
            return;
        };
        if let Some(control) = island.control.take() {
            tasks.spawn(control.run(cancel));
        }
        if let Some(listen) = self.broker {
            let log = crate::log::current_file(&config.log, time::OffsetDateTime::now_utc());
            let host = listen.ip().to_string();
            let text = banner::banner(&banner::Banner {
                topics: &config.topics,
                host: &host,
                port: listen.port(),
                desc,
                file: file.as_deref(),
                view_url,
                sila_url,
                log: log.as_deref(),
            });
            println!("{text}");
        }
    }

    /// Stops the simulated island.
    pub async fn shutdown(self) {
        if let Some(island) = self.island {
            island.handle.shutdown().await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::web::Hex;

    #[tokio::test]
    async fn the_link_is_busy_beyond_its_window_or_while_the_island_has_not_read() {
        let bus = MemBus::new();
        let island = bus.endpoint();
        let clock = Arc::new(BusClock::new(500_000, Instant::now()));
        let link = MemLinkSender(bus.endpoint().sender(), clock.clone());
        let frame = ihex_proto::Packet::command(
            ihex_proto::NodeId::new_sc(0x111).unwrap(),
            ihex_proto::Message::Identify { seq: 1, seconds: 1 },
        )
        .to_frame::<CanFrame>()
        .unwrap();
        assert_eq!(link.busy_for(), None);
        // Each frame sent books its bits: 262 µs for 8 data bytes at 500 kbit/s.
        link.send(frame).unwrap();
        let booked = clock.booked_beyond(Instant::now());
        assert!(booked > Duration::ZERO && booked <= Duration::from_micros(262));
        // 40 frames' time booked (10.5 ms, beyond the window): wait until half the window is left.
        clock.take(40 * ihex_proto::bus::frame_bits(8), Instant::now());
        let before = clock.booked_beyond(Instant::now());
        let wait = link.busy_for().expect("busy");
        let after = clock.booked_beyond(Instant::now());
        assert!(before > BOOK_AHEAD);
        assert!(
            after.saturating_sub(BOOK_AHEAD / 2) <= wait && wait <= before - BOOK_AHEAD / 2,
            "{after:?} {wait:?} {before:?}"
        );
        let sent = 1;
        // The bus clock idle again, but the island has read none of them.
        clock.free_at.store(0, Ordering::Relaxed);
        for _ in sent..SIM_BACKLOG {
            assert_eq!(link.busy_for(), None);
            link.0.try_send(frame).unwrap();
        }
        assert_eq!(link.busy_for(), Some(BACKLOG_POLL));
        drop(island);
        assert_eq!(
            link.busy_for(),
            None,
            "read (or gone), nothing holds the link"
        );
    }

    #[tokio::test]
    async fn a_frame_the_gateway_reads_books_the_bus_too() {
        let bus = MemBus::new();
        let island = bus.endpoint();
        let clock = Arc::new(BusClock::new(500_000, Instant::now()));
        let mut link = MemLink(bus.endpoint(), clock.clone());
        let ack = ihex_proto::Packet::command(
            ihex_proto::NodeId::new_sc(0x111).unwrap(),
            ihex_proto::Message::Identify { seq: 1, seconds: 1 },
        )
        .to_frame::<CanFrame>()
        .unwrap();
        island.send(ack).await.unwrap();
        let before = Instant::now();
        assert_eq!(link.recv().await, Some(ack));
        let booked = clock.booked_beyond(before);
        assert!(
            booked > Duration::ZERO && booked <= Duration::from_micros(262),
            "{booked:?}"
        );
    }

    #[test]
    fn the_bus_clock_books_each_frame_from_when_the_bus_is_free() {
        let t0 = Instant::now();
        let clock = BusClock::new(500_000, t0);
        // 131 bits at 500 kbit/s: 262 µs a frame.
        assert_eq!(clock.booked_beyond(t0), Duration::ZERO);
        for _ in 0..8 {
            clock.take(131, t0);
        }
        assert_eq!(clock.booked_beyond(t0), Duration::from_micros(8 * 262));
        assert_eq!(
            clock.booked_beyond(t0 + Duration::from_micros(262)),
            Duration::from_micros(7 * 262),
            "one frame later, one fewer booked"
        );
        assert_eq!(
            clock.booked_beyond(t0 + Duration::from_secs(1)),
            Duration::ZERO
        );
        // A bus idle since: the next frame starts now, not where the last one ended.
        let later = t0 + Duration::from_secs(1);
        clock.take(131, later);
        assert_eq!(clock.booked_beyond(later), Duration::from_micros(262));
    }

    #[test]
    fn the_island_file_places_its_hexagons() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../examples/islands/bench.toml"
        );
        let layout = island_layout(&load_island(Some(Path::new(path))).unwrap());
        let id = |s: &str| s.parse::<ihex_proto::NodeId>().unwrap();
        // The flower: seven placed, the factory-fresh board left to the automatic arrangement.
        assert_eq!(layout.len(), 7);
        assert_eq!(layout[&id("100")], Hex { q: 0, r: 0 });
        assert_eq!(layout[&id("101")], Hex { q: 0, r: -1 });
        assert!(!layout.contains_key(&id("1f0")));
        // The built-in island places nothing.
        assert!(island_layout(&load_island(None).unwrap()).is_empty());
    }
}
