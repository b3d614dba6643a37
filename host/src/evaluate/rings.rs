//! The ring yardstick (`subsurf evaluate --rings`): per frame, Eq. 8 over the means of linear
//! radiance in rings around x_i instead of over single samples.
//!
//! Why: a path tracer judged sample by sample measures its own noise. Cycles traces from the
//! camera, and a pixel sees the laser's light only where its probe lands in a footprint under a
//! millimetre across, so most pixels of a frame come out black or far too bright at any sample
//! count two cores afford, and per-sample log E is dominated by that grain. The light a
//! renderer carries over a ring of many pixels is a mean of all their probes: its noise falls
//! as one over the square root of the ring's pixels times the samples per pixel, while the
//! fall-off's shape and strength — what a material conversion gets right or wrong — survive
//! the averaging.
//!
//! The rings of a frame are fixed by the frame's samples alone (never by the prediction), so
//! every prediction of the frame — a model's, any renderer's images — is judged on the same
//! rings: log-spaced in the distance `r = |x_o − x_i|` (edges a factor [`RING_RATIO`] apart from
//! the nearest sample out), merged outwards until each ring holds at least
//! [`min_ring_samples`] of the frame's judged samples (a last ring short of that joins the one
//! before it). The samples are those of the per-sample evaluation: the same store, exclusion
//! radius and noise floor (a channel enters a ring where its sample is above the floor t, as
//! it enters Eq. 8). Per ring and channel the means of the measured samples and of the
//! predictions over the same samples give `ln E_ring = ln(mean prediction / mean measured)`;
//! a ring whose mean prediction is at or below the floor t (black, or a renderer's truncated
//! tail) is judged at the floor (`ln(t / mean measured)`, as a black sample is) and counted. The frame's ring log E is the root mean square of its rings'
//! `ln E_ring` (each ring one term: Eq. 8 over rings).

use rayon::prelude::*;
use serde::Serialize;

use super::images::{FrameImages, Reference};
use super::{EvalPoints, EvaluateError, model_at};
use crate::geometry::V3;
use crate::modelfile::ModelFile;
use crate::pipeline::{Context, LogEStats, register_one};
use crate::progress::Progress;
use crate::store::PointSet;

/// The ratio between neighbouring ring edges before merging: four rings per doubling of r.
pub const RING_RATIO: f64 = 1.189_207_115_002_721; // 2^(1/4)

/// The fewest samples a ring holds: [`MIN_RING_SAMPLES`], or a 24th of the frame's judged
/// samples where that is more (at most about 24 rings per frame).
pub const MIN_RING_SAMPLES: usize = 16;

/// The fewest samples a ring of a frame with `n` judged samples holds.
pub fn min_ring_samples(n: usize) -> usize {
    MIN_RING_SAMPLES.max(n.div_ceil(24))
}

/// What predicts a frame's samples.
#[derive(Debug, Clone, Copy)]
pub enum Prediction<'a> {
    /// The model: alpha(x_o) · R_d(x_i → x_o) (Eq. 9), as the per-sample evaluation.
    Model,
    /// An image per frame (`subsurf evaluate --images`): its bilinear read at the sample's
    /// projection over the frame's exposure, against the frames or a reference's images (a
    /// second render judged against a first: the rings and their samples are still the
    /// frame's, the reference's reads, black ones included, what is measured in them).
    Images(&'a FrameImages<'a>, Reference<'a>),
}

/// One sample as the rings see it: its distance from x_i, the measured value and the
/// prediction per channel, and which channels are judged (above the floor, valid).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RingSample {
    /// |x_o − x_i| (mm).
    pub r: f64,
    /// The measured value (frame units: pixel / exposure_s).
    pub measured: [f64; 3],
    /// The prediction (same units; 0 where a renderer left it black).
    pub predicted: [f64; 3],
    /// Bit c: channel c is judged.
    pub judged: u8,
}

