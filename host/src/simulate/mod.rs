//! Synthetic scans with known ground truth: built-in objects, a marble-like heterogeneous and
//! anisotropic material, cameras, a turntable, a laser raster and a realistic sensor.
//!
//! The forward renderer ([`render_frame`]) is also the simulated camera of `subsurf scan`: given a
//! camera, a turntable angle and a laser ray it produces the image the rig would capture. A pixel
//! that sees surface point `x_o` records `alpha(x_o)·R_d(x_i → x_o)` (Eq. 9, with the field's
//! optional direction dependence) plus the laser's first-surface reflection at `x_i` as a small
//! image-space Gaussian, then shot noise, read noise and clipping.
use std::path::Path;
use std::sync::{Arc, Mutex};

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use crate::dataset::{
    DatasetWriter, FrameChannel, FrameSpec, Image, LaserRay, ScanSpec, WriteError, obj_bytes,
};
use crate::geometry::{
    Camera, GeometryError, Scene, V3, add_scaled, cross, dist, dot, normalize, sub,
    turntable_to_world, world_to_turntable,
};
use crate::modelfile::{
    ColourMode, ModelFile, ModelFileError, ModelShape, VertexModel, VertexStatus,
};

mod field;
mod objects;

pub use field::{Field, MAX_ALPHA_AMPLITUDE, TrueParams};
pub use objects::SimObject;

/// Why a simulation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// Building the scene failed.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// Writing the dataset failed (disk full, another capture in the folder).
    #[error(transparent)]
    Write(#[from] WriteError),
    /// Writing the ground-truth model failed.
    #[error(transparent)]
    Model(#[from] ModelFileError),
    /// Writing the ground-truth JSON failed.
    #[error("cannot write ground truth: {0}")]
    Io(#[from] std::io::Error),
    /// The configuration is unusable.
    #[error("invalid simulation: {0}")]
    Invalid(String),
}

/// The camera's sensor and the rig's registration error.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Sensor {
    /// Exposure time, s; raw pixel = radiance · exposure.
    pub exposure_s: f64,
    /// Photo-electrons per raw unit (shot noise); `None` = no shot noise.
    pub gain: Option<f64>,
    /// Standard deviation of the read noise, raw units.
    pub read_noise: f64,
    /// Raw value at which pixels clip; `None` = never.
    pub saturation: Option<f64>,
    /// The sensor's offset: raw units every pixel reads on top of its light and noise, dark
    /// frames included (a black level the camera does not remove).
    pub dark_offset: f64,
    /// Standard deviation (mm) of a tangential offset between where the laser light enters
    /// (`x_i`, where scattering starts) and where its spot appears: misregistration of `x_i`.
    pub misregistration_mm: f64,
}

impl Sensor {
    /// A perfect sensor: no noise, no clipping, no misregistration.
    pub fn ideal() -> Sensor {
        Sensor {
            exposure_s: 1.0,
            gain: None,
            read_noise: 0.0,
            saturation: None,
            dark_offset: 0.0,
            misregistration_mm: 0.0,
        }
    }

    /// A realistic HDR sensor: 1e6 electrons per raw unit, read noise 2e-5, clipping at 20.
    pub fn realistic() -> Sensor {
        Sensor {
            exposure_s: 1.0,
            gain: Some(1e6),
            read_noise: 2e-5,
            saturation: Some(20.0),
            dark_offset: 0.0,
            misregistration_mm: 0.0,
        }
    }
}

impl Sensor {
    /// The radiance at which one pixel's signal-to-noise ratio (shot and read noise) is `snr`
    /// at this sensor's exposure: below it, a sample's log carries more than `1 / snr` of noise.
    /// Solves `raw / sqrt(raw / gain + read_noise²) = snr` for `raw`.
    pub fn radiance_at_snr(&self, snr: f64) -> f64 {
        let k2 = snr * snr;
        let inv_g = self.gain.map_or(0.0, |g| 1.0 / g);
        let s2 = self.read_noise * self.read_noise;
        let raw = 0.5 * (k2 * inv_g + (k2 * k2 * inv_g * inv_g + 4.0 * k2 * s2).sqrt());
        raw / self.exposure_s
    }
}

/// The laser spot's first-surface reflection as the camera sees it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Spot {
    /// Peak radiance of the spot (far above the scattered light).
    pub radiance: f64,
    /// Standard deviation of the spot in pixels.
    pub sigma_px: f64,
}

impl Default for Spot {
    fn default() -> Spot {
        Spot {
            radiance: 1e4,
            sigma_px: 0.7,
        }
    }
}

/// What the pixels of one camera at one turntable angle see: the first surface point per pixel.
struct GBuffer {
    x_o: Vec<Option<V3>>,
    alpha: Vec<[f64; 3]>,
}

/// A scene ready to render: geometry, cameras, material, laser spot.
pub struct SimScene {
    /// The mesh and its ray-casting structure.
    pub scene: Scene,
    /// The cameras (as written to `scan.json`).
    pub cameras: Vec<Camera>,
    /// The material.
    pub field: Field,
    /// The spot.
    pub spot: Spot,
    gbuffers: Mutex<Vec<(usize, u64, Arc<GBuffer>)>>,
}

