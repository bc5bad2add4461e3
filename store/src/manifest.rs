//! The manifest of a job: what it is (scene hash, parameters, encoding), where it stands (state)
//! and which iterations are finished.
//!
//! It is stored as JSON inside a blob of kind [`BlobKind::Manifest`], so it is readable after
//! `zstd -d` yet checksummed like every other blob: a corrupted manifest is an error naming its
//! key, never a job with silently wrong iterations. It is the commit point of a job (see
//! [`crate::job`]): readers trust only what it lists.

use crate::blob::{self, BlobKind, Encoding};
use crate::id::JobId;
use serde::{Deserialize, Serialize};
use std::time::{SystemTime, UNIX_EPOCH};

/// The version of a job's stored layout, recorded in its manifest. A job of another version is
/// refused with a message that says so, never read into a wrong picture.
///
/// * 1: texel grids per polygon, diffuse maps one blob per polygon.
/// * 2: texel grids per chart (`vlf_core::maps::charts`), diffuse maps in chunks of charts.
/// * 3: the stored scene carries albedo textures and texture coordinates.
/// * 4: the parameters say how many batches a pass is cut into (`pass_batches`), which fixes
///   the bits and the snapshots' batches of mirror maps. A job of format 3 is read as what it
///   was, 16 batches a pass (the parameters' default), so that it renders and resumes as it ran;
///   a build that reads 3 at most refuses format 4 rather than cut its maps wrongly.
/// * 5: the polygons of a mirror chart share their plane's mirror slots (one subfield entry per
///   tile, as a diffuse plane's do), so a mirror's directional maps are laid out per plane, not
///   per polygon. A job of format 3 or 4 is read as it was unless its scene has a mirror of
///   several polygons (`FieldJob::open` refuses that one: its maps are laid out otherwise); a
///   build that reads 4 at most refuses format 5 rather than read a plane's slots per polygon.
/// * 6: a mirror job's snapshots store their mirror radiance in the job's encoding as well,
///   one blob per batch of directions (`iters/K/mirror-radiance/`), which renders read; a
///   compacted snapshot keeps only what renders read (summary, diffuse maps, mirror radiance),
///   not its exact state (head, diffuse and mirror totals, `f64`). A job of format 5 or earlier
///   is read as it was, and compacts as it did (its mirror shooting maps only); a build that
///   reads 5 at most refuses format 6 rather than look for a compacted snapshot's totals.
/// * 7: the parameters say how many directions a stint holds (`stint_directions`: consecutive
///   directions of a batch shot into one buffer before it is added to the batch's sum), which
///   fixes the bits. A job of format 6 or earlier is read as what it was, stints of one
///   direction, so that it resumes as it ran; a build that reads 6 at most refuses format 7
///   rather than resume it with other sums.
pub const MANIFEST_FORMAT: u32 = 7;

/// The oldest format this build reads ([`MANIFEST_FORMAT`]'s list says what changed).
pub const OLDEST_READABLE_FORMAT: u32 = 3;

/// Where a job stands.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum JobState {
    /// Created, not started.
    Queued,
    /// Computing iteration `iteration`.
    Propagating { iteration: u32 },
    /// The final field is written and complete.
    Finished,
    /// Stopped by an error.
    Failed { message: String },
    /// Stopped on request.
    Cancelled,
}

impl std::fmt::Display for JobState {
    /// As `vlf jobs` lists it: "queued", "propagating iteration 3", "failed: …".
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            JobState::Queued => write!(f, "queued"),
            JobState::Propagating { iteration } => write!(f, "propagating iteration {iteration}"),
            JobState::Finished => write!(f, "finished"),
            JobState::Failed { message } => write!(f, "failed: {message}"),
            JobState::Cancelled => write!(f, "cancelled"),
        }
    }
}

/// A job's manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// [`MANIFEST_FORMAT`].
    pub format: u32,
    /// The job's id (equal to the one in its key).
    pub job_id: JobId,
    /// Hash of the normalised scene, lower-case hex.
    pub scene_hash: String,
    /// The caller's propagation options, as JSON.
    pub parameters: serde_json::Value,
    /// Where the job stands.
    pub state: JobState,
    /// Iterations whose snapshots are complete, strictly increasing.
    pub finished_iterations: Vec<u32>,
    /// Encoding of the job's radiance blobs.
    pub encoding: Encoding,
    /// Creation time, Unix seconds.
    pub created: u64,
    /// Time of the last update, Unix seconds.
    pub updated: u64,
    /// Whether the final field's mirror maps are re-sampled by backward ray tracing (a setting of
    /// the job's last step, kept so that whoever finishes the job — a restarted coordinator —
    /// does what was asked). Absent in older manifests: false.
    #[serde(default, skip_serializing_if = "is_false")]
    pub resample: bool,
    /// Whether committing a snapshot deletes what only resuming reads of the one before it
    /// ([`Manifest::compacted`]): only the last snapshot is resumed, and a mirror job's exact
    /// state is most of its store (the mirror scene at l = 2049, N = 128: 517 MB of snapshots
    /// kept whole, 160 MB compacted; jobs of format 5 and earlier lose their shooting maps only).
    /// Set when the job is created; absent in older manifests: false.
    #[serde(default, skip_serializing_if = "is_false")]
    pub compact: bool,
    /// Finished snapshots whose exact state was deleted once a later one was committed: they
    /// render as before (their radiance is kept) but do not resume. Strictly increasing,
    /// finished, and never the last finished snapshot.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub compacted: Vec<u32>,
}

fn is_false(b: &bool) -> bool {
    !*b
}

