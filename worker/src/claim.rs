//! Claiming a lease's uncommitted batches as the worker gets there: the coordinator may have
//! given them to an idle worker meanwhile, and the claim's answer says where the run ends.

use super::*;

/// What a worker may compute of its lease: the batches before `committed` are its own; those
/// from there to `end` it claims with `Extend` as it goes, and meanwhile the coordinator may
/// give them to a worker with nothing to do (the reply then says where the run ends). The
/// computing thread asks for more as it starts the last committed batch, so the answer comes
/// while it computes: a claim costs no waiting.
pub(crate) struct Claim {
    state: Mutex<ClaimState>,
    changed: Condvar,
}

pub(crate) struct ClaimState {
    committed: usize,
    end: usize,
    /// An `Extend` is on its way.
    asking: bool,
}

impl Claim {
    pub(crate) fn new(committed: usize, end: usize) -> Claim {
        let state = ClaimState {
            committed,
            end,
            asking: false,
        };
        Claim {
            state: Mutex::new(state),
            changed: Condvar::new(),
        }
    }

    /// The block to compute from batch `done` on, waiting for a claim if need be; `None` when
    /// the run ends there. Blocks are the aligned pieces of the committed part, its last batch
    /// alone while more is to be claimed (the claim is asked as it starts).
    pub(crate) fn next_block(&self, done: usize, asks: &Asks) -> Option<Range<usize>> {
        let mut state = lock(&self.state);
        loop {
            if state.end <= done {
                return None;
            }
            if state.committed > done {
                break;
            }
            ask(&mut state, asks);
            state = self.changed.wait(state).unwrap_or_else(|p| p.into_inner());
        }
        let (committed, end) = (state.committed, state.end);
        let upto = if committed < end && committed - done > 1 {
            committed - 1
        } else {
            committed
        };
        let block = reduce::cover(done..upto).first()?.clone();
        if block.end == committed {
            ask(&mut state, asks);
        }
        Some(block)
    }
}

/// Where the computing thread asks the claimer for more of the lease.
pub(crate) type Asks = tokio::sync::mpsc::UnboundedSender<()>;

pub(crate) fn ask(state: &mut ClaimState, asks: &Asks) {
    if state.asking || state.committed >= state.end {
        return;
    }
    state.asking = true;
    if asks.send(()).is_err() {
        // No one to ask: keep what is committed.
        state.end = state.committed;
        state.asking = false;
    }
}

/// Answers the computing thread's asks with `Extend` calls until it is done. A lease that is
/// gone, or a coordinator that does not answer (after a few tries), ends the run at what is
/// committed: the report then says so, and the rest goes back to the pool.
pub(crate) async fn claimer(
    mut workers: v1::workers_client::WorkersClient<vlf_proto::Authed>,
    worker_id: String,
    lease_id: String,
    claim: Arc<Claim>,
    mut asks: tokio::sync::mpsc::UnboundedReceiver<()>,
) {
    while asks.recv().await.is_some() {
        let mut reply = None;
        for attempt in 0..3 {
            let request = v1::ExtendRequest {
                worker_id: worker_id.clone(),
                lease_id: lease_id.clone(),
            };
            match workers.extend(request).await {
                Ok(r) => {
                    reply = Some(r.into_inner());
                    break;
                }
                Err(status) if transient(&status) && attempt < 2 => {
                    tokio::time::sleep(Duration::from_millis(50 << attempt)).await;
                }
                Err(status) => {
                    tracing::debug!(lease = lease_id, "cannot claim more of the lease: {}", status.message());
                    break;
                }
            }
        }
        let mut state = lock(&claim.state);
        let (committed, end) = (state.committed, state.end);
        match reply.map(|r| (r.committed_end as usize, r.end as usize)) {
            // The coordinator never takes back what is committed, nor lengthens a run.
            Some((c, e)) if committed <= c && c <= e && e <= end => {
                state.committed = c;
                state.end = e;
            }
            Some((c, e)) => {
                tracing::warn!(
                    lease = lease_id,
                    "Extend answered {c}..{e} for a lease committed to {committed} of {end}; stopping there"
                );
                state.end = committed;
            }
            None => state.end = committed,
        }
        state.asking = false;
        claim.changed.notify_all();
    }
}

#[cfg(test)]
// Blocks of one range are what these tests mean.
#[allow(clippy::single_range_in_vec_init)]
mod tests {
    use super::*;

    /// The blocks `claim` hands out from `start` until it says stop (or `limit` blocks).
    fn blocks(claim: &Claim, start: usize, asks: &Asks, limit: usize) -> Vec<Range<usize>> {
        let mut out = Vec::new();
        let mut done = start;
        while let Some(block) = claim.next_block(done, asks) {
            done = block.end;
            out.push(block);
            if out.len() == limit {
                break;
            }
        }
        out
    }

    fn answer(claim: &Claim, committed: usize, end: usize) {
        let mut state = lock(&claim.state);
        (state.committed, state.end, state.asking) = (committed, end, false);
        claim.changed.notify_all();
    }

    #[test]
    fn a_committed_run_is_its_cover_and_asks_nothing() {
        let claim = Claim::new(16, 16);
        let (asks, mut asked) = tokio::sync::mpsc::unbounded_channel();
        assert_eq!(blocks(&claim, 1, &asks, 99), [1..2, 2..4, 4..8, 8..16]);
        assert!(asked.try_recv().is_err());
    }

    #[test]
    fn the_tail_is_claimed_while_the_last_committed_batch_is_computed() {
        let claim = Claim::new(6, 8);
        let (asks, mut asked) = tokio::sync::mpsc::unbounded_channel();
        // The committed part, its last batch alone: the claim goes out as it is handed out.
        assert_eq!(blocks(&claim, 0, &asks, 2), [0..4, 4..5]);
        assert!(asked.try_recv().is_err(), "not yet");
        assert_eq!(blocks(&claim, 5, &asks, 1), [5..6]);
        assert!(asked.try_recv().is_ok());
        // Granted: the rest in one block, and the run ends there.
        answer(&claim, 8, 8);
        assert_eq!(blocks(&claim, 6, &asks, 99), [6..8]);
        assert!(asked.try_recv().is_err(), "one claim");
    }

    #[test]
    fn a_tail_given_to_another_worker_ends_the_run() {
        let claim = Claim::new(6, 8);
        let (asks, _asked) = tokio::sync::mpsc::unbounded_channel();
        assert_eq!(blocks(&claim, 0, &asks, 3), [0..4, 4..5, 5..6]);
        answer(&claim, 6, 6);
        assert_eq!(claim.next_block(6, &asks), None);
    }

    #[test]
    fn a_worker_that_reaches_its_claim_waits_for_the_answer() {
        let claim = Arc::new(Claim::new(2, 4));
        let (asks, mut asked) = tokio::sync::mpsc::unbounded_channel();
        let claimer = {
            let claim = claim.clone();
            std::thread::spawn(move || {
                asked.blocking_recv().expect("an ask");
                answer(&claim, 4, 4);
            })
        };
        assert_eq!(blocks(&claim, 2, &asks, 99), [2..4]);
        claimer.join().unwrap();
    }

    #[test]
    fn with_no_one_to_ask_the_run_ends_at_what_is_committed() {
        let claim = Claim::new(3, 8);
        let (asks, asked) = tokio::sync::mpsc::unbounded_channel();
        drop(asked);
        assert_eq!(blocks(&claim, 0, &asks, 99), [0..2, 2..3]);
    }
}
