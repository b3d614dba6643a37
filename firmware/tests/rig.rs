//! The firmware core on simulated hardware: commands, timing, retransmissions and safety trips.

use subsurf_firmware::rig::{FIRMWARE_VERSION, Micros};
use subsurf_firmware::sim::{SimParams, SimRig};
use subsurf_protocol::*;

mod common;
use common::Host;

impl Host {
    fn advance(&mut self, dt: Micros) {
        let t = self.sim.now() + dt;
        self.sim.advance_to(t);
        self.collect();
    }

    fn kinds(&self) -> Vec<EventKind> {
        self.events.iter().map(|e| e.kind.clone()).collect()
    }
}

fn mv(target: MoveTarget) -> Command {
    Command::Move(Move {
        target,
        max_speed: 10_000,
        accel: 100_000,
    })
}

fn capture(x: u16, channel: u8) -> Capture {
    Capture {
        galvo: GalvoPoint { x, y: 0 },
        settle_us: None,
        channel,
        exposure_us: 5_000,
        trigger_us: 100,
    }
}

#[test]
fn hello_announces_version_and_capabilities() {
    let mut h = Host::new(SimParams::default());
    match h.call(Command::Hello {
        protocol_version: PROTOCOL_VERSION,
    }) {
        Ok(Response::Hello(hello)) => {
            assert_eq!(hello.protocol_version, PROTOCOL_VERSION);
            assert_eq!(hello.firmware_version, FIRMWARE_VERSION);
            assert_eq!(
                hello.capabilities,
                subsurf_firmware::rig::capabilities(&SimParams::default().profile)
            );
            assert_eq!(hello.boot_nonce, SimParams::default().boot_nonce);
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(
        h.call(Command::Hello {
            protocol_version: PROTOCOL_VERSION + 1
        }),
        Err(RigError::UnknownVersion {
            rig: PROTOCOL_VERSION
        })
    );
}

#[test]
fn move_takes_exact_steps_within_speed_limit() {
    let mut h = Host::new(SimParams::default());
    let start = h.sim.hw().position();
    assert_eq!(h.call(mv(MoveTarget::Relative(1000))), Ok(Response::Ack));
    assert_eq!(h.call(mv(MoveTarget::Relative(5))), Err(RigError::Busy));
    h.advance(1_000_000);
    assert_eq!(h.kinds(), vec![EventKind::MoveDone { position: 1000 }]);
    assert_eq!(h.sim.hw().position() - start, 1000);
    assert_eq!(h.sim.hw().steps(), 1000);
    // 10 000 steps/s: never closer than 100 µs, less the planner's timing tolerance (a step
    // may come up to 5 µs early) and 1 µs of rounding.
    let tolerance = subsurf_firmware::stepcompress::MAX_STEP_ERROR_US;
    assert!(h.sim.hw().min_step_interval_us().unwrap() >= 100 - tolerance - 1);
    assert_eq!(h.call(mv(MoveTarget::Relative(-1500))), Ok(Response::Ack));
    h.advance(1_000_000);
    assert_eq!(
        h.events.last().unwrap().kind,
        EventKind::MoveDone { position: -500 }
    );
    assert_eq!(h.sim.hw().position() - start, -500);
}

#[test]
fn move_parameters_are_checked() {
    let mut h = Host::new(SimParams::default());
    let bad_speed = Move {
        target: MoveTarget::Absolute(10),
        max_speed: 0,
        accel: 1,
    };
    assert_eq!(h.call(Command::Move(bad_speed)), Err(RigError::OutOfRange));
    let too_fast = Move {
        target: MoveTarget::Absolute(10),
        max_speed: 1_000_000,
        accel: 1,
    };
    assert_eq!(h.call(Command::Move(too_fast)), Err(RigError::OutOfRange));
    assert_eq!(h.call(mv(MoveTarget::Relative(-3))), Ok(Response::Ack));
    h.advance(100_000);
    assert_eq!(
        h.call(mv(MoveTarget::Relative(i32::MIN))),
        Err(RigError::OutOfRange)
    );
    assert_eq!(h.call(mv(MoveTarget::Relative(0))), Ok(Response::Ack));
    assert_eq!(
        h.events.last().unwrap().kind,
        EventKind::MoveDone { position: -3 }
    );
}

#[test]
fn homing_finds_the_switch_and_zeroes_position() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(h.call(Command::Home), Ok(Response::Ack));
    for _ in 0..12 {
        h.advance(500_000);
        h.call(Command::Heartbeat).unwrap();
    }
    assert_eq!(h.kinds(), vec![EventKind::Homed { previous: None }]);
    assert!(h.sim.hw().home_switch());
    let Ok(Response::Status(s)) = h.call(Command::Status) else {
        panic!()
    };
    assert!(s.homed);
    assert_eq!(s.position, 0);
    assert_eq!(s.state, RigState::Idle);
}

#[test]
fn homing_without_switch_faults() {
    let params = SimParams {
        home_switch_width: 0,
        ..SimParams::default()
    };
    let mut h = Host::new(params);
    assert_eq!(h.call(Command::Home), Ok(Response::Ack));
    for _ in 0..10 {
        h.advance(500_000);
        h.call(Command::Heartbeat).unwrap();
    }
    assert_eq!(
        h.kinds(),
        vec![EventKind::Halted {
            reason: HaltReason::HomingFailed
        }]
    );
    // 16 000 + 2 000 steps searched, then gave up.
    assert_eq!(h.sim.hw().steps(), 18_000);
    assert_eq!(
        h.call(Command::Arm),
        Err(RigError::Faulted(Fault::HomingFailed))
    );
    assert_eq!(h.call(Command::ClearFault), Ok(Response::Ack));
    assert_eq!(h.call(Command::Arm), Ok(Response::Ack));
}

#[test]
fn capture_sequence_timing() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(
        h.call(Command::Capture(capture(1000, 1))),
        Err(RigError::NotArmed)
    );
    assert_eq!(h.call(Command::Arm), Ok(Response::Ack));
    let t0 = h.sim.now();
    assert_eq!(
        h.call(Command::Capture(capture(1000, 1))),
        Ok(Response::CaptureStarted { capture_id: 0 })
    );
    assert_eq!(
        h.call(Command::Capture(capture(1000, 1))),
        Err(RigError::Busy)
    );
    h.advance(20_000);
    // Settle from jump size: 100 µs + 20 µs per 1000 codes of the larger axis jump from the
    // centred mirror (y: 32 768 to 0); the laser
    // leads the trigger by 50 µs and trails the 5 ms exposure by 50 µs.
    let on = t0 + 100 + 32_768 * 20 / 1000;
    let trig_at = on + 50;
    let lasers: Vec<_> = h
        .sim
        .hw()
        .laser_log()
        .entries()
        .map(|e| (e.at, e.value))
        .collect();
    assert_eq!(lasers, vec![(0, 0), (on, 0b10), (trig_at + 5_050, 0)]);
    let trig: Vec<_> = h
        .sim
        .hw()
        .trigger_log()
        .entries()
        .map(|e| (e.at, e.value))
        .collect();
    assert_eq!(
        trig,
        vec![(0, false), (trig_at, true), (trig_at + 100, false)]
    );
    let galvo = h.sim.hw().galvo_log().last().unwrap();
    assert_eq!((galvo.at, galvo.value), (t0, GalvoPoint { x: 1000, y: 0 }));
    // The simulated camera exposes 15 µs after the trigger edge, for the 5 ms exposure.
    let expected = Captured {
        capture_id: 0,
        program_index: None,
        triggered_at_us: trig_at,
        exposure: Some(ExposureActive {
            delay_us: 15,
            duration_us: 5_000,
        }),
        exposure_count: 1,
        lit: true,
        galvo: GalvoPoint { x: 1000, y: 0 },
        channel: 1,
    };
    assert_eq!(h.kinds(), vec![EventKind::Captured(expected)]);
    assert_eq!(h.events[0].timestamp_us, trig_at + 5_050);
}

