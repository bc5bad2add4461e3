//! The survey as leased work: before a job is set up, workers learn what each block of its
//! directions adds to the survey ([`vlf_core::propagate::SurveyPart`]) and write it here; the
//! coordinator reads the parts in order, adds them up ([`vlf_core::propagate::SurveyParts`]) and
//! sets the job up with the sum instead of walking every subfield's rays itself.
//!
//! The parts are leased as the pass [`Pass::Survey`] of "the iteration after snapshot 0", cut
//! into the job's batches like any pass, and stored as that iteration's work
//! (`jobs/J/work/00000/survey/SSSSS-EEEEE.blob`, keyed by batches): so a coordinator that
//! restarts mid-survey finds the parts already learnt by listing the pass
//! ([`FieldJob::stored_blocks`]), and the parts go with the rest of that iteration's work once
//! snapshot 1 is committed. Like every block output, a part is a pure function of the job and
//! the block, written create-only.

use crate::blob::{self, BlobKind};
use crate::error::StoreError;
use crate::field::FieldJob;
use crate::layout;
use crate::store::{Put, PutOutcome};
use rayon::prelude::*;
use std::ops::Range;
use vlf_core::propagate::{Pass, SurveyPart};

use super::pass_name;

impl FieldJob {
    /// The key of the survey part of batches `batches`.
    fn survey_part_key(&self, batches: &Range<usize>) -> Result<String, StoreError> {
        layout::work_block(
            self.id(),
            0,
            &pass_name(Pass::Survey),
            batches.start as u32,
            batches.end as u32,
        )
    }

    /// The blob of `part`, the survey of the job's batches `batches`, encoded for
    /// [`crate::Store::put_all`] (create-only). A part of other directions than the batches
    /// hold is refused.
    pub fn survey_part_put(&self, batches: Range<usize>, part: &SurveyPart) -> Result<Put, StoreError> {
        let key = self.survey_part_key(&batches)?;
        let directions = self.options().batching().directions_of(batches.clone());
        let (a, b) = part.directions;
        if (a as usize..b as usize) != directions {
            return Err(self.decode_error(
                &key,
                format!("a part of directions {a}..{b} is not that of batches {batches:?} ({directions:?})"),
            ));
        }
        self.work_put(key, || blob::encode_bytes(BlobKind::SurveyPart, &part.to_bytes()))
    }

    /// Writes [`FieldJob::survey_part_put`]'s blob.
    pub fn put_survey_part(&self, batches: Range<usize>, part: &SurveyPart) -> Result<PutOutcome, StoreError> {
        let put = self.survey_part_put(batches, part)?;
        self.job().store().put_new(&put.key, put.bytes)
    }

    /// The survey parts of the blocks `blocks` of the job's batches, their requests overlapping,
    /// decoded in parallel, in the order of `blocks`. A part that cannot be read, or holds other
    /// directions than its key says, is an error that names its key.
    pub fn survey_parts(&self, blocks: &[Range<usize>]) -> Result<Vec<SurveyPart>, StoreError> {
        let keys = (blocks.iter())
            .map(|b| self.survey_part_key(b))
            .collect::<Result<Vec<_>, _>>()?;
        let blobs = self.job().store().get_all(&keys)?;
        let batching = self.options().batching();
        (keys.par_iter().zip(&blobs).zip(blocks))
            .map(|((key, blob), batches)| {
                let bytes = (self.job().store().as_async())
                    .decode_with(key, blob, |b| blob::decode_bytes(b, BlobKind::SurveyPart))?;
                let part = SurveyPart::from_bytes(&bytes).map_err(|e| self.decode_error(key, e.to_string()))?;
                let (a, b) = part.directions;
                let expected = batching.directions_of(batches.clone());
                if (a as usize..b as usize) != expected {
                    return Err(self.decode_error(
                        key,
                        format!("holds directions {a}..{b}, where its batches are directions {expected:?}"),
                    ));
                }
                Ok(part)
            })
            .collect()
    }
}
