//! `--validate` prints the homogeneous baseline's held-out row wherever it
//! prints the model's (the baseline with the model's alpha), `evaluate` judges every model by
//! the dataset's protocol, with clustered standard errors, and says what share of the samples
//! the vertices' own models predicted, and the fit's cross-validated choices are in its report.
use std::path::{Path, PathBuf};
use std::process::Command;

use subsurf::simulate::simulate;

fn subsurf(args: &[&str]) -> String {
    subsurf_with_stderr(args).0
}

/// Standard output and standard error (not a terminal here) of a successful run.
fn subsurf_with_stderr(args: &[&str]) -> (String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "subsurf {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    (
        String::from_utf8(o.stdout).unwrap(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// `shared/data/<name>` in the nearest ancestor that has it.
fn shared(name: &str) -> Option<PathBuf> {
    let here = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    here.ancestors()
        .map(|a| a.join("shared/data").join(name))
        .find(|d| d.join("scan.json").is_file())
}

/// The textured simulated slab of `texture::textured_slab_config`, written to `dir`.
fn textured_slab(dir: &Path) {
    simulate(&crate::texture::textured_slab_config(), dir, &()).expect("simulate");
}

fn finite_means(v: &serde_json::Value) -> bool {
    v["mean"]
        .as_array()
        .is_some_and(|m| m.len() == 3 && m.iter().all(|x| x.as_f64().is_some_and(f64::is_finite)))
}

/// On every dataset (the simulated textured slab, and the outside renderer's three when
/// present), with isotropic and anisotropic models, `--validate` prints the baseline's held-out
/// row next to the model's and `fit-report.json` has it (`baseline_held_out` not null). Once it
/// was missing where the model had a vertex without a model of its own
/// (`validate::tests::the_baseline_replaces_every_vertex_and_keeps_alpha`).
#[test]
fn validate_prints_the_baseline_row_on_every_dataset() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = tmp.path().join("texslab");
    textured_slab(&sim);
    let mut scans = vec![(sim, "1")];
    for name in ["sample-slab", "sample-torus", "sample-pebble"] {
        match shared(name) {
            Some(d) => scans.push((d, if name == "sample-slab" { "4" } else { "1" })),
            None => eprintln!("SKIPPED: shared/data/{name} is absent"),
        }
    }
    for (k, (scan, m)) in scans.iter().enumerate() {
        let out = tmp.path().join(format!("m{k}.ply"));
        let report = tmp.path().join(format!("r{k}.json"));
        let args = [
            "fit",
            "--scan",
            scan.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
            "--segments",
            m,
            "--validate",
            "--no-pictures",
            "--cache",
            "off",
            // The rows, not the choices, are under test: no cross-validation (it is slow).
            "--cv-folds",
            "0",
        ];
        let stdout = subsurf(&args);
        assert!(stdout.contains("held out (trust this)"), "{stdout}");
        assert!(stdout.contains("baseline, held out"), "{scan:?}: {stdout}");
        let v = &json(&report)["validation"];
        assert!(finite_means(&v["held_out"]), "{v}");
        assert!(finite_means(&v["baseline_held_out"]), "{scan:?}: {v}");
    }
}

/// `evaluate` judges every model of a dataset by the dataset's protocol, never by the
/// rules its fit used (here a wider exclusion radius than the protocol's): the model file records
/// them and `evaluate` says they differ, but compares the same samples as for a model fitted
/// with the defaults; a flag changes the protocol for every model alike. It reports the share of
/// samples the vertices' own models predicted, the clustered standard error (checked here against
/// the textbook formula on the per-frame figures it prints), the sample-weighted mean, and frames
/// the fit used apart, as in-sample, with a warning.
#[test]
fn evaluate_judges_every_model_by_the_datasets_protocol() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = tmp.path().join("texslab");
    textured_slab(&sim);
    let scan = sim.to_str().unwrap();
    let held: Vec<String> = (1..64).step_by(5).map(|k| k.to_string()).collect();
    let held = held.join(",");
    let fit = |out: &str, extra: &[&str]| {
        let mut a = vec![
            "fit",
            "--scan",
            scan,
            "--out",
            out,
            "--exclude-frames",
            &held,
        ];
        a.extend(["--no-pictures", "--cache", "off", "--cv-folds", "0"]);
        a.extend(extra);
        subsurf_with_stderr(&a).1
    };
    let wide = tmp.path().join("wide.ply");
    let wide = wide.to_str().unwrap();
    let plain = tmp.path().join("plain.ply");
    let plain = plain.to_str().unwrap();
    fit(wide, &["--exclusion-radius", "1.5"]);
    // With stderr no terminal (a long fit in a batch job), the progress comes as one line per
    // stage when it ends, with its time, and no counts while it runs.
    let progress = fit(plain, &[]);
    for stage in ["] extract ", "] fit (round 1)", "] error "] {
        assert!(progress.contains(stage), "{stage:?} not in:\n{progress}");
    }
    assert!(!progress.contains(" 0/"), "{progress}");
    let m = subsurf::modelfile::ModelFile::read(Path::new(wide)).unwrap();
    let rec = m.fitted_with.expect("the fit recorded its rules");
    assert_eq!(rec.exclusion_radius_mm, 1.5);
    let fitted = m.fitted_frames.expect("the fit recorded its frames");
    let held_list = subsurf::dataset::parse_frame_list(&held).unwrap();
    assert!(fitted.iter().all(|f| !held_list.contains(f)));
    assert_eq!(fitted.len() + held_list.len(), 64);
    let eval = |model: &str, extra: &[&str]| -> (serde_json::Value, String) {
        let mut a = vec!["evaluate", "--model", model, "--scan", scan, "--json"];
        a.extend(["--cache", "off"]);
        a.extend(extra);
        let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
            .args(&a)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (
            serde_json::from_slice(&o.stdout).unwrap(),
            String::from_utf8_lossy(&o.stderr).to_string(),
        )
    };
    let (own, _) = eval(wide, &["--frames", &held]);
    assert_eq!(own["protocol"]["exclusion_radius_mm"], 0.5, "{own}");
    assert_eq!(own["protocol"]["fit_rules_differ"], true, "{own}");
    assert_eq!(own["protocol"]["overridden"], false, "{own}");
    let (other, _) = eval(plain, &["--frames", &held]);
    assert_eq!(other["protocol"]["fit_rules_differ"], false, "{other}");
    // The same samples judge both models: the same channel samples per frame.
    let counts = |v: &serde_json::Value| -> Vec<serde_json::Value> {
        v["per_frame"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["channel_samples"].clone())
            .collect()
    };
    assert_eq!(counts(&own), counts(&other));
    let (wider, _) = eval(wide, &["--frames", &held, "--exclusion-radius", "1.5"]);
    assert_eq!(wider["protocol"]["overridden"], true);
    assert_ne!(counts(&wider), counts(&own));
    let share = own["local_share"].as_f64().expect("a local share");
    assert!(share > 0.0 && share <= 1.0, "{own}");

    // The standard error, clustered by raster neighbourhood (one turntable angle), against the
    // textbook formula on the printed per-frame figures and clusters.
    let cell = subsurf::evaluate::summary::RASTER_CELL_MM;
    let frames = own["per_frame"].as_array().unwrap();
    let judged: Vec<&serde_json::Value> =
        frames.iter().filter(|f| f["skipped"].is_null()).collect();
    assert!(judged.len() >= 8, "{own}");
    assert_eq!(own["frames"].as_u64().unwrap() as usize, judged.len());
    for c in 0..3 {
        let mut by: std::collections::BTreeMap<[i64; 3], Vec<(f64, f64)>> = Default::default();
        for f in &judged {
            let Some(y) = f["log_e"][c].as_f64() else {
                continue;
            };
            let n = f["channel_samples"][c].as_f64().unwrap();
            let x: Vec<f64> = f["x_i"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let key = [0, 1, 2].map(|k| (x[k] / cell).floor() as i64);
            by.entry(key).or_default().push((y, n));
        }
        let all: Vec<(f64, f64)> = by.values().flatten().copied().collect();
        let f = all.len() as f64;
        let mean = all.iter().map(|v| v.0).sum::<f64>() / f;
        let g = by.len() as f64;
        let s: f64 = by
            .values()
            .map(|v| v.iter().map(|(y, _)| y - mean).sum::<f64>().powi(2))
            .sum();
        let se = (g / (g - 1.0) * s).sqrt() / f;
        let w: f64 = all.iter().map(|v| v.1).sum();
        let wmean = all.iter().map(|v| v.0 * v.1).sum::<f64>() / w;
        assert!(g >= 2.0, "{own}");
        assert!((own["mean_log_e"][c].as_f64().unwrap() - mean).abs() < 1e-12);
        assert!(
            (own["se_log_e"][c].as_f64().unwrap() - se).abs() < 1e-12,
            "{own}"
        );
        assert!((own["weighted_mean_log_e"][c].as_f64().unwrap() - wmean).abs() < 1e-12);
        assert_eq!(own["clusters"].as_u64().unwrap() as f64, g);
    }

    // Frames the fit used are reported apart, with a warning; the held-out figures do not move.
    let both = format!("{held},0,2,3");
    let (mixed, stderr) = eval(wide, &["--frames", &both]);
    assert!(stderr.contains("in-sample"), "{stderr}");
    assert_eq!(mixed["in_sample_frames"], serde_json::json!([0, 2, 3]));
    assert_eq!(mixed["mean_log_e"], own["mean_log_e"]);
    assert_eq!(mixed["se_log_e"], own["se_log_e"]);
    assert!(
        mixed["in_sample"]["mean_log_e"][1].as_f64().is_some(),
        "{mixed}"
    );

    // The paired difference of two models on the same frames: the difference of their means,
    // and zero against itself.
    let (pair, _) = eval(wide, &["--frames", &held, "--against", plain]);
    for c in 0..3 {
        let d = pair["against"]["mean_difference"][c].as_f64().unwrap();
        let direct =
            own["mean_log_e"][c].as_f64().unwrap() - other["mean_log_e"][c].as_f64().unwrap();
        assert!((d - direct).abs() < 1e-12, "{pair}");
    }
    let (same, _) = eval(wide, &["--frames", &held, "--against", wide]);
    assert_eq!(
        same["against"]["mean_difference"],
        serde_json::json!([0.0, 0.0, 0.0])
    );
}

/// The cross-validation inside the fit: folds of whole raster positions on the one-angle
/// textured slab, disjoint and covering the training frames; `--segments auto` lists every m of
/// the ladder with its held-out error and exactly one chosen, Eq. 6's t1 and the alpha rounds
/// likewise; the fold fits read no frame (they use the run's sample store).
#[test]
fn the_fit_cross_validates_its_choices_from_the_sample_store() {
    use subsurf::crossval::{CvSettings, Segments, fit_scan_in};
    let tmp = tempfile::tempdir().unwrap();
    let sim = tmp.path().join("texslab");
    textured_slab(&sim);
    let ds = subsurf::dataset::Dataset::open(&sim).unwrap();
    let frames: Vec<usize> = (0..ds.spec.frames.len()).filter(|k| k % 5 != 1).collect();
    let opts = subsurf::pipeline::PipelineOptions::for_dataset(&ds);
    let store = subsurf::pipeline::StoreOptions {
        cache: subsurf::pipeline::Cache::Off,
        ..Default::default()
    };
    let ctx = subsurf::pipeline::prepare(&ds, &frames, &opts, &store, &()).unwrap();
    let reads = ds.frame_reads();
    let cv = CvSettings {
        segments: Segments::Auto,
        ..CvSettings::default()
    };
    let out = fit_scan_in(
        &ctx,
        &ctx,
        &frames,
        &cv,
        &subsurf::fit::FitOptions::default(),
        &(),
    )
    .unwrap();
    assert_eq!(ds.frame_reads(), reads, "the fold fits read frames again");
    let r = out
        .report
        .cross_validation
        .as_ref()
        .expect("a cross-validation");
    assert_eq!(r.folds.len(), 5);
    let mut all: Vec<usize> = r.folds.concat();
    all.sort();
    assert_eq!(all, frames);
    // The four m of the ladder, then t1 (none against crossval::T1_CANDIDATE) for the m chosen,
    // then the lattice (judged at surface points when the fit wrote one, from the folds' fits at
    // the rounds chosen: no fit more).
    assert_eq!(r.fits, 5 * 5);
    let names: Vec<&str> = r.choices.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "segments",
            "alpha_t1_share",
            "alpha_rounds",
            "alpha_lattice"
        ]
    );
    let lattice = &r.choices[3];
    assert_eq!(
        out.model.face_alpha.is_some(),
        lattice.chosen == "auto",
        "{lattice:?}"
    );
    // The per-frame errors of the choice, every training frame judged once by its fold.
    assert!(r.per_frame.keys().all(|f| frames.contains(f)));
    assert!(r.per_frame.len() * 2 > frames.len(), "{:?}", r.per_frame);
    for c in r.choices.iter().filter(|c| !c.candidates.is_empty()) {
        assert_eq!(c.candidates.iter().filter(|k| k.chosen).count(), 1, "{c:?}");
        assert!(
            c.candidates
                .iter()
                .all(|k| k.score.is_some_and(f64::is_finite)),
            "{c:?}"
        );
    }
    let seg = &r.choices[0];
    assert_eq!(seg.candidates.len(), 4);
    let m: usize = seg.chosen.parse().unwrap();
    assert_eq!(out.model.shape.segments, m);
    // The textured slab's material is isotropic: the ladder's first m within noise wins.
    eprintln!("{:#?}", r.choices);
    assert!(
        seg.candidates
            .iter()
            .any(|k| k.chosen && k.value == seg.chosen)
    );
    let rounds = &r.choices[2];
    assert!(
        rounds.candidates.len() >= 2,
        "several rounds ran in the folds: {rounds:?}"
    );
    // Without folds nothing is chosen and `auto` is refused.
    let none = CvSettings { folds: 1, ..cv };
    assert!(
        fit_scan_in(
            &ctx,
            &ctx,
            &frames,
            &none,
            &subsurf::fit::FitOptions::default(),
            &()
        )
        .is_err()
    );
}

