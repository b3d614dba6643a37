//! Shared harness for the rig-link end-to-end tests (`rig_link`).
//!
//! Two ways to reach the simulated rig, one scripted session to run over either:
//! - [`virtual_rig`]: the rig stepped inline behind a faulty wire, virtual time, deterministic.
//! - [`PtyRig`]: the rig served by a thread on a real pseudo-terminal pair (wall clock), with
//!   faults injected on the rig's side of the pty.
//! - [`run_script`] sends a long mixed command sequence and records what it asked for;
//!   [`check_exactly_once`] compares that with what the simulated hardware actually did.
#![warn(missing_docs)]

use std::time::Duration;

use subsurf::link::{ByteLink, FaultConfig, FaultyLink, SerialLink};
use subsurf::rig::{ClientConfig, RigClient, RigClientError};
use subsurf::sim::{SimLink, SimParams, SimServer, VirtualRig};
use subsurf_protocol::{Capture, GalvoPoint, MoveTarget};

/// Client timing for lossy links: frequent retransmissions, patient overall.
pub fn lossy_client_config(retransmit_after: Duration) -> ClientConfig {
    ClientConfig {
        retransmit_after,
        give_up_after: Duration::from_secs(10),
        heartbeat_every: Some(Duration::from_millis(100)),
    }
}

/// A client connected to a simulated rig in virtual time over a wire with the given faults.
pub fn virtual_rig(
    to_rig: FaultConfig,
    to_host: FaultConfig,
) -> Result<RigClient<SimLink>, RigClientError> {
    let link = SimLink::new(VirtualRig::new(SimParams::default()), to_rig, to_host);
    RigClient::connect_with_seq(link, lossy_client_config(Duration::from_millis(20)), 1000)
}

/// The simulated rig served on a pseudo-terminal by a background thread, and a client that opened
/// the pty's device path like any serial program.
#[derive(Debug)]
pub struct PtyRig {
    /// The host side.
    pub client: RigClient<SerialLink>,
    /// The serving thread and the rig it serves.
    pub server: SimServer,
    /// Kept open so the controller end never sees end-of-file; also a second writer for noise.
    device: SerialLink,
}

impl PtyRig {
    /// Serve a fresh simulated rig on a new pty; the rig's side of the pty drops, corrupts and
    /// duplicates what it receives with `to_rig` and what it sends with `to_host`.
    pub fn start(
        to_rig: FaultConfig,
        to_host: FaultConfig,
        retransmit_after: Duration,
    ) -> anyhow::Result<Self> {
        let (controller, device) = SerialLink::pty_pair()?;
        let path = device
            .path()
            .ok_or_else(|| anyhow::anyhow!("pty has no path"))?;
        let faulty = FaultyLink::new(controller, to_host, to_rig);
        let server = subsurf::sim::spawn(faulty, SimParams::default())?;
        let link = SerialLink::open(&path, 115_200)?;
        let client = RigClient::connect(link, lossy_client_config(retransmit_after))?;
        Ok(Self {
            client,
            server,
            device,
        })
    }
}

impl PtyRig {
    /// Write raw bytes to the rig through the pty's own device handle, as a second program on
    /// the same serial line would (the client holds the exclusive lock on the path).
    pub fn inject(&mut self, bytes: &[u8]) -> Result<(), subsurf::link::LinkError> {
        self.device.send(bytes)
    }
}

/// What [`run_script`] asked the rig to do, in order.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct ScriptLog {
    /// Every galvo position commanded (by `Galvo` and by `Capture`), in order.
    pub galvo: Vec<GalvoPoint>,
    /// Relative moves, in order.
    pub moves: Vec<i32>,
    /// Capture ids the rig handed out, in order.
    pub capture_ids: Vec<u32>,
    /// Capture ids of the `Captured` reports the client delivered, in order.
    pub captured: Vec<u32>,
    /// Captures whose `Captured` event never reached the caller (the capture itself ran): the
    /// link lost it and the rig no longer kept it for a replay.
    pub lost_capture_events: u32,
    /// Steps of the script (each is at least one request; moves and captures add status polls).
    pub steps: usize,
}

