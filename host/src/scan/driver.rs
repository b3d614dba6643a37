//! The scan driver: home, then per turntable angle run the rig's queued capture program, collect
//! each triggered image from the camera, and commit it to the dataset (see [`crate::dataset::DatasetWriter`]).
//!
//! Faults: a link error ends the session with [`ScanError::Link`] (the caller reconnects and
//! calls again: [`run_with_reconnect`] does that with back-off), a rig halt (emergency stop,
//! interlock) with [`ScanError::RigHalted`], a camera that keeps timing out with
//! [`ScanError::Camera`], a full disk with [`ScanError::Journal`]. Every session ends with the
//! laser off (`Stop`, best effort when the link is gone — the rig's heartbeat timeout covers that)
//! and leaves a dataset the same command resumes.

use super::camera::{Camera, CameraError, Shot, Timing};
use super::plan::{ScanPlan, angle_steps};
use crate::calib::Calibration;
use crate::dataset::{Bracket, MergeOptions, merge_hdr};
use crate::dataset::{
    DarkFrame, DatasetWriter, FrameSpec, Image, LaserRay, STATE_DIR, ScanSpec, WriteError,
    encode_exr, write_atomic,
};
use crate::link::ByteLink;
use crate::progress::Progress;
use crate::rig::{RigClient, RigClientError};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use subsurf_protocol::{DarkCapture, GalvoPoint, MoveTarget, ProgramHeader};

/// Why a scan stopped. Every variant leaves a dataset the same command resumes.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ScanError {
    /// The link to the rig failed (after retries in the rig client).
    #[error("lost the rig")]
    Link(#[source] RigClientError),
    /// The rig refused something or reported a fault; the message says what.
    #[error("the rig refused or failed")]
    Rig(#[source] RigClientError),
    /// The rig halted the scan itself (emergency stop, interlock, homing failure).
    #[error(
        "the rig halted the scan at frame {frame}: {reason}; the laser is off. Fix the cause, then \
         run the same command again to resume"
    )]
    RigHalted {
        /// First frame not written.
        frame: usize,
        /// The rig's reason.
        reason: String,
    },
    /// The camera gave no usable image for a frame, even after retries.
    #[error("frame {frame} failed after {attempts} attempts: {source}")]
    Camera {
        /// The frame.
        frame: usize,
        /// Attempts made.
        attempts: u32,
        /// The last camera error.
        source: CameraError,
    },
    /// Merging or encoding an image failed.
    #[error("frame {frame}: {message}")]
    Image {
        /// The frame.
        frame: usize,
        /// What went wrong.
        message: String,
    },
    /// Writing the dataset failed (disk full, permissions, another scan in the directory).
    #[error(transparent)]
    Journal(#[from] WriteError),
    /// The plan does not fit the rig.
    #[error("the plan does not fit the rig: {0}")]
    Plan(String),
    /// The camera's exposure count does not match the rig's captures (a missed trigger, an
    /// extra exposure, or an exposure the laser did not cover): images would land on the wrong
    /// galvo points, so the scan stops; the frames before are kept.
    #[error(
        "frame {frame}: {message}; the scan stopped with the laser off and every frame before it \
         kept. Check the camera trigger and exposure-active wiring, its read-out time and the rig \
         profile (`subsurf rig profile`), then run the same command again to resume"
    )]
    CaptureMismatch {
        /// The frame whose capture did not match.
        frame: usize,
        /// What did not match.
        message: String,
    },
    /// A dark frame measured nothing (no finite pixels).
    #[error("dark frame at {exposure_s} s: {message}")]
    Dark {
        /// Its exposure.
        exposure_s: f64,
        /// Why.
        message: String,
    },
    /// Stopped on request (Ctrl-C); the laser is off.
    #[error("stopped on request after frame {done} of {total}; run the same command to resume")]
    Interrupted {
        /// Frames complete.
        done: usize,
        /// Frames planned.
        total: usize,
    },
}

impl ScanError {
    /// Whether reconnecting and calling again can help (a link or timeout problem).
    pub fn is_link(&self) -> bool {
        matches!(self, ScanError::Link(_))
    }
}

fn classify(e: RigClientError) -> ScanError {
    match e {
        // A rig that reset is reached again like a lost one: a new session homes and resumes.
        RigClientError::Link(_)
        | RigClientError::NoReply { .. }
        | RigClientError::Rebooted { .. } => ScanError::Link(e),
        e => ScanError::Rig(e),
    }
}

