//! The calendar year of a Unix time (no time-zone data needed: the clock check only compares
//! years). Also compiled into the build script, which records the build year.

/// The UTC calendar year of `secs` seconds after 1970-01-01 (Howard Hinnant's `civil_from_days`).
pub fn year_of(secs: u64) -> i64 {
    let days = (secs / 86_400) as i64 + 719_468;
    let era = days.div_euclid(146_097);
    let doe = days - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let month_from_march = mp + if mp < 10 { 3 } else { -9 };
    yoe + era * 400 + i64::from(month_from_march <= 2)
}
