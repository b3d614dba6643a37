//! `subsurf export --format blender`: the files and the conversion's report, what a model with
//! anisotropy or a face lattice loses, and — in Blender itself (Debian's `blender`, which
//! `.ci/run` installs) — the demo's model rendered in Cycles against subsurf's own render.

use std::path::{Path, PathBuf};
use std::process::Command;

use subsurf::lattice::{FaceAlpha, is_corner, points};
use subsurf::modelfile::{ColourMode, ModelFile, ModelShape};
use subsurf::render::image_stats;

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

/// A Blender to test with: `$SUBSURF_BLENDER`, or `blender` on the PATH. In CI (`CI` set) a
/// missing Blender fails the test; elsewhere the Blender checks are skipped, and say so.
pub(crate) fn blender() -> Option<PathBuf> {
    let from_env = std::env::var_os("SUBSURF_BLENDER").map(PathBuf::from);
    let on_path = std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join("blender"))
            .find(|p| p.is_file())
    });
    let found = from_env.or(on_path);
    if found.is_none() {
        let ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty());
        assert!(
            !ci,
            "CI is set but no Blender was found (`blender` on PATH or $SUBSURF_BLENDER): \
             .ci/run installs Debian's blender"
        );
        eprintln!(
            "SKIPPED the Blender checks: no Blender found (`blender` on PATH or \
             $SUBSURF_BLENDER) and CI is not set"
        );
    }
    found
}

/// The Blenders to test with: [`blender`]'s and, as `$SUBSURF_BPY_PYTHON`, a Python that
/// imports the `bpy` module (the newest Blender PyPI serves; CI installs it beside Debian's 3.4,
/// and fails when it is missing).
fn blenders() -> Vec<PathBuf> {
    let bpy = std::env::var_os("SUBSURF_BPY_PYTHON").map(PathBuf::from);
    if bpy.is_none() {
        let ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty());
        assert!(
            !ci,
            "CI is set but $SUBSURF_BPY_PYTHON (a Python with bpy) is not: .ci/run installs it"
        );
        eprintln!("SKIPPED the bpy module's checks: $SUBSURF_BPY_PYTHON is not set");
    }
    blender().into_iter().chain(bpy).collect()
}

/// Every Blender at hand (Debian's 3.4 and the `bpy` module's newest, whose Principled BSDF is
/// v2 and whose meshes have no auto smooth) builds the `.blend` of the small slab's model,
/// renders its scene with the object's mean light near subsurf's render of the same scene
/// (measured 1.100 in Blender 3.4.1 and 1.091 in 5.0.1 at 32 samples: the small slab's fall-off reaches past its
/// edges, where the two renderers gather differently, docs/export.md), and renders two frames of the small scan that the ring yardstick judges: the report's
/// ring figures are `subsurf evaluate --rings --images`' on the renders, finite, and beside the
/// model's. 48 × 48 px, 32 samples; the frames 64 samples.
#[test]
fn every_blender_builds_renders_and_judges_by_rings() {
    let tmp = tempfile::tempdir().unwrap();
    let slab = crate::fixture::small_slab();
    let model = slab.join("ground-truth.ply");
    let (m, d) = (model.to_str().unwrap(), slab.to_str().unwrap());
    let cache = tmp.path().join("cache");
    let c = cache.to_str().unwrap();
    for (n, b) in blenders().iter().enumerate() {
        let bl = b.to_str().unwrap();
        let scene = tmp.path().join(format!("scene-{n}"));
        let printed = subsurf(&[
            "export",
            "--model",
            m,
            "--out",
            scene.to_str().unwrap(),
            "--size",
            "48x48",
            "--render",
            "--samples",
            "32",
            "--blender",
            bl,
        ]);
        assert!(scene.join("model.blend").is_file(), "{bl}: {printed}");
        let ratio = object_mean_ratio(&scene.join("cycles.exr"), &scene.join("subsurf.exr"));
        eprintln!("{bl}: Cycles' mean over the object / subsurf's {ratio:.4}");
        assert!((0.85..1.2).contains(&ratio), "{bl}: {ratio}");
        let out = tmp.path().join(format!("frames-{n}"));
        subsurf(&[
            "export",
            "--model",
            m,
            "--out",
            out.to_str().unwrap(),
            "--scan",
            d,
            "--frames",
            "5,10",
            "--render",
            "--samples",
            "64",
            "--cache",
            c,
            "--blender",
            bl,
        ]);
        let f = &json(&out.join("export-report.json"))["frames"];
        let images = out.join("frames");
        let judged: serde_json::Value = serde_json::from_str(&subsurf(&[
            "evaluate",
            "--model",
            m,
            "--scan",
            d,
            "--frames",
            "5,10",
            "--json",
            "--cache",
            c,
            "--rings",
            "--images",
            images.to_str().unwrap(),
        ]))
        .unwrap();
        eprintln!(
            "{bl}: rings {} {}",
            f["cycles_ring_mean_log_e"], f["subsurf_ring_mean_log_e"]
        );
        for ch in 0..3 {
            let theirs = f["cycles_ring_mean_log_e"][ch].as_f64().unwrap();
            assert!(theirs.is_finite() && theirs >= 0.0, "{f}");
            assert_eq!(
                judged["ring_mean_log_e"][ch].as_f64(),
                Some(theirs),
                "{judged}"
            );
            assert!(
                f["subsurf_ring_mean_log_e"][ch]
                    .as_f64()
                    .unwrap()
                    .is_finite(),
                "{f}"
            );
        }
    }
}

/// Cycles' mean luminance over the pixels both renders cover, over subsurf's.
fn object_mean_ratio(cycles: &Path, ours: &Path) -> f64 {
    let a = subsurf::export::read_render(cycles).unwrap();
    let b = subsurf::export::read_render(ours).unwrap();
    let lum = |p: &[f32; 3]| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
    let (mut x, mut y) = (0.0, 0.0);
    for k in 0..a.pixels.len() {
        if a.covered[k] && b.covered[k] {
            x += lum(&a.pixels[k]);
            y += lum(&b.pixels[k]);
        }
    }
    x / y
}

