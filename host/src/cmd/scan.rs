//! `subsurf scan`: drive the rig and a camera into a scan dataset — planned, resumable. Parsing,
//! planning (`cmd/plan.rs`), the camera, Ctrl-C and printing here; the scan is
//! `subsurf::scan::acquire`.
use anyhow::bail;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use subsurf::scan::acquire::{AcquireError, AcquireSettings, Order, RigAt, acquire, replay};
use subsurf::scan::driver::ScanConfig;
use subsurf::scan::setup::{camera_from_spec_with, sim_material, sim_noise_floor};

use super::plan::{AdaptiveArgs, PlanArgs, Planner, make_plan, resolve};
use super::progress::Bar;

/// Scan an object: home, then per turntable angle run the rig's capture program and write each
/// camera image to the dataset. Re-running the same command resumes an interrupted scan.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Serial port of the rig.
    #[arg(long, conflicts_with = "sim")]
    pub port: Option<String>,
    /// Baud rate.
    #[arg(long, default_value_t = 115_200)]
    pub baud: u32,
    /// Use the simulated rig in this process (virtual time).
    #[arg(long)]
    pub sim: bool,
    /// Camera: `sim` (or `sim:marble`, `sim:veined`, `sim:homogeneous`: the simulated
    /// material), `dir:PATH` (a camera program saves triggered images there) or
    /// `cmd:"COMMAND {out}"` (run per exposure; `{out}`, `{exposure}`, `{frame}` are replaced).
    #[arg(long, required_unless_present = "replay")]
    pub camera: Option<String>,
    /// Serve a recorded dataset's frames as the rig and camera: the planner's candidates are its
    /// frames (minus --exclude-frames); each frame asked for is copied into --out.
    #[arg(long, conflicts_with_all = ["port", "sim", "camera"])]
    pub replay: Option<PathBuf>,
    /// With --replay: frames that are never candidates (e.g. `96-103`, a test set).
    #[arg(long, requires = "replay")]
    pub exclude_frames: Option<String>,
    #[command(flatten)]
    pub adaptive: AdaptiveArgs,
    /// Output dataset directory (created, or resumed if it holds this scan).
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub plan: PlanArgs,
    /// Seed of the simulated camera's noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Laser channel index.
    #[arg(long, default_value_t = 0)]
    pub laser_channel: u8,
    /// Black level (DN) of the camera's 16-bit TIFF or PNG files (`dir:`/`cmd:` cameras; raw
    /// DNG files carry their own). Default 0.
    #[arg(long)]
    pub black_level: Option<f64>,
    /// White level (DN, where the sensor clips) of the camera's TIFF or PNG files. Default the
    /// largest 16-bit value, 65535.
    #[arg(long)]
    pub white_level: Option<f64>,
    /// Seconds to wait for each camera image.
    #[arg(long, default_value_t = 10.0)]
    pub camera_timeout: f64,
    /// Retries of a frame whose image did not arrive.
    #[arg(long, default_value_t = 2)]
    pub camera_retries: u32,
    /// Reconnection attempts after the link fails.
    #[arg(long, default_value_t = 20)]
    pub reconnects: u32,
    /// Megabytes to keep free on the output disk.
    #[arg(long, default_value_t = 16)]
    pub reserve_mb: u64,
    /// The radiance noise floor to write to scan.json (pixel / exposure_s). Default: the one
    /// measured from the dark frames the scan takes first (the `sim` camera: its sensor's own).
    #[arg(long)]
    pub noise_floor: Option<f64>,
    /// Take no dark frames (every laser off, one per exposure) before the first frame; without
    /// --noise-floor, scan.json then has none and `subsurf fit` measures one from the frames.
    #[arg(long)]
    pub no_dark_frames: bool,
    /// Memory for the sample store extracted as frames arrive (MiB), as `subsurf fit --memory`.
    #[arg(long, default_value_t = (subsurf::store::DEFAULT_BUDGET >> 20) as u64)]
    pub memory: u64,
    /// Do not extract the frames' samples as they arrive (the first `subsurf fit` then decodes
    /// every frame itself).
    #[arg(long)]
    pub no_store: bool,
}

/// The frame order the planner flag asks for.
fn order(p: Planner) -> Order {
    match p {
        Planner::Dense => Order::Dense,
        Planner::Coverage => Order::Coverage,
        Planner::Adaptive => Order::Adaptive,
    }
}

