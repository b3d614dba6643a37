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

/// Where a set of per-frame errors comes from, which decides what its frames share and so how
/// they are clustered ([`Clustering::rule`]).
#[derive(Debug, Clone, Copy)]
pub enum ErrorSource<'a> {
    /// Each frame judged by one model fitted without it (`subsurf evaluate`, a test set, the
    /// planners' test frames): frames share their turntable angle's views, or on a scan of one
    /// angle the vertex models around their x_i.
    HeldOut,
    /// Cross-validated: each frame judged by the fit of the fold that held it out, so the frames
    /// of a fold share one fit (Hastie, Tibshirani and Friedman 7.10). Folds hold whole angles
    /// ([`crate::crossval::folds`]), so a fold is at least as coarse as an angle: with 8 angles
    /// in 5 folds two angles share a fit, and clustering them apart would count one fit's
    /// error twice as independent.
    Folds(&'a [Vec<usize>]),
}

/// One judged frame as the clustering needs it: its index and its light position x_i (mm,
/// turntable frame) where it was registered.
pub type JudgedFrame = (usize, Option<[f64; 3]>);

impl Clustering {
    /// The one clustering rule every judge of subsurf shares (`subsurf evaluate`, the
    /// cross-validation, `bench equivalence`, the adaptive planner and `bench acquisition`), so
    /// that a standard error means the same wherever it is read:
    ///
    /// - cross-validated errors ([`ErrorSource::Folds`]): one cluster per fold;
    /// - held-out errors of a scan with at least two turntable angles among `judged`: one
    ///   cluster per angle;
    /// - held-out errors of a scan with one angle: raster neighbourhoods, cubes of
    ///   [`RASTER_CELL_MM`] by each frame's x_i (a frame without x_i is a cluster of its own).
    ///
    /// A frame in no fold is a cluster of its own ([`Clustering::cluster`]).
    pub fn rule(ds: &Dataset, judged: &[JudgedFrame], source: ErrorSource<'_>) -> Clustering {
        if let ErrorSource::Folds(folds) = source {
            return Clustering::of_folds(folds);
        }
        let angle = |f: usize| {
            ds.spec
                .frames
                .get(f)
                .map_or(0.0, |s| s.turntable_deg.rem_euclid(360.0))
        };
        let mut angles: Vec<f64> = judged.iter().map(|&(f, _)| angle(f)).collect();
        angles.sort_by(f64::total_cmp);
        angles.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
        let mut of = BTreeMap::new();
        if angles.len() >= 2 {
            for &(f, _) in judged {
                let a = angle(f);
                let i = angles
                    .iter()
                    .position(|b| (a - b).abs() < 1e-6)
                    .unwrap_or(0);
                of.insert(f, i);
            }
            return Clustering {
                of,
                rule: "turntable angle".into(),
            };
        }
        let mut cells: BTreeMap<[i64; 3], usize> = BTreeMap::new();
        let mut lone = 0usize;
        for &(f, x_i) in judged {
            let id = match x_i {
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
            of.insert(f, id);
        }
        Clustering {
            of,
            rule: format!(
                "raster neighbourhood (one turntable angle: x_i in cubes of {RASTER_CELL_MM} mm)"
            ),
        }
    }

    /// [`Clustering::rule`] for the held-out frames `evals` of `ds` (skipped frames left out),
    /// each with the x_i it was judged at.
    pub fn of_frames(ds: &Dataset, evals: &[FrameEval]) -> Clustering {
        let judged: Vec<JudgedFrame> = evals
            .iter()
            .filter(|e| e.skipped.is_none())
            .map(|e| (e.frame, e.x_i))
            .collect();
        Clustering::rule(ds, &judged, ErrorSource::HeldOut)
    }

    /// [`Clustering::rule`] for cross-validated errors ([`ErrorSource::Folds`]): each fold one
    /// cluster. Needs no dataset.
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

/// The confidence level of every interval subsurf reports: 95 %, two-sided.
pub const LEVEL: f64 = 0.95;

/// Below this many clusters `subsurf evaluate` warns: the t-interval then rests on at most three
/// degrees of freedom, its half-width is at least 3.18 standard errors (12.7 with two clusters),
/// and the cluster-robust variance itself is biased low with few clusters (Cameron and Miller
/// 2015, section VI), so "about two standard errors" is far too small a bar.
pub const FEW_CLUSTERS: usize = 5;

/// Student's t quantile at probability `p` with `dof` degrees of freedom (`distrs`); infinite
/// without a degree of freedom.
pub fn t_quantile(p: f64, dof: usize) -> f64 {
    if dof == 0 {
        return f64::INFINITY;
    }
    distrs::StudentsT::ppf(p, dof as f64)
}

/// The two-sided [`LEVEL`] t value at `dof` degrees of freedom (3.18 at 3, 12.7 at 1).
pub fn t95(dof: usize) -> f64 {
    t_quantile(0.5 + LEVEL / 2.0, dof)
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

impl ClusteredMean {
    /// Degrees of freedom of the cluster-robust standard error: clusters − 1 (`None` below two
    /// clusters, where it has none).
    pub fn dof(&self) -> Option<usize> {
        (self.clusters >= 2).then(|| self.clusters - 1)
    }

    /// The standard error every decision uses: missing (one cluster) or zero taken as infinite,
    /// so that no test, rule or stop can pass on a spread it could not measure. A zero SE with two
    /// clusters or more comes from deviations that cancel exactly in every cluster, which no real
    /// set of frames does; taking it at face value would make any constant shift significant.
    pub fn decision_se(&self) -> f64 {
        match self.se {
            Some(s) if s > 0.0 && s.is_finite() => s,
            _ => f64::INFINITY,
        }
    }

    /// The half-width of the two-sided `level` t-interval (t with clusters − 1 degrees of
    /// freedom times the SE); infinite where [`ClusteredMean::decision_se`] is.
    pub fn half_width(&self, level: f64) -> f64 {
        let se = self.decision_se();
        if se.is_infinite() {
            return f64::INFINITY;
        }
        t_quantile(0.5 + level / 2.0, self.dof().unwrap_or(0)) * se
    }

    /// The two-sided `level` t-interval of the mean; `None` where it is unbounded (fewer than
    /// two clusters, or no spread measured), so that a written interval is always finite.
    pub fn interval(&self, level: f64) -> Option<[f64; 2]> {
        let h = self.half_width(level);
        h.is_finite().then_some([self.mean - h, self.mean + h])
    }
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
    /// The 95 % t-interval of `mean_log_e` (t with the channel's clusters − 1 degrees of
    /// freedom); `None` where it is unbounded (fewer than two clusters).
    pub ci95_log_e: [Option<[f64; 2]>; 3],
    /// The 95 % t-interval of `weighted_mean_log_e`.
    pub weighted_ci95_log_e: [Option<[f64; 2]>; 3],
    /// Clusters the frames fell into (the most over the channels).
    pub clusters: usize,
    /// Degrees of freedom of the standard errors: clusters − 1 (`None` with one cluster).
    pub dof: Option<usize>,
    /// The two-sided 95 % t value at `dof`: what a difference must exceed, in standard errors,
    /// to be told from noise (3.18 at 3 degrees of freedom, 12.7 at 1; 1.96 only with many).
    pub t95: Option<f64>,
    /// How the frames were clustered.
    pub cluster_rule: String,
}

/// The warning for figures on fewer than [`FEW_CLUSTERS`] clusters: what a difference must
/// exceed there.
pub fn few_clusters_warning(what: &str, clusters: usize) -> Option<String> {
    if clusters >= FEW_CLUSTERS {
        return None;
    }
    Some(match clusters {
        0 | 1 => format!(
            "warning: {what}: {clusters} cluster(s), no degree of freedom: the standard error \
             cannot be estimated, no interval is given and no difference can be told from noise"
        ),
        g => format!(
            "warning: {what}: {g} clusters, {} degree(s) of freedom: the 95 % interval is the \
             mean ± {:.2} standard errors, so a difference inside {:.2} SE is noise (not 2 SE)",
            g - 1,
            t95(g - 1),
            t95(g - 1)
        ),
    })
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
                out.ci95_log_e[c] = m.interval(LEVEL);
                out.clusters = out.clusters.max(m.clusters);
            }
            if let Some(m) = clustered_mean(&weighted) {
                out.weighted_mean_log_e[c] = Some(m.mean);
                out.weighted_se_log_e[c] = m.se;
                out.weighted_ci95_log_e[c] = m.interval(LEVEL);
            }
        }
        out.dof = (out.clusters >= 2).then(|| out.clusters - 1);
        out.t95 = out.dof.map(t95);
        out
    }

