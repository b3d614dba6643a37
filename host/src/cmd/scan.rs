//! `subsurf scan`: drive the rig and a camera into a scan dataset — planned, resumable.
use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use subsurf::link::SerialLink;
use subsurf::rig::{ClientConfig, RigClient};
use subsurf::scan::driver::{FrameSink, ScanConfig, ScanError, run_with_reconnect_into};
use subsurf::scan::plan::estimate_duration;
use subsurf::scan::setup::{
    GROUND_TRUTH_FILE, camera_from_spec_with, rig_timing, sim_noise_floor, write_ground_truth,
};

use super::plan::{PlanArgs, make_plan, resolve};
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
    /// Camera: `sim`, `dir:PATH` (a camera program saves triggered images there) or
    /// `cmd:"COMMAND {out}"` (run per exposure; `{out}`, `{exposure}`, `{frame}` are replaced).
    #[arg(long)]
    pub camera: String,
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

pub fn run(args: Args) -> anyhow::Result<()> {
    if !args.sim && args.port.is_none() {
        bail!("say which rig: --port PATH (serial) or --sim (simulated rig)");
    }
    if args.plan.mesh.is_none() && !args.sim && args.camera != "sim" {
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
    } else if args.camera == "sim" {
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
        &args.camera,
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
            if args.camera == "sim" {
                // The simulated camera's material is known: write it as the floor to compare
                // fitted models with.
                write_ground_truth(&r.mesh, &args.out).with_context(|| {
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
