//! The island description file (TOML): which static and mobile elements exist and how they start.
//!
//! ```toml
//! bounce = true                 # optional: simulate contact bounce on dock/undock (default false)
//!
//! [[static]]
//! id = "111"                    # node ID, hex (0x001..=0xffd); the element's name in every command
//! ports = 6                     # dock ports with a signal loop (0..=8, default 6)
//! uid = "0123456789abcdef00000111"   # optional 96-bit unique ID, 24 hex digits
//! unconfigured = false          # optional: a factory-fresh board with no stored ID (default false)
//! firmware = "0.1.0"            # optional: the firmware version it is flashed with (default: this
//!                               # crate's); its image hash is that image's (deterministic per version)
//! hex = [0, 0]                  # optional: where the gateway's island view draws it (axial hex
//!                               # coordinates q, r; docs/web.md)
//!
//! [[mobile]]
//! id = "2"
//! port = 0                      # its own port it docks by (default 0)
//! ports = 6                     # its own ports (default 6)
//! dock = { static = "111", port = 3 }   # optional: docked at start
//! ```
//!
//! Every mistake is reported with its line and column: syntax and type errors by the TOML parser,
//! semantic ones (duplicate IDs, unknown dock targets, ports out of range) by [`IslandDesc::parse`].

use std::{collections::HashMap, ops::Range, path::Path};

use ihex_proto::{FirmwareVersion, NodeId, Port, Uid};
use ihex_sc_core::FirmwareIdentity;
use serde::Deserialize;
use toml::Spanned;

/// Why an island file was refused.
#[derive(Debug, thiserror::Error)]
pub enum DescError {
    /// The file could not be read.
    #[error("cannot read {path}: {error}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        error: std::io::Error,
    },
    /// Not valid TOML, or a field has the wrong type or value (the message names line and field).
    #[error(transparent)]
    Toml(#[from] toml::de::Error),
    /// Well-formed, but inconsistent.
    #[error("line {line}, column {column}: {msg}")]
    Invalid {
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What is wrong.
        msg: String,
    },
}

/// A static element: wired to the bus, has dock ports.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StaticDesc {
    /// Its node ID (also its name in the island).
    pub id: NodeId,
    /// Number of dock ports.
    pub ports: u8,
    /// Its unique ID (from the file or derived from `id`).
    pub uid: Uid,
    /// False for a factory-fresh board that starts without a node ID.
    pub configured: bool,
    /// The firmware it reports.
    pub firmware: FirmwareIdentity,
    /// Where the gateway's island view draws it: axial hex coordinates `(q, r)`.
    pub hex: Option<(i32, i32)>,
}

/// A mobile element: powered through the static element it is docked on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MobileDesc {
    /// Its node ID (also its name in the island).
    pub id: NodeId,
    /// Number of its own ports.
    pub ports: u8,
    /// The own port it docks by.
    pub port: Port,
    /// Its unique ID (from the file or derived from `id`).
    pub uid: Uid,
    /// False for a factory-fresh board that starts without a node ID.
    pub configured: bool,
    /// Docked at start on (static element, port).
    pub dock: Option<(NodeId, Port)>,
    /// The firmware it reports.
    pub firmware: FirmwareIdentity,
}

/// A validated island description.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct IslandDesc {
    /// Simulate contact bounce (a few rapid level toggles) on dock and undock.
    pub bounce: bool,
    /// Static elements, in file order.
    pub statics: Vec<StaticDesc>,
    /// Mobile elements, in file order.
    pub mobiles: Vec<MobileDesc>,
}

/// Default number of ports of an element (a hexagon).
pub const DEFAULT_PORTS: u8 = 6;

