//! Samples s(x_i, x_o) of one frame (section 4.1/5): for each vertex x_o the camera sees, the
//! pixel value at its projection (bilinear) divided by the exposure, per channel.
//!
//! A sample is dropped — and counted — when it is below the noise floor, clipped, non-finite, or
//! closer to x_i than the exclusion radius (first-surface reflection and single scattering
//! dominate there, section 5).
use crate::dataset::{FrameSpec, Image};
use crate::geometry::{V3, Visible, dist};

/// Settings of sample extraction.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SampleOptions {
    /// Samples closer than this to x_i (mm) are dropped.
    pub exclusion_radius_mm: f64,
    /// Radiance (pixel / exposure) below which a sample is noise.
    pub noise_floor: f64,
    /// Raw value at which pixels clip (`None`: never).
    pub saturation: Option<f64>,
    /// Cosine of the largest angle between normal and view direction (grazing rejection).
    pub cos_min: f64,
}

impl Default for SampleOptions {
    fn default() -> Self {
        SampleOptions {
            exclusion_radius_mm: 0.5,
            noise_floor: 0.0,
            saturation: None,
            cos_min: 0.2,
        }
    }
}

/// One vertex's value in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// The vertex x_o.
    pub vertex: u32,
    /// `|x_o - x_i|`, mm (Eq. 1).
    pub r: f64,
    /// s(x_i, x_o) per channel (radiance); only channels flagged in `valid` are meaningful.
    pub value: [f64; 3],
    /// Bit c set = channel c passed every test.
    pub valid: u8,
}

/// Why samples were dropped (per channel sample).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SampleCounts {
    /// Channel samples kept.
    pub used: u64,
    /// Below the noise floor.
    pub below_noise: u64,
    /// Clipped pixels in the bilinear neighbourhood.
    pub saturated: u64,
    /// NaN or infinite.
    pub non_finite: u64,
    /// Within the exclusion radius of x_i.
    pub excluded: u64,
}

impl SampleCounts {
    /// Adds another frame's counts.
    pub fn add(&mut self, o: &SampleCounts) {
        self.used += o.used;
        self.below_noise += o.below_noise;
        self.saturated += o.saturated;
        self.non_finite += o.non_finite;
        self.excluded += o.excluded;
    }
}

/// The samples of one frame for the vertices `visible` from its camera, with light at `x_i`.
pub fn frame_samples(
    img: &Image,
    frame: &FrameSpec,
    visible: &[Visible],
    positions: &[V3],
    x_i: V3,
    opts: &SampleOptions,
) -> (Vec<Sample>, SampleCounts) {
    let mut counts = SampleCounts::default();
    let mut out = Vec::with_capacity(visible.len());
    let chans = frame.channel.channels();
    let sat = opts.saturation.map(|s| s * 0.999).unwrap_or(f64::INFINITY);
    for vis in visible {
        let x_o = positions[vis.vertex as usize];
        let r = dist(x_o, x_i);
        if r < opts.exclusion_radius_mm {
            counts.excluded += chans.len() as u64;
            continue;
        }
        let mut s = Sample {
            vertex: vis.vertex,
            r,
            value: [0.0; 3],
            valid: 0,
        };
        for &c in chans {
            let Some((val, max_raw)) = img.bilinear(vis.u, vis.v, c) else {
                continue;
            };
            let v = val / frame.exposure_s;
            if !v.is_finite() || !max_raw.is_finite() {
                counts.non_finite += 1;
            } else if max_raw >= sat {
                counts.saturated += 1;
            } else if v <= opts.noise_floor || v <= 0.0 {
                counts.below_noise += 1;
            } else {
                s.value[c] = v;
                s.valid |= 1 << c;
                counts.used += 1;
            }
        }
        if s.valid != 0 {
            out.push(s);
        }
    }
    (out, counts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::FrameChannel;

    #[test]
    fn each_rejection_rule_is_applied_and_counted() {
        let mut img = Image::new(4, 1, 3);
        // Pixel 0: fine; 1: NaN in green; 2: clipped; 3: dark.
        img.data[..3].copy_from_slice(&[1.0, 1.0, 1.0]);
        img.data[3..6].copy_from_slice(&[1.0, f32::NAN, 1.0]);
        img.data[6..9].copy_from_slice(&[50.0, 50.0, 50.0]);
        img.data[9..12].copy_from_slice(&[1e-6, 1e-6, 1e-6]);
        let frame = FrameSpec {
            image: String::new(),
            camera: 0,
            turntable_deg: 0.0,
            exposure_s: 2.0,
            channel: FrameChannel::Rgb,
            laser: None,
            galvo: None,
        };
        let pos = vec![
            [1.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
            [4.0, 0.0, 0.0],
            [0.1, 0.0, 0.0],
        ];
        let vis: Vec<Visible> = (0..5)
            .map(|k| Visible {
                vertex: k,
                u: (k % 4) as f64,
                v: 0.0,
            })
            .collect();
        let opts = SampleOptions {
            exclusion_radius_mm: 0.5,
            noise_floor: 1e-4,
            saturation: Some(40.0),
            cos_min: 0.2,
        };
        let (s, c) = frame_samples(&img, &frame, &vis, &pos, [0.0; 3], &opts);
        assert_eq!(s.len(), 2);
        assert_eq!(s[0].value, [0.5, 0.5, 0.5]);
        assert_eq!(s[1].valid, 0b101);
        assert_eq!(c.non_finite, 1);
        assert_eq!(c.saturated, 3);
        assert_eq!(c.below_noise, 3);
        assert_eq!(c.excluded, 3);
        assert_eq!(c.used, 5);
    }
}
