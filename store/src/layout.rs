//! The keys of a job. Every key of job `J` starts with `jobs/J/`, so listing a job, an iteration
//! or a direction is one prefix listing; numbers are zero-padded so that lexical order (the order
//! of every listing) is numeric order.
//!
//! | key | blob kind | content |
//! |---|---|---|
//! | `jobs/J/manifest.blob` | Manifest | JSON [`crate::Manifest`]; written last, the commit point |
//! | `jobs/J/scene.blob` | Scene | the normalised scene (caller's bytes) |
//! | `jobs/J/survey.blob` | Survey | what setting the job up learnt over all its directions (caller's bytes), so that nobody learns it again |
//! | `jobs/J/mirrors.blob` | MirrorGeometry | with mirrors: every direction's mirror view and the reflection routes, computed when the job was set up (caller's bytes), so that no worker computes them again |
//! | `jobs/J/iters/KKKKK/state.blob` | Snapshot | the head of what shooting the iteration after K reads (or, in jobs written before the split, all that resuming needs) |
//! | `jobs/J/iters/KKKKK/shooting/BBBBB.blob` | Snapshot | what batch B of the directions shoots next: the mirror arrivals to gather (or unshot maps) |
//! | `jobs/J/iters/KKKKK/mirror-totals/BBBBB.blob` | Snapshot | the total mirror maps of batch B of the directions, exact (`f64`): what resuming reads (deleted once K is compacted) |
//! | `jobs/J/iters/KKKKK/mirror-radiance/BBBBB.blob` | BatchRadiance | the same maps as radiance in the job's encoding: what renders read (format 6 on) |
//! | `jobs/J/iters/KKKKK/totals.blob` | Snapshot | the diffuse totals (absent in jobs written before the split; with the mirror totals in jobs written before they were stored by batch) |
//! | `jobs/J/iters/KKKKK/unshot/BBBBB.blob` | Snapshot | in jobs written before the mirror totals were stored by batch: the unshot mirror maps of batch B |
//! | `S/summary.blob` | Summary | JSON: iterations done, unshot power, statistics |
//! | `jobs/J/work/KKKKK/PASS/BBBBB.blob` | BatchOutput | a worker's output for one batch of the iteration after snapshot K (deleted once K+1 is committed; a late one when the job is finished) |
//! | `jobs/J/work/00000/survey/SSSSS-EEEEE.blob` | SurveyPart | what batches S..E of the directions add to the survey, learnt by a worker before the job is set up (deleted with iteration 1's work) |
//! | `S/diffuse/CCCCCCC.blob` | DiffuseMaps | outgoing radiance of the charts of diffuse chunk C (`vlf_core::parts`) |
//! | `S/mirrors/SSSSSSS.blob` | MirrorMaps | directional maps of mirror S |
//! | `S/dirs/DDDDD/tile-TTTT-TTTT.blob` | TileRadiance | tile (s, t) of direction D's parallel subfield |
//!
//! where the stage prefix `S` is `jobs/J/iters/KKKKK` for the snapshot after K iterations (enough to
//! render it) or `jobs/J/field` for the final field. Prefixes: a job `jobs/J/`, an iteration
//! `jobs/J/iters/KKKKK/`, a direction `S/dirs/DDDDD/`.
//!
//! Ranges (the padding): iterations and directions < 100 000, tile indices < 10 000, surfaces
//! < 10 000 000; beyond them a key function returns [`StoreError::Layout`] rather than a key
//! that would sort out of order.

use crate::error::StoreError;
use crate::id::JobId;

/// The prefix of all jobs.
pub const JOBS_PREFIX: &str = "jobs/";

const MAX_ITERATION: u32 = 99_999;
const MAX_DIRECTION: u32 = 99_999;
const MAX_TILE: u32 = 9_999;
const MAX_SURFACE: u32 = 9_999_999;

/// Which radiance a key refers to: the snapshot of an iteration, or the final field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stage {
    /// The snapshot after `k` iterations (`0`: before the first, emission only).
    Iteration(u32),
    /// The final field.
    Field,
}