impl std::fmt::Debug for SimScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimScene")
            .field("scene", &self.scene)
            .field("cameras", &self.cameras.len())
            .finish()
    }
}

/// Ground truth of one rendered frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTruth {
    /// Where the laser light enters (object frame), if the ray hits the object.
    pub x_i: Option<V3>,
    /// Where the spot appears (differs from `x_i` by the misregistration).
    pub spot: Option<V3>,
    /// The true model at `x_i`.
    pub params: Option<TrueParams>,
}

impl SimScene {
    /// A scene of a mesh seen by `cameras`.
    pub fn new(
        mesh: crate::dataset::Mesh,
        cameras: Vec<Camera>,
        field: Field,
        spot: Spot,
    ) -> Result<SimScene, SimError> {
        if cameras.is_empty() {
            return Err(SimError::Invalid("no cameras".into()));
        }
        Ok(SimScene {
            scene: Scene::new(mesh)?,
            cameras,
            field,
            spot,
            gbuffers: Mutex::new(Vec::new()),
        })
    }

    fn gbuffer(&self, cam: usize, deg: f64) -> Arc<GBuffer> {
        let key = deg.to_bits();
        if let Ok(g) = self.gbuffers.lock()
            && let Some((_, _, b)) = g.iter().find(|(c, k, _)| *c == cam && *k == key)
        {
            return b.clone();
        }
        let c = &self.cameras[cam];
        let (w, h) = (c.width as usize, c.height as usize);
        let mut x_o = vec![None; w * h];
        let mut alpha = vec![[0.0; 3]; w * h];
        use rayon::prelude::*;
        x_o.par_iter_mut()
            .zip(alpha.par_iter_mut())
            .enumerate()
            .for_each(|(k, (x, a))| {
                let (u, v) = ((k % w) as f64, (k / w) as f64);
                if let Some((o, d)) = c.ray(u, v)
                    && let Some(hit) = self.scene.cast_world(o, d, deg)
                {
                    *x = Some(hit.point);
                    *a = self.field.alpha_at(hit.point);
                }
            });
        let b = Arc::new(GBuffer { x_o, alpha });
        if let Ok(mut g) = self.gbuffers.lock() {
            // A few angles stay cached: frames of one angle are usually captured together.
            if g.len() >= 4 {
                g.remove(0);
            }
            g.push((cam, key, b.clone()));
        }
        b
    }

    /// Normal of the surface at a hit point (interpolated vertex normals).
    fn normal_at(&self, tri: u32, p: V3) -> V3 {
        self.scene.normal_at(tri, p).unwrap_or([0.0, 0.0, 1.0])
    }

    /// Whether camera `cam` at turntable angle `deg` sees the spot's reflection at `spot`
    /// (object frame, surface normal `n`). The simulator's own rule, as a camera sees: the spot
    /// faces the camera and the camera's ray towards it meets no surface before it (a z-buffer
    /// test). Deliberately not registration's rule ([`Scene::sees`] with its lift-off), which the
    /// simulated scans exist to check.
    fn spot_seen(&self, cam: &Camera, deg: f64, spot: V3, n: V3) -> bool {
        let c_obj = world_to_turntable(cam.center(), deg);
        let facing = normalize(sub(c_obj, spot)).is_some_and(|d| dot(d, n) > 0.0);
        // A misregistered spot sits in the tangent plane, a hair off a curved surface.
        let tol = 1e-3 * self.scene.mesh.diagonal();
        let d_spot = dist(c_obj, spot);
        facing
            && self
                .scene
                .cast(c_obj, sub(spot, c_obj), f64::MAX)
                .is_none_or(|h| h.t >= d_spot - tol)
    }
}

/// Renders what camera `camera` captures at turntable angle `turntable_deg` when the laser fires
/// along `laser` (world frame), through `sensor`; `seed` makes the noise reproducible.
pub fn render_frame(
    sim: &SimScene,
    camera: usize,
    turntable_deg: f64,
    laser: &LaserRay,
    sensor: &Sensor,
    seed: u64,
) -> Image {
    render_frame_truth(sim, camera, turntable_deg, laser, sensor, seed).0
}

