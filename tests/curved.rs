//! Curved objects (issue 4): a noise-free simulated sphere, every 7th frame held out of the fit.
//! The fitted per-vertex model must predict the held-out frames about as well as the ground
//! truth does (the floor left by pixel sampling and registration; measured 1.45–1.65× of it on
//! this small scan, 1.4× on the 4-angle scan of the issue), must claim no term its
//! samples do not support, and must record each vertex's sampled distance range.
//!
//! Before fits were restricted to supported terms and predictions between vertices blended the
//! corners' ln R_d instead of unaligned parameters, this scan gave a held-out mean log E of about
//! 1.3 against a floor of about 0.02.
use subsurf::dataset::{Dataset, select_frames};
use subsurf::evaluate::evaluate_frames;
use subsurf::fit::FitOptions;
use subsurf::modelfile::{ModelFile, VertexStatus, model_of};
use subsurf::pipeline::{MIN_DECAY, PipelineOptions, fit_dataset};
use subsurf::simulate::{SimConfig, SimObject, simulate};

#[test]
fn noise_free_sphere_predicts_held_out_frames_near_the_floor() {
    let tmp = tempfile::tempdir().unwrap();
    // `subsurf simulate --object sphere --vertices 800 --size 256 --angles 2 --raster 8
    //  --noise-free --anisotropy 0 --heterogeneity 0` (alpha texture ±10 % kept).
    let mut cfg = SimConfig::for_object(
        SimObject::Sphere {
            radius: 10.0,
            rings: 20,
        },
        256,
        2,
        8,
    )
    .noise_free();
    cfg.field.anisotropy = 0.0;
    cfg.field.heterogeneity = 0.0;
    simulate(&cfg, tmp.path(), &()).expect("simulate");
    let ds = Dataset::open(tmp.path()).unwrap();
    let n = ds.spec.frames.len();
    let held: Vec<usize> = (3..n).step_by(7).collect();
    let list = held
        .iter()
        .map(|k| k.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let train = select_frames(n, None, Some(&list)).unwrap();
    let opts = PipelineOptions::for_dataset(&ds);
    let out = fit_dataset(&ds, &train, &opts, &FitOptions::default(), &()).expect("fit");
    assert_eq!(out.report.vertices_no_model, 0, "{:?}", out.report.failures);

    // Only supported terms, and the sampled range of every fitted vertex is recorded.
    for vm in out.model.vertices.iter() {
        if vm.status != VertexStatus::Fitted {
            continue;
        }
        let [lo, hi] = vm.r_range.map(f64::from);
        assert!(lo > 0.0 && hi > lo, "range {:?}", vm.r_range);
        let m = model_of(&out.model.shape, vm.terms as usize, &vm.params).unwrap();
        let f = m.channel(0).unwrap();
        for t in &f.segments[0].terms {
            assert!(-t.d * (hi - lo) >= MIN_DECAY, "non-decaying term {t:?}");
        }
    }
    let p = tmp.path().join("model.ply");
    out.model.write(&p).unwrap();
    let model = ModelFile::read(&p).unwrap();

    let (_, fitted) = evaluate_frames(&ds, &model, &held, &opts, &()).unwrap();
    let truth = ModelFile::read(&tmp.path().join("ground-truth.ply")).unwrap();
    let (_, floor) = evaluate_frames(&ds, &truth, &held, &opts, &()).unwrap();
    for c in 0..3 {
        let (f, g) = (fitted.mean[c].unwrap(), floor.mean[c].unwrap());
        eprintln!("channel {c}: held-out mean log E fitted {f:.4}, ground truth {g:.4}");
        // Since samples lit by the laser spot's light and grazing samples are dropped (scanfit,
        // samples.rs), the floor is ~0.0015 instead of ~0.02 and the fit's own error (~0.035)
        // dominates: the bound is on the fitted model, the floor must stay far below it.
        assert!(
            f < 0.05 && g < 0.25 * f,
            "channel {c}: fitted {f} vs ground truth {g}"
        );
        let (fm, gm) = (fitted.median[c].unwrap(), floor.median[c].unwrap());
        assert!(fm < 0.06 && gm < 0.01, "channel {c}: medians {fm} {gm}");
    }
}
