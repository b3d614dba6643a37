//! A heterogeneous medium fitted cell by cell through the tracer (`volume::gridfit`), written as
//! a volume model that `subsurf evaluate --model` judges.
//!
//! ```text
//! cargo run --release --example volume_gridfit -- SCAN TRAIN OUT.json
//! subsurf evaluate --model OUT.json --scan SCAN --frames HELD --json --cache off
//! ```
//!
//! Environment: `CELLS` (cells along the longest side, 12), `PHOTONS` (per frame and round,
//! 2000), `ROUNDS` (8), `SMOOTH` and `PULL` (the penalties' weights, `gridfit::SMOOTH` and `PULL`), `G` (0);
//! `BOUNDARY` (`index-matched`, or `dielectric:IOR:ROUGHNESS` as `subsurf fit --volume-boundary`);
//! `SECTORS` (per ring, 1); `CV=s1:p1,s2:p2,…` scores those candidates and the homogeneous medium by cross-validation
//! over whole turntable angles of TRAIN (`FOLDS`, 4) first and fits the best, judging the
//! held-out rings by a trace of `JUDGE` photons a frame (`PHOTONS`), each ring in `JUDGE_SECTORS`
//! (`SECTORS`).
use anyhow::{Context, Result};
use subsurf::dataset::{Dataset, parse_frame_list};
use subsurf::volume::fit::{HomogeneousFit, fit_homogeneous};
use subsurf::volume::gridfit::{GridFit, cross_validate, fit_grid};
use subsurf::volume::{BoundaryModel, FitInfo, MediumGrid, VolumeMesh, VolumeModel};

fn main() -> Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(a.len() >= 3, "usage: volume_gridfit SCAN TRAIN OUT.json");
    let ds = Dataset::open(&a[0]).with_context(|| format!("opening {}", a[0]))?;
    let train = parse_frame_list(&a[1]).map_err(anyhow::Error::msg)?;
    let out = std::path::PathBuf::from(&a[2]);
    let env = |k: &str, d: f64| {
        std::env::var(k)
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(d)
    };
    let t0 = std::time::Instant::now();
    let say = |s: &str| eprintln!("{s} ({:.0} s)", t0.elapsed().as_secs_f64());
    let boundary: BoundaryModel = std::env::var("BOUNDARY")
        .unwrap_or_else(|_| "index-matched".into())
        .parse()
        .map_err(anyhow::Error::msg)?;
    let surface = boundary.surface()?;
    let mut opts = GridFit {
        global: HomogeneousFit {
            photons: match surface {
                subsurf::volume::dielectric::Surface::IndexMatched => 1500,
                _ => subsurf::volume::model::DIELECTRIC_FIT_PHOTONS,
            },
            rounds: 12,
            g: env("G", 0.0),
            start: (2.0, 0.98),
            floor: ds.spec.noise_floor.unwrap_or(0.0),
            seed: 1,
            surface,
        },
        cells: env("CELLS", 12.0) as usize,
        photons: env("PHOTONS", 2000.0) as usize,
        rounds: env("ROUNDS", 8.0) as usize,
        smooth: env("SMOOTH", subsurf::volume::gridfit::SMOOTH),
        pull: env("PULL", subsurf::volume::gridfit::PULL),
        sectors: env("SECTORS", subsurf::volume::gridfit::SECTORS as f64) as usize,
    };
    if let Ok(cv) = std::env::var("CV") {
        let cands: Vec<(f64, f64)> = cv
            .split(',')
            .filter_map(|c| {
                let (s, p) = c.split_once(':')?;
                Some((s.parse().ok()?, p.parse().ok()?))
            })
            .collect();
        let judge = env("JUDGE", opts.photons as f64) as usize;
        let folds = env("FOLDS", 4.0) as usize;
        let judge_sectors = env("JUDGE_SECTORS", opts.sectors as f64) as usize;
        let scored = cross_validate(
            &ds,
            &train,
            &opts,
            &cands,
            folds,
            judge,
            judge_sectors,
            &say,
        )?;
        for s in &scored {
            println!(
                "cv: smooth {} pull {}: ring loss {:.4} over {} rings",
                s.smooth, s.pull, s.loss, s.rings
            );
        }
        let best = scored
            .iter()
            .min_by(|x, y| x.loss.total_cmp(&y.loss))
            .context("no candidate")?;
        println!("chosen: smooth {} pull {}", best.smooth, best.pull);
        if best.pull.is_infinite() {
            opts.rounds = 0;
        } else {
            opts.smooth = best.smooth;
            opts.pull = best.pull;
        }
    }
    let global = fit_homogeneous(&ds, &train, &opts.global, &|_, _| {})?;
    say(&format!(
        "homogeneous: sigma_t {:.3?} /mm, albedo {:.4?}",
        global.sigma_t, global.albedo
    ));
    let fitted = fit_grid(&ds, &train, &global, &opts, &say)?;
    let g = &fitted.grid;
    let grid = MediumGrid::of_channels(g);
    let (smin, smax) = grid
        .sigma_t
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), s| {
            (a.min(s[1]), b.max(s[1]))
        });
    let mut frames = train.clone();
    frames.sort_unstable();
    frames.dedup();
    let model = VolumeModel {
        g: opts.global.g,
        boundary,
        grid,
        mesh: VolumeMesh::of(&ds.mesh),
        fit: FitInfo {
            frames,
            photons: opts.photons,
            rounds: opts.rounds,
            loss: fitted.loss.map(|l| if l.0.is_finite() { l.0 } else { 0.0 }),
            rings: fitted.loss.map(|l| l.1),
            seconds: t0.elapsed().as_secs_f64(),
            subsurf_version: env!("CARGO_PKG_VERSION").to_string(),
        },
    };
    model.write(&out)?;
    println!(
        "grid {:?} cells of {:.2} mm, {} fitted; green sigma_t {smin:.3}-{smax:.3} /mm; ring loss {:.4}/{:.4}/{:.4}; {:.0} s; wrote {}",
        g[0].dims,
        g[0].cell_mm[0],
        fitted.active,
        fitted.loss[0].0,
        fitted.loss[1].0,
        fitted.loss[2].0,
        t0.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}