/// `jobs/J/`: everything of a job.
pub fn job_prefix(job: &JobId) -> String {
    format!("{JOBS_PREFIX}{job}/")
}

/// `jobs/J/manifest.blob`.
pub fn manifest(job: &JobId) -> String {
    format!("{JOBS_PREFIX}{job}/manifest.blob")
}

/// `jobs/J/scene.blob`.
pub fn scene(job: &JobId) -> String {
    format!("{JOBS_PREFIX}{job}/scene.blob")
}

/// `jobs/J/survey.blob`: what setting the job up learns over all its directions
/// (`vlf_core::propagate::Survey`), written with the job.
pub fn survey(job: &JobId) -> String {
    format!("{JOBS_PREFIX}{job}/survey.blob")
}

/// `jobs/J/mirrors.blob`: every direction's mirror view and the reflection routes
/// (`vlf_core::propagate::MirrorGeometry`), written with the job when it has mirrors.
pub fn mirror_geometry(job: &JobId) -> String {
    format!("{JOBS_PREFIX}{job}/mirrors.blob")
}

/// `jobs/J/iters/KKKKK/` or `jobs/J/field/`: everything of a stage.
pub fn stage_prefix(job: &JobId, stage: Stage) -> Result<String, StoreError> {
    match stage {
        Stage::Iteration(k) => Ok(format!(
            "{JOBS_PREFIX}{job}/iters/{:05}/",
            check("iteration", k, MAX_ITERATION)?
        )),
        Stage::Field => Ok(format!("{JOBS_PREFIX}{job}/field/")),
    }
}

/// `jobs/J/iters/KKKKK/state.blob`: the resume state after `k` iterations.
pub fn state(job: &JobId, k: u32) -> Result<String, StoreError> {
    Ok(format!("{}state.blob", stage_prefix(job, Stage::Iteration(k))?))
}

/// Which mirror maps of a batch of directions a part of a snapshot holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MapPart {
    /// What the batch's directions shoot next (`shooting/`).
    Shooting,
    /// Their total maps (`mirror-totals/`), exact (`f64`): what resuming reads.
    Totals,
    /// Their total maps as radiance in the job's encoding (`mirror-radiance/`, a
    /// [`crate::BlobKind::BatchRadiance`] values blob): what renders read. A snapshot that is
    /// compacted keeps these and loses its exact totals.
    Radiance,
    /// Their unshot maps, in jobs written before the mirror totals were stored by batch
    /// (`unshot/`).
    Unshot,
}

/// `jobs/J/iters/KKKKK/{shooting,mirror-totals,mirror-radiance,unshot}/BBBBB.blob`: the mirror maps `part` of
/// batch `batch` of the directions in the resume state after `k` iterations.
pub fn map_part(job: &JobId, k: u32, part: MapPart, batch: u32) -> Result<String, StoreError> {
    Ok(format!(
        "{}{:05}.blob",
        map_parts(job, k, part)?,
        check("batch", batch, MAX_DIRECTION)?
    ))
}

/// `jobs/J/iters/KKKKK/{shooting,mirror-totals,mirror-radiance,unshot}/`: where the [`map_part`]s `part` of the
/// resume state after `k` iterations are.
pub fn map_parts(job: &JobId, k: u32, part: MapPart) -> Result<String, StoreError> {
    let folder = match part {
        MapPart::Shooting => "shooting",
        MapPart::Totals => "mirror-totals",
        MapPart::Radiance => "mirror-radiance",
        MapPart::Unshot => "unshot",
    };
    Ok(format!("{}{folder}/", stage_prefix(job, Stage::Iteration(k))?))
}

/// The batch a [`map_part`] key names, if `key` is one under `prefix` (its [`map_parts`]).
pub fn parse_map_part(prefix: &str, key: &str) -> Option<u32> {
    let name = key.strip_prefix(prefix)?.strip_suffix(".blob")?;
    (name.len() == 5 && name.bytes().all(|b| b.is_ascii_digit())).then(|| name.parse().ok())?
}

