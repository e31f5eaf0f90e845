//! Typed messages: one variant per interaction, with the exact byte layout of `docs/protocol.md`.

use embedded_can::Frame;

use crate::field::{
    ack, assign_commit, assign_reply, assign_select, boot_up, buzzer_set, dock, dock_confirm,
    dock_link, dock_refuse, fault, fw_begin, fw_data, fw_end, fw_query, health_check, health_reply,
    identify, led_set, power_set, state_query, Field,
};
use crate::fw::{FwAction, FwStatus, FW_BEGIN_MAX_LEN, FW_DATA_LEN};
use crate::state::{DockPartner, StateParts, StateReport};
use crate::{DecodeError, Header, Kind, NodeId, Port, Seq};

/// An 8-bit-per-channel colour.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Rgb {
    /// Red.
    pub r: u8,
    /// Green.
    pub g: u8,
    /// Blue.
    pub b: u8,
}

impl Rgb {
    /// Builds a colour.
    pub const fn new(r: u8, g: u8, b: u8) -> Self {
        Rgb { r, g, b }
    }
}

/// What the LED strip should show.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LedCommand {
    /// Dark.
    Off,
    /// A steady colour; `brightness` scales all three channels (255 = full).
    Steady {
        /// Colour.
        color: Rgb,
        /// 0–255 overall brightness.
        brightness: u8,
    },
    /// The colour switched on and off: on for `duty_pct` % of every `period_10ms` × 10 ms.
    Blink {
        /// Colour.
        color: Rgb,
        /// 0–255 overall brightness.
        brightness: u8,
        /// Blink period in units of 10 ms (1–255, i.e. 10 ms to 2.55 s).
        period_10ms: u8,
        /// Share of the period the LEDs are on, 1–99 %.
        duty_pct: u8,
    },
}

impl LedCommand {
    /// Highest blink duty, in % (a duty of 100 would be steady).
    pub const MAX_DUTY_PCT: u8 = 99;
}

/// What the buzzer should do.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BuzzerCommand {
    /// Silent.
    Off,
    /// A continuous tone.
    Continuous {
        /// Tone frequency, [`BuzzerCommand::MIN_FREQ_HZ`]–[`BuzzerCommand::MAX_FREQ_HZ`].
        freq_hz: u16,
    },
    /// Beeps: `count` times (0 = until told otherwise) on for `on_10ms`, off for `off_10ms`.
    Pattern {
        /// Tone frequency.
        freq_hz: u16,
        /// Beep length in 10 ms units (1–255).
        on_10ms: u8,
        /// Pause length in 10 ms units (1–255).
        off_10ms: u8,
        /// Number of beeps; 0 repeats forever.
        count: u8,
    },
}

impl BuzzerCommand {
    /// Lowest tone the buzzer command accepts, in Hz.
    pub const MIN_FREQ_HZ: u16 = 20;
    /// Highest tone the buzzer command accepts, in Hz.
    pub const MAX_FREQ_HZ: u16 = 20_000;
}

enum_with_unknown! {
    /// Result code of an [`Message::Ack`] or [`Message::AssignReply`]; anything but `Ok` is a refusal.
    pub enum AckResult {
        /// Done.
        Ok = 0 => "ok",
        /// A value was out of range for this node.
        InvalidValue = 1 => "invalid_value",
        /// Not possible in the node's current state (e.g. confirming a dock with nothing docked).
        InvalidState = 2 => "invalid_state",
        /// The node is busy with something that excludes this command.
        Busy = 3 => "busy",
        /// The node does not implement this command (e.g. a dock command on an element without dock ports).
        Unsupported = 4 => "unsupported",
        /// Persisting the result failed (flash write).
        StoreFailed = 5 => "store_failed",
    }
}

enum_with_unknown! {
    /// Fault code of a [`Message::Fault`].
    pub enum FaultCode {
        /// A dock confirm arrived for a port whose signal loop is open (`arg` = port).
        DockConfirmNotDocked = 1 => "dock_confirm_not_docked",
        /// The CAN controller went bus-off and recovered (`detail` = how many times since boot).
        BusOff = 2 => "bus_off",
        /// The CAN controller is error-passive (`detail` = TEC << 8 | REC).
        ErrorPassive = 3 => "error_passive",
        /// Received frames were lost (`detail` = count).
        RxOverrun = 4 => "rx_overrun",
        /// The node was reset by its watchdog.
        WatchdogReset = 5 => "watchdog_reset",
        /// Writing the configuration to flash failed.
        ConfigStore = 6 => "config_store",
        /// A well-formed message arrived that makes no sense here (`arg` = its kind).
        UnexpectedMessage = 7 => "unexpected_message",
        /// A frame addressed to this node could not be decoded (`arg` = its kind bits).
        BadFrame = 8 => "bad_frame",
    }
}

enum_with_unknown! {
    /// Why the gateway refused a docking.
    pub enum DockRefuseReason {
        /// Another docking is in progress (one at a time).
        Busy = 1 => "busy",
        /// The operator or configuration does not allow docking here.
        NotAllowed = 2 => "not_allowed",
    }
}

/// Whether a node is part of the static island or a mobile element.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum BootRole {
    /// Wired on the bus, has dock ports.
    Static,
    /// Docks onto a static element and is powered through it.
    Mobile,
}