/// A galvo point that differs from its neighbours, so a repeated or skipped write shows.
pub fn galvo_point(i: usize, galvo_max: u16) -> GalvoPoint {
    let span = usize::from(galvo_max) + 1;
    GalvoPoint {
        x: u16::try_from(i % span).unwrap_or(0),
        y: u16::try_from((i / span) % span).unwrap_or(0),
    }
}

/// Run `steps` script steps: mostly galvo moves, a relative turntable move every 100 steps and a
/// capture every 100 steps (armed once at the start).
pub fn run_script<L: ByteLink>(
    rig: &mut RigClient<L>,
    steps: usize,
) -> Result<ScriptLog, RigClientError> {
    let caps = rig.hello().capabilities;
    let mut log = ScriptLog::default();
    rig.arm()?;
    for i in 0..steps {
        match i % 100 {
            50 => {
                let by = i32::try_from(i % 7).unwrap_or(0) + 1;
                rig.start_move(MoveTarget::Relative(by), caps.max_speed, caps.max_accel)?;
                rig.wait_idle(Duration::from_secs(30))?;
                log.moves.push(by);
            }
            75 => {
                let galvo = galvo_point(i, caps.galvo_max);
                let id = rig.start_capture(Capture {
                    galvo,
                    settle_us: Some(10),
                    channel: 0,
                    exposure_us: 100,
                    trigger_us: 10,
                })?;
                log.galvo.push(galvo);
                log.capture_ids.push(id);
                match rig.wait_captured(id, Duration::from_secs(30)) {
                    Ok(c) => log.captured.push(c.capture_id),
                    // Lost and not recoverable: the capture ran, its report is gone.
                    Err(RigClientError::EventTimeout { .. }) => log.lost_capture_events += 1,
                    Err(e) => return Err(e),
                }
            }
            _ => {
                let p = galvo_point(i, caps.galvo_max);
                rig.galvo(p.x, p.y)?;
                log.galvo.push(p);
            }
        }
        log.steps += 1;
    }
    rig.disarm()?;
    Ok(log)
}

/// Compare what the script asked for with what the simulated hardware did: every galvo write,
/// every move and every capture exactly once, in order.
pub fn check_exactly_once(log: &ScriptLog, rig: &VirtualRig) {
    assert_eq!(
        rig.missed_log_entries(),
        0,
        "the hardware logs are complete"
    );
    // The first write is the firmware's power-on reset of the galvo.
    let written: Vec<GalvoPoint> = rig.galvo_log().iter().skip(1).map(|e| e.value).collect();
    if let Some(i) = (0..written.len().min(log.galvo.len())).find(|&i| written[i] != log.galvo[i]) {
        panic!(
            "galvo write {i} was {:?}, commanded {:?}",
            written[i], log.galvo[i]
        );
    }
    assert_eq!(
        written.len(),
        log.galvo.len(),
        "galvo writes: {} executed, {} commanded",
        written.len(),
        log.galvo.len()
    );
    let net: i64 = log.moves.iter().map(|&m| i64::from(m)).sum();
    let total: u64 = log.moves.iter().map(|m| u64::from(m.unsigned_abs())).sum();
    assert_eq!(rig.turned_steps(), net, "net turntable steps");
    assert_eq!(
        rig.hardware().steps(),
        total,
        "step pulses (a repeated move adds steps)"
    );
    assert_eq!(i64::from(rig.status().position), net, "rig's position");
    assert_eq!(
        rig.triggers().len(),
        log.capture_ids.len(),
        "camera triggers"
    );
    for pair in log.capture_ids.windows(2) {
        assert_eq!(pair[1], pair[0].wrapping_add(1), "capture ids consecutive");
    }
    assert_eq!(
        rig.hardware().violations(),
        0,
        "no safety violation at the outputs"
    );
}