/// [`render_frame`] that also returns the frame's ground truth.
pub fn render_frame_truth(
    sim: &SimScene,
    camera: usize,
    turntable_deg: f64,
    laser: &LaserRay,
    sensor: &Sensor,
    seed: u64,
) -> (Image, FrameTruth) {
    let camera = camera.min(sim.cameras.len() - 1);
    let cam = &sim.cameras[camera];
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut img = Image::new(w, h, 3);
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let hit = sim
        .scene
        .cast_world(laser.origin, laser.direction, turntable_deg);
    let mut truth = FrameTruth {
        x_i: None,
        spot: None,
        params: None,
    };
    if let Some(hit) = hit {
        let x_i = hit.point;
        let n_i = sim.normal_at(hit.triangle, x_i);
        let params = sim.field.params_at(x_i, n_i);
        // Misregistration: the spot appears displaced along the tangent plane.
        let mut spot = x_i;
        if sensor.misregistration_mm > 0.0 {
            let t1 = normalize(cross(n_i, [0.3, 0.5, 0.8])).unwrap_or([1.0, 0.0, 0.0]);
            let t2 = cross(n_i, t1);
            let sd = sensor.misregistration_mm;
            let z1: f64 = rng.sample(rand_distr::StandardNormal);
            let z2: f64 = rng.sample(rand_distr::StandardNormal);
            spot = add_scaled(add_scaled(spot, sd * z1, t1), sd * z2, t2);
        }
        truth = FrameTruth {
            x_i: Some(x_i),
            spot: Some(spot),
            params: Some(params),
        };
        let g = sim.gbuffer(camera, turntable_deg);
        for (k, x_o) in g.x_o.iter().enumerate() {
            if let Some(x_o) = x_o {
                let l = params.log_rd(x_i, *x_o, n_i);
                for (c, lc) in l.iter().enumerate() {
                    img.data[k * 3 + c] = (g.alpha[k][c] * lc.exp()) as f32;
                }
            }
        }
        // First-surface reflection, visible only if the camera sees the spot.
        if sim.spot_seen(cam, turntable_deg, spot, n_i)
            && let Some([su, sv]) = cam.project(turntable_to_world(spot, turntable_deg))
        {
            let s = sim.spot.sigma_px.max(0.05);
            let reach = (6.0 * s).ceil() as i64;
            let (ci, cj) = (su.round() as i64, sv.round() as i64);
            for j in (cj - reach).max(0)..=(cj + reach).min(h as i64 - 1) {
                for i in (ci - reach).max(0)..=(ci + reach).min(w as i64 - 1) {
                    let r2 = (i as f64 - su).powi(2) + (j as f64 - sv).powi(2);
                    let val = sim.spot.radiance * (-r2 / (2.0 * s * s)).exp();
                    let k = (j as usize * w + i as usize) * 3;
                    for c in 0..3 {
                        img.data[k + c] += val as f32;
                    }
                }
            }
        }
    }
    sense(&mut img, sensor, &mut rng);
    (img, truth)
}

/// What the camera of `sim` records with every laser off (a dark frame): no light, the sensor's
/// noise alone, at `sensor.exposure_s`.
pub fn render_dark(sim: &SimScene, camera: usize, sensor: &Sensor, seed: u64) -> Image {
    let cam = &sim.cameras[camera.min(sim.cameras.len() - 1)];
    let mut img = Image::new(cam.width as usize, cam.height as usize, 3);
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    sense(&mut img, sensor, &mut rng);
    img
}

/// The sensor: radiance → raw, shot noise, read noise, clipping.
fn sense(img: &mut Image, sensor: &Sensor, rng: &mut rand::rngs::StdRng) {
    let read = Normal::new(0.0, sensor.read_noise.max(0.0)).ok();
    for v in &mut img.data {
        let mut raw = *v as f64 * sensor.exposure_s;
        if let Some(g) = sensor.gain
            && raw > 0.0
        {
            let electrons = raw * g;
            let z: f64 = rng.sample(rand_distr::StandardNormal);
            raw = (electrons + electrons.sqrt() * z).max(0.0) / g;
        }
        if let Some(read) = &read
            && sensor.read_noise > 0.0
        {
            raw += read.sample(rng);
        }
        if sensor.dark_offset.is_finite() {
            raw += sensor.dark_offset;
        }
        if let Some(s) = sensor.saturation {
            raw = raw.min(s);
        }
        *v = raw as f32;
    }
}

/// Where the cameras stand.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum CameraRig {
    /// One camera straight above the platter centre, `mm_per_pixel` at `z = 0`, principal point on
    /// a pixel centre (so a slab grid with a spacing that is a multiple of the pixel lands on
    /// pixel centres).
    TopDown {
        /// Height above the platter, mm.
        distance: f64,
        /// Pixel footprint at `z = 0`, mm.
        mm_per_pixel: f64,
        /// Image width and height, pixels.
        size: u32,
    },
    /// `count` cameras on a circle around the object, looking at its centre.
    Orbit {
        /// Number of cameras.
        count: usize,
        /// Distance to the object's centre, mm.
        distance: f64,
        /// Elevation above the platter plane, degrees.
        elevation_deg: f64,
        /// Azimuth of the first camera, degrees (the others follow evenly over ±60°).
        azimuth_deg: f64,
        /// Image width and height, pixels.
        size: u32,
    },
}

/// Where the laser points.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum LaserRig {
    /// One frame per `stride`-th vertex, aimed exactly at it (at every turntable angle).
    AtVertices {
        /// Laser origin, world frame.
        origin: V3,
        /// Take every `stride`-th vertex.
        stride: usize,
    },
    /// An `n × n` galvo raster over the object's bounding sphere; rays that miss give frames with
    /// no spot, as on a real rig.
    Raster {
        /// Laser origin, world frame.
        origin: V3,
        /// Raster size per axis.
        n: usize,
        /// Fraction of the bounding radius the raster spans (<= 1).
        span: f64,
    },
}