enum_with_unknown! {
    /// Why the node (re)started.
    pub enum ResetReason {
        /// Power applied.
        PowerOn = 0 => "power_on",
        /// Independent watchdog expired.
        Watchdog = 1 => "watchdog",
        /// Software requested the reset.
        Software = 2 => "software",
        /// NRST pin (reset button).
        Pin = 3 => "pin",
    }
}

/// The 96-bit unique device ID of an STM32 (reference manual, "Unique device ID register").
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Uid(pub [u8; 12]);

impl Uid {
    /// The 8 bytes carried by [`Message::AssignSelect`].
    pub fn head(&self) -> [u8; 8] {
        let mut h = [0; 8];
        h.copy_from_slice(&self.0[..8]);
        h
    }

    /// The 4 bytes carried by [`Message::AssignCommit`] and [`Message::AssignReply`].
    pub fn tail(&self) -> [u8; 4] {
        let mut t = [0; 4];
        t.copy_from_slice(&self.0[8..]);
        t
    }

    /// Bytes 0–6, carried by [`StateReport::UidLow`].
    pub fn low(&self) -> [u8; 7] {
        let mut l = [0; 7];
        l.copy_from_slice(&self.0[..7]);
        l
    }

    /// Bytes 7–11, carried by [`StateReport::UidHigh`].
    pub fn high(&self) -> [u8; 5] {
        let mut h = [0; 5];
        h.copy_from_slice(&self.0[7..]);
        h
    }

    /// The UID from its two state-report halves ([`Uid::low`], [`Uid::high`]).
    pub fn from_low_high(low: [u8; 7], high: [u8; 5]) -> Uid {
        let mut u = [0; 12];
        u[..7].copy_from_slice(&low);
        u[7..].copy_from_slice(&high);
        Uid(u)
    }
}

impl core::str::FromStr for Uid {
    type Err = crate::ParseError;

    /// 24 hex digits in either case, byte 0 first, optionally prefixed `0x`; `:`, `-` and spaces
    /// between digits are ignored (so a UID copied from a probe's or a log's output parses).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut uid = [0u8; 12];
        let mut n = 0usize;
        for c in crate::addr::strip_hex_prefix(s).chars() {
            if matches!(c, ':' | '-' | ' ') {
                continue;
            }
            let nibble = c.to_digit(16).ok_or(crate::ParseError::Uid)? as u8;
            let byte = uid.get_mut(n / 2).ok_or(crate::ParseError::Uid)?;
            *byte = *byte << 4 | nibble;
            n += 1;
        }
        if n == 24 {
            Ok(Uid(uid))
        } else {
            Err(crate::ParseError::Uid)
        }
    }
}

impl core::fmt::Display for Uid {
    /// 24 lower-case hex digits, byte 0 first: the form the MQTT API and the tools print.
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        crate::Hex(&self.0).fmt(f)
    }
}

/// Bit flags of a [`HealthReply`].
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct HealthFlags(pub u8);

impl HealthFlags {
    /// Relay (power to the dock) is on.
    pub const RELAY: u8 = 1 << 0;
    /// LED strip is lit (steady or blinking).
    pub const LED_ON: u8 = 1 << 1;
    /// LED strip is blinking.
    pub const LED_BLINK: u8 = 1 << 2;
    /// Buzzer is sounding or running a pattern.
    pub const BUZZER: u8 = 1 << 3;
    /// The node is a mobile element.
    pub const MOBILE: u8 = 1 << 4;
    /// The CAN controller is error-passive.
    pub const ERROR_PASSIVE: u8 = 1 << 5;
    /// An identify sequence is running.
    pub const IDENTIFY: u8 = 1 << 6;

    /// True when every bit of `flag` is set.
    pub const fn contains(self, flag: u8) -> bool {
        self.0 & flag == flag
    }

    /// Returns the flags with `flag` set or cleared.
    pub const fn with(self, flag: u8, on: bool) -> Self {
        if on {
            HealthFlags(self.0 | flag)
        } else {
            HealthFlags(self.0 & !flag)
        }
    }
}

/// A node's state snapshot, sent in answer to [`Message::HealthCheck`].
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct HealthReply {
    /// Sequence number of the health check answered.
    pub seq: Seq,
    /// Relay, LED, buzzer, role and CAN state flags.
    pub flags: HealthFlags,
    /// Signal-loop bitmap: bit *n* set = something is docked on port *n* (loop closed).
    pub loops: u8,
    /// CAN transmit error counter.
    pub tec: u8,
    /// CAN receive error counter.
    pub rec: u8,
    /// Seconds since boot, saturating at [`HealthReply::MAX_UPTIME_S`] (24 bits, ~194 days).
    pub uptime_s: u32,
}

impl HealthReply {
    /// Largest uptime that fits the 24-bit field.
    pub const MAX_UPTIME_S: u32 = 0xFF_FFFF;
}

