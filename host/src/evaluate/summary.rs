//! What a set of judged frames says, and how precisely: the mean over frames of log E (Eq. 8,
//! Table 1), the sample-weighted mean, and their standard errors clustered by turntable angle.
//!
//! Why clustered: the frames of one turntable angle share their views (the same pixels see the
//! same vertices, at the same grazing angles, through the same registration of the mesh), and
//! frames whose x_i lie close together share the vertex models that predict them. Their errors
//! are not independent, so a standard error that treats frames as independent draws is too small
//! (on sample-torus's four test angles, the frames of one angle move together). The cluster-
//! robust variance of a mean (Liang and Zeger 1986; Cameron and Miller 2015, "A practitioner's
//! guide to cluster-robust inference", eq. 11 with the G/(G−1) correction) sums the deviations
//! within each cluster first, so correlation inside a cluster counts in full and only clusters
//! are taken as independent. With one frame per cluster it is the usual s/√n.
//!
//! Handwritten: a few lines of arithmetic on the product's own figure (Eq. 8 per frame), which
//! no statistics crate computes for us; the test checks it against the textbook formula.
use std::collections::BTreeMap;

use crate::dataset::Dataset;
use crate::evaluate::FrameEval;

/// How frames are grouped into clusters for the standard error.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Clustering {
    /// Frame → cluster id.
    #[serde(skip)]
    pub of: BTreeMap<usize, usize>,
    /// The rule, in words.
    pub rule: String,
}

/// Side (mm) of the cubes that group the x_i of a scan with one turntable angle into raster
/// neighbourhoods: twice the default largest distance from a vertex to its closest x_i
/// (`PipelineOptions::max_select_mm`, 2 mm), so frames whose x_i can be the closest light
/// position of the same vertices tend to share a cube. Fixed in millimetres, never by the frames
/// judged, so every model compared on a dataset gets the same clusters.
pub const RASTER_CELL_MM: f64 = 4.0;

impl Clustering {
    /// The clusters of the judged frames `evals` of `ds`: whole turntable angles when they hold
    /// at least two; otherwise raster neighbourhoods (cubes of [`RASTER_CELL_MM`] in the turntable
    /// frame, by each frame's x_i; a frame without x_i is a cluster of its own).
    pub fn of_frames(ds: &Dataset, evals: &[FrameEval]) -> Clustering {
        let judged: Vec<&FrameEval> = evals.iter().filter(|e| e.skipped.is_none()).collect();
        let angle = |f: usize| {
            ds.spec
                .frames
                .get(f)
                .map_or(0.0, |s| s.turntable_deg.rem_euclid(360.0))
        };
        let mut angles: Vec<f64> = judged.iter().map(|e| angle(e.frame)).collect();
        angles.sort_by(f64::total_cmp);
        angles.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
        let mut of = BTreeMap::new();
        if angles.len() >= 2 {
            for e in &judged {
                let a = angle(e.frame);
                let i = angles
                    .iter()
                    .position(|b| (a - b).abs() < 1e-6)
                    .unwrap_or(0);
                of.insert(e.frame, i);
            }
            return Clustering {
                of,
                rule: "turntable angle".into(),
            };
        }
        let mut cells: BTreeMap<[i64; 3], usize> = BTreeMap::new();
        let mut lone = 0usize;
        for e in &judged {
            let id = match e.x_i {
                Some(x) if x.iter().all(|v| v.is_finite()) => {
                    // Saturating float-to-int casts: a coordinate beyond ±9e18 cells is one cell.
                    let key = x.map(|v| (v / RASTER_CELL_MM).floor() as i64);
                    let n = cells.len();
                    *cells.entry(key).or_insert(n)
                }
                _ => {
                    lone += 1;
                    usize::MAX - lone
                }
            };
            of.insert(e.frame, id);
        }
        Clustering {
            of,
            rule: format!(
                "raster neighbourhood (one turntable angle: x_i in cubes of {RASTER_CELL_MM} mm)"
            ),
        }
    }

    /// Frames dealt into folds: each fold one cluster (the cross-validation's rule: the frames
    /// of a fold share one fit, Hastie, Tibshirani and Friedman 7.10).
    pub fn of_folds(folds: &[Vec<usize>]) -> Clustering {
        let mut of = BTreeMap::new();
        for (i, fold) in folds.iter().enumerate() {
            for &f in fold {
                of.insert(f, i);
            }
        }
        Clustering {
            of,
            rule: "fold".into(),
        }
    }