    /// [`few_clusters_warning`] for these figures.
    pub fn warning(&self, what: &str) -> Option<String> {
        (self.frames > 0)
            .then(|| few_clusters_warning(what, self.clusters))
            .flatten()
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
    /// The 95 % t-interval of the difference (t with clusters − 1 degrees of freedom); `None`
    /// where it is unbounded. A difference whose interval holds 0 is not told from noise.
    pub ci95: [Option<[f64; 2]>; 3],
    /// Clusters the frames fell into.
    pub clusters: usize,
    /// Degrees of freedom: clusters − 1 (`None` with one cluster).
    pub dof: Option<usize>,
    /// The two-sided 95 % t value at `dof`.
    pub t95: Option<f64>,
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
                out.ci95[c] = m.interval(LEVEL);
                out.clusters = out.clusters.max(m.clusters);
            }
        }
        out.frames = both.len();
        out.dof = (out.clusters >= 2).then(|| out.clusters - 1);
        out.t95 = out.dof.map(t95);
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

    /// The interval is t with clusters − 1 degrees of freedom (the textbook values 3.182 at 3 and
    /// 12.706 at 1), and a missing or zero SE is unbounded for every decision.
    #[test]
    fn the_interval_is_t_with_clusters_minus_one_degrees_of_freedom() {
        assert!((t95(3) - 3.182_446).abs() < 1e-5, "{}", t95(3));
        assert!((t95(1) - 12.706_205).abs() < 1e-5, "{}", t95(1));
        assert!((t95(1000) - 1.962_339).abs() < 1e-5, "{}", t95(1000));
        assert!(t95(0).is_infinite());
        let four: Vec<_> = [0.1, 0.4, 0.2, 0.7]
            .iter()
            .enumerate()
            .map(|(i, &y)| (y, 1.0, (true, i)))
            .collect();
        let m = clustered_mean(&four).unwrap();
        assert_eq!(m.dof(), Some(3));
        let [lo, hi] = m.interval(LEVEL).unwrap();
        let se = m.se.unwrap();
        assert!((hi - m.mean - 3.182_446 * se).abs() < 1e-5 * se);
        assert!((m.mean - lo - 3.182_446 * se).abs() < 1e-5 * se);
        let one: Vec<_> = [0.1, 0.4].iter().map(|&y| (y, 1.0, (true, 0))).collect();
        let m1 = clustered_mean(&one).unwrap();
        assert_eq!((m1.dof(), m1.interval(LEVEL)), (None, None));
        assert!(m1.decision_se().is_infinite() && m1.half_width(0.9).is_infinite());
        // A constant shift in every cluster has SE 0: unbounded, not "certain".
        let flat: Vec<_> = (0..4).map(|i| (0.3, 1.0, (true, i))).collect();
        let mf = clustered_mean(&flat).unwrap();
        assert_eq!(mf.se, Some(0.0));
        assert!(mf.decision_se().is_infinite() && mf.interval(LEVEL).is_none());
        assert!(few_clusters_warning("x", 4).unwrap().contains("3.18"));
        assert!(few_clusters_warning("x", 2).unwrap().contains("12.71"));
        assert!(few_clusters_warning("x", 1).is_some());
        assert_eq!(few_clusters_warning("x", 5), None);
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
