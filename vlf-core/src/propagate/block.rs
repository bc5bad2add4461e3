//! What becomes of an aligned block of batches: a worker computes it on a
//! replica of the iteration's start ([`Propagation::compute_block`]), and a
//! propagation takes its output and mirror maps in
//! ([`Propagation::apply_batch`], [`Propagation::adopt_mirrors`]).
//!
//! Apart from [`super::work`] because a block is the distributed run's unit,
//! not the iteration's: [`super::work`] fixes what a batch is and computes
//! one, bit for bit the same wherever it runs; this is the bookkeeping around
//! many of them on a worker (the block's directions, its mirror maps gathered,
//! moved and sent on, what each batch cost) and on the coordinator (checking
//! and absorbing what comes back). The in-process loop needs none of it.

use super::Propagation;
use super::output::{Arrivals, BatchOutput, MirrorBlock};
use super::reduce::is_aligned_block;
use super::specular::{BatchArrivals, MirrorPower, Unheld};
use super::work::{IterationWork, MirrorIo, Pass, add_into};
use crate::scene::Rgb;
use rayon::prelude::*;
use std::borrow::Cow;
use std::ops::Range;

impl Propagation {
    /// Computes the aligned block `batches` of `pass` on a replica whose
    /// state is the iteration's start (as restored from its checkpoint:
    /// Current, and for [`Pass::Shoot`] with mirrors the block's directions'
    /// maps and, while arrivals are pending, those of the directions the
    /// block gathers from — [`super::Specular::source_batches`]): what a worker does
    /// for a lease. Returns the block's output for the coordinator (its node
    /// sum, [`super::reduce`], and its arrivals settled) and, when the pass uses them, its
    /// directions' mirror maps for the next snapshot.
    ///
    /// The block's total maps *move* into the returned [`MirrorBlock`] (each
    /// gets what its direction just sent, in place, as
    /// [`Propagation::step`] adds it): copying them would cost a worker a
    /// few megabytes per iteration that the in-process loop does not pay.
    /// This propagation then lacks them: computing the block again needs them
    /// restored first ([`Propagation::restore_totals_batch`]), else it is
    /// refused (its directions' maps are elsewhere, [`super::specular::Unheld`]);
    /// [`Propagation::adopt_mirrors`] puts the block's maps back for the next
    /// iteration. Nothing else changes, but for maps never written, whose zeros
    /// the block allocates as it reads them.
    pub fn compute_block(
        &mut self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
    ) -> crate::Result<(BatchOutput, Option<MirrorBlock>)> {
        self.compute_block_costed(work, pass, batches)
            .map(|(output, block, _)| (output, block))
    }

    /// [`Propagation::compute_block`], and what each of the block's batches cost to compute,
    /// in seconds (the gathering of the block's arrivals shared evenly among them): a
    /// coordinator splits the next pass among workers by what its batches cost, and a block's
    /// time spread evenly over its batches would blur the costs that differ most (the mirror
    /// scene's last batches cost twice its first).
    ///
    /// The costs add up to all the block took, in the proportions of the batches' shooting:
    /// what the block does besides shooting and gathering (the arrivals settled, the totals,
    /// the maps made ready) is its batches' work too. Left out, it was half of what the first
    /// mirror iteration of the mirror dragon took (1.25 s of 2.54 s), and a worker looked idle
    /// for it.
    pub fn compute_block_costed(
        &mut self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
    ) -> crate::Result<(BatchOutput, Option<MirrorBlock>, Vec<f64>)> {
        let started = std::time::Instant::now();
        let (output, block, costs) = self.compute_block_timed(work, pass, batches)?;
        Ok((output, block, spread(costs, started.elapsed().as_secs_f64())))
    }

