//! The survey: what setting a propagation up learns by passing over every direction's subfield,
//! kept so that nobody else has to pass over them again.
//!
//! Two things of a field's set-up depend on every direction at once:
//!
//! - the **discrete areas** `T_t = Σ_ω Δω · n_t(ω)` of the true directions (module docs of
//!   [`super`]): the rays of every subfield that land on each texel, which scale emission and
//!   turn power into radiance;
//! - **which mirrors light reaches**, and from which iteration on ([`super::Plan`]): a search
//!   over the pairs of surfaces that face each other along some ray of some subfield.
//!
//! Learning them walks every ray of every subfield: about three quarters of one thread's set-up
//! of the Cornell box and of the mirror scene at l = 2049, N = 128. So it is learnt once per job
//! and stored with it; a worker that opens the job reads it ([`super::Propagation::with_survey`])
//! and builds only the subfields it shoots, as it shoots them (with mirrors too: their views
//! rasterise the mirror planes alone, [`super::specular::MirrorView`]). The survey is a pure function of the scene and
//! the options, so reading it rather than learning it again changes no bit of the field.
//!
//! It can be learnt whole ([`super::Propagation::survey`] of a propagation set up the plain
//! way) or in parts: each range of directions gives a [`SurveyPart`] (learnt by a
//! [`Surveyor`], which builds the texel atlas once for several parts), and the parts add up,
//! exactly and in any split, to the whole ([`SurveyParts`], [`Survey::from_parts`]). The
//! distributed service leases the parts to its workers ([`super::Pass::Survey`]), so the walk
//! that grows with the field is spread over them rather than done by the coordinator alone.
//! With mirrors a part also keeps its directions' subfields restricted to the mirror planes
//! ([`SurveyPart::mirror_planes`]), which the coordinator cuts the mirror views from
//! ([`super::Propagation::with_survey_and_planes`]) rather than rasterising the planes again.

use super::Options;
use super::areas::AreaUnits;
use super::checkpoint::{encode, read_head, version_of};
use super::plan::{self, Plan};
use super::shoot::{Geometry, Stacking};
use crate::directions::DirectionSet;
use crate::maps::TexelAtlas;
use crate::psf::{Footprints, GridSize, Subfield, Subfields};
use crate::scene::Scene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::sync::Arc;

/// The version [`SurveyPart::to_bytes`] writes first. Version 2 carries the mirror planes
/// ([`SurveyPart::mirror_planes`]); a stored part of version 1 cannot be read, and the
/// coordinator learns the survey from its block on itself, as for any part it cannot read.
const PART_VERSION: u32 = 2;

/// The version [`Survey::to_bytes`] writes first. Version 2 records what the survey was learnt
/// for ([`Surveyed`]); version 1 did not.
const SURVEY_VERSION: u32 = 2;
/// The layout before, which [`Survey::read_stored`] passes over.
const UNKEYED_VERSION: u32 = 1;

/// What set-up learns over all directions: see the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Survey {
    version: u32,
    /// What it was learnt for.
    pub of: Surveyed,
    /// Discrete projected area `T_t` of every texel, in cell-area units.
    pub projected_area: Vec<f64>,
    /// Mirrors light can reach, as (surface, first iteration it arrives), by surface
    /// ([`super::Plan::lit_mirrors`]).
    pub lit_mirrors: Vec<(u32, u32)>,
}

/// What a survey was learnt for: the scene, by its content hash, and the options the field's
/// geometry depends on. A survey is only ever used for the same — another number of directions
/// with the same texels would otherwise pass for this one, with the wrong areas.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Surveyed {
    pub scene_hash: String,
    pub directions: usize,
    pub grid: GridSize,
    pub texel_cells: f64,
}

impl Surveyed {
    pub fn of(scene: &Scene, options: &Options) -> Surveyed {
        Surveyed {
            scene_hash: scene.content_hash(),
            directions: options.directions,
            grid: options.grid,
            texel_cells: options.texel_cells,
        }
    }
}