#[test]
fn capture_parameters_are_checked() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(h.call(Command::Arm), Ok(Response::Ack));
    assert_eq!(
        h.call(Command::Capture(capture(0, 3))),
        Err(RigError::NoSuchChannel)
    );
    let long_trigger = Capture {
        trigger_us: 6_000,
        ..capture(0, 0)
    };
    assert_eq!(
        h.call(Command::Capture(long_trigger)),
        Err(RigError::OutOfRange)
    );
    let no_exposure = Capture {
        exposure_us: 0,
        trigger_us: 0,
        ..capture(0, 0)
    };
    assert_eq!(
        h.call(Command::Capture(no_exposure)),
        Err(RigError::ExposureTooShort { min_us: 20 })
    );
    let mut h = Host::new(SimParams::internal_dac());
    assert_eq!(
        h.call(Command::Galvo(GalvoPoint { x: 4096, y: 0 })),
        Err(RigError::OutOfRange)
    );
}

#[test]
fn retransmitted_request_is_answered_not_reexecuted() {
    let mut h = Host::new(SimParams::default());
    let first = h.send(50, mv(MoveTarget::Relative(100)));
    let again = h.send(50, mv(MoveTarget::Relative(100)));
    assert_eq!(first, again);
    assert_eq!(first[0].result, Ok(Response::Ack));
    h.advance(1_000_000);
    assert_eq!(h.kinds(), vec![EventKind::MoveDone { position: 100 }]);
    // Still cached after more traffic, then stale once it fell out of the cache.
    for seq in 51..51 + REPLY_CACHE as u32 - 1 {
        h.send(seq, Command::Heartbeat);
    }
    assert_eq!(h.send(50, mv(MoveTarget::Relative(100))), first);
    h.send(60, Command::Heartbeat);
    let stale = h.send(50, mv(MoveTarget::Relative(100)));
    assert_eq!(stale[0].result, Err(RigError::StaleSequence));
    h.advance(1_000_000);
    assert_eq!(h.kinds().len(), 1, "the move ran once");
    // Farther back than STALE_WINDOW counts as new (a restarted host that skipped Hello).
    h.send(1_000, Command::Heartbeat);
    let far = h.send(1_000 - STALE_WINDOW - 1, mv(MoveTarget::Relative(1)));
    assert_eq!(far[0].result, Ok(Response::Ack));
    let near = h.send(1_000 - STALE_WINDOW - 1 - STALE_WINDOW, Command::Heartbeat);
    assert_eq!(near[0].result, Err(RigError::StaleSequence));
    // A new session (Hello) may start anywhere.
    h.send(
        3,
        Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        },
    );
    assert_eq!(h.send(4, Command::Heartbeat)[0].result, Ok(Response::Ack));
}

