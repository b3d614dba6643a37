//! Validation without ground truth (`subsurf fit --validate`): hold out a spread of frames, fit
//! the rest, judge the model on the held-out frames (Table-1 statistics, Eq. 8) next to its
//! in-sample figures and the homogeneous baseline's, then fit on everything.
//!
//! Which frames are held out matters on a turntable: a frame at a turntable angle the fit also
//! saw has its x_i close to a fitted one, so it measures little more than noise. What a user
//! needs to know is how the model predicts views it never saw — x_i between fitted light
//! positions, distances and viewing angles no training frame had — so whole turntable angles are
//! held out when the scan has enough of them ([`holdout`]).
use crate::dataset::Dataset;
use crate::evaluate::{EvalPoints, EvaluateError, FrameEval, evaluate_in};
use crate::modelfile::{ColourMode, ModelFile, VertexStatus};
use crate::pipeline::{Context, LogEStats};

/// A scan with at least this many distinct turntable angles has whole angles held out.
pub const MIN_ANGLES_FOR_ANGLE_HOLDOUT: usize = 4;
/// Every k-th angle (or, with fewer angles, every k-th frame) is held out.
pub const HOLDOUT_EVERY: usize = 4;

/// The held-out frames and the rule that chose them.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Holdout {
    /// Frames held out of the validation fit.
    pub frames: Vec<usize>,
    /// The rest.
    pub training: Vec<usize>,
    /// The rule, in words (for the report).
    pub rule: String,
}

/// Chooses the held-out frames among `frames`: with at least
/// [`MIN_ANGLES_FOR_ANGLE_HOLDOUT`] distinct turntable angles, every [`HOLDOUT_EVERY`]-th angle
/// (in angle order, starting with the second) with all its frames; otherwise every
/// [`HOLDOUT_EVERY`]-th frame (starting with the second), spread over the scan's order. At least
/// one frame stays in training.
pub fn holdout(ds: &Dataset, frames: &[usize]) -> Holdout {
    let mut angles: Vec<f64> = frames
        .iter()
        .map(|&k| ds.spec.frames[k].turntable_deg.rem_euclid(360.0))
        .collect();
    angles.sort_by(f64::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    let (held, rule): (Vec<usize>, String) = if angles.len() >= MIN_ANGLES_FOR_ANGLE_HOLDOUT {
        let out: Vec<f64> = angles
            .iter()
            .copied()
            .skip(1)
            .step_by(HOLDOUT_EVERY)
            .collect();
        let held = frames
            .iter()
            .copied()
            .filter(|&k| {
                let a = ds.spec.frames[k].turntable_deg.rem_euclid(360.0);
                out.iter().any(|o| (o - a).abs() < 1e-6)
            })
            .collect();
        let list: Vec<String> = out.iter().map(|a| format!("{a}")).collect();
        (
            held,
            format!(
                "whole turntable angles held out: every {HOLDOUT_EVERY}th of the scan's {} angles ({} degrees), so held-out x_i lie between fitted ones",
                angles.len(),
                list.join(", ")
            ),
        )
    } else {
        (
            frames
                .iter()
                .copied()
                .skip(1)
                .step_by(HOLDOUT_EVERY)
                .collect(),
            format!(
                "every {HOLDOUT_EVERY}th frame held out (the scan has {} turntable angle(s), fewer than {MIN_ANGLES_FOR_ANGLE_HOLDOUT})",
                angles.len()
            ),
        )
    };
    let mut training: Vec<usize> = frames
        .iter()
        .copied()
        .filter(|k| !held.contains(k))
        .collect();
    let mut held = held;
    if training.is_empty()
        && let Some(k) = held.pop()
    {
        training.push(k);
    }
    Holdout {
        frames: held,
        training,
        rule,
    }
}

/// The model with every vertex's fall-off replaced by the homogeneous baseline: what the
/// baseline alone predicts, for judging it on held-out frames like any model. It keeps the
/// model's alpha (per vertex and, where there is one, the face lattice), so the two differ only
/// in the per-vertex fall-offs: the comparison says what those add. Every vertex gets the
/// baseline, those without a model of their own too. `None` without a baseline.
pub fn baseline_only(model: &ModelFile) -> Option<ModelFile> {
    let b = model.baseline.as_ref()?;
    let m = model.shape.segments;
    let params = match model.shape.colour {
        ColourMode::Shared => {
            let mut p = b.params[..2].to_vec();
            for _ in 0..m {
                p.extend_from_slice(&b.params[2..]);
            }
            p
        }
        ColourMode::PerChannel => {
            let k = 2 * b.terms;
            let mut p = Vec::with_capacity(3 * k * m);
            for c in 0..3 {
                for _ in 0..m {
                    p.extend_from_slice(&b.params[c * k..(c + 1) * k]);
                }
            }
            p
        }
    };
    let mut out = model.clone();
    out.shape.terms = out.shape.terms.max(b.terms);
    out.baseline = None;
    for v in &mut out.vertices {
        v.status = VertexStatus::Interpolated;
        v.terms = b.terms as u8;
        // Every vertex, one without a model (segments 0) too, at the file's m.
        v.segments = m as u8;
        v.params = params.clone();
        v.r_range = crate::modelfile::NO_RANGE;
    }
    out.check().ok()?;
    Some(out)
}

/// The held-out figures of a validation fit.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Validation {
    /// Which frames were held out, and why those.
    pub holdout: Holdout,
    /// Held-out frames that could be evaluated (registered, model at x_i).
    pub evaluated: usize,
    /// Table-1 statistics on the held-out frames: the number to trust.
    pub held_out: LogEStats,
    /// The same statistics of the homogeneous baseline alone on the held-out frames.
    pub baseline_held_out: Option<LogEStats>,
    /// Table-1 statistics of the validation fit on its own training frames (in-sample).
    pub in_sample: LogEStats,
    /// Per held-out frame.
    pub per_frame: Vec<FrameEval>,
}

