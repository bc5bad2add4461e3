//! The sweep: which propagations to run, running them with their time,
//! memory and size measured, and rendering each result every way the
//! renderer offers.
//!
//! Parameters are varied **one at a time** around a base point (the
//! defaults of `vlf run`): each varied parameter gives a curve of error
//! against time through the base point, which is what a user choosing one
//! setting needs, at a cost linear (not exponential) in the number of
//! values. Three kinds of variation cost different amounts:
//!
//! * propagation parameters (`l`, `N`, `m`, perturbation, filtering) need a
//!   propagation each;
//! * the iteration count needs none: the base propagation is replayed and
//!   its field rendered after every iteration, its time the setup plus the
//!   measured iterations so far;
//! * render settings (mirrors from the rays or ray traced, direct light from
//!   the field or exact) need only renders, and every propagation is
//!   rendered all ways (mirror modes only when the scene has mirrors).

use anyhow::{Context, Result};
use std::time::Instant;
use vlf_core::field::LightField;
use vlf_core::lookup::SpecularMode;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::{Camera, Image};
use vlf_core::scene::Scene;
use vlf_store::{Encoding, FieldJob, Stage, Store};

/// Which values each parameter takes (the base point's value is always
/// included). Empty lists leave a parameter at its base value.
#[derive(Clone, Debug)]
pub struct Sweep {
    /// `(l, N)` pairs refined together: the method converges only when the
    /// angular and the spatial sampling are refined jointly (finer rays with
    /// too few directions leave gaps between the directions' footprints).
    pub joint: Vec<(usize, u32)>,
    pub directions: Vec<usize>,
    pub resolution: Vec<u32>,
    pub tile: Vec<u32>,
    /// Texel edges, in ray spacings.
    pub texel: Vec<f64>,
    /// Render the base propagation after each of its iterations.
    pub iterations: bool,
    /// Add a run with perturbation switched to the other state.
    pub perturbation: bool,
    /// Add a run with filtering switched to the other state.
    pub filter: bool,
}

impl Sweep {
    /// The full sweep: (l, N) ∈ {(33, 16), (129, 32), (513, 64), (2049,
    /// 128)} together, l ∈ {33, 129, 513, 2049}, N ∈ {32, 64, 128}, m ∈ {4,
    /// 8, 16}, texels of 1 and 2 ray spacings, every iteration, perturbation
    /// and filtering toggled.
    pub fn full() -> Sweep {
        Sweep {
            joint: vec![(33, 16), (129, 32), (513, 64), (2049, 128)],
            directions: vec![33, 129, 513, 2049],
            resolution: vec![32, 64, 128],
            tile: vec![4, 8, 16],
            texel: vec![1.0, 2.0],
            iterations: true,
            perturbation: true,
            filter: true,
        }
    }
}

/// One propagation of the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct RunSpec {
    /// The curve it belongs to: `base`, `joint`, `directions`, `resolution`,
    /// `tile`, `perturbation` or `filter`.
    pub axis: &'static str,
    pub options: Options,
}

/// Short description of a propagation's options, e.g. `l=513 N=64 m=8 pert filt`.
pub fn describe(o: &Options) -> String {
    let stop = match o.stop {
        Stop::Iterations(k) => format!(" it={k}"),
        Stop::Converge { .. } => String::new(),
    };
    format!(
        "l={} N={} m={}{}{stop}{}{}",
        o.directions,
        o.grid.resolution,
        o.grid.tile,
        if o.texel_cells != 1.0 {
            format!(" texel={}", o.texel_cells)
        } else {
            String::new()
        },
        if perturbed(o) { " pert" } else { "" },
        if o.filter_sigma.is_some() { " filt" } else { "" },
    )
}

/// Whether `o` perturbs the directions (as the propagation decides it: some iterations, some
/// rotated copies).
pub fn perturbed(o: &Options) -> bool {
    o.perturbation.iterations > 0 && o.perturbation.count > 0
}

/// The propagations of `sweep` around `base`, base first, each distinct set
/// of options once. Values that do not make a valid grid (a tile that does
/// not divide N) are skipped with a warning.
pub fn plan(base: &Options, sweep: &Sweep) -> Vec<RunSpec> {
    let mut runs = vec![RunSpec {
        axis: "base",
        options: base.clone(),
    }];
    let mut add = |axis: &'static str, options: Options| {
        if let Err(e) = options.validate() {
            tracing::warn!("skipping {}: {e}", describe(&options));
            return;
        }
        if !runs.iter().any(|r| r.options == options) {
            runs.push(RunSpec { axis, options });
        }
    };
    for &(l, n) in &sweep.joint {
        match GridSize::new(n, base.grid.tile.min(n)) {
            Ok(grid) => add(
                "joint",
                Options {
                    directions: l,
                    grid,
                    ..base.clone()
                },
            ),
            Err(e) => tracing::warn!("skipping l = {l}, N = {n}: {e}"),
        }
    }
    for &l in &sweep.directions {
        add(
            "directions",
            Options {
                directions: l,
                ..base.clone()
            },
        );
    }
    for &n in &sweep.resolution {
        if let Ok(grid) = GridSize::new(n, base.grid.tile) {
            add("resolution", Options { grid, ..base.clone() });
        } else {
            tracing::warn!("skipping N = {n}: tile {} does not divide it", base.grid.tile);
        }
    }
    for &m in &sweep.tile {
        if let Ok(grid) = GridSize::new(base.grid.resolution, m) {
            add("tile", Options { grid, ..base.clone() });
        } else {
            tracing::warn!("skipping m = {m}: it does not divide N = {}", base.grid.resolution);
        }
    }
    for &texel_cells in &sweep.texel {
        add(
            "texel",
            Options {
                texel_cells,
                ..base.clone()
            },
        );
    }
    if sweep.perturbation {
        let mut o = base.clone();
        o.perturbation = if perturbed(base) {
            Default::default()
        } else {
            vlf_core::propagate::Perturbation {
                iterations: 2,
                count: 4,
            }
        };
        add("perturbation", o);
    }
    if sweep.filter {
        let mut o = base.clone();
        o.filter_sigma = if base.filter_sigma.is_some() { None } else { Some(1.0) };
        add("filter", o);
    }
    runs
}