impl Survey {
    pub fn new(of: Surveyed, projected_area: Vec<f64>, lit_mirrors: Vec<(u32, u32)>) -> Survey {
        Survey {
            version: SURVEY_VERSION,
            of,
            projected_area,
            lit_mirrors,
        }
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads a survey; what cannot be one (truncated, another version, trailing bytes) is a
    /// [`crate::Error::Decode`]. Whether it fits a scene is [`Survey::check`]'s to say.
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<Survey> {
        read_versioned(bytes, SURVEY_VERSION, "survey")
    }

    /// Reads a survey stored with a job: `None` for one of the earlier layout (version 1), which
    /// does not say what it was learnt for — whoever opens the job learns it again rather than
    /// trust it. Anything else that is not a survey is an error, as in [`Survey::from_bytes`].
    pub fn read_stored(bytes: &[u8]) -> crate::Result<Option<Survey>> {
        match version_of(bytes) {
            Some(UNKEYED_VERSION) => Ok(None),
            _ => Survey::from_bytes(bytes).map(Some),
        }
    }

    /// Whether this survey can be that of `scene` with `options` (and `texels` texels): learnt
    /// for them ([`Surveyed`]), one finite, non-negative area per texel, lit mirrors that are
    /// mirror surfaces of the scene, each once, in order, first lit within as many iterations
    /// as the scene has surfaces (the plan's search goes one surface further an iteration). A
    /// survey of another job, or garbage, is refused here rather than propagated.
    pub fn check(&self, scene: &Scene, options: &Options, texels: usize) -> crate::Result<()> {
        let misfit = |m: String| Err(crate::Error::Decode(format!("the survey {m}")));
        let here = Surveyed::of(scene, options);
        if self.of != here {
            let what = match &self.of {
                of if of.scene_hash != here.scene_hash => "another scene".to_string(),
                of => format!(
                    "l = {}, {:?}, texels of {} cells (this job: l = {}, {:?}, {} cells)",
                    of.directions, of.grid, of.texel_cells, here.directions, here.grid, here.texel_cells
                ),
            };
            return misfit(format!("was learnt for {what}"));
        }
        let areas = &self.projected_area;
        if areas.len() != texels {
            return misfit(format!("has {} areas for the scene's {texels} texels", areas.len()));
        }
        if let Some(t) = areas.iter().position(|a| !(a.is_finite() && *a >= 0.0)) {
            return misfit(format!(
                "has area {} at texel {t}: not finite and non-negative",
                areas[t]
            ));
        }
        let surfaces = scene.surfaces.len();
        for (i, &(m, k)) in self.lit_mirrors.iter().enumerate() {
            if m as usize >= surfaces || !scene.material(m as usize).is_mirror() {
                return misfit(format!("lights surface {m}, which is not a mirror of the scene"));
            }
            if k as usize >= surfaces {
                return misfit(format!(
                    "lights mirror {m} first in iteration {k}, past any path of the scene's {surfaces} surfaces"
                ));
            }
            if i > 0 && self.lit_mirrors[i - 1].0 >= m {
                return misfit("lists its lit mirrors out of order or twice".into());
            }
        }
        Ok(())
    }
}

/// What the directions `directions` contribute to a survey: their discrete areas, summed exactly
/// ([`AreaUnits`]), and the pairs of surfaces that face each other along some ray of theirs
/// (none without mirrors). Learnt anywhere — a worker, over the directions it holds — and put
/// together by [`Survey::from_parts`] with the same bits as a survey learnt whole, however the
/// directions were split and in whatever order the parts arrive: integer sums and a set union.
/// So the survey, the serial part of a job's set-up, can be spread over the workers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurveyPart {
    version: u32,
    /// What it was learnt for.
    pub of: Surveyed,
    /// The directions it covers, `start..end`.
    pub directions: (u32, u32),
    units: AreaUnits,
    sends_to: Vec<(u32, u32)>,
    /// With mirrors, per direction of the part, its subfield restricted to the scene's mirror
    /// planes — all of them, as which of them light reaches is known only once every part is in.
    /// The views of the mirror maps are cut from these ([`super::Propagation::with_survey_and_planes`]):
    /// the part builds the whole subfields anyway, so restricting them is a copy (without a
    /// subfield budget; within one, a subfield may be built again), where the
    /// coordinator would otherwise rasterise the mirror planes in every direction itself (most of
    /// its set-up for a curved mirror: 2–3 s of its two threads for the mirror dragon at
    /// l = 2049, N = 128). Empty without mirrors.
    pub mirror_planes: Vec<Subfield>,
}

