//! The scan plan: turntable angles and, per angle, the galvo targets the laser is aimed at.
//!
//! Two planners share one candidate set (a galvo raster over the object's extent at every
//! angle). [`dense_raster`] fires at all of them. [`coverage_plan`] is "model only what the scene
//! requires": every vertex the camera sees needs some x_i (the laser spot, Eq. 9's incident
//! position) within `target_mm`; candidates are picked by greedy set cover, each time the one that
//! covers the most still-uncovered vertices, until the requested fraction is covered.
//!
//! Coverage of a plan is predicted by casting each target's laser ray at the mesh
//! ([`PlanScene::laser_hit`]); a spot counts only where processing will register it: the camera
//! sees it by registration's own rule ([`crate::spot::spot_visible`], the one visibility
//! rule of [`crate::geometry::Scene::sees`] with registration's grazing limit
//! [`crate::spot::SPOT_COS_MIN`]), so the plan predicts exactly the frames the fit uses.

use crate::calib::Calibration;
use crate::dataset::{FrameChannel, Mesh};
use crate::geometry::{Scene, cross, dot, normalize, sub, turntable_to_world, world_to_turntable};
use crate::spot::spot_visible;
use serde::{Deserialize, Serialize};

/// The format string of a saved plan.
pub const PLAN_FORMAT: &str = "subsurf-plan/1";

/// Why a plan could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlanError {
    /// The mesh cannot be ray-cast (empty, out-of-range indices, non-finite vertices).
    #[error("mesh unusable for planning: {0}")]
    Mesh(String),
    /// The options are out of range.
    #[error("invalid plan option: {0}")]
    Options(String),
    /// No laser target hits a part of the object the camera sees.
    #[error(
        "no galvo target hits the object where the camera sees it: check the calibration (camera \
         extrinsics, galvo model) and that the object sits on the turntable"
    )]
    NothingVisible,
    /// A saved plan cannot be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The plan's path.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// A saved plan is not a plan of this format.
    #[error("{path} is not a plan ({PLAN_FORMAT}): {why}")]
    NotAPlan {
        /// The plan's path.
        path: String,
        /// Why.
        why: String,
    },
}

/// One turntable stop and the galvo targets fired there, in firing order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AnglePlan {
    /// Turntable angle in degrees.
    pub turntable_deg: f64,
    /// Galvo codes, in the order the rig runs them.
    pub targets: Vec<[u16; 2]>,
}

/// The whole plan. Frames are numbered angle by angle, target by target.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanPlan {
    /// Always [`PLAN_FORMAT`].
    pub format: String,
    /// `dense` or `coverage`.
    pub planner: String,
    /// The coverage distance the plan was made for (mm).
    pub target_mm: f64,
    /// Exposure times of one frame; more than one means HDR bracketing.
    pub exposures_s: Vec<f64>,
    /// The laser channel lit, as `frames[].channel` writes it.
    pub channel: FrameChannel,
    /// Angles in the order they are visited.
    pub angles: Vec<AnglePlan>,
}

/// One frame of a plan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlannedFrame {
    /// Sequential frame number, also the image name.
    pub index: usize,
    /// Which angle of the plan.
    pub angle_index: usize,
    /// The turntable angle (degrees).
    pub turntable_deg: f64,
    /// Galvo codes.
    pub galvo: [u16; 2],
}

impl ScanPlan {
    /// Number of frames (captures after HDR merging).
    pub fn frame_count(&self) -> usize {
        self.angles.iter().map(|a| a.targets.len()).sum()
    }

    /// Every frame in order.
    pub fn frames(&self) -> Vec<PlannedFrame> {
        let mut out = Vec::with_capacity(self.frame_count());
        for (ai, a) in self.angles.iter().enumerate() {
            for &g in &a.targets {
                out.push(PlannedFrame {
                    index: out.len(),
                    angle_index: ai,
                    turntable_deg: a.turntable_deg,
                    galvo: g,
                });
            }
        }
        out
    }
}

