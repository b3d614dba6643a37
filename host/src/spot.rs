//! Registration: find the laser spot in a frame with sub-pixel accuracy and back-project it onto
//! the mesh at the frame's turntable angle to obtain the light position `x_i` (section 4.1: "the
//! spot location in captured images is determined with sub-pixel accuracy"; section 5).
//!
//! Pure: takes an image and geometry, returns data. Frames without a spot on the object are a
//! [`RegistrationOutcome`], not an error.
use crate::dataset::{FrameSpec, Image};
use crate::geometry::{Camera, Hit, Scene, V3, dist};

/// Cosine of the largest angle between the surface normal at the laser's hit and the direction
/// to the camera at which the spot still counts as seen. Beyond it (and when the hit is
/// occluded) the camera cannot see the spot: the brightest pixel is then scattered light next to
/// the limb, and back-projecting it misplaces x_i by several mean free paths. At grazing angles
/// the back-projection also magnifies the sub-pixel error by `1 / cos`. Same limit as the
/// samples' grazing rejection (`SampleOptions::cos_min`).
/// It is the fit's default (`PipelineOptions::spot_cos_min`): registration itself keeps spots
/// down to [`SPOT_COS_FLOOR`], and whether the frames between the two help the model is the fit's
/// choice (cross-validated, `crate::crossval`), not a constant of registration.
pub const SPOT_COS_MIN: f64 = 0.2;

/// The most grazing view of the spot registration accepts (cos θ, about 84 degrees): below it
/// the spot is foreshortened more than tenfold and its sub-pixel error magnified as much. Frames
/// between this and a fit's `spot_cos_min` are registered and sampled (the store holds them)
/// and the fit decides whether to use them ([`spot_cos`]).
pub const SPOT_COS_FLOOR: f64 = 0.1;

/// Settings of spot detection.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SpotOptions {
    /// Smallest peak radiance (pixel / exposure, summed over channels) that counts as a spot.
    pub min_peak: f64,
    /// Raw pixel value at which the sensor clips (`None`: never).
    pub saturation: Option<f64>,
    /// Largest accepted distance (mm) between the detected `x_i` and the hit of the frame's
    /// `laser` ray; farther frames are flagged and not used.
    pub laser_tolerance_mm: f64,
}

impl Default for SpotOptions {
    fn default() -> Self {
        SpotOptions {
            min_peak: 0.0,
            saturation: None,
            laser_tolerance_mm: 2.0,
        }
    }
}

/// A detected spot in pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Spot {
    /// Sub-pixel column coordinate.
    pub u: f64,
    /// Sub-pixel row coordinate.
    pub v: f64,
    /// Peak value (summed over channels, raw).
    pub peak: f64,
    /// Whether the spot's centre was clipped.
    pub saturated: bool,
    /// Peak of the fitted Gaussian (summed over channels, raw): `peak` for an unclipped spot,
    /// the extrapolated top of a clipped one.
    pub peak_fit: f64,
    /// Standard deviation of the spot as a Gaussian, pixels (from the same log-quadratic fit as
    /// the centre): how far its own light reaches into the samples around it.
    pub sigma_px: f64,
}

/// What registration concluded about a frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum RegistrationOutcome {
    /// The spot lies on the object at `x_i` (object frame).
    Registered {
        /// Eq. 1: the light position x_i, object frame, mm.
        x_i: V3,
        /// Triangle of the mesh that holds `x_i`.
        triangle: u32,
        /// Distance to the hit of the frame's `laser` ray, if the frame has one and it hits.
        laser_disagreement_mm: Option<f64>,
        /// The spot x_i was found at: later stages exclude its light from the samples with it
        /// rather than detecting it again.
        spot: Spot,
    },
    /// No pixel is bright enough to be the spot.
    NoSpot,
    /// The spot's viewing ray misses the mesh.
    SpotOffObject,
    /// The spot and the `laser` ray disagree by more than the tolerance (or the ray misses).
    LaserMismatch {
        /// The detected light position.
        x_i: V3,
        /// Distance to the laser ray's hit; `None` if the ray misses the mesh.
        disagreement_mm: Option<f64>,
    },
}

