//! The noise floor a scan measures from its own dark frames.
//!
//! Why: `noise_floor` decides which pixels are noise in every fit and every error (Eq. 6's t2,
//! Eq. 8's t), and in a real camera's units nobody knows it without measuring. A constant
//! (the old `1e-4`) is a guess in units the camera chose. Before its first frame a scan takes
//! one frame per exposure of its bracket with every laser off ([`subsurf_protocol::Command::
//! DarkCapture`]); what the camera records then is its offset and its read noise.
//!
//! The floor is the detection limit of analytical chemistry (IUPAC; Long and Winefordner 1983),
//! as [`crate::pipeline::noise`] measures it from lit frames: the level that stands
//! [`FLOOR_SNR`] blank standard deviations above the blank, `(max(median, 0) + 3 σ) / t`, with
//! the blank's median and robust σ (1.4826 × the median absolute deviation, so hot pixels and
//! a stray reflection do not inflate it). For an HDR bracket the faintest light is read from the
//! longest exposure, so the dataset's floor is the lowest of the brackets' floors. Shot noise
//! is absent from a dark frame; at the floor it is small beside the read noise of any camera
//! whose floor matters (the `sim` camera's: 8 %, tested).
//!
//! Handwritten: the median and MAD of one image, a few lines; the point is which statistics.

use crate::dataset::{DarkFrame, DarkSubtracted, Image};
use crate::pipeline::noise::FLOOR_SNR;

/// Fewest finite pixel values a dark frame needs for its statistics.
pub const MIN_PIXELS: usize = 64;
/// σ = this × the median absolute deviation, for Gaussian noise.
const MAD_TO_SIGMA: f64 = 1.4826;

/// Why a dark frame measures nothing.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum DarkError {
    /// Too few finite pixels.
    #[error(
        "the dark frame at {exposure_s} s has {finite} finite pixel values, fewer than {MIN_PIXELS}"
    )]
    TooFewPixels {
        /// Its exposure.
        exposure_s: f64,
        /// Finite values it has.
        finite: usize,
    },
    /// The exposure is not a positive number.
    #[error("the dark frame's exposure {0} s is not positive")]
    Exposure(f64),
}

/// The statistics of the dark frame `img` (raw values) exposed `exposure_s`, to be written as
/// `image` in the dataset.
pub fn measure(img: &Image, exposure_s: f64, image: String) -> Result<DarkFrame, DarkError> {
    if !(exposure_s.is_finite() && exposure_s > 0.0) {
        return Err(DarkError::Exposure(exposure_s));
    }
    let mut v: Vec<f64> = img
        .data
        .iter()
        .map(|&x| x as f64)
        .filter(|x| x.is_finite())
        .collect();
    if v.len() < MIN_PIXELS {
        return Err(DarkError::TooFewPixels {
            exposure_s,
            finite: v.len(),
        });
    }
    let median = median_of(&mut v);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - median).abs()).collect();
    let sigma = MAD_TO_SIGMA * median_of(&mut dev);
    let floor = (median.max(0.0) + FLOOR_SNR * sigma) / exposure_s;
    Ok(DarkFrame {
        image,
        exposure_s,
        median,
        sigma,
        floor,
        second: None,
        subtracted: None,
    })
}

/// The dark level a scan subtracts from the lit frames of one exposure, in memory.
#[derive(Debug, Clone, PartialEq)]
pub enum DarkLevel {
    /// One value for every pixel.
    Constant(f64),
    /// Each pixel's own (raw values, the dark frames' size).
    PerPixel(Image),
}

impl DarkLevel {
    /// Subtracts the level from the raw frame `img`, leaving pixels at or above `saturation`
    /// (clipped: the HDR merge and the fit must still see them as clipped) and non-finite ones
    /// as they are. A per-pixel level of another size than the frame is refused.
    pub fn subtract(&self, img: &mut Image, saturation: f32) -> Result<(), String> {
        match self {
            DarkLevel::Constant(l) => {
                let l = *l as f32;
                for v in img.data.iter_mut() {
                    if v.is_finite() && *v < saturation {
                        *v -= l;
                    }
                }
            }
            DarkLevel::PerPixel(level) => {
                if (level.width, level.height) != (img.width, img.height) {
                    return Err(format!(
                        "the dark level is {}x{}, the frame {}x{}",
                        level.width, level.height, img.width, img.height
                    ));
                }
                let (c, lc) = (img.channels, level.channels.max(1));
                for (n, v) in img.data.iter_mut().enumerate() {
                    let (px, k) = (n / c, n % c);
                    let l = level.data[px * lc + k.min(lc - 1)];
                    if v.is_finite() && *v < saturation && l.is_finite() {
                        *v -= l;
                    }
                }
            }
        }
        Ok(())
    }
}

