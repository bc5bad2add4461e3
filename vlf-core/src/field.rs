//! The light field after propagation: what rendering and storage use.
//!
//! For a diffuse surface the field is its Total map turned into outgoing
//! radiance, `L_t = Total_t / T_t` (see [`crate::propagate`]): emitted plus
//! reflected, the same in every direction. Texels that no ray crosses (at
//! polygon borders, or on polygons thinner than a ray cell) have no value of
//! their own; they are filled from their neighbours so bilinear look-ups near
//! edges stay smooth, and a chart that no ray crosses at all takes the light
//! of the charts it touches ([`crate::maps::fill`]).
//!
//! A field is stored (by the `vlf-store` crate) as its radiance only —
//! [`Propagation::diffuse_radiance`] and [`Propagation::mirror_totals`] —
//! and rebuilt with [`LightField::from_radiance`]: everything else is a
//! deterministic function of the scene and the options.

use crate::directions::DirectionSet;
use crate::maps::TexelAtlas;
use crate::propagate::specular::MirrorView;
use crate::propagate::{IterationStats, Options, Propagation};
use crate::scene::{Rgb, Scene};
use glam::DVec3;

/// A propagated virtual light field.
#[derive(Clone, Debug, PartialEq)]
pub struct LightField {
    pub scene: Scene,
    pub options: Options,
    pub atlas: TexelAtlas,
    /// Outgoing radiance of every texel (RGB, holes filled).
    pub radiance: Vec<[f32; 3]>,
    /// Whether a texel was crossed by at least one ray (its value is its own).
    pub covered: Vec<bool>,
    pub emitted: Rgb,
    pub stats: Vec<IterationStats>,
    /// Unshot power left, as a fraction of the emitted power.
    pub unshot_fraction: f64,
    /// Directional radiance of mirrors; `None` for a scene without mirrors.
    pub specular: Option<SpecularField>,
    /// Set by [`LightField::use_exact_direct`]: shade with exact direct light.
    pub exact_direct: Option<crate::direct::ExactDirect>,
}

/// The directional part of the field: for every direction, the radiance
/// leaving each mirror along each ray of its subfield that crosses it (the
/// paper's tile radiance maps), with what is needed to find a ray again.
#[derive(Clone, Debug, PartialEq)]
pub struct SpecularField {
    pub directions: DirectionSet,
    /// Per direction, its subfield on the mirrors alone, with their slots: where each ray
    /// that crosses a mirror finds its radiance ([`MirrorView`]).
    pub views: std::sync::Arc<[MirrorView]>,
    /// `totals[d][slot]`: radiance leaving the mirror along direction `d`.
    pub totals: Vec<Vec<[f32; 3]>>,
}

impl LightField {
    pub(crate) fn from_propagation(p: Propagation) -> Self {
        let radiance = p.diffuse_radiance();
        let totals = p.mirror_totals();
        let unshot_fraction = p.unshot_fraction();
        let stats = p.stats.clone();
        LightField::assemble(p, radiance, totals, stats, unshot_fraction)
    }

    /// Rebuilds a field from its stored radiance: diffuse radiance per texel
    /// (holes filled, see [`Propagation::diffuse_radiance`]) and, with
    /// mirrors, the totals per direction and mirror slot. The geometry
    /// (directions, subfields, texel grids, mirror views) is a
    /// deterministic function of the scene and options, so it is recomputed,
    /// not stored. Sizes that do not fit it, and non-finite or negative
    /// radiance, are an [`Error::Decode`](crate::Error::Decode).
    ///
    /// `p` is a fresh [`Propagation::new`] of the field's scene and options:
    /// its texel atlas and mirror views say where each stored
    /// value goes, and become the field's geometry.
    pub fn from_radiance(
        p: Propagation,
        stats: Vec<IterationStats>,
        radiance: Vec<[f32; 3]>,
        totals: Option<Vec<Vec<[f32; 3]>>>,
    ) -> crate::Result<Self> {
        let bad = |m: String| {
            Err(crate::Error::Decode(format!(
                "stored radiance does not fit the field: {m}"
            )))
        };
        let valid = |v: &[[f32; 3]]| v.iter().flatten().all(|&c| c.is_finite() && c >= 0.0);
        if radiance.len() != p.atlas.texels {
            return bad(format!("{} texel values for {} texels", radiance.len(), p.atlas.texels));
        }
        if !valid(&radiance) {
            return bad("negative or non-finite diffuse radiance".into());
        }
        match (&p.specular, &totals) {
            (None, None) => {}
            (Some(spec), Some(totals)) => {
                if totals.len() != spec.views.len() {
                    return bad(format!(
                        "mirror maps of {} directions, expected {}",
                        totals.len(),
                        spec.views.len()
                    ));
                }
                for (d, (t, v)) in totals.iter().zip(spec.views.iter()).enumerate() {
                    if t.len() != v.slots() {
                        return bad(format!(
                            "direction {d}: {} mirror values for {} slots",
                            t.len(),
                            v.slots()
                        ));
                    }
                    if !valid(t) {
                        return bad(format!("direction {d}: negative or non-finite mirror radiance"));
                    }
                }
            }
            (Some(_), None) => return bad("the scene has mirrors, the stored field no mirror maps".into()),
            (None, Some(_)) => return bad("the stored field has mirror maps, the scene no mirror".into()),
        }
        let emitted = (p.emitted[0] + p.emitted[1] + p.emitted[2]) / 3.0;
        let unshot_fraction = stats
            .last()
            .map_or(1.0, |s| (s.unshot[0] + s.unshot[1] + s.unshot[2]) / 3.0 / emitted);
        Ok(LightField::assemble(p, radiance, totals, stats, unshot_fraction))
    }

