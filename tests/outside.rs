//! Files other tools write and read: a scan's frames written as camera files by
//! outside writers (16-bit TIFF by tifffile, raw DNG by PiDNG, checked with rawpy/LibRaw) fit
//! like the EXR frames; a fitted model opens in trimesh and Open3D with positions, normals and
//! faces intact.
//!
//! The Python tools live in a venv that `.ci/run` installs (`.ci/.venv`, or `$SUBSURF_PYTHON`).
//! Without it the tests print `SKIPPED:` and pass, except under CI (`CI` set), where they fail.
use std::path::{Path, PathBuf};
use std::process::Command;

use subsurf::dataset::{Dataset, ScanSpec, write_exr};
use subsurf::modelfile::ModelFile;

fn workspace() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// The Python with the outside tools (`modules` importable): `$SUBSURF_PYTHON`, else the venv
/// `.ci/run` makes. `None` (after printing `SKIPPED:`) when absent and CI is not set.
fn python(modules: &str) -> Option<PathBuf> {
    let py = std::env::var_os("SUBSURF_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".ci/.venv/bin/python"));
    let ok = py.is_file()
        && Command::new(&py)
            .args(["-c", &format!("import {modules}")])
            .output()
            .is_ok_and(|o| o.status.success());
    if !ok {
        let ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty());
        assert!(
            !ci,
            "CI is set but {} cannot import {modules}: .ci/run installs them in .ci/.venv",
            py.display()
        );
        eprintln!(
            "SKIPPED: no Python with {modules} ({}; `bash .ci/run` makes the venv, or set \
             $SUBSURF_PYTHON) and CI is not set",
            py.display()
        );
        return None;
    }
    Some(py)
}

/// A shared dataset, or `None` (after printing `SKIPPED:`) when shared/ is absent.
fn shared(name: &str) -> Option<PathBuf> {
    let dir = workspace().join("../shared/data").join(name);
    if dir.join("scan.json").is_file() {
        Some(dir)
    } else {
        eprintln!(
            "SKIPPED: {} is absent (CI clones shared/ beside the repo)",
            dir.display()
        );
        None
    }
}

fn run(cmd: &mut Command) -> String {
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "{cmd:?}: {}\n{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn subsurf(args: &[&str]) -> String {
    run(Command::new(env!("CARGO_BIN_EXE_subsurf")).args(args))
}

/// `subsurf fit` on the training frames, then `subsurf evaluate --json` on the held-out ones
/// (the reference commands): the held-out mean log E per channel.
fn held_out_error(scan: &Path, out: &Path, held_out: &str) -> [f64; 3] {
    let model = out.join("m.ply");
    let (scan, model_s) = (scan.to_str().unwrap(), model.to_str().unwrap());
    subsurf(&[
        "fit",
        "--scan",
        scan,
        "--out",
        model_s,
        "--exclude-frames",
        held_out,
        "--no-pictures",
    ]);
    let json = subsurf(&[
        "evaluate", "--model", model_s, "--scan", scan, "--frames", held_out, "--json",
    ]);
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let e = &v["mean_log_e"];
    [0, 1, 2].map(|c| e[c].as_f64().unwrap_or_else(|| panic!("{json}")))
}

/// The held-out error of sample-slab's own EXR frames (frames 1 and 5 held out), fitted once
/// for the tests that compare camera files with it.
fn slab_exr_error(src: &Path) -> [f64; 3] {
    static ERROR: std::sync::OnceLock<[f64; 3]> = std::sync::OnceLock::new();
    *ERROR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        held_out_error(src, tmp.path(), "1,5")
    })
}

/// The camera both outside writers model: 16 bits, black level 1024 DN, white level 65535 DN,
/// exposed to the right: the scan's brightest pixel (the laser spot's peak) at 15/16 of the
/// range, so no pixel clips and every difference from the float frames is quantisation (values
/// rounded to whole DN). On sample-slab 1 DN is then 5.8e-6 of the frames' radiance and the
/// noise floor (2e-5) 3.4 DN above black: one 16-bit exposure cannot hold the renders' range
/// (spot peak / noise floor = 17,500) any finer. Exposed for the tail instead (1 DN = 2.5e-6,
/// the floor at 8 DN) the spot's core clips, which is not quantisation: held-out error then
/// moved by up to 3 % here and by 36 % on sample-torus (BENCHMARKS.md).
const BLACK: f64 = 1024.0;
const WHITE: f64 = 65535.0;
const HEADROOM: f64 = 15.0 / 16.0;

/// A dataset's float frames and the DN per radiance unit of one 16-bit exposure that puts its
/// brightest value at [`HEADROOM`] of the range above black (exposed to the right).
fn exposed_to_the_right(src: &Path) -> (Dataset, Vec<subsurf::dataset::Image>, f64) {
    let ds = Dataset::open(src).unwrap();
    let images: Vec<_> = (0..ds.spec.frames.len())
        .map(|k| ds.read_frame(k).unwrap())
        .collect();
    let brightest = images
        .iter()
        .flat_map(|i| i.data.iter())
        .fold(0.0f64, |m, &v| m.max(v as f64));
    (ds, images, HEADROOM * (WHITE - BLACK) / brightest)
}