/// Planner settings.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanOptions {
    /// Number of equally spaced turntable angles.
    pub angles: usize,
    /// Raster points per axis over the object's galvo window (the candidate spacing).
    pub raster: usize,
    /// Every visible vertex needs an x_i this close (mm).
    pub target_mm: f64,
    /// Fraction of coverable vertices the coverage planner must cover (0..=1].
    pub coverage: f64,
    /// Exposure times per frame (s).
    pub exposures_s: Vec<f64>,
    /// Laser channel.
    pub channel: FrameChannel,
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            angles: 8,
            raster: 24,
            target_mm: 4.0,
            coverage: 1.0,
            exposures_s: vec![0.02],
            channel: FrameChannel::Rgb,
        }
    }
}

impl PlanOptions {
    fn validate(&self) -> Result<(), PlanError> {
        if self.angles == 0 || self.angles > 3600 {
            return Err(PlanError::Options("angles must be 1..=3600".into()));
        }
        if !(2..=1024).contains(&self.raster) {
            return Err(PlanError::Options(
                "raster must be 2..=1024 points per axis".into(),
            ));
        }
        if !(self.target_mm.is_finite() && self.target_mm > 0.0) {
            return Err(PlanError::Options(
                "target distance must be a positive number".into(),
            ));
        }
        if !(self.coverage > 0.0 && self.coverage <= 1.0) {
            return Err(PlanError::Options("coverage must be in (0, 1]".into()));
        }
        if self.exposures_s.is_empty()
            || self
                .exposures_s
                .iter()
                .any(|e| !(e.is_finite() && *e > 0.0))
        {
            return Err(PlanError::Options(
                "exposures must be positive seconds".into(),
            ));
        }
        Ok(())
    }

    /// The equally spaced angles.
    pub fn angle_list(&self) -> Vec<f64> {
        (0..self.angles)
            .map(|k| 360.0 * k as f64 / self.angles as f64)
            .collect()
    }
}

/// The object, camera and laser, for predicting what a target hits and who sees it: the one
/// [`Scene`] (ray casts, normals, visibility) and the calibration.
pub struct PlanScene {
    scene: Scene,
    calib: Calibration,
}

impl PlanScene {
    /// Builds the scene (its BVH is `parry3d-f64`'s, inside [`Scene`]) over the mesh (object
    /// frame, mm); degenerate and duplicate faces are dropped as in a dataset.
    pub fn new(
        vertices: &[[f64; 3]],
        triangles: &[[u32; 3]],
        calib: &Calibration,
    ) -> Result<Self, PlanError> {
        if vertices.is_empty() || triangles.is_empty() {
            return Err(PlanError::Mesh("no vertices or no triangles".into()));
        }
        if vertices.iter().flatten().any(|v| !v.is_finite()) {
            return Err(PlanError::Mesh("a vertex is not finite".into()));
        }
        if triangles
            .iter()
            .flatten()
            .any(|&i| i as usize >= vertices.len())
        {
            return Err(PlanError::Mesh(
                "a triangle refers to a missing vertex".into(),
            ));
        }
        let (mesh, _) = Mesh::new(vertices.to_vec(), triangles.to_vec());
        if mesh.triangles.is_empty() {
            return Err(PlanError::Mesh("no usable triangle".into()));
        }
        let scene = Scene::new(mesh).map_err(|e| PlanError::Mesh(e.to_string()))?;
        Ok(PlanScene {
            scene,
            calib: calib.clone(),
        })
    }

    /// Mesh vertices (object frame).
    pub fn vertices(&self) -> &[[f64; 3]] {
        &self.scene.mesh.positions
    }

    /// The laser spot x_i (object frame) for `codes` at angle `deg`, if the beam hits the object
    /// where processing will register it: it lights the side it enters (not grazing, within
    /// ~87° of the face normal) and the camera sees it ([`spot_visible`]).
    pub fn laser_hit(&self, deg: f64, codes: [u16; 2]) -> Option<[f64; 3]> {
        let (o, d) = self.calib.galvo.ray(codes);
        predicted_spot(&self.scene, &self.calib.camera, deg, o, d)
    }