/// Round 0's candidate fits, fitted once on every frame (`pipeline::fit::OrderCache`), are the
/// very fits a fold would make of the light positions it holds: on sample-torus (a turntable
/// scan whose folds are whole angles), a fold's fit through the filled cache is its fit without
/// it, byte for byte after round 0 and after a further round, and the cache did serve it; the
/// model file the folds judge (`FitRounds::model_file`, no report) is the whole run's model.
#[test]
fn shared_round_zero_candidates_fit_a_fold_as_its_own_fit_would() {
    use subsurf::pipeline::Prepared;
    use subsurf::pipeline::fit::OrderCache;
    let Some(dir) = shared("sample-torus") else {
        eprintln!("SKIPPED: shared/data/sample-torus is absent");
        return;
    };
    let ds = subsurf::dataset::Dataset::open(&dir).unwrap();
    let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let opts = subsurf::pipeline::PipelineOptions::for_dataset(&ds);
    let store = subsurf::pipeline::StoreOptions {
        cache: subsurf::pipeline::Cache::Off,
        ..Default::default()
    };
    let ctx = subsurf::pipeline::prepare(&ds, &frames, &opts, &store, &()).unwrap();
    let fitter = subsurf::fit::FitOptions::default();
    let (folds, _) = subsurf::crossval::folds(&ds, &frames, 5);
    let train: Vec<usize> = frames
        .iter()
        .copied()
        .filter(|f| !folds[1].contains(f))
        .collect();
    let cache = OrderCache::default();
    Prepared::new(&ctx, &frames)
        .unwrap()
        .fill_order_cache(&ctx, &fitter, &cache, &());
    let (fitted, _) = cache.counts();
    assert!(fitted > 0, "the fill fitted the light positions");
    let fold = Prepared::new(&ctx, &train).unwrap();
    let mut own = fold.rounds(&ctx, &fitter, None, &());
    let mut shared = fold.rounds(&ctx, &fitter, Some(&cache), &());
    for round in 0..2 {
        let (a, b) = (own.model().unwrap(), shared.model().unwrap());
        assert_eq!(
            a.model.to_bytes().unwrap(),
            b.model.to_bytes().unwrap(),
            "round {round}"
        );
        // What the folds judge: the model file without the report's own figures, the same.
        assert_eq!(
            own.model_file().unwrap().to_bytes().unwrap(),
            a.model.to_bytes().unwrap(),
            "round {round}: the model file alone"
        );
        own.step();
        shared.step();
    }
    let (_, reused) = cache.counts();
    assert!(
        reused > fitted / 2,
        "the fold found most of its light positions fitted: {reused} of {fitted}"
    );
}

