//! Writing images: tone-mapped 8-bit PNG for looking, linear float EXR for measuring.

use std::path::Path;

use super::RenderError;
use super::raster::Image;

/// Tone mapping: automatic exposure puts the median luminance of the covered pixels at 0.25
/// (photographic mid-grey: a few very bright vertices, e.g. badly extrapolated fits, clip instead
/// of darkening the whole object) unless the 99th percentile would then stay below 0.9, in which
/// case that percentile maps to 0.9; `exposure` overrides it. Then it clips, and applies the sRGB transfer curve. Uncovered pixels
/// are a dark grey, so the object's silhouette is visible even where it is dark.
pub fn tone_map(img: &Image, exposure: Option<f64>) -> image::RgbImage {
    let lum = |p: &[f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    let scale = exposure.unwrap_or_else(|| {
        let mut l: Vec<f64> = img
            .pixels
            .iter()
            .zip(&img.covered)
            .filter(|(_, c)| **c)
            .map(|(p, _)| lum(p))
            .filter(|x| x.is_finite() && *x > 0.0)
            .collect();
        if l.is_empty() {
            return 1.0;
        }
        l.sort_by(f64::total_cmp);
        let p99 = l[((l.len() - 1) as f64 * 0.99) as usize];
        let median = l[l.len() / 2];
        if 0.25 / median * p99 > 0.9 {
            0.25 / median
        } else {
            0.9 / p99
        }
    });
    let srgb = |x: f64| -> u8 {
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
    };
    let mut out = image::RgbImage::new(img.width, img.height);
    for (k, px) in out.pixels_mut().enumerate() {
        *px = if img.covered[k] {
            image::Rgb(img.pixels[k].map(|v| srgb(v as f64 * scale)))
        } else {
            image::Rgb([24, 24, 28])
        };
    }
    out
}

/// Saves the tone-mapped image as PNG.
pub fn save_png(img: &Image, exposure: Option<f64>, path: &Path) -> Result<(), RenderError> {
    tone_map(img, exposure)
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| RenderError::Image {
            path: path.to_path_buf(),
            source,
        })
}

/// Saves the linear radiance as a float32 RGB OpenEXR (uncovered pixels are 0).
pub fn save_exr(img: &Image, path: &Path) -> Result<(), RenderError> {
    let flat: Vec<f32> = img.pixels.iter().flat_map(|p| *p).collect();
    let buf = image::Rgb32FImage::from_raw(img.width, img.height, flat)
        .ok_or_else(|| RenderError::Camera("image buffer size mismatch".into()))?;
    image::DynamicImage::ImageRgb32F(buf)
        .save_with_format(path, image::ImageFormat::OpenExr)
        .map_err(|source| RenderError::Image {
            path: path.to_path_buf(),
            source,
        })
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