/// A finished propagation and what it cost.
pub struct Run {
    pub spec: RunSpec,
    /// Building the subfields and texel maps, seconds.
    pub setup_s: f64,
    /// Seconds of each iteration.
    pub iteration_s: Vec<f64>,
    /// Setup plus all iterations.
    pub propagate_s: f64,
    /// Peak resident memory of the process during the propagation.
    pub peak_bytes: Option<u64>,
    /// Bytes of the field in memory (subfields, maps, mirror totals).
    pub field_bytes: usize,
    /// Bytes of the final field in a store, compressed, in the study's encoding.
    pub stored_bytes: u64,
    pub unshot_fraction: f64,
    pub field: LightField,
    /// Diffuse radiance after the first iteration (for exact direct light).
    pub first_radiance: Vec<[f32; 3]>,
}

impl Run {
    /// The field as it was after the first iteration.
    pub fn first_field(&self) -> LightField {
        let mut first = self.field.clone();
        first.radiance = self.first_radiance.clone();
        first.exact_direct = None;
        first
    }
}

/// Propagates `spec` on `scene` in this process (all rayon threads), timing
/// it and measuring its peak memory, then writes the field to an in-memory
/// store in `encoding` to measure its stored size.
pub fn propagate(scene: &Scene, spec: &RunSpec, encoding: Encoding) -> Result<Run> {
    let baseline = crate::memory::reset_peak();
    let started = Instant::now();
    let mut prop = Propagation::new(scene.clone(), spec.options.clone())
        .with_context(|| format!("cannot set up {}", describe(&spec.options)))?;
    let setup_s = started.elapsed().as_secs_f64();
    // What the plan made of the options for this scene: no perturbation where light reaches a
    // mirror, the filter by the mirrors light reaches. Rows say what ran.
    let mut spec = spec.clone();
    if !prop.plan.perturbation {
        spec.options.perturbation = Default::default();
    }
    spec.options.filter_sigma = prop.plan.filter;
    spec.options.filter_only_with_mirrors = false;
    // The job is created before iterating (it records the starting state) but not timed.
    let store = Store::open("memory://")?;
    let mut job = FieldJob::create(&store, &prop, encoding)?;
    let started = Instant::now();
    let mut first_radiance = None;
    while !prop.finished() {
        prop.step(|_| {});
        if first_radiance.is_none() {
            first_radiance = Some(prop.diffuse_radiance());
        }
    }
    let propagate_s = setup_s + started.elapsed().as_secs_f64();
    let peak_bytes = baseline.and_then(crate::memory::peak_since);
    let field_bytes = prop.field_bytes();
    let iteration_s = prop.stats.iter().map(|s| s.seconds).collect();
    let unshot_fraction = prop.unshot_fraction();

    let field = prop.into_field();
    job.finish(&field, false)?;
    let (stored_bytes, _) = job.stored_bytes(Stage::Field)?;
    Ok(Run {
        spec,
        setup_s,
        iteration_s,
        propagate_s,
        peak_bytes,
        field_bytes,
        stored_bytes,
        unshot_fraction,
        first_radiance: first_radiance.context("a propagation runs at least one iteration")?,
        field,
    })
}

/// The base propagation replayed, its field after every iteration (the
/// last one is the final field). Not timed: the times are the measured
/// run's.
pub fn fields_per_iteration(scene: &Scene, options: &Options) -> Result<Vec<LightField>> {
    let mut prop = Propagation::new(scene.clone(), options.clone())?;
    let mut fields = Vec::new();
    while !prop.finished() {
        prop.step(|_| {});
        fields.push(prop.field_now());
    }
    Ok(fields)
}

/// How a field is rendered.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderMode {
    pub specular: SpecularMode,
    /// Direct light computed exactly per pixel (with this many samples per
    /// emitter) instead of read from the field.
    pub exact_direct: Option<u32>,
}

