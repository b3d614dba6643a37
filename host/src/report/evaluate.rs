//! What `subsurf evaluate` says: the held-out figures of a model on a dataset's frames, with
//! their clustered standard errors, the frames its fit used reported apart as in-sample, and a
//! second model's paired difference. The JSON keys are documented in docs/validation.md.
use std::fmt::Write as _;

use crate::evaluate::{Clustering, EvalPoints, Figures, FrameEval, Paired, split_frames};
use crate::modelfile::{FitRecord, ModelFile};
use crate::pipeline::{PipelineOptions, fit_record};

use super::fmt;

/// The name every report gives the figure to quote: the mean over the frames the fit never saw.
pub const HELD_OUT: &str = "held out";

/// `subsurf evaluate`'s result.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EvaluateReport {
    /// Where the model was compared.
    pub points: EvalPoints,
    /// Held-out frames judged (not skipped): the frames the fit never saw.
    pub frames: usize,
    /// Frames that could not be judged (no spot, no model at x_i...), held out or not.
    pub skipped: usize,
    /// The held-out figures (frames the model's fit did not use): the ones to quote.
    #[serde(flatten)]
    pub held_out: Figures,
    /// Whether the model file says which frames its fit used; without it every frame counts as
    /// held out, which only the user can vouch for.
    pub fitted_frames_known: bool,
    /// The frames evaluated that the model's fit used: in-sample, optimistic.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub in_sample: Option<Figures>,
    /// The frames of `in_sample`.
    pub in_sample_frames: Vec<usize>,
    /// The paired difference of this model minus `--against`'s on the held-out frames.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub against: Option<Paired>,
    /// The share of the samples compared that the vertices' own models predicted.
    pub local_share: Option<f64>,
    /// The rules the samples were read by.
    pub protocol: Protocol,
    /// The folder whose images were judged as the predictions (`--images`), when not the
    /// model's own.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub images: Option<std::path::PathBuf>,
    /// The photons per frame of a volume model's predictions, when the model judged is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub volume_photons: Option<usize>,
    /// Of those images: channel samples they leave black where the frame has light above the
    /// noise floor (judged as the floor), over every frame judged.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unlit: Option<u64>,
    /// What the figures cannot carry on their own: fewer than five clusters (what a difference
    /// must exceed there), frames the fit used.
    pub warnings: Vec<String>,
    /// Every frame: held out ones first, then the in-sample ones.
    pub per_frame: Vec<FrameEval>,
}

/// The evaluation protocol the samples were read by (docs/validation.md).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Protocol {
    /// `true` when a flag changed a rule of the dataset's protocol: figures are then comparable
    /// only with others measured under the same flags.
    pub overridden: bool,
    /// Where the noise floor came from.
    pub noise_floor_source: String,
    /// The rules (noise floor, exclusion radius, grazing limits, coverage check, laser
    /// tolerance), in the terms a model file records its fit's.
    #[serde(flatten)]
    pub rules: FitRecord,
    /// Whether the model's fit read its own samples by other rules (its file's record): its
    /// figures here are still on the protocol's samples.
    pub fit_rules_differ: bool,
}

impl Protocol {
    /// The protocol `opts`, for a model whose file may record other fit rules.
    pub fn of(
        opts: &PipelineOptions,
        overridden: bool,
        noise_floor_source: String,
        model: Option<&ModelFile>,
    ) -> Protocol {
        let rules = fit_record(opts);
        Protocol {
            overridden,
            noise_floor_source,
            rules,
            fit_rules_differ: model
                .and_then(|m| m.fitted_with)
                .is_some_and(|r| r != rules),
        }
    }
}

impl EvaluateReport {
    /// The report of `model`'s judged frames `evals` (and `against`'s on the same frames).
    pub fn new(
        ds: &crate::dataset::Dataset,
        model: &ModelFile,
        evals: &[FrameEval],
        against: Option<(&ModelFile, &[FrameEval])>,
        points: EvalPoints,
        protocol: Protocol,
    ) -> EvaluateReport {
        let fitted = |m: &ModelFile| m.fitted_frames.clone();
        EvaluateReport::of_frames(
            ds,
            fitted(model).as_deref(),
            evals,
            against.map(|(m, e)| (fitted(m), e)),
            points,
            protocol,
        )
    }

