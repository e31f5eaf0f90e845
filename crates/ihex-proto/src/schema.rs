//! A machine-readable description of every message: per kind its name, direction, data length and
//! signals (bit position, length, scaling, unit, range, value names), built from the [`crate::field`]
//! offsets, mode constants and enum tables the codec itself uses, so each fact is written once.
//!
//! [`crate::dbc`] renders it as a DBC file for cantools, SavvyCAN and other CAN tools. The tests
//! (`tests/schema.rs`) hold it to the codec: every kind has an entry ([`of`] is an exhaustive
//! match), the signals cover each payload bit exactly once, reading the signals of an encoded
//! message gives its typed fields, and a raw value just outside a signal's range is refused by
//! [`crate::Packet::decode`].
//!
//! Every signal is an unsigned little-endian ("Intel") bit field, like every field of the codec.
//! The destination and source node IDs are in the identifier, not in the data, so they are not
//! signals. A message whose layout depends on one of its bytes (the `part` of a
//! [`Message::StateReport`]) marks that signal [`Mux::Selector`] and the fields of each layout
//! [`Mux::When`] (DBC multiplexing); fields that a mode merely leaves zero stay plain signals that
//! read 0, and bytes a layout must leave zero are `*reserved` signals whose range is `0`.

use crate::field::{
    ack, assign_commit, assign_reply, assign_select, boot_up, buzzer_set, dock, dock_confirm,
    dock_link, dock_refuse, fault, fw_begin, fw_data, fw_end, fw_query, fw_status, health_check,
    health_reply, identify, led_set, power_set, state_query, state_report, Field,
};
use crate::{
    unit, AckResult, BuzzerCommand, DockRefuseReason, DockState, FaultCode, FwAction, FwPhase,
    FwRefusal, HealthFlags, HealthReply, Kind, LedCommand, Message, NodeId, Port, ResetReason,
    StateParts, StateReport,
};

/// Who sends a message.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Direction {
    /// Gateway → one node or all nodes ([`Kind::is_command`]).
    Command,
    /// Node → gateway.
    Report,
}

impl Direction {
    /// The direction of a kind.
    pub const fn of(kind: Kind) -> Direction {
        if kind.is_command() {
            Direction::Command
        } else {
            Direction::Report
        }
    }
}

/// One message kind, described.
#[derive(Clone, Copy, Debug)]
pub struct MessageSchema {
    /// The kind (its value is identifier bits 28–24).
    pub kind: Kind,
    /// What the message is for, one line.
    pub summary: &'static str,
    /// The fields of the data, in byte order.
    pub signals: &'static [Signal],
}

impl MessageSchema {
    /// [`Kind::name`].
    pub const fn name(&self) -> &'static str {
        self.kind.name()
    }

    /// Data length in bytes ([`Message::len_of`]).
    pub const fn data_len(&self) -> u8 {
        Message::len_of(self.kind)
    }

    /// Who sends it.
    pub const fn direction(&self) -> Direction {
        Direction::of(self.kind)
    }

    /// The signal called `name`.
    pub fn signal(&self, name: &str) -> Option<&'static Signal> {
        self.signals.iter().find(|s| s.name == name)
    }

    /// The multiplexer, if the layout depends on one of its fields.
    pub fn selector(&self) -> Option<&'static Signal> {
        self.signals.iter().find(|s| s.mux == Mux::Selector)
    }

    /// The signals a frame with this data carries: every signal of a message without a
    /// selector; otherwise the selector, the signals always there and those its value selects.
    pub fn signals_in<'a>(&self, data: &'a [u8]) -> impl Iterator<Item = &'static Signal> + 'a {
        let selected = self.selector().and_then(|s| s.raw(data));
        self.signals.iter().filter(move |s| s.present_for(selected))
    }
}

/// Whether a signal is in every frame of its message or only in some (DBC multiplexing).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mux {
    /// In every frame.
    Always,
    /// The multiplexer: its raw value says which [`Mux::When`] signals a frame carries.
    Selector,
    /// Only in frames whose selector has one of these raw values (ascending).
    When(&'static [u8]),
}

/// One field of a message's data: an unsigned little-endian bit field.
///
/// Its physical value is `raw * factor + offset` in `unit`; the codec accepts raw values in
/// `min..=max` (in some modes only `0`, see the comment).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Signal {
    /// Field name as in `docs/protocol.md` (`snake_case`).
    pub name: &'static str,
    /// Bit position of the least significant bit: byte × 8 + bit.
    pub start: u8,
    /// Length in bits.
    pub bits: u8,
    /// Two's complement (no iHEX field is, today).
    pub signed: bool,
    /// Scale from raw to physical value (10 for the 10 ms fields, shown in ms).
    pub factor: u32,
    /// Added after scaling.
    pub offset: i32,
    /// Unit of the physical value (`""` when it has none).
    pub unit: &'static str,
    /// Smallest raw value the codec accepts.
    pub min: u32,
    /// Largest raw value the codec accepts.
    pub max: u32,
    /// Names of raw values (enumerations); empty for plain numbers.
    pub values: &'static [(u8, &'static str)],
    /// What it means, one line.
    pub comment: &'static str,
    /// In every frame, or only in some.
    pub mux: Mux,
}

