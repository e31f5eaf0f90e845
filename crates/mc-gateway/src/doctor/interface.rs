//! The CAN interface as the kernel reports it over rtnetlink (socketcan's `CanInterface::details`)
//! and sysfs (`tx_queue_len`): exists, up, bitrate and sample point, controller state, error
//! counters, `restart-ms`, transmit queue. A `vcan` reports no CAN parameters at all: those lines are
//! "not applicable", not failures.

use socketcan::{nl::CanState, CanInterface};

use super::{boot::Hat, Verdict};

/// Identifier of the exists-and-up check.
pub const CHECK: &str = "can.interface";
/// Identifier of the bitrate and sample-point check.
pub const BITRATE: &str = "can.bitrate";
/// Identifier of the controller state check.
pub const CONTROLLER: &str = "can.controller";
/// Identifier of the transmit-queue check.
pub const TXQUEUE: &str = "can.txqueue";

/// The sample point the SCs' bxCAN uses, in tenths of a percent as the kernel reports it
/// (`docs/protocol.md`, "Bit timing": 1 + 6 + 1 quanta = 87.5 %).
pub const SAMPLE_POINT: u32 = 875;
/// How far the interface's sample point may be from [`SAMPLE_POINT`], tenths of a percent.
pub const SAMPLE_POINT_TOLERANCE: u32 = 25;
/// The shortest transmit queue that does not overflow on a broadcast to a full island
/// (`deploy/systemd/80-can0.link`).
pub const MIN_TXQUEUE: u32 = 1024;

/// What the kernel says about the interface.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Facts {
    /// The interface name.
    pub name: String,
    /// `None`: it exists; `Some(why)`: it does not or cannot be read.
    pub missing: Option<String>,
    /// Administratively up.
    pub up: bool,
    /// A virtual CAN interface (no controller: no bitrate, state or counters).
    pub virtual_can: bool,
    /// Bitrate, bit/s, and sample point, tenths of a percent.
    pub bit_timing: Option<(u32, u32)>,
    /// The controller's clock, Hz (half the MCP2515's crystal).
    pub clock: Option<u32>,
    /// The controller state.
    pub state: Option<CanState>,
    /// Transmit and receive error counters.
    pub berr: Option<(u16, u16)>,
    /// Automatic restart after bus-off, ms (0 = never).
    pub restart_ms: Option<u32>,
    /// The transmit queue length, frames.
    pub txqueuelen: Option<u32>,
}

impl Facts {
    /// True when the interface exists and is up: the bus can be listened to.
    pub fn usable(&self) -> bool {
        self.missing.is_none() && self.up
    }
}

/// Asks the kernel about `iface`.
pub fn gather(iface: &str) -> Facts {
    let mut facts = Facts {
        name: iface.to_owned(),
        ..Facts::default()
    };
    let details = match CanInterface::open(iface).and_then(|i| i.details()) {
        Ok(d) => d,
        Err(e) => {
            facts.missing = Some(e.to_string());
            return facts;
        }
    };
    let sys = |leaf: &str| {
        std::fs::read_to_string(format!("/sys/class/net/{iface}/{leaf}"))
            .ok()
            .map(|s| s.trim().to_owned())
    };
    facts.up = details.is_up;
    // ARPHRD_CAN is 280 for vcan and real controllers alike; only the driver tells them apart,
    // and a vcan carries no CAN link data at all.
    let can = &details.can;
    facts.virtual_can = can.bit_timing.is_none()
        && can.state.is_none()
        && can.clock.is_none()
        && sys("type").as_deref() == Some("280");
    facts.bit_timing = can
        .bit_timing
        .filter(|t| t.bitrate != 0)
        .map(|t| (t.bitrate, t.sample_point));
    facts.clock = can.clock.map(|c| c.freq);
    facts.state = can.state;
    facts.berr = can.berr_counter.map(|b| (b.txerr, b.rxerr));
    facts.restart_ms = can.restart_ms;
    facts.txqueuelen = sys("tx_queue_len").and_then(|s| s.parse().ok());
    facts
}

/// Judges the interface against the configured bitrate (`--bitrate`, the protocol's 500 kbit/s).
pub fn check(f: &Facts, bitrate: u32, hat: &Hat) -> Vec<Verdict> {
    let name = &f.name;
    let n_a = |check| Verdict::skip(check, format!("{name} is not usable (above)"));
    if let Some(why) = &f.missing {
        let action = if name.starts_with("vcan") {
            format!(
                "create it: `sudo ip link add dev {name} type vcan && sudo ip link set up {name}`"
            )
        } else {
            "the MCP2515 overlay did not load: check the boot.* lines, that the HAT is seated, \
             then `dmesg | grep -i mcp251` (it should say \"successfully initialized\"); or --can \
             names the wrong interface"
                .to_owned()
        };
        return vec![
            Verdict::fail(CHECK, format!("no interface {name} ({why})"), action),
            n_a(BITRATE),
            n_a(CONTROLLER),
            n_a(TXQUEUE),
        ];
    }
    if !f.up {
        return vec![
            Verdict::fail(
                CHECK,
                format!("{name} exists but is down"),
                format!(
                    "bring it up with systemd-networkd (deploy/systemd/80-can0.network) or \
                     `sudo ip link set {name} up type can bitrate {bitrate} sample-point 0.875 restart-ms 100 berr-reporting on`"
                ),
            ),
            n_a(BITRATE),
            n_a(CONTROLLER),
            n_a(TXQUEUE),
        ];
    }
    let kind = if f.virtual_can {
        "virtual CAN"
    } else {
        "CAN controller"
    };
    let mut out = vec![Verdict::pass(CHECK, format!("{name} is up ({kind})"))];
    if f.virtual_can {
        out.push(Verdict::skip(BITRATE, "virtual CAN: no bitrate"));
        out.push(Verdict::skip(
            CONTROLLER,
            "virtual CAN: no controller state",
        ));
        out.push(Verdict::skip(TXQUEUE, "virtual CAN: no transmit queue"));
        return out;
    }
    out.push(check_bitrate(f, bitrate, hat));
    out.push(check_controller(f));
    out.push(match f.txqueuelen {
        Some(q) if q >= MIN_TXQUEUE => Verdict::pass(TXQUEUE, format!("txqueuelen {q}")),
        Some(q) => Verdict::fail(
            TXQUEUE,
            format!("txqueuelen {q}: a broadcast to a full island overflows it (sent frames fail with ENOBUFS)"),
            format!(
                "install deploy/systemd/80-can0.link (TransmitQueueLength={MIN_TXQUEUE}) and reboot, or \
                 `sudo ip link set {name} txqueuelen {MIN_TXQUEUE}`"
            ),
        ),
        None => Verdict::skip(TXQUEUE, "the kernel reports no txqueuelen"),
    });
    out
}

