//! A byte as decimal digits without the formatting machinery: the one writer of the `other_<n>`
//! texts and of protocol versions (`major.minor`).

/// Writes `n` in decimal (no leading zeros) into `buf` from `at`; returns the index after the
/// last digit. `buf` needs room for three digits after `at`. A `const fn`, so that tables of texts
/// can be built at compile time.
pub const fn write_decimal(n: u8, buf: &mut [u8], at: usize) -> usize {
    let mut i = at;
    if n >= 100 {
        buf[i] = b'0' + n / 100;
        i += 1;
    }
    if n >= 10 {
        buf[i] = b'0' + n / 10 % 10;
        i += 1;
    }
    buf[i] = b'0' + n % 10;
    i + 1
}
