//! The volume model's go/no-go: a homogeneous medium (σ_t, α per channel) fitted on the true
//! mesh to a scan's training frames, and its predictions of the held-out frames written as
//! images for `subsurf evaluate --images`.
//!
//! ```text
//! cargo run --release --example volume_gonogo -- ../shared/data/sample-torus 0-95 96-103 /tmp/vol [photons] [rounds] [g]
//! subsurf evaluate --model M --scan ../shared/data/sample-torus --frames 96-103 --images /tmp/vol --json --cache off
//! ```
//!
//! `PRED` (environment) sets the photons per predicted frame (default 100,000), `START=s,a` the
//! start (default 2/mm, 0.98).
use anyhow::{Context, Result};
use subsurf::dataset::{Dataset, parse_frame_list, write_exr};
use subsurf::volume::fit::{HomogeneousFit, fit_homogeneous, predict};

fn main() -> Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        a.len() >= 4,
        "usage: volume_gonogo SCAN TRAIN HELD OUTDIR [photons] [rounds] [g]"
    );
    let ds = Dataset::open(&a[0]).with_context(|| format!("opening {}", a[0]))?;
    let train = parse_frame_list(&a[1]).map_err(anyhow::Error::msg)?;
    let held = parse_frame_list(&a[2]).map_err(anyhow::Error::msg)?;
    let out = std::path::PathBuf::from(&a[3]);
    let num = |i: usize, d: f64| a.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let opts = HomogeneousFit {
        photons: num(4, 3000.0) as usize,
        rounds: num(5, 4.0) as usize,
        g: num(6, 0.0),
        start: std::env::var("START")
            .ok()
            .and_then(|s| {
                let (a, b) = s.split_once(',')?;
                Some((a.parse().ok()?, b.parse().ok()?))
            })
            .unwrap_or((2.0, 0.98)),
        floor: ds.spec.noise_floor.unwrap_or(0.0),
        seed: 1,
        surface: subsurf::volume::dielectric::Surface::IndexMatched,
    };
    let t0 = std::time::Instant::now();
    let model = fit_homogeneous(&ds, &train, &opts, &|round, m| {
        eprintln!(
            "round {round}: sigma_t {:.4?} albedo {:.5?} loss {:.4?} ({:.0} s)",
            m.sigma_t,
            m.albedo,
            m.loss,
            t0.elapsed().as_secs_f64()
        );
    })?;
    println!(
        "fitted sigma_t {:.4?} /mm, albedo {:.5?}, g {} in {:.0} s",
        model.sigma_t,
        model.albedo,
        model.g,
        t0.elapsed().as_secs_f64()
    );
    let photons = std::env::var("PRED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(100_000);
    std::fs::create_dir_all(&out)?;
    for (k, img) in predict(&ds, &held, &model, photons, 7)? {
        write_exr(&out.join(subsurf::evaluate::images::image_name(k)), &img)?;
    }
    eprintln!(
        "predicted {} frames in {:.0} s",
        held.len(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