    /// The galvo code window (`[x0, y0, x1, y1]`, inclusive) covering the object at all angles,
    /// widened by 3% on each side.
    pub fn galvo_window(&self, angles: &[f64]) -> [u16; 4] {
        let g = &self.calib.galvo;
        let r = g.world_from_galvo;
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for &deg in angles {
            for v in self.vertices() {
                let w = sub(turntable_to_world(*v, deg), g.origin);
                // galvo-frame direction = Rᵀ w
                let q = [
                    r[0][0] * w[0] + r[1][0] * w[1] + r[2][0] * w[2],
                    r[0][1] * w[0] + r[1][1] * w[1] + r[2][1] * w[2],
                    r[0][2] * w[0] + r[1][2] * w[1] + r[2][2] * w[2],
                ];
                if q[2] <= 0.0 {
                    continue;
                }
                for k in 0..2 {
                    let c = g.centre[k] + (q[k] / q[2]).atan() / g.radians_per_code[k];
                    lo[k] = lo[k].min(c);
                    hi[k] = hi[k].max(c);
                }
            }
        }
        let max = g.max_code as f64;
        let clamp = |v: f64| v.clamp(0.0, max) as u16;
        if !(lo[0].is_finite() && hi[0].is_finite()) {
            return [0, 0, g.max_code, g.max_code];
        }
        let m = 0.03 * (hi[0] - lo[0]).abs().max((hi[1] - lo[1]).abs());
        [
            clamp(lo[0].min(hi[0]) - m),
            clamp(lo[1].min(hi[1]) - m),
            clamp(lo[0].max(hi[0]) + m),
            clamp(lo[1].max(hi[1]) + m),
        ]
    }
}

/// The laser spot x_i (object frame) of the laser ray `origin`, `dir` (world frame) at turntable
/// angle `deg`, where processing will register it: the beam lights the side it enters (not
/// grazing, within ~87° of the face normal) and `camera` sees the hit by registration's own rule
/// ([`spot_visible`]). The one prediction of the planners, from galvo codes
/// ([`PlanScene::laser_hit`]) or from a recorded frame's laser ray (a replayed scan's candidates).
pub fn predicted_spot(
    scene: &Scene,
    camera: &crate::geometry::Camera,
    deg: f64,
    origin: [f64; 3],
    dir: [f64; 3],
) -> Option<[f64; 3]> {
    let hit = scene.cast_world(origin, dir, deg)?;
    let t = scene.mesh.triangles.get(hit.triangle as usize)?;
    let [a, b, c] = t.map(|i| scene.mesh.positions[i as usize]);
    let n = normalize(cross(sub(b, a), sub(c, a)))?;
    let d = normalize(world_to_turntable(dir, deg))?;
    if -dot(n, d) < 0.05 {
        return None;
    }
    spot_visible(scene, camera, deg, &hit).then_some(hit.point)
}

/// The candidate targets: an `n × n` raster over the object's galvo window, in serpentine order
/// (so consecutive galvo jumps are one step).
fn raster(scene: &PlanScene, angles: &[f64], n: usize) -> Vec<[u16; 2]> {
    let [x0, y0, x1, y1] = scene.galvo_window(angles);
    let axis = |a: u16, b: u16| -> Vec<u16> {
        let mut v: Vec<u16> = (0..n)
            .map(|k| {
                (a as f64 + (b as f64 - a as f64) * k as f64 / (n - 1).max(1) as f64).round() as u16
            })
            .collect();
        v.dedup();
        v
    };
    let mut out = Vec::new();
    let ys = axis(y0, y1);
    for (row, &y) in ys.iter().enumerate() {
        let mut xs = axis(x0, x1);
        if row % 2 == 1 {
            xs.reverse();
        }
        out.extend(xs.into_iter().map(|x| [x, y]));
    }
    out
}

/// Predicted coverage of a plan.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Coverage {
    /// Vertices with an x_i within the target distance.
    pub covered: usize,
    /// Vertices any candidate target could cover (the coverable part of the mesh).
    pub coverable: usize,
    /// All vertices.
    pub vertices: usize,
    /// Frames whose spot the camera sees on the object.
    pub useful_frames: usize,
}

impl Coverage {
    /// `covered / coverable` (1 when nothing is coverable).
    pub fn fraction(&self) -> f64 {
        if self.coverable == 0 {
            1.0
        } else {
            self.covered as f64 / self.coverable as f64
        }
    }
}

