//! `subsurf calib`: camera intrinsics and extrinsics from chessboard images, the turntable axis,
//! the galvo model from laser spots, OpenCV calibration import — all into one `calib.json`.
use anyhow::{Context, bail};
use std::path::{Path, PathBuf};

use subsurf::calib::detect::{Gray, detect_chessboard, render_board, simulated_camera};
use subsurf::calib::target::{
    ChessboardTarget, Pose, TargetView, camera_model, fit_intrinsics, fit_turntable,
};
use subsurf::calib::{Calibration, GalvoObservation, fit_galvo};
use subsurf::dataset::{Image, encode_exr};

/// Calibrate the rig; every failure says what was not found.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    action: Action,
}

#[derive(Debug, clap::Subcommand)]
enum Action {
    /// Camera intrinsics from chessboard images; with --turntable images of the board lying on
    /// the platter, also the turntable axis and the camera's extrinsics in the turntable frame.
    Camera {
        /// Images of the board held at different tilts (EXR, PNG, TIFF).
        images: Vec<PathBuf>,
        /// Images of the board lying on the platter, as PATH=DEGREES (turntable angle).
        #[arg(long, value_parser = parse_turntable)]
        turntable: Vec<(PathBuf, f64)>,
        /// Inner corners, COLSxROWS (their sum must be odd, e.g. 9x6).
        #[arg(long, default_value = "9x6", value_parser = parse_board)]
        board: (usize, usize),
        /// Square size, mm.
        #[arg(long, default_value_t = 30.0)]
        square: f64,
        /// calib.json to update (its galvo model is kept); written there.
        #[arg(long)]
        calib: PathBuf,
    },
    /// The galvo model from laser spots seen on a planar target at two or more distances
    /// (JSON: `[{"codes": [x, y], "point": [x, y, z]}, …]`, points in the turntable frame, mm).
    Galvo {
        /// The spot observations.
        #[arg(long)]
        spots: PathBuf,
        /// Largest galvo code.
        #[arg(long, default_value_t = u16::MAX)]
        max_code: u16,
        /// calib.json to update.
        #[arg(long)]
        calib: PathBuf,
    },
    /// Import camera intrinsics from an OpenCV calibration file (FileStorage JSON or YAML with
    /// `camera_matrix`, `distortion_coefficients`, `image_width`, `image_height`) as they are.
    ImportOpencv {
        /// The OpenCV file.
        file: PathBuf,
        /// calib.json to update.
        #[arg(long)]
        calib: PathBuf,
    },
    /// Write simulated chessboard images (tilted views and turntable views) and the command
    /// that calibrates from them — to try the procedure without a rig.
    SimulateTarget {
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
}

fn parse_board(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("{s:?}: expected COLSxROWS, e.g. 9x6"))?;
    Ok((
        a.trim()
            .parse()
            .map_err(|_| format!("{a:?} is not a number"))?,
        b.trim()
            .parse()
            .map_err(|_| format!("{b:?} is not a number"))?,
    ))
}

fn parse_turntable(s: &str) -> Result<(PathBuf, f64), String> {
    let (p, d) = s
        .rsplit_once('=')
        .ok_or_else(|| format!("{s:?}: expected PATH=DEGREES"))?;
    Ok((
        PathBuf::from(p),
        d.parse().map_err(|_| format!("{d:?} is not an angle"))?,
    ))
}

fn load_or_builtin(path: &Path) -> anyhow::Result<Calibration> {
    if path.exists() {
        Ok(Calibration::load(path)?)
    } else {
        eprintln!(
            "{} does not exist yet: starting from the built-in calibration",
            path.display()
        );
        Ok(Calibration::builtin())
    }
}

