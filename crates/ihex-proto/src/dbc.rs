//! Renders [`crate::schema`] as a DBC file, the Vector CANdb++ text format that cantools, SavvyCAN,
//! can-dbc and most CAN tools read. `cargo xtask dbc` writes `docs/ihex.dbc` with it; the tests
//! check the committed file against it and decode frames with cantools (`docs/integrations.md`).
//!
//! Two layouts:
//!
//! * [`Layout::ByKind`] — one message per kind whose ID is the kind alone (`kind << 24`, bit 31 set
//!   as the format requires for 29-bit IDs). A frame's destination and source are not signals: they
//!   are identifier bits, which no DBC signal can address. Tools find the message by comparing only
//!   the kind bits, [`FRAME_ID_MASK`] (cantools `--frame-id-mask 0x1F000000`).
//! * [`Layout::Island`] — one message per kind *and address pair* of the given nodes, with the exact
//!   IDs, for tools that match IDs exactly (SavvyCAN, Wireshark's signal dissector).
//!
//! Written through [`core::fmt::Write`], so it needs no allocator.

use core::fmt::{self, Write};

use crate::schema::{self, Direction, MessageSchema, Mux};
use crate::{Header, Kind, NodeId, BITRATE, PROTOCOL_VERSION};

/// The identifier bits that hold the kind: the mask that matches a frame to its
/// [`Layout::ByKind`] message.
pub const FRAME_ID_MASK: u32 = Header::KIND_MASK << Header::KIND_SHIFT;

/// Set in a DBC message ID for a 29-bit (extended) identifier.
pub const EXTENDED: u32 = 1 << 31;

/// DBC node name of the gateway.
pub const GATEWAY: &str = "Gateway";

/// DBC node name of the sub-controllers in [`Layout::ByKind`]; [`Layout::Island`] names each
/// `SC_<id>` (`SC_111`), and a node without an ID `SC_unconfigured`.
pub const SC: &str = "SC";

/// Which messages the file describes.
#[derive(Clone, Copy, Debug)]
pub enum Layout<'a> {
    /// One message per kind, matched by [`FRAME_ID_MASK`]: the committed `docs/ihex.dbc`.
    ByKind,
    /// One message per kind and address pair of these sub-controllers (each `0x001..=0xFFD`, no
    /// duplicates), plus broadcast commands and the replies of a node still without an ID.
    Island(&'a [NodeId]),
}

/// Why a DBC file could not be written.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Error {
    /// The writer failed.
    Fmt,
    /// An island node that is not a sub-controller ID (`0x001..=0xFFD`).
    NotASubController(NodeId),
    /// An island node listed twice.
    Duplicate(NodeId),
}

impl From<fmt::Error> for Error {
    fn from(_: fmt::Error) -> Self {
        Error::Fmt
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Fmt => f.write_str("writing the DBC text failed"),
            Error::NotASubController(n) => write!(
                f,
                "node {n} is not a sub-controller ID (1 to ffd): an island lists its elements"
            ),
            Error::Duplicate(n) => write!(f, "node {n} is listed twice"),
        }
    }
}

impl core::error::Error for Error {}

/// Writes the DBC file of the whole protocol.
pub fn write<W: Write>(w: &mut W, layout: Layout<'_>) -> Result<(), Error> {
    write_messages(w, layout, &Kind::ALL.map(schema::of))
}

/// Writes a DBC file describing only `messages` (for a tool that wants a few; [`write()`] is the
/// whole protocol).
pub fn write_messages<W: Write>(
    w: &mut W,
    layout: Layout<'_>,
    messages: &[MessageSchema],
) -> Result<(), Error> {
    if let Layout::Island(nodes) = layout {
        for (i, n) in nodes.iter().enumerate() {
            if !n.is_sc() {
                return Err(Error::NotASubController(*n));
            }
            if nodes[..i].contains(n) {
                return Err(Error::Duplicate(*n));
            }
        }
    }
    let db = Db { layout, messages };
    header(w, layout)?;
    message_lines(w, db)?;
    comments(w, db)?;
    attributes(w)?;
    value_tables(w, db)?;
    multiplex_values(w, db)?;
    Ok(())
}

/// What a file describes.
#[derive(Clone, Copy)]
struct Db<'a> {
    layout: Layout<'a>,
    messages: &'a [MessageSchema],
}

/// Version, symbols, nodes.
fn header<W: Write>(w: &mut W, layout: Layout<'_>) -> fmt::Result {
    let (major, minor) = PROTOCOL_VERSION;
    writeln!(w, "VERSION \"iHEX {major}.{minor}\"\n")?;
    w.write_str(concat!(
        "NS_ :\n\tNS_DESC_\n\tCM_\n\tBA_DEF_\n\tBA_\n\tVAL_\n\tBA_DEF_DEF_\n\tVAL_TABLE_\n",
        "\tBO_TX_BU_\n\tSIG_VALTYPE_\n\tSG_MUL_VAL_\n\n",
        "BS_:\n\n",
    ))?;
    write!(w, "BU_: {GATEWAY}")?;
    for_each_sc(layout, |n| write!(w, " {n}"))?;
    w.write_str("\n\n")
}