/// The held-out check on the outside renderer's datasets, their test frames held out of
/// every fit: sample-slab's held-out error with `--segments auto` (m chosen by cross-validation
/// on the 7 training frames) at or below the isotropic fit's, channel by channel (measured
/// 0.1614 / 0.1385 / 0.1515 against 0.1757 / 0.1614 / 0.1750, m = 4 chosen). sample-torus's
/// held-out green with the defaults is a regression check only, within two of its standard
/// errors (clustered by turntable angle) of the figure recorded in docs/validation.md, 0.6267:
/// its earlier bound, 0.568, was reached with a constant chosen on these very frames (so it did not count),
/// and a test that pins a test-set figure would choose by it.
#[test]
fn cross_validated_choices_on_the_shared_datasets() {
    use subsurf::crossval::{CvSettings, Segments, fit_scan_in};
    let fitter = subsurf::fit::FitOptions::default();
    let held_out = |name: &str, held: &[usize], cv: CvSettings| -> Option<([f64; 3], [f64; 3])> {
        let Some(dir) = shared(name) else {
            eprintln!("SKIPPED: shared/data/{name} is absent");
            return None;
        };
        let ds = subsurf::dataset::Dataset::open(&dir).unwrap();
        let frames: Vec<usize> = (0..ds.spec.frames.len())
            .filter(|k| !held.contains(k))
            .collect();
        let opts = subsurf::pipeline::PipelineOptions::for_dataset(&ds);
        let store = subsurf::pipeline::StoreOptions {
            cache: subsurf::pipeline::Cache::Off,
            ..Default::default()
        };
        let ctx = subsurf::pipeline::prepare(&ds, &frames, &opts, &store, &()).unwrap();
        let out = fit_scan_in(&ctx, &ctx, &frames, &cv, &fitter, &()).unwrap();
        let (evals, st) = subsurf::evaluate::evaluate_frames_stored(
            &ds,
            &out.model,
            held,
            &opts,
            subsurf::evaluate::EvalPoints::Vertices,
            &store,
            &(),
        )
        .unwrap();
        let clusters = subsurf::evaluate::Clustering::of_frames(&ds, &evals);
        let fig = subsurf::evaluate::Figures::of(&evals, &clusters);
        Some((
            st.mean.map(|v| v.unwrap()),
            fig.se_log_e.map(|v| v.unwrap_or(f64::INFINITY)),
        ))
    };
    let iso = held_out("sample-slab", &[1, 5], CvSettings::default());
    let auto = held_out(
        "sample-slab",
        &[1, 5],
        CvSettings {
            segments: Segments::Auto,
            ..CvSettings::default()
        },
    );
    if let (Some((iso, _)), Some((auto, _))) = (iso, auto) {
        eprintln!("sample-slab held out: isotropic {iso:.4?}, auto {auto:.4?}");
        for c in 0..3 {
            assert!(auto[c] <= iso[c] + 1e-9, "{auto:?} vs {iso:?}");
        }
    }
    let held: Vec<usize> = (96..104).collect();
    if let Some((t, se)) = held_out("sample-torus", &held, CvSettings::default()) {
        eprintln!("sample-torus held out: {t:.4?} ± {se:.4?}");
        assert!((t[1] - 0.6267).abs() <= 2.0 * se[1], "{t:?} ± {se:?}");
    }
}

