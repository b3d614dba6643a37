//! `subsurf evaluate`: Table-1 statistics of a model on any frames of a scan.
use std::path::PathBuf;

use anyhow::Context;
use subsurf::evaluate::{EvalPoints, evaluate_frames_stored};
use subsurf::modelfile::ModelFile;
use subsurf::pipeline::PipelineOptions;

use super::progress::Bar;

/// Print mean and median log E (Eq. 8, Table 1) of a model on frames of a scan.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model (PLY written by `subsurf fit`).
    #[arg(long)]
    pub model: PathBuf,
    /// The scan dataset: its folder or its `scan.json`.
    #[arg(long)]
    pub scan: PathBuf,
    /// Frames to evaluate, e.g. `3,17,40-59` (default: all).
    #[arg(long)]
    pub frames: Option<String>,
    /// Frames to leave out.
    #[arg(long)]
    pub exclude_frames: Option<String>,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Samples closer than this to x_i (mm) are not compared (default: the model's fit's, from
    /// its file's `comment fitted` line, else 0.5).
    #[arg(long)]
    pub exclusion_radius: Option<f64>,
    /// Drop samples whose bilinear neighbourhood is not covered by the surface at x_o (a pixel
    /// centre seeing the background or another surface, counted as `samples.uncovered`). Off by
    /// default unless the model was fitted with it: it helps simulated scans seen past open
    /// boundaries, not the outside datasets.
    #[arg(long)]
    pub coverage_check: bool,
    /// Override the dataset's noise floor (default: the one the model was fitted with).
    #[arg(long)]
    pub noise_floor: Option<f64>,
    /// Judge the model by this version's defaults for the dataset rather than by the rules it
    /// was fitted with (noise floor, exclusion radius, grazing limits, coverage check, laser
    /// tolerance), which a model file records and `evaluate` otherwise uses.
    #[arg(long)]
    pub ignore_fit_record: bool,
    /// Where the model is compared with the pixels: at the mesh's vertices, or at surface points
    /// (the lattice points of level --surface-level on every face), which is where alpha finer
    /// than the mesh (a model's face lattice) can be judged: at vertices its detail is 0.
    #[arg(long, value_enum, default_value = "vertices")]
    pub at: At,
    /// Lattice level k of the surface points with --at surface (1..=8): (k+1)(k+2)/2 points per
    /// face. Fixed here, not by any model, so models compared at the same k see the same points.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u8).range(1..=8))]
    pub surface_level: u8,
    /// Memory for the sample store (MiB), as `subsurf fit --memory`.
    #[arg(long, default_value_t = (subsurf::store::DEFAULT_BUDGET >> 20) as u64)]
    pub memory: u64,
    /// Where the sample store's files go (`dataset`, a directory, `off`), as `subsurf fit
    /// --cache`: a store of a fit that holds these frames serves the evaluation.
    #[arg(long, default_value = "dataset")]
    pub cache: subsurf::pipeline::Cache,
}

/// Where `evaluate` compares.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum At {
    /// The mesh's vertices.
    Vertices,
    /// The lattice points of level --surface-level on every face.
    Surface,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (ds, frames) = super::open_frames(
        &args.scan,
        args.frames.as_deref(),
        args.exclude_frames.as_deref(),
    )?;
    let model = ModelFile::read(&args.model)
        .with_context(|| format!("reading {}", args.model.display()))?;
    // The model is judged on the terms it was fitted on (its file records them), unless told
    // otherwise: explicit flags override single rules, --ignore-fit-record all of them.
    let mut opts = PipelineOptions::for_dataset(&ds);
    let record = model.fitted_with.filter(|_| !args.ignore_fit_record);
    if let Some(r) = &record {
        opts = opts.with_fit_record(r);
    }
    if let Some(f) = args.noise_floor {
        opts = opts.with_noise_floor(f);
    }
    if let Some(x) = args.exclusion_radius {
        opts.samples.exclusion_radius_mm = x;
    }
    opts.samples.coverage |= args.coverage_check;
    let bar = if args.json {
        Bar::hidden()
    } else {
        Bar(indicatif::ProgressBar::new(0))
    };
    let points = match args.at {
        At::Vertices => EvalPoints::Vertices,
        At::Surface => EvalPoints::Surface {
            level: args.surface_level,
        },
    };
    let store = subsurf::pipeline::StoreOptions {
        budget: usize::try_from(args.memory.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
        cache: args.cache.clone(),
    };
    let (evals, stats) = evaluate_frames_stored(&ds, &model, &frames, &opts, points, &store, &bar)?;
    bar.finish_and_clear();
    let rgb = |v: [Option<f64>; 3]| v.map(|x| x.map_or(serde_json::Value::Null, |x| x.into()));
    let evaluated = evals.iter().filter(|e| e.skipped.is_none()).count();
    let local = subsurf::evaluate::local_share(&evals);
    if args.json {
        let out = serde_json::json!({
            "points": points,
            "frames": evaluated,
            "skipped": evals.len() - evaluated,
            "mean_log_e": rgb(stats.mean),
            "median_log_e": rgb(stats.median),
            "local_share": local,
            "options": {
                "from_model_file": record.is_some(),
                "noise_floor": opts.samples.noise_floor,
                "exclusion_radius_mm": opts.samples.exclusion_radius_mm,
                "cos_min": opts.samples.cos_min,
                "coverage": opts.samples.coverage,
                "laser_tolerance_mm": opts.spot.laser_tolerance_mm,
                "spot_cos_min": opts.spot_cos_min,
            },
            "per_frame": evals,
        });
        println!("{out}");
    } else {
        let f = |v: Option<f64>| subsurf::report::fmt::opt(v, subsurf::report::fmt::log_e);
        let at = match points {
            EvalPoints::Vertices => "at the vertices".to_string(),
            EvalPoints::Surface { level } => format!("at surface points of level {level}"),
        };
        println!(
            "{evaluated} frames evaluated {at}, {} skipped",
            evals.len() - evaluated
        );
        println!("            red      green    blue");
        println!(
            "mean log E  {:8} {:8} {:8}",
            f(stats.mean[0]),
            f(stats.mean[1]),
            f(stats.mean[2])
        );
        println!(
            "median      {:8} {:8} {:8}",
            f(stats.median[0]),
            f(stats.median[1]),
            f(stats.median[2])
        );
        if let Some(l) = local {
            println!(
                "samples predicted by the vertices' own models: {:.1} % (the rest by the homogeneous baseline beyond their sampled range)",
                100.0 * l
            );
        }
        println!(
            "options: {} (noise floor {:.3e}, exclusion radius {} mm, spot cos min {}, coverage check {})",
            if record.is_some() {
                "the model's fit's (its file's record)"
            } else {
                "this version's defaults for the dataset"
            },
            opts.samples.noise_floor,
            opts.samples.exclusion_radius_mm,
            opts.spot_cos_min,
            if opts.samples.coverage { "on" } else { "off" }
        );
        for e in evals.iter().filter(|e| e.skipped.is_some()).take(10) {
            println!(
                "skipped frame {}: {}",
                e.frame,
                e.skipped.as_deref().unwrap_or("")
            );
        }
    }
    Ok(())
}
