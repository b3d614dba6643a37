//! `subsurf demo`: the main job end to end on built-in defaults, no hardware, no arguments —
//! simulated rig, scan, fits with frames held out, renders against the ground truth, pictures,
//! `report.md`/`report.html` in one folder. Parsing and the stages' bars only; the run is
//! `subsurf::demo`, its report `subsurf::report::demo`.

use std::path::PathBuf;

use anyhow::Result;
use subsurf::demo::{DemoOptions, run_demo};

use super::progress::StageBars;

/// Run the whole chain on the simulated rig and write the results into one folder.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output folder (created; files in it are overwritten).
    #[arg(long, default_value = "subsurf-demo")]
    out: PathBuf,
    /// Camera image size of the simulated scan (pixels per side). Default: the size whose pixel
    /// footprint resolves the material (`scan::setup::builtin_image_size`).
    #[arg(long)]
    size: Option<u32>,
    /// Every vertex gets a laser spot x_i this close (mm). Default: the spacing the held-out
    /// fidelity needs (`scan::setup::builtin_target_mm`); larger is a faster, coarser preview.
    #[arg(long)]
    target_mm: Option<f64>,
    /// Turntable angles of the scan.
    #[arg(long, default_value_t = 8)]
    angles: usize,
    /// Laser raster per side (coverage planner picks from it).
    #[arg(long, default_value_t = 24)]
    raster: usize,
    /// Every N-th frame is held out of the fit and used to judge it.
    #[arg(long, default_value_t = 5)]
    hold_out: usize,
    /// Size of the rendered pictures (pixels per side).
    #[arg(long, default_value_t = 480)]
    picture: u32,
    /// Cycles samples per pixel of the "in Blender" render (when Blender is present; two seeds,
    /// the second for Cycles' own noise). 512: the noise, about 3 % per pixel on the default
    /// picture, is below the 5 % the export's Cycles render is from the truth, and both renders
    /// take about a minute on two cores (128 samples: 6 % noise, 7 % from the truth).
    #[arg(long, default_value_t = 512)]
    blender_samples: u32,
    /// Skip the "in Blender" render even when Blender is present.
    #[arg(long)]
    no_blender: bool,
}

pub fn run_cmd(args: Args) -> Result<()> {
    let options = DemoOptions {
        out: args.out.clone(),
        size: args.size,
        target_mm: args.target_mm,
        angles: args.angles,
        raster: args.raster,
        hold_out: args.hold_out,
        picture: args.picture,
        blender_samples: args.blender_samples,
        no_blender: args.no_blender,
    };
    let files = run_demo(
        &options,
        &StageBars("{msg:>12} {bar:40} {pos}/{len} {elapsed}"),
    )?;
    // One line for the files: off a terminal the whole run stays within a screen.
    let names: Vec<String> = files
        .iter()
        .map(|f| f.strip_prefix(&args.out).unwrap_or(f).display().to_string())
        .collect();
    println!(
        "demo results in {}: {}",
        args.out.display(),
        names.join(", ")
    );
    Ok(())
}