impl SurveyPart {
    /// Learns the part of `scene`'s survey with `options` that the directions `range` make:
    /// builds the texel atlas and those directions' subfields only (within `budget` bytes of
    /// subfields when one is given), and passes over their rays. [`Surveyor`] learns several
    /// parts with one atlas.
    pub fn learn(
        scene: &Scene,
        options: &Options,
        range: Range<usize>,
        budget: Option<usize>,
    ) -> crate::Result<SurveyPart> {
        Surveyor::new(scene, options, budget)?.part(range)
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    /// Reads a part; what cannot be one (truncated, another version, trailing bytes) is a
    /// [`crate::Error::Decode`]. Whether it fits a job is [`Survey::from_parts`]'s to say.
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<SurveyPart> {
        read_versioned(bytes, PART_VERSION, "survey part")
    }
}

/// What learning parts of a survey needs, built once for all the parts one learns: the job's
/// scene and texel atlas, the polygons' footprints and stacking, and the subfields as their
/// directions come up (within a budget when one is given). A worker keeps one for the job whose
/// survey it is leased, so the atlas — seconds for a scan of 10⁵ polygons — is built once per
/// worker, not once per block.
pub struct Surveyor {
    scene: Scene,
    of: Surveyed,
    directions: DirectionSet,
    atlas: TexelAtlas,
    stacking: Stacking,
    /// The directions' subfields, none built: each part builds its own (see [`Surveyor::part`]).
    subfields: Subfields,
    mirrors: bool,
}

impl Surveyor {
    /// The geometry that parts of `scene`'s survey with `options` are learnt over; no subfield
    /// is built yet. A part holds its subfields within `budget` bytes when one is given; else,
    /// without mirrors (each subfield read once) none is kept, and with mirrors (read three
    /// times: the areas, the surfaces facing each other, the mirror planes) the part's are, until
    /// it is learnt — within a budget, one read may build a subfield again. Options
    /// that do not make a propagation are refused.
    pub fn new(scene: &Scene, options: &Options, budget: Option<usize>) -> crate::Result<Surveyor> {
        options.validate()?;
        let directions = DirectionSet::new(options.directions)?;
        let atlas = TexelAtlas::new(scene, options.texel_size(), options.grid.ray_spacing())?;
        let footprints = Arc::new(Footprints::new(scene, &atlas.plane_rep));
        let frames = (0..directions.len()).map(|d| directions.frame(d)).collect();
        let mirrors = (0..scene.surfaces.len()).any(|s| scene.material(s).is_mirror());
        let subfields = match budget.or((!mirrors).then_some(0)) {
            Some(bytes) => Subfields::within(footprints, frames, options.grid, bytes),
            None => Subfields::on_demand(footprints, frames, options.grid),
        };
        let stacking = Stacking::new(scene, &atlas);
        Ok(Surveyor {
            scene: scene.clone(),
            of: Surveyed::of(scene, options),
            directions,
            atlas,
            stacking,
            subfields,
            mirrors,
        })
    }

