//! `subsurf calib`: camera intrinsics and extrinsics from chessboard images, the turntable axis,
//! the galvo model from laser spots, OpenCV calibration import — all into one `calib.json`.
//! Parsing only; the procedures are `subsurf::calib::procedure`.
use std::path::PathBuf;

use subsurf::calib::procedure;

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

pub fn run(args: Args) -> anyhow::Result<()> {
    let say = |line: &str| println!("{line}");
    let warn = |line: &str| eprintln!("{line}");
    match args.action {
        Action::Camera {
            images,
            turntable,
            board,
            square,
            calib,
        } => procedure::calibrate_camera(&images, &turntable, board, square, &calib, say, warn)?,
        Action::Galvo {
            spots,
            max_code,
            calib,
        } => procedure::calibrate_galvo(&spots, max_code, &calib, say, warn)?,
        Action::ImportOpencv { file, calib } => procedure::import_opencv(&file, &calib, say, warn)?,
        Action::SimulateTarget { out } => procedure::simulate_target(&out, say)?,
    }
    Ok(())
}
