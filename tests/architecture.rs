//! The architecture invariants of ARCHITECTURE.md that a test can check, checked on the source
//! text (rust-analyzer's "tidy" style): where a dependency may be named, what a crate never does.
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every `.rs` file under `dir` (relative to the workspace root), with its text.
fn sources(dir: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut stack = vec![root().join(dir)];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let rel = p.strip_prefix(root()).unwrap().display().to_string();
                out.push((rel, std::fs::read_to_string(&p).unwrap()));
            }
        }
    }
    assert!(!out.is_empty(), "no sources under {dir}");
    out
}

/// Files under `dir` whose code (comments left out) contains `needle`.
fn naming(dir: &str, needle: &str) -> Vec<String> {
    sources(dir)
        .into_iter()
        .filter(|(_, text)| {
            text.lines()
                .map(str::trim_start)
                .filter(|l| !l.starts_with("//"))
                .any(|l| l.contains(needle))
        })
        .map(|(path, _)| path)
        .collect()
}

#[test]
fn only_the_scene_builds_a_parry_mesh() {
    let users = naming("host/src", "parry3d_f64");
    assert_eq!(users, ["host/src/geometry/mod.rs"], "{users:?}");
}

#[test]
fn the_model_crate_touches_no_files_ports_or_probes() {
    for needle in ["std::fs", "File::", "serialport", "probe_rs", "indicatif"] {
        let users = naming("host/model/src", needle);
        assert!(users.is_empty(), "{needle} in {users:?}");
    }
}

#[test]
fn only_the_binary_draws_progress_bars() {
    let users: Vec<String> = naming("host/src", "indicatif")
        .into_iter()
        .filter(|p| !p.starts_with("host/src/cmd/"))
        .collect();
    assert!(users.is_empty(), "{users:?}");
}

#[test]
fn the_firmware_core_never_imports_embassy() {
    let core: Vec<String> = naming("firmware/src", "embassy")
        .into_iter()
        .filter(|p| !p.contains("/src/bin/"))
        .collect();
    assert!(core.is_empty(), "{core:?}");
}

#[test]
fn spot_lights_and_samples_touch_no_files() {
    for f in ["spot.rs", "pipeline/select/lights.rs", "samples.rs"] {
        let text = std::fs::read_to_string(root().join("host/src").join(f)).unwrap();
        for needle in ["std::fs", "File::", "fs::write", "fs::read"] {
            assert!(!text.contains(needle), "{f} names {needle}");
        }
    }
}

#[test]
fn one_camera_type_and_one_dataset_writer() {
    // The camera model is defined once (geometry) and the writer once (dataset).
    let cameras = naming("host/src", "pub struct Camera {");
    assert_eq!(cameras, ["host/src/geometry/camera.rs"], "{cameras:?}");
    let writers = naming("host/src", "pub struct DatasetWriter");
    assert_eq!(writers, ["host/src/dataset/writer.rs"], "{writers:?}");
}

#[test]
fn one_image_codec_one_obj_writer_one_projection() {
    // EXR is encoded and decoded in one place (dataset::image, the `exr` crate), camera files
    // (TIFF, PNG, DNG) in one place (dataset::camera_file), OBJ text is written in one place
    // (dataset::obj_bytes), lens distortion is applied in one place (geometry::Camera).
    for (needle, owner) in [
        ("exr::", "host/src/dataset/image.rs"),
        ("tiff::", "host/src/dataset/camera_file.rs"),
        ("png::", "host/src/dataset/camera_file.rs"),
        ("ImageFormat::OpenExr", ""),
        ("pub struct LinearImage", ""),
        ("\"v {", "host/src/dataset/mesh.rs"),
        ("fn distort", "host/src/geometry/camera.rs"),
    ] {
        let users = naming("host/src", needle);
        let want: Vec<&str> = [owner].into_iter().filter(|o| !o.is_empty()).collect();
        assert_eq!(users, want, "{needle}");
    }
}

