//! Sufficient statistics of samples binned by distance: the fast mode's data and the start
//! values' data.
//!
//! Per bin b: count n_b, mean distance r̄_b, mean log value ȳ_b, and the centred moments
//! S_rr = Σ(r − r̄)², S_ry = Σ(r − r̄)(y − ȳ), S_yy = Σ(y − ȳ)². With ln R_d linearised inside a
//! bin, ln R_d(r) ≈ ln R_d(r̄) + g·(r − r̄) with g = d ln R_d/dr at r̄, the log objective (Eq. 4)
//! over the bin's samples is exactly
//! n_b·(ln R_d(r̄) − ȳ)² + S_rr·(g − S_ry/S_rr)² + (S_yy − S_ry²/S_rr),
//! so a fit to the bins sees both the level and the local slope of the data. The bin count is the
//! speed/accuracy knob: the neglected term is the curvature of ln R_d across one bin.

/// One distance bin's sufficient statistics (see the module doc).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Bin {
    /// Number of samples n_b.
    pub n: f64,
    /// Mean distance r̄_b.
    pub r: f64,
    /// Mean ln s ȳ_b.
    pub y: f64,
    /// Σ(r − r̄)².
    pub srr: f64,
    /// Σ(r − r̄)(y − ȳ).
    pub sry: f64,
    /// Σ(y − ȳ)².
    pub syy: f64,
}

impl Bin {
    /// The same statistics for distances divided by `scale_r` and log values shifted by −`level`.
    pub fn normalised(self, scale_r: f64, level: f64) -> Self {
        Self {
            n: self.n,
            r: self.r / scale_r,
            y: self.y - level,
            srr: self.srr / (scale_r * scale_r),
            sry: self.sry / scale_r,
            syy: self.syy,
        }
    }
}

/// Bins samples (r, y = ln s) into `count` distance bins over [min r, max r], equal steps in √r
/// (edges lo + (hi − lo)·(b/count)²); returns the non-empty bins in increasing distance. Inputs
/// must be finite (cleaned).
pub fn bin_by_distance(r: &[f64], y: &[f64], count: usize) -> Vec<Bin> {
    let count = count.max(1);
    let (lo, hi) = r
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return Vec::new();
    }
    let span = hi - lo;
    let c = count as f64;
    // Edges at lo + span·(b/count)²: narrow bins near x_i, where the fast terms bend ln R_d
    // most, wide ones in the slowly varying tail.
    let edge = |b: usize| lo + span * (b as f64 / c) * (b as f64 / c);
    // Raw sums relative to each bin's left edge (keeps the centred moments accurate).
    let mut acc = vec![[0.0f64; 6]; count];
    for (&ri, &yi) in r.iter().zip(y) {
        let b = if span > 0.0 {
            ((c * ((ri - lo) / span).sqrt()) as usize).min(count - 1)
        } else {
            0
        };
        let x = ri - edge(b);
        let a = &mut acc[b];
        a[0] += 1.0;
        a[1] += x;
        a[2] += yi;
        a[3] += x * x;
        a[4] += x * yi;
        a[5] += yi * yi;
    }
    acc.iter()
        .enumerate()
        .filter(|(_, a)| a[0] > 0.0)
        .map(|(b, a)| {
            let n = a[0];
            let mx = a[1] / n;
            let my = a[2] / n;
            Bin {
                n,
                r: edge(b) + mx,
                y: my,
                srr: (a[3] - n * mx * mx).max(0.0),
                sry: a[4] - n * mx * my,
                syy: (a[5] - n * my * my).max(0.0),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moments_match_direct_computation() {
        let r: Vec<f64> = (0..100).map(|i| i as f64 * 0.37 % 10.0).collect();
        let y: Vec<f64> = r.iter().map(|v| -0.5 * v + (v * 7.0).sin()).collect();
        let bins = bin_by_distance(&r, &y, 4);
        assert_eq!(bins.iter().map(|b| b.n).sum::<f64>(), 100.0);
        let b = bins[1];
        let hi = r.iter().cloned().fold(0.0, f64::max);
        let sel: Vec<(f64, f64)> = r
            .iter()
            .zip(&y)
            .filter(|(r, _)| ((4.0 * (**r / hi).sqrt()) as usize).min(3) == 1)
            .map(|(a, b)| (*a, *b))
            .collect();
        let n = sel.len() as f64;
        let mr = sel.iter().map(|p| p.0).sum::<f64>() / n;
        let my = sel.iter().map(|p| p.1).sum::<f64>() / n;
        let srr: f64 = sel.iter().map(|p| (p.0 - mr).powi(2)).sum();
        let sry: f64 = sel.iter().map(|p| (p.0 - mr) * (p.1 - my)).sum();
        assert_eq!(b.n, n);
        assert!((b.r - mr).abs() < 1e-12 && (b.y - my).abs() < 1e-12);
        assert!((b.srr - srr).abs() < 1e-9 && (b.sry - sry).abs() < 1e-9);
    }

    #[test]
    fn one_distance_is_one_bin() {
        let bins = bin_by_distance(&[2.0; 5], &[1.0; 5], 8);
        assert_eq!(bins.len(), 1);
        assert_eq!(bins[0].srr, 0.0);
    }
}
