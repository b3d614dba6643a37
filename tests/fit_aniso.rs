//! Anisotropic per-vertex fits (Eq. 3) on a simulated anisotropic slab: the model with
//! direction segments predicts held-out frames better than the isotropic one (Eq. 9), and the
//! direction of slowest fall-off and the along/across ratio it recovers match the simulated
//! material's vein axis and anisotropy.
use std::f64::consts::{PI, TAU};

use subsurf::dataset::{Dataset, select_frames};
use subsurf::evaluate::evaluate_frames;
use subsurf::fit::{FitOptions, Terms};
use subsurf::geometry::add_scaled;
use subsurf::model::TangentFrame;
use subsurf::modelfile::{ModelFile, VertexStatus, model_of};
use subsurf::pipeline::{PipelineOptions, fit_dataset};
use subsurf::simulate::{SimConfig, SimObject, TrueParams, simulate};

const SEGMENTS: usize = 8;
/// The distance range (mm) over which a direction's decay length is measured.
const R1: f64 = 2.0;
const R2: f64 = 5.0;

/// Decay length in one direction: 1 / (mean fall-off rate of ln R_d between `R1` and `R2`), a
/// range the samples cover well (the steepest terms are unresolved below the vertex spacing and
/// gone beyond a few mm).
fn reach(ln_r: impl Fn(f64) -> f64) -> f64 {
    (R2 - R1) / (ln_r(R1) - ln_r(R2))
}

/// Axis (angle mod π, from the doubled-angle mean of the reaches) and max/min reach ratio of
/// reaches sampled at the segment centres.
fn axis_and_ratio(reaches: &[f64]) -> (f64, f64) {
    let m = reaches.len();
    let (mut s, mut c) = (0.0, 0.0);
    for (l, r) in reaches.iter().enumerate() {
        let phi = TAU * l as f64 / m as f64;
        s += r * (2.0 * phi).sin();
        c += r * (2.0 * phi).cos();
    }
    let axis = (0.5 * s.atan2(c)).rem_euclid(PI);
    let max = reaches.iter().copied().fold(0.0, f64::max);
    let min = reaches.iter().copied().fold(f64::INFINITY, f64::min);
    (axis, max / min)
}

fn angle_mod_pi(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(PI);
    d.min(PI - d)
}