/// The cut of the folds' fill: a fold reads its model only at the corners of its
/// held-out frames' x_i, so `FitRounds::model_file_for` fills and refits only those. On
/// sample-torus, a fold's model there is the full fill's: bit for bit on the reference path
/// (which still solves and refits everything), within the fill's tolerance on the default path
/// (weights of the known vertices, kept from round to round), whose restricted model has fewer
/// vertices with a model. A run started from another's fill state gives the same bits.
///
/// The same with m = 4 direction segments on sample-slab, whose flat mesh turns no vertex's
/// frame against a neighbour's: there the default path solves the plain Laplace equation where
/// the reference sweeps the segments' aligned one (`interpolate::harmonic_aligned`).
#[test]
fn a_fold_fills_only_the_vertices_its_frames_read_and_the_same_there() {
    fold_fills_only_what_it_reads("sample-torus", 1, 3);
    // One round: the reference's sweeps of the slab's holes are most of this test's time.
    fold_fills_only_what_it_reads("sample-slab", 4, 1);
}

/// The check above on `name` with `segments` direction segments, over `rounds` rounds.
fn fold_fills_only_what_it_reads(name: &str, segments: usize, rounds: usize) {
    use subsurf::modelfile::VertexStatus;
    use subsurf::pipeline::{PipelineOptions, Prepared, Speed};
    let Some(dir) = shared(name) else {
        eprintln!("SKIPPED: shared/data/{name} is absent");
        return;
    };
    let ds = subsurf::dataset::Dataset::open(&dir).unwrap();
    let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let store = subsurf::pipeline::StoreOptions {
        cache: subsurf::pipeline::Cache::Off,
        ..Default::default()
    };
    let mut base = PipelineOptions::for_dataset(&ds);
    base.model.segments = segments;
    let ctx = subsurf::pipeline::prepare(&ds, &frames, &base, &store, &()).unwrap();
    let fitter = subsurf::fit::FitOptions::default();
    let (folds, _) = subsurf::crossval::folds(&ds, &frames, 5);
    let fold = &folds[2];
    let train: Vec<usize> = frames
        .iter()
        .copied()
        .filter(|f| !fold.contains(f))
        .collect();
    let mut needed = vec![false; ds.mesh.positions.len()];
    for &f in fold {
        if let Ok(reg) = subsurf::pipeline::register_one(&ctx, f) {
            for v in ctx.scene.mesh.triangles[reg.triangle as usize] {
                needed[v as usize] = true;
            }
        }
    }
    assert!(needed.iter().any(|&n| n), "the fold's frames show spots");
    for speed in [Speed::Reference, Speed::Default] {
        let c = ctx.with_options(PipelineOptions { speed, ..base }).unwrap();
        let prepared = Prepared::new(&c, &train).unwrap();
        let mut run = prepared.rounds(&c, &fitter, None, &());
        for round in 0..rounds {
            let part = run.model_file_for(&needed).unwrap();
            let full = run.model_file().unwrap();
            assert_eq!(part.shape.segments, segments);
            let with_model = |m: &subsurf::modelfile::ModelFile| {
                m.vertices
                    .iter()
                    .filter(|v| v.status != VertexStatus::NoModel)
                    .count()
            };
            // The reference refits every vertex (the exact path); the default only the
            // needed ones.
            match speed {
                Speed::Reference => assert_eq!(with_model(&part), with_model(&full)),
                Speed::Default => {
                    assert!(with_model(&part) < with_model(&full), "round {round}")
                }
            }
            for (v, _) in needed.iter().enumerate().filter(|(_, n)| **n) {
                let (a, b) = (&part.vertices[v], &full.vertices[v]);
                assert_eq!(a.status, b.status, "{speed:?} round {round} vertex {v}");
                assert_eq!(a.alpha, b.alpha);
                for (x, y) in a.params.iter().zip(&b.params) {
                    let ok = match speed {
                        Speed::Reference => x.to_bits() == y.to_bits(),
                        Speed::Default => (x - y).abs() <= 1e-5 * (1.0 + y.abs()),
                    };
                    assert!(ok, "{speed:?} round {round} vertex {v}: {x} vs {y}");
                }
            }
            run.step();
        }
        if speed == Speed::Default {
            // A run whose fills start from another's (the next candidate's fold in the
            // cross-validation) gives the same bits as one that solves its own weights.
            run.model_file_for(&needed).unwrap();
            let state = run.fill_state().expect("the run filled");
            assert!(state.has_weights());
            let seeded = prepared.rounds(&c, &fitter, None, &());
            seeded.start_fill_from(state);
            let fresh = prepared.rounds(&c, &fitter, None, &());
            let bytes = |r: &subsurf::pipeline::FitRounds| {
                r.model_file_for(&needed).unwrap().to_bytes().unwrap()
            };
            assert!(
                bytes(&seeded) == bytes(&fresh),
                "a seeded fill changed the model"
            );
        }
    }
}

