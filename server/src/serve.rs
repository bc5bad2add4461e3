//! The listening coordinator: configuration, bearer-token authentication, optional TLS, the
//! lease reaper, and recovery of the store's jobs at start.

use crate::driver;
use crate::scheduler::{Scheduler, Timing};
use crate::service::Api;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::task::JoinHandle;
use tonic::service::Interceptor;
use tonic::transport::{Identity, ServerTlsConfig};
use tonic::{Request, Status};
use vlf_proto::health::{HealthReporter, ServingStatus, health_reporter};
use vlf_proto::v1::jobs_server::{JobsServer, SERVICE_NAME as JOBS};
use vlf_proto::v1::tiles_server::{SERVICE_NAME as TILES, TilesServer};
use vlf_proto::v1::workers_server::{SERVICE_NAME as WORKERS, WorkersServer};
use vlf_store::{Prototypes, Store, StoreError};

/// A certificate chain and its private key, PEM files.
#[derive(Clone, Debug)]
pub struct TlsFiles {
    pub cert: PathBuf,
    pub key: PathBuf,
}

/// What a coordinator serves, and how.
#[derive(Clone, Debug)]
pub struct ServeConfig {
    /// The store every job lives in.
    pub store: String,
    /// Where to listen (port 0: any free port; see [`Server::addr`]).
    pub listen: SocketAddr,
    /// When set, every call must carry `authorization: Bearer <token>`.
    pub token: Option<String>,
    /// When set, serve over TLS.
    pub tls: Option<TlsFiles>,
    pub timing: Timing,
    /// Largest scene upload accepted, bytes.
    pub max_upload_bytes: u64,
    /// Workers in this process take their jobs' geometry from here instead of building it
    /// (`vlf run`).
    pub prototypes: Option<Prototypes>,
    /// At most this many bytes of a job's subfields held by the coordinator (and by workers in
    /// this process, which share its propagation); `None`: all.
    pub subfield_budget: Option<usize>,
    /// Which jobs of the store it takes up as it starts (every one, unless embedded).
    pub take_up: driver::TakeUp,
}

impl ServeConfig {
    /// Default upload limit: 64 MiB.
    pub const MAX_UPLOAD_BYTES: u64 = 64 << 20;

    /// A configuration with the defaults for `store` on `listen`.
    pub fn new(store: impl Into<String>, listen: SocketAddr) -> ServeConfig {
        ServeConfig {
            store: store.into(),
            listen,
            token: None,
            tls: None,
            timing: Timing::default(),
            max_upload_bytes: Self::MAX_UPLOAD_BYTES,
            prototypes: None,
            subfield_budget: None,
            take_up: driver::TakeUp::Every,
        }
    }
}

/// Why a coordinator could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("TLS: {0}")]
    Tls(String),
    #[error("the token must be 1..=4096 printable ASCII characters")]
    Token,
}

/// A running coordinator.
pub struct Server {
    addr: SocketAddr,
    scheduler: Arc<Scheduler>,
    health: HealthReporter,
    /// Set at shutdown: the listener stops accepting and the open `Watch` streams end (see
    /// [`Api`]).
    closing: tokio::sync::watch::Sender<bool>,
    task: JoinHandle<Result<(), tonic::transport::Error>>,
    reaper: JoinHandle<()>,
}

impl Server {
    /// Opens the store, takes up its unfinished jobs, and starts serving.
    pub async fn start(config: ServeConfig) -> Result<Server, ServeError> {
        let url = config.store.clone();
        let store = vlf_store::blocking(move || Store::open(&url))
            .await
            .map_err(|e| StoreError::Layout(e.to_string()))??;
        Server::start_with_store(config, store).await
    }

