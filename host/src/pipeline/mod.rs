//! Scan processing (section 5 of Fuchs et al. 2005): from a dataset to a per-vertex model.
//!
//! One module per stage, in the paper's order; [`fit_dataset`] runs them and reads like section 5:
//!
//! - [`load`]: the mesh prepared for ray casts, the cameras; every read of a frame image.
//! - [`register`]: the laser spot of every frame, found once, and its light position x_i.
//! - [`select`]: the closest x_i per vertex and channel; vertices that chose the same lights
//!   form a group and share one fit; a group's samples.
//! - [`fit`]: one model per group (Eq. 1/3/5/9), with the alpha rounds (Eq. 6).
//! - [`lattice`]: alpha finer than the mesh, Eq. 6 per point of a per-face lattice (section 5).
//! - [`error`]: log E(x_i) (Eq. 8) of every fit with alpha, and which fits are accepted.
//! - [`interpolate`]: a model for every vertex without an accepted fit, from its neighbours.
//! - [`assemble`]: the model file and the vertex counts.
//!
//! Frames are read again by each pass rather than kept, so memory does not grow with the frame
//! count. The solver is passed in ([`Fitter`]): the pipeline never depends on how Eq. 1 is
//! fitted. Progress goes to a [`Progress`]; each stage's wall time into the report.
pub mod assemble;
pub mod check;
pub mod error;
pub mod extract;
pub mod fit;
pub mod interpolate;
pub mod lattice;
pub mod load;
mod options;
pub mod register;
mod report;
pub mod select;

use crate::dataset::{Dataset, DatasetError};
use crate::geometry::GeometryError;
use crate::modelfile::ModelFile;
use crate::progress::Progress;

pub use extract::{Cache, StoreOptions};
pub use fit::{
    Fitter, MIN_DECAY, MIN_SHARE, MIN_SUPPORT, SEGMENT_MAX_RATE_RATIO, unsupported_term,
};
pub use load::{Context, SamplesError};
pub use options::{
    ALPHA_T1_SHARE, AlphaLattice, MAX_SEGMENTS, ModelChoice, PipelineOptions, SEGMENT_LADDER,
    Segments,
};
pub use register::{RegisteredFrame, register_one};
pub use report::{
    AlphaReport, AlphaRound, BASELINE_POOL, BaselineReport, FailReason, FitReport, FitWarning,
    FrameCounts, LogEStats, ModelSize, OrderCount, TermDropped,
};

/// A fit within this log E (3 % RMS) is never an outlier, however good the typical fit is
/// (noise-free scans: log E ~ 1e-4 with relative spread far above `outlier_factor`).
pub const OUTLIER_MIN_LOG_E: f64 = 0.03;

/// Why the pipeline stopped (per-frame and per-vertex problems are reported, not errors).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// The mesh could not be prepared.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// The dataset is unusable.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// Nothing could be fitted at all.
    #[error("no vertex could be fitted: {0}")]
    NothingFitted(String),
    /// Options are inconsistent.
    #[error("invalid options: {0}")]
    Invalid(String),
    /// The sample store could not be written or read.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
}

/// The result of [`fit_dataset`].
#[derive(Debug)]
pub struct FitOutput {
    /// The model (write with [`ModelFile::write`]).
    pub model: ModelFile,
    /// The report (`fit-report.json`).
    pub report: FitReport,
}

/// Runs the whole pipeline over the frames `frames` of `ds` with `opts.model.segments`
/// direction segments: [`prepare`] (the one pass over the frames, through the dataset's sample
/// cache) then [`fit_prepared`].
pub fn fit_dataset(
    ds: &Dataset,
    frames: &[usize],
    opts: &PipelineOptions,
    fitter: &dyn Fitter,
    progress: &dyn Progress,
) -> Result<FitOutput, PipelineError> {
    let ctx = prepare(ds, frames, opts, &StoreOptions::default(), progress)?;
    fit_prepared(&ctx, frames, fitter, progress)
}

