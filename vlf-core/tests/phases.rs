//! Where an iteration's time goes (`Propagation::phase_times`): one record per iteration
//! stepped, each phase timed, and the phases together no longer than the step itself (they
//! follow each other inside it). Counted and compared, not timed against a budget.

use std::time::Instant;
use vlf_core::propagate::{Options, Propagation, Stop};
use vlf_core::psf::GridSize;
use vlf_core::scene::{ImportOptions, load_obj};

#[test]
fn every_iteration_records_its_phases_within_its_time() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
    let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
    let options = Options {
        directions: 129,
        grid: GridSize::new(32, 8).unwrap(),
        stop: Stop::Iterations(3),
        ..Options::default()
    };
    // One thread and two (stints claimed one at a time, `propagate::claim`).
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let mut p = Propagation::new(scene.clone(), options.clone()).unwrap();
            let mut steps = Vec::new();
            while !p.finished() {
                let t = Instant::now();
                p.step(|_| {});
                steps.push(t.elapsed().as_secs_f64());
            }
            assert_eq!(p.phase_times.len(), steps.len(), "{threads} threads");
            for (phases, &step) in p.phase_times.iter().zip(&steps) {
                for (name, t) in [
                    ("plan", phases.plan),
                    ("shoot", phases.shoot),
                    ("reduce", phases.reduce),
                    ("finish", phases.finish),
                ] {
                    assert!(t >= 0.0 && t.is_finite(), "{threads} threads: {name} took {t} s");
                }
                assert!(phases.shoot > 0.0, "{phases:?}");
                assert!(
                    phases.total() <= step,
                    "{threads} threads: {phases:?} in a step of {step} s"
                );
            }
        });
    }
}
