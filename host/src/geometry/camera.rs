//! The one camera model: exactly a `cameras[]` entry of `scan.json` (`docs/scan-format.md`), the
//! OpenCV pinhole camera with radial-tangential distortion `[k1, k2, p1, p2, k3]`.
//!
//! Calibration writes it (`calib.json`), scans and simulations write it to `scan.json`,
//! processing projects through it, the renderer rasterises through it. Framing helpers (the
//! renderer's field-of-view look-at and automatic framing) build it with [`Camera::look_at`].
use serde::{Deserialize, Serialize};

use super::{V3, cross, dot, normalize, sub};

/// A calibrated camera: world → pixel and pixel → world ray. Camera coordinates: x right, y
/// down, z forward; pixel centres at integer coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length in pixels along x.
    pub fx: f64,
    /// Focal length in pixels along y.
    pub fy: f64,
    /// Principal point x (pixel centres at integer coordinates).
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
    /// OpenCV distortion `[k1, k2, p1, p2, k3]` (`k3` may be left out; absent: none). Kept as
    /// written, so a dataset's `scan.json` round-trips unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<Vec<f64>>,
    /// Row-major 4x4 matrix taking world points to camera coordinates.
    pub camera_from_world: [[f64; 4]; 4],
}

impl Camera {
    /// A distortion-free camera at `eye` looking at `target` with `up` pointing up in the image:
    /// focal length `f` pixels, principal point at the image centre. `None` when `eye` and
    /// `target` coincide or `up` is parallel to the view direction.
    pub fn look_at(eye: V3, target: V3, up: V3, f: f64, width: u32, height: u32) -> Option<Camera> {
        let z = normalize(sub(target, eye))?;
        let x = normalize(cross(z, up))?;
        let y = cross(z, x);
        let row = |a: V3| [a[0], a[1], a[2], -dot(a, eye)];
        Some(Camera {
            width,
            height,
            fx: f,
            fy: f,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
            distortion: None,
            camera_from_world: [row(x), row(y), row(z), [0.0, 0.0, 0.0, 1.0]],
        })
    }

