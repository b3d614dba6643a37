//! `subsurf bench render`: the renderer's figures for BENCHMARKS.md
//! (release mode; output pasted unedited).

use std::time::Instant;

use anyhow::{Context, Result};
use subsurf::render::{self, Camera, HierarchyParams, Method, RenderOptions};

/// The error-bound curve the benchmark walks: (ε, tail tolerance), loosest first.
pub const CURVE: [(f64, f64); 7] = [
    (1.0, 1e-3),
    (0.5, 1e-3),
    (0.3, 1e-3),
    (0.2, 1e-3),
    (0.1, 1e-4),
    (0.05, 1e-4),
    (0.02, 1e-5),
];

/// Hierarchical against exact transport on the built-in marble torus.
#[derive(Debug, clap::Args)]
pub struct RenderBench {
    /// Vertices of the built-in model (rounded to a torus grid).
    #[arg(long, default_value_t = 50_000)]
    vertices: usize,
    /// Image width and height.
    #[arg(long, default_value_t = 384)]
    size: u32,
    /// Write the speed/error curve as a PNG here.
    #[arg(long)]
    plot: Option<std::path::PathBuf>,
}

pub fn bench_render(b: RenderBench) -> Result<()> {
    let nu = ((b.vertices as f64 * 2.5).sqrt().round() as usize).max(3);
    let nv = (b.vertices / nu).max(3);
    let model = render::synthetic::marble_torus(nu, nv);
    let lights: Vec<render::Light> = vec![
        "point:120,-80,90:9000,9000,9000".parse()?,
        "dir:0.3,1,-0.4:0.3,0.3,0.35".parse()?,
    ];
    let (lo, hi) = model.bounds();
    let cam = Camera::framing(lo, hi, [0.6, -1.0, 0.8], b.size, b.size)?;
    println!(
        "model: marble torus, {} vertices, {} faces; image {}x{}; {} rayon threads",
        model.len(),
        model.triangles.len(),
        b.size,
        b.size,
        rayon::current_num_threads()
    );
    let t = Instant::now();
    let exact = render::render(
        &model,
        &lights,
        &cam,
        &RenderOptions {
            method: Method::Exact,
            eta: Some(1.3),
        },
    )
    .context("exact render")?;
    let t_exact = t.elapsed().as_secs_f64();
    println!();
    println!(
        "| method | ε (sr) | tail tol | transport s | render s | speed-up (transport) | speed-up (render) | mean rel. pixel error | clusters/receiver | points/receiver | build s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| exact | – | – | {:.3} | {:.3} | 1 | 1 | 0 | 0 | {:.0} | – |",
        exact.seconds[1],
        t_exact,
        exact.stats.point_evals as f64 / exact.stats.receivers.max(1) as f64
    );
    let mut curve = Vec::new();
    for (eps, tol) in CURVE {
        let opts = RenderOptions {
            method: Method::Hierarchical(HierarchyParams {
                max_solid_angle: eps,
                tail_tolerance: tol,
            }),
            eta: Some(1.3),
        };
        let t = Instant::now();
        let h = render::render(&model, &lights, &cam, &opts)?;
        let total = t.elapsed().as_secs_f64();
        let err = render::relative_pixel_error(&h.image, &exact.image, 1e-3).unwrap_or(f64::NAN);
        let r = h.stats.receivers.max(1) as f64;
        println!(
            "| hierarchical | {eps} | {tol:e} | {:.3} | {:.3} | {:.1} | {:.1} | {:.4}% | {:.0} | {:.0} | {:.3} |",
            h.seconds[1],
            total,
            exact.seconds[1] / h.seconds[1],
            t_exact / total,
            100.0 * err,
            h.stats.cluster_evals as f64 / r,
            h.stats.point_evals as f64 / r,
            h.stats.build_seconds
        );
        curve.push((total, err));
    }
    for q in [
        render::Quality::Draft,
        render::Quality::Balanced,
        render::Quality::Best,
    ] {
        println!(
            "`--quality {:?}` = ε {}, tail tol {:e}",
            q,
            q.params().max_solid_angle,
            q.params().tail_tolerance
        );
    }
    if let Some(path) = b.plot {
        subsurf::plot::tradeoff_curve(
            &path,
            "Hierarchical transport: time vs. error (exact = reference)",
            &curve,
            t_exact,
        )
        .with_context(|| format!("writing {}", path.display()))?;
        println!("plot: {}", path.display());
    }
    Ok(())
}