/// What to scan and how.
#[derive(Debug, Clone)]
pub struct ScanConfig {
    /// Output dataset directory.
    pub out: PathBuf,
    /// The plan.
    pub plan: ScanPlan,
    /// The rig's calibration (camera, galvo).
    pub calib: Calibration,
    /// The object mesh as OBJ text (copied into the dataset as `object.obj`).
    pub mesh_obj: Vec<u8>,
    /// `noise_floor` written to `scan.json` as given (`--noise-floor`, or the `sim` camera's
    /// own); `None`: the one the dark frames measure ([`super::dark`]), or none without them.
    pub noise_floor: Option<f64>,
    /// Take the dark frames (one per exposure, every laser off) before the first frame.
    pub dark_frames: bool,
    /// Laser channel index on the rig.
    pub laser_channel: u8,
    /// Turntable speed (steps/s) and acceleration (steps/s²); `None` = the rig's maximum.
    pub move_speed: Option<u32>,
    /// See `move_speed`.
    pub move_accel: Option<u32>,
    /// Camera trigger pulse (µs).
    pub trigger_us: u32,
    /// Minimum time between capture starts, µs; never less than the exposure plus the rig
    /// profile's camera read-out (0 = exactly that).
    pub interval_us: u32,
    /// Most points per uploaded program (bounds memory for HDR brackets).
    pub chunk_points: usize,
    /// How often a frame's capture is retried when the camera gives nothing.
    pub camera_retries: u32,
    /// Bytes kept free on the disk.
    pub reserve_bytes: u64,
    /// Set to stop cleanly (Ctrl-C).
    pub stop: Arc<AtomicBool>,
    /// The frames of `plan` to capture, by index among [`ScanPlan::frames`], in this order
    /// (`None`: every planned frame in plan order). A steered scan
    /// ([`super::adaptive`]) grows it batch by batch; it is not part of the scan's identity, so
    /// each batch resumes the same dataset.
    pub order: Option<Vec<usize>>,
}

impl ScanConfig {
    /// Sensible defaults for `plan` and `calib`.
    pub fn new(out: PathBuf, plan: ScanPlan, calib: Calibration, mesh_obj: Vec<u8>) -> Self {
        ScanConfig {
            out,
            plan,
            calib,
            mesh_obj,
            noise_floor: None,
            dark_frames: true,
            laser_channel: 0,
            move_speed: None,
            move_accel: None,
            trigger_us: 100,
            interval_us: 0,
            chunk_points: 64,
            camera_retries: 2,
            reserve_bytes: 16 << 20,
            stop: Arc::new(AtomicBool::new(false)),
            order: None,
        }
    }

    /// The string that identifies this scan in its directory (resume refuses any other).
    pub fn identity(&self, camera: &str) -> String {
        let id = serde_json::json!({
            "plan": self.plan,
            "calib": self.calib,
            "noise_floor": self.noise_floor,
            "laser_channel": self.laser_channel,
            "camera": camera,
            "steered": self.order.is_some(),
            "mesh_crc32": crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(&self.mesh_obj),
        });
        serde_json::to_string_pretty(&id).unwrap_or_default()
    }
}

/// What a scan did.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanSummary {
    /// The dataset's `scan.json`.
    pub scan_json: PathBuf,
    /// Frames in the plan.
    pub frames_total: usize,
    /// Frames that were already complete when this run started.
    pub resumed_from: usize,
    /// Frames written by this run.
    pub frames_written: usize,
    /// Rig clock time the scan took (virtual on the simulated rig), summed over sessions.
    pub rig_seconds: f64,
    /// Wall-clock time.
    pub wall_seconds: f64,
    /// Reconnections after link failures.
    pub reconnects: u32,
    /// Camera retries.
    pub camera_retries: u32,
    /// What the frame sink said at the end, if the scan had one ([`FrameSink::finish`]).
    pub sink: Option<Result<String, String>>,
    /// The dark frames and what they measured (empty when none were taken).
    pub dark_frames: Vec<DarkFrame>,
    /// The `noise_floor` written to `scan.json`.
    pub noise_floor: Option<f64>,
}

/// The raw level at which the frames a scan writes are clipped, for `scan.json`: the camera's
/// own for single exposures; for merged brackets (written with exposure 1) the level a pixel
/// clipped in every bracket is given by [`merge_hdr`] (at least 98 % of saturation over the
/// shortest exposure). `None` when the camera never clips.
pub fn frame_saturation(camera_saturation: f32, exposures_s: &[f64]) -> Option<f64> {
    let sat = camera_saturation as f64;
    if !(sat.is_finite() && sat > 0.0) {
        return None;
    }
    if exposures_s.len() <= 1 {
        return Some(sat);
    }
    let shortest = exposures_s.iter().copied().fold(f64::INFINITY, f64::min);
    (shortest.is_finite() && shortest > 0.0).then(|| 0.98 * sat / shortest)
}

/// Receives each frame as it is committed, while the scan goes on: processing that can start
/// before the scan ends (the sample store's extraction, `pipeline::extract::ScanExtraction`,
/// which `subsurf scan` attaches). A sink never fails the scan: what it cannot do it reports at
/// the end.
pub trait FrameSink {
    /// The scan (its dataset at `dir`, `scan.json`'s header `header`, `frames` planned frames seen
    /// from the views `views`: camera, turntable angle) starts or resumes.
    fn begin(&mut self, dir: &Path, header: &ScanSpec, frames: usize, views: &[(usize, f64)]);
    /// Frame `k` is committed with its `scan.json` entry and its image as written.
    fn frame(&mut self, k: usize, entry: &FrameSpec, image: Image);
    /// Every frame is committed and `scan.json` written: what the sink has to say.
    fn finish(&mut self) -> Result<String, String>;
}

/// A frame sink and the views (camera, turntable angle) it is to begin with.
type PendingSink = (Box<dyn FrameSink>, Vec<(usize, f64)>);

