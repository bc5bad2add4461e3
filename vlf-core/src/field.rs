//! The light field after propagation: what rendering and storage use.
//!
//! For a diffuse surface the field is its Total map turned into outgoing
//! radiance, `L_t = Total_t / T_t` (see [`crate::propagate`]): emitted plus
//! reflected, the same in every direction. Texels that no ray crosses (at
//! polygon borders, or on polygons thinner than a ray cell) have no value of
//! their own; they are filled from their neighbours so bilinear look-ups near
//! edges stay smooth.
//!
//! On disk (`DIR/field.vlf`): the magic `VLFFIELD`, a format version (u32 LE),
//! then a zstd-compressed bincode encoding of [`LightField`]. Writes go to a
//! temporary file renamed into place, so a reader never sees half a field.

use crate::directions::DirectionSet;
use crate::maps::TexelAtlas;
use crate::propagate::specular::MirrorLayout;
use crate::propagate::{IterationStats, Options, Propagation};
use crate::psf::Subfield;
use crate::scene::{Rgb, Scene};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::path::Path;

const MAGIC: &[u8; 8] = b"VLFFIELD";
const VERSION: u32 = 1;
const FILE: &str = "field.vlf";

/// A propagated virtual light field.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
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
}

/// The directional part of the field: for every direction, the radiance
/// leaving each mirror along each ray of its subfield that crosses it (the
/// paper's tile radiance maps), with what is needed to find a ray again.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpecularField {
    pub directions: DirectionSet,
    pub subfields: Vec<Subfield>,
    pub layouts: Vec<MirrorLayout>,
    /// `totals[d][slot]`: radiance leaving the mirror along direction `d`.
    pub totals: Vec<Vec<[f32; 3]>>,
}