/// Frame `k`'s float values as little-endian f32 under `tmp/raw`, for `camera_files.py`.
fn write_raw(tmp: &Path, k: usize, img: &subsurf::dataset::Image) -> PathBuf {
    let raw = tmp.join("raw");
    std::fs::create_dir_all(&raw).unwrap();
    let bytes: Vec<u8> = img.data.iter().flat_map(|v| v.to_le_bytes()).collect();
    let path = raw.join(format!("{k:03}.f32"));
    std::fs::write(&path, bytes).unwrap();
    path
}

/// Runs `tests/outside/camera_files.py` (the outside writers) on `frames`; what it printed.
fn camera_files(
    py: &Path,
    tmp: &Path,
    ds: &Dataset,
    dn_per_unit: f64,
    frames: Vec<serde_json::Value>,
) -> String {
    let cam = &ds.spec.cameras[0];
    let job = tmp.join("job.json");
    std::fs::write(
        &job,
        serde_json::json!({
            "width": cam.width, "height": cam.height, "black": BLACK, "white": WHITE,
            "dn_per_unit": dn_per_unit, "frames": frames,
        })
        .to_string(),
    )
    .unwrap();
    run(Command::new(py)
        .arg(workspace().join("tests/outside/camera_files.py"))
        .arg(&job))
}

/// Sample-slab's frames converted to 16-bit TIFF (tifffile) and to raw DNG (PiDNG, a
/// Bayer mosaic; read back by rawpy/LibRaw) decode to exactly the quantised frames and fit, on
/// the same training frames, exactly as those quantised values do as float EXR (to 0.1 % of
/// held-out error: decoding adds nothing); against the original EXR frames' held-out error
/// (frames 1 and 5, the dataset's test set) the quantisation itself moves it by 2.5 / 2.7 /
/// 0.5 % (r/g/b), asserted within 3 % (0.8 / 1.3 / 0.8 % within 2 % before the fit held slow
/// terms: the EXR fit, reading the dim tail unquantised, gained that much).
#[test]
fn camera_files_from_outside_writers_fit_like_the_exr_frames() {
    let Some(py) = python("numpy, tifffile, pidng, rawpy") else {
        return;
    };
    let Some(src) = shared("sample-slab") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let (ds, images, dn_per_unit) = exposed_to_the_right(&src);
    let quantised = |v: f32| (v as f64 * dn_per_unit).round().clamp(0.0, WHITE - BLACK);
    let (tiff_dir, dng_dir, float_dir) = (
        tmp.path().join("tiff"),
        tmp.path().join("dng"),
        tmp.path().join("quantised-exr"),
    );
    let mut frames = Vec::new();
    for (k, img) in images.iter().enumerate() {
        assert_eq!(img.channels, 3);
        frames.push(serde_json::json!({
            "raw": write_raw(tmp.path(), k, img),
            "tiff": tiff_dir.join(format!("frames/{k:03}.tif")),
            "dng": dng_dir.join(format!("frames/{k:03}.dng")),
        }));
    }
    // Each converted dataset: the same scan.json and mesh, frames renamed, the noise floor in
    // the units the frames decode to ((DN − black) / (white − black) for camera files); the
    // TIFF's levels in scan.json, the DNG's in the files. The float reference holds the
    // quantised values in the original units.
    let scale = dn_per_unit / (WHITE - BLACK);
    for (dir, ext) in [(&tiff_dir, "tif"), (&dng_dir, "dng"), (&float_dir, "exr")] {
        std::fs::create_dir_all(dir.join("frames")).unwrap();
        std::fs::copy(src.join(&ds.spec.mesh), dir.join(&ds.spec.mesh)).unwrap();
        let mut spec: ScanSpec = ds.spec.clone();
        if ext != "exr" {
            spec.noise_floor = spec.noise_floor.map(|f| f * scale);
        }
        if ext == "tif" {
            spec.levels.black = Some(BLACK);
            spec.levels.white = Some(WHITE);
        }
        for (k, f) in spec.frames.iter_mut().enumerate() {
            f.image = format!("frames/{k:03}.{ext}");
        }
        std::fs::write(
            dir.join("scan.json"),
            serde_json::to_string_pretty(&spec).unwrap(),
        )
        .unwrap();
    }
    for (k, img) in images.iter().enumerate() {
        let mut q = img.clone();
        for v in &mut q.data {
            *v = (quantised(*v) / dn_per_unit) as f32;
        }
        write_exr(&float_dir.join(format!("frames/{k:03}.exr")), &q).unwrap();
    }
    let printed = camera_files(&py, tmp.path(), &ds, dn_per_unit, frames);
    assert!(printed.contains("\"clipped_photosites\": 0"), "{printed}");

    // The TIFF and the DNG (binned from its mosaic) decode to exactly the quantised frames.
    let (t, d) = (
        Dataset::open(&tiff_dir).unwrap(),
        Dataset::open(&dng_dir).unwrap(),
    );
    assert_eq!((t.saturation(), d.saturation()), (Some(1.0), Some(1.0)));
    for (k, img) in images.iter().enumerate() {
        let tif = t.read_frame(k).unwrap();
        assert_eq!(tif, d.read_frame(k).unwrap(), "frame {k}");
        for (a, b) in img.data.iter().zip(&tif.data) {
            let want = (quantised(*a) / (WHITE - BLACK)) as f32;
            assert!(
                (b - want).abs() <= 1e-7,
                "frame {k}: {a} -> {b}, want {want}"
            );
        }
    }

    let held_out = "1,5";
    let fit = |dir: &Path, name: &str| {
        let out = tmp.path().join(format!("{name}-fit"));
        std::fs::create_dir_all(&out).unwrap();
        held_out_error(dir, &out, held_out)
    };
    let original = slab_exr_error(&src);
    let float = fit(&float_dir, "quantised-exr");
    eprintln!(
        "held-out mean log E r/g/b: EXR {original:.4?}; quantised to 16 bits (1 DN = {:.3e}): \
         as float EXR {float:.4?}",
        1.0 / dn_per_unit
    );
    for (name, dir) in [("16-bit TIFF", &tiff_dir), ("DNG", &dng_dir)] {
        let e = fit(dir, name);
        eprintln!("held-out mean log E r/g/b: {name} {e:.4?}");
        for c in 0..3 {
            let same = (e[c] - float[c]).abs() / float[c];
            assert!(
                same <= 0.001,
                "{name} channel {c}: held-out {:.5} vs the same values as float {:.5}",
                e[c],
                float[c]
            );
            // 3 %: the 16-bit copy (1 DN = 5.8e-6, the floor 3.4 DN) fits 0.1760 / 0.1622 /
            // 0.1719, where the EXR fit was before it held slow terms; the EXR's own fit, which
            // reads the dim tail unquantised, is now 2.5 / 2.7 / 0.5 % lower.
            let rel = (e[c] - original[c]).abs() / original[c];
            assert!(
                rel <= 0.03,
                "{name} channel {c}: held-out {:.4} vs EXR {:.4} ({:.2} %)",
                e[c],
                original[c],
                100.0 * rel
            );
        }
    }
}