/// An open scan: the dataset writer and the plan, across rig sessions.
pub struct Scan<'a> {
    cfg: &'a ScanConfig,
    writer: DatasetWriter,
    sink: Option<Box<dyn FrameSink>>,
    /// A sink not yet begun, with its views: it begins once the header is final (after the
    /// dark frames set the noise floor), so it extracts what a later `subsurf fit` reads.
    pending_sink: Option<PendingSink>,
    /// The dark frames taken (this run or a resumed one's, from the scan's state).
    dark: Vec<DarkFrame>,
    /// The dark level of each exposure, subtracted from every lit frame before it is merged and
    /// written ([`super::dark::measure_pair`]).
    dark_levels: Vec<(f64, super::dark::DarkLevel)>,
    frames: Vec<super::plan::PlannedFrame>,
    resumed_from: usize,
    written: usize,
    rig_us: u64,
    retries: u32,
    started: Instant,
}

impl<'a> Scan<'a> {
    /// Opens (or resumes) the dataset for `cfg` scanned with `camera`.
    pub fn open(cfg: &'a ScanConfig, camera: &dyn Camera) -> Result<Self, ScanError> {
        if cfg.plan.exposures_s.is_empty() {
            return Err(ScanError::Plan("no exposure times".into()));
        }
        let header = ScanSpec::new(
            vec![cfg.calib.camera.clone()],
            cfg.noise_floor,
            frame_saturation(camera.saturation(), &cfg.plan.exposures_s),
        );
        let (mut writer, done) = DatasetWriter::open(
            &cfg.out,
            &cfg.identity(&camera.describe()),
            header,
            &cfg.mesh_obj,
        )?;
        writer.reserve_bytes = cfg.reserve_bytes;
        // Dark frames a killed run took already are not taken again.
        let dark: Vec<DarkFrame> = std::fs::read(dark_state(&cfg.out))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default();
        if !dark.is_empty() {
            writer.set_dark_frames(
                dark.clone(),
                cfg.noise_floor.or(super::dark::floor_of(&dark)),
            )?;
        }
        let dark_levels =
            super::dark::levels_of(&cfg.out, &dark).map_err(|message| ScanError::Dark {
                exposure_s: 0.0,
                message: format!("reading the dark level back: {message}"),
            })?;
        let all = cfg.plan.frames();
        let frames = match &cfg.order {
            None => all,
            Some(order) => order
                .iter()
                .map(|&i| {
                    all.get(i).copied().ok_or_else(|| {
                        ScanError::Plan(format!("frame {i} asked for, the plan has {}", all.len()))
                    })
                })
                .collect::<Result<Vec<_>, _>>()?,
        };
        Ok(Scan {
            cfg,
            writer,
            sink: None,
            pending_sink: None,
            dark,
            dark_levels,
            frames,
            resumed_from: done,
            written: 0,
            rig_us: 0,
            retries: 0,
            started: Instant::now(),
        })
    }

    /// Frames complete.
    pub fn done(&self) -> usize {
        self.writer.done()
    }

    /// Hands every frame committed from now on to `sink` as well ([`FrameSink`]); it begins
    /// once the dark frames are taken.
    pub fn with_sink(mut self, sink: Box<dyn FrameSink>) -> Self {
        let mut views: Vec<(usize, f64)> = Vec::new();
        for f in &self.frames {
            if !views
                .iter()
                .any(|v| v.1.to_bits() == f.turntable_deg.to_bits())
            {
                views.push((0, f.turntable_deg));
            }
        }
        self.pending_sink = Some((sink, views));
        self
    }

    /// Begins the sink, if one waits: the header is final.
    fn begin_sink(&mut self) {
        if let Some((mut sink, views)) = self.pending_sink.take() {
            sink.begin(
                &self.cfg.out,
                self.writer.header(),
                self.frames.len(),
                &views,
            );
            self.sink = Some(sink);
        }
    }

    /// Whether the dark frames still have to be taken.
    fn dark_pending(&self) -> bool {
        self.cfg.dark_frames && self.dark.is_empty()
    }

