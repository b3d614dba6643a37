//! The radiance noise floor measured from a scan's own frames, for a dataset whose `scan.json`
//! gives none (and to check one it gives).
//!
//! Why measure: the floor decides which samples are noise (dropped), Eq. 6's t2 and Eq. 8's
//! threshold t, so a missing floor (0) lets pixels of pure noise into every fit and every error:
//! sample-pebble's frames as 16-bit TIFF brackets without the key moved the held-out green error
//! from 0.379 to 0.773 (issue 39). A real camera's dataset has no floor unless its user measured
//! one, so it must come from the frames.
//!
//! How: the noise level function of the frames (Foi et al. 2008, "Practical Poissonian-Gaussian
//! noise modeling and fitting for single-image raw-data"; Liu et al. 2008): at pixels whose
//! centre and axis neighbours all see the object's surface, the residual of a pixel against a
//! prediction from its neighbours that is exact for a locally cubic signal ([`residual`]) is
//! noise, binned by the local level. Its standard deviation over the level,
//! σ(m)/m, is the relative noise at that level; it falls as the light rises. The floor is the
//! level at which it has fallen to 1/3: the signal three times its noise, the limit of detection
//! of analytical chemistry (IUPAC; Long and Winefordner 1983). The same definition measures
//! a sensor's read noise and a Monte Carlo renderer's photon noise, since both are in the
//! residuals; it assumes nothing about their form. Not chosen on any test frame: the ratio 3 is
//! the textbook detection limit, the bins and frame counts are sized for the estimate's own
//! precision.
//!
//! Handwritten: the residual statistics of one product's frames, a few dozen lines; no crate
//! measures a noise level function.
use crate::dataset::Dataset;
use crate::geometry::Scene;

/// The signal-to-noise ratio at the floor: the level whose noise is a third of it.
pub const FLOOR_SNR: f64 = 3.0;
/// Frames read to measure (spread over the scan's order).
pub const MAX_FRAMES: usize = 16;
/// Pixel centres examined per frame at most (larger frames are strided).
const MAX_CENTRES: usize = 128 * 128;
/// Levels per decade of the noise level function's bins.
const BINS_PER_DECADE: f64 = 4.0;
/// Residuals a bin needs for its standard deviation to count (its relative precision is about
/// 1/√(2n): 5 % at 200).
const MIN_PER_BIN: usize = 200;

/// A measured noise floor.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NoiseEstimate {
    /// The floor (radiance: pixel / exposure_s); 0 when no level was noisier than the criterion.
    pub floor: f64,
    /// How it was measured, in words.
    pub method: String,
    /// Frames read.
    pub frames: Vec<usize>,
    /// The noise level function: (level, relative noise σ/m, residuals) per bin.
    pub levels: Vec<(f64, f64, usize)>,
}

/// Why the floor could not be measured.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum NoiseError {
    /// A frame could not be read.
    #[error("frame {frame}: {source}")]
    Frame {
        /// The frame.
        frame: usize,
        /// Why.
        source: crate::dataset::DatasetError,
    },
    /// No frame had enough surface pixels with light.
    #[error(
        "no frame has enough pixels on the surface with light to measure the noise floor: give `noise_floor` in scan.json or --noise-floor"
    )]
    NoData,
}

/// The frames [`estimate`] reads among `frames`: at most [`MAX_FRAMES`], evenly spread.
pub fn frames_to_read(frames: &[usize]) -> Vec<usize> {
    if frames.len() <= MAX_FRAMES {
        return frames.to_vec();
    }
    (0..MAX_FRAMES)
        .map(|i| frames[i * frames.len() / MAX_FRAMES])
        .collect()
}

/// Measures the noise floor of `ds` from up to [`MAX_FRAMES`] of `frames` (see the module).
pub fn estimate(
    ds: &Dataset,
    scene: &Scene,
    frames: &[usize],
) -> Result<NoiseEstimate, NoiseError> {
    use rayon::prelude::*;
    let read = frames_to_read(frames);
    let per: Vec<Result<Vec<(f64, f64)>, NoiseError>> =
        read.par_iter().map(|&k| residuals(ds, scene, k)).collect();
    let mut all = Vec::new();
    for r in per {
        all.extend(r?);
    }
    floor_of(all, read)
}

/// Scale of the residual [`residual`] leaves: its variance is σ² (1 + 17/36 = 53/36) for pixels of the
/// same noise σ (the predictor averages two axis stencils of weights (−1, 4, 4, −1)/6, whose
/// squares sum to 34/36, halved by the average).
const RESIDUAL_SCALE: f64 = 36.0 / 53.0;