impl RenderMode {
    pub fn specular_name(&self) -> &'static str {
        match self.specular {
            SpecularMode::Rays => "rays",
            SpecularMode::Trace { .. } => "trace",
        }
    }

    pub fn direct_name(&self) -> &'static str {
        if self.exact_direct.is_some() { "exact" } else { "field" }
    }
}

/// Renders `field` (whose first-iteration state is `first`, needed for
/// exact direct light) with `mode`; returns the image and seconds per frame.
pub fn render(
    field: &LightField,
    first: &LightField,
    camera: &Camera,
    samples: u32,
    mode: RenderMode,
) -> Result<(Image, f64)> {
    let started = Instant::now();
    let image = match mode.exact_direct {
        None => field.render(camera, samples, mode.specular),
        Some(n) => {
            let mut exact = field.clone();
            exact.use_exact_direct(first, n)?;
            exact.render(camera, samples, mode.specular)
        }
    };
    Ok((image, started.elapsed().as_secs_f64()))
}

/// Which pixels the errors look at, from the first hit of each pixel's
/// centre ray.
pub struct PixelMasks {
    /// Pixels showing an emitter's front, or next to one (8-neighbourhood):
    /// left out of every error (see [`vlf_core::render::compare`]).
    pub emitters: Vec<bool>,
    /// Pixels showing a mirror's front.
    pub mirrors: Vec<bool>,
}

impl PixelMasks {
    pub fn new(scene: &Scene, camera: &Camera) -> PixelMasks {
        let bvh = vlf_core::render::Bvh::build(scene);
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut emitter = vec![false; w * h];
        let mut mirrors = vec![false; w * h];
        for y in 0..h {
            for x in 0..w {
                let (origin, dir) = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
                let hit = bvh.intersect(scene, scene.normalisation.to_vlf(origin), dir, 0.0, f64::INFINITY);
                if let Some(hit) = hit.filter(|h| h.front) {
                    let m = scene.material(hit.surface);
                    emitter[y * w + x] = m.is_emitter();
                    mirrors[y * w + x] = m.is_mirror();
                }
            }
        }
        let mut emitters = vec![false; w * h];
        for y in 0..h {
            for x in 0..w {
                let near = (y.saturating_sub(1)..(y + 2).min(h))
                    .any(|j| (x.saturating_sub(1)..(x + 2).min(w)).any(|i| emitter[j * w + i]));
                emitters[y * w + x] = near;
            }
        }
        PixelMasks { emitters, mirrors }
    }

    /// The pixel selection of the study's errors.
    pub fn pixels(&self, with_mirrors: bool) -> vlf_core::render::compare::Pixels<'_> {
        vlf_core::render::compare::Pixels {
            exclude: Some(&self.emitters),
            mask: with_mirrors.then_some(&self.mirrors[..]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plan_varies_one_parameter_at_a_time_and_skips_invalid_grids() {
        let base = Options {
            perturbation: vlf_core::propagate::Perturbation {
                iterations: 2,
                count: 4,
            },
            filter_sigma: Some(1.0),
            ..Options::default()
        };
        let runs = plan(&base, &Sweep::full());
        assert_eq!(runs[0].options, base);
        // 3 joint (l, N) besides the base's, 3 other l, 2 other N, 2 other m,
        // 1 other texel, perturbation off, filter off.
        assert_eq!(
            runs.len(),
            1 + 3 + 3 + 2 + 2 + 1 + 1 + 1,
            "{:?}",
            runs.iter().map(|r| describe(&r.options)).collect::<Vec<_>>()
        );
        for r in runs[1..].iter().filter(|r| r.axis != "joint") {
            let o = &r.options;
            let changed = [
                o.directions != base.directions,
                o.grid.resolution != base.grid.resolution,
                o.grid.tile != base.grid.tile,
                o.texel_cells != base.texel_cells,
                o.perturbation != base.perturbation,
                o.filter_sigma != base.filter_sigma,
            ];
            assert_eq!(changed.iter().filter(|&&c| c).count(), 1, "{}", describe(o));
        }
        // A tile that does not divide N is skipped.
        let sweep = Sweep {
            joint: vec![],
            directions: vec![],
            resolution: vec![36],
            tile: vec![3],
            texel: vec![],
            iterations: false,
            perturbation: false,
            filter: false,
        };
        assert_eq!(plan(&base, &sweep).len(), 1);
    }

    #[test]
    fn masks_cover_the_emitter_and_its_rim_and_the_mirrors() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/mirrors.obj");
        let (scene, _) = vlf_core::scene::load_obj(&path, &Default::default()).unwrap();
        // Looking straight up from below the light: it fills the middle of the image.
        let camera = Camera::new(
            glam::DVec3::new(278.0, 400.0, 279.5),
            glam::DVec3::new(278.0, 600.0, 279.5),
            glam::DVec3::Z,
            60.0,
            32,
            32,
        )
        .unwrap();
        let masks = PixelMasks::new(&scene, &camera);
        let emitters = masks.emitters.iter().filter(|&&e| e).count();
        assert!(emitters > 0 && emitters < 32 * 32, "{emitters}");
        assert!(masks.emitters[16 * 32 + 16]);
        assert!(!masks.emitters[0]);
    }
}