/// The export folder holds the glTF, the scene, the script and a report whose per-vertex
/// conversion errors are numbers (the built-in torus has a slow third term no Burley profile
/// has: its log E is well above 0).
#[test]
fn export_writes_the_scene_and_reports_the_conversion_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("torus");
    let printed = subsurf(&[
        "export",
        "--builtin",
        "torus:48,20",
        "--out",
        out.to_str().unwrap(),
        "--size",
        "64x48",
        "--no-blender",
    ]);
    assert!(printed.contains("conversion log E"), "{printed}");
    for f in [
        "model.glb",
        "scene.json",
        "build_blend.py",
        "export-report.json",
        "export-report.md",
        "export-report.html",
        "export-map.png",
    ] {
        assert!(out.join(f).is_file(), "{f} missing: {printed}");
    }
    let r = json(&out.join("export-report.json"));
    assert_eq!(r["vertices"], 960);
    assert_eq!(r["per_vertex"].as_array().unwrap().len(), 960);
    let log_e = &r["conversion_log_e"]["median"];
    for c in 0..3 {
        let x = log_e[c].as_f64().unwrap();
        assert!(x > 0.0 && x < 1.0, "{log_e}");
        assert!(r["tail_excess"]["median"][c].as_f64().unwrap().is_finite());
    }
    let scene = json(&out.join("scene.json"));
    assert_eq!(scene["format"], "subsurf-blender-scene/1");
    assert_eq!(scene["method"], "BURLEY");
    assert_eq!(scene["camera"]["width"], 64);
    assert_eq!(scene["lights"].as_array().unwrap().len(), 2);
    let s = image_stats(&out.join("export-map.png")).unwrap();
    assert!(s.distinct_colours > 20, "{s:?}");
}

/// `--gather` scales the colour by the two renderers' gathers on the model's shape and says so
/// in the report: under uniform light (`uniform`) and under the scene's lights (`lights`),
/// the colours of the plain export times the reported factor; `off` writes no gather section.
/// (On this veined torus the uniform factor spans 0.60 to 2.8, 5th to 95th percentile: subsurf
/// lights a vein's vertex with its slower neighbours' light, Cycles with the vein's own.)
#[test]
fn the_gather_factor_scales_the_colour_and_is_reported() {
    let dir = tempfile::tempdir().unwrap();
    let export = |mode: &str| {
        let out = dir.path().join(mode);
        let o = out.to_str().unwrap();
        subsurf(
            &[
                "export",
                "--builtin",
                "torus:48,20",
                "--out",
                o,
                "--size",
                "64x48",
            ]
            .into_iter()
            .chain(["--no-blender", "--gather", mode])
            .collect::<Vec<_>>(),
        );
        json(&out.join("export-report.json"))
    };
    let off = export("off");
    assert!(off.get("gather").is_none(), "{}", off["gather"]);
    for mode in ["uniform", "lights"] {
        let r = export(mode);
        let g = &r["gather"];
        assert_eq!(g["reference"], mode, "{g}");
        assert_eq!(g["vertices"], 960, "{g}");
        let [median, lo, hi] = [0, 1, 2].map(|k| g["factor"][k].as_f64().unwrap());
        assert!(
            lo > 0.0 && lo <= median && median <= hi && hi.is_finite(),
            "{g}"
        );
        let mut ratio: Vec<f64> = (0..960)
            .map(|i| {
                let c = |v: &serde_json::Value| v["per_vertex"][i]["colour"][1].as_f64().unwrap();
                c(&r) / c(&off)
            })
            .collect();
        assert!(ratio.iter().all(|&k| k.is_finite() && k > 0.0));
        assert!(
            ratio.iter().any(|&k| (k - 1.0).abs() > 1e-3),
            "nothing scaled: {g}"
        );
        ratio.sort_by(f64::total_cmp);
        let mid = ratio[480];
        assert!(
            mid >= lo && mid <= hi,
            "green median factor {mid} outside {g}"
        );
    }
}

/// A candidate conversion: `--colour two-lobe` on the built-in torus (a slow third term)
/// writes the slow lobe (scene "lobes": 2, the slow attributes, shares in [0, 1]) and fits the
/// fall-off never worse than one fitted lobe (its starting point). On this torus the terms'
/// split of the light holds the two lobes together: measured, both median log E 0.269 — the
/// share is fixed by the c_k, and here one shape is the best a 25 % slow share allows; on
/// sample-torus's fitted model two lobes give 0.026 against 0.19 (docs/export.md). With
/// Blender the script builds the two-BSDF `.blend`.
#[test]
fn two_lobes_are_written_and_fit_no_worse_than_one() {
    let dir = tempfile::tempdir().unwrap();
    let median = |out: &Path| -> Vec<f64> {
        let r = json(&out.join("export-report.json"));
        (0..3)
            .map(|c| r["conversion_log_e"]["median"][c].as_f64().unwrap())
            .collect()
    };
    let (one, two) = (dir.path().join("one"), dir.path().join("two"));
    for (out, colour) in [(&one, "fitted"), (&two, "two-lobe")] {
        let mut args = vec![
            "export",
            "--builtin",
            "torus:48,20",
            "--out",
            out.to_str().unwrap(),
            "--size",
            "64x48",
            "--colour",
            colour,
        ];
        if colour == "fitted" || blender().is_none() {
            args.push("--no-blender");
        }
        subsurf(&args);
    }
    let scene = json(&two.join("scene.json"));
    assert_eq!(scene["lobes"], 2);
    assert_eq!(json(&one.join("scene.json"))["lobes"], 1);
    let r = json(&two.join("export-report.json"));
    assert_eq!(r["colour_rule"], "two-lobe");
    for v in r["per_vertex"].as_array().unwrap() {
        let w = v["slow"]["weight"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&w), "{v}");
    }
    let (l1, l2) = (median(&one), median(&two));
    for c in 0..3 {
        assert!(l2[c] <= l1[c] + 1e-9, "two lobes {l2:?}, one {l1:?}");
    }
    if blender().is_some() {
        assert!(two.join("model.blend").is_file());
    }
}