/// Vertex sets each candidate covers, as bitsets.
struct CoverSets {
    words: usize,
    sets: Vec<(usize, [u16; 2], Vec<u64>)>,
}

fn cover_sets(
    scene: &PlanScene,
    angles: &[f64],
    targets: &[[u16; 2]],
    target_mm: f64,
) -> CoverSets {
    let n = scene.vertices().len();
    let words = n.div_ceil(64);
    let r2 = target_mm * target_mm;
    let mut sets = Vec::new();
    for (ai, &deg) in angles.iter().enumerate() {
        for &t in targets {
            let Some(x) = scene.laser_hit(deg, t) else {
                continue;
            };
            let mut bits = vec![0u64; words];
            for (i, v) in scene.vertices().iter().enumerate() {
                let d = sub(*v, x);
                if dot(d, d) <= r2 {
                    bits[i / 64] |= 1 << (i % 64);
                }
            }
            sets.push((ai, t, bits));
        }
    }
    CoverSets { words, sets }
}

fn count(bits: &[u64]) -> usize {
    bits.iter().map(|w| w.count_ones() as usize).sum()
}

/// Predicts the coverage of `plan` over `scene`.
pub fn predict_coverage(scene: &PlanScene, plan: &ScanPlan, candidate_raster: usize) -> Coverage {
    let angles: Vec<f64> = plan.angles.iter().map(|a| a.turntable_deg).collect();
    let all = cover_sets(
        scene,
        &angles,
        &raster(scene, &angles, candidate_raster),
        plan.target_mm,
    );
    let mut coverable = vec![0u64; all.words];
    for (_, _, b) in &all.sets {
        for (c, w) in coverable.iter_mut().zip(b) {
            *c |= w;
        }
    }
    let mut covered = vec![0u64; all.words];
    let mut useful = 0;
    for (ai, a) in plan.angles.iter().enumerate() {
        let sets = cover_sets(scene, &[a.turntable_deg], &a.targets, plan.target_mm);
        useful += sets.sets.len();
        let _ = ai;
        for (_, _, b) in &sets.sets {
            for (c, w) in covered.iter_mut().zip(b) {
                *c |= w;
            }
        }
    }
    // Only count coverage of coverable vertices (a plan on other candidates may reach a few more).
    for (c, w) in covered.iter_mut().zip(&coverable) {
        *c &= w;
    }
    Coverage {
        covered: count(&covered),
        coverable: count(&coverable),
        vertices: scene.vertices().len(),
        useful_frames: useful,
    }
}

fn new_plan(planner: &str, opts: &PlanOptions, angles: Vec<AnglePlan>) -> ScanPlan {
    ScanPlan {
        format: PLAN_FORMAT.into(),
        planner: planner.into(),
        target_mm: opts.target_mm,
        exposures_s: opts.exposures_s.clone(),
        channel: opts.channel,
        angles,
    }
}

/// The dense raster: every candidate target at every angle (the galvo window bounds the object).
pub fn dense_raster(scene: &PlanScene, opts: &PlanOptions) -> Result<ScanPlan, PlanError> {
    opts.validate()?;
    let angles = opts.angle_list();
    let targets = raster(scene, &angles, opts.raster);
    Ok(new_plan(
        "dense",
        opts,
        angles
            .into_iter()
            .map(|turntable_deg| AnglePlan {
                turntable_deg,
                targets: targets.clone(),
            })
            .collect(),
    ))
}

/// The coarsest dense raster (fewest points per axis, at most `opts.raster`) whose predicted
/// coverage reaches `opts.coverage`: the fair baseline for [`coverage_plan`].
pub fn dense_for_target(scene: &PlanScene, opts: &PlanOptions) -> Result<ScanPlan, PlanError> {
    opts.validate()?;
    for n in 2..opts.raster {
        let o = PlanOptions {
            raster: n,
            ..opts.clone()
        };
        let plan = dense_raster(scene, &o)?;
        if predict_coverage(scene, &plan, opts.raster).fraction() >= opts.coverage {
            return Ok(plan);
        }
    }
    dense_raster(scene, opts)
}