    /// One dark frame per exposure (every laser off), their statistics, and the header's noise
    /// floor from them (unless given): see [`super::dark`]. Kept in the scan's state, so a
    /// resumed scan does not take them again.
    fn take_dark_frames<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        progress: &dyn Progress,
        exposures_us: &[u32],
    ) -> Result<(), ScanError> {
        progress.set_message("dark frames (laser off)");
        let dir = self.cfg.out.join("dark");
        std::fs::create_dir_all(&dir).map_err(|e| {
            ScanError::Journal(WriteError::Io {
                path: dir.display().to_string(),
                source: e,
            })
        })?;
        let mut dark = Vec::with_capacity(exposures_us.len());
        let mut levels = Vec::with_capacity(exposures_us.len());
        for (b, &exp_us) in exposures_us.iter().enumerate() {
            let mut pair = Vec::with_capacity(2);
            for second in [false, true] {
                let mut attempts = 0u32;
                // The second frame of a pair is shot as bracket b of a frame past the first's.
                let shot_frame = b + usize::from(second) * exposures_us.len();
                let img = loop {
                    self.check_stop()?;
                    match self.dark_shot(rig, camera, shot_frame, b, exp_us)? {
                        Ok(img) => break img,
                        Err(e) => {
                            attempts += 1;
                            self.retries += 1;
                            if attempts > self.cfg.camera_retries {
                                return Err(ScanError::Camera {
                                    frame: 0,
                                    attempts,
                                    source: e,
                                });
                            }
                            progress.println(&format!(
                                "dark frame {b}: {e}; retrying ({attempts}/{})",
                                self.cfg.camera_retries
                            ));
                        }
                    }
                };
                pair.push(img);
            }
            let exposure_s = exp_us as f64 * 1e-6;
            let name = super::dark::image_name(b, exp_us);
            let second = super::dark::second_name(b, exp_us);
            let level_name = super::dark::level_name(b, exp_us);
            let dark_err = |message: String| ScanError::Dark {
                exposure_s,
                message,
            };
            let (d, level) = super::dark::measure_pair(
                &pair[0],
                &pair[1],
                exposure_s,
                name.clone(),
                second.clone(),
                level_name.clone(),
            )
            .map_err(|e| dark_err(e.to_string()))?;
            for (img, path) in pair.iter().zip([&name, &second]) {
                let bytes = encode_exr(img).map_err(|e| dark_err(e.to_string()))?;
                write_atomic(&self.cfg.out.join(path), &bytes)?;
            }
            if let super::dark::DarkLevel::PerPixel(img) = &level {
                let bytes = encode_exr(img).map_err(|e| dark_err(e.to_string()))?;
                write_atomic(&self.cfg.out.join(&level_name), &bytes)?;
            }
            dark.push(d);
            levels.push((exposure_s, level));
        }
        let state = serde_json::to_vec_pretty(&dark).map_err(|e| {
            ScanError::Journal(WriteError::Io {
                path: dark_state(&self.cfg.out).display().to_string(),
                source: std::io::Error::other(e),
            })
        })?;
        write_atomic(&dark_state(&self.cfg.out), &state)?;
        // The values a resumed run reads back from the state, not the ones in memory:
        // serde_json's float parser may land one ulp away from a 17-digit value, and a resumed
        // scan must write the same scan.json as an uninterrupted one.
        let dark: Vec<DarkFrame> = serde_json::from_slice(&state).unwrap_or(dark);
        for (d, (_, level)) in dark.iter().zip(levels.iter_mut()) {
            if let super::dark::DarkLevel::Constant(m) = level {
                *m = d.median;
            }
        }
        let floor = self.cfg.noise_floor.or(super::dark::floor_of(&dark));
        self.writer.set_dark_frames(dark.clone(), floor)?;
        self.dark = dark;
        self.dark_levels = levels;
        Ok(())
    }

    /// The camera's image with every laser off at exposure `exp_us` (bracket `b`).
    fn dark_shot<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        frame: usize,
        b: usize,
        exp_us: u32,
    ) -> Result<Result<Image, CameraError>, ScanError> {
        let mut shot = Shot {
            frame,
            bracket: b,
            turntable_deg: 0.0,
            galvo: [0, 0],
            channel: self.cfg.laser_channel,
            exposure_s: exp_us as f64 * 1e-6,
            triggered_at_us: None,
            exposure_count: None,
            rig_boot: None,
            dark: true,
        };
        if camera.timing() == Timing::RigTriggered {
            if let Err(e) = camera.begin_batch() {
                return Ok(Err(e));
            }
            let base = rig.status().map_err(classify)?.exposures;
            let readout = rig.hello().capabilities.camera_readout_us;
            let timeout = Duration::from_micros(2_000_000 + 4 * (exp_us as u64 + readout as u64));
            let c = rig
                .dark_capture(
                    DarkCapture {
                        exposure_us: exp_us,
                        trigger_us: self.cfg.trigger_us.min(exp_us).max(1),
                    },
                    timeout,
                )
                .map_err(|e| self.halted_or(e))?;
            if let Some(message) = capture_mismatch(&c, base.wrapping_add(1), true) {
                return Err(ScanError::CaptureMismatch {
                    frame: 0,
                    message: format!("dark frame {b}: {message}"),
                });
            }
            shot.galvo = [c.galvo.x, c.galvo.y];
            shot.triggered_at_us = Some(c.triggered_at_us);
            shot.exposure_count = Some(c.exposure_count);
            shot.rig_boot = Some(rig.hello().boot_nonce);
        }
        // A host-timed camera exposes with the laser as the session left it: off.
        fetch(rig, camera, &shot)
    }

    /// Whether every planned frame is written.
    pub fn complete(&self) -> bool {
        self.done() >= self.frames.len()
    }

    /// Runs one rig session until the plan is done or something fails. Always tries to leave
    /// the laser off.
    pub fn session<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        progress: &dyn Progress,
    ) -> Result<(), ScanError> {
        let t0 = rig.status().map_err(classify)?.uptime_us;
        let result = self.session_inner(rig, camera, progress);
        // Laser off whatever happened; on a dead link the rig's heartbeat timeout does it.
        let _ = rig.stop();
        if let Ok(s) = rig.status() {
            self.rig_us += s.uptime_us.saturating_sub(t0);
        }
        result
    }

    fn check_stop(&self) -> Result<(), ScanError> {
        if self.cfg.stop.load(Ordering::Relaxed) {
            return Err(ScanError::Interrupted {
                done: self.done(),
                total: self.frames.len(),
            });
        }
        Ok(())
    }

    fn session_inner<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        progress: &dyn Progress,
    ) -> Result<(), ScanError> {
        let caps = rig.hello().capabilities;
        progress.set_length(self.frames.len() as u64);
        progress.set_position(self.done() as u64);
        if self.complete() {
            self.begin_sink();
            return Ok(());
        }
        let max_code = caps.galvo_max;
        if let Some(f) = self
            .frames
            .iter()
            .find(|f| f.galvo[0] > max_code || f.galvo[1] > max_code)
        {
            return Err(ScanError::Plan(format!(
                "frame {} aims at galvo codes {:?}, the rig's largest code is {max_code}",
                f.index, f.galvo
            )));
        }
        let exposures_us: Vec<u32> = self
            .cfg
            .plan
            .exposures_s
            .iter()
            .map(|e| (e * 1e6).round().max(1.0) as u32)
            .collect();
        if let Some(e) = exposures_us.iter().find(|e| **e > caps.max_exposure_us) {
            return Err(ScanError::Plan(format!(
                "exposure {e} µs exceeds the rig's limit of {} µs",
                caps.max_exposure_us
            )));
        }
        // Whatever a previous session left running (a program whose host vanished) stops now,
        // and the events of that stop are dropped (the client never delivers a previous
        // session's own events).
        rig.stop().map_err(classify)?;
        drain_events(rig)?;
        // Clear a fault left from before (an e-stop that was released); refuses while pressed.
        let status = rig.status().map_err(classify)?;
        if status.fault.is_some() {
            rig.clear_fault().map_err(|e| self.halted_or(e))?;
        }
        progress.set_message("homing");
        rig.home().map_err(|e| self.halted_or(e))?;
        rig.wait_idle(Duration::from_secs(600))
            .map_err(|e| self.halted_or(e))?;
        let speed = self
            .cfg
            .move_speed
            .unwrap_or(caps.max_speed)
            .min(caps.max_speed);
        let accel = self
            .cfg
            .move_accel
            .unwrap_or(caps.max_accel)
            .min(caps.max_accel);
        let spr = caps.steps_per_rev;
        if self.dark_pending() {
            self.take_dark_frames(rig, camera, progress, &exposures_us)?;
        }
        self.begin_sink();
        while !self.complete() {
            self.check_stop()?;
            let first = self.frames[self.done()];
            let steps = angle_steps(first.turntable_deg, spr);
            progress.set_message(&format!("turntable → {:.1}°", first.turntable_deg));
            rig.start_move(MoveTarget::Absolute(steps as i32), speed, accel)
                .map_err(|e| self.halted_or(e))?;
            let s = rig
                .wait_idle(Duration::from_secs(600))
                .map_err(|e| self.halted_or(e))?;
            let deg = s.position as f64 * 360.0 / spr.max(1) as f64;
            rig.arm().map_err(|e| self.halted_or(e))?;
            progress.set_message(&format!("{deg:.1}°"));
            // The rest of this angle, in program-sized chunks.
            let max_pts = (caps.max_program_points as usize)
                .min(self.cfg.chunk_points)
                .max(1);
            let chunk: Vec<_> = self.frames[self.done()..]
                .iter()
                .take_while(|f| f.angle_index == first.angle_index)
                .take(max_pts)
                .copied()
                .collect();
            self.run_chunk(rig, camera, progress, &chunk, deg, &exposures_us)?;
        }
        rig.disarm().map_err(classify)?;
        Ok(())
    }

    fn halted_or(&self, e: RigClientError) -> ScanError {
        match e {
            // The rig stopped because it stopped hearing from us: a link problem, resumable by
            // reconnecting.
            RigClientError::Halted { ref reason, .. } if reason.contains("HeartbeatLost") => {
                ScanError::Link(e)
            }
            RigClientError::Halted { reason, .. } => ScanError::RigHalted {
                frame: self.done(),
                reason,
            },
            RigClientError::Rejected { ref error, .. }
                if matches!(
                    error,
                    subsurf_protocol::RigError::EmergencyStop
                        | subsurf_protocol::RigError::InterlockOpen
                        | subsurf_protocol::RigError::Faulted(_)
                ) =>
            {
                ScanError::RigHalted {
                    frame: self.done(),
                    reason: format!("{error:?}"),
                }
            }
            e => classify(e),
        }
    }

    /// Captures `chunk` (frames of one angle) with every exposure, merges and commits them.
    fn run_chunk<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        progress: &dyn Progress,
        chunk: &[super::plan::PlannedFrame],
        deg: f64,
        exposures_us: &[u32],
    ) -> Result<(), ScanError> {
        let n_exp = exposures_us.len();
        let mut brackets: Vec<Vec<Bracket>> = vec![Vec::with_capacity(n_exp); chunk.len()];
        for (b, &exp_us) in exposures_us.iter().enumerate() {
            let mut next = 0usize;
            let mut attempts = 0u32;
            while next < chunk.len() {
                self.check_stop()?;
                let rest = &chunk[next..];
                // Frames are committed as their last bracket arrives.
                let last = b + 1 == n_exp;
                let got = match camera.timing() {
                    Timing::RigTriggered => self.program(
                        rig,
                        camera,
                        progress,
                        last,
                        rest,
                        b,
                        deg,
                        exp_us,
                        &mut brackets[next..],
                    )?,
                    Timing::HostTimed => self.host_timed(
                        rig,
                        camera,
                        progress,
                        last,
                        rest,
                        b,
                        deg,
                        exp_us,
                        &mut brackets[next..],
                    )?,
                };
                next += got.count;
                if let Some(err) = got.camera_error {
                    attempts += 1;
                    self.retries += 1;
                    if attempts > self.cfg.camera_retries {
                        return Err(ScanError::Camera {
                            frame: chunk[next].index,
                            attempts,
                            source: err,
                        });
                    }
                    progress.println(&format!(
                        "frame {}: {err}; retrying ({attempts}/{})",
                        chunk[next].index, self.cfg.camera_retries
                    ));
                } else {
                    attempts = 0;
                }
            }
        }
        Ok(())
    }

    fn shot(&self, f: &super::plan::PlannedFrame, b: usize, deg: f64, exp_us: u32) -> Shot {
        Shot {
            frame: f.index,
            bracket: b,
            turntable_deg: deg,
            galvo: f.galvo,
            channel: self.cfg.laser_channel,
            exposure_s: exp_us as f64 * 1e-6,
            triggered_at_us: None,
            exposure_count: None,
            rig_boot: None,
            dark: false,
        }
    }

    /// Runs `rest` as one queued program; returns how many leading points got an image.
    #[allow(clippy::too_many_arguments)]
    fn program<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        progress: &dyn Progress,
        last_bracket: bool,
        rest: &[super::plan::PlannedFrame],
        b: usize,
        deg: f64,
        exp_us: u32,
        out: &mut [Vec<Bracket>],
    ) -> Result<Progressed, ScanError> {
        let points: Vec<GalvoPoint> = rest
            .iter()
            .map(|f| GalvoPoint {
                x: f.galvo[0],
                y: f.galvo[1],
            })
            .collect();
        let readout = rig.hello().capabilities.camera_readout_us;
        let interval_us = self.cfg.interval_us.max(exp_us.saturating_add(readout));
        let header = ProgramHeader {
            len: points.len() as u16,
            channel: self.cfg.laser_channel,
            settle_us: None,
            exposure_us: exp_us,
            trigger_us: self.cfg.trigger_us.min(exp_us).max(1),
            interval_us,
        };
        camera.begin_batch().map_err(|e| ScanError::Camera {
            frame: rest[0].index,
            attempts: 1,
            source: e,
        })?;
        rig.load_program(header, &points)
            .map_err(|e| self.halted_or(e))?;
        // Images are matched to captures by the camera's exposure count, which the rig confirms
        // per capture from the camera's exposure-active output.
        let base = rig.status().map_err(classify)?.exposures;
        let first_id = rig.run_program().map_err(|e| self.halted_or(e))?;
        let per =
            Duration::from_micros(2_000_000 + 4 * (exp_us as u64 + interval_us as u64 + 50_000));
        for (i, f) in rest.iter().enumerate() {
            let c = wait_capture(rig, first_id.wrapping_add(i as u32), per)
                .map_err(|e| self.halted_or(e))?;
            let expected = base.wrapping_add(i as u32 + 1);
            if let Some(message) = capture_mismatch(&c, expected, false) {
                let _ = rig.stop();
                let _ = drain_events(rig);
                return Err(ScanError::CaptureMismatch {
                    frame: f.index,
                    message,
                });
            }
            let mut shot = self.shot(f, b, deg, exp_us);
            shot.galvo = [c.galvo.x, c.galvo.y];
            shot.triggered_at_us = Some(c.triggered_at_us);
            shot.exposure_count = Some(c.exposure_count);
            shot.rig_boot = Some(rig.hello().boot_nonce);
            match fetch(rig, camera, &shot)? {
                Ok(img) => {
                    out[i].push(Bracket {
                        exposure_s: shot.exposure_s,
                        image: img,
                    });
                    if last_bracket {
                        self.commit(f, deg, &mut out[i], camera)?;
                        progress.inc(1);
                    }
                }
                Err(e) => {
                    // Stop the program; the rest is rerun from this point.
                    rig.stop().map_err(classify)?;
                    rig.wait_idle(Duration::from_secs(60))
                        .map_err(|e| self.halted_or(e))?;
                    // The `Halted { Stop }` and `ProgramDone` events of this stop are ours.
                    drain_events(rig)?;
                    rig.arm().map_err(|e| self.halted_or(e))?;
                    return Ok(Progressed {
                        count: i,
                        camera_error: Some(e),
                    });
                }
            }
        }
        rig.wait_idle(Duration::from_secs(60))
            .map_err(|e| self.halted_or(e))?;
        Ok(Progressed {
            count: rest.len(),
            camera_error: None,
        })
    }

    /// Host-timed exposures: galvo, laser on, camera, laser off — one frame at a time.
    #[allow(clippy::too_many_arguments)]
    fn host_timed<L: ByteLink>(
        &mut self,
        rig: &mut RigClient<L>,
        camera: &mut dyn Camera,
        progress: &dyn Progress,
        last_bracket: bool,
        rest: &[super::plan::PlannedFrame],
        b: usize,
        deg: f64,
        exp_us: u32,
        out: &mut [Vec<Bracket>],
    ) -> Result<Progressed, ScanError> {
        for (i, f) in rest.iter().enumerate() {
            self.check_stop()?;
            rig.galvo(f.galvo[0], f.galvo[1])
                .map_err(|e| self.halted_or(e))?;
            rig.poll(Duration::from_millis(5)).map_err(classify)?;
            rig.laser(self.cfg.laser_channel, true)
                .map_err(|e| self.halted_or(e))?;
            let shot = self.shot(f, b, deg, exp_us);
            let r = fetch(rig, camera, &shot);
            let off = rig.laser(self.cfg.laser_channel, false);
            let r = r?;
            off.map_err(|e| self.halted_or(e))?;
            match r {
                Ok(img) => {
                    out[i].push(Bracket {
                        exposure_s: shot.exposure_s,
                        image: img,
                    });
                    if last_bracket {
                        self.commit(f, deg, &mut out[i], camera)?;
                        progress.inc(1);
                    }
                }
                Err(e) => {
                    return Ok(Progressed {
                        count: i,
                        camera_error: Some(e),
                    });
                }
            }
        }
        Ok(Progressed {
            count: rest.len(),
            camera_error: None,
        })
    }

    fn commit(
        &mut self,
        f: &super::plan::PlannedFrame,
        deg: f64,
        brackets: &mut Vec<Bracket>,
        camera: &dyn Camera,
    ) -> Result<(), ScanError> {
        // The dark level of each exposure off every bracket first: the merge and the fit see
        // light alone (clipped pixels stay clipped).
        for b in brackets.iter_mut() {
            if let Some(level) = super::dark::level_for(&self.dark_levels, b.exposure_s) {
                level
                    .subtract(&mut b.image, camera.saturation())
                    .map_err(|message| ScanError::Image {
                        frame: f.index,
                        message,
                    })?;
            }
        }
        let (image, exposure_s) = if brackets.len() == 1 {
            let b = brackets.remove(0);
            (b.image, b.exposure_s)
        } else {
            let merged = merge_hdr(
                brackets,
                &MergeOptions {
                    saturation: camera.saturation(),
                    noise_floor: 0.0,
                },
            )
            .map_err(|e| ScanError::Image {
                frame: f.index,
                message: e.to_string(),
            })?;
            brackets.clear();
            (merged, 1.0)
        };
        let bytes = encode_exr(&image).map_err(|e| ScanError::Image {
            frame: f.index,
            message: e.to_string(),
        })?;
        let (origin, direction) = self.cfg.calib.galvo.ray(f.galvo);
        let entry = FrameSpec {
            image: DatasetWriter::image_name(f.index),
            camera: 0,
            turntable_deg: deg,
            exposure_s,
            channel: self.cfg.plan.channel,
            laser: Some(LaserRay { origin, direction }),
            galvo: Some(f.galvo.map(u32::from)),
            levels: Default::default(),
            brackets: Vec::new(),
        };
        let sent = self.sink.as_ref().map(|_| entry.clone());
        self.writer.commit(entry, &bytes)?;
        self.written += 1;
        if let (Some(sink), Some(entry)) = (&mut self.sink, sent) {
            sink.frame(self.writer.done() - 1, &entry, image);
        }
        Ok(())
    }

    /// Writes the final `scan.json` and reports.
    pub fn finish(mut self, reconnects: u32) -> Result<ScanSummary, ScanError> {
        let frames_total = self.frames.len();
        let (resumed_from, frames_written, rig_us, retries, started) = (
            self.resumed_from,
            self.written,
            self.rig_us,
            self.retries,
            self.started,
        );
        let noise_floor = self.writer.header().noise_floor;
        self.begin_sink();
        let scan_json = self.writer.finish()?;
        let sink = self.sink.map(|mut s| s.finish());
        let dark_frames = self.dark;
        Ok(ScanSummary {
            sink,
            scan_json,
            frames_total,
            resumed_from,
            frames_written,
            rig_seconds: rig_us as f64 * 1e-6,
            wall_seconds: started.elapsed().as_secs_f64(),
            reconnects,
            camera_retries: retries,
            dark_frames,
            noise_floor,
        })
    }

    /// Writes `scan.json` with the frames so far (after an error, so the partial dataset is
    /// readable).
    pub fn flush_index(&self) -> Result<(), ScanError> {
        Ok(self.writer.write_index()?)
    }
}