/// One ring of a frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Ring {
    /// Inner edge (mm).
    pub r_min: f64,
    /// Outer edge (mm).
    pub r_max: f64,
    /// Judged samples per channel.
    pub samples: [u64; 3],
    /// ln(mean prediction / mean measured) per channel; `None` without samples.
    pub ln_e: [Option<f64>; 3],
}

/// A frame judged by its rings.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameRings {
    /// Frame index.
    pub frame: usize,
    /// The root mean square of the rings' ln E per channel; `None` where no ring has samples.
    pub log_e: [Option<f64>; 3],
    /// The rings, inner first.
    pub rings: Vec<Ring>,
    /// Ring channels whose mean prediction is at or below the noise floor, judged at the floor.
    pub unlit: u64,
    /// Why the frame was not judged, if it was not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
}

/// The rings of one frame's samples, judged with the noise floor `t`.
pub fn judge_rings(frame: usize, samples: &[RingSample], t: f64) -> FrameRings {
    let mut s: Vec<&RingSample> = samples
        .iter()
        .filter(|s| s.judged != 0 && s.r.is_finite() && s.r >= 0.0)
        .collect();
    s.sort_by(|a, b| a.r.total_cmp(&b.r));
    let mut out = FrameRings {
        frame,
        log_e: [None; 3],
        rings: Vec::new(),
        unlit: 0,
        skipped: None,
    };
    let Some(first) = s.first() else {
        return out;
    };
    let need = min_ring_samples(s.len());
    // Ring bounds as index ranges of the sorted samples: fine log-spaced cells from the nearest
    // sample out, merged until each holds `need`.
    let r0 = first.r.max(1e-6);
    let cell = |r: f64| -> i64 { ((r.max(r0) / r0).ln() / RING_RATIO.ln()).floor() as i64 };
    let mut bounds: Vec<(usize, usize)> = Vec::new();
    let mut start = 0;
    let mut i = 0;
    while i < s.len() {
        // The end of the cell holding sample i.
        let c = cell(s[i].r);
        let mut j = i;
        while j < s.len() && cell(s[j].r) == c {
            j += 1;
        }
        if j - start >= need {
            bounds.push((start, j));
            start = j;
        }
        i = j;
    }
    if start < s.len() {
        match bounds.last_mut() {
            Some(last) => last.1 = s.len(),
            None => bounds.push((start, s.len())),
        }
    }
    let mut sum_sq = [0.0; 3];
    let mut count = [0u64; 3];
    for (k, &(a, b)) in bounds.iter().enumerate() {
        let members = &s[a..b];
        let edge = |m: usize| r0 * RING_RATIO.powi(cell(s[m].r) as i32);
        let r_min = if k == 0 { r0 } else { edge(a) };
        let r_max = if b == s.len() { s[b - 1].r } else { edge(b) };
        let mut ring = Ring {
            r_min,
            r_max,
            samples: [0; 3],
            ln_e: [None; 3],
        };
        for c in 0..3 {
            let (mut m, mut p, mut n) = (0.0, 0.0, 0u64);
            for x in members.iter().filter(|x| x.judged & (1 << c) != 0) {
                m += x.measured[c];
                p += x.predicted[c].max(0.0);
                n += 1;
            }
            if n == 0 {
                continue;
            }
            // A reference render's ring mean below the floor is judged at the floor as well
            // (two black renders agree); the frames' means are above it by construction.
            let (m, p) = ((m / n as f64).max(t), p / n as f64);
            if m <= 0.0 {
                continue;
            }
            // A ring mean below the floor is light the frames cannot tell from none: judged
            // as the floor, as a black sample is (else a renderer's truncated tail would count
            // without bound).
            let ln_p = if p > t && p > 0.0 {
                p.ln()
            } else {
                out.unlit += 1;
                t.max(f64::MIN_POSITIVE).ln()
            };
            let e = ln_p - m.ln();
            ring.samples[c] = n;
            ring.ln_e[c] = Some(e);
            sum_sq[c] += e * e;
            count[c] += 1;
        }
        out.rings.push(ring);
    }
    out.log_e = [0, 1, 2].map(|c| (count[c] > 0).then(|| (sum_sq[c] / count[c] as f64).sqrt()));
    out
}

