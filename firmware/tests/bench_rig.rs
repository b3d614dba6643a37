//! What a real bench exercises and the old simulator never did, each in the simulator: camera
//! confirmation and read-out, sessions across a reset, the board's galvo, the rig profile,
//! two-pass homing, exposure timing, and the time limits on light.

use subsurf_firmware::rig::Micros;
use subsurf_firmware::sim::{SimCamera, SimParams, SimRig};
use subsurf_protocol::*;

mod common;
use common::Host;

impl Host {
    /// One request with an explicit `seq`; its single reply's result.
    fn send_one(&mut self, seq: Seq, command: Command) -> Result<Response, RigError> {
        let mut replies = self.send(seq, command);
        assert_eq!(replies.len(), 1);
        replies.remove(0).result
    }

    /// Let `dt` pass with a heartbeat every 100 ms.
    fn advance(&mut self, dt: Micros) {
        let end = self.sim.now() + dt;
        while self.sim.now() < end {
            let t = (self.sim.now() + 100_000).min(end);
            self.sim.advance_to(t);
            self.collect();
            self.call(Command::Heartbeat).unwrap();
        }
    }

    fn status(&mut self) -> Status {
        match self.call(Command::Status) {
            Ok(Response::Status(s)) => s,
            other => panic!("{other:?}"),
        }
    }

    fn captured(&self) -> Vec<Captured> {
        self.events
            .iter()
            .filter_map(|e| match e.kind {
                EventKind::Captured(c) => Some(c),
                _ => None,
            })
            .collect()
    }

    fn home(&mut self) {
        assert_eq!(self.call(Command::Home), Ok(Response::Ack));
        self.advance(20_000_000);
        assert!(
            self.events
                .iter()
                .any(|e| matches!(e.kind, EventKind::Homed { .. })),
            "{:?}",
            self.events
        );
        self.events.clear();
    }
}

fn program(len: u16, exposure_us: u32, interval_us: u32) -> ProgramHeader {
    ProgramHeader {
        len,
        channel: 0,
        settle_us: None,
        exposure_us,
        trigger_us: 10,
        interval_us,
    }
}

fn load(h: &mut Host, header: ProgramHeader) -> Result<Response, RigError> {
    h.call(Command::ProgramLoad(header))?;
    let points: Vec<GalvoPoint> = (0..header.len)
        .map(|i| GalvoPoint {
            x: 30_000 + i * 10,
            y: 30_000,
        })
        .collect();
    for (i, chunk) in points.chunks(PROGRAM_CHUNK).enumerate() {
        h.call(Command::ProgramPoints(ProgramChunk {
            offset: (i * PROGRAM_CHUNK) as u16,
            points: heapless::Vec::from_slice(chunk).unwrap(),
        }))?;
    }
    Ok(Response::Ack)
}

// ---------------------------------------------------------------------------------------------
// Finding 1: capture integrity.

#[test]
fn program_refuses_intervals_shorter_than_exposure_plus_readout() {
    let mut h = Host::new(SimParams::default());
    // The default profile's camera reads out for 10 ms.
    assert_eq!(
        h.call(Command::ProgramLoad(program(4, 1_000, 0))),
        Err(RigError::IntervalTooShort { min_us: 11_000 })
    );
    assert_eq!(
        h.call(Command::ProgramLoad(program(4, 1_000, 10_999))),
        Err(RigError::IntervalTooShort { min_us: 11_000 })
    );
    assert_eq!(load(&mut h, program(4, 1_000, 11_000)), Ok(Response::Ack));
}

