//! The study end to end on a tiny scene with a given reference image (no
//! Python needed): the bundled Cornell box at 64×48 against Mitsuba 3.
//!
//! `data/cornell-64x48.pfm` was rendered by `vlf study` itself through
//! `study/mitsuba/reference.py` (Mitsuba 3.9.1 `scalar_rgb`, path tracer,
//! 16 384 samples per pixel, box filter), camera eye 278,273,-800 target
//! 278,273,0 fovy 39°; its own noise is a relative RMSE of about 1 % over the
//! compared pixels.

use glam::DVec3;
use std::path::Path;
use vlf_core::propagate::{Options, Perturbation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::render::Camera;
use vlf_study::report::Row;
use vlf_study::sweep::Sweep;
use vlf_study::{ReferenceSource, Study};

fn study(out: &Path) -> Study {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    Study {
        scene: root.join("../scenes/cornell.obj"),
        camera: Camera::new(
            DVec3::new(278.0, 273.0, -800.0),
            DVec3::new(278.0, 273.0, 0.0),
            DVec3::Y,
            39.0,
            64,
            48,
        )
        .unwrap(),
        samples: 2,
        base: Options {
            directions: 129,
            grid: GridSize::new(32, 8).unwrap(),
            stop: Stop::Converge {
                epsilon: 1e-3,
                max_iterations: 100,
            },
            perturbation: Perturbation {
                iterations: 2,
                count: 4,
            },
            filter_sigma: Some(1.0),
            // Texels of 2 ray spacings: with 1, each texel is crossed by about
            // one ray per direction and its aliasing noise shows at this size.
            texel_cells: 2.0,
            ..Options::default()
        },
        sweep: Sweep {
            joint: vec![(33, 16), (129, 32), (513, 64)],
            directions: vec![33],
            resolution: vec![16, 64],
            tile: vec![],
            texel: vec![],
            iterations: true,
            perturbation: false,
            filter: true,
        },
        encoding: vlf_store::Encoding::F16,
        trace_depth: 8,
        direct_samples: 32,
        block: 8,
        reference: ReferenceSource::Image(root.join("tests/data/cornell-64x48.pfm")),
        out: out.to_path_buf(),
    }
}

fn base_render<'a>(rows: &'a [Row], axis: &str, key: impl Fn(&Row) -> u64) -> Vec<(u64, &'a Row)> {
    let mut v: Vec<_> = rows
        .iter()
        .filter(|r| (r.axis == axis || r.axis == "base") && r.specular == "trace" && r.direct == "field")
        .map(|r| (key(r), r))
        .collect();
    v.sort_by_key(|p| p.0);
    v.dedup_by_key(|p| p.0);
    v
}