/// The firmware version a virtual board reports when the file gives none: this crate's version.
pub const DEFAULT_FIRMWARE: FirmwareVersion =
    match FirmwareVersion::parse(env!("CARGO_PKG_VERSION")) {
        Some(v) => v,
        None => panic!("the crate version is MAJOR.MINOR.PATCH with numbers up to 255"),
    };

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileRaw {
    #[serde(default)]
    bounce: bool,
    #[serde(default, rename = "static")]
    statics: Vec<StaticRaw>,
    #[serde(default, rename = "mobile")]
    mobiles: Vec<MobileRaw>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct StaticRaw {
    id: Spanned<HexId>,
    ports: Option<Spanned<u8>>,
    uid: Option<Spanned<HexUid>>,
    #[serde(default)]
    unconfigured: bool,
    firmware: Option<Version>,
    hex: Option<Spanned<[i32; 2]>>,
}

/// The largest axial coordinate of a hexagon, either sign.
pub const MAX_HEX: i32 = 1000;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MobileRaw {
    id: Spanned<HexId>,
    ports: Option<Spanned<u8>>,
    port: Option<Spanned<u8>>,
    uid: Option<Spanned<HexUid>>,
    #[serde(default)]
    unconfigured: bool,
    dock: Option<DockRaw>,
    firmware: Option<Version>,
}

/// An element's firmware from its optional `firmware` key: the factory image of that version.
fn firmware_identity(firmware: Option<Version>) -> FirmwareIdentity {
    let version = firmware.map_or(DEFAULT_FIRMWARE, |v| v.0);
    FirmwareIdentity {
        version,
        image_hash: simulated_image_hash(version),
        // A board starts with a confirmed image; updates over the bus change that.
        trial: false,
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct DockRaw {
    #[serde(rename = "static")]
    static_id: Spanned<HexId>,
    port: Spanned<u8>,
}

/// A node ID written as a hex string (`"111"` or `"0x111"`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct HexId(NodeId);

impl<'de> Deserialize<'de> for HexId {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        parse_node_id(&s)
            .map(HexId)
            .map_err(serde::de::Error::custom)
    }
}

/// Parses a node ID as the island file and the CLI write it (`ihex_proto`'s form: hex, optional
/// `0x`) and checks that a sub-controller may own it (`001..=ffd`).
pub fn parse_node_id(s: &str) -> Result<NodeId, String> {
    match s.trim().parse::<NodeId>() {
        Ok(id) if id.is_sc() => Ok(id),
        Ok(_) => Err(format!("node id {s:?} is outside 001..=ffd")),
        Err(e) => Err(format!("node id {s:?}: {e}")),
    }
}

/// A firmware version written as `"MAJOR.MINOR.PATCH"`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Version(FirmwareVersion);

impl<'de> Deserialize<'de> for Version {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse::<FirmwareVersion>()
            .map(Version)
            .map_err(|e| serde::de::Error::custom(format!("firmware {s:?}: {e}")))
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct HexUid([u8; 12]);

impl<'de> Deserialize<'de> for HexUid {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse::<Uid>()
            .map(|u| HexUid(u.0))
            .map_err(|e| serde::de::Error::custom(format!("uid {s:?}: {e}")))
    }
}

/// The unique ID a virtual board gets when the file gives none: deterministic, distinct for distinct
/// node IDs, and spread over all 12 bytes so that assignment by UID head or tail both discriminate.
pub fn derived_uid(id: NodeId) -> Uid {
    // SplitMix64 of the ID fills the head; the tail carries the ID itself, which keeps UIDs unique.
    let z = splitmix64(id.get() as u64);
    let mut uid = [0u8; 12];
    uid[..8].copy_from_slice(&z.to_be_bytes());
    uid[8..10].copy_from_slice(b"SN");
    uid[10..].copy_from_slice(&id.get().to_be_bytes());
    Uid(uid)
}

/// The image hash a virtual board reports when the file gives none: that of the image it is first
/// flashed with ([`crate::board::factory_image`]) — deterministic per version, different for
/// different versions, as on a real bench.
pub fn simulated_image_hash(version: FirmwareVersion) -> [u8; 7] {
    crate::board::factory_image_hash(version)
}

/// SplitMix64's output function: a fixed, well-spread 64-bit mix of `x`.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

struct Locator<'a>(&'a str);

impl Locator<'_> {
    fn err(&self, span: Range<usize>, msg: impl Into<String>) -> DescError {
        let before = &self.0[..span.start.min(self.0.len())];
        let line = before.matches('\n').count() + 1;
        let column = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
        DescError::Invalid {
            line,
            column,
            msg: msg.into(),
        }
    }
}