#[test]
fn program_streams_one_event_per_point() {
    let mut h = Host::new(SimParams::default());
    let header = ProgramHeader {
        len: 40,
        channel: 2,
        settle_us: Some(50),
        exposure_us: 1_000,
        trigger_us: 10,
        interval_us: 12_000,
    };
    assert_eq!(h.call(Command::ProgramLoad(header)), Ok(Response::Ack));
    let points: Vec<GalvoPoint> = (0..40).map(|i| GalvoPoint { x: i * 100, y: 7 }).collect();
    assert_eq!(
        h.call(Command::ProgramRun),
        Err(RigError::ProgramIncomplete)
    );
    let chunk = |offset: usize, n: usize| {
        Command::ProgramPoints(ProgramChunk {
            offset: offset as u16,
            points: heapless::Vec::from_slice(&points[offset..offset + n]).unwrap(),
        })
    };
    assert_eq!(h.call(chunk(0, 32)), Ok(Response::Ack));
    assert_eq!(
        h.call(chunk(0, 32)),
        Err(RigError::ProgramIncomplete),
        "out of order"
    );
    assert_eq!(h.call(chunk(32, 8)), Ok(Response::Ack));
    assert_eq!(h.call(Command::ProgramRun), Err(RigError::NotArmed));
    assert_eq!(h.call(Command::Arm), Ok(Response::Ack));
    let t0 = h.sim.now();
    assert_eq!(
        h.call(Command::ProgramRun),
        Ok(Response::ProgramStarted {
            first_capture_id: 0
        })
    );
    for _ in 0..50 {
        h.advance(10_000);
        h.call(Command::Heartbeat).unwrap();
    }
    let kinds = h.kinds();
    assert_eq!(kinds.len(), 41);
    for (i, k) in kinds[..40].iter().enumerate() {
        let EventKind::Captured(c) = k else {
            panic!("{k:?}")
        };
        assert_eq!(c.capture_id, i as u32);
        assert_eq!(c.program_index, Some(i as u16));
        assert_eq!(c.galvo, points[i]);
        // Fixed 50 µs settle, then the 50 µs laser lead.
        assert_eq!(c.triggered_at_us, t0 + 12_000 * i as u64 + 100);
        assert_eq!(c.exposure_count, i as u32 + 1);
        assert!(c.lit);
    }
    assert_eq!(
        kinds[40],
        EventKind::ProgramDone {
            completed: 40,
            finished: true
        }
    );
    let seqs: Vec<u32> = h.events.iter().map(|e| e.event_seq).collect();
    assert_eq!(seqs, (0..41).collect::<Vec<_>>());
    assert_eq!(h.sim.hw().violations(), 0);
}

