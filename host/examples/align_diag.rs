//! Where `subsurf align`'s pose error comes from, on a dataset whose true mesh is known: each
//! training spot's triangulated point against the true surface (how far inside it, along the
//! laser ray, the camera ray and the normal; the angles of incidence and of view), and the
//! pose `align` finds from the dataset's mesh (any pose and unit) against the truth, up to the
//! truth's own symmetries.
//!
//! ```sh
//! cargo run --release -p subsurf --example align_diag -- spots SCAN TRUTH.obj EXCLUDE
//! cargo run --release -p subsurf --example align_diag -- pose SCAN TRUTH.obj EXCLUDE [DEPTH_MODEL]
//! ```
//! `pose` prints the rotation (degrees), the translation of the truth's centroid (mm) and the
//! scale's relative error of the found pose, with the symmetry of the truth that brings it
//! closest (a half turn about a principal axis through the centroid, or none).
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use subsurf::align::{AlignOptions, DepthModel, Similarity, align_points, spot_points};
use subsurf::dataset::{Dataset, Mesh, load_obj, select_frames};
use subsurf::geometry::{Scene, V3, add_scaled, dot, sub};

fn open(scan: &str, truth: &str, exclude: &str) -> Result<(Dataset, Mesh, Vec<usize>), String> {
    let ds = Dataset::open(Path::new(scan)).map_err(|e| e.to_string())?;
    let truth = load_obj(Path::new(truth)).map_err(|e| e.to_string())?.0;
    let frames =
        select_frames(ds.spec.frames.len(), None, Some(exclude)).map_err(|e| e.to_string())?;
    Ok((ds, truth, frames))
}

/// Distance along `back` (a unit direction out of the surface) from the surface entry of the
/// ray through `p` to `p`; positive when `p` lies below the entry.
fn depth_along(scene: &Scene, p: V3, back: V3) -> Option<(f64, u32, V3)> {
    let start = add_scaled(p, 200.0, back);
    let hit = scene.cast(start, back.map(|x| -x), 400.0)?;
    Some((dot(sub(hit.point, p), back), hit.triangle, hit.point))
}

fn spots(scan: &str, truth: &str, exclude: &str) -> Result<(), String> {
    let (ds, truth, frames) = open(scan, truth, exclude)?;
    let opts = AlignOptions::for_dataset(&ds);
    let ev = spot_points(&ds, &frames, &opts.evidence, &()).map_err(|e| e.to_string())?;
    let scene = Scene::new(truth).map_err(|e| e.to_string())?;
    let models: Vec<String> = DepthModel::ALL
        .iter()
        .map(|m| format!("n.{0} n2.{0}", m.name()))
        .collect();
    println!(
        "frame deg cos_laser cos_camera cos_lc normal_mm laser_mm camera_mm gap_mm footprint_mm z u v {}",
        models.join(" ")
    );
    for sp in &ev.points {
        let Some(c) = scene.closest(sp.point, f64::INFINITY) else {
            continue;
        };
        let Some(n) = scene.face_normal(c.triangle) else {
            continue;
        };
        // Signed: negative inside (outward normals).
        let normal_mm = dot(sub(sp.point, c.point), n);
        let laser = depth_along(&scene, sp.point, sp.to_laser);
        let camera = depth_along(&scene, sp.point, sp.to_camera);
        let (cos_l, cos_c) = match laser {
            Some((_, tri, at)) => {
                let m = scene.normal_at(tri, at).unwrap_or(n);
                (dot(m, sp.to_laser), dot(m, sp.to_camera))
            }
            None => (f64::NAN, f64::NAN),
        };
        // Per model, how far its unit of depth moves the point along the normal.
        let per: Vec<String> = DepthModel::ALL
            .iter()
            .map(|m| {
                let b = m.directions(sp, n);
                format!("{:.4} {:.4}", dot(n, b[0]), dot(n, b[1]))
            })
            .collect();
        println!(
            "{} {:.1} {:.3} {:.3} {:.3} {:.4} {:.4} {:.4} {:.4} {:.4} {:.2} {:.3} {:.3} {}",
            sp.frame,
            ds.spec.frames[sp.frame].turntable_deg,
            cos_l,
            cos_c,
            dot(sp.to_laser, sp.to_camera),
            normal_mm,
            laser.map_or(f64::NAN, |l| l.0),
            camera.map_or(f64::NAN, |l| l.0),
            sp.gap_mm,
            sp.footprint_mm,
            sp.point[2],
            sp.uv[0],
            sp.uv[1],
            per.join(" ")
        );
    }
    Ok(())
}

