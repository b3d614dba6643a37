//! Samples s(x_i, x_o) of one frame (section 4.1/5): for each vertex x_o the camera sees, the
//! pixel value at its projection (bilinear) divided by the exposure, per channel.
//!
//! A sample is dropped — and counted — when it is below the noise floor, clipped, non-finite, or
//! closer to x_i than the exclusion radius (first-surface reflection and single scattering
//! dominate there, section 5), or when its bilinear neighbourhood lies where the laser spot's
//! own light, in the image, is above the noise floor. The spot is spread in the image (optics,
//! sensor), not on the surface: seen at an angle, its light reaches samples well beyond the
//! exclusion radius (up to 30 times the scattered light was measured there).
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
    /// Cosine of the largest angle between normal and view direction (grazing rejection). A
    /// pixel's footprint on the surface grows as `1 / cos`, and close to the silhouette the
    /// bilinear neighbourhood mixes in the background: at 0.5 the footprint is at most twice
    /// the frontal one (on the built-in sphere, samples at cos 0.2–0.3 were off by up to 15 %
    /// in ground truth, those above 0.5 by 0.6 % RMS).
    pub cos_min: f64,
}

impl Default for SampleOptions {
    fn default() -> Self {
        SampleOptions {
            exclusion_radius_mm: 0.5,
            noise_floor: 0.0,
            saturation: None,
            cos_min: 0.5,
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
    /// Within the exclusion radius of x_i, or inside the laser spot's light in the image.
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
    let spot = spot_exclusion(img, frame, opts);
    for vis in visible {
        let x_o = positions[vis.vertex as usize];
        let r = dist(x_o, x_i);
        let in_spot = spot
            .is_some_and(|(u, v, reach)| (vis.u - u).powi(2) + (vis.v - v).powi(2) < reach * reach);
        if r < opts.exclusion_radius_mm || in_spot {
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

/// The laser spot in the frame and how far (pixels) from its centre a sample is affected: the
/// spot's reach down to the noise floor ([`crate::registration::Spot::reach_px`]; with no floor,
/// down to 1e-6 of its peak) plus the bilinear neighbourhood (√2 px).
fn spot_exclusion(img: &Image, frame: &FrameSpec, opts: &SampleOptions) -> Option<(f64, f64, f64)> {
    let spot = crate::registration::detect_spot(img, 0.0, opts.saturation)?;
    // Floor in the spot's units: raw, summed over channels.
    let floor_raw = opts.noise_floor * frame.exposure_s * img.channels as f64;
    let floor = floor_raw.max(1e-6 * spot.peak_fit);
    Some((
        spot.u,
        spot.v,
        spot.reach_px(floor) + std::f64::consts::SQRT_2,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::FrameChannel;

    #[test]
    fn each_rejection_rule_is_applied_and_counted() {
        let mut img = Image::new(16, 1, 3);
        // Pixel 0: fine; 1: NaN in green; 2: clipped; 3: dark; 13: fine but next to the laser
        // spot at 14.
        img.data[..3].copy_from_slice(&[1.0, 1.0, 1.0]);
        img.data[3..6].copy_from_slice(&[1.0, f32::NAN, 1.0]);
        img.data[6..9].copy_from_slice(&[50.0, 50.0, 50.0]);
        img.data[9..12].copy_from_slice(&[1e-6, 1e-6, 1e-6]);
        img.data[39..42].copy_from_slice(&[1.0, 1.0, 1.0]);
        img.data[42..45].copy_from_slice(&[1000.0, 1000.0, 1000.0]);
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
            [5.0, 0.0, 0.0],
        ];
        let vis: Vec<Visible> = (0..6)
            .map(|k| Visible {
                vertex: k,
                u: if k == 5 { 13.0 } else { (k % 4) as f64 },
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
        // Vertex 4 by the exclusion radius, vertex 5 by the spot's light in the image.
        assert_eq!(c.excluded, 6);
        assert_eq!(c.used, 5);
    }

    #[test]
    fn the_spot_reaches_as_far_as_its_light_exceeds_the_floor() {
        let spot = crate::registration::Spot {
            u: 0.0,
            v: 0.0,
            peak: 100.0,
            saturated: false,
            peak_fit: 100.0,
            sigma_px: 0.8,
        };
        // 100·exp(-d²/(2σ²)) = 1e-2 at d = σ·sqrt(2 ln 1e4).
        let d = spot.reach_px(1e-2);
        assert!((d - 0.8 * (2.0 * 1e4f64.ln()).sqrt()).abs() < 1e-12);
        assert_eq!(spot.reach_px(1e3), 0.0);
    }
}
