//! Workers joining and being heard from. All the scheduler keeps of a worker is its id, its
//! abilities and when it was last heard from: the workers alive size the leases
//! (`alive_workers`), and one silent too long loses its leases, which `Scheduler::reap` does
//! with the other expired leases (in `leases`).

use super::{Abilities, Scheduler, Unknown, WorkerEntry, alive_surveyors, alive_workers, touch};
use std::time::Instant;

impl Scheduler {
    /// Registers a worker with what its build can do and returns its id.
    pub fn register(&self, name: &str, abilities: Abilities) -> String {
        let mut state = self.lock();
        state.counter += 1;
        let number = state.counter;
        let id = format!("w{number}.{}-{}", self.epoch, sanitize(name));
        state.workers.insert(
            id.clone(),
            WorkerEntry {
                number,
                last_seen: Instant::now(),
                abilities,
            },
        );
        tracing::info!(worker = id, "worker registered");
        id
    }

    /// Workers heard from within three heartbeats.
    pub fn workers_alive(&self) -> u32 {
        alive_workers(&self.lock(), self.timing)
    }

    /// Workers alive that learn survey parts ([`Abilities::surveys`]).
    pub fn surveyors_alive(&self) -> u32 {
        alive_surveyors(&self.lock(), self.timing)
    }

    /// Notes that `worker` is alive.
    pub fn heartbeat(&self, worker: &str) -> Result<(), Unknown> {
        let mut state = self.lock();
        touch(&mut state, worker)
    }
}

/// A worker's name as it may appear in its id.
fn sanitize(name: &str) -> String {
    name.chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        .take(48)
        .collect()
}