/// The coverage planner (greedy set cover over the raster candidates, see the module docs).
/// Angles left without targets are dropped, so the turntable does not stop there.
pub fn coverage_plan(scene: &PlanScene, opts: &PlanOptions) -> Result<ScanPlan, PlanError> {
    opts.validate()?;
    let angles = opts.angle_list();
    let cands = cover_sets(
        scene,
        &angles,
        &raster(scene, &angles, opts.raster),
        opts.target_mm,
    );
    if cands.sets.is_empty() {
        return Err(PlanError::NothingVisible);
    }
    let mut coverable = vec![0u64; cands.words];
    for (_, _, b) in &cands.sets {
        for (c, w) in coverable.iter_mut().zip(b) {
            *c |= w;
        }
    }
    let goal = (opts.coverage * count(&coverable) as f64).ceil() as usize;
    let mut covered = vec![0u64; cands.words];
    let mut chosen = vec![false; cands.sets.len()];
    // Lazy greedy: gains only shrink, so a stale upper bound that still wins is exact.
    let mut gains: Vec<usize> = cands.sets.iter().map(|(_, _, b)| count(b)).collect();
    let mut have = 0;
    while have < goal {
        let mut best = None;
        while let Some((k, _)) = gains
            .iter()
            .enumerate()
            .filter(|(k, _)| !chosen[*k])
            .max_by_key(|(k, g)| (**g, std::cmp::Reverse(*k)))
        {
            let fresh: usize = cands.sets[k]
                .2
                .iter()
                .zip(&covered)
                .map(|(b, c)| (b & !c).count_ones() as usize)
                .sum();
            if fresh == gains[k] {
                best = Some(k);
                break;
            }
            gains[k] = fresh;
        }
        let Some(k) = best.filter(|k| gains[*k] > 0) else {
            break;
        };
        chosen[k] = true;
        for (c, w) in covered.iter_mut().zip(&cands.sets[k].2) {
            *c |= w;
        }
        have = count(&covered);
    }
    // Keep the raster (serpentine) order within each angle.
    let mut per_angle: Vec<Vec<[u16; 2]>> = vec![Vec::new(); angles.len()];
    for (k, (ai, t, _)) in cands.sets.iter().enumerate() {
        if chosen[k] {
            per_angle[*ai].push(*t);
        }
    }
    Ok(new_plan(
        "coverage",
        opts,
        angles
            .into_iter()
            .zip(per_angle)
            .filter(|(_, t)| !t.is_empty())
            .map(|(turntable_deg, targets)| AnglePlan {
                turntable_deg,
                targets,
            })
            .collect(),
    ))
}

/// The rig's timing, from its capabilities and configuration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RigTiming {
    /// Turntable microsteps per revolution.
    pub steps_per_rev: u32,
    /// Turntable cruise speed (steps/s).
    pub max_speed_sps: f64,
    /// Turntable acceleration (steps/s²).
    pub accel_sps2: f64,
    /// Time homing takes (s).
    pub home_s: f64,
    /// Galvo settle time: `base + per_code · |jump|` (s), jump = the larger axis change.
    pub settle_base_s: f64,
    /// See `settle_base_s`.
    pub settle_per_code_s: f64,
    /// Fixed cost per capture on top of exposure and settle (trigger, laser switching, event).
    pub capture_overhead_s: f64,
    /// Minimum time between the starts of consecutive program captures.
    pub interval_s: f64,
    /// Camera read-out after each exposure (s): a program capture period is at least the
    /// exposure plus this (the rig refuses shorter intervals).
    #[serde(default)]
    pub readout_s: f64,
}

/// Time of a trapezoidal (or triangular) move of `steps` steps from rest to rest.
pub fn trapezoid_s(steps: u64, v: f64, a: f64) -> f64 {
    if steps == 0 || v <= 0.0 || a <= 0.0 {
        return 0.0;
    }
    let n = steps as f64;
    let ramp = v * v / a; // steps spent accelerating plus decelerating at full speed
    if n >= ramp {
        n / v + v / a
    } else {
        2.0 * (n / a).sqrt()
    }
}

