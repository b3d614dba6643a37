//! The radiance noise floor measured from a scan's own frames, for a dataset whose `scan.json`
//! gives none (and to check one it gives).
//!
//! Why measure: the floor decides which samples are noise (dropped), Eq. 6's t2 and Eq. 8's
//! threshold t, so a missing floor (0) lets pixels of pure noise into every fit and every error:
//! sample-pebble's frames as 16-bit TIFF brackets without the key moved the held-out green error
//! from 0.379 to 0.773. A real camera's dataset has no floor unless its user measured
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
/// σ = this × the median absolute deviation, for Gaussian noise.
const MAD_TO_SIGMA: f64 = 1.4826;

/// A measured noise floor.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NoiseEstimate {
    /// The floor (radiance: pixel / exposure_s), positive: where no level is noisier than the
    /// criterion the estimate is refused ([`NoiseError::NoFloor`]), never 0.
    pub floor: f64,
    /// How it was measured, in words.
    pub method: String,
    /// Frames read.
    pub frames: Vec<usize>,
    /// The noise level function: (level, relative noise σ/m, residuals) per bin.
    pub levels: Vec<(f64, f64, usize)>,
    /// Correlation of the residuals of horizontally adjacent pixels, each divided by its level
    /// (`None` with too few pairs); [`INDEPENDENT_CORRELATION`] for noise that is independent
    /// from pixel to pixel.
    pub neighbour_correlation: Option<f64>,
}

/// The correlation [`residual`] leaves between horizontally adjacent pixels when the noise is
/// independent from pixel to pixel: Σ_a h(a) h(a + x̂) / Σ_a h(a)² of its stencil h, −26/53.
/// Demosaicing (a Bayer camera's TIFF or a DNG developed by rawpy), denoising and resampling
/// correlate neighbouring pixels, which moves it and makes the residual's σ an underestimate of
/// the pixel noise (the predictor, built from the neighbours, follows part of the noise).
pub const INDEPENDENT_CORRELATION: f64 = -26.0 / 53.0;

/// How far the measured neighbour correlation may stand from [`INDEPENDENT_CORRELATION`] before
/// the floor is refused. A Bayer mosaic's green channel demosaiced bilinearly moves it by 0.39
/// (σ read 2.3x low), its red and blue by 0.65 (σ 5.8x low; test
/// `correlated_noise_is_refused`); the outside renderer's Monte Carlo frames, whose pixels are
/// traced independently, stand 0.08 (sample-slab), 0.10 (sample-pebble) and 0.16
/// (sample-torus) from it at the levels below their floors, where the signal's own residual
/// still adds a little. A mild smoothing that moves it by less (a 3-tap (0.1, 0.8, 0.1)
/// kernel: 0.14) reads σ about 25 % low, within the 1.5x a floor is good to.
pub const MAX_CORRELATION_SHIFT: f64 = 0.25;

