//! Writing images: tone-mapped 8-bit PNG for looking (exposure from the image, a highlight
//! shoulder instead of clipping, [`ToneMapping`] says what was done), linear float EXR for
//! measuring (the real values, never scaled or clipped).

use std::path::Path;

use super::RenderError;
use super::raster::Image;

/// Quantile of the lit pixels' brightest channel that automatic exposure maps to white (1.0
/// before the highlight shoulder): the exposure comes from the image, so at most 0.2 % of the lit
/// object is brighter than white, and the shoulder keeps even those below 255 unless they are
/// [`SHOULDER_CLIP`] times brighter still.
pub const WHITE_QUANTILE: f64 = 0.998;

/// Where the highlight shoulder starts (linear, after exposure): below it the tone curve is the
/// identity, above it values roll off smoothly towards 1 instead of clipping.
pub const SHOULDER_KNEE: f64 = 0.8;

/// How many times brighter than white a value must be to come out as 255 after the shoulder
/// (`shoulder(x) >= 0.9955`, which the sRGB curve rounds to 255).
pub const SHOULDER_CLIP: f64 = 1.56;

/// How a linear image became an 8-bit picture, for the report beside it: a picture never clips
/// silently.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToneMapping {
    /// Linear scale applied to the radiance before the tone curve.
    pub exposure: f64,
    /// True when the exposure was chosen from the image ([`auto_exposure`]), false when given.
    pub automatic: bool,
    /// Lit pixels (covered, some channel above zero).
    pub lit_pixels: usize,
    /// Fraction of the lit pixels with some channel at 255 (clipped).
    pub clipped: f64,
}

impl ToneMapping {
    /// One sentence for a report: how the exposure was chosen and what clipped.
    pub fn describe(&self) -> String {
        format!(
            "{} exposure x{:.3} ({}), linear up to {SHOULDER_KNEE} then a smooth highlight \
             shoulder, sRGB; {:.2} % of the lit pixels clipped",
            if self.automatic { "automatic" } else { "fixed" },
            self.exposure,
            if self.automatic {
                format!(
                    "the {:.1}th percentile of the brightest channel maps to white",
                    100.0 * WHITE_QUANTILE
                )
            } else {
                "given".to_string()
            },
            100.0 * self.clipped
        )
    }
}

/// The exposure that maps the [`WHITE_QUANTILE`] of the lit pixels' brightest channel to 1.0
/// (1.0 for an image with nothing lit).
pub fn auto_exposure(img: &Image) -> f64 {
    let mut l: Vec<f64> = img
        .pixels
        .iter()
        .zip(&img.covered)
        .filter(|(_, c)| **c)
        .map(|(p, _)| p.iter().map(|&v| v as f64).fold(0.0, f64::max))
        .filter(|x| x.is_finite() && *x > 0.0)
        .collect();
    if l.is_empty() {
        return 1.0;
    }
    l.sort_by(f64::total_cmp);
    let white = l[((l.len() - 1) as f64 * WHITE_QUANTILE).round() as usize];
    1.0 / white
}

/// The tone curve after exposure: identity up to [`SHOULDER_KNEE`], then an exponential roll-off
/// with the same slope at the knee that approaches 1 (continuous and smooth, so highlights keep
/// their gradient instead of becoming a flat band).
pub fn shoulder(x: f64) -> f64 {
    if !x.is_finite() || x <= 0.0 {
        return 0.0;
    }
    if x <= SHOULDER_KNEE {
        return x;
    }
    let w = 1.0 - SHOULDER_KNEE;
    SHOULDER_KNEE + w * (1.0 - (-(x - SHOULDER_KNEE) / w).exp())
}

/// The sRGB transfer curve to 8 bits.
fn srgb8(x: f64) -> u8 {
    let x = if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let y = if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (y * 255.0).round() as u8
}

/// Tone mapping: `exposure` (or [`auto_exposure`] from the image), the highlight [`shoulder`],
/// the sRGB curve. Uncovered pixels are a dark grey, so the object's silhouette is visible even
/// where it is dark. Returns the picture and what was done to it.
pub fn tone_map_with(img: &Image, exposure: Option<f64>) -> (image::RgbImage, ToneMapping) {
    let scale = exposure.unwrap_or_else(|| auto_exposure(img));
    let mut out = image::RgbImage::new(img.width, img.height);
    let (mut lit, mut clipped) = (0usize, 0usize);
    for (k, px) in out.pixels_mut().enumerate() {
        *px = if img.covered[k] {
            let p = img.pixels[k];
            let rgb = p.map(|v| srgb8(shoulder(v as f64 * scale)));
            if p.iter().any(|&v| v > 0.0) {
                lit += 1;
                if rgb.contains(&255) {
                    clipped += 1;
                }
            }
            image::Rgb(rgb)
        } else {
            image::Rgb([24, 24, 28])
        };
    }
    let info = ToneMapping {
        exposure: scale,
        automatic: exposure.is_none(),
        lit_pixels: lit,
        clipped: if lit == 0 {
            0.0
        } else {
            clipped as f64 / lit as f64
        },
    };
    (out, info)
}

