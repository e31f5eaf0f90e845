//! The node state machine: inputs in, outputs queued, timers advanced; the contract is in the crate docs.

mod command;
mod ident;
mod retained;
mod state;
mod update;

pub use retained::RETAINED_WORDS;
pub use update::{
    FlashError, UpdateConfig, CHUNK_LEN, MAX_IMAGE_LEN, RESET_DELAY_MS, TRIAL_CONFIRM_MS,
};

use ihex_proto::{
    uart::{UartDecoder, UartError, UartReply},
    BootRole, BuzzerCommand, DockPartner, FaultCode, FirmwareVersion, HealthFlags, HealthReply,
    LedCommand, Message, NodeId, Packet, Port, ResetReason, Rgb, Uid, PROTOCOL_VERSION,
};

use crate::debounce::Debounce;
use crate::queue::OutputQueue;
use crate::{Actuators, BuzzerOutput, LedOutput, Millis};

/// A signal-loop level must stay unchanged this long before it counts (a bouncing contact = one event).
pub const DEBOUNCE_MS: u64 = 50;
/// A half-received UART request is dropped after this idle gap.
pub const UART_IDLE_RESET_MS: u64 = 100;
/// A mobile element waits this long after boot (or after being given an ID) for one of its own
/// signal loops to debounce closed before it hands-shakes with port 0. Longer than [`DEBOUNCE_MS`],
/// so a loop that is closed from the start is always seen in time.
pub const HANDSHAKE_SETTLE_MS: u64 = 200;
/// The LED while an identify runs: full white, blinking 500 ms at 50 %.
pub const IDENTIFY_LED: LedOutput = LedOutput {
    duty: Rgb::new(255, 255, 255),
    blink: Some((500, 50)),
};
/// The buzzer while an identify runs: 2 kHz, 100 ms beep every 500 ms, until the identify ends.
pub const IDENTIFY_BUZZER: BuzzerOutput = BuzzerOutput::Pattern {
    freq_hz: 2000,
    on_ms: 100,
    off_ms: 400,
    count: 0,
};

/// Port 0, evaluated at compile time.
const PORT0: Port = match Port::new(0) {
    Some(p) => p,
    None => panic!("port 0 exists"),
};

/// The firmware a node runs, as its adapter knows it; the core only reports it
/// (`StateReport::Firmware` and `ImageHash`).
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FirmwareIdentity {
    /// The running firmware's version.
    pub version: FirmwareVersion,
    /// The first 7 bytes of the running image's hash; all zero when unknown.
    pub image_hash: [u8; 7],
    /// Running a trial image that has not confirmed itself yet.
    pub trial: bool,
}

/// What a static element keeps of its docks across a reset it asked for itself (an update's swap
/// or revert): the relay, the confirmed ports and their links. The adapter saves it when the node
/// asks for [`Output::Reset`] (the firmware as a [`Retained::encode`] block in no-init RAM, which
/// survives a system reset but not a power cut; the simulator in its board) and hands it back with [`Node::restore`] after
/// that reset only, so a docked mobile element keeps its power and its docking through the update.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Retained {
    /// The relay was on.
    pub relay: bool,
    /// Ports the gateway had confirmed (bit n = port n).
    pub confirmed: u8,
    /// The mobile element linked to each confirmed port.
    pub links: [Option<DockPartner>; Port::COUNT as usize],
}

/// How a node is built and what it remembers across resets.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Config {
    /// Static element (on the bus, has dock ports) or mobile element (docks onto one).
    pub role: BootRole,
    /// Number of dock ports with a signal loop (`0..=8`).
    pub ports: u8,
    /// The MCU's 96-bit unique ID (CAN node-ID assignment selects by it).
    pub uid: Uid,
    /// The stored node ID; `None` for a factory-fresh board, which stays quiet until given one.
    pub node_id: Option<NodeId>,
    /// Why the node started (reported in the boot-up announcement).
    pub reset: ResetReason,
    /// The firmware it runs (reported on a state query); `trial` is cleared once the core has
    /// confirmed the image.
    pub firmware: FirmwareIdentity,
    /// What it needs to take firmware updates.
    pub update: UpdateConfig,
}