    /// The cluster of frame `f` (a frame not clustered is its own).
    pub fn cluster(&self, f: usize) -> (bool, usize) {
        match self.of.get(&f) {
            Some(&c) => (true, c),
            None => (false, f),
        }
    }
}

/// A mean over frames and its clustered standard error.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ClusteredMean {
    /// The (weighted) mean.
    pub mean: f64,
    /// Its cluster-robust standard error; `None` with fewer than two clusters.
    pub se: Option<f64>,
    /// Frames that entered.
    pub frames: usize,
    /// Clusters they fell into.
    pub clusters: usize,
}

/// The weighted mean of `values` (value, weight, cluster) and its cluster-robust standard
/// error: V = G/(G−1) · Σ_g (Σ_{f∈g} w_f (y_f − ȳ))² / (Σ w)². `None` when no value is finite or
/// the weights sum to zero. Non-finite values and weights are left out.
pub fn clustered_mean(values: &[(f64, f64, (bool, usize))]) -> Option<ClusteredMean> {
    let kept: Vec<&(f64, f64, (bool, usize))> = values
        .iter()
        .filter(|(y, w, _)| y.is_finite() && w.is_finite() && *w >= 0.0)
        .collect();
    let wsum: f64 = kept.iter().map(|v| v.1).sum();
    if kept.is_empty() || wsum <= 0.0 {
        return None;
    }
    let mean = kept.iter().map(|v| v.0 * v.1).sum::<f64>() / wsum;
    let mut by: BTreeMap<(bool, usize), f64> = BTreeMap::new();
    for (y, w, c) in &kept {
        *by.entry(*c).or_default() += w * (y - mean);
    }
    let g = by.len();
    let se = (g >= 2).then(|| {
        let s: f64 = by.values().map(|u| u * u).sum();
        (g as f64 / (g as f64 - 1.0) * s).sqrt() / wsum
    });
    Some(ClusteredMean {
        mean,
        se,
        frames: kept.len(),
        clusters: g,
    })
}

/// The figures of a set of judged frames, per channel r, g, b.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Figures {
    /// Frames judged (not skipped).
    pub frames: usize,
    /// The mean over frames of each frame's log E (Table 1's figure).
    pub mean_log_e: [Option<f64>; 3],
    /// The median over frames.
    pub median_log_e: [Option<f64>; 3],
    /// The clustered standard error of `mean_log_e`.
    pub se_log_e: [Option<f64>; 3],
    /// The mean over frames weighted by each frame's samples in that channel: a frame of 20
    /// samples weighs a tenth of one of 200.
    pub weighted_mean_log_e: [Option<f64>; 3],
    /// The clustered standard error of `weighted_mean_log_e`.
    pub weighted_se_log_e: [Option<f64>; 3],
    /// Clusters the frames fell into (the most over the channels).
    pub clusters: usize,
    /// How the frames were clustered.
    pub cluster_rule: String,
}

impl Figures {
    /// The figures of `evals` (skipped frames left out), clustered by `clusters`.
    pub fn of(evals: &[FrameEval], clusters: &Clustering) -> Figures {
        let judged: Vec<&FrameEval> = evals.iter().filter(|e| e.skipped.is_none()).collect();
        let vals: Vec<[f64; 3]> = judged
            .iter()
            .map(|e| e.log_e.map(|x| x.unwrap_or(f64::NAN)))
            .collect();
        let stats = crate::pipeline::LogEStats::of(&vals);
        let mut out = Figures {
            frames: judged.len(),
            mean_log_e: stats.mean,
            median_log_e: stats.median,
            cluster_rule: clusters.rule.clone(),
            ..Figures::default()
        };
        for c in 0..3 {
            let plain: Vec<(f64, f64, (bool, usize))> = judged
                .iter()
                .filter_map(|e| Some((e.log_e[c]?, 1.0, clusters.cluster(e.frame))))
                .collect();
            let weighted: Vec<(f64, f64, (bool, usize))> = judged
                .iter()
                .filter_map(|e| {
                    Some((
                        e.log_e[c]?,
                        e.channel_samples[c] as f64,
                        clusters.cluster(e.frame),
                    ))
                })
                .collect();
            if let Some(m) = clustered_mean(&plain) {
                out.se_log_e[c] = m.se;
                out.clusters = out.clusters.max(m.clusters);
            }
            if let Some(m) = clustered_mean(&weighted) {
                out.weighted_mean_log_e[c] = Some(m.mean);
                out.weighted_se_log_e[c] = m.se;
            }
        }
        out
    }
}

