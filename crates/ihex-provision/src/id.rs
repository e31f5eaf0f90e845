//! Node-ID validation and the optional registry file of IDs already handed out.
//!
//! IDs are written in hex, as everywhere in the MQTT API (`"123"`, also `0x123`). Only `0x001..=0xFFD`
//! may be given to a sub-controller: `000` is the gateway, `ffe` marks an unconfigured SC and `fff`
//! is broadcast. The registry is a small CSV (`id,uid,port,note`), one line per assigned ID, so a lab
//! that numbers its boards over USB does not give two boards the same ID.

use std::{
    fs,
    io::{self, Write},
    path::{Path, PathBuf},
};

use ihex_proto::NodeId;

/// Why an ID cannot be used.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum IdError {
    /// Not 1 to 3 hex digits.
    #[error("node ID {0:?}: {1}")]
    NotHex(String, ihex_proto::ParseError),
    /// One of the reserved addresses.
    #[error("node ID {0:03x} is reserved ({1}); assignable IDs are 001..=ffd")]
    Reserved(u16, &'static str),
    /// Already assigned to another board.
    #[error("node ID {id} is already assigned ({source_desc}); pick another ID")]
    Duplicate {
        /// The ID asked for.
        id: NodeId,
        /// Where the duplicate was found (registry line or gateway node list).
        source_desc: String,
    },
}

/// Parses a hex node ID and checks that a sub-controller may own it.
pub fn parse_sc_id(text: &str) -> Result<NodeId, IdError> {
    let id: NodeId = text
        .trim()
        .parse()
        .map_err(|e| IdError::NotHex(text.to_owned(), e))?;
    let raw = id.get();
    match id {
        NodeId::GATEWAY => Err(IdError::Reserved(raw, "the gateway's address")),
        NodeId::UNCONFIGURED => Err(IdError::Reserved(raw, "marks an unconfigured node")),
        NodeId::BROADCAST => Err(IdError::Reserved(raw, "the broadcast address")),
        id => Ok(id),
    }
}

/// Errors of the registry file.
#[derive(Debug, thiserror::Error)]
pub enum RegistryError {
    /// The file could not be read or appended to.
    #[error("registry {path}: {source}")]
    Io {
        /// The registry file.
        path: PathBuf,
        /// The OS error.
        source: io::Error,
    },
    /// A line whose first field is not an ID.
    #[error("registry {path}, line {line}: {source}")]
    BadLine {
        /// The registry file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with its ID.
        source: IdError,
    },
}

/// One assigned ID as the registry records it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Entry {
    /// The node ID.
    pub id: NodeId,
    /// The rest of the line (unique ID, port, note), kept as written.
    pub rest: String,
    /// 1-based line number in the file.
    pub line: usize,
}

/// The CSV of IDs already assigned. A missing file is an empty registry (it is created on first use).
#[derive(Debug)]
pub struct Registry {
    path: PathBuf,
    entries: Vec<Entry>,
}