/// Something the adapter must do.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Output {
    /// Transmit this frame.
    Frame(Packet),
    /// Write these two bytes to the configuration UART.
    Uart([u8; 2]),
    /// Persist this node ID (flash); report a failure with [`Node::handle_store_failed`].
    StoreId(NodeId),
    /// Reconfigure the CAN acceptance filters: the node ID changed
    /// (use `ihex_proto::filter::sc_filters(node.node_id())`).
    FiltersChanged,
    /// Erase the DFU slot's pages that hold its first `len` bytes; report with
    /// [`Node::handle_fw_erased`].
    EraseDfu {
        /// Bytes from the slot's start (a multiple of [`CHUNK_LEN`]).
        len: u32,
    },
    /// Program `data` at `offset` of the (erased) DFU slot; report a failure with
    /// [`Node::handle_fw_write_failed`].
    WriteDfu {
        /// Offset in the slot (a multiple of [`CHUNK_LEN`]).
        offset: u32,
        /// The bytes.
        data: [u8; CHUNK_LEN],
    },
    /// Read `len` bytes of the DFU slot from `offset` back and hash them (SHA-512,
    /// `ihex_image::Hasher`); report with [`Node::handle_fw_hashed`].
    HashDfu {
        /// Offset in the slot.
        offset: u32,
        /// Bytes.
        len: u32,
    },
    /// Tell the bootloader to swap the DFU image in at the next reset (embassy-boot
    /// `mark_updated`); report with [`Node::handle_fw_marked`].
    MarkUpdated,
    /// Confirm the running image (embassy-boot `mark_booted`); report with
    /// [`Node::handle_fw_confirmed`].
    MarkBooted,
    /// Reset the chip (the bootloader then swaps a marked image in, or reverts one on trial).
    /// Nothing the core asks after this matters.
    Reset,
}

/// One sub-controller's complete behaviour.
#[derive(Debug)]
pub struct Node {
    /// Build-time facts; `node_id` is kept equal to the ID in force.
    config: Config,
    uart: UartDecoder,
    /// When the last UART byte arrived (meaningful while `uart` is pending).
    uart_last: Millis,
    /// Whether the last [`Output::StoreId`] came from a UART request (it then gets the error reply).
    store_from_uart: bool,
    /// Reset time, for the uptime.
    boot: Millis,
    queue: OutputQueue,
    loops: [Debounce; Port::COUNT as usize],
    /// Ports the gateway confirmed and that are still docked: the relay follows them.
    confirmed: u8,
    /// Per port, the mobile element the gateway linked to it; only while the port is confirmed.
    links: [Option<DockPartner>; Port::COUNT as usize],
    relay: bool,
    /// The commanded LED (identify overrides it while it runs), as commanded: reported as is.
    led: LedCommand,
    /// The commanded buzzer (identify overrides it while it runs); `Off` once a finite pattern ends.
    buzzer: BuzzerCommand,
    /// When a finite commanded buzzer pattern ends.
    buzzer_end: Option<Millis>,
    identify_until: Option<Millis>,
    /// A mobile element's pending handshake: the settle deadline.
    handshake_at: Option<Millis>,
    /// An ID was just put in force that calls for a new boot-up announcement.
    announce_due: bool,
    /// Selected by a CAN `AssignSelect` matching our UID head.
    selected: bool,
    tec: u8,
    rec: u8,
    error_passive: bool,
    bus_off: bool,
    bus_off_count: u32,
    /// The actuator state the adapter last saw through [`Node::actuators_changed`].
    shown: Option<Actuators>,
    /// Firmware update and trial boot.
    update: update::Update,
    /// After [`Node::restore`]: when every restored port must have debounced closed (else it is
    /// withdrawn: the mobile element left during the reset).
    restore_check_at: Option<Millis>,
}

