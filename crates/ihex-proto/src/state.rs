//! State read-back: what a [`crate::Message::StateQuery`] asks for and the
//! [`crate::Message::StateReport`] parts a node answers with, plus the dock link they report.
//!
//! A reply is one report per part of the groups asked, in ascending part number, closed by
//! [`StateReport::End`] (which echoes the query's `seq` and counts the reports before it, so the
//! gateway knows the reply is complete and whether a frame of it was lost). Part numbers are
//! spaced by group so each group can grow: `0x00..=0x0F` actuators, `0x10..=0x1F` docking,
//! `0x20..=0x2F` identity, `0xFF` end. A part this version does not know decodes as
//! [`StateReport::Other`] with its raw bytes, so an older gateway survives a newer node; known
//! parts are checked like every other message (ranges, reserved bytes zero).

use core::fmt;

use crate::field::state_report as f;
use crate::message::{
    bad_value, check_buzzer, check_led, decode_buzzer, decode_led, decode_partner, encode_buzzer,
    encode_led, encode_partner, reserved,
};
use crate::{BootRole, BuzzerCommand, DecodeError, Kind, LedCommand, NodeId, Port, Seq};

/// The groups of state a [`crate::Message::StateQuery`] asks for: a bitmap.
///
/// Bits this version does not define are carried as they are and ignored by a node that does
/// not know them (senders of version 1.1 set them to 0): a newer gateway asking for a newer group
/// still gets the groups an older node knows, and [`StateReport::End`] says which those were.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StateParts(pub u8);

impl StateParts {
    /// LED, buzzer, relay, identify and the port bitmaps: parts `Led`, `Buzzer`, `Power`.
    pub const ACTUATORS: u8 = 1 << 0;
    /// One `Dock(port)` part per port that is closed, confirmed or linked.
    pub const DOCKING: u8 = 1 << 1;
    /// Parts `Firmware`, `ImageHash`, `UidLow`, `UidHigh`, `Protocol`.
    pub const IDENTITY: u8 = 1 << 2;
    /// Every group this version defines.
    pub const ALL: StateParts = StateParts(Self::ACTUATORS | Self::DOCKING | Self::IDENTITY);

    /// True when every bit of `group` is set.
    pub const fn contains(self, group: u8) -> bool {
        self.0 & group == group
    }

    /// Only the groups this version defines.
    pub const fn known(self) -> StateParts {
        StateParts(self.0 & Self::ALL.0)
    }
}

/// The mobile element docked on a static element's port, as [`crate::Message::DockLink`] sets it
/// and [`DockState`] reports it.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DockPartner {
    /// The mobile element's node ID (`0x001..=0xFFD`; `0xFFF` on the wire means none).
    pub node: NodeId,
    /// Its own port by which it is docked.
    pub port: Port,
}

/// A firmware version, `major.minor.patch`, as `StateReport::Firmware` carries it.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FirmwareVersion {
    /// Major.
    pub major: u8,
    /// Minor.
    pub minor: u8,
    /// Patch.
    pub patch: u8,
}

impl FirmwareVersion {
    /// A version from its three numbers.
    pub const fn new(major: u8, minor: u8, patch: u8) -> Self {
        FirmwareVersion {
            major,
            minor,
            patch,
        }
    }

    /// Parses `MAJOR.MINOR.PATCH` (each `0..=255`, decimal), optionally followed by a semver
    /// pre-release (`-…`) or build (`+…`) suffix, which is ignored: the wire has no room for it.
    /// `const`, so a firmware can turn `env!("CARGO_PKG_VERSION")` into its version at compile time.
    pub const fn parse(s: &str) -> Option<Self> {
        let b = s.as_bytes();
        let mut nums = [0u16; 3];
        let mut n = 0;
        let mut digits = 0;
        let mut i = 0;
        while i < b.len() {
            let c = b[i];
            if c.is_ascii_digit() {
                // No leading zeros (as in semver), and at most three digits.
                if digits == 3 || (digits == 1 && nums[n] == 0) {
                    return None;
                }
                nums[n] = nums[n] * 10 + (c - b'0') as u16;
                digits += 1;
            } else if c == b'.' && n < 2 && digits > 0 {
                n += 1;
                digits = 0;
            } else if (c == b'-' || c == b'+') && n == 2 && digits > 0 && i + 1 < b.len() {
                break;
            } else {
                return None;
            }
            i += 1;
        }
        if n != 2 || digits == 0 || nums[0] > 255 || nums[1] > 255 || nums[2] > 255 {
            return None;
        }
        Some(FirmwareVersion::new(
            nums[0] as u8,
            nums[1] as u8,
            nums[2] as u8,
        ))
    }
}

impl core::str::FromStr for FirmwareVersion {
    type Err = crate::ParseError;

