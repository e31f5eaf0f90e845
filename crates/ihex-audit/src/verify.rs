//! Verification, sans-IO: the lines of a chain in, the first broken line and what is wrong with it
//! out. It reads one line ahead, which is what tells an edit from an insertion, a deletion from a
//! swap (see [`Problem`]).
//!
//! What the chain alone cannot show: an edit of the very last line, or lines cut off the end at a
//! line boundary. Both are caught when the verification is given the head an anchor published
//! ([`Verifier::with_anchor`]).

use std::fmt;

use crate::chain::{hash_line, link, to_hex, Hash, Head};

/// Where a line is: its file (as the caller names it) and its line number there (from 1).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Loc {
    /// The file's name.
    pub file: String,
    /// The line number, from 1.
    pub line: u64,
}

impl fmt::Display for Loc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.file, self.line)
    }
}

/// One line of a chain as read from its file.
#[derive(Clone, Debug)]
pub struct RawLine {
    /// Where it is.
    pub loc: Loc,
    /// Its bytes, without the `\n`.
    pub bytes: Vec<u8>,
    /// It ended with `\n` (only the last line of a file may not: a write a crash cut short).
    pub terminated: bool,
}

/// What is wrong with a line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Problem {
    /// The last line of the chain is incomplete (no `\n`): the writer stopped mid-line (a crash,
    /// a power cut) or the file was cut there.
    Torn,
    /// Not a record: edited so that it no longer parses, or cut short in the middle of the chain.
    Malformed(String),
    /// Changed after it was written: the next line's `prev` is not its hash (or its `seq` is not
    /// the one its place calls for).
    Edited,
    /// Records `from..=to` are missing before this line.
    Deleted {
        /// First missing sequence number.
        from: u64,
        /// Last missing sequence number.
        to: u64,
    },
    /// Not part of the chain: added between two records.
    Inserted,
    /// Out of order: this record belongs elsewhere (a swap or a move).
    Reordered {
        /// The sequence number this place calls for.
        expected: u64,
    },
    /// The chain ends before the anchor's head: records were cut off its end.
    Truncated {
        /// The anchor's sequence number.
        anchor: u64,
    },
    /// The line at the anchor's sequence number is not the one the anchor recorded.
    AnchorMismatch,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::Torn => write!(f, "torn last line: the write was cut short (a crash?)"),
            Problem::Malformed(why) => write!(f, "not a record (edited or cut): {why}"),
            Problem::Edited => write!(
                f,
                "edited: the line differs from the one the next record's hash was made from"
            ),
            Problem::Deleted { from, to } if from == to => {
                write!(f, "deleted: record {from} is missing before this line")
            }
            Problem::Deleted { from, to } => {
                write!(
                    f,
                    "deleted: records {from} to {to} are missing before this line"
                )
            }
            Problem::Inserted => write!(f, "inserted: this line is not part of the chain"),
            Problem::Reordered { expected } => write!(
                f,
                "reordered: record {expected} belongs here (records swapped or moved)"
            ),
            Problem::Truncated { anchor } => write!(
                f,
                "truncated: the chain ends before record {anchor}, which the anchor recorded"
            ),
            Problem::AnchorMismatch => write!(
                f,
                "the anchor recorded a different line for this record (edited or rewritten)"
            ),
        }
    }
}

/// The first broken line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Finding {
    /// Where it is (for [`Problem::Truncated`]: the chain's last line).
    pub loc: Option<Loc>,
    /// What is wrong.
    pub problem: Problem,
}

impl fmt::Display for Finding {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.loc {
            Some(loc) => write!(f, "{loc}: {}", self.problem),
            None => write!(f, "{}", self.problem),
        }
    }
}

/// What the verification found.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct Report {
    /// Records checked (up to the first broken line).
    pub records: u64,
    /// The last good record.
    pub head: Option<Head>,
    /// Torn lines a restarted writer left behind and continued after (in a new file): the chain
    /// goes on from the line before each.
    pub recovered: Vec<Loc>,
    /// The first broken line, `None` when the chain is whole.
    pub broken: Option<Finding>,
}

#[derive(Clone, Debug)]
struct Parsed {
    loc: Loc,
    hash: Hash,
    link: Result<(u64, Hash), String>,
}

impl Parsed {
    fn new(raw: &RawLine) -> Parsed {
        Parsed {
            loc: raw.loc.clone(),
            hash: hash_line(&raw.bytes),
            link: link(&raw.bytes).map_err(|e| e.to_string()),
        }
    }

    fn seq(&self) -> Option<u64> {
        self.link.as_ref().ok().map(|l| l.0)
    }

    fn prev(&self) -> Option<Hash> {
        self.link.as_ref().ok().map(|l| l.1)
    }
}

/// Checks a chain line by line: [`Verifier::push`] every line in order (files in order of their
/// first record), then [`Verifier::finish`].
#[derive(Debug, Default)]
pub struct Verifier {
    report: Report,
    /// The last good line.
    before: Option<Parsed>,
    /// The line being judged, waiting for the one after it.
    cur: Option<(Parsed, bool)>,
    /// The head an anchor published, if the caller has one.
    anchor: Option<Head>,
}

