//! `subsurf evaluate`: Table-1 statistics of a model on any frames of a scan.
use std::path::PathBuf;

use anyhow::Context;
use subsurf::evaluate::EvalPoints;
use subsurf::modelfile::ModelFile;

use super::progress::Bar;

/// Print mean and median log E (Eq. 8, Table 1) of a model on frames of a scan.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model written by `subsurf fit`: the empirical model (PLY) or a volume (JSON), told
    /// apart by the file's content.
    #[arg(long)]
    pub model: PathBuf,
    /// Photons per frame of a volume model's predictions (default 1 million; 4 million behind a
    /// dielectric boundary).
    #[arg(long)]
    pub photons: Option<usize>,
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
    /// A second model (PLY) judged on the same samples: prints this model's error minus that
    /// one's, per frame paired, with its clustered standard error.
    #[arg(long, conflicts_with = "images")]
    pub against: Option<PathBuf>,
    /// Judge the images in this folder (`<frame, 6 digits>.exr`, in the frames' units: pixel /
    /// exposure_s is radiance) as predictions of the frames instead of the model: any
    /// renderer's, e.g. `subsurf export --render`'s Cycles frames. Same samples, rules and
    /// Eq. 8 as judging the model; the model still says which light positions apply.
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// Also judge by rings around x_i: Eq. 8 over ring means of linear radiance (a renderer's
    /// noise averages out; docs/validation.md), JSON keys `ring_mean_log_e`, `ring_per_frame`,
    /// `rings` beside the per-sample ones.
    #[arg(long, conflicts_with = "against")]
    pub rings: bool,
    /// Change the evaluation protocol: samples closer than this to x_i (mm) are not compared
    /// (default: the protocol's 0.5 for every model). Figures under a changed protocol compare
    /// only with figures under the same one.
    #[arg(long)]
    pub exclusion_radius: Option<f64>,
    /// Change the evaluation protocol: drop samples whose bilinear neighbourhood is not covered
    /// by the surface at x_o (counted as `samples.uncovered`).
    #[arg(long)]
    pub coverage_check: bool,
    /// Change the evaluation protocol: this noise floor instead of the dataset's.
    #[arg(long)]
    pub noise_floor: Option<f64>,
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
    use subsurf::evaluate::run::{AnyModel, EvaluateSettings, evaluate_report, report_text};
    let (ds, frames) = super::open_frames(
        &args.scan,
        args.frames.as_deref(),
        args.exclude_frames.as_deref(),
    )?;
    let read = |p: &PathBuf| ModelFile::read(p).with_context(|| format!("reading {}", p.display()));
    let model = AnyModel::read(&args.model)?;
    let against = args.against.as_ref().map(read).transpose()?;
    let judged = model.judged(against.as_ref(), args.images.as_deref(), args.photons)?;
    let settings = EvaluateSettings {
        changes: subsurf::pipeline::ProtocolChanges {
            noise_floor: args.noise_floor,
            exclusion_radius_mm: args.exclusion_radius,
            coverage_check: args.coverage_check,
        },
        points: match args.at {
            At::Vertices => EvalPoints::Vertices,
            At::Surface => EvalPoints::Surface {
                level: args.surface_level,
            },
        },
        store: subsurf::pipeline::StoreOptions {
            budget: usize::try_from(args.memory.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
            cache: args.cache.clone(),
        },
        rings: args.rings,
    };
    let bar = match args.json {
        true => Bar::hidden(),
        false => Bar::new(indicatif::ProgressBar::new(0)),
    };
    let (report, rings) = evaluate_report(&ds, &frames, judged, &settings, &bar)?;
    bar.finish_and_clear();
    for w in report.in_sample_warning().iter().chain(&report.warnings) {
        eprintln!("{w}");
    }
    print!("{}", report_text(&report, rings.as_ref(), args.json)?);
    Ok(())
}