impl RegistrationOutcome {
    /// Why a frame was not registered, in words (`None` for a registered one).
    pub fn why_not(&self) -> Option<String> {
        match self {
            RegistrationOutcome::Registered { .. } => None,
            RegistrationOutcome::NoSpot => Some(
                "no laser spot seen (nothing bright enough, or the laser hits where the camera cannot see)"
                    .into(),
            ),
            RegistrationOutcome::SpotOffObject => {
                Some("the spot's viewing ray misses the mesh".into())
            }
            RegistrationOutcome::LaserMismatch {
                disagreement_mm, ..
            } => Some(match disagreement_mm {
                Some(d) => format!("the spot lies {d:.2} mm from the laser ray's hit"),
                None => "the laser ray misses the mesh".into(),
            }),
        }
    }
}

fn luminance(img: &Image, i: usize, j: usize) -> f64 {
    let k = (j * img.width + i) * img.channels;
    let s: f64 = img.data[k..k + img.channels]
        .iter()
        .map(|v| *v as f64)
        .sum();
    if s.is_finite() { s } else { f64::NAN }
}

/// Finds the laser spot: the brightest finite pixel, refined to sub-pixel accuracy.
///
/// Unclipped spots: a Gaussian through the peak and its two neighbours per axis, fitted in log
/// space (exact for a Gaussian spot). Clipped spots: the centroid of the clipped plateau refined
/// by a least-squares log-quadratic (circular Gaussian) through the unclipped pixels around it.
/// Hand-written because it is the product's accuracy: no maintained crate does sub-pixel laser
/// spot detection on float images.
pub fn detect_spot(img: &Image, min_peak: f64, saturation: Option<f64>) -> Option<Spot> {
    let (w, h) = (img.width, img.height);
    let mut best = (f64::NEG_INFINITY, 0, 0);
    for j in 0..h {
        for i in 0..w {
            let l = luminance(img, i, j);
            if l > best.0 {
                best = (l, i, j);
            }
        }
    }
    let (peak, pi, pj) = best;
    if !(peak > min_peak && peak > 0.0) {
        return None;
    }
    let sat_level = saturation.map(|s| s * img.channels as f64 * 0.999);
    let clipped = |l: f64| sat_level.is_some_and(|s| l >= s);
    if !clipped(peak) {
        let at = |i: isize, j: isize| -> Option<f64> {
            if i < 0 || j < 0 || i >= w as isize || j >= h as isize {
                return None;
            }
            let l = luminance(img, i as usize, j as usize);
            (l > 0.0).then(|| l.ln())
        };
        let (ci, cj) = (pi as isize, pj as isize);
        let l0 = peak.ln();
        // (offset, second difference of ln L) per axis; a Gaussian has -1/σ² there.
        let refine = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => {
                let den = a - 2.0 * l0 + b;
                if den < 0.0 {
                    ((0.5 * (a - b) / den).clamp(-0.5, 0.5), Some(den))
                } else {
                    (0.0, None)
                }
            }
            _ => (0.0, None),
        };
        let (du, cu) = refine(at(ci - 1, cj), at(ci + 1, cj));
        let (dv, cv) = refine(at(ci, cj - 1), at(ci, cj + 1));
        // The wider axis (a spot seen at an angle is elongated); one pixel if nothing curves.
        let sigma_px = [cu, cv]
            .iter()
            .flatten()
            .map(|c| (-1.0 / c).sqrt())
            .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))))
            .unwrap_or(1.0);
        return Some(Spot {
            u: pi as f64 + du,
            v: pj as f64 + dv,
            peak,
            saturated: false,
            peak_fit: peak,
            sigma_px,
        });
    }
    // Clipped: flood the plateau (bounded), then fit ln L = a + b·u + c·v + e·(u² + v²) through
    // the unclipped ring around it (weighted by L so faint, noise-dominated pixels count less).
    let limit = 64;
    let mut plateau = vec![(pi, pj)];
    let mut seen = std::collections::HashSet::from([(pi, pj)]);
    let mut k = 0;
    while k < plateau.len() && plateau.len() < limit * limit {
        let (i, j) = plateau[k];
        k += 1;
        for (di, dj) in [(-1isize, 0isize), (1, 0), (0, -1), (0, 1)] {
            let (ni, nj) = (i as isize + di, j as isize + dj);
            if ni < 0 || nj < 0 || ni >= w as isize || nj >= h as isize {
                continue;
            }
            let q = (ni as usize, nj as usize);
            if seen.insert(q) && clipped(luminance(img, q.0, q.1)) {
                plateau.push(q);
            }
        }
    }
    let n = plateau.len() as f64;
    let cu = plateau.iter().map(|p| p.0 as f64).sum::<f64>() / n;
    let cv = plateau.iter().map(|p| p.1 as f64).sum::<f64>() / n;
    let rad = ((n / std::f64::consts::PI).sqrt() + 3.0).ceil() as isize;
    let mut ata = [[0.0f64; 4]; 4];
    let mut atb = [0.0f64; 4];
    let mut used = 0;
    let sat = sat_level.unwrap_or(f64::INFINITY);
    for j in (cv.round() as isize - rad)..=(cv.round() as isize + rad) {
        for i in (cu.round() as isize - rad)..=(cu.round() as isize + rad) {
            if i < 0 || j < 0 || i >= w as isize || j >= h as isize {
                continue;
            }
            let l = luminance(img, i as usize, j as usize);
            if !(l > 0.02 * sat && l < sat) {
                continue;
            }
            let (x, y) = (i as f64 - cu, j as f64 - cv);
            let row = [1.0, x, y, x * x + y * y];
            let wgt = l / sat;
            for a in 0..4 {
                for b in 0..4 {
                    ata[a][b] += wgt * row[a] * row[b];
                }
                atb[a] += wgt * row[a] * l.ln();
            }
            used += 1;
        }
    }
    let (mut u, mut v) = (cu, cv);
    // Without a usable fit: the plateau's radius.
    let mut sigma_px = (n / std::f64::consts::PI).sqrt().max(1.0);
    let mut peak_fit = peak;
    if used >= 6
        && let Some(sol) = solve4(ata, atb)
        && sol[3] < 0.0
    {
        // ln L = … + e·ρ² with e = -1/(2σ²).
        sigma_px = (-0.5 / sol[3]).sqrt();
        let (du, dv) = (-sol[1] / (2.0 * sol[3]), -sol[2] / (2.0 * sol[3]));
        // The extrapolated top, trusted up to 100× the clipping level (a poorly constrained
        // ring fit extrapolates without bound, and would then claim the whole image).
        let top = (sol[0] + sol[1] * du + sol[2] * dv + sol[3] * (du * du + dv * dv)).exp();
        if top.is_finite() && top > peak {
            peak_fit = top.min(100.0 * peak);
        }
        // Trust the refinement only inside the plateau's extent.
        if du.abs() <= 1.0 + (n.sqrt()) && dv.abs() <= 1.0 + n.sqrt() {
            u += du;
            v += dv;
        }
    }
    Some(Spot {
        u,
        v,
        peak,
        saturated: true,
        peak_fit,
        sigma_px,
    })
}

