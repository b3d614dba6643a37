//! Link drop-out: the pseudo-terminal to the simulated rig is closed mid-scan and reopened after
//! longer than the rig's heartbeat timeout. The scan reconnects, handshakes again and completes;
//! the rig's own laser log shows the laser went off within the heartbeat timeout of the drop.
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use subsurf::calib::Calibration;
use subsurf::dataset::Dataset;
use subsurf::link::{ByteLink, LinkError, SerialLink};
use subsurf::rig::{ClientConfig, RigClient, RigClientError};
use subsurf::scan::driver::{ScanConfig, run_with_reconnect};
use subsurf::scan::plan::{PlanOptions, PlanScene, dense_raster};
use subsurf::scan::setup::{builtin_object, camera_from_spec, obj_text};
use subsurf::sim::SimParams;

/// A serial link that is unplugged (closed, every call fails) at `until`.
struct Unplugged {
    inner: Option<SerialLink>,
    until: Instant,
    name: String,
}

impl Unplugged {
    fn check(&mut self) -> Result<&mut SerialLink, LinkError> {
        if Instant::now() >= self.until {
            self.inner = None; // closes the pseudo-terminal
        }
        self.inner.as_mut().ok_or_else(|| LinkError::Closed {
            link: self.name.clone(),
        })
    }
}

impl ByteLink for Unplugged {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.check()?.send(bytes)
    }
    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        let left = self.until.saturating_duration_since(Instant::now());
        self.check()?.recv(buf, timeout.min(left))
    }
    fn describe(&self) -> String {
        self.name.clone()
    }
}

#[test]
fn scan_survives_the_pty_closing_and_the_rig_turns_the_laser_off_in_time() {
    let mut params = SimParams::default();
    params.config.heartbeat_timeout_ms = 400;
    let timeout = Duration::from_millis(400);
    let (controller, device) = SerialLink::pty_pair().unwrap();
    let path = device.path().unwrap();
    let spawned = Instant::now();
    let server = subsurf::sim::spawn(controller, params).unwrap();
    // The device end stays open here, so the rig never sees end-of-file between clients.
    let _device = device;

    let obj = builtin_object();
    let mesh = obj.mesh();
    let (centre, radius) = obj.bounds();
    let calib = Calibration::builtin_for(centre, radius, 24);
    let scene = PlanScene::new(&mesh.positions, &mesh.triangles, &calib).unwrap();
    let plan = dense_raster(
        &scene,
        &PlanOptions {
            angles: 2,
            raster: 5,
            exposures_s: vec![0.04],
            ..PlanOptions::default()
        },
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = ScanConfig::new(dir.path().join("ds"), plan, calib.clone(), obj_text(&mesh));
    let mut camera = camera_from_spec("sim", &mesh, &calib, 5, Duration::from_secs(1)).unwrap();

    let outage = Duration::from_millis(1200);
    let dropped_at: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let reopened_at: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let mut connect = || -> Result<RigClient<Unplugged>, RigClientError> {
        let now = Instant::now();
        let mut drop = dropped_at.lock().unwrap();
        let until = match *drop {
            None => {
                // First connection: unplugged one second in, in the middle of the first program.
                let at = now + Duration::from_millis(1000);
                *drop = Some(at);
                at
            }
            Some(at) if now < at + outage => {
                return Err(RigClientError::Link(LinkError::Closed {
                    link: path.clone(),
                }));
            }
            Some(_) => {
                reopened_at.lock().unwrap().get_or_insert(now);
                now + Duration::from_secs(3600)
            }
        };
        let link = Unplugged {
            inner: Some(SerialLink::open(&path, 115_200)?),
            until,
            name: path.clone(),
        };
        RigClient::connect(link, ClientConfig::default())
    };
    let summary = run_with_reconnect(&cfg, &mut connect, camera.as_mut(), &(), 40).unwrap();
    assert!(summary.reconnects >= 1, "{summary:?}");
    assert_eq!(summary.frames_total, cfg.plan.frame_count());
    let ds = Dataset::open(&cfg.out).unwrap();
    assert_eq!(ds.spec.frames.len(), cfg.plan.frame_count());

    // Rig clock ≈ time since the server was spawned (it starts its clock right after).
    let rig_us = |t: Instant| t.duration_since(spawned).as_micros() as u64;
    let drop_us = rig_us(dropped_at.lock().unwrap().unwrap());
    let reopen_us = rig_us(reopened_at.lock().unwrap().unwrap());
    let log: Vec<(u64, u8)> =
        server.with_rig(|r| r.laser_log().iter().map(|e| (e.at, e.value)).collect());
    let lit_before_drop = log
        .iter()
        .any(|&(at, v)| v != 0 && at + 300_000 > drop_us && at <= drop_us);
    assert!(
        lit_before_drop,
        "the laser was not working when the link dropped: {log:?}"
    );
    let deadline = drop_us + timeout.as_micros() as u64 + 50_000;
    // State of the laser from the deadline until the host came back: off, and never switched on.
    let state_at = |t: u64| log.iter().rev().find(|(at, _)| *at <= t).map_or(0, |e| e.1);
    assert_eq!(
        state_at(deadline),
        0,
        "laser still on at the heartbeat deadline: {log:?}"
    );
    assert!(
        !log.iter()
            .any(|&(at, v)| v != 0 && at > deadline && at < reopen_us),
        "laser switched on while the host was gone: {log:?}"
    );
    let last_off_after_drop = log
        .iter()
        .filter(|&&(at, v)| v == 0 && at >= drop_us.saturating_sub(60_000))
        .map(|e| e.0)
        .next()
        .unwrap();
    assert!(last_off_after_drop <= deadline);
    assert_eq!(server.with_rig(|r| r.status().lasers), 0);
    server.stop().unwrap();
}
