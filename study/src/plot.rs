//! Plots of the study (PNG): error against propagation time, one curve per
//! varied parameter, both axes logarithmic, each point labelled with its
//! value. Text is drawn with an embedded DejaVu Sans (the `dejavu` crate)
//! through plotters' pure-Rust `ab_glyph` backend, so plotting needs no
//! system fonts.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Once;

use anyhow::{Context, Result, anyhow};
use plotters::prelude::*;

use crate::report::Row;

const WIDTH: u32 = 960;
const HEIGHT: u32 = 600;

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // DejaVu Sans is a valid TrueType font; failure would be a broken crate.
        if plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular()).is_err() {
            tracing::warn!("cannot register the embedded font: plots will have no text");
        }
    });
}

/// Which error a plot shows.
#[derive(Clone, Copy, Debug)]
pub enum Measure {
    RelativeRmse,
    BlockError,
}

impl Measure {
    fn of(self, row: &Row) -> f64 {
        match self {
            Measure::RelativeRmse => row.error.relative_rmse,
            Measure::BlockError => row.error.block_error,
        }
    }

    fn name(self, block: u32) -> String {
        match self {
            Measure::RelativeRmse => "relative RMSE".into(),
            Measure::BlockError => format!("error of {block}×{block} block means"),
        }
    }
}

/// One curve: name, and (time, error, label) points sorted by time.
type Curve = (String, Vec<(f64, f64, String)>);

/// The curves of a plot: for every varied parameter, its rows rendered the
/// base way plus the base point, ordered by the parameter's value; and the
/// directions again with exact direct light and with mirrors from the rays.
pub fn curves(rows: &[Row], measure: Measure) -> Vec<Curve> {
    let base_render = |r: &&Row| r.specular == "trace" && r.direct == "field";
    let Some(base) = rows.iter().find(|r| r.is_base()) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    let mut add = |name: String, mut points: Vec<(f64, f64, String, f64)>| {
        if points.len() >= 2 {
            points.sort_by(|a, b| a.3.total_cmp(&b.3));
            out.push((name, points.into_iter().map(|(t, e, l, _)| (t, e, l)).collect()));
        }
    };
    let point = |r: &Row, label: String, order: f64| (r.propagate_s, measure.of(r), label, order);
    for (axis, title, key) in [
        (
            "joint",
            "l and N together",
            (|r: &Row| r.directions as f64) as fn(&Row) -> f64,
        ),
        ("directions", "directions l", |r: &Row| r.directions as f64),
        ("resolution", "resolution N", |r: &Row| r.resolution as f64),
        ("tile", "tile m", |r: &Row| r.tile as f64),
        ("texel", "texel size", |r: &Row| r.texel),
    ] {
        let mut points: Vec<_> = rows
            .iter()
            .filter(base_render)
            .filter(|r| r.axis == axis)
            .map(|r| point(r, point_label(axis, r), key(r)))
            .collect();
        points.push(point(base, point_label(axis, base), key(base)));
        add(title.into(), points);
    }
    let iterations: Vec<_> = rows
        .iter()
        .filter(base_render)
        .filter(|r| r.axis == "iterations")
        .map(|r| point(r, format!("{}", r.iterations), r.iterations as f64))
        .collect();
    add("iterations".into(), iterations);
    for (specular, direct, title) in [
        ("trace", "exact", "l and N, exact direct light"),
        ("rays", "field", "l and N, mirrors from the rays"),
    ] {
        let points: Vec<_> = rows
            .iter()
            .filter(|r| r.specular == specular && r.direct == direct)
            .filter(|r| r.axis == "joint" || r.axis == "base")
            .map(|r| point(r, point_label("joint", r), r.directions as f64))
            .collect();
        add(title.into(), points);
    }
    // Single points: perturbation and filtering toggled.
    for axis in ["perturbation", "filter"] {
        if let Some(r) = rows.iter().filter(base_render).find(|r| r.axis == axis) {
            let label = if axis == "perturbation" {
                if r.perturbation { "perturbed" } else { "no perturbation" }
            } else if r.filter {
                "filtered"
            } else {
                "no filter"
            };
            out.push((label.into(), vec![(r.propagate_s, measure.of(r), String::new())]));
        }
    }
    out
}

