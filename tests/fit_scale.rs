//! `subsurf bench fit-scale` works end to end on a tiny grid (the figures themselves come from a
//! release build into BENCHMARKS.md; nothing here is timed): rows for every pair, datasets deleted
//! after their fit, the JSON and the plot written.
use std::process::Command;

#[test]
fn fit_scale_tabulates_every_pair_and_deletes_its_datasets() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scratch");
    let json = tmp.path().join("rows.json");
    let png = tmp.path().join("scale.png");
    let out = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args([
            "bench",
            "fit-scale",
            "--vertices",
            "300,600",
            "--frames",
            "9,18",
        ])
        .args(["--size", "48", "--raster", "3", "--dir"])
        .arg(&dir)
        .arg("--json")
        .arg(&json)
        .arg("--plot")
        .arg(&png)
        .output()
        .expect("run subsurf bench fit-scale");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let pairs: Vec<(u64, u64)> = rows
        .iter()
        .map(|r| {
            (
                r["vertices"].as_u64().unwrap(),
                r["frames"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(pairs.len(), 4, "{pairs:?}");
    assert_eq!(
        pairs.iter().map(|p| p.1).collect::<Vec<_>>(),
        [9, 18, 9, 18]
    );
    assert!(pairs[2].0 > pairs[0].0, "{pairs:?}");
    for r in &rows {
        assert!(r["peak_rss_mib"].as_f64().unwrap() > 1.0, "{r}");
        assert!(r["wall_s"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["registered"].as_u64().unwrap() > 0, "{r}");
        for stage in ["registration", "fit", "error", "interpolate"] {
            assert!(r["stages"][stage].as_f64().is_some(), "{stage} in {r}");
        }
    }
    // Every run's progress line and the children's output reach a non-terminal stdout.
    assert!(stdout.contains("[4/4] "), "{stdout}");
    assert!(stdout.contains("fit wall"), "{stdout}");
    // The growth summary compares the frame doublings.
    assert!(stdout.contains("frames 9 -> 18 at"), "{stdout}");
    // No dataset is left behind.
    let left: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("scan-") || n.ends_with(".ply"))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    let img = image::open(&png).expect("decode plot").to_rgb8();
    assert_eq!(img.dimensions(), (1200, 480));
}

/// `subsurf bench one-pass` end to end on a tiny simulated scan: the fit decodes each frame once
/// (its reads in the JSON), the ratio is written; `--no-pictures` in `--fit-args` is accepted (the
/// bench gives it too), and what the bench must own (`--cache`) is refused before any work.
#[test]
fn one_pass_bench_reports_the_ratio_and_guards_its_own_fit_arguments() {
    let tmp = tempfile::tempdir().unwrap();
    let scan = tmp.path().join("scan");
    let sim = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args([
            "simulate",
            "--object",
            "slab",
            "--vertices",
            "81",
            "--size",
            "48",
        ])
        .args(["--angles", "1", "--raster", "3", "--out"])
        .arg(&scan)
        .output()
        .expect("run subsurf simulate");
    assert!(
        sim.status.success(),
        "{}",
        String::from_utf8_lossy(&sim.stderr)
    );
    let json = tmp.path().join("op.json");
    let run = |fit_args: &str| {
        Command::new(env!("CARGO_BIN_EXE_subsurf"))
            .args(["bench", "one-pass", "--scan"])
            .arg(&scan)
            .arg("--dir")
            .arg(tmp.path().join("out"))
            .arg("--json")
            .arg(&json)
            .arg(format!("--fit-args={fit_args}"))
            .output()
            .expect("run subsurf bench one-pass")
    };
    let out = run("--no-pictures,--cv-folds,0");
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let fig: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let frames = fig["frames"].as_u64().unwrap();
    assert_eq!(frames, 9, "{fig}");
    assert_eq!(fig["frame_reads"]["total"].as_u64(), Some(frames), "{fig}");
    assert_eq!(fig["frame_reads"]["most"].as_u64(), Some(1), "{fig}");
    assert!(fig["ratio"].as_f64().unwrap() > 0.0, "{fig}");
    std::fs::remove_file(&json).unwrap();
    let refused = run("--cache,dataset");
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("--fit-args may not set --cache"), "{err}");
    assert!(!json.exists(), "nothing measured for a refused run");
}