/// The run over frames `frames` of `ds`: the mesh prepared for ray casts and the sample store
/// of those frames ([`extract::extract`]: each frame decoded once, or none when the cache
/// serves), with the lattice points a fit of them samples ([`extract::fit_points`]). Every
/// fit, evaluation and validation of any of these frames then runs from it without reading a
/// frame.
pub fn prepare<'a>(
    ds: &'a Dataset,
    frames: &[usize],
    opts: &PipelineOptions,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<Context<'a>, PipelineError> {
    check_options(opts)?;
    let ctx = Context::new(ds, *opts)?;
    let points = extract::fit_points(&ctx, frames);
    let held = extract::extract(&ctx, frames, points, store, progress)?;
    Ok(ctx.with_store(held))
}

fn check_options(opts: &PipelineOptions) -> Result<(), PipelineError> {
    if !(1..=MAX_SEGMENTS).contains(&opts.model.segments) {
        return Err(PipelineError::Invalid(format!(
            "segments must be 1..={MAX_SEGMENTS}, got {}",
            opts.model.segments
        )));
    }
    let share = opts.alpha_window.t1_share;
    if share.is_nan() || share <= 0.0 {
        return Err(PipelineError::Invalid(format!(
            "the Eq. 6 t1 share must be > 0 (inf: none), got {share}"
        )));
    }
    Ok(())
}

/// The pipeline over frames `frames` of a prepared run ([`prepare`]; its store must hold them),
/// with the run's options (`ctx.opts`): registration from the store, selection, the fit with
/// the alpha rounds, the lattice, the error, interpolation and the model file. Reads no frame.
pub fn fit_prepared(
    ctx: &Context,
    frames: &[usize],
    fitter: &dyn Fitter,
    progress: &dyn Progress,
) -> Result<FitOutput, PipelineError> {
    let opts = &ctx.opts;
    check_options(opts)?;
    let ds = ctx.ds;
    let store = ctx
        .store()
        .filter(|s| s.holds(frames))
        .ok_or_else(|| PipelineError::Invalid("the run's sample store lacks frames".into()))?;
    let mut report = FitReport {
        options: Some(*opts),
        mesh: ds.mesh_report.clone(),
        vertices: ds.mesh.positions.len(),
        sample_store: Some(store.report().clone()),
        ..FitReport::default()
    };
    report.frames.total = ds.spec.frames.len();
    report.frames.selected = frames.len();
    report
        .stage_seconds
        .insert("extract".into(), store.report().seconds);
    let mut clock = report::StageClock::start();
    // Registration: the spot in every frame, x_i on the mesh (found by the extraction pass).
    let regs = register::registered(ctx, frames, &mut report.frames);
    clock.lap("registration", &mut report);
    // "We select for each vertex in the mesh the closest light position x_i."
    let groups = select::select_groups(ctx, &regs);
    report.frames.fitted = groups.pooling.frames;
    report.frames.pooling = groups.pooling;
    clock.lap("selection", &mut report);
    // Fit R_d per x_i (Eq. 1/3/5/9), with the modulation texture alpha (Eq. 6) in rounds.
    let fitted = fit::fit_groups(ctx, &regs, &groups, fitter, progress);
    report.samples = fitted.counts;
    report.terms_dropped = fitted.dropped.clone();
    report.segment_fallbacks = fitted
        .fits
        .iter()
        .filter(|f| f.as_ref().is_ok_and(|g| g.isotropic_fallback))
        .count();
    report.alpha = fitted.alpha_report.clone();
    clock.lap("fit", &mut report);
    // A preset's approximations against exact fits of a sample of light positions (issue 28).
    report.reflectance_check = check::reflectance(ctx, &regs, &groups, &fitted, fitter, progress);
    clock.lap("check", &mut report);
    // alpha finer than the mesh (section 5): Eq. 6 per lattice point, with the final fits.
    let lattice = lattice::fit_lattice(ctx, &regs, &groups, &fitted, progress);
    if opts.alpha_lattice.max_level().is_some() {
        report.alpha.lattice = Some(lattice.report);
    }
    clock.lap("lattice", &mut report);
    // log E(x_i) (Eq. 8) with alpha; fits above the threshold fail.
    let (errors, baseline_log_e) = error::log_e_of_fits(ctx, &regs, &groups, &fitted, progress);
    report.baseline = fitted.baseline.as_ref().map(|b| report::BaselineReport {
        terms: b.params.terms,
        params: b.params.params.clone(),
        r_range: b.params.r_range,
        samples: b.samples,
        log_e: LogEStats::of(&baseline_log_e),
    });
    clock.lap("error", &mut report);
    let (own, shape) = error::accept(&groups, &fitted, &errors, opts, &mut report)?;
    // Failed vertices are interpolated from their neighbours, refitted with the common order;
    // with the order chosen per light position, with the largest order chosen (the blend of
    // neighbours' curves of different orders needs it; unsupported terms are still dropped).
    let common_n = match opts.order {
        Some(_) => shape.terms,
        None => report
            .orders
            .iter()
            .max_by_key(|(_, c)| **c)
            .map_or(shape.terms, |(n, _)| *n),
    };
    let refits = interpolate::fill(&ctx.scene, &own, &shape, common_n, fitter);
    let mut model = assemble::model_file(ds, shape, &own, &refits, &fitted.alpha, &mut report);
    model.baseline = fitted.baseline.as_ref().map(|b| b.params.clone());
    model.face_alpha = lattice.face_alpha;
    report.model_size = assemble::model_size(&model, fitter.max_terms(), opts.model.segments);
    clock.lap("interpolate", &mut report);
    report.peak_rss_mib = crate::util::peak_rss_mib();
    report.frames.reads = ds.frame_reads();
    report.warnings = report.derive_warnings();
    Ok(FitOutput { model, report })
}

