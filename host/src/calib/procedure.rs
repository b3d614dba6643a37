//! The calibration procedures behind `subsurf calib`, each from its files into `calib.json`:
//! camera intrinsics (and, with turntable views, extrinsics and the axis) from chessboard
//! images, the galvo model from laser spots, an OpenCV calibration import, and simulated
//! chessboard images to try the procedure without a rig. The command only parses its flags;
//! `say` prints a result line (stdout), `warn` a note (stderr).
use std::path::{Path, PathBuf};

use super::detect::{Gray, detect_chessboard, render_board, simulated_camera};
use super::target::{
    ChessboardTarget, Pose, TargetView, camera_model, fit_intrinsics, fit_turntable,
};
use super::{CalibError, Calibration, GalvoObservation, fit_galvo};
use crate::dataset::{Image, ImageError, encode_exr};

/// Why a calibration procedure failed; every failure says what was not found.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ProcedureError {
    /// The inputs do not allow the calibration.
    #[error("{0}")]
    Invalid(String),
    /// A step failed; `what` names it, `source` says why.
    #[error("{what}")]
    Step {
        /// The step (e.g. `cannot read board.png`).
        what: String,
        /// Why.
        #[source]
        source: Box<ProcedureError>,
    },
    /// A fit or the calibration file failed.
    #[error(transparent)]
    Calib(#[from] CalibError),
    /// An image could not be decoded or encoded.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// A file could not be read or written.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// A JSON file is not what it should be.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

crate::util::step_context!(ProcedureError);

fn load_or_builtin(path: &Path, warn: fn(&str)) -> Result<Calibration, ProcedureError> {
    if path.exists() {
        Ok(Calibration::load(path)?)
    } else {
        warn(&format!(
            "{} does not exist yet: starting from the built-in calibration",
            path.display()
        ));
        Ok(Calibration::builtin())
    }
}

fn detect(path: &Path, t: &ChessboardTarget) -> Result<(TargetView, u32, u32), ProcedureError> {
    let bytes = std::fs::read(path).step(|| format!("cannot read {}", path.display()))?;
    let img =
        Image::decode_picture(&bytes).step(|| format!("{} is not an image", path.display()))?;
    let g = Gray::from_linear(img.width, img.height, img.channels, &img.data);
    let view = detect_chessboard(&g, t).step(|| format!("in {}", path.display()))?;
    Ok((view, img.width as u32, img.height as u32))
}

/// `calib camera`: intrinsics from the chessboard `images` (board `cols`×`rows` inner corners
/// of `square` mm) and, with 3 or more `turntable` views (path, degrees), the extrinsics and
/// the turntable axis; written into `calib` (started from the built-in calibration when absent).
pub fn calibrate_camera(
    images: &[PathBuf],
    turntable: &[(PathBuf, f64)],
    board: (usize, usize),
    square: f64,
    calib: &Path,
    say: fn(&str),
    warn: fn(&str),
) -> Result<(), ProcedureError> {
    let t = ChessboardTarget {
        cols: board.0,
        rows: board.1,
        square_mm: square,
    };
    if images.len() + turntable.len() < 3 {
        return Err(ProcedureError::Invalid(
            "give at least 3 images of the chessboard (tilted differently)".into(),
        ));
    }
    let mut views = Vec::new();
    let mut size = None;
    for p in images.iter().chain(turntable.iter().map(|(p, _)| p)) {
        let (v, w, h) = detect(p, &t)?;
        if size.is_some_and(|s| s != (w, h)) {
            return Err(ProcedureError::Invalid(format!(
                "{}: image size differs from the others",
                p.display()
            )));
        }
        size = Some((w, h));
        views.push(v);
    }
    let (w, h) = size.unwrap_or((0, 0));
    let intr = fit_intrinsics(&views)?;
    say(&format!(
        "intrinsics: fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} k2 {:.4}; reprojection RMS {:.3} px",
        intr.k[0],
        intr.k[1],
        intr.k[2],
        intr.k[3],
        intr.distortion[0],
        intr.distortion[1],
        intr.rms_px
    ));
    let mut c = load_or_builtin(calib, warn)?;
    if turntable.len() >= 3 {
        let deg: Vec<f64> = turntable.iter().map(|(_, d)| *d).collect();
        let axis = fit_turntable(&intr, &views, images.len(), &deg)?;
        say(&format!(
            "turntable axis (camera frame): direction {:.5?}, platter centre {:.2?} mm; RMS {:.3} mm",
            axis.direction.as_slice(),
            axis.point.as_slice(),
            axis.rms_mm
        ));
        c.camera = camera_model(w, h, &intr, &axis);
        c.turntable = Some(crate::calib::TurntableAxis {
            point_camera: [axis.point[0], axis.point[1], axis.point[2]],
            direction_camera: [axis.direction[0], axis.direction[1], axis.direction[2]],
        });
    } else {
        if !turntable.is_empty() {
            return Err(ProcedureError::Invalid(format!(
                "the turntable axis needs the board on the platter at 3 or more angles; \
                 got {}",
                turntable.len()
            )));
        }
        warn("no --turntable images: extrinsics left as they were");
        c.camera.width = w;
        c.camera.height = h;
        (c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy) =
            (intr.k[0], intr.k[1], intr.k[2], intr.k[3]);
        c.camera.distortion = Some(intr.distortion.to_vec());
    }
    c.save(calib)?;
    say(&format!("written to {}", calib.display()));
    Ok(())
}

/// `calib galvo`: the galvo model from the spot observations in `spots` (JSON), into `calib`.
pub fn calibrate_galvo(
    spots: &Path,
    max_code: u16,
    calib: &Path,
    say: fn(&str),
    warn: fn(&str),
) -> Result<(), ProcedureError> {
    let text =
        std::fs::read_to_string(spots).step(|| format!("cannot read {}", spots.display()))?;
    let obs: Vec<GalvoObservation> = serde_json::from_str(&text)
        .step(|| format!("{} is not a list of spot observations", spots.display()))?;
    let (g, rms) = fit_galvo(&obs, max_code)?;
    say(&format!(
        "galvo: pivot {:.2?} mm; spot-to-ray RMS {rms:.3} mm",
        g.origin
    ));
    let mut c = load_or_builtin(calib, warn)?;
    c.galvo = g;
    c.save(calib)?;
    say(&format!("written to {}", calib.display()));
    Ok(())
}

/// `calib import-opencv`: intrinsics from an OpenCV calibration `file` (FileStorage YAML or
/// JSON), into `calib`.
pub fn import_opencv(
    file: &Path,
    calib: &Path,
    say: fn(&str),
    warn: fn(&str),
) -> Result<(), ProcedureError> {
    let text = std::fs::read_to_string(file).step(|| format!("cannot read {}", file.display()))?;
    let k = opencv_matrix(&text, "camera_matrix").ok_or_else(|| {
        ProcedureError::Invalid(format!("{}: no camera_matrix found", file.display()))
    })?;
    if k.len() != 9 {
        return Err(ProcedureError::Invalid(format!(
            "{}: camera_matrix has {} values, not 9",
            file.display(),
            k.len()
        )));
    }
    let d = opencv_matrix(&text, "distortion_coefficients").unwrap_or_default();
    let mut c = load_or_builtin(calib, warn)?;
    (c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy) = (k[0], k[4], k[2], k[5]);
    let mut distortion = [0.0; 5];
    for (i, v) in d.iter().take(5).enumerate() {
        distortion[i] = *v;
    }
    c.camera.distortion = Some(distortion.to_vec());
    if let Some(w) = opencv_scalar(&text, "image_width") {
        c.camera.width = w as u32;
    }
    if let Some(h) = opencv_scalar(&text, "image_height") {
        c.camera.height = h as u32;
    }
    c.save(calib)?;
    say(&format!(
        "intrinsics imported from {} into {}",
        file.display(),
        calib.display()
    ));

    Ok(())
}

/// Numbers of an OpenCV matrix node `name` (FileStorage YAML or JSON: its `data` list).
fn opencv_matrix(text: &str, name: &str) -> Option<Vec<f64>> {
    let at = text.find(name)?;
    let rest = &text[at..];
    let data = rest.find("data")?;
    let open = rest[data..].find('[')? + data;
    let close = rest[open..].find(']')? + open;
    rest[open + 1..close]
        .split([',', ' ', '\n', '\r', '\t'])
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse::<f64>().ok())
        .collect()
}