/// Half turns about the principal axes through the centroid of `mesh` that map its vertices
/// onto its vertices (to 1e-6 of its size), the identity first.
fn symmetries(mesh: &Mesh) -> Vec<Similarity> {
    let n = mesh.positions.len() as f64;
    let c = mesh
        .positions
        .iter()
        .fold(Vector3::zeros(), |a, p| a + Vector3::from(*p))
        / n;
    let mut cov = Matrix3::zeros();
    for p in &mesh.positions {
        let d = Vector3::from(*p) - c;
        cov += d * d.transpose();
    }
    let axes = cov.symmetric_eigen().eigenvectors;
    let tol = 1e-6 * mesh.diagonal();
    let scene = Scene::new(mesh.clone()).expect("a mesh");
    let mut out = vec![Similarity::identity()];
    for k in 0..3 {
        let a = axes.column(k).into_owned();
        let r = 2.0 * a * a.transpose() - Matrix3::identity();
        let g = Similarity {
            scale: 1.0,
            rotation: r,
            translation: c - r * c,
        };
        let onto = mesh.positions.iter().all(|p| {
            scene
                .closest(g.apply(*p), f64::INFINITY)
                .is_some_and(|q| q.distance < tol)
        });
        if onto {
            out.push(g);
        }
    }
    out
}

fn pose(scan: &str, truth: &str, exclude: &str, model: Option<&str>) -> Result<(), String> {
    let (ds, truth, frames) = open(scan, truth, exclude)?;
    let mut opts = AlignOptions::for_dataset(&ds);
    opts.scale = std::env::var("SCALE").ok().and_then(|s| s.parse().ok());
    opts.spot_depth = std::env::var("DEPTH").ok().and_then(|s| s.parse().ok());
    if let Some(m) = model {
        opts.depth_model = m.parse()?;
    }
    let (name, source) = ds.source_mesh().map_err(|e| e.to_string())?;
    let ev = spot_points(&ds, &frames, &opts.evidence, &()).map_err(|e| e.to_string())?;
    let t0 = std::time::Instant::now();
    let out = align_points(&source, &name, ev, &opts, &()).map_err(|e| e.to_string())?;
    let secs = t0.elapsed().as_secs_f64();
    println!(
        "{}",
        serde_json::to_string(&out.record).map_err(|e| e.to_string())?
    );
    println!(
        "model {} depth {:.4} {:.4} mm",
        out.depth_model.name(),
        out.depth[0],
        out.depth[1]
    );
    report(&truth, &out.mesh);
    println!("align_points {secs:.2} s");
    Ok(())
}

/// The similarity from `truth` to `aligned` (same vertices, same order), reduced by the truth's
/// symmetries, as rotation, centroid translation and scale errors.
fn report(truth: &Mesh, aligned: &Mesh) {
    let all = vec![1.0; truth.positions.len()];
    let Some(e) = Similarity::fit(&truth.positions, &aligned.positions, &all) else {
        println!("no similarity fits");
        return;
    };
    let n = truth.positions.len() as f64;
    let c = truth
        .positions
        .iter()
        .fold(Vector3::zeros(), |a, p| a + Vector3::from(*p))
        / n;
    let best = symmetries(truth)
        .iter()
        .enumerate()
        .map(|(k, g)| (k, e.then(g)))
        .map(|(k, x)| {
            let cos = ((x.rotation.trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
            (k, x, cos.acos().to_degrees())
        })
        .min_by(|a, b| a.2.total_cmp(&b.2));
    let Some((k, x, deg)) = best else { return };
    let moved = Vector3::from(x.apply([c.x, c.y, c.z])) - c;
    let axis = nalgebra::Rotation3::from_matrix(&x.rotation)
        .axis()
        .map_or(Vector3::zeros(), |a| a.into_inner());
    let rms = (truth
        .positions
        .iter()
        .map(|p| (Vector3::from(x.apply(*p)) - Vector3::from(*p)).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt();
    println!(
        "pose error (symmetry {k}): rotation {deg:.4} deg, centroid moved ({:.4}, {:.4}, {:.4}) mm, \
         scale {:+.4} %, vertex RMS {rms:.4} mm, axis ({:.3}, {:.3}, {:.3})",
        moved.x,
        moved.y,
        moved.z,
        100.0 * (x.scale - 1.0),
        axis.x,
        axis.y,
        axis.z
    );
}

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let r = match (a.first().map(String::as_str), a.len()) {
        (Some("spots"), 4) => spots(&a[1], &a[2], &a[3]),
        (Some("pose"), 4) => pose(&a[1], &a[2], &a[3], None),
        (Some("pose"), 5) => pose(&a[1], &a[2], &a[3], Some(&a[4])),
        (Some("aligned"), 3) => (|| {
            let t = load_obj(Path::new(&a[1])).map_err(|e| e.to_string())?.0;
            let m = load_obj(Path::new(&a[2])).map_err(|e| e.to_string())?.0;
            report(&t, &m);
            Ok(())
        })(),
        _ => Err(
            "usage: align_diag spots SCAN TRUTH EXCLUDE | pose SCAN TRUTH EXCLUDE [MODEL] | aligned TRUTH ALIGNED"
                .into(),
        ),
    };
    if let Err(e) = r {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
