//! The study's results: one [`Row`] per rendered field, the equal-quality
//! comparison with the path tracer, and the CSV and Markdown files.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context, Result};
use vlf_core::render::compare::{Comparison, Pixels, compare};

use crate::reference::Reference;

/// One field rendered one way, measured.
#[derive(Clone, Debug)]
pub struct Row {
    /// The curve it belongs to (see [`crate::sweep::RunSpec::axis`]); the
    /// iteration replay is `iterations`.
    pub axis: String,
    /// The propagation's options in short (`l=513 N=64 m=8 pert filt`).
    pub label: String,
    pub directions: usize,
    pub resolution: u32,
    pub tile: u32,
    /// Texel edge in ray spacings.
    pub texel: f64,
    pub iterations: u32,
    pub perturbation: bool,
    pub filter: bool,
    /// `rays` or `trace`.
    pub specular: &'static str,
    /// `field` or `exact`.
    pub direct: &'static str,
    /// Setup plus iterations, seconds.
    pub propagate_s: f64,
    /// One frame at the study's size, seconds.
    pub render_s: f64,
    pub peak_mb: Option<f64>,
    pub field_mb: f64,
    pub stored_mb: Option<f64>,
    pub unshot: f64,
    pub error: Comparison,
    /// Path tracer time to the same relative RMSE, seconds.
    pub pt_equal_s: Option<f64>,
    /// Path tracer time to the same block error, seconds.
    pub pt_equal_block_s: Option<f64>,
}

impl Row {
    /// Frames of a walkthrough after which the field (propagation once, then
    /// `render_s` per frame) has cost less than path tracing every frame to
    /// the same relative RMSE: `propagate_s / (pt_equal_s − render_s)`.
    /// `None` when the path tracer is faster per frame (or unknown).
    pub fn break_even_frames(&self) -> Option<f64> {
        let pt = self.pt_equal_s?;
        (pt > self.render_s).then(|| self.propagate_s / (pt - self.render_s))
    }

    /// Whether this is the base point rendered the base way.
    pub fn is_base(&self) -> bool {
        self.axis == "base" && self.specular == "trace" && self.direct == "field"
    }
}

/// The path tracer's error as a function of its time, fitted to its ladder
/// of timed renders: error `= c / √spp` (unbiased Monte Carlo), time
/// `= spp × seconds_per_spp`.
#[derive(Clone, Copy, Debug)]
pub struct PathTracerFit {
    pub rmse_at_1spp: f64,
    pub block_at_1spp: f64,
    pub seconds_per_spp: f64,
}

impl PathTracerFit {
    /// Fits the ladder of `reference` (`None` without one). `c` is the
    /// geometric mean of `e_i · √spp_i`, the least-squares fit in log space.
    pub fn new(reference: &Reference, block: u32, pixels: Pixels) -> Result<Option<PathTracerFit>> {
        if reference.ladder.is_empty() {
            return Ok(None);
        }
        let (mut log_rmse, mut log_block, mut seconds, mut spp) = (0.0, 0.0, 0.0, 0.0);
        for l in &reference.ladder {
            let e = compare(&l.image, &reference.image, block, pixels)?;
            let root = (l.spp as f64).sqrt();
            log_rmse += (e.relative_rmse * root).ln();
            log_block += (e.block_error * root).ln();
            seconds += l.seconds;
            spp += l.spp as f64;
        }
        let n = reference.ladder.len() as f64;
        Ok(Some(PathTracerFit {
            rmse_at_1spp: (log_rmse / n).exp(),
            block_at_1spp: (log_block / n).exp(),
            seconds_per_spp: seconds / spp,
        }))
    }

    /// Seconds the path tracer needs for a relative RMSE of `error`.
    pub fn seconds_for_rmse(&self, error: f64) -> f64 {
        (self.rmse_at_1spp / error).powi(2) * self.seconds_per_spp
    }

    /// Seconds the path tracer needs for a block error of `error`.
    pub fn seconds_for_block(&self, error: f64) -> f64 {
        (self.block_at_1spp / error).powi(2) * self.seconds_per_spp
    }
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or(String::new(), |v| format!("{v:.digits$}"))
}

/// Writes the rows as CSV (one header line, then one line per row).
pub fn write_csv(path: &Path, rows: &[Row]) -> Result<()> {
    let mut out = String::from(
        "axis,label,directions,resolution,tile,texel,iterations,perturbation,filter,specular,direct,\
         propagate_s,render_s,peak_mb,field_mb,stored_mb,unshot,relative_rmse,mean_error,block_error,\
         block,mirror_rmse,pt_equal_s,pt_equal_block_s,break_even_frames\n",
    );
    for r in rows {
        let e = &r.error;
        writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{:.4},{:.4},{},{:.3},{},{:.3e},{:.5},{:.5},{:.5},{},{},{},{},{}",
            r.axis,
            r.label,
            r.directions,
            r.resolution,
            r.tile,
            r.texel,
            r.iterations,
            r.perturbation,
            r.filter,
            r.specular,
            r.direct,
            r.propagate_s,
            r.render_s,
            opt(r.peak_mb, 1),
            r.field_mb,
            opt(r.stored_mb, 3),
            r.unshot,
            e.relative_rmse,
            e.mean_error,
            e.block_error,
            e.block,
            opt(e.masked_rmse, 5),
            opt(r.pt_equal_s, 3),
            opt(r.pt_equal_block_s, 3),
            opt(r.break_even_frames(), 1),
        )?;
    }
    std::fs::write(path, out).with_context(|| format!("cannot write {}", path.display()))
}

