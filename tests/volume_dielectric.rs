//! The rough dielectric boundary against Mitsuba 3: its BSDF value by value
//! (`tests/outside/mitsuba_bsdf.py`, `roughdielectric`).

use crate::volume::{mitsuba, run_mitsuba};
use subsurf::volume::dielectric::{RoughDielectric, Transport};

/// The boundary of sample-pebble, as its README gives it: GGX width 0.2, index 1.55 inside.
const IOR: f64 = 1.55;
const ALPHA: f64 = 0.2;

fn dir(theta: f64, phi: f64) -> [f64; 3] {
    [
        theta.sin() * phi.cos(),
        theta.sin() * phi.sin(),
        theta.cos(),
    ]
}

/// Mitsuba 3's `roughdielectric` (GGX, α 0.2, int_ior 1.55, ext_ior 1) and subsurf's BSDF
/// give the same values, in both transport modes, and the same sampling density, for pairs
/// of directions on both sides: reflection outside and inside (with total internal
/// reflection), refraction in and out, near-normal and grazing, within 0.1 % (Mitsuba
/// computes in single precision).
#[test]
fn mitsuba_roughdielectric_values_agree_with_the_bsdf() {
    let Some(py) = mitsuba() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let mut pairs = Vec::new();
    let thetas = [0.05, 0.4, 0.75, 1.1, 1.45];
    for &ti in &thetas {
        for wi_up in [true, false] {
            let wi = dir(if wi_up { ti } else { std::f64::consts::PI - ti }, 0.3);
            for &to in &thetas {
                for (k, phi) in [0.3 + std::f64::consts::PI, 0.3, 2.0]
                    .into_iter()
                    .enumerate()
                {
                    for wo_up in [true, false] {
                        // Near the mirror and refraction directions as well as away from them.
                        let t = to * if k == 2 { 0.6 } else { 1.0 };
                        let wo = dir(if wo_up { t } else { std::f64::consts::PI - t }, phi);
                        pairs.push((wi, wo));
                    }
                }
            }
        }
    }
    let spec = serde_json::json!({
        "alpha": ALPHA, "int_ior": IOR, "ext_ior": 1.0,
        "pairs": pairs.iter().map(|(a, b)| [a.to_vec(), b.to_vec()]).collect::<Vec<_>>(),
    });
    let spec_path = tmp.path().join("pairs.json");
    std::fs::write(&spec_path, spec.to_string()).unwrap();
    let o = run_mitsuba(&py, "mitsuba_bsdf.py", &[&spec_path]);
    let out: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let values = out["values"].as_array().unwrap();
    assert_eq!(values.len(), pairs.len());
    let b = RoughDielectric {
        eta: IOR,
        alpha: ALPHA,
    };
    let (mut nonzero, mut worst) = ([0usize; 4], 0.0f64);
    for ((wi, wo), v) in pairs.iter().zip(values) {
        let ours = [
            b.eval(*wi, *wo, Transport::Radiance),
            b.eval(*wi, *wo, Transport::Importance),
            b.pdf(*wi, *wo),
        ];
        let theirs = ["radiance", "importance", "pdf"].map(|k| v[k].as_f64().unwrap());
        for (x, y) in ours.iter().zip(&theirs) {
            let scale = x.abs().max(y.abs());
            let rel = (x - y).abs() / scale.max(1e-300);
            assert!(
                rel < 1e-3 || scale < 1e-6,
                "wi {wi:?} wo {wo:?}: subsurf {ours:?} mitsuba {theirs:?}"
            );
            if scale >= 1e-6 {
                worst = worst.max(rel);
            }
        }
        if ours[0] > 1e-6 {
            let side = (wi[2] > 0.0) as usize * 2 + (wo[2] > 0.0) as usize;
            nonzero[side] += 1;
        }
    }
    eprintln!(
        "non-zero pairs by (wi up, wo up): {nonzero:?}; worst relative difference {worst:.2e}"
    );
    assert!(nonzero.iter().all(|&n| n >= 10), "{nonzero:?}");
}