#[test]
fn heartbeat_loss_turns_laser_off() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Arm).unwrap();
    h.call(Command::Laser {
        channel: 0,
        on: true,
    })
    .unwrap();
    assert_eq!(h.sim.hw().lasers(), 1);
    h.advance(1_999_000);
    assert_eq!(h.sim.hw().lasers(), 1);
    h.advance(2_000);
    assert_eq!(h.sim.hw().lasers(), 0);
    assert!(!h.sim.rig().armed());
    assert_eq!(
        h.kinds(),
        vec![EventKind::Halted {
            reason: HaltReason::HeartbeatLost
        }]
    );
    assert_eq!(
        h.call(Command::Laser {
            channel: 0,
            on: true
        }),
        Err(RigError::NotArmed)
    );
}

#[test]
fn estop_aborts_program_and_faults() {
    let mut h = Host::new(SimParams::default());
    let header = ProgramHeader {
        len: 3,
        channel: 0,
        settle_us: Some(0),
        exposure_us: 10_000,
        trigger_us: 5,
        interval_us: 25_000,
    };
    h.call(Command::ProgramLoad(header)).unwrap();
    let pts = heapless::Vec::from_slice(&[GalvoPoint::default(); 3]).unwrap();
    h.call(Command::ProgramPoints(ProgramChunk {
        offset: 0,
        points: pts,
    }))
    .unwrap();
    h.call(Command::Arm).unwrap();
    h.call(Command::ProgramRun).unwrap();
    h.advance(30_000);
    assert_eq!(h.sim.hw().lasers(), 1);
    let now = h.sim.now();
    h.sim.set_estop(now, true);
    h.collect();
    assert_eq!(h.sim.hw().lasers(), 0);
    assert!(!h.sim.hw().trigger());
    let kinds = h.kinds();
    assert!(matches!(kinds[0], EventKind::Captured(_)));
    assert_eq!(
        kinds[1],
        EventKind::ProgramDone {
            completed: 1,
            finished: false
        }
    );
    assert_eq!(
        kinds[2],
        EventKind::Halted {
            reason: HaltReason::EmergencyStop
        }
    );
    assert_eq!(
        h.call(Command::Arm),
        Err(RigError::Faulted(Fault::EmergencyStop))
    );
    assert_eq!(h.call(Command::ClearFault), Err(RigError::EmergencyStop));
    let now = h.sim.now();
    h.sim.set_estop(now, false);
    assert_eq!(h.call(Command::ClearFault), Ok(Response::Ack));
    assert_eq!(h.call(Command::Arm), Ok(Response::Ack));
}

