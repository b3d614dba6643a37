//! Stage `load` (section 5: "the acquired data"): the dataset's mesh prepared for ray casts
//! (BVH, adjacency), its cameras, the sample store of the run ([`super::extract`]) and reading a
//! frame's image as samples.
//!
//! Owns every read of a frame image; never keeps an image beyond the call that read it. With a
//! store ([`Context::with_store`]) a frame it holds is never read again: its registration and
//! samples come from the store.
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use crate::dataset::{Dataset, DatasetError, FrameSpec};
use crate::geometry::{Camera, CoverageMap, Scene, SurfacePoints, V3, Visible};
use crate::samples::{SampleCounts, frame_samples};
use crate::spot::RegistrationOutcome;
use crate::store::{FrameSamples, PointSet, SampleStore, StoreError, StorePoints};

use super::register::RegisteredFrame;
use super::{PipelineError, PipelineOptions};

/// Visible vertices per (camera, turntable angle bits).
type VisCache = HashMap<(usize, u64), Arc<Vec<Visible>>>;

/// Coverage maps per (camera, turntable angle bits), with their total pixel count.
type CoverageCache = (HashMap<(usize, u64), Arc<CoverageMap>>, usize);

/// Pixels the coverage cache holds at most (4 bytes each: 256 MiB) before it starts over; the
/// scans in use (128 × 128, 12–64 views) stay far below.
const COVERAGE_PIXELS: usize = 1 << 26;

/// Why a frame's samples could not be had.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SamplesError {
    /// Its image could not be read.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// The store could not give them (a spilled frame's file).
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Shared state of one run: scene, cameras, cached visibility, the sample store. Cheap to
/// derive for other fit settings ([`Context::with_options`]): the scene, caches and store are
/// shared.
pub struct Context<'a> {
    /// The dataset.
    pub ds: &'a Dataset,
    /// Mesh with BVH.
    pub scene: Arc<Scene>,
    cams: Arc<Vec<Camera>>,
    vis: Arc<Mutex<VisCache>>,
    cov: Arc<Mutex<CoverageCache>>,
    store: Option<Arc<SampleStore>>,
    /// Options.
    pub opts: PipelineOptions,
}

impl<'a> Context<'a> {
    /// Prepares the mesh and cameras of `ds`.
    pub fn new(ds: &'a Dataset, opts: PipelineOptions) -> Result<Context<'a>, PipelineError> {
        Ok(Context {
            ds,
            scene: Arc::new(Scene::new(ds.mesh.clone())?),
            cams: Arc::new(ds.spec.cameras.clone()),
            vis: Arc::new(Mutex::new(HashMap::new())),
            cov: Arc::new(Mutex::new((HashMap::new(), 0))),
            store: None,
            opts,
        })
    }

    /// This context with the sample store `store`: the frames it holds are never read again.
    pub fn with_store(mut self, store: SampleStore) -> Context<'a> {
        self.store = Some(Arc::new(store));
        self
    }

    /// The run's sample store, if it has one.
    pub fn store(&self) -> Option<&SampleStore> {
        self.store.as_deref()
    }