impl Node {
    /// A node that has just reset at `now`. Queues the boot-up announcement (and, for a mobile
    /// element, schedules its handshake) unless it has no ID yet.
    pub fn new(config: Config, now: Millis) -> Self {
        let mut config = config;
        // A reserved ID in flash (corrupt or never written) is treated as no ID at all.
        config.node_id = config.node_id.filter(|id| id.is_sc());
        config.ports = config.ports.min(Port::COUNT);
        let mut node = Node {
            config,
            uart: UartDecoder::new(),
            uart_last: now,
            store_from_uart: false,
            boot: now,
            queue: OutputQueue::default(),
            loops: [Debounce::default(); Port::COUNT as usize],
            confirmed: 0,
            links: [None; Port::COUNT as usize],
            relay: false,
            led: LedCommand::Off,
            buzzer: BuzzerCommand::Off,
            buzzer_end: None,
            identify_until: None,
            handshake_at: None,
            announce_due: false,
            selected: false,
            tec: 0,
            rec: 0,
            error_passive: false,
            bus_off: false,
            bus_off_count: 0,
            shown: None,
            update: update::Update::new(config.firmware.trial, now),
            restore_check_at: None,
        };
        if node.config.node_id.is_some() {
            node.announce(now);
        }
        node
    }

    /// What to keep across a reset the node asks for ([`Retained`]); all off for a mobile element.
    pub fn retained(&self) -> Retained {
        Retained {
            relay: self.relay,
            confirmed: self.confirmed,
            links: self.links,
        }
    }

    /// Takes back what the node kept across the reset it asked for (call right after
    /// [`Node::new`] and the first loop levels, and only after a software reset: a power cut
    /// loses it). The relay is on again at once; a restored port is confirmed without a new
    /// `DockDetected`, and is withdrawn (`DockRemoved`, relay off if it was the last) unless its
    /// loop has debounced closed by [`DEBOUNCE_MS`] after the restore. Ignored by a node
    /// without a relay.
    pub fn restore(&mut self, retained: Retained, now: Millis) {
        self.advance(now);
        if !self.has_relay() {
            return;
        }
        let mask = if self.config.ports >= 8 {
            u8::MAX
        } else {
            (1u8 << self.config.ports) - 1
        };
        self.relay = retained.relay;
        self.confirmed = retained.confirmed & mask;
        for (i, link) in retained.links.iter().enumerate() {
            self.links[i] = link.filter(|_| self.confirmed & (1 << i) != 0);
        }
        if self.confirmed != 0 {
            // One tick past the debounce, so a loop reported closed at `now` has counted.
            self.restore_check_at = Some(now.add_ms(DEBOUNCE_MS + 1));
        }
    }

    /// The node ID in force, `None` while unconfigured.
    pub fn node_id(&self) -> Option<NodeId> {
        self.config.node_id
    }

    /// The node's configuration (role, ports, UID, ID).
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// A frame arrived (raw 29-bit ID and data, as received: the core decodes and validates it).
    /// `extended`/`remote` describe the frame's flags.
    pub fn handle_frame(
        &mut self,
        raw_id: u32,
        extended: bool,
        remote: bool,
        data: &[u8],
        now: Millis,
    ) {
        self.advance(now);
        self.on_frame(raw_id, extended, remote, data, now);
    }

    /// The current level of a dock port's signal loop (`closed` = pulled low = something docked).
    /// Call on every edge and/or periodically; the core debounces.
    pub fn handle_loop_level(&mut self, port: Port, closed: bool, now: Millis) {
        self.advance(now);
        if port.get() < self.config.ports {
            self.loops[port.get() as usize].input(closed, now);
            // A periodic caller may report a level that has already been stable long enough.
            self.advance(now);
        }
    }

    /// One byte from the configuration UART.
    pub fn handle_uart_byte(&mut self, byte: u8, now: Millis) {
        self.advance(now);
        self.on_uart_byte(byte, now);
    }

    /// The CAN controller's error counters and state, for health replies and fault reports.
    pub fn handle_can_status(&mut self, tec: u8, rec: u8, bus_off: bool, now: Millis) {
        self.advance(now);
        self.tec = tec;
        self.rec = rec;
        let passive = tec >= 128 || rec >= 128;
        if passive && !self.error_passive {
            let detail = (u32::from(tec) << 8) | u32::from(rec);
            self.fault(FaultCode::ErrorPassive, 0, detail);
        }
        self.error_passive = passive;
        if bus_off && !self.bus_off {
            self.bus_off_count = self.bus_off_count.saturating_add(1);
        } else if !bus_off && self.bus_off {
            // Reported on recovery: only then can the frame actually go out.
            self.fault(FaultCode::BusOff, 0, self.bus_off_count);
        }
        self.bus_off = bus_off;
    }