#[test]
fn interlock_open_disarms_and_blocks_arming() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Arm).unwrap();
    h.call(Command::Laser {
        channel: 2,
        on: true,
    })
    .unwrap();
    assert_eq!(h.sim.hw().lasers(), 0b100);
    let now = h.sim.now();
    h.sim.set_interlock(now + 10, false);
    h.collect();
    assert_eq!(h.sim.hw().lasers(), 0);
    assert_eq!(
        h.kinds(),
        vec![EventKind::Halted {
            reason: HaltReason::InterlockOpen
        }]
    );
    assert_eq!(h.call(Command::Arm), Err(RigError::InterlockOpen));
}

#[test]
fn moving_turns_laser_off_and_refuses_it() {
    let mut h = Host::new(SimParams::default());
    h.call(Command::Arm).unwrap();
    h.call(Command::Laser {
        channel: 0,
        on: true,
    })
    .unwrap();
    h.call(mv(MoveTarget::Relative(500))).unwrap();
    assert_eq!(h.sim.hw().lasers(), 0);
    assert_eq!(
        h.call(Command::Laser {
            channel: 0,
            on: true
        }),
        Err(RigError::Busy)
    );
    h.advance(500_000);
    assert_eq!(
        h.sim.hw().lasers(),
        0,
        "manual channels stay off after the move"
    );
    assert_eq!(
        h.call(Command::Laser {
            channel: 0,
            on: true
        }),
        Ok(Response::Ack)
    );
    assert_eq!(h.call(Command::Stop), Ok(Response::Ack));
    assert_eq!(h.sim.hw().lasers(), 0);
    assert!(!h.sim.rig().armed());
    assert_eq!(h.sim.hw().violations(), 0);
}

#[test]
fn framed_bytes_with_garbage_between_frames() {
    let mut sim = SimRig::default();
    let mut stream = vec![0x13, 0x37, 0xff];
    let mut buf = [0u8; MAX_FRAME];
    for (seq, command) in [
        (
            1,
            Command::Hello {
                protocol_version: PROTOCOL_VERSION,
            },
        ),
        (2, Command::Status),
    ] {
        stream.push(0);
        let n = encode_request(&Request { seq, command }, &mut buf).unwrap();
        stream.extend_from_slice(&buf[..n]);
        stream.extend_from_slice(&[9, 9, 9]);
    }
    for chunk in stream.chunks(5) {
        let now = sim.now() + 10;
        sim.feed(now, chunk);
    }
    let mut out = vec![0u8; 4096];
    let n = sim.drain(&mut out);
    let mut dec = FrameDecoder::new();
    let msgs: Vec<RigMessage> = dec.decode(&out[..n]).collect();
    assert_eq!(msgs.len(), 2);
    let RigMessage::Reply(Reply {
        seq: 2,
        result: Ok(Response::Status(s)),
    }) = &msgs[1]
    else {
        panic!("{msgs:?}")
    };
    // A lone 0 before each frame flushed the garbage in front of it: two corrupt frames counted.
    assert_eq!(s.rx_dropped, 2);
    assert_eq!(sim.rig().rx_stats().frames, 2);
}

#[test]
fn galvo_settle_grows_with_the_larger_axis_jump_and_saturates() {
    use subsurf_firmware::galvo_settle_us;
    let profile = SimParams::default().profile;
    let p = |x, y| GalvoPoint { x, y };
    assert_eq!(galvo_settle_us(&profile, p(0, 0), p(0, 0)), 100);
    assert_eq!(galvo_settle_us(&profile, p(0, 0), p(1000, 500)), 120);
    assert_eq!(
        galvo_settle_us(&profile, p(60_000, 0), p(10_000, 65_535)),
        100 + 65_535 * 20 / 1000
    );
    let mut extreme = profile;
    extreme.galvo.settle_min_us = u32::MAX;
    extreme.galvo.settle_per_kcode_us = u32::MAX;
    assert_eq!(galvo_settle_us(&extreme, p(0, 0), p(u16::MAX, 0)), u32::MAX);
}