impl Signal {
    /// The raw value of this signal in `data`; `None` when `data` is too short.
    pub fn raw(&self, data: &[u8]) -> Option<u32> {
        let mut raw = 0u64;
        for i in 0..self.bits as usize {
            let bit = self.start as usize + i;
            let byte = data.get(bit / 8)?;
            raw |= u64::from((byte >> (bit % 8)) & 1) << i;
        }
        // `bits` is at most 32 (checked by the tests), so this is exact.
        Some(raw as u32)
    }

    /// The physical value of a raw value (`raw * factor + offset`).
    pub const fn physical(&self, raw: u32) -> i64 {
        raw as i64 * self.factor as i64 + self.offset as i64
    }

    /// True when a frame whose selector reads `selected` (`None`: no selector) carries this signal.
    pub fn present_for(&self, selected: Option<u32>) -> bool {
        match self.mux {
            Mux::Always | Mux::Selector => true,
            Mux::When(values) => {
                selected.is_some_and(|v| values.iter().any(|w| u32::from(*w) == v))
            }
        }
    }

    /// The name of a raw value, if it has one.
    pub fn label(&self, raw: u32) -> Option<&'static str> {
        self.values
            .iter()
            .find(|(v, _)| u32::from(*v) == raw)
            .map(|(_, name)| *name)
    }

    /// An 8-bit field at byte `byte`.
    const fn byte(name: &'static str, byte: usize, comment: &'static str) -> Signal {
        Signal {
            name,
            start: (byte * 8) as u8,
            bits: 8,
            signed: false,
            factor: 1,
            offset: 0,
            unit: "",
            min: 0,
            max: u8::MAX as u32,
            values: &[],
            comment,
            mux: Mux::Always,
        }
    }

    /// A little-endian field over the bytes of `field`.
    const fn le(name: &'static str, field: Field, comment: &'static str) -> Signal {
        let bits = ((field.end - field.start) * 8) as u8;
        Signal {
            bits,
            max: if bits >= 32 {
                u32::MAX
            } else {
                (1 << bits) - 1
            },
            ..Signal::byte(name, field.start, comment)
        }
    }

    /// Byte `i` of a unique-ID field starting at byte `first` (`uid_<n>` names the UID byte, not
    /// the payload byte).
    const fn uid(name: &'static str, first: usize, i: usize) -> Signal {
        Signal::byte(name, first + i, "a byte of the 96-bit STM32 unique ID")
    }

    /// The bit `mask` (one bit set) of byte `byte`.
    const fn flag(name: &'static str, byte: usize, mask: u8, comment: &'static str) -> Signal {
        assert!(mask.count_ones() == 1, "a flag is one bit");
        Signal::bits(name, byte, mask, comment)
    }

    /// The bits `mask` (contiguous) of byte `byte`, as one number.
    const fn bits(name: &'static str, byte: usize, mask: u8, comment: &'static str) -> Signal {
        let bits = mask.count_ones();
        assert!(
            bits > 0 && bits + mask.leading_zeros() + mask.trailing_zeros() == 8,
            "the bits of a field are contiguous"
        );
        Signal {
            start: (byte * 8) as u8 + mask.trailing_zeros() as u8,
            bits: bits as u8,
            max: (1 << bits) - 1,
            ..Signal::byte(name, byte, comment)
        }
    }

    /// Bytes `from..to` that the layout leaves zero and the codec refuses otherwise.
    const fn reserved(name: &'static str, from: usize, to: usize) -> Signal {
        Signal::le(name, from..to, "reserved, always 0").range(0, 0)
    }

    const fn named(self, name: &'static str) -> Signal {
        Signal { name, ..self }
    }

    /// The multiplexer of its message.
    const fn selector(self) -> Signal {
        Signal {
            mux: Mux::Selector,
            ..self
        }
    }

    /// Only in frames whose selector is one of `values` (ascending).
    const fn when(self, values: &'static [u8]) -> Signal {
        Signal {
            mux: Mux::When(values),
            ..self
        }
    }

    const fn range(self, min: u32, max: u32) -> Signal {
        Signal { min, max, ..self }
    }

    const fn unit(self, unit: &'static str) -> Signal {
        Signal { unit, ..self }
    }

    /// A count of 10 ms, shown in ms.
    const fn ms(self) -> Signal {
        Signal {
            factor: unit::MS_PER_UNIT as u32,
            unit: "ms",
            ..self
        }
    }

    const fn values(self, values: &'static [(u8, &'static str)]) -> Signal {
        Signal { values, ..self }
    }
}

