//! Job ids: short, unique, URL- and path-safe, and sorting by creation time.
//!
//! A new id is 7 base-32 digits of the Unix time in seconds, `-`, and 8 base-32 digits (40 bits)
//! of a hash of the time in nanoseconds, the process id, a per-process counter and the randomly
//! keyed std hasher — e.g. `1qx3k9z-m4c7t0ab`. Ids made in the same second by different processes
//! collide with probability ~n²/2⁴¹. Ids from elsewhere (a CLI argument) are accepted if they are
//! 1 ..= 64 characters of `[a-z0-9_-]` not starting with `-`.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::hash::{BuildHasher, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// Crockford's base 32, lower case: no `i`, `l`, `o`, `u`.
const ALPHABET: &[u8; 32] = b"0123456789abcdefghjkmnpqrstvwxyz";

/// The id of a job.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct JobId(String);

impl JobId {
    /// A new, unique id.
    pub fn generate() -> JobId {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let now = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
        let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
        hasher.write_u128(now.as_nanos());
        hasher.write_u32(std::process::id());
        hasher.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
        JobId(format!("{}-{}", base32(now.as_secs(), 7), base32(hasher.finish(), 8)))
    }

    /// Checks an id given from outside.
    pub fn parse(id: &str) -> Result<JobId, String> {
        let ok = (1..=64).contains(&id.len())
            && !id.starts_with('-')
            && id
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_');
        if ok {
            Ok(JobId(id.to_string()))
        } else {
            Err(format!(
                "invalid job id `{id}`: use 1 to 64 characters of a-z, 0-9, `-`, `_`, not starting with `-`"
            ))
        }
    }

    /// The id as text.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// The low `5 × digits` bits of `value` in base 32, most significant digit first.
fn base32(value: u64, digits: u32) -> String {
    (0..digits)
        .rev()
        .map(|i| ALPHABET[((value >> (5 * i)) & 31) as usize] as char)
        .collect()
}

impl fmt::Display for JobId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl TryFrom<String> for JobId {
    type Error = String;
    fn try_from(s: String) -> Result<JobId, String> {
        JobId::parse(&s)
    }
}

impl From<JobId> for String {
    fn from(id: JobId) -> String {
        id.0
    }
}

impl std::str::FromStr for JobId {
    type Err = String;
    fn from_str(s: &str) -> Result<JobId, String> {
        JobId::parse(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_ids_are_valid_unique_and_time_ordered() {
        let ids: Vec<JobId> = (0..1000).map(|_| JobId::generate()).collect();
        let mut unique = ids.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), ids.len());
        for id in &ids {
            assert_eq!(JobId::parse(id.as_str()).as_ref(), Ok(id));
            assert_eq!(id.as_str().len(), 16);
        }
        assert!(base32(1, 7) < base32(2, 7) && base32(31, 7) < base32(32, 7));
    }

    #[test]
    fn bad_ids_are_refused() {
        for bad in ["", "-a", "A", "a/b", "a.b", "a b", &"x".repeat(65)] {
            assert!(JobId::parse(bad).is_err(), "{bad:?}");
        }
    }
}
