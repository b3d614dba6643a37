//! `subsurf fit`: a scan dataset in, a per-vertex model (`docs/model-format.md`) and
//! `fit-report.json` out. Parsing only; the fit is `subsurf::fit_scan`.
use std::path::PathBuf;

use subsurf::fit::Preset;
use subsurf::fit_scan::{FitScanSettings, fit_scan};
use subsurf::modelfile::ColourMode;
use subsurf::volume::model::{ModelKind, VolumeFitSettings};

use super::progress::StageBars;

/// Colour handling.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Colour {
    /// One fall-off with channel scales s_g, s_b (Eq. 9, the paper's choice for objects).
    Shared,
    /// Separate fall-off per channel (Eq. 3 per channel).
    PerChannel,
}

/// Speed/accuracy presets ([`PipelineOptions::with_preset`]: the same in `bench tradeoff`).
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum PresetArg {
    /// Exact fit on all samples, n = 3, isotropic (default).
    Exact,
    /// Fast previews (binned, subsampled), isotropic.
    Draft,
    /// Binned sufficient statistics, 4 direction segments.
    Balanced,
    /// Exact, automatic order, 8 direction segments.
    Best,
    /// The exact default without its cost cuts (every fold's fill solved and refitted
    /// everywhere, every round scored until two in a row do not lower the best at all): the
    /// reference `subsurf bench equivalence` checks the default against.
    Reference,
}

