//! `subsurf demo` at a reduced size: it leaves a report, rendered PNGs, a fall-off plot and an
//! error map, every one a real picture.

use std::process::Command;

use subsurf::render::image_stats;

#[test]
fn demo_leaves_report_renders_falloff_plot_and_error_map() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args([
            "demo",
            "--size",
            "48",
            "--angles",
            "3",
            "--raster",
            "8",
            "--picture",
            "96",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("demo results in"), "{stdout}");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("## Scan") && report.contains("## Fit"),
        "{report}"
    );
    for (name, w, h) in [
        ("render-key-light.png", 96, 96),
        ("render-back-light.png", 96, 96),
        ("falloff.png", 800, 520),
        ("error-map.png", 720, 414),
        ("model.png", 1200, 374),
    ] {
        let s = image_stats(&out.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!((s.width, s.height), (w, h), "{name}");
        assert!(
            s.distinct_colours > 20 && s.luma_std > 5.0,
            "{name} looks blank: {s:?}"
        );
    }
    assert!(out.join("model.ply").exists() && out.join("fit-report.json").exists());
}