/// Pairs of adjacent residuals the correlation needs to be read.
const MIN_PAIRS: usize = 1000;

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
    /// The frames' noise is below a third of the signal already at the lowest level measured:
    /// the floor lies below every level seen, which is what a black level or an ambient
    /// pedestal left in the frames, or denoised or lossy frames, look like.
    #[error(
        "the frames' noise is below 1/{FLOOR_SNR} of the signal at every level measured, the \
         lowest {lowest:.3e} (noise {relative:.3} of it), so no noise floor can be measured from \
         them: a black level or an ambient light left in the frames (set `black_level` in \
         scan.json, take dark frames, or subtract it), or denoised or lossy frames; measure the \
         camera's floor from dark frames and give `noise_floor` in scan.json (or --noise-floor)"
    )]
    NoFloor {
        /// The lowest level measured (radiance).
        lowest: f64,
        /// Its relative noise σ/m.
        relative: f64,
    },
    /// Neighbouring pixels' noise is correlated (demosaiced, denoised or resampled frames): the
    /// residual's spread would understate the noise.
    #[error(
        "the noise of neighbouring pixels is correlated (residual correlation {measured:.3}, \
         {INDEPENDENT_CORRELATION:.3} for independent pixels): the frames look demosaiced, \
         denoised or resampled, and a floor measured from them would be too low; use the \
         camera's raw frames, or measure its floor from dark frames and give `noise_floor` in \
         scan.json (or --noise-floor)"
    )]
    Correlated {
        /// The measured correlation.
        measured: f64,
    },
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
    let per: Vec<Result<Residuals, NoiseError>> =
        read.par_iter().map(|&k| residuals(ds, scene, k)).collect();
    let mut all = Residuals::default();
    for r in per {
        let r = r?;
        all.points.extend(r.points);
        all.pairs.extend(r.pairs);
    }
    let mut e = floor_of(all.points, read)?;
    // Where the noise dominates the signal's own residual (a fall-off steeper than cubic, a
    // texture edge), whose neighbours correlate whatever the noise: at levels up to the floor.
    let noisy: Vec<(f64, f64)> = all
        .pairs
        .iter()
        .filter(|p| p.0 <= e.floor)
        .map(|p| (p.1, p.2))
        .collect();
    let correlation = neighbour_correlation(&noisy);
    if let Some(c) = correlation
        && (c - INDEPENDENT_CORRELATION).abs() > MAX_CORRELATION_SHIFT
    {
        return Err(NoiseError::Correlated { measured: c });
    }
    e.neighbour_correlation = correlation;
    Ok(e)
}

/// A frame's residuals: (local level, scaled residual) per examined pixel and channel, and the
/// level-normalised residuals of horizontally adjacent pixel pairs (for the correlation).
#[derive(Default)]
struct Residuals {
    points: Vec<(f64, f64)>,
    /// (the pair's lower level, left residual / its level, right residual / its level).
    pairs: Vec<(f64, f64, f64)>,
}

