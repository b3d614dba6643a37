//! What changes in a fit when the mesh moves (BENCHMARKS.md's `subsurf align` section, mesh
//! registration): the diagnostics behind "why a sub-pixel motion of the mesh moves held-out error".
//!
//! ```sh
//! # per frame: x_i, its triangle and the corners' models (status, order, log E, sampled range)
//! cargo run --release -p subsurf --example pose_diag -- corners SCAN MODEL.ply FRAMES
//! # per light position of a fit of SCAN without EXCLUDE: its frames, vertices, samples per channel
//! cargo run --release -p subsurf --example pose_diag -- lights SCAN EXCLUDE
//! # two models of one mesh vertex by vertex: status changes, how far ln R_d moved (2–6 mm);
//! # with VERBOSE=1 every fitted vertex whose curve moved by more than 0.3
//! cargo run --release -p subsurf --example pose_diag -- cmp A.ply B.ply
//! ```
use std::collections::BTreeMap;
use std::path::Path;

use subsurf::dataset::{Dataset, select_frames};
use subsurf::modelfile::{ModelFile, VertexStatus, model_of};
use subsurf::pipeline::register::registered;
use subsurf::pipeline::select::{group_samples, select_groups};
use subsurf::pipeline::{Context, PipelineOptions, StoreOptions, prepare, register_one};

fn corners(scan: &str, model: &str, frames: &str) -> Result<(), String> {
    let ds = Dataset::open(Path::new(scan)).map_err(|e| e.to_string())?;
    let model = ModelFile::read(Path::new(model)).map_err(|e| e.to_string())?;
    let frames =
        select_frames(ds.spec.frames.len(), Some(frames), None).map_err(|e| e.to_string())?;
    let mut opts = PipelineOptions::for_dataset(&ds);
    if let Some(r) = &model.fitted_with {
        opts = opts.with_fit_record(r);
    }
    let ctx = Context::new(&ds, opts).map_err(|e| e.to_string())?;
    for k in frames {
        let reg = match register_one(&ctx, k) {
            Ok(r) => r,
            Err(e) => {
                println!("frame {k}: {e}");
                continue;
            }
        };
        let t = ds.mesh.triangles[reg.triangle as usize];
        let w = ctx.scene.barycentric(reg.triangle, reg.x_i);
        println!(
            "frame {k}: x_i {:.3?} triangle {} barycentric {:.3?}",
            reg.x_i, reg.triangle, w
        );
        for v in t {
            let m = &model.vertices[v as usize];
            println!(
                "   v{v} {:?} n{} m{} log E {:.3} r {:.2?} alpha {:.3?}",
                m.status, m.terms, m.segments, m.log_e, m.r_range, m.alpha
            );
        }
    }
    Ok(())
}

fn lights(scan: &str, exclude: &str) -> Result<(), String> {
    let ds = Dataset::open(Path::new(scan)).map_err(|e| e.to_string())?;
    let frames =
        select_frames(ds.spec.frames.len(), None, Some(exclude)).map_err(|e| e.to_string())?;
    let opts = PipelineOptions::for_dataset(&ds);
    let ctx =
        prepare(&ds, &frames, &opts, &StoreOptions::default(), &()).map_err(|e| e.to_string())?;
    let mut counts = Default::default();
    let regs = registered(&ctx, &frames, &mut counts);
    let groups = select_groups(&ctx, &regs);
    for (key, members) in groups.keys.iter().zip(&groups.members) {
        let (data, _) = group_samples(&ctx, &regs, key).map_err(|e| format!("{e:?}"))?;
        let fr: Vec<usize> = key.frames[0]
            .iter()
            .map(|&i| regs[i as usize].frame)
            .collect();
        let (lo, hi) = data[1].iter().fold((f64::INFINITY, 0.0f64), |(a, b), x| {
            (a.min(x.r), b.max(x.r))
        });
        println!(
            "light position of frames {fr:?}: {} vertices, samples r/g/b {} {} {}, r {lo:.2}-{hi:.2} mm, x_i {:.2?}",
            members.len(),
            data[0].len(),
            data[1].len(),
            data[2].len(),
            regs[key.anchors[0] as usize].x_i
        );
    }
    Ok(())
}

fn cmp(pa: &str, pb: &str) -> Result<(), String> {
    let a = ModelFile::read(Path::new(pa)).map_err(|e| e.to_string())?;
    let b = ModelFile::read(Path::new(pb)).map_err(|e| e.to_string())?;
    if a.vertices.len() != b.vertices.len() {
        return Err("the models have different vertex counts".into());
    }
    let verbose = std::env::var("VERBOSE").is_ok();
    // (status A -> status B) -> (vertices, sum and max of the largest |Δ ln R_d|).
    let mut moved: BTreeMap<String, (usize, f64, f64)> = BTreeMap::new();
    for (i, (va, vb)) in a.vertices.iter().zip(&b.vertices).enumerate() {
        let key = format!("{:?} -> {:?}", va.status, vb.status);
        let entry = moved.entry(key).or_insert((0, 0.0, 0.0));
        entry.0 += 1;
        if va.status == VertexStatus::NoModel || vb.status == VertexStatus::NoModel {
            continue;
        }
        let ma = model_of(&a.shape, va.terms as usize, &va.params).map_err(|e| e.to_string())?;
        let mb = model_of(&b.shape, vb.terms as usize, &vb.params).map_err(|e| e.to_string())?;
        let worst = [2.0, 3.0, 4.0, 6.0]
            .iter()
            .flat_map(|&r| {
                let (x, y) = (ma.ln_eval(r, None), mb.ln_eval(r, None));
                (0..3).map(move |c| (x[c] - y[c]).abs())
            })
            .fold(0.0, f64::max);
        entry.1 += worst;
        entry.2 = entry.2.max(worst);
        if verbose && worst > 0.3 && va.status == VertexStatus::Fitted {
            println!(
                "v{i} {:.2?} {:?} -> {:?} n {} -> {} log E {:.3} -> {:.3} r {:.2?} -> {:.2?}: {worst:.3}",
                a.positions[i],
                va.status,
                vb.status,
                va.terms,
                vb.terms,
                va.log_e,
                vb.log_e,
                va.r_range,
                vb.r_range
            );
        }
    }
    for (k, (n, sum, max)) in moved {
        println!(
            "{k}: {n} vertices, largest |Δ ln R_d| at 2, 3, 4, 6 mm: mean {:.4}, max {max:.4}",
            sum / n as f64
        );
    }
    Ok(())
}

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let r = match (a.first().map(String::as_str), a.len()) {
        (Some("corners"), 4) => corners(&a[1], &a[2], &a[3]),
        (Some("lights"), 3) => lights(&a[1], &a[2]),
        (Some("cmp"), 3) => cmp(&a[1], &a[2]),
        _ => {
            Err("usage: pose_diag corners SCAN MODEL FRAMES | lights SCAN EXCLUDE | cmp A B".into())
        }
    };
    if let Err(e) = r {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