    /// The part the directions `range` make: their discrete areas, and with mirrors the pairs
    /// of surfaces their rays find facing each other. The subfields it builds go with it: no
    /// later part reads the same directions, so a surveyor kept from part to part (a worker's,
    /// from lease to lease) holds the atlas only.
    pub fn part(&self, range: Range<usize>) -> crate::Result<SurveyPart> {
        if range.is_empty() || range.end > self.directions.len() {
            return Err(crate::Error::Parameter(format!(
                "directions {range:?} are not a part of the {} directions",
                self.directions.len()
            )));
        }
        let geometry = Geometry {
            scene: &self.scene,
            atlas: &self.atlas,
            stacking: &self.stacking,
        };
        let subfields = self.subfields.released();
        let units = AreaUnits::of(geometry, &self.directions, range.clone(), |d| subfields.get(d));
        let (sends_to, mirror_planes) = match self.mirrors {
            true => (
                plan::sends_to(geometry, &subfields, range.clone()),
                (range.clone().into_par_iter())
                    .map(|d| subfields.get(d).only(|s| self.scene.material(s as usize).is_mirror()))
                    .collect(),
            ),
            false => (Vec::new(), Vec::new()),
        };
        Ok(SurveyPart {
            version: PART_VERSION,
            of: self.of.clone(),
            directions: (range.start as u32, range.end as u32),
            units,
            sends_to,
            mirror_planes,
        })
    }
}

/// Reads `what`, written by [`encode`] with `version` first; what cannot be one (truncated,
/// another version, trailing bytes) is a [`crate::Error::Decode`].
pub(super) fn read_versioned<T: serde::de::DeserializeOwned>(
    bytes: &[u8],
    version: u32,
    what: &str,
) -> crate::Result<T> {
    let mut rest = bytes;
    let value = read_versioned_from(&mut rest, bytes.len() as u64, version, what)?;
    if !rest.is_empty() {
        return Err(crate::Error::Decode(format!("{what}: trailing bytes")));
    }
    Ok(value)
}

/// [`read_versioned`] out of `reader`, as its bytes come (out of a decompressor, say): nothing
/// holds the serialised value whole, a hundred megabytes for a curved mirror's geometry. Reads
/// no further than the value; whether anything follows is the caller's to check (a blob's reader
/// checks that it was read to its end).
///
/// `len` is how many bytes the reader holds at most. A length written in the bytes (of a
/// string, say) that claims more is an error before anything is allocated for it: reading from
/// a stream, bincode would otherwise make a buffer of that length first, and a damaged or
/// hostile blob could ask for terabytes.
pub(crate) fn read_versioned_from<T: serde::de::DeserializeOwned>(
    mut reader: impl std::io::Read,
    len: u64,
    version: u32,
    what: &str,
) -> crate::Result<T> {
    use bincode::Options as _;
    let bad = |m: String| crate::Error::Decode(format!("{what}: {m}"));
    let mut head = [0u8; 4];
    let got = read_head(&mut reader, &mut head).map_err(|e| bad(e.to_string()))?;
    match version_of(&head[..got]) {
        Some(v) if v == version => {}
        Some(v) => return Err(bad(format!("version {v}, this build reads {version}"))),
        None => return Err(bad(format!("{got} bytes, too short"))),
    }
    // bincode's own defaults (`bincode::deserialize`), bounded by `len`.
    let options = (bincode::DefaultOptions::new())
        .with_fixint_encoding()
        .allow_trailing_bytes()
        .with_limit(len);
    // The version is the value's first field: read again, ahead of the rest.
    (options.deserialize_from(std::io::Read::chain(&head[..], reader))).map_err(|e| bad(e.to_string()))
}

impl Survey {
    /// The survey of `scene` with `options` from parts learnt separately ([`SurveyPart`]), given
    /// in any order: the same bits as [`super::Propagation::survey`] of a propagation that
    /// learnt it whole. Parts that were learnt for another job, overlap, leave directions out or
    /// disagree on the texels are refused with an error that says which.
    pub fn from_parts(scene: &Scene, options: &Options, mut parts: Vec<SurveyPart>) -> crate::Result<Survey> {
        let mut survey = SurveyParts::new(scene, options);
        // Another job's part is named as such, wherever it would have gone.
        if let Some(other) = parts.iter().find(|p| p.of != survey.of) {
            return Err(another_job(other));
        }
        parts.sort_by_key(|p| p.directions);
        for part in parts {
            survey.add(part)?;
        }
        survey.finish(scene)
    }
}

fn another_job(part: &SurveyPart) -> crate::Error {
    let (a, b) = part.directions;
    crate::Error::Decode(format!(
        "survey parts: the part of directions {a}..{b} was learnt for another job"
    ))
}

/// A survey put together from its parts in direction order, as they come in (the coordinator of
/// a job reads the parts its workers learnt block by block, and keeps one sum, not every part):
/// the same bits as [`Survey::from_parts`] of all of them.
pub struct SurveyParts {
    of: Surveyed,
    /// The scene's surfaces: a pair of surfaces facing each other names two of them.
    surfaces: usize,
    /// Whether the scene has mirrors: then every part has its directions' mirror planes.
    mirrors: bool,
    /// The mirror planes of the directions added so far ([`SurveyPart::mirror_planes`]).
    planes: Vec<Subfield>,
    /// The directions the parts added so far cover: `0..next`.
    next: u32,
    units: Option<AreaUnits>,
    edges: Vec<(u32, u32)>,
}

impl SurveyParts {
    /// No part yet, of the survey of `scene` with `options`.
    pub fn new(scene: &Scene, options: &Options) -> SurveyParts {
        SurveyParts {
            of: Surveyed::of(scene, options),
            surfaces: scene.surfaces.len(),
            mirrors: Plan::counted(scene).mirrors > 0,
            planes: Vec::new(),
            next: 0,
            units: None,
            edges: Vec::new(),
        }
    }

