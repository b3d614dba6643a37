//! Resolving what a scan needs: the object (built-in or an OBJ file), the calibration, the rig's
//! timing, and the camera named on the command line.

use super::camera::{Camera, CmdCamera, DirCamera};
use super::plan::RigTiming;
use super::simcam::SimCamera;
use crate::calib::Calibration;
use crate::dataset::{Levels, Mesh};
use crate::simulate::{Field, Sensor, SimObject, Spot};
use std::path::Path;
use std::time::Duration;
use subsurf_protocol::RigProfile;

/// Radius of the built-in object, mm: a bead. Small, so that a vertex spacing and a pixel
/// footprint fine enough for the material (see [`builtin_object`]) stay a few thousand vertices
/// and a ~100² image, which keeps `scan --sim` + `fit` to seconds.
pub const BUILTIN_RADIUS_MM: f64 = 4.0;

/// Sampling of the built-in scan, against the material's shortest mean free path `1 / |d_max|`
/// (Eq. 1: the steepest exponential term falls by `e` over it). Samples `s(x_i, x_o)` exist only
/// at vertices, so the vertex spacing is at most one mean free path: a few vertices then lie in
/// the band (about 0.5–1.5 mean free paths beyond the exclusion radius) where that term
/// dominates, and its `c_k, d_k` are constrained by data instead of extrapolated.
pub const VERTEX_SPACING_PER_MEAN_FREE_PATH: f64 = 1.0;

/// Pixel footprint of the built-in scan against the shortest mean free path: a pixel spans at
/// most half of it, so the bilinear sample of the fall-off between pixel centres is off by at most
/// `ln cosh(|d| p / 2) < 0.03` where the steepest term dominates (the noise, elsewhere less), and
/// the laser spot's reflection (a Gaussian of 0.8 px) stays inside the exclusion radius.
pub const PIXEL_FOOTPRINT_PER_MEAN_FREE_PATH: f64 = 0.5;

/// Target spacing of the laser positions x_i of a fidelity scan of the built-in object, against
/// the shortest mean free path. A vertex takes the model of its closest x_i, and a frame the fit
/// never saw is predicted from the vertex models around its x_i, so the lights must sit closer
/// than the distance over which the fit at one x_i stops describing its neighbours. Measured with
/// `scan --sim` + `fit` (every fifth frame held out, host/tests/scan_fit.rs): a 2 mm plan (8.8
/// mean free paths, the coverage preview) gives held-out log E 0.026–0.043, 0.4 mm (1.8) gives
/// 0.009–0.012, within 1.5x of the ground truth's own floor.
pub const TARGET_SPACING_PER_MEAN_FREE_PATH: f64 = 1.75;

/// The coverage planner's target distance (mm) for a scan of the built-in object whose model is
/// to predict frames it did not see: [`TARGET_SPACING_PER_MEAN_FREE_PATH`] mean free paths of
/// the material the `sim` camera renders (0.40 mm for the default marble).
pub fn builtin_target_mm() -> f64 {
    TARGET_SPACING_PER_MEAN_FREE_PATH / sim_field().steepest_falloff()
}

/// Signal-to-noise ratio of one pixel at the simulated scan's noise floor: log E (Eq. 8)
/// compares logarithms, and a sample at SNR `k` carries about `1/k` of noise in its log, so
/// samples fainter than SNR 50 (2 %) would make the noise, not the model, the error.
pub const FLOOR_SNR: f64 = 50.0;

/// The built-in object of `subsurf scan --sim`: a sphere of radius [`BUILTIN_RADIUS_MM`] resting
/// on the platter, its vertex spacing (largest at the equator, `π r / rings`) at most
/// [`VERTEX_SPACING_PER_MEAN_FREE_PATH`] mean free paths of the material the `sim` camera renders.
pub fn builtin_object() -> SimObject {
    let spacing = VERTEX_SPACING_PER_MEAN_FREE_PATH / sim_field().steepest_falloff();
    SimObject::Sphere {
        radius: BUILTIN_RADIUS_MM,
        rings: (std::f64::consts::PI * BUILTIN_RADIUS_MM / spacing).ceil() as usize,
    }
}