    /// See [`FirmwareVersion::parse`].
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        FirmwareVersion::parse(s).ok_or(crate::ParseError::Version)
    }
}

impl fmt::Display for FirmwareVersion {
    /// `major.minor.patch`, in one write: every state document shows it, and `write!` of three
    /// numbers costs ten times as much.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut buf = [0u8; 11];
        let mut n = 0;
        for (i, part) in [self.major, self.minor, self.patch].into_iter().enumerate() {
            if i > 0 {
                buf[n] = b'.';
                n += 1;
            }
            let digits = [part / 100, part / 10 % 10, part % 10];
            let first = if part >= 100 {
                0
            } else if part >= 10 {
                1
            } else {
                2
            };
            for d in &digits[first..] {
                buf[n] = b'0' + d;
                n += 1;
            }
        }
        f.write_str(core::str::from_utf8(&buf[..n]).map_err(|_| fmt::Error)?)
    }
}

/// The `Power` part: relay, port bitmaps, identify, role and port count.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PowerState {
    /// The relay is on.
    pub relay: bool,
    /// Signal-loop bitmap (debounced): bit *n* set = something docked on port *n*.
    pub loops: u8,
    /// Ports the gateway confirmed that are still docked.
    pub confirmed: u8,
    /// Seconds of identify remaining, rounded up; 0 = not identifying.
    pub identify_s: u8,
    /// Static or mobile element.
    pub role: BootRole,
    /// Number of dock ports (`0..=8`).
    pub ports: u8,
}

/// A `Dock(port)` part: what a static element knows about one of its ports.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DockState {
    /// The port's signal loop is closed (debounced).
    pub closed: bool,
    /// The gateway confirmed the docking and it is still docked.
    pub confirmed: bool,
    /// The mobile element the gateway linked to this port ([`crate::Message::DockLink`]).
    pub partner: Option<DockPartner>,
}

impl DockState {
    /// Flag bit: loop closed.
    pub const CLOSED: u8 = 1 << 0;
    /// Flag bit: confirmed.
    pub const CONFIRMED: u8 = 1 << 1;
    /// Flag bit: linked (a partner follows).
    pub const LINKED: u8 = 1 << 2;
}

/// One part of a node's state ([`crate::Message::StateReport`]). See `docs/protocol.md`.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StateReport {
    /// `0x00`: the commanded LED (identify does not show here), as `LedSet` carries it.
    Led(LedCommand),
    /// `0x01`: the commanded buzzer in force (a finite pattern that has ended is `Off`).
    Buzzer(BuzzerCommand),
    /// `0x02`: relay, bitmaps, identify, role and port count.
    Power(PowerState),
    /// `0x10 | port`: one dock port of a static element.
    Dock {
        /// The port.
        port: Port,
        /// What the element knows about it.
        state: DockState,
    },
    /// `0x20`: the running firmware's version.
    Firmware {
        /// Version.
        version: FirmwareVersion,
        /// Running a trial image that has not confirmed itself yet.
        trial: bool,
    },
    /// `0x21`: the first 7 bytes of the running image's hash (all zero = unknown).
    ImageHash([u8; 7]),
    /// `0x22`: unique-ID bytes 0–6 ([`crate::Uid::low`]).
    UidLow([u8; 7]),
    /// `0x23`: unique-ID bytes 7–11 ([`crate::Uid::high`]).
    UidHigh([u8; 5]),
    /// `0x24` (protocol 1.3): the protocol version the node speaks, as its `BootUp` announces it,
    /// so that a gateway that missed the `BootUp` (it restarted) still knows it.
    Protocol {
        /// `(major, minor)`, as [`crate::PROTOCOL_VERSION`].
        version: (u8, u8),
    },
    /// `0xFF`: the reply to one query is complete.
    End {
        /// The query's sequence number.
        seq: Seq,
        /// The groups answered: those asked that this node knows.
        parts: StateParts,
        /// Reports sent before this one in the reply.
        count: u8,
    },
    /// A part this version does not know, kept as received.
    Other {
        /// Its part number (never one of the known parts).
        part: u8,
        /// Bytes 1–7.
        data: [u8; 7],
    },
}

impl StateReport {
    /// Part number of [`StateReport::Led`].
    pub const LED: u8 = 0x00;
    /// Part number of [`StateReport::Buzzer`].
    pub const BUZZER: u8 = 0x01;
    /// Part number of [`StateReport::Power`].
    pub const POWER: u8 = 0x02;
    /// Part number of [`StateReport::Dock`] for port 0; port *n* is `DOCK | n`.
    pub const DOCK: u8 = 0x10;
    /// Part number of [`StateReport::Firmware`].
    pub const FIRMWARE: u8 = 0x20;
    /// Part number of [`StateReport::ImageHash`].
    pub const IMAGE_HASH: u8 = 0x21;
    /// Part number of [`StateReport::UidLow`].
    pub const UID_LOW: u8 = 0x22;
    /// Part number of [`StateReport::UidHigh`].
    pub const UID_HIGH: u8 = 0x23;
    /// Part number of [`StateReport::Protocol`].
    pub const PROTOCOL: u8 = 0x24;
    /// Part number of [`StateReport::End`].
    pub const END: u8 = 0xFF;

