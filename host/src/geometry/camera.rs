//! OpenCV pinhole camera with radial-tangential distortion `[k1, k2, p1, p2, k3]`.
use super::{V3, normalize};
use crate::dataset::CameraSpec;

/// A calibrated camera: world → pixel and pixel → world ray.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    dist: [f64; 5],
    r: [[f64; 3]; 3],
    t: V3,
}

impl Camera {
    /// The camera of a dataset's description.
    pub fn new(spec: &CameraSpec) -> Camera {
        let mut dist = [0.0; 5];
        if let Some(d) = &spec.distortion {
            for (k, v) in d.iter().take(5).enumerate() {
                dist[k] = *v;
            }
        }
        let m = &spec.camera_from_world;
        Camera {
            width: spec.width,
            height: spec.height,
            fx: spec.fx,
            fy: spec.fy,
            cx: spec.cx,
            cy: spec.cy,
            dist,
            r: [
                [m[0][0], m[0][1], m[0][2]],
                [m[1][0], m[1][1], m[1][2]],
                [m[2][0], m[2][1], m[2][2]],
            ],
            t: [m[0][3], m[1][3], m[2][3]],
        }
    }

    /// Camera centre in the world frame, `-Rᵀ·t`.
    pub fn center(&self) -> V3 {
        let r = &self.r;
        let t = self.t;
        [
            -(r[0][0] * t[0] + r[1][0] * t[1] + r[2][0] * t[2]),
            -(r[0][1] * t[0] + r[1][1] * t[1] + r[2][1] * t[2]),
            -(r[0][2] * t[0] + r[1][2] * t[1] + r[2][2] * t[2]),
        ]
    }

    fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Pixel coordinates of a world point; `None` behind the camera.
    pub fn project(&self, p: V3) -> Option<[f64; 2]> {
        let r = &self.r;
        let c = [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + self.t[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + self.t[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + self.t[2],
        ];
        if c[2].is_nan() || c[2] <= 0.0 {
            return None;
        }
        let (x, y) = self.distort(c[0] / c[2], c[1] / c[2]);
        let uv = [self.fx * x + self.cx, self.fy * y + self.cy];
        (uv[0].is_finite() && uv[1].is_finite()).then_some(uv)
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
        if self.dist != [0.0; 5] {
            for _ in 0..50 {
                let (dx, dy) = self.distort(x, y);
                let (ex, ey) = (dx - xd, dy - yd);
                x -= ex;
                y -= ey;
                if ex.abs() + ey.abs() < 1e-15 {
                    break;
                }
            }
        }
        let r = &self.r;
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

    fn spec(distortion: Option<Vec<f64>>) -> CameraSpec {
        let (s, c) = 20f64.to_radians().sin_cos();
        CameraSpec {
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
            let cam = Camera::new(&spec(d));
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
        let cam = Camera::new(&spec(None));
        let (o, d) = cam.ray(63.2, 48.1).unwrap();
        assert!(dist(o, cam.center()) < 1e-12);
        // The optical axis maps back to the principal point; behind the camera projects to None.
        let p = add_scaled(o, 100.0, d);
        let uv = cam.project(p).unwrap();
        assert!((uv[0] - 63.2).abs() < 1e-9 && (uv[1] - 48.1).abs() < 1e-9);
        assert!(cam.project(add_scaled(o, -100.0, d)).is_none());
    }
}
