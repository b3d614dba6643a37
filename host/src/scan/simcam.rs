//! The `sim` camera: renders what the rig's camera would capture, through the simulator's
//! forward renderer and sensor model (`crate::simulate`), from the state the rig reported for
//! each trigger (turntable angle, galvo codes) and the calibration's galvo model.
//!
//! Noise is seeded per frame and bracket (`seed`, frame, bracket), so the same scan always writes
//! the same images, however often it is interrupted and resumed.

use super::camera::{Camera, CameraError, Shot, Timing};
use crate::calib::Calibration;
use crate::dataset::Image;
use crate::dataset::{LaserRay, Mesh};
use crate::simulate::{Field, Sensor, SimScene, Spot, render_dark, render_frame};

/// The simulated camera.
pub struct SimCamera {
    scene: SimScene,
    calib: Calibration,
    sensor: Sensor,
    seed: u64,
}

impl SimCamera {
    /// A simulated camera seeing `mesh` (object frame) made of `field`, calibrated as `calib`;
    /// `sensor.exposure_s` is replaced by each shot's exposure.
    pub fn new(
        mesh: Mesh,
        calib: &Calibration,
        field: Field,
        sensor: Sensor,
        seed: u64,
    ) -> Result<Self, CameraError> {
        let scene = SimScene::new(mesh, vec![calib.camera.clone()], field, Spot::default())
            .map_err(|e| CameraError::Spec(format!("sim: {e}")))?;
        Ok(SimCamera {
            scene,
            calib: calib.clone(),
            sensor,
            seed,
        })
    }

    /// Sets the laser spot's first-surface reflection.
    pub fn with_spot(mut self, spot: Spot) -> Self {
        self.scene.spot = spot;
        self
    }
}

impl Camera for SimCamera {
    fn describe(&self) -> String {
        format!("sim(seed {})", self.seed)
    }
    fn timing(&self) -> Timing {
        Timing::RigTriggered
    }
    fn is_quick(&self) -> bool {
        true
    }
    fn saturation(&self) -> f32 {
        self.sensor.saturation.map_or(f32::INFINITY, |s| s as f32)
    }
    fn capture(&mut self, shot: &Shot) -> Result<Image, CameraError> {
        let (origin, direction) = self.calib.galvo.ray(shot.galvo);
        let sensor = Sensor {
            exposure_s: shot.exposure_s,
            ..self.sensor
        };
        let seed = self
            .seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add((shot.frame as u64) << 8 | shot.bracket as u64);
        if shot.dark {
            // Seeded apart from every lit frame's noise.
            return Ok(render_dark(&self.scene, 0, &sensor, !seed));
        }
        Ok(render_frame(
            &self.scene,
            0,
            shot.turntable_deg,
            &LaserRay { origin, direction },
            &sensor,
            seed,
        ))
    }
}