    /// The report of judged frames `evals` of a model whose fit used the frames `fitted` (if
    /// known; sorted), and a second model's (its fitted frames, its judged frames).
    pub fn of_frames(
        ds: &crate::dataset::Dataset,
        fitted_frames: Option<&[usize]>,
        evals: &[FrameEval],
        against: Option<(Option<Vec<usize>>, &[FrameEval])>,
        points: EvalPoints,
        protocol: Protocol,
    ) -> EvaluateReport {
        let clusters = Clustering::of_frames(ds, evals);
        let (held, fitted) = split_frames(fitted_frames, evals);
        let against = against.map(|(bm, b)| {
            // Only frames neither model was fitted to: a difference of in-sample errors says
            // nothing about prediction.
            let (b_held, _) = split_frames(bm.as_deref(), b);
            Paired::of(&held, &b_held, &clusters)
        });
        let skipped = evals.iter().filter(|e| e.skipped.is_some()).count();
        let held_out = Figures::of(&held, &clusters);
        let mut warnings: Vec<String> = held_out.warning(HELD_OUT).into_iter().collect();
        if let Some(a) = &against {
            warnings.extend(crate::evaluate::summary::few_clusters_warning(
                "the paired difference",
                a.clusters,
            ));
            warnings.dedup();
        }
        EvaluateReport {
            warnings,
            points,
            frames: held_out.frames,
            skipped,
            held_out,
            fitted_frames_known: fitted_frames.is_some(),
            in_sample: (!fitted.is_empty()).then(|| Figures::of(&fitted, &clusters)),
            in_sample_frames: fitted.iter().map(|e| e.frame).collect(),
            against,
            local_share: crate::evaluate::local_share(&held),
            protocol,
            images: None,
            volume_photons: None,
            unlit: evals.iter().filter_map(|e| e.unlit).reduce(|a, b| a + b),
            per_frame: held.into_iter().chain(fitted).collect(),
        }
    }

    /// The warning to print when frames the model was fitted to were evaluated.
    pub fn in_sample_warning(&self) -> Option<String> {
        (!self.in_sample_frames.is_empty()).then(|| {
            format!(
                "warning: {} of the frames evaluated were used by this model's fit (frames {}): \
                 they are reported apart as in-sample (optimistic); quote the {HELD_OUT} figure",
                self.in_sample_frames.len(),
                crate::dataset::format_frame_list(&self.in_sample_frames)
            )
        })
    }

