//! HDR merging of exposure brackets: the one merge, for the brackets `subsurf scan --exposure
//! a,b,c` takes and for the bracket files another program's dataset lists per frame
//! (`frames[].brackets`, [`super::Dataset::read_frame`]). Images are the one image type,
//! [`super::Image`] (linear, black level removed).

use serde::{Deserialize, Serialize};

use super::{Image, ImageError};

/// One exposure of a bracket.
#[derive(Debug, Clone)]
pub struct Bracket {
    /// Exposure time (s).
    pub exposure_s: f64,
    /// The image as the sensor gave it (linear, black level removed).
    pub image: Image,
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
/// Debevec and Malik's merge for a linear sensor: per pixel and channel, each exposure's
/// `value / exposure` is averaged with the weight `exposure · hat(value)`: the hat is 0 at and
/// above 98% of saturation, and rises linearly from the noise floor to half of it and falls again,
/// so long exposures dominate the dark parts (more signal per read noise) and saturated samples
/// never count. A sample saturated or not finite in every exposure keeps the shortest exposure's
/// value (a lower bound, like the camera would report; at or above the saturation over the
/// shortest exposure, or not finite), so the readers' rules still see it as clipped or bad and
/// drop it, never as a made-up value. Hand-written: the merge is a few lines and no maintained
/// crate does linear-sensor weighting.
pub fn merge_hdr(brackets: &[Bracket], opts: &MergeOptions) -> Result<Image, ImageError> {
    let first = brackets
        .first()
        .ok_or_else(|| ImageError::Format("no exposures to merge".into()))?;
    for b in brackets {
        b.image.check()?;
        if (b.image.width, b.image.height, b.image.channels)
            != (first.image.width, first.image.height, first.image.channels)
        {
            return Err(ImageError::Format("brackets differ in size".into()));
        }
        if !(b.exposure_s.is_finite() && b.exposure_s > 0.0) {
            return Err(ImageError::Format("exposure must be positive".into()));
        }
    }
    let shortest = brackets
        .iter()
        .min_by(|a, b| a.exposure_s.total_cmp(&b.exposure_s))
        .unwrap_or(first);
    let sat = 0.98 * opts.saturation;
    let floor = opts.noise_floor.max(0.0);
    let mut out = Image::new(first.image.width, first.image.height, first.image.channels);
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
            (v as f64 / shortest.exposure_s) as f32
        };
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merge_recovers_radiance_across_saturation() {
        // Radiances spanning 1:10^4; the sensor saturates at 1.0.
        let radiance = [0.5f32, 5.0, 50.0, 500.0, 4000.0];
        let exposures = [1e-4, 1e-3, 1e-2];
        let brackets: Vec<Bracket> = exposures
            .iter()
            .map(|&e| Bracket {
                exposure_s: e,
                image: Image {
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

    /// What no exposure measured is never made up: a value clipped or not finite in every
    /// exposure keeps the shortest one's (clipped stays at or above saturation over it, NaN and
    /// infinity stay, for the readers' rules to drop); one good exposure is enough.
    #[test]
    fn values_no_exposure_measured_stay_clipped_or_not_finite() {
        let bracket = |exposure_s: f64, data: [f32; 4]| Bracket {
            exposure_s,
            image: Image {
                width: 4,
                height: 1,
                channels: 1,
                data: data.to_vec(),
            },
        };
        let nan = f32::NAN;
        let m = merge_hdr(
            &[
                bracket(0.5, [1.0, nan, f32::INFINITY, nan]),
                bracket(2.0, [1.0, nan, 1.0, 0.4]),
            ],
            &MergeOptions {
                saturation: 1.0,
                noise_floor: 0.0,
            },
        )
        .unwrap();
        assert_eq!(
            m.data[0], 2.0,
            "clipped in both: the shortest's value over its exposure"
        );
        assert!(m.data[0] as f64 * 0.5 >= 1.0);
        assert!(m.data[1].is_nan());
        assert_eq!(m.data[2], f32::INFINITY);
        assert!((m.data[3] - 0.2).abs() < 1e-7, "{}", m.data[3]);
    }
}