/// One iHEX message: the payload part of a frame. See `docs/protocol.md` for each layout.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Message {
    /// `[seq, on]` — switch the power relay (`on` is 0 or 1).
    PowerSet {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// Relay state.
        on: bool,
    },
    /// `[code, arg, detail:u32le]` — a fault report.
    Fault {
        /// What happened.
        code: FaultCode,
        /// Code-specific argument (a port, a kind).
        arg: u8,
        /// Code-specific detail (counters, registers).
        detail: u32,
    },
    /// `[port]` — the signal loop of `port` closed (debounced).
    DockDetected {
        /// Dock port of the reporting (static) node.
        port: Port,
    },
    /// `[port]` — the signal loop of `port` opened; the node already switched its relay off.
    DockRemoved {
        /// Dock port of the reporting node.
        port: Port,
    },
    /// `[seq, port]` — the gateway allows docking on `port`: the node powers its relay.
    DockConfirm {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// Dock port.
        port: Port,
    },
    /// `[seq, port, reason]` — the gateway refuses docking on `port`.
    DockRefuse {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// Dock port.
        port: Port,
        /// Why.
        reason: DockRefuseReason,
    },
    /// `[port]` — a mobile element that was just powered through a dock announces itself and the port
    /// (of its own) it is docked by.
    Handshake {
        /// The mobile element's own port.
        port: Port,
    },
    /// `[kind, seq, result, detail]` — answers an acknowledged command.
    Ack {
        /// Kind of the command answered.
        kind: Kind,
        /// Its sequence number.
        seq: Seq,
        /// Done, or why not.
        result: AckResult,
        /// Result-specific detail (for `InvalidValue`, the byte offset of the bad field).
        detail: u8,
    },
    /// `[uid0..uid7]` — selects the node whose unique ID starts with these bytes for numbering.
    AssignSelect {
        /// First 8 bytes of the unique ID.
        uid_head: [u8; 8],
    },
    /// `[uid8..uid11, id:u16le, seq]` — the selected node whose unique ID ends so takes `new_id`.
    AssignCommit {
        /// Last 4 bytes of the unique ID.
        uid_tail: [u8; 4],
        /// The ID to take (`0x001..=0xFFD`).
        new_id: NodeId,
        /// Sequence number echoed by the reply.
        seq: Seq,
    },
    /// `[seq, result, id:u16le, uid8..uid11]` — a node's answer to [`Message::AssignCommit`].
    AssignReply {
        /// Sequence number of the commit.
        seq: Seq,
        /// Done, or why not.
        result: AckResult,
        /// The ID the node now has.
        new_id: NodeId,
        /// Last 4 bytes of its unique ID, so the gateway can tell boards apart.
        uid_tail: [u8; 4],
    },
    /// `[major, minor, role, ports, reset]` — sent once after every reset.
    BootUp {
        /// Protocol/firmware version.
        version: (u8, u8),
        /// Static or mobile element.
        role: BootRole,
        /// Number of dock ports (`0..=8`).
        ports: u8,
        /// Why the node started.
        reset: ResetReason,
    },
    /// `[seq, mode, freq:u16le, on, off, count]` — buzzer command.
    BuzzerSet {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// What to do.
        cmd: BuzzerCommand,
    },
    /// `[seq, mode, r, g, b, brightness, period, duty]` — LED strip command.
    LedSet {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// What to show.
        cmd: LedCommand,
    },
    /// `[seq, seconds]` — blink and beep for `seconds` (0 stops an identify in progress).
    Identify {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// Duration.
        seconds: u8,
    },
    /// `[seq]` — everybody addressed answers with a [`Message::HealthReply`].
    HealthCheck {
        /// Sequence number echoed in the replies.
        seq: Seq,
    },
    /// `[seq, flags, loops, tec, rec, uptime:u24le]` — state snapshot.
    HealthReply(HealthReply),
    /// `[seq, parts]` — the addressed nodes report these groups of their state, one
    /// [`Message::StateReport`] per part, closed by [`StateReport::End`]. Not acknowledged.
    StateQuery {
        /// Sequence number echoed by the closing [`StateReport::End`].
        seq: Seq,
        /// The groups asked for.
        parts: StateParts,
    },
    /// `[part, 7 bytes]` — one part of a node's state, answering a [`Message::StateQuery`].
    StateReport(StateReport),
    /// `[seq, port, partner:u16le, partner_port]` — the mobile element `partner` is the one docked
    /// on `port` of the addressed static element (`None`, sent as `0xFFF`, clears the link).
    DockLink {
        /// Sequence number echoed by the ack.
        seq: Seq,
        /// The static element's dock port.
        port: Port,
        /// The mobile element docked there and its own port; `None` clears.
        partner: Option<DockPartner>,
    },
    /// `[image_id:u32le, len:u24le, flags]` — a firmware transfer of this image starts; the same
    /// image ID and length resume the node's transfer. Flags: bit 0 `force` (allow a downgrade).
    FwBegin {
        /// First 4 bytes (LE) of the image's payload SHA-512.
        image_id: u32,
        /// Image length (header block + payload), up to [`FW_BEGIN_MAX_LEN`].
        len: u32,
        /// Accept an image older than the running one.
        force: bool,
    },
    /// `[image_id:u32le, action]` — commit or abort the transfer of this image.
    FwEnd {
        /// The image.
        image_id: u32,
        /// What to do.
        action: FwAction,
    },
    /// `[image_id:u32le]` — every addressed node answers with a [`Message::FwStatus`] about this image.
    FwQuery {
        /// The image.
        image_id: u32,
    },
    /// `[phase, reason, first:u16le, run:u16le, missing:u16le]` — a node's transfer status.
    FwStatus(FwStatus),
    /// `[index:u16le, 6 bytes]` — image bytes `6 × index .. 6 × index + 6`.
    FwData {
        /// Frame index.
        index: u16,
        /// The bytes (past the image's end: don't care).
        data: [u8; FW_DATA_LEN],
    },
}

/// A message with its addresses: exactly what one frame carries.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Packet {
    /// Sender.
    pub src: NodeId,
    /// Addressee.
    pub dest: NodeId,
    /// Content.
    pub msg: Message,
}

/// Encoded payload: up to 8 bytes.
type Data = heapless::Vec<u8, 8>;

