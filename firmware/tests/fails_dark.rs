//! The board on a real bench after its first power-on (`power_on.rs`): what happens when
//! something else fails (a wrong profile, a save that did not happen, a late step interrupt, an
//! unconfigured board), each finding the simulator can show, in the simulator (the board-only
//! ones are in `board_model.rs` and `pulse_train.rs`).

use subsurf_firmware::sim::SimParams;
use subsurf_protocol::*;

mod common;
use common::Host;

// ---------------------------------------------------------------------------------------------
// Finding B: a profile whose laser polarity is not the wiring's. The board reads its undriven
// laser lines (the wiring's resistors hold them at the off level) and the core refuses to arm,
// so nothing ever asks for light.

#[test]
fn a_wrong_laser_polarity_refuses_to_arm_and_no_laser_is_ever_driven() {
    for stored_active_low in [false, true] {
        let mut params = SimParams::default();
        params.profile.laser.active_low = stored_active_low;
        let mut h = Host::new(params);
        h.sim
            .rig_mut()
            .hw_mut()
            .set_laser_wiring(!stored_active_low);
        assert_eq!(h.call(Command::Arm), Err(RigError::LaserPolarity));
        assert_eq!(
            h.call(Command::Laser {
                channel: 0,
                on: true
            }),
            Err(RigError::NotArmed)
        );
        assert!(
            h.sim.hw().laser_log().entries().all(|e| e.value == 0),
            "a laser was driven"
        );
        // Sending the wiring's polarity fixes it.
        let mut right = params.profile;
        right.laser.active_low = !stored_active_low;
        assert_eq!(h.call(Command::SetProfile(right)), Ok(Response::Ack));
        assert_eq!(h.call(Command::Arm), Ok(Response::Ack));
    }
}

// ---------------------------------------------------------------------------------------------
// Finding E: `SetProfile` was acknowledged before the flash write, and a failed write went only
// to the board's log: after a reset the old profile (and its polarity) came back unannounced. The
// reply now waits for the write and its read-back.

#[test]
fn a_save_is_acknowledged_only_once_flash_holds_it() {
    let mut h = Host::new(SimParams::default());
    let old = RigProfile::DEFAULT;
    let mut new = old;
    new.laser.active_low = !old.laser.active_low;
    for error in [SaveError::Erase, SaveError::Program, SaveError::Verify] {
        h.sim.rig_mut().hw_mut().fail_next_save(error);
        assert_eq!(
            h.call(Command::SetProfile(new)),
            Err(RigError::ProfileNotSaved(error))
        );
        // Nothing changed: the profile in force is the one flash holds, the one a reset brings.
        assert_eq!(h.call(Command::GetProfile), Ok(Response::Profile(old)));
        assert_eq!(
            h.call(Command::GetStoredProfile),
            Ok(Response::Profile(old))
        );
    }
    assert_eq!(h.sim.hw().saves(), 0);
    assert_eq!(h.call(Command::SetProfile(new)), Ok(Response::Ack));
    assert_eq!(h.sim.hw().saves(), 1);
    assert_eq!(
        h.call(Command::GetStoredProfile),
        Ok(Response::Profile(new))
    );
    // A blank flash says so.
    h.sim.rig_mut().hw_mut().erase_stored_profile();
    assert_eq!(
        h.call(Command::GetStoredProfile),
        Err(RigError::ProfileNotStored)
    );
}

// ---------------------------------------------------------------------------------------------
// Finding C: a step interrupt later than one period made the timer repeat a period, a step nobody
// counted. The board's train detects it (`pulse_train.rs`, its test) and stops the timer; the
// core then faults, stops the motion at once, forgets `homed` and reports it.

#[test]
fn a_late_step_interrupt_stops_the_motion_and_is_reported() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(h.call(Command::Home), Ok(Response::Ack));
    for _ in 0..200 {
        let t = h.sim.now() + 100_000;
        h.sim.advance_to(t);
        h.collect();
        h.call(Command::Heartbeat).unwrap();
    }
    assert!(
        h.events
            .iter()
            .any(|e| matches!(e.kind, EventKind::Homed { .. }))
    );
    let mv = Command::Move(Move {
        target: MoveTarget::Relative(8_000),
        max_speed: 8_000,
        accel: 40_000,
    });
    assert_eq!(h.call(mv), Ok(Response::Ack));
    let t = h.sim.now() + 200_000;
    h.sim.advance_to(t);
    h.collect();
    assert!(h.sim.rig().moving());
    let now = h.sim.now();
    h.sim.rig_mut().handle_step_late(now);
    h.collect();
    assert!(!h.sim.rig().moving(), "still moving");
    assert_eq!(h.sim.rig().fault(), Some(Fault::StepLate));
    assert!(h.events.iter().any(|e| matches!(
        e.kind,
        EventKind::Halted {
            reason: HaltReason::StepLate
        }
    )));
    let Ok(Response::Status(st)) = h.call(Command::Status) else {
        panic!("status")
    };
    assert!(!st.homed);
    assert_eq!(
        h.call(Command::Move(Move {
            target: MoveTarget::Absolute(0),
            max_speed: 8_000,
            accel: 40_000,
        })),
        Err(RigError::Faulted(Fault::StepLate))
    );
}

// ---------------------------------------------------------------------------------------------
// Finding G: without a profile only `Arm` was refused; `Home` and `Move` ran on guessed
// mechanics (and the board energised EN at boot). Now they are refused too, and the board keeps
// EN released until a profile is stored and the e-stop reads closed (`rig::follow_enable`).

#[test]
fn an_unconfigured_rig_refuses_motion_until_a_profile_is_stored() {
    use subsurf_firmware::Rig;
    use subsurf_firmware::sim::SimHardware;
    let params = SimParams::default();
    let hw = SimHardware::new(params.profile, params.camera, 0, 40);
    let mut rig = Rig::new_unconfigured(hw, Config::DEFAULT, 7, 0);
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
    let mv = Command::Move(Move {
        target: MoveTarget::Relative(100),
        max_speed: 1_000,
        accel: 10_000,
    });
    assert_eq!(
        call(&mut rig, Command::Home),
        Err(RigError::ProfileNotStored)
    );
    assert_eq!(call(&mut rig, mv.clone()), Err(RigError::ProfileNotStored));
    assert_eq!(rig.hw().steps(), 0);
    assert_eq!(
        call(&mut rig, Command::SetProfile(RigProfile::DEFAULT)),
        Ok(Response::Ack)
    );
    assert_eq!(call(&mut rig, mv), Ok(Response::Ack));
}