/// `jobs/J/iters/KKKKK/totals.blob`: the totals half of the resume state after `k` iterations.
pub fn totals(job: &JobId, k: u32) -> Result<String, StoreError> {
    Ok(format!("{}totals.blob", stage_prefix(job, Stage::Iteration(k))?))
}

/// `jobs/J/work/`: everything the workers write for the coordinator to absorb (the survey's
/// parts, every iteration's batch outputs), none of it needed once the job is finished.
pub fn work_root(job: &JobId) -> String {
    format!("{JOBS_PREFIX}{job}/work/")
}

/// `jobs/J/work/KKKKK/`: the batch outputs of the iteration that starts from snapshot `k`.
pub fn work_prefix(job: &JobId, k: u32) -> Result<String, StoreError> {
    let k = check("iteration", k, MAX_ITERATION)?;
    Ok(format!("{}{k:05}/", work_root(job)))
}

/// `jobs/J/work/KKKKK/PASS/`: the outputs of pass `pass` (a name such as `shoot` or `areas-00`)
/// of the iteration that starts from snapshot `k`.
pub fn work_pass(job: &JobId, k: u32, pass: &str) -> Result<String, StoreError> {
    if pass.is_empty() || !pass.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-') {
        return Err(StoreError::Layout(format!("pass name `{pass}` is not a key segment")));
    }
    Ok(format!("{}{pass}/", work_prefix(job, k)?))
}

/// `jobs/J/work/KKKKK/PASS/SSSSS-EEEEE.blob`: the output of batches `start..end` of pass `pass`
/// of the iteration that starts from snapshot `k`.
pub fn work_block(job: &JobId, k: u32, pass: &str, start: u32, end: u32) -> Result<String, StoreError> {
    let start = check("batch", start, MAX_DIRECTION)?;
    let end = check("batch", end, MAX_DIRECTION)?;
    if end <= start {
        return Err(StoreError::Layout(format!("empty batch range {start}..{end}")));
    }
    Ok(format!("{}{start:05}-{end:05}.blob", work_pass(job, k, pass)?))
}

/// The batch range a [`work_block`] key names, if `key` is one under `prefix` (its pass's
/// [`work_pass`]).
pub fn parse_work_block(prefix: &str, key: &str) -> Option<std::ops::Range<u32>> {
    let name = key.strip_prefix(prefix)?.strip_suffix(".blob")?;
    let (start, end) = name.split_once('-')?;
    let digits = |s: &str| s.len() == 5 && s.bytes().all(|b| b.is_ascii_digit());
    if !digits(start) || !digits(end) {
        return None;
    }
    let (start, end) = (start.parse().ok()?, end.parse().ok()?);
    (start < end).then_some(start..end)
}

/// `S/summary.blob`: what a stage is (iterations, unshot power, statistics).
pub fn summary(job: &JobId, stage: Stage) -> Result<String, StoreError> {
    Ok(format!("{}summary.blob", stage_prefix(job, stage)?))
}

/// `S/diffuse/CCCCCCC.blob`: the diffuse maps of chunk `chunk` (a run of charts).
pub fn diffuse(job: &JobId, stage: Stage, chunk: u32) -> Result<String, StoreError> {
    let chunk = check("chunk", chunk, MAX_SURFACE)?;
    Ok(format!("{}diffuse/{chunk:07}.blob", stage_prefix(job, stage)?))
}

/// `S/mirrors/SSSSSSS.blob`: the directional maps of mirror `surface`.
pub fn mirror(job: &JobId, stage: Stage, surface: u32) -> Result<String, StoreError> {
    let surface = check("surface", surface, MAX_SURFACE)?;
    Ok(format!("{}mirrors/{surface:07}.blob", stage_prefix(job, stage)?))
}

/// `S/dirs/DDDDD/`: every tile of direction `dir`.
pub fn direction_prefix(job: &JobId, stage: Stage, dir: u32) -> Result<String, StoreError> {
    let dir = check("direction", dir, MAX_DIRECTION)?;
    Ok(format!("{}dirs/{dir:05}/", stage_prefix(job, stage)?))
}

