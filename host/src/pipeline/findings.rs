//! What a run found: `fit-report.json` and the per-vertex failure reasons it counts.
use std::collections::BTreeMap;

use crate::samples::SampleCounts;

use super::PipelineOptions;

/// Why a vertex has no fitted model of its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FailReason {
    /// No light position within the selection distance (for every needed channel).
    NoData,
    /// Too few usable samples, or at too few distances.
    TooFewSamples,
    /// The solver did not converge.
    NotConverged,
    /// log E(x_i) (Eq. 8) above the acceptance threshold.
    HighError,
    /// The fit gave non-finite or non-physical parameters (c <= 0, d >= 0, s <= 0).
    NonPhysical,
    /// The selected frame's image could not be read.
    FrameUnreadable,
}

/// Why a fitted exponential term was dropped ("model only what the scene requires"): the
/// samples do not support it, so the fit is repeated with one term fewer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TermDropped {
    /// The term hardly decays over the sampled distances (|d|·(r_max − r_min) below
    /// [`super::MIN_DECAY`]): it is indistinguishable from a constant there and would never
    /// decay beyond (fits produce d ≈ −1e−16 such terms). A light position's fit keeps such a
    /// term beside others, held at the least decay ([`TermDropped::HeldAtLeastDecay`]), since
    /// dropping it changes the curve's shape; the homogeneous baseline's fit drops it, and a
    /// fall-off of that term alone fails.
    NonDecaying,
    /// The term carries at least [`super::MIN_SHARE`] of R_d at fewer than
    /// [`super::MIN_SUPPORT`] distinct sampled distances: typically a fall-off steeper than the
    /// spacing of the samples near x_i resolves, which the fit places below the smallest
    /// sampled distance, where it explodes.
    Unresolved,
    /// Not a drop: a term that hardly decays, kept beside the others at the least decay. Counted
    /// apart, as `FitReport::terms_held`, never under `terms_dropped`.
    HeldAtLeastDecay,
}

/// Frames by what registration concluded.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FrameCounts {
    /// Frames in the dataset.
    pub total: usize,
    /// Frames selected for this run (`--frames`/`--exclude-frames`).
    pub selected: usize,
    /// Frames with x_i on the object.
    pub registered: usize,
    /// Frames without a bright enough spot.
    pub no_spot: usize,
    /// Which frames those are, in the order judged.
    pub no_spot_frames: Vec<usize>,
    /// Registered frames left out because the camera sees their spot more grazing than the
    /// run's `spot_cos_min` (`PipelineOptions::spot_cos_min`).
    pub grazing: usize,
    /// Frames whose spot is not on the mesh.
    pub spot_off_object: usize,
    /// Frames whose spot disagrees with the laser ray (flagged, not used).
    pub laser_mismatch: usize,
    /// Frames whose image could not be read.
    pub unreadable: usize,
    /// The first few read errors, verbatim.
    pub unreadable_errors: Vec<String>,
    /// Registered frames whose samples some fit uses (every frame of a light position some
    /// vertex selected).
    pub fitted: usize,
    /// How the registered frames were pooled into light positions.
    pub pooling: super::select::Pooling,
    /// Reads of frame images by this process so far ([`crate::dataset::Dataset::frame_reads`]):
    /// each frame once per run, at the extraction pass, none when the sample cache served.
    pub reads: crate::dataset::FrameReads,
}

/// Table-1 statistics of log E(x_i) over the fitted light positions, per channel.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LogEStats {
    /// Number of light positions with a value.
    pub count: usize,
    /// Mean per channel (Table 1).
    pub mean: [Option<f64>; 3],
    /// Median per channel.
    pub median: [Option<f64>; 3],
}

impl LogEStats {
    /// Statistics of per-light values `[r, g, b]` (NaN = missing).
    pub fn of(values: &[[f64; 3]]) -> LogEStats {
        let mut st = LogEStats {
            count: values.len(),
            ..LogEStats::default()
        };
        for c in 0..3 {
            let mut v: Vec<f64> = values
                .iter()
                .map(|x| x[c])
                .filter(|x| x.is_finite())
                .collect();
            if v.is_empty() {
                continue;
            }
            v.sort_by(f64::total_cmp);
            st.mean[c] = Some(v.iter().sum::<f64>() / v.len() as f64);
            let m = v.len() / 2;
            st.median[c] = Some(if v.len() % 2 == 1 {
                v[m]
            } else {
                0.5 * (v[m - 1] + v[m])
            });
        }
        st
    }

