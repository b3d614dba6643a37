//! `subsurf fit` draws its pictures beside the report: the per-vertex error map
//! log E(x_i) and the model picture with the vertex status; `--no-pictures` skips them.
use std::path::Path;
use std::process::Command;

use subsurf::simulate::{SimConfig, SimObject, simulate};

fn small_slab(dir: &Path) {
    let cfg = SimConfig::for_object(SimObject::Slab { size: 20.0, n: 20 }, 64, 1, 8);
    simulate(&cfg, dir, &()).expect("simulate");
}

fn fit(scan: &Path, out: &Path, extra: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .arg("fit")
        .arg("--scan")
        .arg(scan)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .expect("run subsurf fit");
    let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    stdout
}

/// Distinct colours among the pixels, and how many pixels are not white.
fn content(img: &image::RgbImage) -> (usize, usize) {
    let mut colours = std::collections::HashSet::new();
    let mut inked = 0;
    for p in img.pixels() {
        colours.insert(p.0);
        inked += usize::from(p.0 != [255, 255, 255]);
    }
    (colours.len(), inked)
}

#[test]
fn fit_writes_an_error_map_and_a_model_picture_beside_the_report() {
    let tmp = tempfile::tempdir().unwrap();
    let scan = tmp.path().join("scan");
    small_slab(&scan);
    let out = tmp.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    let stdout = fit(&scan, &out.join("model.ply"), &[]);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("fit-report.json")).unwrap())
            .unwrap();
    let listed: Vec<&str> = report["pictures"]
        .as_array()
        .expect("report lists the pictures")
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    assert_eq!(listed.len(), 2, "{report}");
    assert!(report["process_peak_rss_mib"].as_f64().unwrap() > 0.0);

    // Error map: one 420x420 panel under a 34-pixel title, seen from the front and from
    // behind.
    let error_png = out.join("fit-report-error-map.png");
    assert!(
        stdout.contains(&error_png.display().to_string()),
        "{stdout}"
    );
    let err = image::open(&error_png).expect("decode error map").to_rgb8();
    let (w, h) = subsurf::plot::surface_picture_size(1, (420, 420), true);
    assert_eq!(err.dimensions(), (w, h));
    let (colours, inked) = content(&err);
    assert!(colours > 50, "error map has {colours} colours");
    assert!(inked > (w * h / 10) as usize, "error map is nearly blank");

    // Model picture: four 360x400 panels (alpha, reflectance, reach, status).
    let model_png = out.join("fit-report-model.png");
    let model = image::open(&model_png).expect("decode model").to_rgb8();
    let (w, h) = subsurf::plot::surface_picture_size(4, (360, 400), true);
    assert_eq!(model.dimensions(), (w, h));
    let (colours, inked) = content(&model);
    assert!(colours > 50, "model picture has {colours} colours");
    assert!(
        inked > (w * h / 10) as usize,
        "model picture is nearly blank"
    );
    // Every view shows the slab in colour, not only in the grey of missing values: the panel's
    // centre pixel is coloured (alpha, and viridis for the scalar panels), in the front view
    // and in the view from behind below it (views of 400 − 30 − 82 pixels: title, legend).
    let view_h = 400 - 30 - 82;
    for k in 0..4 {
        for row in 0..2 {
            let centre = model
                .get_pixel(k * 360 + 180, 34 + 30 + row * view_h + view_h / 2)
                .0;
            let grey = centre[0] == centre[1] && centre[1] == centre[2];
            assert!(
                !grey || k == 0,
                "panel {k} view {row} is grey at its centre: {centre:?}"
            );
        }
    }

    // --no-pictures: the model and the reports only, no PNG (in a directory `fit` creates); the
    // report's Markdown and HTML faces carry no pictures then.
    let quiet = tmp.path().join("quiet");
    fit(&scan, &quiet.join("model.ply"), &["--no-pictures"]);
    let mut names: Vec<String> = std::fs::read_dir(&quiet)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "fit-report.html",
            "fit-report.json",
            "fit-report.md",
            "model.ply"
        ]
    );
    let html = std::fs::read_to_string(quiet.join("fit-report.html")).unwrap();
    assert!(
        !html.contains("data:image/png"),
        "no pictures were asked for"
    );
}
