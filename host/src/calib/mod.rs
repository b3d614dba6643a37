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
pub mod procedure;
pub mod target;

pub use galvo::{GalvoModel, GalvoObservation, fit_galvo};

use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::geometry::Camera;

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
    /// The camera (the one camera model, exactly `scan.json`'s), extrinsics in the world
    /// (turntable) frame.
    pub camera: Camera,
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
        self.camera
            .check()
            .map_err(|m| CalibError::Invalid(format!("camera: {m}")))?;
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
        let mut camera = Camera::look_at(eye, centre, [0.0, 0.0, 1.0], f, size, size)
            .unwrap_or_else(|| {
                // Only a non-finite centre or radius gets here: a camera that sees nothing.
                Camera::look_at([0.0, -1.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0], f, size, size)
                    .expect("a fixed, non-degenerate view")
            });
        // A calibration always states its distortion model (zero here).
        camera.distortion = Some(vec![0.0; 5]);
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
        let cw = c.camera.center();
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