/// A plan's expected duration, split by cause.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DurationEstimate {
    /// Homing.
    pub home_s: f64,
    /// Turntable moves.
    pub turntable_s: f64,
    /// Galvo settling.
    pub settle_s: f64,
    /// Exposures.
    pub exposure_s: f64,
    /// Per-capture overhead.
    pub overhead_s: f64,
    /// The dark frames a new scan takes first (one capture per exposure, every laser off).
    pub dark_s: f64,
}

impl DurationEstimate {
    /// Sum of all parts (s).
    pub fn total_s(&self) -> f64 {
        self.home_s
            + self.turntable_s
            + self.settle_s
            + self.exposure_s
            + self.overhead_s
            + self.dark_s
    }
}

/// Steps from 0 to the angle, as the rig rounds it.
pub fn angle_steps(deg: f64, steps_per_rev: u32) -> i64 {
    (deg / 360.0 * steps_per_rev as f64).round() as i64
}

/// Estimates how long the rig takes to run `plan` from `frame_from` on (galvo starts centred).
pub fn estimate_duration(plan: &ScanPlan, t: &RigTiming, frame_from: usize) -> DurationEstimate {
    let mut est = DurationEstimate {
        home_s: t.home_s,
        turntable_s: 0.0,
        settle_s: 0.0,
        exposure_s: 0.0,
        overhead_s: 0.0,
        dark_s: 0.0,
    };
    if frame_from == 0 {
        est.dark_s = plan
            .exposures_s
            .iter()
            .map(|e| t.interval_s.max(e + t.readout_s) + t.capture_overhead_s)
            .sum();
    }
    let mut pos = 0i64;
    let mut frame = 0usize;
    let brackets = plan.exposures_s.len() as f64;
    let exp: f64 = plan.exposures_s.iter().sum();
    for a in &plan.angles {
        let n = a.targets.len();
        if frame + n <= frame_from {
            frame += n;
            continue;
        }
        let target = angle_steps(a.turntable_deg, t.steps_per_rev);
        est.turntable_s += trapezoid_s(target.abs_diff(pos), t.max_speed_sps, t.accel_sps2);
        pos = target;
        let mut g: Option<[u16; 2]> = None;
        for &c in &a.targets {
            if frame >= frame_from {
                // Each bracket is one capture; the galvo jumps only before the first.
                let jump = g.map_or(t.settle_base_s, |p| {
                    t.settle_base_s
                        + t.settle_per_code_s * p[0].abs_diff(c[0]).max(p[1].abs_diff(c[1])) as f64
                });
                // A capture starts when the previous one is done and `interval` has passed since
                // the previous start.
                let settle = jump + (brackets - 1.0) * t.settle_base_s;
                est.settle_s += settle;
                est.exposure_s += exp;
                let busy = settle + exp;
                let period: f64 = plan
                    .exposures_s
                    .iter()
                    .map(|e| t.interval_s.max(e + t.readout_s))
                    .sum();
                est.overhead_s += brackets * t.capture_overhead_s + (period - busy).max(0.0);
                g = Some(c);
            }
            frame += 1;
        }
    }
    est
}

/// A plan saved by `subsurf plan --save`, checked to be of [`PLAN_FORMAT`].
pub fn load_plan(path: &std::path::Path) -> Result<ScanPlan, PlanError> {
    let shown = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| PlanError::Read {
        path: shown.clone(),
        source,
    })?;
    let plan: ScanPlan = serde_json::from_str(&text).map_err(|e| PlanError::NotAPlan {
        path: shown.clone(),
        why: e.to_string(),
    })?;
    if plan.format != PLAN_FORMAT {
        return Err(PlanError::NotAPlan {
            path: shown,
            why: format!("format {:?}", plan.format),
        });
    }
    Ok(plan)
}