/// [`fit_dataset`] with the direction segments chosen by `segments` (`opts.model.segments` is
/// ignored). [`Segments::Auto`] runs one whole fit per m of [`SEGMENT_LADDER`] and keeps the
/// smallest m whose mean log E (Table 1, mean over channels) is within the tolerance of the
/// best (the rule of [`crate::fit::choose_order`]); the report says what was tried. One pass
/// over the frames serves every fit of the ladder ([`prepare`]).
pub fn fit_scan(
    ds: &Dataset,
    frames: &[usize],
    opts: &PipelineOptions,
    segments: Segments,
    fitter: &dyn Fitter,
    progress: &dyn Progress,
) -> Result<FitOutput, PipelineError> {
    let ctx = prepare(ds, frames, opts, &StoreOptions::default(), progress)?;
    fit_scan_in(&ctx, frames, segments, fitter, progress)
}

/// [`fit_scan`] of a prepared run ([`prepare`]), with its options but for the segments.
pub fn fit_scan_in(
    ctx: &Context,
    frames: &[usize],
    segments: Segments,
    fitter: &dyn Fitter,
    progress: &dyn Progress,
) -> Result<FitOutput, PipelineError> {
    let tolerance = match segments {
        Segments::Fixed(m) => {
            let mut o = ctx.opts;
            o.model.segments = m;
            return fit_prepared(&ctx.with_options(o)?, frames, fitter, progress);
        }
        Segments::Auto { tolerance } => tolerance,
    };
    if !(tolerance >= 0.0 && tolerance.is_finite()) {
        return Err(PipelineError::Invalid(
            "the segments tolerance must be finite and >= 0".into(),
        ));
    }
    let mut runs = Vec::new();
    for m in SEGMENT_LADDER {
        let mut o = ctx.opts;
        o.model.segments = m;
        let run = fit_prepared(&ctx.with_options(o)?, frames, fitter, progress);
        let log_e = run
            .as_ref()
            .ok()
            .and_then(|out| out.report.log_e.mean_over_channels());
        runs.push((m, log_e, run));
    }
    let candidates: Vec<(usize, Option<f64>)> = runs.iter().map(|(m, e, _)| (*m, *e)).collect();
    let choice = crate::fit::choose_order(&candidates, tolerance);
    let chosen = choice.as_ref().map_or(1, |c| c.chosen);
    let (_, _, run) = runs
        .into_iter()
        .find(|(m, _, _)| *m == chosen)
        .ok_or_else(|| PipelineError::Invalid("no segment count was fitted".into()))?;
    let mut out = run?;
    out.report.segments_choice = choice;
    Ok(out)
}