/// Fit the per-vertex subsurface-scattering model to a scan (section 5).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scan dataset: its folder or its `scan.json`.
    #[arg(long)]
    pub scan: PathBuf,
    /// Output model (binary PLY; a volume's JSON, its name ending in `.json`).
    #[arg(long, default_value = "model.ply")]
    pub out: PathBuf,
    /// `empirical`: the per-vertex model; `volume`: a homogeneous scattering volume on the
    /// scan's mesh (docs/volume.md), of the flags below only the frames' and `--noise-floor`.
    #[arg(long, default_value = "empirical")]
    pub model_kind: ModelKind,
    /// Volume fit: photons per frame and round (default 1,500; 6,000 behind a dielectric).
    #[arg(long)]
    pub volume_photons: Option<usize>,
    /// Volume fit: rounds of trace and fit (default 12).
    #[arg(long)]
    pub volume_rounds: Option<usize>,
    /// Volume fit: then a grid of this many cells along the longest side, cell by cell (default
    /// 1: homogeneous; docs/volume.md).
    #[arg(long, default_value_t = 1)]
    pub volume_cells: usize,
    /// Volume fit: the boundary, `index-matched` or `dielectric:IOR:ROUGHNESS` (GGX width α).
    #[arg(long, default_value = "index-matched")]
    pub volume_boundary: subsurf::volume::model::BoundaryModel,
    /// Volume fit: the phase function's Henyey-Greenstein g, held fixed.
    #[arg(long, default_value_t = 0.0)]
    pub volume_g: f64,
    /// Output report (default: `fit-report.json` beside the model).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Frames to use, e.g. `3,17,40-59` (default: all).
    #[arg(long)]
    pub frames: Option<String>,
    /// Frames to hold out of the fit.
    #[arg(long)]
    pub exclude_frames: Option<String>,
    /// Colour model.
    #[arg(long, value_enum, default_value = "shared")]
    pub colour: Colour,
    /// Direction segments m (Eq. 3); 1 = isotropic; `auto` chooses m among 1, 2, 4, 8 by
    /// cross-validation (`--cv-folds`): the simplest whose held-out error is within one standard
    /// error of the best (the candidates are in the report's `cross_validation`). Default: the
    /// preset's (1 for exact).
    #[arg(long)]
    pub segments: Option<String>,
    /// Folds of the cross-validation inside the fit (whole turntable angles, or spread raster
    /// positions on a one-angle scan): each fold's frames are predicted by a fit of the others,
    /// which chooses `--segments auto` and the number of alpha rounds. 0 or 1: no
    /// cross-validation (the rounds run to `--alpha-rounds` or convergence). Default: 5; 0 for
    /// `--preset draft` unless `--segments auto` (a preview does not pay for the fold fits,
    /// which cost several times the fit itself: BENCHMARKS.md).
    #[arg(long)]
    pub cv_folds: Option<usize>,
    /// The folds' alpha rounds stop once this many rounds in a row have not lowered the best
    /// cross-validated error by half a standard error (early stopping; the report lists the
    /// rounds scored). 0: score every round up to `--alpha-rounds`. With `--preset reference`
    /// any lower error counts.
    #[arg(long, default_value_t = subsurf::crossval::DEFAULT_PATIENCE)]
    pub cv_patience: usize,
    /// Exponential terms n (Eq. 1): the largest n a light position may use (each chooses its
    /// own n and m, see `--fixed-order`), or `auto` for the smallest order within 1 % of the
    /// best. Default: the preset's (3 for exact).
    #[arg(long)]
    pub terms: Option<String>,
    /// Fit every light position at the largest n and m (`--terms`, `--segments`) instead of
    /// choosing each one's order from its samples (AICc, `subsurf_model::order`).
    #[arg(long)]
    pub fixed_order: bool,
    /// Solver preset.
    #[arg(long, value_enum, default_value = "exact")]
    pub preset: PresetArg,
    /// Samples closer than this to x_i are dropped (mm).
    #[arg(long, default_value_t = 0.5)]
    pub exclusion_radius: f64,
    /// A vertex whose closest x_i is farther than this has no data (mm).
    #[arg(long, default_value_t = 2.0)]
    pub max_distance: f64,
    /// Frames whose laser spots x_i lie within this distance (mm) are one light position, fitted
    /// together (default: half the mesh's median edge length; 0: only identical x_i).
    #[arg(long)]
    pub pool_distance: Option<f64>,
    /// Fits with log E (Eq. 8) above this are failures, interpolated from neighbours.
    #[arg(long, default_value_t = 1.0)]
    pub max_log_e: f64,
    /// Fits with log E above this multiple of the median fit's (and above 0.03) are outliers,
    /// interpolated from neighbours (`inf` disables).
    #[arg(long, default_value_t = 3.0)]
    pub outlier_factor: f64,
    /// At most this many extra fit rounds on samples divided by the previous round's alpha
    /// (Eq. 6); they stop early when alpha has converged (`--alpha-tolerance`).
    #[arg(long, default_value_t = 8)]
    pub alpha_rounds: usize,
    /// Convergence of the alpha rounds: RMS change of ln alpha between rounds.
    #[arg(long, default_value_t = 2e-3)]
    pub alpha_tolerance: f64,
    /// Eq. 6's upper threshold t1 as a share of each light position's brightest sample: brighter
    /// samples (near x_i, not yet multiple scattering) do not enter alpha ("inf", the default:
    /// none).
    /// By default chosen per scan by cross-validation, none against 0.3
    /// (`crossval::T1_CANDIDATE`); given, it is fixed.
    #[arg(long)]
    pub alpha_t1_share: Option<f64>,
    /// alpha finer than the mesh (section 5's "higher resolution texture"): `auto` estimates
    /// Eq. 6 per point of a per-face lattice whose level follows the pixel footprint (at most
    /// 8) and writes it (`face_alpha`) where the images show detail above the noise; a number
    /// 1..=8 caps the level; `off` keeps alpha per vertex only. By default `auto`, and the
    /// lattice found is written only when the cross-validation's folds, judged at surface
    /// points, say it predicts better than alpha per vertex; given, it is fixed (not judged).
    #[arg(long)]
    pub alpha_lattice: Option<subsurf::pipeline::AlphaLattice>,
    /// Eq. 6's shrinkage of alpha towards 1, as a multiple of the empirical-Bayes pseudo-count
    /// (the noise within a texel over the texture's variance between texels): 1 = the empirical
    /// one, 0 = none (the plain geometric mean of s / R_d), `inf` = no texture (alpha = 1).
    #[arg(long, default_value_t = 1.0)]
    pub alpha_shrinkage: f64,
    /// Frames whose laser spot the camera sees more grazing than this (cos θ at the spot) are
    /// not fitted, nor evaluated with the model: their spot is foreshortened and x_i least
    /// certain. Registration keeps spots down to cos θ = 0.1.
    #[arg(long, default_value_t = subsurf::spot::SPOT_COS_MIN)]
    pub spot_cos_min: f64,
    /// Largest disagreement between detected spot and laser ray (mm).
    #[arg(long, default_value_t = 2.0)]
    pub laser_tolerance: f64,
    /// Override the dataset's noise floor.
    #[arg(long)]
    pub noise_floor: Option<f64>,
    /// Drop samples whose bilinear neighbourhood is not covered by the surface at x_o (a pixel
    /// centre seeing the background or another surface, counted as `samples.uncovered`). Off by
    /// default: it helps simulated scans seen past open boundaries, not the outside datasets.
    #[arg(long)]
    pub coverage_check: bool,
    /// Validate first: hold out a spread of frames (whole turntable angles when the scan has at
    /// least 4), fit the rest, report held-out Table-1 statistics next to the in-sample ones and
    /// the homogeneous baseline's, then fit on everything (`docs/validation.md`).
    #[arg(long)]
    pub validate: bool,
    /// Memory for the sample store (MiB): the samples of every frame are read once and kept in
    /// memory up to this, the rest read back from the store's files per use.
    #[arg(long, default_value_t = (subsurf::store::DEFAULT_BUDGET >> 20) as u64)]
    pub memory: u64,
    /// Where the sample store's files go: `dataset` (`.subsurf-cache/` in the dataset, reused by
    /// later fits of the same frames with the same extraction options), a directory, or `off`.
    #[arg(long, default_value = "dataset")]
    pub cache: subsurf::pipeline::Cache,
    /// Skip the check that the scan's laser spots (as the extraction pass detected them) lie on
    /// the mesh surface (a mesh in another pose or unit fails it: run `subsurf align` first).
    #[arg(long)]
    pub skip_mesh_check: bool,
    /// Measure the noise floor from the frames also when scan.json gives one, and warn when the
    /// two differ by more than 2x (reads up to 16 frames a second time; without a floor in
    /// scan.json it is always measured).
    #[arg(long)]
    pub check_noise_floor: bool,
    /// Do not draw the PNGs beside the report (`<report>-error-map.png`: log E(x_i) per vertex,
    /// Eq. 8; `<report>-model.png`: alpha, reflectance, reach and vertex status).
    #[arg(long)]
    pub no_pictures: bool,
    /// Fit every vertex of the mesh even when it is far finer than the frames' pixels (by
    /// default such a mesh is fitted at the level of detail the pixels support, one vertex per
    /// pixel footprint, and the model is prolonged to every vertex; `--preset reference` never
    /// coarsens).
    #[arg(long)]
    pub full_mesh: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (ds, frames) = super::open_frames(
        &args.scan,
        args.frames.as_deref(),
        args.exclude_frames.as_deref(),
    )?;
    let stages = StageBars("{msg:>12} {bar:40} {pos}/{len} {eta}");
    if args.model_kind == ModelKind::Volume {
        let mut s = VolumeFitSettings::defaults(&ds, args.out)
            .behind(args.volume_boundary.surface()?, args.volume_g);
        s.fit.photons = args.volume_photons.unwrap_or(s.fit.photons);
        s.fit.rounds = args.volume_rounds.unwrap_or(s.fit.rounds);
        s.fit.floor = args.noise_floor.unwrap_or(s.fit.floor);
        s.cells = args.volume_cells;
        subsurf::volume::model::fit_volume(&ds, &frames, &s, &stages)?;
        return Ok(());
    }
    let preset = match args.preset {
        PresetArg::Exact | PresetArg::Reference => None,
        PresetArg::Draft => Some(Preset::Draft),
        PresetArg::Balanced => Some(Preset::Balanced),
        PresetArg::Best => Some(Preset::Best),
    };
    let settings = FitScanSettings {
        scan: args.scan,
        out: args.out,
        report: args.report,
        colour: match args.colour {
            Colour::Shared => ColourMode::Shared,
            Colour::PerChannel => ColourMode::PerChannel,
        },
        segments: args.segments,
        cv_folds: args.cv_folds,
        cv_patience: args.cv_patience,
        terms: args.terms,
        fixed_order: args.fixed_order,
        preset,
        reference: matches!(args.preset, PresetArg::Reference),
        exclusion_radius: args.exclusion_radius,
        max_distance: args.max_distance,
        pool_distance: args.pool_distance,
        max_log_e: args.max_log_e,
        outlier_factor: args.outlier_factor,
        alpha_rounds: args.alpha_rounds,
        alpha_tolerance: args.alpha_tolerance,
        alpha_t1_share: args.alpha_t1_share,
        alpha_lattice: args.alpha_lattice,
        alpha_shrinkage: args.alpha_shrinkage,
        spot_cos_min: args.spot_cos_min,
        laser_tolerance: args.laser_tolerance,
        noise_floor: args.noise_floor,
        coverage_check: args.coverage_check,
        validate: args.validate,
        memory: args.memory,
        cache: args.cache,
        skip_mesh_check: args.skip_mesh_check,
        check_noise_floor: args.check_noise_floor,
        no_pictures: args.no_pictures,
        full_mesh: args.full_mesh,
    };
    fit_scan(&ds, &frames, &settings, &stages)?;
    Ok(())
}
