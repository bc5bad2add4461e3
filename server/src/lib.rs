//! The VLF coordinator: a thin gRPC layer over `vlf-store`'s iteration protocol.
//!
//! A job's iteration is a list of passes, each cut into batches of directions
//! (`vlf_core::propagate::Batching`, the job's `pass_batches`) whose sums add up along a fixed tree
//! (`vlf_core::propagate::reduce`). The coordinator hands aligned blocks of batches out as
//! **leases** with a deadline; a worker computes its block from the store and writes the block's
//! node sum back into the store; the coordinator reads the blocks back *in order* as they are
//! reported and absorbs them ([`vlf_store::Coordinator`]), so the result has the same bits
//! however many workers there are, however the leases were cut and in whatever order they
//! finish. Radiance never crosses the coordinator's network connections: only leases and reports
//! do (a lease is ~60 bytes).
//!
//! Read top-down: [`scheduler`] (jobs, leases, workers: the state machine, no networking) →
//! [`driver`] (one task per job: passes, absorbing, snapshots) → [`upload`] (scenes sent by
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
