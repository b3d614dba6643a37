//! Framing helpers: the renderer builds the one camera model ([`Camera`], exactly the `scan.json`
//! camera of `crate::geometry`) from a field of view, from the object's bounds, or from JSON, and
//! parses the command line's camera specification. No projection lives here.

use crate::geometry::Camera;

use super::RenderError;

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn norm(a: [f64; 3]) -> Option<[f64; 3]> {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    (l > 1e-12 && l.is_finite()).then(|| a.map(|x| x / l))
}

fn check_size(width: u32, height: u32) -> Result<(), RenderError> {
    if width == 0 || height == 0 || width > 16384 || height > 16384 {
        return Err(RenderError::Camera(
            "image size must be 1..=16384 pixels per side".into(),
        ));
    }
    Ok(())
}

impl Camera {
    /// A camera at `eye` looking at `target` with `up` pointing up in the image, vertical field of
    /// view `fov_y_deg` ([`Camera::look_at`] with the focal length of that field of view).
    pub fn look_at_fov(
        eye: [f64; 3],
        target: [f64; 3],
        up: [f64; 3],
        fov_y_deg: f64,
        width: u32,
        height: u32,
    ) -> Result<Self, RenderError> {
        let bad = |s: &str| RenderError::Camera(s.to_string());
        check_size(width, height)?;
        if !(fov_y_deg > 0.0 && fov_y_deg < 179.0) {
            return Err(bad("field of view must be in (0, 179) degrees"));
        }
        norm(sub(target, eye)).ok_or_else(|| bad("eye and target coincide"))?;
        let f = 0.5 * height as f64 / (0.5 * fov_y_deg.to_radians()).tan();
        Camera::look_at(eye, target, up, f, width, height)
            .ok_or_else(|| bad("up is parallel to the view direction"))
    }

    /// A look-at camera from `direction` (pointing from the object to the eye) that frames the
    /// box `lo..hi`, with +z up in the image.
    pub fn framing(
        lo: [f64; 3],
        hi: [f64; 3],
        direction: [f64; 3],
        width: u32,
        height: u32,
    ) -> Result<Self, RenderError> {
        let c = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let radius = 0.5
            * (sub(hi, lo).iter().map(|x| x * x).sum::<f64>())
                .sqrt()
                .max(1e-6);
        let d = norm(direction).ok_or_else(|| RenderError::Camera("zero view direction".into()))?;
        let fov: f64 = 30.0;
        let aspect = (width as f64 / height as f64).min(1.0);
        let dist = 1.1 * radius / ((0.5 * fov).to_radians().tan() * aspect);
        let eye = [c[0] + d[0] * dist, c[1] + d[1] * dist, c[2] + d[2] * dist];
        let up = if d[2].abs() > 0.99 {
            [0.0, 1.0, 0.0]
        } else {
            [0.0, 0.0, 1.0]
        };
        Self::look_at_fov(eye, c, up, fov, width, height)
    }

    /// Reads one camera from JSON: a scan-format camera object, or a whole `scan.json` (then
    /// camera `index` of its `cameras` list).
    pub fn from_json(text: &str, index: usize) -> Result<Self, RenderError> {
        let bad = |s: String| RenderError::Camera(s);
        let v: serde_json::Value =
            serde_json::from_str(text).map_err(|e| bad(format!("not JSON: {e}")))?;
        let obj = match v.get("cameras") {
            Some(list) => list
                .get(index)
                .cloned()
                .ok_or_else(|| bad(format!("no camera {index} in `cameras`")))?,
            None => v,
        };
        let cam: Camera =
            serde_json::from_value(obj).map_err(|e| bad(format!("invalid camera: {e}")))?;
        cam.check_for_render()?;
        Ok(cam)
    }

    fn check_for_render(&self) -> Result<(), RenderError> {
        check_size(self.width, self.height)?;
        self.check().map_err(RenderError::Camera)
    }
}

/// A camera as the command line names it, before any file is read.
#[derive(Clone, Debug, PartialEq)]
pub enum CameraSpec {
    /// `auto[:DX,DY,DZ]`: frame the object, looking from the direction given (object → eye).
    Auto([f64; 3]),
    /// `lookat:EX,EY,EZ:TX,TY,TZ[:FOV_DEG]`.
    LookAt {
        /// Eye position, mm.
        eye: [f64; 3],
        /// Point looked at, mm.
        target: [f64; 3],
        /// Vertical field of view, degrees.
        fov_deg: f64,
    },
    /// `FILE.json[#K]`: camera K of a scan.json, or a single camera object.
    File {
        /// The JSON file.
        path: std::path::PathBuf,
        /// Index into `cameras`.
        index: usize,
    },
}

