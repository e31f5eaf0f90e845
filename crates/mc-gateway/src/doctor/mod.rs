//! `mc-gateway doctor`: checks a gateway's surroundings in bring-up order (the Pi's boot
//! configuration, the CAN interface, the bus, the broker, the island, the clock, the disks) and says
//! per check what it found and what to do, one line each (`docs/deploy.md`, "Bring-up").
//!
//! Every check is a pure function from gathered facts to a [`Verdict`] (the `check` functions of
//! the submodules, tested on their own); the gathering (files, netlink, a CAN socket, an MQTT
//! connection, `statvfs`) sits in thin adapters beside them. [`run`] gathers and judges in order;
//! a check whose precondition failed (no interface: no traffic to look at) is
//! [`Status::Skip`]ped with the reason.

pub mod boot;
pub mod broker;
pub mod bus;
pub mod calendar;
pub mod clock;
pub mod disk;
pub mod interface;
pub mod island;
pub mod traffic;

use std::{path::PathBuf, time::Duration};

use serde::Serialize;

use crate::{
    config::{self, Broker, Config, Link, Options},
    error::ConfigError,
};

/// How one check came out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// All as it should be.
    Pass,
    /// Something to fix: [`Verdict::action`] says what.
    Fail,
    /// Not applicable here (a virtual CAN interface has no bitrate) or not checkable because an
    /// earlier check failed; [`Verdict::found`] says which.
    Skip,
}

impl Status {
    /// The mark printed before the line.
    pub fn mark(self) -> &'static str {
        match self {
            Status::Pass => "✓",
            Status::Fail => "✗",
            Status::Skip => "–",
        }
    }
}

/// The outcome of one check: one line of the report, one element of `--json`'s `checks`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Verdict {
    /// Stable identifier (`boot.spi`, `can.bitrate`, …; the table in `docs/deploy.md`).
    pub check: &'static str,
    /// Pass, fail or skip.
    pub status: Status,
    /// What the check found, in words.
    pub found: String,
    /// What to do about it (always set on a failure).
    pub action: Option<String>,
}

impl Verdict {
    /// A passed check.
    pub fn pass(check: &'static str, found: impl Into<String>) -> Verdict {
        Verdict {
            check,
            status: Status::Pass,
            found: found.into(),
            action: None,
        }
    }

    /// A failed check and what to do.
    pub fn fail(
        check: &'static str,
        found: impl Into<String>,
        action: impl Into<String>,
    ) -> Verdict {
        Verdict {
            check,
            status: Status::Fail,
            found: found.into(),
            action: Some(action.into()),
        }
    }

    /// A check that does not apply or could not run, and why.
    pub fn skip(check: &'static str, why: impl Into<String>) -> Verdict {
        Verdict {
            check,
            status: Status::Skip,
            found: why.into(),
            action: None,
        }
    }
}

/// Every verdict, in check order.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Report {
    /// True when no check failed (skipped ones do not count): the exit status is 0 exactly then.
    pub ok: bool,
    /// The checks in the order they ran.
    pub checks: Vec<Verdict>,
}

impl Report {
    /// A report of these verdicts.
    pub fn new(checks: Vec<Verdict>) -> Report {
        Report {
            ok: checks.iter().all(|v| v.status != Status::Fail),
            checks,
        }
    }

    /// One verdict by its identifier.
    pub fn get(&self, check: &str) -> Option<&Verdict> {
        self.checks.iter().find(|v| v.check == check)
    }

    /// The text report: one line per check (`✓ check  found`, `✗ check  found → action`), then a
    /// summary line.
    pub fn text(&self) -> String {
        let width = self.checks.iter().map(|v| v.check.len()).max().unwrap_or(0);
        let mut out = String::new();
        for v in &self.checks {
            out.push_str(&format!(
                "{} {:width$}  {}",
                v.status.mark(),
                v.check,
                v.found
            ));
            if let Some(action) = &v.action {
                out.push_str(" → ");
                out.push_str(action);
            }
            out.push('\n');
        }
        let failed = self
            .checks
            .iter()
            .filter(|v| v.status == Status::Fail)
            .count();
        if failed == 0 {
            out.push_str("all checks passed\n");
        } else {
            out.push_str(&format!(
                "{failed} check(s) failed: fix the first ✗ first, the later ones often follow from it\n"
            ));
        }
        out
    }

    /// The `--json` document (`docs/deploy.md` describes its fields).
    pub fn json(&self) -> String {
        serde_json::to_string_pretty(self)
            .unwrap_or_else(|e| format!("{{\"ok\":false,\"checks\":[],\"error\":\"{e}\"}}"))
    }
}