    /// [`Propagation::compute_block_costed`] with the batches' costs of shooting and gathering
    /// alone.
    fn compute_block_timed(
        &mut self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
    ) -> crate::Result<(BatchOutput, Option<MirrorBlock>, Vec<f64>)> {
        let directions = self.block_directions(work, &batches)?;
        self.hold_block_maps(work, pass, directions.clone())?;
        let (output, sent, costs) = self.shoot_block(work, pass, batches, directions.clone())?;
        let Some((unshot, incident, power_in)) = sent else {
            return Ok((output, None, costs));
        };
        let first_lit = self.plan.first_mirror_iteration().unwrap_or(u32::MAX);
        let Some(spec) = self.specular.as_mut() else {
            unreachable!("shoot_block sends mirror maps only with mirrors");
        };
        // Total += what was just sent (as `Propagation::step` does), moved
        // out of the replica rather than copied.
        let total = directions
            .zip(&unshot)
            .map(|(d, u)| {
                let maps = &mut spec.maps[d];
                let mut t = std::mem::take(&mut maps.total);
                // The block holds it now: not zeros, whatever the direction's other maps are.
                maps.unheld = Unheld::Elsewhere;
                add_into(&mut t, u);
                t
            })
            .collect();
        // The exchange of what arrived waits for the next iteration's
        // shooting (`finish_iteration` decides alike); before light can reach
        // a mirror, the unshot maps stay as they were.
        let pending = work.index >= first_lit;
        let block = MirrorBlock {
            iterations: work.index + 1,
            batches: output.batches.clone(),
            pending,
            shooting: if pending { incident } else { unshot },
            total,
            power_in: if pending { power_in } else { Vec::new() },
        };
        Ok((output, Some(block), costs))
    }

    /// Makes sure the maps of `directions` that shooting them in `pass` reads are here, when
    /// the pass shoots mirror maps: their totals and, unless arrivals are pending, their unshot
    /// maps. Maps never written are zeros, allocated now (a replica of a new job's snapshot);
    /// one elsewhere that was not restored is an error, not zeros. The arrivals of the
    /// directions a block gathers from are checked as the gather reads them
    /// ([`super::Specular::gather`]): finding those directions again here cost a worker as much
    /// as planning its reads did (3 % of its CPU for the mirror dragon).
    fn hold_block_maps(&mut self, work: &IterationWork, pass: Pass, directions: Range<usize>) -> crate::Result<()> {
        let spec = match (self.specular.as_mut(), pass, work.uses_mirror_maps()) {
            (Some(spec), Pass::Shoot, true) => spec,
            _ => return Ok(()),
        };
        spec.hold_zeros(directions.clone());
        if let Some(d) = directions.clone().find(|&d| !spec.holds(d, &spec.maps[d].total)) {
            return Err(crate::Error::Parameter(format!(
                "the mirror totals of direction {d} are not restored (a block computed before took them)"
            )));
        }
        let unshot = |d: usize| spec.holds(d, &spec.maps[d].unshot);
        match directions.clone().find(|&d| spec.pending.is_none() && !unshot(d)) {
            Some(d) => Err(crate::Error::Parameter(format!(
                "the mirror unshot map of direction {d} is not restored"
            ))),
            None => Ok(()),
        }
    }