/// The statistics of two dark frames `a`, `b` of one exposure and the level to subtract from the
/// lit frames of that exposure (`image`, `second`: their names in the dataset; `level_image`:
/// where a per-pixel level is written).
///
/// Why two: their difference holds the read noise twice and neither the offset nor the fixed
/// pattern, so σ = 1.4826 · MAD(a − b) / √2 is the noise alone, where one frame's spread counted a
/// fixed pattern as noise. The level is their mean: per pixel where the fixed pattern resolves
/// (the mean's spread over pixels, s, exceeds σ: then the fixed pattern's variance s² − σ²/2 is
/// above the σ²/2 a per-pixel estimate adds, and subtracting it per pixel leaves less error than
/// one value), else its median. Once the level is subtracted the floor is 3 σ / t.
pub fn measure_pair(
    a: &Image,
    b: &Image,
    exposure_s: f64,
    image: String,
    second: String,
    level_image: String,
) -> Result<(DarkFrame, DarkLevel), DarkError> {
    if !(exposure_s.is_finite() && exposure_s > 0.0) {
        return Err(DarkError::Exposure(exposure_s));
    }
    if (a.width, a.height, a.channels) != (b.width, b.height, b.channels) {
        return Err(DarkError::TooFewPixels {
            exposure_s,
            finite: 0,
        });
    }
    let pairs: Vec<(f64, f64)> = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(&x, &y)| (x as f64, y as f64))
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect();
    if pairs.len() < MIN_PIXELS {
        return Err(DarkError::TooFewPixels {
            exposure_s,
            finite: pairs.len(),
        });
    }
    let mut diff: Vec<f64> = pairs.iter().map(|(x, y)| x - y).collect();
    let mid = median_of(&mut diff);
    let mut dev: Vec<f64> = diff.iter().map(|d| (d - mid).abs()).collect();
    let sigma = MAD_TO_SIGMA * median_of(&mut dev) / std::f64::consts::SQRT_2;
    let mut mean: Vec<f64> = pairs.iter().map(|(x, y)| 0.5 * (x + y)).collect();
    let median = median_of(&mut mean);
    let mut spread: Vec<f64> = mean.iter().map(|m| (m - median).abs()).collect();
    let s = MAD_TO_SIGMA * median_of(&mut spread);
    let (level, subtracted) = if s > sigma {
        let mut img = a.clone();
        for (v, (&x, &y)) in img.data.iter_mut().zip(a.data.iter().zip(&b.data)) {
            *v = if x.is_finite() && y.is_finite() {
                0.5 * (x + y)
            } else {
                median as f32
            };
        }
        (
            DarkLevel::PerPixel(img),
            DarkSubtracted::PerPixel { image: level_image },
        )
    } else {
        (DarkLevel::Constant(median), DarkSubtracted::Median)
    };
    Ok((
        DarkFrame {
            image,
            exposure_s,
            median,
            sigma,
            floor: FLOOR_SNR * sigma / exposure_s,
            second: Some(second),
            subtracted: Some(subtracted),
        },
        level,
    ))
}

/// The dataset's floor from its dark frames: the lowest (the longest exposure's, as a rule);
/// `None` without any.
pub fn floor_of(dark: &[DarkFrame]) -> Option<f64> {
    dark.iter()
        .map(|d| d.floor)
        .filter(|f| f.is_finite())
        .min_by(f64::total_cmp)
}

