//! Rig calibration: the camera (intrinsics, extrinsics), the turntable axis and the galvo model
//! (galvo codes → laser ray), all in one `calib.json`.
//!
//! Contract: everything is in millimetres and in the world frame of `docs/scan-format.md` (the
//! object frame at turntable angle 0: `+z` is the turntable axis, origin on the axis at the
//! platter). The scan writes each frame's `laser` ray from [`GalvoModel::ray`]. Fitting code here
//! never touches files except [`Calibration::load`] / [`Calibration::save`].

pub mod detect;
pub mod galvo;
mod lsq;
pub mod target;

pub use galvo::{GalvoModel, GalvoObservation, fit_galvo};

use serde::{Deserialize, Serialize};
use std::path::Path;

/// The format string of `calib.json`.
pub const CALIB_FORMAT: &str = "subsurf-calib/1";

/// Why a calibration could not be loaded, saved or computed. Every variant says what was missing.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CalibError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The JSON was malformed or had the wrong shape.
    #[error("{path}: not a calibration file: {source}")]
    Json {
        /// The file.
        path: String,
        /// The parser's message.
        source: serde_json::Error,
    },
    /// The file is well-formed but holds an unusable value.
    #[error("{0}")]
    Invalid(String),
    /// The calibration target was not found where it was needed.
    #[error("calibration target not found: {0}")]
    TargetNotFound(String),
    /// Not enough observations to determine the parameters.
    #[error("not enough data: {0}")]
    NotEnoughData(String),
    /// The solver did not reach a usable answer.
    #[error("calibration did not converge: {0}")]
    NotConverged(String),
}

/// An OpenCV pinhole camera, exactly the `cameras[]` entry of `scan.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length in pixels (x).
    pub fx: f64,
    /// Focal length in pixels (y).
    pub fy: f64,
    /// Principal point (x), pixel centres at integers.
    pub cx: f64,
    /// Principal point (y).
    pub cy: f64,
    /// OpenCV distortion `[k1, k2, p1, p2, k3]`.
    #[serde(default)]
    pub distortion: [f64; 5],
    /// World → camera, 4x4 row-major (x right, y down, z forward).
    pub camera_from_world: [[f64; 4]; 4],
}

impl CameraModel {
    /// The camera centre in the world frame (`-Rᵀ t`).
    pub fn centre_world(&self) -> [f64; 3] {
        let m = &self.camera_from_world;
        let t = [m[0][3], m[1][3], m[2][3]];
        let mut c = [0.0; 3];
        for (i, ci) in c.iter_mut().enumerate() {
            *ci = -(m[0][i] * t[0] + m[1][i] * t[1] + m[2][i] * t[2]);
        }
        c
    }

    /// World point → camera coordinates.
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        let m = &self.camera_from_world;
        let mut q = [0.0; 3];
        for (i, qi) in q.iter_mut().enumerate() {
            *qi = m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3];
        }
        q
    }

    /// Camera coordinates → pixel, with OpenCV distortion; `None` behind the camera.
    pub fn project_camera(&self, q: [f64; 3]) -> Option<[f64; 2]> {
        if q[2] <= 1e-9 {
            return None;
        }
        let (x, y) = (q[0] / q[2], q[1] / q[2]);
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        Some([self.fx * xd + self.cx, self.fy * yd + self.cy])
    }

    /// World point → pixel; `None` behind the camera.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        self.project_camera(self.to_camera(p))
    }

    /// Whether a pixel position lies on the sensor.
    pub fn in_image(&self, uv: [f64; 2]) -> bool {
        uv[0] >= -0.5
            && uv[1] >= -0.5
            && uv[0] < self.width as f64 - 0.5
            && uv[1] < self.height as f64 - 0.5
    }

    fn validate(&self) -> Result<(), CalibError> {
        let finite = [self.fx, self.fy, self.cx, self.cy]
            .iter()
            .chain(self.distortion.iter())
            .chain(self.camera_from_world.iter().flatten())
            .all(|v| v.is_finite());
        if !finite || self.fx <= 0.0 || self.fy <= 0.0 || self.width == 0 || self.height == 0 {
            return Err(CalibError::Invalid(
                "camera: intrinsics must be finite, focal lengths and image size positive".into(),
            ));
        }
        Ok(())
    }
}

/// The measured turntable axis, in camera coordinates (mm), as found by
/// [`fit_turntable_axis`]. The world frame is built from it, so scans only use it indirectly
/// through `camera_from_world`; it is kept for inspection and re-use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TurntableAxis {
    /// A point on the axis (the platter centre), camera coordinates.
    pub point_camera: [f64; 3],
    /// Unit direction of the axis (up), camera coordinates.
    pub direction_camera: [f64; 3],
}

/// Everything `calib.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Always [`CALIB_FORMAT`].
    pub format: String,
    /// The camera, extrinsics in the world (turntable) frame.
    pub camera: CameraModel,
    /// The turntable axis as measured, if it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub turntable: Option<TurntableAxis>,
    /// Galvo codes → laser ray.
    pub galvo: GalvoModel,
}