#[test]
fn every_capture_is_confirmed_and_counted_by_the_camera() {
    let mut h = Host::new(SimParams::default());
    load(&mut h, program(10, 1_000, 11_000)).unwrap();
    h.call(Command::Arm).unwrap();
    h.call(Command::ProgramRun).unwrap();
    h.advance(200_000);
    let caps = h.captured();
    assert_eq!(caps.len(), 10);
    for (i, c) in caps.iter().enumerate() {
        assert_eq!(c.exposure_count, i as u32 + 1, "capture {i}");
        let e = c.exposure.expect("confirmed");
        assert_eq!((e.delay_us, e.duration_us), (15, 1_000));
        assert!(c.lit);
    }
    assert_eq!(h.sim.hw().exposures(), 10);
    assert_eq!(h.status().exposures, 10);
}

#[test]
fn a_missed_trigger_is_reported_not_shifted() {
    let params = SimParams {
        camera: SimCamera {
            miss_triggers: [Some(3), None, None, None],
            ..SimCamera::default()
        },
        ..SimParams::default()
    };
    let mut h = Host::new(params);
    load(&mut h, program(6, 1_000, 11_000)).unwrap();
    h.call(Command::Arm).unwrap();
    h.call(Command::ProgramRun).unwrap();
    h.advance(200_000);
    let caps = h.captured();
    assert_eq!(caps.len(), 6);
    let counts: Vec<u32> = caps.iter().map(|c| c.exposure_count).collect();
    // Capture 3 got no image: its count does not advance, the later ones are one behind their
    // index. Matching images by count (not by order) puts every image on its own galvo point.
    assert_eq!(counts, vec![1, 2, 3, 3, 4, 5]);
    assert_eq!(caps[3].exposure, None);
    assert!(!caps[3].lit);
    assert!(
        caps.iter()
            .enumerate()
            .all(|(i, c)| i == 3 || c.exposure.is_some())
    );
}

// ---------------------------------------------------------------------------------------------
// Finding 2: sessions.

#[test]
fn a_rebooted_rig_refuses_everything_until_hello_and_says_so_by_nonce() {
    let mut params = SimParams::default();
    let mut h = Host::new(params);
    let before = h.status().boot_nonce;
    assert_eq!(before, params.boot_nonce);
    // Power cycle: a new rig with another nonce; the host retransmits its last Move.
    params.boot_nonce ^= 0xdead_beef;
    let mut rebooted = Host::without_hello(params);
    let seq = h.seq;
    let retransmitted = Command::Move(Move {
        target: MoveTarget::Relative(500),
        max_speed: 1_000,
        accel: 10_000,
    });
    assert_eq!(
        rebooted.send_one(seq, retransmitted.clone()),
        Err(RigError::NoSession)
    );
    assert_eq!(
        rebooted.send_one(seq + 1, Command::Status),
        Err(RigError::NoSession)
    );
    rebooted.advance_without_heartbeat(1_000_000);
    assert_eq!(rebooted.sim.hw().steps(), 0, "the move did not run twice");
    let Ok(Response::Hello(hello)) = rebooted.send_one(
        seq + 2,
        Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        },
    ) else {
        panic!()
    };
    assert_eq!(hello.boot_nonce, params.boot_nonce);
    assert_ne!(hello.boot_nonce, before);
    assert!(
        matches!(rebooted.send_one(seq + 3, Command::Status), Ok(Response::Status(s)) if s.boot_nonce == hello.boot_nonce && !s.homed)
    );
}

impl Host {
    fn advance_without_heartbeat(&mut self, dt: Micros) {
        let t = self.sim.now() + dt;
        self.sim.advance_to(t);
        self.collect();
    }
}

#[test]
fn absolute_moves_need_a_homed_axis() {
    let mut h = Host::new(SimParams::default());
    let to = |t| {
        Command::Move(Move {
            target: MoveTarget::Absolute(t),
            max_speed: 10_000,
            accel: 100_000,
        })
    };
    assert_eq!(h.call(to(100)), Err(RigError::NotHomed));
    h.home();
    assert_eq!(h.call(to(100)), Ok(Response::Ack));
    h.advance(500_000);
    assert_eq!(h.status().position, 100);
}