    /// The same run (scene, caches, store) with other fit settings. The extraction settings
    /// (spot detection, sample rules) cannot change: the store and the visibility caches were
    /// made with them.
    pub fn with_options(&self, opts: PipelineOptions) -> Result<Context<'a>, PipelineError> {
        if opts.spot != self.opts.spot || opts.samples != self.opts.samples {
            return Err(PipelineError::Invalid(
                "a derived run must keep the extraction settings of its store".into(),
            ));
        }
        Ok(Context {
            ds: self.ds,
            scene: self.scene.clone(),
            cams: self.cams.clone(),
            vis: self.vis.clone(),
            cov: self.cov.clone(),
            store: self.store.clone(),
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
    ///
    /// With a store that holds frame `k`, its outcome is the store's (the image is not read).
    /// The error is why the image could not be read.
    pub fn register(&self, k: usize) -> Result<RegistrationOutcome, String> {
        if let Some(r) = self.store().and_then(|s| s.record(k)) {
            return r.outcome.clone();
        }
        let img = self.ds.read_frame(k).map_err(|e| e.to_string())?;
        Ok(self.register_image(&img, &self.ds.spec.frames[k]).0)
    }

    /// Registers the frame `f` (its `scan.json` entry) from its image `img` (the rule of
    /// [`Context::register`]), with the spot detected in it
    /// ([`crate::spot::register_frame_detected`]).
    pub fn register_image(
        &self,
        img: &crate::dataset::Image,
        f: &FrameSpec,
    ) -> (RegistrationOutcome, Option<crate::spot::Spot>) {
        crate::spot::register_frame_detected(
            img,
            f,
            &self.cams[f.camera],
            &self.scene,
            &self.opts.spot,
        )
    }

    /// The samples of a registered frame at the vertices: from the store when it holds the
    /// frame, else read from its image (the spot is registration's).
    pub fn samples(&self, reg: &RegisteredFrame) -> Result<FrameSamples, SamplesError> {
        if let Some(store) = self.store()
            && store.record(reg.frame).is_some()
        {
            return Ok(store
                .samples(reg.frame, PointSet::Vertices)?
                .unwrap_or_default());
        }
        let img = self.ds.read_frame(reg.frame)?;
        let f = &self.ds.spec.frames[reg.frame];
        let (samples, counts) = self.vertex_samples(&img, f, reg.x_i, &reg.spot);
        Ok(FrameSamples {
            samples: Arc::new(samples),
            counts,
        })
    }

    /// Samples of the image `img` of frame `f` (its `scan.json` entry) at the vertices it sees,
    /// with light at `x_i` and the laser spot `spot` ([`frame_samples`] with this run's rules).
    pub fn vertex_samples(
        &self,
        img: &crate::dataset::Image,
        f: &FrameSpec,
        x_i: V3,
        spot: &crate::spot::Spot,
    ) -> (Vec<crate::samples::Sample>, SampleCounts) {
        let vis = self.visible(f.camera, f.turntable_deg);
        let cov = self.coverage(f.camera, f.turntable_deg);
        frame_samples(
            img,
            f,
            &vis,
            &self.ds.mesh.positions,
            x_i,
            Some(spot),
            Some((&self.scene, &cov)),
            &self.opts.samples,
        )
    }

    /// Samples of the image `img` of frame `f` at the store's lattice points `pts` of which
    /// `visible` are seen (by the vertices' rules, [`Context::vertex_samples`]), those the
    /// store keeps (above [`StorePoints::min_value`]); `Sample::vertex` indexes `pts.points`.
    /// The counts are of every visible point.
    pub fn surface_samples(
        &self,
        img: &crate::dataset::Image,
        f: &FrameSpec,
        x_i: V3,
        spot: &crate::spot::Spot,
        pts: &StorePoints,
        visible: &[Visible],
    ) -> (Vec<crate::samples::Sample>, SampleCounts) {
        let cov = self.coverage(f.camera, f.turntable_deg);
        crate::samples::frame_samples_above(
            img,
            f,
            visible,
            &pts.points.positions,
            x_i,
            Some(spot),
            Some((&self.scene, &cov)),
            &self.opts.samples,
            pts.min_value,
        )
    }

    /// The samples of a registered frame at the store's lattice points
    /// ([`crate::store::SampleStore::points`]); `None` without a store, or a lattice in it.
    pub fn lattice_samples(
        &self,
        reg: &RegisteredFrame,
    ) -> Result<Option<FrameSamples>, SamplesError> {
        match self.store() {
            Some(s) if s.points().is_some() => Ok(s.samples(reg.frame, PointSet::Lattice)?),
            _ => Ok(None),
        }
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

    /// Interpolated unit normal at a point of triangle `tri` ([`crate::geometry::Scene::normal_at`],
    /// the one interpolation: x_i's normal, which its tangent frame is built from); +z where it
    /// degenerates.
    pub fn normal_at(&self, tri: u32, p: V3) -> V3 {
        self.scene.normal_at(tri, p).unwrap_or([0.0, 0.0, 1.0])
    }
}