    /// Adds the part that continues the directions added so far. A part of another job, one that
    /// does not start where the others end, or over other texels is refused, and nothing is
    /// added.
    pub fn add(&mut self, part: SurveyPart) -> crate::Result<()> {
        let misfit = |m: String| Err(crate::Error::Decode(format!("survey parts: {m}")));
        let (a, b) = part.directions;
        if part.of != self.of {
            return Err(another_job(&part));
        }
        if a != self.next || b <= a {
            return misfit(format!(
                "directions {a}..{b} do not continue from direction {} (each direction once, none left out)",
                self.next
            ));
        }
        if let Some(&(s, t)) =
            (part.sends_to.iter()).find(|&&(s, t)| s as usize >= self.surfaces || t as usize >= self.surfaces)
        {
            return misfit(format!(
                "the part of directions {a}..{b} names surfaces {s} and {t} of the scene's {}",
                self.surfaces
            ));
        }
        let planes = if self.mirrors { (b - a) as usize } else { 0 };
        if part.mirror_planes.len() != planes {
            return misfit(format!(
                "the part of directions {a}..{b} has {} mirror planes for {planes}",
                part.mirror_planes.len()
            ));
        }
        match &mut self.units {
            Some(units) if part.units.texels() != units.texels() => {
                return misfit(format!(
                    "the part of directions {a}..{b} has {} texels, the first {}",
                    part.units.texels(),
                    units.texels()
                ));
            }
            Some(units) => units.add(&part.units),
            None => self.units = Some(part.units),
        }
        self.edges.extend(part.sends_to);
        self.planes.extend(part.mirror_planes);
        self.edges.sort_unstable();
        self.edges.dedup();
        self.next = b;
        Ok(())
    }

    /// The survey, once the parts cover every direction.
    pub fn finish(self, scene: &Scene) -> crate::Result<Survey> {
        self.finish_with_planes(scene).map(|(survey, _)| survey)
    }

