//! The colour rule chosen per model by the frames it was fitted on (`subsurf export --colour
//! auto --scan S`): every candidate conversion's closed-form Cycles render ([`super::replay`])
//! judged by the ring yardstick (docs/validation.md) on the model's own training frames, the
//! cheapest candidate that cannot be told from the best one kept.
//!
//! Why the replay and not Cycles: the choice compares candidates that differ by a few per cent
//! of ring log E, and one Cycles render of a pixel-sized spot carries tens of per cent of noise
//! on the same rings. The replay is Cycles' expectation, so the comparison has no render noise
//! and costs seconds, not hours; that it is Cycles' expectation is checked where Cycles renders
//! (`replay_agreement_ring_mean_log_e` of `export --render --scan`).
//!
//! Why training frames: the frames a model is judged by afterwards (its test frames) must not
//! pick its conversion. The model file names the frames its fit was given
//! (`comment fitted_frames`); only those are read.

use serde::Serialize;

use super::convert::ColourRule;
use super::frames::{Subject, frame_scenes};
use super::replay::{Kernel, Replay};
use super::{Export, ExportError, ExportOptions};
use crate::dataset::Dataset;
use crate::evaluate::EvalPoints;
use crate::evaluate::images::{FrameImages, Reference};
use crate::evaluate::rings::{Prediction, evaluate_rings_in};
use crate::evaluate::summary::{Clustering, ErrorSource, JudgedFrame, clustered_mean, t95};
use crate::modelfile::ModelFile;
use crate::progress::Progress;

/// The candidates, cheapest first: one Burley lobe before two (a Mix Shader of two Principled
/// BSDFs costs Cycles a second closure per shading point), and of the one-lobe rules the one
/// that follows the fall-off where it was measured before the one that keeps its total light.
pub const CANDIDATES: [ColourRule; 3] =
    [ColourRule::Fitted, ColourRule::Total, ColourRule::TwoLobe];

/// Training frames replayed at most, spread evenly over the fitted frames: the choice needs the
/// fall-off at many light positions, not every frame of a 100-frame scan (each frame is
/// replayed once per candidate).
pub const MAX_FRAMES: usize = 24;

/// The choice's file in an export folder.
pub const CHOICE_FILE: &str = "colour-choice.json";

/// Confidence of the interval that decides whether a cheaper candidate is told from the best.
const LEVEL: f64 = 0.95;

/// One candidate's figures on the training frames.
#[derive(Clone, Debug, Serialize)]
pub struct Candidate {
    /// The colour rule (`None`: subsurf's own prediction, beside).
    pub colour: Option<ColourRule>,
    /// Subsurface lobes per point it costs (0 for subsurf's model).
    pub lobes: u8,
    /// The replay's ring mean log E per channel over the frames judged.
    pub ring_mean_log_e: [Option<f64>; 3],
    /// The score: the mean over frames of each frame's ring log E averaged over its channels.
    pub score: Option<f64>,
    /// Its standard error, clustered as `subsurf evaluate` clusters.
    pub se: Option<f64>,
    /// Score minus the best candidate's, paired per frame.
    pub difference: Option<f64>,
    /// The difference's 95 % t-interval (clusters − 1 degrees of freedom); `None` with one
    /// cluster.
    pub difference_ci95: Option<[f64; 2]>,
}

/// The choice and what it rests on.
#[derive(Clone, Debug, Serialize)]
pub struct ColourChoice {
    /// The rule chosen.
    pub colour: ColourRule,
    /// The training frames judged (by every candidate and the model).
    pub frames: Vec<usize>,
    /// Training frames picked but not judged, and why.
    pub skipped: Vec<super::frames::SkippedFrame>,
    /// Clusters of those frames, degrees of freedom and the t value of the intervals.
    pub clusters: usize,
    /// Clusters − 1 (`None` with one cluster).
    pub dof: Option<usize>,
    /// The two-sided 95 % t value at `dof`.
    pub t95: Option<f64>,
    /// How frames were clustered.
    pub cluster_rule: String,
    /// The Cycles kernel replayed (`V3`: Blender 3.x, `V4`: 4.0 on).
    pub kernel: String,
    /// Every candidate, in [`CANDIDATES`]' order.
    pub candidates: Vec<Candidate>,
    /// subsurf's own prediction on the same frames and rings (the model the candidates
    /// convert: how close a conversion comes to it).
    pub model: Candidate,
    /// Why the rule was chosen, in words.
    pub reason: String,
}

