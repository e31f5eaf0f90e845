//! `mc-gateway`: parse the configuration, set up logging and signals, run until SIGINT/SIGTERM.

use anyhow::Context as _;
use tokio_util::sync::CancellationToken;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let config = mc_gateway::Config::from_env_and_args()?;
    // Held to the end: dropping it flushes the log file.
    let _log = mc_gateway::log::init(&config.log)?;
    let shutdown = CancellationToken::new();
    mc_gateway::shutdown::on_signals(shutdown.clone()).context("cannot install signal handlers")?;
    mc_gateway::run(config, shutdown).await?;
    Ok(())
}