/// Image size (pixels per side) of the built-in calibration: `Calibration::builtin_for` frames
/// the object's bounding diameter with 15 % margin, so the footprint at the object is
/// `2.3 r / size`; the size is the smallest multiple of 16 that makes it at most
/// [`PIXEL_FOOTPRINT_PER_MEAN_FREE_PATH`] mean free paths.
pub fn builtin_image_size() -> u32 {
    let (_, radius) = builtin_object().bounds();
    let footprint = PIXEL_FOOTPRINT_PER_MEAN_FREE_PATH / sim_field().steepest_falloff();
    let size = (2.3 * radius / footprint).ceil() as u32;
    size.div_ceil(16) * 16
}

/// The calibration of a scan of the built-in object when no `calib.json` is given:
/// [`Calibration::builtin_for`] framing [`builtin_object`], `size` pixels per side (default
/// [`builtin_image_size`]).
pub fn builtin_calibration(size: Option<u32>) -> Calibration {
    let (centre, radius) = builtin_object().bounds();
    Calibration::builtin_for(centre, radius, size.unwrap_or_else(builtin_image_size))
}

/// Exposure (s) of a scan of a user's object when none is given.
pub const DEFAULT_EXPOSURE_S: f64 = 0.05;

/// A scan's exposure bracket (s): `given` when not empty; else, for the built-in object, the
/// `sim` camera's bracket ([`sim_exposures_s`]); else [`DEFAULT_EXPOSURE_S`].
pub fn scan_exposures_s(given: &[f64], builtin: bool) -> Vec<f64> {
    if !given.is_empty() {
        given.to_vec()
    } else if builtin {
        sim_exposures_s()
    } else {
        vec![DEFAULT_EXPOSURE_S]
    }
}

/// Exposure bracket of a `--camera sim` scan (s), shortest first (merged per frame by
/// `dataset::merge_hdr`, section 5's HDR capture):
/// - the spot exposure keeps the laser spot's reflection unclipped (at half the clipping
///   level), so registration takes the exact log-Gaussian sub-pixel path; a clipped spot's
///   plateau and ring are skewed by the scattered light around it, most near the limb, which
///   misplaced x_i by ~0.1 mm (0.4 mean free paths);
/// - the scatter exposure is the longest at which the brightest scattered light the material can
///   produce ([`Field::peak_radiance`]) stays unclipped, so every sample is as far above the
///   noise as the sensor allows — but no longer than the simulated rig accepts.
pub fn sim_exposures_s() -> Vec<f64> {
    let sensor = sim_sensor();
    let rig_max = f64::from(subsurf_protocol::MAX_EXPOSURE_US) * 1e-6;
    let Some(sat) = sensor.saturation else {
        return vec![sensor.exposure_s.min(rig_max)];
    };
    let peak = sim_field().peak_radiance();
    let spot = (0.5 * sat / (sim_spot().radiance + peak)).min(rig_max);
    let scatter = (sat / peak).min(rig_max);
    // Whole microseconds: the rig takes exposures in µs.
    let us = |s: f64| (s * 1e6).floor().max(1.0) * 1e-6;
    vec![us(spot), us(scatter)]
}

/// The laser spot's first-surface reflection as the `sim` camera draws it (as `subsurf
/// simulate` does): far brighter than the scattered light.
pub fn sim_spot() -> Spot {
    Spot {
        radiance: 200.0,
        sigma_px: 0.8,
    }
}

/// `noise_floor` of a `--camera sim` scan (radiance) with the exposure bracket `exposures_s`:
/// where one pixel's SNR drops to [`FLOOR_SNR`] at the longest exposure.
pub fn sim_noise_floor(exposures_s: &[f64]) -> f64 {
    Sensor {
        exposure_s: exposures_s.iter().copied().fold(0.0, f64::max),
        ..sim_sensor()
    }
    .radiance_at_snr(FLOOR_SNR)
}

