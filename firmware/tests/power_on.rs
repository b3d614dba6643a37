//! The board's first power-on on a real bench: each finding the simulator can show, in the
//! simulator (the board-only ones are in `board_model.rs` and `pulse_train.rs`).

use subsurf_firmware::rig::Micros;
use subsurf_firmware::sim::{SimCamera, SimParams};
use subsurf_protocol::*;

mod common;
use common::Host;

impl Host {
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

    fn advance_quietly(&mut self, dt: Micros) {
        let t = self.sim.now() + dt;
        self.sim.advance_to(t);
        self.collect();
    }

    fn status(&mut self) -> Status {
        match self.call(Command::Status) {
            Ok(Response::Status(s)) => s,
            other => panic!("{other:?}"),
        }
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

    fn halted(&self, reason: HaltReason) -> bool {
        self.events
            .iter()
            .any(|e| e.kind == EventKind::Halted { reason })
    }
}

fn move_by(steps: i32) -> Command {
    Command::Move(Move {
        target: MoveTarget::Relative(steps),
        max_speed: 10_000,
        accel: 50_000,
    })
}

fn move_to(position: i32) -> Command {
    Command::Move(Move {
        target: MoveTarget::Absolute(position),
        max_speed: 10_000,
        accel: 50_000,
    })
}

// ---------------------------------------------------------------------------------------------
// Finding 4: an e-stop while idle keeps `homed`.

#[test]
fn an_estop_while_idle_forgets_the_home_position() {
    let mut h = Host::new(SimParams::default());
    h.home();
    assert!(h.status().homed);
    // Nothing moves; the e-stop cuts the drivers' power and someone turns the table by hand.
    let now = h.sim.now();
    h.sim.set_estop(now + 1_000, true);
    h.collect();
    h.advance(100_000);
    let now = h.sim.now();
    h.sim.set_estop(now + 1_000, false);
    h.collect();
    assert_eq!(h.call(Command::ClearFault), Ok(Response::Ack));
    let s = h.status();
    assert!(!s.homed, "homed survived an e-stop: {s:?}");
    assert_eq!(h.call(move_to(100)), Err(RigError::NotHomed));
}

// ---------------------------------------------------------------------------------------------
// Finding 6: any request refreshes the heartbeat, even a refused one.

#[test]
fn refused_requests_do_not_keep_the_laser_on() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Arm).unwrap();
    h.call(Command::Laser {
        channel: 0,
        on: true,
    })
    .unwrap();
    assert_eq!(h.sim.hw().lasers(), 1);
    // A stuck host retransmits a request the rig refuses, every 100 ms, for 3 s (the heartbeat
    // timeout is 2 s): only accepted requests show a host that is listening.
    let refused = Command::Laser {
        channel: 7,
        on: true,
    };
    for _ in 0..30 {
        h.advance_quietly(100_000);
        assert_eq!(h.call(refused.clone()), Err(RigError::NoSuchChannel));
    }
    assert_eq!(h.sim.hw().lasers(), 0, "the laser stayed on");
    assert!(h.halted(HaltReason::HeartbeatLost), "{:?}", h.events);
    assert!(!h.sim.rig().armed());
}

#[test]
fn requests_before_a_session_do_not_count_as_heartbeats() {
    let mut h = Host::without_hello(SimParams::default());
    h.call(Command::Status).unwrap_err();
    assert!(!h.sim.rig().link_alive());
}

// ---------------------------------------------------------------------------------------------
// Finding 10: an open interlock does not stop motion.

#[test]
fn an_open_interlock_holds_the_feed_and_refuses_motion() {
    let mut h = Host::new(SimParams::default());
    h.call(move_by(20_000)).unwrap();
    h.advance(400_000);
    assert!(h.sim.rig().moving());
    let now = h.sim.now();
    h.sim.set_interlock(now, false);
    h.collect();
    assert!(h.halted(HaltReason::InterlockOpen), "{:?}", h.events);
    // Decelerated to rest (10 000 steps/s at 50 000 steps/s²: v²/2a = 1000 steps, after the up
    // to 100 steps planned ahead), not cut dead and not run to its end.
    let at_open = h.sim.hw().steps();
    h.advance(1_000_000);
    assert!(!h.sim.rig().moving());
    let braking = h.sim.hw().steps() - at_open;
    assert!((990..=1_110).contains(&braking), "{braking} braking steps");
    assert_eq!(h.call(move_by(100)), Err(RigError::InterlockOpen));
    assert_eq!(h.call(Command::Home), Err(RigError::InterlockOpen));
    let now = h.sim.now();
    h.sim.set_interlock(now, true);
    h.collect();
    assert_eq!(h.call(move_by(100)), Ok(Response::Ack));
}