/// `BO_` with its `SG_` lines, per message.
fn message_lines<W: Write>(w: &mut W, db: Db<'_>) -> fmt::Result {
    for_each_message(db, |m| {
        writeln!(
            w,
            "BO_ {} {}: {} {}",
            m.dbc_id(),
            m.name(),
            m.schema.data_len(),
            m.transmitter()
        )?;
        for s in m.schema.signals {
            write!(w, " SG_ {}", s.name)?;
            match s.mux {
                Mux::Always => {}
                Mux::Selector => w.write_str(" M")?,
                // Several values: the first here, all of them in `SG_MUL_VAL_`.
                Mux::When(values) => write!(w, " m{}", values.first().copied().unwrap_or(0))?,
            }
            write!(
                w,
                " : {}|{}@1{} ({},{}) [{}|{}] \"{}\" ",
                s.start,
                s.bits,
                if s.signed { '-' } else { '+' },
                s.factor,
                s.offset,
                s.physical(s.min),
                s.physical(s.max),
                s.unit,
            )?;
            m.receivers(db.layout, w)?;
            w.write_char('\n')?;
        }
        w.write_char('\n')
    })
}

/// `CM_` for the file, the nodes, every message and every signal.
fn comments<W: Write>(w: &mut W, db: Db<'_>) -> fmt::Result {
    let layout = db.layout;
    let (major, minor) = PROTOCOL_VERSION;
    write!(
        w,
        "CM_ \"iHEX CAN protocol {major}.{minor}, generated from crates/ihex-proto by cargo xtask \
         dbc: do not edit. Reference: docs/protocol.md. Extended 29-bit identifiers: kind << 24 | \
         destination << 12 | source; the addresses are in the identifier, not in the data. "
    )?;
    match layout {
        Layout::ByKind => writeln!(
            w,
            "Message IDs hold the kind only: match frames with the frame-ID mask {FRAME_ID_MASK:#010X} \
             (cantools decode --frame-id-mask {FRAME_ID_MASK:#010X}).\";"
        )?,
        Layout::Island(_) => w.write_str(
            "One message per kind and address pair of this island, with exact IDs; message \
             names end in the sub-controller ID (hex), _all for broadcast.\";\n",
        )?,
    }
    writeln!(
        w,
        "CM_ BU_ {GATEWAY} \"The main controller (Raspberry Pi), node ID 0x000.\";"
    )?;
    for_each_sc(layout, |n| {
        write!(w, "CM_ BU_ {n} \"")?;
        match n {
            ScName::Any => w.write_str(
                "A sub-controller (static or mobile element): node IDs 0x001 to 0xFFD, 0xFFE \
                 while it has none.",
            )?,
            ScName::Node(id) => write!(w, "The sub-controller with node ID 0x{:03X}.", id.get())?,
            ScName::Unconfigured => {
                w.write_str("A sub-controller that has no node ID yet (0xFFE).")?
            }
        }
        w.write_str("\";\n")
    })?;
    for_each_message(db, |m| {
        let id = m.dbc_id();
        writeln!(
            w,
            "CM_ BO_ {id} \"{}. See docs/protocol.md, {}.\";",
            m.schema.summary,
            m.schema.name()
        )?;
        for s in m.schema.signals {
            writeln!(w, "CM_ SG_ {id} {} \"{}.\";", s.name, s.comment)?;
        }
        Ok(())
    })
}

/// The bus type and bitrate, as Vector's database attributes.
fn attributes<W: Write>(w: &mut W) -> fmt::Result {
    w.write_str(concat!(
        "BA_DEF_  \"BusType\" STRING ;\n",
        "BA_DEF_  \"Baudrate\" INT 0 1000000;\n",
        "BA_DEF_DEF_  \"BusType\" \"CAN\";\n",
    ))?;
    writeln!(w, "BA_DEF_DEF_  \"Baudrate\" {BITRATE};")?;
    w.write_str("BA_ \"BusType\" \"CAN\";\n")?;
    writeln!(w, "BA_ \"Baudrate\" {BITRATE};")
}

/// `VAL_` for every signal with named values.
fn value_tables<W: Write>(w: &mut W, db: Db<'_>) -> fmt::Result {
    for_each_message(db, |m| {
        for s in m.schema.signals.iter().filter(|s| !s.values.is_empty()) {
            write!(w, "VAL_ {} {}", m.dbc_id(), s.name)?;
            for (raw, name) in s.values {
                write!(w, " {raw} \"{name}\"")?;
            }
            w.write_str(" ;\n")?;
        }
        Ok(())
    })
}