#[test]
fn stop_decelerates_and_clears_homed_estop_cuts_at_once() {
    let mut h = Host::new(SimParams::default());
    h.home();
    let long = Command::Move(Move {
        target: MoveTarget::Relative(10_000),
        max_speed: 10_000,
        accel: 50_000,
    });
    let (pos0, steps0) = (h.status().position, h.sim.hw().steps());
    h.call(long.clone()).unwrap();
    // Cruising at 10 000 steps/s after 0.5 s.
    h.advance_without_heartbeat(500_000);
    let at_stop = h.sim.hw().steps();
    h.call(Command::Stop).unwrap();
    assert!(h.sim.rig().moving(), "a stop request decelerates");
    assert!(!h.status().homed, "a halt that cuts a motion clears homed");
    h.advance(1_000_000);
    assert!(!h.sim.rig().moving());
    // v²/2a = 1000 steps of ramp-down after the steps already queued (at most PLAN_AHEAD_US of
    // them, 100 at 10 000 steps/s), never faster than cruise.
    let braking = h.sim.hw().steps() - at_stop;
    assert!((990..=1_110).contains(&braking), "{braking} braking steps");
    assert_eq!(
        (h.status().position - pos0) as u64,
        h.sim.hw().steps() - steps0
    );
    // E-stop: no more steps at all.
    h.home();
    h.call(long).unwrap();
    h.advance_without_heartbeat(500_000);
    let at_estop = h.sim.hw().steps();
    let now = h.sim.now();
    h.sim.set_estop(now, true);
    h.collect();
    assert!(!h.sim.rig().moving());
    h.advance(100_000);
    assert_eq!(h.sim.hw().steps(), at_estop);
    assert!(!h.status().homed);
}

// ---------------------------------------------------------------------------------------------
// Finding 3: the simulator's galvo is the board's.

#[test]
fn boot_centres_the_mirror_and_never_slams_it_to_zero() {
    for params in [SimParams::default(), SimParams::internal_dac()] {
        let sim = SimRig::new(params);
        let c = params.profile.galvo.output.center();
        let log: Vec<GalvoPoint> = sim.hw().galvo_log().entries().map(|e| e.value).collect();
        assert_eq!(log, vec![GalvoPoint { x: c, y: c }]);
    }
}

#[test]
fn internal_dac_rig_settles_by_its_own_model() {
    // The board's fallback path: 12-bit codes, 300 µs per 1000 codes. The simulator's mirror
    // follows the profile, so an exposure on a moving mirror is counted.
    let mut h = Host::new(SimParams::internal_dac());
    h.call(Command::Arm).unwrap();
    let far = |settle_us| {
        Command::Capture(Capture {
            galvo: GalvoPoint { x: 4095, y: 0 },
            settle_us,
            channel: 0,
            exposure_us: 100,
            trigger_us: 10,
        })
    };
    assert!(matches!(
        h.call(Command::Galvo(GalvoPoint { x: 4096, y: 0 })),
        Err(RigError::OutOfRange)
    ));
    // The settle from the profile: no smear.
    h.call(far(None)).unwrap();
    h.advance(20_000);
    assert_eq!(h.sim.hw().unsettled_exposures(), 0);
    // The 16-bit figure (20 µs/kcode) on this galvo: the spot moves during the exposure.
    h.call(Command::Galvo(GalvoPoint { x: 0, y: 0 })).unwrap();
    h.call(far(Some(100 + 4095 * 20 / 1000))).unwrap();
    h.advance(20_000);
    assert_eq!(h.sim.hw().unsettled_exposures(), 1);
}

// ---------------------------------------------------------------------------------------------
// Finding 4: mechanics and I/O as configuration.

