//! The sample store: each frame decoded once per fit, a store spilled to disk or opened
//! from the dataset's cache fits the very model an in-memory one does, and a cache is used only
//! for the frames and options it was made from.
use std::path::Path;

use subsurf::dataset::Dataset;
use subsurf::fit::FitOptions;
use subsurf::pipeline::{Cache, PipelineOptions, StoreOptions, fit_prepared, prepare};

use crate::fixture::small_slab_copy;

/// The model file's bytes of a fit of all frames of `ds` with `store`, and the run's report.
fn fit_bytes(
    ds: &Dataset,
    opts: &PipelineOptions,
    store: &StoreOptions,
    out: &Path,
) -> (Vec<u8>, subsurf::pipeline::FitReport) {
    let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let ctx = prepare(ds, &frames, opts, store, &()).expect("prepare");
    let fitted = fit_prepared(&ctx, &frames, &FitOptions::default(), &()).expect("fit");
    fitted.model.write(out).expect("write");
    (std::fs::read(out).unwrap(), fitted.report)
}

/// Every frame file is opened once per fit: the extraction pass reads each frame, no later
/// stage (the fit rounds, the lattice, the error) reads one again, and a fit from the cache
/// reads none. The model is byte-identical whether the store is in memory, spilled entirely to
/// disk (a zero budget, to the cache or to a scratch store) or opened from the cache.
#[test]
fn each_frame_is_read_once_and_spilled_or_cached_stores_fit_the_same_model() {
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("scan");
    small_slab_copy(&data);
    let opts = {
        let ds = Dataset::open(&data).unwrap();
        PipelineOptions::for_dataset(&ds)
    };
    let memory = StoreOptions {
        budget: usize::MAX,
        cache: Cache::Off,
    };
    let ds = Dataset::open(&data).unwrap();
    let (in_memory, rep) = fit_bytes(&ds, &opts, &memory, &d.path().join("a.ply"));
    let counts = ds.frame_read_counts();
    assert!(
        counts.iter().all(|&n| n == 1),
        "every frame read exactly once: {counts:?}"
    );
    let st = rep.sample_store.clone().unwrap();
    assert_eq!((st.frames_decoded, st.spilled), (counts.len(), 0));
    assert!(
        rep.alpha.rounds >= 1,
        "the alpha rounds ran: {:?}",
        rep.alpha
    );

    // Everything spilled: every read of samples goes to the store's files.
    let ds = Dataset::open(&data).unwrap();
    let spilled = StoreOptions {
        budget: 0,
        cache: Cache::Dataset,
    };
    let (from_disk, rep) = fit_bytes(&ds, &opts, &spilled, &d.path().join("b.ply"));
    assert!(rep.sample_store.as_ref().unwrap().spilled > 0);
    assert!(ds.frame_read_counts().iter().all(|&n| n == 1));
    assert_eq!(in_memory, from_disk, "a spilled store fits the same model");

    // Spilled to a scratch store (no cache), whose lattice file holds no r: the run measures it.
    let ds = Dataset::open(&data).unwrap();
    let scratch = StoreOptions {
        budget: 0,
        cache: Cache::Off,
    };
    let (from_scratch, rep) = fit_bytes(&ds, &opts, &scratch, &d.path().join("s.ply"));
    let st = rep.sample_store.as_ref().unwrap();
    assert!(st.spilled > 0 && st.point_samples > 0, "{st:?}");
    assert_eq!(
        in_memory, from_scratch,
        "a spilled scratch store fits the same model"
    );

    // The cache: no frame is read.
    let ds = Dataset::open(&data).unwrap();
    let cached = StoreOptions {
        budget: 64 << 20,
        cache: Cache::Dataset,
    };
    let (from_cache, rep) = fit_bytes(&ds, &opts, &cached, &d.path().join("c.ply"));
    let st = rep.sample_store.unwrap();
    assert!(st.from_cache && st.frames_decoded == 0, "{st:?}");
    assert_eq!(ds.frame_reads().total, 0);
    assert_eq!(
        in_memory, from_cache,
        "the cached store fits the same model"
    );
}

