//! Clock sanity: a Pi without a real-time clock starts at its last saved time (or 1970) until NTP
//! answers; TLS certificates and log timestamps are wrong until then.

use super::{calendar::year_of, Verdict};

/// Identifier of the clock check.
pub const CHECK: &str = "clock";

/// The year this binary was built (the build script's `IHEX_BUILD_YEAR`).
pub const BUILD_YEAR: i64 = parse_year(env!("IHEX_BUILD_YEAR"));

const fn parse_year(s: &str) -> i64 {
    let b = s.as_bytes();
    let mut i = 0;
    let mut y = 0i64;
    while i < b.len() {
        y = y * 10 + (b[i] - b'0') as i64;
        i += 1;
    }
    y
}

/// Seconds since 1970 by the system clock (0 when it is before 1970).
pub fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// Judges the clock at `now` (Unix seconds) against the build year.
pub fn check(now: u64, build_year: i64) -> Verdict {
    let year = year_of(now);
    if year < build_year {
        Verdict::fail(
            CHECK,
            format!("the clock says {year}, before this gateway was built ({build_year})"),
            "the Pi has no battery clock: give it network time (`timedatectl` should say \
             \"System clock synchronized: yes\"; check the lab's NTP server is reachable), or \
             `sudo date -s 'YYYY-MM-DD HH:MM'`",
        )
    } else {
        Verdict::pass(CHECK, format!("year {year} (built {build_year})"))
    }
}