/// The scan's end: its lines after the bar, or the interrupt's message and exit code 130.
fn finish(progress: &Bar, result: Result<Vec<String>, AcquireError>) -> anyhow::Result<()> {
    progress.finish_and_clear();
    match result {
        Ok(lines) => {
            for line in lines {
                println!("{line}");
            }
            Ok(())
        }
        Err(AcquireError::Interrupted(e)) => {
            eprintln!("{e}");
            std::process::exit(130);
        }
        Err(e) => Err(e.into()),
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if let Some(src) = args.replay.clone() {
        let progress = Bar::with_template("{msg:>12} {bar:30} {pos}/{len}");
        let exclude = match &args.exclude_frames {
            Some(f) => subsurf::dataset::parse_frame_list(f).map_err(anyhow::Error::msg)?,
            None => Vec::new(),
        };
        let (planner, settings) = (order(args.plan.planner), args.adaptive.settings());
        let mut say = |line: &str| progress.suspend(|| println!("{line}"));
        let r = replay(
            &src,
            &args.out,
            &exclude,
            planner,
            &settings,
            args.plan.target_mm,
            &progress,
            &mut say,
        );
        return finish(&progress, r);
    }
    let camera_spec = args.camera.clone().unwrap_or_default();
    if !args.sim && args.port.is_none() {
        bail!("say which rig: --port PATH (serial) or --sim (simulated rig)");
    }
    let material = sim_material(&camera_spec);
    if args.plan.mesh.is_none() && !args.sim && material.is_none() {
        bail!("--mesh object.obj is required with a real rig (the built-in object is simulated)");
    }
    let r = resolve(&args.plan)?;
    let (plan, _scene, _opts) = make_plan(&args.plan, &r)?;
    let mut cfg = ScanConfig::new(
        args.out.clone(),
        plan,
        r.calib.clone(),
        subsurf::dataset::obj_bytes(&r.mesh),
    );
    if let Some(f) = args.noise_floor {
        if !(f.is_finite() && f >= 0.0) {
            bail!("--noise-floor must be a finite number >= 0, got {f}");
        }
        cfg.noise_floor = Some(f);
    } else if material.is_some() {
        cfg.noise_floor = Some(sim_noise_floor(&cfg.plan.exposures_s));
    }
    cfg.dark_frames = !args.no_dark_frames;
    cfg.laser_channel = args.laser_channel;
    cfg.move_speed = args.plan.speed;
    cfg.move_accel = args.plan.accel;
    cfg.interval_us = args.plan.interval_us;
    cfg.camera_retries = args.camera_retries;
    cfg.reserve_bytes = args.reserve_mb << 20;
    let stop = Arc::new(AtomicBool::new(false));
    cfg.stop = stop.clone();
    {
        let stop = stop.clone();
        // Ctrl-C: finish the frame in hand, laser off, journal consistent, exit.
        let _ = ctrlc::set_handler(move || stop.store(true, Ordering::Relaxed));
    }
    let mut camera = camera_from_spec_with(
        &camera_spec,
        &r.mesh,
        &r.calib,
        args.seed,
        Duration::from_secs_f64(args.camera_timeout.max(0.01)),
        subsurf::dataset::Levels {
            black: args.black_level,
            white: args.white_level,
        },
    )?;
    let progress = Bar::with_template("{bar:30} {pos}/{len} frames  {per_sec}  ETA {eta}  {msg}");
    subsurf::progress::Progress::set_length(&progress, cfg.plan.frame_count() as u64);
    let steer = (args.plan.planner == Planner::Adaptive && args.plan.plan.is_none()).then(|| {
        (
            args.adaptive.settings(),
            super::plan::sim_timing(&args.plan),
        )
    });
    let settings = AcquireSettings {
        rig: match &args.port {
            Some(port) if !args.sim => RigAt::Serial {
                port: port.clone(),
                baud: args.baud,
            },
            _ => RigAt::Sim,
        },
        reconnects: args.reconnects,
        material: material.as_ref(),
        memory: args.memory,
        no_store: args.no_store,
        steer,
        noise_floor: args.noise_floor,
    };
    let mut say = |line: &str| progress.suspend(|| println!("{line}"));
    let r = acquire(
        cfg,
        &r.mesh,
        &r.calib,
        camera.as_mut(),
        &settings,
        &progress,
        &mut say,
    );
    finish(&progress, r)
}
