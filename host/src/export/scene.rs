//! The render set-up in Blender's terms (`scene.json`, read by `build_blend.py`), so that the
//! `.blend` shows what `subsurf render` shows for the same lights and camera.
//!
//! - **Units.** The model is in mm; Blender's unit is the metre (glTF's too). Every length is
//!   multiplied by [`METRES_PER_MM`]; the scene displays lengths in mm.
//! - **Lights.** The renderer's point light of intensity I gives irradiance `I cos θ / d²` (d in
//!   mm); Cycles' point light of power P watts gives `P / (4π) · cos θ / d²` (d in m: measured,
//!   a white Lambertian plate 2 m under 1000 W renders 1000/(16π²)). So
//!   `P = 4π I · (0.001)²`, colour `I / max(I)`, radius 0 (a true point). A directional light of
//!   irradiance E is a sun of strength E W/m² (a plate facing it renders E/π), angle 0. A spot is
//!   a Blender spot of the same cone (`spot_size` twice the half-angle) with its smooth edge
//!   mapped from angles to Cycles' cosines; Cycles 3.4 also weights a spot by the cosine of the
//!   angle to its axis (`spot_light_attenuation`), which the renderer does not.
//! - **Camera.** [`crate::geometry::Camera`] (OpenCV: x right, y down, z forward; pixel centres
//!   at integers) becomes a Blender camera looking down its −z with +y up: the same rotation with
//!   y and z negated; focal length `fx · sensor width / width` with the sensor fitted
//!   horizontally; the principal point's offset from the image centre as lens shift, in units of
//!   the width (`shift_x = ((w − 1)/2 − cx)/w`, `shift_y = (cy − (h − 1)/2)/w`). Lens
//!   distortion and non-square pixels have no Blender counterpart and are refused.

use serde::Serialize;

use super::ExportError;
use crate::geometry::Camera;
use crate::render::Light;

/// Metres per model unit (the model file is in mm).
pub const METRES_PER_MM: f64 = 1e-3;

/// Blender's default sensor width, mm (any width gives the same picture: the lens scales with it).
const SENSOR_MM: f64 = 36.0;

/// A light as `build_blend.py` creates it.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "type", rename_all = "SCREAMING_SNAKE_CASE")]
pub enum BlenderLight {
    /// `bpy.types.PointLight`, radius 0.
    Point {
        /// World matrix, metres.
        matrix_world: [[f64; 4]; 4],
        /// `energy`, watts.
        power: f64,
        /// `color`, linear RGB.
        colour: [f64; 3],
    },
    /// `bpy.types.SpotLight`, radius 0.
    Spot {
        /// World matrix (−z along the axis), metres.
        matrix_world: [[f64; 4]; 4],
        /// `energy`, watts.
        power: f64,
        /// `color`.
        colour: [f64; 3],
        /// `spot_size`, radians (the full cone angle).
        spot_size: f64,
        /// `spot_blend`.
        spot_blend: f64,
    },
    /// `bpy.types.SunLight`, angle 0.
    Sun {
        /// World matrix (−z along the direction light travels).
        matrix_world: [[f64; 4]; 4],
        /// `energy`: irradiance, W/m².
        strength: f64,
        /// `color`.
        colour: [f64; 3],
    },
}

/// The camera as `build_blend.py` creates it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BlenderCamera {
    /// World matrix (−z along the view, +y up), metres.
    pub matrix_world: [[f64; 4]; 4],
    /// `lens`, mm.
    pub lens: f64,
    /// `sensor_width`, mm (`sensor_fit = HORIZONTAL`).
    pub sensor_width: f64,
    /// `shift_x`, fractions of the image width.
    pub shift_x: f64,
    /// `shift_y`, fractions of the image width.
    pub shift_y: f64,
    /// `clip_start`, metres.
    pub clip_start: f64,
    /// `clip_end`, metres.
    pub clip_end: f64,
    /// `resolution_x`, pixels.
    pub width: u32,
    /// `resolution_y`, pixels.
    pub height: u32,
}