    /// Persisting the node ID failed: the core reports a fault (and answers UART with an error).
    pub fn handle_store_failed(&mut self, now: Millis) {
        self.advance(now);
        self.fault(FaultCode::ConfigStore, 0, 0);
        if self.store_from_uart {
            self.queue.push(Output::Uart(
                UartReply::Error(UartError::StoreFailed).encode(),
            ));
        }
    }

    /// The adapter finished a finite buzzer pattern.
    pub fn handle_buzzer_done(&mut self, now: Millis) {
        self.advance(now);
        // While identify runs the adapter plays the endless identify pattern, so a "done" can only
        // be a stale report about the commanded pattern, which the core ends on its own clock.
        if self.identify_until.is_none() && self.buzzer_end.is_some() {
            self.buzzer = BuzzerCommand::Off;
            self.buzzer_end = None;
        }
    }

    /// Advances timers (debounce, identify, UART idle, handshake) to `now`.
    pub fn tick(&mut self, now: Millis) {
        self.advance(now);
    }

    /// The latest time by which [`Node::tick`] must be called again, `None` if nothing is pending.
    pub fn poll_at(&self) -> Option<Millis> {
        let uart = self
            .uart
            .is_pending()
            .then(|| self.uart_last.add_ms(UART_IDLE_RESET_MS));
        self.loops[..self.config.ports as usize]
            .iter()
            .map(Debounce::deadline)
            .chain([
                uart,
                self.identify_until,
                self.buzzer_end,
                self.handshake_at,
                self.restore_check_at,
                self.update.deadline(),
            ])
            .flatten()
            .min()
    }

    /// Next queued output, `None` when drained.
    pub fn poll_output(&mut self) -> Option<Output> {
        self.queue.pop()
    }

    /// The effective actuator setting (identify overrides LED and buzzer while it runs).
    pub fn actuators(&self) -> Actuators {
        if self.identify_until.is_some() {
            Actuators {
                led: IDENTIFY_LED,
                buzzer: IDENTIFY_BUZZER,
                relay: self.relay,
            }
        } else {
            Actuators {
                led: command::led_output(self.led),
                buzzer: command::buzzer_output(self.buzzer),
                relay: self.relay,
            }
        }
    }

    /// True once after every change of [`Node::actuators`] (reading it clears the flag).
    ///
    /// Also true on the first call after [`Node::new`], so the adapter applies the initial state.
    pub fn actuators_changed(&mut self) -> bool {
        let now = self.actuators();
        if self.shown == Some(now) {
            false
        } else {
            self.shown = Some(now);
            true
        }
    }

    /// The debounced signal-loop bitmap: bit *n* set = port *n*'s loop is closed.
    pub fn loops(&self) -> u8 {
        self.loops[..self.config.ports as usize]
            .iter()
            .enumerate()
            .fold(
                0,
                |acc, (i, d)| if d.closed() { acc | (1 << i) } else { acc },
            )
    }

    /// True while an identify sequence runs.
    pub fn is_identifying(&self) -> bool {
        self.identify_until.is_some()
    }

    /// Outputs lost because the output queue was full (see the crate docs for what goes first).
    pub fn dropped_outputs(&self) -> u32 {
        self.queue.dropped()
    }

    /// The health snapshot this node would send now for a check with `seq`.
    pub fn health(&self, seq: ihex_proto::Seq, now: Millis) -> HealthReply {
        let a = self.actuators();
        let led_on = a.led.duty != Rgb::default();
        let flags = HealthFlags::default()
            .with(HealthFlags::RELAY, a.relay)
            .with(HealthFlags::LED_ON, led_on)
            .with(HealthFlags::LED_BLINK, led_on && a.led.blink.is_some())
            .with(HealthFlags::BUZZER, a.buzzer != BuzzerOutput::Off)
            .with(HealthFlags::MOBILE, self.config.role == BootRole::Mobile)
            .with(HealthFlags::ERROR_PASSIVE, self.error_passive)
            .with(HealthFlags::IDENTIFY, self.identify_until.is_some());
        let uptime = now.since(self.boot) / 1000;
        HealthReply {
            seq,
            flags,
            loops: self.loops(),
            tec: self.tec,
            rec: self.rec,
            uptime_s: uptime.min(u64::from(HealthReply::MAX_UPTIME_S)) as u32,
        }
    }

