//! The VLF gRPC API, package `vlf.v1` (see `vlf/v1/vlf.proto`): the code tonic and prost
//! generate from it, and the conversions between its messages and the library's types, so the
//! server, the workers and the command line agree on one meaning of every field.

/// The generated code of `vlf.v1`.
pub mod v1 {
    tonic::include_proto!("vlf.v1");
}

/// The standard gRPC health service, `grpc.health.v1` (what load balancers and Kubernetes' gRPC
/// probes ask): the coordinator serves it without a token, and `vlf health` asks it.
pub mod health {
    pub use tonic_health::ServingStatus;
    pub use tonic_health::pb::{
        HealthCheckRequest, HealthCheckResponse, health_check_response, health_client::HealthClient,
    };
    pub use tonic_health::server::{HealthReporter, health_reporter};
}

mod connect;
mod convert;

pub use connect::{Authed, BearerToken, Clients, ConnectError, Target};
pub use convert::{JobSpec, pass_blocks_from_wire, pass_blocks_to_wire, pass_from_wire, pass_to_wire};

/// The metadata key of the bearer token.
pub const AUTHORIZATION: &str = "authorization";

/// Makes ring the process's TLS crypto provider, unless one is installed already. rustls cannot
/// pick one by itself when, as here, more than one is compiled in (the S3 client brings
/// aws-lc-rs); both the server and the clients call this before any TLS set-up.
pub fn install_crypto_provider() {
    // An error means a provider is installed already, which is all that is needed.
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// Logging of every VLF binary (`vlf`, `vlf-server`, `vlf-worker`): `tracing` events to stderr,
/// filtered by `RUST_LOG` (default `info`), with colour codes only when stderr is a terminal (a
/// person watching), not in logs and pipes.
pub fn init_logging() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}