/// What `doctor` takes besides the gateway's own configuration.
#[derive(Clone, Debug)]
pub struct DoctorOptions {
    /// The Pi's boot configuration; `None`: the first of [`boot::DEFAULT_PATHS`] that exists.
    pub boot_config: Option<PathBuf>,
    /// What the `mcp2515-can0` overlay must say.
    pub hat: boot::Hat,
    /// How long to listen to the bus for traffic and answers.
    pub listen: Duration,
    /// How long the broker may take to connect, and then to echo the test message.
    pub broker_timeout: Duration,
}

impl Default for DoctorOptions {
    fn default() -> DoctorOptions {
        DoctorOptions {
            boot_config: None,
            hat: boot::Hat::default(),
            listen: Duration::from_secs(3),
            broker_timeout: Duration::from_secs(5),
        }
    }
}

/// The `doctor` subcommand: the gateway's options (so `--config /etc/ihex/gateway.toml` is read
/// as by the service) plus its own.
pub fn command() -> clap::Command {
    use clap::{value_parser, Arg, ArgAction};
    crate::config::Options::args()
        .into_iter()
        .fold(clap::Command::new("doctor"), |c, a| c.arg(a))
        .about("Check the Pi, the CAN bus, the broker and the island, one line per check")
        .long_about(
            "Checks, in order, what a gateway needs and says for each check what it found and what \
             to do: the Pi's boot configuration (SPI, the mcp2515-can0 overlay), the CAN interface \
             (exists, up, 500 kbit/s, sample point, controller state, error counters, restart-ms, \
             transmit queue), traffic and error frames on the bus, the broker (reachable, TLS, login, \
             a publish/subscribe round trip under the island's prefix), the island (which nodes answer \
             a health check, their firmware and protocol versions and UIDs), the clock, and free disk \
             space for the log and state directories.\n\n\
             It reads the gateway's configuration like the gateway does (--config FILE, IHEX_* \
             environment, flags), so run it with the service's: \
             `mc-gateway doctor --config /etc/ihex/gateway.toml` (and the service's environment file \
             for the broker password). It sends a health check, a state query and a firmware-status \
             query on the bus and publishes one message on ISLAND/ihex/doctor/…: safe while the \
             gateway runs.\n\n\
             Exit status: 0 when no check failed (✓ or – on every line), 1 otherwise, 2 on bad \
             arguments.",
        )
        .arg(
            Arg::new("boot_config")
                .long("boot-config")
                .value_name("FILE")
                .value_parser(value_parser!(PathBuf))
                .help_heading("Doctor options")
                .help("The Pi's config.txt [default: /boot/firmware/config.txt, else /boot/config.txt; neither: skipped]"),
        )
        .arg(
            Arg::new("hat_oscillator")
                .long("hat-oscillator")
                .value_name("HZ")
                .value_parser(value_parser!(u32).range(1_000_000..=40_000_000))
                .default_value("8000000")
                .help_heading("Doctor options")
                .help("The HAT's MCP2515 crystal, Hz, as printed on it (the overlay's oscillator=)"),
        )
        .arg(
            Arg::new("hat_interrupt")
                .long("hat-interrupt")
                .value_name("GPIO")
                .value_parser(value_parser!(u8).range(0..=53))
                .default_value("25")
                .help_heading("Doctor options")
                .help("The GPIO the HAT's INT pin is wired to (the overlay's interrupt=)"),
        )
        .arg(
            Arg::new("listen_ms")
                .long("listen-ms")
                .value_name("MS")
                .value_parser(value_parser!(u64).range(100..=60_000))
                .default_value("3000")
                .help_heading("Doctor options")
                .help("How long to listen on the bus for traffic and the nodes' answers, ms"),
        )
        .arg(
            Arg::new("json")
                .long("json")
                .action(ArgAction::SetTrue)
                .help_heading("Doctor options")
                .help("Print one JSON document ({\"ok\":…,\"checks\":[{\"check\",\"status\",\"found\",\"action\"}]}) instead of lines"),
        )
}

/// The doctor's own options from its parsed subcommand (the gateway's are read with
/// [`crate::config::Options`]).
pub fn options_from(m: &clap::ArgMatches) -> DoctorOptions {
    let d = DoctorOptions::default();
    DoctorOptions {
        boot_config: m.get_one::<PathBuf>("boot_config").cloned(),
        hat: boot::Hat {
            oscillator: m
                .get_one::<u32>("hat_oscillator")
                .copied()
                .unwrap_or(d.hat.oscillator),
            interrupt: m
                .get_one::<u8>("hat_interrupt")
                .copied()
                .unwrap_or(d.hat.interrupt),
        },
        listen: m
            .get_one::<u64>("listen_ms")
            .map(|ms| Duration::from_millis(*ms))
            .unwrap_or(d.listen),
        ..d
    }
}