impl Verifier {
    /// A verifier at the start of a chain.
    pub fn new() -> Verifier {
        Verifier::default()
    }

    /// A verifier that also checks the chain against the head an anchor published: the record
    /// with the anchor's number must have the anchor's hash, and the chain must reach it.
    pub fn with_anchor(anchor: Head) -> Verifier {
        Verifier {
            anchor: Some(anchor),
            ..Verifier::default()
        }
    }

    /// True once a broken line was found (further lines are not read).
    pub fn done(&self) -> bool {
        self.report.broken.is_some()
    }

    /// The next line of the chain (only a file's last line may lack its `\n`).
    pub fn push(&mut self, raw: &RawLine) {
        if self.done() {
            return;
        }
        let next = Parsed::new(raw);
        if let Some((cur, terminated)) = self.cur.take() {
            if !terminated {
                // A torn line followed by more: the writer restarted in a new file and chained
                // on from the line before it.
                self.report.recovered.push(cur.loc);
            } else {
                self.judge(cur, Some(&next));
            }
        }
        self.cur = Some((next, raw.terminated));
    }

    /// The end of the chain: judges the last line and, with an anchor, checks that the chain
    /// reaches it.
    pub fn finish(mut self) -> Report {
        if let Some((cur, terminated)) = self.cur.take() {
            if self.done() {
            } else if !terminated {
                self.fail(Some(cur.loc), Problem::Torn);
            } else {
                self.judge(cur, None);
            }
        }
        if let (Some(anchor), None) = (self.anchor, &self.report.broken) {
            if self.report.head.is_none_or(|h| h.seq < anchor.seq) {
                let loc = self.before.as_ref().map(|b| b.loc.clone());
                let anchor = anchor.seq;
                self.fail(loc, Problem::Truncated { anchor });
            }
        }
        self.report
    }

    fn fail(&mut self, loc: Option<Loc>, problem: Problem) {
        self.report.broken = Some(Finding { loc, problem });
    }

    fn accept(&mut self, cur: Parsed, seq: u64) {
        if let Some(a) = self.anchor {
            if a.seq == seq && a.hash != cur.hash {
                return self.fail(Some(cur.loc), Problem::AnchorMismatch);
            }
        }
        self.report.records += 1;
        self.report.head = Some(Head {
            seq,
            hash: cur.hash,
        });
        self.before = Some(cur);
    }

    /// Judges `cur` knowing the line after it (`None` at the end of the chain).
    fn judge(&mut self, cur: Parsed, next: Option<&Parsed>) {
        let (seq, prev) = match &cur.link {
            Ok(l) => *l,
            Err(why) => return self.fail(Some(cur.loc.clone()), Problem::Malformed(why.clone())),
        };
        let expected = self
            .before
            .as_ref()
            .and_then(Parsed::seq)
            .map_or(0, |s| s + 1);
        let before_hash = self.before.as_ref().map_or([0; 32], |b| b.hash);
        let next_seq = next.and_then(Parsed::seq);
        let next_prev = next.and_then(Parsed::prev);
        if seq == expected {
            if prev == before_hash {
                return self.accept(cur, seq);
            }
            if next_seq == Some(seq) || self.before.as_ref().is_some_and(|b| b.hash == cur.hash) {
                return self.fail(Some(cur.loc), Problem::Inserted);
            }
            // Its `prev` does not match the line before: either that line was edited (then the
            // line after this one still chains to this one), or this one was.
            let loc = match (next_prev, &self.before) {
                (Some(np), _) if np != cur.hash => cur.loc,
                (_, Some(b)) => b.loc.clone(),
                (_, None) => cur.loc,
            };
            return self.fail(Some(loc), Problem::Edited);
        }
        if let Some(b) = &self.before {
            if b.seq() == Some(seq) {
                // Two lines with one number: the one the next line chains to is genuine.
                let loc = if b.hash == cur.hash || next_prev != Some(cur.hash) {
                    cur.loc
                } else {
                    b.loc.clone()
                };
                return self.fail(Some(loc), Problem::Inserted);
            }
        }
        let problem = if next_seq == Some(expected + 1) {
            // The next line is the one after this place: this line's number was changed.
            Problem::Edited
        } else if next_seq == Some(expected) && prev == next.map_or([0; 32], |n| n.hash) {
            Problem::Reordered { expected }
        } else if next_seq == Some(expected) && next_prev == Some(before_hash) {
            Problem::Inserted
        } else if seq > expected {
            Problem::Deleted {
                from: expected,
                to: seq - 1,
            }
        } else {
            Problem::Reordered { expected }
        };
        self.fail(Some(cur.loc), problem)
    }
}

/// The head as text for a report.
pub fn describe_head(head: Option<Head>) -> String {
    match head {
        Some(h) => format!("record {} ({})", h.seq, to_hex(&h.hash)),
        None => "no record".into(),
    }
}