    /// As [`Server::start`] with an open store (in-process use: a `memory://` store is shared
    /// with in-process workers only through its handle).
    pub async fn start_with_store(config: ServeConfig, store: Store) -> Result<Server, ServeError> {
        let token = match &config.token {
            Some(t) if t.is_empty() || t.len() > 4096 || !t.bytes().all(|b| b.is_ascii_graphic()) => {
                return Err(ServeError::Token);
            }
            t => t.clone(),
        };
        let scheduler = Scheduler::new(store, config.timing, config.prototypes.clone(), config.subfield_budget);
        let resumed = driver::recover(&scheduler, &config.take_up).await?;
        if resumed > 0 {
            tracing::info!(resumed, "took up unfinished jobs of the store");
        }

        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .map_err(|source| ServeError::Bind {
                addr: config.listen,
                source,
            })?;
        let addr = listener.local_addr().map_err(|source| ServeError::Bind {
            addr: config.listen,
            source,
        })?;

        let (closing, closed) = tokio::sync::watch::channel(false);
        let api = Api::new(scheduler.clone(), config.max_upload_bytes).closing_with(closed);
        let auth = BearerAuth {
            token: token.map(|t| Arc::from(format!("Bearer {t}").as_str())),
        };
        // Room for the upload plus the request's other fields; the upload itself is checked
        // against the limit with a message that states it.
        let decode_limit = usize::try_from(config.max_upload_bytes.saturating_add(1 << 20)).unwrap_or(usize::MAX);
        let jobs = JobsServer::new(api.clone()).max_decoding_message_size(decode_limit);
        let mut builder = tonic::transport::Server::builder();
        if let Some(tls) = &config.tls {
            vlf_proto::install_crypto_provider();
            let cert = std::fs::read(&tls.cert)
                .map_err(|e| ServeError::Tls(format!("cannot read {}: {e}", tls.cert.display())))?;
            let key = std::fs::read(&tls.key)
                .map_err(|e| ServeError::Tls(format!("cannot read {}: {e}", tls.key.display())))?;
            builder = builder
                .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(cert, key)))
                .map_err(|e| ServeError::Tls(e.to_string()))?;
        }
        // `grpc.health.v1`, open without the token: a probe (Kubernetes', a load balancer's,
        // `vlf health`) learns only whether the coordinator serves. It does once its store is
        // open and its jobs are taken up, which is done by now.
        let (health, health_service) = health_reporter();
        set_health(&health, ServingStatus::Serving).await;
        let router = builder
            .add_service(health_service)
            .add_service(tonic::service::interceptor::InterceptedService::new(jobs, auth.clone()))
            .add_service(WorkersServer::with_interceptor(api.clone(), auth.clone()))
            .add_service(TilesServer::with_interceptor(api, auth));

        let incoming = connections(listener);
        let mut stopping = closing.subscribe();
        // A `Server` dropped without a shutdown stops too (its sender gone).
        let task = tokio::spawn(router.serve_with_incoming_shutdown(incoming, async move {
            let _ = stopping.wait_for(|closing| *closing).await;
        }));
        let reaper = {
            let scheduler = scheduler.clone();
            let timing = scheduler.timing();
            let tick =
                (timing.lease.min(timing.heartbeat) / 4).clamp(Duration::from_millis(20), Duration::from_millis(250));
            tokio::spawn(async move {
                let mut interval = tokio::time::interval(tick);
                loop {
                    interval.tick().await;
                    scheduler.reap();
                }
            })
        };
        tracing::info!(%addr, store = config.store, tls = config.tls.is_some(), "coordinator listening");
        Ok(Server {
            addr,
            scheduler,
            health,
            closing,
            task,
            reaper,
        })
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    pub fn scheduler(&self) -> &Arc<Scheduler> {
        &self.scheduler
    }

    /// Stops serving and waits for the server task: calls in flight are answered (a worker's
    /// long poll within its bound), open `Watch` streams end with `UNAVAILABLE`, and health
    /// checks answer `NOT_SERVING` to the connections still open.
    pub async fn shutdown(mut self) {
        set_health(&self.health, ServingStatus::NotServing).await;
        // A health `Watch` (gRPC clients that check health by streaming) has seen
        // `NOT_SERVING`; it ends as its status is dropped.
        for service in SERVICES {
            self.health.clear_service_status(service).await;
        }
        self.closing.send_replace(true);
        self.reaper.abort();
        // Calls in flight finish first, for `DRAIN` at most: a client that stopped reading a
        // stream does not hold the coordinator up.
        if tokio::time::timeout(DRAIN, &mut self.task).await.is_err() {
            tracing::warn!(
                "calls still open {} s after the shutdown: stopping without them",
                DRAIN.as_secs()
            );
            self.task.abort();
            let _ = (&mut self.task).await;
        }
    }

    /// Serves until the server task ends (an error) or `stop` resolves.
    pub async fn run_until(
        mut self,
        stop: impl std::future::Future<Output = ()>,
    ) -> Result<(), tonic::transport::Error> {
        let result = tokio::select! {
            r = &mut self.task => r.unwrap_or(Ok(())),
            _ = stop => Ok(()),
        };
        self.shutdown().await;
        result
    }
}

