//! The workers' side of the work: cutting a lease from the open passes, giving an idle worker
//! the unclaimed tail of another's, claims, reports, and leases that expire (or whose worker
//! died). Apart from the blocks already stored when a pass opens, every change of a batch's
//! state is made here, so that a batch `Leased(n)` is one of lease `n` and goes back to
//! `Pending` when that lease does not finish is kept in one file.

use super::pass::{BatchState, PassRun, find_run, first_claim};
use super::{
    Grant, JobEntry, LeaseEntry, MAX_BATCH_EXPIRIES, MAX_BATCH_FAILURES, MAX_EXPIRED_KEPT, Scheduler, State, Unknown,
    alive_workers, block_len, publish, touch,
};
use std::collections::HashMap;
use std::ops::Range;
use std::time::{Duration, Instant};
use vlf_core::propagate::Pass;
use vlf_core::propagate::reduce;
use vlf_store::JobId;

/// A lease about to be handed out (see [`Scheduler::hand_out`]).
struct Lease<'a> {
    number: u64,
    worker: &'a str,
    batches: Range<usize>,
    committed: usize,
}

impl Scheduler {
    /// Leases the first pending batch of the oldest job to `worker`, its open passes taken in
    /// shooting order ([`Pass::shooting_rank`]), waiting up to `wait` for one.
    pub async fn lease(&self, worker: &str, wait: Duration) -> Result<Option<Grant>, Unknown> {
        let until = Instant::now() + wait;
        loop {
            let notified = self.work_ready.notified();
            tokio::pin!(notified);
            // Register interest before looking, so a pass opened in between is not missed.
            notified.as_mut().enable();
            if let Some(grant) = self.try_lease(worker)? {
                return Ok(Some(grant));
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            tokio::select! {
                _ = &mut notified => {}
                _ = tokio::time::sleep(left) => {}
            }
        }
    }

    fn try_lease(&self, worker: &str) -> Result<Option<Grant>, Unknown> {
        let mut guard = self.lock();
        let state = &mut *guard;
        touch(state, worker)?;
        let alive = alive_workers(state, self.timing);
        let takes = |pass| state.workers.get(worker).is_some_and(|w| w.abilities.takes(pass));
        let mut jobs: Vec<(&JobId, &JobEntry)> = state.jobs.iter().collect();
        jobs.sort_by_key(|(_, j)| j.order);
        let found = jobs.iter().find_map(|(id, entry)| {
            if !entry.is_open() {
                return None;
            }
            // A rotated copy's shot before the next copy's areas: a worker keeps the subfields
            // its areas built for the shot, one copy's at most (`Pass::shooting_rank`). So a pass
            // also waits for one ranked before it that opens as soon as what is written is
            // absorbed (a copy's shot, its areas all written and absorbed but for the last
            // blocks: milliseconds): leased the next copy's areas meanwhile, a lone worker would
            // fill its keep with subfields it must build again.
            let opening = opening_once_absorbed(&entry.passes);
            let mut order: Vec<usize> = (0..entry.passes.len()).collect();
            order.sort_by_key(|&p| entry.passes[p].pass.shooting_rank());
            order.into_iter().find_map(|p| {
                let run = &entry.passes[p];
                let rank = run.pass.shooting_rank();
                if !takes(run.pass) || opening.iter().any(|q| q.shooting_rank() < rank) {
                    return None;
                }
                let (b, home) = run.first_pending(worker, &entry.shooting, &state.workers)?;
                Some(((*id).clone(), p, b, home))
            })
        });
        let Some((job, p, first, home)) = found else {
            return Ok(self.steal(state, worker, alive));
        };
        state.counter += 1;
        let number = state.counter;
        let abilities = state.workers.get(worker).map(|w| w.abilities).unwrap_or_default();
        let takes_runs = abilities.runs;
        let home = home.filter(|home| alive > 1 && home.contains(&first));
        let Some(entry) = state.jobs.get_mut(&job) else {
            unreachable!("found above");
        };
        let most = self.timing.max_lease_batches.max(1);
        let open: usize = entry.passes.iter().map(|r| r.batches.len() - r.done).sum();
        let speed = match entry.passes[p].pass {
            Pass::Survey => entry.clock.survey_batch_seconds,
            _ => entry.clock.batch_seconds,
        };
        let run = &mut entry.passes[p];
        let n = run.batches.len();
        let (batches, committed) = match home {
            // What is left of its home in one lease, as far as the lease's lifetime allows:
            // homes are split by what the batches cost on the workers that shot them, so they
            // balance the workers, and follow one that slows down, without a lease per quarter.
            // What the cost split mispredicts, the workers even out at the end of the pass: the
            // worker claims the last quarter of its run when it gets there, and one with
            // nothing left to do can be given it meanwhile (`Scheduler::steal`).
            Some(home) if takes_runs => {
                let len = block_len(n, n, 1, speed, self.timing.lease).min(most);
                let batches = run.pending_run_within(first, home.end.min(first + len));
                let committed = first_claim(&batches, abilities.claims);
                (batches, committed)
            }
            _ => {
                let len = block_len(n, open, alive, speed, self.timing.lease).min(most);
                let batches = if takes_runs {
                    run.pending_run(first, len)
                } else {
                    run.pending_block(first, len)
                };
                (batches.clone(), batches.end)
            }
        };
        let lease = Lease {
            number,
            worker,
            batches,
            committed,
        };
        Ok(Some(self.hand_out(&mut state.leases, entry, p, job, lease, alive)))
    }

    /// Marks `lease`'s batches of the open pass `p` of `entry` (the job `job`) leased, records the
    /// lease and publishes the job's status.
    fn hand_out(
        &self,
        leases: &mut HashMap<String, LeaseEntry>,
        entry: &mut JobEntry,
        p: usize,
        job: JobId,
        lease: Lease,
        alive: u32,
    ) -> Grant {
        entry.clock.use_clock.leased();
        let run = &mut entry.passes[p];
        for b in &mut run.batches[lease.batches.clone()] {
            b.state = BatchState::Leased(lease.number);
        }
        let grant = Grant {
            lease_id: format!("l{}.{}", lease.number, self.epoch),
            job: job.clone(),
            snapshot: run.snapshot,
            pass: run.pass,
            batches: lease.batches.clone(),
            committed: lease.committed,
            deadline: self.timing.lease,
            reads: run.reads.clone(),
        };
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        leases.insert(
            grant.lease_id.clone(),
            LeaseEntry {
                number: lease.number,
                job,
                snapshot: grant.snapshot,
                pass: grant.pass,
                worker: lease.worker.to_string(),
                batches: lease.batches,
                committed: lease.committed,
                deadline: Instant::now() + self.timing.lease,
            },
        );
        grant
    }

    /// With nothing pending, gives `worker` the tail of another worker's lease that this one has
    /// not claimed yet. Of the leases of open passes with unclaimed batches, the one with the
    /// most (the oldest among equals). This is how the
    /// workers share the end of a pass as threads steal work from one another: the cost split
    /// of the homes (`home`) predicts what a worker's batches cost from the last iteration, and
    /// a worker that shares its machine, or meets other arrivals, takes longer than predicted.
    fn steal(&self, state: &mut State, worker: &str, alive: u32) -> Option<Grant> {
        let abilities = state.workers.get(worker)?.abilities;
        if !abilities.runs {
            return None;
        }
        let open = |job: &JobId| state.jobs.get(job).is_some_and(JobEntry::is_open);
        let (victim, _) = state
            .leases
            .iter()
            .filter(|(_, l)| l.worker != worker && l.committed < l.batches.end && open(&l.job))
            .filter(|(_, l)| abilities.takes(l.pass))
            .map(|(id, l)| (id.clone(), (l.batches.end - l.committed, std::cmp::Reverse(l.number))))
            .max_by_key(|(_, key)| *key)?;
        state.counter += 1;
        let number = state.counter;
        let lease = state.leases.get_mut(&victim)?;
        let batches = lease.committed..lease.batches.end;
        lease.batches.end = batches.start;
        let (job, snapshot, pass) = (lease.job.clone(), lease.snapshot, lease.pass);
        let entry = state.jobs.get_mut(&job)?;
        let p = entry
            .passes
            .iter()
            .position(|r| (r.snapshot, r.pass) == (snapshot, pass))?;
        let committed = first_claim(&batches, abilities.claims);
        tracing::debug!(job = %job, ?batches, from = victim, worker, "tail of a lease given to an idle worker");
        let lease = Lease {
            number,
            worker,
            batches,
            committed,
        };
        Some(self.hand_out(&mut state.leases, entry, p, job, lease, alive))
    }

    /// `worker` claims the rest of its lease. Returns the lease as it stands, `(committed, end)`
    /// — `end` earlier than granted when its tail went to another worker — or `None` when the
    /// lease is gone (expired, its job ended).
    pub fn extend(&self, worker: &str, lease_id: &str) -> Result<Option<(usize, usize)>, Unknown> {
        let mut state = self.lock();
        touch(&mut state, worker)?;
        let Some(lease) = state.leases.get_mut(lease_id).filter(|l| l.worker == worker) else {
            return Ok(None);
        };
        lease.committed = lease.batches.end;
        Ok(Some((lease.committed, lease.batches.end)))
    }

    /// Records a worker's result for a lease: `Ok(())` when the block's output is in the store,
    /// `Err(message)` when it could not be computed; `seconds` is what computing it took. Returns
    /// whether the report was taken (`false`: the lease had expired or its job ended; nothing
    /// changes).
    pub fn report(
        &self,
        worker: &str,
        lease_id: &str,
        result: Result<(), String>,
        seconds: f64,
    ) -> Result<bool, Unknown> {
        self.report_run(worker, lease_id, result, seconds, None, &[])
    }

    /// [`Scheduler::report`] of a lease computed up to `end` (`None`: to its end): a worker
    /// that could not claim the rest (the coordinator did not answer) reports what it has, and
    /// the batches after `end` are pending again. An `end` outside the lease is not taken.
    /// `costs` are what each batch computed cost, in order (empty: `seconds` shared evenly).
    pub fn report_run(
        &self,
        worker: &str,
        lease_id: &str,
        result: Result<(), String>,
        seconds: f64,
        end: Option<usize>,
        costs: &[f64],
    ) -> Result<bool, Unknown> {
        let mut state = self.lock();
        touch(&mut state, worker)?;
        let alive = alive_workers(&state, self.timing);
        if !state.leases.contains_key(lease_id) {
            revive_late(&mut state, worker, lease_id, end);
        }
        let Some(lease) = state.leases.get(lease_id) else {
            return Ok(false);
        };
        if lease.worker != worker || end.is_some_and(|e| e <= lease.batches.start || e > lease.batches.end) {
            return Ok(false);
        }
        let Some(lease) = state.leases.remove(lease_id) else {
            return Ok(false);
        };
        let number = lease.number;
        let Some(entry) = state.jobs.get_mut(&lease.job) else {
            return Ok(false);
        };
        let Some(run) = find_run(&mut entry.passes, &lease) else {
            return Ok(false);
        };
        let pass = run.pass;
        let full = lease.batches.clone();
        if !run.batches[full.clone()]
            .iter()
            .all(|b| b.state == BatchState::Leased(number))
        {
            return Ok(false);
        }
        let batches = full.start..end.unwrap_or(full.end);
        let mut requeued = false;
        if batches.end < full.end {
            for b in &mut run.batches[batches.end..full.end] {
                b.state = BatchState::Pending;
            }
            requeued = true;
        }
        match result {
            Ok(()) => {
                for block in reduce::cover(batches.clone()) {
                    run.mark_done(block);
                }
                if pass == Pass::Shoot {
                    entry
                        .shooting
                        .record(worker, batches.clone(), run.batches.len(), seconds, costs);
                }
                // A survey's batches cost another thing than the iterations': each its own speed.
                if seconds.is_finite() && seconds > 0.0 {
                    let speed = match pass {
                        Pass::Survey => &mut entry.clock.survey_batch_seconds,
                        _ => &mut entry.clock.batch_seconds,
                    };
                    *speed = Some(seconds / batches.len() as f64);
                }
                entry.clock.use_clock.reported(worker, seconds);
                entry.driver.notify_one();
            }
            Err(message) => {
                tracing::warn!(job = %lease.job, ?batches, worker, "block failed: {message}");
                let mut failures = 0;
                for b in &mut run.batches[batches.clone()] {
                    b.failures += 1;
                    b.state = BatchState::Pending;
                    failures = failures.max(b.failures);
                }
                if failures >= MAX_BATCH_FAILURES {
                    entry.failure = Some(format!(
                        "batches {batches:?} of {pass:?} failed {failures} times; last: {message}"
                    ));
                    entry.driver.notify_one();
                } else {
                    requeued = true;
                }
            }
        }
        let status = entry.status.borrow().clone();
        publish(entry, status, alive);
        drop(state);
        if requeued {
            self.work_ready.notify_waiters();
        }
        Ok(true)
    }

    /// Expires leases past their deadline and forgets workers silent for three heartbeats
    /// (their leases expire with them). The expired leases of workers still heard from are kept
    /// a while ([`MAX_EXPIRED_KEPT`]), so that a late report on one is still taken if no other
    /// worker took its batches meanwhile. Returns how many leases expired.
    pub fn reap(&self) -> usize {
        let now = Instant::now();
        let mut state = self.lock();
        let dead_after = self.timing.heartbeat * 3;
        let dead: Vec<String> = state
            .workers
            .iter()
            .filter(|(_, w)| now.duration_since(w.last_seen) > dead_after)
            .map(|(id, _)| id.clone())
            .collect();
        for id in &dead {
            tracing::warn!(
                worker = id,
                "worker silent for 3 heartbeats: its leases go back to the pool"
            );
            state.workers.remove(id);
        }
        let expired: Vec<String> = state
            .leases
            .iter()
            .filter(|(_, l)| l.deadline <= now || dead.contains(&l.worker))
            .map(|(id, _)| id.clone())
            .collect();
        let alive = alive_workers(&state, self.timing);
        for id in &expired {
            let Some(lease) = state.leases.remove(id) else {
                continue;
            };
            let number = lease.number;
            if let Some(entry) = state.jobs.get_mut(&lease.job) {
                if let Some(run) = find_run(&mut entry.passes, &lease) {
                    let (batches, pass) = (lease.batches.clone(), run.pass);
                    let (mut any, mut expiries) = (false, 0);
                    for b in &mut run.batches[batches.clone()] {
                        if b.state == BatchState::Leased(number) {
                            b.state = BatchState::Pending;
                            b.expiries += 1;
                            expiries = expiries.max(b.expiries);
                            any = true;
                        }
                    }
                    if any {
                        tracing::warn!(job = %lease.job, ?batches, worker = lease.worker, "lease expired");
                    }
                    if expiries >= MAX_BATCH_EXPIRIES && entry.failure.is_none() {
                        entry.failure = Some(format!(
                            "batches {batches:?} of {pass:?} were leased {expiries} times and never reported in \
                             time: every worker that took them hung on them or died (out of memory?), or one \
                             batch takes longer than the lease (--lease-seconds)"
                        ));
                        entry.driver.notify_one();
                    }
                }
                let status = entry.status.borrow().clone();
                publish(entry, status, alive);
            }
            // Its worker, alive, may still report it (slow, not dead): kept for that.
            if !dead.contains(&lease.worker) {
                keep_expired(&mut state.expired, id.clone(), lease);
            }
        }
        drop(state);
        if !expired.is_empty() {
            self.work_ready.notify_waiters();
        }
        expired.len()
    }
}

/// The passes not open yet that open as soon as the driver absorbs what is written: those whose
/// prerequisites are all done, with every open pass absorbed before them (the driver absorbs in
/// [`Pass::absorbing_rank`] order: a copy's shot opens once its areas and every earlier copy's
/// areas are in).
fn opening_once_absorbed(passes: &[PassRun]) -> Vec<Pass> {
    let done = |r: &PassRun| r.done == r.batches.len();
    let open = |pass: Pass| passes.iter().any(|r| r.pass == pass);
    (passes.iter().filter(|r| done(r)))
        .flat_map(|r| r.pass.dependents())
        .filter(|&q| !open(q))
        .filter(|&q| {
            let last = q.prerequisites().into_iter().map(Pass::absorbing_rank).max();
            (passes.iter())
                .filter(|r| Some(r.pass.absorbing_rank()) <= last)
                .all(done)
        })
        .collect()
}

/// Keeps `lease`, expired while its worker is still heard from, among the expired ones a late
/// report may revive ([`revive_late`]), the oldest let go past [`MAX_EXPIRED_KEPT`].
fn keep_expired(expired: &mut HashMap<String, LeaseEntry>, id: String, lease: LeaseEntry) {
    expired.insert(id, lease);
    while expired.len() > MAX_EXPIRED_KEPT {
        let Some(oldest) = (expired.iter()).min_by_key(|(_, l)| l.number).map(|(id, _)| id.clone()) else {
            break;
        };
        expired.remove(&oldest);
    }
}

/// A report on a lease that expired while its worker was still heard from (a slow worker, or a
/// slow batch: not a dead one) is taken as the lease's own when no other worker has taken any of
/// its batches since: each is still pending, or leased again to the same worker (which asked
/// for its next lease while its report went out from the background, and was given the same
/// batches back), whose newer leases of them go. The lease is put back as it was, and the
/// report then finds it. Else nothing changes and the report is ignored. Without it, a worker
/// whose blocks outlast the deadline had them expire, took them again, as slowly, and never
/// reported one in time: the job stalled, and its speed, learnt from reports, never changed.
fn revive_late(state: &mut State, worker: &str, lease_id: &str, end: Option<usize>) {
    let Some(lease) = state.expired.remove(lease_id) else {
        return;
    };
    // The worker's own leases, by number, with their runs: those it may hold the batches by.
    let own: HashMap<u64, (String, Range<usize>)> = (state.leases.iter())
        .filter(|(_, l)| {
            l.worker == worker && l.job == lease.job && (l.snapshot, l.pass) == (lease.snapshot, lease.pass)
        })
        .map(|(id, l)| (l.number, (id.clone(), l.batches.clone())))
        .collect();
    let inside = |r: &Range<usize>| r.start >= lease.batches.start && r.end <= lease.batches.end;
    let mut superseded: Vec<String> = Vec::new();
    let revivable = lease.worker == worker
        && end.is_none_or(|e| e > lease.batches.start && e <= lease.batches.end)
        && (state.jobs.get_mut(&lease.job))
            .and_then(|entry| find_run(&mut entry.passes, &lease))
            .is_some_and(|run| {
                run.batches[lease.batches.clone()].iter().all(|b| match b.state {
                    BatchState::Pending => true,
                    BatchState::Leased(n) => match own.get(&n) {
                        Some((id, range)) if inside(range) => {
                            if !superseded.contains(id) {
                                superseded.push(id.clone());
                            }
                            true
                        }
                        _ => false,
                    },
                    BatchState::Done => false,
                })
            });
    if !revivable {
        return;
    }
    for id in &superseded {
        state.leases.remove(id);
    }
    let number = lease.number;
    if let Some(run) = (state.jobs.get_mut(&lease.job)).and_then(|entry| find_run(&mut entry.passes, &lease)) {
        for b in &mut run.batches[lease.batches.clone()] {
            b.state = BatchState::Leased(number);
        }
    }
    tracing::info!(job = %lease.job, batches = ?lease.batches, worker, superseded = superseded.len(), "late report taken: no other worker took its batches");
    state.leases.insert(lease_id.to_string(), lease);
}