/// The rig's timing from its profile, for the move speed and acceleration and capture interval
/// the scan will use.
pub fn rig_timing(
    profile: &RigProfile,
    speed: Option<u32>,
    accel: Option<u32>,
    interval_us: u32,
) -> RigTiming {
    let (max_v, max_a) = (profile.motor.max_speed, profile.motor.max_accel);
    let v = speed.unwrap_or(max_v).min(max_v) as f64;
    let a = accel.unwrap_or(max_a).min(max_a) as f64;
    let h = &profile.homing;
    let (hv, ha, slow) = (h.speed as f64, h.accel as f64, h.slow_speed as f64);
    let spr = profile.steps_per_rev().unwrap_or(1);
    // Two-pass homing from anywhere (half a turn on average): the fast approach brakes past the
    // switch by its ramp, the release pass comes back through it and brakes again, then the
    // back-off and the slow approach over ramp + back-off at the slow speed.
    let half = spr as f64 / 2.0;
    let home_s = if hv > 0.0 && ha > 0.0 && slow > 0.0 {
        let ramp = hv * hv / (2.0 * ha);
        let backoff = h.backoff_steps as f64;
        super::plan::trapezoid_s(half as u64, hv, ha)
            + super::plan::trapezoid_s((2.0 * ramp) as u64, hv, ha)
            + backoff / slow
            + (ramp + backoff) / slow
    } else {
        0.0
    };
    RigTiming {
        steps_per_rev: spr,
        max_speed_sps: v,
        accel_sps2: a,
        home_s,
        settle_base_s: profile.galvo.settle_min_us as f64 * 1e-6,
        settle_per_code_s: profile.galvo.settle_per_kcode_us as f64 * 1e-9,
        // The laser window's margins around each exposure.
        capture_overhead_s: f64::from(profile.laser.lead_us + profile.laser.tail_us) * 1e-6,
        interval_s: interval_us as f64 * 1e-6,
        readout_s: f64::from(profile.camera.readout_us) * 1e-6,
    }
}

/// Why a camera could not be set up.
pub fn camera_from_spec(
    spec: &str,
    mesh: &Mesh,
    calib: &Calibration,
    seed: u64,
    timeout: Duration,
) -> Result<Box<dyn Camera>, super::camera::CameraError> {
    camera_from_spec_with(spec, mesh, calib, seed, timeout, Levels::default())
}

/// [`camera_from_spec`] with the black and white level of a `dir:` or `cmd:` camera's TIFF or
/// PNG files (`subsurf scan --black-level --white-level`; raw files carry their own).
pub fn camera_from_spec_with(
    spec: &str,
    mesh: &Mesh,
    calib: &Calibration,
    seed: u64,
    timeout: Duration,
    levels: Levels,
) -> Result<Box<dyn Camera>, super::camera::CameraError> {
    levels.check().map_err(super::camera::CameraError::Spec)?;
    if spec == "sim" || spec.starts_with("sim:") || spec.starts_with("sim+") {
        // `+dark=V`: the simulated sensor reads V raw units of offset on every pixel (a camera
        // whose black level is not removed), which the scan's dark frames measure and subtract.
        let (spec, dark_offset) = match spec.split_once("+dark=") {
            Some((s, v)) => (
                s,
                v.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v >= 0.0)
                    .ok_or_else(|| {
                        super::camera::CameraError::Spec(format!(
                            "+dark= takes a raw offset >= 0, got {v:?}"
                        ))
                    })?,
            ),
            None => (spec, 0.0),
        };
        let field = sim_material(spec).ok_or_else(|| {
            super::camera::CameraError::Spec(format!(
                "unknown simulated material in {spec:?}: use sim, sim:marble, sim:veined or \
                 sim:homogeneous (then +dark=OFFSET for a sensor offset)"
            ))
        })?;
        let sensor = Sensor {
            dark_offset,
            ..sim_sensor()
        };
        return Ok(Box::new(
            SimCamera::new(mesh.clone(), calib, field, sensor, seed)?.with_spot(sim_spot()),
        ));
    }
    if let Some(dir) = spec.strip_prefix("dir:") {
        return Ok(Box::new(
            DirCamera::new(Path::new(dir), timeout)?.with_levels(levels),
        ));
    }
    if let Some(cmd) = spec.strip_prefix("cmd:") {
        return Ok(Box::new(CmdCamera::new(cmd, timeout)?.with_levels(levels)));
    }
    Err(super::camera::CameraError::Spec(format!(
        "unknown camera {spec:?}: use sim, dir:PATH or cmd:\"COMMAND {{out}}\""
    )))
}

