//! The client side of the API: a channel to a coordinator (plain or TLS) and clients that send
//! the bearer token with every call.

use crate::health::HealthClient;
use crate::v1::{jobs_client::JobsClient, tiles_client::TilesClient, workers_client::WorkersClient};
use std::path::PathBuf;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};

/// Where a coordinator is and how to talk to it.
#[derive(Clone, Debug, Default)]
pub struct Target {
    /// `http://HOST:PORT`, or `https://HOST:PORT` for TLS.
    pub url: String,
    /// Bearer token, when the server requires one.
    pub token: Option<String>,
    /// PEM file of the CA that signed the server's certificate (TLS with a private CA).
    pub ca_cert: Option<PathBuf>,
}

/// Why a connection could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    #[error("`{url}` is not a server URL (expected http://HOST:PORT or https://HOST:PORT): {reason}")]
    Url { url: String, reason: String },
    #[error("cannot read the CA certificate {path}: {source}")]
    Ca {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the token is not valid header text (printable ASCII only)")]
    Token,
    #[error("cannot connect to {url}: {source}")]
    Transport {
        url: String,
        #[source]
        source: tonic::transport::Error,
    },
}

/// Adds `authorization: Bearer <token>` to every request.
#[derive(Clone)]
pub struct BearerToken(Option<MetadataValue<tonic::metadata::Ascii>>);

impl Interceptor for BearerToken {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert(crate::AUTHORIZATION, value.clone());
        }
        Ok(request)
    }
}

/// A channel with the token interceptor.
pub type Authed = InterceptedService<Channel, BearerToken>;

/// The three clients over one connection, and the health service's.
#[derive(Clone)]
pub struct Clients {
    pub jobs: JobsClient<Authed>,
    pub workers: WorkersClient<Authed>,
    pub tiles: TilesClient<Authed>,
    pub health: HealthClient<Authed>,
}

impl Target {
    pub fn new(url: impl Into<String>) -> Target {
        Target {
            url: url.into(),
            ..Default::default()
        }
    }

    fn endpoint(&self) -> Result<Endpoint, ConnectError> {
        let url_error = |reason: String| ConnectError::Url {
            url: self.url.clone(),
            reason,
        };
        if !(self.url.starts_with("http://") || self.url.starts_with("https://")) {
            return Err(url_error("no http:// or https:// scheme".into()));
        }
        let mut endpoint = Endpoint::from_shared(self.url.clone()).map_err(|e| url_error(e.to_string()))?;
        if self.url.starts_with("https://") {
            crate::install_crypto_provider();
            let mut tls = ClientTlsConfig::new().with_enabled_roots();
            if let Some(path) = &self.ca_cert {
                let pem = std::fs::read(path).map_err(|source| ConnectError::Ca {
                    path: path.clone(),
                    source,
                })?;
                tls = tls.ca_certificate(Certificate::from_pem(pem));
            }
            endpoint = endpoint.tls_config(tls).map_err(|e| url_error(e.to_string()))?;
        }
        Ok(endpoint
            .connect_timeout(std::time::Duration::from_secs(5))
            .tcp_nodelay(true))
    }

    fn interceptor(&self) -> Result<BearerToken, ConnectError> {
        match &self.token {
            None => Ok(BearerToken(None)),
            Some(t) => format!("Bearer {t}")
                .parse()
                .map(|v| BearerToken(Some(v)))
                .map_err(|_| ConnectError::Token),
        }
    }

    /// Connects now (fails at once when nothing listens).
    pub async fn connect(&self) -> Result<Clients, ConnectError> {
        let channel = self
            .endpoint()?
            .connect()
            .await
            .map_err(|source| ConnectError::Transport {
                url: self.url.clone(),
                source,
            })?;
        self.clients(channel)
    }

    /// Clients that connect on first use and reconnect after the server went away (workers, which
    /// outlive coordinator restarts).
    pub fn connect_lazy(&self) -> Result<Clients, ConnectError> {
        let channel = self.endpoint()?.connect_lazy();
        self.clients(channel)
    }

    fn clients(&self, channel: Channel) -> Result<Clients, ConnectError> {
        let auth = self.interceptor()?;
        // Uploads may be large; the server states its own limit.
        let limit = 1 << 30;
        Ok(Clients {
            jobs: JobsClient::with_interceptor(channel.clone(), auth.clone())
                .max_encoding_message_size(limit)
                .max_decoding_message_size(limit),
            workers: WorkersClient::with_interceptor(channel.clone(), auth.clone()),
            tiles: TilesClient::with_interceptor(channel.clone(), auth.clone()).max_decoding_message_size(limit),
            health: HealthClient::with_interceptor(channel, auth),
        })
    }
}
