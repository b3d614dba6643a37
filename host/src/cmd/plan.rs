//! `subsurf plan`: what a scan will do, before anything moves — frames, expected duration,
//! predicted coverage.
use anyhow::{Context, bail};
use std::path::PathBuf;

use subsurf::calib::Calibration;
use subsurf::dataset::{Mesh, load_obj};
use subsurf::scan::plan::{
    PlanOptions, PlanScene, RigTiming, ScanPlan, coverage_plan, dense_for_target, dense_raster,
    describe, load_plan,
};
use subsurf::scan::setup::{builtin_calibration, builtin_object, rig_timing, scan_exposures_s};

/// Which planner.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Planner {
    /// Aim only where visible vertices still lack an x_i within the target distance.
    Coverage,
    /// Fire at every raster point at every angle.
    Dense,
    /// Steered by predicted error (`subsurf scan` only): a sparse coverage start, then batch
    /// by batch where the model is least certain, until its cross-validated error stops
    /// falling. Its candidates are the dense raster's frames.
    Adaptive,
}

/// Object, calibration and planner options shared by `plan` and `scan`.
#[derive(Debug, Clone, clap::Args)]
pub struct PlanArgs {
    /// Object mesh (Wavefront OBJ, mm, object frame). Default: the built-in sphere.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Rig calibration (`calib.json`). Default: the simulated rig's built-in calibration.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// A plan saved by `subsurf plan --save` (overrides the planner options).
    #[arg(long)]
    pub plan: Option<PathBuf>,
    /// Planner.
    #[arg(long, value_enum, default_value = "coverage")]
    pub planner: Planner,
    /// Turntable angles (equally spaced).
    #[arg(long, default_value_t = 8)]
    pub angles: usize,
    /// Galvo raster points per axis over the object (the candidate spacing).
    #[arg(long, default_value_t = 24)]
    pub raster: usize,
    /// Every visible vertex needs a laser spot x_i this close, mm.
    #[arg(long, default_value_t = 2.0)]
    pub target_mm: f64,
    /// Fraction of coverable vertices to cover (coverage planner).
    #[arg(long, default_value_t = 1.0)]
    pub coverage: f64,
    /// Exposure time(s) in seconds; several (comma-separated) = HDR bracketing. Default
    /// `scan::setup::scan_exposures_s`: 0.05, or with the built-in object the simulated camera's.
    #[arg(long, value_delimiter = ',')]
    pub exposure: Vec<f64>,
    /// Built-in calibration's image size (pixels, square), when no --calib is given. Default:
    /// the size whose pixel footprint resolves the simulated material (`builtin_image_size`).
    #[arg(long)]
    pub size: Option<u32>,
    /// Turntable speed, steps/s (default: the rig's maximum).
    #[arg(long)]
    pub speed: Option<u32>,
    /// Turntable acceleration, steps/s² (default: the rig's maximum).
    #[arg(long)]
    pub accel: Option<u32>,
    /// Minimum time between capture starts, µs (never less than the exposure plus the rig
    /// profile's camera read-out; 0 = exactly that).
    #[arg(long, default_value_t = 0)]
    pub interval_us: u32,
}

/// The adaptive planner's stopping rules and batch sizes (`--planner adaptive`; `scan` and
/// `bench acquisition` embed them).
#[derive(Debug, Clone, clap::Args)]
pub struct AdaptiveArgs {
    /// Stop once the cross-validated held-out log E is at most this.
    #[arg(long)]
    pub until_error: Option<f64>,
    /// Stop before more frames than this.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Stop before more rig time than this (seconds, the plan's timing model).
    #[arg(long)]
    pub max_rig_time: Option<f64>,
    /// Frames of the sparse start (default: an eighth of the candidates that show a spot).
    #[arg(long)]
    pub start_frames: Option<usize>,
    /// Frames per batch (default: as many as the start).
    #[arg(long)]
    pub batch: Option<usize>,
    /// Batches after the best so far, none gaining on it by half an SE, before the scan stops.
    #[arg(long, default_value_t = subsurf::scan::adaptive::DEFAULT_PATIENCE)]
    pub patience: usize,
    /// Cross-validation folds of each assessment.
    #[arg(long, default_value_t = subsurf::crossval::DEFAULT_FOLDS)]
    pub cv_folds: usize,
    /// Which sparse start: 0 from the densest spot, any other a start drawn by this seed.
    #[arg(long, default_value_t = 0)]
    pub start_seed: u64,
}

