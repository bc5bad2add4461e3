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
//! of the Cornell box and of the mirror scene at l = 2049, N = 128. The coordinator
//! of a job learns them when it creates the job and stores them with it; a worker that opens the
//! job reads them ([`super::Propagation::with_survey`]) and builds only the subfields it shoots,
//! as it shoots them (a scene with mirrors still builds every subfield once, for the mirror
//! layouts). The survey is a pure function of the scene and the options, so reading it rather
//! than learning it again changes no bit of the field.

use super::Options;
use super::checkpoint::{encode, version_of};
use crate::psf::GridSize;
use crate::scene::Scene;
use serde::{Deserialize, Serialize};

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
        let bad = |m: String| crate::Error::Decode(format!("survey: {m}"));
        match version_of(bytes) {
            Some(SURVEY_VERSION) => {}
            Some(v) => return Err(bad(format!("version {v}, this build reads {SURVEY_VERSION}"))),
            None => return Err(bad(format!("{} bytes, too short", bytes.len()))),
        }
        let survey: Survey = bincode::deserialize(bytes).map_err(|e| bad(e.to_string()))?;
        if encode(&survey).len() != bytes.len() {
            return Err(bad("trailing bytes".into()));
        }
        Ok(survey)
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
