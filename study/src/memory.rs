//! Peak memory of one stretch of work, from the kernel's own accounting.
//!
//! Linux keeps a process's high-water mark of resident memory (`VmHWM` in
//! `/proc/self/status`), and writing `5` to `/proc/self/clear_refs` resets it
//! to the current resident size (Linux ≥ 4.0). A study runs many
//! propagations in one process, so before each one the allocator is first
//! asked to hand its free memory back (`malloc_trim`, glibc), the mark is
//! reset, and the propagation's peak is the mark afterwards minus the
//! resident size at the reset: memory the propagation itself needed at its
//! worst. Elsewhere (or where `/proc` is read-only) the figure is absent.

/// A reset high-water mark: the resident size it started from.
#[derive(Clone, Copy, Debug)]
pub struct Baseline {
    resident: u64,
}

fn status_kib(field: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Trims the heap and resets the high-water mark; `None` if this system cannot.
pub fn reset_peak() -> Option<Baseline> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free heap pages to the kernel; it
    // takes the allocator's own locks and touches no live allocation, so it
    // is sound to call at any time from any thread.
    unsafe {
        libc::malloc_trim(0);
    }
    std::fs::write("/proc/self/clear_refs", "5").ok()?;
    Some(Baseline {
        resident: status_kib("VmRSS:")? * 1024,
    })
}

/// Peak resident memory since `baseline` was taken, beyond its resident size, in bytes.
pub fn peak_since(baseline: Baseline) -> Option<u64> {
    Some((status_kib("VmHWM:")? * 1024).saturating_sub(baseline.resident))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_peak_sees_a_large_allocation_and_resets() {
        let Some(baseline) = reset_peak() else {
            return; // not Linux, or /proc is read-only here: nothing to check
        };
        let block = vec![1u8; 256 << 20];
        std::hint::black_box(&block);
        let during = peak_since(baseline).unwrap();
        assert!(during >= 250 << 20, "{during}");
        drop(block);
        let baseline = reset_peak().unwrap();
        assert!(peak_since(baseline).unwrap() < 64 << 20);
    }
}
