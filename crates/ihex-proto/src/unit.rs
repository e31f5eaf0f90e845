//! The bus's time unit: durations travel as `u8` counts of 10 ms (LED blink period, buzzer on/off).
//! The conversions are written here once for the gateway, the node core and the tools.

/// Milliseconds per unit of a `*_10ms` field.
pub const MS_PER_UNIT: u16 = 10;
/// Shortest duration a `*_10ms` field carries, in ms (1 unit).
pub const MIN_MS: u16 = MS_PER_UNIT;
/// Longest duration a `*_10ms` field carries, in ms (255 units).
pub const MAX_MS: u16 = 255 * MS_PER_UNIT;

/// The duration of `units` × 10 ms, in ms.
pub const fn to_ms(units: u8) -> u16 {
    units as u16 * MS_PER_UNIT
}

/// `ms` in 10 ms units, rounded to the nearest (…4 down, …5 up); `None` outside
/// [`MIN_MS`]`..=`[`MAX_MS`] (never clamped: a caller that wants a duration the bus cannot carry
/// must say so).
pub const fn from_ms(ms: u32) -> Option<u8> {
    if ms < MIN_MS as u32 || ms > MAX_MS as u32 {
        return None;
    }
    let units = (ms + MS_PER_UNIT as u32 / 2) / MS_PER_UNIT as u32;
    // 2550 + 5 rounds to 255 at most, so the cast is exact.
    Some(units as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounds_to_the_nearest_unit_and_refuses_what_the_bus_cannot_carry() {
        assert_eq!(from_ms(9), None);
        assert_eq!(from_ms(10), Some(1));
        assert_eq!(from_ms(14), Some(1));
        assert_eq!(from_ms(15), Some(2));
        assert_eq!(from_ms(504), Some(50));
        assert_eq!(from_ms(2550), Some(255));
        assert_eq!(from_ms(2551), None);
        for u in 1..=255u8 {
            assert_eq!(from_ms(u32::from(to_ms(u))), Some(u));
        }
    }
}