/// The frames `frames` of a run whose store holds them, judged by their rings for `prediction`
/// (the model's, or images'), and the mean over frames of the rings' log E.
pub fn evaluate_rings_in(
    ctx: &Context,
    model: Option<&ModelFile>,
    prediction: Prediction,
    frames: &[usize],
    at: EvalPoints,
    progress: &dyn Progress,
) -> Result<(Vec<FrameRings>, LogEStats), EvaluateError> {
    if let Some(model) = model {
        super::check_mesh(ctx.ds, model)?;
    }
    let set = at.point_set();
    progress.start("rings", frames.len() as u64);
    let t = ctx.opts.error_threshold;
    let evals: Result<Vec<FrameRings>, EvaluateError> = frames
        .par_iter()
        .map(|&k| {
            let r = match ring_samples(ctx, model, prediction, k, set) {
                Ok(Ok(samples)) => Ok(judge_rings(k, &samples, t)),
                Ok(Err(reason)) => Ok(FrameRings {
                    frame: k,
                    log_e: [None; 3],
                    rings: Vec::new(),
                    unlit: 0,
                    skipped: Some(reason),
                }),
                Err(e) => Err(e),
            };
            progress.inc(1);
            r
        })
        .collect();
    let evals = evals?;
    let vals: Vec<[f64; 3]> = evals
        .iter()
        .filter(|e| e.skipped.is_none())
        .map(|e| e.log_e.map(|x| x.unwrap_or(f64::NAN)))
        .collect();
    Ok((evals, LogEStats::of(&vals)))
}