fn push_all(d: &mut Data, bytes: &[u8]) {
    // Every layout in this module is at most 8 bytes long, so this never truncates.
    let _ = d.extend_from_slice(bytes);
}

impl Message {
    /// The kind field this message is sent with.
    pub const fn kind(&self) -> Kind {
        match self {
            Message::PowerSet { .. } => Kind::PowerSet,
            Message::Fault { .. } => Kind::Fault,
            Message::DockDetected { .. } => Kind::DockDetected,
            Message::DockRemoved { .. } => Kind::DockRemoved,
            Message::DockConfirm { .. } => Kind::DockConfirm,
            Message::DockRefuse { .. } => Kind::DockRefuse,
            Message::Handshake { .. } => Kind::Handshake,
            Message::Ack { .. } => Kind::Ack,
            Message::AssignSelect { .. } => Kind::AssignSelect,
            Message::AssignCommit { .. } => Kind::AssignCommit,
            Message::AssignReply { .. } => Kind::AssignReply,
            Message::BootUp { .. } => Kind::BootUp,
            Message::BuzzerSet { .. } => Kind::BuzzerSet,
            Message::LedSet { .. } => Kind::LedSet,
            Message::Identify { .. } => Kind::Identify,
            Message::HealthCheck { .. } => Kind::HealthCheck,
            Message::HealthReply(_) => Kind::HealthReply,
            Message::StateQuery { .. } => Kind::StateQuery,
            Message::StateReport(_) => Kind::StateReport,
            Message::DockLink { .. } => Kind::DockLink,
            Message::FwBegin { .. } => Kind::FwBegin,
            Message::FwEnd { .. } => Kind::FwEnd,
            Message::FwQuery { .. } => Kind::FwQuery,
            Message::FwStatus(_) => Kind::FwStatus,
            Message::FwData { .. } => Kind::FwData,
        }
    }

    /// The sequence number of a command that expects an [`Message::Ack`], if this is one.
    pub const fn ack_seq(&self) -> Option<Seq> {
        match *self {
            Message::PowerSet { seq, .. }
            | Message::DockConfirm { seq, .. }
            | Message::DockRefuse { seq, .. }
            | Message::BuzzerSet { seq, .. }
            | Message::LedSet { seq, .. }
            | Message::Identify { seq, .. }
            | Message::DockLink { seq, .. } => Some(seq),
            _ => None,
        }
    }

    /// Checks value ranges. [`Message::decode`] only returns messages that pass this; call it before
    /// encoding values that came from outside (a JSON command, a test generator).
    pub fn validate(&self) -> Result<(), DecodeError> {
        let kind = self.kind();
        let bad = |field: &'static str, raw: u32| Err(DecodeError::Value { kind, field, raw });
        match *self {
            Message::LedSet { cmd, .. } => check_led(kind, cmd)?,
            Message::BuzzerSet { cmd, .. } => check_buzzer(kind, cmd)?,
            Message::StateReport(r) => r.validate()?,
            Message::DockLink {
                partner: Some(p), ..
            } if !p.node.is_sc() => return bad("partner", p.node.get() as u32),
            // An assignment reply may report "still no ID" (0xFFE) after a failure.
            Message::AssignCommit { new_id, .. } | Message::AssignReply { new_id, .. }
                if !(new_id.is_sc()
                    || (kind == Kind::AssignReply && new_id == NodeId::UNCONFIGURED)) =>
            {
                return bad("id", new_id.get() as u32);
            }
            Message::BootUp { ports, .. } if ports > Port::COUNT => {
                return bad("ports", ports as u32);
            }
            Message::HealthReply(h) if h.uptime_s > HealthReply::MAX_UPTIME_S => {
                return bad("uptime", h.uptime_s);
            }
            Message::FwBegin { len, .. } if len > FW_BEGIN_MAX_LEN => return bad("len", len),
            _ => {}
        }
        Ok(())
    }

