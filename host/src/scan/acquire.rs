//! One scan as `subsurf scan` runs it, once its plan, camera and configuration are made: the
//! rig reached (the simulated rig in virtual time, or a serial port, reconnecting), the frames
//! captured — in the plan's order, or steered by the adaptive planner — with the sample store
//! extracted as they arrive, the simulated material's ground truth, and the summary for the
//! user; or a recorded dataset replayed as the rig and camera (`--replay`). The command only
//! parses, plans and prints.
use std::path::Path;

use super::adaptive::{
    AcquisitionReport, AdaptiveError, AdaptiveSettings, FrameSource, cover_order, run_adaptive,
    run_fixed,
};
use super::camera::Camera;
use super::driver::{FrameSink, ScanConfig, ScanError, run_with_reconnect_into};
use super::plan::{PlanError, PlanScene, RigTiming, estimate_duration};
use super::replay::{Replay, ReplayError};
use super::rigsource::{Connect, RigSource, SinkFactory};
use super::setup::{GROUND_TRUTH_FILE, rig_timing, write_ground_truth_of};
use crate::calib::Calibration;
use crate::dataset::Mesh;
use crate::link::{ByteLink, SerialLink};
use crate::progress::Progress;
use crate::rig::{ClientConfig, RigClient};
use crate::simulate::Field;

/// Where the rig is.
#[derive(Debug, Clone)]
pub enum RigAt {
    /// The simulated rig in this process (virtual time).
    Sim,
    /// A serial port.
    Serial {
        /// The port.
        port: String,
        /// Baud rate.
        baud: u32,
    },
}

/// How frames are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Order {
    /// Every candidate, in order.
    Dense,
    /// The coverage planner's order.
    Coverage,
    /// Steered by the adaptive planner.
    Adaptive,
}

/// The scan's settings beyond its [`ScanConfig`] (the command's flags).
pub struct AcquireSettings<'a> {
    /// Where the rig is.
    pub rig: RigAt,
    /// Reconnection attempts after the link fails.
    pub reconnects: u32,
    /// The simulated camera's material, whose ground truth is written beside the scan.
    pub material: Option<&'a Field>,
    /// Memory for the sample store (MiB).
    pub memory: u64,
    /// Do not extract the frames' samples as they arrive.
    pub no_store: bool,
    /// Steer the scan with these settings and this timing model (the adaptive planner without
    /// a fixed plan); `None`: the plan's frames in order.
    pub steer: Option<(AdaptiveSettings, RigTiming)>,
    /// The noise floor the user gave (`--noise-floor`), for the dark frames' summary.
    pub noise_floor: Option<f64>,
}

