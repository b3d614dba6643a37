//! Scan processing (section 5 of Fuchs et al. 2005): from a dataset to a per-vertex model.
//!
//! One module per stage, in the paper's order; [`fit_dataset`] runs them and reads like section 5:
//!
//! - [`load`]: the mesh prepared for ray casts, the cameras; every read of a frame image.
//! - [`register`]: the laser spot of every frame, found once, and its light position x_i.
//! - [`select`]: the closest x_i per vertex and channel; vertices that chose the same lights
//!   form a group and share one fit; a group's samples.
//! - [`fit`]: one model per group (Eq. 1/3/5/9), with the alpha rounds (Eq. 6).
//! - [`detail`] (stage `lattice`): alpha finer than the mesh, Eq. 6 per point of a per-face
//!   lattice (section 5); the lattice's geometry is [`crate::lattice`].
//! - [`error`]: log E(x_i) (Eq. 8) of every fit with alpha, and which fits are accepted.
//! - [`fill`] (stage `interpolate`): a model for every vertex without an accepted fit, from its
//!   neighbours; the graph interpolation itself is [`crate::interpolate`].
//! - [`assemble`]: the model file and the vertex counts.
//!
//! Frames are read again by each pass rather than kept, so memory does not grow with the frame
//! count. The solver is passed in ([`Fitter`]): the pipeline never depends on how Eq. 1 is
//! fitted. Progress goes to a [`Progress`]; each stage's wall time into the report.
pub mod assemble;
pub mod check;
pub mod detail;
pub mod error;
pub mod extract;
pub mod fill;
mod findings;
pub mod fit;
pub mod load;
pub mod noise;
mod options;
pub mod register;
pub mod select;

use crate::dataset::{Dataset, DatasetError};
use crate::geometry::GeometryError;
use crate::modelfile::ModelFile;
use crate::progress::Progress;

pub use extract::{Cache, StoreOptions};
pub use findings::{
    AlphaReport, AlphaRound, BASELINE_POOL, BaselineReport, CvCandidate, CvChoice, CvReport,
    FailReason, FitReport, FitWarning, FrameCounts, LogEStats, ModelSize, OrderCount, TermDropped,
};
pub use fit::{
    Fitter, MIN_DECAY, MIN_SHARE, MIN_SUPPORT, SEGMENT_MAX_RATE_RATIO, unsupported_term,
};
pub use load::{Context, SamplesError};
pub use options::{
    ALPHA_T1_SHARE, AlphaLattice, FILL_TOLERANCE, MAX_SEGMENTS, ModelChoice, PipelineOptions,
    Speed, fit_record,
};
pub use register::{RegisteredFrame, register_one};

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

/// Runs the whole pipeline over the frames `frames` of `ds` with the options `opts` as they are
/// (no cross-validated choice: that is `crate::crossval`): [`prepare`] (the one pass over the frames, through the dataset's sample
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

/// A dataset's radiance noise floor and where it came from.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct NoiseFloor {
    /// The floor the run uses.
    pub value: f64,
    /// Where it came from: `scan.json`, `measured` or a flag.
    pub source: String,
    /// The measurement, where one was made ([`noise::estimate`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measured: Option<noise::NoiseEstimate>,
    /// Set when a given floor and the measured one differ by more than a factor 2.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