    /// Encodes the payload bytes (no validation: see [`Message::validate`]). Bytes a mode does not
    /// use are zero.
    pub fn encode(&self) -> heapless::Vec<u8, 8> {
        let mut b = [0u8; 8];
        match *self {
            Message::PowerSet { seq, on } => {
                b[power_set::SEQ] = seq;
                b[power_set::ON] = on as u8;
            }
            Message::Fault { code, arg, detail } => {
                b[fault::CODE] = code.to_raw();
                b[fault::ARG] = arg;
                b[fault::DETAIL].copy_from_slice(&detail.to_le_bytes());
            }
            Message::DockDetected { port }
            | Message::DockRemoved { port }
            | Message::Handshake { port } => b[dock::PORT] = port.get(),
            Message::DockConfirm { seq, port } => {
                b[dock_confirm::SEQ] = seq;
                b[dock_confirm::PORT] = port.get();
            }
            Message::DockRefuse { seq, port, reason } => {
                b[dock_refuse::SEQ] = seq;
                b[dock_refuse::PORT] = port.get();
                b[dock_refuse::REASON] = reason.to_raw();
            }
            Message::Ack {
                kind,
                seq,
                result,
                detail,
            } => {
                b[ack::KIND] = kind as u8;
                b[ack::SEQ] = seq;
                b[ack::RESULT] = result.to_raw();
                b[ack::DETAIL] = detail;
            }
            Message::AssignSelect { uid_head } => {
                b[assign_select::UID_HEAD].copy_from_slice(&uid_head)
            }
            Message::AssignCommit {
                uid_tail,
                new_id,
                seq,
            } => {
                b[assign_commit::UID_TAIL].copy_from_slice(&uid_tail);
                b[assign_commit::ID].copy_from_slice(&new_id.get().to_le_bytes());
                b[assign_commit::SEQ] = seq;
            }
            Message::AssignReply {
                seq,
                result,
                new_id,
                uid_tail,
            } => {
                b[assign_reply::SEQ] = seq;
                b[assign_reply::RESULT] = result.to_raw();
                b[assign_reply::ID].copy_from_slice(&new_id.get().to_le_bytes());
                b[assign_reply::UID_TAIL].copy_from_slice(&uid_tail);
            }
            Message::BootUp {
                version,
                role,
                ports,
                reset,
            } => {
                b[boot_up::MAJOR] = version.0;
                b[boot_up::MINOR] = version.1;
                b[boot_up::ROLE] = match role {
                    BootRole::Static => boot_up::ROLE_STATIC,
                    BootRole::Mobile => boot_up::ROLE_MOBILE,
                };
                b[boot_up::PORTS] = ports;
                b[boot_up::RESET] = reset.to_raw();
            }
            Message::BuzzerSet { seq, cmd } => {
                b[buzzer_set::SEQ] = seq;
                encode_buzzer(cmd, &mut b);
            }
            Message::LedSet { seq, cmd } => {
                b[led_set::SEQ] = seq;
                encode_led(cmd, &mut b);
            }
            Message::Identify { seq, seconds } => {
                b[identify::SEQ] = seq;
                b[identify::SECONDS] = seconds;
            }
            Message::HealthCheck { seq } => b[health_check::SEQ] = seq,
            Message::HealthReply(h) => {
                b[health_reply::SEQ] = h.seq;
                b[health_reply::FLAGS] = h.flags.0;
                b[health_reply::LOOPS] = h.loops;
                b[health_reply::TEC] = h.tec;
                b[health_reply::REC] = h.rec;
                let up = h.uptime_s.min(HealthReply::MAX_UPTIME_S).to_le_bytes();
                b[health_reply::UPTIME].copy_from_slice(&up[..3]);
            }
            Message::StateQuery { seq, parts } => {
                b[state_query::SEQ] = seq;
                b[state_query::PARTS] = parts.0;
            }
            Message::StateReport(r) => r.encode_into(&mut b),
            Message::DockLink { seq, port, partner } => {
                b[dock_link::SEQ] = seq;
                b[dock_link::PORT] = port.get();
                encode_partner(partner, &mut b, dock_link::PARTNER, dock_link::PARTNER_PORT);
            }
            Message::FwBegin {
                image_id,
                len,
                force,
            } => {
                b[fw_begin::IMAGE_ID].copy_from_slice(&image_id.to_le_bytes());
                b[fw_begin::LEN].copy_from_slice(&len.to_le_bytes()[..3]);
                b[fw_begin::FLAGS] = u8::from(force);
            }
            Message::FwEnd { image_id, action } => {
                b[fw_end::IMAGE_ID].copy_from_slice(&image_id.to_le_bytes());
                b[fw_end::ACTION] = action.to_raw();
            }
            Message::FwQuery { image_id } => {
                b[fw_query::IMAGE_ID].copy_from_slice(&image_id.to_le_bytes());
            }
            Message::FwStatus(st) => st.encode_into(&mut b),
            Message::FwData { index, data } => {
                b[fw_data::INDEX].copy_from_slice(&index.to_le_bytes());
                b[fw_data::DATA].copy_from_slice(&data);
            }
        }
        let mut d = Data::new();
        push_all(&mut d, &b[..Self::len_of(self.kind()) as usize]);
        d
    }

    /// Number of data bytes a kind always has.
    pub const fn len_of(kind: Kind) -> u8 {
        match kind {
            Kind::PowerSet => 2,
            Kind::Fault => 6,
            Kind::DockDetected | Kind::DockRemoved | Kind::Handshake => 1,
            Kind::DockConfirm => 2,
            Kind::DockRefuse => 3,
            Kind::Ack => 4,
            Kind::AssignSelect => 8,
            Kind::AssignCommit => 7,
            Kind::AssignReply => 8,
            Kind::BootUp => 5,
            Kind::BuzzerSet => 7,
            Kind::LedSet => 8,
            Kind::Identify => 2,
            Kind::HealthCheck => 1,
            Kind::HealthReply => 8,
            Kind::StateQuery => 2,
            Kind::StateReport => 8,
            Kind::DockLink => 5,
            Kind::FwBegin => 8,
            Kind::FwEnd => 5,
            Kind::FwQuery => 4,
            Kind::FwStatus => 8,
            Kind::FwData => 8,
        }
    }

