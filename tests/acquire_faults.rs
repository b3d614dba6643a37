//! Faults during a simulated scan: emergency stop, Ctrl-C, a camera that times out. Each one
//! stops with the laser off and a clear message, and the same scan resumes to completion.
use crate::fixture::{Planner, rig_scan};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use subsurf::dataset::Dataset;
use subsurf::dataset::Image;
use subsurf::link::{ByteLink, LinkError};
use subsurf::rig::{ClientConfig, RigClient};
use subsurf::scan::camera::{Camera, CameraError, Shot, Timing};
use subsurf::scan::driver::{ScanConfig, ScanError, run};
use subsurf::scan::plan::PlanOptions;
use subsurf::scan::setup::camera_from_spec;
use subsurf::sim::{SimLink, SimParams, VirtualRig};

fn config() -> (ScanConfig, subsurf::dataset::Mesh, tempfile::TempDir) {
    rig_scan(
        24,
        Planner::Dense,
        PlanOptions {
            angles: 2,
            raster: 4,
            exposures_s: vec![0.05],
            ..PlanOptions::default()
        },
    )
}

fn client<L: ByteLink>(link: L) -> RigClient<L> {
    RigClient::connect_with_seq(link, ClientConfig::default(), 3).unwrap()
}

/// The simulated rig whose emergency stop is pressed at a virtual time.
struct EstopAt {
    inner: SimLink,
    at: Duration,
    pressed: bool,
}

impl ByteLink for EstopAt {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.inner.send(bytes)
    }
    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        let n = self.inner.recv(buf, timeout)?;
        if !self.pressed && self.inner.elapsed() >= self.at {
            self.inner.rig_mut().set_estop(true);
            self.pressed = true;
        }
        Ok(n)
    }
    fn describe(&self) -> String {
        "simulated rig with an emergency stop".into()
    }
    fn now(&self) -> Instant {
        self.inner.now()
    }
}

#[test]
fn emergency_stop_halts_with_the_laser_off_and_the_scan_resumes() {
    let (cfg, mesh, _dir) = config();
    let mut camera = camera_from_spec("sim", &mesh, &cfg.calib, 1, Duration::from_secs(1)).unwrap();
    // Two-pass homing takes ~2.5 s of virtual time; press the button in the middle of the
    // captures.
    let link = EstopAt {
        inner: SimLink::clean(VirtualRig::new(SimParams::default())),
        at: Duration::from_millis(4000),
        pressed: false,
    };
    let mut rig = client(link);
    let err = run(&cfg, &mut rig, camera.as_mut(), &()).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, ScanError::RigHalted { .. }), "{msg}");
    assert!(
        msg.contains("EmergencyStop") && msg.contains("laser is off"),
        "{msg}"
    );
    let mut link = rig.into_link();
    assert_eq!(link.inner.rig().status().lasers, 0);
    let done = Dataset::open(&cfg.out).unwrap().spec.frames.len();
    assert!(done > 0 && done < cfg.plan.frame_count(), "{done}");
    // Released: the same scan resumes and completes.
    link.inner.rig_mut().set_estop(false);
    let mut rig = client(link.inner);
    let s = run(&cfg, &mut rig, camera.as_mut(), &()).unwrap();
    assert_eq!(s.resumed_from, done);
    assert_eq!(
        Dataset::open(&cfg.out).unwrap().spec.frames.len(),
        cfg.plan.frame_count()
    );
}

/// Wraps a camera: sets `stop` after `after` images, or fails frame `fail_frame` `fails` times.
struct Flaky {
    inner: Box<dyn Camera>,
    shots: usize,
    dark_shots: usize,
    stop_after: Option<(usize, Arc<AtomicBool>)>,
    fail_frame: usize,
    fails: u32,
}

impl Camera for Flaky {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn timing(&self) -> Timing {
        self.inner.timing()
    }
    fn is_quick(&self) -> bool {
        true
    }
    fn capture(&mut self, shot: &Shot) -> Result<Image, CameraError> {
        self.shots += 1;
        self.dark_shots += usize::from(shot.dark);
        if let Some((n, stop)) = &self.stop_after
            && self.shots >= *n
        {
            stop.store(true, Ordering::Relaxed);
        }
        if shot.frame == self.fail_frame && self.fails > 0 {
            self.fails -= 1;
            return Err(CameraError::Timeout {
                camera: "flaky".into(),
                frame: shot.frame,
                waited: Duration::from_secs(1),
            });
        }
        self.inner.capture(shot)
    }
}

#[test]
fn ctrl_c_stops_cleanly_with_the_laser_off() {
    let (mut cfg, mesh, _dir) = config();
    let stop = Arc::new(AtomicBool::new(false));
    cfg.stop = stop.clone();
    let mut camera = Flaky {
        inner: camera_from_spec("sim", &mesh, &cfg.calib, 1, Duration::from_secs(1)).unwrap(),
        shots: 0,
        dark_shots: 0,
        stop_after: Some((5, stop.clone())),
        fail_frame: usize::MAX,
        fails: 0,
    };
    let mut rig = client(SimLink::clean(VirtualRig::new(SimParams::default())));
    let err = run(&cfg, &mut rig, &mut camera, &()).unwrap_err();
    assert!(matches!(err, ScanError::Interrupted { .. }), "{err}");
    assert_eq!(rig.link().rig().status().lasers, 0);
    assert!(!rig.link().rig().status().armed);
    stop.store(false, Ordering::Relaxed);
    camera.stop_after = None;
    let s = run(&cfg, &mut rig, &mut camera, &()).unwrap();
    assert!(s.resumed_from >= 4, "{s:?}");
    // The dark frames (two per exposure) were taken once, by the first run; the resumed one kept
    // their floor.
    assert_eq!(camera.dark_shots, 2 * cfg.plan.exposures_s.len());
    assert_eq!(s.dark_frames.len(), cfg.plan.exposures_s.len());
    let ds = Dataset::open(&cfg.out).unwrap();
    assert_eq!(
        ds.spec.noise_floor,
        subsurf::scan::dark::floor_of(&s.dark_frames)
    );
}

#[test]
fn a_camera_timeout_is_retried_then_fails_the_frame_clearly() {
    let (cfg, mesh, _dir) = config();
    let mut camera = Flaky {
        inner: camera_from_spec("sim", &mesh, &cfg.calib, 1, Duration::from_secs(1)).unwrap(),
        shots: 0,
        dark_shots: 0,
        stop_after: None,
        fail_frame: 3,
        fails: 1,
    };
    let mut rig = client(SimLink::clean(VirtualRig::new(SimParams::default())));
    let s = run(&cfg, &mut rig, &mut camera, &()).unwrap();
    assert_eq!(s.camera_retries, 1);
    assert_eq!(s.frames_written, cfg.plan.frame_count());

    let (cfg, mesh, _dir) = config();
    let mut camera = Flaky {
        inner: camera_from_spec("sim", &mesh, &cfg.calib, 1, Duration::from_secs(1)).unwrap(),
        shots: 0,
        dark_shots: 0,
        stop_after: None,
        fail_frame: 2,
        fails: 100,
    };
    let mut rig = client(SimLink::clean(VirtualRig::new(SimParams::default())));
    let err = run(&cfg, &mut rig, &mut camera, &()).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("frame 2 failed after 3 attempts") && msg.contains("no image"),
        "{msg}"
    );
    assert_eq!(rig.link().rig().status().lasers, 0);
    assert_eq!(Dataset::open(&cfg.out).unwrap().spec.frames.len(), 2);
}
