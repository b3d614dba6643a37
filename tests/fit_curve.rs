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

/// NIST's certified b1..b6 of Lanczos1, 2 and 3 and the digits a fitter of them must reach.
const NIST: [(&str, [f64; 6], f64); 3] = [
    (
        "lanczos1.csv",
        [
            9.5100000027E-02,
            1.0000000001E+00,
            8.6070000013E-01,
            3.0000000002E+00,
            1.5575999998E+00,
            5.0000000001E+00,
        ],
        9.0,
    ),
    (
        "lanczos2.csv",
        [
            9.6251029939E-02,
            1.0057332849E+00,
            8.6424689056E-01,
            3.0078283915E+00,
            1.5529016879E+00,
            5.0028798100E+00,
        ],
        9.0,
    ),
    (
        "lanczos3.csv",
        [
            8.6816414977E-02,
            9.5498101505E-01,
            8.4400777463E-01,
            2.9515951832E+00,
            1.5825685901E+00,
            4.9863565084E+00,
        ],
        8.0,
    ),
];

#[test]
fn nist_lanczos_family_linear_objective_from_both_start_vectors() {
    for (name, certified, need) in NIST {
        let file = data(name);
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
            let d = digits(&nist_params(&v), &certified);
            assert!(d >= need, "{name} from {start}: {d} digits: {v}");
        }
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

/// Curves are fitted as the file streams in (a block at a time); a file larger than a block
/// whose ids alternate row by row is read again whole: its output is that of the same rows
/// sorted by id, curve for curve.
#[test]
fn interleaved_ids_in_a_large_file_fit_like_sorted_ones() {
    let dir = tempfile::tempdir().unwrap();
    let (mut apart, mut sorted) = (String::from("id,r,value\n"), String::from("id,r,value\n"));
    let mut rows: [Vec<String>; 2] = [Vec::new(), Vec::new()];
    for k in 0..40_000 {
        let r = 5.0 * k as f64 / 40_000.0;
        for (id, rows) in rows.iter_mut().enumerate() {
            let v = (1.0 + id as f64) * (-r).exp() + 3.0 * (-4.0 * r).exp();
            let row = format!("{id},{r:.10e},{v:.10e}\n");
            apart += &row;
            rows.push(row);
        }
    }
    for r in &rows {
        sorted += &r.concat();
    }
    assert!(apart.len() > 2 << 20, "larger than the reader's block");
    let run = |name: &str, text: &str| {
        let p = write(&dir, name, text);
        let (ok, out, err) = fit_curve(&[p.to_str().unwrap(), "--batch", "--terms", "2", "--json"]);
        assert!(ok, "{err}");
        out
    };
    let (a, s) = (run("apart.csv", &apart), run("sorted.csv", &sorted));
    assert_eq!(a.lines().count(), 2);
    assert_eq!(a, s);
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
    // A sum of two exponentials is no dipole: the fit says so in log E instead of failing.
    assert!(v["log_e"].as_f64().unwrap() > 0.01, "{v}");
}

/// Jensen's ketchup, every channel (the low-albedo material that once fell into the
/// sigma_a -> 0 minimum), through the binary with a free scale and with --absolute.
#[test]
fn dipole_recovers_jensen_ketchup_through_the_binary() {
    use subsurf::model::Material;
    let m = Material::by_name("ketchup").unwrap();
    let dir = tempfile::tempdir().unwrap();
    for (absolute, k) in [(false, 0.25), (true, 1.0)] {
        let mut text = String::from("r,r_value,g_value,b_value\n");
        for i in 0..140 {
            let r = 0.05 * 1.04f64.powi(i);
            let v: Vec<String> = (0..3)
                .map(|ch| format!("{:e}", k * m.dipole(ch).unwrap().r_d(r)))
                .collect();
            text += &format!("{r:e},{}\n", v.join(","));
        }
        let p = write(&dir, "ketchup.csv", &text);
        let mut args = vec![p.to_str().unwrap(), "--model", "dipole", "--json"];
        if absolute {
            args.push("--absolute");
        }
        let (ok, out, err) = fit_curve(&args);
        assert!(ok, "{err}");
        let v: Value = serde_json::from_str(out.trim()).unwrap();
        for (ch, c) in v["channels"].as_array().unwrap().iter().enumerate() {
            let truth = m.dipole(ch).unwrap();
            let rel = |key: &str, want: f64| (c[key].as_f64().unwrap() / want - 1.0).abs();
            assert!(rel("sigma_s_prime", truth.sigma_s_prime) < 1e-4, "{c}");
            assert!(rel("sigma_a", truth.sigma_a) < 1e-4, "{c}");
            assert!(rel("scale", k) < 1e-3, "{c}");
            assert_eq!(c["converged"], true);
        }
    }
}

/// `--bins auto` (the default) fits large curves on 64 bins' statistics: log E measured on every
/// sample is the exact fit's (`--bins exact`) to 1e-4; a bad `--bins` is refused clearly.
#[test]
fn default_bins_match_the_exact_fit() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("id,r,value\n");
    let mut seed = 5u64;
    let mut uniform = || {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut samples: Vec<Vec<(f64, f64)>> = Vec::new();
    for (id, terms) in [
        [(0.3, 0.4), (2.0, 1.5), (40.0, 6.0)],
        [(1.0, 0.25), (5.0, 1.0), (9.0, 3.0)],
    ]
    .iter()
    .enumerate()
    {
        let mut curve = Vec::new();
        for _ in 0..1500 {
            let r = 10.0 / terms[0].1 * uniform().powi(2);
            let v: f64 = terms.iter().map(|(c, l)| c * (-l * r).exp()).sum();
            let noise = 0.02 * (uniform() - 0.5);
            let v = v * noise.exp();
            text += &format!("{id},{r:.10e},{v:.10e}\n");
            curve.push((r, v));
        }
        samples.push(curve);
    }
    let p = write(&dir, "big.csv", &text);
    let log_e = |v: &Value, curve: &[(f64, f64)]| -> f64 {
        let terms: Vec<(f64, f64)> = v["terms"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| (t["c"].as_f64().unwrap(), t["d"].as_f64().unwrap()))
            .collect();
        let sq: f64 = curve
            .iter()
            .map(|(r, s)| {
                let rd: f64 = terms.iter().map(|(c, d)| c * (d * r).exp()).sum();
                (rd.ln() - s.ln()).powi(2)
            })
            .sum();
        (sq / curve.len() as f64).sqrt()
    };
    let run = |extra: &[&str]| -> Vec<Value> {
        let mut args = vec![p.to_str().unwrap(), "--batch", "--json"];
        args.extend_from_slice(extra);
        let (ok, out, err) = fit_curve(&args);
        assert!(ok, "{err}");
        out.lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let (auto, exact) = (run(&[]), run(&["--bins", "exact"]));
    for (k, curve) in samples.iter().enumerate() {
        assert_eq!(auto[k]["converged"], true, "{}", auto[k]);
        let (a, e) = (log_e(&auto[k], curve), log_e(&exact[k], curve));
        assert!(a <= e * (1.0 + 1e-4), "curve {k}: auto {a} exact {e}");
        // The exact fit reports log E on the samples; the binned one its estimate.
        assert!((exact[k]["log_e"].as_f64().unwrap() / e - 1.0).abs() < 1e-9);
        assert!((auto[k]["log_e"].as_f64().unwrap() / a - 1.0).abs() < 0.01);
    }
    let (ok, _, err) = fit_curve(&[p.to_str().unwrap(), "--batch", "--bins", "lots"]);
    assert!(!ok && err.contains("--bins"), "{err}");
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

/// Two samples determine one term; the order falls to it and the output says so. One
/// sample determines nothing: reported, not fatal.
#[test]
fn few_samples_fit_the_order_they_determine() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(&dir, "few.csv", "r,value\n0,1\n1,0.5\n");
    let (ok, out, err) = fit_curve(&[p.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["converged"], true, "{v}");
    assert_eq!(v["reduced_from"], 3, "{v}");
    let terms = v["terms"].as_array().unwrap();
    assert_eq!(terms.len(), 1);
    assert!((terms[0]["c"].as_f64().unwrap() - 1.0).abs() < 1e-9, "{v}");
    assert!(
        (terms[0]["d"].as_f64().unwrap() - 0.5f64.ln()).abs() < 1e-9,
        "{v}"
    );
    let (ok, out, err) = fit_curve(&[p.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(out.contains("order reduced from 3 to 1"), "{out}");
    let p = write(&dir, "one.csv", "r,value\n0,1\n");
    let (ok, out, err) = fit_curve(&[p.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["converged"], false);
    assert!(v["error"].as_str().unwrap().contains("too few"), "{v}");
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