/// Everything the Markdown report says besides the rows.
pub struct Setting<'a> {
    pub scene: &'a str,
    pub camera: String,
    pub samples: u32,
    pub threads: usize,
    pub reference: &'a Reference,
    pub fit: Option<PathTracerFit>,
    pub encoding: &'a str,
    /// The reference's own noise over the compared pixels (relative RMSE).
    pub noise: Option<f64>,
    /// Pixels left out (emitters and their neighbours).
    pub excluded: usize,
}

/// Seconds with two significant digits (0.0042 s, 0.56 s, 21 s).
fn seconds(v: f64) -> String {
    if !v.is_finite() || v <= 0.0 {
        return format!("{v}");
    }
    let digits = (1 - v.log10().floor() as i32).max(0) as usize;
    format!("{v:.digits$}")
}

fn percent(v: f64) -> String {
    format!("{:.2} %", v * 100.0)
}

/// Writes the Markdown report: set-up, the table, the best setting per time
/// budget, and the equal-quality comparison.
pub fn write_markdown(path: &Path, cx: &Setting, rows: &[Row]) -> Result<()> {
    let mut md = String::new();
    writeln!(md, "# Accuracy study: {}\n", cx.scene)?;
    writeln!(
        md,
        "Camera {}, {}×{} samples per pixel (box filter), {} threads; stored sizes in {}.",
        cx.camera, cx.samples, cx.samples, cx.threads, cx.encoding
    )?;
    let r = cx.reference;
    write!(md, "Reference: {}", r.source)?;
    if let Some(s) = r.seconds {
        write!(md, ", rendered in {s:.1} s")?;
    }
    if let Some(n) = cx.noise {
        write!(md, "; its own noise is a relative RMSE of {}", percent(n))?;
    }
    writeln!(md, ".\n")?;
    writeln!(
        md,
        "Errors are relative to the reference's mean: RMSE over pixels, the signed error of the mean, \
         the RMSE of {b}×{b} block means (edges placed a pixel off do not count), and the RMSE over \
         mirror pixels. The {excluded} pixels showing an emitter or next to one are left out: both renderers \
         draw emitters exactly, only their sub-pixel coverage differs, and at many times the mean radiance \
         those edges would decide every number.\n",
        b = rows.first().map_or(16, |r| r.error.block),
        excluded = cx.excluded
    )?;
    writeln!(
        md,
        "| curve | field | specular | direct | iterations | propagate s | frame s | peak MB | stored MB | RMSE | mean | block | mirrors | PT same RMSE s | break-even frames |"
    )?;
    writeln!(
        md,
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )?;
    for row in rows {
        let e = &row.error;
        writeln!(
            md,
            "| {} | {} | {} | {} | {} | {:.2} | {:.3} | {} | {} | {} | {:+.2} % | {} | {} | {} | {} |",
            row.axis,
            row.label,
            row.specular,
            row.direct,
            row.iterations,
            row.propagate_s,
            row.render_s,
            opt(row.peak_mb, 0),
            opt(row.stored_mb, 2),
            percent(e.relative_rmse),
            e.mean_error * 100.0,
            percent(e.block_error),
            e.masked_rmse.map_or(String::new(), percent),
            opt(row.pt_equal_s, 2),
            opt(row.break_even_frames(), 1),
        )?;
    }

    writeln!(md, "\n## Best setting for a time budget\n")?;
    writeln!(
        md,
        "The lowest block error among the rows whose propagation fits the budget:\n"
    )?;
    writeln!(
        md,
        "| budget | field | specular | direct | propagate s | block | RMSE |"
    )?;
    writeln!(md, "|---:|---|---|---|---:|---:|---:|")?;
    for (budget, best) in best_per_budget(rows) {
        writeln!(
            md,
            "| {budget} s | {} | {} | {} | {:.2} | {} | {} |",
            best.label,
            best.specular,
            best.direct,
            best.propagate_s,
            percent(best.error.block_error),
            percent(best.error.relative_rmse)
        )?;
    }

    writeln!(md, "\n## Against path tracing every frame\n")?;
    match (&cx.fit, rows.iter().find(|r| r.is_base())) {
        (Some(fit), Some(base)) => {
            writeln!(
                md,
                "Fitted to the path tracer's timed renders: relative RMSE {} × spp^-½, block error {} × spp^-½, \
                 {:.3} s per sample per pixel at this size.\n",
                percent(fit.rmse_at_1spp),
                percent(fit.block_at_1spp),
                fit.seconds_per_spp
            )?;
            writeln!(
                md,
                "The base field ({}, mirrors {}, direct light from the field) has a relative RMSE of {}: the path tracer \
                 reaches that in {} s per frame, the field costs {} s once plus {} s per frame, so the field \
                 is cheaper from frame {} of a walkthrough on. Matching its block error instead takes the path \
                 tracer {} s per frame.",
                base.label,
                base.specular,
                percent(base.error.relative_rmse),
                seconds(base.pt_equal_s.unwrap_or(f64::NAN)),
                seconds(base.propagate_s),
                seconds(base.render_s),
                base.break_even_frames()
                    .map_or("— never (the path tracer is faster per frame)".into(), |f| format!(
                        "{:.0}",
                        f.ceil()
                    )),
                seconds(base.pt_equal_block_s.unwrap_or(f64::NAN)),
            )?;
        }
        _ => writeln!(
            md,
            "No timed path-tracer renders (the reference was given as an image): no equal-quality figures."
        )?,
    }
    std::fs::write(path, md).with_context(|| format!("cannot write {}", path.display()))
}