#[test]
fn the_study_runs_on_a_given_reference_and_its_error_falls_as_l_and_n_grow() {
    let out = tempfile::tempdir().unwrap();
    let s = study(out.path());
    let outcome = vlf_study::run(&s, &mut |_, _, _| {}).unwrap();
    let rows = &outcome.rows;

    // Runs: base (129/32), joint 33/16 and 513/64, l = 33 at N = 32, N = 16
    // and 64 at l = 129, filter off; each rendered two ways (no mirrors: no
    // "rays" mode), plus the iterations of the base.
    let runs = 1 + 2 + 1 + 2 + 1;
    assert!(rows.len() > 2 * runs, "{} rows", rows.len());
    assert_eq!(rows.iter().filter(|r| r.axis != "iterations").count(), 2 * runs);
    assert!(rows.iter().all(|r| r.specular == "trace"));

    // Error falls as l and N grow together (block error: what the field's
    // sampling decides, not sub-pixel edge placement), both with the field's
    // direct light and with exact direct light.
    for direct in ["field", "exact"] {
        let mut curve: Vec<&Row> = rows
            .iter()
            .filter(|r| (r.axis == "joint" || r.axis == "base") && r.direct == direct)
            .collect();
        curve.sort_by_key(|r| r.directions);
        assert_eq!(curve.len(), 3, "{direct}");
        for pair in curve.windows(2) {
            let (a, b) = (&pair[0], &pair[1]);
            assert!(
                b.error.block_error < a.error.block_error && b.error.relative_rmse < a.error.relative_rmse,
                "{direct}: {} → {}: {:?} → {:?}",
                a.label,
                b.label,
                a.error,
                b.error
            );
        }
        // And it is a real match, not just a trend: the finest is within 10 %.
        assert!(curve[2].error.block_error < 0.10, "{direct}: {:?}", curve[2].error);
    }
    // So does a finer grid at a fixed l, and more directions at a fixed N
    // from the coarsest.
    let n = base_render(rows, "resolution", |r| r.resolution as u64);
    assert_eq!(n.len(), 3);
    for pair in n.windows(2) {
        assert!(
            pair[1].1.error.relative_rmse < pair[0].1.error.relative_rmse,
            "{} → {}",
            pair[0].0,
            pair[1].0
        );
    }
    let l = base_render(rows, "directions", |r| r.directions as u64);
    assert!(l[1].1.error.block_error < l[0].1.error.block_error);

    // The energy is right: the converged base field's mean is within 4 % of
    // Mitsuba's (measured: −2.3 %; the reference's own noise is about 1 %).
    let base = rows.iter().find(|r| r.is_base()).unwrap();
    assert!(base.error.mean_error.abs() < 0.04, "{:?}", base.error);
    // Iterations converge towards it from below (light still unshot).
    let iterations: Vec<_> = rows.iter().filter(|r| r.axis == "iterations").collect();
    assert!(!iterations.is_empty());
    assert!(iterations[0].error.mean_error < -0.2, "{:?}", iterations[0].error);
    for pair in iterations.windows(2) {
        assert!(pair[1].error.mean_error > pair[0].error.mean_error);
    }
    // Their times are the base run's set-up and iterations so far: within the base's time.
    let last = iterations.last().unwrap();
    assert!(
        last.propagate_s > 0.0 && last.propagate_s <= base.propagate_s,
        "{} > {}",
        last.propagate_s,
        base.propagate_s
    );
    // The budget table offers settings, not the base's field part way.
    assert!(
        vlf_study::report::best_per_budget(rows)
            .iter()
            .all(|(_, r)| r.axis != "iterations")
    );
    // Exact direct light beats the field's own at the base point.
    let exact = rows.iter().find(|r| r.axis == "base" && r.direct == "exact").unwrap();
    assert!(exact.error.relative_rmse < base.error.relative_rmse);

    // The files: a CSV row per result, the report, plots and images.
    let csv = std::fs::read_to_string(out.path().join("study.csv")).unwrap();
    assert_eq!(csv.lines().count(), rows.len() + 1);
    assert!(csv.starts_with("axis,label,directions"));
    let md = std::fs::read_to_string(out.path().join("study.md")).unwrap();
    assert!(md.contains("| base | l=129 N=32 m=8 texel=2 pert filt |"), "{md}");
    assert!(md.contains("no equal-quality figures"));
    for plot in ["error-vs-time.png", "block-error-vs-time.png", "reference.png"] {
        let img = image::open(out.path().join(plot)).unwrap();
        assert!(img.width() > 0, "{plot}");
    }
    assert!(
        outcome
            .files
            .iter()
            .any(|f| f.to_string_lossy().ends_with("-error.png"))
    );
}

#[test]
fn a_reference_of_the_wrong_size_is_a_clear_error() {
    let out = tempfile::tempdir().unwrap();
    let mut s = study(out.path());
    s.camera = Camera::new(s.camera.eye, s.camera.target, s.camera.up, 39.0, 32, 24).unwrap();
    s.sweep = Sweep {
        joint: vec![],
        directions: vec![],
        resolution: vec![],
        tile: vec![],
        texel: vec![],
        iterations: false,
        perturbation: false,
        filter: false,
    };
    let e = format!("{:#}", vlf_study::run(&s, &mut |_, _, _| {}).err().unwrap());
    assert!(e.contains("64x48") && e.contains("32x24"), "{e}");
}
