//! Which of a preset's settings moves a model, one at a time (made when the draft preset
//! rendered the tradeoff benchmark's sphere 11–14 % dark). Fits a scan with variants of the fit
//! options, each the same as a preset but for one setting, and prints per variant:
//!
//! - `render`: the pipeline's fit, its exact render against the exact render of the ground truth
//!   (mean relative pixel error, absolute and signed, as `bench tradeoff`), whether the run has a
//!   baseline; with `nobase`, the same model rendered without its baseline;
//! - `lp`: per light position, the variant's fit against the exact fit of the same samples at
//!   n = 1, 2, 3 (m = 1), by the reflectance each predicts within reach
//!   (`baseline::reflectance_within_reach`, both without a baseline): the mean and spread of
//!   ln(variant / exact), and the fits that failed in the variant only;
//! - `pooled`: the baseline's pooled fit (red, every light position's samples) at n = 1, 2, 3:
//!   converged or not, after how many iterations, and whether the drop rule keeps its terms.
//!
//! The scans: `subsurf bench tradeoff --keep --work DIR` leaves `DIR/scan-{0,1,2}` (truth:
//! `DIR/scan-0/ground-truth.ply`). Then, e.g.
//!
//! ```text
//! cargo run --release -p subsurf --example preset_ablation -- DIR/scan-0 DIR/scan-0/ground-truth.ply \
//!     draft=8,2,30,1 sub1=8,1,30,1 bins16=16,2,30,1 it100=8,2,100,1 balanced=16,1,100,4 \
//!     balanced-nobase=16,1,100,4,nobase exact=0,1,200,1 draft=8,2,30,1,lp draft=8,2,30,1,pooled
//! ```
//!
//! A variant is `name=bins,subsample,iterations,segments[,mode]` with n = 3 and bins 0 = every
//! sample (no fast mode).
use std::path::Path;
use std::time::Instant;

use anyhow::{Context as _, Result, anyhow, bail};
use subsurf::dataset::{Dataset, select_frames};
use subsurf::fit::{FitOptions, Terms, fit_expsum};
use subsurf::model::{ColourModel, Support};
use subsurf::modelfile::{ColourMode, ModelFile};
use subsurf::pipeline::fit::fit_at;
use subsurf::pipeline::register::registered;
use subsurf::pipeline::select::{ChannelSamples, group_samples, select_groups};
use subsurf::pipeline::{FrameCounts, PipelineOptions, fit_dataset, prepare, unsupported_term};
use subsurf::render::{self, Camera, Image, Light, Method, RenderOptions};

/// One variant of the command line.
struct Variant {
    name: String,
    fit: FitOptions,
    segments: usize,
    mode: String,
}

fn parse(arg: &str) -> Result<Variant> {
    let (name, rest) = arg
        .split_once('=')
        .ok_or_else(|| anyhow!("variant {arg:?}: want name=bins,subsample,iterations,segments"))?;
    let p: Vec<&str> = rest.split(',').collect();
    if p.len() < 4 {
        bail!("variant {arg:?}: want name=bins,subsample,iterations,segments[,mode]");
    }
    let num = |s: &str| -> Result<usize> { s.parse().with_context(|| format!("in {arg:?}")) };
    let bins = num(p[0])?;
    Ok(Variant {
        name: name.to_string(),
        fit: FitOptions {
            terms: Terms::Fixed(3),
            bins: (bins > 0).then_some(bins),
            subsample: num(p[1])?,
            max_iterations: num(p[2])?,
            ..FitOptions::default()
        },
        segments: num(p[3])?,
        mode: p.get(4).unwrap_or(&"render").to_string(),
    })
}

/// The exact render from the default view under the default lights, as `bench tradeoff`.
fn render_exact(model: &ModelFile, px: u32) -> Result<Image> {
    let (lo, hi) = model.bounds();
    let cam = Camera::framing(lo, hi, render::DEFAULT_VIEW, px, px)?;
    let lights = Light::defaults_for(model.bounds());
    let opts = RenderOptions {
        method: Method::Exact,
        ..RenderOptions::default()
    };
    Ok(render::render(model, &lights, &cam, &opts)?.image)
}

/// Every light position's samples, as the pipeline selects them.
fn light_positions(ds: &Dataset) -> Result<Vec<ChannelSamples>> {
    let frames = select_frames(ds.spec.frames.len(), None, None).map_err(|e| anyhow!(e))?;
    // One decode pass into the run's sample store, as `subsurf fit` does (`--cache off`: an
    // ablation leaves nothing in the dataset).
    let store = subsurf::pipeline::StoreOptions {
        cache: subsurf::pipeline::Cache::Off,
        ..Default::default()
    };
    let ctx = prepare(ds, &frames, &PipelineOptions::for_dataset(ds), &store, &())?;
    let regs = registered(&ctx, &frames, &mut FrameCounts::default());
    let groups = select_groups(&ctx, &regs);
    Ok(groups
        .keys
        .iter()
        .filter_map(|k| group_samples(&ctx, &regs, k).ok().map(|(d, _)| d))
        .collect())
}