/// [`tone_map_with`] without the description.
pub fn tone_map(img: &Image, exposure: Option<f64>) -> image::RgbImage {
    tone_map_with(img, exposure).0
}

/// Saves the tone-mapped image as PNG; returns how it was tone-mapped.
pub fn save_png(
    img: &Image,
    exposure: Option<f64>,
    path: &Path,
) -> Result<ToneMapping, RenderError> {
    let (picture, info) = tone_map_with(img, exposure);
    picture
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| RenderError::Image {
            path: path.to_path_buf(),
            source,
        })?;
    Ok(info)
}

/// Saves the linear radiance as a float32 RGB OpenEXR (uncovered pixels are 0), through the one
/// EXR encoder ([`crate::dataset::write_exr`]).
pub fn save_exr(img: &Image, path: &Path) -> Result<(), RenderError> {
    let linear = crate::dataset::Image {
        width: img.width as usize,
        height: img.height as usize,
        channels: 3,
        data: img.pixels.iter().flat_map(|p| *p).collect(),
    };
    crate::dataset::write_exr(path, &linear).map_err(RenderError::Exr)
}

/// What a test needs to know to say an image is a real picture: its size and how much it varies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageStats {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Number of distinct 8-bit RGB colours.
    pub distinct_colours: usize,
    /// Standard deviation of the 8-bit luma over all pixels.
    pub luma_std: f64,
}

/// Decodes an image file and measures it.
pub fn image_stats(path: &Path) -> Result<ImageStats, image::ImageError> {
    let img = image::open(path)?.to_rgb8();
    let mut colours: Vec<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    let luma: Vec<f64> = colours
        .iter()
        .map(|p| 0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64)
        .collect();
    let n = luma.len().max(1) as f64;
    let mean = luma.iter().sum::<f64>() / n;
    let var = luma.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / n;
    colours.sort_unstable();
    colours.dedup();
    Ok(ImageStats {
        width: img.width(),
        height: img.height(),
        distinct_colours: colours.len(),
        luma_std: var.sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A lit disc whose brightness rises towards a small, very bright highlight (like a key
    /// light's spot): `n` × `n` pixels, the corners uncovered.
    fn highlight_image(n: u32) -> Image {
        let mut pixels = Vec::new();
        let mut covered = Vec::new();
        let c = (n as f64 - 1.0) / 2.0;
        for y in 0..n {
            for x in 0..n {
                let r = ((x as f64 - c).powi(2) + (y as f64 - c).powi(2)).sqrt() / c;
                covered.push(r <= 1.0);
                // 1 at the rim, 100 at the centre.
                let v = (100.0 * (-4.6 * r).exp()) as f32;
                pixels.push([v, 0.9 * v, 0.8 * v]);
            }
        }
        Image {
            width: n,
            height: n,
            pixels,
            covered,
        }
    }

    #[test]
    fn the_shoulder_is_continuous_monotonic_and_reaches_255_only_far_above_white() {
        let mut prev = 0.0;
        for k in 1..4000 {
            let x = k as f64 * 1e-3;
            let y = shoulder(x);
            assert!(y > prev && y < 1.0, "x {x}: {y}");
            prev = y;
        }
        let eps = 1e-9;
        assert!((shoulder(SHOULDER_KNEE + eps) - shoulder(SHOULDER_KNEE - eps)).abs() < 1e-8);
        assert!(srgb8(shoulder(1.0)) < 255);
        assert!(srgb8(shoulder(0.99 * SHOULDER_CLIP)) < 255);
        assert_eq!(srgb8(shoulder(1.01 * SHOULDER_CLIP)), 255);
        assert_eq!(shoulder(f64::NAN), 0.0);
    }

    #[test]
    fn automatic_exposure_keeps_clipping_below_half_a_percent_and_says_so() {
        let img = highlight_image(201);
        let (_, t) = tone_map_with(&img, None);
        assert!(t.automatic && t.lit_pixels > 30_000, "{t:?}");
        assert!(t.clipped <= 0.005, "{t:?}");
        // The exposure maps the 99.8th percentile (r = 0.045 of the radius: 81) to white, not
        // a mid-grey rule that burns the highlight out.
        assert!((t.exposure * 81.4 - 1.0).abs() < 0.05, "{t:?}");
        assert!(t.describe().contains("automatic"), "{}", t.describe());
        // A fixed exposure that overexposes is reported, not hidden.
        let (_, over) = tone_map_with(&img, Some(1.0));
        assert!(!over.automatic && over.clipped > 0.01, "{over:?}");
    }

    #[test]
    fn the_exr_keeps_the_real_linear_values() {
        let img = highlight_image(33);
        let max = img
            .pixels
            .iter()
            .flat_map(|p| p.iter().copied())
            .fold(0.0f32, f32::max);
        assert!(max > 50.0);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.exr");
        save_exr(&img, &p).unwrap();
        let back = image::open(&p).unwrap().to_rgb32f();
        let back_max = back.pixels().flat_map(|p| p.0).fold(0.0f32, f32::max);
        assert_eq!(back_max, max);
    }
}
