//! Sample cleaning: what goes into a fit, and an account of what was dropped and why.

use serde::{Deserialize, Serialize};

/// How many input samples were used and why the others were dropped. Dropped samples are never
/// silently lost: every input sample is counted exactly once.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SampleReport {
    /// Samples given.
    pub input: usize,
    /// Samples used by the fit.
    pub used: usize,
    /// Dropped: distance or value NaN or infinite.
    pub dropped_non_finite: usize,
    /// Dropped: value zero or negative (no logarithm; below the noise floor).
    pub dropped_non_positive: usize,
    /// Dropped: negative distance.
    pub dropped_negative_distance: usize,
    /// Usable but left out by `FitOptions::subsample` (every k-th usable sample is fitted).
    #[serde(default)]
    pub skipped_subsample: usize,
}

impl SampleReport {
    /// Every input sample counted exactly once: used, dropped by a rule, or skipped by
    /// subsampling.
    pub fn accounted(&self) -> usize {
        self.used
            + self.dropped_non_finite
            + self.dropped_non_positive
            + self.dropped_negative_distance
            + self.skipped_subsample
    }
}

/// Keeps samples with finite r ≥ 0 and finite s > 0; returns them with the account.
pub fn clean(r: &[f64], s: &[f64]) -> (Vec<f64>, Vec<f64>, SampleReport) {
    let mut report = SampleReport {
        input: r.len().max(s.len()),
        ..Default::default()
    };
    // Samples without a partner (length mismatch) count as non-finite.
    report.dropped_non_finite = r.len().abs_diff(s.len());
    // Branch-free: every sample is written, the write position advances only for kept ones
    // (the per-fit hot path sees millions of samples; data-dependent branches mispredict).
    let len = r.len().min(s.len());
    let mut out_r = vec![0.0; len];
    let mut out_s = vec![0.0; len];
    let mut kept = 0;
    let (mut non_finite, mut negative, mut non_positive) = (0, 0, 0);
    for (&ri, &si) in r.iter().zip(s) {
        let finite = ri.is_finite() & si.is_finite();
        let neg = finite & (ri < 0.0);
        let nonpos = finite & !neg & (si <= 0.0);
        let keep = finite & !neg & !nonpos;
        non_finite += usize::from(!finite);
        negative += usize::from(neg);
        non_positive += usize::from(nonpos);
        out_r[kept] = ri;
        out_s[kept] = si;
        kept += usize::from(keep);
    }
    out_r.truncate(kept);
    out_s.truncate(kept);
    report.dropped_non_finite += non_finite;
    report.dropped_negative_distance += negative;
    report.dropped_non_positive += non_positive;
    report.used = out_r.len();
    (out_r, out_s, report)
}

/// Number of distinct distances, counted up to `cap` (a linear scan with at most `cap` values
/// remembered: no sort of the samples on the per-fit path).
pub(crate) fn distinct_distances(r: &[f64], cap: usize) -> usize {
    let mut seen: Vec<f64> = Vec::with_capacity(cap);
    for &v in r {
        if seen.len() >= cap {
            break;
        }
        if !seen.contains(&v) {
            seen.push(v);
        }
    }
    seen.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drops_and_counts() {
        let r = [0.0, 1.0, f64::NAN, 2.0, -1.0, 3.0, f64::INFINITY, 4.0];
        let s = [1.0, 0.0, 1.0, -2.0, 1.0, f64::NAN, 1.0, 0.5];
        let (cr, cs, rep) = clean(&r, &s);
        assert_eq!(cr, vec![0.0, 4.0]);
        assert_eq!(cs, vec![1.0, 0.5]);
        assert_eq!(rep.used, 2);
        assert_eq!(rep.dropped_non_finite, 3);
        assert_eq!(rep.dropped_non_positive, 2);
        assert_eq!(rep.dropped_negative_distance, 1);
        assert_eq!(
            rep.used
                + rep.dropped_non_finite
                + rep.dropped_non_positive
                + rep.dropped_negative_distance,
            rep.input
        );
        assert_eq!(distinct_distances(&[1.0, 1.0, 2.0], 10), 2);
    }
}
