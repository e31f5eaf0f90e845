//! Tampering with a chain is caught at the line it was done: property tests over edits, deletions,
//! insertions, swaps and truncations anywhere in the middle; rotation keeps the chain; a torn last
//! line is reported as such and a restarted writer continues a valid chain after it.

use std::fs;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use ihex_audit::dir::{chain_files, file_lines, verify_dir, Writer, WriterOptions};
use ihex_audit::verify::{Loc, RawLine};
use ihex_audit::{Chain, Head, Kind, Problem, Record, Verifier};
use proptest::prelude::*;

fn t0() -> SystemTime {
    UNIX_EPOCH + Duration::from_secs(1_764_079_510)
}

fn record(i: usize) -> Record {
    let mut r = Record::new(Kind::Command, serde_json::json!({"cmd": "led", "n": i}));
    r.user = Some(format!("user{}", i % 3));
    r.interface = Some("mqtt".into());
    r
}

/// `n` chained lines (without their `\n`).
fn chain(n: usize) -> Vec<Vec<u8>> {
    let mut c = Chain::new();
    (0..n)
        .map(|i| {
            let mut out = Vec::new();
            let b = c.build(t0(), &record(i), &mut out).unwrap();
            c.advance(b);
            out.pop();
            out
        })
        .collect()
}

fn raw(lines: &[Vec<u8>]) -> Vec<RawLine> {
    lines
        .iter()
        .enumerate()
        .map(|(i, b)| RawLine {
            loc: Loc {
                file: "f".into(),
                line: i as u64 + 1,
            },
            bytes: b.clone(),
            terminated: true,
        })
        .collect()
}

/// The first broken line (1-based) and its problem, `None` for a whole chain.
fn check(lines: &[RawLine], anchor: Option<Head>) -> Option<(u64, Problem)> {
    let mut v = anchor.map_or_else(Verifier::new, Verifier::with_anchor);
    for l in lines {
        v.push(l);
    }
    let f = v.finish().broken?;
    Some((f.loc.map_or(0, |l| l.line), f.problem))
}

const N: usize = 12;

#[test]
fn a_whole_chain_verifies() {
    assert_eq!(check(&raw(&chain(N)), None), None);
}