fn check_bitrate(f: &Facts, bitrate: u32, hat: &Hat) -> Verdict {
    let name = &f.name;
    let set_it = format!(
        "set BitRate={}K and SamplePoint=87.5% in deploy/systemd/80-can0.network (or `sudo ip link set {name} down; \
         sudo ip link set {name} up type can bitrate {bitrate} sample-point 0.875 restart-ms 100`)",
        bitrate / 1000
    );
    let clock = match f.clock {
        // The MCP2515's CAN clock is half its crystal.
        Some(c) if c != hat.oscillator / 2 => format!(
            "; controller clock {c} Hz means a {} Hz crystal in the overlay, not the HAT's {} Hz",
            u64::from(c) * 2,
            hat.oscillator
        ),
        _ => String::new(),
    };
    match f.bit_timing {
        None => Verdict::fail(
            BITRATE,
            format!("{name} has no bitrate set{clock}"),
            set_it,
        ),
        Some((rate, _)) if rate != bitrate => Verdict::fail(
            BITRATE,
            format!(
                "{name} runs at {rate} bit/s, the island at {bitrate} bit/s: nodes see only errors{clock}"
            ),
            set_it,
        ),
        Some((rate, sp)) if sp.abs_diff(SAMPLE_POINT) > SAMPLE_POINT_TOLERANCE => Verdict::fail(
            BITRATE,
            format!(
                "{rate} bit/s but sample point {}.{} % (the nodes sample at 87.5 %): errors on long cables{clock}",
                sp / 10,
                sp % 10
            ),
            set_it,
        ),
        Some((rate, sp)) if !clock.is_empty() => Verdict::fail(
            BITRATE,
            format!("{rate} bit/s, sample point {}.{} %{clock}", sp / 10, sp % 10),
            format!(
                "correct oscillator= in the boot config ({}) and reboot",
                hat.overlay_line()
            ),
        ),
        Some((rate, sp)) => Verdict::pass(
            BITRATE,
            format!("{rate} bit/s, sample point {}.{} %", sp / 10, sp % 10),
        ),
    }
}

fn check_controller(f: &Facts) -> Verdict {
    let counters = match f.berr {
        Some((tx, rx)) => format!(", error counters tx {tx} rx {rx}"),
        None => String::new(),
    };
    let restart = match f.restart_ms {
        Some(ms) => format!(", restart-ms {ms}"),
        None => String::new(),
    };
    let found = |state: &str| format!("{state}{counters}{restart}");
    let physical = "check termination (120 Ω at both ends: CANH–CANL ≈ 60 Ω with power off), \
                    CANH/CANL not swapped, CAN_GND connected, and that every node runs at 500 kbit/s";
    match f.state {
        Some(CanState::BusOff) => Verdict::fail(
            CONTROLLER,
            found("bus-off: the controller gave up after too many errors"),
            format!("{physical}; then restart-ms brings it back (or `sudo ip link set {} down && sudo ip link set {} up`)", f.name, f.name),
        ),
        Some(CanState::ErrorPassive) => Verdict::fail(
            CONTROLLER,
            found("error-passive: many errors on the bus"),
            format!("{physical}; no other node powered on also gives this (nobody acknowledges)"),
        ),
        Some(CanState::ErrorWarning) => Verdict::fail(
            CONTROLLER,
            found("error-warning: errors on the bus"),
            physical.to_owned(),
        ),
        Some(CanState::Stopped) | Some(CanState::Sleeping) => Verdict::fail(
            CONTROLLER,
            found("controller stopped"),
            format!("bring {} down and up again (systemd-networkd or `ip link`)", f.name),
        ),
        Some(CanState::ErrorActive) | None if f.restart_ms == Some(0) => Verdict::fail(
            CONTROLLER,
            found(if f.state.is_some() { "error-active" } else { "state unknown" }),
            format!(
                "restart-ms 0: after a bus-off the controller stays off until someone restarts it; \
                 set RestartSec=100ms (deploy/systemd/80-can0.network) or `ip link set {} type can restart-ms 100`",
                f.name
            ),
        ),
        Some(CanState::ErrorActive) => Verdict::pass(CONTROLLER, found("error-active")),
        None => Verdict::pass(CONTROLLER, found("the driver reports no state")),
    }
}