/// What a scan says about its floor: a line on the dark frames and the floor written, and a
/// warning when a floor the user gave (`given`) and the measured one differ by more than 2x
/// (wrong units, or a black level left in the frames).
pub fn summary(dark: &[DarkFrame], written: Option<f64>, given: Option<f64>) -> Vec<String> {
    let mut out = Vec::new();
    let Some(measured) = floor_of(dark) else {
        if let Some(w) = written {
            out.push(format!("noise floor {w:.3e} (given; no dark frames taken)"));
        }
        return out;
    };
    let each: Vec<String> = dark
        .iter()
        .map(|d| {
            format!(
                "{} s: median {:.3e}, σ {:.3e}",
                d.exposure_s, d.median, d.sigma
            )
        })
        .collect();
    out.push(format!(
        "dark frames ({}): noise floor measured {measured:.3e} (the level {FLOOR_SNR} σ above the \
         dark level at the longest exposure){}",
        each.join("; "),
        match (given, written) {
            (Some(g), _) => format!(", scan.json keeps the given {g:.3e}"),
            (None, Some(w)) if w != measured => format!(", scan.json keeps {w:.3e}"),
            _ => ", written to scan.json".to_string(),
        }
    ));
    if let Some(g) = given {
        let ratio = (g / measured).max(measured / g);
        if ratio.is_nan() || ratio > 2.0 {
            out.push(format!(
                "warning: the given noise floor {g:.3e} and the one the dark frames measure, \
                 {measured:.3e}, differ by more than 2x: check the camera's units and black level \
                 (docs/scan-format.md), or leave --noise-floor out to use the measured one"
            ));
        }
    }
    out
}

/// Where a scan writes the dark frame of bracket `b` (exposure `exposure_us`).
pub fn image_name(b: usize, exposure_us: u32) -> String {
    format!("dark/{b:02}-{exposure_us}us.exr")
}

/// Where a scan writes the second dark frame of bracket `b`.
pub fn second_name(b: usize, exposure_us: u32) -> String {
    format!("dark/{b:02}-{exposure_us}us-b.exr")
}

/// Where a scan writes the per-pixel dark level of bracket `b`.
pub fn level_name(b: usize, exposure_us: u32) -> String {
    format!("dark/{b:02}-{exposure_us}us-level.exr")
}

/// The level of each dark frame that records one as subtracted, by exposure, read back from the
/// dataset directory `dir` (a per-pixel level from its image): what a resumed scan subtracts.
pub fn levels_of(
    dir: &std::path::Path,
    dark: &[DarkFrame],
) -> Result<Vec<(f64, DarkLevel)>, String> {
    let mut out = Vec::new();
    for d in dark {
        match &d.subtracted {
            None => {}
            Some(DarkSubtracted::Median) => out.push((d.exposure_s, DarkLevel::Constant(d.median))),
            Some(DarkSubtracted::PerPixel { image }) => {
                let path = crate::dataset::confined_path(dir, image).map_err(|e| e.to_string())?;
                let img = crate::dataset::read_image(&path).map_err(|e| e.to_string())?;
                out.push((d.exposure_s, DarkLevel::PerPixel(img)));
            }
        }
    }
    Ok(out)
}

/// The level of `levels` for exposure `exposure_s` (within a millionth).
pub fn level_for(levels: &[(f64, DarkLevel)], exposure_s: f64) -> Option<&DarkLevel> {
    levels
        .iter()
        .find(|(t, _)| (t - exposure_s).abs() <= 1e-6 * exposure_s.abs())
        .map(|(_, l)| l)
}

