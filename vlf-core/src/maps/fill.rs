//! Texels that no ray crosses: their values, for rendering, from their neighbours.
//!
//! A texel's radiance is what its rays brought over its rays, `L_t = Φ_t / T_t`
//! ([`crate::propagate`]); a texel no ray crosses (`T_t = 0`) takes part in no exchange and has
//! no value of its own. It is still drawn — a look-up reads it bilinearly at a chart's border —
//! so it is given its neighbours' light. Nothing here changes the propagation: these texels
//! neither receive nor shoot, so their values add no energy anywhere.
//!
//! * **Within a chart** ([`within_charts`]): the mean of its covered neighbours among the eight
//!   around it, ring by ring outwards from the covered texels (border texels, a few rings).
//! * **Across charts** ([`AcrossCharts`]): a chart that no ray crosses at all. On a scan at a
//!   coarse resolution these are many: the full Stanford dragon (871 414 triangles, N = 64)
//!   leaves 9 648 charts of one to four texels at its creases, where no neighbour lies within
//!   the angle a chart grows over ([`super::charts`]), and every one of them was drawn black —
//!   a peppering of dark spots over a lit statue. Such a chart takes the light arriving at the
//!   charts it touches: at each of its vertices, the texel of every other chart that holds the
//!   vertex. A neighbour `d` of reflectance `ρ_d` and emission `Le_d` showing `L_d` receives
//!   `E/π = (L_d − Le_d) / ρ_d`; the chart's texel `t` shows `Le_c + ρ_t · E/π`, the mean of
//!   that estimate over its neighbours, per channel (a neighbour that reflects nothing of a
//!   channel says nothing of its irradiance in it). Charts whose neighbours are all dark take
//!   theirs from the charts filled in the ring before, as within a chart.
//!
//! The plan of the second step is a function of the scene, its texel atlas and which texels
//! rays cross — fixed once a propagation is set up — so it is found once
//! ([`AcrossCharts::plan`]) and applied to every snapshot. Both steps are deterministic
//! (charts and texels in index order), so every process finds the same bits.

use super::TexelAtlas;
use crate::scene::{Rgb, Scene, vertex_key};
use rustc_hash::FxHashMap as HashMap;