    /// Firmware flag bit: running an unconfirmed trial image.
    pub const FIRMWARE_TRIAL: u8 = 1 << 0;

    /// The part number (byte 0).
    pub const fn part(&self) -> u8 {
        match self {
            StateReport::Led(_) => Self::LED,
            StateReport::Buzzer(_) => Self::BUZZER,
            StateReport::Power(_) => Self::POWER,
            StateReport::Dock { port, .. } => Self::DOCK | port.get(),
            StateReport::Firmware { .. } => Self::FIRMWARE,
            StateReport::ImageHash(_) => Self::IMAGE_HASH,
            StateReport::UidLow(_) => Self::UID_LOW,
            StateReport::UidHigh(_) => Self::UID_HIGH,
            StateReport::Protocol { .. } => Self::PROTOCOL,
            StateReport::End { .. } => Self::END,
            StateReport::Other { part, .. } => *part,
        }
    }

    /// True for the part numbers this version decodes (anything else is [`StateReport::Other`]).
    pub const fn is_known_part(part: u8) -> bool {
        matches!(
            part,
            Self::LED | Self::BUZZER | Self::POWER | 0x10
                ..=0x17
                    | Self::FIRMWARE
                    | Self::IMAGE_HASH
                    | Self::UID_LOW
                    | Self::UID_HIGH
                    | Self::PROTOCOL
                    | Self::END
        )
    }

    /// Value ranges (what decoding accepts).
    pub(crate) fn validate(&self) -> Result<(), DecodeError> {
        let kind = Kind::StateReport;
        match *self {
            StateReport::Led(cmd) => check_led(kind, cmd),
            StateReport::Buzzer(cmd) => check_buzzer(kind, cmd),
            StateReport::Power(p) if p.ports > Port::COUNT => {
                Err(bad_value(kind, "ports", p.ports as u32))
            }
            StateReport::Dock {
                state: DockState {
                    partner: Some(p), ..
                },
                ..
            } if !p.node.is_sc() => Err(bad_value(kind, "partner", p.node.get() as u32)),
            // An `Other` with a known number would encode into bytes that decode as that part.
            StateReport::Other { part, .. } if Self::is_known_part(part) => {
                Err(bad_value(kind, "part", part as u32))
            }
            _ => Ok(()),
        }
    }

    /// Writes the 8 data bytes (no validation).
    pub(crate) fn encode_into(&self, b: &mut [u8; 8]) {
        b[f::PART] = self.part();
        match *self {
            StateReport::Led(cmd) => encode_led(cmd, b),
            StateReport::Buzzer(cmd) => encode_buzzer(cmd, b),
            StateReport::Power(p) => {
                b[f::power::RELAY] = p.relay as u8;
                b[f::power::LOOPS] = p.loops;
                b[f::power::CONFIRMED] = p.confirmed;
                b[f::power::IDENTIFY] = p.identify_s;
                b[f::power::ROLE] = matches!(p.role, BootRole::Mobile) as u8;
                b[f::power::PORTS] = p.ports;
            }
            StateReport::Dock { state, .. } => {
                let flag = |on: bool, bit: u8| if on { bit } else { 0 };
                b[f::dock::FLAGS] = flag(state.closed, DockState::CLOSED)
                    | flag(state.confirmed, DockState::CONFIRMED)
                    | flag(state.partner.is_some(), DockState::LINKED);
                encode_partner(state.partner, b, f::dock::PARTNER, f::dock::PARTNER_PORT);
            }
            StateReport::Firmware { version, trial } => {
                b[f::firmware::MAJOR] = version.major;
                b[f::firmware::MINOR] = version.minor;
                b[f::firmware::PATCH] = version.patch;
                b[f::firmware::FLAGS] = if trial { Self::FIRMWARE_TRIAL } else { 0 };
            }
            StateReport::ImageHash(h) => b[f::IMAGE_HASH].copy_from_slice(&h),
            StateReport::UidLow(u) => b[f::UID_LOW].copy_from_slice(&u),
            StateReport::UidHigh(u) => b[f::UID_HIGH].copy_from_slice(&u),
            StateReport::Protocol {
                version: (major, minor),
            } => {
                b[f::protocol::MAJOR] = major;
                b[f::protocol::MINOR] = minor;
            }
            StateReport::End { seq, parts, count } => {
                b[f::end::SEQ] = seq;
                b[f::end::PARTS] = parts.0;
                b[f::end::COUNT] = count;
            }
            StateReport::Other { data, .. } => b[f::DATA].copy_from_slice(&data),
        }
    }

