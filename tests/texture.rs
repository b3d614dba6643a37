//! alpha finer than the mesh (section 5: "the modulation texture alpha(x_o) is
//! determined as higher resolution texture"), judged on frames the fit never saw, at surface
//! points between the vertices, beside the ground truth (the best case) and at the vertices
//! (where a face lattice has no detail, so both fits must agree there).
use subsurf::dataset::Dataset;
use subsurf::evaluate::{EvalPoints, evaluate_frames_at};
use subsurf::fit::FitOptions;
use subsurf::modelfile::ModelFile;
use subsurf::pipeline::{AlphaLattice, PipelineOptions, fit_dataset};
use subsurf::simulate::{SimConfig, SimObject, simulate};

/// The scene: the slab's top face as a coarse mesh (9 × 9 vertices, 2.5 mm edges), one camera
/// straight above at 0.25 mm per pixel whose 16 mm view stays inside the slab (no boundary
/// vertices, which read the background), an 8 × 8 laser raster, a realistic sensor; a
/// homogeneous isotropic material whose only variation is alpha along veins of 4 mm wavelength
/// (under two edge lengths) with a log-amplitude of 1 (ln alpha spans ±0.5 red, far above the
/// pixel noise). `subsurf simulate --object slab --vertices 81 --size 64 --top-down 0.25
/// --angles 1 --raster 8 --alpha-amplitude 1 --vein-wavelength 4 --heterogeneity 0
/// --anisotropy 0` writes the same scan.
pub fn textured_slab_config() -> SimConfig {
    let mut cfg = SimConfig::for_object(SimObject::Slab { size: 20.0, n: 9 }, 64, 1, 8)
        .top_down(0.25)
        .expect("a positive footprint");
    cfg.field.heterogeneity = 0.0;
    cfg.field.anisotropy = 0.0;
    cfg.field.alpha_amplitude = 1.0;
    cfg.field.vein_wavelength = 4.0;
    cfg.field.seed = 7;
    cfg
}

fn mean(s: &subsurf::pipeline::LogEStats) -> [f64; 3] {
    [0, 1, 2].map(|c| s.mean[c].expect("a mean per channel"))
}

#[test]
fn a_texture_finer_than_the_mesh_is_judged_at_surface_points() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = textured_slab_config();
    simulate(&cfg, tmp.path(), &()).expect("simulate");
    // The texture is recorded in the ground truth's configuration.
    let gt: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("ground-truth.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(gt["config"]["field"]["alpha_amplitude"], 1.0);
    assert_eq!(gt["config"]["field"]["vein_wavelength"], 4.0);
    let truth = ModelFile::read(&tmp.path().join("ground-truth.ply")).unwrap();
    assert!(
        truth.face_alpha.is_some(),
        "the ground truth holds the texture"
    );

    let ds = Dataset::open(tmp.path()).unwrap();
    let n = ds.spec.frames.len();
    let held: Vec<usize> = (0..n).filter(|k| k % 5 == 1).collect();
    let training: Vec<usize> = (0..n).filter(|k| k % 5 != 1).collect();
    let opts = PipelineOptions::for_dataset(&ds);
    let fit = |lattice: AlphaLattice| {
        let o = PipelineOptions {
            alpha_lattice: lattice,
            ..opts
        };
        fit_dataset(&ds, &training, &o, &FitOptions::default(), &())
            .expect("fit")
            .model
    };
    let with_lattice = fit(AlphaLattice::Auto);
    let vertex_only = fit(AlphaLattice::Off);
    assert!(vertex_only.face_alpha.is_none());
    let fa = with_lattice
        .face_alpha
        .as_ref()
        .expect("the fit wrote a lattice");
    assert!(!fa.is_flat());

    let surface = EvalPoints::Surface { level: 4 };
    let judge = |m: &ModelFile, at: EvalPoints| {
        let (evals, stats) = evaluate_frames_at(&ds, m, &held, &opts, at, &()).unwrap();
        let evaluated = evals.iter().filter(|e| e.skipped.is_none()).count();
        assert!(evaluated >= 10, "{evals:?}");
        mean(&stats)
    };
    let rows = [
        ("ground truth", &truth),
        ("lattice (auto)", &with_lattice),
        ("vertex alpha only", &vertex_only),
    ]
    .map(|(name, m)| {
        let (v, s) = (judge(m, EvalPoints::Vertices), judge(m, surface));
        eprintln!("{name:>18}: held-out mean log E at vertices {v:.4?}, at surface points (level 4) {s:.4?}");
        (v, s)
    });
    let [(gt_v, gt_s), (la_v, la_s), (vo_v, vo_s)] = rows;
    // Measured (dev and release alike, the scan is seeded): at surface points the lattice fit
    // 0.130 / 0.116 / 0.151 (r / g / b), the vertex-only fit 0.280 / 0.229 / 0.332, the ground
    // truth 0.117 / 0.125 / 0.152; at the vertices both fits 0.083 / 0.087 / 0.087 (the same
    // vertex models: the lattice pass runs after them and has no detail at corners), the
    // ground truth 0.088 / 0.100 / 0.117 (the fits' vertex alphas absorb the bilinear reads).
    for c in 0..3 {
        // The texture shows at surface points: without a lattice the error doubles.
        assert!(
            vo_s[c] > 1.5 * gt_s[c],
            "channel {c}: {vo_s:?} vs truth {gt_s:?}"
        );
        // The lattice fit recovers it: under 0.6 of the vertex-only error (measured
        // 0.47 / 0.51 / 0.45) and within 25 % of the ground truth (measured 1.11 / 0.93 / 0.99).
        assert!(la_s[c] < 0.6 * vo_s[c], "channel {c}: {la_s:?} vs {vo_s:?}");
        assert!(
            la_s[c] < 1.25 * gt_s[c],
            "channel {c}: {la_s:?} vs truth {gt_s:?}"
        );
        // At the vertices the two fits agree (within 2 %, measured equal) and are not worse
        // than the ground truth by more than the noise.
        assert!(
            (la_v[c] - vo_v[c]).abs() <= 0.02 * vo_v[c],
            "channel {c}: {la_v:?} vs {vo_v:?}"
        );
        assert!(
            vo_v[c] < 1.5 * gt_v[c],
            "channel {c}: {vo_v:?} vs truth {gt_v:?}"
        );
    }

    // The point set is the option's, and a bad level or another mesh is refused.
    assert!(
        evaluate_frames_at(
            &ds,
            &truth,
            &held,
            &opts,
            EvalPoints::Surface { level: 0 },
            &()
        )
        .is_err()
    );
    let mut other = truth.clone();
    other.triangles.swap(0, 1);
    other.face_alpha = None;
    assert!(evaluate_frames_at(&ds, &other, &held, &opts, surface, &()).is_err());
}

