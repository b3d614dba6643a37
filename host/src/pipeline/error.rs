//! Stage `error` (section 5, Eq. 8): log E(x_i) of every group's fit with alpha, measured on the
//! frames read again (cheaper in memory than keeping the samples), and the acceptance of each
//! fit: too few samples, above `max_log_e`, or an outlier against the median fit fails, and its
//! vertices go to the `interpolate` stage.
//!
//! Owns the acceptance rule and the Table-1 statistics of the run; never refits.
use std::collections::BTreeMap;

use rayon::prelude::*;

use crate::model::{ColourModel, LogEAccumulator};
use crate::modelfile::{ModelShape, params_of};
use crate::progress::Progress;

use super::findings::{FailReason, FitReport, LogEStats, OrderCount};
use super::fit::{Fitted, ln_rd_with};
use super::load::Context;
use super::register::RegisteredFrame;
use super::select::{Groups, group_samples};
use super::{OUTLIER_MIN_LOG_E, PipelineError, PipelineOptions};

/// A vertex's own accepted fit.
#[derive(Debug, Clone)]
pub struct OwnFit {
    /// Parameters in the model file's order.
    pub params: Vec<f64>,
    /// Its order n.
    pub terms: usize,
    /// Its direction segments m.
    pub segments: usize,
    /// log E(x_i) of the fit, mean over channels.
    pub log_e: f32,
    /// The model.
    pub model: ColourModel,
    /// Sampled distance range.
    pub r_range: [f64; 2],
}

/// log E(x_i) (Eq. 8, with alpha) per channel of every group's fit; `None` where the group has
/// no fit or its frames could not be read. Second: with `baseline`, the same of the homogeneous
/// baseline (with the model's alpha) on the group's samples, when there is one: a figure of the
/// report only, which the cross-validation's fold models, judged and dropped, do without (it
/// costs about as many exponentials and logarithms as the model's own).
pub fn log_e_of_fits(
    ctx: &Context,
    regs: &[RegisteredFrame],
    groups: &Groups,
    fitted: &Fitted,
    baseline: bool,
    progress: &dyn Progress,
) -> (Vec<Option<[f64; 3]>>, Vec<[f64; 3]>) {
    progress.start("error", groups.keys.len() as u64);
    let threshold = ctx.opts.error_threshold;
    // The default's vectorised ln R_d ([`crate::model::ExpSum::ln_eval_many`]); the reference
    // keeps libm's.
    let vectorised = ctx.opts.speed == super::Speed::Default;
    let baseline = fitted
        .baseline
        .as_ref()
        .filter(|_| baseline)
        .map(|b| &b.baseline.model);
    // ln alpha once per vertex, not once per sample: the same logarithm of the same number.
    let ln_alpha: Vec<[f64; 3]> = fitted.alpha.iter().map(|a| a.map(f64::ln)).collect();
    let both: Vec<Option<([f64; 3], [f64; 3])>> = fitted
        .fits
        .par_iter()
        .zip(&groups.keys)
        .map(|(f, key)| {
            let out = f.as_ref().ok().and_then(|g| {
                let (data, _) = group_samples(ctx, regs, key).ok()?;
                let mut acc = [LogEAccumulator::default(); 3];
                let mut base = [LogEAccumulator::default(); 3];
                let (model, baseline) =
                    (g.model.ln_evaluator(), baseline.map(|b| b.ln_evaluator()));
                let ln_model = ln_rd_with(&model, &data, true, vectorised);
                let ln_base = baseline
                    .as_ref()
                    .map(|b| ln_rd_with(b, &data, false, vectorised));
                for (ch, d) in data.iter().enumerate() {
                    for (j, x) in d.iter().enumerate() {
                        let ln_alpha = ln_alpha[x.vertex as usize][ch];
                        let ln = ln_alpha + ln_model[ch][j];
                        acc[ch].add_ln(ln, x.s, threshold);
                        // The baseline with the model's alpha, as the held-out row judges it.
                        if let Some(ln_b) = &ln_base {
                            base[ch].add_ln(ln_alpha + ln_b[ch][j], x.s, threshold);
                        }
                    }
                }
                Some((
                    acc.map(|a| a.log_e().unwrap_or(f64::NAN)),
                    base.map(|a| a.log_e().unwrap_or(f64::NAN)),
                ))
            });
            progress.inc(1);
            out
        })
        .collect();
    (
        both.iter().map(|b| b.map(|b| b.0)).collect(),
        both.iter().flatten().map(|b| b.1).collect(),
    )
}

/// The mean over the channels with a value.
fn channel_mean(le: &[f64; 3]) -> Option<f64> {
    let f: Vec<f64> = le.iter().copied().filter(|x| x.is_finite()).collect();
    (!f.is_empty()).then(|| f.iter().sum::<f64>() / f.len() as f64)
}