#[test]
fn reply_precedes_the_events_its_command_caused() {
    let mut sim = SimRig::default();
    sim.rig_mut().handle_request(
        0,
        Request {
            seq: 0,
            command: Command::Hello {
                protocol_version: PROTOCOL_VERSION,
            },
        },
    );
    sim.rig_mut().poll_message();
    sim.rig_mut().handle_request(
        0,
        Request {
            seq: 1,
            command: Command::Arm,
        },
    );
    sim.rig_mut().handle_request(
        0,
        Request {
            seq: 2,
            command: Command::Stop,
        },
    );
    let msgs: Vec<RigMessage> = std::iter::from_fn(|| sim.rig_mut().poll_message()).collect();
    assert!(
        matches!(
            &msgs[..],
            [
                RigMessage::Reply(Reply { seq: 1, .. }),
                RigMessage::Reply(Reply {
                    seq: 2,
                    result: Ok(Response::Ack)
                }),
                RigMessage::Event(Event {
                    kind: EventKind::Halted {
                        reason: HaltReason::Stop
                    },
                    ..
                }),
            ]
        ),
        "{msgs:?}"
    );
}

#[test]
fn estop_pressed_at_boot_is_a_fault() {
    use subsurf_firmware::Rig;
    use subsurf_firmware::sim::SimHardware;
    let params = SimParams::default();
    let mut hw = SimHardware::new(params.profile, params.camera, 0, 10);
    hw.set_estop(true);
    let mut rig = Rig::new(hw, params.profile, params.config, 1, 0);
    assert_eq!(rig.fault(), Some(Fault::EmergencyStop));
    rig.handle_request(
        0,
        Request {
            seq: 0,
            command: Command::Hello {
                protocol_version: PROTOCOL_VERSION,
            },
        },
    );
    rig.handle_request(
        0,
        Request {
            seq: 1,
            command: Command::Arm,
        },
    );
    let replies: Vec<RigMessage> = std::iter::from_fn(|| rig.poll_message()).collect();
    assert!(replies.contains(&RigMessage::Reply(Reply {
        seq: 1,
        result: Err(RigError::Faulted(Fault::EmergencyStop))
    })));
    assert_eq!(rig.laser_output(), 0);
}

#[test]
fn moves_are_planned_ahead_in_compressed_segments() {
    let mut h = Host::new(SimParams::default());
    assert_eq!(h.sim.hw().next_step_at(), None);
    let t0 = h.sim.now();
    h.call(mv(MoveTarget::Relative(2_000))).unwrap();
    // Queued with the request, before its time: the first step of a move from rest at
    // 100 000 steps/s² comes sqrt(2/a) = 4472 µs later (up to 5 µs early, never late).
    let first = h.sim.hw().next_step_at().expect("steps queued at once");
    assert!((t0 + 4_467..=t0 + 4_472).contains(&first), "{first}");
    h.advance(1_000_000);
    assert_eq!(h.sim.hw().next_step_at(), None);
    assert_eq!(h.sim.rig().position(), 2_000);
    // 2 000 steps (ramp up, cruise, ramp down over 0.3 s) in about one segment per refill of
    // the queue (every 5 ms), not one per step.
    let segments = h.sim.hw().segments();
    assert!(segments < 100, "{segments} segments for 2 000 steps");
}

fn replay(h: &mut Host, since: u32, max: u8) -> EventReplay {
    match h.call(Command::Replay { since, max }) {
        Ok(Response::Events(r)) => r,
        other => panic!("not an event replay: {other:?}"),
    }
}

