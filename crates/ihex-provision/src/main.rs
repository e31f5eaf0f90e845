//! `ihex-provision`: give sub-controllers their node IDs (serial or CAN), watch the gateway's events,
//! make signed firmware images and update nodes through the gateway (`fw`).
#![forbid(unsafe_code)]

/// Prints a line on stdout like `println!`, but a reader that went away (`… | head`) does not
/// panic the program: output stops, the work (an update under way) goes on to its end and its
/// exit status.
macro_rules! say {
    ($($arg:tt)*) => { $crate::out::line(format_args!($($arg)*)) };
}

mod audit;
mod fw;
mod out;

use std::{path::PathBuf, process::ExitCode, time::Duration};

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use ihex_proto::NodeId;
use ihex_provision::{
    api::{self, Event},
    can::{self, Assignment, Topics},
    id::{self, Registry},
    mqtt::{Broker, Session},
    procedure,
    serial::{self, SerialPort},
};

#[derive(Parser)]
#[command(
    version,
    about = "Number the island's sub-controllers and check the gateway from the command line"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Set (or read) a board's node ID over its ST-Link virtual COM port (115200 8N1).
    Serial(SerialArgs),
    /// Assign a node ID over CAN by the board's 96-bit unique ID, through the gateway's MQTT API.
    Can(CanArgs),
    /// Wait for an event from the gateway (optionally after sending a command); exit 0 once it arrives.
    WaitEvent(WaitArgs),
    /// Firmware images: make a signing key, pack and sign the firmware, inspect an image.
    Fw {
        #[command(subcommand)]
        cmd: fw::FwCmd,
    },
    /// The gateway's audit trail: verify its hash chain, show who did what (docs/audit.md).
    Audit {
        #[command(subcommand)]
        cmd: audit::AuditCmd,
    },
    /// Guided procedures (docs/procedures.md).
    Procedure {
        #[command(subcommand)]
        cmd: ProcedureCmd,
    },
}

#[derive(Subcommand)]
enum ProcedureCmd {
    /// Send a TOML procedure file as a `procedure` command and follow it to its end: exit 0 when
    /// every step was done, 1 otherwise.
    Run(ProcedureRunArgs),
    /// Check a TOML procedure file with the gateway's own parser and print its JSON command.
    Check {
        /// The procedure file.
        file: PathBuf,
    },
}

#[derive(Args)]
struct ProcedureRunArgs {
    #[command(flatten)]
    broker: BrokerArgs,
    /// The procedure file (`examples/procedures/sample-handover.toml`).
    file: PathBuf,
    /// Give up waiting for its end after this many seconds (the procedure itself goes on; cancel
    /// it with `procedure_cancel`).
    #[arg(long, default_value_t = 3600)]
    timeout_secs: u64,
}

#[derive(Args)]
struct SerialArgs {
    /// The board's serial device (the NUCLEO's ST-Link VCP: /dev/ttyACM0, or /dev/serial/by-id/...).
    #[arg(long)]
    port: PathBuf,
    /// The node ID to store, in hex (001..=ffd).
    #[arg(long, required_unless_present = "query", conflicts_with = "query")]
    id: Option<String>,
    /// Only read the stored ID.
    #[arg(long)]
    query: bool,
    /// CSV of IDs already handed out (id,uid,port,note): a duplicate is refused, a success appended.
    #[arg(long)]
    registry: Option<PathBuf>,
    /// How long to wait for each reply, in milliseconds.
    #[arg(long, default_value_t = 1000)]
    timeout_ms: u64,
}

#[derive(Args)]
pub(crate) struct BrokerArgs {
    /// The gateway's MQTT broker, HOST[:PORT].
    #[arg(long, env = "IHEX_BROKER", default_value = "127.0.0.1:1883")]
    broker: String,
    /// MQTT user name (with --password).
    #[arg(long, env = "IHEX_MQTT_USERNAME", requires = "password")]
    username: Option<String>,
    /// MQTT password.
    #[arg(
        long,
        env = "IHEX_MQTT_PASSWORD",
        requires = "username",
        hide_env_values = true
    )]
    password: Option<String>,
    /// The gateway's island name: every topic is then prefixed `ISLAND/`.
    #[arg(long, env = "IHEX_ISLAND")]
    pub(crate) island: Option<String>,
    /// Commands topic (before the island prefix).
    #[arg(long, default_value = "CommandsTopic")]
    commands_topic: String,
    /// Events topic (before the island prefix).
    #[arg(long, default_value = "EventsTopic")]
    events_topic: String,
    /// Root of the retained node-state topics `<root>/<id>/state` (before the island prefix).
    #[arg(long, default_value = "ihex/node")]
    node_state_root: String,
}

