//! How an iteration used its workers: what says whether a job is limited by its workers'
//! compute, by their balance, or by the coordinator between iterations.
//!
//! Of an iteration of `seconds` (from its start to the next one's), the workers computed in the
//! span from its first lease to its last report; the rest, `seconds − span`, is the serial part
//! between iterations (the last block's absorb, the diffuse reflection, the next head's write,
//! the next leases), which no worker count shortens. In the span, `workers` workers reported
//! `busy` compute seconds in all: `busy / (workers · span)` is how evenly the work was spread,
//! 1 when every worker computed all along, less when some waited for the last one.

use std::time::Instant;
use vlf_proto::v1;

/// An iteration's use of its workers (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct IterationUse {
    /// From the iteration's start to the next one's.
    pub seconds: f64,
    /// Compute seconds the workers reported for its leases, summed.
    pub busy_seconds: f64,
    /// From its first lease to its last report (0 when none was reported).
    pub span_seconds: f64,
    /// Workers that reported work in it.
    pub workers: u32,
}

impl IterationUse {
    /// `busy / (workers · span)`: 1 when every worker computed throughout the span; `None`
    /// when nothing was computed.
    pub fn balance(&self) -> Option<f64> {
        let capacity = f64::from(self.workers) * self.span_seconds;
        (capacity > 0.0).then(|| self.busy_seconds / capacity)
    }

    /// The serial part: the iteration's time outside the span in which workers computed.
    pub fn between_seconds(&self) -> f64 {
        (self.seconds - self.span_seconds).max(0.0)
    }

    /// Worker time spent waiting in the span: `workers · span − busy`.
    pub fn waiting_seconds(&self) -> f64 {
        f64::from(self.workers) * self.span_seconds - self.busy_seconds
    }

    pub fn from_wire(u: &v1::IterationUse) -> IterationUse {
        IterationUse {
            seconds: u.seconds,
            busy_seconds: u.busy_seconds,
            span_seconds: u.span_seconds,
            workers: u.workers,
        }
    }

    pub fn to_wire(self) -> v1::IterationUse {
        v1::IterationUse {
            seconds: self.seconds,
            busy_seconds: self.busy_seconds,
            span_seconds: self.span_seconds,
            workers: self.workers,
        }
    }
}

/// What the current iteration's leases and reports have shown so far.
#[derive(Default)]
pub(super) struct UseClock {
    first_lease: Option<Instant>,
    last_report: Option<Instant>,
    busy_seconds: f64,
    workers: Vec<String>,
}

impl UseClock {
    /// A lease of the iteration was handed out.
    pub(super) fn leased(&mut self) {
        self.first_lease.get_or_insert_with(Instant::now);
    }

    /// `worker` reported a lease of the iteration done, computed in `seconds`.
    pub(super) fn reported(&mut self, worker: &str, seconds: f64) {
        self.last_report = Some(Instant::now());
        if seconds.is_finite() && seconds > 0.0 {
            self.busy_seconds += seconds;
        }
        if !self.workers.iter().any(|w| w == worker) {
            self.workers.push(worker.to_string());
        }
    }

    /// The iteration's use, as it ends after `seconds`; the clock starts over.
    pub(super) fn end(&mut self, seconds: f64) -> IterationUse {
        let span = match (self.first_lease, self.last_report) {
            (Some(first), Some(last)) => last.saturating_duration_since(first).as_secs_f64(),
            _ => 0.0,
        };
        let used = IterationUse {
            seconds,
            busy_seconds: self.busy_seconds,
            span_seconds: span.min(seconds),
            workers: self.workers.len() as u32,
        };
        *self = UseClock::default();
        used
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn sums_reports_per_worker_and_measures_the_span() {
        let mut clock = UseClock::default();
        assert_eq!(
            clock.end(0.1),
            IterationUse {
                seconds: 0.1,
                ..Default::default()
            }
        );
        clock.leased();
        std::thread::sleep(Duration::from_millis(20));
        clock.leased(); // a later lease does not move the start
        clock.reported("w1", 0.004);
        clock.reported("w2", 0.006);
        clock.reported("w1", 0.002);
        clock.reported("w2", f64::NAN); // not a time: not counted
        let used = clock.end(10.0);
        assert_eq!(used.workers, 2);
        assert!((used.busy_seconds - 0.012).abs() < 1e-12);
        assert!(used.span_seconds >= 0.02 && used.span_seconds < 10.0, "{used:?}");
        assert!((used.between_seconds() - (10.0 - used.span_seconds)).abs() < 1e-12);
        let balance = used.balance().unwrap();
        assert!((balance - 0.012 / (2.0 * used.span_seconds)).abs() < 1e-12);
        assert!((used.waiting_seconds() - (2.0 * used.span_seconds - 0.012)).abs() < 1e-12);
        assert_eq!(IterationUse::from_wire(&used.to_wire()), used);
        // Started over.
        assert_eq!(clock.end(1.0).workers, 0);
    }

    #[test]
    fn the_span_never_exceeds_the_iteration() {
        let mut clock = UseClock::default();
        clock.leased();
        std::thread::sleep(Duration::from_millis(5));
        clock.reported("w", 0.001);
        let used = clock.end(0.001);
        assert_eq!(used.span_seconds, 0.001);
        assert_eq!(used.between_seconds(), 0.0);
        assert_eq!(IterationUse::default().balance(), None);
    }
}
