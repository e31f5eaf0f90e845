//! The chain, sans-IO: how one record becomes one JSON line that carries its sequence number and the
//! SHA-256 of the line before it. Nothing here touches a file or reads a clock: the writer
//! ([`crate::dir`]) passes the time in and writes the bytes out.
//!
//! A line is `{"seq":N,"prev":"<64 hex digits>","ts":"<RFC 3339 UTC, ms>",<the record's fields>}`
//! followed by `\n`. `prev` is the SHA-256 of the previous line's bytes without its `\n`; the first
//! record of a chain has `seq` 0 and `prev` [`GENESIS`].

use std::time::SystemTime;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// The `prev` of a chain's first record.
pub const GENESIS: &str = "0000000000000000000000000000000000000000000000000000000000000000";

/// A SHA-256 digest.
pub type Hash = [u8; 32];

/// The SHA-256 of a line's bytes (without its `\n`).
pub fn hash_line(line: &[u8]) -> Hash {
    Sha256::digest(line).into()
}

/// `hash` as 64 lowercase hex digits.
pub fn to_hex(hash: &Hash) -> String {
    hex_in(hash, &mut [0; 64]).to_owned()
}

/// `hash` as 64 lowercase hex digits, written into `buf` (no allocation on a record's path).
fn hex_in<'b>(hash: &Hash, buf: &'b mut [u8; 64]) -> &'b str {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    for (i, b) in hash.iter().enumerate() {
        buf[2 * i] = DIGITS[usize::from(b >> 4)];
        buf[2 * i + 1] = DIGITS[usize::from(b & 15)];
    }
    // Only ASCII digits were written.
    std::str::from_utf8(buf).unwrap_or_default()
}

/// 64 hex digits as a hash; `None` for anything else.
pub fn from_hex(s: &str) -> Option<Hash> {
    let b = s.as_bytes();
    if b.len() != 64 {
        return None;
    }
    let digit = |c: u8| match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    };
    let mut out = [0u8; 32];
    for (i, pair) in b.chunks_exact(2).enumerate() {
        out[i] = digit(pair[0])? << 4 | digit(pair[1])?;
    }
    Some(out)
}

/// The last record of a chain: its sequence number and the hash of its line. Published as the
/// anchor, and compared with one by the verification.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Head {
    /// Its sequence number.
    pub seq: u64,
    /// The SHA-256 of its line.
    pub hash: Hash,
}

impl Head {
    /// `SEQ:HEX`, the form the anchor and `audit verify --head` use.
    pub fn to_text(&self) -> String {
        format!("{}:{}", self.seq, to_hex(&self.hash))
    }

    /// Reads `SEQ:HEX`.
    pub fn from_text(s: &str) -> Option<Head> {
        let (seq, hash) = s.trim().split_once(':')?;
        Some(Head {
            seq: seq.parse().ok()?,
            hash: from_hex(hash)?,
        })
    }
}

/// The parts of a line the chain itself reads.
#[derive(Deserialize)]
pub(crate) struct Link<'a> {
    pub(crate) seq: u64,
    #[serde(borrow)]
    pub(crate) prev: &'a str,
}

/// A line not (or no longer) readable as a record.
#[derive(Debug, thiserror::Error)]
pub enum LineError {
    /// Not JSON with a `seq` and a `prev`.
    #[error("not an audit record: {0}")]
    NotARecord(String),
    /// `prev` is not 64 hex digits.
    #[error("`prev` is not a SHA-256 in hex")]
    BadPrev,
}

/// Reads a line's `seq` and `prev`.
pub(crate) fn link(line: &[u8]) -> Result<(u64, Hash), LineError> {
    let l: Link<'_> =
        serde_json::from_slice(line).map_err(|e| LineError::NotARecord(e.to_string()))?;
    Ok((l.seq, from_hex(l.prev).ok_or(LineError::BadPrev)?))
}

#[derive(Serialize)]
struct Line<'a, B> {
    seq: u64,
    prev: &'a str,
    ts: &'a str,
    #[serde(flatten)]
    body: &'a B,
}

/// `t` as RFC 3339 UTC with milliseconds (`2026-11-25T14:05:10.123Z`).
pub fn rfc3339(t: SystemTime) -> String {
    rfc3339_in(t, &mut [0; 32]).to_owned()
}