/// The health service's names: the whole server (`""`) and each API.
const SERVICES: [&str; 4] = ["", JOBS, WORKERS, TILES];

/// How long a shutdown waits for the calls in flight: longer than a worker's long poll may
/// last (the scheduler bounds it to 10 s).
const DRAIN: Duration = Duration::from_secs(12);

/// Sets the health of the whole server and of each of its APIs.
async fn set_health(health: &HealthReporter, status: ServingStatus) {
    for service in SERVICES {
        health.set_service_status(service, status).await;
    }
}

/// Checks `authorization: Bearer <token>` on every call when a token is configured.
#[derive(Clone)]
struct BearerAuth {
    /// `Bearer <token>`.
    token: Option<Arc<str>>,
}

impl Interceptor for BearerAuth {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.token else {
            return Ok(request);
        };
        let given = request
            .metadata()
            .get(vlf_proto::AUTHORIZATION)
            .map(|v| v.as_bytes())
            .unwrap_or_default();
        if constant_time_eq(given, expected.as_bytes()) {
            Ok(request)
        } else {
            Err(Status::unauthenticated(
                "this server requires a bearer token (vlf --token, or VLF_TOKEN)",
            ))
        }
    }
}

/// Equality whose time does not depend on where the inputs differ (a token is a secret).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The listener's connections, with Nagle's algorithm off: a reply goes out as soon as it is
/// written. With it on, a reply written in several frames (a lease answered after a long poll)
/// waited for the client's delayed acknowledgement, 40 ms on Linux — which about half of the
/// jobs paid on a worker's first lease.
fn connections(
    listener: tokio::net::TcpListener,
) -> impl tokio_stream::Stream<Item = std::io::Result<tokio::net::TcpStream>> {
    tokio_stream::StreamExt::map(tokio_stream::wrappers::TcpListenerStream::new(listener), |conn| {
        let conn = conn?;
        conn.set_nodelay(true)?;
        Ok(conn)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_compare_exactly() {
        assert!(constant_time_eq(b"Bearer abc", b"Bearer abc"));
        assert!(!constant_time_eq(b"Bearer abd", b"Bearer abc"));
        assert!(!constant_time_eq(b"Bearer ab", b"Bearer abc"));
        let mut auth = BearerAuth {
            token: Some(Arc::from("Bearer s3cret")),
        };
        assert_eq!(
            auth.call(Request::new(())).unwrap_err().code(),
            tonic::Code::Unauthenticated
        );
        let mut ok = Request::new(());
        ok.metadata_mut()
            .insert(vlf_proto::AUTHORIZATION, "Bearer s3cret".parse().unwrap());
        assert!(auth.call(ok).is_ok());
        let mut open = BearerAuth { token: None };
        assert!(open.call(Request::new(())).is_ok());
    }

    #[tokio::test]
    async fn connections_send_replies_at_once() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let mut incoming = Box::pin(connections(listener));
        let _client = tokio::net::TcpStream::connect(addr).await.unwrap();
        let accepted = tokio_stream::StreamExt::next(&mut incoming).await.unwrap().unwrap();
        assert!(accepted.nodelay().unwrap(), "Nagle's algorithm is on");
    }
}