    /// Runs every timer that is due at `now`, in a fixed order.
    fn advance(&mut self, now: Millis) {
        if self.uart.is_pending() && now.since(self.uart_last) >= UART_IDLE_RESET_MS {
            self.uart.reset();
        }
        for i in 0..self.config.ports {
            if let Some(closed) = self.loops[i as usize].poll(now) {
                // `i < ports <= Port::COUNT`, so the port is valid.
                if let Some(port) = Port::new(i) {
                    self.on_loop_change(port, closed);
                }
            }
        }
        if self.handshake_at.is_some_and(|t| now >= t) {
            self.handshake_at = None;
            let port = self.first_closed_loop().unwrap_or(PORT0);
            self.report(Message::Handshake { port });
        }
        if self.buzzer_end.is_some_and(|t| now >= t) {
            self.buzzer_end = None;
            self.buzzer = BuzzerCommand::Off;
        }
        if self.identify_until.is_some_and(|t| now >= t) {
            self.identify_until = None;
        }
        if self.restore_check_at.is_some_and(|t| now >= t) {
            self.restore_check_at = None;
            for i in 0..self.config.ports {
                let Some(port) = Port::new(i) else { continue };
                if self.confirmed & port.mask() != 0 && !self.loops[i as usize].closed() {
                    self.withdraw(port);
                    self.report(Message::DockRemoved { port });
                }
            }
        }
        self.advance_update(now);
    }

    /// A debounced loop level changed.
    fn on_loop_change(&mut self, port: Port, closed: bool) {
        match self.config.role {
            // A port restored confirmed across a reset is still docked: nothing new to report.
            BootRole::Static if closed && self.confirmed & port.mask() != 0 => {}
            BootRole::Static if closed => self.report(Message::DockDetected { port }),
            BootRole::Static => {
                // Power goes off before the report is even queued.
                self.withdraw(port);
                self.report(Message::DockRemoved { port });
            }
            BootRole::Mobile => {
                if closed && self.handshake_at.is_some() {
                    self.handshake_at = None;
                    self.report(Message::Handshake { port });
                }
            }
        }
    }

    /// The port is no longer confirmed (it opened, or the gateway withdrew it): its link goes, and
    /// the relay goes off if it was the last confirmed port.
    fn withdraw(&mut self, port: Port) {
        self.links[port.get() as usize] = None;
        if self.confirmed & port.mask() != 0 {
            self.confirmed &= !port.mask();
            if self.confirmed == 0 {
                self.relay = false;
            }
        }
    }

    /// The lowest port whose loop is (debounced) closed.
    fn first_closed_loop(&self) -> Option<Port> {
        let loops = self.loops();
        (loops != 0)
            .then(|| Port::new(loops.trailing_zeros() as u8))
            .flatten()
    }

    /// Boot-up announcement (and, for a mobile element, the handshake) under the ID in force.
    fn announce(&mut self, now: Millis) {
        self.report(Message::BootUp {
            version: PROTOCOL_VERSION,
            role: self.config.role,
            ports: self.config.ports,
            reset: self.config.reset,
        });
        if self.config.role == BootRole::Mobile {
            match self.first_closed_loop() {
                Some(port) => {
                    self.handshake_at = None;
                    self.report(Message::Handshake { port });
                }
                None => self.handshake_at = Some(now.add_ms(HANDSHAKE_SETTLE_MS)),
            }
        }
    }

    /// Queues a report to the gateway; an unconfigured node stays silent.
    fn report(&mut self, msg: Message) {
        if let Some(id) = self.config.node_id {
            self.queue.push(Output::Frame(Packet::report(id, msg)));
        }
    }

    /// Queues a fault report.
    fn fault(&mut self, code: FaultCode, arg: u8, detail: u32) {
        self.report(Message::Fault { code, arg, detail });
    }
}
