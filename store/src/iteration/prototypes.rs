//! Propagations a process's coordinator hands its workers (`vlf run`), so that a worker in the
//! same process starts from the coordinator's state instead of building the geometry again. Apart
//! from the replica: it only saves time within one process, and a worker elsewhere never sees it.

use crate::id::JobId;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use vlf_core::propagate::Propagation;

/// Propagations of jobs built in this process, for replicas to start from instead of building
/// the geometry again — a coordinator and workers sharing a process (`vlf run`). Each is the
/// job's whole state at the snapshot its coordinator took it up from ([`Replica::at_snapshot`](super::Replica::at_snapshot)).
/// The geometry is a pure function of the job's scene and options, and the state is that
/// snapshot's, so it gives the same bits as a replica built from the store.
///
/// Each of the process's workers takes a job's propagation once: all but the last get a copy,
/// the last the one offered (a copy of one whose mirror maps are held costs memory and time: the
/// mirror scene's was 13 MB of maps, 2–4 ms of its first iteration). A worker that asks again
/// (its replica was dropped) finds none and builds one from the store.
#[derive(Clone)]
pub struct Prototypes {
    offers: Arc<Mutex<HashMap<JobId, Offer>>>,
    workers: usize,
}

struct Offer {
    prop: Propagation,
    /// Workers that have not taken it yet.
    left: usize,
}

impl Prototypes {
    /// Prototypes for the `workers` workers of this process.
    pub fn new(workers: usize) -> Prototypes {
        Prototypes {
            offers: Arc::default(),
            workers: workers.max(1),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<JobId, Offer>> {
        // Plain data: a panic elsewhere cannot leave it half-changed.
        self.offers.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Offers `prop`, job `id`'s propagation at its last snapshot, to the workers of this
    /// process.
    pub fn insert(&self, id: JobId, prop: Propagation) {
        let left = self.workers;
        self.lock().insert(id, Offer { prop, left });
    }

    /// Job `id`'s propagation for one worker, if one is offered: a copy, or for the last worker
    /// the one offered. The copies share the geometry that never changes (the subfields, and
    /// with mirrors their views and routes: [`vlf_core::propagate::Specular::shares_geometry`]).
    /// With mirrors, the routes are turned around by source before the first copy
    /// ([`vlf_core::propagate::Specular::prepare_settle`]), so the copies share that table too
    /// (64 MB and 0.7–0.9 s for the 47 794-triangle mirror dragon at l = 2049, N = 128), which
    /// each worker's replica built for itself otherwise.
    pub fn take(&self, id: &JobId) -> Option<Propagation> {
        let mut offers = self.lock();
        let offer = offers.get_mut(id)?;
        if let Some(spec) = &offer.prop.specular {
            spec.prepare_settle();
        }
        offer.left -= 1;
        if offer.left == 0 {
            offers.remove(id).map(|o| o.prop)
        } else {
            Some(offer.prop.clone())
        }
    }

    /// Withdraws job `id`'s propagation (the job ended).
    pub fn remove(&self, id: &JobId) {
        self.lock().remove(id);
    }
}

impl std::fmt::Debug for Prototypes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let jobs: Vec<String> = self.lock().keys().map(|id| id.to_string()).collect();
        f.debug_struct("Prototypes")
            .field("jobs", &jobs)
            .field("workers", &self.workers)
            .finish()
    }
}