/// `subsurf bench equivalence` on sample-slab, its test frames 1 and 5 held out: the default
/// fit predicts the training frames' outer cross-validation (two folds, clustered by fold, one
/// degree of freedom) as the reference preset does (two one-sided tests at the margin), makes
/// the same choices, and its ln R_d and ln alpha change by less than 0.01 RMS. The test frames'
/// change is reported beside, not judged.
#[test]
fn the_default_fit_predicts_as_the_reference_preset_does() {
    let Some(dir) = shared("sample-slab") else {
        eprintln!("SKIPPED: shared/data/sample-slab is absent");
        return;
    };
    let case = subsurf::bench::equivalence::run_case("sample-slab", &dir, &[1, 5], 2, &())
        .expect("both fits");
    let table = subsurf::bench::equivalence::table(std::slice::from_ref(&case));
    eprintln!("{table}");
    assert!(
        case.cv.as_ref().is_some_and(|t| t.pass
            && t.clusters == 2
            && t.dof == Some(1)
            && t.cluster_rule == "fold"),
        "{table}"
    );
    assert!(case.test.as_ref().is_some_and(|t| t.frames == 2), "{table}");
    assert!(case.choices.iter().all(|c| c.pass), "{table}");
    assert!(!case.choices.is_empty());
    assert!(case.rms_ln_rd.is_some_and(|x| x <= 0.01), "{table}");
    assert!(case.rms_ln_alpha.is_some_and(|x| x <= 0.01), "{table}");
    assert!(case.pass());
}