fn opencv_scalar(text: &str, name: &str) -> Option<f64> {
    let at = text.find(name)? + name.len();
    let rest = text[at..].trim_start_matches(['"', ':', ' ', '\t']);
    let end = rest.find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))?;
    rest[..end].parse().ok()
}

/// Writes simulated chessboard images (tilted views and turntable views) into `out` and says
/// the command that calibrates from them: the procedure without a rig.
pub fn simulate_target(out: &Path, say: fn(&str)) -> Result<(), ProcedureError> {
    std::fs::create_dir_all(out).step(|| format!("cannot create {}", out.display()))?;
    let t = ChessboardTarget {
        cols: 9,
        rows: 6,
        square_mm: 30.0,
    };
    let cam = simulated_camera();
    let save = |name: &str, g: &Gray| -> Result<PathBuf, ProcedureError> {
        let img = Image {
            width: g.width,
            height: g.height,
            channels: 1,
            data: g.data.clone(),
        };
        let p = out.join(name);
        std::fs::write(&p, encode_exr(&img)?).step(|| format!("cannot write {}", p.display()))?;
        Ok(p)
    };
    let mut cmd = String::from("subsurf calib camera");
    let centre = nalgebra::Vector3::new(
        t.square_mm * (t.cols as f64 - 1.0) / 2.0,
        t.square_mm * (t.rows as f64 - 1.0) / 2.0,
        0.0,
    );
    for (k, ax) in [
        [0.4, 0.1, 0.0],
        [-0.4, 0.2, 0.1],
        [0.1, -0.45, -0.1],
        [0.25, 0.35, 0.3],
        [-0.3, -0.3, 0.5],
    ]
    .iter()
    .enumerate()
    {
        let r = nalgebra::Rotation3::new(nalgebra::Vector3::from(*ax)).into_inner();
        let pose = Pose {
            r,
            t: nalgebra::Vector3::new(0.0, 0.0, 520.0) - r * centre,
        };
        let p = save(&format!("tilted-{k}.exr"), &render_board(&cam, &t, &pose))?;
        cmd.push_str(&format!(" {}", p.display()));
    }
    let m = cam.camera_from_world;
    let r_cw = nalgebra::Matrix3::from_fn(|i, j| m[i][j]);
    let t_cw = nalgebra::Vector3::new(m[0][3], m[1][3], m[2][3]);
    let r_wb = nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);
    let t_wb = nalgebra::Vector3::new(-120.0, 75.0, 0.0);
    for d in [0.0, 60.0, 120.0, 180.0, 240.0, 300.0] {
        let rz =
            nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), f64::to_radians(d))
                .into_inner();
        let pose = Pose {
            r: r_cw * rz * r_wb,
            t: r_cw * rz * t_wb + t_cw,
        };
        let p = save(
            &format!("turntable-{d:03.0}.exr"),
            &render_board(&cam, &t, &pose),
        )?;
        cmd.push_str(&format!(" --turntable {}={d}", p.display()));
    }
    cmd.push_str(" --board 9x6 --square 30 --calib calib.json");
    say("simulated camera: fx = fy = 400, cx = 159.5, cy = 119.5, 35° elevation, 600 mm");
    say(&cmd);
    Ok(())
}
