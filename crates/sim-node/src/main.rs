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
    // Boot events may precede the subscription: start from a full picture.
    for v in island.snapshot().await? {
        println!("{}", console::view_line(&v));
    }
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
    match console::parse(line) {
        Ok(None) => true,
        Ok(Some(Command::Quit)) => false,
        Ok(Some(cmd)) => {
            match console::execute(island, cmd).await {
                Ok(lines) => lines.iter().for_each(|l| println!("{l}")),
                Err(e) => println!("error: {e}"),
            }
            true
        }
        Err(e) => {
            println!("error: {e}");
            true
        }
    }
}