/// A model with anisotropy (m = 2) and a face lattice of alpha: the export says it averaged the
/// segments and what that costs, and that it cut the mesh for the lattice (or, dropping it,
/// what the detail was worth).
#[test]
fn anisotropy_and_a_lattice_are_reported_with_their_cost() {
    let base = subsurf::render::synthetic::marble_torus(24, 12);
    let shape = ModelShape {
        terms: 3,
        segments: 2,
        colour: ColourMode::Shared,
    };
    let mut m = ModelFile {
        shape,
        ..base.clone()
    };
    for v in &mut m.vertices {
        // Segment 1 falls off 40 % more slowly than segment 0.
        let p = v.params.clone();
        let mut q = p.clone();
        for t in 0..3 {
            q.push(p[2 + 2 * t]);
            q.push(p[3 + 2 * t] / 1.4);
        }
        v.params = q;
        v.segments = 2;
    }
    let k = 3;
    let one: Vec<[f32; 3]> = points(k)
        .map(|(_, i, j)| {
            if is_corner(k, i, j) {
                [0.0; 3]
            } else {
                [0.2; 3]
            }
        })
        .collect();
    m.face_alpha =
        Some(FaceAlpha::new(vec![k; m.triangles.len()], one.repeat(m.triangles.len())).unwrap());
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("aniso.ply");
    m.write(&model).unwrap();
    let out = dir.path().join("refined");
    let printed = subsurf(&[
        "export",
        "--model",
        model.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--size",
        "32x32",
        "--no-blender",
    ]);
    assert!(
        printed.contains("dropped: anisotropy (Eq. 3, m = 2 segments) averaged"),
        "{printed}"
    );
    assert!(
        printed.contains("cutting every face at level 3"),
        "{printed}"
    );
    let r = json(&out.join("export-report.json"));
    let aniso = r["dropped"]["anisotropy"][1]["mean"][0].as_f64().unwrap();
    assert!(aniso > 0.01 && aniso < 1.0, "{aniso}");
    assert_eq!(r["refinement"]["level"], 3);
    assert_eq!(r["written"][1], 9 * m.triangles.len());
    let report = std::fs::read_to_string(out.join("export-report.md")).unwrap();
    assert!(report.contains("## What Cycles cannot carry"), "{report}");

    let dropped = dir.path().join("dropped");
    let printed = subsurf(&[
        "export",
        "--model",
        model.to_str().unwrap(),
        "--out",
        dropped.to_str().unwrap(),
        "--size",
        "32x32",
        "--lattice",
        "drop",
        "--no-blender",
    ]);
    assert!(printed.contains("face lattice of alpha"), "{printed}");
    let r = json(&dropped.join("export-report.json"));
    let (rms, max) = (
        r["dropped"]["lattice_detail"][0].as_f64().unwrap(),
        r["dropped"]["lattice_detail"][1].as_f64().unwrap(),
    );
    assert!(rms > 0.05 && (max - 0.2).abs() < 1e-6, "{rms} {max}");
    assert_eq!(r["written"][1], m.triangles.len());
}

/// The demo's fitted model, exported, rendered headless in Blender's Cycles under the demo's
/// key light and camera (96 px, 256 samples), against subsurf's render of the same model. The
/// demo's sphere (radius 4 mm) is no larger than its fall-off's reach (3d ≈ 3.6 mm): without a
/// factor Cycles' disk probes gather a quarter more light than subsurf's surface sum and its
/// picture is uniformly about 25 % brighter (measured 21.7 %). The demo exports with the gather
/// factor measured under its key light (`--gather lights`, docs/export.md): measured 6.3 %
/// (Blender 5.0.1, noise 4.3 %, signed −4.3 %) and 10.6 % (3.4.1, noise 9.6 %, signed −6.2 %).
/// The bounds hold that: no longer brighter, within about twice the noise, the same silhouette.
#[test]
fn the_demo_model_renders_in_blender_like_subsurfs_render() {
    if blender().is_none() {
        return;
    }
    let (out, stdout) = crate::demo::demo();
    assert!(
        stdout.contains("in Blender: mean relative pixel error"),
        "{stdout}"
    );
    let dir = out.join("blender");
    for f in ["model.blend", "cycles.exr", "subsurf.exr", "difference.png"] {
        assert!(dir.join(f).is_file(), "{f} missing");
    }
    let r = json(&dir.join("export-report.json"));
    let c = &r["comparison"];
    let err = c["mean_relative_error"].as_f64().unwrap();
    let signed = c["luminance_mean_signed"].as_f64().unwrap();
    let p95 = c["luminance_p95"].as_f64().unwrap();
    eprintln!(
        "Cycles against subsurf on the demo model: mean relative pixel error {:.1} %, mean \
         signed luminance {:+.1} %, 95th percentile {:.1} %, coverage mismatch {:.2} %",
        100.0 * err,
        100.0 * signed,
        100.0 * p95,
        100.0 * c["coverage_mismatch"].as_f64().unwrap()
    );
    assert_eq!(r["gather"]["reference"], "lights", "{}", r["gather"]);
    assert!(
        r["gather"]["factor"][0].as_f64().unwrap() < 0.9,
        "{}",
        r["gather"]
    );
    let noise = c["cycles_noise"].as_f64().unwrap();
    assert!(err < 0.05 + 1.5 * noise, "{c}");
    assert!(
        signed > -0.15 && signed < 0.1,
        "neither brighter nor much darker: {c}"
    );
    assert!(c["coverage_mismatch"].as_f64().unwrap() < 0.02, "{c}");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("in Blender"), "{report}");
    let s = image_stats(&out.join("render-blender-key-light.png")).unwrap();
    assert!(s.distinct_colours > 20 && s.luma_std > 5.0, "{s:?}");
}