/// Judges `model` (fitted on `holdout.training`) on the held-out frames, beside the baseline,
/// from the run's sample store (`ctx`, [`crate::pipeline::prepare`] of the training and held-out
/// frames): no frame is read again.
pub fn judge(
    ctx: &Context,
    model: &ModelFile,
    holdout: Holdout,
    in_sample: LogEStats,
    progress: &dyn crate::progress::Progress,
) -> Result<Validation, EvaluateError> {
    let at = EvalPoints::Vertices;
    let (per_frame, held_out) = evaluate_in(ctx, model, &holdout.frames, at, progress)?;
    let baseline_held_out = match baseline_only(model) {
        Some(b) => Some(evaluate_in(ctx, &b, &holdout.frames, at, progress)?.1),
        None => None,
    };
    Ok(Validation {
        evaluated: per_frame.iter().filter(|e| e.skipped.is_none()).count(),
        holdout,
        held_out,
        baseline_held_out,
        in_sample,
        per_frame,
    })
}

/// `[1, 2, 3, 7, 9, 10]` as `1-3,7,9-10` (the syntax `--frames` reads).
pub fn frame_list(frames: &[usize]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < frames.len() {
        let mut j = i;
        while j + 1 < frames.len() && frames[j + 1] == frames[j] + 1 {
            j += 1;
        }
        parts.push(if j > i {
            format!("{}-{}", frames[i], frames[j])
        } else {
            frames[i].to_string()
        });
        i = j + 1;
    }
    parts.join(",")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modelfile::{BaselineParams, ModelShape};

    /// The baseline is judged as a model on every dataset: a vertex without a model of its own
    /// and vertices of fewer segments than the file's take it too (a model with such vertices
    /// once had no baseline row), and it keeps the model's alpha.
    #[test]
    fn the_baseline_replaces_every_vertex_and_keeps_alpha() {
        let mut m = ModelFile::homogeneous(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            vec![[0.0, 0.0, 1.0]; 3],
            vec![[0, 1, 2]],
            [0.8, 0.6],
            &[(1.0, -1.0)],
        );
        m.shape = ModelShape {
            terms: 1,
            segments: 2,
            ..m.shape
        };
        m.vertices[0].params = vec![0.8, 0.6, 1.0, -1.0, 2.0, -1.5];
        m.vertices[0].segments = 2;
        m.vertices[1].alpha = [1.2, 0.9, 1.0];
        let none = &mut m.vertices[2];
        none.status = VertexStatus::NoModel;
        none.terms = 0;
        none.segments = 0;
        none.params.clear();
        m.check().unwrap();
        assert_eq!(baseline_only(&m), None, "no baseline, no row");
        m.baseline = Some(BaselineParams {
            terms: 1,
            params: vec![0.7, 0.5, 3.0, -0.8],
            r_range: [0.5, 9.0],
        });
        let b = baseline_only(&m).expect("a baseline model");
        for (v, w) in b.vertices.iter().zip(&m.vertices) {
            assert_eq!(v.segments, 2);
            assert_eq!(v.params, vec![0.7, 0.5, 3.0, -0.8, 3.0, -0.8]);
            assert_eq!(v.alpha, w.alpha);
        }
    }

    #[test]
    fn frame_lists_read_back() {
        let f = [1, 2, 3, 7, 9, 10];
        assert_eq!(frame_list(&f), "1-3,7,9-10");
        assert_eq!(
            crate::dataset::parse_frame_list(&frame_list(&f)).unwrap(),
            f.to_vec()
        );
        assert_eq!(frame_list(&[]), "");
    }
}
