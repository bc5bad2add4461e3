//! The one error type of the store: every variant names the store URL and, where there is one,
//! the key, so a message alone says which object of which store is at fault.

use crate::blob::BlobError;

/// An error of the store layer.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// The URL names no supported backend, or its backend cannot be configured.
    #[error(
        "cannot open store `{url}`: {reason} (supported: a directory path or file:///PATH, \
         s3://BUCKET[/PREFIX], memory://)"
    )]
    Url { url: String, reason: String },
    /// No object at `key`.
    #[error("`{key}` not found in store `{url}`")]
    NotFound { url: String, key: String },
    /// A create-only write found different content already at `key`.
    #[error("`{key}` already exists in store `{url}` with different content (create-only write refused)")]
    AlreadyExists { url: String, key: String },
    /// `key` is not a valid key (see [`crate::layout`]).
    #[error("invalid key `{key}` for store `{url}`: {reason}")]
    InvalidKey { url: String, key: String, reason: String },
    /// The backend failed (I/O, network, permissions…).
    #[error("{op} `{key}` in store `{url}` failed: {source}")]
    Backend {
        op: &'static str,
        url: String,
        key: String,
        #[source]
        source: Box<object_store::Error>,
    },
    /// The object at `key` is not a valid blob of the expected kind.
    #[error("blob `{key}` in store `{url}`: {source}")]
    Blob {
        url: String,
        key: String,
        #[source]
        source: BlobError,
    },
    /// A manifest decodes as a blob but its content is not a valid manifest.
    #[error("manifest `{key}` in store `{url}` is invalid: {reason}")]
    Manifest { url: String, key: String, reason: String },
    /// A job operation that its state does not allow.
    #[error("job `{job}` in store `{url}`: {reason}")]
    Job { url: String, job: String, reason: String },
    /// Stored light-field data that decodes as blobs but does not fit the job's scene and options.
    #[error("job `{job}` in store `{url}`: {source}")]
    Field {
        url: String,
        job: String,
        #[source]
        source: vlf_core::Error,
    },
    /// A value out of the range the key layout can represent.
    #[error("key layout: {0}")]
    Layout(String),
    /// A blocking method was called from inside an async runtime.
    #[error(
        "store `{url}`: blocking call from inside an async runtime; use `Store::as_async()` there \
         (or call from a plain thread)"
    )]
    InsideRuntime { url: String },
    /// The internal runtime could not be started.
    #[error("store `{url}`: cannot start the I/O runtime: {reason}")]
    Runtime { url: String, reason: String },
}