/// For budgets of 0.5, 1, 2, 5, 10, 30 and 60 s: the row of lowest block
/// error among those propagating within the budget (budgets nothing fits
/// are left out). The base's field after each iteration is left out: it is
/// not a setting one can ask for, and its label is the base's.
pub fn best_per_budget(rows: &[Row]) -> Vec<(f64, &Row)> {
    [0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0]
        .into_iter()
        .filter_map(|budget| {
            rows.iter()
                .filter(|r| r.axis != "iterations" && r.propagate_s <= budget)
                .min_by(|a, b| a.error.block_error.total_cmp(&b.error.block_error))
                .map(|r| (budget, r))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::LadderImage;
    use vlf_core::render::Image;

    fn flat(w: u32, h: u32, v: f32) -> Image {
        Image {
            width: w,
            height: h,
            pixels: vec![[v; 3]; (w * h) as usize],
        }
    }

    /// An image whose pixels alternate ±a around 1: relative RMSE a.
    fn noisy(a: f32) -> Image {
        let mut img = flat(8, 8, 1.0);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            *p = [if i % 2 == 0 { 1.0 + a } else { 1.0 - a }; 3];
        }
        img
    }

    #[test]
    fn the_fit_recovers_one_over_root_spp_and_inverts_it() {
        let reference = Reference {
            image: flat(8, 8, 1.0),
            source: "test".into(),
            spp: None,
            seconds: None,
            noise: None,
            halves: None,
            ladder: [1u32, 4, 16]
                .iter()
                .map(|&spp| LadderImage {
                    spp,
                    seconds: 0.5 * spp as f64,
                    image: noisy(0.4 / (spp as f32).sqrt()),
                })
                .collect(),
        };
        let fit = PathTracerFit::new(&reference, 4, Pixels::default()).unwrap().unwrap();
        assert!((fit.rmse_at_1spp - 0.4).abs() < 1e-6, "{fit:?}");
        assert!((fit.seconds_per_spp - 0.5).abs() < 1e-12);
        // 0.4 / √spp = 0.1 at 16 spp: 8 s.
        assert!((fit.seconds_for_rmse(0.1) - 8.0).abs() < 1e-4);
    }

    #[test]
    fn seconds_keep_two_significant_digits() {
        assert_eq!(seconds(0.0042), "0.0042");
        assert_eq!(seconds(0.56), "0.56");
        assert_eq!(seconds(7.09), "7.1");
        assert_eq!(seconds(21.4), "21");
    }

    #[test]
    fn break_even_is_propagation_over_the_per_frame_saving() {
        let error = compare(&flat(2, 2, 1.0), &flat(2, 2, 1.0), 1, Pixels::default()).unwrap();
        let mut row = Row {
            axis: "base".into(),
            label: "x".into(),
            directions: 513,
            resolution: 64,
            tile: 8,
            texel: 1.0,
            iterations: 4,
            perturbation: true,
            filter: true,
            specular: "trace",
            direct: "field",
            propagate_s: 10.0,
            render_s: 0.5,
            peak_mb: None,
            field_mb: 1.0,
            stored_mb: None,
            unshot: 1e-3,
            error,
            pt_equal_s: Some(2.5),
            pt_equal_block_s: None,
        };
        assert_eq!(row.break_even_frames(), Some(5.0));
        row.pt_equal_s = Some(0.4);
        assert_eq!(row.break_even_frames(), None);
        assert!(row.is_base());
        let mut worse = row.clone();
        worse.error.block_error = 0.5;
        worse.propagate_s = 0.2;
        let rows = [row.clone(), worse];
        let best = best_per_budget(&rows);
        assert_eq!(best[0].0, 0.5);
        assert_eq!(best[0].1.propagate_s, 0.2);
        assert_eq!(best.last().unwrap().1.propagate_s, 10.0);
    }
}
