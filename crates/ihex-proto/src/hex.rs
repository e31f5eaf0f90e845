//! Bytes as lower-case hex digits: the one writer of UIDs, image hashes and raw frame data.

use core::fmt;

/// `bytes` as lower-case hex digits, two per byte, no separators (`Display`). Written a chunk at a
/// time from a table, not a `{:02x}` per byte: state documents carry several of these.
#[derive(Clone, Copy, Debug)]
pub struct Hex<'a>(pub &'a [u8]);

const DIGITS: &[u8; 16] = b"0123456789abcdef";

impl fmt::Display for Hex<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut buf = [0u8; 64];
        for chunk in self.0.chunks(buf.len() / 2) {
            for (pair, b) in buf.chunks_exact_mut(2).zip(chunk) {
                pair[0] = DIGITS[usize::from(b >> 4)];
                pair[1] = DIGITS[usize::from(b & 0x0f)];
            }
            let text = core::str::from_utf8(&buf[..chunk.len() * 2]).map_err(|_| fmt::Error)?;
            f.write_str(text)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::{format, string::String, vec::Vec};

    #[test]
    fn matches_the_formatter_for_every_byte_and_length() {
        let all: Vec<u8> = (0..=255).collect();
        let slow: String = all.iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(format!("{}", Hex(&all)), slow);
        for n in [0, 1, 31, 32, 33, 64, 65] {
            let slow: String = all[..n].iter().map(|b| format!("{b:02x}")).collect();
            assert_eq!(format!("{}", Hex(&all[..n])), slow, "length {n}");
        }
    }
}