/// The schema of `kind`.
pub const fn of(kind: Kind) -> MessageSchema {
    let (summary, signals): (&str, &[Signal]) = match kind {
        Kind::PowerSet => ("Gateway to node or all: switch the power relay", &POWER_SET),
        Kind::Fault => (
            "Node to gateway: something went wrong (like CANopen EMCY)",
            &FAULT,
        ),
        Kind::DockDetected => (
            "Node to gateway: the signal loop of a dock port closed",
            &DOCK_REPORT,
        ),
        Kind::DockRemoved => (
            "Node to gateway: the signal loop of a dock port opened (relay already off)",
            &DOCK_REPORT,
        ),
        Kind::DockConfirm => (
            "Gateway to node or all: go ahead, power the docked element",
            &DOCK_CONFIRM,
        ),
        Kind::DockRefuse => (
            "Gateway to node or all: do not power it (or withdraw a confirmation)",
            &DOCK_REFUSE,
        ),
        Kind::Handshake => (
            "Mobile node to gateway: freshly powered, names its own dock port",
            &HANDSHAKE,
        ),
        Kind::Ack => ("Node to gateway: answers every acknowledged command", &ACK),
        Kind::AssignSelect => (
            "Gateway to all: select the node whose unique ID starts with these 8 bytes",
            &ASSIGN_SELECT,
        ),
        Kind::AssignCommit => (
            "Gateway to all: the selected node with this unique-ID tail takes a new node ID",
            &ASSIGN_COMMIT,
        ),
        Kind::AssignReply => ("Node to gateway: result of an AssignCommit", &ASSIGN_REPLY),
        Kind::BootUp => (
            "Node to gateway: announcement after reset (and after getting an ID)",
            &BOOT_UP,
        ),
        Kind::BuzzerSet => (
            "Gateway to node or all: buzzer off, continuous or beep pattern",
            &BUZZER_SET,
        ),
        Kind::LedSet => (
            "Gateway to node or all: LED strip off, steady or blinking",
            &LED_SET,
        ),
        Kind::Identify => (
            "Gateway to node or all: blink and beep so a person can find the element",
            &IDENTIFY,
        ),
        Kind::HealthCheck => (
            "Gateway to node or all: are you there? Answered by HealthReply",
            &HEALTH_CHECK,
        ),
        Kind::HealthReply => ("Node to gateway: state snapshot", &HEALTH_REPLY),
        Kind::StateQuery => (
            "Gateway to node or all: report these groups of your state, closed by an end report",
            &STATE_QUERY,
        ),
        Kind::StateReport => (
            "Node to gateway: one part of its state, answering a StateQuery; part selects the layout",
            &STATE_REPORT,
        ),
        Kind::DockLink => (
            "Gateway to one static node: this mobile element is the one docked on your port",
            &DOCK_LINK,
        ),
        Kind::FwBegin => (
            "Gateway to node or all: a firmware transfer of this image starts (or resumes)",
            &FW_BEGIN,
        ),
        Kind::FwEnd => (
            "Gateway to node or all: commit (verify, install, reset) or abort a transfer",
            &FW_END,
        ),
        Kind::FwQuery => (
            "Gateway to node or all: report your transfer status for this image",
            &FW_QUERY,
        ),
        Kind::FwStatus => (
            "Node to gateway: transfer phase, refusal reason, the first run of missing frames",
            &FW_STATUS,
        ),
        Kind::FwData => (
            "Gateway to node or all: six image bytes at 6 x index; the lowest priority",
            &FW_DATA,
        ),
    };
    MessageSchema {
        kind,
        summary,
        signals,
    }
}

/// Every message, in kind order.
pub fn all() -> impl Iterator<Item = MessageSchema> {
    Kind::ALL.iter().map(|k| of(*k))
}

const SEQ: &str = "sequence number, echoed by the answer";
const PORT_MAX: u32 = Port::COUNT as u32 - 1;

const OFF_ON: &[(u8, &str)] = &[(0, "off"), (1, "on")];
const ROLES: &[(u8, &str)] = &[
    (boot_up::ROLE_STATIC, "static"),
    (boot_up::ROLE_MOBILE, "mobile"),
];
const BUZZER_MODES: &[(u8, &str)] = &[
    (buzzer_set::MODE_OFF, "off"),
    (buzzer_set::MODE_CONTINUOUS, "continuous"),
    (buzzer_set::MODE_PATTERN, "pattern"),
];
const LED_MODES: &[(u8, &str)] = &[
    (led_set::MODE_OFF, "off"),
    (led_set::MODE_STEADY, "steady"),
    (led_set::MODE_BLINK, "blink"),
];

/// Every kind's value with its name, for an `Ack`'s `kind`.
static KINDS: [(u8, &str); Kind::ALL.len()] = kind_table();