/// The floor measured from the outside renderer's frames (their own pixel-independent Monte
/// Carlo noise) is a positive floor within a factor of 4 of the one their scan.json gives, and
/// their residuals correlate between neighbours as independent noise does: the estimate
/// neither refuses nor silently returns 0 on data it did not make.
#[test]
fn the_floor_measured_from_the_outside_renderers_frames_is_near_the_given_one() {
    use subsurf::pipeline::noise;
    for name in ["sample-slab", "sample-torus", "sample-pebble"] {
        let Some(dir) = shared(name) else {
            eprintln!("SKIPPED: shared/data/{name} is absent");
            continue;
        };
        let ds = subsurf::dataset::Dataset::open(&dir).unwrap();
        let given = ds
            .spec
            .noise_floor
            .expect("the shared datasets give a floor");
        let scene = subsurf::geometry::Scene::new(ds.mesh.clone()).unwrap();
        let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
        let e = noise::estimate(&ds, &scene, &frames).unwrap();
        eprintln!(
            "{name}: measured {:.3e} (given {given:.3e}), neighbour correlation {:?}, levels {:?}",
            e.floor, e.neighbour_correlation, e.levels
        );
        // The floor the renderer's scan.json gives is its own choice, not a 3 σ level: within
        // a factor of 4 (sample-torus's measured floor is 0.26 of it, sample-slab's 0.82).
        assert!(e.floor > given / 4.0 && e.floor < given * 4.0, "{name}");
        let c = e.neighbour_correlation.expect("pairs below the floor");
        assert!((c - noise::INDEPENDENT_CORRELATION).abs() < noise::MAX_CORRELATION_SHIFT);
    }
}