/// The exposures of the bracket test, as multiples of the exposed-to-the-right one: ×64 puts the
/// noise floor at 220 DN (steps of 0.5 % of its value), ×4096 at 14,000 DN; both clip the spot
/// and more (the ×64 one the spot's core, the ×4096 one most of the lit slab).
const BRACKET_GAINS: [f64; 3] = [1.0, 64.0, 4096.0];

/// HDR capture as another camera program writes it: sample-slab's frames as a bracket
/// of 16-bit exposures, one file per exposure (tifffile: 16-bit RGB TIFF at ×1, ×64, ×4096; PiDNG:
/// raw DNG at ×1 and ×64), listed per frame in `scan.json`'s `brackets`, the longer exposures
/// clipped over much of the image. Merged per pixel ([`subsurf::dataset::merge_hdr`]) the
/// frames equal the float frames within the ×1 exposure's quantisation, and to within 0.5 %
/// where the values lie above the noise floor (one exposure: up to 15 %); the fit's held-out
/// error (frames 1 and 5, the dataset's test set) is within 2.5 % of the EXR fit's in every
/// channel, closer than one exposure's 2.5 / 2.7 / 0.5 %. (The bound was 1 % against 1.3 % before
/// the fit held slow terms rather than dropping them: that made the EXR fit's figure 2 % lower,
/// 0.1717 / 0.1580 / 0.1728, by the dim tail the 16-bit copies quantise; the TIFF and DNG
/// brackets lie 1.1–1.3 / 1.6–2.0 / 0.2–0.3 % above it.)
#[test]
fn bracketed_camera_files_fit_like_the_exr_frames() {
    let Some(py) = python("numpy, tifffile, pidng, rawpy") else {
        return;
    };
    let Some(src) = shared("sample-slab") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let (ds, images, dn_per_unit) = exposed_to_the_right(&src);
    let scale = dn_per_unit / (WHITE - BLACK);
    let (tiff_dir, dng_dir) = (tmp.path().join("tiff"), tmp.path().join("dng"));
    let dng_gains = &BRACKET_GAINS[..2];
    let name = |k: usize, b: usize, ext: &str| format!("frames/{k:03}_{b}.{ext}");
    let mut frames = Vec::new();
    for (k, img) in images.iter().enumerate() {
        let f32_path = write_raw(tmp.path(), k, img);
        let brackets: Vec<_> = BRACKET_GAINS
            .iter()
            .enumerate()
            .skip(1)
            .map(|(b, &gain)| {
                serde_json::json!({
                    "gain": gain,
                    "tiff": tiff_dir.join(name(k, b, "tif")),
                    "dng": (b < dng_gains.len()).then(|| dng_dir.join(name(k, b, "dng"))),
                })
            })
            .collect();
        frames.push(serde_json::json!({
            "raw": f32_path,
            "tiff": tiff_dir.join(name(k, 0, "tif")),
            "dng": dng_dir.join(name(k, 0, "dng")),
            "brackets": brackets,
        }));
    }
    // Each dataset: the same scan.json and mesh; each frame's shortest exposure as its image,
    // at its own exposure_s, the longer ones in `brackets`; the noise floor in the decoded units.
    for (dir, ext, gains) in [
        (&tiff_dir, "tif", &BRACKET_GAINS[..]),
        (&dng_dir, "dng", dng_gains),
    ] {
        std::fs::create_dir_all(dir.join("frames")).unwrap();
        std::fs::copy(src.join(&ds.spec.mesh), dir.join(&ds.spec.mesh)).unwrap();
        let mut spec: serde_json::Value = serde_json::to_value(&ds.spec).unwrap();
        spec["noise_floor"] = serde_json::json!(ds.spec.noise_floor.map(|f| f * scale));
        if ext == "tif" {
            spec["black_level"] = BLACK.into();
            spec["white_level"] = WHITE.into();
        }
        for (k, f) in spec["frames"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
        {
            let e = f["exposure_s"].as_f64().unwrap();
            f["image"] = name(k, 0, ext).into();
            f["brackets"] = gains
                .iter()
                .enumerate()
                .skip(1)
                .map(|(b, g)| serde_json::json!({"image": name(k, b, ext), "exposure_s": e * g}))
                .collect();
        }
        std::fs::write(
            dir.join("scan.json"),
            serde_json::to_string_pretty(&spec).unwrap(),
        )
        .unwrap();
    }
    let printed = camera_files(&py, tmp.path(), &ds, dn_per_unit, frames);
    let clipped: serde_json::Value = serde_json::from_str(printed.trim()).unwrap();
    let clipped: Vec<u64> = clipped["clipped_by_bracket"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_u64().unwrap())
        .collect();
    eprintln!("clipped values per exposure (×{BRACKET_GAINS:?}): {clipped:?}");
    assert_eq!(clipped[0], 0, "the shortest exposure clips nothing");
    assert!(clipped[1..].iter().all(|&n| n > 0), "{clipped:?}");

    // The merged frames against the float ones: within half a DN of the shortest exposure
    // everywhere, and within 0.5 % above the noise floor.
    let floor = ds.spec.noise_floor.unwrap_or(0.0);
    let (t, d) = (
        Dataset::open(&tiff_dir).unwrap(),
        Dataset::open(&dng_dir).unwrap(),
    );
    assert_eq!((t.saturation(), d.saturation()), (Some(1.0), Some(1.0)));
    for (name, set) in [("TIFF", &t), ("DNG", &d)] {
        let mut worst = 0.0f64;
        for (k, img) in images.iter().enumerate() {
            let merged = set.read_frame(k).unwrap();
            for (&v, &m) in img.data.iter().zip(&merged.data) {
                let (v, m) = (v as f64, m as f64 / scale);
                // Half a DN, and the rounding of single-precision values (the frames' and the
                // merge's).
                assert!(
                    (m - v).abs() <= 0.5 / dn_per_unit + 4.0 * f32::EPSILON as f64 * v.abs(),
                    "{name} frame {k}: {v} merged as {m}"
                );
                if v > floor {
                    worst = worst.max((m - v).abs() / v);
                }
            }
        }
        eprintln!("{name} bracket: largest relative error above the noise floor {worst:.2e}");
        assert!(worst <= 5e-3, "{name}: {worst}");
    }

    let held_out = "1,5";
    let fit = |dir: &Path, name: &str| {
        let out = tmp.path().join(format!("{name}-fit"));
        std::fs::create_dir_all(&out).unwrap();
        held_out_error(dir, &out, held_out)
    };
    let original = slab_exr_error(&src);
    eprintln!("held-out mean log E r/g/b: EXR {original:.4?}");
    for (name, dir) in [("TIFF bracket", &tiff_dir), ("DNG bracket", &dng_dir)] {
        let e = fit(dir, name);
        eprintln!("held-out mean log E r/g/b: {name} {e:.4?}");
        for c in 0..3 {
            let rel = (e[c] - original[c]).abs() / original[c];
            assert!(
                rel <= 0.025,
                "{name} channel {c}: held-out {:.4} vs EXR {:.4} ({:.2} %)",
                e[c],
                original[c],
                100.0 * rel
            );
        }
    }
}

/// A fitted model opens in trimesh (and Open3D where it is installed, and
/// Blender's importer where Blender is) with positions, normals and faces as subsurf reads them.
#[test]
fn a_fitted_model_opens_in_trimesh_and_open3d() {
    let Some(py) = python("numpy, trimesh") else {
        return;
    };
    let Some(src) = shared("sample-slab") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let model = tmp.path().join("m.ply");
    subsurf(&[
        "fit",
        "--scan",
        src.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
        "--no-pictures",
    ]);
    let mut m = ModelFile::read(&model).unwrap();
    // With alpha finer than the mesh too (elements face_alpha and face_alpha_point; the shared
    // scans have no texture above their noise, so the fit writes none): a lattice of level 2
    // with detail between the corners on every face.
    let faces = m.triangles.len();
    let detail = (0..faces)
        .flat_map(|f| {
            subsurf::lattice::points(2).map(move |(n, i, j)| {
                if subsurf::lattice::is_corner(2, i, j) {
                    [0.0; 3]
                } else {
                    [0.01 * (f % 7) as f32, -0.02 * n as f32, 0.005]
                }
            })
        })
        .collect();
    m.face_alpha = Some(subsurf::lattice::FaceAlpha::new(vec![2; faces], detail).unwrap());
    let with_lattice = tmp.path().join("lattice.ply");
    m.write(&with_lattice).unwrap();
    for path in [&model, &with_lattice] {
        check_outside_readers(&py, path, &m);
    }
}

/// Opens `path` with trimesh (and Open3D where installed) and checks that they read `m`'s
/// positions, normals and faces.
fn check_outside_readers(py: &Path, path: &Path, m: &ModelFile) {
    let printed = run(Command::new(py)
        .arg(workspace().join("tests/outside/open_model.py"))
        .arg(path));
    let readers: serde_json::Value = serde_json::from_str(printed.trim()).unwrap();
    let n = m.positions.len();
    let sum = |v: &[[f64; 3]]| {
        v.iter()
            .fold([0.0; 3], |s, p| [s[0] + p[0], s[1] + p[1], s[2] + p[2]])
    };
    for (reader, got) in readers.as_object().unwrap() {
        assert_eq!(got["vertices"], n, "{reader}");
        assert_eq!(got["faces"], m.triangles.len(), "{reader}");
        let first = serde_json::json!([m.positions[0], m.normals[0], m.triangles[0]]);
        let last = serde_json::json!([m.positions[n - 1], m.normals[n - 1], m.triangles.last()]);
        assert_eq!(got["first"], first, "{reader}");
        assert_eq!(got["last"], last, "{reader}");
        for (key, want) in [
            ("sum_positions", sum(&m.positions)),
            ("sum_normals", sum(&m.normals)),
        ] {
            for c in 0..3 {
                let g = got[key][c].as_f64().unwrap();
                assert!(
                    (g - want[c]).abs() < 1e-9 * n as f64,
                    "{reader} {key}: {g} vs {want:?}"
                );
            }
        }
    }
    if readers.get("open3d").is_none() {
        eprintln!(
            "SKIPPED the Open3D check: Open3D is not installed (CI reads with trimesh and Blender)"
        );
    }
    // Blender's own importer, where Blender is installed (CI does not install it: hundreds of
    // megabytes). Positions are single precision in Blender.
    let Some(blender) = std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join("blender"))
            .find(|p| p.is_file())
    }) else {
        eprintln!("SKIPPED the Blender check: no blender on PATH");
        return;
    };
    let printed = run(Command::new(blender)
        .args(["-b", "--factory-startup", "--python"])
        .arg(workspace().join("tests/outside/blender_ply.py"))
        .arg("--")
        .arg(path));
    let line = printed
        .lines()
        .find_map(|l| l.strip_prefix("BLENDER "))
        .unwrap_or_else(|| panic!("{printed}"));
    let got: serde_json::Value = serde_json::from_str(line).unwrap();
    assert_eq!(got["vertices"], n, "blender");
    assert_eq!(got["faces"], m.triangles.len(), "blender");
    for (at, v, f) in [("first", 0, 0), ("last", n - 1, m.triangles.len() - 1)] {
        for c in 0..3 {
            let g = got[at][0][c].as_f64().unwrap();
            assert!(
                (g - m.positions[v][c]).abs() < 1e-5 * (1.0 + g.abs()),
                "blender {at}"
            );
        }
        assert_eq!(
            got[at][1],
            serde_json::json!(m.triangles[f]),
            "blender {at}"
        );
    }
}