impl IslandDesc {
    /// Reads and validates an island file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, DescError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|error| DescError::Io {
            path: path.display().to_string(),
            error,
        })?;
        Self::parse(&text)
    }

    /// Parses and validates an island description.
    pub fn parse(text: &str) -> Result<Self, DescError> {
        let raw: FileRaw = toml::from_str(text)?;
        let loc = Locator(text);
        let mut seen_id: HashMap<NodeId, ()> = HashMap::new();
        let mut seen_uid: HashMap<[u8; 12], NodeId> = HashMap::new();
        let mut check_unique = |id: &Spanned<HexId>,
                                uid: Uid,
                                uid_span: Option<Range<usize>>|
         -> Result<(), DescError> {
            let node = id.get_ref().0;
            if seen_id.insert(node, ()).is_some() {
                return Err(loc.err(id.span(), format!("node id \"{node}\" is used twice")));
            }
            if let Some(other) = seen_uid.insert(uid.0, node) {
                let span = uid_span.unwrap_or(id.span());
                return Err(loc.err(
                    span,
                    format!("uid of \"{node}\" is the same as that of \"{other}\""),
                ));
            }
            Ok(())
        };
        let ports_of = |p: &Option<Spanned<u8>>| -> Result<u8, DescError> {
            match p {
                None => Ok(DEFAULT_PORTS),
                Some(p) if *p.get_ref() <= Port::COUNT => Ok(*p.get_ref()),
                Some(p) => Err(loc.err(
                    p.span(),
                    format!("ports = {} is more than {}", p.get_ref(), Port::COUNT),
                )),
            }
        };

        let mut desc = IslandDesc {
            bounce: raw.bounce,
            ..Default::default()
        };
        let mut placed: HashMap<(i32, i32), NodeId> = HashMap::new();
        for s in &raw.statics {
            let id = s.id.get_ref().0;
            let uid = s
                .uid
                .as_ref()
                .map_or(derived_uid(id), |u| Uid(u.get_ref().0));
            check_unique(&s.id, uid, s.uid.as_ref().map(|u| u.span()))?;
            let hex = match &s.hex {
                None => None,
                Some(h) => {
                    let [q, r] = *h.get_ref();
                    if q.abs() > MAX_HEX || r.abs() > MAX_HEX {
                        return Err(loc.err(
                            h.span(),
                            format!("hex = [{q}, {r}]: coordinates are -{MAX_HEX} to {MAX_HEX}"),
                        ));
                    }
                    if let Some(other) = placed.insert((q, r), id) {
                        return Err(loc.err(
                            h.span(),
                            format!("hex = [{q}, {r}] is taken by \"{other}\""),
                        ));
                    }
                    Some((q, r))
                }
            };
            desc.statics.push(StaticDesc {
                id,
                ports: ports_of(&s.ports)?,
                uid,
                configured: !s.unconfigured,
                firmware: firmware_identity(s.firmware),
                hex,
            });
        }
        let mut taken: HashMap<(NodeId, Port), NodeId> = HashMap::new();
        for m in &raw.mobiles {
            let id = m.id.get_ref().0;
            let uid = m
                .uid
                .as_ref()
                .map_or(derived_uid(id), |u| Uid(u.get_ref().0));
            check_unique(&m.id, uid, m.uid.as_ref().map(|u| u.span()))?;
            let ports = ports_of(&m.ports)?;
            let port = match &m.port {
                None => 0,
                Some(p) if *p.get_ref() < ports.max(1) => *p.get_ref(),
                Some(p) => {
                    return Err(loc.err(
                        p.span(),
                        format!("port = {} but \"{id}\" has {ports} ports", p.get_ref()),
                    ))
                }
            };
            let dock = match &m.dock {
                None => None,
                Some(d) => {
                    let target = d.static_id.get_ref().0;
                    let Some(st) = desc.statics.iter().find(|s| s.id == target) else {
                        return Err(loc.err(
                            d.static_id.span(),
                            format!(
                                "dock.static = \"{target}\" is not a static element of this island"
                            ),
                        ));
                    };
                    let p = *d.port.get_ref();
                    let Some(port) = Port::new(p).filter(|_| p < st.ports) else {
                        return Err(loc.err(
                            d.port.span(),
                            format!(
                                "dock.port = {p} but static \"{target}\" has {} ports",
                                st.ports
                            ),
                        ));
                    };
                    if let Some(other) = taken.insert((target, port), id) {
                        return Err(loc.err(
                            d.port.span(),
                            format!("port {p} of \"{target}\" is already taken by \"{other}\""),
                        ));
                    }
                    Some((target, port))
                }
            };
            desc.mobiles.push(MobileDesc {
                id,
                ports,
                // Bounded above by `ports <= 8`.
                port: Port::new(port).unwrap_or(Port::new(0).expect("port 0 exists")),
                uid,
                configured: !m.unconfigured,
                dock,
                firmware: firmware_identity(m.firmware),
            });
        }
        Ok(desc)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::sc_id as id;

    fn invalid_at(text: &str) -> (usize, String) {
        match IslandDesc::parse(text) {
            Err(DescError::Invalid { line, msg, .. }) => (line, msg),
            other => panic!("expected a validation error, got {other:?}"),
        }
    }

    #[test]
    fn parses_the_documented_example() {
        let text = r#"
bounce = true

[[static]]
id = "111"
ports = 6
uid = "0123456789abcdef00000111"

[[static]]
id = "0x112"
firmware = "1.2.3"
hex = [1, -1]

[[mobile]]
id = "2"
port = 1
dock = { static = "111", port = 3 }
firmware = "0.9.0"

[[mobile]]
id = "3"
unconfigured = true
"#;
        let d = IslandDesc::parse(text).unwrap();
        assert!(d.bounce);
        assert_eq!(d.statics.len(), 2);
        assert_eq!(d.statics[0].id, id(0x111));
        assert_eq!(d.statics[0].uid.0[..2], [0x01, 0x23]);
        assert_eq!(d.statics[1].id, id(0x112));
        assert_eq!(d.statics[1].ports, DEFAULT_PORTS);
        assert_eq!(d.statics[1].uid, derived_uid(id(0x112)));
        assert_eq!((d.statics[0].hex, d.statics[1].hex), (None, Some((1, -1))));
        assert_eq!(d.mobiles[0].dock, Some((id(0x111), Port::new(3).unwrap())));
        assert_eq!(d.mobiles[0].port, Port::new(1).unwrap());
        assert!(d.mobiles[0].configured);
        assert_eq!(d.mobiles[1].dock, None);
        assert!(!d.mobiles[1].configured);
        // Firmware: the crate's version and its simulated hash unless the file says otherwise.
        let fw = |version, image_hash| FirmwareIdentity {
            version,
            image_hash,
            trial: false,
        };
        assert_eq!(
            d.statics[0].firmware,
            fw(DEFAULT_FIRMWARE, simulated_image_hash(DEFAULT_FIRMWARE))
        );
        let v123 = FirmwareVersion::new(1, 2, 3);
        assert_eq!(d.statics[1].firmware, fw(v123, simulated_image_hash(v123)));
        let v090 = FirmwareVersion::new(0, 9, 0);
        assert_eq!(d.mobiles[0].firmware, fw(v090, simulated_image_hash(v090)));
        assert_eq!(d.mobiles[1].firmware, d.statics[0].firmware);
    }

    #[test]
    fn simulated_hashes_follow_the_version() {
        let v = FirmwareVersion::new;
        assert_eq!(
            simulated_image_hash(v(1, 2, 3)),
            simulated_image_hash(v(1, 2, 3))
        );
        let mut seen = std::collections::HashSet::new();
        for major in 0..4 {
            for minor in 0..4 {
                for patch in 0..4 {
                    let h = simulated_image_hash(v(major, minor, patch));
                    assert_ne!(h, [0; 7], "all zero means unknown");
                    assert!(seen.insert(h), "{major}.{minor}.{patch} collides");
                }
            }
        }
        assert_eq!(
            Some(DEFAULT_FIRMWARE),
            env!("CARGO_PKG_VERSION").parse().ok()
        );
    }

    #[test]
    fn every_example_island_file_is_valid() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../examples/islands");
        let mut n = 0;
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                let d =
                    IslandDesc::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                assert!(!d.statics.is_empty(), "{}", path.display());
                n += 1;
            }
        }
        assert!(n >= 2, "found {n} example islands");
    }

    #[test]
    fn derived_uids_differ_in_head_and_tail() {
        let a = derived_uid(id(1));
        let b = derived_uid(id(2));
        assert_ne!(a.head(), b.head());
        assert_ne!(a.tail(), b.tail());
        assert_eq!(a, derived_uid(id(1)));
    }

    #[test]
    fn duplicate_ids_name_the_second_line() {
        let (line, msg) = invalid_at("[[static]]\nid = \"111\"\n[[mobile]]\nid = \"111\"\n");
        assert_eq!(line, 4);
        assert!(msg.contains("used twice"), "{msg}");
    }

    #[test]
    fn unknown_dock_target_is_reported_at_its_field() {
        let (line, msg) =
            invalid_at("[[static]]\nid = \"111\"\n\n[[mobile]]\nid = \"2\"\ndock = { static = \"999\", port = 0 }\n");
        assert_eq!(line, 6);
        assert!(msg.contains("\"999\""), "{msg}");
    }

    #[test]
    fn dock_port_beyond_the_static_ports_is_refused() {
        let (line, msg) =
            invalid_at("[[static]]\nid = \"111\"\nports = 2\n[[mobile]]\nid = \"2\"\ndock = { static = \"111\", port = 2 }\n");
        assert_eq!(line, 6);
        assert!(msg.contains("2 ports"), "{msg}");
    }

    #[test]
    fn two_mobiles_on_one_port_are_refused() {
        let text = "[[static]]\nid = \"111\"\n[[mobile]]\nid = \"2\"\ndock = { static = \"111\", port = 1 }\n\
                    [[mobile]]\nid = \"3\"\ndock = { static = \"111\", port = 1 }\n";
        let (line, msg) = invalid_at(text);
        assert_eq!(line, 8);
        assert!(msg.contains("already taken by \"2\""), "{msg}");
    }

    #[test]
    fn too_many_ports_and_duplicate_uids_are_refused() {
        let (line, _) = invalid_at("[[static]]\nid = \"1\"\nports = 9\n");
        assert_eq!(line, 3);
        let u = "uid = \"000000000000000000000001\"";
        let (line, msg) = invalid_at(&format!(
            "[[static]]\nid = \"1\"\n{u}\n[[static]]\nid = \"2\"\n{u}\n"
        ));
        assert_eq!(line, 6);
        assert!(msg.contains("same as that of \"1\""), "{msg}");
    }

    #[test]
    fn hexagons_stay_apart_and_near() {
        let (line, msg) = invalid_at(
            "[[static]]\nid = \"1\"\nhex = [0, 0]\n[[static]]\nid = \"2\"\nhex = [0, 0]\n",
        );
        assert_eq!(line, 6);
        assert_eq!(msg, "hex = [0, 0] is taken by \"1\"");
        let (line, msg) = invalid_at("[[static]]\nid = \"1\"\nhex = [0, 1001]\n");
        assert_eq!(line, 3);
        assert!(msg.contains("-1000 to 1000"), "{msg}");
    }

    #[test]
    fn type_and_value_errors_come_from_toml_with_the_line() {
        for (text, needle) in [
            ("[[static]]\nid = 111\n", "line 2"),
            ("[[static]]\nid = \"fff\"\n", "outside 001..=ffd"),
            ("[[static]]\nid = \"xyz\"\n", "1 to 3 hex digits"),
            ("[[static]]\nid = \"1\"\ncolour = 3\n", "colour"),
            ("[[static]]\nid = \"1\"\nuid = \"12\"\n", "24 hex digits"),
            (
                "[[static]]\nid = \"1\"\nfirmware = \"1.2\"\n",
                "MAJOR.MINOR.PATCH",
            ),
            ("[[mobile]]\nid = \"1\"\nfirmware = \"1.2.300\"\n", "line 3"),
            // The image hash is the image's: the file cannot set it.
            (
                "[[static]]\nid = \"1\"\nimage_hash = \"00112233445566\"\n",
                "image_hash",
            ),
            ("[[static]]\nid = \"1\"\nfirmware = 1\n", "line 3"),
            ("[[static]]\nid = \"1\"\nhex = [1]\n", "line 3"),
            ("[[mobile]]\nid = \"1\"\nhex = [1, 2]\n", "hex"),
            ("[[static]\n", "line 1"),
        ] {
            match IslandDesc::parse(text) {
                Err(e @ DescError::Toml(_)) => {
                    let s = e.to_string();
                    assert!(s.contains(needle), "{text:?}: {s}");
                }
                other => panic!("{text:?}: expected a TOML error, got {other:?}"),
            }
        }
    }

    #[test]
    fn node_ids_parse_like_the_cli_writes_them() {
        assert_eq!(parse_node_id("111"), Ok(id(0x111)));
        assert_eq!(parse_node_id("0xABC"), Ok(id(0xabc)));
        assert!(parse_node_id("0").is_err());
        assert!(parse_node_id("1000").is_err());
        assert!(parse_node_id("").is_err());
    }
}