impl LightField {
    pub(crate) fn from_propagation(p: Propagation) -> Self {
        let unshot_fraction = p.unshot_fraction();
        let covered: Vec<bool> = p.projected_area.iter().map(|&a| a > 0.0).collect();
        let mut radiance: Vec<[f32; 3]> = p
            .total
            .iter()
            .zip(&p.projected_area)
            .map(|(t, &a)| {
                if a > 0.0 {
                    [(t[0] / a) as f32, (t[1] / a) as f32, (t[2] / a) as f32]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        fill_holes(&p.atlas, &covered, &mut radiance);
        let specular = p.specular.map(|s| SpecularField {
            totals: s
                .maps
                .iter()
                .map(|m| {
                    m.total
                        .iter()
                        .map(|t| [t[0] as f32, t[1] as f32, t[2] as f32])
                        .collect()
                })
                .collect(),
            layouts: s.layouts,
            directions: p.directions,
            subfields: p.subfields,
        });
        LightField {
            specular,
            scene: p.scene,
            options: p.options,
            atlas: p.atlas,
            radiance,
            covered,
            emitted: p.emitted,
            stats: p.stats,
            unshot_fraction,
        }
    }

    /// Outgoing diffuse radiance of `surface` at point `p` (VLF frame),
    /// bilinear between texel centres.
    pub fn radiance_at(&self, surface: usize, p: DVec3) -> Rgb {
        let g = &self.atlas.grids[surface];
        let c = g.coords(p) - 0.5;
        let (x0, y0) = (c.x.floor(), c.y.floor());
        let (fx, fy) = (c.x - x0, c.y - y0);
        let clamp = |v: f64, n: u32| (v.max(0.0) as u32).min(n - 1);
        let (xa, xb) = (clamp(x0, g.width), clamp(x0 + 1.0, g.width));
        let (ya, yb) = (clamp(y0, g.height), clamp(y0 + 1.0, g.height));
        let at = |x: u32, y: u32| self.radiance[g.first + (y * g.width + x) as usize];
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

    /// Writes `DIR/field.vlf` atomically (creating `DIR`).
    pub fn save(&self, dir: &Path) -> crate::Result<()> {
        std::fs::create_dir_all(dir).map_err(|e| crate::Error::io(dir, e))?;
        let payload = bincode::serialize(self).map_err(|e| crate::Error::Format {
            path: dir.join(FILE),
            message: format!("cannot encode the field: {e}"),
        })?;
        let compressed = zstd::encode_all(&payload[..], 3).map_err(|e| crate::Error::io(dir.join(FILE), e))?;
        let mut bytes = Vec::with_capacity(compressed.len() + 12);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&VERSION.to_le_bytes());
        bytes.extend_from_slice(&compressed);
        let tmp = dir.join(format!("{FILE}.tmp"));
        std::fs::write(&tmp, &bytes).map_err(|e| crate::Error::io(&tmp, e))?;
        std::fs::rename(&tmp, dir.join(FILE)).map_err(|e| crate::Error::io(dir.join(FILE), e))
    }

    /// Reads `DIR/field.vlf`, refusing truncated, corrupted or foreign files.
    pub fn load(dir: &Path) -> crate::Result<Self> {
        let path = dir.join(FILE);
        let bytes = std::fs::read(&path).map_err(|e| crate::Error::io(&path, e))?;
        let bad = |message: String| crate::Error::Format {
            path: path.clone(),
            message,
        };
        if bytes.len() < 12 || &bytes[..8] != MAGIC {
            return Err(bad("not a VLF field file (bad magic)".into()));
        }
        let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        if version != VERSION {
            return Err(bad(format!(
                "field format version {version}, this build reads {VERSION}"
            )));
        }
        let payload = zstd::decode_all(&bytes[12..]).map_err(|e| bad(format!("corrupted or truncated: {e}")))?;
        let field: LightField =
            bincode::deserialize(&payload).map_err(|e| bad(format!("corrupted or truncated: {e}")))?;
        field.check().map_err(bad)?;
        Ok(field)
    }

    /// Internal consistency of a decoded field (sizes agree, values finite).
    fn check(&self) -> Result<(), String> {
        if self.atlas.grids.len() != self.scene.surfaces.len() {
            return Err("texel grids do not match the surfaces".into());
        }
        let mut first = 0usize;
        for g in &self.atlas.grids {
            if g.first != first || g.width == 0 || g.height == 0 {
                return Err("texel atlas layout is inconsistent".into());
            }
            first += g.len();
        }
        if first != self.atlas.texels || self.radiance.len() != first || self.covered.len() != first {
            return Err("radiance maps do not match the texel atlas".into());
        }
        if self.radiance.iter().flatten().any(|v| !v.is_finite()) {
            return Err("non-finite radiance".into());
        }
        if self
            .scene
            .surfaces
            .iter()
            .any(|s| s.material >= self.scene.materials.len())
        {
            return Err("a surface refers to a missing material".into());
        }
        Ok(())
    }
}

/// Fills uncovered texels with the mean of covered neighbours, growing
/// outwards a ring per pass (a few passes suffice: holes are border texels).
fn fill_holes(atlas: &TexelAtlas, covered: &[bool], radiance: &mut [[f32; 3]]) {
    for g in &atlas.grids {
        let (w, h) = (g.width as i64, g.height as i64);
        let mut known: Vec<bool> = covered[g.first..g.first + g.len()].to_vec();
        if !known.iter().any(|&k| k) {
            continue;
        }
        loop {
            let mut changed = false;
            let snapshot = known.clone();
            for y in 0..h {
                for x in 0..w {
                    let i = (y * w + x) as usize;
                    if snapshot[i] {
                        continue;
                    }
                    let (mut sum, mut n) = ([0.0f32; 3], 0);
                    for (dx, dy) in [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, 1), (-1, 1), (1, -1)] {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx >= 0 && yy >= 0 && xx < w && yy < h {
                            let j = (yy * w + xx) as usize;
                            if snapshot[j] {
                                let v = radiance[g.first + j];
                                sum = [sum[0] + v[0], sum[1] + v[1], sum[2] + v[2]];
                                n += 1;
                            }
                        }
                    }
                    if n > 0 {
                        radiance[g.first + i] = [sum[0] / n as f32, sum[1] / n as f32, sum[2] / n as f32];
                        known[i] = true;
                        changed = true;
                    }
                }
            }
            if !changed {
                break;
            }
        }
    }
}