/// Frame `k`'s samples with their predictions; the inner `Err` is why the frame is skipped (as
/// the per-sample evaluation skips it), the outer an image that cannot be read.
fn ring_samples(
    ctx: &Context,
    model: Option<&ModelFile>,
    prediction: Prediction,
    k: usize,
    set: PointSet,
) -> Result<Result<Vec<RingSample>, String>, EvaluateError> {
    let Some(f) = ctx.ds.spec.frames.get(k) else {
        return Ok(Err(format!(
            "dataset has {} frames",
            ctx.ds.spec.frames.len()
        )));
    };
    let reg = match register_one(ctx, k) {
        Ok(r) => r,
        Err(e) => return Ok(Err(e)),
    };
    let x_i = reg.x_i;
    // Images of a volume (no model file) are judged wherever the laser meets the mesh.
    let at = match model {
        Some(m) => match model_at(ctx, m, reg.triangle, x_i) {
            Some(at) => Some((m, at)),
            None => return Ok(Err("no model at x_i".into())),
        },
        None => None,
    };
    let Some(store) = ctx.store() else {
        return Ok(Err("no sample store".into()));
    };
    let fs = match store.samples(k, set) {
        Ok(Some(fs)) => fs,
        Ok(None) => return Ok(Err("no samples at these points".into())),
        Err(e) => return Ok(Err(e.to_string())),
    };
    let points = match set {
        PointSet::Vertices => None,
        PointSet::Lattice => match store.points() {
            Some(p) => Some(p),
            None => return Ok(Err("no surface points in the store".into())),
        },
    };
    let position = |p: usize| -> V3 {
        match points {
            None => ctx.ds.mesh.positions[p],
            Some(pts) => pts.points.positions[p],
        }
    };
    let t = ctx.opts.error_threshold;
    let chans = f.channel.channels();
    let mut out = Vec::with_capacity(fs.samples.len());
    match prediction {
        Prediction::Model => {
            let Some((model, at)) = at else {
                return Ok(Err("no model to predict with".into()));
            };
            for s in fs.samples.iter() {
                let p = s.vertex as usize;
                let x_o = position(p);
                let a = match points {
                    None => model.vertices[p].alpha.map(|a| a as f64),
                    Some(pts) => model.alpha_at(pts.points.face[p] as usize, pts.points.bary[p]),
                };
                let (r, phi) = at.frame.polar(x_i, x_o);
                let ln = at.ln_eval(r, phi);
                let mut judged = 0u8;
                for &c in chans {
                    if s.valid & (1 << c) != 0 && s.value[c] > t && s.value[c].is_finite() {
                        judged |= 1 << c;
                    }
                }
                let predicted = [0, 1, 2].map(|c| {
                    let v = a[c] * ln[c].exp();
                    if v.is_finite() { v } else { 0.0 }
                });
                out.push(RingSample {
                    r: crate::geometry::dist(x_o, x_i),
                    measured: s.value,
                    predicted,
                    judged,
                });
            }
        }
        Prediction::Images(images, reference) => {
            let judged = match super::images::prepare(ctx, model, k, set) {
                Ok(j) => j,
                Err(reason) => return Ok(Err(reason)),
            };
            let cam = ctx.camera(f.camera);
            let size = (cam.width as usize, cam.height as usize);
            let img = images.read(k, size)?;
            let truth_img = match reference {
                Reference::Frames => None,
                Reference::Images(r) => Some(r.read(k, size)?),
            };
            for s in judged.samples.iter() {
                let Some(&(u, v)) = judged.uv.get(&s.vertex) else {
                    continue;
                };
                let Some(read) = img.bilinear_channels(u, v, chans) else {
                    continue;
                };
                let truth = match &truth_img {
                    None => None,
                    Some(r) => match r.bilinear_channels(u, v, chans) {
                        Some(tr) => Some(tr),
                        None => continue,
                    },
                };
                let (mut measured, mut predicted, mut ok) = ([0.0; 3], [0.0; 3], 0u8);
                for &c in chans {
                    if s.valid & (1 << c) == 0 {
                        continue;
                    }
                    measured[c] = match truth {
                        None => s.value[c],
                        Some(tr) => tr[c].0 / f.exposure_s,
                    };
                    predicted[c] = read[c].0 / f.exposure_s;
                    // The rings are the frame's (its samples above the floor), whatever is
                    // measured in them: a reference render's black pixels count in its ring
                    // means, as the frame's samples do, rather than only its lit ones.
                    if s.value[c] > t
                        && s.value[c].is_finite()
                        && measured[c].is_finite()
                        && predicted[c].is_finite()
                    {
                        ok |= 1 << c;
                    }
                }
                out.push(RingSample {
                    r: crate::geometry::dist(position(s.vertex as usize), x_i),
                    measured,
                    predicted,
                    judged: ok,
                });
            }
        }
    }
    Ok(Ok(out))
}

