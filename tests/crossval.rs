//! Issue 25: a model is judged on the fit's terms. `--validate` prints the homogeneous
//! baseline's held-out row wherever it prints the model's (the baseline with the model's alpha),
//! `evaluate` reads frames by the rules the model file records unless told otherwise and says
//! what share of the samples the vertices' own models predicted, and the fit's cross-validated
//! choices are in its report.
use std::path::{Path, PathBuf};
use std::process::Command;

use subsurf::simulate::simulate;

fn subsurf(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "subsurf {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).unwrap()
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

/// `evaluate` judges a model by the rules its fit used (here a wider exclusion radius than the
/// default), recorded in the model file; `--ignore-fit-record` falls back to the defaults and
/// explicit flags override. It reports the share of samples the vertices' own models predicted.
#[test]
fn evaluate_uses_the_options_the_model_was_fitted_with() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = tmp.path().join("texslab");
    textured_slab(&sim);
    let scan = sim.to_str().unwrap();
    let model = tmp.path().join("m.ply");
    let model = model.to_str().unwrap();
    let held: Vec<String> = (1..64).step_by(5).map(|k| k.to_string()).collect();
    let held = held.join(",");
    subsurf(&[
        "fit",
        "--scan",
        scan,
        "--out",
        model,
        "--exclude-frames",
        &held,
        "--exclusion-radius",
        "1.5",
        "--no-pictures",
        "--cache",
        "off",
    ]);
    let rec = subsurf::modelfile::ModelFile::read(Path::new(model))
        .unwrap()
        .fitted_with
        .expect("the fit recorded its rules");
    assert_eq!(rec.exclusion_radius_mm, 1.5);
    let eval = |extra: &[&str]| -> serde_json::Value {
        let mut a = vec!["evaluate", "--model", model, "--scan", scan, "--json"];
        a.extend(["--frames", &held, "--cache", "off"]);
        a.extend(extra);
        serde_json::from_str(&subsurf(&a)).unwrap()
    };
    let own = eval(&[]);
    assert_eq!(own["options"]["from_model_file"], true, "{own}");
    assert_eq!(own["options"]["exclusion_radius_mm"], 1.5, "{own}");
    let defaults = eval(&["--ignore-fit-record"]);
    assert_eq!(defaults["options"]["exclusion_radius_mm"], 0.5);
    let explicit = eval(&["--ignore-fit-record", "--exclusion-radius", "1.5"]);
    assert_eq!(own["mean_log_e"], explicit["mean_log_e"]);
    assert_ne!(own["mean_log_e"], defaults["mean_log_e"]);
    let share = own["local_share"].as_f64().expect("a local share");
    assert!(share > 0.0 && share <= 1.0, "{own}");
}

/// The cross-validation inside the fit: folds of whole raster positions on the one-angle
/// textured slab, disjoint and covering the training frames; `--segments auto` lists every m of
/// the ladder with its held-out error and exactly one chosen, the alpha rounds likewise; the fold
/// fits read no frame (they use the run's sample store).
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
    assert_eq!(r.fits, 4 * 5);
    let names: Vec<&str> = r.choices.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["segments", "alpha_rounds"]);
    for c in &r.choices {
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
    let rounds = &r.choices[1];
    assert!(
        rounds.candidates.len() >= 2,
        "several rounds ran in the folds: {rounds:?}"
    );
    // Without folds nothing is chosen and `auto` is refused.
    let none = CvSettings { folds: 1, ..cv };
    assert!(
        fit_scan_in(
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

/// Done-when of issue 25 on the outside renderer's datasets, their test frames held out of
/// every fit: sample-slab's held-out error with `--segments auto` (m chosen by cross-validation
/// on the 7 training frames) at or below the isotropic fit's, channel by channel (measured
/// 0.1614 / 0.1385 / 0.1515 against 0.1757 / 0.1614 / 0.1750, m = 4 chosen); sample-torus's
/// held-out green with the defaults no worse than 0.568 (measured 0.5680: the rounds chosen,
/// 0, are what the fit ran before).
#[test]
fn cross_validated_choices_on_the_shared_datasets() {
    use subsurf::crossval::{CvSettings, Segments, fit_scan_in};
    let fitter = subsurf::fit::FitOptions::default();
    let held_out = |name: &str, held: &[usize], cv: CvSettings| -> Option<[f64; 3]> {
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
        let out = fit_scan_in(&ctx, &frames, &cv, &fitter, &()).unwrap();
        let (_, st) = subsurf::evaluate::evaluate_frames_stored(
            &ds,
            &out.model,
            held,
            &opts,
            subsurf::evaluate::EvalPoints::Vertices,
            &store,
            &(),
        )
        .unwrap();
        Some(st.mean.map(|v| v.unwrap()))
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
    if let (Some(iso), Some(auto)) = (iso, auto) {
        eprintln!("sample-slab held out: isotropic {iso:.4?}, auto {auto:.4?}");
        for c in 0..3 {
            assert!(auto[c] <= iso[c] + 1e-9, "{auto:?} vs {iso:?}");
        }
    }
    let held: Vec<usize> = (96..104).collect();
    if let Some(t) = held_out("sample-torus", &held, CvSettings::default()) {
        eprintln!("sample-torus held out: {t:.4?}");
        assert!(t[1] <= 0.5681, "{t:?}");
    }
}