fn per_light_position(groups: &[ChannelSamples], v: &Variant) {
    let exact = FitOptions {
        terms: Terms::Fixed(3),
        ..FitOptions::default()
    };
    let mut fails = 0;
    for n in 1..=3 {
        let mut logs = Vec::new();
        for data in groups {
            let (lo, hi) = data
                .iter()
                .flatten()
                .fold((f64::INFINITY, 0.0f64), |(a, b), x| {
                    (a.min(x.r), b.max(x.r))
                });
            let within = |m: &ColourModel| {
                subsurf::baseline::reflectance_within_reach(m, Support::new(lo, hi), None)
                    .map(|t| t.iter().sum::<f64>())
            };
            let a = fit_at(data, ColourMode::Shared, n, 1, &v.fit);
            let b = fit_at(data, ColourMode::Shared, n, 1, &exact);
            match (a, b) {
                (Ok(a), Ok(b)) => {
                    if let (Some(a), Some(b)) = (within(&a), within(&b)) {
                        logs.push((a / b).ln());
                    }
                }
                (Err(_), Ok(_)) => fails += 1,
                _ => {}
            }
        }
        let k = logs.len().max(1) as f64;
        let mean = logs.iter().sum::<f64>() / k;
        let sd = (logs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / k).sqrt();
        let worst = logs.iter().map(|x| x.abs()).fold(0.0, f64::max);
        println!(
            "{:<16} lp n={n}: {:4} light positions, ln(variant / exact) mean {:+.4} ± {:.4}, \
             sd {:.4}, largest |ln| {:.4}; failed in the variant only (n ≤ {n}): {fails}",
            v.name,
            logs.len(),
            mean,
            sd / k.sqrt(),
            sd,
            worst
        );
    }
}

fn pooled(groups: &[ChannelSamples], v: &Variant) {
    let (mut r, mut s) = (Vec::new(), Vec::new());
    for data in groups {
        let d = &data[0];
        let step = d.len().div_ceil(subsurf::pipeline::BASELINE_POOL).max(1);
        for x in d.iter().step_by(step) {
            r.push(x.r);
            s.push(x.s);
        }
    }
    println!("{:<16} pooled: {} red samples", v.name, r.len());
    for n in 1..=3 {
        let o = FitOptions {
            terms: Terms::Fixed(n),
            ..v.fit.clone()
        };
        let status = match fit_expsum(&r, &s, &o) {
            Ok(f) => format!(
                "converged after {} iterations, log E {:.5}, rates {:?}",
                f.iterations,
                f.log_e,
                f.model.terms.iter().map(|t| t.d).collect::<Vec<_>>()
            ),
            Err(e) => e.to_string(),
        };
        let free = FitOptions {
            require_convergence: false,
            ..o
        };
        let dropped = fit_expsum(&r, &s, &free)
            .ok()
            .and_then(|f| unsupported_term(&f.model, &r));
        println!("{:<16}   n={n}: {status}; drop rule: {dropped:?}", "");
    }
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 {
        bail!("usage: preset_ablation SCAN_DIR TRUTH.ply VARIANT...");
    }
    let ds = Dataset::open(Path::new(&args[0]))?;
    let truth = render_exact(&ModelFile::read(Path::new(&args[1]))?, 256)?;
    let frames = select_frames(ds.spec.frames.len(), None, None).map_err(|e| anyhow!(e))?;
    let mut groups: Option<Vec<ChannelSamples>> = None;
    for arg in &args[2..] {
        let v = parse(arg)?;
        if v.mode == "lp" || v.mode == "pooled" {
            if groups.is_none() {
                groups = Some(light_positions(&ds)?);
            }
            let g = groups.as_deref().unwrap_or_default();
            if v.mode == "lp" {
                per_light_position(g, &v);
            } else {
                pooled(g, &v);
            }
            continue;
        }
        let mut opts = PipelineOptions::for_dataset(&ds);
        opts.model.segments = v.segments;
        let t = Instant::now();
        let out = fit_dataset(&ds, &frames, &opts, &v.fit, &())?;
        let fit_s = t.elapsed().as_secs_f64();
        let has_baseline = out.model.baseline.is_some();
        let mut model = out.model;
        if v.mode == "nobase" {
            model.baseline = None;
        }
        let (abs, signed) =
            render::relative_pixel_errors(&render_exact(&model, 256)?, &truth, 1e-3)
                .ok_or_else(|| anyhow!("no comparable pixels"))?;
        println!(
            "{:<16} fit {fit_s:6.2} s, vs truth {:5.2} % (signed {:+5.2} %), baseline {}{}, \
             fitted / interpolated {} / {}",
            v.name,
            100.0 * abs,
            100.0 * signed,
            if has_baseline { "yes" } else { "NONE" },
            if v.mode == "nobase" { " (removed)" } else { "" },
            out.report.vertices_fitted,
            out.report.vertices_interpolated
        );
    }
    Ok(())
}
