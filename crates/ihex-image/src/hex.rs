//! Hex text for digests and key files: the one formatter and the one key-file parser.
//!
//! A key file is text: lines starting with `#` are comments, blank lines are ignored, and exactly
//! one line holds the 32 key bytes as 64 hex digits. Parsing is a `const fn`, so a key file can
//! become a constant at compile time (`include_str!`).

use core::fmt;

use crate::error::KeyTextError;

/// Writes `bytes` as lower-case hex.
pub(crate) fn write(f: &mut fmt::Formatter<'_>, bytes: &[u8]) -> fmt::Result {
    for b in bytes {
        write!(f, "{b:02x}")?;
    }
    Ok(())
}

const fn nibble(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

const fn is_space(c: u8) -> bool {
    matches!(c, b' ' | b'\t' | b'\r')
}

/// The 32 bytes of a key file's text (see the module docs).
pub(crate) const fn parse_key_text(text: &str) -> Result<[u8; 32], KeyTextError> {
    let b = text.as_bytes();
    let mut key = [0u8; 32];
    let mut found = false;
    let mut i = 0;
    while i < b.len() {
        // One line: [i, end).
        let mut end = i;
        while end < b.len() && b[end] != b'\n' {
            end += 1;
        }
        let mut s = i;
        while s < end && is_space(b[s]) {
            s += 1;
        }
        let mut e = end;
        while e > s && is_space(b[e - 1]) {
            e -= 1;
        }
        if s < e && b[s] != b'#' {
            if found {
                return Err(KeyTextError::Several);
            }
            if e - s != 64 {
                return Err(KeyTextError::NotHex);
            }
            let mut k = 0;
            while k < 32 {
                match (nibble(b[s + 2 * k]), nibble(b[s + 2 * k + 1])) {
                    (Some(hi), Some(lo)) => key[k] = hi << 4 | lo,
                    _ => return Err(KeyTextError::NotHex),
                }
                k += 1;
            }
            found = true;
        }
        i = end + 1;
    }
    if found {
        Ok(key)
    } else {
        Err(KeyTextError::Missing)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEX: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";

    #[test]
    fn comments_blank_lines_and_spaces_are_ignored() {
        let text = format!("# a comment\n\n   {}  \r\n# trailer\n", HEX.to_uppercase());
        let want: Vec<u8> = (0..32).collect();
        assert_eq!(parse_key_text(&text).unwrap().to_vec(), want);
    }

    #[test]
    fn malformed_key_texts_are_refused() {
        assert_eq!(
            parse_key_text("# only a comment\n"),
            Err(KeyTextError::Missing)
        );
        assert_eq!(parse_key_text(&HEX[..62]), Err(KeyTextError::NotHex));
        let bad = format!("{}zz", &HEX[..62]);
        assert_eq!(parse_key_text(&bad), Err(KeyTextError::NotHex));
        let two = format!("{HEX}\n{HEX}\n");
        assert_eq!(parse_key_text(&two), Err(KeyTextError::Several));
    }
}
