//! Every picture the plot module draws is decoded and checked: right size, not blank.

use crate::render_common::{assert_picture, fails, ok, subsurf};
use subsurf::model::Material;
use subsurf::plot;
use subsurf::render;

#[test]
fn figure_3_falloff_with_both_fits() {
    let dir = tempfile::tempdir().unwrap();
    let d = Material::by_name("marble").unwrap().dipole(1).unwrap();
    let skin = Material::by_name("skin1").unwrap().dipole(1).unwrap();
    let r: Vec<f64> = (0..300).map(|i| 0.05 + i as f64 * 0.08).collect();
    // A layered sample (skin over marble) with a slight multiplicative ripple: a fall-off no
    // single homogeneous medium produces, the situation of the paper's Figure 3.
    let s: Vec<f64> = r
        .iter()
        .map(|&x| (3.0 * skin.r_d(x) + d.r_d(x)) * (1.0 + 0.01 * (1.3 * x).sin()))
        .collect();
    let png = dir.path().join("f.png");
    let fits = subsurf::evaluate::compare_falloff(&r, &s, 1.3);
    let sum = plot::falloff_figure(&png, "marble", &r, &s, &fits).unwrap();
    assert_eq!(sum.samples, 300);
    // Figure 3's point: the sum of exponentials follows the measured fall-off where the dipole
    // cannot (its log E at least twice the sum's).
    let (expsum, dipole) = (sum.expsum_log_e.unwrap(), sum.dipole_log_e.unwrap());
    assert!(
        expsum > 0.0 && 2.0 * expsum < dipole,
        "expsum {expsum}, dipole {dipole}"
    );
    assert_picture(&png, 800, 520);
    // Nothing positive to plot on a log axis: an error, not a panic or an empty file.
    assert!(
        plot::falloff_figure(
            &dir.path().join("g.png"),
            "x",
            &[1.0, 2.0],
            &[0.0, -1.0],
            &subsurf::evaluate::compare_falloff(&[1.0, 2.0], &[0.0, -1.0], 1.3)
        )
        .is_err()
    );
}

#[test]
fn error_maps_and_model_viewer() {
    let dir = tempfile::tempdir().unwrap();
    let mut iso = render::synthetic::marble_torus(40, 16);
    let mut aniso = iso.clone();
    for v in 0..iso.len() {
        let p = iso.positions[v];
        iso.vertices[v].log_e = (0.04 + 0.02 * (0.2 * p[0]).sin()) as f32;
        aniso.vertices[v].log_e = (0.02 + 0.01 * (0.2 * p[0]).sin()) as f32;
    }
    iso.vertices[3].log_e = f32::NAN;
    let png = dir.path().join("e.png");
    plot::error_maps(
        &png,
        &[
            ("isotropic".into(), &iso),
            ("anisotropic, m = 4".into(), &aniso),
        ],
        render::DEFAULT_VIEW,
        (300, 320),
    )
    .unwrap();
    // Two panels, each seen from the front and from behind.
    let (w, h) = plot::surface_picture_size(2, (300, 320), true);
    assert_picture(&png, w, h);
    let png = dir.path().join("m.png");
    iso.vertices[10].status = subsurf::modelfile::VertexStatus::Interpolated;
    plot::model_viewer(&png, &iso, render::DEFAULT_VIEW, (240, 300)).unwrap();
    let (w, h) = plot::surface_picture_size(4, (240, 300), true);
    assert_picture(&png, w, h);
}

#[test]
fn tradeoff_curve_plot() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("t.png");
    plot::tradeoff_curve(
        &png,
        "t",
        &[(0.5, 0.03), (1.0, 0.008), (2.0, 0.001), (4.0, 0.0)],
        30.0,
    )
    .unwrap();
    assert_picture(&png, 720, 480);
    assert!(plot::tradeoff_curve(&png, "t", &[], 1.0).is_err());
}

#[test]
fn plot_commands_write_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("s.csv");
    let mut text = String::from("# one lit point\nr,value\n");
    for i in 0..120 {
        let r = 0.1 + i as f64 * 0.1;
        text.push_str(&format!(
            "{r},{}\n",
            0.5 * (-1.2 * r).exp() + 0.01 * (-0.2 * r).exp()
        ));
    }
    std::fs::write(&csv, text).unwrap();
    let out = dir.path().join("f.png");
    ok(subsurf()
        .args(["plot", "falloff"])
        .arg(&csv)
        .arg("--out")
        .arg(&out));
    assert_picture(&out, 800, 520);
    let out = dir.path().join("m.png");
    ok(subsurf().args(["plot", "model", "--out"]).arg(&out));
    let (w, h) = plot::surface_picture_size(4, (360, 400), true);
    assert_picture(&out, w, h);
    // A bad CSV line is named.
    std::fs::write(&csv, "r,value\n1,2\nthree,4\n").unwrap();
    let err = fails(subsurf().args(["plot", "falloff"]).arg(&csv));
    assert!(err.contains("s.csv") && err.contains("line 3"), "{err}");
}