struct Progressed {
    count: usize,
    camera_error: Option<CameraError>,
}

/// Where a scan keeps its dark frames' statistics between runs.
fn dark_state(out: &Path) -> PathBuf {
    out.join(STATE_DIR).join("dark.json")
}

/// Drops events already sent by the rig (those of a stopped program).
/// Why capture `c` cannot be trusted, if it cannot: the camera did not confirm it, its count is
/// not the `expected` one (an exposure the rig did not trigger, or one missed earlier), or the
/// laser did not cover the whole exposure (unless `dark`: a dark capture has no laser).
pub fn capture_mismatch(
    c: &subsurf_protocol::Captured,
    expected: u32,
    dark: bool,
) -> Option<String> {
    if c.exposure.is_none() {
        return Some(format!(
            "the camera did not confirm capture {} (no exposure-active edge: a missed trigger, \
             or the camera was still reading out)",
            c.capture_id
        ));
    }
    if c.exposure_count != expected {
        return Some(format!(
            "capture {} is the camera's exposure {} but should be exposure {expected}: the camera \
             took an exposure the rig did not trigger, or missed one",
            c.capture_id, c.exposure_count
        ));
    }
    if !dark && !c.lit {
        return Some(format!(
            "the laser did not cover the whole exposure of capture {} (exposure-active {:?}): \
             raise laser.lead_us / laser.tail_us in the rig profile",
            c.capture_id, c.exposure
        ));
    }
    None
}