/// The sample store opens in pyarrow (and pandas): the frames, the registered ones, and
/// per sample file the rows, the samples per channel and their sums read as subsurf holds them.
#[test]
fn the_sample_store_opens_in_pyarrow() {
    use subsurf::pipeline::{PipelineOptions, StoreOptions, prepare};
    use subsurf::store::PointSet;
    let Some(py) = python("pyarrow") else {
        return;
    };
    let d = tempfile::tempdir().unwrap();
    let data = d.path().join("scan");
    crate::fixture::small_slab_copy(&data);
    let ds = Dataset::open(&data).unwrap();
    let opts = PipelineOptions::for_dataset(&ds);
    let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let ctx = prepare(&ds, &frames, &opts, &StoreOptions::default(), &()).unwrap();
    let store = ctx.store().unwrap();
    let dir = store.report().dir.clone().unwrap();
    assert!(
        dir.starts_with(data.join(".subsurf-cache")),
        "{}",
        dir.display()
    );
    let printed = run(Command::new(&py)
        .arg(workspace().join("tests/outside/read_store.py"))
        .arg(&dir));
    let got: serde_json::Value = serde_json::from_str(printed.trim()).unwrap();
    assert_eq!(got["frames"], frames.len());
    let registered = store
        .records()
        .iter()
        .filter(|r| {
            matches!(
                r.outcome,
                Ok(subsurf::spot::RegistrationOutcome::Registered { .. })
            )
        })
        .count();
    assert_eq!(got["registered"], registered);
    for (set, name) in [
        (PointSet::Vertices, "vertices"),
        (PointSet::Lattice, "points"),
    ] {
        let (mut rows, mut sum_r, mut sum_s, mut valid) = (0usize, 0.0, [0.0; 3], [0usize; 3]);
        let mut rs = Vec::new();
        let mut ss = [Vec::new(), Vec::new(), Vec::new()];
        for &k in &frames {
            let Some(fs) = store.samples(k, set).unwrap() else {
                continue;
            };
            for x in fs.samples.iter() {
                rows += 1;
                rs.push(x.r);
                for c in 0..3 {
                    if x.valid & (1 << c) != 0 {
                        valid[c] += 1;
                        ss[c].push(x.value[c]);
                    }
                }
            }
        }
        if set == PointSet::Lattice && store.points().is_none() {
            continue;
        }
        let fsum = |v: &[f64]| v.iter().sum::<f64>();
        sum_r += fsum(&rs);
        for c in 0..3 {
            sum_s[c] = fsum(&ss[c]);
        }
        let g = &got[name];
        assert_eq!(g["rows"], rows, "{name}: {printed}");
        assert_eq!(g["valid"], serde_json::json!(valid), "{name}");
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs().max(1e-300);
        assert!(
            close(g["sum_r"].as_f64().unwrap(), sum_r),
            "{name}: {printed}"
        );
        for c in 0..3 {
            assert!(
                close(g["sum_s"][c].as_f64().unwrap(), sum_s[c]),
                "{name} {c}"
            );
        }
    }
    if let Some(n) = got.get("pandas_rows") {
        assert_eq!(n, &got["vertices"]["rows"]);
    }
}

