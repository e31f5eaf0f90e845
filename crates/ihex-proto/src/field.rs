//! Byte offsets of every field in the data of each message (smoltcp-style), as tabled in
//! `docs/protocol.md`. Single bytes are `usize` offsets, multi-byte little-endian fields ranges;
//! the wire values of the mode and role bytes are `u8` constants beside them.
//!
//! The codec in [`crate::Message`] reads and writes through these constants, so they are the
//! layout; an [`crate::Message::Ack`]'s `detail` for `InvalidValue`/`InvalidState` is one of them.

/// A multi-byte field: its byte range.
pub type Field = core::ops::Range<usize>;

/// [`crate::Message::PowerSet`].
pub mod power_set {
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// Relay state, `0`/`1`.
    pub const ON: usize = 1;
}

/// [`crate::Message::Fault`].
pub mod fault {
    use super::Field;
    /// Fault code.
    pub const CODE: usize = 0;
    /// Code-specific argument.
    pub const ARG: usize = 1;
    /// Code-specific detail, `u32` LE.
    pub const DETAIL: Field = 2..6;
}

/// [`crate::Message::DockDetected`], [`crate::Message::DockRemoved`], [`crate::Message::Handshake`].
pub mod dock {
    /// Dock port.
    pub const PORT: usize = 0;
}

/// [`crate::Message::DockConfirm`].
pub mod dock_confirm {
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// Dock port.
    pub const PORT: usize = 1;
}

/// [`crate::Message::DockRefuse`].
pub mod dock_refuse {
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// Dock port.
    pub const PORT: usize = 1;
    /// Refusal reason.
    pub const REASON: usize = 2;
}

/// [`crate::Message::Ack`].
pub mod ack {
    /// Kind of the command answered.
    pub const KIND: usize = 0;
    /// Its sequence number.
    pub const SEQ: usize = 1;
    /// Result code.
    pub const RESULT: usize = 2;
    /// Result-specific detail.
    pub const DETAIL: usize = 3;
}

/// [`crate::Message::AssignSelect`].
pub mod assign_select {
    use super::Field;
    /// Unique-ID bytes 0–7.
    pub const UID_HEAD: Field = 0..8;
}

/// [`crate::Message::AssignCommit`].
pub mod assign_commit {
    use super::Field;
    /// Unique-ID bytes 8–11.
    pub const UID_TAIL: Field = 0..4;
    /// New node ID, `u16` LE.
    pub const ID: Field = 4..6;
    /// Sequence number.
    pub const SEQ: usize = 6;
}

/// [`crate::Message::AssignReply`].
pub mod assign_reply {
    use super::Field;
    /// Sequence number of the commit.
    pub const SEQ: usize = 0;
    /// Result code.
    pub const RESULT: usize = 1;
    /// The node's ID now, `u16` LE.
    pub const ID: Field = 2..4;
    /// Unique-ID bytes 8–11.
    pub const UID_TAIL: Field = 4..8;
}

/// [`crate::Message::BootUp`].
pub mod boot_up {
    /// Protocol major version.
    pub const MAJOR: usize = 0;
    /// Protocol minor version.
    pub const MINOR: usize = 1;
    /// Role, [`ROLE_STATIC`] / [`ROLE_MOBILE`].
    pub const ROLE: usize = 2;
    /// Number of dock ports.
    pub const PORTS: usize = 3;
    /// Reset reason.
    pub const RESET: usize = 4;

    /// `ROLE` of a static element ([`crate::BootRole::Static`]).
    pub const ROLE_STATIC: u8 = 0;
    /// `ROLE` of a mobile element ([`crate::BootRole::Mobile`]).
    pub const ROLE_MOBILE: u8 = 1;
}