impl ColourChoice {
    /// The lines `subsurf export` prints.
    pub fn text(&self) -> String {
        let mut s = format!(
            "colour rule chosen by the replay of {} training frames ({} skipped; {} clusters by \
             {}, rings, Cycles kernel {}):\n",
            self.frames.len(),
            self.skipped.len(),
            self.clusters,
            self.cluster_rule,
            self.kernel
        );
        for c in self.candidates.iter().chain([&self.model]) {
            let f = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:.3}"));
            s += &format!(
                "  {:<18} ring log E {} / {} / {}, score {} ± {}{}\n",
                match c.colour {
                    None => "subsurf's model".to_string(),
                    Some(r) => format!(
                        "{} ({} lobe{})",
                        r.name(),
                        c.lobes,
                        ["", "s"][(c.lobes > 1) as usize]
                    ),
                },
                f(c.ring_mean_log_e[0]),
                f(c.ring_mean_log_e[1]),
                f(c.ring_mean_log_e[2]),
                f(c.score),
                f(c.se),
                match (c.difference, c.difference_ci95) {
                    (Some(d), Some([a, b])) if d != 0.0 =>
                        format!(", {d:+.3} against the best [{a:+.3}, {b:+.3}]"),
                    (Some(d), None) if d != 0.0 => format!(", {d:+.3} against the best"),
                    _ => String::new(),
                }
            );
        }
        s + &format!("  chosen: {} ({})\n", self.colour.name(), self.reason)
    }

    /// Writes [`CHOICE_FILE`] into the export folder `dir` (written already).
    pub fn write(&self, dir: &std::path::Path) -> Result<std::path::PathBuf, ExportError> {
        super::write_json(dir, CHOICE_FILE, self)
    }
}

/// What the subsurface colour is, as `subsurf export --colour` asks for it (docs/export.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ColourArg {
    /// The fall-off's total diffuse reflectance T.
    Total,
    /// Amplitude fitted with the Burley shape in log space over the sampled distances.
    Fitted,
    /// Two Burley lobes (near and slow Principled BSDFs mixed by a Mix Shader), T split between
    /// them as the fitted terms' reflectances split it.
    TwoLobe,
    /// Chosen among the three by Cycles' render replayed in closed form on the training frames
    /// of `--scan` the model was fitted on, judged by rings (`colour-choice.json`).
    Auto,
}

impl ColourArg {
    /// The rule asked for; `Auto` gives the default, which [`export_choosing`] replaces.
    pub fn rule(self) -> ColourRule {
        match self {
            ColourArg::Total => ColourRule::Total,
            ColourArg::Fitted => ColourRule::Fitted,
            ColourArg::TwoLobe => ColourRule::TwoLobe,
            ColourArg::Auto => ColourRule::default(),
        }
    }
}

/// [`super::export`] with `opts`, or, given `auto` (the model's scan and the version of the
/// Blender that will render it, if known), with the colour rule [`choose_colour`] chooses by
/// that scan's training frames in that version's kernel (Blender 4.0 on when none is known).
pub fn export_choosing(
    model: &ModelFile,
    opts: &ExportOptions,
    auto: Option<(&Dataset, Option<(u32, u32)>)>,
    store: &crate::pipeline::StoreOptions,
    progress: &dyn Progress,
) -> Result<(Export, Option<ColourChoice>), ExportError> {
    match auto {
        None => Ok((super::export(model, opts, progress)?, None)),
        Some((ds, version)) => {
            let kernel = version.map(Kernel::of).unwrap_or_default();
            let (c, e) = choose_colour(ds, model, opts, kernel, store, progress)?;
            Ok((e, Some(c)))
        }
    }
}

/// At most `max` of `frames`, spread evenly (every frame when there are no more than `max`).
fn spread(frames: &[usize], max: usize) -> Vec<usize> {
    if frames.len() <= max || max == 0 {
        return frames.to_vec();
    }
    (0..max).map(|i| frames[i * frames.len() / max]).collect()
}