/// A complete simulated scan.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SimConfig {
    /// The object.
    pub object: SimObject,
    /// The material.
    pub field: Field,
    /// The cameras.
    pub cameras: CameraRig,
    /// Turntable angles, degrees.
    pub turntable_deg: Vec<f64>,
    /// The laser.
    pub laser: LaserRig,
    /// The sensor.
    pub sensor: Sensor,
    /// The laser spot.
    pub spot: Spot,
    /// `noise_floor` written to `scan.json` (radiance).
    pub noise_floor: f64,
    /// Seed of all noise.
    pub seed: u64,
    /// Write PFM frames instead of OpenEXR.
    pub pfm: bool,
}

impl SimConfig {
    /// The same scan without noise (`subsurf simulate --noise-free`): an ideal sensor, a spot far
    /// above the scattered light, and a noise floor only rounding stays under.
    pub fn noise_free(mut self) -> SimConfig {
        self.sensor = Sensor::ideal();
        self.spot.radiance = 1e4;
        self.noise_floor = 1e-9;
        self
    }

    /// The same scan seen by one camera straight above the platter (400 mm up) at
    /// `mm_per_pixel` (at z = 0), as many pixels square as the first camera had, and the laser
    /// raster narrowed to 85 % of that view (`subsurf simulate --top-down`). Why: a view inside a
    /// slab sees none of its boundary, whose vertices read the background in their bilinear
    /// neighbourhood (measured at 0.16–0.79 of the true value on a slab's edge), and a raster inside the
    /// view keeps every spot seen.
    pub fn top_down(mut self, mm_per_pixel: f64) -> Result<SimConfig, SimError> {
        if !(mm_per_pixel.is_finite() && mm_per_pixel > 0.0) {
            return Err(SimError::Invalid(format!(
                "pixel footprint {mm_per_pixel} mm is not positive"
            )));
        }
        let size = match self.cameras {
            CameraRig::TopDown { size, .. } | CameraRig::Orbit { size, .. } => size,
        };
        self.cameras = CameraRig::TopDown {
            distance: 400.0,
            mm_per_pixel,
            size,
        };
        let half_view = 0.5 * size as f64 * mm_per_pixel;
        let (_, radius) = self.object.bounds();
        if let LaserRig::Raster { span, .. } = &mut self.laser {
            *span = span.min(0.85 * half_view / radius.max(1e-9));
        }
        Ok(self)
    }

    /// A default scan of `object`: realistic sensor, marble field, three orbiting cameras of
    /// `size` pixels, `angles` turntable steps and an `n × n` raster.
    pub fn for_object(object: SimObject, size: u32, angles: usize, n: usize) -> SimConfig {
        let (laser, cameras) = match object {
            SimObject::Slab { .. } => (
                LaserRig::Raster {
                    origin: [0.0, 0.0, 850.0],
                    n,
                    span: 0.65,
                },
                CameraRig::Orbit {
                    count: 1,
                    distance: 600.0,
                    elevation_deg: 70.0,
                    azimuth_deg: -90.0,
                    size,
                },
            ),
            _ => (
                LaserRig::Raster {
                    origin: [0.0, -600.0, 500.0],
                    n,
                    span: 0.95,
                },
                CameraRig::Orbit {
                    count: 3,
                    distance: 600.0,
                    elevation_deg: 35.0,
                    azimuth_deg: -90.0,
                    size,
                },
            ),
        };
        SimConfig {
            object,
            field: Field::default(),
            cameras,
            turntable_deg: (0..angles.max(1))
                .map(|k| 360.0 * k as f64 / angles.max(1) as f64)
                .collect(),
            laser,
            sensor: Sensor::realistic(),
            spot: Spot {
                radiance: 200.0,
                sigma_px: 0.8,
            },
            noise_floor: 1e-4,
            seed: 7,
            pfm: false,
        }
    }
}