/// Fills the texels no ray crosses (`covered[t]` false) of every chart that some ray crosses
/// with the mean of their covered (or already filled) neighbours, a ring per pass.
pub fn within_charts(atlas: &TexelAtlas, covered: &[bool], radiance: &mut [[f32; 3]]) {
    for g in &atlas.charts {
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

/// How the charts that no ray crosses take their light from the charts they touch (see the
/// module docs): which charts, in which order, from which texels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AcrossCharts {
    /// The dark charts that have a source, ring by ring, in chart order within a ring.
    fills: Vec<ChartFill>,
    /// Dark charts that touch no chart with light (a loose piece no ray crosses): left as they
    /// are, zero.
    unreached: usize,
}

/// One dark chart and the texels it reads: (their chart, the texel's index in the atlas).
#[derive(Clone, Debug, PartialEq)]
struct ChartFill {
    chart: u32,
    sources: Vec<(u32, u32)>,
}

impl AcrossCharts {
    /// The plan for `scene`'s `atlas` where `covered[t]` says whether any ray crosses texel
    /// `t`. Costs a pass over the surfaces' vertices when some chart is dark, nothing otherwise.
    pub fn plan(scene: &Scene, atlas: &TexelAtlas, covered: &[bool]) -> AcrossCharts {
        let dark: Vec<bool> = (atlas.charts.iter())
            .map(|g| !covered[g.first..g.first + g.len()].iter().any(|&c| c))
            .collect();
        if !dark.iter().any(|&d| d) {
            return AcrossCharts::default();
        }
        // The charts at each vertex of a dark chart, increasing.
        let mut at_vertex: HashMap<[i64; 3], Vec<u32>> = HashMap::default();
        for (s, surface) in scene.surfaces.iter().enumerate() {
            if dark[atlas.chart_of[s] as usize] {
                for &p in &surface.vertices {
                    at_vertex.entry(vertex_key(p)).or_default();
                }
            }
        }
        for (s, surface) in scene.surfaces.iter().enumerate() {
            let chart = atlas.chart_of[s];
            for &p in &surface.vertices {
                if let Some(list) = at_vertex.get_mut(&vertex_key(p))
                    && list.last() != Some(&chart)
                {
                    list.push(chart);
                }
            }
        }
        for list in at_vertex.values_mut() {
            list.sort_unstable();
            list.dedup();
        }
        // Every dark chart's candidate sources: the texel of each other chart at each of its
        // vertices.
        let mut candidates: Vec<Vec<(u32, u32)>> = vec![Vec::new(); atlas.charts.len()];
        for (s, surface) in scene.surfaces.iter().enumerate() {
            let chart = atlas.chart_of[s];
            if !dark[chart as usize] {
                continue;
            }
            for &p in &surface.vertices {
                for &other in at_vertex.get(&vertex_key(p)).into_iter().flatten() {
                    if other != chart {
                        let g = &atlas.charts[other as usize];
                        candidates[chart as usize].push((other, g.index(g.coords(p)) as u32));
                    }
                }
            }
        }
        // Ring by ring: a dark chart reads the charts lit, or filled in an earlier ring.
        let mut known: Vec<bool> = dark.iter().map(|&d| !d).collect();
        let mut fills = Vec::new();
        loop {
            let ring: Vec<ChartFill> = (0..atlas.charts.len())
                .filter(|&c| !known[c])
                .filter_map(|c| {
                    let mut sources: Vec<(u32, u32)> = (candidates[c].iter().copied())
                        .filter(|&(other, _)| known[other as usize])
                        .collect();
                    sources.sort_unstable();
                    sources.dedup();
                    (!sources.is_empty()).then_some(ChartFill {
                        chart: c as u32,
                        sources,
                    })
                })
                .collect();
            if ring.is_empty() {
                break;
            }
            for f in &ring {
                known[f.chart as usize] = true;
            }
            fills.extend(ring);
        }
        let unreached = known.iter().filter(|&&k| !k).count();
        AcrossCharts { fills, unreached }
    }

    /// Number of dark charts given light, and of those that touch none.
    pub fn counts(&self) -> (usize, usize) {
        (self.fills.len(), self.unreached)
    }

    /// Gives every planned dark chart its neighbours' light (module docs): `albedo[t]` is texel
    /// `t`'s diffuse reflectance, `emission(c)` chart `c`'s emitted radiance (what its look
    /// shows on top of what it reflects).
    pub fn apply(
        &self,
        atlas: &TexelAtlas,
        albedo: &[Rgb],
        emission: impl Fn(usize) -> Rgb,
        radiance: &mut [[f32; 3]],
    ) {
        for fill in &self.fills {
            let (mut sum, mut n) = ([0.0f64; 3], [0u32; 3]);
            for &(other, t) in &fill.sources {
                let (rho, le, l) = (albedo[t as usize], emission(other as usize), radiance[t as usize]);
                for k in 0..3 {
                    if rho[k] > 0.0 {
                        sum[k] += (l[k] as f64 - le[k]).max(0.0) / rho[k];
                        n[k] += 1;
                    }
                }
            }
            let irradiance: Rgb = std::array::from_fn(|k| if n[k] > 0 { sum[k] / n[k] as f64 } else { 0.0 });
            let le = emission(fill.chart as usize);
            let g = &atlas.charts[fill.chart as usize];
            for t in g.first..g.first + g.len() {
                radiance[t] = std::array::from_fn(|k| (le[k] + albedo[t][k] * irradiance[k]) as f32);
            }
        }
    }
}