/// A pixel's residual against the prediction from its neighbours two pixels either way along
/// each axis, (4 (v₋₁ + v₊₁) − (v₋₂ + v₊₂)) / 6 averaged over the two axes: exact for a signal
/// that is a cubic along each axis (and for any product term x·y), so the fall-off's curvature,
/// which the plain four-neighbour mean leaves in the residual (on the shared renders a quarter of
/// the value per pixel where the light falls by e per 4 pixels), does not count as noise.
/// `v`: the centre, then x−1, x+1, x−2, x+2, y−1, y+1, y−2, y+2.
fn residual(v: &[f64; 9]) -> f64 {
    let px = (4.0 * (v[1] + v[2]) - (v[3] + v[4])) / 6.0;
    let py = (4.0 * (v[5] + v[6]) - (v[7] + v[8])) / 6.0;
    v[0] - 0.5 * (px + py)
}

/// (local level, scaled residual) at the examined pixels of frame `k` (radiance units): pixels
/// whose centre and eight axis neighbours (two either way) all see the surface and none is
/// clipped or not finite.
fn residuals(ds: &Dataset, scene: &Scene, k: usize) -> Result<Vec<(f64, f64)>, NoiseError> {
    let spec = &ds.spec.frames[k];
    let img = ds
        .read_frame(k)
        .map_err(|source| NoiseError::Frame { frame: k, source })?;
    let Some(cam) = ds.spec.cameras.get(spec.camera) else {
        return Ok(Vec::new());
    };
    let (w, h) = (img.width, img.height);
    if w < 5 || h < 5 {
        return Ok(Vec::new());
    }
    let stride = ((w * h) as f64 / MAX_CENTRES as f64).sqrt().ceil().max(1.0) as usize;
    let sees = |i: usize, j: usize| -> bool {
        cam.ray(i as f64, j as f64)
            .and_then(|(o, d)| scene.cast_world(o, d, spec.turntable_deg))
            .is_some()
    };
    let saturation = ds.saturation().unwrap_or(f64::INFINITY);
    let exposure = spec.exposure_s;
    let channels = spec.channel.channels();
    let scale = RESIDUAL_SCALE.sqrt();
    let mut out = Vec::new();
    for j in (2..h - 2).step_by(stride) {
        for i in (2..w - 2).step_by(stride) {
            let at = [
                (i, j),
                (i - 1, j),
                (i + 1, j),
                (i - 2, j),
                (i + 2, j),
                (i, j - 1),
                (i, j + 1),
                (i, j - 2),
                (i, j + 2),
            ];
            if !at.iter().all(|&(a, b)| sees(a, b)) {
                continue;
            }
            for &c in channels {
                let c = c.min(img.channels - 1);
                let v = at.map(|(a, b)| img.get(a, b, c) as f64);
                if v.iter().any(|x| !x.is_finite() || *x >= saturation) {
                    continue;
                }
                let level = v.iter().sum::<f64>() / 9.0 / exposure;
                if level > 0.0 && level.is_finite() {
                    out.push((level, residual(&v) / exposure * scale));
                }
            }
        }
    }
    Ok(out)
}

