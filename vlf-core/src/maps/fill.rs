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
//!   vertex and faces the same side (a wall's other face, back to back on the same vertices,
//!   sees other light). A neighbour texel `d` of reflectance `ρ_d` and emission `Le_d` showing
//!   `L_d` receives `E/π = (L_d − Le_d) / ρ_d`; over the neighbours, per channel, the estimate
//!   is the ratio of sums `E/π = Σ (L_d − Le_d) / Σ ρ_d` (a texel that reflects little of a
//!   channel, such as a dark pixel of a texture, weighs little in it rather than multiplying
//!   its light), taken from the texels rays cross where there are any, and the chart's texel
//!   `t` shows `Le_c + ρ_t · E/π`. Charts whose neighbours are all dark take theirs from the
//!   charts filled in the ring before, as within a chart; a chart that touches no light at all
//!   shows its own emission, `Le_c`.
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
    /// Dark charts that touch no chart with light (a loose piece no ray crosses): they show
    /// their emission alone.
    unreached: Vec<u32>,
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
        // vertices, where that chart faces the same side (its grid's normal, `u × v`, within
        // 90° of the dark chart's).
        let facing = |g: &super::TexelGrid| g.axis_u.cross(g.axis_v);
        let mut candidates: Vec<Vec<(u32, u32)>> = vec![Vec::new(); atlas.charts.len()];
        for (s, surface) in scene.surfaces.iter().enumerate() {
            let chart = atlas.chart_of[s];
            if !dark[chart as usize] {
                continue;
            }
            let normal = facing(&atlas.charts[chart as usize]);
            for &p in &surface.vertices {
                for &other in at_vertex.get(&vertex_key(p)).into_iter().flatten() {
                    let g = &atlas.charts[other as usize];
                    if other != chart && facing(g).dot(normal) > 0.0 {
                        candidates[chart as usize].push((other, g.index(g.coords(p)) as u32));
                    }
                }
            }
        }
        // Ring by ring: a dark chart reads the charts lit, or filled in an earlier ring; of a lit
        // chart, the texels rays cross where it has any at the vertices (a border texel's value
        // is its neighbours' mean, over its own reflectance).
        let mut known: Vec<bool> = dark.iter().map(|&d| !d).collect();
        let mut waiting: Vec<u32> = (0..atlas.charts.len() as u32).filter(|&c| dark[c as usize]).collect();
        let mut fills = Vec::new();
        loop {
            let ring: Vec<ChartFill> = (waiting.iter())
                .filter_map(|&c| {
                    let mut sources: Vec<(u32, u32)> = (candidates[c as usize].iter().copied())
                        .filter(|&(other, _)| known[other as usize])
                        .collect();
                    if sources.iter().any(|&(_, t)| covered[t as usize]) {
                        sources.retain(|&(_, t)| covered[t as usize]);
                    }
                    sources.sort_unstable();
                    sources.dedup();
                    (!sources.is_empty()).then_some(ChartFill { chart: c, sources })
                })
                .collect();
            if ring.is_empty() {
                break;
            }
            for f in &ring {
                known[f.chart as usize] = true;
            }
            waiting.retain(|&c| !known[c as usize]);
            fills.extend(ring);
        }
        AcrossCharts {
            fills,
            unreached: waiting,
        }
    }

    /// Number of dark charts given light, and of those that touch none.
    pub fn counts(&self) -> (usize, usize) {
        (self.fills.len(), self.unreached.len())
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
            // E/π = Σ (L_d − Le_d) / Σ ρ_d, per channel.
            let (mut reflected, mut rho) = ([0.0f64; 3], [0.0f64; 3]);
            for &(other, t) in &fill.sources {
                let (r, le, l) = (albedo[t as usize], emission(other as usize), radiance[t as usize]);
                for k in 0..3 {
                    reflected[k] += (l[k] as f64 - le[k]).max(0.0);
                    rho[k] += r[k];
                }
            }
            let irradiance: Rgb = std::array::from_fn(|k| if rho[k] > 0.0 { reflected[k] / rho[k] } else { 0.0 });
            let le = emission(fill.chart as usize);
            let g = &atlas.charts[fill.chart as usize];
            for t in g.first..g.first + g.len() {
                radiance[t] = std::array::from_fn(|k| (le[k] + albedo[t][k] * irradiance[k]) as f32);
            }
        }
        for &c in &self.unreached {
            let (le, g) = (emission(c as usize), &atlas.charts[c as usize]);
            radiance[g.first..g.first + g.len()].fill(le.map(|v| v as f32));
        }
    }
}
