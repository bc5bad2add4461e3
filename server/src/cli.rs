//! The flags of `vlf serve` and `vlf-server` (one definition for both).

use crate::scheduler::Timing;
use crate::serve::{ServeConfig, Server, TlsFiles};
use anyhow::{Context, Result, bail};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

#[derive(clap::Args, Clone, Debug)]
pub struct ServeArgs {
    /// Store of the jobs: a directory, file:///PATH, s3://BUCKET/PREFIX. Unfinished jobs in it are
    /// taken up at start.
    #[arg(long, value_name = "URL")]
    pub store: String,
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1:7464")]
    pub listen: SocketAddr,
    /// Require `authorization: Bearer TOKEN` on every call (workers and clients).
    #[arg(long, env = "VLF_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Serve over TLS with this certificate chain (PEM); needs --tls-key.
    #[arg(long, requires = "tls_key", value_name = "PEM")]
    pub tls_cert: Option<PathBuf>,
    /// Private key of --tls-cert (PEM).
    #[arg(long, requires = "tls_cert", value_name = "PEM")]
    pub tls_key: Option<PathBuf>,
    /// Seconds a worker has to report a leased batch before it goes to another worker (a late
    /// report is still taken if none took it meanwhile).
    #[arg(long, default_value_t = 60.0)]
    pub lease_seconds: f64,
    /// Heartbeat interval asked of workers, seconds (silent for three: dead).
    #[arg(long, default_value_t = 2.0)]
    pub heartbeat_seconds: f64,
    /// Most batches one lease may hold (leases are otherwise sized to the workers alive and the
    /// job's speed; the result is the same bits either way).
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub max_lease_batches: u32,
    /// Largest scene upload accepted, bytes.
    #[arg(long, default_value_t = ServeConfig::MAX_UPLOAD_BYTES)]
    pub max_upload_bytes: u64,
    /// Hold at most this much of a job's subfields (e.g. 256MiB): the coordinator reads them
    /// only to learn a job's survey, where its workers do not. Default: none kept for a job
    /// without mirrors (each built once), all held with mirrors while the survey is learnt
    /// (each read twice); none after set-up either way.
    #[arg(long, value_name = "SIZE")]
    pub subfield_memory: Option<bytesize::ByteSize>,
}

impl ServeArgs {
    /// The configuration the flags ask for.
    pub fn config(&self) -> Result<ServeConfig> {
        let seconds = |name: &str, s: f64| -> Result<Duration> {
            if !(s.is_finite() && (0.05..=86_400.0).contains(&s)) {
                bail!("--{name} must be between 0.05 and 86400 seconds, got {s}");
            }
            Ok(Duration::from_secs_f64(s))
        };
        Ok(ServeConfig {
            store: self.store.clone(),
            listen: self.listen,
            token: self.token.clone(),
            tls: match (&self.tls_cert, &self.tls_key) {
                (Some(cert), Some(key)) => Some(TlsFiles {
                    cert: cert.clone(),
                    key: key.clone(),
                }),
                _ => None,
            },
            timing: Timing {
                lease: seconds("lease-seconds", self.lease_seconds)?,
                heartbeat: seconds("heartbeat-seconds", self.heartbeat_seconds)?,
                max_lease_batches: self.max_lease_batches as usize,
            },
            max_upload_bytes: self.max_upload_bytes,
            prototypes: None,
            subfield_budget: self
                .subfield_memory
                .map(|b| usize::try_from(b.as_u64()).unwrap_or(usize::MAX)),
            take_up: crate::driver::TakeUp::Every,
        })
    }
}

/// Serves until Ctrl-C or SIGTERM.
pub async fn serve(args: ServeArgs) -> Result<()> {
    let server = Server::start(args.config()?)
        .await
        .context("cannot start the coordinator")?;
    let scheme = if args.tls_cert.is_some() { "https" } else { "http" };
    // Scripts and tests read this line to learn the port (with --listen HOST:0).
    println!("listening on {scheme}://{}", server.addr());
    server
        .run_until(shutdown_signal())
        .await
        .context("the coordinator stopped")?;
    Ok(())
}

/// Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(s) => s,
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
                return;
            }
        };
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
