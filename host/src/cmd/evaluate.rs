//! `subsurf evaluate`: Table-1 statistics of a model on any frames of a scan.
use std::path::PathBuf;

use anyhow::{Context, anyhow};
use subsurf::dataset::{Dataset, select_frames};
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
    /// Samples closer than this to x_i (mm) are not compared.
    #[arg(long, default_value_t = 0.5)]
    pub exclusion_radius: f64,
    /// Drop samples whose bilinear neighbourhood is not covered by the surface at x_o (a pixel
    /// centre seeing the background or another surface, counted as `samples.uncovered`). Off by
    /// default: it helps simulated scans seen past open boundaries, not the outside datasets.
    #[arg(long)]
    pub coverage_check: bool,
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
    let ds =
        Dataset::open(&args.scan).with_context(|| format!("opening {}", args.scan.display()))?;
    let model = ModelFile::read(&args.model)
        .with_context(|| format!("reading {}", args.model.display()))?;
    let frames = select_frames(
        ds.spec.frames.len(),
        args.frames.as_deref(),
        args.exclude_frames.as_deref(),
    )
    .map_err(|e| anyhow!(e))?;
    let mut opts = PipelineOptions::for_dataset(&ds);
    opts.samples.exclusion_radius_mm = args.exclusion_radius;
    opts.samples.coverage = args.coverage_check;
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
    if args.json {
        let out = serde_json::json!({
            "points": points,
            "frames": evaluated,
            "skipped": evals.len() - evaluated,
            "mean_log_e": rgb(stats.mean),
            "median_log_e": rgb(stats.median),
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