#[test]
fn anisotropic_fit_beats_isotropic_and_recovers_the_axis() {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = SimConfig::for_object(SimObject::Slab { size: 20.0, n: 41 }, 96, 1, 10);
    cfg.field.anisotropy = 0.6;
    // A homogeneous material with long veins, so that neighbours share the anisotropy and the
    // held-out positions are predicted by interpolation of equal models.
    cfg.field.heterogeneity = 0.0;
    cfg.field.alpha_amplitude = 0.0;
    cfg.field.vein_wavelength = 400.0;
    // The vein pattern sets the local anisotropy strength (0..0.6): take the strongest seed.
    let vein_at_centre = |seed: u64| {
        let mut f = cfg.field.clone();
        f.seed = seed;
        f.vein([0.0; 3])
    };
    cfg.field.seed = (1..64u64)
        .max_by(|a, b| vein_at_centre(*a).total_cmp(&vein_at_centre(*b)))
        .unwrap();
    let strength = cfg.field.params_at([0.0; 3], [0.0, 0.0, 1.0]).anisotropy;
    assert!(strength > 0.5, "anisotropy strength {strength}");
    cfg.spot.radiance = 2000.0;
    simulate(&cfg, tmp.path(), &()).expect("simulate");
    let ds = Dataset::open(tmp.path()).unwrap();
    let n_frames = ds.spec.frames.len();
    // Every 5th laser position is held out of the fits.
    let held: Vec<usize> = (0..n_frames).filter(|k| k % 5 == 2).collect();
    let held_list = held
        .iter()
        .map(|k| k.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let train = select_frames(n_frames, None, Some(&held_list)).unwrap();
    let mut opts = PipelineOptions::for_dataset(&ds);
    opts.max_select_mm = 4.0;
    // (model, in-sample mean log E, held-out mean log E), red channel.
    let run = |segments: usize, terms: usize| -> (ModelFile, f64, f64) {
        let mut o = opts;
        o.model.segments = segments;
        // Eq. 3 itself at this m: every light position at the fixed order (the per-vertex choice
        // of n and m is `subsurf_model::order`'s, tested there and in `objects`).
        o.order = None;
        let fo = FitOptions {
            terms: Terms::Fixed(terms),
            ..FitOptions::default()
        };
        let out = fit_dataset(&ds, &train, &o, &fo, &()).expect("fit");
        assert_eq!(out.report.vertices_no_model, 0, "{:?}", out.report);
        assert_eq!(out.model.shape.segments, segments);
        let (_, st) = evaluate_frames(&ds, &out.model, &held, &o, &()).unwrap();
        let (fit, pred) = (out.report.log_e.mean[0].unwrap(), st.mean[0].unwrap());
        eprintln!("m = {segments}, n = {terms}: in-sample log E {fit:.4}, held-out {pred:.4}");
        (out.model, fit, pred)
    };

    // n = 3 (the default): the segments explain the data far better, in the fit and on held-out
    // frames, and their direction of slowest fall-off and its strength match the material's.
    // Measured 2026-11-25, with fits repeatable bit for bit: in-sample 0.353 vs 0.680, held-out
    // 0.337 vs 0.661 (0.52x); 2026-12-07, the slow terms held: 0.153 vs 0.672, 0.144 vs 0.658. The bound is 0.6x, not the 0.5x of earlier runs: those took
    // whatever order rayon summed the alpha accumulators in, and on this scene, which has no
    // texture, the 8 alpha rounds do not converge (the prior is 1.2-1.4 from the segments'
    // misfit, not from alpha), so their end point moved with rounding: 0.23 and 0.35 in-sample
    // were both seen at m = 8 before the fold was fixed. Without alpha rounds the segments alone
    // give 0.56 vs 0.74 here; the alpha rounds absorbing anisotropic misfit is a known limit.
    let (_, iso3_fit, iso3_pred) = run(1, 3);
    let (aniso3, aniso3_fit, aniso3_pred) = run(SEGMENTS, 3);
    assert!(
        aniso3_fit < 0.6 * iso3_fit,
        "in-sample log E: anisotropic {aniso3_fit}, isotropic {iso3_fit}"
    );
    assert!(
        aniso3_pred < 0.6 * iso3_pred,
        "held-out log E: anisotropic {aniso3_pred}, isotropic {iso3_pred}"
    );
    let (axis_deg, ratio, count) = axis_errors(&cfg, &aniso3);
    eprintln!(
        "{count} vertices: median axis error {axis_deg:.1} deg, median (ratio - 1) fitted / true {ratio:.2}"
    );
    assert!(count >= 100, "{count} fitted interior vertices");
    // 18°, not the 15° of earlier runs: since a third term that hardly decays is held at the
    // least decay instead of dropped, every light position here fits its three terms, not two
    // where the third ran flat. Held-out 0.144 against 0.205 (m = 8); on the 502 vertices both
    // fitted, the axis 15.7° from the truth's against 12.3° (617 vertices now, 15.2°): the third
    // term's segments spread the 2–5 mm reach the axis is read from.
    assert!(axis_deg < 18.0, "median axis error {axis_deg} degrees");
    assert!(
        (0.5..1.5).contains(&ratio),
        "median anisotropy (ratio - 1), fitted / true: {ratio}"
    );
}

/// Median over fitted interior vertices of the anisotropic model `aniso` of (axis error in
/// degrees, (fitted max/min decay-length ratio − 1) / (true − 1)), and how many vertices.
fn axis_errors(cfg: &SimConfig, aniso: &ModelFile) -> (f64, f64, usize) {
    let normal = [0.0, 0.0, 1.0];
    let frame = TangentFrame::from_normal(normal).unwrap();
    let m = aniso.shape.segments;
    let (mut axis_err, mut ratio_rel) = (Vec::new(), Vec::new());
    for (v, vm) in aniso.vertices.iter().enumerate() {
        let p = aniso.positions[v];
        if vm.status != VertexStatus::Fitted || p[0].abs() > 6.0 || p[1].abs() > 6.0 {
            continue;
        }
        let model = model_of(&aniso.shape, vm.terms as usize, &vm.params).unwrap();
        let fitted: Vec<f64> = (0..m)
            .map(|l| {
                let phi = TAU * l as f64 / m as f64;
                reach(|r| model.ln_eval(r, Some(phi))[0])
            })
            .collect();
        let truth: TrueParams = cfg.field.params_at(p, normal);
        let true_reach: Vec<f64> = (0..m)
            .map(|l| {
                let phi = TAU * l as f64 / m as f64;
                let dir = add_scaled(frame.t.map(|x| x * phi.cos()), phi.sin(), frame.b);
                reach(|r| truth.log_rd(p, add_scaled(p, r, dir), normal)[0])
            })
            .collect();
        let (a_fit, q_fit) = axis_and_ratio(&fitted);
        let (a_true, q_true) = axis_and_ratio(&true_reach);
        // The definition finds the material's vein axis in the truth itself.
        let (_, vein) = frame.polar(p, add_scaled(p, 1.0, truth.axis));
        let off = angle_mod_pi(a_true, vein.unwrap()).to_degrees();
        assert!(
            off < 5.0,
            "true decay lengths peak {off} degrees off the vein axis"
        );
        axis_err.push(angle_mod_pi(a_fit, a_true).to_degrees());
        ratio_rel.push((q_fit - 1.0) / (q_true - 1.0));
    }
    if axis_err.is_empty() {
        return (f64::NAN, f64::NAN, 0);
    }
    axis_err.sort_by(f64::total_cmp);
    ratio_rel.sort_by(f64::total_cmp);
    (
        axis_err[axis_err.len() / 2],
        ratio_rel[ratio_rel.len() / 2],
        axis_err.len(),
    )
}