    /// Reads the 8 data bytes (length already checked): known parts are checked field by field,
    /// unknown ones kept as [`StateReport::Other`].
    pub(crate) fn decode(d: &[u8]) -> Result<StateReport, DecodeError> {
        let kind = Kind::StateReport;
        let bad = |field: &'static str, raw: u8| bad_value(kind, field, raw as u32);
        let bit = |field: &'static str, raw: u8| match raw {
            0 => Ok(false),
            1 => Ok(true),
            v => Err(bad(field, v)),
        };
        let mut data = [0; 7];
        data.copy_from_slice(&d[f::DATA]);
        let part = d[f::PART];
        let report = match part {
            // The LED layout fills all 8 bytes: nothing is reserved after it.
            Self::LED => StateReport::Led(decode_led(kind, d)?),
            Self::BUZZER => {
                let cmd = decode_buzzer(kind, d)?;
                reserved(kind, d, crate::Message::len_of(Kind::BuzzerSet) as usize)?;
                StateReport::Buzzer(cmd)
            }
            Self::POWER => {
                reserved(kind, d, f::power::PORTS + 1)?;
                StateReport::Power(PowerState {
                    relay: bit("relay", d[f::power::RELAY])?,
                    loops: d[f::power::LOOPS],
                    confirmed: d[f::power::CONFIRMED],
                    identify_s: d[f::power::IDENTIFY],
                    role: match d[f::power::ROLE] {
                        0 => BootRole::Static,
                        1 => BootRole::Mobile,
                        v => return Err(bad("role", v)),
                    },
                    ports: d[f::power::PORTS],
                })
            }
            0x10..=0x17 => {
                let flags = d[f::dock::FLAGS];
                let known = DockState::CLOSED | DockState::CONFIRMED | DockState::LINKED;
                if flags & !known != 0 {
                    return Err(bad("flags", flags));
                }
                reserved(kind, d, f::dock::PARTNER_PORT + 1)?;
                let partner = decode_partner(kind, d, f::dock::PARTNER, f::dock::PARTNER_PORT)?;
                // The flag and the partner field say the same thing: both or neither.
                if partner.is_some() != (flags & DockState::LINKED != 0) {
                    return Err(bad("flags", flags));
                }
                StateReport::Dock {
                    port: Port::new(part & 0x07).ok_or(bad("part", part))?,
                    state: DockState {
                        closed: flags & DockState::CLOSED != 0,
                        confirmed: flags & DockState::CONFIRMED != 0,
                        partner,
                    },
                }
            }
            Self::FIRMWARE => {
                let flags = d[f::firmware::FLAGS];
                if flags & !Self::FIRMWARE_TRIAL != 0 {
                    return Err(bad("flags", flags));
                }
                reserved(kind, d, f::firmware::FLAGS + 1)?;
                StateReport::Firmware {
                    version: FirmwareVersion::new(
                        d[f::firmware::MAJOR],
                        d[f::firmware::MINOR],
                        d[f::firmware::PATCH],
                    ),
                    trial: flags & Self::FIRMWARE_TRIAL != 0,
                }
            }
            Self::IMAGE_HASH => StateReport::ImageHash(data),
            Self::UID_LOW => StateReport::UidLow(data),
            Self::UID_HIGH => {
                reserved(kind, d, f::UID_HIGH.end)?;
                let mut high = [0; 5];
                high.copy_from_slice(&d[f::UID_HIGH]);
                StateReport::UidHigh(high)
            }
            Self::PROTOCOL => {
                reserved(kind, d, f::protocol::MINOR + 1)?;
                StateReport::Protocol {
                    version: (d[f::protocol::MAJOR], d[f::protocol::MINOR]),
                }
            }
            Self::END => {
                reserved(kind, d, f::end::COUNT + 1)?;
                StateReport::End {
                    seq: d[f::end::SEQ],
                    parts: StateParts(d[f::end::PARTS]),
                    count: d[f::end::COUNT],
                }
            }
            part => StateReport::Other { part, data },
        };
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::FirmwareVersion;

    #[test]
    fn versions_print_as_three_decimal_numbers_and_read_back() {
        for a in 0..=255u8 {
            for (major, minor, patch) in [(a, 0, 0), (0, a, 0), (1, 2, a), (a, a, a)] {
                let v = FirmwareVersion::new(major, minor, patch);
                let text = v.to_string();
                assert_eq!(text, format!("{major}.{minor}.{patch}"));
                assert_eq!(FirmwareVersion::parse(&text), Some(v));
            }
        }
    }
}
