//! Power-preserving Gaussian filtering of Next maps.
//!
//! Perturbation and point-sampled rays leave high-frequency noise in the
//! maps; the paper smooths the Next maps with a small Gaussian before they
//! are shot. To keep energy balance exact the filter *scatters* power: texel
//! `i` spreads `Φ_i` over the texels `j` of the same surface that rays cross
//! (`T_j > 0`) with weights `g(|i − j|) / Σ_j g(|i − j|)`, which sum to one.

use crate::maps::TexelAtlas;
use crate::scene::Rgb;
use rayon::prelude::*;

pub(crate) fn gaussian(atlas: &TexelAtlas, area: &[f64], power: &mut [Rgb], sigma: f64) {
    let radius = (2.5 * sigma).ceil() as i64;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let filtered: Vec<Vec<Rgb>> = atlas
        .grids
        .par_iter()
        .map(|g| {
            let (w, h) = (g.width as i64, g.height as i64);
            let src = &power[g.first..g.first + g.len()];
            let valid = &area[g.first..g.first + g.len()];
            let mut out = vec![[0.0; 3]; g.len()];
            for y in 0..h {
                for x in 0..w {
                    let i = (y * w + x) as usize;
                    let p = src[i];
                    if p == [0.0; 3] {
                        continue;
                    }
                    let taps = || {
                        (-radius..=radius)
                            .flat_map(move |dy| (-radius..=radius).map(move |dx| (dx, dy)))
                            .filter_map(|(dx, dy)| {
                                let (xx, yy) = (x + dx, y + dy);
                                let j = (yy * w + xx) as usize;
                                (xx >= 0 && yy >= 0 && xx < w && yy < h && valid[j] > 0.0)
                                    .then(|| (j, kernel[(dx + radius) as usize] * kernel[(dy + radius) as usize]))
                            })
                    };
                    let norm: f64 = taps().map(|(_, g)| g).sum();
                    if norm <= 0.0 {
                        out[i] = [out[i][0] + p[0], out[i][1] + p[1], out[i][2] + p[2]];
                        continue;
                    }
                    for (j, g) in taps() {
                        let k = g / norm;
                        for c in 0..3 {
                            out[j][c] += p[c] * k;
                        }
                    }
                }
            }
            out
        })
        .collect();
    for (g, out) in atlas.grids.iter().zip(filtered) {
        power[g.first..g.first + g.len()].copy_from_slice(&out);
    }
}