#[test]
fn profile_is_validated_applied_and_handed_to_flash() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(
        h.call(Command::GetProfile),
        Ok(Response::Profile(RigProfile::DEFAULT))
    );
    let mut bad = RigProfile::DEFAULT;
    bad.motor.step_pulse_us = 1;
    assert_eq!(
        h.call(Command::SetProfile(bad)),
        Err(RigError::BadProfile(ProfileError::StepTiming))
    );
    assert_eq!(h.sim.hw().saves(), 0);
    let mut p = RigProfile::DEFAULT;
    p.motor.microsteps = 32;
    p.laser.channels = 1;
    p.galvo = RigProfile::INTERNAL_DAC;
    h.home();
    assert_eq!(h.call(Command::SetProfile(p)), Ok(Response::Ack));
    assert_eq!(h.sim.hw().saves(), 1);
    assert_eq!(h.call(Command::GetStoredProfile), Ok(Response::Profile(p)));
    let s = h.status();
    assert!(!s.homed, "new mechanics: home again");
    assert_eq!(s.galvo, GalvoPoint { x: 2048, y: 2048 });
    let Ok(Response::Hello(hello)) = h.call(Command::Hello {
        protocol_version: PROTOCOL_VERSION,
    }) else {
        panic!()
    };
    assert_eq!(hello.capabilities.steps_per_rev, 32_000);
    assert_eq!(hello.capabilities.galvo_max, 4095);
    assert_eq!(hello.capabilities.laser_channels, 1);
    h.call(Command::Arm).unwrap();
    assert_eq!(
        h.call(Command::Laser {
            channel: 1,
            on: true
        }),
        Err(RigError::NoSuchChannel)
    );
}

// ---------------------------------------------------------------------------------------------
// Finding 5: two-pass homing, repeatable.

/// Physical position of home (hardware position where the rig says 0), modulo a revolution.
fn homed_at(start_position: i64, speed: u32) -> i64 {
    let mut params = SimParams {
        start_position,
        ..SimParams::default()
    };
    params.profile.homing.speed = speed;
    let mut h = Host::new(params);
    h.home();
    assert_eq!(h.status().position, 0);
    let rev = i64::from(params.profile.steps_per_rev().unwrap());
    (h.sim.hw().position() - i64::from(h.status().position)).rem_euclid(rev)
}

#[test]
fn homing_is_repeatable_from_any_start_and_speed() {
    // On the switch at either end of its 40-step band, just above it, far away; fast approaches
    // at three speeds (steps are planned ahead, so the switch is always seen with steps queued).
    let mut seen = Vec::new();
    for start in [0, 20, 39, 45, 4_000, 15_990] {
        for speed in [2_000, 8_000, 12_000] {
            seen.push((homed_at(start, speed), start, speed));
        }
    }
    let min = seen.iter().map(|s| s.0).min().unwrap();
    let max = seen.iter().map(|s| s.0).max().unwrap();
    assert!(max - min <= 1, "home spread {} steps: {seen:?}", max - min);
}

#[test]
fn homing_faults_when_the_switch_never_releases() {
    let params = SimParams {
        home_switch_width: 20_000,
        ..SimParams::default()
    };
    let mut h = Host::new(params);
    h.call(Command::Home).unwrap();
    h.advance(60_000_000);
    assert!(h.events.iter().any(|e| e.kind
        == EventKind::Halted {
            reason: HaltReason::HomingFailed
        }));
}

// ---------------------------------------------------------------------------------------------
// Finding 6: exposure timing.

#[test]
fn exposures_below_the_hardware_minimum_are_refused() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Arm).unwrap();
    let c = |exposure_us| {
        Command::Capture(Capture {
            galvo: GalvoPoint::default(),
            settle_us: Some(0),
            channel: 0,
            exposure_us,
            trigger_us: 1,
        })
    };
    assert_eq!(h.call(c(1)), Err(RigError::ExposureTooShort { min_us: 20 }));
    assert!(matches!(h.call(c(20)), Ok(Response::CaptureStarted { .. })));
}