    fn assemble(
        p: Propagation,
        radiance: Vec<[f32; 3]>,
        totals: Option<Vec<Vec<[f32; 3]>>>,
        stats: Vec<IterationStats>,
        unshot_fraction: f64,
    ) -> Self {
        let covered: Vec<bool> = p.projected_area.iter().map(|&a| a > 0.0).collect();
        let specular = p.specular.zip(totals).map(|(s, totals)| SpecularField {
            totals,
            views: s.views,
            directions: p.directions,
        });
        LightField {
            specular,
            scene: p.scene,
            options: p.options,
            atlas: p.atlas,
            radiance,
            covered,
            emitted: p.emitted,
            stats,
            unshot_fraction,
            exact_direct: None,
        }
    }

    /// The field's fingerprint: SHA-256 (lower-case hex) of its radiance as propagated, every
    /// bit of it, before a store's encoding rounds it. Two runs that give the same field give
    /// the same digest, whatever split of threads, workers or machines computed them, and a
    /// field that differs in one bit of one value gives another: so a user compares a
    /// cluster's result with a local `vlf propagate` by two short strings
    /// (`vlf status`, `vlf propagate`), where the fields themselves may be gigabytes apart.
    ///
    /// What it covers: the number of iterations, the diffuse radiance of every texel
    /// ([`LightField::radiance`]) and, with mirrors, every direction's mirror totals, each
    /// value's `f32` bits little-endian. Everything else in a field is a function of the scene
    /// and the options (geometry) or of the iterations' timing (statistics). The mirror totals
    /// (hundreds of MB at l = 2049) are hashed one direction per task, in parallel, and the
    /// directions' hashes hashed in order, so the digest does not depend on the thread count.
    pub fn digest(&self) -> String {
        use rayon::prelude::*;
        let mirrors: Option<Vec<[u8; 32]>> =
            (self.specular.as_ref()).map(|spec| spec.totals.par_iter().map(|t| mirror_digest(t)).collect());
        digest_of(self.stats.len(), &self.radiance, mirrors.as_deref())
    }

    /// Outgoing diffuse radiance of `surface` at point `p` (VLF frame),
    /// bilinear between texel centres.
    pub fn radiance_at(&self, surface: usize, p: DVec3) -> Rgb {
        self.bilinear(&self.radiance, surface, p)
    }

    /// Bilinear look-up of per-texel `values` (laid out like the atlas).
    pub(crate) fn bilinear(&self, values: &[[f32; 3]], surface: usize, p: DVec3) -> Rgb {
        let g = self.atlas.grid(surface);
        let c = g.coords(p) - 0.5;
        let (x0, y0) = (c.x.floor(), c.y.floor());
        let (fx, fy) = (c.x - x0, c.y - y0);
        let clamp = |v: f64, n: u32| (v.max(0.0) as u32).min(n - 1);
        let (xa, xb) = (clamp(x0, g.width), clamp(x0 + 1.0, g.width));
        let (ya, yb) = (clamp(y0, g.height), clamp(y0 + 1.0, g.height));
        let at = |x: u32, y: u32| values[g.first + (y * g.width + x) as usize];
        let mut out = [0.0; 3];
        for (x, y, w) in [
            (xa, ya, (1.0 - fx) * (1.0 - fy)),
            (xb, ya, fx * (1.0 - fy)),
            (xa, yb, (1.0 - fx) * fy),
            (xb, yb, fx * fy),
        ] {
            let v = at(x, y);
            for k in 0..3 {
                out[k] += v[k] as f64 * w;
            }
        }
        out
    }
}

