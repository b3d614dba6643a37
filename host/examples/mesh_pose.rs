//! The measurements behind `subsurf align`'s figures in BENCHMARKS.md: move a mesh into another
//! pose and unit (as another scanner would deliver it), and measure how far one mesh lies from
//! another's surface.
//!
//! ```sh
//! cargo run --release -p subsurf --example mesh_pose -- move IN.obj OUT.obj SCALE RX RY RZ TX TY TZ
//! cargo run --release -p subsurf --example mesh_pose -- surface A.obj B.obj   # A's vertices vs B's surface
//! cargo run --release -p subsurf --example mesh_pose -- vertices A.obj B.obj  # vertex i vs vertex i
//! ```
//! `move` applies `p ↦ SCALE · R · p + T` with R from the Euler angles RX, RY, RZ (degrees, roll
//! pitch yaw as `nalgebra::Rotation3::from_euler_angles`) and T in the output's unit.
use std::path::Path;

use nalgebra::{Rotation3, Vector3};
use subsurf::dataset::{Mesh, load_obj, write_obj};
use subsurf::geometry::{Scene, dist};

fn load(p: &str) -> Result<Mesh, String> {
    load_obj(Path::new(p))
        .map(|(m, _)| m)
        .map_err(|e| e.to_string())
}

fn rms_max(d: &[f64]) -> (f64, f64) {
    let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len().max(1) as f64).sqrt();
    (rms, d.iter().copied().fold(0.0, f64::max))
}

fn run(args: &[String]) -> Result<(), String> {
    let usage = "usage: mesh_pose move IN OUT SCALE RX RY RZ TX TY TZ | surface A B | vertices A B";
    match args.first().map(String::as_str) {
        Some("move") if args.len() == 10 => {
            let mesh = load(&args[1])?;
            let f: Vec<f64> = args[3..]
                .iter()
                .map(|x| x.parse().map_err(|_| format!("not a number: {x}")))
                .collect::<Result<_, _>>()?;
            let r = Rotation3::from_euler_angles(
                f[1].to_radians(),
                f[2].to_radians(),
                f[3].to_radians(),
            );
            let t = Vector3::new(f[4], f[5], f[6]);
            let moved = mesh
                .positions
                .iter()
                .map(|p| {
                    let q = f[0] * (r * Vector3::new(p[0], p[1], p[2])) + t;
                    [q.x, q.y, q.z]
                })
                .collect();
            let (m, _) = Mesh::new(moved, mesh.triangles.clone());
            write_obj(Path::new(&args[2]), &m).map_err(|e| e.to_string())
        }
        Some("surface") if args.len() == 3 => {
            let (a, b) = (load(&args[1])?, load(&args[2])?);
            let scene = Scene::new(b).map_err(|e| e.to_string())?;
            let d: Vec<f64> = a
                .positions
                .iter()
                .map(|p| {
                    scene
                        .closest(*p, f64::INFINITY)
                        .map_or(f64::NAN, |c| c.distance)
                })
                .collect();
            let (rms, max) = rms_max(&d);
            println!("surface distance: RMS {rms:.4} mm, max {max:.4} mm");
            Ok(())
        }
        Some("vertices") if args.len() == 3 => {
            let (a, b) = (load(&args[1])?, load(&args[2])?);
            if a.positions.len() != b.positions.len() {
                return Err("the meshes have different vertex counts".into());
            }
            let d: Vec<f64> = a
                .positions
                .iter()
                .zip(&b.positions)
                .map(|(p, q)| dist(*p, *q))
                .collect();
            let (rms, max) = rms_max(&d);
            println!("vertex distance: RMS {rms:.4} mm, max {max:.4} mm");
            Ok(())
        }
        _ => Err(usage.into()),
    }
}

fn main() -> std::process::ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{e}");
            std::process::ExitCode::FAILURE
        }
    }
}
