//! The iHEX audit trail: an append-only chain of JSON lines, each carrying its sequence number and
//! the SHA-256 of the line before it, so that an edit, a deletion, an insertion or a reordering of
//! lines shows at the line where it was made ([`verify`]). [`chain`] builds lines (sans-IO, time
//! passed in); [`dir`] keeps them in files rotated by size and day, the chain carried across
//! files, and continues it after a crash; [`record`] is what a line says (who, through which
//! interface, what, with what outcome). docs/audit.md describes the trail and its threat model.
//!
//! ```
//! use std::time::SystemTime;
//! use ihex_audit::{dir::{verify_dir, Writer, WriterOptions}, record::{Kind, Record}};
//!
//! let tmp = tempfile::tempdir().unwrap();
//! let (mut w, _) = Writer::open(tmp.path(), WriterOptions::default()).unwrap();
//! w.append(SystemTime::now(), &Record::new(Kind::Start, serde_json::json!({"version": "0.1.0"}))).unwrap();
//! w.append(SystemTime::now(), &Record::new(Kind::Stop, serde_json::Value::Null)).unwrap();
//! let report = verify_dir(tmp.path(), None).unwrap();
//! assert_eq!((report.records, report.broken), (2, None));
//! ```

#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod chain;
pub mod dir;
pub mod record;
pub mod verify;

pub use chain::{Chain, Head};
pub use dir::{AuditError, Writer, WriterOptions};
pub use record::{Entry, Kind, Record};
pub use verify::{Finding, Problem, Report, Verifier};
