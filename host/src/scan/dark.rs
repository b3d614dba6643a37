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

use crate::dataset::{DarkFrame, Image};
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
    })
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