    /// The shooting of [`Propagation::compute_block`], which reads the state
    /// and changes nothing: the block's output and, when the pass shoots
    /// mirror maps, what each of its directions sent (gathered now from the
    /// pending arrivals — the exchange, see `specular::Pending` — or as
    /// restored), the incident maps it received and their `Φ_in`; and what each batch
    /// cost, in seconds.
    #[allow(clippy::type_complexity)]
    fn shoot_block(
        &self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
        directions: Range<usize>,
    ) -> crate::Result<(BatchOutput, Option<SentMaps>, Vec<f64>)> {
        let gathering = std::time::Instant::now();
        let spec = match (&self.specular, pass, work.uses_mirror_maps()) {
            (Some(spec), Pass::Shoot, true) => Some(spec),
            _ => None,
        };
        let (scene, dirs) = (&self.scene, &self.directions);
        let unshot: Option<Vec<Cow<[Rgb]>>> = spec
            .map(|spec| match &spec.pending {
                Some(pending) => {
                    spec.check_sources_known(directions.clone(), pending, &work.batching())?;
                    let read = |d: usize| spec.maps[d].incident.as_slice();
                    directions
                        .clone()
                        .into_par_iter()
                        .map(|i| spec.gather(scene, dirs, &read, pending, i).map(Cow::Owned))
                        .collect::<crate::Result<_>>()
                }
                None => Ok(directions
                    .clone()
                    .map(|d| Cow::Borrowed(&spec.maps[d].unshot[..]))
                    .collect()),
            })
            .transpose()?;
        // The block's incident maps, from zero.
        let mut incident: Option<Vec<Vec<Rgb>>> = unshot
            .as_ref()
            .map(|maps| maps.iter().map(|m| vec![[0.0; 3]; m.len()]).collect());
        let mut maps: Option<Vec<MirrorIo>> = unshot.as_ref().zip(incident.as_mut()).map(|(unshot, incident)| {
            unshot
                .iter()
                .zip(incident.iter_mut())
                .map(|(unshot, incident)| MirrorIo { unshot, incident })
                .collect()
        });
        let gathered = gathering.elapsed().as_secs_f64() / batches.len() as f64;
        // The block's stints claimed one at a time by the replica's threads, as
        // `Propagation::step` shoots a pass: the same leaves, folded into the block's node.
        let shooting = std::time::Instant::now();
        let (sum, seconds) = self.shoot_claimed(work, pass, batches.clone(), maps.as_deref_mut(), |_| {})?;
        // The threads shot at once, so the batches' thread seconds add up to more than the block
        // took: each batch is given its share of the block's time instead, which keeps their
        // proportions (what the coordinator cuts homes by) and adds up to the worker's time, as a
        // report's seconds must.
        let threads_time: f64 = seconds.iter().sum();
        let wall = shooting.elapsed().as_secs_f64();
        let share = if threads_time > 0.0 { wall / threads_time } else { 0.0 };
        let costs: Vec<f64> = seconds.iter().map(|cost| gathered + cost * share).collect();
        drop(maps);
        // What the block's directions brought to the mirrors, settled here batch by batch
        // (`specular::Pending`): their `Φ_in` stays with their maps.
        let power_in: Option<Vec<MirrorPower>> = spec.zip(incident.as_ref()).map(|(spec, incident)| {
            (directions.clone().into_par_iter().zip(incident))
                .map(|(d, m)| spec.power_in_of(dirs, d, m))
                .collect()
        });
        let arrivals = spec.zip(power_in.as_ref()).map(|(spec, power_in)| {
            Arrivals::Settled(spec.settle_batches(scene, &work.batching(), batches.clone(), power_in))
        });
        let output = BatchOutput {
            iteration: work.index,
            pass,
            batches: batches.start as u32..batches.end as u32,
            sum,
            arrivals,
        };
        // Gathered maps are the block's own; restored ones are copied (only
        // before light reaches a mirror: the iteration then keeps them).
        let sent = (unshot.zip(incident).zip(power_in)).map(|((unshot, incident), power_in)| {
            (unshot.into_iter().map(Cow::into_owned).collect(), incident, power_in)
        });
        Ok((output, sent, costs))
    }