// ---------------------------------------------------------------------------------------------
// Finding 3: `lit` judged against the scheduled window, not the one the timer ran.

fn capture_with_timer_latency(latency_us: u32, tail_us: u32) -> Captured {
    let mut params = SimParams {
        camera: SimCamera {
            timer_latency_us: latency_us,
            ..SimCamera::default()
        },
        ..SimParams::default()
    };
    params.profile.laser.tail_us = tail_us;
    let mut h = Host::new(params);
    h.call(Command::Arm).unwrap();
    h.call(Command::Capture(Capture {
        galvo: GalvoPoint::default(),
        settle_us: Some(0),
        channel: 0,
        exposure_us: 1_000,
        trigger_us: 10,
    }))
    .unwrap();
    h.advance(50_000);
    let captured: Vec<Captured> = h
        .events
        .iter()
        .filter_map(|e| match e.kind {
            EventKind::Captured(c) => Some(c),
            _ => None,
        })
        .collect();
    assert_eq!(captured.len(), 1, "{:?}", h.events);
    assert_eq!(
        h.sim.hw().unlit_exposures(),
        0,
        "the simulated light missed the exposure"
    );
    captured[0]
}

#[test]
fn lit_is_judged_by_the_window_the_timer_ran() {
    // The rig task woke 120 µs late: the one-pulse timer (laser on, trigger edge, laser off) ran
    // 120 µs after the schedule, and the exposure (15 µs after the edge, 1 ms long) sat inside the
    // light with the default 50 µs margins. A scan stops on "not lit": it must not say so here.
    let c = capture_with_timer_latency(120, 50);
    assert!(c.lit, "a lit exposure reported as not lit: {c:?}");
    let e = c.exposure.unwrap();
    assert_eq!(e.delay_us, 15);
    // A tail shorter than the camera's own delay still fails, wherever the window lay.
    let mut params = SimParams::default();
    params.profile.laser.tail_us = 0;
    let c0 = {
        let mut h = Host::new(params);
        h.call(Command::Arm).unwrap();
        h.call(Command::Capture(Capture {
            galvo: GalvoPoint::default(),
            settle_us: Some(0),
            channel: 0,
            exposure_us: 1_000,
            trigger_us: 10,
        }))
        .unwrap();
        h.advance(50_000);
        h.events
            .iter()
            .find_map(|e| match e.kind {
                EventKind::Captured(c) => Some(c),
                _ => None,
            })
            .unwrap()
    };
    assert!(!c0.lit, "{c0:?}");
}

// ---------------------------------------------------------------------------------------------
// Finding 5: homing brakes by a hard stop, then restarts at cruise speed.

#[test]
fn homing_brakes_on_a_ramp_and_never_stops_dead_at_speed() {
    // Far from the switch: the fast approach (8 000 steps/s) sees it with steps queued ahead,
    // the release pass too; each must ramp down from its speed. Only the slow approach
    // (1 000 steps/s, "slow enough to stop within one step") may stop dead at the edge.
    for start in [4_000, 12_345] {
        let params = SimParams {
            start_position: start,
            ..SimParams::default()
        };
        let slow = params.profile.homing.slow_speed;
        let mut h = Host::new(params);
        h.home();
        let fastest = h.sim.hw().fastest_hard_stop();
        assert!(
            fastest <= slow + slow / 10,
            "from {start}: stopped dead at {fastest} steps/s (slow speed {slow})"
        );
        assert_eq!(h.sim.hw().violations(), 0);
    }
}

// ---------------------------------------------------------------------------------------------
// Finding 1: light at every boot with active-low lasers. The board reads the profile before it
// drives any laser or trigger pin; with none stored it keeps them high-impedance (the external
// pull resistors hold them off) and the core refuses to arm until a profile is set.

