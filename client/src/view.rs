//! `vlf view`: a walkthrough of a job's field in a window (`vlf_viewer::view`).

use crate::{SpecularArg, ViewArgs};
use anyhow::{Context, Result, bail};
use glam::DVec3;
use vlf_store::FieldJob;
use vlf_viewer::{MirrorMode, ViewOptions, Walk};

pub fn run(args: ViewArgs) -> Result<()> {
    if args.depth > 64 {
        bail!("--depth must be at most 64, got {}", args.depth);
    }
    if !args.exposure.is_finite() {
        bail!("--exposure must be finite, got {}", args.exposure);
    }
    if let Some(speed) = args.speed
        && !(speed.is_finite() && speed > 0.0)
    {
        bail!("--speed must be a positive number of scene units per second, got {speed}");
    }
    let opened = args.source.open("view", false)?;
    let id = opened.id.clone();
    let job = FieldJob::open(&opened.store, &id).with_context(|| format!("cannot open job {id}"))?;
    let stage = opened.stage.unwrap_or_else(|| job.latest_stage());
    let field = job
        .load(stage)
        .with_context(|| format!("cannot read {} of job {id}", crate::render::describe(stage)))?;
    // The scene spans about 2 / scale scene units (the VLF frame is [-1, 1]³).
    let n = field.scene.normalisation;
    let size = 2.0 / n.scale;
    let eye = args.eye.unwrap_or(n.center);
    let target = args.target.unwrap_or(eye + DVec3::Z);
    if eye == target || !(eye.is_finite() && target.is_finite()) {
        bail!("--eye and --target must be finite and apart, got {eye} and {target}");
    }
    let walk = Walk::new(eye, target, args.fovy, args.speed.unwrap_or(0.25 * size));
    // The camera's own checks (field of view, size) before a window opens.
    walk.camera(args.size.0, args.size.1)?;
    let options = ViewOptions {
        title: format!("vlf view {id} {}", crate::render::describe(stage)),
        size: args.size,
        walk,
        exposure: args.exposure,
        mirrors: match args.specular {
            SpecularArg::Rays => MirrorMode::Rays,
            SpecularArg::Trace => MirrorMode::Trace { depth: args.depth },
        },
        vsync: !args.no_vsync,
        frames: args.frames,
        screenshot_dir: args.screenshot_dir,
        screenshot_at_exit: args.screenshot,
    };
    let stats = vlf_viewer::view(field, options)?;
    if stats.frames > 0 {
        println!(
            "{} frames in {:.2} s ({:.1} fps) on {}; first frame after {:.2} s",
            stats.frames,
            stats.seconds,
            stats.frames as f64 / stats.seconds.max(1e-9),
            stats.adapter,
            stats.first_frame_seconds.unwrap_or(f64::NAN)
        );
    }
    for path in &stats.screenshots {
        println!("screenshot → {}", path.display());
    }
    Ok(())
}