/// A cache serves only the frames and options it was made from: other extraction options, a
/// frame file that changed, or a frame it does not hold make the run decode again; a run of
/// fewer frames is served by a store of more.
#[test]
fn the_cache_is_invalidated_by_changed_frames_and_extraction_options() {
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("scan");
    small_slab_copy(&data);
    let cached = StoreOptions::default();
    let ds = Dataset::open(&data).unwrap();
    let opts = PipelineOptions::for_dataset(&ds);
    let all: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let decoded = |opts: &PipelineOptions, frames: &[usize]| {
        let ds = Dataset::open(&data).unwrap();
        let ctx = prepare(&ds, frames, opts, &cached, &()).unwrap();
        let r = ctx.store().unwrap().report();
        (r.frames_decoded, r.from_cache, ds.frame_reads().total)
    };
    let n = all.len();
    assert_eq!(decoded(&opts, &all), (n, false, n as u64));
    assert_eq!(decoded(&opts, &all), (0, true, 0));
    // Fewer frames: the store of all serves them (the lattice follows the frames' views, so
    // leave it out here: the slab has one view either way, but other scans need not).
    let mut vertices_only = opts;
    vertices_only.alpha_lattice = subsurf::pipeline::AlphaLattice::Off;
    let ds2 = Dataset::open(&data).unwrap();
    let ctx = prepare(&ds2, &all, &vertices_only, &cached, &()).unwrap();
    assert!(ctx.store().unwrap().report().from_cache);
    drop(ctx);
    assert_eq!(decoded(&vertices_only, &all[..n / 2]), (0, true, 0));
    // Another extraction option.
    let mut other = opts;
    other.samples.exclusion_radius_mm += 0.25;
    assert_eq!(decoded(&other, &all), (n, false, n as u64));
    // A frame file that changed (rewritten with the same bytes: only its time differs).
    let f = data.join(&ds.spec.frames[3].image);
    let bytes = std::fs::read(&f).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::write(&f, bytes).unwrap();
    assert_eq!(decoded(&opts, &all), (n, false, n as u64));
    assert_eq!(decoded(&opts, &all), (0, true, 0));
    // A cache that cannot be read (a truncated file) is rebuilt, and the report says why.
    for e in std::fs::read_dir(data.join(".subsurf-cache")).unwrap() {
        let frames = e.unwrap().path().join("frames.arrow");
        let len = std::fs::metadata(&frames).unwrap().len();
        std::fs::File::options()
            .write(true)
            .open(&frames)
            .unwrap()
            .set_len(len / 2)
            .unwrap();
    }
    let ds3 = Dataset::open(&data).unwrap();
    let ctx = prepare(&ds3, &all, &opts, &cached, &()).unwrap();
    let r = ctx.store().unwrap().report();
    assert!(!r.from_cache && r.frames_decoded == n);
    assert!(
        r.cache_rejected
            .as_deref()
            .is_some_and(|why| why.contains("frames.arrow")),
        "{:?}",
        r.cache_rejected
    );
    drop(ctx);
    assert_eq!(decoded(&opts, &all), (0, true, 0));
}

/// `subsurf fit` twice on the same scan: the second run starts from the cache, decodes no frame,
/// and writes the same model; `--cache off` leaves nothing in the dataset.
#[test]
fn a_second_fit_starts_from_the_cache() {
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("scan");
    small_slab_copy(&data);
    let fit = |out: &str, extra: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_subsurf"))
            .args(["fit", "--no-pictures", "--scan"])
            .arg(&data)
            .arg("--out")
            .arg(d.path().join(out))
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.path().join("fit-report.json")).unwrap())
                .unwrap();
        (std::fs::read(d.path().join(out)).unwrap(), r)
    };
    let (a, r) = fit("a.ply", &["--cache", "off"]);
    assert!(!data.join(".subsurf-cache").exists());
    assert_eq!(r["sample_store"]["not_cached"], "--cache off");
    let (b, r) = fit("b.ply", &[]);
    assert_eq!(r["sample_store"]["from_cache"], false);
    assert!(data.join(".subsurf-cache").is_dir());
    let (c, r) = fit("c.ply", &[]);
    assert_eq!(r["sample_store"]["from_cache"], true);
    assert_eq!(r["frames"]["reads"]["total"], 0);
    assert!(a == b && b == c, "the same model from every store");
}

/// `subsurf scan` extracts each frame's samples as it arrives: the first `subsurf fit` after the
/// scan starts from that store, decodes no frame, and writes the model a fit that decodes every
/// frame itself writes.
#[test]
fn a_fit_after_a_scan_starts_from_the_store_the_scan_wrote() {
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("scan");
    let run = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_subsurf"))
            .args(args)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let data_s = data.to_str().unwrap();
    let printed = run(&[
        "scan", "--sim", "--camera", "sim", "--quiet", "--size", "64", "--angles", "4", "--raster",
        "6", "--out", data_s,
    ]);
    assert!(printed.contains("sample store of"), "{printed}");
    let fit = |out: &str, extra: &[&str]| {
        let model = d.path().join(out);
        let mut args = vec!["fit", "--no-pictures", "--scan", data_s, "--out"];
        args.push(model.to_str().unwrap());
        args.extend_from_slice(extra);
        run(&args);
        let r: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.path().join("fit-report.json")).unwrap())
                .unwrap();
        (std::fs::read(&model).unwrap(), r)
    };
    let (from_scan, r) = fit("a.ply", &[]);
    assert_eq!(
        r["sample_store"]["from_cache"], true,
        "{}",
        r["sample_store"]
    );
    assert_eq!(r["frames"]["reads"]["total"], 0);
    let (decoded, r) = fit("b.ply", &["--cache", "off"]);
    assert!(r["frames"]["reads"]["total"].as_u64().unwrap() > 0);
    assert!(from_scan == decoded, "the scan's store fits the same model");
}