const fn kind_table() -> [(u8, &'static str); Kind::ALL.len()] {
    let mut t = [(0, ""); Kind::ALL.len()];
    let mut i = 0;
    while i < t.len() {
        t[i] = (Kind::ALL[i] as u8, Kind::ALL[i].name());
        i += 1;
    }
    t
}

/// The highest assigned kind value.
const KIND_MAX: u32 = {
    let mut max = 0;
    let mut i = 0;
    while i < Kind::ALL.len() {
        if Kind::ALL[i] as u32 > max {
            max = Kind::ALL[i] as u32;
        }
        i += 1;
    }
    max
};

static POWER_SET: [Signal; 2] = [
    Signal::byte("seq", power_set::SEQ, SEQ),
    Signal::byte("on", power_set::ON, "relay state")
        .range(0, 1)
        .values(OFF_ON),
];

static FAULT: [Signal; 3] = [
    Signal::byte("code", fault::CODE, "fault code; unknown codes are kept")
        .values(FaultCode::TABLE),
    Signal::byte("arg", fault::ARG, "code-specific argument (a port, a kind)"),
    Signal::le(
        "detail",
        fault::DETAIL,
        "code-specific detail (counters, registers): docs/protocol.md, Fault codes",
    ),
];

/// `DockDetected` and `DockRemoved`.
static DOCK_REPORT: [Signal; 1] = [Signal::byte(
    "port",
    dock::PORT,
    "dock port of the reporting static element",
)
.range(0, PORT_MAX)];

static HANDSHAKE: [Signal; 1] = [Signal::byte(
    "port",
    dock::PORT,
    "the mobile element's own dock port by which it is docked",
)
.range(0, PORT_MAX)];

static DOCK_CONFIRM: [Signal; 2] = [
    Signal::byte("seq", dock_confirm::SEQ, SEQ),
    Signal::byte("port", dock_confirm::PORT, "dock port to power").range(0, PORT_MAX),
];

static DOCK_REFUSE: [Signal; 3] = [
    Signal::byte("seq", dock_refuse::SEQ, SEQ),
    Signal::byte("port", dock_refuse::PORT, "dock port refused").range(0, PORT_MAX),
    Signal::byte(
        "reason",
        dock_refuse::REASON,
        "why; unknown reasons are kept",
    )
    .values(DockRefuseReason::TABLE),
];

static ACK: [Signal; 4] = [
    Signal::byte("kind", ack::KIND, "kind of the command answered")
        .range(0, KIND_MAX)
        .values(&KINDS),
    Signal::byte("seq", ack::SEQ, "sequence number of the command answered"),
    Signal::byte(
        "result",
        ack::RESULT,
        "result; anything but ok is a refusal",
    )
    .values(AckResult::TABLE),
    Signal::byte(
        "detail",
        ack::DETAIL,
        "result-specific: for invalid_value and invalid_state the byte offset of the field",
    ),
];

static ASSIGN_SELECT: [Signal; 8] = {
    let f = assign_select::UID_HEAD.start;
    [
        Signal::uid("uid_0", f, 0),
        Signal::uid("uid_1", f, 1),
        Signal::uid("uid_2", f, 2),
        Signal::uid("uid_3", f, 3),
        Signal::uid("uid_4", f, 4),
        Signal::uid("uid_5", f, 5),
        Signal::uid("uid_6", f, 6),
        Signal::uid("uid_7", f, 7),
    ]
};

static ASSIGN_COMMIT: [Signal; 6] = {
    let f = assign_commit::UID_TAIL.start;
    [
        Signal::uid("uid_8", f, 0),
        Signal::uid("uid_9", f, 1),
        Signal::uid("uid_10", f, 2),
        Signal::uid("uid_11", f, 3),
        Signal::le("id", assign_commit::ID, "the node ID to take")
            .range(NodeId::FIRST_SC.get() as u32, NodeId::LAST_SC.get() as u32),
        Signal::byte("seq", assign_commit::SEQ, SEQ),
    ]
};

static ASSIGN_REPLY: [Signal; 7] = {
    let f = assign_reply::UID_TAIL.start;
    [
        Signal::byte("seq", assign_reply::SEQ, "sequence number of the commit"),
        Signal::byte("result", assign_reply::RESULT, "result of the assignment")
            .values(AckResult::TABLE),
        Signal::le(
            "id",
            assign_reply::ID,
            "the node ID now in force; 0xFFE (4094) = still none",
        )
        .range(
            NodeId::FIRST_SC.get() as u32,
            NodeId::UNCONFIGURED.get() as u32,
        ),
        Signal::uid("uid_8", f, 0),
        Signal::uid("uid_9", f, 1),
        Signal::uid("uid_10", f, 2),
        Signal::uid("uid_11", f, 3),
    ]
};

static BOOT_UP: [Signal; 5] = [
    Signal::byte("major", boot_up::MAJOR, "protocol version, major"),
    Signal::byte("minor", boot_up::MINOR, "protocol version, minor"),
    Signal::byte("role", boot_up::ROLE, "static (wired on the bus) or mobile")
        .range(0, boot_up::ROLE_MOBILE as u32)
        .values(ROLES),
    Signal::byte("ports", boot_up::PORTS, "number of dock ports").range(0, Port::COUNT as u32),
    Signal::byte(
        "reset",
        boot_up::RESET,
        "why the node started; unknown reasons are kept",
    )
    .values(ResetReason::TABLE),
];

static BUZZER_SET: [Signal; 6] =
    concat(&[&[Signal::byte("seq", buzzer_set::SEQ, SEQ)], &BUZZER_FIELDS]);

/// The `BuzzerSet` fields after `seq`, which a `Buzzer` state report carries at the same offsets.
const BUZZER_FIELDS: [Signal; 5] = [
    Signal::byte(
        "mode",
        buzzer_set::MODE,
        "off, continuous tone or beep pattern",
    )
    .range(0, buzzer_set::MODE_PATTERN as u32)
    .values(BUZZER_MODES),
    Signal::le(
        "freq",
        buzzer_set::FREQ,
        "tone frequency, 20 to 20000 Hz; 0 when off",
    )
    .range(0, BuzzerCommand::MAX_FREQ_HZ as u32)
    .unit("Hz"),
    Signal::byte("on", buzzer_set::ON, "beep length (pattern); 0 otherwise").ms(),
    Signal::byte(
        "off",
        buzzer_set::OFF,
        "pause length (pattern); 0 otherwise",
    )
    .ms(),
    Signal::byte(
        "count",
        buzzer_set::COUNT,
        "beeps (pattern), 0 = until told otherwise; 0 otherwise",
    ),
];

static LED_SET: [Signal; 8] = concat(&[&[Signal::byte("seq", led_set::SEQ, SEQ)], &LED_FIELDS]);

/// The `LedSet` fields after `seq`, which a `Led` state report carries at the same offsets.
const LED_FIELDS: [Signal; 7] = [
    Signal::byte("mode", led_set::MODE, "off, steady or blinking")
        .range(0, led_set::MODE_BLINK as u32)
        .values(LED_MODES),
    Signal::byte("r", led_set::R, "red; 0 when off"),
    Signal::byte("g", led_set::G, "green; 0 when off"),
    Signal::byte("b", led_set::B, "blue; 0 when off"),
    Signal::byte(
        "brightness",
        led_set::BRIGHTNESS,
        "scales all channels, 255 = full; 0 when off",
    ),
    Signal::byte(
        "period",
        led_set::PERIOD,
        "blink period (blink); 0 otherwise",
    )
    .ms(),
    Signal::byte(
        "duty",
        led_set::DUTY,
        "share of the period lit (blink); 0 otherwise",
    )
    .range(0, LedCommand::MAX_DUTY_PCT as u32)
    .unit("%"),
];

static IDENTIFY: [Signal; 2] = [
    Signal::byte("seq", identify::SEQ, SEQ),
    Signal::byte(
        "seconds",
        identify::SECONDS,
        "how long to blink and beep; 0 stops",
    )
    .unit("s"),
];

static HEALTH_CHECK: [Signal; 1] = [Signal::byte(
    "seq",
    health_check::SEQ,
    "sequence number, echoed in every reply",
)];

static HEALTH_REPLY: [Signal; 13] = {
    let f = health_reply::FLAGS;
    [
        Signal::byte(
            "seq",
            health_reply::SEQ,
            "sequence number of the check answered",
        ),
        Signal::flag("relay", f, HealthFlags::RELAY, "power relay on"),
        Signal::flag("led_on", f, HealthFlags::LED_ON, "LED strip lit"),
        Signal::flag("led_blink", f, HealthFlags::LED_BLINK, "LED strip blinking"),
        Signal::flag(
            "buzzer",
            f,
            HealthFlags::BUZZER,
            "buzzer sounding or running a pattern",
        ),
        Signal::flag(
            "mobile",
            f,
            HealthFlags::MOBILE,
            "the node is a mobile element",
        ),
        Signal::flag(
            "error_passive",
            f,
            HealthFlags::ERROR_PASSIVE,
            "CAN controller error-passive",
        ),
        Signal::flag("identify", f, HealthFlags::IDENTIFY, "identify running"),
        Signal::flag("flag_7", f, 1 << 7, "unassigned flag, sent as 0"),
        Signal::byte(
            "loops",
            health_reply::LOOPS,
            "signal-loop bitmap: bit n set = something docked on port n",
        ),
        Signal::byte("tec", health_reply::TEC, "CAN transmit error counter"),
        Signal::byte("rec", health_reply::REC, "CAN receive error counter"),
        Signal::le(
            "uptime",
            health_reply::UPTIME,
            "seconds since boot, saturating",
        )
        .range(0, HealthReply::MAX_UPTIME_S)
        .unit("s"),
    ]
};

static STATE_QUERY: [Signal; 5] = concat(&[
    &[Signal::byte(
        "seq",
        state_query::SEQ,
        "sequence number, echoed by the closing end report",
    )],
    &named(
        state_groups(state_query::PARTS),
        ["actuators", "docking", "identity", "parts_unassigned"],
    ),
]);

/// `StateReport`: `part` selects the layout of bytes 1 to 7. Every part number has one: the known
/// parts their fields (prefixed with the part's name, the UID bytes named as in `AssignSelect`),
/// every other number the raw bytes of [`StateReport::Other`].
static STATE_REPORT: [Signal; 72] = concat(&[
    &[Signal::byte(
        "part",
        state_report::PART,
        "which part of the node's state this report carries; selects the layout",
    )
    .values(PART_NAMES)
    .selector()],
    &in_part(
        LED_FIELDS,
        [
            "led_mode",
            "led_r",
            "led_g",
            "led_b",
            "led_brightness",
            "led_period",
            "led_duty",
        ],
        &[StateReport::LED],
    ),
    &in_part(
        BUZZER_FIELDS,
        [
            "buzzer_mode",
            "buzzer_freq",
            "buzzer_on",
            "buzzer_off",
            "buzzer_count",
        ],
        &[StateReport::BUZZER],
    ),
    &[Signal::reserved(
        "buzzer_reserved",
        Message::len_of(Kind::BuzzerSet) as usize,
        STATE_REPORT_LEN,
    )
    .when(&[StateReport::BUZZER])],
    &in_part(
        [
            Signal::byte("relay", state_report::power::RELAY, "relay state")
                .range(0, 1)
                .values(OFF_ON),
            Signal::byte(
                "loops",
                state_report::power::LOOPS,
                "debounced signal-loop bitmap: bit n set = something docked on port n",
            ),
            Signal::byte(
                "confirmed",
                state_report::power::CONFIRMED,
                "bitmap of the ports the gateway confirmed that are still docked",
            ),
            Signal::byte(
                "identify",
                state_report::power::IDENTIFY,
                "identify time remaining, rounded up; 0 = not identifying",
            )
            .unit("s"),
            Signal::byte(
                "role",
                state_report::power::ROLE,
                "static (wired on the bus) or mobile",
            )
            .range(0, boot_up::ROLE_MOBILE as u32)
            .values(ROLES),
            Signal::byte("ports", state_report::power::PORTS, "number of dock ports")
                .range(0, Port::COUNT as u32),
            Signal::reserved("reserved", state_report::power::PORTS + 1, STATE_REPORT_LEN),
        ],
        [
            "power_relay",
            "power_loops",
            "power_confirmed",
            "power_identify",
            "power_role",
            "power_ports",
            "power_reserved",
        ],
        &[StateReport::POWER],
    ),
    &in_part(
        [
            Signal::flag(
                "closed",
                state_report::dock::FLAGS,
                DockState::CLOSED,
                "the port's signal loop is closed (debounced)",
            ),
            Signal::flag(
                "confirmed",
                state_report::dock::FLAGS,
                DockState::CONFIRMED,
                "the gateway confirmed the docking and it is still docked",
            ),
            Signal::flag(
                "linked",
                state_report::dock::FLAGS,
                DockState::LINKED,
                "a mobile element is linked: set exactly when partner is not 0xFFF",
            ),
            Signal::bits(
                "flags_reserved",
                state_report::dock::FLAGS,
                !(DockState::CLOSED | DockState::CONFIRMED | DockState::LINKED),
                "unassigned flags, always 0",
            )
            .range(0, 0),
            PARTNER[0],
            PARTNER[1],
            Signal::reserved(
                "reserved",
                state_report::dock::PARTNER_PORT + 1,
                STATE_REPORT_LEN,
            ),
        ],
        [
            "dock_closed",
            "dock_confirmed",
            "dock_linked",
            "dock_flags_reserved",
            "dock_partner",
            "dock_partner_port",
            "dock_reserved",
        ],
        &DOCK_PARTS,
    ),
    &in_part(
        [
            Signal::byte(
                "major",
                state_report::firmware::MAJOR,
                "firmware version, major",
            ),
            Signal::byte(
                "minor",
                state_report::firmware::MINOR,
                "firmware version, minor",
            ),
            Signal::byte(
                "patch",
                state_report::firmware::PATCH,
                "firmware version, patch",
            ),
            Signal::flag(
                "trial",
                state_report::firmware::FLAGS,
                StateReport::FIRMWARE_TRIAL,
                "running a trial image that has not confirmed itself yet",
            ),
            Signal::bits(
                "flags_reserved",
                state_report::firmware::FLAGS,
                !StateReport::FIRMWARE_TRIAL,
                "unassigned flags, always 0",
            )
            .range(0, 0),
            Signal::reserved(
                "reserved",
                state_report::firmware::FLAGS + 1,
                STATE_REPORT_LEN,
            ),
        ],
        [
            "firmware_major",
            "firmware_minor",
            "firmware_patch",
            "firmware_trial",
            "firmware_flags_reserved",
            "firmware_reserved",
        ],
        &[StateReport::FIRMWARE],
    ),
    &in_part(
        bytes_of(
            state_report::IMAGE_HASH,
            "a byte of the running image's hash (all 0 = unknown)",
        ),
        [
            "image_hash_0",
            "image_hash_1",
            "image_hash_2",
            "image_hash_3",
            "image_hash_4",
            "image_hash_5",
            "image_hash_6",
        ],
        &[StateReport::IMAGE_HASH],
    ),
    &in_part(
        bytes_of(state_report::UID_LOW, UID_BYTE),
        [
            "uid_0", "uid_1", "uid_2", "uid_3", "uid_4", "uid_5", "uid_6",
        ],
        &[StateReport::UID_LOW],
    ),
    &in_part(
        bytes_of(state_report::UID_HIGH, UID_BYTE),
        ["uid_7", "uid_8", "uid_9", "uid_10", "uid_11"],
        &[StateReport::UID_HIGH],
    ),
    &[Signal::reserved(
        "uid_high_reserved",
        state_report::UID_HIGH.end,
        STATE_REPORT_LEN,
    )
    .when(&[StateReport::UID_HIGH])],
    &in_part(
        [
            Signal::byte(
                "major",
                state_report::protocol::MAJOR,
                "protocol version the node speaks, major (as in its BootUp)",
            ),
            Signal::byte(
                "minor",
                state_report::protocol::MINOR,
                "protocol version the node speaks, minor",
            ),
            // Five reserved bytes: a signal carries at most 32 bits.
            Signal::reserved(
                "reserved",
                state_report::protocol::MINOR + 1,
                STATE_REPORT_LEN - 1,
            ),
            Signal::reserved("reserved", STATE_REPORT_LEN - 1, STATE_REPORT_LEN),
        ],
        [
            "protocol_major",
            "protocol_minor",
            "protocol_reserved",
            "protocol_reserved_7",
        ],
        &[StateReport::PROTOCOL],
    ),
    &in_part(
        concat::<7>(&[
            &[Signal::byte(
                "seq",
                state_report::end::SEQ,
                "sequence number of the query answered",
            )],
            &state_groups(state_report::end::PARTS),
            &[
                Signal::byte(
                    "count",
                    state_report::end::COUNT,
                    "reports sent before this one in the reply",
                ),
                Signal::reserved("reserved", state_report::end::COUNT + 1, STATE_REPORT_LEN),
            ],
        ]),
        [
            "end_seq",
            "end_actuators",
            "end_docking",
            "end_identity",
            "end_parts_unassigned",
            "end_count",
            "end_reserved",
        ],
        &[StateReport::END],
    ),
    &in_part(
        bytes_of(
            state_report::DATA,
            "a byte of a part this version does not know, kept as received",
        ),
        [
            "data_1", "data_2", "data_3", "data_4", "data_5", "data_6", "data_7",
        ],
        &UNKNOWN_PARTS,
    ),
]);

static DOCK_LINK: [Signal; 4] = [
    Signal::byte("seq", dock_link::SEQ, SEQ),
    Signal::byte("port", dock_link::PORT, "the static element's dock port").range(0, PORT_MAX),
    PARTNER[0],
    PARTNER[1],
];

const IMAGE_ID: &str = "the image: first 4 bytes (LE) of its payload SHA-512";

static FW_BEGIN: [Signal; 4] = [
    Signal::le("image_id", fw_begin::IMAGE_ID, IMAGE_ID),
    Signal::le("len", fw_begin::LEN, "image length: header block + payload").unit("B"),
    Signal::flag("force", fw_begin::FLAGS, 0x01, "accept a downgrade").values(OFF_ON),
    Signal::bits(
        "flags_reserved",
        fw_begin::FLAGS,
        0xFE,
        "reserved, always 0",
    )
    .range(0, 0),
];

static FW_END: [Signal; 2] = [
    Signal::le("image_id", fw_end::IMAGE_ID, IMAGE_ID),
    Signal::byte("action", fw_end::ACTION, "what to do with the transfer")
        .range(1, 2)
        .values(FwAction::TABLE),
];

static FW_QUERY: [Signal; 1] = [Signal::le("image_id", fw_query::IMAGE_ID, IMAGE_ID)];

static FW_STATUS: [Signal; 5] = [
    Signal::byte(
        "phase",
        fw_status::PHASE,
        "where the node is in the transfer",
    )
    .values(FwPhase::TABLE),
    Signal::byte(
        "reason",
        fw_status::REASON,
        "why it refused; none otherwise",
    )
    .values(FwRefusal::TABLE),
    Signal::le(
        "first_missing",
        fw_status::FIRST_MISSING,
        "first frame index still missing",
    ),
    Signal::le(
        "run",
        fw_status::RUN,
        "frames missing from first_missing on without a gap",
    ),
    Signal::le("missing", fw_status::MISSING, "frames missing in all"),
];

const FW_BYTE: &str = "an image byte";

static FW_DATA: [Signal; 7] = {
    let f = fw_data::DATA.start;
    [
        Signal::le(
            "index",
            fw_data::INDEX,
            "frame index: the bytes are at 6 x index",
        ),
        Signal::byte("data_0", f, FW_BYTE),
        Signal::byte("data_1", f + 1, FW_BYTE),
        Signal::byte("data_2", f + 2, FW_BYTE),
        Signal::byte("data_3", f + 3, FW_BYTE),
        Signal::byte("data_4", f + 4, FW_BYTE),
        Signal::byte("data_5", f + 5, FW_BYTE),
    ]
};

const STATE_REPORT_LEN: usize = Message::len_of(Kind::StateReport) as usize;

const UID_BYTE: &str = "a byte of the 96-bit STM32 unique ID";

/// The names of the part numbers (a `StateReport`'s `part`).
const PART_NAMES: &[(u8, &str)] = &[
    (StateReport::LED, "led"),
    (StateReport::BUZZER, "buzzer"),
    (StateReport::POWER, "power"),
    (StateReport::DOCK, "dock_0"),
    (StateReport::DOCK | 1, "dock_1"),
    (StateReport::DOCK | 2, "dock_2"),
    (StateReport::DOCK | 3, "dock_3"),
    (StateReport::DOCK | 4, "dock_4"),
    (StateReport::DOCK | 5, "dock_5"),
    (StateReport::DOCK | 6, "dock_6"),
    (StateReport::DOCK | 7, "dock_7"),
    (StateReport::FIRMWARE, "firmware"),
    (StateReport::IMAGE_HASH, "image_hash"),
    (StateReport::UID_LOW, "uid_low"),
    (StateReport::UID_HIGH, "uid_high"),
    (StateReport::PROTOCOL, "protocol"),
    (StateReport::END, "end"),
];

/// The part numbers of the `Dock(port)` parts, one per port: they share one layout.
const DOCK_PARTS: [u8; Port::COUNT as usize] = {
    let mut t = [0; Port::COUNT as usize];
    let mut i = 0;
    while i < t.len() {
        t[i] = StateReport::DOCK | i as u8;
        i += 1;
    }
    t
};

/// How many part numbers are not [`StateReport::is_known_part`].
const UNKNOWN_PART_COUNT: usize = {
    let mut n = 0;
    let mut part = 0;
    while part <= u8::MAX as usize {
        if !StateReport::is_known_part(part as u8) {
            n += 1;
        }
        part += 1;
    }
    n
};

/// The part numbers this version does not know: they decode as [`StateReport::Other`].
const UNKNOWN_PARTS: [u8; UNKNOWN_PART_COUNT] = {
    let mut t = [0; UNKNOWN_PART_COUNT];
    let mut n = 0;
    let mut part = 0;
    while part <= u8::MAX as usize {
        if !StateReport::is_known_part(part as u8) {
            t[n] = part as u8;
            n += 1;
        }
        part += 1;
    }
    t
};

/// A dock partner as [`Message::DockLink`] and a `Dock(port)` report carry it: a node ID, `0xFFF`
/// for none, and its port, 0 for none. The offsets are the same in both.
const PARTNER: [Signal; 2] = {
    assert!(
        dock_link::PARTNER.start == state_report::dock::PARTNER.start
            && dock_link::PARTNER_PORT == state_report::dock::PARTNER_PORT
    );
    [
        Signal::le(
            "partner",
            dock_link::PARTNER,
            "node ID of the mobile element docked there, 0x001 to 0xFFD; 0xFFF (4095) = none",
        )
        .range(
            NodeId::FIRST_SC.get() as u32,
            NodeId::BROADCAST.get() as u32,
        ),
        Signal::byte(
            "partner_port",
            dock_link::PARTNER_PORT,
            "the mobile element's own dock port; 0 when none",
        )
        .range(0, PORT_MAX),
    ]
};

/// The groups of a [`StateParts`] bitmap at byte `byte`, one bit each, and the bits version 1.1
/// does not define as one number (unnamed: see [`named`]).
const fn state_groups(byte: usize) -> [Signal; 4] {
    [
        Signal::flag(
            "",
            byte,
            StateParts::ACTUATORS,
            "group actuators: the led, buzzer and power parts",
        ),
        Signal::flag(
            "",
            byte,
            StateParts::DOCKING,
            "group docking: a dock part per port closed, confirmed or linked",
        ),
        Signal::flag(
            "",
            byte,
            StateParts::IDENTITY,
            "group identity: the firmware, image_hash, uid_low, uid_high and protocol parts",
        ),
        Signal::bits(
            "",
            byte,
            !StateParts::ALL.0,
            "groups version 1.1 does not define: sent as 0, kept, ignored by nodes",
        ),
    ]
}

/// One 8-bit signal per byte of `field` (unnamed: see [`named`]).
const fn bytes_of<const N: usize>(field: Field, comment: &'static str) -> [Signal; N] {
    assert!(field.end - field.start == N, "one signal per byte");
    let mut out = [Signal::byte("", 0, comment); N];
    let mut i = 0;
    while i < N {
        out[i] = Signal::byte("", field.start + i, comment);
        i += 1;
    }
    out
}

/// `fields` renamed `names`: a layout written once and used in several messages, or unnamed.
const fn named<const N: usize>(fields: [Signal; N], names: [&'static str; N]) -> [Signal; N] {
    let mut out = fields;
    let mut i = 0;
    while i < N {
        out[i] = fields[i].named(names[i]);
        i += 1;
    }
    out
}

/// `fields` renamed `names` as the layout of the state-report parts `parts` (signal names are
/// unique in a message, so each part's fields carry the part's name).
const fn in_part<const N: usize>(
    fields: [Signal; N],
    names: [&'static str; N],
    parts: &'static [u8],
) -> [Signal; N] {
    let mut out = named(fields, names);
    let mut i = 0;
    while i < N {
        out[i] = out[i].when(parts);
        i += 1;
    }
    out
}

/// The signals of `parts` one after the other; `N` is their number.
const fn concat<const N: usize>(parts: &[&[Signal]]) -> [Signal; N] {
    let mut out = [Signal::byte("", 0, ""); N];
    let mut n = 0;
    let mut i = 0;
    while i < parts.len() {
        let mut j = 0;
        while j < parts[i].len() {
            out[n] = parts[i][j];
            n += 1;
            j += 1;
        }
        i += 1;
    }
    assert!(n == N, "N is the number of signals");
    out
}