#[test]
fn a_rig_without_a_stored_profile_refuses_light_until_one_is_set() {
    use subsurf_firmware::Rig;
    use subsurf_firmware::sim::SimHardware;
    let params = SimParams::default();
    let hw = SimHardware::new(params.profile, params.camera, 0, 40);
    let mut rig = Rig::new_unconfigured(hw, Config::DEFAULT, 7, 0);
    assert!(!rig.profile_known());
    let mut seq = 0;
    let mut call = |rig: &mut Rig<SimHardware>, command| {
        seq += 1;
        rig.handle_request(0, Request { seq, command });
        let mut result = None;
        while let Some(m) = rig.poll_message() {
            if let RigMessage::Reply(r) = m {
                result = Some(r.result);
            }
        }
        result.expect("a reply")
    };
    call(
        &mut rig,
        Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        },
    )
    .unwrap();
    assert_eq!(
        call(&mut rig, Command::Arm),
        Err(RigError::ProfileNotStored)
    );
    assert_eq!(
        rig.hw().laser_log().total(),
        1,
        "only the boot's lasers-off"
    );
    // An invalid stored profile is no profile either.
    let mut bad = RigProfile::DEFAULT;
    bad.laser.channels = 0;
    let hw = SimHardware::new(params.profile, params.camera, 0, 40);
    assert!(!Rig::new(hw, bad, Config::DEFAULT, 7, 0).profile_known());
    // The host sets the wiring's profile: now the rig knows the polarities.
    let mut wiring = RigProfile::DEFAULT;
    wiring.laser.active_low = true;
    assert_eq!(
        call(&mut rig, Command::SetProfile(wiring)),
        Ok(Response::Ack)
    );
    assert!(rig.profile_known());
    assert_eq!(call(&mut rig, Command::Arm), Ok(Response::Ack));
}

// ---------------------------------------------------------------------------------------------
// Finding 2: a profile save blocks every interrupt while the flash erases, so the core stores
// the profile only while nothing moves or emits (inside `SetProfile`, which a moving rig
// refuses, since a save is answered only once flash reads it back).

#[test]
fn the_profile_is_persisted_only_while_idle_and_dark() {
    let mut h = Host::new(SimParams::default());
    let mut p = RigProfile::DEFAULT;
    p.motor.microsteps = 32;
    h.call(move_by(2_000)).unwrap();
    assert_eq!(h.call(Command::SetProfile(p)), Err(RigError::Busy));
    assert_eq!(h.sim.hw().saves(), 0);
    h.advance(2_000_000);
    assert!(!h.sim.rig().moving());
    // Armed with a laser on: the save switches it off and disarms first.
    h.call(Command::Arm).unwrap();
    h.call(Command::Laser {
        channel: 0,
        on: true,
    })
    .unwrap();
    assert_ne!(h.sim.hw().lasers(), 0);
    assert_eq!(h.call(Command::SetProfile(p)), Ok(Response::Ack));
    assert_eq!(h.sim.hw().saves(), 1);
    assert_eq!(h.sim.hw().lasers(), 0);
    assert_eq!(h.sim.hw().violations(), 0, "stored while moving or lit");
    assert!(!h.status().armed);
}

// ---------------------------------------------------------------------------------------------
// Finding 6: the light's deadlines for a hardware timer (the board arms one a little after
// them, so a stuck executor cannot keep a laser on).

#[test]
fn the_light_deadline_is_the_earliest_of_heartbeat_manual_limit_and_window() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(
        h.sim.rig().light_deadline(),
        None,
        "dark: nothing to enforce"
    );
    h.call(Command::Arm).unwrap();
    assert_eq!(h.sim.rig().light_deadline(), None, "armed but dark");
    let t0 = h.sim.now();
    h.call(Command::Laser {
        channel: 0,
        on: true,
    })
    .unwrap();
    // The heartbeat (2 s) comes before the manual limit (10 s).
    assert_eq!(h.sim.rig().light_deadline(), Some(t0 + 2_000_000));
    // An accepted request moves it; a refused one does not.
    h.advance_quietly(500_000);
    h.call(Command::Laser {
        channel: 7,
        on: true,
    })
    .unwrap_err();
    assert_eq!(h.sim.rig().light_deadline(), Some(t0 + 2_000_000));
    h.call(Command::Heartbeat).unwrap();
    assert_eq!(h.sim.rig().light_deadline(), Some(t0 + 2_500_000));
    h.call(Command::Laser {
        channel: 0,
        on: false,
    })
    .unwrap();
    assert_eq!(h.sim.rig().light_deadline(), None);
    // A capture's window: its scheduled laser-off.
    h.call(Command::Capture(Capture {
        galvo: GalvoPoint::default(),
        settle_us: Some(0),
        channel: 0,
        exposure_us: 1_000,
        trigger_us: 10,
    }))
    .unwrap();
    let now = h.sim.now();
    let d = h.sim.rig().light_deadline().expect("a window ahead");
    assert!(d > now && d <= now + 1_200, "{d} vs {now}");
}