/// A camera's dataset without `noise_floor`, as a new user writes one: a shared dataset's
/// frames as 16-bit TIFF brackets (×1, ×64, ×4096; tifffile), once with the renders' floor in
/// the decoded units and once without the key. Without it the floor is measured from the frames
/// (`pipeline::noise`), and the fit's held-out green error (the dataset's test frames, judged
/// on the same samples: the given floor's) is within 2 % of the fit with the floor. Before, a
/// missing floor was 0 and moved sample-pebble's from 0.379 to 0.773. With the black level also
/// left out of scan.json, the fit refuses with a message that names it, or lands within 2 %.
fn a_bracketed_dataset_without_a_noise_floor_fits_as_with_it(dataset: &str, held: &str) {
    let Some(py) = python("numpy, tifffile, pidng, rawpy") else {
        return;
    };
    let Some(src) = shared(dataset) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let (ds, images, dn_per_unit) = exposed_to_the_right(&src);
    let scale = dn_per_unit / (WHITE - BLACK);
    let given = tmp.path().join("given");
    let name = |k: usize, b: usize| format!("frames/{k:03}_{b}.tif");
    let mut frames = Vec::new();
    for (k, img) in images.iter().enumerate() {
        let brackets: Vec<_> = BRACKET_GAINS
            .iter()
            .enumerate()
            .skip(1)
            .map(|(b, &gain)| serde_json::json!({"gain": gain, "tiff": given.join(name(k, b))}))
            .collect();
        frames.push(serde_json::json!({
            "raw": write_raw(tmp.path(), k, img),
            "tiff": given.join(name(k, 0)),
            "brackets": brackets,
        }));
    }
    std::fs::create_dir_all(given.join("frames")).unwrap();
    camera_files(&py, tmp.path(), &ds, dn_per_unit, frames);
    let floor = ds
        .spec
        .noise_floor
        .expect("the shared datasets give their floor")
        * scale;
    let (missing, no_black) = (tmp.path().join("missing"), tmp.path().join("no-black"));
    for dir in [&given, &missing, &no_black] {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::copy(src.join(&ds.spec.mesh), dir.join(&ds.spec.mesh)).unwrap();
        let mut spec: serde_json::Value = serde_json::to_value(&ds.spec).unwrap();
        spec["noise_floor"] = floor.into();
        spec["black_level"] = BLACK.into();
        spec["white_level"] = WHITE.into();
        for (k, f) in spec["frames"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
        {
            let e = f["exposure_s"].as_f64().unwrap();
            f["image"] = name(k, 0).into();
            f["brackets"] = BRACKET_GAINS
                .iter()
                .enumerate()
                .skip(1)
                .map(|(b, g)| serde_json::json!({"image": name(k, b), "exposure_s": e * g}))
                .collect();
        }
        if dir != &given {
            // The datasets without the key read the same files (through a link to the other's
            // frames folder: paths stay inside the dataset).
            std::os::unix::fs::symlink(given.join("frames"), dir.join("frames")).unwrap();
            spec.as_object_mut().unwrap().remove("noise_floor");
        }
        if dir == &no_black {
            spec.as_object_mut().unwrap().remove("black_level");
        }
        std::fs::write(
            dir.join("scan.json"),
            serde_json::to_string_pretty(&spec).unwrap(),
        )
        .unwrap();
    }
    let fit = |scan: &Path| -> Result<(PathBuf, serde_json::Value), String> {
        let model = scan.join("m.ply");
        let report = scan.join("fit-report.json");
        let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
            .args(["fit", "--scan", scan.to_str().unwrap(), "--out"])
            .arg(&model)
            .args(["--exclude-frames", held, "--no-pictures", "--cache", "off"])
            .output()
            .unwrap();
        if !o.status.success() {
            return Err(String::from_utf8_lossy(&o.stderr).into_owned());
        }
        let r = serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap();
        Ok((model, r))
    };
    // Held-out green (mean log E and its clustered SE) on the samples of the given floor.
    let judge = |model: &Path| -> (f64, f64) {
        let mut a = vec!["evaluate", "--model", model.to_str().unwrap()];
        a.extend([
            "--scan",
            given.to_str().unwrap(),
            "--frames",
            held,
            "--json",
        ]);
        a.extend(["--cache", "off"]);
        let v: serde_json::Value = serde_json::from_str(&subsurf(&a)).unwrap();
        let green = |key: &str| v[key][1].as_f64().unwrap_or(f64::NAN);
        (green("mean_log_e"), green("se_log_e"))
    };
    let (with_floor, _) = fit(&given).unwrap();
    let (a, a_se) = judge(&with_floor);
    let (without, report) = fit(&missing).unwrap();
    let measured = report["noise_floor"]["value"].as_f64().unwrap();
    assert!(
        report["noise_floor"]["source"]
            .as_str()
            .unwrap()
            .starts_with("measured"),
        "{}",
        report["noise_floor"]
    );
    let (b, b_se) = judge(&without);
    eprintln!(
        "{dataset}: noise floor given {floor:.3e}, measured {measured:.3e} ({:.2}x); held-out \
         green with the floor {a:.4} ± {a_se:.4}, measured {b:.4} ± {b_se:.4} ({:+.2} %)",
        measured / floor,
        100.0 * (b / a - 1.0)
    );
    // With the black level left in too: refused with a message naming it, or within 2 %.
    let no_black_within = match fit(&no_black) {
        Err(message) => {
            eprintln!("{dataset} without the black level: refused: {message}");
            assert!(message.contains("black_level"), "{message}");
            true
        }
        Ok((model, report)) => {
            let (c, c_se) = judge(&model);
            eprintln!(
                "{dataset} without the black level: floor {}, held-out green {c:.4} ± {c_se:.4} \
                 ({:+.2} %)",
                report["noise_floor"]["value"],
                100.0 * (c / a - 1.0)
            );
            (c / a - 1.0).abs() <= 0.02
        }
    };
    assert!(measured > floor / 4.0 && measured < floor * 4.0);
    assert!((b / a - 1.0).abs() <= 0.02, "{a} {b}");
    assert!(
        no_black_within,
        "without the black level: neither refused nor within 2 %"
    );
}

#[test]
fn a_bracketed_slab_without_a_noise_floor_fits_as_with_it() {
    a_bracketed_dataset_without_a_noise_floor_fits_as_with_it("sample-slab", "1,5");
}

#[test]
fn a_bracketed_pebble_without_a_noise_floor_fits_as_with_it() {
    a_bracketed_dataset_without_a_noise_floor_fits_as_with_it("sample-pebble", "96-103");
}

/// Ignored: the torus's measured floor is its noise's (a third of the signal at 3e-6), 0.15x
/// the floor its scan.json gives, and its fit at that floor is worse on its training folds as on
/// its test frames (docs/validation.md, "The noise floor, measured where `scan.json` has none").
/// `cargo test -- --ignored` runs it.
#[test]
#[ignore = "sample-torus: the measured floor is 0.15x scan.json's and the fit with it is worse (docs/validation.md)"]
fn a_bracketed_torus_without_a_noise_floor_fits_as_with_it() {
    a_bracketed_dataset_without_a_noise_floor_fits_as_with_it("sample-torus", "96-103");
}

/// A mesh as scanners deliver it, far finer than the frames' pixels. sample-pebble's
/// mesh subdivided twice by trimesh (40,962 vertices; the frames support about 11,000) is fitted
/// at the frames' level of detail and the model prolonged to every vertex: the model has the
/// given mesh's vertices, the report says what was fitted, and the held-out frames judge it
/// like the fit on the 2,562-vertex mesh, within the two fits' standard errors.
#[test]
fn a_mesh_finer_than_the_pixels_fits_at_their_level_of_detail() {
    let (Some(py), Some(src)) = (python("trimesh"), shared("sample-pebble")) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let fine = tmp.path().join("fine");
    std::fs::create_dir_all(fine.join("frames")).unwrap();
    std::fs::copy(src.join("scan.json"), fine.join("scan.json")).unwrap();
    for e in std::fs::read_dir(src.join("frames")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), fine.join("frames").join(e.file_name())).unwrap();
    }
    run(Command::new(&py).args([
        "-c",
        "import sys, trimesh\n\
         m = trimesh.load(sys.argv[1], process=False)\n\
         m = m.subdivide().subdivide()\n\
         m.export(sys.argv[2])",
        src.join("object.obj").to_str().unwrap(),
        fine.join("object.obj").to_str().unwrap(),
    ]));
    let judge = |scan: &Path, out: &Path| -> (serde_json::Value, serde_json::Value) {
        std::fs::create_dir_all(out).unwrap();
        let model = out.join("m.ply");
        let report = out.join("r.json");
        let (scan, model_s) = (scan.to_str().unwrap(), model.to_str().unwrap());
        subsurf(&[
            "fit",
            "--scan",
            scan,
            "--out",
            model_s,
            "--report",
            report.to_str().unwrap(),
            "--exclude-frames",
            "96-103",
            "--no-pictures",
            "--cache",
            "off",
        ]);
        let json = subsurf(&[
            "evaluate", "--model", model_s, "--scan", scan, "--frames", "96-103", "--json",
        ]);
        let r = serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap();
        (r, serde_json::from_str(&json).unwrap())
    };
    let (report, held_fine) = judge(&fine, &tmp.path().join("out-fine"));
    let (_, held_given) = judge(&src, &tmp.path().join("out-given"));
    let lod = &report["level_of_detail"];
    assert_eq!(lod["vertices"], 40_962, "{lod}");
    assert_eq!(lod["coarsened"], true, "{lod}");
    let (fitted, supported) = (
        lod["fitted_vertices"].as_f64().unwrap(),
        lod["supported_vertices"].as_f64().unwrap(),
    );
    assert!(
        fitted > 0.5 * supported && fitted < 2.0 * supported,
        "fitted {fitted} vertices where the pixels support {supported}"
    );
    let m = subsurf::modelfile::ModelFile::read(&tmp.path().join("out-fine/m.ply")).unwrap();
    assert_eq!(m.len(), 40_962);
    assert!(
        m.vertices
            .iter()
            .all(|v| v.status != subsurf::modelfile::VertexStatus::NoModel)
    );
    for c in 0..3 {
        let (a, b) = (
            held_fine["mean_log_e"][c].as_f64().unwrap(),
            held_given["mean_log_e"][c].as_f64().unwrap(),
        );
        let se = held_fine["se_log_e"][c]
            .as_f64()
            .unwrap()
            .max(held_given["se_log_e"][c].as_f64().unwrap());
        assert!(
            (a - b).abs() < 2.0 * se,
            "channel {c}: held-out log E {a} on the fine mesh, {b} on the given one (SE {se})"
        );
    }
}

