//! Eq. 2 / Eq. 6: the modulation texture alpha(x_o), the average multiplicative correction
//! s(x_i, x_o) / R_d(x_i → x_o) over the samples in a medium intensity window.

use serde::{Deserialize, Serialize};

/// The window X = {x_o | t1 > s(x_i, x_o) > t2} of Eq. 6: samples dominated by multiple
/// scattering, bright enough that camera noise is small, not saturated.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IntensityWindow {
    /// Lower threshold t2 (exclusive).
    pub t2: f64,
    /// Upper threshold t1 (exclusive).
    pub t1: f64,
}

impl IntensityWindow {
    /// Whether sample value s lies strictly inside (t2, t1).
    pub fn contains(&self, s: f64) -> bool {
        s > self.t2 && s < self.t1
    }
}

/// Streaming Eq. 6 for one texel x_o: feed (s, R_d) pairs from every x_i that sees x_o.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct AlphaAccumulator {
    /// Σ s / R_d over accepted samples.
    pub sum: f64,
    /// |X|, the number of accepted samples.
    pub count: u64,
}

impl AlphaAccumulator {
    /// Adds one sample s(x_i, x_o) with model value R_d(x_i → x_o); returns whether it was used
    /// (inside the window, both finite, R_d > 0).
    pub fn add(&mut self, s: f64, r_d: f64, window: &IntensityWindow) -> bool {
        let ratio = s / r_d;
        if window.contains(s) && r_d > 0.0 && r_d.is_finite() && ratio.is_finite() {
            self.sum += ratio;
            self.count += 1;
            true
        } else {
            false
        }
    }

    /// Merges another accumulator (for parallel accumulation).
    pub fn merge(&mut self, other: &Self) {
        self.sum += other.sum;
        self.count += other.count;
    }

    /// alpha(x_o) (Eq. 6), or `None` when no sample fell in the window.
    pub fn alpha(&self) -> Option<f64> {
        (self.count > 0).then(|| self.sum / self.count as f64)
    }
}

/// Eq. 6 over (s, R_d) pairs in one go.
pub fn alpha(pairs: impl IntoIterator<Item = (f64, f64)>, window: &IntensityWindow) -> Option<f64> {
    let mut acc = AlphaAccumulator::default();
    for (s, r_d) in pairs {
        acc.add(s, r_d, window);
    }
    acc.alpha()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn averages_ratios_inside_window_only() {
        let w = IntensityWindow { t2: 0.1, t1: 10.0 };
        let a = alpha(
            [
                (1.0, 0.5),
                (2.0, 0.5),
                (20.0, 1.0),
                (0.05, 1.0),
                (1.0, 0.0),
                (f64::NAN, 1.0),
            ],
            &w,
        );
        assert_eq!(a, Some(3.0));
        assert_eq!(alpha([(20.0, 1.0)], &w), None);
    }
}