fn detect(path: &Path, t: &ChessboardTarget) -> anyhow::Result<(TargetView, u32, u32)> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let img = Image::decode_picture(&bytes)
        .with_context(|| format!("{} is not an image", path.display()))?;
    let g = Gray::from_linear(img.width, img.height, img.channels, &img.data);
    let view = detect_chessboard(&g, t).with_context(|| format!("in {}", path.display()))?;
    Ok((view, img.width as u32, img.height as u32))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.action {
        Action::Camera {
            images,
            turntable,
            board,
            square,
            calib,
        } => {
            let t = ChessboardTarget {
                cols: board.0,
                rows: board.1,
                square_mm: square,
            };
            if images.len() + turntable.len() < 3 {
                bail!("give at least 3 images of the chessboard (tilted differently)");
            }
            let mut views = Vec::new();
            let mut size = None;
            for p in images.iter().chain(turntable.iter().map(|(p, _)| p)) {
                let (v, w, h) = detect(p, &t)?;
                if size.is_some_and(|s| s != (w, h)) {
                    bail!("{}: image size differs from the others", p.display());
                }
                size = Some((w, h));
                views.push(v);
            }
            let (w, h) = size.unwrap_or((0, 0));
            let intr = fit_intrinsics(&views)?;
            println!(
                "intrinsics: fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} k2 {:.4}; reprojection RMS {:.3} px",
                intr.k[0],
                intr.k[1],
                intr.k[2],
                intr.k[3],
                intr.distortion[0],
                intr.distortion[1],
                intr.rms_px
            );
            let mut c = load_or_builtin(&calib)?;
            if turntable.len() >= 3 {
                let deg: Vec<f64> = turntable.iter().map(|(_, d)| *d).collect();
                let axis = fit_turntable(&intr, &views, images.len(), &deg)?;
                println!(
                    "turntable axis (camera frame): direction {:.5?}, platter centre {:.2?} mm; RMS {:.3} mm",
                    axis.direction.as_slice(),
                    axis.point.as_slice(),
                    axis.rms_mm
                );
                c.camera = camera_model(w, h, &intr, &axis);
                c.turntable = Some(subsurf::calib::TurntableAxis {
                    point_camera: [axis.point[0], axis.point[1], axis.point[2]],
                    direction_camera: [axis.direction[0], axis.direction[1], axis.direction[2]],
                });
            } else {
                if !turntable.is_empty() {
                    bail!(
                        "the turntable axis needs the board on the platter at 3 or more angles; \
                         got {}",
                        turntable.len()
                    );
                }
                eprintln!("no --turntable images: extrinsics left as they were");
                c.camera.width = w;
                c.camera.height = h;
                (c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy) =
                    (intr.k[0], intr.k[1], intr.k[2], intr.k[3]);
                c.camera.distortion = Some(intr.distortion.to_vec());
            }
            c.save(&calib)?;
            println!("written to {}", calib.display());
        }
        Action::Galvo {
            spots,
            max_code,
            calib,
        } => {
            let text = std::fs::read_to_string(&spots)
                .with_context(|| format!("cannot read {}", spots.display()))?;
            let obs: Vec<GalvoObservation> = serde_json::from_str(&text).with_context(|| {
                format!("{} is not a list of spot observations", spots.display())
            })?;
            let (g, rms) = fit_galvo(&obs, max_code)?;
            println!(
                "galvo: pivot {:.2?} mm; spot-to-ray RMS {rms:.3} mm",
                g.origin
            );
            let mut c = load_or_builtin(&calib)?;
            c.galvo = g;
            c.save(&calib)?;
            println!("written to {}", calib.display());
        }
        Action::ImportOpencv { file, calib } => {
            let text = std::fs::read_to_string(&file)
                .with_context(|| format!("cannot read {}", file.display()))?;
            let k = opencv_matrix(&text, "camera_matrix")
                .with_context(|| format!("{}: no camera_matrix found", file.display()))?;
            if k.len() != 9 {
                bail!(
                    "{}: camera_matrix has {} values, not 9",
                    file.display(),
                    k.len()
                );
            }
            let d = opencv_matrix(&text, "distortion_coefficients").unwrap_or_default();
            let mut c = load_or_builtin(&calib)?;
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
            c.save(&calib)?;
            println!(
                "intrinsics imported from {} into {}",
                file.display(),
                calib.display()
            );
        }
        Action::SimulateTarget { out } => simulate_target(&out)?,
    }
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

fn simulate_target(out: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let t = ChessboardTarget {
        cols: 9,
        rows: 6,
        square_mm: 30.0,
    };
    let cam = simulated_camera();
    let save = |name: &str, g: &Gray| -> anyhow::Result<PathBuf> {
        let img = Image {
            width: g.width,
            height: g.height,
            channels: 1,
            data: g.data.clone(),
        };
        let p = out.join(name);
        std::fs::write(&p, encode_exr(&img)?)
            .with_context(|| format!("cannot write {}", p.display()))?;
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
    println!("simulated camera: fx = fy = 400, cx = 159.5, cy = 119.5, 35° elevation, 600 mm");
    println!("{cmd}");
    Ok(())
}