/// The paired difference of two models' log E on the frames both judged (model A − model B).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Paired {
    /// Frames both judged (in at least one channel).
    pub frames: usize,
    /// Mean over those frames of log E(A) − log E(B), per channel.
    pub mean_difference: [Option<f64>; 3],
    /// Its clustered standard error.
    pub se: [Option<f64>; 3],
    /// Clusters the frames fell into.
    pub clusters: usize,
    /// How the frames were clustered.
    pub cluster_rule: String,
}

impl Paired {
    /// The paired difference of `a` − `b` (per frame, per channel, where both have a value).
    pub fn of(a: &[FrameEval], b: &[FrameEval], clusters: &Clustering) -> Paired {
        let bs: BTreeMap<usize, &FrameEval> = b
            .iter()
            .filter(|e| e.skipped.is_none())
            .map(|e| (e.frame, e))
            .collect();
        let pairs: Vec<(&FrameEval, &FrameEval)> = a
            .iter()
            .filter(|e| e.skipped.is_none())
            .filter_map(|e| Some((e, *bs.get(&e.frame)?)))
            .collect();
        let mut out = Paired {
            cluster_rule: clusters.rule.clone(),
            ..Paired::default()
        };
        let mut both = std::collections::BTreeSet::new();
        for c in 0..3 {
            let d: Vec<(f64, f64, (bool, usize))> = pairs
                .iter()
                .filter_map(|(x, y)| {
                    let v = x.log_e[c]? - y.log_e[c]?;
                    both.insert(x.frame);
                    Some((v, 1.0, clusters.cluster(x.frame)))
                })
                .collect();
            if let Some(m) = clustered_mean(&d) {
                out.mean_difference[c] = Some(m.mean);
                out.se[c] = m.se;
                out.clusters = out.clusters.max(m.clusters);
            }
        }
        out.frames = both.len();
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With one frame per cluster the clustered SE is the textbook s/√n; clusters that move
    /// together make it larger than the independent one; fewer than two clusters give none.
    #[test]
    fn the_clustered_se_is_the_textbook_one_per_frame_and_larger_when_frames_move_together() {
        let ys = [0.3, 0.5, 0.4, 0.8, 0.6, 0.2];
        let lone: Vec<_> = ys
            .iter()
            .enumerate()
            .map(|(i, &y)| (y, 1.0, (true, i)))
            .collect();
        let m = clustered_mean(&lone).unwrap();
        let n = ys.len() as f64;
        let mean = ys.iter().sum::<f64>() / n;
        let s2 = ys.iter().map(|y| (y - mean).powi(2)).sum::<f64>() / (n - 1.0);
        assert!((m.mean - mean).abs() < 1e-15);
        assert!((m.se.unwrap() - (s2 / n).sqrt()).abs() < 1e-15);
        assert_eq!((m.frames, m.clusters), (6, 6));
        // The same values in three pairs that move together (0.3/0.2, 0.5/0.4 ... sorted).
        let pairs: Vec<_> = [0.2, 0.3, 0.4, 0.5, 0.6, 0.8]
            .iter()
            .enumerate()
            .map(|(i, &y)| (y, 1.0, (true, i / 2)))
            .collect();
        let p = clustered_mean(&pairs).unwrap();
        assert_eq!(p.clusters, 3);
        assert!(p.se.unwrap() > m.se.unwrap(), "{p:?} {m:?}");
        let one: Vec<_> = ys.iter().map(|&y| (y, 1.0, (true, 0))).collect();
        assert_eq!(clustered_mean(&one).unwrap().se, None);
        assert_eq!(clustered_mean(&[]), None);
        assert_eq!(clustered_mean(&[(f64::NAN, 1.0, (true, 0))]), None);
    }

    /// Weights: a frame of many samples pulls the weighted mean; zero weights leave it out of the
    /// mean (its cluster still counts only through weight).
    #[test]
    fn the_weighted_mean_follows_the_samples() {
        let v = [(0.2, 244.0, (true, 0)), (1.0, 20.0, (true, 1))];
        let m = clustered_mean(&v).unwrap();
        assert!((m.mean - (0.2 * 244.0 + 20.0) / 264.0).abs() < 1e-15);
        // Two clusters: V = 2 · (u0² + u1²) / W², u_g = w_g (y_g − ȳ).
        let u0 = 244.0 * (0.2 - m.mean);
        let u1 = 20.0 * (1.0 - m.mean);
        let se = (2.0 * (u0 * u0 + u1 * u1)).sqrt() / 264.0;
        assert!((m.se.unwrap() - se).abs() < 1e-15);
    }
}
