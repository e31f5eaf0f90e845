//! `sim-node`: run an island of virtual sub-controllers on a SocketCAN interface, print every
//! actuator change, and take control commands on stdin.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Parser;
use sim_node::{
    console::{self, Command},
    Island, IslandDesc, IslandHandle, Link,
};
use tokio::io::{AsyncBufReadExt, BufReader};

/// Virtual iHEX sub-controllers on a CAN interface: each element of the island file runs the real
/// SC core. Actuator changes are printed as they happen; type `help` for the control commands.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// SocketCAN interface to put the virtual nodes on (e.g. vcan0).
    #[arg(long, env = "SIM_NODE_IFACE")]
    iface: String,
    /// Island description file (TOML; see docs/sim-node.md and examples/islands/).
    #[arg(long, env = "SIM_NODE_ISLAND")]
    island: PathBuf,
}

#[tokio::main]
async fn main() -> std::process::ExitCode {
    let args = Args::parse();
    match run(args).await {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sim-node: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(args: Args) -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();

    let desc = IslandDesc::load(&args.island)
        .with_context(|| format!("island file {}", args.island.display()))?;
    let link = Link::socketcan(&args.iface);
    let island = Island::start(&desc, link)
        .with_context(|| format!("starting the island on {}", args.iface))?;
    println!(
        "sim-node: {} static and {} mobile element(s) on {}; type `help` for commands",
        desc.statics.len(),
        desc.mobiles.len(),
        args.iface
    );

    let mut events = island.subscribe();
    let printer = tokio::spawn(async move {
        loop {
            match events.recv().await {
                Ok(e) => println!("{}", console::event_line(&e)),
                Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                    println!("... {n} change(s) not shown (output too slow)")
                }
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
            }
        }
    });

    let mut lines = BufReader::new(tokio::io::stdin()).lines();
    let mut stdin_open = true;
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => break,
            line = lines.next_line(), if stdin_open => match line {
                Ok(Some(line)) => {
                    if !run_line(&island, &line).await {
                        break;
                    }
                }
                // No more input (e.g. started in the background): keep simulating until Ctrl-C.
                Ok(None) | Err(_) => stdin_open = false,
            },
        }
    }
    island.shutdown().await;
    printer.abort();
    Ok(())
}

/// Runs one console line; false when the user asked to quit.
async fn run_line(island: &IslandHandle, line: &str) -> bool {
    let cmd = match console::parse(line) {
        Ok(Some(c)) => c,
        Ok(None) => return true,
        Err(e) => {
            println!("error: {e}");
            return true;
        }
    };
    let result = match cmd {
        Command::Dock {
            mobile,
            static_id,
            port,
        } => island.dock(mobile, static_id, port).await,
        Command::Undock(m) => island.undock(m).await,
        Command::Cycle(n) => island.power_cycle(n).await,
        Command::Bus(n, on) => island.set_on_bus(n, on).await,
        Command::Uart(n, bytes) => island.uart(n, &bytes).await.map(|reply| {
            let hex: Vec<String> = reply.iter().map(|b| format!("{b:02x}")).collect();
            println!(
                "{n:>3}  uart reply: {}",
                if hex.is_empty() {
                    "(none)".into()
                } else {
                    hex.join(" ")
                }
            );
        }),
        Command::Show => island.snapshot().await.map(|all| {
            for v in &all {
                println!("{}", console::view_line(v));
            }
        }),
        Command::Help => {
            println!("{}", console::HELP);
            Ok(())
        }
        Command::Quit => return false,
    };
    if let Err(e) = result {
        println!("error: {e}");
    }
    true
}