/// The camera-file variants that hide a camera's noise floor, written by outside tools
/// (`tests/outside/floor_variants.py`: tifffile, PiDNG, rawpy, imagecodecs) from sample-slab's
/// frames on a 16-bit camera exposed for the tail (the renders' floor at 50 DN above black).
/// Without `noise_floor` in scan.json, each gives a clear error or a floor within 1.5x of the
/// one the clean files measure, never a silent 0:
/// - the clean TIFFs with their black level given: the reference floor;
/// - the same files with the black level left out of scan.json (the format's default 0): refused,
///   the message naming `black_level`;
/// - an ambient pedestal of 4 floors on every pixel: refused, or within 1.5x;
/// - a Bayer mosaic developed by rawpy (AHD demosaicing): refused as correlated;
/// - a JPEG: refused as not linear.
#[test]
fn a_floor_hidden_by_the_camera_files_is_refused_or_measured_within_one_and_a_half_times() {
    let Some(py) = python("numpy, tifffile, pidng, rawpy, imagecodecs") else {
        return;
    };
    let Some(src) = shared("sample-slab") else {
        return;
    };
    use subsurf::pipeline::noise::{NoiseError, estimate};
    let tmp = tempfile::tempdir().unwrap();
    let ds = Dataset::open(&src).unwrap();
    let floor = ds.spec.noise_floor.expect("sample-slab gives its floor");
    let dn_per_unit = 50.0 / floor;
    let out = tmp.path().join("files");
    std::fs::create_dir_all(&out).unwrap();
    let frames: Vec<serde_json::Value> = (0..ds.spec.frames.len())
        .map(|k| {
            let img = ds.read_frame(k).unwrap();
            serde_json::json!({
                "raw": write_raw(tmp.path(), k, &img),
                "out": out.join(format!("{k:03}")),
            })
        })
        .collect();
    let cam = &ds.spec.cameras[0];
    let job = tmp.path().join("variants.json");
    std::fs::write(
        &job,
        serde_json::json!({
            "width": cam.width, "height": cam.height, "black": BLACK, "white": WHITE,
            "dn_per_unit": dn_per_unit, "pedestal": 200.0, "frames": frames,
        })
        .to_string(),
    )
    .unwrap();
    run(Command::new(&py)
        .arg(workspace().join("tests/outside/floor_variants.py"))
        .arg(&job));
    // A dataset of the variant's files (`suffix`), without noise_floor, with `black` declared.
    let variant = |name: &str, suffix: &str, black: Option<f64>| -> Dataset {
        let dir = tmp.path().join(name);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(src.join(&ds.spec.mesh), dir.join(&ds.spec.mesh)).unwrap();
        std::os::unix::fs::symlink(&out, dir.join("files")).unwrap();
        let mut spec: serde_json::Value = serde_json::to_value(&ds.spec).unwrap();
        spec.as_object_mut().unwrap().remove("noise_floor");
        if let Some(b) = black {
            spec["black_level"] = b.into();
        }
        spec["white_level"] = WHITE.into();
        for (k, f) in spec["frames"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
        {
            f["image"] = format!("files/{k:03}{suffix}").into();
        }
        std::fs::write(
            dir.join("scan.json"),
            serde_json::to_string_pretty(&spec).unwrap(),
        )
        .unwrap();
        Dataset::open(&dir).unwrap()
    };
    let measure = |d: &Dataset| {
        let scene = subsurf::geometry::Scene::new(d.mesh.clone()).unwrap();
        let all: Vec<usize> = (0..d.spec.frames.len()).collect();
        estimate(d, &scene, &all)
    };
    let clean = measure(&variant("clean", ".clean.tif", Some(BLACK))).expect("the clean files");
    let reference = clean.floor;
    eprintln!(
        "clean TIFFs: floor {reference:.3e} (decoded units), correlation {:?}",
        clean.neighbour_correlation
    );
    assert!(reference > 0.0);
    let within = |f: f64| f > reference / 1.5 && f < reference * 1.5;
    // The black level left in.
    let left_in = measure(&variant("black-left-in", ".clean.tif", None));
    eprintln!("black level left in: {left_in:?}");
    match &left_in {
        Err(e @ NoiseError::NoFloor { .. }) => assert!(e.to_string().contains("black_level")),
        Ok(e) => assert!(within(e.floor), "{} against {reference}", e.floor),
        Err(e) => panic!("{e}"),
    }
    // An ambient pedestal.
    let pedestal = measure(&variant("pedestal", ".pedestal.tif", Some(BLACK)));
    eprintln!("pedestal: {pedestal:?}");
    match &pedestal {
        Err(NoiseError::NoFloor { .. }) => {}
        Ok(e) => assert!(within(e.floor), "{} against {reference}", e.floor),
        Err(e) => panic!("{e}"),
    }
    // Demosaiced by rawpy.
    let demosaiced = measure(&variant("demosaiced", ".demosaiced.tif", Some(0.0)));
    eprintln!("demosaiced: {demosaiced:?}");
    match &demosaiced {
        Err(NoiseError::Correlated { .. }) => {}
        Ok(e) => assert!(within(e.floor), "{} against {reference}", e.floor),
        Err(e) => panic!("{e}"),
    }
    // A JPEG is refused when its frame is read.
    let jpeg = measure(&variant("jpeg", ".jpg", None));
    let message = match &jpeg {
        Err(e) => format!("{e}"),
        Ok(e) => panic!("a JPEG measured a floor: {e:?}"),
    };
    eprintln!("jpeg: {message}");
    assert!(message.contains("JPEG"), "{message}");
}