impl Propagation {
    /// The field as it stands after the iterations done so far, leaving the
    /// propagation free to go on: what a study renders after every
    /// iteration. Costs a copy of the scene and texel grids (the mirror views
    /// are shared); [`Propagation::into_field`] is the move at the end.
    pub fn field_now(&self) -> LightField {
        let covered: Vec<bool> = self.projected_area.iter().map(|&a| a > 0.0).collect();
        let specular = self
            .specular
            .as_ref()
            .zip(self.mirror_totals())
            .map(|(s, totals)| SpecularField {
                directions: self.directions.clone(),
                views: s.views.clone(),
                totals,
            });
        LightField {
            scene: self.scene.clone(),
            options: self.options.clone(),
            atlas: self.atlas.clone(),
            radiance: self.diffuse_radiance(),
            covered,
            emitted: self.emitted,
            stats: self.stats.clone(),
            unshot_fraction: self.unshot_fraction(),
            specular,
            exact_direct: None,
        }
    }

    /// Outgoing diffuse radiance of every texel as it stands, `Total_t / T_t`
    /// (emitted plus reflected so far), with texels no ray crosses filled
    /// from their neighbours, within their chart or, for a chart no ray
    /// crosses, from the charts it touches ([`crate::maps::fill`]): what
    /// rendering reads. An emitter's rays carry
    /// `k_c·Le` (`Propagation::emission_scale`), its look `Le`: the
    /// difference `(k_c − 1)·Le` is taken off.
    pub fn diffuse_radiance(&self) -> Vec<[f32; 3]> {
        let covered: Vec<bool> = self.projected_area.iter().map(|&a| a > 0.0).collect();
        let mut radiance: Vec<[f32; 3]> = self
            .total
            .iter()
            .zip(&self.projected_area)
            .zip(&self.owners)
            .map(|((t, &a), &c)| {
                if a > 0.0 {
                    let le = self.scene.materials[self.atlas.chart_material[c as usize] as usize].emission;
                    let extra = self.emission_scale[c as usize] - 1.0;
                    std::array::from_fn(|k| (t[k] / a - le[k] * extra).max(0.0) as f32)
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        crate::maps::fill::within_charts(&self.atlas, &covered, &mut radiance);
        let across = self.hole_fill.get_or_init(|| {
            let plan = crate::maps::fill::AcrossCharts::plan(&self.scene, &self.atlas, &covered);
            let (filled, unreached) = plan.counts();
            if filled + unreached > 0 {
                tracing::debug!(filled, unreached, "charts no ray crosses, lit from their neighbours");
            }
            plan
        });
        let emission = |c: usize| self.scene.materials[self.atlas.chart_material[c] as usize].emission;
        across.apply(&self.atlas, &self.albedo, emission, &mut radiance);
        radiance
    }

    /// Radiance that left every mirror along every ray so far, per direction
    /// and mirror slot (`None` without specular machinery).
    pub fn mirror_totals(&self) -> Option<Vec<Vec<[f32; 3]>>> {
        self.specular.as_ref().map(|s| {
            (0..s.maps.len())
                .map(|d| {
                    (s.map_or_zeros(d, |m| &m.total).iter())
                        .map(|t| [t[0] as f32, t[1] as f32, t[2] as f32])
                        .collect()
                })
                .collect()
        })
    }
}

/// [`LightField::digest`] from its parts: the number of iterations, the diffuse radiance and,
/// with mirrors, every direction's [`mirror_digest`] in order. For whoever writes a field
/// without holding all of it (a coordinator streams the mirror totals from the last
/// snapshot's parts, a batch of directions at a time): the same string.
pub fn digest_of(iterations: usize, radiance: &[[f32; 3]], mirrors: Option<&[[u8; 32]]>) -> String {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(b"vlf field digest 1");
    h.update((iterations as u64).to_le_bytes());
    hash_values(&mut h, radiance);
    if let Some(directions) = mirrors {
        h.update((directions.len() as u64).to_le_bytes());
        for d in directions {
            h.update(d);
        }
    }
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// The hash of one direction's mirror totals in [`LightField::digest`].
pub fn mirror_digest(totals: &[[f32; 3]]) -> [u8; 32] {
    use sha2::{Digest, Sha256};
    let mut d = Sha256::new();
    hash_values(&mut d, totals);
    d.finalize().into()
}

/// Feeds `v` to `h`: its length, then every value's `f32` bits little-endian.
fn hash_values(h: &mut sha2::Sha256, v: &[[f32; 3]]) {
    use sha2::Digest;
    h.update((v.len() as u64).to_le_bytes());
    let mut buf = Vec::with_capacity(12 * 1024);
    for chunk in v.chunks(1024) {
        buf.clear();
        buf.extend(chunk.iter().flatten().flat_map(|c| c.to_le_bytes()));
        h.update(&buf);
    }
}