/// [`crate::Message::BuzzerSet`].
pub mod buzzer_set {
    use super::Field;
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// Mode: [`MODE_OFF`], [`MODE_CONTINUOUS`], [`MODE_PATTERN`].
    pub const MODE: usize = 1;
    /// Tone frequency in Hz, `u16` LE.
    pub const FREQ: Field = 2..4;
    /// Beep length × 10 ms.
    pub const ON: usize = 4;
    /// Pause length × 10 ms.
    pub const OFF: usize = 5;
    /// Number of beeps.
    pub const COUNT: usize = 6;

    /// `MODE` of [`crate::BuzzerCommand::Off`].
    pub const MODE_OFF: u8 = 0;
    /// `MODE` of [`crate::BuzzerCommand::Continuous`].
    pub const MODE_CONTINUOUS: u8 = 1;
    /// `MODE` of [`crate::BuzzerCommand::Pattern`].
    pub const MODE_PATTERN: u8 = 2;
}

/// [`crate::Message::LedSet`].
pub mod led_set {
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// Mode: [`MODE_OFF`], [`MODE_STEADY`], [`MODE_BLINK`].
    pub const MODE: usize = 1;
    /// Red.
    pub const R: usize = 2;
    /// Green.
    pub const G: usize = 3;
    /// Blue.
    pub const B: usize = 4;
    /// Overall brightness.
    pub const BRIGHTNESS: usize = 5;
    /// Blink period × 10 ms.
    pub const PERIOD: usize = 6;
    /// Blink duty, %.
    pub const DUTY: usize = 7;

    /// `MODE` of [`crate::LedCommand::Off`].
    pub const MODE_OFF: u8 = 0;
    /// `MODE` of [`crate::LedCommand::Steady`].
    pub const MODE_STEADY: u8 = 1;
    /// `MODE` of [`crate::LedCommand::Blink`].
    pub const MODE_BLINK: u8 = 2;
}

/// [`crate::Message::Identify`].
pub mod identify {
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// Duration in seconds.
    pub const SECONDS: usize = 1;
}

/// [`crate::Message::HealthCheck`].
pub mod health_check {
    /// Sequence number.
    pub const SEQ: usize = 0;
}

/// [`crate::Message::HealthReply`].
pub mod health_reply {
    use super::Field;
    /// Sequence number of the check answered.
    pub const SEQ: usize = 0;
    /// State flags.
    pub const FLAGS: usize = 1;
    /// Signal-loop bitmap.
    pub const LOOPS: usize = 2;
    /// CAN transmit error counter.
    pub const TEC: usize = 3;
    /// CAN receive error counter.
    pub const REC: usize = 4;
    /// Uptime in seconds, 24-bit LE.
    pub const UPTIME: Field = 5..8;
}

/// [`crate::Message::StateQuery`].
pub mod state_query {
    /// Sequence number, echoed by the reply's closing `End` report.
    pub const SEQ: usize = 0;
    /// Bitmap of the state groups asked for ([`crate::StateParts`]).
    pub const PARTS: usize = 1;
}

/// [`crate::Message::StateReport`]: byte 0 names the part, the rest depends on it. The `Led` part
/// uses the offsets of [`led_set`] and the `Buzzer` part those of [`buzzer_set`] (their byte 0,
/// the sequence number, is the part here), followed by one reserved byte.
pub mod state_report {
    use super::Field;
    /// Which part of the state this report carries ([`crate::StateReport::part`]).
    pub const PART: usize = 0;
    /// The part's data (all 7 bytes, as an unknown part keeps them).
    pub const DATA: Field = 1..8;

    /// The `Power` part.
    pub mod power {
        /// Relay, `0`/`1`.
        pub const RELAY: usize = 1;
        /// Signal-loop bitmap.
        pub const LOOPS: usize = 2;
        /// Confirmed-port bitmap.
        pub const CONFIRMED: usize = 3;
        /// Identify seconds remaining.
        pub const IDENTIFY: usize = 4;
        /// Role, `0` static / `1` mobile.
        pub const ROLE: usize = 5;
        /// Number of dock ports.
        pub const PORTS: usize = 6;
    }

