//! Power-preserving Gaussian filtering of Next maps.
//!
//! Perturbation and point-sampled rays leave high-frequency noise in the
//! maps; the paper smooths the Next maps with a small Gaussian before they
//! are shot. To keep energy balance exact the filter *scatters* power: texel
//! `i` spreads `Φ_i` over the texels `j` of the same surface that rays cross
//! (`T_j > 0`) with weights `g(|i − j|) / Σ_j g(|i − j|)`, which sum to one.
//!
//! The filter runs between iterations, where every worker waits for it, so
//! its inner loop matters: the taps of a texel are gathered once (weights
//! `g_x · g_y` of the taps inside the grid that rays cross, row by row) and
//! used for both the normalisation and the scatter. The result is the same,
//! to the bit, as the definition above evaluated tap by tap (tested against
//! it below).

use crate::maps::TexelAtlas;
use crate::scene::Rgb;
use rayon::prelude::*;

/// The 1-D weights `g(d) = exp(−d² / 2σ²)` for `d = −r..=r`, `r = ⌈2.5σ⌉`.
fn kernel(sigma: f64) -> (usize, Vec<f64>) {
    let radius = (2.5 * sigma).ceil() as i64;
    let kernel = (-radius..=radius)
        .map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    (radius as usize, kernel)
}

pub(crate) fn gaussian(atlas: &TexelAtlas, area: &[f64], power: &mut [Rgb], sigma: f64) {
    let (radius, kernel) = kernel(sigma);
    let filtered: Vec<Vec<Rgb>> = atlas
        .charts
        .par_iter()
        .map(|g| {
            let (w, h) = (g.width as usize, g.height as usize);
            let src = &power[g.first..g.first + g.len()];
            let valid = &area[g.first..g.first + g.len()];
            let mut out = vec![[0.0; 3]; g.len()];
            // (texel, weight) of the current texel's taps.
            let mut taps: Vec<(usize, f64)> = Vec::with_capacity((2 * radius + 1).pow(2));
            for y in 0..h {
                let rows = y.saturating_sub(radius)..(y + radius + 1).min(h);
                for x in 0..w {
                    let i = y * w + x;
                    let p = src[i];
                    if p == [0.0; 3] {
                        continue;
                    }
                    let columns = x.saturating_sub(radius)..(x + radius + 1).min(w);
                    taps.clear();
                    for yy in rows.clone() {
                        let gy = kernel[yy + radius - y];
                        for xx in columns.clone() {
                            let j = yy * w + xx;
                            if valid[j] > 0.0 {
                                taps.push((j, kernel[xx + radius - x] * gy));
                            }
                        }
                    }
                    let norm: f64 = taps.iter().map(|&(_, g)| g).sum();
                    if norm <= 0.0 {
                        out[i] = [out[i][0] + p[0], out[i][1] + p[1], out[i][2] + p[2]];
                        continue;
                    }
                    for &(j, g) in &taps {
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
    for (g, out) in atlas.charts.iter().zip(filtered) {
        power[g.first..g.first + g.len()].copy_from_slice(&out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::maps::TexelGrid;
    use glam::DVec3;

    /// The filter as defined: every tap of the (2r+1)² window tested on its
    /// own, the weights summed, then scattered.
    fn by_definition(atlas: &TexelAtlas, area: &[f64], power: &mut [Rgb], sigma: f64) {
        let (radius, kernel) = kernel(sigma);
        let radius = radius as i64;
        for g in &atlas.charts {
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
                        for c in 0..3 {
                            out[j][c] += p[c] * (g / norm);
                        }
                    }
                }
            }
            power[g.first..g.first + g.len()].copy_from_slice(&out);
        }
    }

    fn grid(width: u32, height: u32, first: usize) -> TexelGrid {
        TexelGrid {
            origin: DVec3::ZERO,
            axis_u: DVec3::X,
            axis_v: DVec3::Y,
            texel: 0.1,
            width,
            height,
            first,
        }
    }

    /// Two grids (one narrower than the window), texels that rays miss, an
    /// isolated texel with no valid neighbour, zero and non-zero power.
    fn fixture() -> (TexelAtlas, Vec<f64>, Vec<Rgb>) {
        let atlas = TexelAtlas {
            charts: vec![grid(13, 9, 0), grid(2, 11, 117), grid(1, 1, 139)],
            chart_of: vec![0, 1, 2],
            chart_material: vec![0, 0, 0],
            plane_rep: vec![0, 1, 2],
            texels: 140,
        };
        // A small deterministic generator: the test needs variety, not quality.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let area: Vec<f64> = (0..140).map(|i| if i % 7 == 3 { 0.0 } else { next() }).collect();
        let power: Vec<Rgb> = (0..140)
            .map(|i| match i % 5 {
                0 => [0.0; 3],
                _ => [next(), next() * 3.0, next() * 1e-3],
            })
            .collect();
        (atlas, area, power)
    }

    #[test]
    fn equals_the_definition_to_the_bit() {
        let (atlas, area, power) = fixture();
        for sigma in [0.3, 0.6, 1.0, 1.7, 4.0] {
            let (mut fast, mut reference) = (power.clone(), power.clone());
            gaussian(&atlas, &area, &mut fast, sigma);
            by_definition(&atlas, &area, &mut reference, sigma);
            let bits = |v: &[Rgb]| v.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&reference), "σ = {sigma}");
            assert_ne!(fast, power, "σ = {sigma}: the filter moved no power");
        }
    }

    #[test]
    fn preserves_power_and_keeps_it_on_valid_texels() {
        let (atlas, area, power) = fixture();
        let mut filtered = power.clone();
        gaussian(&atlas, &area, &mut filtered, 1.0);
        for c in 0..3 {
            let before: f64 = power.iter().map(|p| p[c]).sum();
            let after: f64 = filtered.iter().map(|p| p[c]).sum();
            assert!(
                (after - before).abs() <= 1e-12 * before,
                "channel {c}: {before} → {after}"
            );
        }
        // Power lands only where rays cross, except a texel that has no
        // valid tap at all, which keeps its own.
        for (i, p) in filtered.iter().enumerate() {
            if area[i] <= 0.0 && *p != [0.0; 3] {
                assert_eq!(*p, power[i], "texel {i} received power");
            }
        }
        assert_eq!(filtered[139], power[139], "a lone texel keeps its power");
    }
}