proptest! {
    #[test]
    fn an_edit_is_found_at_its_line(k in 0..N - 1, at in 0usize..200, byte in 0x20u8..0x7f) {
        let mut lines = chain(N);
        let at = at % lines[k].len();
        prop_assume!(lines[k][at] != byte);
        lines[k][at] = byte;
        let (line, problem) = check(&raw(&lines), None).expect("caught");
        prop_assert_eq!(line, k as u64 + 1, "{:?}", problem);
        prop_assert!(matches!(problem, Problem::Edited | Problem::Malformed(_)), "{:?}", problem);
    }

    #[test]
    fn a_rewritten_field_is_found_at_its_line(k in 0..N - 1) {
        let mut lines = chain(N);
        let text = String::from_utf8(lines[k].clone()).unwrap();
        lines[k] = text.replace("\"led\"", "\"buzzer\"").into_bytes();
        prop_assert_eq!(check(&raw(&lines), None), Some((k as u64 + 1, Problem::Edited)));
    }

    #[test]
    fn a_changed_seq_is_found_at_its_line(k in 1..N - 1, seq in 0u64..100) {
        let mut lines = chain(N);
        let text = String::from_utf8(lines[k].clone()).unwrap();
        let edited = text.replacen(&format!("\"seq\":{k},"), &format!("\"seq\":{seq},"), 1);
        prop_assume!(edited != text);
        lines[k] = edited.into_bytes();
        let (line, _) = check(&raw(&lines), None).expect("caught");
        prop_assert_eq!(line, k as u64 + 1);
    }

    #[test]
    fn a_deletion_is_found_where_the_line_was(k in 0..N - 1) {
        let mut lines = chain(N);
        lines.remove(k);
        let k = k as u64;
        prop_assert_eq!(
            check(&raw(&lines), None),
            Some((k + 1, Problem::Deleted { from: k, to: k }))
        );
    }

    #[test]
    fn an_insertion_is_found_at_the_inserted_line(k in 1..N, j in 0..N, forged in any::<bool>()) {
        let mut lines = chain(N);
        let extra = if forged {
            // A line made to look like the next record, chained to the line before it.
            let mut c = Chain::after(&lines[k - 1]).unwrap();
            let mut out = Vec::new();
            let b = c.build(t0(), &Record::new(Kind::Command, serde_json::json!({"forged": 1})), &mut out).unwrap();
            c.advance(b);
            out.pop();
            out
        } else {
            lines[j].clone()
        };
        // A forged line before the last one is as good as the last one: only the anchor tells.
        prop_assume!(!(forged && k == N - 1));
        lines.insert(k, extra);
        let (line, problem) = check(&raw(&lines), None).expect("caught");
        // A copy of the line that follows: of two identical lines, the second is the copy.
        let at = if !forged && j == k { k + 2 } else { k + 1 };
        prop_assert_eq!(line, at as u64, "{:?}", problem);
        prop_assert!(
            matches!(problem, Problem::Inserted | Problem::Reordered { .. }),
            "{:?}", problem
        );
    }

    #[test]
    fn a_swap_is_found_at_the_first_swapped_line(k in 0..N - 1, d in 0..N) {
        let mut lines = chain(N);
        let j = k + 1 + d % (N - 1 - k);
        lines.swap(k, j);
        let (line, problem) = check(&raw(&lines), None).expect("caught");
        prop_assert_eq!(line, k as u64 + 1, "{:?}", problem);
    }

    #[test]
    fn a_cut_line_in_the_middle_is_found(k in 0..N - 1, keep in 1usize..100) {
        let mut lines = chain(N);
        let keep = keep % lines[k].len();
        lines[k].truncate(keep);
        let (line, problem) = check(&raw(&lines), None).expect("caught");
        prop_assert_eq!(line, k as u64 + 1);
        prop_assert!(matches!(problem, Problem::Malformed(_)), "{:?}", problem);
    }

    #[test]
    fn a_cut_file_ends_in_a_torn_line(k in 0..N, keep in 1usize..100) {
        let mut lines = raw(&chain(N));
        lines.truncate(k + 1);
        let keep = keep % lines[k].bytes.len();
        lines[k].bytes.truncate(keep);
        lines[k].terminated = false;
        prop_assert_eq!(check(&lines, None), Some((k as u64 + 1, Problem::Torn)));
    }

    #[test]
    fn the_anchor_catches_the_end(cut in 1..N) {
        let lines = chain(N);
        let anchor = Head { seq: N as u64 - 1, hash: ihex_audit::chain::hash_line(&lines[N - 1]) };
        prop_assert_eq!(check(&raw(&lines), Some(anchor)), None);
        // Lines cut off at a line boundary: only the anchor shows it.
        let short = &lines[..N - cut];
        prop_assert_eq!(check(&raw(short), None), None);
        prop_assert_eq!(
            check(&raw(short), Some(anchor)),
            Some(((N - cut) as u64, Problem::Truncated { anchor: N as u64 - 1 }))
        );
        // The last line edited: only the anchor shows it.
        let mut edited = lines.clone();
        edited[N - 1] = String::from_utf8(edited[N - 1].clone()).unwrap().replace("led", "LED").into_bytes();
        prop_assert_eq!(check(&raw(&edited), None), None);
        prop_assert_eq!(check(&raw(&edited), Some(anchor)), Some((N as u64, Problem::AnchorMismatch)));
    }
}

fn opts(file_bytes: u64) -> WriterOptions {
    WriterOptions {
        file_bytes,
        max_bytes: None,
    }
}

#[test]
fn rotation_by_size_and_day_carries_the_chain() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut w, resumed) = Writer::open(tmp.path(), opts(600)).unwrap();
    assert_eq!(resumed.head, None);
    for i in 0..10 {
        w.append(t0(), &record(i)).unwrap();
    }
    // The next UTC day starts a file of its own.
    let head = w
        .append(t0() + Duration::from_secs(86_400), &record(10))
        .unwrap();
    assert_eq!(head.seq, 10);
    let files = chain_files(tmp.path()).unwrap();
    assert!(files.len() >= 3, "{files:?}");
    let last = files
        .last()
        .unwrap()
        .file_name()
        .unwrap()
        .to_str()
        .unwrap()
        .to_owned();
    assert_eq!(last, "audit-000000000010-20251126.jsonl");
    for f in &files[..files.len() - 1] {
        assert!(fs::metadata(f).unwrap().len() <= 600);
    }
    let report = verify_dir(tmp.path(), Some(head)).unwrap();
    assert_eq!((report.records, report.broken), (11, None));

    // A deletion across a file boundary: the second file's first line is gone.
    let second = &files[1];
    let text = fs::read_to_string(second).unwrap();
    let (_, rest) = text.split_once('\n').unwrap();
    fs::write(second, rest).unwrap();
    let broken = verify_dir(tmp.path(), None).unwrap().broken.unwrap();
    let name = second.file_name().unwrap().to_str().unwrap();
    assert_eq!(
        broken.loc.clone().unwrap(),
        Loc {
            file: name.into(),
            line: 1
        }
    );
    assert!(
        matches!(broken.problem, Problem::Deleted { .. }),
        "{broken}"
    );
}

