//! How precisely a held-out set's mean log E (Eq. 8, Table 1: the mean over frames of each
//! frame's RMS log ratio) is known from its samples: the bootstrap standard error of
//! `subsurf evaluate`'s mean, resampling each frame's vertices (all channels of a vertex together)
//! with replacement, the model fixed. Behind BENCHMARKS.md's `subsurf align` section:
//! the held-out error of sample-torus moves under sub-pixel motions of the mesh by about this
//! much.
//!
//! ```sh
//! cargo run --release -p subsurf --example held_out_se -- SCAN MODEL.ply FRAMES [RESAMPLES]
//! ```
//! Samples are those `evaluate` compares at the vertices, by the model's fit record.
use std::path::Path;

use rand::{Rng, SeedableRng};
use subsurf::dataset::{Dataset, select_frames};
use subsurf::evaluate::model_at;
use subsurf::model::LogEAccumulator;
use subsurf::modelfile::ModelFile;
use subsurf::pipeline::{Context, PipelineOptions, StoreOptions, register_one};
use subsurf::store::PointSet;

/// Per held-out frame, per vertex compared: the squared ln ratio per channel (NaN: not compared).
type FrameRows = Vec<[f64; 3]>;

fn rows(ctx: &Context, model: &ModelFile, k: usize) -> Result<FrameRows, String> {
    let reg = register_one(ctx, k)?;
    let at = model_at(ctx, model, reg.triangle, reg.x_i).ok_or("no model at x_i")?;
    let store = ctx.store().ok_or("no sample store")?;
    let fs = store
        .samples(k, PointSet::Vertices)
        .map_err(|e| e.to_string())?
        .ok_or("no samples")?;
    let mut out = Vec::new();
    for s in fs.samples.iter() {
        let v = s.vertex as usize;
        let a = model.vertices[v].alpha.map(f64::from);
        let (r, phi) = at.frame.polar(reg.x_i, ctx.ds.mesh.positions[v]);
        let ln = at.ln_eval(r, phi);
        let mut row = [f64::NAN; 3];
        for c in 0..3 {
            let mut acc = LogEAccumulator::default();
            if s.valid & (1 << c) != 0
                && acc.add_ln(a[c].ln() + ln[c], s.value[c], ctx.opts.error_threshold)
            {
                row[c] = acc.sum_sq;
            }
        }
        if row.iter().any(|x| x.is_finite()) {
            out.push(row);
        }
    }
    Ok(out)
}

/// The mean over frames of each frame's log E per channel (frames without a sample in a channel
/// left out of that channel's mean, as `LogEStats` does).
fn mean_log_e(frames: &[Vec<&[f64; 3]>]) -> [f64; 3] {
    let mut out = [0.0; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let per: Vec<f64> = frames
            .iter()
            .filter_map(|f| {
                let x: Vec<f64> = f.iter().map(|r| r[c]).filter(|x| x.is_finite()).collect();
                (!x.is_empty()).then(|| (x.iter().sum::<f64>() / x.len() as f64).sqrt())
            })
            .collect();
        *o = per.iter().sum::<f64>() / per.len().max(1) as f64;
    }
    out
}

fn run(a: &[String]) -> Result<(), String> {
    if a.len() < 3 {
        return Err("usage: held_out_se SCAN MODEL.ply FRAMES [RESAMPLES]".into());
    }
    let ds = Dataset::open(Path::new(&a[0])).map_err(|e| e.to_string())?;
    let model = ModelFile::read(Path::new(&a[1])).map_err(|e| e.to_string())?;
    let frames =
        select_frames(ds.spec.frames.len(), Some(&a[2]), None).map_err(|e| e.to_string())?;
    let resamples: usize = a
        .get(3)
        .map_or(Ok(4000), |x| x.parse())
        .map_err(|_| "RESAMPLES")?;
    let mut opts = PipelineOptions::for_dataset(&ds);
    if let Some(r) = &model.fitted_with {
        opts = opts.with_fit_record(r);
    }
    let ctx = Context::new(&ds, opts).map_err(|e| e.to_string())?;
    let held =
        subsurf::pipeline::extract::extract(&ctx, &frames, None, &StoreOptions::default(), &())
            .map_err(|e| e.to_string())?;
    let ctx = ctx.with_store(held);
    let per: Vec<(usize, FrameRows)> = frames
        .iter()
        .filter_map(|&k| rows(&ctx, &model, k).ok().map(|r| (k, r)))
        .filter(|(_, r)| !r.is_empty())
        .collect();
    let all: Vec<Vec<&[f64; 3]>> = per.iter().map(|(_, r)| r.iter().collect()).collect();
    let mean = mean_log_e(&all);
    let mut rng = rand::rngs::StdRng::seed_from_u64(24);
    let mut draws: Vec<[f64; 3]> = Vec::with_capacity(resamples);
    for _ in 0..resamples {
        let frames: Vec<Vec<&[f64; 3]>> = per
            .iter()
            .map(|(_, r)| {
                (0..r.len())
                    .map(|_| &r[rng.random_range(0..r.len())])
                    .collect()
            })
            .collect();
        draws.push(mean_log_e(&frames));
    }
    let sd = |c: usize| {
        let m = draws.iter().map(|d| d[c]).sum::<f64>() / draws.len() as f64;
        (draws.iter().map(|d| (d[c] - m).powi(2)).sum::<f64>() / (draws.len() - 1) as f64).sqrt()
    };
    for (k, r) in &per {
        println!("frame {k}: {} vertices compared", r.len());
    }
    let se = [sd(0), sd(1), sd(2)];
    println!(
        "mean log E {:.4} {:.4} {:.4}; bootstrap SE over the frames' vertices ({resamples} resamples) {:.4} {:.4} {:.4} ({:.1} %, {:.1} %, {:.1} %)",
        mean[0],
        mean[1],
        mean[2],
        se[0],
        se[1],
        se[2],
        100.0 * se[0] / mean[0],
        100.0 * se[1] / mean[1],
        100.0 * se[2] / mean[2]
    );
    Ok(())
}

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    if let Err(e) = run(&a) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
