//! The audit trail's verification time: a chain of realistic command and answer records written
//! into a temporary directory (not timed), then `verify_dir` over all of it, timed (docs/audit.md).

use std::path::Path;
use std::time::{Duration, Instant, SystemTime};

use ihex_audit::dir::{chain_files, verify_dir, Writer, WriterOptions};
use ihex_audit::{AuditError, Kind, Record};
use serde::{Deserialize, Serialize};

/// What one run measured.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AuditVerify {
    /// Records in the chain.
    pub records: u64,
    /// Their size on disk, bytes.
    pub bytes: u64,
    /// Files (rotated at the default size).
    pub files: usize,
    /// The fastest of the timed verifications, seconds (the file cache warm).
    pub seconds: f64,
}

/// The records the gateway writes for one command: the command as received, then its answer.
fn command_records(i: u64) -> [Record; 2] {
    let rid = format!("r{i}");
    let node = format!("{:x}", 1 + i % 64);
    let mut cmd = Record::new(
        Kind::Command,
        serde_json::json!({"command": {"cmd": "led", "node": node, "color": "red", "request_id": rid}}),
    );
    cmd.interface = Some("mqtt".into());
    cmd.user = Some("alice".into());
    cmd.request_id = Some(rid.clone());
    cmd.elements = vec![node.clone()];
    let mut answer = cmd.clone();
    answer.kind = Kind::Answer;
    answer.data = serde_json::json!({"event": "command_result", "payload": {"request_id": rid,
        "cmd": "led", "node": node, "result": "ok", "reason": null,
        "origin": {"interface": "mqtt", "user": "alice"}}});
    [cmd, answer]
}

/// Writes `records` records into `dir` and times their verification (`runs` times).
pub fn run(dir: &Path, records: u64, runs: usize) -> Result<AuditVerify, AuditError> {
    let (mut w, _) = Writer::open(dir, WriterOptions::default())?;
    let t0 = SystemTime::now();
    for i in 0..records.div_ceil(2) {
        for (j, r) in command_records(i).iter().enumerate() {
            if 2 * i + j as u64 >= records {
                break;
            }
            w.append(t0 + Duration::from_millis(i), r)?;
        }
    }
    w.sync()?;
    let files = chain_files(dir)?;
    let mut bytes = 0;
    for f in &files {
        bytes += std::fs::metadata(f).map(|m| m.len()).unwrap_or(0);
    }
    let mut best = f64::INFINITY;
    for _ in 0..runs.max(1) {
        let start = Instant::now();
        let report = verify_dir(dir, None)?;
        best = best.min(start.elapsed().as_secs_f64());
        assert_eq!(
            (report.records, report.broken),
            (records, None),
            "the benchmark's own chain verifies"
        );
    }
    Ok(AuditVerify {
        records,
        bytes,
        files: files.len(),
        seconds: best,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_small_chain_is_written_and_verified() {
        let dir = tempfile::tempdir().unwrap();
        let r = run(dir.path(), 1001, 1).unwrap();
        assert_eq!((r.records, r.files), (1001, 1));
        assert!(r.bytes > 1001 * 200, "{r:?}");
    }
}