/// The simulated camera's sensor: the simulator's realistic HDR sensor (shot and read noise,
/// clipping); exposure comes from each shot ([`sim_exposures_s`] by default).
pub fn sim_sensor() -> Sensor {
    Sensor::realistic()
}

/// The material the `sim` camera renders: the simulator's marble field (heterogeneous, with the
/// modulation texture alpha), isotropic so that the model file's isotropic Eq. 9 (the paper's
/// choice for objects) holds it exactly and `ground-truth.ply` is the true model, not an
/// approximation of it.
pub fn sim_field() -> Field {
    Field {
        anisotropy: 0.0,
        ..Field::default()
    }
}

/// The material of a simulated camera `spec` (`sim`, or `sim:NAME`), `None` for any other
/// camera or an unknown name. `sim` and `sim:marble` are [`sim_field`]; `sim:homogeneous` is its
/// base material alone (no veins, no modulation texture), the material that needs fewest light
/// positions; `sim:veined` has veins a few millimetres apart, strong on the parameters and on
/// alpha, so the built-in bead (4 mm radius) holds several of them: the material that needs
/// most. The pair lets a steered scan be checked to stop earlier on the one than on the other.
pub fn sim_material(spec: &str) -> Option<Field> {
    match spec {
        "sim" | "sim:marble" => Some(sim_field()),
        "sim:homogeneous" => Some(Field {
            heterogeneity: 0.0,
            alpha_amplitude: 0.0,
            ..sim_field()
        }),
        "sim:veined" => Some(Field {
            heterogeneity: 1.0,
            alpha_amplitude: 0.5,
            vein_wavelength: 4.0,
            ..sim_field()
        }),
        _ => None,
    }
}

/// A `subsurf simulate` configuration that captures what `subsurf scan --sim --camera sim` does
/// (its isotropic material, spot and sensor) with one camera orbiting `object` and one exposure
/// per frame: the spot exposure of [`sim_exposures_s`], which keeps the laser spot unclipped, so
/// registration is sub-pixel exact and the spot's own light can be told from the scattered
/// light (a clipped spot's light leaks into the samples near x_i and the steepest term fits
/// it); the noise floor follows that exposure. `angles` × `raster`² frames. The scans of
/// `subsurf bench tradeoff` and of the tests that check its findings.
pub fn single_exposure_sim(
    object: SimObject,
    image_px: u32,
    angles: usize,
    raster: usize,
) -> crate::simulate::SimConfig {
    use crate::simulate::{CameraRig, SimConfig};
    let mut cfg = SimConfig::for_object(object, image_px, angles, raster);
    let exposure = sim_exposures_s()[0];
    cfg.field = sim_field();
    cfg.spot = sim_spot();
    cfg.sensor = Sensor {
        exposure_s: exposure,
        ..sim_sensor()
    };
    cfg.noise_floor = sim_noise_floor(&[exposure]);
    if let CameraRig::Orbit { count, .. } = &mut cfg.cameras {
        *count = 1;
    }
    cfg
}

/// File name of the ground truth a `--camera sim` scan writes beside `scan.json`.
pub const GROUND_TRUTH_FILE: &str = "ground-truth.ply";

/// Writes the true model of what the `sim` camera renders (`mesh` made of [`sim_field`]) as
/// `dir/ground-truth.ply`, the same file `subsurf simulate` writes: the floor a fitted model is
/// judged against (`subsurf evaluate --model ground-truth.ply`).
pub fn write_ground_truth(mesh: &Mesh, dir: &Path) -> Result<(), crate::modelfile::ModelFileError> {
    write_ground_truth_of(mesh, &sim_field(), dir)
}

/// [`write_ground_truth`] of a simulated camera's material `field` ([`sim_material`]).
pub fn write_ground_truth_of(
    mesh: &Mesh,
    field: &Field,
    dir: &Path,
) -> Result<(), crate::modelfile::ModelFileError> {
    crate::simulate::ground_truth_model(mesh, field).write(&dir.join(GROUND_TRUTH_FILE))
}