    /// The batches of mirror maps that [`Propagation::compute_block`] reads
    /// for `batches` of `pass`, of the snapshot the iteration starts from
    /// (whose head this replica holds): the batches' shooting maps — while
    /// arrivals are pending, those of every direction the block gathers from
    /// ([`super::Specular::source_batches`]) — and the block's own totals. Nothing
    /// unless the pass shoots mirror maps.
    pub fn mirror_batches_read(
        &self,
        work: &IterationWork,
        pass: Pass,
        batches: Range<usize>,
    ) -> crate::Result<(Vec<usize>, Vec<usize>)> {
        let directions = self.block_directions(work, &batches)?;
        let spec = match (&self.specular, pass, work.uses_mirror_maps()) {
            (Some(spec), Pass::Shoot, true) => spec,
            _ => return Ok((Vec::new(), Vec::new())),
        };
        let shooting = match &spec.pending {
            Some(pending) => spec.source_batches(directions, pending, &work.batching()),
            None => batches.clone().collect(),
        };
        Ok((shooting, batches.collect()))
    }

    /// The directions of an aligned block of batches, or why it is not one.
    fn block_directions(&self, work: &IterationWork, batches: &Range<usize>) -> crate::Result<Range<usize>> {
        if !is_aligned_block(batches, work.batches()) {
            return Err(crate::Error::Parameter(format!(
                "batches {batches:?} are not an aligned block of the {} batches",
                work.batches()
            )));
        }
        Ok(work.batching().directions_of(batches.clone()))
    }

    /// Absorbs a worker's block output into `work`: what the coordinator
    /// does, in order. Outputs of another iteration, out of order, or whose
    /// arrivals do not fit are refused. Arrivals as earlier builds reported them (`Φ_in`) are
    /// settled here, as this build's workers settle theirs.
    pub fn apply_batch(&mut self, work: &mut IterationWork, out: BatchOutput) -> crate::Result<()> {
        if out.iteration != work.index {
            return Err(crate::Error::Parameter(format!(
                "batch output of iteration {} offered to iteration {}",
                out.iteration, work.index
            )));
        }
        let batches = out.batches.start as usize..out.batches.end as usize;
        let range = self.block_directions(work, &batches)?;
        let wants_arrivals = out.pass == Pass::Shoot && work.uses_mirror_maps();
        let arrivals = match (out.arrivals, wants_arrivals) {
            (None, false) => None,
            (Some(arrivals), true) => Some(self.settled_arrivals(work, &batches, range, arrivals)?),
            _ => {
                return Err(crate::Error::Decode(format!(
                    "batches {batches:?} of {:?}: mirror arrivals missing or unexpected",
                    out.pass
                )));
            }
        };
        work.absorb(out.pass, batches.clone(), out.sum)?;
        if let Some(parts) = arrivals {
            for (slot, part) in work.arrivals[batches].iter_mut().zip(parts) {
                *slot = Some(part);
            }
        }
        Ok(())
    }

    /// A block's arrivals, for its `batches` and their directions `range`, as checked and
    /// settled parts: one per batch, finite non-negative power, feeding batches that exist.
    fn settled_arrivals(
        &self,
        work: &IterationWork,
        batches: &Range<usize>,
        range: Range<usize>,
        arrivals: Arrivals,
    ) -> crate::Result<Vec<BatchArrivals>> {
        let Some(spec) = self.specular.as_ref() else {
            return Err(crate::Error::Decode(
                "mirror arrivals for a scene without mirrors".into(),
            ));
        };
        let count = work.batches();
        let misfit = |what: &str| {
            Err(crate::Error::Decode(format!(
                "mirror {what} of batches {batches:?} do not fit"
            )))
        };
        match arrivals {
            Arrivals::Settled(parts) => {
                let fits = |part: &BatchArrivals| {
                    let x = &part.exchange;
                    super::checkpoint::valid(&[x.incident, x.reflected])
                        && part.feeds.windows(2).all(|w| w[0] < w[1])
                        && part.feeds.last().is_none_or(|&t| (t as usize) < count)
                };
                if parts.len() != batches.len() || !parts.iter().all(fits) {
                    return misfit("arrivals");
                }
                Ok(parts)
            }
            Arrivals::Power(power) => {
                let mirrors = spec.mirrors.len() as u32;
                let fits = power.len() == range.len()
                    && (power.iter()).all(|p| super::checkpoint::mirror_power_fits(p, mirrors));
                if !fits {
                    return misfit("power");
                }
                Ok(spec.settle_batches(&self.scene, &work.batching(), batches.clone(), &power))
            }
        }
    }

