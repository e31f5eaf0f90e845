//! The bytes a JSON string treats specially — `"`, `\` and the control characters below U+0020 —
//! found eight bytes at a time (as serde_json's own scan does): where the command parser's single
//! pass stops reading a string, and whether the writer must escape one.

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
}