/// Median of finite values (reorders `v`; `v` not empty).
fn median_of(v: &mut [f64]) -> f64 {
    let n = v.len();
    let (_, hi, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let hi = *hi;
    if n % 2 == 1 {
        return hi;
    }
    let lo = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    fn image(values: impl IntoIterator<Item = f32>, w: usize) -> Image {
        let data: Vec<f32> = values.into_iter().collect();
        let h = data.len() / w;
        let mut img = Image::new(w, h, 1);
        img.data.copy_from_slice(&data[..w * h]);
        img
    }

    /// Gaussian read noise with an offset and a few hot pixels: the offset and σ come back, the
    /// hot pixels do not move them, and the floor is (offset + 3 σ) / t.
    #[test]
    fn a_dark_frame_gives_its_offset_and_read_noise_despite_hot_pixels() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let n = Normal::new(0.002, 0.0005).unwrap();
        let mut v: Vec<f32> = (0..128 * 128).map(|_| n.sample(&mut rng) as f32).collect();
        for k in (0..v.len()).step_by(97) {
            v[k] = 1.0;
        }
        v[5] = f32::NAN;
        let d = measure(&image(v, 128), 0.01, "dark/x.exr".into()).unwrap();
        assert!((d.median - 0.002).abs() < 2e-5, "{d:?}");
        assert!((d.sigma / 0.0005 - 1.0).abs() < 0.03, "{d:?}");
        let want = (d.median + 3.0 * d.sigma) / 0.01;
        assert!((d.floor - want).abs() < 1e-12 * want, "{d:?}");
        // Three brackets: the longest exposure's is the lowest floor.
        let longer = DarkFrame {
            exposure_s: 0.1,
            floor: d.floor / 10.0,
            ..d.clone()
        };
        assert_eq!(floor_of(&[d.clone(), longer.clone()]), Some(longer.floor));
        assert_eq!(floor_of(&[]), None);
    }

    /// Two dark frames with an offset and a fixed pattern: σ from their difference is the read
    /// noise alone (one frame's spread would count the pattern), the pattern resolves and is
    /// subtracted per pixel, leaving a lit frame's light; without a pattern the median is.
    #[test]
    fn two_dark_frames_give_the_noise_without_the_offset_or_the_pattern() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let read = Normal::new(0.0, 0.0005).unwrap();
        let pattern_n = Normal::new(0.0, 0.002).unwrap();
        let pattern: Vec<f64> = (0..128 * 128).map(|_| pattern_n.sample(&mut rng)).collect();
        let frame = |rng: &mut rand::rngs::StdRng, with_pattern: bool| {
            image(
                pattern
                    .iter()
                    .map(|p| (0.01 + if with_pattern { *p } else { 0.0 } + read.sample(rng)) as f32)
                    .collect::<Vec<_>>(),
                128,
            )
        };
        let (a, b) = (frame(&mut rng, true), frame(&mut rng, true));
        let (d, level) = measure_pair(&a, &b, 0.5, "a".into(), "b".into(), "level".into()).unwrap();
        assert!((d.sigma / 0.0005 - 1.0).abs() < 0.04, "{d:?}");
        assert!((d.median - 0.01).abs() < 1e-4, "{d:?}");
        assert!((d.floor - 3.0 * d.sigma / 0.5).abs() < 1e-12);
        assert!(matches!(
            d.subtracted,
            Some(DarkSubtracted::PerPixel { .. })
        ));
        let single = measure(&a, 0.5, "a".into()).unwrap();
        assert!(
            single.sigma > 3.0 * d.sigma,
            "one frame counts the pattern: {single:?}"
        );
        // A lit frame: light 0.1 on top of the same offset and pattern.
        let mut lit = frame(&mut rng, true);
        for v in lit.data.iter_mut() {
            *v += 0.1;
        }
        level.subtract(&mut lit, f32::INFINITY).unwrap();
        let mean = lit.data.iter().map(|&v| v as f64).sum::<f64>() / lit.data.len() as f64;
        let rms = (lit
            .data
            .iter()
            .map(|&v| (v as f64 - 0.1).powi(2))
            .sum::<f64>()
            / lit.data.len() as f64)
            .sqrt();
        assert!((mean - 0.1).abs() < 1e-4, "{mean}");
        assert!(rms < 0.0005 * 1.5, "{rms}: the pattern is gone");
        // A clipped pixel stays clipped.
        let mut clipped = image(vec![20.0f32; 128 * 128], 128);
        level.subtract(&mut clipped, 20.0).unwrap();
        assert!(clipped.data.iter().all(|&v| v == 20.0));
        // No pattern: the median.
        let (a, b) = (frame(&mut rng, false), frame(&mut rng, false));
        let (d, level) = measure_pair(&a, &b, 0.5, "a".into(), "b".into(), "level".into()).unwrap();
        assert_eq!(d.subtracted, Some(DarkSubtracted::Median));
        assert!(matches!(level, DarkLevel::Constant(m) if (m - 0.01).abs() < 1e-4));
    }

    /// A negative offset (a black level set too high) counts as none; a frame without finite
    /// pixels or with a bad exposure is an error, never a floor.
    #[test]
    fn bad_dark_frames_are_errors_and_a_negative_offset_counts_as_none() {
        let v: Vec<f32> = (0..400)
            .map(|k| -0.01 + 0.001 * ((k % 3) as f32 - 1.0))
            .collect();
        let d = measure(&image(v, 20), 1.0, "dark/x.exr".into()).unwrap();
        assert!(d.median < 0.0);
        assert!((d.floor - 3.0 * d.sigma).abs() < 1e-12, "{d:?}");
        let nan = image(vec![f32::NAN; 400], 20);
        assert_eq!(
            measure(&nan, 1.0, String::new()),
            Err(DarkError::TooFewPixels {
                exposure_s: 1.0,
                finite: 0
            })
        );
        let ok = image(vec![0.0; 400], 20);
        assert_eq!(
            measure(&ok, 0.0, String::new()),
            Err(DarkError::Exposure(0.0))
        );
    }
}