/// A fit is repeatable bit for bit whatever the number of threads: the alpha rounds' float sums
/// associate the same way (fixed chunks merged in order), so later rounds never inherit
/// rounding differences. Before the fixed chunks, this scene's model differed between 1 and 2
/// threads (and the sphere's; measured 2026-11-25 with `subsurf fit` under RAYON_NUM_THREADS).
#[test]
fn a_fit_is_the_same_on_any_number_of_threads() {
    let tmp = tempfile::tempdir().unwrap();
    simulate(&textured_slab_config(), tmp.path(), &()).expect("simulate");
    let ds = Dataset::open(tmp.path()).unwrap();
    let training: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let opts = PipelineOptions::for_dataset(&ds);
    let fit_on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let out = pool
            .install(|| fit_dataset(&ds, &training, &opts, &FitOptions::default(), &()))
            .expect("fit");
        assert!(out.report.alpha.rounds > 0, "the alpha rounds ran");
        out.model.to_bytes().unwrap()
    };
    let one = fit_on(1);
    assert!(one == fit_on(2), "1 and 2 threads differ");
    assert!(one == fit_on(3), "1 and 3 threads differ");
}

/// A round (the alpha step and the refit together) is kept only if the training
/// objective of the model it leaves falls against the last kept round's, so the objective is
/// non-increasing round after round, on a scan where several rounds run (the textured slab runs
/// all 8: objective 95.5, 52.8, 51.4, ... 51.1). The model after round r handed out by
/// `fit_prepared_rounds` (what the cross-validated choice of the rounds judges) is the model a
/// fit with `alpha_rounds = r` writes, byte for byte.
#[test]
fn alpha_rounds_never_raise_the_objective_round_after_round() {
    let tmp = tempfile::tempdir().unwrap();
    simulate(&textured_slab_config(), tmp.path(), &()).expect("simulate");
    let ds = Dataset::open(tmp.path()).unwrap();
    let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let opts = PipelineOptions::for_dataset(&ds);
    let out = fit_dataset(&ds, &frames, &opts, &FitOptions::default(), &()).expect("fit");
    let a = &out.report.alpha;
    let log = &a.round_log;
    assert!(a.rounds >= 2, "several rounds ran: {a:?}");
    assert!(log.len() >= 3, "{log:?}");
    assert_eq!(log[0].round, 0);
    let mut last_kept = log[0].objective;
    for k in &log[1..] {
        assert!(k.objective.is_finite() && k.previous.is_finite(), "{k:?}");
        // What a round had to beat is the last kept round's objective, not the previous fits
        // under the new alpha.
        assert_eq!(k.previous, last_kept, "{log:?}");
        if k.kept {
            assert!(k.objective < last_kept, "{log:?}");
            last_kept = k.objective;
        }
    }
    let kept: Vec<f64> = log.iter().filter(|k| k.kept).map(|k| k.objective).collect();
    assert_eq!(kept.len(), a.rounds + 1, "{log:?}");
    assert!(kept.windows(2).all(|w| w[1] < w[0]), "{kept:?}");

    // Round by round, as the cross-validation sees them.
    let ctx = subsurf::pipeline::prepare(
        &ds,
        &frames,
        &opts,
        &subsurf::pipeline::StoreOptions::default(),
        &(),
    )
    .unwrap();
    let mut models = Vec::new();
    subsurf::pipeline::fit_prepared_rounds(
        &ctx,
        &frames,
        &FitOptions::default(),
        &(),
        &mut |r, o| {
            models.push((r, o.model.to_bytes().unwrap()));
            r < 2
        },
    )
    .unwrap();
    assert_eq!(models.iter().map(|m| m.0).collect::<Vec<_>>(), [0, 1, 2]);
    for (r, bytes) in &models {
        let o = PipelineOptions {
            alpha_rounds: *r,
            ..opts
        };
        let direct = fit_dataset(&ds, &frames, &o, &FitOptions::default(), &()).expect("fit");
        assert!(
            direct.model.to_bytes().unwrap() == *bytes,
            "round {r} differs"
        );
    }
}
