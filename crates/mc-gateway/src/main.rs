//! `mc-gateway`: parse the configuration, set up logging and signals, run until SIGINT/SIGTERM.
//! `mc-gateway doctor` runs the bring-up checks instead (`mc_gateway::doctor`) and exits 0 only
//! when none failed; `--check-config` prints the effective configuration and exits. A failure is
//! one line on stderr and exit status 1; once logging runs, it is also the JSON log's last line.

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
    if config.settings.check_config {
        check(&config)?;
        return Ok(ExitCode::SUCCESS);
    }
    // Held to the end: dropping it flushes the log file.
    let log = mc_gateway::log::init(&config.log)?;
    let result = async {
        let shutdown = CancellationToken::new();
        mc_gateway::shutdown::on_signals(shutdown.clone())
            .context("cannot install signal handlers")?;
        mc_gateway::run(*config, shutdown).await?;
        anyhow::Ok(())
    }
    .await;
    if let Err(e) = &result {
        mc_gateway::log::fatal(&report(e));
    }
    drop(log);
    result.map(|()| ExitCode::SUCCESS)
}

/// `--check-config`: the report on stdout; problems make it fail (exit status 1).
fn check(config: &mc_gateway::Config) -> anyhow::Result<()> {
    print!("{}", mc_gateway::config::check::report(config));
    let problems = mc_gateway::config::check::problems(config);
    if problems.is_empty() {
        println!("configuration OK");
        return Ok(());
    }
    anyhow::bail!(
        "the configuration has {} problem(s):\n  {}",
        problems.len(),
        problems.join("\n  ")
    )
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