impl BrokerArgs {
    fn broker(&self) -> Result<Broker> {
        let mut b = Broker::parse(&self.broker)?;
        b.credentials = self.username.clone().zip(self.password.clone());
        Ok(b)
    }

    fn topics(&self) -> Topics {
        self.topics_of(self.island.as_deref())
    }

    /// The topics of `island` (another island than --island, on the same broker).
    fn topics_of(&self, island: Option<&str>) -> Topics {
        Topics::new(
            island,
            &self.commands_topic,
            &self.events_topic,
            &self.node_state_root,
        )
    }
}

#[derive(Args)]
struct CanArgs {
    #[command(flatten)]
    broker: BrokerArgs,
    /// The board's 96-bit unique ID: 24 hex digits (the firmware logs it over RTT at boot, a probe
    /// reads it: docs/deploy.md).
    #[arg(long)]
    uid: String,
    /// The node ID to give it, in hex (001..=ffd).
    #[arg(long)]
    id: String,
    /// Do not ask the gateway which IDs are taken.
    #[arg(long)]
    skip_duplicate_check: bool,
    /// CSV of IDs already handed out (as for `serial`): a duplicate is refused, a success appended.
    #[arg(long)]
    registry: Option<PathBuf>,
    /// How long to wait for each answer, in seconds.
    #[arg(long, default_value_t = 5)]
    timeout_secs: u64,
}

#[derive(Args)]
struct WaitArgs {
    #[command(flatten)]
    broker: BrokerArgs,
    /// The event name to wait for (node_online, new_connection, ...).
    #[arg(long)]
    event: String,
    /// Only an event whose payload has this top-level field value, `KEY=VALUE` (repeatable).
    #[arg(long = "match", value_parser = parse_kv)]
    matches: Vec<(String, String)>,
    /// A JSON command to publish on the commands topic once subscribed.
    #[arg(long)]
    send: Option<String>,
    /// Give up after this many seconds (exit code 1).
    #[arg(long, default_value_t = 30)]
    timeout_secs: u64,
    /// Create this file once subscribed, so a script knows when to start the event's source.
    #[arg(long)]
    ready_file: Option<PathBuf>,
    /// Retry connecting to the broker until the timeout (it may still be starting).
    #[arg(long)]
    retry_connect: bool,
}