fn solve4(mut a: [[f64; 4]; 4], mut b: [f64; 4]) -> Option<[f64; 4]> {
    for c in 0..4 {
        let p = (c..4).max_by(|&x, &y| a[x][c].abs().total_cmp(&a[y][c].abs()))?;
        if a[p][c].abs() < 1e-300 {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        let pivot = a[c];
        for r in c + 1..4 {
            let f = a[r][c] / pivot[c];
            for (x, p) in a[r].iter_mut().zip(pivot).skip(c) {
                *x -= f * p;
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = [0.0; 4];
    for c in (0..4).rev() {
        let s: f64 = (c + 1..4).map(|k| a[c][k] * x[k]).sum();
        x[c] = (b[c] - s) / a[c][c];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Whether the camera can see the point `hit` (object frame, turntable at `deg`): the one
/// visibility rule ([`Scene::sees`]) with the interpolated vertex normal (as shading sees it) and
/// the grazing limit [`SPOT_COS_MIN`]. The scan planner predicts registration with this very
/// function, so a plan's "seen" is processing's "registered".
pub fn spot_visible(scene: &Scene, camera: &Camera, deg: f64, hit: &Hit) -> bool {
    spot_visible_at(scene, camera, deg, hit, SPOT_COS_MIN)
}

/// [`spot_visible`] with the grazing limit `cos_min`.
pub fn spot_visible_at(scene: &Scene, camera: &Camera, deg: f64, hit: &Hit, cos_min: f64) -> bool {
    scene
        .normal_at(hit.triangle, hit.point)
        .and_then(|n| scene.sees(camera, deg, hit.point, n, cos_min))
        .is_some()
}

/// cos θ of the camera's view of a frame's spot: between the interpolated normal and the
/// direction to the camera centre, at the laser's hit when the frame has a laser ray that hits
/// the mesh (the point [`register_frame`]'s visibility rule judges), else at the registered
/// x_i on triangle `triangle`. `None` where the normal degenerates.
pub fn spot_cos(
    scene: &Scene,
    frame: &FrameSpec,
    camera: &Camera,
    x_i: V3,
    triangle: u32,
) -> Option<f64> {
    let deg = frame.turntable_deg;
    let (p, tri) = frame
        .laser
        .as_ref()
        .and_then(|l| scene.cast_world(l.origin, l.direction, deg))
        .map_or((x_i, triangle), |h| (h.point, h.triangle));
    let n = scene.normal_at(tri, p)?;
    let c = crate::geometry::world_to_turntable(camera.center(), deg);
    let to_cam = crate::geometry::normalize(crate::geometry::sub(c, p))?;
    let cos = crate::geometry::dot(n, to_cam);
    cos.is_finite().then_some(cos)
}

/// Registers one frame: detect the spot, back-project it onto the mesh at the frame's turntable
/// angle, cross-check with the frame's `laser` ray.
///
/// A frame whose `laser` ray hits the mesh where the camera cannot see it ([`spot_visible_at`]
/// with [`SPOT_COS_FLOOR`]: occluded, or more grazing than that) has
/// [`RegistrationOutcome::NoSpot`]: whatever is brightest in it is scattered light, not the spot,
/// and would be registered up to the laser tolerance away from the true x_i.
///
/// Measured on `shared/data/sample-torus`: of its 96 training frames 24 have a laser
/// ray that misses the mesh and 16 a hit the camera cannot see — none of them for the grazing
/// limit (cos θ = 0.64 at every one) but because the near tube hides the hit: the line of sight
/// from the camera meets the near tube 16.8 mm before the hit. Their brightest pixel is the spot's
/// glow past the near tube's limb and back-projects within 0.32–0.35 mm of the laser's hit (the
/// registered frames: median 0.16 mm, at most 0.37 mm), so they *could* be registered, with x_i
/// either from the glow or from the laser ray. Their samples disagree with every other frame's:
/// with them, the homogeneous baseline's log E over the training frames rose from 0.66 to 1.03
/// (the far tube seen past the near one's silhouette, next to a half-hidden spot whose light the
/// spot exclusion cannot model). So a hidden hit stays `NoSpot`. The rule is part of the
/// evaluation protocol (docs/validation.md), not a fit setting: it decides which frames have an
/// observable x_i at all, so no held-out error can compare it (the frames judged would differ).
///
/// Second: the spot detected in the image, whatever the mesh made of it (also for a hidden
/// hit, `NoSpot`, and for `SpotOffObject` and `LaserMismatch`): the mesh-free evidence that the
/// mesh sits where the scan saw the object ([`crate::align::check_spots`]).
pub fn register_frame_detected(
    img: &Image,
    frame: &FrameSpec,
    camera: &Camera,
    scene: &Scene,
    opts: &SpotOptions,
) -> (RegistrationOutcome, Option<Spot>) {
    let min_peak = opts.min_peak * frame.exposure_s;
    let detected = detect_spot(img, min_peak, opts.saturation);
    if let Some(l) = &frame.laser
        && let Some(h) = scene.cast_world(l.origin, l.direction, frame.turntable_deg)
        && !spot_visible_at(scene, camera, frame.turntable_deg, &h, SPOT_COS_FLOOR)
    {
        return (RegistrationOutcome::NoSpot, detected);
    }
    let Some(spot) = detected else {
        return (RegistrationOutcome::NoSpot, None);
    };
    let Some((o, d)) = camera.ray(spot.u, spot.v) else {
        return (RegistrationOutcome::SpotOffObject, detected);
    };
    let Some(hit) = scene.cast_world(o, d, frame.turntable_deg) else {
        return (RegistrationOutcome::SpotOffObject, detected);
    };
    let x_i = hit.point;
    let mut disagreement = None;
    if let Some(l) = &frame.laser {
        let lh = scene.cast_world(l.origin, l.direction, frame.turntable_deg);
        disagreement = lh.map(|h| dist(h.point, x_i));
        if disagreement.is_none_or(|dd| dd > opts.laser_tolerance_mm) {
            return (
                RegistrationOutcome::LaserMismatch {
                    x_i,
                    disagreement_mm: disagreement,
                },
                detected,
            );
        }
    }
    (
        RegistrationOutcome::Registered {
            x_i,
            triangle: hit.triangle,
            laser_disagreement_mm: disagreement,
            spot,
        },
        detected,
    )
}

/// [`register_frame_detected`]'s outcome alone.
pub fn register_frame(
    img: &Image,
    frame: &FrameSpec,
    camera: &Camera,
    scene: &Scene,
    opts: &SpotOptions,
) -> RegistrationOutcome {
    register_frame_detected(img, frame, camera, scene, opts).0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaussian(w: usize, u0: f64, v0: f64, sigma: f64, amp: f64, sat: Option<f64>) -> Image {
        let mut img = Image::new(w, w, 3);
        for j in 0..w {
            for i in 0..w {
                let r2 = (i as f64 - u0).powi(2) + (j as f64 - v0).powi(2);
                let mut val = amp * (-r2 / (2.0 * sigma * sigma)).exp() + 1e-6;
                if let Some(s) = sat {
                    val = val.min(s);
                }
                for c in 0..3 {
                    img.data[(j * w + i) * 3 + c] = val as f32;
                }
            }
        }
        img
    }

    #[test]
    fn unclipped_spots_are_found_to_a_hundredth_of_a_pixel() {
        for (u0, v0) in [(10.0, 12.0), (10.3, 12.45), (20.49, 5.2)] {
            let s = detect_spot(&gaussian(32, u0, v0, 0.8, 100.0, None), 0.0, None).unwrap();
            assert!(
                (s.u - u0).abs() < 1e-2 && (s.v - v0).abs() < 1e-2,
                "{s:?} {u0} {v0}"
            );
            assert!(!s.saturated);
            assert!((s.sigma_px - 0.8).abs() < 0.01, "{s:?}");
        }
    }

    #[test]
    fn clipped_spots_are_found_to_a_tenth_of_a_pixel() {
        for (u0, v0) in [(16.0, 16.0), (15.3, 16.7), (12.8, 18.25)] {
            let img = gaussian(32, u0, v0, 1.2, 1000.0, Some(10.0));
            let s = detect_spot(&img, 0.0, Some(10.0)).unwrap();
            assert!(s.saturated);
            assert!((s.sigma_px - 1.2).abs() < 0.1, "{s:?}");
            assert!(
                (s.u - u0).abs() < 0.1 && (s.v - v0).abs() < 0.1,
                "{s:?} {u0} {v0}"
            );
        }
    }

    #[test]
    fn dark_or_nan_frames_have_no_spot() {
        let img = Image::new(8, 8, 3);
        assert!(detect_spot(&img, 0.0, None).is_none());
        let mut img = gaussian(16, 8.0, 8.0, 1.0, 1e-3, None);
        assert!(detect_spot(&img, 1.0, None).is_none());
        img.data.iter_mut().for_each(|v| *v = f32::NAN);
        assert!(detect_spot(&img, 0.0, None).is_none());
    }
}