#[test]
fn one_vertex_model_type_set_and_one_tangent_frame_rule() {
    // The per-vertex model is the model file's type set (`modelfile`): the renderer, the plots
    // and evaluation take `ModelFile`; no second vertex-model, status or colour-mode type.
    for needle in [
        "pub struct VertexModel",
        "pub enum VertexStatus",
        "pub enum ColourMode",
        "pub struct ModelFile",
    ] {
        let owners = naming("host/src", needle);
        assert_eq!(owners, ["host/src/modelfile.rs"], "{needle}: {owners:?}");
    }
    assert!(naming("host/model/src", "pub struct VertexModel").is_empty());
    // Eq. 3's directions come from one frame function (`TangentFrame::with_rule`, the model
    // crate): nobody else builds a frame from its parts or has a reference-axis rule.
    for dir in ["host/src", "tests"] {
        let builders: Vec<String> = sources(dir)
            .into_iter()
            .filter(|(_, text)| {
                text.lines()
                    .map(str::trim_start)
                    .filter(|l| !l.starts_with("//"))
                    .any(|l| l.contains("TangentFrame {") && !l.contains("-> TangentFrame {"))
            })
            .map(|(path, _)| path)
            .collect();
        assert!(
            builders.is_empty(),
            "frames built outside the model crate: {builders:?}"
        );
    }
    let rules = naming("host", "abs() > 0.9 {");
    assert_eq!(rules, ["host/model/src/model/aniso.rs"], "{rules:?}");
}

/// The guide's wiring table is what a person wires a bench from: it must name the pins the
/// board's pin map uses, and must not call an input the scans require optional (a table that
/// once called the exposure-active output "optional" left benches whose every capture the scan
/// refused as unconfirmed).
#[test]
fn the_guide_s_wiring_table_matches_the_board_s_pin_map() {
    let readme = std::fs::read_to_string(root().join("docs/guide/rig.md")).expect("rig.md");
    let pins =
        std::fs::read_to_string(root().join("firmware/src/bin/board/pins.rs")).expect("pins.rs");
    let table = readme
        .split("| Function | Nucleo pin (MCU) | Connect to |")
        .nth(1)
        .expect("the guide's wiring table")
        .split("\n\n")
        .next()
        .unwrap_or_default();
    assert!(
        !table.to_ascii_lowercase().contains("optional"),
        "the wiring table calls something optional:\n{table}"
    );
    // Every MCU pin of the pin map's table (`| PA0 ...`, `| PC6 ...`) appears in the guide's.
    for line in pins.lines().filter(|l| l.starts_with("//! |")) {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        let Some(mcu) = cells.get(2) else { continue };
        for pin in mcu.split('/') {
            let pin = pin.trim();
            if pin.len() >= 3
                && pin.starts_with('P')
                && pin[1..2].chars().all(|c| c.is_ascii_uppercase())
                && pin != "PA2"
                && pin != "PA3"
            {
                assert!(
                    table.contains(pin),
                    "{pin} of pins.rs is missing from the guide's wiring table"
                );
            }
        }
    }
    assert!(table.contains("TIM3_CH2"), "the trigger's timer");
}

/// The files directly in `dir` (relative to the workspace root): their stems and line counts.
fn files_in(dir: &str) -> Vec<(String, usize)> {
    let mut out: Vec<(String, usize)> = std::fs::read_dir(root().join(dir))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "rs"))
        .map(|p| {
            let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
            let lines = std::fs::read_to_string(&p).unwrap().lines().count();
            (stem, lines)
        })
        .collect();
    out.sort();
    out
}

/// A pipeline stage and a library module never share a name: "the interpolation" is one
/// file, found where a newcomer looks. The stages (`host/src/pipeline/*.rs`) are named for what
/// the stage does to the run (fill, detail, select); the algorithms they call keep theirs
/// (`interpolate`, `lattice`, `spot`).
#[test]
fn a_stage_and_a_library_module_never_share_a_name() {
    let top: Vec<String> = std::fs::read_dir(root().join("host/src"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_dir() || p.extension().is_some_and(|x| x == "rs"))
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    let twice: Vec<String> = files_in("host/src/pipeline")
        .into_iter()
        .map(|(stem, _)| stem)
        .filter(|stem| stem != "mod" && top.contains(stem))
        .collect();
    assert!(
        twice.is_empty(),
        "named in host/src and host/src/pipeline: {twice:?}"
    );
}

/// A stage's file stays readable (at most 800 lines) and the binary stays thin: `cmd/` parses
/// arguments and calls the library, under 3,500 lines in all.
#[test]
fn pipeline_files_stay_short_and_the_commands_thin() {
    let long: Vec<(String, usize)> = files_in("host/src/pipeline")
        .into_iter()
        .filter(|(_, n)| *n > 800)
        .collect();
    assert!(long.is_empty(), "pipeline files over 800 lines: {long:?}");
    let cmd: usize = files_in("host/src/cmd").iter().map(|(_, n)| n).sum();
    assert!(cmd < 3500, "host/src/cmd/ has {cmd} lines");
}