    /// The `Dock(port)` parts.
    pub mod dock {
        use super::Field;
        /// Loop closed / confirmed / linked flags.
        pub const FLAGS: usize = 1;
        /// The linked mobile element's node ID, `u16` LE (`0xFFF` = none).
        pub const PARTNER: Field = 2..4;
        /// The linked mobile element's own port.
        pub const PARTNER_PORT: usize = 4;
    }

    /// The `Firmware` part.
    pub mod firmware {
        /// Version major.
        pub const MAJOR: usize = 1;
        /// Version minor.
        pub const MINOR: usize = 2;
        /// Version patch.
        pub const PATCH: usize = 3;
        /// Flags (bit 0: running an unconfirmed trial image).
        pub const FLAGS: usize = 4;
    }

    /// The `ImageHash` part: the first 7 bytes of the running image's hash.
    pub const IMAGE_HASH: Field = 1..8;
    /// The `UidLow` part: unique-ID bytes 0–6.
    pub const UID_LOW: Field = 1..8;
    /// The `UidHigh` part: unique-ID bytes 7–11.
    pub const UID_HIGH: Field = 1..6;

    /// The `Protocol` part: the protocol version the node speaks.
    pub mod protocol {
        /// Major version.
        pub const MAJOR: usize = 1;
        /// Minor version.
        pub const MINOR: usize = 2;
    }

    /// The `End` part, closing the reply to one query.
    pub mod end {
        /// Sequence number of the query answered.
        pub const SEQ: usize = 1;
        /// The groups answered.
        pub const PARTS: usize = 2;
        /// Number of reports sent before this one in the reply.
        pub const COUNT: usize = 3;
    }
}

/// [`crate::Message::DockLink`].
pub mod dock_link {
    use super::Field;
    /// Sequence number.
    pub const SEQ: usize = 0;
    /// The static element's dock port.
    pub const PORT: usize = 1;
    /// The mobile element docked there, `u16` LE (`0xFFF` clears the link).
    pub const PARTNER: Field = 2..4;
    /// The mobile element's own port.
    pub const PARTNER_PORT: usize = 4;
}

/// [`crate::Message::FwBegin`].
pub mod fw_begin {
    use super::Field;
    /// The image's ID (first 4 bytes of its payload SHA-512), `u32` LE.
    pub const IMAGE_ID: Field = 0..4;
    /// Image length in bytes (header block + payload), `u24` LE.
    pub const LEN: Field = 4..7;
    /// Flags (bit 0: force, i.e. allow a downgrade).
    pub const FLAGS: usize = 7;
}

/// [`crate::Message::FwData`].
pub mod fw_data {
    use super::Field;
    /// Frame index, `u16` LE: the bytes start at image offset `6 × index`.
    pub const INDEX: Field = 0..2;
    /// Six image bytes.
    pub const DATA: Field = 2..8;
}

/// [`crate::Message::FwQuery`].
pub mod fw_query {
    use super::Field;
    /// The image the gateway asks about, `u32` LE.
    pub const IMAGE_ID: Field = 0..4;
}

/// [`crate::Message::FwEnd`].
pub mod fw_end {
    use super::Field;
    /// The image, `u32` LE.
    pub const IMAGE_ID: Field = 0..4;
    /// `1` commit, `2` abort.
    pub const ACTION: usize = 4;
}

/// [`crate::Message::FwStatus`].
pub mod fw_status {
    use super::Field;
    /// Phase of the node's transfer.
    pub const PHASE: usize = 0;
    /// Refusal reason (`0` none).
    pub const REASON: usize = 1;
    /// First missing frame index, `u16` LE.
    pub const FIRST_MISSING: Field = 2..4;
    /// Missing frames from there on without a gap, `u16` LE.
    pub const RUN: Field = 4..6;
    /// All missing frames, `u16` LE (saturating).
    pub const MISSING: Field = 6..8;
}