/// `S/dirs/DDDDD.blob`: the radiance of every mirror slot of direction `dir`, tile after tile
/// (a final field's mirror radiance, as this build writes it).
pub fn direction(job: &JobId, stage: Stage, dir: u32) -> Result<String, StoreError> {
    let dir = check("direction", dir, MAX_DIRECTION)?;
    Ok(format!("{}dirs/{dir:05}.blob", stage_prefix(job, stage)?))
}

/// `S/dirs/DDDDD/tile-SSSS-TTTT.blob`: tile (`s`, `t`) of direction `dir`, as earlier builds
/// wrote a final field's mirror radiance (one blob per tile).
pub fn tile(job: &JobId, stage: Stage, dir: u32, s: u32, t: u32) -> Result<String, StoreError> {
    let (s, t) = (check("tile index", s, MAX_TILE)?, check("tile index", t, MAX_TILE)?);
    Ok(format!("{}tile-{s:04}-{t:04}.blob", direction_prefix(job, stage, dir)?))
}

/// The direction of a [`direction`] key (`…/dirs/DDDDD.blob`), if `key` is one.
pub fn parse_direction(key: &str) -> Option<u32> {
    let mut segments = key.rsplit('/');
    let name = segments.next()?.strip_suffix(".blob")?;
    let digits = name.len() == 5 && name.bytes().all(|b| b.is_ascii_digit());
    (digits && segments.next() == Some("dirs")).then(|| name.parse().ok())?
}

/// The tile indices `(s, t)` of a tile key (as listed under a direction prefix).
pub fn parse_tile(key: &str) -> Option<(u32, u32)> {
    let name = key.rsplit('/').next()?.strip_prefix("tile-")?.strip_suffix(".blob")?;
    let (s, t) = name.split_once('-')?;
    Some((s.parse().ok()?, t.parse().ok()?))
}

fn check(what: &str, value: u32, max: u32) -> Result<u32, StoreError> {
    if value <= max {
        Ok(value)
    } else {
        Err(StoreError::Layout(format!(
            "{what} {value} exceeds {max}, the largest the key layout holds"
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_and_order() {
        let job = JobId::parse("j1").unwrap();
        assert_eq!(manifest(&job), "jobs/j1/manifest.blob");
        assert_eq!(state(&job, 7).unwrap(), "jobs/j1/iters/00007/state.blob");
        assert_eq!(
            diffuse(&job, Stage::Field, 12).unwrap(),
            "jobs/j1/field/diffuse/0000012.blob"
        );
        let t = tile(&job, Stage::Iteration(3), 512, 2, 10).unwrap();
        assert_eq!(t, "jobs/j1/iters/00003/dirs/00512/tile-0002-0010.blob");
        assert!(t.starts_with(&direction_prefix(&job, Stage::Iteration(3), 512).unwrap()));
        assert_eq!(parse_tile(&t), Some((2, 10)));
        let d = direction(&job, Stage::Field, 512).unwrap();
        assert_eq!(d, "jobs/j1/field/dirs/00512.blob");
        assert_eq!(parse_tile(&d), None);
        assert_eq!(parse_direction(&d), Some(512));
        assert_eq!(parse_direction(&t), None);
        assert_eq!(parse_direction("jobs/j1/field/diffuse/0000012.blob"), None);
        assert!(!d.starts_with(&direction_prefix(&job, Stage::Field, 512).unwrap()));
        assert!(state(&job, 9).unwrap() < state(&job, 10).unwrap());
        assert!(tile(&job, Stage::Field, 0, 0, 9).unwrap() < tile(&job, Stage::Field, 0, 0, 10).unwrap());
        assert!(matches!(state(&job, 100_000), Err(StoreError::Layout(_))));
        assert!(matches!(
            tile(&job, Stage::Field, 0, 10_000, 0),
            Err(StoreError::Layout(_))
        ));
    }
}