/// The default view direction of `auto`: from the front-right, above.
pub const DEFAULT_VIEW: [f64; 3] = [0.6, -1.0, 0.7];

fn triple(s: &str) -> Result<[f64; 3], RenderError> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| RenderError::Camera(format!("`{s}`: {e}")))?;
    match v[..] {
        [a, b, c] if a.is_finite() && b.is_finite() && c.is_finite() => Ok([a, b, c]),
        _ => Err(RenderError::Camera(format!(
            "`{s}` is not three finite numbers"
        ))),
    }
}

impl std::str::FromStr for CameraSpec {
    type Err = RenderError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let parts: Vec<&str> = s.split(':').collect();
        match parts[..] {
            ["auto"] => Ok(Self::Auto(DEFAULT_VIEW)),
            ["auto", d] => Ok(Self::Auto(triple(d)?)),
            ["lookat", e, t] => Ok(Self::LookAt {
                eye: triple(e)?,
                target: triple(t)?,
                fov_deg: 30.0,
            }),
            ["lookat", e, t, f] => Ok(Self::LookAt {
                eye: triple(e)?,
                target: triple(t)?,
                fov_deg: f
                    .parse()
                    .map_err(|_| RenderError::Camera(format!("bad field of view `{f}`")))?,
            }),
            _ if s.ends_with(".json") || s.contains(".json#") => {
                let (path, index) = match s.rsplit_once('#') {
                    Some((p, k)) => (
                        p,
                        k.parse()
                            .map_err(|_| RenderError::Camera(format!("bad camera index `{k}`")))?,
                    ),
                    None => (s, 0),
                };
                Ok(Self::File {
                    path: path.into(),
                    index,
                })
            }
            _ => Err(RenderError::Camera(format!(
                "`{s}`: expected auto[:DX,DY,DZ], lookat:EX,EY,EZ:TX,TY,TZ[:FOV] or FILE.json[#K]"
            ))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_puts_the_target_at_the_principal_point_and_up_up() {
        let c = Camera::look_at_fov([0.0, -100.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0], 40.0, 64, 48)
            .unwrap();
        let g = &c;
        let p = g.project([0.0; 3]).unwrap();
        assert!((p[0] - 31.5).abs() < 1e-9 && (p[1] - 23.5).abs() < 1e-9);
        let up = g.project([0.0, 0.0, 10.0]).unwrap();
        assert!(up[1] < 23.5, "+z appears above the centre");
        let right = g.project([10.0, 0.0, 0.0]).unwrap();
        assert!(right[0] > 31.5, "+x appears to the right seen from -y");
        let e = c.center();
        assert!((e[1] + 100.0).abs() < 1e-9 && e[0].abs() < 1e-9);
        assert!(Camera::look_at_fov([0.0; 3], [0.0; 3], [0.0, 0.0, 1.0], 40.0, 8, 8).is_err());
    }

    #[test]
    fn camera_specs_parse() {
        assert_eq!(
            "auto".parse::<CameraSpec>().unwrap(),
            CameraSpec::Auto(DEFAULT_VIEW)
        );
        assert_eq!(
            "auto:0,0,1".parse::<CameraSpec>().unwrap(),
            CameraSpec::Auto([0.0, 0.0, 1.0])
        );
        assert!(matches!(
            "lookat:0,-100,0:0,0,0:40".parse::<CameraSpec>().unwrap(),
            CameraSpec::LookAt { fov_deg: 40.0, .. }
        ));
        assert_eq!(
            "scan/scan.json#2".parse::<CameraSpec>().unwrap(),
            CameraSpec::File {
                path: "scan/scan.json".into(),
                index: 2
            }
        );
        for bad in [
            "",
            "lookat:1,2",
            "auto:1,2",
            "cam.json#x",
            "lookat:0,0,0:1,1,1:wide",
        ] {
            assert!(bad.parse::<CameraSpec>().is_err(), "{bad}");
        }
    }

    #[test]
    fn scan_format_cameras_parse_and_project() {
        let text = r#"{"format":"subsurf-scan/1","cameras":[{"width":128,"height":128,"fx":3200.0,
            "fy":3200.0,"cx":63.5,"cy":63.5,"camera_from_world":[[1,0,0,0],[0,-1,0,0],[0,0,-1,600],[0,0,0,1]]}]}"#;
        let c = Camera::from_json(text, 0).unwrap();
        let p = c.project([0.0, 0.0, 0.0]).unwrap();
        assert_eq!(p, [63.5, 63.5]);
        assert!(Camera::from_json(text, 1).is_err());
        assert!(Camera::from_json("{]", 0).is_err());
        assert!(Camera::from_json(r#"{"width":0,"height":1,"fx":1,"fy":1,"cx":0,"cy":0,"camera_from_world":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#, 0).is_err());
    }
}
