//! The Raspberry Pi's boot configuration (`config.txt`): SPI on, and the `mcp2515-can0` overlay with
//! the HAT's crystal and interrupt GPIO (`deploy/boot/config.txt`, `docs/deploy.md` section 3).
//!
//! [`check`] judges the text; [`check_file`] reads the file first.

use std::path::{Path, PathBuf};

use super::Verdict;

/// Identifier of the SPI check.
pub const SPI: &str = "boot.spi";
/// Identifier of the overlay check.
pub const OVERLAY: &str = "boot.overlay";
/// Where Raspberry Pi OS keeps `config.txt`: bookworm first, then bullseye and older.
pub const DEFAULT_PATHS: [&str; 2] = ["/boot/firmware/config.txt", "/boot/config.txt"];
/// The overlay that creates `can0` for an MCP2515 on SPI0 CE0.
pub const OVERLAY_NAME: &str = "mcp2515-can0";

/// What the HAT needs in the overlay's parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Hat {
    /// The MCP2515's crystal, Hz.
    pub oscillator: u32,
    /// The GPIO its INT pin drives.
    pub interrupt: u8,
}

impl Default for Hat {
    /// The HAT `deploy/boot/config.txt` is written for: 8 MHz crystal, INT on GPIO 25.
    fn default() -> Hat {
        Hat {
            oscillator: 8_000_000,
            interrupt: 25,
        }
    }
}

impl Hat {
    /// The overlay line this HAT needs.
    pub fn overlay_line(&self) -> String {
        format!(
            "dtoverlay={OVERLAY_NAME},oscillator={},interrupt={}",
            self.oscillator, self.interrupt
        )
    }
}

/// Which `config.txt` to read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Location {
    /// Named with `--boot-config`: it must be readable.
    Given(PathBuf),
    /// The first of [`DEFAULT_PATHS`] that exists.
    Found(PathBuf),
    /// None of them exists: not a Raspberry Pi.
    Absent,
}

/// The file to read: `given`, else the first of [`DEFAULT_PATHS`] that exists.
pub fn locate(given: Option<&Path>) -> Location {
    match given {
        Some(p) => Location::Given(p.to_owned()),
        None => DEFAULT_PATHS
            .iter()
            .map(PathBuf::from)
            .find(|p| p.is_file())
            .map_or(Location::Absent, Location::Found),
    }
}

/// Reads the located file and checks it.
pub fn check_file(location: Location, hat: &Hat) -> Vec<Verdict> {
    let path = match location {
        Location::Absent => {
            let why = format!(
                "not a Raspberry Pi: neither {} nor {} exists (give --boot-config FILE to check one)",
                DEFAULT_PATHS[0], DEFAULT_PATHS[1]
            );
            return vec![Verdict::skip(SPI, why.clone()), Verdict::skip(OVERLAY, why)];
        }
        Location::Given(p) | Location::Found(p) => p,
    };
    match std::fs::read_to_string(&path) {
        Ok(text) => check(&path.display().to_string(), &text, hat),
        Err(e) => {
            let found = format!("cannot read {}: {e}", path.display());
            let action = "give the Pi's config.txt with --boot-config FILE (bookworm: /boot/firmware/config.txt)";
            vec![
                Verdict::fail(SPI, found.clone(), action),
                Verdict::skip(OVERLAY, found),
            ]
        }
    }
}

/// What the file says, as far as the HAT is concerned.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
struct Facts {
    /// `Some((on, line))` for the last `spi` parameter.
    spi: Option<(bool, usize)>,
    /// The last `mcp2515-can0` overlay: its line and parameters (`oscillator`, `interrupt`, …).
    overlay: Option<(usize, Vec<(String, String)>)>,
}

