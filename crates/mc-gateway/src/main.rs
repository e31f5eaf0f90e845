//! `mc-gateway`: parse the configuration, set up logging and signals, run until SIGINT/SIGTERM.
//! `mc-gateway doctor` runs the bring-up checks instead (`mc_gateway::doctor`) and exits 0 only
//! when none failed. A failure is one line on stderr and exit status 1.

use std::process::ExitCode;

use anyhow::Context as _;
use mc_gateway::doctor::{self, Invocation};
use tokio_util::sync::CancellationToken;

// One thread: the gateway's tasks hand every frame and publication to each other, which on one
// thread costs no cross-thread wake-up, and a Pi-class island never needs a second core for it
// (docs/benchmarks.md: CPU per 1,000 frames, peak RSS).
#[tokio::main(flavor = "current_thread")]
async fn main() -> ExitCode {
    match run().await {
        Ok(code) => code,
        Err(e) => {
            eprintln!("mc-gateway: {}", report(&e));
            ExitCode::FAILURE
        }
    }
}

async fn run() -> anyhow::Result<ExitCode> {
    let config = match doctor::invocation()? {
        Invocation::Gateway(config) => config,
        Invocation::Doctor {
            config,
            options,
            json,
        } => {
            for w in &config.warnings {
                eprintln!("mc-gateway doctor: {w}");
            }
            let report = doctor::run(&config, &options).await;
            if json {
                println!("{}", report.json());
            } else {
                print!("{}", report.text());
            }
            return Ok(if report.ok {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            });
        }
    };
    // Held to the end: dropping it flushes the log file.
    let _log = mc_gateway::log::init(&config.log)?;
    let shutdown = CancellationToken::new();
    mc_gateway::shutdown::on_signals(shutdown.clone()).context("cannot install signal handlers")?;
    mc_gateway::run(*config, shutdown).await?;
    Ok(ExitCode::SUCCESS)
}

/// An error and its causes on one line, each cause only when the text so far does not say it
/// already (the gateway's errors quote their source in their own message).
fn report(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let cause = cause.to_string();
        if !text.contains(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
    }
    text
}