/// Chooses `model`'s colour rule by the replay of its training frames of `ds` (the frames its
/// fit was given, at most [`MAX_FRAMES`]), in the Cycles `kernel`, with the rest of `opts`;
/// returns the choice and the chosen export.
pub fn choose_colour(
    ds: &Dataset,
    model: &ModelFile,
    opts: &ExportOptions,
    kernel: Kernel,
    store: &crate::pipeline::StoreOptions,
    progress: &dyn Progress,
) -> Result<(ColourChoice, Export), ExportError> {
    let fitted = model.fitted_frames.as_deref().unwrap_or(&[]);
    let known: Vec<usize> = fitted
        .iter()
        .copied()
        .filter(|&k| k < ds.spec.frames.len())
        .collect();
    if known.is_empty() {
        return Err(ExportError::Invalid(format!(
            "--colour auto needs the frames the model was fitted on among the scan's {} frames \
             (the model file's `comment fitted_frames`): {}; give --colour instead",
            ds.spec.frames.len(),
            if fitted.is_empty() {
                "the model file names none".to_string()
            } else {
                format!("it names {} frames, none in this scan", fitted.len())
            }
        )));
    }
    let (popts, _) = crate::pipeline::evaluation_protocol(ds)
        .map_err(|e| ExportError::Invalid(format!("the dataset's noise floor: {e}")))?;
    let at = EvalPoints::Vertices;
    let ctx = crate::evaluate::judged_store(ds, &[model], &known, &popts, at, store, progress)?;
    let mut exports = CANDIDATES
        .iter()
        .map(|&colour| {
            super::export(
                model,
                &ExportOptions {
                    colour,
                    ..opts.clone()
                },
                progress,
            )
        })
        .collect::<Result<Vec<Export>, ExportError>>()?;
    // The scenes depend on the model and the scan only, not on the conversion.
    let mut sc = frame_scenes(
        &ctx,
        Subject::Empirical(model, Some(&exports[0])),
        &known,
        1,
    )?;
    // Spread over the frames that have a scene: a scan's frames cycle through laser positions,
    // and every k-th frame by index can be a light position that never meets the object.
    let lit: Vec<usize> = sc.frames.iter().map(|s| s.frame).collect();
    let frames = spread(&lit, MAX_FRAMES);
    sc.frames.retain(|s| frames.contains(&s.frame));
    let own = evaluate_rings_in(&ctx, Some(model), Prediction::Model, &frames, at, progress)?.0;
    let mut per_frame: Vec<Vec<crate::evaluate::rings::FrameRings>> = Vec::new();
    for e in &exports {
        let replay = Replay::new(&ctx, &sc, &e.mesh, e.scene.exit_fresnel_ior, kernel)?;
        let kept = replay.kept(&frames);
        let images = FrameImages::made(Replay::NAME, &kept);
        let p = Prediction::Images(&images, Reference::Frames);
        per_frame.push(evaluate_rings_in(&ctx, Some(model), p, &frames, at, progress)?.0);
    }
    // The model's own prediction last: judged on the same frames, never chosen.
    per_frame.push(own);
    let judged: Vec<JudgedFrame> = sc
        .frames
        .iter()
        .map(|s| (s.frame, Some(s.x_i_mm)))
        .collect();
    let clusters = Clustering::rule(ds, &judged, ErrorSource::HeldOut);
    // A frame counts where every candidate judged it: the candidates are compared on the same
    // frames.
    let score = |r: &crate::evaluate::rings::FrameRings| -> Option<f64> {
        let v: Vec<f64> = r.log_e.iter().flatten().copied().collect();
        (r.skipped.is_none() && !v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let common: Vec<usize> = sc
        .frames
        .iter()
        .map(|s| s.frame)
        .filter(|&k| {
            per_frame
                .iter()
                .all(|c| c.iter().any(|r| r.frame == k && score(r).is_some()))
        })
        .collect();
    let mut skipped = sc.skipped.clone();
    for &k in &frames {
        let why = per_frame
            .iter()
            .flatten()
            .find(|r| r.frame == k && r.skipped.is_some())
            .and_then(|r| r.skipped.clone());
        if let Some(reason) = why {
            skipped.push(super::frames::SkippedFrame { frame: k, reason });
        } else if !common.contains(&k) {
            let reason = "no ring holds a judged sample".to_string();
            skipped.push(super::frames::SkippedFrame { frame: k, reason });
        }
    }
    if common.is_empty() {
        return Err(ExportError::Invalid(
            "no training frame could be judged for every candidate conversion".into(),
        ));
    }
    let scores: Vec<Vec<f64>> = per_frame
        .iter()
        .map(|c| {
            common
                .iter()
                .map(|&k| {
                    c.iter()
                        .find(|r| r.frame == k)
                        .and_then(score)
                        .unwrap_or(0.0)
                })
                .collect()
        })
        .collect();
    let means: Vec<Option<crate::evaluate::summary::ClusteredMean>> = scores
        .iter()
        .map(|s| {
            let v: Vec<_> = common
                .iter()
                .zip(s)
                .map(|(&k, &y)| (y, 1.0, clusters.cluster(k)))
                .collect();
            clustered_mean(&v)
        })
        .collect();
    let best = (0..CANDIDATES.len())
        .min_by(|&a, &b| {
            let m = |i: usize| means[i].as_ref().map_or(f64::INFINITY, |m| m.mean);
            m(a).total_cmp(&m(b))
        })
        .unwrap_or(0);
    let differences: Vec<Option<crate::evaluate::summary::ClusteredMean>> = scores
        .iter()
        .map(|s| {
            let v: Vec<_> = common
                .iter()
                .enumerate()
                .map(|(n, &k)| (s[n] - scores[best][n], 1.0, clusters.cluster(k)))
                .collect();
            clustered_mean(&v)
        })
        .collect();
    // The cheapest candidate whose paired difference from the best has an interval reaching 0:
    // a better figure the training frames cannot tell from noise is not worth a costlier
    // material.
    let tied = |i: usize| {
        i == best
            || differences[i]
                .as_ref()
                .and_then(|d| d.interval(LEVEL))
                .is_some_and(|[lo, _]| lo <= 0.0)
    };
    let chosen = (0..CANDIDATES.len()).find(|&i| tied(i)).unwrap_or(best);
    let n_clusters = means
        .iter()
        .flatten()
        .map(|m| m.clusters)
        .max()
        .unwrap_or(0);
    let dof = (n_clusters >= 2).then(|| n_clusters - 1);
    let summary = |i: usize| {
        let ring_mean_log_e = [0, 1, 2].map(|c| {
            let v: Vec<f64> = common
                .iter()
                .filter_map(|&k| per_frame[i].iter().find(|r| r.frame == k)?.log_e[c])
                .collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        });
        Candidate {
            colour: CANDIDATES.get(i).copied(),
            lobes: exports.get(i).map_or(0, |e| e.scene.lobes),
            ring_mean_log_e,
            score: means[i].as_ref().map(|m| m.mean),
            se: means[i].as_ref().and_then(|m| m.se),
            difference: differences[i].as_ref().map(|d| d.mean),
            difference_ci95: differences[i].as_ref().and_then(|d| d.interval(LEVEL)),
        }
    };
    let candidates = (0..CANDIDATES.len()).map(summary).collect();
    let model = summary(CANDIDATES.len());
    let reason = if chosen == best {
        "the lowest score".to_string()
    } else {
        format!(
            "the cheapest whose difference from the best ({}) the training frames cannot tell \
             from noise",
            CANDIDATES[best].name()
        )
    };
    let choice = ColourChoice {
        colour: CANDIDATES[chosen],
        frames: common,
        skipped,
        clusters: n_clusters,
        dof,
        t95: dof.map(t95),
        cluster_rule: clusters.rule.clone(),
        kernel: format!("{kernel:?}"),
        candidates,
        model,
        reason,
    };
    let export = exports.swap_remove(chosen);
    Ok((choice, export))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_spread_over_the_whole_list_and_kept_when_few() {
        let all: Vec<usize> = (0..96).collect();
        let s = spread(&all, 24);
        assert_eq!(s.len(), 24);
        assert_eq!((s[0], s[1], s[23]), (0, 4, 92));
        assert_eq!(spread(&[3, 7], 24), vec![3, 7]);
    }
}