/// The ring figures as JSON keys beside the per-sample ones: `ring_mean_log_e` (r, g, b, the
/// mean over judged frames), `ring_per_frame` (per frame its ring log E and black rings) and
/// `rings` (per frame the rings' edges and sample counts, with the rule that made them).
pub fn json_keys(
    evals: &[FrameRings],
    stats: &LogEStats,
) -> serde_json::Map<String, serde_json::Value> {
    use serde_json::json;
    let mut m = serde_json::Map::new();
    m.insert("ring_mean_log_e".into(), json!(stats.mean));
    m.insert(
        "ring_per_frame".into(),
        json!(
            evals
                .iter()
                .map(|e| json!({
                    "frame": e.frame,
                    "log_e": e.log_e,
                    "rings": e.rings.len(),
                    "unlit": e.unlit,
                    "skipped": e.skipped,
                }))
                .collect::<Vec<_>>()
        ),
    );
    m.insert(
        "rings".into(),
        json!({
            "ratio": RING_RATIO,
            "min_samples": MIN_RING_SAMPLES,
            "min_share": 1.0 / 24.0,
            "frames": evals
                .iter()
                .map(|e| json!({
                    "frame": e.frame,
                    "edges": std::iter::once(e.rings.first().map_or(0.0, |r| r.r_min))
                        .chain(e.rings.iter().map(|r| r.r_max))
                        .collect::<Vec<f64>>(),
                    "samples": e.rings.iter().map(|r| r.samples).collect::<Vec<_>>(),
                    "ln_e": e.rings.iter().map(|r| r.ln_e).collect::<Vec<_>>(),
                }))
                .collect::<Vec<_>>(),
        }),
    );
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(r: f64, measured: f64, predicted: f64) -> RingSample {
        RingSample {
            r,
            measured: [measured; 3],
            predicted: [predicted; 3],
            judged: 0b111,
        }
    }

    /// A prediction k times the measurement on every sample is ln k off in every ring; a noisy
    /// prediction whose noise averages out within a ring is judged near 0 by the rings, where
    /// per sample it would be far off.
    #[test]
    fn rings_average_before_the_logarithm() {
        let mut s = Vec::new();
        for i in 0..400 {
            let r = 0.5 + 0.05 * i as f64;
            let m = (-r / 3.0).exp();
            s.push(sample(r, m, 2.0 * m));
        }
        let f = judge_rings(0, &s, 1e-9);
        assert!(f.rings.len() > 3, "{}", f.rings.len());
        for c in 0..3 {
            assert!((f.log_e[c].unwrap() - 2f64.ln()).abs() < 1e-12);
        }
        // Every other sample black, the rest twice as bright: the ring means agree.
        let noisy: Vec<RingSample> = s
            .iter()
            .enumerate()
            .map(|(i, x)| {
                sample(
                    x.r,
                    x.measured[0],
                    if i % 2 == 0 { 0.0 } else { x.predicted[0] },
                )
            })
            .collect();
        let f = judge_rings(0, &noisy, 1e-9);
        assert!(f.log_e[1].unwrap() < 0.05, "{:?}", f.log_e);
        assert_eq!(f.unlit, 0);
        // Every ring holds enough samples, and all samples are in some ring.
        let need = min_ring_samples(400) as u64;
        assert!(
            f.rings.iter().all(|r| r.samples[1] >= need),
            "{:?}",
            f.rings
        );
        assert_eq!(f.rings.iter().map(|r| r.samples[1]).sum::<u64>(), 400);
        // Edges increase outwards.
        assert!(
            f.rings
                .windows(2)
                .all(|w| w[0].r_max <= w[1].r_min + 1e-12 && w[0].r_min < w[1].r_min)
        );
    }

    /// A black prediction is judged at the floor and counted; channels not judged stay out.
    #[test]
    fn black_rings_are_judged_at_the_floor() {
        let s: Vec<RingSample> = (0..20)
            .map(|i| RingSample {
                r: 1.0 + i as f64 * 0.01,
                measured: [1.0, 1.0, 1.0],
                predicted: [0.0, 1.0, 1.0],
                judged: 0b011,
            })
            .collect();
        let f = judge_rings(3, &s, 0.01);
        assert_eq!(f.rings.len(), 1);
        assert!((f.log_e[0].unwrap() - 0.01f64.ln().abs()).abs() < 1e-12);
        assert_eq!(f.log_e[1], Some(0.0));
        assert_eq!(f.log_e[2], None);
        assert_eq!(f.unlit, 1);
        assert_eq!(judge_rings(0, &[], 0.01).log_e, [None; 3]);
        // A mean prediction above 0 but below the floor is judged at the floor too.
        let dim: Vec<RingSample> = s.iter().map(|x| sample(x.r, 1.0, 1e-6)).collect();
        let f = judge_rings(3, &dim, 0.01);
        assert!((f.log_e[1].unwrap() - 0.01f64.ln().abs()).abs() < 1e-12);
        assert_eq!(f.unlit, 3);
    }
}