impl Calibration {
    /// Reads and validates `calib.json`.
    pub fn load(path: &Path) -> Result<Self, CalibError> {
        let text = std::fs::read_to_string(path).map_err(|source| CalibError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let calib: Calibration =
            serde_json::from_str(&text).map_err(|source| CalibError::Json {
                path: path.display().to_string(),
                source,
            })?;
        calib.validate()?;
        Ok(calib)
    }

    /// Writes `calib.json` (pretty JSON).
    pub fn save(&self, path: &Path) -> Result<(), CalibError> {
        self.validate()?;
        let text = serde_json::to_string_pretty(self).map_err(|source| CalibError::Json {
            path: path.display().to_string(),
            source,
        })?;
        std::fs::write(path, text + "\n").map_err(|source| CalibError::Io {
            path: path.display().to_string(),
            source,
        })
    }

    /// Checks the format string and that every number is usable.
    pub fn validate(&self) -> Result<(), CalibError> {
        if self.format != CALIB_FORMAT {
            return Err(CalibError::Invalid(format!(
                "format is {:?}, expected {CALIB_FORMAT:?}",
                self.format
            )));
        }
        self.camera.validate()?;
        self.galvo.validate()
    }

    /// The built-in calibration of the simulated rig for the built-in sphere (radius 10 mm).
    pub fn builtin() -> Self {
        Self::builtin_for([0.0, 0.0, 10.0], 10.0, 128)
    }

    /// The built-in calibration for an object with bounding sphere `(centre, radius)`: a
    /// `size`² camera 600 mm from the object at 35° elevation (the paper's camera distance, Fig. 2)
    /// framing it, and the laser from 780 mm above the camera's side, its 16-bit galvo spanning
    /// the object with 20% to spare.
    pub fn builtin_for(centre: [f64; 3], radius: f64, size: u32) -> Self {
        let el = 35f64.to_radians();
        let eye = [
            centre[0],
            centre[1] - 600.0 * el.cos(),
            centre[2] + 600.0 * el.sin(),
        ];
        let f = 0.5 * size as f64 * 600.0 / (radius * 1.15);
        let camera = look_at_camera(eye, centre, size, size, f);
        let origin = [0.0, -600.0, 500.0];
        let d = sub(centre, origin);
        let half = (1.2 * radius / dot(d, d).sqrt()).atan();
        let galvo = GalvoModel::looking_at(origin, centre, u16::MAX, half);
        Calibration {
            format: CALIB_FORMAT.to_string(),
            camera,
            turntable: None,
            galvo,
        }
    }
}

/// A camera at `eye` looking at `target` with the world `+z` up in the image.
pub fn look_at_camera(
    eye: [f64; 3],
    target: [f64; 3],
    width: u32,
    height: u32,
    f: f64,
) -> CameraModel {
    let z = normalize(sub(target, eye));
    let x = normalize(cross(z, [0.0, 0.0, 1.0]));
    let y = cross(z, x);
    let r = [x, y, z];
    let t = [-dot(x, eye), -dot(y, eye), -dot(z, eye)];
    let mut m = [[0.0; 4]; 4];
    for i in 0..3 {
        m[i][..3].copy_from_slice(&r[i]);
        m[i][3] = t[i];
    }
    m[3][3] = 1.0;
    CameraModel {
        width,
        height,
        fx: f,
        fy: f,
        cx: (width as f64 - 1.0) / 2.0,
        cy: (height as f64 - 1.0) / 2.0,
        distortion: [0.0; 5],
        camera_from_world: m,
    }
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_round_trips_and_sees_the_platter_centre() {
        let c = Calibration::builtin();
        let text = serde_json::to_string(&c).unwrap();
        let back: Calibration = serde_json::from_str(&text).unwrap();
        let (a, b) = (c.camera.camera_from_world, back.camera.camera_from_world);
        assert!(
            a.iter()
                .flatten()
                .zip(b.iter().flatten())
                .all(|(x, y)| (x - y).abs() < 1e-9)
        );
        assert_eq!(c.galvo.max_code, back.galvo.max_code);
        let uv = c.camera.project([0.0, 0.0, 10.0]).unwrap();
        assert!((uv[0] - 63.5).abs() < 1e-9 && (uv[1] - 63.5).abs() < 1e-9);
        let cw = c.camera.centre_world();
        assert!((cw[1] + 600.0 * 35f64.to_radians().cos()).abs() < 1e-9);
        let (o, d) = c.galvo.ray([32768, 32768]);
        let to_centre = normalize(sub([0.0, 0.0, 10.0], o));
        assert!(dot(d, to_centre) > 0.999_999);
    }

    #[test]
    fn wrong_format_is_named() {
        let mut c = Calibration::builtin();
        c.format = "x".into();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("subsurf-calib/1"), "{e}");
    }
}
