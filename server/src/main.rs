//! `vlf-server`: the coordinator alone (the same as `vlf serve`).

use clap::Parser;

/// mimalloc reuses freed pages (see the `vlf` binary): fewer page faults per iteration.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

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
    vlf_proto::init_logging();
    let cli = Cli::parse();
    if let Err(e) = vlf_server::cli::serve(cli.serve).await {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