    /// [`SurveyParts::finish`], and every direction's mirror planes (none without mirrors): what
    /// [`super::Propagation::with_survey_and_planes`] cuts the mirror views from.
    pub fn finish_with_planes(self, scene: &Scene) -> crate::Result<(Survey, Vec<Subfield>)> {
        let directions = self.of.directions;
        let units = match self.units {
            Some(units) if self.next as usize == directions => units,
            _ => {
                return Err(crate::Error::Decode(format!(
                    "survey parts: they cover {} of the {directions} directions",
                    self.next
                )));
            }
        };
        let lit = match Plan::counted(scene).mirrors {
            0 => Vec::new(),
            _ => plan::lit_mirrors(scene, &self.edges),
        };
        Ok((Survey::new(self.of, units.areas(), lit), self.planes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::propagate::{Propagation, Stop};
    use crate::scene::{ImportOptions, load_obj};

    fn bundled(name: &str) -> Scene {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../scenes")
            .join(name);
        load_obj(&path, &ImportOptions::default()).unwrap().0
    }

    fn options(directions: usize) -> Options {
        Options {
            directions,
            grid: GridSize::new(32, 8).unwrap(),
            stop: Stop::Iterations(1),
            ..Options::default()
        }
    }

    /// The parts of `cuts` (direction boundaries), learnt apart, through their bytes as a store
    /// holds them, in reverse order.
    fn parts(scene: &Scene, options: &Options, cuts: &[usize], budget: Option<usize>) -> Vec<SurveyPart> {
        let mut parts: Vec<SurveyPart> = (cuts.windows(2))
            .map(|c| SurveyPart::learn(scene, options, c[0]..c[1], budget).unwrap())
            .map(|p| SurveyPart::from_bytes(&p.to_bytes()).unwrap())
            .collect();
        parts.reverse();
        parts
    }

    #[test]
    fn parts_learnt_apart_make_the_survey_learnt_whole() {
        let options = options(129);
        for name in ["cornell.obj", "mirrors.obj"] {
            let scene = bundled(name);
            let whole = Propagation::new(scene.clone(), options.clone()).unwrap().survey();
            assert_eq!(!whole.lit_mirrors.is_empty(), name == "mirrors.obj", "{name}");
            for (cuts, budget) in [
                (&[0, 129][..], None),
                (&[0, 1, 64, 100, 129][..], None),
                (&[0, 7, 129][..], Some(0)),
            ] {
                let survey = Survey::from_parts(&scene, &options, parts(&scene, &options, cuts, budget)).unwrap();
                assert!(survey == whole, "{name}, parts {cuts:?}, budget {budget:?}");
            }
        }
    }

    /// A coordinator adds its workers' parts as they come in, in order: the same survey, and a
    /// part out of turn is refused without spoiling the sum.
    #[test]
    fn parts_added_in_order_make_the_survey_and_refuse_one_out_of_turn() {
        let options = options(129);
        for name in ["cornell.obj", "mirrors.obj"] {
            let scene = bundled(name);
            let whole = Propagation::new(scene.clone(), options.clone()).unwrap().survey();
            // One surveyor for several parts, as a worker's lease learns its blocks.
            let surveyor = Surveyor::new(&scene, &options, None).unwrap();
            let parts: Vec<SurveyPart> = [0..8, 8..64, 64..129]
                .into_iter()
                .map(|r| surveyor.part(r).unwrap())
                .collect();
            let mut sum = SurveyParts::new(&scene, &options);
            sum.add(parts[0].clone()).unwrap();
            let e = sum.add(parts[2].clone()).unwrap_err().to_string();
            assert!(e.contains("do not continue from direction 8"), "{e}");
            sum.add(parts[1].clone()).unwrap();
            let e = sum.add(parts[1].clone()).unwrap_err().to_string();
            assert!(e.contains("do not continue from direction 64"), "{e}");
            let mut early = SurveyParts::new(&scene, &options);
            early.add(parts[0].clone()).unwrap();
            let e = early.finish(&scene).unwrap_err().to_string();
            assert!(e.contains("cover 8 of the 129"), "{e}");
            sum.add(parts[2].clone()).unwrap();
            assert!(sum.finish(&scene).unwrap() == whole, "{name}");
        }
    }

    #[test]
    fn parts_that_do_not_make_a_survey_are_refused() {
        let (scene, options) = (bundled("cornell.obj"), options(33));
        let refused = |parts: Vec<SurveyPart>, says: &str| {
            let e = Survey::from_parts(&scene, &options, parts).unwrap_err().to_string();
            assert!(e.contains(says), "{e} (expected: {says})");
        };
        // In reverse order: the second part first.
        let [b, a] = parts(&scene, &options, &[0, 16, 33], None).try_into().unwrap();
        let overlapping = SurveyPart::learn(&scene, &options, 10..33, None).unwrap();
        refused(vec![a.clone()], "cover 16 of the 33");
        refused(vec![b.clone()], "do not continue from direction 0");
        refused(vec![a.clone(), overlapping], "do not continue from direction 16");
        refused(
            vec![a.clone(), b.clone(), b.clone()],
            "do not continue from direction 33",
        );
        refused(Vec::new(), "cover 0 of the 33");
        let other = Options {
            texel_cells: 2.0,
            ..options.clone()
        };
        let elsewhere = SurveyPart::learn(&scene, &other, 16..33, None).unwrap();
        refused(vec![b.clone(), elsewhere], "another job");
        // A pair of surfaces the scene does not have (a part that decodes, yet is garbage).
        let mut stray = b.clone();
        stray.sends_to = vec![(0, scene.surfaces.len() as u32)];
        refused(vec![a.clone(), stray], "names surfaces 0 and");
        assert!(Survey::from_parts(&scene, &options, vec![b.clone(), a.clone()]).is_ok());
        // Not a part of the directions.
        for range in [0..0, 30..34] {
            let e = SurveyPart::learn(&scene, &options, range.clone(), None).unwrap_err();
            assert!(matches!(e, crate::Error::Parameter(_)), "{range:?}: {e}");
        }
        // Bytes that are not a part.
        let bytes = a.to_bytes();
        let longer = [bytes.clone(), vec![0]].concat();
        for bad in [&bytes[..bytes.len() - 1], &bytes[..3], &longer[..]] {
            let e = SurveyPart::from_bytes(bad).unwrap_err();
            assert!(matches!(e, crate::Error::Decode(_)), "{e}");
        }
    }
}
