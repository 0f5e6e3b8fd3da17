//! `holoface-server`: see `holoface-server --help` and deploy/server.example.toml.

use anyhow::Context as _;
use holoface_alignment_server::{AlignmentServer, ServerConfig, config::ConfigError, shutdown_signal};

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let (settings, log) = match ServerConfig::load() {
        Ok(v) => v,
        Err(ConfigError::Cli(e)) => e.exit(),
        Err(e) => return Err(e).context("configuration"),
    };
    holoface_process::logging::init(tracing_subscriber::EnvFilter::new(log.filter_directive()));
    let server = AlignmentServer::bind(settings)
        .await
        .context("starting the alignment server")?;
    // One machine-readable line for scripts and the loopback benchmark.
    let metrics = server
        .metrics_addr()
        .map_or_else(|| "off".to_owned(), |a| a.to_string());
    println!(
        "holoface-server on {} certificate-sha256 {} metrics {metrics}",
        server.local_addr()?,
        server.fingerprint()
    );
    server
        .run(shutdown_signal())
        .await
        .context("running the alignment server")
}
