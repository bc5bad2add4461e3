//! The discrete areas `T_t = Σ_ω Δω · n_t(ω)` (see the module above: what every texel's
//! emission and radiance are normalised by), summed exactly so that any split of the
//! directions gives the same bits.
//!
//! **Why exact.** A sum of `f64` terms has bits that depend on the order of its additions,
//! which then has to be fixed: a buffer per direction, cleared, filled and added in direction
//! order a few directions at a time, with the threads meeting after every few. Here each
//! weight `Δω` is a whole number of units of [`AREA_UNIT`] = 2⁻⁸⁰ (a direction set's weights
//! are at least 10⁻⁴, so none has a bit below that), and a texel's area is kept as an `i128`
//! count of units while it is summed: integer additions, exact in any order and grouping, the
//! result the true sum rounded once to `f64`. So the threads each add the directions they take
//! into an accumulator of their own, never waiting for one another, and a part of the
//! directions summed anywhere — a worker of the distributed service, another machine — adds
//! to the others' parts with the same bits ([`AreaUnits`]).

use super::shoot;
use crate::directions::DirectionSet;
use crate::psf::Subfield;
use rayon::prelude::*;
use std::ops::Range;

/// The unit of the exact sums: 2⁻⁸⁰.
const AREA_UNIT: f64 = 1.0 / (1u128 << 80) as f64;

/// Discrete areas of some of a direction set's directions, in whole [`AREA_UNIT`]s: parts
/// computed anywhere add up exactly ([`AreaUnits::add`]) to what all the directions give.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub(crate) struct AreaUnits(Vec<i128>);

impl AreaUnits {
    /// The areas of `directions[range]`, one accumulator per piece of the range that a thread
    /// takes (a few per thread), each direction's subfield from `subfield(d)` (stored or built on
    /// the fly).
    pub(crate) fn of<F, S>(
        geometry: shoot::Geometry,
        directions: &DirectionSet,
        range: Range<usize>,
        subfield: F,
    ) -> AreaUnits
    where
        F: Fn(usize) -> S + Sync,
        S: std::ops::Deref<Target = Subfield>,
    {
        let texels = geometry.atlas.texels;
        let piece = range.len() / (4 * rayon::current_num_threads()).max(1);
        let units = (range.into_par_iter())
            .with_min_len(piece.max(1))
            .fold(
                || (vec![0i128; texels], shoot::Scratch::default()),
                |(mut acc, mut scratch), d| {
                    let unit = units_of(directions.get(d).weight);
                    shoot::count(geometry, &subfield(d), &mut scratch, |t| acc[t] += unit);
                    (acc, scratch)
                },
            )
            .map(|(acc, _)| AreaUnits(acc))
            .reduce_with(|mut a, b| {
                a.add(&b);
                a
            });
        units.unwrap_or_else(|| AreaUnits(vec![0; texels]))
    }

    /// Adds another part's areas (of other directions, over the same texels).
    pub(crate) fn add(&mut self, other: &AreaUnits) {
        debug_assert_eq!(self.0.len(), other.0.len(), "parts over other texels");
        self.0.iter_mut().zip(&other.0).for_each(|(a, b)| *a += b);
    }

    /// How many texels it covers.
    pub(crate) fn texels(&self) -> usize {
        self.0.len()
    }

    /// The areas, each the exact sum rounded once to `f64`.
    pub(crate) fn areas(&self) -> Vec<f64> {
        self.0.iter().map(|&u| u as f64 * AREA_UNIT).collect()
    }
}

/// `T_t` for every texel, over every direction of `directions`.
pub(crate) fn discrete_areas<F, S>(geometry: shoot::Geometry, directions: &DirectionSet, subfield: F) -> Vec<f64>
where
    F: Fn(usize) -> S + Sync,
    S: std::ops::Deref<Target = Subfield>,
{
    AreaUnits::of(geometry, directions, 0..directions.len(), subfield).areas()
}

/// `weight` as a whole number of [`AREA_UNIT`]s: exact for any weight of at least 2⁻²⁸ (its
/// last bit is then at or above 2⁻⁸⁰), which every direction set's weights are (tested); a
/// weight is at most 2π, 2⁸³ units, so an `i128` holds more than 2⁴³ crossings of a texel.
fn units_of(weight: f64) -> i128 {
    let units = weight / AREA_UNIT;
    debug_assert!(units.fract() == 0.0, "weight {weight} is not a whole number of units");
    units as i128
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::propagate::{Options, Propagation, Stop};
    use crate::psf::GridSize;
    use crate::scene::{ImportOptions, load_obj};

    #[test]
    fn every_direction_sets_weights_are_whole_units() {
        for l in [9, 33, 129, 513, 2049, 8193] {
            let set = DirectionSet::new(l).unwrap();
            for d in 0..set.len() {
                let w = set.get(d).weight;
                assert!(w >= 2f64.powi(-28), "l = {l}, direction {d}: weight {w}");
                assert_eq!(units_of(w) as f64 * AREA_UNIT, w, "l = {l}, direction {d}");
            }
        }
    }

    #[test]
    fn areas_have_the_same_bits_however_the_directions_are_split() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
        let options = Options {
            directions: 513,
            grid: GridSize::new(32, 8).unwrap(),
            stop: Stop::Iterations(1),
            ..Options::default()
        };
        let p = Propagation::new(scene, options).unwrap();
        let geometry = shoot::Geometry {
            scene: &p.scene,
            atlas: &p.atlas,
            stacking: &p.stacking,
        };
        let all = 0..p.directions.len();
        let whole = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| AreaUnits::of(geometry, &p.directions, all.clone(), |d| p.subfields.get(d)))
        };
        let one = whole(1);
        assert_eq!(one.areas(), p.projected_area, "the propagation's own areas");
        for threads in [2, 3, 7] {
            assert!(whole(threads) == one, "{threads} threads");
        }
        // Parts summed separately, as workers would, added in any order.
        let cuts = [0, 7, 200, 201, 513];
        let parts: Vec<AreaUnits> = (cuts.windows(2))
            .map(|c| AreaUnits::of(geometry, &p.directions, c[0]..c[1], |d| p.subfields.get(d)))
            .collect();
        for order in [[0, 1, 2, 3], [3, 1, 0, 2]] {
            let mut sum = parts[order[0]].clone();
            for &i in &order[1..] {
                sum.add(&parts[i]);
            }
            assert!(sum == one, "parts added in the order {order:?}");
        }
        // The same quantity as the plain sum in direction order, in `f64`, to its rounding.
        let mut plain = vec![0.0f64; p.atlas.texels];
        let mut scratch = shoot::Scratch::default();
        for d in all {
            let w = p.directions.get(d).weight;
            shoot::count(geometry, &p.subfields.get(d), &mut scratch, |t| plain[t] += w);
        }
        let areas = one.areas();
        let worst = (areas.iter().zip(&plain))
            .map(|(a, b)| (a - b).abs() / a.max(1e-300))
            .fold(0.0, f64::max);
        assert!(worst < 1e-12, "{worst:e}");
        assert!(areas.iter().filter(|&&a| a > 0.0).count() > p.atlas.texels / 2);
    }
}