    /// The mean over channels of the per-channel means (`None` if no channel has one): the
    /// single figure `--segments auto` compares.
    pub fn mean_over_channels(&self) -> Option<f64> {
        let means: Vec<f64> = self.mean.iter().flatten().copied().collect();
        (!means.is_empty()).then(|| means.iter().sum::<f64>() / means.len() as f64)
    }
}

/// `fit-report.json`.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FitReport {
    /// Vertices of the mesh.
    pub vertices: usize,
    /// Vertices with their own fit.
    pub vertices_fitted: usize,
    /// Vertices interpolated from neighbours.
    pub vertices_interpolated: usize,
    /// Vertices left without a model (not connected to any fitted vertex).
    pub vertices_no_model: usize,
    /// Failed vertices by reason (before interpolation).
    pub failures: BTreeMap<FailReason, usize>,
    /// Frames.
    pub frames: FrameCounts,
    /// Mesh problems found on loading.
    pub mesh: crate::dataset::MeshReport,
    /// Samples kept and dropped in the fit stage.
    pub samples: SampleCounts,
    /// log E(x_i) (Eq. 8, with alpha) over fitted light positions.
    pub log_e: LogEStats,
    /// Number of fitted light positions per chosen model order n.
    pub orders: BTreeMap<usize, usize>,
    /// The histogram of the orders chosen per light position ([`crate::order`]): accepted fits
    /// and the vertices that use them, per (n, m).
    pub chosen_orders: Vec<OrderCount>,
    /// The numbers the model stores, against the same model with every vertex at the maximum
    /// order.
    pub model_size: ModelSize,
    /// Terms dropped because the samples do not support them, by reason (each drop refits
    /// with one term fewer; counted in the last fit round, not in interpolation refits).
    pub terms_dropped: BTreeMap<TermDropped, usize>,
    /// Terms that hardly decayed over the sampled distances and were kept beside the others at
    /// the least decay instead of dropped (counted as `terms_dropped` is).
    pub terms_held: usize,
    /// Light positions fitted isotropically (their m segments equal) because the joint Eq. 3
    /// fit at m > 1 failed (no direction segment with enough samples of its own, or the solve
    /// did not converge) or gave an implausible segment (see `pipeline::fit`), in the last round.
    pub segment_fallbacks: usize,
    /// Where each vertex's alpha(x_o) (Eq. 6) comes from.
    pub alpha: AlphaReport,
    /// The homogeneous baseline (one isotropic fall-off for all x_i, [`crate::baseline`]).
    pub baseline: Option<BaselineReport>,
    /// The log E(x_i) acceptance threshold applied: `max_log_e`, or `outlier_factor` × the
    /// median fit's log E (at least [`super::OUTLIER_MIN_LOG_E`]) if lower.
    pub max_log_e: f64,
    /// Wall time per stage, seconds (`extract`: the one pass that decoded the frames, or
    /// opened the sample cache, shared by every fit of the run).
    pub stage_seconds: BTreeMap<String, f64>,
    /// The run's sample store: how many frames were decoded, samples held, memory, spill,
    /// cache.
    pub sample_store: Option<crate::store::StoreReport>,
    /// Peak resident memory of the process, MiB (Linux; `None` elsewhere).
    pub peak_rss_mib: Option<f64>,
    /// The options used.
    pub options: Option<PipelineOptions>,
    /// A preset's fits against exact fits of a sample of light positions ([`super::check`]);
    /// `None` for an exact fitter.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reflectance_check: Option<super::check::ReflectanceCheck>,
    /// What the run found that makes its model suspect, for people ([`FitWarning`]).
    pub warnings: Vec<FitWarning>,
    /// The cross-validated choices of the run (`crate::crossval`): the folds, every candidate's
    /// held-out error and the one chosen; `None` for a fit without cross-validation.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cross_validation: Option<CvReport>,
}