/// The floor from (level, scaled residual) pairs: binned by level, the lowest level from which
/// on the relative noise stays at or below 1 / [`FLOOR_SNR`] (interpolated in log level between
/// the last bin above and the first below).
fn floor_of(mut pts: Vec<(f64, f64)>, frames: Vec<usize>) -> Result<NoiseEstimate, NoiseError> {
    pts.retain(|p| p.0 > 0.0 && p.0.is_finite() && p.1.is_finite());
    if pts.len() < MIN_PER_BIN {
        return Err(NoiseError::NoData);
    }
    let bin = |m: f64| (m.log10() * BINS_PER_DECADE).floor() as i64;
    let mut bins: std::collections::BTreeMap<i64, (f64, f64, usize)> = Default::default();
    for &(m, r) in &pts {
        let e = bins.entry(bin(m)).or_default();
        e.0 += m;
        e.1 += r * r;
        e.2 += 1;
    }
    let levels: Vec<(f64, f64, usize)> = bins
        .values()
        .filter(|b| b.2 >= MIN_PER_BIN)
        .map(|&(sm, sr, n)| {
            let m = sm / n as f64;
            (m, (sr / n as f64).sqrt() / m, n)
        })
        .collect();
    if levels.is_empty() {
        return Err(NoiseError::NoData);
    }
    let limit = 1.0 / FLOOR_SNR;
    // The last bin, from low levels up, whose relative noise is above the limit, among the bins
    // below the first run of two that are at or under it.
    let mut above: Option<usize> = None;
    for (i, l) in levels.iter().enumerate() {
        if l.1 > limit {
            above = Some(i);
        } else if levels.get(i + 1).is_none_or(|n| n.1 <= limit) {
            break;
        }
    }
    let method = format!(
        "measured: the level at which the frames' noise is 1/{FLOOR_SNR} of the signal (noise level function of {} pixel residuals on the surface, {} frames)",
        pts.len(),
        frames.len()
    );
    let floor = match above {
        None => 0.0,
        Some(i) if i + 1 >= levels.len() => levels[i].0,
        Some(i) => {
            // Linear in log level between the bin above the limit and the next one.
            let (a, b) = (levels[i], levels[i + 1]);
            let t = ((a.1 - limit) / (a.1 - b.1)).clamp(0.0, 1.0);
            (a.0.ln() + t * (b.0.ln() - a.0.ln())).exp()
        }
    };
    Ok(NoiseEstimate {
        floor,
        method,
        frames,
        levels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// A sensor with read noise σ and no other: the floor is where the level is 3σ, wherever
    /// the levels lie; a noiseless one has none.
    #[test]
    fn the_floor_is_three_times_the_noise() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let sigma = 2e-4;
        let noise = Normal::new(0.0, sigma).unwrap();
        let mut pts = Vec::new();
        for _ in 0..200_000 {
            // Levels spread over four decades around the floor.
            let m = 10f64.powf(rng.random_range(-5.0..-1.0));
            pts.push((m, noise.sample(&mut rng)));
        }
        let e = floor_of(pts.clone(), vec![0]).unwrap();
        let want = FLOOR_SNR * sigma;
        assert!(
            (e.floor / want - 1.0).abs() < 0.15,
            "{} against {want}: {:?}",
            e.floor,
            e.levels
        );
        let quiet: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, 0.0)).collect();
        assert_eq!(floor_of(quiet, vec![0]).unwrap().floor, 0.0);
        assert!(matches!(floor_of(vec![], vec![]), Err(NoiseError::NoData)));
    }

    /// The residual's predictor is exact for a cubic along each axis and a product term, so a
    /// smooth fall-off leaves no residual; its noise scale makes the residual of independent
    /// unit noise unit.
    #[test]
    fn the_residual_ignores_a_smooth_signal_and_is_scaled_to_the_noise() {
        let f = |x: f64, y: f64| {
            1.0 + 0.3 * x - 0.2 * y + 0.05 * x * x * x + 0.1 * x * y - 0.02 * y * y
        };
        let at = [
            (0, 0),
            (-1, 0),
            (1, 0),
            (-2, 0),
            (2, 0),
            (0, -1),
            (0, 1),
            (0, -2),
            (0, 2),
        ];
        let v = at.map(|(a, b)| f(a as f64, b as f64));
        assert!(residual(&v).abs() < 1e-12);
        // Var(residual) of unit-variance independent pixels, from the weights.
        let w = [
            1.0,
            -1.0 / 3.0,
            -1.0 / 3.0,
            1.0 / 12.0,
            1.0 / 12.0,
            -1.0 / 3.0,
            -1.0 / 3.0,
            1.0 / 12.0,
            1.0 / 12.0,
        ];
        let var: f64 = w.iter().map(|x| x * x).sum();
        assert!((var * RESIDUAL_SCALE - 1.0).abs() < 1e-12, "{var}");
        for (k, wk) in w.iter().enumerate() {
            let mut e = [0.0; 9];
            e[k] = 1.0;
            assert!((residual(&e) - wk).abs() < 1e-15);
        }
    }

    /// Photon noise (variance proportional to the level) and read noise together: the floor
    /// solves m = 3 σ(m).
    #[test]
    fn the_floor_of_photon_and_read_noise_solves_the_detection_limit() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let (a, b) = (1e-5, 1e-9);
        let mut pts = Vec::new();
        for _ in 0..300_000 {
            let m = 10f64.powf(rng.random_range(-6.0..-1.0));
            let sd = (a * m + b).sqrt();
            pts.push((m, Normal::new(0.0, sd).unwrap().sample(&mut rng)));
        }
        let e = floor_of(pts, vec![0]).unwrap();
        // m² = 9 (a m + b)
        let k = FLOOR_SNR * FLOOR_SNR;
        let want = (k * a + (k * k * a * a + 4.0 * k * b).sqrt()) / 2.0;
        assert!((e.floor / want - 1.0).abs() < 0.15, "{} {want}", e.floor);
    }

    #[test]
    fn at_most_sixteen_frames_spread_over_the_scan_are_read() {
        let all: Vec<usize> = (0..100).collect();
        let f = frames_to_read(&all);
        assert_eq!(f.len(), MAX_FRAMES);
        assert_eq!(f[0], 0);
        assert!(f[MAX_FRAMES - 1] >= 90);
        assert_eq!(frames_to_read(&all[..5]), vec![0, 1, 2, 3, 4]);
    }
}
