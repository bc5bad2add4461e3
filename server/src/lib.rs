//! The VLF coordinator: a thin gRPC layer over `vlf-store`'s iteration protocol.
//!
//! A job's iteration is a list of passes, each cut into batches of directions
//! (`vlf_core::propagate::work::batch_size`). The coordinator hands batches out as **leases** with a
//! deadline; a worker computes its batch from the store and writes the output back into the
//! store; the coordinator, once every batch of a pass is reported, reads them back *in batch
//! order* and absorbs them ([`vlf_store::Coordinator`]), so the result has the same bits however
//! many workers there are and in whatever order they finish. Radiance never crosses the
//! coordinator's network connections: only leases and reports do (a lease is ~60 bytes).
//!
//! Read top-down: [`scheduler`] (jobs, leases, workers: the state machine, no networking) →
//! [`driver`] (one task per job: passes, barriers, snapshots) → [`upload`] (scenes sent by
//! clients) → [`service`] (the gRPC services over the scheduler) → [`serve`] (configuration,
//! authentication, TLS, the listening server).

pub mod cli;
pub mod driver;
pub mod scheduler;
pub mod serve;
pub mod service;
pub mod upload;

pub use scheduler::{Scheduler, Timing};
pub use serve::{ServeConfig, Server, TlsFiles};