    /// Decodes the payload of a frame of this kind, checking length, every value range and that
    /// bytes the mode leaves unused are zero: an accepted payload re-encodes to the same bytes.
    pub fn decode(kind: Kind, d: &[u8]) -> Result<Message, DecodeError> {
        let expected = Self::len_of(kind);
        if d.len() != expected as usize {
            return Err(DecodeError::Length {
                kind,
                expected,
                got: d.len().min(255) as u8,
            });
        }
        let bad = |field: &'static str, raw: u8| DecodeError::Value {
            kind,
            field,
            raw: raw as u32,
        };
        let port = |raw: u8| Port::new(raw).ok_or(bad("port", raw));
        let node_id = |f: Field| {
            let raw = u16::from_le_bytes([d[f.start], d[f.start + 1]]);
            NodeId::new(raw).ok_or(DecodeError::Value {
                kind,
                field: "id",
                raw: raw as u32,
            })
        };
        let bytes4 = |f: Field| [d[f.start], d[f.start + 1], d[f.start + 2], d[f.start + 3]];
        let msg = match kind {
            Kind::PowerSet => Message::PowerSet {
                seq: d[power_set::SEQ],
                on: match d[power_set::ON] {
                    0 => false,
                    1 => true,
                    v => return Err(bad("on", v)),
                },
            },
            Kind::Fault => Message::Fault {
                code: FaultCode::from_raw(d[fault::CODE]),
                arg: d[fault::ARG],
                detail: u32::from_le_bytes(bytes4(fault::DETAIL)),
            },
            Kind::DockDetected => Message::DockDetected {
                port: port(d[dock::PORT])?,
            },
            Kind::DockRemoved => Message::DockRemoved {
                port: port(d[dock::PORT])?,
            },
            Kind::Handshake => Message::Handshake {
                port: port(d[dock::PORT])?,
            },
            Kind::DockConfirm => Message::DockConfirm {
                seq: d[dock_confirm::SEQ],
                port: port(d[dock_confirm::PORT])?,
            },
            Kind::DockRefuse => Message::DockRefuse {
                seq: d[dock_refuse::SEQ],
                port: port(d[dock_refuse::PORT])?,
                reason: DockRefuseReason::from_raw(d[dock_refuse::REASON]),
            },
            Kind::Ack => Message::Ack {
                kind: Kind::from_raw(d[ack::KIND]).ok_or(bad("kind", d[ack::KIND]))?,
                seq: d[ack::SEQ],
                result: AckResult::from_raw(d[ack::RESULT]),
                detail: d[ack::DETAIL],
            },
            Kind::AssignSelect => {
                let mut uid_head = [0; 8];
                uid_head.copy_from_slice(&d[assign_select::UID_HEAD]);
                Message::AssignSelect { uid_head }
            }
            Kind::AssignCommit => Message::AssignCommit {
                uid_tail: bytes4(assign_commit::UID_TAIL),
                new_id: node_id(assign_commit::ID)?,
                seq: d[assign_commit::SEQ],
            },
            Kind::AssignReply => Message::AssignReply {
                seq: d[assign_reply::SEQ],
                result: AckResult::from_raw(d[assign_reply::RESULT]),
                new_id: node_id(assign_reply::ID)?,
                uid_tail: bytes4(assign_reply::UID_TAIL),
            },
            Kind::BootUp => Message::BootUp {
                version: (d[boot_up::MAJOR], d[boot_up::MINOR]),
                role: match d[boot_up::ROLE] {
                    boot_up::ROLE_STATIC => BootRole::Static,
                    boot_up::ROLE_MOBILE => BootRole::Mobile,
                    v => return Err(bad("role", v)),
                },
                ports: d[boot_up::PORTS],
                reset: ResetReason::from_raw(d[boot_up::RESET]),
            },
            Kind::BuzzerSet => Message::BuzzerSet {
                seq: d[buzzer_set::SEQ],
                cmd: decode_buzzer(kind, d)?,
            },
            Kind::LedSet => Message::LedSet {
                seq: d[led_set::SEQ],
                cmd: decode_led(kind, d)?,
            },
            Kind::Identify => Message::Identify {
                seq: d[identify::SEQ],
                seconds: d[identify::SECONDS],
            },
            Kind::HealthCheck => Message::HealthCheck {
                seq: d[health_check::SEQ],
            },
            Kind::HealthReply => {
                let up = health_reply::UPTIME;
                Message::HealthReply(HealthReply {
                    seq: d[health_reply::SEQ],
                    flags: HealthFlags(d[health_reply::FLAGS]),
                    loops: d[health_reply::LOOPS],
                    tec: d[health_reply::TEC],
                    rec: d[health_reply::REC],
                    uptime_s: u32::from_le_bytes([
                        d[up.start],
                        d[up.start + 1],
                        d[up.start + 2],
                        0,
                    ]),
                })
            }
            Kind::StateQuery => Message::StateQuery {
                seq: d[state_query::SEQ],
                parts: StateParts(d[state_query::PARTS]),
            },
            Kind::StateReport => Message::StateReport(StateReport::decode(d)?),
            Kind::DockLink => Message::DockLink {
                seq: d[dock_link::SEQ],
                port: port(d[dock_link::PORT])?,
                partner: decode_partner(kind, d, dock_link::PARTNER, dock_link::PARTNER_PORT)?,
            },
            Kind::FwBegin => {
                let l = fw_begin::LEN;
                Message::FwBegin {
                    image_id: u32::from_le_bytes(bytes4(fw_begin::IMAGE_ID)),
                    len: u32::from_le_bytes([d[l.start], d[l.start + 1], d[l.start + 2], 0]),
                    force: match d[fw_begin::FLAGS] {
                        0 => false,
                        1 => true,
                        v => return Err(bad("flags", v)),
                    },
                }
            }
            Kind::FwEnd => Message::FwEnd {
                image_id: u32::from_le_bytes(bytes4(fw_end::IMAGE_ID)),
                action: FwAction::from_raw(d[fw_end::ACTION])
                    .ok_or(bad("action", d[fw_end::ACTION]))?,
            },
            Kind::FwQuery => Message::FwQuery {
                image_id: u32::from_le_bytes(bytes4(fw_query::IMAGE_ID)),
            },
            Kind::FwStatus => Message::FwStatus(FwStatus::decode(d)),
            Kind::FwData => {
                let mut data = [0; FW_DATA_LEN];
                data.copy_from_slice(&d[fw_data::DATA]);
                Message::FwData {
                    index: u16::from_le_bytes([
                        d[fw_data::INDEX.start],
                        d[fw_data::INDEX.start + 1],
                    ]),
                    data,
                }
            }
        };
        msg.validate()?;
        Ok(msg)
    }
}

