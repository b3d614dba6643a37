//! Stage `load` (section 5: "the acquired data"): the dataset's mesh prepared for ray casts
//! (BVH, adjacency), its cameras, and reading a frame's image as samples.
//!
//! Owns every read of a frame image; never keeps an image beyond the call that read it, so memory
//! does not grow with the frame count (frames are read again by later passes instead).
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use crate::dataset::{Dataset, DatasetError};
use crate::geometry::{Camera, CoverageMap, Scene, SurfacePoints, V3, Visible};
use crate::registration::{RegistrationOutcome, register_frame};
use crate::samples::{Sample, SampleCounts, frame_samples};

use super::register::RegisteredFrame;
use super::{PipelineError, PipelineOptions};

/// Visible vertices per (camera, turntable angle bits).
type VisCache = HashMap<(usize, u64), Arc<Vec<Visible>>>;

/// Coverage maps per (camera, turntable angle bits), with their total pixel count.
type CoverageCache = (HashMap<(usize, u64), Arc<CoverageMap>>, usize);

/// Pixels the coverage cache holds at most (4 bytes each: 256 MiB) before it starts over; the
/// scans in use (128 × 128, 12–64 views) stay far below.
const COVERAGE_PIXELS: usize = 1 << 26;

/// Shared state of one run: scene, cameras, cached visibility.
pub struct Context<'a> {
    /// The dataset.
    pub ds: &'a Dataset,
    /// Mesh with BVH.
    pub scene: Scene,
    cams: Vec<Camera>,
    vis: Mutex<VisCache>,
    cov: Mutex<CoverageCache>,
    /// Options.
    pub opts: PipelineOptions,
}

impl<'a> Context<'a> {
    /// Prepares the mesh and cameras of `ds`.
    pub fn new(ds: &'a Dataset, opts: PipelineOptions) -> Result<Context<'a>, PipelineError> {
        Ok(Context {
            ds,
            scene: Scene::new(ds.mesh.clone())?,
            cams: ds.spec.cameras.clone(),
            vis: Mutex::new(HashMap::new()),
            cov: Mutex::new((HashMap::new(), 0)),
            opts,
        })
    }

    /// The camera model of camera `k`.
    pub fn camera(&self, k: usize) -> &Camera {
        &self.cams[k]
    }

    /// Visible vertices of camera `cam` at turntable angle `deg` (cached: frames share angles).
    pub fn visible(&self, cam: usize, deg: f64) -> Arc<Vec<Visible>> {
        let key = (cam, deg.to_bits());
        if let Ok(m) = self.vis.lock()
            && let Some(v) = m.get(&key)
        {
            return v.clone();
        }
        let v = Arc::new(self.scene.visible_vertices(
            &self.cams[cam],
            deg,
            self.opts.samples.cos_min,
        ));
        if let Ok(mut m) = self.vis.lock() {
            if m.len() >= 256 {
                m.clear();
            }
            m.insert(key, v.clone());
        }
        v
    }

    /// The coverage map of camera `cam` at turntable angle `deg` ([`Scene::covers`]), one per
    /// view, shared by every frame of it (its pixels are cast once, on demand).
    pub fn coverage(&self, cam: usize, deg: f64) -> Arc<CoverageMap> {
        let key = (cam, deg.to_bits());
        let Ok(mut m) = self.cov.lock() else {
            return Arc::new(CoverageMap::new(
                &self.cams[cam],
                deg,
                self.opts.samples.cos_min,
            ));
        };
        if let Some(v) = m.0.get(&key) {
            return v.clone();
        }
        let map = Arc::new(CoverageMap::new(
            &self.cams[cam],
            deg,
            self.opts.samples.cos_min,
        ));
        if m.1 + map.pixels() > COVERAGE_PIXELS {
            m.0.clear();
            m.1 = 0;
        }
        m.1 += map.pixels();
        m.0.insert(key, map.clone());
        map
    }

    /// Registers frame `k`: reads its image, detects the spot, back-projects it (the `register`
    /// stage calls this; see [`super::register`]).
    pub fn register(&self, k: usize) -> Result<RegistrationOutcome, DatasetError> {
        let img = self.ds.read_frame(k)?;
        let f = &self.ds.spec.frames[k];
        Ok(register_frame(
            &img,
            f,
            &self.cams[f.camera],
            &self.scene,
            &self.opts.spot,
        ))
    }

    /// The samples of a registered frame (reads its image again; the spot is registration's).
    pub fn samples(
        &self,
        reg: &RegisteredFrame,
    ) -> Result<(Vec<Sample>, SampleCounts), DatasetError> {
        let img = self.ds.read_frame(reg.frame)?;
        let f = &self.ds.spec.frames[reg.frame];
        let vis = self.visible(f.camera, f.turntable_deg);
        let cov = self.coverage(f.camera, f.turntable_deg);
        Ok(frame_samples(
            &img,
            f,
            &vis,
            &self.ds.mesh.positions,
            reg.x_i,
            Some(&reg.spot),
            Some((&self.scene, &cov)),
            &self.opts.samples,
        ))
    }

    /// Surface points of `pts` the camera of frame `k` sees (the rule of [`Context::visible`]
    /// at each point: [`Scene::visible_points`]); not cached: the caller reads all frames of
    /// one view with it.
    pub fn visible_points(&self, pts: &SurfacePoints, k: usize) -> Vec<Visible> {
        let f = &self.ds.spec.frames[k];
        self.scene.visible_points(
            pts,
            &self.cams[f.camera],
            f.turntable_deg,
            self.opts.samples.cos_min,
        )
    }

    /// The samples of a registered frame at the surface points `pts` of which `visible` (from
    /// [`Context::visible_points`] for this frame's view) are seen, by the same rules as the
    /// vertices' ([`Context::samples`], `frame_samples`); `Sample::vertex` indexes `pts`.
    pub fn point_samples(
        &self,
        reg: &RegisteredFrame,
        pts: &SurfacePoints,
        visible: &[Visible],
    ) -> Result<(Vec<Sample>, SampleCounts), DatasetError> {
        let img = self.ds.read_frame(reg.frame)?;
        let f = &self.ds.spec.frames[reg.frame];
        let cov = self.coverage(f.camera, f.turntable_deg);
        Ok(frame_samples(
            &img,
            f,
            visible,
            &pts.positions,
            reg.x_i,
            Some(&reg.spot),
            Some((&self.scene, &cov)),
            &self.opts.samples,
        ))
    }

    /// Interpolated unit normal at a point of triangle `tri` ([`crate::geometry::Scene::normal_at`],
    /// the one interpolation: x_i's normal, which its tangent frame is built from); +z where it
    /// degenerates.
    pub fn normal_at(&self, tri: u32, p: V3) -> V3 {
        self.scene.normal_at(tri, p).unwrap_or([0.0, 0.0, 1.0])
    }
}