impl Manifest {
    /// A new manifest of a queued job.
    pub fn new(job_id: JobId, scene_hash: &str, parameters: serde_json::Value, encoding: Encoding) -> Manifest {
        let now = now();
        Manifest {
            format: MANIFEST_FORMAT,
            job_id,
            scene_hash: scene_hash.to_ascii_lowercase(),
            parameters,
            state: JobState::Queued,
            finished_iterations: Vec::new(),
            encoding,
            created: now,
            updated: now,
            resample: false,
            compact: false,
            compacted: Vec::new(),
        }
    }

    /// The last finished iteration, if any.
    pub fn last_finished(&self) -> Option<u32> {
        self.finished_iterations.last().copied()
    }

    /// Whether iteration `k`'s snapshot is complete.
    pub fn is_finished(&self, k: u32) -> bool {
        self.finished_iterations.binary_search(&k).is_ok()
    }

    /// Checks the invariants a stored manifest must satisfy.
    pub fn validate(&self) -> Result<(), String> {
        if self.format < OLDEST_READABLE_FORMAT {
            return Err(format!(
                "the job was made by an older version of vlf (store format {}, this version reads \
                 {OLDEST_READABLE_FORMAT} to {MANIFEST_FORMAT}): its scene and maps are laid out otherwise (format 1: texels per \
                 polygon; 2: no albedo textures); propagate the scene again",
                self.format
            ));
        }
        if self.format > MANIFEST_FORMAT {
            return Err(format!(
                "the job was made by a newer version of vlf (store format {}, this version reads \
                 {OLDEST_READABLE_FORMAT} to {MANIFEST_FORMAT}): upgrade vlf to read it",
                self.format
            ));
        }
        if self.scene_hash.is_empty() || !self.scene_hash.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!("scene hash `{}` is not hexadecimal", self.scene_hash));
        }
        if self.finished_iterations.windows(2).any(|w| w[0] >= w[1]) {
            return Err(format!(
                "finished iterations {:?} are not strictly increasing",
                self.finished_iterations
            ));
        }
        if self.compacted.windows(2).any(|w| w[0] >= w[1])
            || !self.compacted.iter().all(|k| self.is_finished(*k))
            || self.compacted.last().is_some_and(|k| Some(*k) == self.last_finished())
        {
            return Err(format!(
                "compacted snapshots {:?} are not strictly increasing finished snapshots before the \
                 last of {:?}",
                self.compacted, self.finished_iterations
            ));
        }
        if self.encoding == Encoding::Bytes {
            return Err("radiance encoding cannot be `bytes`".into());
        }
        if self.updated < self.created {
            return Err("updated before created".into());
        }
        Ok(())
    }

    /// The manifest as a blob.
    pub fn to_blob(&self) -> Result<Vec<u8>, String> {
        let json = serde_json::to_vec_pretty(self).map_err(|e| format!("cannot serialise: {e}"))?;
        blob::encode_bytes(BlobKind::Manifest, &json).map_err(|e| e.to_string())
    }

    /// Parses and validates a manifest blob's content (its decoded bytes).
    pub fn from_json(json: &[u8]) -> Result<Manifest, String> {
        let manifest: Manifest = serde_json::from_slice(json).map_err(|e| format!("bad JSON: {e}"))?;
        manifest.validate()?;
        Ok(manifest)
    }

    /// Sets `updated` to now (never before `created`).
    pub fn touch(&mut self) {
        self.updated = now().max(self.created);
    }
}

/// Unix seconds now (0 if the clock is before 1970).
fn now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_round_trip_and_validation() {
        let mut m = Manifest::new(
            JobId::generate(),
            "ABCDEF01",
            serde_json::json!({"directions": 513}),
            Encoding::F16,
        );
        m.state = JobState::Propagating { iteration: 3 };
        m.finished_iterations = vec![0, 1, 2];
        let json = serde_json::to_vec(&m).unwrap();
        assert_eq!(Manifest::from_json(&json).unwrap(), m);
        assert!(String::from_utf8_lossy(&json).contains(r#""state":{"kind":"propagating","iteration":3}"#));
        // Compacted snapshots: finished ones before the last, in order.
        m.compact = true;
        m.compacted = vec![0, 1];
        assert_eq!(Manifest::from_json(&serde_json::to_vec(&m).unwrap()).unwrap(), m);
        for bad in [vec![0, 1, 2], vec![1, 0], vec![1, 1], vec![5]] {
            m.compacted = bad;
            let e = Manifest::from_json(&serde_json::to_vec(&m).unwrap()).unwrap_err();
            assert!(e.contains("compacted"), "{e}");
        }
        m.compacted = Vec::new();
        m.finished_iterations = vec![0, 2, 2];
        assert!(Manifest::from_json(&serde_json::to_vec(&m).unwrap()).is_err());
        assert!(Manifest::from_json(b"{}").is_err());
        assert!(Manifest::from_json(b"\xff").is_err());
    }

    #[test]
    fn formats_from_the_oldest_readable_to_this_one_are_read_and_no_others() {
        let m = Manifest::new(JobId::generate(), "ab", serde_json::json!({}), Encoding::F16);
        let with = |format: u32| Manifest::from_json(&serde_json::to_vec(&Manifest { format, ..m.clone() }).unwrap());
        for format in OLDEST_READABLE_FORMAT..=MANIFEST_FORMAT {
            assert!(with(format).is_ok(), "format {format}");
        }
        let older = with(OLDEST_READABLE_FORMAT - 1).unwrap_err();
        assert!(
            older.contains("older version") && older.contains("propagate the scene again"),
            "{older}"
        );
        let newer = with(MANIFEST_FORMAT + 1).unwrap_err();
        assert!(newer.contains("newer version") && newer.contains("upgrade"), "{newer}");
    }
}
