//! The homogeneous baseline (one isotropic fall-off for the whole object) and a light
//! position's samples scaled onto it: the simplest candidate of every light position.

use super::*;

/// The baseline's fall-off with the channel scales of a light position's samples: per channel,
/// the mean of ln s − ln R_d (the least-squares scale of the log objective). `None` without
/// samples in a channel or if the result is not a valid model.
pub(super) fn scaled_baseline(base: &ColourModel, data: &ChannelSamples) -> Option<ColourModel> {
    let mut a = [0.0; 3];
    let ev = base.ln_evaluator();
    for (c, d) in data.iter().enumerate() {
        let v: Vec<f64> = d
            .iter()
            .map(|x| x.s.ln() - ev.ln_eval_channel(c, x.r, x.phi))
            .filter(|v| v.is_finite())
            .collect();
        if v.is_empty() {
            return None;
        }
        a[c] = v.iter().sum::<f64>() / v.len() as f64;
    }
    let scale = |f: &Anisotropic, k: f64| Anisotropic {
        segments: f.segments.iter().map(|e| e.scaled(k.exp())).collect(),
    };
    let m = match base {
        ColourModel::Shared { falloff, s_g, s_b } => ColourModel::Shared {
            falloff: scale(falloff, a[0]),
            s_g: s_g * (a[1] - a[0]).exp(),
            s_b: s_b * (a[2] - a[0]).exp(),
        },
        ColourModel::PerChannel { channels } => ColourModel::PerChannel {
            channels: [
                scale(&channels[0], a[0]),
                scale(&channels[1], a[1]),
                scale(&channels[2], a[2]),
            ],
        },
    };
    m.validate().ok().map(|_| m)
}

/// The homogeneous baseline: one isotropic fall-off (m = 1, the model's colour mode) fitted to
/// every group's samples pooled as captured (alpha = 1), at most [`BASELINE_POOL`] per channel
/// and group (evenly strided). `None` if that fit fails.
pub(super) fn fit_baseline(
    ctx: &Context,
    regs: &[RegisteredFrame],
    groups: &Groups,
    fitter: &dyn Fitter,
) -> Option<FittedBaseline> {
    let pooled: ChannelSamples = groups
        .keys
        .par_iter()
        .map(|key| {
            let mut out: ChannelSamples = Default::default();
            if let Ok((data, _)) = group_samples(ctx, regs, key) {
                for (ch, d) in data.into_iter().enumerate() {
                    let step = d.len().div_ceil(BASELINE_POOL).max(1);
                    out[ch].extend(
                        d.into_iter()
                            .step_by(step)
                            .map(|x| GroupSample { phi: None, ..x }),
                    );
                }
            }
            out
        })
        .reduce(ChannelSamples::default, |mut a, b| {
            for (x, y) in a.iter_mut().zip(b) {
                x.extend(y);
            }
            a
        });
    let choice = ModelChoice {
        colour: ctx.opts.model.colour,
        segments: 1,
    };
    // As the interpolation's refits do: one term fewer while the fit fails. The pooled curve's
    // top term often runs its rate to 0 (a constant, which the drop rule then removes), and the
    // solver gets there slowly: at the draft preset's iteration limit that fit failed, the run
    // kept no baseline, and its renders came out 11–14 % dark (BENCHMARKS.md, the tradeoff benchmark).
    let fitter = &AtMost::dropping(fitter);
    let max_n = fitter.max_terms().unwrap_or(1);
    let (model, terms, _) = fit_samples(&pooled, &choice, fitter, false, &mut Vec::new())
        .or_else(|e| {
            (1..max_n)
                .rev()
                .find_map(|n| {
                    let at_most = AtMost::terms(fitter, n);
                    fit_samples(&pooled, &choice, &at_most, false, &mut Vec::new()).ok()
                })
                .ok_or(e)
        })
        .ok()?;
    let r_range = pooled
        .iter()
        .flatten()
        .fold([f64::INFINITY, 0.0], |[lo, hi], x| {
            [lo.min(x.r), hi.max(x.r)]
        });
    let (params, _, _) = params_of(&model).ok()?;
    params
        .iter()
        .all(|p| p.is_finite())
        .then(|| FittedBaseline {
            baseline: Baseline { model, r_range },
            params: BaselineParams {
                terms,
                params,
                r_range,
            },
            samples: pooled.iter().map(Vec::len).sum(),
        })
}

/// The baseline of a run: for prediction, for the model file, and how many samples it pooled.
#[derive(Debug, Clone)]
pub struct FittedBaseline {
    /// As prediction uses it.
    pub baseline: Baseline,
    /// As the model file stores it.
    pub params: BaselineParams,
    /// Channel samples pooled.
    pub samples: usize,
}