/// `SG_MUL_VAL_` (extended multiplexing) for every signal present under several selector values,
/// consecutive values as one range.
fn multiplex_values<W: Write>(w: &mut W, db: Db<'_>) -> fmt::Result {
    for_each_message(db, |m| {
        let Some(selector) = m.schema.selector() else {
            return Ok(());
        };
        for s in m.schema.signals {
            let Mux::When(values) = s.mux else { continue };
            if values.len() < 2 {
                continue;
            }
            write!(
                w,
                "SG_MUL_VAL_ {} {} {} ",
                m.dbc_id(),
                s.name,
                selector.name
            )?;
            let mut sep = "";
            let mut i = 0;
            while i < values.len() {
                let first = values[i];
                while i + 1 < values.len() && u16::from(values[i + 1]) == u16::from(values[i]) + 1 {
                    i += 1;
                }
                write!(w, "{sep}{first}-{}", values[i])?;
                sep = ", ";
                i += 1;
            }
            w.write_str(";\n")?;
        }
        Ok(())
    })
}

/// The name of a sub-controller node in the file.
enum ScName {
    /// [`Layout::ByKind`]: every sub-controller.
    Any,
    /// `SC_<id>`.
    Node(NodeId),
    /// `SC_unconfigured`: a node that has no ID yet.
    Unconfigured,
}

impl fmt::Display for ScName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ScName::Any => f.write_str(SC),
            ScName::Node(n) => write!(f, "{SC}_{n}"),
            ScName::Unconfigured => write!(f, "{SC}_unconfigured"),
        }
    }
}

fn for_each_sc(layout: Layout<'_>, mut f: impl FnMut(ScName) -> fmt::Result) -> fmt::Result {
    match layout {
        Layout::ByKind => f(ScName::Any),
        Layout::Island(nodes) => {
            for n in nodes {
                f(ScName::Node(*n))?;
            }
            f(ScName::Unconfigured)
        }
    }
}

/// One DBC message: a kind, and in an island its addresses.
struct DbcMessage {
    schema: MessageSchema,
    /// `None` in [`Layout::ByKind`].
    header: Option<Header>,
}

impl DbcMessage {
    fn dbc_id(&self) -> u32 {
        let id = match self.header {
            Some(h) => h.to_raw(),
            None => (self.schema.kind as u32) << Header::KIND_SHIFT,
        };
        EXTENDED | id
    }

    /// The sub-controller end of the exchange: the destination of a command, the source of a
    /// report.
    fn sc(&self) -> Option<NodeId> {
        self.header.map(|h| match self.schema.direction() {
            Direction::Command => h.dest,
            Direction::Report => h.src,
        })
    }

    fn sc_name(&self) -> ScName {
        match self.sc() {
            None => ScName::Any,
            Some(n) if n == NodeId::UNCONFIGURED => ScName::Unconfigured,
            Some(n) => ScName::Node(n),
        }
    }

    fn name(&self) -> MessageName<'_> {
        MessageName(self)
    }

    fn transmitter(&self) -> Transmitter<'_> {
        Transmitter(self)
    }

    fn receivers<W: Write>(&self, layout: Layout<'_>, w: &mut W) -> fmt::Result {
        match self.schema.direction() {
            Direction::Report => w.write_str(GATEWAY),
            Direction::Command if self.sc() == Some(NodeId::BROADCAST) => {
                let mut sep = "";
                for_each_sc(layout, |n| {
                    write!(w, "{sep}{n}")?;
                    sep = ",";
                    Ok(())
                })
            }
            Direction::Command => write!(w, "{}", self.sc_name()),
        }
    }
}

struct MessageName<'a>(&'a DbcMessage);

impl fmt::Display for MessageName<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.0.schema.name())?;
        match self.0.sc() {
            None => Ok(()),
            Some(NodeId::BROADCAST) => f.write_str("_all"),
            Some(NodeId::UNCONFIGURED) => f.write_str("_unconfigured"),
            Some(n) => write!(f, "_{n}"),
        }
    }
}

struct Transmitter<'a>(&'a DbcMessage);

impl fmt::Display for Transmitter<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0.schema.direction() {
            Direction::Command => f.write_str(GATEWAY),
            Direction::Report => write!(f, "{}", self.0.sc_name()),
        }
    }
}

/// Calls `f` for every message of the layout, in kind order, then destination, then source (each
/// in the order gateway, the island's nodes as given, `0xFFE`, broadcast).
fn for_each_message(db: Db<'_>, mut f: impl FnMut(&DbcMessage) -> fmt::Result) -> fmt::Result {
    for &schema in db.messages {
        match db.layout {
            Layout::ByKind => f(&DbcMessage {
                schema,
                header: None,
            })?,
            Layout::Island(nodes) => {
                // Every address the island can use; the protocol's own address rules pick the
                // pairs each kind allows.
                let addresses = || {
                    [NodeId::GATEWAY]
                        .iter()
                        .chain(nodes)
                        .chain(&[NodeId::UNCONFIGURED, NodeId::BROADCAST])
                        .copied()
                };
                for dest in addresses() {
                    for src in addresses() {
                        let header = Header {
                            kind: schema.kind,
                            dest,
                            src,
                        };
                        if header.check_addresses().is_ok() {
                            f(&DbcMessage {
                                schema,
                                header: Some(header),
                            })?;
                        }
                    }
                }
            }
        }
    }
    Ok(())
}