#[test]
fn replay_returns_kept_events_and_says_which_are_gone_after_overflow() {
    use subsurf_firmware::rig::EVENT_HISTORY;
    let mut h = Host::new(SimParams::default());
    let total = EVENT_HISTORY as u32 + 8;
    for i in 0..total {
        assert_eq!(h.call(mv(MoveTarget::Relative(1))), Ok(Response::Ack));
        h.advance(10_000);
        assert_eq!(h.events.len() as u32, i + 1);
    }
    let sent = h.events.clone();
    let events_before = h.events.len();
    // Everything before the last EVENT_HISTORY events was overwritten.
    let r = replay(&mut h, 0, u8::MAX);
    assert_eq!((r.oldest, r.next_event_seq), (8, total));
    assert_eq!(
        &r.events[..],
        &sent[8..8 + REPLAY_BATCH],
        "from the oldest kept, capped"
    );
    // Within the history: exactly the asked-for events, identical to the ones sent live.
    let r = replay(&mut h, 20, 2);
    assert_eq!(&r.events[..], &sent[20..22]);
    let r = replay(&mut h, total - 2, 5);
    assert_eq!(&r.events[..], &sent[sent.len() - 2..]);
    // Nothing missing, or a host that is confused about the rig's counter: harmless answers.
    assert!(replay(&mut h, total, 5).events.is_empty());
    assert_eq!(
        replay(&mut h, total + 3, 0).events.len(),
        1,
        "max 0 counts as 1"
    );
    // Replaying is read-only: no new events, no state change.
    assert_eq!(h.events.len(), events_before);
    let s = h.call(Command::Status);
    assert!(
        matches!(s, Ok(Response::Status(s)) if s.next_event_seq == total && s.position == total as i32)
    );
}

/// A dark capture (version 6) triggers the camera for its exposure with every laser off, armed
/// or not, and reports it unlit (channel 0); a manual laser left on goes off for it. With
/// the interlock open the rig halts it as it halts any capture, the laser still off.
#[test]
fn a_dark_capture_exposes_the_camera_with_every_laser_off() {
    let dark = DarkCapture {
        exposure_us: 5_000,
        trigger_us: 100,
    };
    for (armed, interlock_closed) in [(true, true), (false, true), (false, false)] {
        let open = !interlock_closed;
        let mut h = Host::new(SimParams::default());
        if armed {
            h.call(Command::Arm).unwrap();
            h.call(Command::Laser {
                channel: 1,
                on: true,
            })
            .unwrap();
            assert_eq!(h.sim.hw().lasers(), 0b10);
            h.advance(10);
        }
        if !interlock_closed {
            let now = h.sim.now();
            h.sim.set_interlock(now + 10, false);
            h.advance(100);
            h.events.clear();
        }
        let t0 = h.sim.now();
        let Ok(Response::CaptureStarted { capture_id }) = h.call(Command::DarkCapture(dark)) else {
            panic!("dark capture refused (armed {armed}, interlock {interlock_closed})");
        };
        h.advance(20_000);
        // No laser output at any time after the dark capture was asked for.
        let lit_after: Vec<_> = h
            .sim
            .hw()
            .laser_log()
            .entries()
            .filter(|e| e.at >= t0 && e.value != 0)
            .map(|e| (e.at, e.value))
            .collect();
        assert_eq!(lit_after, vec![], "armed {armed}");
        assert_eq!(h.sim.hw().lasers(), 0);
        if open {
            assert_eq!(
                h.kinds(),
                vec![EventKind::Halted {
                    reason: HaltReason::InterlockOpen
                }]
            );
            continue;
        }
        let trig: Vec<_> = h
            .sim
            .hw()
            .trigger_log()
            .entries()
            .filter(|e| e.at >= t0)
            .map(|e| e.value)
            .collect();
        assert_eq!(
            (trig.iter().filter(|v| **v).count(), trig.last()),
            (1, Some(&false)),
            "the camera is triggered once: {trig:?}"
        );
        let captured: Vec<Captured> = h
            .kinds()
            .into_iter()
            .filter_map(|k| match k {
                EventKind::Captured(c) => Some(c),
                _ => None,
            })
            .collect();
        assert_eq!(captured.len(), 1);
        let c = &captured[0];
        assert_eq!(c.capture_id, capture_id);
        assert_eq!((c.lit, c.channel), (false, 0));
        assert_eq!(
            c.exposure.map(|e| e.duration_us),
            Some(5_000),
            "the camera exposed"
        );
    }
    // Its timing is checked like any capture's.
    let mut h = Host::new(SimParams::default());
    assert_eq!(
        h.call(Command::DarkCapture(DarkCapture {
            exposure_us: 5_000,
            trigger_us: 6_000,
        })),
        Err(RigError::OutOfRange)
    );
}
