//! Choices of the fit made by cross-validation: folds of the training frames, each fitted on
//! the rest and judged on itself as `subsurf evaluate` judges (WIP: the segment ladder).
use crate::pipeline::{
    Context, CvCandidate, CvChoice, CvReport, FitOutput, Fitter, PipelineError, fit_prepared,
};
use crate::progress::Progress;

/// How many direction segments m (Eq. 3) the fit uses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Segments {
    /// Exactly m.
    Fixed(usize),
    /// "Model only what the scene requires": one fit per m of [`SEGMENT_LADDER`].
    Auto {
        /// Relative tolerance, e.g. 0.05 = within 5 % of the best.
        tolerance: f64,
    },
}

/// The values of m `--segments auto` tries, in order.
pub const SEGMENT_LADDER: [usize; 4] = [1, 2, 4, 8];

/// A fit of the prepared run `ctx` on `frames` with the segments chosen by `segments`.
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
    let mut report = CvReport {
        rule: "in-sample".into(),
        ..CvReport::default()
    };
    report.choices.push(CvChoice {
        name: "segments".into(),
        rule: format!("smallest m within {tolerance} of the best in-sample log E"),
        candidates: runs
            .iter()
            .map(|(m, e, _)| CvCandidate {
                value: m.to_string(),
                score: *e,
                chosen: *m == chosen,
                ..CvCandidate::default()
            })
            .collect(),
        chosen: chosen.to_string(),
    });
    let (_, _, run) = runs
        .into_iter()
        .find(|(m, _, _)| *m == chosen)
        .ok_or_else(|| PipelineError::Invalid("no segment count was fitted".into()))?;
    let mut out = run?;
    out.report.cross_validation = Some(report);
    Ok(out)
}