    /// The report as text for a terminal.
    pub fn text(&self) -> String {
        let mut o = String::new();
        let at = match self.points {
            EvalPoints::Vertices => "at the vertices".to_string(),
            EvalPoints::Surface { level } => format!("at surface points of level {level}"),
        };
        let _ = writeln!(
            o,
            "{} {HELD_OUT} frames evaluated {at}{}, {} skipped",
            self.frames,
            if self.fitted_frames_known {
                ""
            } else {
                " (the model file does not say which frames its fit used: all counted as held out)"
            },
            self.skipped
        );
        let what = match (&self.images, self.volume_photons) {
            (_, Some(n)) => Some(format!("the volume model's images, {n} photons a frame,")),
            (Some(dir), None) => Some(format!("the images in {} (not the model),", dir.display())),
            (None, None) => None,
        };
        if let Some(what) = what {
            let _ = writeln!(
                o,
                "predictions: {what} on the dataset's samples and rules{}",
                self.unlit
                    .filter(|&n| n > 0)
                    .map(|n| format!(
                        "; {n} channel samples black in the images where the frames have light \
                         (judged at the noise floor)"
                    ))
                    .unwrap_or_default()
            );
        }
        figures_text(&mut o, HELD_OUT, &self.held_out);
        if let Some(a) = &self.against {
            let pm = |c: usize| {
                format!(
                    "{:>8} ± {:<8}",
                    fmt::opt(a.mean_difference[c], fmt::log_e),
                    fmt::opt(a.se[c], fmt::log_e)
                )
            };
            let _ = writeln!(
                o,
                "this model − --against, {} frames, {} clusters ({}), {}: {} {} {}",
                a.frames,
                a.clusters,
                a.cluster_rule,
                dof_text(a.dof, a.t95),
                pm(0),
                pm(1),
                pm(2)
            );
            let _ = writeln!(
                o,
                "  95 % interval {} {} {}",
                interval_text(a.ci95[0]),
                interval_text(a.ci95[1]),
                interval_text(a.ci95[2])
            );
        }
        if let Some(f) = &self.in_sample {
            figures_text(&mut o, "in-sample (frames the fit used)", f);
        }
        if let Some(l) = self.local_share {
            let _ = writeln!(
                o,
                "samples predicted by the vertices' own models: {:.1} % (the rest by the homogeneous baseline beyond their sampled range)",
                100.0 * l
            );
        }
        let p = &self.protocol;
        let _ = writeln!(
            o,
            "protocol{}: noise floor {:.3e} ({}), exclusion radius {} mm, spot cos min {}, coverage check {}{}",
            if p.overridden {
                " (changed by flags: compare only with figures under the same flags)"
            } else {
                " (the dataset's)"
            },
            p.rules.noise_floor,
            p.noise_floor_source,
            p.rules.exclusion_radius_mm,
            p.rules.spot_cos_min,
            if p.rules.coverage { "on" } else { "off" },
            if p.fit_rules_differ {
                "; the model's fit read its samples by other rules (its file's record)"
            } else {
                ""
            }
        );
        for e in self
            .per_frame
            .iter()
            .filter(|e| e.skipped.is_some())
            .take(10)
        {
            let _ = writeln!(
                o,
                "skipped frame {}: {}",
                e.frame,
                e.skipped.as_deref().unwrap_or("")
            );
        }
        o
    }
}

fn figures_text(o: &mut String, title: &str, f: &Figures) {
    let pm = |m: Option<f64>, se: Option<f64>| {
        format!(
            "{:>8} ± {:<8}",
            fmt::opt(m, fmt::log_e),
            fmt::opt(se, fmt::log_e)
        )
    };
    let _ = writeln!(
        o,
        "{title}: {} frames, {} clusters ({}), {}",
        f.frames,
        f.clusters,
        f.cluster_rule,
        dof_text(f.dof, f.t95)
    );
    let _ = writeln!(
        o,
        "                   red                 green               blue"
    );
    let _ = writeln!(
        o,
        "mean log E      {} {} {}",
        pm(f.mean_log_e[0], f.se_log_e[0]),
        pm(f.mean_log_e[1], f.se_log_e[1]),
        pm(f.mean_log_e[2], f.se_log_e[2])
    );
    let _ = writeln!(
        o,
        "95 % interval   {} {} {}",
        interval_text(f.ci95_log_e[0]),
        interval_text(f.ci95_log_e[1]),
        interval_text(f.ci95_log_e[2])
    );
    let _ = writeln!(
        o,
        "sample-weighted {} {} {}",
        pm(f.weighted_mean_log_e[0], f.weighted_se_log_e[0]),
        pm(f.weighted_mean_log_e[1], f.weighted_se_log_e[1]),
        pm(f.weighted_mean_log_e[2], f.weighted_se_log_e[2])
    );
    let _ = writeln!(
        o,
        "median          {:>8}            {:>8}            {:>8}",
        fmt::opt(f.median_log_e[0], fmt::log_e),
        fmt::opt(f.median_log_e[1], fmt::log_e),
        fmt::opt(f.median_log_e[2], fmt::log_e)
    );
}

/// "3 degrees of freedom (t 3.18)", or why there are none.
fn dof_text(dof: Option<usize>, t95: Option<f64>) -> String {
    match (dof, t95) {
        (Some(d), Some(t)) => format!("{d} degrees of freedom (95 % t {t:.2})"),
        _ => "no degree of freedom (no standard error)".into(),
    }
}

/// A 95 % interval in a column of 19 characters.
fn interval_text(ci: Option<[f64; 2]>) -> String {
    match ci {
        Some([lo, hi]) => format!(
            "{:<19}",
            format!("[{}, {}]", fmt::log_e(lo), fmt::log_e(hi))
        ),
        None => format!("{:<19}", "unbounded"),
    }
}
