//! A heterogeneous medium grown from the training frames' own media (`volume::local`), its
//! regulariser chosen by cross-validation over turntable angles, and its predictions of the
//! held-out frames written as images for `subsurf evaluate --images`.
//!
//! ```text
//! cargo run --release --example volume_grow -- SCAN TRAIN HELD OUTDIR [g]
//! subsurf evaluate --model M --scan SCAN --frames HELD --images OUTDIR --json --cache off
//! ```
//!
//! `PRED` (environment) sets the photons per predicted frame and channel (default 100,000).
use anyhow::{Context, Result};
use subsurf::dataset::{Dataset, parse_frame_list, write_exr};
use subsurf::geometry::Scene;
use subsurf::volume::dielectric::Surface;
use subsurf::volume::fit::{HomogeneousFit, frame_geometry};
use subsurf::volume::local::{LocalFit, grow};
use subsurf::volume::medium::grid_image;
use subsurf::volume::trace::Boundary;

fn main() -> Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        a.len() >= 4,
        "usage: volume_grow SCAN TRAIN HELD OUTDIR [g]"
    );
    let ds = Dataset::open(&a[0]).with_context(|| format!("opening {}", a[0]))?;
    let train = parse_frame_list(&a[1]).map_err(anyhow::Error::msg)?;
    let held = parse_frame_list(&a[2]).map_err(anyhow::Error::msg)?;
    let out = std::path::PathBuf::from(&a[3]);
    let g = a.get(4).and_then(|s| s.parse().ok()).unwrap_or(0.0);
    let env = |k: &str, d: usize| {
        std::env::var(k)
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(d)
    };
    let opts = LocalFit {
        global: HomogeneousFit {
            photons: 1500,
            rounds: 12,
            g,
            start: (2.0, 0.98),
            floor: ds.spec.noise_floor.unwrap_or(0.0),
            seed: 1,
            surface: subsurf::volume::dielectric::Surface::IndexMatched,
        },
        photons: env("LOCAL_PHOTONS", 3000),
        rounds: env("LOCAL_ROUNDS", 8),
        min_rings: 3,
        bandwidths: vec![1.5, 3.0, 6.0, 12.0],
        shrinkage: vec![0.01, 0.1, 1.0],
        cells: env("CELLS", 16),
        cv_photons: env("CV_PHOTONS", 1000),
        folds: 5,
    };
    let t0 = std::time::Instant::now();
    let grown = grow(&ds, &train, &opts, &|s| {
        eprintln!("{s} ({:.0} s)", t0.elapsed().as_secs_f64())
    })?;
    let best = &grown.candidates[0];
    println!(
        "chosen: h {:?} mm, p {} (cross-validated ring loss {:.4}); the scan's medium scored {:.4}; {:.0} s",
        best.bandwidth,
        best.shrinkage,
        best.loss,
        grown
            .candidates
            .iter()
            .find(|c| c.bandwidth.is_none())
            .map_or(f64::NAN, |c| c.loss),
        t0.elapsed().as_secs_f64()
    );
    let scene = Scene::new(ds.mesh.clone())?;
    let boundary = Boundary::of(&scene);
    let photons = env("PRED", 100_000);
    std::fs::create_dir_all(&out)?;
    for &k in &held {
        let f = &ds.spec.frames[k];
        let cam = &ds.spec.cameras[f.camera];
        let img = match frame_geometry(&scene, &ds, k) {
            Some(geo) => grid_image(
                &scene,
                boundary,
                &geo,
                &grown.grid,
                g,
                Surface::IndexMatched,
                photons,
                7,
                k,
            ),
            None => subsurf::dataset::Image::new(cam.width as usize, cam.height as usize, 3),
        };
        write_exr(&out.join(subsurf::evaluate::images::image_name(k)), &img)?;
    }
    eprintln!(
        "predicted {} frames in {:.0} s",
        held.len(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