/// The cross-validation of a fit's choices (`crate::crossval`): folds of the training frames,
/// each fitted on the rest and judged on itself as `subsurf evaluate` judges, and per choice
/// every candidate's cross-validated error.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CvReport {
    /// How the folds were made, in words.
    pub rule: String,
    /// Per fold, its frames (held out of that fold's fit).
    pub folds: Vec<Vec<usize>>,
    /// Every choice, in the order they were made (each with the earlier ones' outcome).
    pub choices: Vec<CvChoice>,
    /// Fits run (one per fold and candidate).
    pub fits: usize,
    /// Light positions whose round-0 candidates were fitted, once for every fit of the run
    /// that holds their frames (`pipeline::fit::OrderCache`).
    pub round0_fitted: usize,
    /// Times a fold's or the final fit's round 0 found a light position's candidates fitted.
    pub round0_reused: usize,
    /// Wall time of the cross-validation, seconds.
    pub seconds: f64,
    /// The chosen settings' held-out log E per frame (r, g, b; `null` where a channel had no
    /// sample), each frame judged by the fold fit that did not see it: what two fits' scores are
    /// compared by, frame by frame and clustered by fold (docs/validation.md).
    pub per_frame: std::collections::BTreeMap<usize, [Option<f64>; 3]>,
    /// Why no choice could be cross-validated, when none was (too few light positions to make
    /// folds): every choice then took its default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
}

/// One cross-validated choice.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CvChoice {
    /// The setting chosen (`segments`, `alpha_rounds`, …).
    pub name: String,
    /// The rule that chose, in words.
    pub rule: String,
    /// Every candidate, in the order the rule prefers them.
    pub candidates: Vec<CvCandidate>,
    /// The value chosen.
    pub chosen: String,
}

/// One candidate of a cross-validated choice.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CvCandidate {
    /// The setting's value.
    pub value: String,
    /// Table-1 statistics of log E (Eq. 8) over the held-out frames of every fold (each frame
    /// judged by the fit that did not see it).
    pub held_out: LogEStats,
    /// The criterion: mean over the frames every candidate of the choice predicted of the frame's
    /// log E (mean over its channels).
    pub score: Option<f64>,
    /// How much worse than the best candidate (paired over those frames), and the standard error
    /// of that difference.
    pub worse_by: Option<f64>,
    /// The standard error of `worse_by`.
    pub se: Option<f64>,
    /// Whether it was chosen.
    pub chosen: bool,
    /// A remark (e.g. the candidate fitted the same model as another and was not fitted again).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// Something a run found that makes its model suspect although it was written.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
#[non_exhaustive]
pub enum FitWarning {
    /// No homogeneous baseline could be fitted (at any order). Below each light position's
    /// smallest sampled distance its model then continues with its slope there, which cannot
    /// steepen towards x_i as measured fall-offs do: renders come out dark (the tradeoff
    /// benchmark's sphere: 11–14 %, BENCHMARKS.md).
    NoBaseline,
    /// The run's fits and exact fits of the same light positions disagree in the reflectance
    /// they predict within reach by more than the tolerance and the noise ([`super::check`]).
    ReflectanceBiased {
        /// Light positions checked.
        checked: usize,
        /// The bias: mean ln(run's / exact), relative.
        mean: f64,
        /// Its standard error.
        standard_error: f64,
        /// The tolerance (relative).
        tolerance: f64,
    },
}

impl std::fmt::Display for FitWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FitWarning::NoBaseline => write!(
                f,
                "no homogeneous baseline could be fitted: below each light position's smallest \
                 sampled distance its model continues with its slope there, and renders come out \
                 dark (11-14 % on the tradeoff benchmark's sphere)"
            ),
            FitWarning::ReflectanceBiased {
                checked,
                mean,
                standard_error,
                tolerance,
            } => write!(
                f,
                "the preset's fits of {checked} light positions predict {:.1} ± {:.1} % {} \
                 diffuse reflectance than exact fits of the same samples (tolerance {:.0} %): \
                 the preset biases this scan's model; fit without --preset (exact) to compare",
                100.0 * mean.abs(),
                100.0 * standard_error,
                if *mean < 0.0 { "less" } else { "more" },
                100.0 * tolerance
            ),
        }
    }
}

impl FitReport {
    /// The warnings that follow from the report's figures.
    pub(crate) fn derive_warnings(&self) -> Vec<FitWarning> {
        let mut out = Vec::new();
        if self.baseline.is_none() && self.vertices_fitted > 0 {
            out.push(FitWarning::NoBaseline);
        }
        if let Some(c) = &self.reflectance_check
            && c.biased()
        {
            out.push(FitWarning::ReflectanceBiased {
                checked: c.checked,
                mean: c.mean,
                standard_error: c.standard_error,
                tolerance: c.tolerance,
            });
        }
        out
    }
}

