//! `subsurf scan`: drive the rig and a camera into a scan dataset — planned, resumable.
use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use subsurf::link::SerialLink;
use subsurf::rig::{ClientConfig, RigClient};
use subsurf::scan::adaptive::{
    AcquisitionReport, AdaptiveError, AdaptiveSettings, FrameSource, cover_order, run_adaptive,
    run_fixed,
};
use subsurf::scan::driver::{FrameSink, ScanConfig, ScanError, run_with_reconnect_into};
use subsurf::scan::plan::PlanScene;
use subsurf::scan::plan::estimate_duration;
use subsurf::scan::replay::Replay;
use subsurf::scan::rigsource::RigSource;
use subsurf::scan::setup::{
    GROUND_TRUTH_FILE, camera_from_spec_with, rig_timing, sim_material, sim_noise_floor,
    write_ground_truth_of,
};

use super::plan::{PlanArgs, Planner, make_plan, resolve};
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
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Memory for the sample store extracted as frames arrive (MiB), as `subsurf fit --memory`.
    #[arg(long, default_value_t = (subsurf::store::DEFAULT_BUDGET >> 20) as u64)]
    pub memory: u64,
    /// Do not extract the frames' samples as they arrive (the first `subsurf fit` then decodes
    /// every frame itself).
    #[arg(long)]
    pub no_store: bool,
}

/// The adaptive planner's stopping rules and batch sizes (`--planner adaptive`).
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
    /// Batches in a row whose improvement is within its standard error before the scan stops.
    #[arg(long, default_value_t = subsurf::scan::adaptive::DEFAULT_PATIENCE)]
    pub patience: usize,
    /// Cross-validation folds of each assessment.
    #[arg(long, default_value_t = subsurf::crossval::DEFAULT_FOLDS)]
    pub cv_folds: usize,
}

impl AdaptiveArgs {
    /// The library's settings.
    pub fn settings(&self) -> AdaptiveSettings {
        AdaptiveSettings {
            start: self.start_frames,
            batch: self.batch,
            patience: self.patience,
            until_error: self.until_error,
            max_frames: self.max_frames,
            max_rig_s: self.max_rig_time,
            folds: self.cv_folds,
            near_mm: None,
        }
    }
}

/// Prints the learning curve of a steered scan as it goes, and its end.
fn report(rep: &AcquisitionReport, out: &std::path::Path) {
    println!(
        "{} planner: {} frames in {}; {}",
        rep.planner,
        rep.order().len(),
        out.display(),
        rep.stopped.as_deref().unwrap_or("not finished")
    );
    if !rep.curve.is_empty() {
        println!(
            "learning curve and frame order in {}",
            out.join(subsurf::scan::adaptive::REPORT_FILE).display()
        );
    }
}

