//! Curved objects: a noise-free simulated sphere, every 7th frame held out of the fit.
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

/// A noise-free simulated sphere of radius 10 mm (`rings` rings, `size` px cameras, 2 turntable
/// angles, a `raster` x `raster` laser raster) of a homogeneous isotropic material (alpha
/// texture kept), in a temporary directory that lives as long as the returned guard.
fn isotropic_noise_free_sphere(
    rings: usize,
    size: u32,
    raster: usize,
) -> (tempfile::TempDir, Dataset) {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = SimConfig::for_object(
        SimObject::Sphere {
            radius: 10.0,
            rings,
        },
        size,
        2,
        raster,
    )
    .noise_free();
    cfg.field.anisotropy = 0.0;
    cfg.field.heterogeneity = 0.0;
    simulate(&cfg, tmp.path(), &()).expect("simulate");
    let ds = Dataset::open(tmp.path()).unwrap();
    (tmp, ds)
}

#[test]
fn noise_free_sphere_predicts_held_out_frames_near_the_floor() {
    // `subsurf simulate --object sphere --vertices 800 --size 256 --angles 2 --raster 8
    //  --noise-free --anisotropy 0 --heterogeneity 0` (alpha texture ±10 % kept).
    let (tmp, ds) = isotropic_noise_free_sphere(20, 256, 8);
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
        // samples.rs), the floor is ~0.0015 instead of ~0.02 and the fit's own error dominates:
        // the bound is on the fitted model, the floor must stay well below it. (Pooling the three
        // cameras' views of each spot brought the fit from ~0.0062 to ~0.0050 on the
        // same scan through the CLI, so the floor is now a quarter of it, no longer less.)
        assert!(
            f < 0.05 && g < 0.4 * f,
            "channel {c}: fitted {f} vs ground truth {g}"
        );
        let (fm, gm) = (fitted.median[c].unwrap(), floor.median[c].unwrap());
        assert!(fm < 0.06 && gm < 0.01, "channel {c}: medians {fm} {gm}");
    }
}

/// "Data is then collected from all images in which a particular location on the object was
/// illuminated" (section 5): the built-in rig's three cameras see every spot, and their frames
/// (one x_i, registered three times to within the pooling tolerance) are one light position,
/// fitted with all three views' samples. Without pooling (`pool_mm = 0`), each vertex took the
/// one frame whose x_i was closest and the other views' samples were dropped. Noise-free, so
/// the views agree and more of them must not predict held-out frames worse.
#[test]
fn every_view_of_a_spot_is_pooled_into_its_light_position() {
    let (_tmp, ds) = isotropic_noise_free_sphere(14, 128, 5);
    let n = ds.spec.frames.len();
    let held: Vec<usize> = (1..n).step_by(7).collect();
    let train: Vec<usize> = (0..n).filter(|k| !held.contains(k)).collect();
    let run = |pool_mm: Option<f64>| {
        let mut opts = PipelineOptions::for_dataset(&ds);
        opts.pool_mm = pool_mm;
        let out = fit_dataset(&ds, &train, &opts, &FitOptions::default(), &()).expect("fit");
        let (_, st) = evaluate_frames(&ds, &out.model, &held, &opts, &()).unwrap();
        (out.report, st.mean_over_channels().unwrap())
    };
    let (pooled, held_pooled) = run(None);
    let (single, held_single) = run(Some(0.0));
    let p = pooled.frames.pooling;
    eprintln!(
        "pooling {p:?}; samples pooled {} of {}; held-out mean log E pooled {held_pooled:.4}, \
         one view {held_single:.4}",
        pooled.samples.pooled, pooled.samples.used
    );
    // Three cameras per spot: light positions of (mostly) three frames each.
    // Half the median edge, at most the selection distance.
    assert!(
        p.tolerance_mm > 0.0 && p.tolerance_mm <= PipelineOptions::for_dataset(&ds).max_select_mm
    );
    assert!(
        p.light_positions > 0 && 2 * p.light_positions <= p.frames,
        "{p:?}"
    );
    assert!(p.pooled_frames >= p.frames / 2, "{p:?}");
    assert!(pooled.samples.pooled > 0);
    assert!(pooled.samples.used > single.samples.used);
    let s = single.frames.pooling;
    assert_eq!((s.pooled_frames, single.samples.pooled), (0, 0));
    assert_eq!(s.light_positions, s.frames);
    assert!(
        held_pooled <= 1.05 * held_single,
        "pooled {held_pooled} vs one view {held_single}"
    );
}