/// The correlation of adjacent residual pairs (each already divided by its level), robust to a
/// few glints: pairs beyond 5 robust standard deviations of either side are left out.
fn neighbour_correlation(pairs: &[(f64, f64)]) -> Option<f64> {
    if pairs.len() < MIN_PAIRS {
        return None;
    }
    let spread = |f: fn(&(f64, f64)) -> f64| {
        let mut v: Vec<f64> = pairs.iter().map(|p| f(p).abs()).collect();
        let mid = v.len() / 2;
        v.select_nth_unstable_by(mid, f64::total_cmp);
        MAD_TO_SIGMA * v[mid]
    };
    let (sa, sb) = (spread(|p| p.0), spread(|p| p.1));
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for &(a, b) in pairs {
        if a.abs() > 5.0 * sa || b.abs() > 5.0 * sb {
            continue;
        }
        ab += a * b;
        aa += a * a;
        bb += b * b;
    }
    let c = ab / (aa * bb).sqrt();
    c.is_finite().then_some(c)
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
/// clipped or not finite; and where the pixel to the right qualifies too, the pair of their
/// residuals over their levels.
fn residuals(ds: &Dataset, scene: &Scene, k: usize) -> Result<Residuals, NoiseError> {
    let spec = &ds.spec.frames[k];
    let img = ds
        .read_frame(k)
        .map_err(|source| NoiseError::Frame { frame: k, source })?;
    let Some(cam) = ds.spec.cameras.get(spec.camera) else {
        return Ok(Residuals::default());
    };
    let (w, h) = (img.width, img.height);
    if w < 6 || h < 5 {
        return Ok(Residuals::default());
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
    let stencil = |i: usize, j: usize| {
        [
            (i, j),
            (i - 1, j),
            (i + 1, j),
            (i - 2, j),
            (i + 2, j),
            (i, j - 1),
            (i, j + 1),
            (i, j - 2),
            (i, j + 2),
        ]
    };
    // (level, scaled residual) of the pixel at `at`'s centre in channel c, where it qualifies.
    let read = |at: &[(usize, usize); 9], c: usize| -> Option<(f64, f64)> {
        let v = at.map(|(a, b)| img.get(a, b, c) as f64);
        if v.iter().any(|x| !x.is_finite() || *x >= saturation) {
            return None;
        }
        let level = v.iter().sum::<f64>() / 9.0 / exposure;
        (level > 0.0 && level.is_finite()).then(|| (level, residual(&v) / exposure * scale))
    };
    let mut out = Residuals::default();
    for j in (2..h - 2).step_by(stride) {
        for i in (2..w - 3).step_by(stride) {
            let at = stencil(i, j);
            if !at.iter().all(|&(a, b)| sees(a, b)) {
                continue;
            }
            let right = stencil(i + 1, j);
            let right_sees = sees(i + 3, j) && right.iter().all(|&(a, b)| sees(a, b));
            for &c in channels {
                let c = c.min(img.channels - 1);
                let Some(p) = read(&at, c) else { continue };
                out.points.push(p);
                if right_sees && let Some(q) = read(&right, c) {
                    out.pairs.push((p.0.min(q.0), p.1 / p.0, q.1 / q.0));
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
    let mut bins: std::collections::BTreeMap<i64, (f64, Vec<f64>)> = Default::default();
    for &(m, r) in &pts {
        let e = bins.entry(bin(m)).or_default();
        e.0 += m;
        e.1.push(r.abs());
    }
    // Each bin's spread as the RMS of its residuals without the largest 0.1 %: a hot pixel, a
    // glint or a texture edge among a bin's pixels is left out, where a plain RMS would let a
    // few of them set the noise. Not the median absolute deviation: a Monte Carlo renderer's
    // photon noise (and a camera's at low light) is heavy-tailed, its tails are the noise, and
    // the MAD reads it low. Chosen on training frames only, by cross-validation: each shared
    // render's training angles in 4 folds of 2, each fold predicted by a fit of the others at
    // the floor each statistic measures, judged on the same samples (scan.json's floor); mean
    // held-out green of the folds ± SE. sample-torus: trimmed RMS 0.875 ± 0.075 (floor
    // 3.15e-6), plain RMS 0.875 ± 0.074 (3.26e-6), MAD 0.946 ± 0.059 (2.14e-6; worse in 3 of
    // the 4 folds); sample-pebble: 0.435 ± 0.026 (3.19e-5), 0.441 ± 0.027 (3.47e-5), 0.430 ±
    // 0.007 (1.61e-5), a tie; sample-slab's floors differ by 8 % (1.64-1.78e-5). The trim keeps
    // the RMS's figure and its robustness. For Gaussian noise it lowers σ by 0.6 %.
    let levels: Vec<(f64, f64, usize)> = bins
        .into_values()
        .filter(|b| b.1.len() >= MIN_PER_BIN)
        .map(|(sm, mut r)| {
            let n = r.len();
            let m = sm / n as f64;
            let keep = n - n / 1000;
            r.select_nth_unstable_by(keep - 1, f64::total_cmp);
            let ss: f64 = r[..keep].iter().map(|x| x * x).sum();
            (m, (ss / keep as f64).sqrt() / m, n)
        })
        .collect();
    if levels.is_empty() {
        return Err(NoiseError::NoData);
    }
    let limit = 1.0 / FLOOR_SNR;
    // The lowest level seen already has its noise below the limit: the floor is below every
    // level measured, and 0 would let pure noise into every fit. Refused, with what to do.
    if levels[0].1 <= limit {
        return Err(NoiseError::NoFloor {
            lowest: levels[0].0,
            relative: levels[0].1,
        });
    }
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
        // Unreachable after the check above (the lowest bin is above the limit); kept as the
        // same refusal rather than a panic.
        None => {
            return Err(NoiseError::NoFloor {
                lowest: levels[0].0,
                relative: levels[0].1,
            });
        }
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
        neighbour_correlation: None,
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
        assert!(matches!(
            floor_of(quiet, vec![0]),
            Err(NoiseError::NoFloor { .. })
        ));
        assert!(matches!(floor_of(vec![], vec![]), Err(NoiseError::NoData)));
    }

    /// A pedestal left in the frames (a black level, ambient light) lifts every level above the
    /// noise: the lowest bin is already below a third, and the floor is refused with what to
    /// do, not returned as 0 or as the pedestal's own level.
    #[test]
    fn a_pedestal_under_the_signal_is_refused() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let sigma = 2e-4;
        let noise = Normal::new(0.0, sigma).unwrap();
        let pedestal = 1e-2;
        let pts: Vec<(f64, f64)> = (0..200_000)
            .map(|_| {
                let m = 10f64.powf(rng.random_range(-5.0..-1.0));
                (m + pedestal, noise.sample(&mut rng))
            })
            .collect();
        let e = floor_of(pts, vec![0]);
        let Err(err) = e else {
            panic!("a pedestal gave a floor: {e:?}");
        };
        assert!(matches!(err, NoiseError::NoFloor { .. }));
        assert!(err.to_string().contains("black_level"), "{err}");
    }

    /// The per-bin spread is robust: one residual in 2,000 replaced by a glint a hundred times
    /// the noise leaves the floor within 15 %, where a plain RMS would raise it 2.4 times.
    #[test]
    fn glints_do_not_raise_the_floor() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let sigma = 2e-4;
        let noise = Normal::new(0.0, sigma).unwrap();
        let pts: Vec<(f64, f64)> = (0..200_000)
            .map(|i| {
                let m = 10f64.powf(rng.random_range(-5.0..-1.0));
                let r = noise.sample(&mut rng);
                (m, if i % 2000 == 0 { 100.0 * sigma } else { r })
            })
            .collect();
        let e = floor_of(pts, vec![0]).unwrap();
        let want = FLOOR_SNR * sigma;
        assert!((e.floor / want - 1.0).abs() < 0.15, "{} {want}", e.floor);
    }

    /// The residuals of independent pixel noise correlate between neighbours by the stencil's
    /// own −26/53; the green channel of a Bayer mosaic of the same noise demosaiced bilinearly
    /// (each missing green the mean of its four neighbours) moves it beyond the limit.
    #[test]
    fn correlated_noise_is_refused() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let normal = Normal::new(0.0, 1.0).unwrap();
        let (w, h) = (400, 300);
        let white: Vec<f64> = (0..w * h).map(|_| normal.sample(&mut rng)).collect();
        // RGGB: green where i + j is odd.
        let green = |i: usize, j: usize| (i + j) % 2 == 1;
        let mut demosaiced = white.clone();
        for j in 1..h - 1 {
            for i in 1..w - 1 {
                if !green(i, j) {
                    demosaiced[j * w + i] = (white[j * w + i - 1]
                        + white[j * w + i + 1]
                        + white[(j - 1) * w + i]
                        + white[(j + 1) * w + i])
                        / 4.0;
                }
            }
        }
        let pairs_of = |img: &[f64]| -> Vec<(f64, f64)> {
            let at = |i: usize, j: usize| img[j * w + i];
            let r = |i: usize, j: usize| {
                residual(&[
                    at(i, j),
                    at(i - 1, j),
                    at(i + 1, j),
                    at(i - 2, j),
                    at(i + 2, j),
                    at(i, j - 1),
                    at(i, j + 1),
                    at(i, j - 2),
                    at(i, j + 2),
                ])
            };
            let mut out = Vec::new();
            for j in 3..h - 3 {
                for i in 3..w - 4 {
                    out.push((r(i, j), r(i + 1, j)));
                }
            }
            out
        };
        let white_c = neighbour_correlation(&pairs_of(&white)).unwrap();
        assert!(
            (white_c - INDEPENDENT_CORRELATION).abs() < 0.02,
            "{white_c} against {INDEPENDENT_CORRELATION}"
        );
        let demosaiced_c = neighbour_correlation(&pairs_of(&demosaiced)).unwrap();
        assert!(
            (demosaiced_c - INDEPENDENT_CORRELATION).abs() > MAX_CORRELATION_SHIFT + 0.1,
            "{demosaiced_c}"
        );
        assert_eq!(neighbour_correlation(&[(1.0, 1.0); 10]), None);
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