/// Light positions (accepted fits) and their vertices that chose one order (n, m).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct OrderCount {
    /// Terms n.
    pub terms: usize,
    /// Direction segments m.
    pub segments: usize,
    /// Accepted fits with this order.
    pub light_positions: usize,
    /// Vertices with their own fit of this order.
    pub vertices: usize,
    /// Of the light positions, those whose model is the homogeneous baseline's fall-off with
    /// their own channel scales (the smallest candidate of the choice, 3 parameters).
    pub on_baseline: usize,
}

/// What choosing the order per light position saved: parameters stored in the model file's
/// `params` (all vertices with a model, interpolated ones included) against every such vertex
/// at the maximum order (`max_terms`, `max_segments`).
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct ModelSize {
    /// Numbers stored.
    pub numbers: usize,
    /// Numbers a model with every vertex at the maximum order stores.
    pub fixed_numbers: usize,
    /// The maximum n (`--terms`, or the preset's).
    pub max_terms: usize,
    /// The maximum m (`--segments`, or the preset's).
    pub max_segments: usize,
}

/// The homogeneous baseline in the report.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct BaselineReport {
    /// Terms n of the fit.
    pub terms: usize,
    /// Parameters in the model file's order (m = 1).
    pub params: Vec<f64>,
    /// `[r_min, r_max]` of the pooled samples, mm.
    pub r_range: [f64; 2],
    /// Channel samples pooled (every k-th of a group's samples above [`BASELINE_POOL`]).
    pub samples: usize,
    /// Table-1 statistics of log E(x_i) (Eq. 8, with the model's alpha) of the baseline on the
    /// fitted light positions: compare with `log_e`.
    pub log_e: LogEStats,
}

/// At most this many samples per channel of one light position go into the baseline's pooled fit
/// (evenly strided), so its cost does not grow with the image size.
pub const BASELINE_POOL: usize = 2000;

/// One alpha round (Eq. 6) in the report.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct AlphaRound {
    /// Round (0 = the fit on the samples as captured).
    pub round: usize,
    /// Training objective of the model the round leaves: sum over the fitted samples of
    /// (ln alpha + ln R_d − ln s)^2, the round's fits with the alpha Eq. 6 derives from them
    /// (the alpha step and the refit together).
    pub objective: f64,
    /// The same of the last kept round (what the round had to beat); equals `objective` for
    /// round 0.
    pub previous: f64,
    /// The round's fits against the alpha they were fitted to (before the alpha step).
    pub fitted: f64,
    /// Light positions whose new fit was worse than their previous one and kept the previous.
    pub fits_kept_previous: usize,
    /// Whether the round lowered the objective and was kept (a round that does not is
    /// discarded and the rounds stop).
    pub kept: bool,
}

/// Where the vertices' alpha(x_o) (Eq. 6) come from.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct AlphaReport {
    /// Eq. 6 from the vertex's own samples in the intensity window.
    pub from_samples: usize,
    /// No sample in the window (never seen by a fitted frame): interpolated from neighbours.
    pub interpolated: usize,
    /// Neither: alpha = 1.
    pub default_one: usize,
    /// Fit rounds on alpha-divided samples that were run (at most `alpha_rounds`).
    pub rounds: usize,
    /// RMS change of ln alpha(x_o) in the last round (0 when no extra round ran): below
    /// `alpha_tolerance` when the rounds converged.
    pub last_change: f64,
    /// Whether the rounds stopped because alpha converged (RMS change below the tolerance) or a
    /// round no longer lowered the objective.
    pub converged: bool,
    /// Every round: its training objective and whether it was kept.
    pub round_log: Vec<AlphaRound>,
    /// Per channel, the pseudo-samples at alpha = 1 Eq. 6 was shrunk with in the last round
    /// (noise over texture variance, [`crate::model::empirical_prior`]).
    pub prior: [f64; 3],
    /// alpha finer than the mesh ([`super::detail`]); `None` with `--alpha-lattice off`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lattice: Option<super::detail::LatticeReport>,
}

/// Wall time per stage, into the report.
pub(crate) struct StageClock(std::time::Instant);

impl StageClock {
    pub(crate) fn start() -> StageClock {
        StageClock(std::time::Instant::now())
    }

    /// Records the time since the last lap as stage `name`.
    pub(crate) fn lap(&mut self, name: &str, report: &mut FitReport) {
        report
            .stage_seconds
            .insert(name.to_string(), self.0.elapsed().as_secs_f64());
        self.0 = std::time::Instant::now();
    }
}
