//! The storage layer of VLF: typed, checksummed, zstd-compressed blobs and job manifests in a
//! local directory, an S3-compatible bucket or memory, chosen by URL.
//!
//! Read top-down: [`blob`] (the byte format of every stored object) → `codec` (how radiance
//! becomes bytes: F32, F16, RGB9E5) → [`backend`] (URL → `object_store` backend) → [`store`]
//! (keys → bytes, blocking and async) → [`layout`] (the keys of a job) → [`manifest`] and [`job`]
//! (what a job is, and the commit protocol that keeps it consistent through crashes).
//!
//! This crate knows nothing of light fields: it stores what it is given. The field's types and
//! their serialisation live in `vlf-core`.

pub mod backend;
pub mod blob;
mod codec;
pub mod error;
pub mod id;
pub mod job;
pub mod layout;
pub mod manifest;
pub mod store;

pub use blob::{BlobError, BlobKind, Data, Decoded, Encoding};
pub use error::StoreError;
pub use id::JobId;
pub use job::Job;
pub use layout::Stage;
pub use manifest::{JobState, Manifest};
pub use store::{AsyncStore, PutOutcome, Store};
