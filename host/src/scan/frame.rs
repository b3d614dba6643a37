//! Linear float images, their OpenEXR encoding, and HDR merging of exposure brackets.

use serde::{Deserialize, Serialize};

/// A linear image, black level removed: `channels` interleaved `f32` per pixel (1 or 3).
#[derive(Debug, Clone, PartialEq)]
pub struct LinearImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// 1 (grey) or 3 (RGB).
    pub channels: usize,
    /// Row-major interleaved samples.
    pub data: Vec<f32>,
}

/// Why an image could not be encoded, decoded or merged.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageError {
    /// Size or channel count does not match the data, or brackets disagree.
    #[error("image shape: {0}")]
    Shape(String),
    /// The EXR/other codec failed.
    #[error("image codec: {0}")]
    Codec(String),
}

impl LinearImage {
    /// A black image.
    pub fn zeros(width: usize, height: usize, channels: usize) -> Self {
        LinearImage {
            width,
            height,
            channels,
            data: vec![0.0; width * height * channels],
        }
    }

    fn check(&self) -> Result<(), ImageError> {
        if !(self.channels == 1 || self.channels == 3)
            || self.width == 0
            || self.height == 0
            || self.data.len() != self.width * self.height * self.channels
        {
            return Err(ImageError::Shape(format!(
                "{}x{}x{} with {} samples",
                self.width,
                self.height,
                self.channels,
                self.data.len()
            )));
        }
        Ok(())
    }

    /// RGB float32 OpenEXR bytes (grey is written to all three channels). Written in one thread
    /// with a fixed encoding so equal images always give equal bytes.
    pub fn to_exr(&self) -> Result<Vec<u8>, ImageError> {
        use exr::prelude::*;
        self.check()?;
        let (w, c) = (self.width, self.channels);
        let px = |x: usize, y: usize| {
            let i = (y * w + x) * c;
            if c == 3 {
                (self.data[i], self.data[i + 1], self.data[i + 2])
            } else {
                (self.data[i], self.data[i], self.data[i])
            }
        };
        let image = Image::from_channels(
            (self.width, self.height),
            SpecificChannels::rgb(|Vec2(x, y)| px(x, y)),
        );
        let mut buf = std::io::Cursor::new(Vec::new());
        image
            .write()
            .non_parallel()
            .to_buffered(&mut buf)
            .map_err(|e| ImageError::Codec(e.to_string()))?;
        Ok(buf.into_inner())
    }

    /// Reads any image the `image` crate decodes (EXR, PFM-free formats, 16-bit PNG/TIFF) as
    /// linear RGB float. Integer formats are scaled to `[0, 1]`; they must already be linear.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ImageError> {
        let img = image::load_from_memory(bytes).map_err(|e| ImageError::Codec(e.to_string()))?;
        let rgb = img.to_rgb32f();
        Ok(LinearImage {
            width: rgb.width() as usize,
            height: rgb.height() as usize,
            channels: 3,
            data: rgb.into_raw(),
        })
    }
}

/// One exposure of a bracket.
#[derive(Debug, Clone)]
pub struct Bracket {
    /// Exposure time (s).
    pub exposure_s: f64,
    /// The image as the sensor gave it (linear, black level removed).
    pub image: LinearImage,
}

/// How to merge brackets.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MergeOptions {
    /// Pixel value at which the sensor saturates.
    pub saturation: f32,
    /// Pixel values under this are noise (read-noise floor).
    pub noise_floor: f32,
}

/// Merges an exposure bracket into one linear radiance image (value per second of exposure).
///
/// Per pixel and channel, each exposure's `value / exposure` is averaged with the weight
/// `exposure · hat(value)`: the hat is 0 at and above 98% of saturation and below the noise
/// floor, and rises linearly in between, so long exposures dominate the dark parts (more signal
/// per read noise) and saturated samples never count. A sample saturated in every exposure takes
/// the shortest exposure's value (a lower bound, like the camera would report). Hand-written:
/// the merge is a few lines and no maintained crate does linear-sensor weighting.
pub fn merge_hdr(brackets: &[Bracket], opts: &MergeOptions) -> Result<LinearImage, ImageError> {
    let first = brackets
        .first()
        .ok_or_else(|| ImageError::Shape("no exposures to merge".into()))?;
    for b in brackets {
        b.image.check()?;
        if (b.image.width, b.image.height, b.image.channels)
            != (first.image.width, first.image.height, first.image.channels)
        {
            return Err(ImageError::Shape("brackets differ in size".into()));
        }
        if !(b.exposure_s.is_finite() && b.exposure_s > 0.0) {
            return Err(ImageError::Shape("exposure must be positive".into()));
        }
    }
    let shortest = brackets
        .iter()
        .min_by(|a, b| a.exposure_s.total_cmp(&b.exposure_s))
        .unwrap_or(first);
    let sat = 0.98 * opts.saturation;
    let floor = opts.noise_floor.max(0.0);
    let mut out = LinearImage::zeros(first.image.width, first.image.height, first.image.channels);
    for (i, o) in out.data.iter_mut().enumerate() {
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for b in brackets {
            let v = b.image.data[i];
            if !v.is_finite() || v >= sat {
                continue;
            }
            let w = if v <= floor {
                1e-6
            } else {
                ((v - floor) / (sat - floor))
                    .min(1.0 - (v - floor) / (sat - floor))
                    .max(1e-6) as f64
            } * b.exposure_s;
            num += w * v as f64 / b.exposure_s;
            den += w;
        }
        *o = if den > 0.0 {
            (num / den) as f32
        } else {
            let v = shortest.image.data[i];
            if v.is_finite() {
                (v as f64 / shortest.exposure_s) as f32
            } else {
                0.0
            }
        };
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_round_trips_and_is_deterministic() {
        let mut img = LinearImage::zeros(5, 3, 3);
        for (k, v) in img.data.iter_mut().enumerate() {
            *v = k as f32 * 0.25;
        }
        let a = img.to_exr().unwrap();
        assert_eq!(a, img.to_exr().unwrap());
        let back = LinearImage::from_bytes(&a).unwrap();
        assert_eq!(back, img);
    }

    #[test]
    fn merge_recovers_radiance_across_saturation() {
        // Radiances spanning 1:10^4; the sensor saturates at 1.0.
        let radiance = [0.5f32, 5.0, 50.0, 500.0, 4000.0];
        let exposures = [1e-4, 1e-3, 1e-2];
        let brackets: Vec<Bracket> = exposures
            .iter()
            .map(|&e| Bracket {
                exposure_s: e,
                image: LinearImage {
                    width: 5,
                    height: 1,
                    channels: 1,
                    data: radiance.iter().map(|r| (r * e as f32).min(1.0)).collect(),
                },
            })
            .collect();
        let m = merge_hdr(
            &brackets,
            &MergeOptions {
                saturation: 1.0,
                noise_floor: 1e-6,
            },
        )
        .unwrap();
        for (got, want) in m.data.iter().zip(radiance) {
            assert!((got / want - 1.0).abs() < 1e-4, "{got} vs {want}");
        }
        assert!(
            merge_hdr(
                &[],
                &MergeOptions {
                    saturation: 1.0,
                    noise_floor: 0.0
                }
            )
            .is_err()
        );
    }
}