impl Registry {
    /// Reads `path`; blank lines, `#` comments and a header line starting with `id` are skipped.
    pub fn load(path: &Path) -> Result<Self, RegistryError> {
        let text = match fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == io::ErrorKind::NotFound => String::new(),
            Err(source) => {
                return Err(RegistryError::Io {
                    path: path.into(),
                    source,
                })
            }
        };
        let mut entries = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line_no = i + 1;
            let l = line.trim();
            if l.is_empty() || l.starts_with('#') {
                continue;
            }
            let (first, rest) = l.split_once(',').unwrap_or((l, ""));
            if first.trim().eq_ignore_ascii_case("id") {
                continue;
            }
            let id = parse_sc_id(first).map_err(|source| RegistryError::BadLine {
                path: path.into(),
                line: line_no,
                source,
            })?;
            entries.push(Entry {
                id,
                rest: rest.trim().to_owned(),
                line: line_no,
            });
        }
        Ok(Registry {
            path: path.into(),
            entries,
        })
    }

    /// The entries in file order.
    pub fn entries(&self) -> &[Entry] {
        &self.entries
    }

    /// Refuses `id` when a line already holds it.
    pub fn check_free(&self, id: NodeId) -> Result<(), IdError> {
        match self.entries.iter().find(|e| e.id == id) {
            Some(e) => Err(IdError::Duplicate {
                id,
                source_desc: format!("{} line {}: {:?}", self.path.display(), e.line, e.rest),
            }),
            None => Ok(()),
        }
    }

    /// Appends `id,uid,port,note` (writing the header first when the file is new).
    pub fn record(
        &mut self,
        id: NodeId,
        uid: &str,
        port: &str,
        note: &str,
    ) -> Result<(), RegistryError> {
        let io_err = |source| RegistryError::Io {
            path: self.path.clone(),
            source,
        };
        let is_new = fs::metadata(&self.path)
            .map(|m| m.len() == 0)
            .unwrap_or(true);
        let mut f = fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.path)
            .map_err(io_err)?;
        let clean = |s: &str| s.replace([',', '\n', '\r'], " ");
        let rest = format!("{},{},{}", clean(uid), clean(port), clean(note));
        let mut out = String::new();
        if is_new {
            out.push_str("id,uid,port,note\n");
        }
        out.push_str(&format!("{:03x},{rest}\n", id.get()));
        f.write_all(out.as_bytes()).map_err(io_err)?;
        let line = self.entries.last().map_or(0, |e| e.line) + 1 + usize::from(is_new);
        self.entries.push(Entry { id, rest, line });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepts_hex_ids_in_range() {
        assert_eq!(parse_sc_id("123").unwrap().get(), 0x123);
        assert_eq!(parse_sc_id("0x1").unwrap().get(), 1);
        assert_eq!(parse_sc_id(" FfD ").unwrap().get(), 0xffd);
        assert_eq!(parse_sc_id("0X00a").unwrap().get(), 0xa);
    }

    #[test]
    fn refuses_reserved_and_oversized_ids() {
        assert!(matches!(parse_sc_id("000"), Err(IdError::Reserved(0, _))));
        assert!(matches!(parse_sc_id("0"), Err(IdError::Reserved(0, _))));
        assert!(matches!(
            parse_sc_id("ffe"),
            Err(IdError::Reserved(0xffe, _))
        ));
        assert!(matches!(
            parse_sc_id("fff"),
            Err(IdError::Reserved(0xfff, _))
        ));
        for bad in ["", "0x", "12g", "-1", "1 2", "123456789", "1000", "fffff"] {
            assert!(
                matches!(parse_sc_id(bad), Err(IdError::NotHex(..))),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn error_messages_name_the_problem() {
        let msg = parse_sc_id("fff").unwrap_err().to_string();
        assert!(msg.contains("fff") && msg.contains("broadcast"), "{msg}");
        let msg = parse_sc_id("1000").unwrap_err().to_string();
        assert!(msg.contains("1 to 3 hex digits"), "{msg}");
    }

    fn temp_path(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("ihex-provision-{}-{name}", std::process::id()));
        let _ = fs::remove_file(&dir);
        dir
    }

    #[test]
    fn registry_round_trip_and_duplicates() {
        let path = temp_path("reg.csv");
        let mut reg = Registry::load(&path).unwrap();
        assert!(reg.entries().is_empty());
        reg.check_free(NodeId::new_sc(0x111).unwrap()).unwrap();
        reg.record(NodeId::new_sc(0x111).unwrap(), "", "/dev/ttyACM0", "hex 1")
            .unwrap();
        reg.record(NodeId::new_sc(0x2).unwrap(), "", "/dev/ttyACM1", "a,b")
            .unwrap();

        let again = Registry::load(&path).unwrap();
        let ids: Vec<u16> = again.entries().iter().map(|e| e.id.get()).collect();
        assert_eq!(ids, [0x111, 0x2]);
        assert_eq!(again.entries()[1].line, 3);
        assert_eq!(reg.entries(), again.entries());
        let err = again
            .check_free(NodeId::new_sc(0x111).unwrap())
            .unwrap_err();
        assert!(matches!(err, IdError::Duplicate { .. }));
        assert!(err.to_string().contains("line 2"), "{err}");
        again.check_free(NodeId::new_sc(0x112).unwrap()).unwrap();
        fs::remove_file(&path).unwrap();
    }

    #[test]
    fn registry_reports_bad_lines() {
        let path = temp_path("bad.csv");
        fs::write(&path, "# lab A\nid,uid\n001,x\n\nfff,broadcast?\n").unwrap();
        let err = Registry::load(&path).unwrap_err();
        assert!(
            matches!(err, RegistryError::BadLine { line: 5, .. }),
            "{err}"
        );
        fs::remove_file(&path).unwrap();
    }
}