/// `--replay`: a recorded dataset as the rig and camera.
fn replay(args: &Args, src: &std::path::Path, progress: &Bar) -> anyhow::Result<()> {
    let exclude = match &args.exclude_frames {
        Some(f) => subsurf::dataset::parse_frame_list(f).map_err(anyhow::Error::msg)?,
        None => Vec::new(),
    };
    let mut source = Replay::open(src, &args.out, &exclude).with_context(|| {
        format!(
            "cannot replay {} into {}",
            src.display(),
            args.out.display()
        )
    })?;
    let rep = match args.plan.planner {
        Planner::Adaptive => {
            run_adaptive(&mut source, &args.adaptive.settings(), progress, &mut |p| {
                progress.suspend(|| println!("{}", p.line()))
            })?
        }
        Planner::Dense => {
            let order: Vec<usize> = source.candidates().iter().map(|c| c.id).collect();
            run_fixed(&mut source, "dense", &order, progress)?
        }
        Planner::Coverage => {
            let order = cover_order(
                source.candidates(),
                &source.recorded().mesh.positions,
                args.plan.target_mm,
            );
            run_fixed(&mut source, "coverage", &order, progress)?
        }
    };
    progress.finish_and_clear();
    report(&rep, &args.out);
    Ok(())
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if let Some(src) = args.replay.clone() {
        let progress = if args.quiet {
            Bar::hidden()
        } else {
            Bar::with_template("{msg:>12} {bar:30} {pos}/{len}")
        };
        return replay(&args, &src, &progress);
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
    let progress = if args.quiet {
        Bar::hidden()
    } else {
        let p = Bar::new(ProgressBar::new(cfg.plan.frame_count() as u64));
        p.set_style(
            ProgressStyle::with_template(
                "{bar:30} {pos}/{len} frames  {per_sec}  ETA {eta}  {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        p
    };
    // Each frame is registered and sampled as it arrives, into the sample store `subsurf fit`
    // starts from (`pipeline::extract::ScanExtraction`).
    let memory = args.memory;
    let no_store = args.no_store;
    let sink = move || -> Option<Box<dyn FrameSink>> {
        (!no_store).then(|| {
            Box::new(subsurf::pipeline::extract::ScanExtraction::new(
                subsurf::pipeline::StoreOptions {
                    budget: usize::try_from(memory.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
                    cache: subsurf::pipeline::Cache::Dataset,
                },
            )) as Box<dyn FrameSink>
        })
    };
    if args.plan.planner == Planner::Adaptive && args.plan.plan.is_none() {
        let scene = PlanScene::new(&r.mesh.positions, &r.mesh.triangles, &r.calib)?;
        let timing = super::plan::sim_timing(&args.plan);
        let (rep, measured) = if args.sim {
            let connect = Box::new(|| {
                let link = subsurf::sim::SimLink::clean(subsurf::sim::VirtualRig::new(
                    subsurf::sim::SimParams::default(),
                ));
                RigClient::connect_with_seq(link, ClientConfig::default(), 1)
            });
            steer(
                &args,
                cfg,
                &scene,
                connect,
                camera.as_mut(),
                Box::new(sink),
                timing,
                &progress,
            )?
        } else {
            let port = args.port.clone().unwrap_or_default();
            let baud = args.baud;
            let connect = Box::new(move || {
                let link = SerialLink::open(&port, baud)?;
                RigClient::connect(link, ClientConfig::default())
            });
            steer(
                &args,
                cfg,
                &scene,
                connect,
                camera.as_mut(),
                Box::new(sink),
                timing,
                &progress,
            )?
        };
        progress.finish_and_clear();
        if let Some(field) = &material {
            write_ground_truth_of(&r.mesh, field, &args.out).with_context(|| {
                format!(
                    "cannot write {}",
                    args.out.join(GROUND_TRUTH_FILE).display()
                )
            })?;
        }
        report(&rep, &args.out);
        println!("rig time measured by this run: {measured:.2} s (homing of every batch included)");
        return Ok(());
    }
    let result = if args.sim {
        let mut connect = || {
            let link = subsurf::sim::SimLink::clean(subsurf::sim::VirtualRig::new(
                subsurf::sim::SimParams::default(),
            ));
            RigClient::connect_with_seq(link, ClientConfig::default(), 1)
        };
        run_with_reconnect_into(
            &cfg,
            &mut connect,
            camera.as_mut(),
            &progress,
            args.reconnects,
            sink(),
        )
    } else {
        let port = args.port.clone().unwrap_or_default();
        let baud = args.baud;
        let mut connect = || {
            let link = SerialLink::open(&port, baud)?;
            RigClient::connect(link, ClientConfig::default())
        };
        run_with_reconnect_into(
            &cfg,
            &mut connect,
            camera.as_mut(),
            &progress,
            args.reconnects,
            sink(),
        )
    };
    progress.finish_and_clear();
    match result {
        Ok(s) => {
            if let Some(field) = &material {
                // The simulated camera's material is known: write it as the floor to compare
                // fitted models with.
                write_ground_truth_of(&r.mesh, field, &args.out).with_context(|| {
                    format!(
                        "cannot write {}",
                        args.out.join(GROUND_TRUTH_FILE).display()
                    )
                })?;
            }
            let p = subsurf_firmware::sim::SimParams::default();
            let t = rig_timing(&p.profile, cfg.move_speed, cfg.move_accel, cfg.interval_us);
            let est = estimate_duration(&cfg.plan, &t, s.resumed_from);
            println!(
                "scan complete: {} frames in {} ({} written now, {} were already done); rig time \
                 {:.2} s (planned {:.2} s), wall {:.1} s, {} reconnects, {} camera retries",
                s.frames_total,
                s.scan_json.display(),
                s.frames_written,
                s.resumed_from,
                s.rig_seconds,
                est.total_s(),
                s.wall_seconds,
                s.reconnects,
                s.camera_retries
            );
            for line in
                subsurf::scan::dark::summary(&s.dark_frames, s.noise_floor, args.noise_floor)
            {
                println!("{line}");
            }
            match &s.sink {
                Some(Ok(m)) => println!("{m}"),
                Some(Err(e)) => println!(
                    "no sample store was kept ({e}): the first `subsurf fit` reads the frames"
                ),
                None => {}
            }
            Ok(())
        }
        Err(e @ ScanError::Interrupted { .. }) => {
            eprintln!("{e}");
            std::process::exit(130);
        }
        Err(e) => Err(e).context(format!("scan into {} stopped", args.out.display())),
    }
}

/// A steered scan over the rig `connect` reaches: the adaptive planner's loop with the rig and
/// camera as its frame source.
#[allow(clippy::too_many_arguments)]
fn steer<'a, L: subsurf::link::ByteLink>(
    args: &Args,
    cfg: ScanConfig,
    scene: &PlanScene,
    connect: subsurf::scan::rigsource::Connect<'a, L>,
    camera: &'a mut dyn subsurf::scan::camera::Camera,
    sink: subsurf::scan::rigsource::SinkFactory<'a>,
    timing: subsurf::scan::plan::RigTiming,
    progress: &Bar,
) -> anyhow::Result<(AcquisitionReport, f64)> {
    let out = cfg.out.clone();
    let mut source = RigSource::new(cfg, scene, connect, camera, sink, args.reconnects, timing)
        .with_context(|| format!("cannot open {}", out.display()))?;
    let rep = run_adaptive(&mut source, &args.adaptive.settings(), progress, &mut |p| {
        progress.suspend(|| println!("{}", p.line()))
    });
    match rep {
        Ok(rep) => Ok((rep, source.measured_rig_s())),
        Err(AdaptiveError::Scan(e @ ScanError::Interrupted { .. })) => {
            eprintln!("{e}");
            std::process::exit(130);
        }
        Err(e) => Err(e).context(format!("steered scan into {} stopped", out.display())),
    }
}