/// The acceptance threshold: `max_log_e`, lowered to `outlier_factor` × the median fit's log E
/// (at least [`OUTLIER_MIN_LOG_E`]). A fit far worse than the typical one (e.g. x_i
/// misregistered near a silhouette, so every distance is wrong) is a failure.
fn acceptance_threshold(errors: &[Option<[f64; 3]>], opts: &PipelineOptions) -> f64 {
    let mut means: Vec<f64> = errors
        .iter()
        .flatten()
        .map(|le| channel_mean(le).unwrap_or(0.0))
        .filter(|m| m.is_finite())
        .collect();
    means.sort_by(f64::total_cmp);
    match means.get(means.len() / 2) {
        Some(&median) if median > 0.0 => opts
            .max_log_e
            .min((opts.outlier_factor * median).max(OUTLIER_MIN_LOG_E)),
        _ => opts.max_log_e,
    }
}

/// Each vertex's own fit, where its group's fit is accepted, and the shape of the model. Counts
/// failures by reason, the orders, the threshold and the Table-1 statistics into `report`.
pub fn accept(
    groups: &Groups,
    fitted: &Fitted,
    errors: &[Option<[f64; 3]>],
    opts: &PipelineOptions,
    report: &mut FitReport,
) -> Result<(Vec<Option<OwnFit>>, ModelShape), PipelineError> {
    let shape_terms = fitted
        .fits
        .iter()
        .filter_map(|f| f.as_ref().ok().map(|g| g.terms))
        .max()
        .unwrap_or(0);
    if shape_terms == 0 {
        let mut reasons: BTreeMap<FailReason, usize> = BTreeMap::new();
        for e in fitted.fits.iter().filter_map(|f| f.as_ref().err()) {
            *reasons.entry(*e).or_default() += 1;
        }
        return Err(PipelineError::NothingFitted(format!(
            "{} registered frames of {} selected; failed fits by reason: {:?}",
            report.frames.registered, report.frames.selected, reasons
        )));
    }
    let shape = ModelShape {
        terms: shape_terms,
        segments: opts.model.segments,
        colour: opts.model.colour,
    };
    let max_log_e = acceptance_threshold(errors, opts);
    report.max_log_e = max_log_e;
    let nv = groups.no_data.len();
    let mut own: Vec<Option<OwnFit>> = vec![None; nv];
    let mut vertex_fail: Vec<Option<FailReason>> = groups
        .no_data
        .iter()
        .map(|&n| n.then_some(FailReason::NoData))
        .collect();
    let mut light_log_e = Vec::new();
    // (n, m) -> (light positions, vertices, light positions on the baseline's fall-off).
    let mut chosen: BTreeMap<(usize, usize), (usize, usize, usize)> = BTreeMap::new();
    for ((f, err), verts) in fitted.fits.iter().zip(errors).zip(&groups.members) {
        let outcome = match (f, err) {
            (Err(e), _) => Err(*e),
            (Ok(_), None) => Err(FailReason::FrameUnreadable),
            (Ok(g), Some(le)) => match channel_mean(le) {
                None => Err(FailReason::TooFewSamples),
                Some(mean) if mean > max_log_e => Err(FailReason::HighError),
                Some(mean) => match params_of(&g.model) {
                    Ok((p, n, m)) if p.iter().all(|x| x.is_finite()) => {
                        light_log_e.push(*le);
                        *report.orders.entry(n).or_default() += 1;
                        let e = chosen.entry((n, m)).or_default();
                        e.0 += 1;
                        e.1 += verts.len();
                        e.2 += g.on_baseline as usize;
                        Ok(OwnFit {
                            params: p,
                            terms: n,
                            segments: m,
                            log_e: mean as f32,
                            model: g.model.clone(),
                            r_range: g.r_range,
                        })
                    }
                    _ => Err(FailReason::NonPhysical),
                },
            },
        };
        for &v in verts {
            match &outcome {
                Ok(o) => own[v as usize] = Some(o.clone()),
                Err(e) => vertex_fail[v as usize] = Some(*e),
            }
        }
    }
    report.log_e = LogEStats::of(&light_log_e);
    report.chosen_orders = chosen
        .into_iter()
        .map(
            |((terms, segments), (light_positions, vertices, on_baseline))| OrderCount {
                terms,
                segments,
                light_positions,
                vertices,
                on_baseline,
            },
        )
        .collect();
    for r in vertex_fail.iter().flatten() {
        *report.failures.entry(*r).or_default() += 1;
    }
    Ok((own, shape))
}