#[test]
fn a_torn_line_is_reported_and_a_restart_continues_the_chain() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut w, _) = Writer::open(tmp.path(), opts(1 << 20)).unwrap();
    for i in 0..5 {
        w.append(t0(), &record(i)).unwrap();
    }
    drop(w);
    // A crash mid-write: half a line at the end of the file.
    let file = chain_files(tmp.path()).unwrap().pop().unwrap();
    let mut bytes = fs::read(&file).unwrap();
    bytes.extend_from_slice(br#"{"seq":5,"prev":"ab"#);
    fs::write(&file, &bytes).unwrap();
    let report = verify_dir(tmp.path(), None).unwrap();
    let broken = report.broken.unwrap();
    assert_eq!(broken.problem, Problem::Torn);
    assert_eq!(broken.loc.unwrap().line, 6);
    assert_eq!(report.records, 5);

    // The restarted writer leaves the torn line as it is and goes on in a new file.
    let (mut w, resumed) = Writer::open(tmp.path(), opts(1 << 20)).unwrap();
    assert_eq!(resumed.head.map(|h| h.seq), Some(4));
    assert_eq!(resumed.torn.unwrap().line, 6);
    let head = w.append(t0(), &record(5)).unwrap();
    assert_eq!(head.seq, 5);
    w.append(t0(), &record(6)).unwrap();
    assert_eq!(
        fs::read(&file).unwrap(),
        bytes,
        "the old file is not touched"
    );
    let report = verify_dir(tmp.path(), None).unwrap();
    assert_eq!(report.broken, None);
    assert_eq!(report.records, 7);
    assert_eq!(report.recovered.len(), 1);
    assert_eq!(report.recovered[0].line, 6);
}

#[test]
fn a_torn_first_line_of_a_file_does_not_share_its_name() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut w, _) = Writer::open(tmp.path(), opts(1 << 20)).unwrap();
    w.append(t0(), &record(0)).unwrap();
    drop(w);
    // A crash right after a new file was started: a file holding only a torn line.
    let torn = tmp.path().join("audit-000000000001-20251125.jsonl");
    fs::write(&torn, br#"{"seq":1,"#).unwrap();
    let (mut w, resumed) = Writer::open(tmp.path(), opts(1 << 20)).unwrap();
    assert_eq!(resumed.head.map(|h| h.seq), Some(0));
    w.append(t0(), &record(1)).unwrap();
    assert_eq!(fs::read(&torn).unwrap(), br#"{"seq":1,"#);
    let files = chain_files(tmp.path()).unwrap();
    assert_eq!(
        files.last().unwrap().file_name().unwrap(),
        "audit-000000000001-20251125-1.jsonl"
    );
    let report = verify_dir(tmp.path(), None).unwrap();
    assert_eq!((report.records, report.broken), (2, None));
    let lines = file_lines(files.last().unwrap()).unwrap();
    assert_eq!(lines.len(), 1);
}

#[test]
fn a_full_directory_refuses_and_keeps_the_chain_whole() {
    let tmp = tempfile::tempdir().unwrap();
    let options = WriterOptions {
        file_bytes: 1 << 20,
        max_bytes: Some(700),
    };
    let (mut w, _) = Writer::open(tmp.path(), options).unwrap();
    let mut written = 0;
    let err = loop {
        match w.append(t0(), &record(written)) {
            Ok(_) => written += 1,
            Err(e) => break e,
        }
    };
    assert!(err.is_full(), "{err}");
    assert!(written >= 2);
    assert_eq!(w.head().unwrap().seq, written as u64 - 1);
    let report = verify_dir(tmp.path(), None).unwrap();
    assert_eq!((report.records, report.broken), (written as u64, None));
}
