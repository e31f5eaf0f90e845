//! The bytes a JSON string treats specially — `"`, `\` and the control characters below U+0020 —
//! found eight bytes at a time (as serde_json's own scan does): where the command parser's single
//! pass stops reading a string, and how a writer escapes one ([`write_str`]: the publications'
//! JSON, the gateway's JSON log lines).

/// Where the first `"`, `\` or control character is in `bytes`.
pub(crate) fn special_byte(bytes: &[u8]) -> Option<usize> {
    const ONES: u64 = u64::from_le_bytes([1; 8]);
    const HIGH: u64 = ONES << 7;
    // Per byte, the high bit of `x - 1 & !x` is set where `x` is zero; the lowest flag is always
    // right (a borrow only flags bytes above a zero one), which is all this needs.
    let zero = |x: u64| x.wrapping_sub(ONES) & !x;
    let mut chunks = bytes.chunks_exact(8);
    for (i, chunk) in chunks.by_ref().enumerate() {
        let mut word = [0; 8];
        word.copy_from_slice(chunk);
        let w = u64::from_le_bytes(word);
        let found = (zero(w ^ (ONES * u64::from(b'"')))
            | zero(w ^ (ONES * u64::from(b'\\')))
            | w.wrapping_sub(ONES * 0x20) & !w)
            & HIGH;
        if found != 0 {
            return Some(i * 8 + (found.trailing_zeros() / 8) as usize);
        }
    }
    let tail = chunks.remainder();
    let at = tail
        .iter()
        .position(|&b| b == b'"' || b == b'\\' || b < 0x20)?;
    Some(bytes.len() - tail.len() + at)
}

/// Writes `s` as a JSON string, quotes included, in the pieces `out` is given: runs of `s` as they
/// are and the escapes between them — the bytes serde_json writes for it (`\"`, `\\`, `\b`, `\f`,
/// `\n`, `\r`, `\t`, other control characters as `\u00xx`).
pub fn write_str(s: &str, mut out: impl FnMut(&str)) {
    let bytes = s.as_bytes();
    let Some(first) = special_byte(bytes) else {
        out("\"");
        out(s);
        return out("\"");
    };
    out("\"");
    let mut run = 0;
    for (i, &b) in bytes.iter().enumerate().skip(first) {
        let short = match b {
            b'"' => "\\\"",
            b'\\' => "\\\\",
            0x08 => "\\b",
            0x09 => "\\t",
            0x0a => "\\n",
            0x0c => "\\f",
            0x0d => "\\r",
            0x00..=0x1f => "",
            _ => continue,
        };
        // Every byte split at is ASCII, so both pieces are whole characters.
        out(&s[run..i]);
        run = i + 1;
        if short.is_empty() {
            const DIGITS: &[u8; 16] = b"0123456789abcdef";
            let (hi, lo) = (DIGITS[usize::from(b >> 4)], DIGITS[usize::from(b & 0xf)]);
            let u = [b'\\', b'u', b'0', b'0', hi, lo];
            out(std::str::from_utf8(&u).unwrap_or_default());
        } else {
            out(short);
        }
    }
    out(&s[run..]);
    out("\"");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_quote_backslash_or_control_character_is_found() {
        for len in 0..24 {
            for end in [b'"', b'\\', b'\n', 0, 0x1f] {
                // Non-ASCII and bytes near the ones looked for before it, other enders after it.
                let mut bytes: Vec<u8> = "a\u{e9} !#[\x7f".bytes().cycle().take(len).collect();
                bytes.push(end);
                bytes.extend_from_slice(b"\"\\\x01xyz");
                assert_eq!(special_byte(&bytes), Some(len), "{bytes:?}");
            }
            let plain: Vec<u8> = "ab\x20\x21\u{e9}".bytes().cycle().take(len).collect();
            assert_eq!(special_byte(&plain), None);
        }
    }

    #[test]
    fn strings_are_written_as_serde_json_writes_them() {
        let mut all: String = (0u8..0x80).map(char::from).collect();
        all.push_str("\u{e9}\u{2028}\u{1f600}\"end");
        for s in ["", "plain", "a\"b", "\\", "\u{7f}", "\x00\x1f", &all] {
            let mut text = String::new();
            write_str(s, |t| text.push_str(t));
            assert_eq!(text, serde_json::to_string(s).unwrap(), "{s:?}");
        }
    }
}
