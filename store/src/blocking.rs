//! Blocking work for async code, on threads kept between calls.
//!
//! The coordinator and the workers are async (tokio), but a [`crate::Store`] and a propagation
//! block: [`blocking`] runs such work on a thread of its own and awaits the result. Tokio's
//! `spawn_blocking` will not do: its threads are inside the runtime, where the blocking store
//! refuses to run (it would stall the runtime's own I/O).
//!
//! A thread per call cost this VM about 0.3 ms, three times per iteration of a job: the
//! coordinator absorbs, then releases; a worker computes. So threads are kept: one that finishes
//! waits [`IDLE`] for the next call before it exits, and a call takes the thread that went idle
//! last (its stack and caches are the warmest), or starts one when none is idle. A thread puts
//! itself back on the idle list before it delivers the result, so the caller's next call finds
//! it there.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError, Sender};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Duration;

/// How long an idle thread waits for work before it exits.
const IDLE: Duration = Duration::from_secs(10);

/// A call's work: it returns the delivery of its result, which the thread runs once it is idle
/// again, so that the caller's next call finds it idle.
type Job = Box<dyn FnOnce() -> Delivery + Send>;
type Delivery = Box<dyn FnOnce() + Send>;

/// The idle threads, by number and the sender of their queue, most recently idle last.
static IDLE_THREADS: Mutex<Vec<(u64, Sender<Job>)>> = Mutex::new(Vec::new());
static THREADS_STARTED: AtomicU64 = AtomicU64::new(0);

fn idle_threads() -> MutexGuard<'static, Vec<(u64, Sender<Job>)>> {
    IDLE_THREADS.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Runs `work` — blocking [`crate::Store`] calls, or computing with them — on a thread outside
/// any async runtime and awaits its result: how async code (the coordinator, workers) uses the
/// blocking API.
pub async fn blocking<T: Send + 'static>(work: impl FnOnce() -> T + Send + 'static) -> Result<T, Panicked> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let job: Job = Box::new(move || {
        let out = work();
        Box::new(move || {
            let _ = tx.send(out);
        })
    });
    run(job).map_err(|_| Panicked)?;
    // A job that panics drops `tx` (and ends its thread): the receiver sees it.
    rx.await.map_err(|_| Panicked)
}

/// Hands `job` to the thread that went idle last, or to a new one.
fn run(mut job: Job) -> std::io::Result<()> {
    while let Some((_, thread)) = idle_threads().pop() {
        match thread.send(job) {
            Ok(()) => return Ok(()),
            // Its thread is gone (a job panicked on it): try the next.
            Err(mpsc::SendError(back)) => job = back,
        }
    }
    let number = THREADS_STARTED.fetch_add(1, Ordering::Relaxed);
    let (tx, rx) = mpsc::channel::<Job>();
    tx.send(job)
        .map_err(|_| std::io::Error::other("a new thread's queue is closed"))?;
    std::thread::Builder::new()
        .name("vlf-store-blocking".into())
        .spawn(move || {
            loop {
                match rx.recv_timeout(IDLE) {
                    Ok(job) => {
                        let deliver = job();
                        idle_threads().push((number, tx.clone()));
                        deliver();
                    }
                    Err(RecvTimeoutError::Timeout) => {
                        // Leave only if no caller has taken this thread meanwhile (one that has
                        // is about to send it a job).
                        let mut idle = idle_threads();
                        if let Some(at) = idle.iter().position(|(n, _)| *n == number) {
                            idle.remove(at);
                            return;
                        }
                    }
                    Err(RecvTimeoutError::Disconnected) => return,
                }
            }
        })
        .map(drop)
}

/// A [`blocking`] task that panicked (or whose thread could not start).
#[derive(Debug, thiserror::Error)]
#[error("a blocking task panicked or could not start")]
pub struct Panicked;

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn work_runs_outside_the_runtime_on_kept_threads() {
        let outside = blocking(|| tokio::runtime::Handle::try_current().is_err())
            .await
            .unwrap();
        assert!(outside, "a blocking job ran inside the runtime");
        // One after another, the calls share a thread.
        let first = blocking(|| std::thread::current().id()).await.unwrap();
        let mut same = 0;
        for _ in 0..20 {
            if blocking(|| std::thread::current().id()).await.unwrap() == first {
                same += 1;
            }
        }
        assert!(same > 0, "no thread was kept");
        // Calls at once run at once, on as many threads.
        let barrier = std::sync::Arc::new(std::sync::Barrier::new(4));
        let calls = (0..4).map(|_| {
            let barrier = barrier.clone();
            blocking(move || {
                barrier.wait();
                std::thread::current().id()
            })
        });
        let ids = futures::future::join_all(calls).await;
        let ids: std::collections::HashSet<_> = ids.into_iter().map(Result::unwrap).collect();
        assert_eq!(ids.len(), 4);
        // A panic is reported, and the threads go on serving.
        assert!(blocking(|| panic!("on purpose")).await.is_err());
        assert_eq!(blocking(|| 2 + 2).await.unwrap(), 4);
    }
}