impl Packet {
    /// A command from the gateway to `dest` (a node or [`NodeId::BROADCAST`]).
    pub const fn command(dest: NodeId, msg: Message) -> Packet {
        Packet {
            src: NodeId::GATEWAY,
            dest,
            msg,
        }
    }

    /// A report from node `src` to the gateway.
    pub const fn report(src: NodeId, msg: Message) -> Packet {
        Packet {
            src,
            dest: NodeId::GATEWAY,
            msg,
        }
    }

    /// The identifier fields.
    pub const fn header(&self) -> Header {
        Header {
            kind: self.msg.kind(),
            dest: self.dest,
            src: self.src,
        }
    }

    /// Checks addresses and value ranges: exactly what [`Packet::from_frame`] accepts.
    pub fn validate(&self) -> Result<(), DecodeError> {
        self.header().check_addresses()?;
        self.msg.validate()
    }

    /// Raw 29-bit identifier and payload bytes.
    pub fn encode(&self) -> (u32, heapless::Vec<u8, 8>) {
        (self.header().to_raw(), self.msg.encode())
    }

    /// Decodes a raw 29-bit identifier and payload.
    pub fn decode(raw_id: u32, data: &[u8]) -> Result<Packet, DecodeError> {
        let h = Header::from_raw(raw_id)?;
        h.check_addresses()?;
        let msg = Message::decode(h.kind, data)?;
        Ok(Packet {
            src: h.src,
            dest: h.dest,
            msg,
        })
    }

    /// Builds a frame of any embedded-can frame type (socketcan's `CanFrame`, embassy's `Frame`, …).
    ///
    /// Returns `None` only if `F` refuses an extended data frame of at most 8 bytes, which no
    /// conforming implementation does.
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        F::new(self.header().to_id(), &self.msg.encode())
    }

    /// Decodes a received frame: standard IDs, remote frames, unknown kinds, wrong lengths, bad
    /// addresses and out-of-range values are all errors, never panics.
    pub fn from_frame<F: Frame>(frame: &F) -> Result<Packet, DecodeError> {
        if frame.is_remote_frame() {
            return Err(DecodeError::Remote);
        }
        let h = Header::from_id(frame.id())?;
        h.check_addresses()?;
        // No truncation: a frame type with longer payloads (CAN FD) must fail the length check,
        // not have its first 8 bytes taken for a classic frame.
        let msg = Message::decode(h.kind, frame.data())?;
        Ok(Packet {
            src: h.src,
            dest: h.dest,
            msg,
        })
    }
}

/// A `Value` error of `kind`.
pub(crate) const fn bad_value(kind: Kind, field: &'static str, raw: u32) -> DecodeError {
    DecodeError::Value { kind, field, raw }
}

/// Bytes a mode does not use must be zero, so that every accepted payload has exactly one
/// encoding (decode then encode gives the same bytes) and a future use of them is detectable.
pub(crate) fn reserved(kind: Kind, d: &[u8], from: usize) -> Result<(), DecodeError> {
    match d
        .get(from..)
        .and_then(|rest| rest.iter().find(|b| **b != 0))
    {
        Some(b) => Err(bad_value(kind, "reserved", *b as u32)),
        None => Ok(()),
    }
}

/// Writes an LED command at the [`led_set`] offsets from `MODE` on (byte 0 is the caller's).
pub(crate) fn encode_led(cmd: LedCommand, b: &mut [u8; 8]) {
    let (color, brightness) = match cmd {
        LedCommand::Off => {
            b[led_set::MODE] = led_set::MODE_OFF;
            (None, 0)
        }
        LedCommand::Steady { color, brightness } => {
            b[led_set::MODE] = led_set::MODE_STEADY;
            (Some(color), brightness)
        }
        LedCommand::Blink {
            color,
            brightness,
            period_10ms,
            duty_pct,
        } => {
            b[led_set::MODE] = led_set::MODE_BLINK;
            b[led_set::PERIOD] = period_10ms;
            b[led_set::DUTY] = duty_pct;
            (Some(color), brightness)
        }
    };
    if let Some(c) = color {
        b[led_set::R] = c.r;
        b[led_set::G] = c.g;
        b[led_set::B] = c.b;
        b[led_set::BRIGHTNESS] = brightness;
    }
}

/// Reads an LED command at the [`led_set`] offsets (8 bytes, byte 0 not looked at); value
/// ranges are [`check_led`]'s.
pub(crate) fn decode_led(kind: Kind, d: &[u8]) -> Result<LedCommand, DecodeError> {
    let color = Rgb::new(d[led_set::R], d[led_set::G], d[led_set::B]);
    let brightness = d[led_set::BRIGHTNESS];
    let cmd = match d[led_set::MODE] {
        led_set::MODE_OFF => {
            reserved(kind, d, led_set::R)?;
            LedCommand::Off
        }
        led_set::MODE_STEADY => {
            reserved(kind, d, led_set::PERIOD)?;
            LedCommand::Steady { color, brightness }
        }
        led_set::MODE_BLINK => LedCommand::Blink {
            color,
            brightness,
            period_10ms: d[led_set::PERIOD],
            duty_pct: d[led_set::DUTY],
        },
        v => return Err(bad_value(kind, "mode", v as u32)),
    };
    Ok(cmd)
}