/// A rotation (columns = the local axes in world coordinates) and an origin in metres as a
/// row-major 4×4 world matrix.
fn matrix(cols: [[f64; 3]; 3], origin_mm: [f64; 3]) -> [[f64; 4]; 4] {
    let t = origin_mm.map(|x| x * METRES_PER_MM);
    [
        [cols[0][0], cols[1][0], cols[2][0], t[0]],
        [cols[0][1], cols[1][1], cols[2][1], t[1]],
        [cols[0][2], cols[1][2], cols[2][2], t[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn unit(a: [f64; 3]) -> Option<[f64; 3]> {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    (l > 1e-12 && l.is_finite()).then(|| a.map(|x| x / l))
}

/// A frame whose −z points along `dir` (a light's axis).
fn pointing(dir: [f64; 3], origin_mm: [f64; 3]) -> Option<[[f64; 4]; 4]> {
    let z = unit(dir.map(|x| -x))?;
    let helper = if z[2].abs() < 0.9 {
        [0.0, 0.0, 1.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let x = unit(cross(helper, z))?;
    let y = cross(z, x);
    Some(matrix([x, y, z], origin_mm))
}

/// `(power, colour)` of a Cycles point or spot light with the renderer's intensity `i`.
fn point_power(i: [f64; 3]) -> Option<(f64, [f64; 3])> {
    let max = i.iter().copied().fold(0.0, f64::max);
    (max > 0.0 && max.is_finite()).then(|| {
        (
            4.0 * std::f64::consts::PI * max * METRES_PER_MM * METRES_PER_MM,
            i.map(|x| x / max),
        )
    })
}

/// The renderer's lights as Blender lights; lights that emit nothing are left out.
pub fn lights(lights: &[Light]) -> Result<Vec<BlenderLight>, ExportError> {
    let mut out = Vec::new();
    for l in lights {
        match *l {
            Light::Point {
                position,
                intensity,
            } => {
                if let Some((power, colour)) = point_power(intensity) {
                    out.push(BlenderLight::Point {
                        matrix_world: matrix(
                            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                            position,
                        ),
                        power,
                        colour,
                    });
                }
            }
            Light::Spot {
                position,
                direction,
                inner,
                outer,
                intensity,
            } => {
                let Some((power, colour)) = point_power(intensity) else {
                    continue;
                };
                let m = pointing(direction, position)
                    .ok_or_else(|| ExportError::Invalid("a spot light has no direction".into()))?;
                // Cycles smooths over cos ∈ [cos outer, cos outer + (1 − cos outer)·blend].
                let (ci, co) = (inner.cos(), outer.cos());
                out.push(BlenderLight::Spot {
                    matrix_world: m,
                    power,
                    colour,
                    spot_size: 2.0 * outer,
                    spot_blend: ((ci - co) / (1.0 - co)).clamp(0.0, 1.0),
                });
            }
            Light::Directional {
                direction,
                irradiance,
            } => {
                let max = irradiance.iter().copied().fold(0.0, f64::max);
                if !(max > 0.0 && max.is_finite()) {
                    continue;
                }
                let m = pointing(direction, [0.0; 3]).ok_or_else(|| {
                    ExportError::Invalid("a directional light has no direction".into())
                })?;
                out.push(BlenderLight::Sun {
                    matrix_world: m,
                    strength: max,
                    colour: irradiance.map(|x| x / max),
                });
            }
        }
    }
    Ok(out)
}

/// The beam power, in Blender watts, that gives Cycles' radiance the scan's units for a laser
/// of power `flux` in the scan's units.
///
/// Why π and 10⁻⁶: a model's R_d is fitted to samples s = pixel / exposure_s, so it is the
/// radiance at x_o per unit of laser power as the scan measures it (the shared datasets: per
/// watt). Cycles' subsurface closure sends out `L(x_o) = R(r) Φ / π` for a beam of power Φ
/// (its plateau under irradiance E is `A E / π`, measured, docs/export.md), with R per m²
/// where R_d is per mm². So `Φ = π · flux · 10⁻⁶ W` makes Cycles' pixel / exposure_s the
/// model's s.
pub fn beam_watts(flux: f64) -> f64 {
    std::f64::consts::PI * flux * METRES_PER_MM * METRES_PER_MM
}

/// The beam power, in Blender watts, that gives a Cycles volume's radiance the scan's units
/// for a laser of power `flux` in the scan's units.
///
/// Why no π: a volume is rendered by its physics, so radiance is power per m² per steradian
/// as subsurf's tracer computes it per mm² (its images are the frames' units, checked against
/// Mitsuba 3 and sample-slab, docs/volume.md); only the area changes, 10⁻⁶ m² per mm².
pub fn volume_beam_watts(flux: f64) -> f64 {
    flux * METRES_PER_MM * METRES_PER_MM
}

/// A scan frame's laser as a Cycles spot light: a point `standoff_mm` before the hit
/// point `hit_mm` along the ray `direction` (world frame, mm), its cone just wide enough to
/// light a disk of radius `footprint_mm` there, carrying the beam power `watts` onto it.
///
/// Cycles 3.4 gives a spot of power P the intensity `P/(4π)` per steradian times the cosine
/// of the angle to its axis inside the cone (`spot_attenuation`), so the power through a cone
/// of half-angle θ is `P/(4π) · π sin²θ`: P = 4 · watts / sin²θ. The light is a point (radius
/// 0): no camera ray sees it.
pub fn laser_spot(
    hit_mm: [f64; 3],
    direction: [f64; 3],
    standoff_mm: f64,
    footprint_mm: f64,
    watts: f64,
) -> Result<BlenderLight, ExportError> {
    let d = unit(direction)
        .ok_or_else(|| ExportError::Invalid("the laser ray has no direction".into()))?;
    if !(standoff_mm > 0.0 && footprint_mm > 0.0 && watts > 0.0 && watts.is_finite()) {
        return Err(ExportError::Invalid(format!(
            "laser: standoff {standoff_mm} mm, footprint {footprint_mm} mm, power {watts} W"
        )));
    }
    let origin = [0, 1, 2].map(|k| hit_mm[k] - standoff_mm * d[k]);
    let half = (footprint_mm / standoff_mm).atan();
    let matrix_world = pointing(d, origin)
        .ok_or_else(|| ExportError::Invalid("the laser ray has no direction".into()))?;
    let power = 4.0 * watts / half.sin().powi(2);
    if !power.is_finite() {
        return Err(ExportError::Invalid(format!("laser power {power} W")));
    }
    Ok(BlenderLight::Spot {
        matrix_world,
        power,
        colour: [1.0; 3],
        spot_size: 2.0 * half,
        spot_blend: 0.0,
    })
}

/// The turntable's rotation R_z(θ) (docs/scan-format.md: a mesh point p sits at R_z(θ)·p) as a
/// Blender world matrix.
pub fn turntable_matrix(deg: f64) -> [[f64; 4]; 4] {
    let (s, c) = deg.to_radians().sin_cos();
    matrix([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]], [0.0; 3])
}

/// The camera in Blender's terms; `bounds` (mm) set the clipping range around the object.
pub fn camera(cam: &Camera, bounds: ([f64; 3], [f64; 3])) -> Result<BlenderCamera, ExportError> {
    cam.check()
        .map_err(|e| ExportError::Camera(format!("unusable camera: {e}")))?;
    if cam.distortion_coefficients().iter().any(|&k| k != 0.0) {
        return Err(ExportError::Camera(
            "the camera has lens distortion, which a Blender camera cannot reproduce".into(),
        ));
    }
    if ((cam.fx - cam.fy) / cam.fx).abs() > 1e-3 {
        return Err(ExportError::Camera(format!(
            "fx = {} and fy = {} differ: non-square pixels have no Blender camera",
            cam.fx, cam.fy
        )));
    }
    let m = &cam.camera_from_world;
    // Rows of the rotation are the camera axes in world coordinates.
    let axis = |r: usize| [m[r][0], m[r][1], m[r][2]];
    let (x, y, z) = (axis(0), axis(1), axis(2));
    let ortho = |a: [f64; 3], b: [f64; 3]| (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).abs();
    let norm = |a: [f64; 3]| (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    if ortho(x, y) > 1e-6
        || ortho(y, z) > 1e-6
        || ortho(x, z) > 1e-6
        || [x, y, z].iter().any(|a| (norm(*a) - 1.0).abs() > 1e-6)
    {
        return Err(ExportError::Camera(
            "camera_from_world is not a rotation and a translation".into(),
        ));
    }
    let eye = cam.center();
    let (w, h) = (cam.width as f64, cam.height as f64);
    // Blender: +x right, +y up, looking down −z: OpenCV's y and z negated.
    let neg = |a: [f64; 3]| a.map(|v| -v);
    let matrix_world = matrix([x, neg(y), neg(z)], eye);
    let (lo, hi) = bounds;
    let corners = (0..8).map(|k| {
        [
            if k & 1 == 0 { lo[0] } else { hi[0] },
            if k & 2 == 0 { lo[1] } else { hi[1] },
            if k & 4 == 0 { lo[2] } else { hi[2] },
        ]
    });
    let (mut near, mut far) = (f64::INFINITY, 0.0f64);
    for c in corners {
        let d = norm([c[0] - eye[0], c[1] - eye[1], c[2] - eye[2]]);
        near = near.min(d);
        far = far.max(d);
    }
    let size = norm([hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]]);
    let clip_start = (0.01 * (near - size).max(0.0)).max(1e-3 * size).max(1e-6) * METRES_PER_MM;
    let clip_end = (10.0 * far).max(1.0) * METRES_PER_MM;
    Ok(BlenderCamera {
        matrix_world,
        lens: cam.fx * SENSOR_MM / w,
        sensor_width: SENSOR_MM,
        shift_x: ((w - 1.0) / 2.0 - cam.cx) / w,
        shift_y: (cam.cy - (h - 1.0) / 2.0) / w,
        clip_start,
        clip_end,
        width: cam.width,
        height: cam.height,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The camera's axes: Blender's −z is the view direction, +y is up in the picture (OpenCV's
    /// −y), the eye in metres; the centred principal point is no shift.
    #[test]
    fn a_look_at_camera_becomes_a_blender_camera_looking_the_same_way() {
        let cam = Camera::look_at_fov([0.0, -200.0, 50.0], [0.0; 3], [0.0, 0.0, 1.0], 30.0, 64, 48)
            .unwrap();
        let b = camera(&cam, ([-10.0; 3], [10.0; 3])).unwrap();
        let m = b.matrix_world;
        let col = |k: usize| [m[0][k], m[1][k], m[2][k]];
        let view = col(2).map(|v| -v);
        let want = unit([0.0, 200.0, -50.0]).unwrap();
        for k in 0..3 {
            assert!((view[k] - want[k]).abs() < 1e-12);
        }
        assert!(col(1)[2] > 0.9, "up is +z: {:?}", col(1));
        assert!((m[1][3] + 0.2).abs() < 1e-12 && (m[2][3] - 0.05).abs() < 1e-12);
        assert_eq!((b.shift_x, b.shift_y), (0.0, 0.0));
        // Vertical field of view 30° on a 64 × 48 image: f = 24 / tan 15°.
        let f = 24.0 / 15f64.to_radians().tan();
        assert!((b.lens - f * 36.0 / 64.0).abs() < 1e-9);
        assert!(b.clip_start > 0.0 && b.clip_start < 0.19 && b.clip_end > 0.21);
        let mut d = cam.clone();
        d.distortion = Some(vec![0.1, 0.0, 0.0, 0.0]);
        assert!(camera(&d, ([-10.0; 3], [10.0; 3])).is_err());
    }

    /// The laser's spot: aimed along the ray, `standoff` before the hit point, its cone's
    /// footprint the one asked for, and the power through the cone (Cycles' cosine-weighted
    /// spot) the beam's.
    #[test]
    fn the_laser_spot_puts_the_beam_on_the_hit_point() {
        let hit = [1.0, 2.0, 3.0];
        let dir = [0.0, 0.6, -0.8];
        let l = laser_spot(hit, dir, 5.0, 0.2, beam_watts(2.0)).unwrap();
        let BlenderLight::Spot {
            matrix_world: m,
            power,
            spot_size,
            spot_blend,
            ..
        } = l
        else {
            panic!("{l:?}")
        };
        let origin = [m[0][3], m[1][3], m[2][3]].map(|x| x / METRES_PER_MM);
        for k in 0..3 {
            assert!(
                (origin[k] + 5.0 * dir[k] - hit[k]).abs() < 1e-9,
                "{origin:?}"
            );
            assert!((-m[k][2] - dir[k]).abs() < 1e-12, "−z along the ray");
        }
        let half = spot_size / 2.0;
        assert!((5.0 * half.tan() - 0.2).abs() < 1e-12);
        assert_eq!(spot_blend, 0.0);
        let through =
            power / (4.0 * std::f64::consts::PI) * std::f64::consts::PI * half.sin().powi(2);
        assert!((through - beam_watts(2.0)).abs() < 1e-18 + 1e-12 * through);
        assert!((beam_watts(1.0) - std::f64::consts::PI * 1e-6).abs() < 1e-18);
        assert!(laser_spot(hit, [0.0; 3], 5.0, 0.2, 1.0).is_err());
        assert!(laser_spot(hit, dir, 5.0, 0.2, f64::NAN).is_err());
        // The turntable turns +x towards +y.
        let t = turntable_matrix(90.0);
        assert!((t[1][0] - 1.0).abs() < 1e-12 && t[0][0].abs() < 1e-12);
    }

    /// 1 unit of point intensity at 1 mm is 1 unit of irradiance: 4π·10⁻⁶ W at 1 mm = 0.001 m
    /// gives 10⁻⁶/10⁻⁶ in Cycles' P/(4π d²).
    #[test]
    fn lights_carry_the_renderers_irradiance() {
        let ls = lights(&[
            "point:0,0,100:200,100,0".parse().unwrap(),
            "dir:0,0,-1:0.5,0.5,0.25".parse().unwrap(),
            "point:0,0,1:0,0,0".parse().unwrap(),
            "spot:0,0,100:0,0,-1:30".parse().unwrap(),
        ])
        .unwrap();
        assert_eq!(ls.len(), 3, "the dark light is left out");
        let BlenderLight::Point { power, colour, .. } = &ls[0] else {
            panic!("{ls:?}")
        };
        let e_at_100mm = power / (4.0 * std::f64::consts::PI * 0.1 * 0.1);
        assert!((e_at_100mm - 200.0 / 100.0 / 100.0).abs() < 1e-12);
        assert_eq!(*colour, [1.0, 0.5, 0.0]);
        let BlenderLight::Sun {
            strength,
            matrix_world,
            ..
        } = &ls[1]
        else {
            panic!()
        };
        assert_eq!(*strength, 0.5);
        assert!((matrix_world[2][2] - 1.0).abs() < 1e-12, "−z points down");
        let BlenderLight::Spot {
            spot_size,
            spot_blend,
            ..
        } = &ls[2]
        else {
            panic!()
        };
        assert!((spot_size - 60f64.to_radians()).abs() < 1e-12);
        assert!(*spot_blend > 0.0 && *spot_blend < 1.0);
    }
}