impl AdaptiveArgs {
    /// The library's settings.
    pub fn settings(&self) -> subsurf::scan::adaptive::AdaptiveSettings {
        subsurf::scan::adaptive::AdaptiveSettings {
            start: self.start_frames,
            batch: self.batch,
            patience: self.patience,
            until_error: self.until_error,
            max_frames: self.max_frames,
            max_rig_s: self.max_rig_time,
            folds: self.cv_folds,
            start_seed: self.start_seed,
            ..Default::default()
        }
    }
}

/// Print a scan plan: frames, expected duration and predicted coverage.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub plan: PlanArgs,
    /// Also plan the dense raster that reaches the same coverage, for comparison.
    #[arg(long)]
    pub compare: bool,
    /// Save the plan as JSON (for `subsurf scan --plan`).
    #[arg(long)]
    pub save: Option<PathBuf>,
}

/// The resolved inputs of a plan.
pub struct Resolved {
    pub mesh: Mesh,
    pub calib: Calibration,
    pub builtin: bool,
}

/// Loads the mesh and calibration named by `a` (or the built-in ones).
pub fn resolve(a: &PlanArgs) -> anyhow::Result<Resolved> {
    let (mesh, builtin) = match &a.mesh {
        Some(p) => {
            let (mesh, report) =
                load_obj(p).with_context(|| format!("cannot load mesh {}", p.display()))?;
            let _ = report;
            (mesh, false)
        }
        None => (builtin_object().mesh(), true),
    };
    let calib = match &a.calib {
        Some(p) => Calibration::load(p)?,
        None if builtin => builtin_calibration(a.size),
        None => bail!("--calib calib.json is required with --mesh (run `subsurf calib` first)"),
    };
    Ok(Resolved {
        mesh,
        calib,
        builtin,
    })
}

/// Builds (or loads) the plan.
pub fn make_plan(a: &PlanArgs, r: &Resolved) -> anyhow::Result<(ScanPlan, PlanScene, PlanOptions)> {
    let scene = PlanScene::new(&r.mesh.positions, &r.mesh.triangles, &r.calib)?;
    let opts = PlanOptions {
        angles: a.angles,
        raster: a.raster,
        target_mm: a.target_mm,
        coverage: a.coverage,
        exposures_s: scan_exposures_s(&a.exposure, r.builtin),
        channel: subsurf::dataset::FrameChannel::Rgb,
    };
    let plan = if let Some(p) = &a.plan {
        load_plan(p)?
    } else {
        match a.planner {
            Planner::Coverage => coverage_plan(&scene, &opts)?,
            Planner::Dense | Planner::Adaptive => dense_raster(&scene, &opts)?,
        }
    };
    Ok((plan, scene, opts))
}

/// The simulated rig's timing (what `--sim` scans run on).
pub fn sim_timing(a: &PlanArgs) -> RigTiming {
    let p = subsurf_firmware::sim::SimParams::default();
    rig_timing(&p.profile, a.speed, a.accel, a.interval_us)
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let r = resolve(&args.plan)?;
    let (plan, scene, opts) = make_plan(&args.plan, &r)?;
    let timing = sim_timing(&args.plan);
    println!("{}", describe(&plan, &scene, opts.raster, &timing));
    if args.compare {
        let dense = dense_for_target(&scene, &opts)?;
        println!(
            "for comparison, the coarsest dense raster reaching {:.0}% coverage:",
            100.0 * opts.coverage
        );
        println!("{}", describe(&dense, &scene, opts.raster, &timing));
    }
    if let Some(p) = &args.save {
        std::fs::write(p, serde_json::to_string_pretty(&plan)? + "\n")
            .with_context(|| format!("cannot write {}", p.display()))?;
        println!("plan saved to {}", p.display());
    }
    Ok(())
}
