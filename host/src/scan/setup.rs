//! Resolving what a scan needs: the object (built-in or an OBJ file), the calibration, the rig's
//! timing, and the camera named on the command line.

use super::camera::{Camera, CmdCamera, DirCamera};
use super::plan::RigTiming;
use super::simcam::SimCamera;
use crate::calib::Calibration;
use crate::dataset::Mesh;
use crate::simulate::{Field, Sensor, SimObject, Spot};
use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;
use subsurf_protocol::{Capabilities, Config};

/// Default exposure of a `--camera sim` scan (s).
pub const SIM_EXPOSURE_S: f64 = 1.0;

/// The built-in object of `subsurf scan --sim`: a sphere of radius 10 mm resting on the platter.
pub fn builtin_object() -> SimObject {
    SimObject::Sphere {
        radius: 10.0,
        rings: 16,
    }
}

/// The mesh as Wavefront OBJ text (deterministic: equal meshes give equal bytes).
pub fn obj_text(mesh: &Mesh) -> Vec<u8> {
    let mut s = String::from("# subsurf scan object (mm, object frame)\n");
    for p in &mesh.positions {
        let _ = writeln!(s, "v {} {} {}", p[0], p[1], p[2]);
    }
    for t in &mesh.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s.into_bytes()
}

/// The rig's timing from its handshake capabilities and configuration, for the move speed and
/// acceleration and capture interval the scan will use.
pub fn rig_timing(
    caps: &Capabilities,
    cfg: &Config,
    speed: Option<u32>,
    accel: Option<u32>,
    interval_us: u32,
) -> RigTiming {
    let v = speed.unwrap_or(caps.max_speed).min(caps.max_speed) as f64;
    let a = accel.unwrap_or(caps.max_accel).min(caps.max_accel) as f64;
    let hv = cfg.home_speed.min(caps.max_speed) as f64;
    let ha = cfg.home_accel.min(caps.max_accel) as f64;
    // Homing runs at home speed until the switch, from anywhere: half a turn on average, and it
    // stops on the switch without decelerating.
    let half = caps.steps_per_rev as f64 / 2.0;
    let home_s = if hv > 0.0 && ha > 0.0 {
        let ramp = hv * hv / (2.0 * ha);
        if half > ramp {
            hv / ha + (half - ramp) / hv
        } else {
            (2.0 * half / ha).sqrt()
        }
    } else {
        0.0
    };
    RigTiming {
        steps_per_rev: caps.steps_per_rev,
        max_speed_sps: v,
        accel_sps2: a,
        home_s,
        settle_base_s: cfg.galvo_settle_min_us as f64 * 1e-6,
        settle_per_code_s: cfg.galvo_settle_per_kcode_us as f64 * 1e-9,
        capture_overhead_s: 0.0,
        interval_s: interval_us as f64 * 1e-6,
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
    if spec == "sim" {
        let sensor = sim_sensor();
        // The spot as `subsurf simulate` renders it (a bright first-surface reflection).
        let spot = Spot {
            radiance: 200.0,
            sigma_px: 0.8,
        };
        return Ok(Box::new(
            SimCamera::new(mesh.clone(), calib, Field::default(), sensor, seed)?.with_spot(spot),
        ));
    }
    if let Some(dir) = spec.strip_prefix("dir:") {
        return Ok(Box::new(DirCamera::new(Path::new(dir), timeout)?));
    }
    if let Some(cmd) = spec.strip_prefix("cmd:") {
        return Ok(Box::new(CmdCamera::new(cmd, timeout)?));
    }
    Err(super::camera::CameraError::Spec(format!(
        "unknown camera {spec:?}: use sim, dir:PATH or cmd:\"COMMAND {{out}}\""
    )))
}

/// The simulated camera's sensor: the simulator's realistic HDR sensor (shot and read noise,
/// clipping); exposure comes from each shot ([`SIM_EXPOSURE_S`] by default, the exposure the
/// sensor's noise figures are given for).
pub fn sim_sensor() -> Sensor {
    Sensor::realistic()
}