fn drain_events<L: ByteLink>(rig: &mut RigClient<L>) -> Result<(), ScanError> {
    rig.poll(Duration::from_millis(20)).map_err(classify)?;
    while rig.next_event(Duration::ZERO).map_err(classify)?.is_some() {}
    Ok(())
}

/// Waits for the `Captured` event of capture `id`.
fn wait_capture<L: ByteLink>(
    rig: &mut RigClient<L>,
    id: u32,
    timeout: Duration,
) -> Result<subsurf_protocol::Captured, RigClientError> {
    rig.wait_captured(id, timeout)
}

/// Gets the camera's image for `shot`, keeping the rig's heartbeat going when the camera is slow.
fn fetch<L: ByteLink>(
    rig: &mut RigClient<L>,
    camera: &mut dyn Camera,
    shot: &Shot,
) -> Result<Result<Image, CameraError>, ScanError> {
    if camera.is_quick() {
        return Ok(camera.capture(shot));
    }
    std::thread::scope(|s| {
        let h = s.spawn(|| camera.capture(shot));
        while !h.is_finished() {
            rig.poll(Duration::from_millis(10)).map_err(classify)?;
        }
        h.join().map_err(|_| ScanError::Image {
            frame: shot.frame,
            message: "the camera thread panicked".into(),
        })
    })
}

