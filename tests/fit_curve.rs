//! End-to-end tests of `subsurf fit-curve` through the binary.

use std::path::PathBuf;
use std::process::Command;

use serde_json::Value;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(name)
}

fn fit_curve(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .arg("fit-curve")
        .args(args)
        .output()
        .expect("run subsurf");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Smallest number of correct significant digits over all parameters.
fn digits(got: &[f64], want: &[f64]) -> f64 {
    got.iter()
        .zip(want)
        .map(|(g, w)| -((g - w).abs() / w.abs()).max(1e-17).log10())
        .fold(f64::INFINITY, f64::min)
}

fn nist_params(v: &Value) -> Vec<f64> {
    v["terms"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| [t["c"].as_f64().unwrap(), -t["d"].as_f64().unwrap()])
        .collect()
}

const CERTIFIED: [f64; 6] = [
    9.5100000027E-02,
    1.0000000001E+00,
    8.6070000013E-01,
    3.0000000002E+00,
    1.5575999998E+00,
    5.0000000001E+00,
];

#[test]
fn nist_lanczos1_linear_objective_from_both_start_vectors() {
    let file = data("lanczos1.csv");
    for start in ["1.2,0.3,5.6,5.5,6.5,7.6", "0.5,0.7,3.6,4.2,4,6.3"] {
        let (ok, out, err) = fit_curve(&[
            file.to_str().unwrap(),
            "--objective",
            "linear",
            "--terms",
            "3",
            "--start",
            start,
            "--json",
        ]);
        assert!(ok, "{err}");
        let v: Value = serde_json::from_str(out.trim()).unwrap();
        assert_eq!(v["model"], "expsum");
        assert_eq!(v["converged"], true);
        let d = digits(&nist_params(&v), &CERTIFIED);
        assert!(d >= 9.0, "start {start}: {d} digits: {v}");
        assert!(v["rss"].as_f64().unwrap() < 1.5e-25);
    }
}

#[test]
fn nist_lanczos1_log_objective_recovers_generating_values() {
    let (ok, out, err) = fit_curve(&[
        data("lanczos1.csv").to_str().unwrap(),
        "--objective",
        "log",
        "--terms",
        "3",
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    let d = digits(&nist_params(&v), &[0.0951, 1.0, 0.8607, 3.0, 1.5576, 5.0]);
    assert!(d >= 9.0, "{d} digits: {v}");
    // Terms sorted by rate, d < 0.
    let ds: Vec<f64> = v["terms"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["d"].as_f64().unwrap())
        .collect();
    assert!(ds.windows(2).all(|w| w[0] > w[1]) && ds.iter().all(|d| *d < 0.0));
}

fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
    let p = dir.path().join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn curve_csv(batch: bool, rgb: bool) -> String {
    let mut s = String::from("# synthetic\n");
    s += match (batch, rgb) {
        (false, false) => "r,value\n",
        (false, true) => "r,r_value,g_value,b_value\n",
        (true, false) => "id,r,value\n",
        (true, true) => "id,r,r_value,g_value,b_value\n",
    };
    let ids: &[&str] = if batch { &["a", "b", "c"] } else { &[""] };
    for (k, id) in ids.iter().enumerate() {
        for i in 0..120 {
            let r = i as f64 * 0.1;
            let v = 0.2 * (-0.4 * r).exp() + (2.0 + k as f64) * (-2.0 * r).exp();
            if batch {
                s += &format!("{id},");
            }
            if rgb {
                s += &format!("{r},{v},{},{}\n", 0.5 * v, 0.25 * v);
            } else {
                s += &format!("{r},{v}\n");
            }
        }
    }
    s
}

#[test]
fn batch_fits_every_id_and_rgb_gives_channels() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "b.csv", &curve_csv(true, true));
    let (ok, out, err) = fit_curve(&[p.to_str().unwrap(), "--batch", "--terms", "2", "--json"]);
    assert!(ok, "{err}");
    let lines: Vec<Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    for (k, v) in lines.iter().enumerate() {
        assert_eq!(v["id"], ["a", "b", "c"][k]);
        let ch = v["channels"].as_array().unwrap();
        assert_eq!(ch.len(), 3);
        let c_fast = |c: &Value| c["terms"][1]["c"].as_f64().unwrap();
        assert!((c_fast(&ch[0]) - (2.0 + k as f64)).abs() < 1e-6);
        assert!((c_fast(&ch[1]) / c_fast(&ch[0]) - 0.5).abs() < 1e-6);
        assert_eq!(ch[2]["channel"], "b");
    }
}

#[test]
fn auto_terms_and_dipole_json() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "c.csv", &curve_csv(false, false));
    let (ok, out, err) = fit_curve(&[p.to_str().unwrap(), "--terms", "auto", "--json"]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["order"]["chosen"], 2, "{v}");
    let (ok, out, err) = fit_curve(&[
        p.to_str().unwrap(),
        "--model",
        "dipole",
        "--eta",
        "1.4",
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["model"], "dipole");
    assert_eq!(v["eta"], 1.4);
    assert!(v["sigma_s_prime"].as_f64().unwrap() > 0.0 && v["sigma_a"].as_f64().unwrap() > 0.0);
}

#[test]
fn bad_files_name_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "bad.csv", "# x\nr,value\n0,1\n1,two\n");
    let (ok, _, err) = fit_curve(&[p.to_str().unwrap()]);
    assert!(!ok);
    assert!(err.contains("line 4"), "{err}");
    let p = write(&dir, "bad2.csv", "r,value\n0,1,2\n");
    let (ok, _, err) = fit_curve(&[p.to_str().unwrap()]);
    assert!(!ok && err.contains("line 2"), "{err}");
    let (ok, _, err) = fit_curve(&["/nonexistent/file.csv"]);
    assert!(!ok && err.contains("file.csv"), "{err}");
}

#[test]
fn too_few_samples_is_reported_not_fatal() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "few.csv", "r,value\n0,1\n1,0.5\n");
    let (ok, out, err) = fit_curve(&[p.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["converged"], false);
    assert!(v["error"].as_str().unwrap().contains("too few"));
}

#[test]
fn plot_is_a_non_blank_png() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "p.csv", &curve_csv(false, true));
    let png = dir.path().join("fig3.png");
    let (ok, _, err) = fit_curve(&[
        p.to_str().unwrap(),
        "--terms",
        "2",
        "--plot",
        png.to_str().unwrap(),
        "--plot-dipole",
    ]);
    assert!(ok, "{err}");
    let img = image::open(&png).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (900, 600));
    let non_white = img.pixels().filter(|p| p.0 != [255, 255, 255]).count();
    assert!(non_white > 5_000, "{non_white}");
    // Colour: the three channels' fits are drawn in red, green and blue.
    assert!(
        img.pixels()
            .any(|p| p.0[0] > 150 && p.0[1] < 80 && p.0[2] < 80)
    );
    assert!(
        img.pixels()
            .any(|p| p.0[2] > 150 && p.0[0] < 80 && p.0[1] < 100)
    );
}