fn look_at(center: V3, target: V3, size: u32, fov_radius: f64) -> Camera {
    let fwd = normalize(sub(target, center)).unwrap_or([0.0, 0.0, -1.0]);
    let up = if fwd[2].abs() > 0.99 {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    };
    let f = 0.5 * size as f64 * dist(center, target) / (fov_radius * 1.15);
    Camera::look_at(center, target, up, f, size, size).unwrap_or_else(|| {
        // `center == target` (or not finite): straight down, +y up.
        let row = |a: V3| [a[0], a[1], a[2], -dot(a, center)];
        Camera {
            width: size,
            height: size,
            fx: f,
            fy: f,
            cx: (size as f64 - 1.0) / 2.0,
            cy: (size as f64 - 1.0) / 2.0,
            distortion: None,
            camera_from_world: [
                row([1.0, 0.0, 0.0]),
                row([0.0, -1.0, 0.0]),
                row([0.0, 0.0, -1.0]),
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    })
}

/// The camera descriptions of a rig for an object with bounding sphere `(centre, radius)`.
pub fn rig_cameras(rig: &CameraRig, centre: V3, radius: f64) -> Vec<Camera> {
    match *rig {
        CameraRig::TopDown {
            distance,
            mm_per_pixel,
            size,
        } => {
            let mut c = look_at([0.0, 0.0, distance], [0.0; 3], size, radius);
            c.fx = distance / mm_per_pixel;
            c.fy = c.fx;
            c.cx = (size / 2) as f64;
            c.cy = (size / 2) as f64;
            vec![c]
        }
        CameraRig::Orbit {
            count,
            distance,
            elevation_deg,
            azimuth_deg,
            size,
        } => (0..count.max(1))
            .map(|k| {
                let az = if count > 1 {
                    azimuth_deg - 60.0 + 120.0 * k as f64 / (count - 1) as f64
                } else {
                    azimuth_deg
                }
                .to_radians();
                let el = elevation_deg.to_radians();
                let pos = [
                    centre[0] + distance * el.cos() * az.cos(),
                    centre[1] + distance * el.cos() * az.sin(),
                    centre[2] + distance * el.sin(),
                ];
                look_at(pos, centre, size, radius)
            })
            .collect(),
    }
}

/// The laser rays of one turntable angle.
pub fn rig_lasers(
    rig: &LaserRig,
    scene: &Scene,
    centre: V3,
    radius: f64,
    deg: f64,
) -> Vec<LaserRay> {
    match *rig {
        LaserRig::AtVertices { origin, stride } => scene
            .mesh
            .positions
            .iter()
            .step_by(stride.max(1))
            .map(|p| LaserRay {
                origin,
                direction: sub(turntable_to_world(*p, deg), origin),
            })
            .collect(),
        LaserRig::Raster { origin, n, span } => {
            let c = turntable_to_world(centre, deg);
            let fwd = normalize(sub(c, origin)).unwrap_or([0.0, 0.0, -1.0]);
            let a = normalize(cross(fwd, [0.0, 0.0, 1.0]))
                .or_else(|| normalize(cross(fwd, [0.0, 1.0, 0.0])))
                .unwrap_or([1.0, 0.0, 0.0]);
            let b = cross(fwd, a);
            let n = n.max(1);
            let mut out = Vec::with_capacity(n * n);
            for j in 0..n {
                for i in 0..n {
                    let s = |k: usize| {
                        if n == 1 {
                            0.0
                        } else {
                            span * radius * (2.0 * k as f64 / (n - 1) as f64 - 1.0)
                        }
                    };
                    let target = add_scaled(add_scaled(c, s(i), a), s(j), b);
                    out.push(LaserRay {
                        origin,
                        direction: sub(target, origin),
                    });
                }
            }
            out
        }
    }
}

/// What a simulation wrote.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SimSummary {
    /// Frames written.
    pub frames: usize,
    /// Frames whose laser ray misses the object.
    pub frames_without_hit: usize,
    /// Vertices of the mesh.
    pub vertices: usize,
}

#[derive(serde::Serialize)]
struct FrameTruthJson {
    frame: usize,
    x_i: Option<V3>,
    spot: Option<V3>,
    params: Option<Vec<f64>>,
    anisotropy: Option<f64>,
}

/// The true per-vertex model of `mesh` made of `field`, as `docs/model-format.md` holds it:
/// isotropic shared colour with n = 3 terms and the true alpha(x_o): at the vertices, and when
/// the field's alpha varies (`alpha_amplitude` ≠ 0) also between them, as a face lattice
/// ([`true_face_alpha`], per face as fine as the texture needs), so the ground truth is the
/// best case at surface points too, not only at vertices. The field's direction dependence
/// (anisotropy) cannot be written in this shape; it is part of the floor a fitted isotropic
/// model is compared against.
pub fn ground_truth_model(mesh: &crate::dataset::Mesh, field: &Field) -> ModelFile {
    let mut m = ModelFile {
        shape: ModelShape {
            terms: 3,
            segments: 1,
            colour: ColourMode::Shared,
        },
        positions: mesh.positions.clone(),
        normals: mesh.normals.clone(),
        triangles: mesh.triangles.clone(),
        vertices: mesh
            .positions
            .iter()
            .zip(&mesh.normals)
            .map(|(p, n)| VertexModel {
                alpha: field.alpha_at(*p).map(|a| a as f32),
                status: VertexStatus::Fitted,
                log_e: 0.0,
                terms: 3,
                segments: 1,
                params: field.params_at(*p, *n).model_params(),
                r_range: crate::modelfile::NO_RANGE,
            })
            .collect(),
        baseline: None,
        frame: crate::model::FrameRule::CURRENT,
        face_alpha: None,
        fitted_with: None,
        fitted_frames: None,
    };
    if field.alpha_amplitude != 0.0 {
        m.face_alpha = true_face_alpha(&m, field);
    }
    m
}

/// Largest error in ln alpha the ground truth's face lattice may make against the true texture
/// at any point of the finest lattice: well below the camera noise of any simulated scan (1 %
/// and more), so the ground truth stays the best case, and no face is finer than that needs.
pub const TRUE_ALPHA_TOLERANCE: f64 = 0.005;

/// The true alpha(x_o) between the vertices of `model` as a face lattice: per face the smallest
/// level whose piecewise linear detail reproduces the true alpha within [`TRUE_ALPHA_TOLERANCE`]
/// (in ln alpha) at every point of the finest lattice ([`crate::lattice::MAX_LEVEL`]), or that
/// level where none does; at each lattice point x (on the flat face, where the simulated camera
/// sees the surface), detail = ln alpha_true(x) − ln(barycentric interpolation of the corners'
/// stored vertex alphas), per channel, and 0 at the corners (`docs/model-format.md`). Why the
/// smallest level: the file should cost what the texture needs (a smooth 25 mm vein on a fine
/// mesh is level 1 or 2, not 45 points a face). `None` if some value is not finite (an alpha
/// amplitude too large for f32).
pub fn true_face_alpha(model: &ModelFile, field: &Field) -> Option<crate::lattice::FaceAlpha> {
    use crate::lattice::{FaceAlpha, MAX_LEVEL, is_corner, point_bary, points};
    let mut levels = Vec::with_capacity(model.triangles.len());
    let mut detail = Vec::new();
    for t in &model.triangles {
        let corner = |c: usize| {
            let v = t[c] as usize;
            (model.positions[v], model.vertices[v].alpha.map(f64::from))
        };
        let cs = [corner(0), corner(1), corner(2)];
        // Position and ln of the interpolated vertex alpha at barycentric coordinates w.
        let at = |w: [f64; 3]| {
            let mut x = [0.0; 3];
            let mut interp = [0.0; 3];
            for (wc, (p, a)) in w.iter().zip(&cs) {
                for d in 0..3 {
                    x[d] += wc * p[d];
                    interp[d] += wc * a[d];
                }
            }
            (x, interp.map(f64::ln))
        };
        let lattice_of = |k: u8| -> Vec<[f32; 3]> {
            points(k)
                .map(|(_, i, j)| {
                    if is_corner(k, i, j) {
                        return [0.0f32; 3];
                    }
                    let (x, ln_interp) = at(point_bary(k, i, j));
                    let truth = field.alpha_at(x);
                    [0, 1, 2].map(|c| (truth[c].ln() - ln_interp[c]) as f32)
                })
                .collect()
        };
        // The finest lattice's points are where a level is checked.
        let checks: Vec<([f64; 3], [f64; 3])> = points(MAX_LEVEL)
            .map(|(_, i, j)| {
                let w = point_bary(MAX_LEVEL, i, j);
                let (x, ln_interp) = at(w);
                let truth = field.alpha_at(x);
                (w, [0, 1, 2].map(|c| truth[c].ln() - ln_interp[c]))
            })
            .collect();
        let mut chosen = None;
        for k in 1..=MAX_LEVEL {
            let d = lattice_of(k);
            let face = FaceAlpha::new(vec![k], d.clone()).ok()?;
            let worst = checks
                .iter()
                .flat_map(|(w, want)| {
                    let got = face.detail_at(0, *w);
                    (0..3).map(move |c| (got[c] - want[c]).abs())
                })
                .fold(0.0, f64::max);
            if worst <= TRUE_ALPHA_TOLERANCE || k == MAX_LEVEL {
                chosen = Some((k, d));
                break;
            }
        }
        let (k, d) = chosen?;
        levels.push(k);
        detail.extend(d);
    }
    FaceAlpha::new(levels, detail).ok()
}

/// Writes a simulated dataset to `out` and its ground truth beside it: `out/ground-truth.ply`
/// (the true model, `docs/model-format.md`: isotropic shared colour n = 3 per vertex and the true
/// alpha, finer than the mesh as a face lattice when it varies, [`ground_truth_model`]; the
/// direction dependence is in the JSON) and `out/ground-truth.json` (configuration,
/// and per frame the true `x_i`, spot position and parameters at `x_i`). Frames are rendered and
/// written in small parallel batches, so memory does not grow with the frame count.
pub fn simulate(
    cfg: &SimConfig,
    out: &Path,
    progress: &dyn crate::progress::Progress,
) -> Result<SimSummary, SimError> {
    use rayon::prelude::*;
    cfg.field.check()?;
    let mesh = cfg.object.mesh();
    let (centre, radius) = cfg.object.bounds();
    let cameras = rig_cameras(&cfg.cameras, centre, radius);
    let sim = SimScene::new(mesh.clone(), cameras.clone(), cfg.field.clone(), cfg.spot)?;
    // The one crash-safe writer; the configuration identifies the capture, so running the same
    // simulation again into the same folder resumes it (frames are seeded by index).
    let identity = serde_json::to_string_pretty(cfg).map_err(std::io::Error::other)?;
    let (mut writer, done) = DatasetWriter::open(
        out,
        &identity,
        ScanSpec::new(
            cameras.clone(),
            Some(cfg.noise_floor),
            cfg.sensor.saturation,
        ),
        &obj_bytes(&mesh),
    )?;
    let mut plan = Vec::new();
    for &deg in &cfg.turntable_deg {
        for ray in rig_lasers(&cfg.laser, &sim.scene, centre, radius, deg) {
            for cam in 0..cameras.len() {
                plan.push((deg, ray, cam));
            }
        }
    }
    if plan.is_empty() {
        return Err(SimError::Invalid("the rig produces no frames".into()));
    }
    progress.set_length(plan.len() as u64);
    let mut truths = Vec::with_capacity(plan.len());
    let mut without_hit = 0;
    for (b, batch) in plan.chunks(16).enumerate() {
        let rendered: Vec<(Image, FrameTruth)> = batch
            .par_iter()
            .enumerate()
            .map(|(k, (deg, ray, cam))| {
                let seed = cfg.seed ^ ((b * 16 + k) as u64).wrapping_mul(0x2545_F491_4F6C_DD1D);
                render_frame_truth(&sim, *cam, *deg, ray, &cfg.sensor, seed)
            })
            .collect();
        for (k, ((deg, ray, cam), (img, truth))) in (b * 16..).zip(batch.iter().zip(rendered)) {
            let spec = FrameSpec {
                image: String::new(),
                camera: *cam,
                turntable_deg: *deg,
                exposure_s: cfg.sensor.exposure_s,
                channel: FrameChannel::Rgb,
                laser: Some(LaserRay {
                    origin: ray.origin,
                    direction: normalize(ray.direction).unwrap_or(ray.direction),
                }),
                galvo: None,
                levels: Default::default(),
                brackets: Vec::new(),
            };
            if k >= done {
                writer.add_image(spec, &img, cfg.pfm)?;
            }
            without_hit += usize::from(truth.x_i.is_none());
            truths.push(FrameTruthJson {
                frame: k,
                x_i: truth.x_i,
                spot: truth.spot,
                params: truth.params.map(|p| p.model_params()),
                anisotropy: truth.params.map(|p| p.anisotropy),
            });
            progress.inc(1);
        }
    }
    let frames = writer.done();
    writer.finish()?;
    let truth_model = ground_truth_model(&mesh, &cfg.field);
    truth_model.write(&out.join("ground-truth.ply"))?;
    let json = serde_json::json!({
        "format": "subsurf-ground-truth/1",
        "config": cfg,
        "frames": truths,
    });
    std::fs::write(
        out.join("ground-truth.json"),
        serde_json::to_string(&json).map_err(std::io::Error::other)?,
    )?;
    Ok(SimSummary {
        frames,
        frames_without_hit: without_hit,
        vertices: mesh.positions.len(),
    })
}

/// For the host's unit tests: a slab of 8 mm (5 × 5 vertices) seen from above at 72 px and
/// 0.125 mm per pixel, lit at a 5 × 5 raster at one turntable angle: 25 frames of one view.
#[cfg(test)]
pub(crate) fn top_down_slab_config() -> SimConfig {
    let mut cfg = SimConfig::for_object(SimObject::Slab { size: 8.0, n: 5 }, 72, 1, 5);
    cfg.cameras = CameraRig::TopDown {
        distance: 400.0,
        mm_per_pixel: 0.125,
        size: 72,
    };
    cfg.laser = LaserRig::Raster {
        origin: [0.0, 0.0, 850.0],
        n: 5,
        span: 0.65,
    };
    cfg.turntable_deg = vec![0.0];
    cfg.pfm = true;
    cfg
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ground truth holds the true alpha between the vertices: within the tolerance at the
    /// finest lattice's points (exact on faces at the finest level), and at random surface points of veins of twice the edge length far closer
    /// than the vertex alphas alone (RMS ln alpha error measured 0.063 against 0.63: the
    /// pattern's warp octaves, down to 1.6 mm, are what level 8 on 4 mm edges leaves); no
    /// lattice where alpha is constant.
    #[test]
    fn ground_truth_holds_alpha_finer_than_the_mesh() {
        use crate::lattice::{MAX_LEVEL, point_bary, points};
        let mesh = SimObject::Slab { size: 20.0, n: 6 }.mesh();
        let field = Field {
            alpha_amplitude: 1.5,
            vein_wavelength: 8.0,
            ..Field::default()
        };
        let m = ground_truth_model(&mesh, &field);
        m.check().unwrap();
        let fa = m.face_alpha.as_ref().expect("a lattice");
        let at_point = |f: usize, w: [f64; 3]| {
            let t = m.triangles[f];
            let mut x = [0.0; 3];
            for (wc, v) in w.iter().zip(t) {
                x = crate::geometry::add_scaled(x, *wc, m.positions[v as usize]);
            }
            x
        };
        // At every point of the finest lattice: within the tolerance on faces below the finest
        // level, exact (to f32) on faces at it.
        for f in 0..m.triangles.len() {
            let tol = if fa.level(f) == MAX_LEVEL {
                1e-5
            } else {
                TRUE_ALPHA_TOLERANCE + 1e-5
            };
            for (_, i, j) in points(MAX_LEVEL) {
                let w = point_bary(MAX_LEVEL, i, j);
                let (got, want) = (m.alpha_at(f, w), field.alpha_at(at_point(f, w)));
                for c in 0..3 {
                    let e = (got[c].ln() - want[c].ln()).abs();
                    assert!(e < tol, "face {f} level {}: {e}", fa.level(f));
                }
            }
        }
        // Each face is only as fine as the texture needs: veins twice the edge length need the
        // finest level somewhere, and the default 25 mm pattern (amplitude 0.2) fewer points.
        assert!(fa.levels().contains(&MAX_LEVEL), "{:?}", fa.levels());
        let smooth = ground_truth_model(&mesh, &Field::default());
        let sfa = smooth.face_alpha.as_ref().expect("a lattice");
        let (n_veins, n_smooth) = (fa.detail().len(), sfa.detail().len());
        eprintln!("lattice points: veins of 8 mm {n_veins}, default {n_smooth}");
        assert!((n_smooth as f64) < 0.75 * n_veins as f64);
        // Between lattice points: the lattice against the vertex alphas alone.
        let mut flat = m.clone();
        flat.face_alpha = None;
        let (mut with, mut without) = (0.0, 0.0);
        for k in 0..500u64 {
            let f = (hash(k, 1) * m.triangles.len() as f64) as usize % m.triangles.len();
            let (a, b) = (hash(k, 2), hash(k, 3));
            let (u, v) = if a + b > 1.0 {
                (1.0 - a, 1.0 - b)
            } else {
                (a, b)
            };
            let w = [u, v, 1.0 - u - v];
            let truth = field.alpha_at(at_point(f, w))[0].ln();
            with += (m.alpha_at(f, w)[0].ln() - truth).powi(2);
            without += (flat.alpha_at(f, w)[0].ln() - truth).powi(2);
        }
        eprintln!(
            "RMS ln alpha error: lattice {:.4}, vertices only {:.4}",
            (with / 500.0f64).sqrt(),
            (without / 500.0f64).sqrt()
        );
        assert!(with < 0.05 * without, "{with} vs {without}");
        let constant = Field {
            alpha_amplitude: 0.0,
            ..field
        };
        assert!(ground_truth_model(&mesh, &constant).face_alpha.is_none());
    }

    fn hash(k: u64, s: u64) -> f64 {
        use rand::Rng;
        rand::rngs::StdRng::seed_from_u64(k * 7 + s).random::<f64>()
    }

    #[test]
    fn unusable_fields_are_refused() {
        for f in [
            Field {
                vein_wavelength: 0.0,
                ..Field::default()
            },
            Field {
                alpha_amplitude: f64::NAN,
                ..Field::default()
            },
            Field {
                alpha_amplitude: 11.0,
                ..Field::default()
            },
        ] {
            assert!(matches!(f.check(), Err(SimError::Invalid(_))), "{f:?}");
        }
        assert!(Field::default().check().is_ok());
    }

    #[test]
    fn the_spot_lands_where_the_laser_hits_and_scattering_falls_off() {
        let object = SimObject::Slab { size: 8.0, n: 9 };
        let cams = rig_cameras(
            &CameraRig::TopDown {
                distance: 400.0,
                mm_per_pixel: 0.125,
                size: 80,
            },
            [0.0; 3],
            6.0,
        );
        let sim = SimScene::new(object.mesh(), cams, Field::default(), Spot::default()).unwrap();
        let laser = LaserRay {
            origin: [0.0, 0.0, 850.0],
            direction: [1.0, 0.5, -850.0],
        };
        let (img, truth) = render_frame_truth(&sim, 0, 0.0, &laser, &Sensor::ideal(), 1);
        let x_i = truth.x_i.unwrap();
        let [u, v] = sim.cameras[0].project(x_i).unwrap();
        // Brightest pixel is the spot's.
        let (mut best, mut at) = (0.0, 0);
        for k in 0..img.width * img.height {
            if img.data[k * 3] > best {
                best = img.data[k * 3];
                at = k;
            }
        }
        assert_eq!((at % 80) as f64, u.round());
        assert_eq!((at / 80) as f64, v.round());
        // Far from the spot the value is the scattering only, and it decreases with distance.
        let a = img.get(62, 40, 1);
        let b = img.get(70, 40, 1);
        assert!(a > b && b > 0.0, "{a} {b}");
        // A ray that misses gives a black image.
        let miss = LaserRay {
            origin: [0.0, 0.0, 850.0],
            direction: [100.0, 0.0, -850.0],
        };
        let (img, t) = render_frame_truth(&sim, 0, 0.0, &miss, &Sensor::ideal(), 1);
        assert!(t.x_i.is_none() && img.data.iter().all(|v| *v == 0.0));
    }
}
