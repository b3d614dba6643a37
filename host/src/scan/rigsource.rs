//! The rig and a camera as a [`FrameSource`]: a steered scan's batches captured by the scan
//! driver ([`super::driver`]), each batch one resumable run of the same dataset whose frame
//! order ([`ScanConfig::order`]) grows batch by batch.
//!
//! The candidates are the frames of a candidate plan (the dense raster: every target at every
//! angle), each with the x_i its laser ray is predicted to light ([`PlanScene::laser_hit`]).
use std::path::Path;

use super::adaptive::{AdaptiveError, Candidate, FrameSource};
use super::camera::Camera;
use super::driver::{FrameSink, Scan, ScanConfig, run_with_reconnect_into};
use super::plan::{PlanScene, RigTiming};
use crate::link::ByteLink;
use crate::progress::Progress;
use crate::rig::{RigClient, RigClientError};

/// Connects to the rig (again after a link failure).
pub type Connect<'a, L> = Box<dyn FnMut() -> Result<RigClient<L>, RigClientError> + 'a>;

/// Makes the frame sink of each batch's run (the sample store's extraction), if any.
pub type SinkFactory<'a> = Box<dyn FnMut() -> Option<Box<dyn FrameSink>> + 'a>;

/// The rig, a camera and a candidate plan, serving a steered scan.
pub struct RigSource<'a, L: ByteLink> {
    cfg: ScanConfig,
    cands: Vec<Candidate>,
    connect: Connect<'a, L>,
    camera: &'a mut dyn Camera,
    sink: SinkFactory<'a>,
    reconnects: u32,
    timing: RigTiming,
    done: usize,
    rig_s: f64,
}

impl<'a, L: ByteLink> RigSource<'a, L> {
    /// The candidate plan of `cfg` (its `order` is replaced batch by batch), predicted over
    /// `scene`, captured by `camera` over the rig `connect` reaches; `timing` is the rig's, for
    /// the learning curve's rig time. Opens (or resumes) the output dataset.
    pub fn new(
        mut cfg: ScanConfig,
        scene: &PlanScene,
        connect: Connect<'a, L>,
        camera: &'a mut dyn Camera,
        sink: SinkFactory<'a>,
        reconnects: u32,
        timing: RigTiming,
    ) -> Result<Self, AdaptiveError> {
        let cands = cfg
            .plan
            .frames()
            .iter()
            .enumerate()
            .map(|(i, f)| Candidate {
                id: i,
                turntable_deg: f.turntable_deg,
                galvo: Some(f.galvo),
                x_i: scene.laser_hit(f.turntable_deg, f.galvo),
            })
            .collect();
        cfg.order = Some(Vec::new());
        // Opening the dataset writes its identity, mesh and scan.json (the start batch reads
        // the mesh), and says how many frames an earlier run left.
        let done = Scan::open(&cfg, camera)?.done();
        Ok(RigSource {
            cfg,
            cands,
            connect,
            camera,
            sink,
            reconnects,
            timing,
            done,
            rig_s: 0.0,
        })
    }

    /// Rig time the runs of this process measured (s; the rig's clock, virtual on the simulated
    /// rig), homing of every batch's session included.
    pub fn measured_rig_s(&self) -> f64 {
        self.rig_s
    }
}

impl<L: ByteLink> FrameSource for RigSource<'_, L> {
    fn candidates(&self) -> &[Candidate] {
        &self.cands
    }
    fn dir(&self) -> &Path {
        &self.cfg.out
    }
    fn done(&self) -> usize {
        self.done
    }
    fn acquire(&mut self, order: &[usize], progress: &dyn Progress) -> Result<(), AdaptiveError> {
        self.cfg.order = Some(order.to_vec());
        let sink = (self.sink)();
        let s = run_with_reconnect_into(
            &self.cfg,
            &mut *self.connect,
            &mut *self.camera,
            progress,
            self.reconnects,
            sink,
        )?;
        self.done = s.frames_total;
        self.rig_s += s.rig_seconds;
        if let Some(Err(e)) = &s.sink {
            progress.println(&format!(
                "no sample store was kept for this batch ({e}): the fit reads the frames"
            ));
        }
        Ok(())
    }
    fn timing(&self) -> &RigTiming {
        &self.timing
    }
    fn exposures_s(&self) -> &[f64] {
        &self.cfg.plan.exposures_s
    }
    fn describe(&self) -> String {
        format!("rig, camera {}", self.camera.describe())
    }
}