fn latency_capture(lead_us: u32, tail_us: u32) -> Captured {
    let mut params = SimParams {
        camera: SimCamera {
            timer_latency_us: 30,
            ..SimCamera::default()
        },
        ..SimParams::default()
    };
    params.profile.laser.lead_us = lead_us;
    params.profile.laser.tail_us = tail_us;
    let mut h = Host::new(params);
    h.call(Command::Arm).unwrap();
    h.call(Command::Capture(Capture {
        galvo: GalvoPoint::default(),
        settle_us: Some(0),
        channel: 0,
        exposure_us: 200,
        trigger_us: 10,
    }))
    .unwrap();
    h.advance(20_000);
    h.captured()[0]
}

#[test]
fn trigger_edge_is_timestamped_and_the_laser_window_covers_latency() {
    // The rig reports the edge the hardware saw (30 µs after it drove the pin), and with the
    // margins the whole exposure is lit.
    let c = latency_capture(50, 50);
    let e = c.exposure.unwrap();
    assert_eq!(e.delay_us, 15);
    assert!(c.lit);
    // Window starting at the trigger with no tail (the old firmware): latency cuts the end.
    let c0 = latency_capture(0, 0);
    assert!(!c0.lit, "{c0:?}");
    assert_eq!(c0.triggered_at_us, c.triggered_at_us - 50);
}

// ---------------------------------------------------------------------------------------------
// Finding 7: time limits on light.

#[test]
fn heartbeat_timeout_is_capped_at_a_few_seconds() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(
        h.call(Command::SetConfig(Config {
            heartbeat_timeout_ms: 600_000
        })),
        Err(RigError::OutOfRange)
    );
    assert_eq!(
        h.call(Command::SetConfig(Config {
            heartbeat_timeout_ms: MAX_HEARTBEAT_TIMEOUT_MS
        })),
        Ok(Response::Ack)
    );
}

#[test]
fn manual_laser_goes_off_by_itself() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Arm).unwrap();
    h.call(Command::Laser {
        channel: 0,
        on: true,
    })
    .unwrap();
    // Heartbeats keep the link alive; the profile's 10 s still ends it.
    h.advance(9_900_000);
    assert_eq!(h.sim.hw().lasers(), 1);
    h.advance(200_000);
    assert_eq!(h.sim.hw().lasers(), 0);
    assert!(h.events.iter().any(|e| e.kind
        == EventKind::Halted {
            reason: HaltReason::LaserTimeout
        }));
    assert!(!h.sim.rig().armed());
}

#[test]
fn a_stalled_step_generator_faults_and_drops_homed() {
    let mut h = Host::new(SimParams::default());
    h.home();
    h.call(Command::Move(Move {
        target: MoveTarget::Relative(5_000),
        max_speed: 10_000,
        accel: 100_000,
    }))
    .unwrap();
    h.advance_without_heartbeat(100_000);
    let now = h.sim.now();
    h.sim.rig_mut().handle_stall(now);
    h.collect();
    let s = h.status();
    assert_eq!(s.fault, Some(Fault::StepStall));
    assert!(!s.homed);
    assert!(!h.sim.rig().moving());
}

#[test]
fn homing_twice_reports_the_drift_between_the_two_zeros() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Home).unwrap();
    h.advance(20_000_000);
    assert!(
        h.events
            .iter()
            .any(|e| e.kind == EventKind::Homed { previous: None }),
        "first homing has nothing to compare with: {:?}",
        h.events
    );
    h.events.clear();
    h.call(Command::Move(Move {
        target: MoveTarget::Absolute(5_000),
        max_speed: 10_000,
        accel: 100_000,
    }))
    .unwrap();
    h.advance(1_000_000);
    h.events.clear();
    h.call(Command::Home).unwrap();
    h.advance(20_000_000);
    assert!(
        h.events
            .iter()
            .any(|e| e.kind == EventKind::Homed { previous: Some(0) }),
        "{:?}",
        h.events
    );
}