/// The value ranges of an LED command.
pub(crate) fn check_led(kind: Kind, cmd: LedCommand) -> Result<(), DecodeError> {
    if let LedCommand::Blink {
        period_10ms,
        duty_pct,
        ..
    } = cmd
    {
        if period_10ms == 0 {
            return Err(bad_value(kind, "period", 0));
        }
        if duty_pct == 0 || duty_pct > LedCommand::MAX_DUTY_PCT {
            return Err(bad_value(kind, "duty", duty_pct as u32));
        }
    }
    Ok(())
}

/// Writes a buzzer command at the [`buzzer_set`] offsets from `MODE` on (byte 0 is the caller's).
pub(crate) fn encode_buzzer(cmd: BuzzerCommand, b: &mut [u8; 8]) {
    let freq = match cmd {
        BuzzerCommand::Off => {
            b[buzzer_set::MODE] = buzzer_set::MODE_OFF;
            None
        }
        BuzzerCommand::Continuous { freq_hz } => {
            b[buzzer_set::MODE] = buzzer_set::MODE_CONTINUOUS;
            Some(freq_hz)
        }
        BuzzerCommand::Pattern {
            freq_hz,
            on_10ms,
            off_10ms,
            count,
        } => {
            b[buzzer_set::MODE] = buzzer_set::MODE_PATTERN;
            b[buzzer_set::ON] = on_10ms;
            b[buzzer_set::OFF] = off_10ms;
            b[buzzer_set::COUNT] = count;
            Some(freq_hz)
        }
    };
    if let Some(f) = freq {
        b[buzzer_set::FREQ].copy_from_slice(&f.to_le_bytes());
    }
}

/// Reads a buzzer command at the [`buzzer_set`] offsets; bytes past the `BuzzerSet` length are
/// not looked at (a longer layout checks its own tail); value ranges are [`check_buzzer`]'s.
pub(crate) fn decode_buzzer(kind: Kind, d: &[u8]) -> Result<BuzzerCommand, DecodeError> {
    let d = &d[..Message::len_of(Kind::BuzzerSet) as usize];
    let f = buzzer_set::FREQ;
    let freq_hz = u16::from_le_bytes([d[f.start], d[f.start + 1]]);
    let cmd = match d[buzzer_set::MODE] {
        buzzer_set::MODE_OFF => {
            reserved(kind, d, f.start)?;
            BuzzerCommand::Off
        }
        buzzer_set::MODE_CONTINUOUS => {
            reserved(kind, d, buzzer_set::ON)?;
            BuzzerCommand::Continuous { freq_hz }
        }
        buzzer_set::MODE_PATTERN => BuzzerCommand::Pattern {
            freq_hz,
            on_10ms: d[buzzer_set::ON],
            off_10ms: d[buzzer_set::OFF],
            count: d[buzzer_set::COUNT],
        },
        v => return Err(bad_value(kind, "mode", v as u32)),
    };
    Ok(cmd)
}

/// The value ranges of a buzzer command.
pub(crate) fn check_buzzer(kind: Kind, cmd: BuzzerCommand) -> Result<(), DecodeError> {
    let freq = match cmd {
        BuzzerCommand::Off => None,
        BuzzerCommand::Continuous { freq_hz } => Some(freq_hz),
        BuzzerCommand::Pattern {
            freq_hz,
            on_10ms,
            off_10ms,
            ..
        } => {
            if on_10ms == 0 {
                return Err(bad_value(kind, "on", 0));
            }
            if off_10ms == 0 {
                return Err(bad_value(kind, "off", 0));
            }
            Some(freq_hz)
        }
    };
    match freq {
        Some(f) if !(BuzzerCommand::MIN_FREQ_HZ..=BuzzerCommand::MAX_FREQ_HZ).contains(&f) => {
            Err(bad_value(kind, "freq", f as u32))
        }
        _ => Ok(()),
    }
}

/// Writes a dock partner (`0xFFF` and port 0 for none) at the given offsets.
pub(crate) fn encode_partner(
    partner: Option<DockPartner>,
    b: &mut [u8; 8],
    id: Field,
    port: usize,
) {
    let (node, p) = match partner {
        Some(DockPartner { node, port }) => (node.get(), port.get()),
        None => (NodeId::BROADCAST.get(), 0),
    };
    b[id].copy_from_slice(&node.to_le_bytes());
    b[port] = p;
}

/// Reads a dock partner: `0xFFF` with port 0 is none, otherwise a sub-controller ID and a port.
pub(crate) fn decode_partner(
    kind: Kind,
    d: &[u8],
    id: Field,
    port: usize,
) -> Result<Option<DockPartner>, DecodeError> {
    let raw = u16::from_le_bytes([d[id.start], d[id.start + 1]]);
    let p = d[port];
    if raw == NodeId::BROADCAST.get() {
        return match p {
            0 => Ok(None),
            v => Err(bad_value(kind, "partner_port", v as u32)),
        };
    }
    let node = NodeId::new_sc(raw).ok_or(bad_value(kind, "partner", raw as u32))?;
    let port = Port::new(p).ok_or(bad_value(kind, "partner_port", p as u32))?;
    Ok(Some(DockPartner { node, port }))
}