    /// Why this camera is unusable, if it is: zero image size, non-positive or non-finite
    /// intrinsics, distortion not 4 or 5 finite numbers, extrinsics non-finite or with a last row
    /// other than `[0, 0, 0, 1]`.
    pub fn check(&self) -> Result<(), String> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if self.width == 0 || self.height == 0 {
            return Err("zero image size".into());
        }
        if !(finite(&[self.fx, self.fy, self.cx, self.cy]) && self.fx > 0.0 && self.fy > 0.0) {
            return Err("focal lengths must be positive and finite".into());
        }
        if let Some(d) = &self.distortion
            && (!(4..=5).contains(&d.len()) || !finite(d))
        {
            return Err("distortion must be 4 or 5 finite numbers".into());
        }
        let m = &self.camera_from_world;
        if !m.iter().all(|r| finite(r)) || m[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err("camera_from_world must be finite with last row [0,0,0,1]".into());
        }
        Ok(())
    }

    /// The distortion coefficients `[k1, k2, p1, p2, k3]`, zeros where left out.
    pub fn distortion_coefficients(&self) -> [f64; 5] {
        let mut d = [0.0; 5];
        if let Some(v) = &self.distortion {
            for (k, x) in v.iter().take(5).enumerate() {
                d[k] = *x;
            }
        }
        d
    }

    fn rotation(&self) -> [[f64; 3]; 3] {
        let m = &self.camera_from_world;
        [
            [m[0][0], m[0][1], m[0][2]],
            [m[1][0], m[1][1], m[1][2]],
            [m[2][0], m[2][1], m[2][2]],
        ]
    }

    fn translation(&self) -> V3 {
        let m = &self.camera_from_world;
        [m[0][3], m[1][3], m[2][3]]
    }

    /// Camera centre in the world frame, `-Rᵀ·t`.
    pub fn center(&self) -> V3 {
        let r = self.rotation();
        let t = self.translation();
        [
            -(r[0][0] * t[0] + r[1][0] * t[1] + r[2][0] * t[2]),
            -(r[0][1] * t[0] + r[1][1] * t[1] + r[2][1] * t[2]),
            -(r[0][2] * t[0] + r[1][2] * t[1] + r[2][2] * t[2]),
        ]
    }

    /// World point → camera coordinates.
    pub fn to_camera(&self, p: V3) -> V3 {
        let m = &self.camera_from_world;
        let r = |k: usize| m[k][0] * p[0] + m[k][1] * p[1] + m[k][2] * p[2] + m[k][3];
        [r(0), r(1), r(2)]
    }

    fn distort(d: &[f64; 5], x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = *d;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Camera coordinates → pixel coordinates (with distortion); `None` behind the camera.
    pub fn project_camera(&self, c: V3) -> Option<[f64; 2]> {
        if c[2].is_nan() || c[2] <= 0.0 {
            return None;
        }
        let (x, y) = Self::distort(&self.distortion_coefficients(), c[0] / c[2], c[1] / c[2]);
        let uv = [self.fx * x + self.cx, self.fy * y + self.cy];
        (uv[0].is_finite() && uv[1].is_finite()).then_some(uv)
    }

    /// Pixel coordinates of a world point; `None` behind the camera.
    pub fn project(&self, p: V3) -> Option<[f64; 2]> {
        self.project_camera(self.to_camera(p))
    }

    /// Is `(u, v)` inside the image (pixel areas included)?
    pub fn inside(&self, u: f64, v: f64) -> bool {
        u >= -0.5 && v >= -0.5 && u < self.width as f64 - 0.5 && v < self.height as f64 - 0.5
    }

    /// The world ray through pixel coordinates `(u, v)`: origin (camera centre) and unit
    /// direction. Distortion is inverted by fixed-point iteration as OpenCV's `undistortPoints`.
    pub fn ray(&self, u: f64, v: f64) -> Option<(V3, V3)> {
        let xd = (u - self.cx) / self.fx;
        let yd = (v - self.cy) / self.fy;
        let (mut x, mut y) = (xd, yd);
        let dist = self.distortion_coefficients();
        if dist != [0.0; 5] {
            for _ in 0..50 {
                let (dx, dy) = Self::distort(&dist, x, y);
                let (ex, ey) = (dx - xd, dy - yd);
                x -= ex;
                y -= ey;
                if ex.abs() + ey.abs() < 1e-15 {
                    break;
                }
            }
        }
        let r = self.rotation();
        let d = [
            r[0][0] * x + r[1][0] * y + r[2][0],
            r[0][1] * x + r[1][1] * y + r[2][1],
            r[0][2] * x + r[1][2] * y + r[2][2],
        ];
        Some((self.center(), normalize(d)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{add_scaled, dist};

    fn spec(distortion: Option<Vec<f64>>) -> Camera {
        let (s, c) = 20f64.to_radians().sin_cos();
        Camera {
            width: 128,
            height: 96,
            fx: 900.0,
            fy: 880.0,
            cx: 63.2,
            cy: 48.1,
            distortion,
            camera_from_world: [
                [1.0, 0.0, 0.0, 1.5],
                [0.0, -c, -s, 2.0],
                [0.0, s, -c, 300.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    }

    #[test]
    fn project_and_ray_are_inverse_with_distortion() {
        for d in [None, Some(vec![-0.2, 0.05, 0.001, -0.002, 0.01])] {
            let cam = spec(d);
            for (u, v) in [(0.0, 0.0), (63.0, 40.0), (127.0, 95.0), (10.3, 80.7)] {
                let (o, dir) = cam.ray(u, v).unwrap();
                let p = add_scaled(o, 280.0, dir);
                let back = cam.project(p).unwrap();
                assert!(
                    (back[0] - u).abs() < 1e-9 && (back[1] - v).abs() < 1e-9,
                    "{u} {v} {back:?}"
                );
            }
        }
    }

    #[test]
    fn centre_and_principal_point() {
        let cam = spec(None);
        let (o, d) = cam.ray(63.2, 48.1).unwrap();
        assert!(dist(o, cam.center()) < 1e-12);
        // The optical axis maps back to the principal point; behind the camera projects to None.
        let p = add_scaled(o, 100.0, d);
        let uv = cam.project(p).unwrap();
        assert!((uv[0] - 63.2).abs() < 1e-9 && (uv[1] - 48.1).abs() < 1e-9);
        assert!(cam.project(add_scaled(o, -100.0, d)).is_none());
    }

    #[test]
    fn look_at_centres_the_target_with_up_up() {
        let c =
            Camera::look_at([0.0, -100.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0], 50.0, 64, 48).unwrap();
        let p = c.project([0.0; 3]).unwrap();
        assert!((p[0] - 31.5).abs() < 1e-9 && (p[1] - 23.5).abs() < 1e-9);
        assert!(c.project([0.0, 0.0, 10.0]).unwrap()[1] < 23.5);
        assert!(c.project([10.0, 0.0, 0.0]).unwrap()[0] > 31.5);
        assert!(dist(c.center(), [0.0, -100.0, 0.0]) < 1e-9);
        assert!(c.check().is_ok());
        assert!(Camera::look_at([0.0; 3], [0.0; 3], [0.0, 0.0, 1.0], 50.0, 8, 8).is_none());
        assert!(Camera::look_at([0.0, 0.0, 9.0], [0.0; 3], [0.0, 0.0, 1.0], 50.0, 8, 8).is_none());
    }

    #[test]
    fn scan_json_cameras_round_trip_unchanged() {
        for text in [
            r#"{"width":8,"height":8,"fx":1.0,"fy":1.0,"cx":3.5,"cy":3.5,"camera_from_world":[[1.0,0.0,0.0,0.0],[0.0,1.0,0.0,0.0],[0.0,0.0,1.0,0.0],[0.0,0.0,0.0,1.0]]}"#,
            r#"{"width":8,"height":8,"fx":1.0,"fy":1.0,"cx":3.5,"cy":3.5,"distortion":[0.1,0.0,0.0,0.0],"camera_from_world":[[1.0,0.0,0.0,0.0],[0.0,1.0,0.0,0.0],[0.0,0.0,1.0,0.0],[0.0,0.0,0.0,1.0]]}"#,
        ] {
            let c: Camera = serde_json::from_str(text).unwrap();
            assert!(c.check().is_ok());
            assert_eq!(serde_json::to_string(&c).unwrap(), text);
        }
    }
}
