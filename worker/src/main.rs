//! `vlf-worker`: a worker alone (the same as `vlf worker`).

use clap::Parser;

/// mimalloc reuses freed pages (see the `vlf` binary): fewer page faults per iteration.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

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
    vlf_proto::init_logging();
    let cli = Cli::parse();
    if let Err(e) = vlf_worker::cli::work(cli.worker).await {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