    /// Takes a block's mirror maps into this propagation, as if it had
    /// stepped them itself: for a coordinator that holds every map (the
    /// service's coordinator does not: the maps go through the store from
    /// worker to worker), and for a worker's replica that computed them and
    /// now starts the next iteration (restore its head first). Call when the
    /// propagation holds the snapshot they belong to. Maps for another
    /// snapshot or of other sizes are refused; their values are trusted, as
    /// [`Propagation::compute_block`] made them from checked inputs (maps
    /// from bytes go through [`Propagation::restore_shooting_batch`]).
    pub fn adopt_mirrors(&mut self, block: MirrorBlock) -> crate::Result<()> {
        let batching = self.batching();
        let batches = block.batches.start as usize..block.batches.end as usize;
        if batches.is_empty() || batches.end > batching.count() {
            return Err(crate::Error::Parameter(format!("mirror maps of batches {batches:?}")));
        }
        let range = batching.directions_of(batches.clone());
        if block.iterations != self.iterations_done()
            || block.shooting.len() != range.len()
            || block.total.len() != range.len()
        {
            return Err(crate::Error::Parameter(format!(
                "mirror maps of batches {batches:?} after {} iterations offered after {}",
                block.iterations,
                self.iterations_done()
            )));
        }
        let Some(spec) = self.specular.as_mut() else {
            return Err(crate::Error::Parameter(
                "mirror maps for a scene without mirrors".into(),
            ));
        };
        let fits = |maps: &[Vec<Rgb>]| maps.iter().zip(range.clone()).all(|(a, d)| a.len() == spec.slots(d));
        let power_fits = !block.pending || block.power_in.len() == range.len();
        if !fits(&block.shooting) || !fits(&block.total) || !power_fits {
            return Err(crate::Error::Parameter(format!(
                "mirror maps of batches {batches:?} do not fit their directions"
            )));
        }
        {
            if spec.pending.is_some() != block.pending {
                return Err(crate::Error::Parameter(
                    "mirror maps of a block that did not exchange like the iteration".into(),
                ));
            }
            for ((m, shooting), total) in spec.maps[range.clone()].iter_mut().zip(block.shooting).zip(block.total) {
                m.total = total;
                if block.pending {
                    m.incident = shooting;
                } else {
                    m.unshot = shooting;
                }
            }
            // Arrivals: their `Φ_in`, as the block found it, for the gathers that read them.
            if block.pending {
                spec.know_power(range, block.power_in);
            }
        }
        Ok(())
    }
}

/// What a block's directions sent and received on their mirrors: their unshot maps (gathered or
/// as restored), their incident maps, and the `Φ_in` of those.
type SentMaps = (Vec<Vec<Rgb>>, Vec<Vec<Rgb>>, Vec<MirrorPower>);

/// `costs` scaled to add up to `seconds`, in their proportions (evenly where they are all zero).
fn spread(costs: Vec<f64>, seconds: f64) -> Vec<f64> {
    let sum: f64 = costs.iter().sum();
    let n = costs.len().max(1) as f64;
    costs
        .into_iter()
        .map(|c| if sum > 0.0 { c * seconds / sum } else { seconds / n })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::spread;

    #[test]
    fn costs_spread_over_a_block_keep_their_proportions_and_add_up_to_it() {
        let spread_out = spread(vec![1.0, 3.0, 0.0, 4.0], 2.0);
        assert_eq!(spread_out, vec![0.25, 0.75, 0.0, 1.0]);
        // Nothing timed: the block's time evenly.
        assert_eq!(spread(vec![0.0; 4], 2.0), vec![0.5; 4]);
        assert!(spread(Vec::new(), 2.0).is_empty());
    }
}
