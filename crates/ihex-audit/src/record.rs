//! What one audit record says: the fields every record may have (who, through which interface,
//! about which elements) and the record's own data. The gateway writes these; `ihex-provision audit
//! show` reads them.

use serde::{Deserialize, Serialize};

/// What happened.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// The gateway started (with its version and configuration).
    Start,
    /// The gateway stopped.
    Stop,
    /// A command, as received.
    Command,
    /// A command's answer (`command_result` or `command_rejected`).
    Answer,
    /// The leases held changed (the retained leases document).
    Lease,
    /// A firmware upload or update ended (`fw_report`, an upload's outcome).
    Firmware,
    /// Records that could not be written (a full disk): how many, and when.
    Gap,
}

/// One record (the chain adds `seq`, `prev` and `ts`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// What happened.
    pub kind: Kind,
    /// The interface a command came through (`mqtt`, `web`, `ha`, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interface: Option<String>,
    /// The identity something other than the sender vouches for (the broker's username, the web
    /// token's name, a client certificate's name, `local`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub user: Option<String>,
    /// A name the sender gave itself in the command: recorded, not vouched for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub claimed: Option<String>,
    /// The command's `request_id`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub request_id: Option<String>,
    /// The elements (node IDs as the MQTT API writes them) it concerns; empty for the whole island.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub elements: Vec<String>,
    /// The rest: the command as received, the answer, the leases, the report.
    #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
    pub data: serde_json::Value,
}

impl Record {
    /// A record of `kind` with `data` and nothing else.
    pub fn new(kind: Kind, data: serde_json::Value) -> Record {
        Record {
            kind,
            interface: None,
            user: None,
            claimed: None,
            request_id: None,
            elements: Vec::new(),
            data,
        }
    }

    /// True when it concerns `element` (or the whole island: no elements named).
    pub fn concerns(&self, element: &str) -> bool {
        self.elements.is_empty()
            || self
                .elements
                .iter()
                .any(|e| e.eq_ignore_ascii_case(element))
    }
}

/// A line read back: the chain's fields and the record.
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct Entry {
    /// Its sequence number.
    pub seq: u64,
    /// When it was recorded (RFC 3339 UTC).
    pub ts: String,
    /// The record.
    #[serde(flatten)]
    pub record: Record,
}
