//! Reconstruction errors: E(x_i → x_o) (Eq. 7), log E(x_i) (Eq. 8) and the Table-1 mean.
//! Logarithms are natural.

use serde::{Deserialize, Serialize};

/// Eq. 7: E(x_i → x_o) = alpha(x_o)·R_d(x_i → x_o) / s(x_i, x_o); 1 is a perfect reconstruction.
pub fn reconstruction_error(alpha: f64, r_d: f64, s: f64) -> f64 {
    alpha * r_d / s
}

/// Streaming Eq. 8 for one x_i: log E(x_i) = sqrt(mean over X of (ln E(x_i → x_o))²) with
/// X = {x_o | s(x_i, x_o) > t}. Works from logarithms so underflowed model values still count.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LogEAccumulator {
    /// Σ (ln E)² over accepted samples.
    pub sum_sq: f64,
    /// |X|.
    pub count: u64,
}

impl LogEAccumulator {
    /// Adds a sample given ln(alpha·R_d) and the measured s; used when s > t and everything is
    /// finite. Returns whether it was used.
    pub fn add_ln(&mut self, ln_model: f64, s: f64, t: f64) -> bool {
        if !(s > t && s > 0.0 && s.is_finite() && ln_model.is_finite()) {
            return false;
        }
        let e = ln_model - s.ln();
        self.sum_sq += e * e;
        self.count += 1;
        true
    }

    /// Adds a sample given alpha, R_d and s (Eq. 7 inside).
    pub fn add(&mut self, alpha: f64, r_d: f64, s: f64, t: f64) -> bool {
        self.add_ln(alpha.ln() + r_d.ln(), s, t)
    }

    /// Merges another accumulator.
    pub fn merge(&mut self, other: &Self) {
        self.sum_sq += other.sum_sq;
        self.count += other.count;
    }

    /// log E(x_i) (Eq. 8), or `None` when no sample passed the threshold.
    pub fn log_e(&self) -> Option<f64> {
        (self.count > 0).then(|| (self.sum_sq / self.count as f64).sqrt())
    }
}

/// Table 1: the mean over x_i of log E(x_i) (one channel). Non-finite entries are skipped;
/// `None` if nothing is left.
pub fn table1_mean(log_e: &[f64]) -> Option<f64> {
    let (s, n) = log_e
        .iter()
        .filter(|v| v.is_finite())
        .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| s / n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_e_is_rms_of_log_ratio() {
        let mut acc = LogEAccumulator::default();
        let e = 0.1f64;
        assert!(acc.add(1.0, e.exp(), 1.0, 0.5));
        assert!(acc.add(1.0, (-e).exp(), 1.0, 0.5));
        assert!(!acc.add(1.0, 1.0, 0.1, 0.5));
        assert!(!acc.add(1.0, f64::NAN, 1.0, 0.5));
        assert!((acc.log_e().unwrap() - e).abs() < 1e-15);
        assert_eq!(LogEAccumulator::default().log_e(), None);
        assert_eq!(reconstruction_error(2.0, 3.0, 6.0), 1.0);
        assert_eq!(table1_mean(&[0.01, 0.03, f64::NAN]), Some(0.02));
        assert_eq!(table1_mean(&[]), None);
    }
}
