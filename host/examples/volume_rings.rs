//! One frame's ring sums around x_i, the data's beside a homogeneous medium's traced by the
//! volume tracer: the check of the forward model against a dataset whose medium is known.
//!
//! ```text
//! cargo run --release --example volume_rings -- ../shared/data/sample-slab 4 2,2,2 0.99,0.985,0.98 [g] [photons] [ior,alpha]
//! ```
//!
//! With `ior,alpha` (e.g. `1.55,0.2`) the boundary is a rough dielectric instead of
//! index-matched. With `SECTORS=n` in the environment each ring is split into n sectors of
//! azimuth about the beam (`volume::fit::pixel_bins`), a line each.
use anyhow::{Context, Result};
use subsurf::dataset::Dataset;
use subsurf::geometry::Scene;
use subsurf::volume::dielectric::Surface;
use subsurf::volume::fit::{FrameRings, frame_geometry, model_rings, ring_edge};
use subsurf::volume::trace::{Boundary, TraceSettings, trace_frame};

fn triple(s: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s.split(',').map(|x| x.parse()).collect::<Result<_, _>>()?;
    anyhow::ensure!(v.len() == 3, "three numbers: {s}");
    Ok([v[0], v[1], v[2]])
}

fn main() -> Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        a.len() >= 4,
        "usage: volume_rings SCAN FRAME S,S,S A,A,A [g] [photons] [ior,alpha]"
    );
    let ds = Dataset::open(&a[0]).with_context(|| format!("opening {}", a[0]))?;
    let k: usize = a[1].parse()?;
    let (sigma, albedo) = (triple(&a[2])?, triple(&a[3])?);
    let g = a.get(4).map_or(Ok(0.0), |s| s.parse())?;
    let photons = a.get(5).map_or(Ok(100_000), |s| s.parse())?;
    let surface = match a.get(6) {
        None => Surface::IndexMatched,
        Some(s) => {
            let v: Vec<f64> = s.split(',').map(|x| x.parse()).collect::<Result<_, _>>()?;
            anyhow::ensure!(v.len() == 2, "ior,alpha: {s}");
            Surface::RoughDielectric {
                ior: v[0],
                alpha: v[1],
            }
        }
    };
    let scene = Scene::new(ds.mesh.clone())?;
    let geo = frame_geometry(&scene, &ds, k).context("the frame's laser ray misses the mesh")?;
    let settings = TraceSettings {
        surface,
        ..TraceSettings::for_medium(sigma, albedo, g, photons, 1)
    };
    let records = trace_frame(&scene, Boundary::of(&scene), &geo, &settings, k);
    let img = ds.read_frame(k)?;
    let sectors: usize = std::env::var("SECTORS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1)
        .max(1);
    let frame =
        FrameRings::with_sectors(&scene, geo, k, &img, ds.spec.frames[k].exposure_s, sectors);
    let model = model_rings(&frame, &records, &settings, sigma, albedo);
    println!(
        "{} records; boundary {:?}",
        records.len(),
        Boundary::of(&scene)
    );
    for (j, m) in model.iter().enumerate() {
        if frame.count[j] == 0 {
            continue;
        }
        let ratio: [f64; 3] = std::array::from_fn(|c| m[c] / frame.data[j][c]);
        println!(
            "ring {:6.2} mm sector {} {:5} px: data {:.3e} model/data {:.3?}",
            ring_edge((j / sectors) as u32),
            j % sectors,
            frame.count[j],
            frame.data[j][1],
            ratio
        );
    }
    Ok(())
}
