//! Worker processes: `vlf worker` started as children of this program, for runs that measure
//! what a cluster's workers do (`vlf bench --worker-processes`). Unlike the embedded service's
//! workers, which share the coordinator's process and take its geometry, each builds the job's
//! geometry itself, reaches the store by its URL and talks to the coordinator over loopback
//! gRPC from its own address space: what separate machines would do, on one.

use anyhow::{Context, Result, bail};
use std::process::{Child, Command, Stdio};

/// Worker processes started for one run; killed (and reaped) when dropped.
pub struct WorkerProcesses {
    children: Vec<Child>,
}

impl WorkerProcesses {
    /// Starts `count` `vlf worker` processes of `threads` compute threads each, for the
    /// coordinator at `server`, reaching the store at `store_url`, each holding at most `budget`
    /// bytes of subfields when one is given. Their logs go to this program's standard error, at
    /// the `warn` level unless `RUST_LOG` says otherwise.
    pub fn start(
        count: usize,
        threads: usize,
        server: &str,
        store_url: &str,
        budget: Option<usize>,
    ) -> Result<WorkerProcesses> {
        if store_url.starts_with("memory://") {
            bail!(
                "worker processes cannot open this program's `{store_url}` store: give them one \
                 they can reach, a directory (--store /dev/shm/vlf-bench keeps it in memory) or \
                 an object store"
            );
        }
        let exe = std::env::current_exe().context("cannot find this program to start the worker processes")?;
        let mut started = WorkerProcesses { children: Vec::new() };
        for w in 0..count {
            let mut command = Command::new(&exe);
            command.args(["worker", "--server", server, "--store", store_url]);
            command.args(["--threads", &threads.to_string(), "--name", &format!("process-{w}")]);
            if let Some(bytes) = budget {
                command.args(["--subfield-memory", &bytes.to_string()]);
            }
            if std::env::var_os("RUST_LOG").is_none() {
                command.env("RUST_LOG", "warn");
            }
            command.stdin(Stdio::null()).stdout(Stdio::null());
            die_with_this_thread(&mut command);
            let child = command
                .spawn()
                .with_context(|| format!("cannot start worker process {w} ({})", exe.display()))?;
            started.children.push(child);
        }
        Ok(started)
    }

    /// The first process that has exited, and how: a worker runs until it is stopped, so one
    /// that exits — successfully or not — has failed its run (a refused registration, a store it
    /// cannot open, a crash).
    pub fn exited(&mut self) -> Option<String> {
        self.children.iter_mut().enumerate().find_map(|(w, child)| {
            let status = child.try_wait().ok()??;
            Some(format!("worker process {w} exited ({status}); its errors are above"))
        })
    }

    /// CPU seconds the processes have used so far, user and system, every thread: what the
    /// workers' share of a run costs, which this process's clock does not count. `None` where
    /// it cannot be read (it is read from Linux's `/proc`).
    pub fn cpu_seconds(&self) -> Option<f64> {
        self.children.iter().map(|c| process_cpu_seconds(c.id())).sum()
    }
}

impl Drop for WorkerProcesses {
    fn drop(&mut self) {
        for child in &mut self.children {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Has the child killed when the thread that starts it ends — this program stopped by a signal
/// it does not catch (`kill`, the OOM killer) included, where `Drop` never runs: a worker left
/// behind would retry registering forever, and could register with a later run's coordinator on
/// the same port. Linux only; elsewhere they are stopped by `Drop` alone.
#[cfg(target_os = "linux")]
fn die_with_this_thread(command: &mut Command) {
    use std::os::unix::process::CommandExt;
    // SAFETY: the closure runs in the child between fork and exec, where only async-signal-safe
    // calls are allowed: it makes one `prctl(PR_SET_PDEATHSIG)` system call, allocates nothing,
    // takes no lock and touches no state shared with the parent.
    unsafe {
        command.pre_exec(|| {
            rustix::process::set_parent_process_death_signal(Some(rustix::process::Signal::KILL))
                .map_err(std::io::Error::from)
        });
    }
}

#[cfg(not(target_os = "linux"))]
fn die_with_this_thread(_: &mut Command) {}

/// CPU seconds process `pid` has used, user and system, from `/proc/PID/stat`: fields 14 and 15
/// (`utime`, `stime`) in clock ticks. The second field, the command's name in parentheses, may
/// hold spaces, so the fields are counted from the last `)`.
fn process_cpu_seconds(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    ticks_of_stat(&stat).map(|ticks| ticks as f64 / rustix::param::clock_ticks_per_second() as f64)
}

/// `utime + stime` of a `/proc/PID/stat` line, in clock ticks.
fn ticks_of_stat(stat: &str) -> Option<u64> {
    let fields: Vec<&str> = stat.get(stat.rfind(')')? + 1..)?.split_whitespace().collect();
    // `fields[0]` is field 3 (the state), so field n is `fields[n - 3]`.
    let utime: u64 = fields.get(11)?.parse().ok()?;
    let stime: u64 = fields.get(12)?.parse().ok()?;
    Some(utime + stime)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_ticks_are_read_past_a_name_with_spaces_and_parentheses() {
        let stat = "4242 (vlf (worker) 1) S 1 4242 4242 0 -1 4194304 900 0 0 0 157 31 0 0 20 0 9 0 \
                    1234 5000000 800 18446744073709551615";
        assert_eq!(ticks_of_stat(stat), Some(157 + 31));
        assert_eq!(ticks_of_stat("4242 (vlf) S 1 2"), None, "a line cut short");
        assert_eq!(ticks_of_stat("no parenthesis"), None);
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn a_live_process_has_a_cpu_clock() {
        assert!(process_cpu_seconds(std::process::id()).is_some_and(|s| s >= 0.0));
        assert_eq!(process_cpu_seconds(u32::MAX), None, "no such process");
    }

    #[test]
    fn a_memory_store_is_refused_with_what_to_give_instead() {
        let refused = WorkerProcesses::start(1, 1, "http://127.0.0.1:1", "memory://", None)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(refused.contains("--store"), "{refused}");
    }
}
