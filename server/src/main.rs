//! `vlf-server`: the coordinator alone (the same as `vlf serve`).

use clap::Parser;

#[derive(Parser)]
#[command(
    name = "vlf-server",
    version,
    about = "VLF coordinator: jobs, leases to workers, progress, tiles"
)]
struct Cli {
    #[command(flatten)]
    serve: vlf_server::cli::ServeArgs,
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
    if let Err(e) = vlf_server::cli::serve(cli.serve).await {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