/// Reads `dtparam=`/`dtoverlay=` lines. A `dtparam=` after a `dtoverlay=` line sets that overlay's
/// parameters (the firmware's rule), before any overlay the base tree's (`spi`). Lines in a
/// `[none]` section do not apply; other conditional sections are taken as applying.
fn parse(text: &str) -> Facts {
    let mut facts = Facts::default();
    // Which overlay later dtparam lines belong to: None = the base device tree.
    let mut current: Option<String> = None;
    let mut skipping = false;
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if let Some(section) = line.strip_prefix('[') {
            skipping = section.trim_end_matches(']').trim() == "none";
            continue;
        }
        if skipping {
            continue;
        }
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        let mut params = value.split(',').map(str::trim);
        match key.trim() {
            "dtoverlay" => {
                let name = params.next().unwrap_or("").to_owned();
                // `dtoverlay=` alone ends the previous overlay's parameters.
                current = (!name.is_empty()).then(|| name.clone());
                if name == OVERLAY_NAME {
                    facts.overlay = Some((n + 1, params.filter_map(param).collect()));
                }
            }
            "dtparam" => {
                for (k, v) in params.filter_map(param) {
                    match current.as_deref() {
                        None if k == "spi" => {
                            facts.spi =
                                Some((matches!(v.as_str(), "on" | "true" | "yes" | "1"), n + 1))
                        }
                        Some(OVERLAY_NAME) => {
                            if let Some((_, ps)) = &mut facts.overlay {
                                ps.push((k, v));
                            }
                        }
                        _ => {}
                    }
                }
            }
            _ => {}
        }
    }
    facts
}

/// `name=value` (a bare `name` means `on`).
fn param(p: &str) -> Option<(String, String)> {
    if p.is_empty() {
        return None;
    }
    Some(match p.split_once('=') {
        Some((k, v)) => (k.trim().to_owned(), v.trim().to_owned()),
        None => (p.to_owned(), "on".to_owned()),
    })
}

/// Judges the text of `config.txt` (`path` only names it in the lines).
pub fn check(path: &str, text: &str, hat: &Hat) -> Vec<Verdict> {
    let facts = parse(text);
    let spi = match facts.spi {
        Some((true, line)) => Verdict::pass(SPI, format!("{path}:{line}: dtparam=spi=on")),
        Some((false, line)) => Verdict::fail(
            SPI,
            format!("{path}:{line} switches SPI off"),
            "change that line to dtparam=spi=on (the HAT talks SPI) and reboot",
        ),
        None => Verdict::fail(
            SPI,
            format!("{path}: no dtparam=spi=on"),
            format!("append dtparam=spi=on to {path} (deploy/boot/config.txt) and reboot"),
        ),
    };
    let overlay = match &facts.overlay {
        None => Verdict::fail(
            OVERLAY,
            format!("{path}: no dtoverlay={OVERLAY_NAME}: the kernel creates no can0"),
            format!("append {} to {path} and reboot", hat.overlay_line()),
        ),
        Some((line, params)) => {
            let get = |k: &str| {
                params
                    .iter()
                    .rev()
                    .find(|(pk, _)| pk == k)
                    .map(|(_, v)| v.as_str())
            };
            let mut wrong = Vec::new();
            let osc = get("oscillator");
            if osc.and_then(|v| v.parse::<u32>().ok()) != Some(hat.oscillator) {
                wrong.push(match osc {
                    Some(v) => format!(
                        "oscillator={v}, but the HAT's crystal is {} Hz (a wrong value gives a wrong bitrate or no can0)",
                        hat.oscillator
                    ),
                    None => format!("no oscillator= (the HAT's crystal, {} Hz)", hat.oscillator),
                });
            }
            let int = get("interrupt");
            if int.and_then(|v| v.parse::<u8>().ok()) != Some(hat.interrupt) {
                wrong.push(match int {
                    Some(v) => format!(
                        "interrupt={v}, but the HAT's INT is on GPIO {} (a wrong GPIO: can0 receives nothing)",
                        hat.interrupt
                    ),
                    None => format!("no interrupt= (the HAT's INT GPIO, {})", hat.interrupt),
                });
            }
            if wrong.is_empty() {
                Verdict::pass(
                    OVERLAY,
                    format!(
                        "{path}:{line}: {OVERLAY_NAME}, oscillator {} Hz, interrupt GPIO {}",
                        hat.oscillator, hat.interrupt
                    ),
                )
            } else {
                Verdict::fail(
                    OVERLAY,
                    format!("{path}:{line}: {}", wrong.join("; ")),
                    format!(
                        "make the line {} (read the crystal's can on the HAT: 8.000 = 8000000; \
                         --hat-oscillator/--hat-interrupt if your HAT differs) and reboot",
                        hat.overlay_line()
                    ),
                )
            }
        }
    };
    vec![spi, overlay]
}