/// The noise floor of `ds`: `scan.json`'s when it gives one (measured too when `check`, and a
/// warning when the two differ by more than 2x), else measured from up to
/// [`noise::MAX_FRAMES`] of `frames` ([`noise::estimate`]).
pub fn noise_floor(
    ds: &Dataset,
    frames: &[usize],
    check: bool,
) -> Result<NoiseFloor, PipelineError> {
    let measure = || -> Result<noise::NoiseEstimate, PipelineError> {
        let scene = crate::geometry::Scene::new(ds.mesh.clone())?;
        noise::estimate(ds, &scene, frames).map_err(|e| PipelineError::Invalid(e.to_string()))
    };
    match ds.spec.noise_floor {
        Some(given) => {
            let measured = if check { measure().ok() } else { None };
            let warning = measured.as_ref().and_then(|m| {
                let ratio = (m.floor.max(f64::MIN_POSITIVE) / given.max(f64::MIN_POSITIVE)).max(
                    given.max(f64::MIN_POSITIVE) / m.floor.max(f64::MIN_POSITIVE),
                );
                (ratio > 2.0).then(|| {
                    format!(
                        "scan.json's noise_floor {given:.3e} and the one measured from the frames, {:.3e} (where the noise is 1/{} of the signal), differ by more than 2x: check the dataset's units or measure the camera's floor (docs/scan-format.md)",
                        m.floor,
                        noise::FLOOR_SNR
                    )
                })
            });
            Ok(NoiseFloor {
                value: given,
                source: if ds.spec.dark_frames.is_empty() {
                    "scan.json".into()
                } else {
                    "scan.json (the scan's dark frames)".into()
                },
                measured,
                warning,
            })
        }
        None => {
            let m = measure()?;
            Ok(NoiseFloor {
                value: m.floor,
                source: "measured (none in scan.json)".into(),
                measured: Some(m),
                warning: None,
            })
        }
    }
}

/// The evaluation protocol of `ds` ([`PipelineOptions::evaluation_protocol`]) with the dataset's
/// noise floor: `scan.json`'s, else measured from its frames (all of them, whichever are judged,
/// so every evaluation of the dataset has the same floor).
pub fn evaluation_protocol(ds: &Dataset) -> Result<(PipelineOptions, NoiseFloor), PipelineError> {
    let all: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let floor = noise_floor(ds, &all, false)?;
    Ok((
        PipelineOptions::evaluation_protocol(ds).with_noise_floor(floor.value),
        floor,
    ))
}

/// The rules a judge changes for every model alike (`subsurf evaluate`'s protocol flags).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProtocolChanges {
    /// A noise floor instead of the dataset's.
    pub noise_floor: Option<f64>,
    /// An exclusion radius (mm) instead of the protocol's.
    pub exclusion_radius_mm: Option<f64>,
    /// Drop samples whose neighbourhood the surface does not cover.
    pub coverage_check: bool,
}

/// The evaluation protocol of `ds` ([`evaluation_protocol`]) with `changes`: the options, where
/// the floor came from, and whether any rule was changed (figures under a changed protocol
/// compare only with figures under the same one). A floor given where the dataset has none
/// replaces it without measuring one.
pub fn evaluation_protocol_with(
    ds: &Dataset,
    changes: ProtocolChanges,
) -> Result<(PipelineOptions, String, bool), PipelineError> {
    let (mut opts, floor) = if changes.noise_floor.is_some() && ds.spec.noise_floor.is_none() {
        (
            PipelineOptions::evaluation_protocol(ds),
            NoiseFloor::default(),
        )
    } else {
        evaluation_protocol(ds)?
    };
    let mut source = floor.source;
    if let Some(f) = changes.noise_floor {
        opts = opts.with_noise_floor(f);
        source = "--noise-floor".into();
    }
    if let Some(x) = changes.exclusion_radius_mm {
        opts.samples.exclusion_radius_mm = x;
    }
    opts.samples.coverage |= changes.coverage_check;
    let changed = changes.noise_floor.is_some()
        || changes.exclusion_radius_mm.is_some()
        || changes.coverage_check;
    Ok((opts, source, changed))
}