/// What a plan will do, for a person: its frames, its expected duration by part and its
/// predicted coverage (`subsurf plan`).
pub fn describe(plan: &ScanPlan, scene: &PlanScene, raster: usize, t: &RigTiming) -> String {
    let cov = predict_coverage(scene, plan, raster);
    let est = estimate_duration(plan, t, 0);
    format!(
        "{} planner: {} frames at {} turntable angles, {} exposure(s) each\n\
         expected duration {:.1} s (homing {:.1}, turntable {:.1}, galvo settle {:.1}, exposure {:.1}, dark frames {:.1}, other {:.1})\n\
         predicted coverage: {} of {} coverable vertices ({:.1}%) have an x_i within {} mm; {} vertices in all",
        plan.planner,
        plan.frame_count(),
        plan.angles.len(),
        plan.exposures_s.len(),
        est.total_s(),
        est.home_s,
        est.turntable_s,
        est.settle_s,
        est.exposure_s,
        est.dark_s,
        est.overhead_s,
        cov.covered,
        cov.coverable,
        100.0 * cov.fraction(),
        plan.target_mm,
        cov.vertices,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A UV sphere of radius `r` centred at height `r`.
    pub(crate) fn sphere(r: f64, rings: usize, segs: usize) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let mut v = vec![[0.0, 0.0, 2.0 * r]];
        for i in 1..rings {
            let th = std::f64::consts::PI * i as f64 / rings as f64;
            for j in 0..segs {
                let ph = 2.0 * std::f64::consts::PI * j as f64 / segs as f64;
                v.push([
                    r * th.sin() * ph.cos(),
                    r * th.sin() * ph.sin(),
                    r + r * th.cos(),
                ]);
            }
        }
        v.push([0.0, 0.0, 0.0]);
        let last = (v.len() - 1) as u32;
        let mut t = Vec::new();
        let idx = |i: usize, j: usize| (1 + (i - 1) * segs + j % segs) as u32;
        for j in 0..segs {
            t.push([0, idx(1, j), idx(1, j + 1)]);
            t.push([last, idx(rings - 1, j + 1), idx(rings - 1, j)]);
        }
        for i in 1..rings - 1 {
            for j in 0..segs {
                t.push([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)]);
                t.push([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]);
            }
        }
        (v, t)
    }

    #[test]
    fn trapezoid_matches_kinematics() {
        // Triangular: 100 steps at a = 1e4 → t = 2 sqrt(100/1e4) = 0.2 s.
        assert!((trapezoid_s(100, 1e6, 1e4) - 0.2).abs() < 1e-12);
        // Trapezoidal: v = 1000, a = 1e4, n = 10000 → 10 + 0.1.
        assert!((trapezoid_s(10_000, 1000.0, 1e4) - 10.1).abs() < 1e-12);
        // Continuous at the switch-over point n = v²/a.
        let n = 100;
        assert!((trapezoid_s(n, 1000.0, 1e4) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn coverage_planner_halves_the_dense_raster() {
        let (v, t) = sphere(12.0, 14, 24);
        let scene = PlanScene::new(&v, &t, &Calibration::builtin()).unwrap();
        let opts = PlanOptions {
            angles: 6,
            raster: 16,
            target_mm: 5.0,
            ..PlanOptions::default()
        };
        for coverage in [0.9, 1.0] {
            let opts = PlanOptions {
                coverage,
                ..opts.clone()
            };
            let dense = dense_for_target(&scene, &opts).unwrap();
            let dc = predict_coverage(&scene, &dense, opts.raster);
            assert!(dc.coverable > v.len() / 3, "{dc:?}");
            assert!(dc.fraction() >= coverage);
            let cov = coverage_plan(&scene, &opts).unwrap();
            let cc = predict_coverage(&scene, &cov, opts.raster);
            eprintln!(
                "dense {} frames {dc:?}; coverage {} frames {cc:?}",
                dense.frame_count(),
                cov.frame_count()
            );
            assert!(cc.fraction() >= coverage);
            assert!(
                2 * cov.frame_count() <= dense.frame_count(),
                "coverage {} vs dense {}",
                cov.frame_count(),
                dense.frame_count()
            );
        }
    }

    #[test]
    fn nothing_to_see_is_an_error() {
        let (mut v, t) = sphere(5.0, 6, 8);
        for p in &mut v {
            p[2] += 5000.0; // far above the camera's view
        }
        let scene = PlanScene::new(&v, &t, &Calibration::builtin()).unwrap();
        let e = coverage_plan(&scene, &PlanOptions::default()).unwrap_err();
        assert!(matches!(e, PlanError::NothingVisible));
    }
}