/// What the command line asks for: the gateway, or the doctor.
#[derive(Debug)]
pub enum Invocation {
    /// `mc-gateway [OPTIONS]`: run the gateway.
    Gateway(Box<Config>),
    /// `mc-gateway doctor [OPTIONS]`: run the checks.
    Doctor {
        /// The gateway's configuration the checks use.
        config: Box<Config>,
        /// The doctor's own options.
        options: DoctorOptions,
        /// `--json`.
        json: bool,
    },
}

/// The gateway's command line with the `doctor` subcommand.
pub fn command_line() -> clap::Command {
    config::command()
        .subcommand(command())
        // No `help` subcommand: `mc-gateway help` stays an unknown argument, as without doctor.
        .disable_help_subcommand(true)
}

/// Parses the process's command line and environment (reading `--config` files); a bad value is
/// an error naming where it was given. `--help`, `--version` and malformed arguments end the
/// process the way clap does.
pub fn invocation() -> Result<Invocation, ConfigError> {
    let args: Vec<_> = std::env::args_os().collect();
    let m = config::matches(command_line(), &args)?;
    let Some(("doctor", sub)) = m.subcommand() else {
        return Config::from_matches(&m).map(|c| Invocation::Gateway(Box::new(c)));
    };
    // Options given before `doctor` count too; those after it win.
    let mut cli = Options::from_matches(sub).or(Options::from_matches(&m));
    let file = match &cli.config {
        Some(path) => Options::load(path)?,
        None => Options::default(),
    };
    // Nothing configured means the demo to the gateway; the doctor is for real hardware, so it
    // checks the lab's defaults instead (can0 and the lab broker, with the usual warning).
    let merged = cli.clone().or(file.clone());
    if merged.broker.is_none() && merged.can.is_none() && merged.sim != Some(true) {
        cli.can = Some(config::DEFAULT_CAN.into());
    }
    Ok(Invocation::Doctor {
        config: Box::new(Config::resolve(cli, file)?),
        options: options_from(sub),
        json: sub.get_flag("json"),
    })
}

/// Runs every check in order against `config` (resolved as the gateway resolves it).
pub async fn run(config: &Config, opts: &DoctorOptions) -> Report {
    let mut checks = Vec::new();

    // The Pi's boot configuration.
    checks.extend(boot::check_file(
        boot::locate(opts.boot_config.as_deref()),
        &opts.hat,
    ));

    // The CAN interface, then one session on it for traffic and the island.
    let mut island_verdict = None;
    match &config.can.link {
        Link::SocketCan(iface) => {
            let facts = interface::gather(iface);
            let usable = facts.usable();
            checks.extend(interface::check(&facts, config.can.bitrate, &opts.hat));
            if usable {
                match bus::gather(iface, opts.listen).await {
                    Ok(bus) => {
                        checks.push(traffic::check(&bus.traffic, opts.listen));
                        island_verdict = Some(island::check(&bus.island, opts.listen));
                    }
                    Err(e) => checks.push(Verdict::fail(
                        traffic::CHECK,
                        format!("cannot use {iface}: {e}"),
                        "run the doctor on the gateway's machine, as a user that may open raw CAN sockets",
                    )),
                }
            } else {
                checks.push(Verdict::skip(
                    traffic::CHECK,
                    format!("{iface} is not usable (above)"),
                ));
            }
        }
        Link::Simulated { .. } => {
            checks.push(Verdict::skip(
                interface::CHECK,
                "simulated island (demo): no CAN interface to check (give --can IFACE)",
            ));
        }
    }

    // The broker.
    match &config.mqtt.broker {
        Broker::External { .. } => {
            let facts = broker::gather(config, opts.broker_timeout).await;
            checks.extend(broker::check(&facts));
        }
        Broker::Embedded { .. } => checks.push(Verdict::skip(
            broker::CONNECT,
            "embedded demo broker: nothing to check (give --broker HOST[:PORT])",
        )),
    }

    checks.push(island_verdict.unwrap_or_else(|| {
        Verdict::skip(island::CHECK, "no usable CAN interface to ask the nodes on")
    }));

    checks.push(clock::check(clock::now_unix(), clock::BUILD_YEAR));

    let state =
        crate::config::state_dir(std::env::var_os("XDG_STATE_HOME"), std::env::var_os("HOME"));
    checks.extend(disk::check_dirs(
        config.log.dir.as_deref(),
        state.as_deref(),
    ));

    Report::new(checks)
}