/// Why the scan stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AcquireError {
    /// Stopped by the user (Ctrl-C): the journal is consistent and the scan resumes.
    #[error(transparent)]
    Interrupted(ScanError),
    /// The flags do not allow the scan.
    #[error("{0}")]
    Invalid(String),
    /// A step failed; `what` names it, `source` says why.
    #[error("{what}")]
    Step {
        /// The step (e.g. `scan into out/ stopped`).
        what: String,
        /// Why.
        #[source]
        source: Box<AcquireError>,
    },
    /// The scan failed.
    #[error(transparent)]
    Scan(#[from] ScanError),
    /// The steered scan failed.
    #[error(transparent)]
    Adaptive(#[from] AdaptiveError),
    /// The scene could not be built.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The replay could not be set up.
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// The ground truth could not be written.
    #[error(transparent)]
    Model(#[from] crate::modelfile::ModelFileError),
}

/// Names the step that failed, as `anyhow::Context` does in the binary.
fn step(what: String) -> impl FnOnce(AcquireError) -> AcquireError {
    move |e| AcquireError::Step {
        what,
        source: Box::new(e),
    }
}

/// What the user reads at the end of a steered scan.
fn report(rep: &AcquisitionReport, out: &Path) -> Vec<String> {
    let mut lines = vec![format!(
        "{} planner: {} frames in {}; {}",
        rep.planner,
        rep.order().len(),
        out.display(),
        rep.stopped.as_deref().unwrap_or("not finished")
    )];
    if !rep.curve.is_empty() {
        lines.push(format!(
            "learning curve and frame order in {}",
            out.join(super::adaptive::REPORT_FILE).display()
        ));
    }
    lines
}

/// `--replay`: the recorded dataset `src` (minus `exclude`) as the rig and camera, into `out`,
/// its frames chosen by `order`; `say` prints the learning curve as it goes. Returns the
/// lines for the end.
#[allow(clippy::too_many_arguments)]
pub fn replay(
    src: &Path,
    out: &Path,
    exclude: &[usize],
    order: Order,
    adaptive: &AdaptiveSettings,
    target_mm: f64,
    progress: &dyn Progress,
    say: &mut dyn FnMut(&str),
) -> Result<Vec<String>, AcquireError> {
    let mut source = Replay::open(src, out, exclude)
        .map_err(AcquireError::from)
        .map_err(step(format!(
            "cannot replay {} into {}",
            src.display(),
            out.display()
        )))?;
    let rep = match order {
        Order::Adaptive => run_adaptive(&mut source, adaptive, progress, &mut |p| say(&p.line()))?,
        Order::Dense => {
            let order: Vec<usize> = source.candidates().iter().map(|c| c.id).collect();
            run_fixed(&mut source, "dense", &order, progress)?
        }
        Order::Coverage => {
            let order = cover_order(
                source.candidates(),
                &source.recorded().mesh.positions,
                target_mm,
            );
            run_fixed(&mut source, "coverage", &order, progress)?
        }
    };
    Ok(report(&rep, out))
}

/// The ground truth of the simulated camera's material beside the scan.
fn ground_truth(mesh: &Mesh, field: Option<&Field>, out: &Path) -> Result<(), AcquireError> {
    if let Some(field) = field {
        write_ground_truth_of(mesh, field, out)
            .map_err(AcquireError::from)
            .map_err(step(format!(
                "cannot write {}",
                out.join(GROUND_TRUTH_FILE).display()
            )))?;
    }
    Ok(())
}

/// Runs the scan `cfg` of `mesh` (seen through `calib`) with `camera`; `say` prints the
/// learning curve of a steered scan as it goes. Returns the lines for the end: what was
/// captured, the rig time, the dark frames, the sample store.
pub fn acquire(
    cfg: ScanConfig,
    mesh: &Mesh,
    calib: &Calibration,
    camera: &mut dyn Camera,
    s: &AcquireSettings,
    progress: &dyn Progress,
    say: &mut dyn FnMut(&str),
) -> Result<Vec<String>, AcquireError> {
    // Each frame is registered and sampled as it arrives, into the sample store `subsurf fit`
    // starts from (`pipeline::extract::ScanExtraction`).
    let memory = s.memory;
    let no_store = s.no_store;
    let sink = move || -> Option<Box<dyn FrameSink>> {
        (!no_store).then(|| {
            Box::new(crate::pipeline::extract::ScanExtraction::new(
                crate::pipeline::StoreOptions {
                    budget: usize::try_from(memory.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
                    cache: crate::pipeline::Cache::Dataset,
                },
            )) as Box<dyn FrameSink>
        })
    };
    if let Some((settings, timing)) = &s.steer {
        let out = cfg.out.clone();
        let scene = PlanScene::new(&mesh.positions, &mesh.triangles, calib)?;
        let (rep, measured) = match &s.rig {
            RigAt::Sim => {
                let connect = Box::new(|| {
                    let link = crate::sim::SimLink::clean(crate::sim::VirtualRig::new(
                        crate::sim::SimParams::default(),
                    ));
                    RigClient::connect_with_seq(link, ClientConfig::default(), 1)
                });
                let sink = Box::new(sink);
                steer(
                    cfg, &scene, connect, camera, sink, s, settings, *timing, progress, say,
                )?
            }
            RigAt::Serial { port, baud } => {
                let (port, baud) = (port.clone(), *baud);
                let connect = Box::new(move || {
                    let link = SerialLink::open(&port, baud)?;
                    RigClient::connect(link, ClientConfig::default())
                });
                let sink = Box::new(sink);
                steer(
                    cfg, &scene, connect, camera, sink, s, settings, *timing, progress, say,
                )?
            }
        };
        ground_truth(mesh, s.material, &out)?;
        let mut lines = report(&rep, &out);
        lines.push(format!(
            "rig time measured by this run: {measured:.2} s (homing of every batch included)"
        ));
        return Ok(lines);
    }
    let result = match &s.rig {
        RigAt::Sim => {
            let mut connect = || {
                let link = crate::sim::SimLink::clean(crate::sim::VirtualRig::new(
                    crate::sim::SimParams::default(),
                ));
                RigClient::connect_with_seq(link, ClientConfig::default(), 1)
            };
            run_with_reconnect_into(&cfg, &mut connect, camera, progress, s.reconnects, sink())
        }
        RigAt::Serial { port, baud } => {
            let mut connect = || {
                let link = SerialLink::open(port, *baud)?;
                RigClient::connect(link, ClientConfig::default())
            };
            run_with_reconnect_into(&cfg, &mut connect, camera, progress, s.reconnects, sink())
        }
    };
    let s_ = match result {
        Ok(summary) => summary,
        Err(e @ ScanError::Interrupted { .. }) => return Err(AcquireError::Interrupted(e)),
        Err(e) => {
            return Err(step(format!("scan into {} stopped", cfg.out.display()))(
                AcquireError::Scan(e),
            ));
        }
    };
    // The simulated camera's material is known: write it as the floor to compare fitted
    // models with.
    ground_truth(mesh, s.material, &cfg.out)?;
    let p = subsurf_firmware::sim::SimParams::default();
    let t = rig_timing(&p.profile, cfg.move_speed, cfg.move_accel, cfg.interval_us);
    let est = estimate_duration(&cfg.plan, &t, s_.resumed_from);
    let mut lines = vec![format!(
        "scan complete: {} frames in {} ({} written now, {} were already done); rig time \
         {:.2} s (planned {:.2} s), wall {:.1} s, {} reconnects, {} camera retries",
        s_.frames_total,
        s_.scan_json.display(),
        s_.frames_written,
        s_.resumed_from,
        s_.rig_seconds,
        est.total_s(),
        s_.wall_seconds,
        s_.reconnects,
        s_.camera_retries
    )];
    lines.extend(super::dark::summary(
        &s_.dark_frames,
        s_.noise_floor,
        s.noise_floor,
    ));
    match &s_.sink {
        Some(Ok(m)) => lines.push(m.clone()),
        Some(Err(e)) => lines.push(format!(
            "no sample store was kept ({e}): the first `subsurf fit` reads the frames"
        )),
        None => {}
    }
    Ok(lines)
}

/// A steered scan over the rig `connect` reaches: the adaptive planner's loop with the rig and
/// camera as its frame source; the report and the rig time it measured.
#[allow(clippy::too_many_arguments)]
fn steer<'a, L: ByteLink>(
    cfg: ScanConfig,
    scene: &PlanScene,
    connect: Connect<'a, L>,
    camera: &'a mut dyn Camera,
    sink: SinkFactory<'a>,
    s: &AcquireSettings,
    settings: &AdaptiveSettings,
    timing: RigTiming,
    progress: &dyn Progress,
    say: &mut dyn FnMut(&str),
) -> Result<(AcquisitionReport, f64), AcquireError> {
    let out = cfg.out.clone();
    let mut source = RigSource::new(cfg, scene, connect, camera, sink, s.reconnects, timing)
        .map_err(AcquireError::from)
        .map_err(step(format!("cannot open {}", out.display())))?;
    let rep = run_adaptive(&mut source, settings, progress, &mut |p| say(&p.line()));
    match rep {
        Ok(rep) => Ok((rep, source.measured_rig_s())),
        Err(AdaptiveError::Scan(e @ ScanError::Interrupted { .. })) => {
            Err(AcquireError::Interrupted(e))
        }
        Err(e) => Err(
            step(format!("steered scan into {} stopped", out.display()))(AcquireError::Adaptive(e)),
        ),
    }
}