/// Tick values 1, 2, 5 × 10^k within `[lo, hi]` (log axes).
fn one_two_five(lo: f64, hi: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let mut decade = 10f64.powf(lo.log10().floor());
    while decade <= hi {
        for m in [1.0, 2.0, 5.0] {
            let v = m * decade;
            if v >= lo && v <= hi {
                out.push(v);
            }
        }
        decade *= 10.0;
    }
    out
}

fn point_label(axis: &str, r: &Row) -> String {
    match axis {
        "joint" => format!("{}/{}", r.directions, r.resolution),
        "resolution" => r.resolution.to_string(),
        "tile" => r.tile.to_string(),
        "texel" => format!("texel {}", r.texel),
        _ => r.directions.to_string(),
    }
}

/// Whether `rows` make a curve of `measure` to draw: some sweep with two points, one of positive
/// time and error ([`error_vs_time`] refuses to draw nothing).
pub fn has_curve(rows: &[Row], measure: Measure) -> bool {
    (curves(rows, measure).iter())
        .flat_map(|(_, p)| p.iter())
        .any(|&(t, e, _)| t > 0.0 && e > 0.0)
}

/// Draws error against propagation time into `path` (PNG).
pub fn error_vs_time(path: &Path, title: &str, rows: &[Row], measure: Measure) -> Result<()> {
    register_font();
    let curves = curves(rows, measure);
    let all: Vec<(f64, f64)> = curves
        .iter()
        .flat_map(|(_, p)| p.iter().map(|&(t, e, _)| (t, e)))
        .filter(|(t, e)| *t > 0.0 && *e > 0.0)
        .collect();
    if all.is_empty() {
        return Err(anyhow!("nothing to plot"));
    }
    let bounds = |v: &mut dyn Iterator<Item = f64>| {
        let (lo, hi) = v.fold((f64::INFINITY, 0.0f64), |(lo, hi), x| (lo.min(x), hi.max(x)));
        (lo / 1.5, hi * 1.5)
    };
    // Room above the data for the legend (log axis: a factor).
    let (t0, t1) = bounds(&mut all.iter().map(|p| p.0));
    let (e0, e1) = bounds(&mut all.iter().map(|p| p.1));
    let e1 = e1 * 4.0;
    let block = rows.first().map_or(16, |r| r.error.block);

    let mut buffer = vec![255u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(48)
            .y_label_area_size(72)
            .build_cartesian_2d(
                (t0..t1).log_scale().with_key_points(one_two_five(t0, t1)),
                (e0..e1).log_scale().with_key_points(one_two_five(e0, e1)),
            )
            .map_err(|e| anyhow!("{e}"))?;
        chart
            .configure_mesh()
            .x_desc("propagation time, s (log)")
            .y_desc(format!("{} (log)", measure.name(block)))
            .y_label_formatter(&|v| {
                let p = v * 100.0;
                if p >= 10.0 {
                    format!("{p:.0} %")
                } else if p >= 1.0 {
                    format!("{p:.1} %")
                } else {
                    format!("{p:.2} %")
                }
            })
            .x_label_formatter(&|v| if *v >= 1.0 { format!("{v:.0}") } else { format!("{v}") })
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
        for (i, (name, points)) in curves.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            let line: Vec<(f64, f64)> = points.iter().map(|&(t, e, _)| (t, e)).collect();
            chart
                .draw_series(LineSeries::new(line.clone(), colour.stroke_width(2)))
                .map_err(|e| anyhow!("{e}"))?
                .label(name.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
            chart
                .draw_series(line.iter().map(|&p| Circle::new(p, 4, colour.filled())))
                .map_err(|e| anyhow!("{e}"))?;
            chart
                .draw_series(points.iter().filter(|p| !p.2.is_empty()).map(|(t, e, label)| {
                    EmptyElement::at((*t, *e))
                        + Text::new(label.clone(), (6, -16), ("sans-serif", 13).into_font().color(&colour))
                }))
                .map_err(|e| anyhow!("{e}"))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
        root.present().map_err(|e| anyhow!("{e}"))?;
    }
    image::RgbImage::from_raw(WIDTH, HEIGHT, buffer)
        .context("plot buffer size")?
        .save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// The curves' names and point counts, for the report and tests.
pub fn summary(rows: &[Row], measure: Measure) -> BTreeMap<String, usize> {
    curves(rows, measure).into_iter().map(|(n, p)| (n, p.len())).collect()
}