fn parse_kv(s: &str) -> Result<(String, String), String> {
    s.split_once('=')
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .ok_or_else(|| format!("{s:?} is not KEY=VALUE"))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Serial(a) => run_serial(a),
        Cmd::Can(a) => tokio_main(run_can(a)),
        Cmd::WaitEvent(a) => tokio_main(run_wait(a)),
        Cmd::Procedure {
            cmd: ProcedureCmd::Check { file },
        } => procedure_command(&file, "check").map(|json| say!("{json}")),
        Cmd::Procedure {
            cmd: ProcedureCmd::Run(a),
        } => match tokio_main(run_procedure(a)) {
            Ok(true) => Ok(()),
            Ok(false) => return ExitCode::FAILURE,
            Err(e) => Err(e),
        },
        Cmd::Fw { cmd } => match fw::run(cmd) {
            Ok(true) => Ok(()),
            Ok(false) => return ExitCode::FAILURE,
            Err(e) => Err(e),
        },
        Cmd::Audit { cmd } => match audit::run(cmd) {
            Ok(true) => Ok(()),
            Ok(false) => return ExitCode::FAILURE,
            Err(e) => Err(e),
        },
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("ihex-provision: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn tokio_main<T>(f: impl std::future::Future<Output = Result<T>>) -> Result<T> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("tokio runtime")?
        .block_on(f)
}

fn run_serial(a: SerialArgs) -> Result<()> {
    let timeout = Duration::from_millis(a.timeout_ms);
    // Validate everything before touching the port.
    let want = a.id.as_deref().map(id::parse_sc_id).transpose()?;
    let mut registry = a.registry.as_deref().map(Registry::load).transpose()?;
    if let (Some(id), Some(reg)) = (want, &registry) {
        reg.check_free(id)?;
    }
    let mut session = serial::Session::new(SerialPort::open(&a.port)?, timeout);
    match want {
        None => {
            let id = session.query_id()?;
            if id == NodeId::UNCONFIGURED {
                say!("{}: no node ID yet (unconfigured)", a.port.display());
            } else {
                say!("{}: node ID {id}", a.port.display());
            }
        }
        Some(id) => {
            let before = session.query_id()?;
            session.set_id(id)?;
            say!(
                "{}: node ID {id} stored (was {})",
                a.port.display(),
                show(before)
            );
            if let Some(reg) = registry.as_mut() {
                reg.record(id, "", &a.port.display().to_string(), "set over serial")?;
            }
        }
    }
    Ok(())
}

fn show(id: NodeId) -> String {
    if id == NodeId::UNCONFIGURED {
        "unconfigured".into()
    } else {
        id.to_string()
    }
}

async fn run_can(a: CanArgs) -> Result<()> {
    let new_id = id::parse_sc_id(&a.id)?;
    let uid = api::parse_uid(&a.uid)?;
    let mut registry = a.registry.as_deref().map(Registry::load).transpose()?;
    if let Some(reg) = &registry {
        reg.check_free(new_id)?;
    }
    let broker = a.broker.broker()?;
    let assignment = Assignment {
        uid,
        new_id,
        skip_duplicate_check: a.skip_duplicate_check,
        timeout: Duration::from_secs(a.timeout_secs),
    };
    let result = can::assign(&broker, &a.broker.topics(), &assignment).await?;
    let answer = ihex_gateway_core::event::Event::CommandResult(result);
    say!("node {uid} assigned ID {new_id}: {}", answer.to_json());
    if let Some(reg) = registry.as_mut() {
        reg.record(
            new_id,
            &uid.to_string(),
            &a.broker.broker,
            "assigned over CAN",
        )?;
    }
    Ok(())
}

async fn run_wait(a: WaitArgs) -> Result<()> {
    let broker = a.broker.broker()?;
    let topics = a.broker.topics();
    let timeout = Duration::from_secs(a.timeout_secs);
    let deadline = tokio::time::Instant::now() + timeout;
    let subs = std::slice::from_ref(&topics.events);
    let mut session = loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        match Session::connect(&broker, subs, left.max(Duration::from_secs(1))).await {
            Ok(s) => break s,
            Err(e) if a.retry_connect && !left.is_zero() => {
                eprintln!("(broker not ready: {e}; retrying)");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            Err(e) => return Err(e.into()),
        }
    };
    if let Some(path) = &a.ready_file {
        std::fs::write(path, b"subscribed\n")
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(cmd) = a.send {
        serde_json::from_str::<serde_json::Value>(&cmd).context("--send is not JSON")?;
        session.publish(&topics.commands, cmd).await?;
    }
    while let Some(msg) = session.recv_until(deadline).await? {
        match Event::parse(&msg.payload) {
            Ok(e) if e.name == a.event && e.matches(&a.matches) => {
                say!("{}", String::from_utf8_lossy(&msg.payload));
                session.close().await;
                return Ok(());
            }
            Ok(e) => eprintln!("(skipping {} event)", e.name),
            Err(err) => eprintln!("(skipping message on {}: {err})", msg.topic),
        }
    }
    session.close().await;
    bail!(
        "no {:?} event on {} within {timeout:?}",
        a.event,
        topics.events
    )
}

/// The `procedure` command of a procedure file, with a request id made for it.
fn procedure_command(file: &std::path::Path, request_id: &str) -> Result<String> {
    let text =
        std::fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    procedure::command_from_toml(&text, request_id).with_context(|| file.display().to_string())
}

/// Runs a procedure file; true when its outcome is `done`.
async fn run_procedure(a: ProcedureRunArgs) -> Result<bool> {
    let request_id = api::new_request_id("procedure");
    let command = procedure_command(&a.file, &request_id)?;
    let broker = a.broker.broker()?;
    let timeout = Duration::from_secs(a.timeout_secs);
    let ended = procedure::run(
        &broker,
        &a.broker.topics(),
        &command,
        &request_id,
        timeout,
        |e| {
            say!(
                "{}",
                serde_json::json!({"event": e.name, "payload": e.payload})
            )
        },
    )
    .await?;
    Ok(ended.payload["outcome"] == "done")
}
