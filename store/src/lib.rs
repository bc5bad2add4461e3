//! The storage layer of VLF: typed, checksummed, zstd-compressed blobs and job manifests in a
//! local directory, an S3-compatible bucket or memory, chosen by URL.
//!
//! Read top-down: [`blob`] (the byte format of every stored object) → `codec` (how radiance
//! becomes bytes: F32, F16, RGB9E5) → [`backend`] (URL → `object_store` backend) → [`store`]
//! (keys → bytes, blocking and async) → [`layout`] (the keys of a job) → [`manifest`] and [`job`]
//! (what a job is, and the commit protocol that keeps it consistent through crashes); [`parts`]
//! reads a stage part by part, for viewers; [`writer`] writes a propagation's snapshots while it
//! goes on.
//!
//! Everything but [`field`] stores what it is given; [`field`] is the one module that maps
//! `vlf-core`'s propagations and fields onto a job's keys (what is stored, in which encoding, and
//! how a reader rebuilds a field from it). The field's own serialisations (scene, checkpoint) live
//! in `vlf-core`; this crate adds the I/O, which `vlf-core` keeps out of itself.

pub mod backend;
pub mod blob;
mod blocking;
mod codec;
pub mod error;
pub mod field;
pub mod id;
pub mod iteration;
pub mod job;
pub mod layout;
pub mod manifest;
pub mod parts;
pub mod store;
pub mod writer;

pub use blob::{BlobError, BlobKind, Data, Decoded, Encoding};
pub use blocking::{Panicked, blocking};
pub use error::StoreError;
pub use field::{FieldJob, PendingSnapshot, Summary};
pub use id::JobId;
pub use iteration::{
    Coordinator, CoordinatorPhases, HeldMaps, Prototypes, ReadAhead, Replica, ReplicaPhases, SnapshotCommit,
    WorkTraffic,
};
pub use job::Job;
pub use layout::{MapPart, Stage};
pub use manifest::{JobState, Manifest};
pub use parts::StageParts;
pub use store::{AsyncStore, IN_FLIGHT, Put, PutOutcome, READ_HERE, Store, Traffic, Writing, file_threads};
pub use writer::SnapshotWriter;
