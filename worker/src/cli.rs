//! The flags of `vlf worker` and `vlf-worker` (one definition for both).

use crate::{StoreChoice, WorkerConfig};
use anyhow::{Context, Result, bail};
use std::path::PathBuf;
use vlf_proto::Target;

#[derive(clap::Args, Clone, Debug)]
pub struct WorkerArgs {
    /// The coordinator: http://HOST:PORT (https:// for TLS).
    #[arg(long, env = "VLF_SERVER", value_name = "URL")]
    pub server: String,
    /// Bearer token the coordinator requires.
    #[arg(long, env = "VLF_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// PEM of the CA that signed the coordinator's certificate.
    #[arg(long, value_name = "PEM")]
    pub ca_cert: Option<PathBuf>,
    /// Reach the store by this URL instead of the one the coordinator gives.
    #[arg(long, value_name = "URL")]
    pub store: Option<String>,
    /// Compute threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Name in the coordinator's logs (default: host name and process id).
    #[arg(long)]
    pub name: Option<String>,
    /// Hold at most this much of a job's subfields (e.g. 512MiB, 2GB): the subfields of the
    /// directions this worker shoots are kept, others are built when needed and dropped. The
    /// same bits; a job whose field does not fit one machine completes across several.
    /// Per job: a worker keeps the geometry of the last two jobs it worked on. Default: all of
    /// them.
    #[arg(long, env = "VLF_SUBFIELD_MEMORY", value_name = "SIZE")]
    pub subfield_memory: Option<bytesize::ByteSize>,
    /// Test hook: stall with a lease after this many leases.
    #[arg(long, hide = true)]
    pub hang_after_leases: Option<u64>,
}

impl WorkerArgs {
    pub fn config(&self) -> Result<WorkerConfig> {
        if self.threads == Some(0) || self.threads.is_some_and(|t| t > 1024) {
            bail!("--threads must be between 1 and 1024");
        }
        let host = std::fs::read_to_string("/etc/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "worker".into());
        Ok(WorkerConfig {
            target: Target {
                url: self.server.clone(),
                token: self.token.clone(),
                ca_cert: self.ca_cert.clone(),
            },
            name: self
                .name
                .clone()
                .unwrap_or_else(|| format!("{host}-{}", std::process::id())),
            threads: self.threads,
            store: match &self.store {
                Some(url) => StoreChoice::Url(url.clone()),
                None => StoreChoice::FromServer,
            },
            hang_after: self.hang_after_leases,
            prototypes: None,
            subfield_budget: self
                .subfield_memory
                .map(|b| usize::try_from(b.as_u64()).unwrap_or(usize::MAX)),
        })
    }
}

/// Works until Ctrl-C or SIGTERM.
pub async fn work(args: WorkerArgs) -> Result<()> {
    let config = args.config()?;
    tracing::info!(server = config.target.url, "worker starting");
    let stats = crate::run(config, shutdown_signal())
        .await
        .context("the worker stopped")?;
    tracing::info!(
        batches = stats.batches,
        failed = stats.failed,
        compute_s = format!("{:.2}", stats.compute_seconds),
        "worker done"
    );
    Ok(())
}

async fn shutdown_signal() {
    #[cfg(unix)]
    if let Ok(mut term) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
        return;
    }
    let _ = tokio::signal::ctrl_c().await;
}