/// The context that judges the models of the run `run` on `frames` by the dataset's evaluation
/// protocol ([`PipelineOptions::evaluation_protocol`], or `protocol` when given): the run itself
/// when its samples were read by the protocol's rules (every fit with the default sample rules:
/// nothing is read again), else a second pass over `frames` under the protocol's rules. The
/// cross-validation's folds and `subsurf fit --validate` judge through it, so a fit's own
/// exclusion radius, noise floor or grazing limits never change which samples judge its
/// models. The second pass samples the run's lattice points too (where the cross-validation
/// judges the lattice at surface points).
pub fn judge_context<'a>(
    run: &Context<'a>,
    frames: &[usize],
    protocol: Option<&PipelineOptions>,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<Context<'a>, PipelineError> {
    let protocol = protocol
        .copied()
        .unwrap_or_else(|| PipelineOptions::evaluation_protocol(run.ds));
    let opts = run.opts.judged_by(&protocol);
    if opts.spot == run.opts.spot && opts.samples == run.opts.samples {
        return run.with_options(opts);
    }
    let opts = PipelineOptions {
        alpha_lattice: AlphaLattice::Off,
        ..opts
    };
    let ctx = Context::new(run.ds, opts)?;
    // The run's lattice points, sampled by the protocol's rules above the protocol's t2: where
    // the cross-validation judges the lattice of alpha finer than the mesh
    // (`crate::crossval`), on the samples the run's own store would hold there by the protocol.
    let points = run
        .store()
        .and_then(|s| s.points())
        .map(|p| crate::store::StorePoints {
            min_value: protocol.alpha_window.t2,
            ..p.clone()
        });
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
    if opts.alpha_shrinkage.is_nan() || opts.alpha_shrinkage < 0.0 {
        return Err(PipelineError::Invalid(format!(
            "the Eq. 6 shrinkage must be >= 0 (inf: no texture), got {}",
            opts.alpha_shrinkage
        )));
    }
    let floor = crate::spot::SPOT_COS_FLOOR;
    if !(floor..=1.0).contains(&opts.spot_cos_min) {
        return Err(PipelineError::Invalid(format!(
            "the spot's grazing limit must be {floor}..=1 (cos θ), got {}",
            opts.spot_cos_min
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
    fit_prepared_with(ctx, frames, fitter, None, progress)
}

/// `fitter` as the reference preset runs it (libm's exp and ln, [`Fitter::reference`]) where
/// the run is the reference (`ctx.opts.speed`); `None`: use `fitter` as it is.
pub(crate) fn reference_fitter(ctx: &Context, fitter: &dyn Fitter) -> Option<Box<dyn Fitter>> {
    (ctx.opts.speed == Speed::Reference)
        .then(|| fitter.reference())
        .flatten()
}

/// [`fit_prepared`] taking round 0's candidates from `cache` where another fit of the run
/// (the cross-validation's) fitted them ([`fit::OrderCache`]): the same model.
pub fn fit_prepared_with(
    ctx: &Context,
    frames: &[usize],
    fitter: &dyn Fitter,
    cache: Option<&fit::OrderCache>,
    progress: &dyn Progress,
) -> Result<FitOutput, PipelineError> {
    let reference = reference_fitter(ctx, fitter);
    let fitter = reference.as_deref().unwrap_or(fitter);
    let mut run = Setup::new(ctx, frames)?;
    let fitted = fit::fit_groups(ctx, &run.regs, &run.groups, fitter, cache, progress);
    run.clock.lap("fit", &mut run.report);
    run.finish(ctx, fitted, fitter, progress)
}

/// [`fit_prepared`] with the model after every alpha round handed to `each` (round, model): the
/// model of round 0 (the fits of the samples as captured, with their Eq. 6 alpha), then of every
/// kept round ([`fit::AlphaRounds`]), as long as `each` returns `true`. The model of round r is
/// the one [`fit_prepared`] returns with `alpha_rounds = r`; the cross-validated choice of the
/// number of rounds (`crate::crossval`) judges each without fitting the rounds again.
pub fn fit_prepared_rounds(
    ctx: &Context,
    frames: &[usize],
    fitter: &dyn Fitter,
    progress: &dyn Progress,
    each: &mut dyn FnMut(usize, FitOutput) -> bool,
) -> Result<(), PipelineError> {
    let prepared = Prepared::new(ctx, frames)?;
    let mut run = prepared.rounds(ctx, fitter, None, progress);
    loop {
        let out = run.model()?;
        if !each(run.rounds(), out) || !run.step() {
            return Ok(());
        }
    }
}

/// A fit's registration and selection on frames `frames` of a prepared run, done once, for a
/// caller that steps the alpha rounds itself ([`FitRounds`]): the cross-validation runs its
/// folds' fits side by side, round by round, so that their pooled held-out error can end every
/// fold's rounds once more rounds stop helping (`crate::crossval`).
pub struct Prepared {
    setup: Setup,
}

impl Prepared {
    /// Registration from the store and selection; no fit yet.
    pub fn new(ctx: &Context, frames: &[usize]) -> Result<Prepared, PipelineError> {
        Ok(Prepared {
            setup: Setup::new(ctx, frames)?,
        })
    }

    /// Round 0's candidates of every light position of this selection, into `cache`
    /// ([`fit::OrderCache::fill`]).
    pub fn fill_order_cache(
        &self,
        ctx: &Context,
        fitter: &dyn Fitter,
        cache: &fit::OrderCache,
        progress: &dyn Progress,
    ) {
        cache.fill(ctx, &self.setup.regs, &self.setup.groups, fitter, progress);
    }

    /// The lattice of alpha finer than the mesh that the lattice stage ([`detail::fit_lattice`])
    /// finds from `fitted` (a state of this selection's rounds, [`FitRounds::fitted`]) under the
    /// run `ctx`: the model's `face_alpha` were it finished with `ctx`'s settings. The stages
    /// after it do not depend on it, so the cross-validation adds it to a fold's model judged at
    /// that state, neither fitting nor finishing the fold again.
    pub fn lattice_of(
        &self,
        ctx: &Context,
        fitted: &fit::Fitted,
    ) -> Option<crate::lattice::FaceAlpha> {
        let setup = &self.setup;
        detail::fit_lattice(ctx, &setup.regs, &setup.groups, fitted, &()).face_alpha
    }

    /// The baseline and round 0 fitted ([`fit::AlphaRounds::start`]), round 0's candidates
    /// from `cache` where known.
    pub fn rounds<'r, 'a>(
        &'r self,
        ctx: &'r Context<'a>,
        fitter: &'r dyn Fitter,
        cache: Option<&'r fit::OrderCache>,
        progress: &'r dyn Progress,
    ) -> FitRounds<'r, 'a> {
        let setup = &self.setup;
        FitRounds {
            setup,
            ctx,
            fitter,
            progress,
            rounds: fit::AlphaRounds::start(
                ctx,
                &setup.regs,
                &setup.groups,
                fitter,
                cache,
                progress,
            ),
            last_fill: std::sync::Mutex::new(None),
        }
    }
}

/// The alpha rounds of one [`Prepared`] fit, stepped by the caller: [`FitRounds::model`] is the
/// model [`fit_prepared`] returns with `alpha_rounds` = [`FitRounds::rounds`].
pub struct FitRounds<'r, 'a> {
    setup: &'r Setup,
    ctx: &'r Context<'a>,
    fitter: &'r dyn Fitter,
    progress: &'r dyn Progress,
    rounds: fit::AlphaRounds<'r, 'a>,
    /// The last finish's fill, the next one's start ([`fill::FillHow::warm`]).
    last_fill: std::sync::Mutex<Option<fill::FillState>>,
}

impl FitRounds<'_, '_> {
    /// The rounds kept so far (0: round 0 only).
    pub fn rounds(&self) -> usize {
        self.rounds.rounds()
    }

    /// The state of the last kept round (its fits and alpha), as the stages after the fit take
    /// it ([`Prepared::lattice_of`]).
    pub fn fitted(&self) -> fit::Fitted {
        self.rounds.fitted()
    }

    /// The model of the last kept round: the stages after the fit run on it.
    pub fn model(&self) -> Result<FitOutput, PipelineError> {
        self.finish(Figures::All, None)
    }

    /// [`FitRounds::model`]'s model file alone, for a caller that judges it and drops the
    /// report (the cross-validation's folds): the report's figures no model number depends on
    /// are not computed ([`Figures::ModelOnly`]). The same model, bit for bit.
    pub fn model_file(&self) -> Result<ModelFile, PipelineError> {
        self.finish(Figures::ModelOnly, None).map(|out| out.model)
    }

    /// [`FitRounds::model_file`] where only the vertices marked in `needed` must have their
    /// model (a fold judges its frames with the corners of their x_i's triangles alone): the
    /// others without a fit of their own are left without one. At the needed vertices the
    /// same models as [`FitRounds::model_file`]'s, on the reference path bit for bit; on the
    /// default path within the fill's tolerance, its weights kept from this run's previous
    /// fill ([`fill::FillHow`]).
    pub fn model_file_for(&self, needed: &[bool]) -> Result<ModelFile, PipelineError> {
        self.finish(Figures::ModelOnly, Some(needed))
            .map(|out| out.model)
    }

    fn finish(
        &self,
        figures: Figures,
        needed: Option<&[bool]>,
    ) -> Result<FitOutput, PipelineError> {
        let mut last = self
            .last_fill
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let how = fill::FillHow {
            needed,
            speed: self.ctx.opts.speed,
            warm: last.as_ref(),
        };
        let (out, state) = finish_state(
            self.setup,
            self.ctx,
            self.rounds.fitted(),
            self.fitter,
            self.progress,
            figures,
            &how,
        )?;
        *last = Some(state);
        Ok(out)
    }

    /// The last finish's fill state ([`fill::FillHow::warm`]), for another run on the
    /// same mesh to start from ([`FitRounds::start_fill_from`]).
    pub fn fill_state(&self) -> Option<fill::FillState> {
        self.last_fill
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Starts this run's fills from `state`, another run's on the same mesh, if this one has
    /// not filled yet. Why: the cross-validation's candidates (t1 on and off) fit the same
    /// folds, so a fold's known vertices, and with them the interpolation's weights, are
    /// mostly the same in both. The fill uses the weights only where their known set and
    /// targets are its own, so the model is the same bit for bit.
    pub fn start_fill_from(&self, state: fill::FillState) {
        self.last_fill
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get_or_insert(state);
    }

    /// The next round ([`fit::AlphaRounds::step`]): `false` when the rounds are over.
    pub fn step(&mut self) -> bool {
        self.rounds.step()
    }
}

/// The stages after the fit ([`Setup::finish_with`]) on the state `fitted` of `setup`'s rounds,
/// leaving `setup` as it is (the fold fits of the cross-validation finish it more than once).
fn finish_state(
    setup: &Setup,
    ctx: &Context,
    fitted: fit::Fitted,
    fitter: &dyn Fitter,
    progress: &dyn Progress,
    figures: Figures,
    fill: &fill::FillHow,
) -> Result<(FitOutput, fill::FillState), PipelineError> {
    let mut run = Setup {
        frames: setup.frames.clone(),
        report: setup.report.clone(),
        regs: Vec::new(),
        groups: select::Groups::default(),
        clock: findings::StageClock::start(),
        figures,
    };
    run.finish_with(
        ctx,
        &setup.regs,
        &setup.groups,
        fitted,
        fitter,
        progress,
        fill,
    )
}

/// What [`Setup::finish_with`] computes besides the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Figures {
    /// Every figure of the fit report.
    All,
    /// Only what the model file depends on: the homogeneous baseline's log E (Eq. 8), a figure
    /// of the report alone, is left out.
    ModelOnly,
}

/// A run's registration and selection, before the fit.
struct Setup {
    /// The frames the fit was given (the model file records them).
    frames: Vec<usize>,
    report: FitReport,
    regs: Vec<RegisteredFrame>,
    groups: select::Groups,
    clock: findings::StageClock,
    /// What [`Setup::finish_with`] computes besides the model.
    figures: Figures,
}

impl Setup {
    fn new(ctx: &Context, frames: &[usize]) -> Result<Setup, PipelineError> {
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
        let mut clock = findings::StageClock::start();
        // Registration: the spot in every frame, x_i on the mesh (found by the extraction pass).
        let regs = register::registered(ctx, frames, &mut report.frames);
        clock.lap("registration", &mut report);
        // "We select for each vertex in the mesh the closest light position x_i."
        let groups = select::select_groups(ctx, &regs);
        report.frames.fitted = groups.pooling.frames;
        report.frames.pooling = groups.pooling;
        clock.lap("selection", &mut report);
        // Sorted and distinct: the model file's ranges and `evaluate::split_fitted`'s binary
        // search read them so.
        let mut fitted = frames.to_vec();
        fitted.sort_unstable();
        fitted.dedup();
        Ok(Setup {
            frames: fitted,
            report,
            regs,
            groups,
            clock,
            figures: Figures::All,
        })
    }

    fn finish(
        mut self,
        ctx: &Context,
        fitted: fit::Fitted,
        fitter: &dyn Fitter,
        progress: &dyn Progress,
    ) -> Result<FitOutput, PipelineError> {
        let (regs, groups) = (
            std::mem::take(&mut self.regs),
            std::mem::take(&mut self.groups),
        );
        let how = fill::FillHow {
            speed: ctx.opts.speed,
            ..fill::FillHow::default()
        };
        self.finish_with(ctx, &regs, &groups, fitted, fitter, progress, &how)
            .map(|(out, _)| out)
    }

    /// The stages after the fit: the lattice, the error, acceptance, interpolation and the
    /// model file; second, the fill's state a later round's fill may start from.
    #[allow(clippy::too_many_arguments)]
    fn finish_with(
        &mut self,
        ctx: &Context,
        regs: &[RegisteredFrame],
        groups: &select::Groups,
        fitted: fit::Fitted,
        fitter: &dyn Fitter,
        progress: &dyn Progress,
        fill: &fill::FillHow,
    ) -> Result<(FitOutput, fill::FillState), PipelineError> {
        let opts = &ctx.opts;
        let ds = ctx.ds;
        let report = &mut self.report;
        let clock = &mut self.clock;
        report.samples = fitted.counts;
        let mut dropped = fitted.dropped.clone();
        report.terms_held = dropped.remove(&TermDropped::HeldAtLeastDecay).unwrap_or(0);
        report.terms_dropped = dropped;
        report.segment_fallbacks = fitted
            .fits
            .iter()
            .filter(|f| f.as_ref().is_ok_and(|g| g.isotropic_fallback))
            .count();
        report.alpha = fitted.alpha_report.clone();
        // A preset's approximations against exact fits of a sample of light positions:
        // an approximation may make a model noisier, never biased (`check`).
        report.reflectance_check = check::reflectance(ctx, regs, groups, &fitted, fitter, progress);
        clock.lap("check", report);
        // alpha finer than the mesh (section 5): Eq. 6 per lattice point, with the final fits.
        let lattice = detail::fit_lattice(ctx, regs, groups, &fitted, progress);
        if opts.alpha_lattice.max_level().is_some() {
            report.alpha.lattice = Some(lattice.report);
        }
        clock.lap("lattice", report);
        // log E(x_i) (Eq. 8) with alpha; fits above the threshold fail.
        let (errors, baseline_log_e) = error::log_e_of_fits(
            ctx,
            regs,
            groups,
            &fitted,
            self.figures == Figures::All,
            progress,
        );
        report.baseline = fitted.baseline.as_ref().map(|b| findings::BaselineReport {
            terms: b.params.terms,
            params: b.params.params.clone(),
            r_range: b.params.r_range,
            samples: b.samples,
            log_e: LogEStats::of(&baseline_log_e),
        });
        clock.lap("error", report);
        let (own, shape) = error::accept(groups, &fitted, &errors, opts, report)?;
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
        let (refits, fill_state) = fill::fill(&ctx.scene, &own, &shape, common_n, fitter, fill);
        let mut model = assemble::model_file(ds, shape, &own, &refits, &fitted.alpha, report);
        model.baseline = fitted.baseline.as_ref().map(|b| b.params.clone());
        model.face_alpha = lattice.face_alpha;
        model.fitted_with = Some(options::fit_record(opts));
        model.fitted_frames = Some(self.frames.clone());
        report.model_size = assemble::model_size(&model, fitter.max_terms(), opts.model.segments);
        clock.lap("interpolate", report);
        report.peak_rss_mib = crate::util::peak_rss_mib();
        report.frames.reads = ds.frame_reads();
        report.warnings = report.derive_warnings();
        Ok((
            FitOutput {
                model,
                report: report.clone(),
            },
            fill_state,
        ))
    }
}