/// Runs `scan` over `rig` until done (single session; link failures are returned).
pub fn run<L: ByteLink>(
    cfg: &ScanConfig,
    rig: &mut RigClient<L>,
    camera: &mut dyn Camera,
    progress: &dyn Progress,
) -> Result<ScanSummary, ScanError> {
    let mut scan = Scan::open(cfg, camera)?;
    match scan.session(rig, camera, progress) {
        Ok(()) => scan.finish(0),
        Err(e) => {
            let _ = scan.flush_index();
            Err(e)
        }
    }
}

/// Runs the scan, reconnecting with back-off (0.1 s doubling to 5 s, up to `max_reconnects`)
/// whenever the link fails; each reconnect handshakes again and resumes at the first frame not
/// written.
pub fn run_with_reconnect<L: ByteLink>(
    cfg: &ScanConfig,
    connect: &mut dyn FnMut() -> Result<RigClient<L>, RigClientError>,
    camera: &mut dyn Camera,
    progress: &dyn Progress,
    max_reconnects: u32,
) -> Result<ScanSummary, ScanError> {
    run_with_reconnect_into(cfg, connect, camera, progress, max_reconnects, None)
}

/// [`run_with_reconnect`], every committed frame handed to `sink` as well ([`FrameSink`]).
pub fn run_with_reconnect_into<L: ByteLink>(
    cfg: &ScanConfig,
    connect: &mut dyn FnMut() -> Result<RigClient<L>, RigClientError>,
    camera: &mut dyn Camera,
    progress: &dyn Progress,
    max_reconnects: u32,
    sink: Option<Box<dyn FrameSink>>,
) -> Result<ScanSummary, ScanError> {
    let mut scan = Scan::open(cfg, camera)?;
    if let Some(s) = sink {
        scan = scan.with_sink(s);
    }
    let mut reconnects = 0u32;
    let mut backoff = Duration::from_millis(100);
    let mut ever_connected = false;
    loop {
        let outcome = match connect() {
            Ok(mut rig) => {
                ever_connected = true;
                scan.session(&mut rig, camera, progress)
            }
            // A rig that was never reached is a wrong port or a rig that is off: say so now.
            Err(e) if !ever_connected => {
                let _ = scan.flush_index();
                return Err(classify(e));
            }
            Err(e) => Err(classify(e)),
        };
        match outcome {
            Ok(()) => return scan.finish(reconnects),
            Err(e) if e.is_link() && reconnects < max_reconnects => {
                reconnects += 1;
                progress.println(&format!(
                    "{e}; reconnecting in {backoff:?} (attempt {reconnects}/{max_reconnects})"
                ));
                if cfg.stop.load(Ordering::Relaxed) {
                    let _ = scan.flush_index();
                    return Err(ScanError::Interrupted {
                        done: scan.done(),
                        total: scan.frames.len(),
                    });
                }
                std::thread::sleep(backoff);
                backoff = (backoff * 2).min(Duration::from_secs(5));
            }
            Err(e) => {
                let _ = scan.flush_index();
                return Err(e);
            }
        }
    }
}
