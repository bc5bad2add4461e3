//! `vlf-worker`: a worker alone (the same as `vlf worker`).

use clap::Parser;

#[derive(Parser)]
#[command(
    name = "vlf-worker",
    version,
    about = "VLF worker: leases batches of directions and propagates them"
)]
struct Cli {
    #[command(flatten)]
    worker: vlf_worker::cli::WorkerArgs,
}

#[tokio::main]
async fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a person watching, not in logs and pipes.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    if let Err(e) = vlf_worker::cli::work(cli.worker).await {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