fn subsurf_fails(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(args)
        .output()
        .unwrap();
    assert!(!o.status.success(), "subsurf {args:?} should fail");
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// `mean_log_e` and the per-frame green log E of `subsurf evaluate … --json`.
fn figures(v: &serde_json::Value) -> (Vec<f64>, Vec<(u64, Option<f64>)>) {
    let mean = v["mean_log_e"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    let per = v["per_frame"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["frame"].as_u64().unwrap(), f["log_e"][1].as_f64()))
        .collect();
    (mean, per)
}

/// `subsurf evaluate --images` judges any renderer's pictures of a scan's frames like a model
/// (what the Cycles renders of scan frames are judged by): the frames themselves, judged as images, are exact (log E 0: the same points,
/// neighbourhoods and units as the samples); `subsurf predict`'s images of the small slab's
/// frames (the simulation's true model) give the model's figures on the same samples, up to
/// where the prediction is taken (the bilinear read of pixel-centre predictions against the
/// model at the vertex itself: measured 2.5 % on the means, 0.004 on a frame). The samples are
/// read with the coverage check: at the slab's boundary vertices a read mixes in the
/// background, which the frame and any image see but a model at the vertex does not (there the
/// two differ by design). Images twice as bright are ln 2 off on every sample; a missing image,
/// one of the wrong size or with a NaN is an error naming its frame.
#[test]
fn predicts_images_judged_as_images_give_the_models_figures() {
    let ds = crate::fixture::small_slab();
    let model = ds.join("ground-truth.ply");
    let tmp = tempfile::tempdir().unwrap();
    let images = tmp.path().join("frames");
    std::fs::create_dir_all(&images).unwrap();
    let frames = [5usize, 10];
    for k in frames {
        subsurf(&[
            "predict",
            "--model",
            model.to_str().unwrap(),
            "--scan",
            ds.to_str().unwrap(),
            "--frame",
            &k.to_string(),
            "--out",
            images.join(format!("{k:06}.exr")).to_str().unwrap(),
        ]);
    }
    let cache = tmp.path().join("cache");
    let evaluate = |extra: &[&str]| -> serde_json::Value {
        let mut args = vec![
            "evaluate",
            "--model",
            model.to_str().unwrap(),
            "--scan",
            ds.to_str().unwrap(),
            "--frames",
            "5,10",
            "--json",
            "--coverage-check",
            "--cache",
            cache.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        serde_json::from_str(&subsurf(&args)).unwrap()
    };
    let of_model = evaluate(&[]);
    let of_images = evaluate(&["--images", images.to_str().unwrap()]);
    for key in ["mean_log_e", "per_frame", "frames", "se_log_e"] {
        assert!(of_images.get(key).is_some(), "{key} missing: {of_images}");
    }
    assert_eq!(of_images["frames"], 2, "{of_images}");
    assert_eq!(of_images["unlit"], 0, "{of_images}");
    let (m_mean, m_per) = figures(&of_model);
    let (i_mean, i_per) = figures(&of_images);
    eprintln!("model {m_mean:?} {m_per:?}\nimages {i_mean:?} {i_per:?}");
    assert!(m_mean.iter().all(|&x| x > 0.05), "{m_mean:?}");
    for (a, b) in m_mean.iter().zip(&i_mean) {
        assert!(
            (a - b).abs() <= 0.05 * a.max(*b),
            "mean log E: model {m_mean:?}, its images {i_mean:?}"
        );
    }
    for ((fa, a), (fb, b)) in m_per.iter().zip(&i_per) {
        assert_eq!(fa, fb);
        let (a, b) = (a.unwrap(), b.unwrap());
        assert!(
            (a - b).abs() <= 0.05 * a.max(b) + 0.005,
            "frame {fa}: {a} vs {b}"
        );
    }
    // The ring yardstick: the model and its own images judged on the same rings (fixed by
    // the frame's samples) agree within the bilinear read's rounding, beside the per-sample keys.
    let r_model = evaluate(&["--rings"]);
    let r_images = evaluate(&["--rings", "--images", images.to_str().unwrap()]);
    for key in [
        "ring_mean_log_e",
        "ring_per_frame",
        "rings",
        "mean_log_e",
        "per_frame",
    ] {
        assert!(r_images.get(key).is_some(), "{key} missing: {r_images}");
    }
    assert_eq!(r_model["mean_log_e"], of_model["mean_log_e"]);
    let ring_edges = |v: &serde_json::Value| v["rings"]["frames"].clone();
    let edges_of = |v: &serde_json::Value| -> Vec<serde_json::Value> {
        ring_edges(v)
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["edges"].clone())
            .collect()
    };
    assert_eq!(
        edges_of(&r_model),
        edges_of(&r_images),
        "the same rings for both"
    );
    let ring_mean = |v: &serde_json::Value| -> Vec<f64> {
        v["ring_mean_log_e"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let (rm, ri) = (ring_mean(&r_model), ring_mean(&r_images));
    eprintln!("rings: model {rm:?}, images {ri:?}");
    for (a, b) in rm.iter().zip(&ri) {
        assert!(
            (a - b).abs() <= 0.01,
            "ring mean log E: model {rm:?}, its images {ri:?}"
        );
    }
    for f in edges_of(&r_model) {
        assert!(
            f.as_array().unwrap().len() >= 3,
            "at least two rings a frame: {f}"
        );
    }
    // Twice as bright is ln 2 off in every ring, whatever the model's own error.
    let bright_rings = tmp.path().join("bright-rings");
    std::fs::create_dir_all(&bright_rings).unwrap();
    for k in frames {
        let name = format!("{k:06}.exr");
        let mut img = subsurf::dataset::read_image(&images.join(&name)).unwrap();
        img.data.iter_mut().for_each(|v| *v *= 2.0);
        subsurf::dataset::write_exr(&bright_rings.join(&name), &img).unwrap();
    }
    let rb = ring_mean(&evaluate(&[
        "--rings",
        "--images",
        bright_rings.to_str().unwrap(),
    ]));
    for (b, m) in rb.iter().zip(&ri) {
        assert!(*b >= 2f64.ln() - m - 1e-9, "twice as bright: {rb:?}");
    }
    // The frames as their own prediction: exact.
    let own = tmp.path().join("own");
    std::fs::create_dir_all(&own).unwrap();
    for k in frames {
        let name = format!("{k:06}.exr");
        std::fs::copy(ds.join("frames").join(&name), own.join(&name)).unwrap();
    }
    let (o_mean, _) = figures(&evaluate(&["--images", own.to_str().unwrap()]));
    assert!(o_mean.iter().all(|&x| x < 1e-9), "{o_mean:?}");
    // Twice as bright: every ln E moves by ln 2, so log E is at least ln 2 − the model's.
    let bright = tmp.path().join("bright");
    std::fs::create_dir_all(&bright).unwrap();
    for k in frames {
        let name = format!("{k:06}.exr");
        let mut img = subsurf::dataset::read_image(&images.join(&name)).unwrap();
        img.data.iter_mut().for_each(|v| *v *= 2.0);
        subsurf::dataset::write_exr(&bright.join(&name), &img).unwrap();
    }
    let (b_mean, _) = figures(&evaluate(&["--images", bright.to_str().unwrap()]));
    for (b, m) in b_mean.iter().zip(&m_mean) {
        assert!(*b > 2f64.ln() - m - 1e-9, "twice as bright: {b_mean:?}");
    }
    // A missing image, a wrong size, a NaN: errors naming the frame.
    let broken = tmp.path().join("broken");
    std::fs::create_dir_all(&broken).unwrap();
    std::fs::copy(images.join("000005.exr"), broken.join("000005.exr")).unwrap();
    let run = |dir: &Path| {
        subsurf_fails(&[
            "evaluate",
            "--model",
            model.to_str().unwrap(),
            "--scan",
            ds.to_str().unwrap(),
            "--frames",
            "5,10",
            "--cache",
            cache.to_str().unwrap(),
            "--images",
            dir.to_str().unwrap(),
        ])
    };
    let e = run(&broken);
    assert!(e.contains("frame 10") && e.contains("missing"), "{e}");
    let small = subsurf::dataset::Image::new(32, 32, 3);
    subsurf::dataset::write_exr(&broken.join("000010.exr"), &small).unwrap();
    let e = run(&broken);
    assert!(e.contains("frame 10") && e.contains("32x32"), "{e}");
    let mut nan = subsurf::dataset::read_image(&images.join("000010.exr")).unwrap();
    nan.data[7] = f32::NAN;
    subsurf::dataset::write_exr(&broken.join("000010.exr"), &nan).unwrap();
    let e = run(&broken);
    assert!(e.contains("frame 10") && e.contains("non-finite"), "{e}");
}

/// A copy of the small slab at `dir` whose frames are exposure brackets: each frame's `image`
/// an exposure of 0.5 s (the pixels × 0.5, the saturation with them) and one bracket of 2 s
/// (× 2), merged back into the same radiance (docs/scan-format.md) — a dataset whose frames'
/// exposure is not 1.
fn bracketed_small_slab(dir: &Path) {
    crate::fixture::small_slab_copy(dir);
    let _ = std::fs::remove_dir_all(dir.join(".subsurf-cache"));
    let scan = dir.join("scan.json");
    let mut spec = json(&scan);
    // The sensor clips at the same light: its raw level scales with the shortest exposure.
    if let Some(sat) = spec["saturation"].as_f64() {
        spec["saturation"] = (sat * 0.5).into();
    }
    for f in spec["frames"].as_array_mut().unwrap() {
        let name = f["image"].as_str().unwrap().to_string();
        let img = subsurf::dataset::read_image(&dir.join(&name)).unwrap();
        let exposure = f["exposure_s"].as_f64().unwrap_or(1.0);
        let scaled = |t: f64| {
            let mut x = img.clone();
            x.data.iter_mut().for_each(|v| *v *= (t / exposure) as f32);
            x
        };
        subsurf::dataset::write_exr(&dir.join(&name), &scaled(0.5)).unwrap();
        let long = name.replace(".exr", "_b.exr");
        subsurf::dataset::write_exr(&dir.join(&long), &scaled(2.0)).unwrap();
        f["exposure_s"] = 0.5.into();
        f["brackets"] = serde_json::json!([{ "image": long, "exposure_s": 2.0 }]);
    }
    std::fs::write(&scan, serde_json::to_vec_pretty(&spec).unwrap()).unwrap();
}

/// `subsurf export --scan S --frames F --render` renders two frames of a small scan in
/// Cycles with the exported material (the frame's camera and exposure, the laser as a narrow
/// spot on x_i) into `frames/<frame>.exr`, and its report judges them like a model, beside the
/// model's own log E. The scan is the small slab with exposure brackets (exposure 0.5 s: the
/// renders must be in the frames' units). Checked: the renders are the camera's size and carry
/// the beam's power times the exposure (with the colour the total reflectance, their total light
/// within 25 % of `subsurf predict`'s image of the same frame), the report's subsurf column is `subsurf evaluate`'s, and `subsurf
/// evaluate --images` on the renders gives the report's Cycles column; and the same with the
/// frames as camera files (16-bit PNG brackets, [`camera_file_small_slab`]). 64 × 64 px, 128
/// samples: a few seconds each.
#[test]
fn scan_frames_render_in_cycles_and_are_judged_like_a_model() {
    if blender().is_none() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("bracketed");
    bracketed_small_slab(&ds);
    let ds = ds.as_path();
    let model = crate::fixture::small_slab().join("ground-truth.ply");
    let out = tmp.path().join("export");
    let cache = tmp.path().join("cache");
    let (m, d, c) = (
        model.to_str().unwrap(),
        ds.to_str().unwrap(),
        cache.to_str().unwrap(),
    );
    let printed = render_frames_5_and_10(m, &out, ds, &cache);
    assert!(printed.contains("Cycles / subsurf (green)"), "{printed}");
    let report = json(&out.join("export-report.json"));
    let f = &report["frames"];
    let rows = f["per_frame"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{f}");
    let scenes = json(&out.join("frames.json"));
    assert_eq!(scenes["frames"].as_array().unwrap().len(), 2, "{scenes}");
    let of_model: serde_json::Value = serde_json::from_str(&subsurf(&[
        "evaluate", "--model", m, "--scan", d, "--frames", "5,10", "--json", "--cache", c,
    ]))
    .unwrap();
    // The brackets merge back into the plain slab's radiance: the same figures.
    let plain = crate::fixture::small_slab();
    let of_plain: serde_json::Value = serde_json::from_str(&subsurf(&[
        "evaluate",
        "--model",
        m,
        "--scan",
        plain.to_str().unwrap(),
        "--frames",
        "5,10",
        "--json",
        "--cache",
        tmp.path().join("plain-cache").to_str().unwrap(),
    ]))
    .unwrap();
    for ch in 0..3 {
        let (a, b) = (
            of_plain["mean_log_e"][ch].as_f64().unwrap(),
            of_model["mean_log_e"][ch].as_f64().unwrap(),
        );
        assert!((a - b).abs() < 1e-4 * a, "brackets: {a} vs {b}");
    }
    let images = out.join("frames");
    let of_images: serde_json::Value = serde_json::from_str(&subsurf(&[
        "evaluate",
        "--model",
        m,
        "--scan",
        d,
        "--frames",
        "5,10",
        "--json",
        "--cache",
        c,
        "--images",
        images.to_str().unwrap(),
    ]))
    .unwrap();
    for (n, row) in rows.iter().enumerate() {
        let k = row["frame"].as_u64().unwrap();
        assert_eq!(of_model["per_frame"][n]["frame"].as_u64(), Some(k));
        for ch in 0..3 {
            let ours = row["subsurf_log_e"][ch].as_f64().unwrap();
            let theirs = row["cycles_log_e"][ch].as_f64().unwrap();
            assert_eq!(of_model["per_frame"][n]["log_e"][ch].as_f64(), Some(ours));
            assert_eq!(
                of_images["per_frame"][n]["log_e"][ch].as_f64(),
                Some(theirs)
            );
            assert!(theirs.is_finite() && theirs > 0.0, "{row}");
        }
        // The renders carry the beam's power: their light adds up to the model's prediction.
        let ratio = light_against_prediction(&images, m, ds, k, &tmp.path().join("plain"));
        eprintln!("frame {k}: Cycles' total light / the model's {ratio:.3}; {row}");
        assert!((0.75..1.25).contains(&ratio), "frame {k}: {ratio}");
    }
    let mean = f["cycles_mean_log_e"][1].as_f64().unwrap();
    assert_eq!(of_images["mean_log_e"][1].as_f64(), Some(mean));

    // The same frames as camera files (16-bit PNG, three brackets, exposures far from 1): the
    // scenes carry the frames' own exposure, so the renders are in the camera files' units
    // (their light adds up to `subsurf predict`'s image of the same frame, as the EXR
    // dataset's does) and judge like the EXR dataset's: the figures differ by the 16-bit
    // quantisation only (measured: subsurf's within 1.4 %, Cycles' within 0.02 %).
    let cam = tmp.path().join("camera-files");
    camera_file_small_slab(&cam);
    let cam_out = tmp.path().join("export-camera-files");
    render_frames_5_and_10(m, &cam_out, &cam, &tmp.path().join("cam-cache"));
    let cam_report = json(&cam_out.join("export-report.json"));
    let cam_rows = cam_report["frames"]["per_frame"].as_array().unwrap();
    assert_eq!(cam_rows.len(), rows.len(), "{cam_report}");
    for (a, b) in rows.iter().zip(cam_rows) {
        assert_eq!(a["frame"], b["frame"]);
        for ch in 0..3 {
            let close = |key: &str, tol: f64| {
                let (x, y) = (a[key][ch].as_f64().unwrap(), b[key][ch].as_f64().unwrap());
                assert!(
                    (x - y).abs() <= tol * x,
                    "{key} channel {ch}: EXR {x}, camera files {y}"
                );
            };
            close("subsurf_log_e", 0.03);
            close("cycles_log_e", 0.005);
        }
        let k = b["frame"].as_u64().unwrap();
        let ratio = light_against_prediction(
            &cam_out.join("frames"),
            m,
            &cam,
            k,
            &tmp.path().join("camera"),
        );
        eprintln!("camera files, frame {k}: Cycles' total light / the model's {ratio:.3}");
        assert!(
            (0.75..1.25).contains(&ratio),
            "camera files, frame {k}: {ratio}"
        );
    }
}

/// `subsurf export --render` of frames 5 and 10 of `scan` at 128 samples into `out`; what it
/// printed. With the colour the total reflectance T, Cycles scatters exactly the model's light:
/// the units checks.
fn render_frames_5_and_10(model: &str, out: &Path, scan: &Path, cache: &Path) -> String {
    subsurf(&[
        "export",
        "--model",
        model,
        "--out",
        out.to_str().unwrap(),
        "--scan",
        scan.to_str().unwrap(),
        "--frames",
        "5,10",
        "--render",
        "--samples",
        "128",
        "--colour",
        "total",
        "--cache",
        cache.to_str().unwrap(),
    ])
}

/// Frame `k`'s Cycles render in `renders` (64 × 64 px) against `subsurf predict`'s image of the
/// same frame of `scan` by `model` (written under `scratch`): their total light's ratio.
fn light_against_prediction(
    renders: &Path,
    model: &str,
    scan: &Path,
    k: u64,
    scratch: &Path,
) -> f64 {
    let name = format!("{k:06}.exr");
    let cycles = subsurf::dataset::read_image(&renders.join(&name)).unwrap();
    assert_eq!((cycles.width, cycles.height), (64, 64));
    std::fs::create_dir_all(scratch).unwrap();
    let predicted = scratch.join(&name);
    subsurf(&[
        "predict",
        "--model",
        model,
        "--scan",
        scan.to_str().unwrap(),
        "--frame",
        &k.to_string(),
        "--out",
        predicted.to_str().unwrap(),
    ]);
    let predicted = subsurf::dataset::read_image(&predicted).unwrap();
    let total = |img: &subsurf::dataset::Image| img.data.iter().map(|&v| v as f64).sum::<f64>();
    total(&cycles) / total(&predicted)
}

/// A copy of the small slab at `dir` whose frames are camera files: 16-bit linear PNGs
/// (docs/scan-format.md, "Camera files"; decoded as DN / 65535) at three exposures ×1, ×64,
/// ×4096, the shortest with the brightest pixel at half the white level, each declared with the
/// exposure that makes decoded / exposure_s the EXR frames' radiance.
fn camera_file_small_slab(dir: &Path) {
    crate::fixture::small_slab_copy(dir);
    let _ = std::fs::remove_dir_all(dir.join(".subsurf-cache"));
    let scan = dir.join("scan.json");
    let mut spec = json(&scan);
    // Camera files clip at their white level (1 decoded): the float frames' clipped pixels are
    // written at it in every exposure, and there is no float saturation.
    let saturation = spec.as_object_mut().unwrap().remove("saturation");
    let clipped = saturation.and_then(|s| s.as_f64()).unwrap_or(f64::INFINITY) as f32;
    let frames = spec["frames"].as_array_mut().unwrap();
    let radiance: Vec<subsurf::dataset::Image> = frames
        .iter()
        .map(|f| {
            let mut img =
                subsurf::dataset::read_image(&dir.join(f["image"].as_str().unwrap())).unwrap();
            let exposure = f["exposure_s"].as_f64().unwrap_or(1.0) as f32;
            img.data.iter_mut().for_each(|v| {
                *v = if *v >= clipped {
                    f32::INFINITY
                } else {
                    *v / exposure
                }
            });
            img
        })
        .collect();
    let brightest = radiance
        .iter()
        .flat_map(|i| i.data.iter())
        .filter(|v| v.is_finite())
        .fold(0.0f32, |a, &v| a.max(v)) as f64;
    let t0 = 0.5 / brightest;
    for (f, img) in frames.iter_mut().zip(&radiance) {
        let stem = f["image"]
            .as_str()
            .unwrap()
            .trim_end_matches(".exr")
            .to_string();
        let mut names = Vec::new();
        for (tag, t) in [("", t0), ("_b", 64.0 * t0), ("_c", 4096.0 * t0)] {
            let dn: Vec<u16> = img
                .data
                .iter()
                .map(|&v| ((v as f64 * t).clamp(0.0, 1.0) * 65535.0).round() as u16)
                .collect();
            let (w, h) = (img.width as u32, img.height as u32);
            let name = format!("{stem}{tag}.png");
            match img.channels {
                1 => image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, dn)
                    .unwrap()
                    .save(dir.join(&name)),
                _ => image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(w, h, dn)
                    .unwrap()
                    .save(dir.join(&name)),
            }
            .unwrap();
            names.push((name, t));
        }
        f["image"] = names[0].0.clone().into();
        f["exposure_s"] = names[0].1.into();
        f["brackets"] = names[1..]
            .iter()
            .map(|(n, t)| serde_json::json!({ "image": n, "exposure_s": t }))
            .collect::<Vec<_>>()
            .into();
    }
    std::fs::write(&scan, serde_json::to_vec_pretty(&spec).unwrap()).unwrap();
}

/// The sum of channel `c` of `img` over the render border of frame `k`'s scene in
/// `frames.json` (the only pixels Cycles rendered), a pixel inside its edges (where Blender
/// versions round the border differently).
fn border_sum(
    img: &subsurf::dataset::Image,
    scenes: &serde_json::Value,
    k: usize,
    c: usize,
) -> f64 {
    let s = scenes["frames"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["frame"] == k)
        .unwrap();
    let b: Vec<f64> = match s["border"].as_array() {
        Some(b) => b.iter().map(|x| x.as_f64().unwrap()).collect(),
        None => vec![0.0, 1.0, 0.0, 1.0],
    };
    let (w, h) = (img.width as f64, img.height as f64);
    let mut sum = 0.0;
    for j in 0..img.height {
        for i in 0..img.width {
            // Blender's border: fractions from the bottom left; pixel centres.
            let (x, y) = ((i as f64 + 0.5) / w, 1.0 - (j as f64 + 0.5) / h);
            let inside = |z: f64, lo: f64, hi: f64, n: f64| z >= lo + 1.0 / n && z <= hi - 1.0 / n;
            if inside(x, b[0], b[1], w) && inside(y, b[2], b[3], h) {
                sum += img.data[(j * img.width + i) * img.channels + c] as f64;
            }
        }
    }
    sum
}

/// A volume model's export in every Blender at hand: the medium as a Principled Volume inside
/// the mesh, two frames of the small scan rendered by Cycles' own volume path tracer and judged
/// beside subsurf's trace of the same medium. The two renderers of one medium agree: per frame
/// and channel, the light over the rendered region within 10 % of subsurf's trace (measured at
/// 1024 samples: Blender 3.4.1 −1 to +2 %, 5.0.1 −4 to −6 %), and Cycles against the trace on
/// the frame's rings (`agreement_ring_mean_log_e`, green) below 0.15 (measured 0.074 and 0.047).
/// A grid of two cells builds its lookup, and where the Blender carries OpenVDB, its
/// `medium.vdb`.
#[test]
fn every_blender_renders_a_volume_model_as_subsurfs_tracer_does() {
    use subsurf::volume::fit::Homogeneous;
    use subsurf::volume::{FitInfo, MediumGrid, VolumeModel, predict_model};
    let tmp = tempfile::tempdir().unwrap();
    let slab = crate::fixture::small_slab();
    let d = slab.to_str().unwrap();
    let ds = subsurf::dataset::Dataset::open(slab).unwrap();
    let medium = Homogeneous {
        sigma_t: [2.0, 1.5, 2.5],
        albedo: [0.98, 0.95, 0.9],
        g: 0.2,
        loss: [(0.0, 0); 3],
        surface: subsurf::volume::dielectric::Surface::IndexMatched,
    };
    let info = FitInfo {
        frames: vec![],
        photons: 1,
        rounds: 1,
        loss: [0.0; 3],
        rings: [0; 3],
        seconds: 0.0,
        subsurf_version: "test".into(),
    };
    // The small slab's face closed into a block 8 mm deep: the renderers of a volume fill what
    // a closed surface bounds (the export closes an open face itself, by its own depth).
    let mut model = VolumeModel::homogeneous(&ds.mesh, &medium, info);
    let (lo, hi) = model.mesh.bounds();
    let block = subsurf::geometry::shapes::block([lo[0], lo[1], hi[2] - 8.0], hi);
    model.mesh = subsurf::volume::VolumeMesh::of(&block);
    let path = tmp.path().join("medium.json");
    model.write(&path).unwrap();
    let mut grid = model.clone();
    let (lo, hi) = model.mesh.bounds();
    grid.grid = MediumGrid::homogeneous(lo, hi, medium.sigma_t, medium.albedo);
    grid.grid.dims = [2, 1, 1];
    grid.grid.cell_mm[0] /= 2.0;
    grid.grid.sigma_t = vec![[2.0; 3], [4.0, 3.0, 2.0]];
    grid.grid.albedo = vec![[0.98; 3], [0.9, 0.95, 0.99]];
    let grid_path = tmp.path().join("grid.json");
    grid.write(&grid_path).unwrap();
    let frames = [5usize, 10];
    let ours = predict_model(&ds, &frames, &model, 200_000, 3).unwrap();
    let cache = tmp.path().join("cache");
    let c = cache.to_str().unwrap();
    let all = blenders();
    for (n, b) in all.iter().enumerate() {
        let bl = b.to_str().unwrap();
        let out = tmp.path().join(format!("volume-{n}"));
        let printed = subsurf(&[
            "export",
            "--model",
            path.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--scan",
            d,
            "--frames",
            "5,10",
            "--render",
            "--samples",
            "1024",
            "--photons",
            "200000",
            "--cache",
            c,
            "--blender",
            bl,
        ]);
        eprintln!("{bl}:\n{printed}");
        assert!(out.join("model.blend").is_file(), "{bl}: {printed}");
        let scenes = json(&out.join("frames.json"));
        for (k, img) in &ours {
            let exr = out.join(format!("frames/{k:06}.exr"));
            let theirs = subsurf::dataset::read_exr_with_alpha(&exr).unwrap().0;
            for ch in 0..3 {
                let (a, b) = (
                    border_sum(&theirs, &scenes, *k, ch),
                    border_sum(img, &scenes, *k, ch),
                );
                eprintln!("{bl}: frame {k} channel {ch}: Cycles {a:.5e}, subsurf {b:.5e}");
                assert!(
                    (a / b - 1.0).abs() < 0.1,
                    "{bl}: frame {k} channel {ch}: {a} / {b}"
                );
            }
        }
        let f = &json(&out.join("export-report.json"))["frames"];
        let agree = f["agreement_ring_mean_log_e"][1].as_f64().unwrap();
        assert!(
            agree < 0.15,
            "{bl}: Cycles against subsurf's trace on rings {agree}: {f}"
        );
        let gout = tmp.path().join(format!("grid-{n}"));
        subsurf(&[
            "export",
            "--model",
            grid_path.to_str().unwrap(),
            "--out",
            gout.to_str().unwrap(),
            "--blender",
            bl,
        ]);
        assert!(gout.join("model.blend").is_file(), "{bl}");
        if n + 1 == all.len() && std::env::var_os("SUBSURF_BPY_PYTHON").is_some() {
            // The newest Blender (the bpy module) carries OpenVDB.
            assert!(gout.join("medium.vdb").is_file(), "{bl}: no medium.vdb");
        }
    }
}

/// `export --colour auto --scan S`: every candidate conversion replayed on the frames the model
/// was fitted on (never its held-out ones), subsurf's own prediction beside, and the cheapest
/// candidate the training frames cannot tell from the best exported; without training frames or
/// without a scan, a clear error.
#[test]
fn the_colour_rule_is_chosen_by_the_replay_of_the_training_frames_only() {
    let ds = crate::fixture::small_slab();
    let tmp = tempfile::tempdir().unwrap();
    let (d, cache) = (ds.to_str().unwrap(), tmp.path().join("cache"));
    let c = cache.to_str().unwrap();
    let model = tmp.path().join("m.ply");
    let m = model.to_str().unwrap();
    subsurf(&[
        "fit",
        "--scan",
        d,
        "--out",
        m,
        "--exclude-frames",
        "5,10",
        "--no-pictures",
        "--cache",
        c,
    ]);
    let out = tmp.path().join("auto");
    let printed = subsurf(&[
        "export",
        "--model",
        m,
        "--out",
        out.to_str().unwrap(),
        "--scan",
        d,
        "--colour",
        "auto",
        "--no-blender",
        "--cache",
        c,
    ]);
    assert!(printed.contains("chosen:"), "{printed}");
    let choice = json(&out.join("colour-choice.json"));
    let frames: Vec<u64> = choice["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_u64().unwrap())
        .collect();
    assert!(frames.len() >= 4, "{choice}");
    assert!(!frames.contains(&5) && !frames.contains(&10), "{choice}");
    let cands = choice["candidates"].as_array().unwrap();
    let names: Vec<&str> = cands
        .iter()
        .map(|c| c["colour"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["fitted", "total", "two-lobe"], "{choice}");
    let score = |c: &serde_json::Value| c["score"].as_f64().unwrap();
    for c in cands.iter().chain([&choice["model"]]) {
        assert!(score(c).is_finite() && score(c) > 0.0, "{c}");
    }
    assert!(choice["model"]["colour"].is_null(), "{choice}");
    let best = (0..3)
        .min_by(|&a, &b| score(&cands[a]).total_cmp(&score(&cands[b])))
        .unwrap();
    let chosen = names
        .iter()
        .position(|n| *n == choice["colour"].as_str().unwrap())
        .unwrap();
    // The first candidate in cost order whose paired difference from the best reaches 0.
    let tied = |i: usize| {
        i == best
            || cands[i]["difference_ci95"]
                .as_array()
                .is_some_and(|iv| iv[0].as_f64().unwrap() <= 0.0)
    };
    assert_eq!(chosen, (0..3).find(|&i| tied(i)).unwrap(), "{choice}");
    assert!(
        (score(&cands[best]) - score(&cands[chosen])).abs() <= 1e-12 || chosen < best,
        "{choice}"
    );
    // What was written is the chosen conversion.
    let scene = json(&out.join("scene.json"));
    assert_eq!(scene["lobes"], cands[chosen]["lobes"], "{scene}");
    // No training frames named (a simulator's ground truth), or no scan: told, nothing chosen.
    let truth = ds.join("ground-truth.ply");
    let t = truth.to_str().unwrap();
    let o = tmp.path().join("none");
    let o = o.to_str().unwrap();
    let err = subsurf_fails(&[
        "export",
        "--model",
        t,
        "--out",
        o,
        "--scan",
        d,
        "--colour",
        "auto",
        "--no-blender",
        "--cache",
        c,
    ]);
    assert!(err.contains("fitted on"), "{err}");
    let err = subsurf_fails(&["export", "--model", m, "--out", o, "--colour", "auto"]);
    assert!(err.contains("--colour auto needs --scan"), "{err}");
    let err = subsurf_fails(&[
        "export",
        "--model",
        m,
        "--out",
        o,
        "--scan",
        d,
        "--no-blender",
    ]);
    assert!(err.contains("--scan is read with --render"), "{err}");
}