/// [`rfc3339`], written into `buf` (no allocation on a record's path).
fn rfc3339_in(t: SystemTime, buf: &mut [u8; 32]) -> &str {
    use std::io::Write;
    let t = time::OffsetDateTime::from(t);
    let mut w = &mut buf[..];
    let _ = write!(
        w,
        "{:04}-{:02}-{:02}T{:02}:{:02}:{:02}.{:03}Z",
        t.year(),
        u8::from(t.month()),
        t.day(),
        t.hour(),
        t.minute(),
        t.second(),
        t.millisecond()
    );
    let len = 32 - w.len();
    std::str::from_utf8(&buf[..len]).unwrap_or_default()
}

/// Where the chain stands: the next record's sequence number and `prev`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Chain {
    next: u64,
    prev: Hash,
}

/// A line built and not yet written: [`Chain::advance`] once it is.
#[derive(Debug)]
#[must_use]
pub struct Built {
    head: Head,
}

impl Built {
    /// The head the chain has once the line is written.
    pub fn head(&self) -> Head {
        self.head
    }
}

impl Default for Chain {
    fn default() -> Self {
        Chain::new()
    }
}

impl Chain {
    /// An empty chain: its first record has `seq` 0 and `prev` [`GENESIS`].
    pub fn new() -> Chain {
        Chain {
            next: 0,
            prev: [0; 32],
        }
    }

    /// The chain that continues after `last_line` (its bytes without `\n`).
    pub fn after(last_line: &[u8]) -> Result<Chain, LineError> {
        let (seq, _) = link(last_line)?;
        Ok(Chain {
            next: seq + 1,
            prev: hash_line(last_line),
        })
    }

    /// The sequence number of the next record.
    pub fn next_seq(&self) -> u64 {
        self.next
    }

    /// The last record written, `None` for an empty chain.
    pub fn head(&self) -> Option<Head> {
        Some(Head {
            seq: self.next.checked_sub(1)?,
            hash: self.prev,
        })
    }

    /// Appends the line of `body` (a struct or map; its fields follow `seq`, `prev` and `ts`)
    /// recorded at `ts`, with its `\n`, to `out`. The chain moves on only at [`Chain::advance`],
    /// once the line is safely written.
    pub fn build<B: Serialize>(
        &self,
        ts: SystemTime,
        body: &B,
        out: &mut Vec<u8>,
    ) -> Result<Built, serde_json::Error> {
        let start = out.len();
        let (mut prev, mut time) = ([0; 64], [0; 32]);
        let line = Line {
            seq: self.next,
            prev: hex_in(&self.prev, &mut prev),
            ts: rfc3339_in(ts, &mut time),
            body,
        };
        serde_json::to_writer(&mut *out, &line)?;
        let hash = hash_line(&out[start..]);
        out.push(b'\n');
        Ok(Built {
            head: Head {
                seq: self.next,
                hash,
            },
        })
    }

    /// The line `built` describes was written: the next record chains to it.
    pub fn advance(&mut self, built: Built) {
        self.next = built.head.seq + 1;
        self.prev = built.head.hash;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, UNIX_EPOCH};

    #[test]
    fn lines_chain_to_each_other() {
        let mut c = Chain::new();
        let t = UNIX_EPOCH + Duration::from_millis(1_764_079_510_123);
        let mut out = Vec::new();
        let b = c
            .build(t, &serde_json::json!({"kind": "start"}), &mut out)
            .unwrap();
        c.advance(b);
        let first = out.strip_suffix(b"\n").unwrap().to_vec();
        assert_eq!(
            String::from_utf8(first.clone()).unwrap(),
            format!(
                r#"{{"seq":0,"prev":"{GENESIS}","ts":"2025-11-25T14:05:10.123Z","kind":"start"}}"#
            )
        );
        out.clear();
        let b = c
            .build(t, &serde_json::json!({"kind": "x"}), &mut out)
            .unwrap();
        assert_eq!(b.head().seq, 1);
        let (seq, prev) = link(out.strip_suffix(b"\n").unwrap()).unwrap();
        assert_eq!((seq, prev), (1, hash_line(&first)));
        // Not advanced: the same record again.
        assert_eq!(c.next_seq(), 1);
        c.advance(b);
        assert_eq!(Chain::after(out.strip_suffix(b"\n").unwrap()).unwrap(), c);
    }

    #[test]
    fn head_text_round_trips() {
        let h = Head {
            seq: 42,
            hash: hash_line(b"x"),
        };
        assert_eq!(Head::from_text(&h.to_text()), Some(h));
        assert_eq!(Head::from_text("42:abc"), None);
    }
}
