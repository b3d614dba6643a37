//! The laser-safety invariants over random command and input sequences: the laser is never on
//! while unarmed, moving, stopped, in fault, with the e-stop pressed or the interlock open, or
//! after the heartbeat timeout, and never longer than the manual limit or a capture's window.
//! Checked after every request, input change, camera edge, stall and rig deadline, both from the
//! core's state and from the simulated hardware's own view of its outputs. The random sequences
//! include profile changes, homing, decelerating stops, step-generator stalls, missed camera
//! triggers and trigger latency.

use proptest::prelude::*;
use subsurf_firmware::rig::Micros;
use subsurf_firmware::sim::{SimCamera, SimParams, SimRig};
use subsurf_protocol::*;

#[derive(Debug, Clone)]
enum Op {
    Request(Command),
    Estop(bool),
    Interlock(bool),
    /// The board's step timer ran dry.
    Stall,
    /// Let this much time pass, µs.
    Wait(Micros),
}

fn galvo() -> impl Strategy<Value = GalvoPoint> {
    (any::<u16>(), any::<u16>()).prop_map(|(x, y)| GalvoPoint { x, y })
}

fn command() -> impl Strategy<Value = Command> {
    let capture = (
        galvo(),
        prop::option::of(0u32..2_000),
        0u8..4,
        1u32..20_000,
        1u32..500,
    )
        .prop_map(|(galvo, settle_us, channel, exposure_us, trigger_us)| {
            Command::Capture(Capture {
                galvo,
                settle_us,
                channel,
                exposure_us,
                trigger_us,
            })
        });
    let mv = (
        prop_oneof![
            (-3000i32..3000).prop_map(MoveTarget::Absolute),
            (-3000i32..3000).prop_map(MoveTarget::Relative)
        ],
        1u32..30_000,
        1u32..300_000,
    )
        .prop_map(|(target, max_speed, accel)| {
            Command::Move(Move {
                target,
                max_speed,
                accel,
            })
        });
    let load = (
        1u16..6,
        0u8..3,
        prop::option::of(0u32..500),
        1u32..5_000,
        0u32..8_000,
    )
        .prop_map(|(len, channel, settle_us, exposure_us, interval_us)| {
            Command::ProgramLoad(ProgramHeader {
                len,
                channel,
                settle_us,
                exposure_us,
                trigger_us: 1,
                interval_us,
            })
        });
    let points = (0u16..6, prop::collection::vec(galvo(), 0..6)).prop_map(|(offset, pts)| {
        Command::ProgramPoints(ProgramChunk {
            offset,
            points: heapless::Vec::from_slice(&pts).unwrap(),
        })
    });
    let config = prop_oneof![50u32..3_000, 0u32..1_000_000].prop_map(|ms| {
        Command::SetConfig(Config {
            heartbeat_timeout_ms: ms,
        })
    });
    let profile = (any::<bool>(), 1u8..4, 1u32..3_000, 0u32..30_000, 0u32..200).prop_map(
        |(internal, channels, manual_max_ms, readout_us, lead_us)| {
            let mut p = RigProfile::DEFAULT;
            if internal {
                p.galvo = RigProfile::INTERNAL_DAC;
            }
            p.laser.channels = channels;
            p.laser.manual_max_ms = manual_max_ms;
            p.laser.lead_us = lead_us;
            p.camera.readout_us = readout_us;
            Command::SetProfile(p)
        },
    );
    prop_oneof![
        4 => Just(Command::Arm),
        1 => Just(Command::Disarm),
        4 => (0u8..4, any::<bool>()).prop_map(|(channel, on)| Command::Laser { channel, on }),
        3 => capture,
        2 => mv,
        1 => Just(Command::Home),
        1 => galvo().prop_map(Command::Galvo),
        1 => load,
        2 => points,
        2 => Just(Command::ProgramRun),
        1 => Just(Command::Stop),
        1 => Just(Command::ClearFault),
        2 => Just(Command::Heartbeat),
        1 => Just(Command::Status),
        1 => config,
        1 => (any::<u32>(), any::<u8>()).prop_map(|(since, max)| Command::Replay { since, max }),
        1 => profile,
        1 => Just(Command::GetProfile),
        1 => any::<u16>().prop_map(|protocol_version| Command::Hello { protocol_version }),
    ]
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        12 => command().prop_map(Op::Request),
        1 => any::<bool>().prop_map(Op::Estop),
        1 => any::<bool>().prop_map(Op::Interlock),
        1 => Just(Op::Stall),
        6 => prop_oneof![0u64..2_000, 0u64..200_000, 0u64..4_000_000].prop_map(Op::Wait),
    ]
}

/// What the test itself knows, independent of the core's bookkeeping.
struct Model {
    last_request: Micros,
    estop: bool,
    interlock_closed: bool,
}

fn check(sim: &SimRig, model: &Model, after: &str) -> Result<(), TestCaseError> {
    let rig = sim.rig();
    let hw = sim.hw();
    prop_assert_eq!(hw.violations(), 0, "hardware saw a breach after {}", after);
    prop_assert_eq!(hw.lasers(), rig.laser_output());
    prop_assert!(rig.config().heartbeat_timeout_ms <= MAX_HEARTBEAT_TIMEOUT_MS);
    if hw.lasers() != 0 {
        // On no longer than the manual limit (captures here are shorter than any limit drawn).
        let mut on_since = 0;
        let mut was_on = false;
        for e in hw.laser_log().entries() {
            if e.value != 0 && !was_on {
                on_since = e.at;
            }
            was_on = e.value != 0;
        }
        let limit = u64::from(rig.profile().laser.manual_max_ms) * 1000 + 20_000 + 400;
        prop_assert!(
            sim.now() - on_since <= limit,
            "laser on for {} µs (limit {}) after {}",
            sim.now() - on_since,
            limit,
            after
        );
        prop_assert!(rig.armed(), "laser on while disarmed after {}", after);
        prop_assert!(!rig.moving(), "laser on while moving after {}", after);
        prop_assert!(rig.fault().is_none(), "laser on in fault after {}", after);
        prop_assert!(!model.estop, "laser on with e-stop after {}", after);
        prop_assert!(
            model.interlock_closed,
            "laser on with interlock open after {}",
            after
        );
        let timeout = u64::from(rig.config().heartbeat_timeout_ms) * 1000;
        prop_assert!(
            sim.now() < model.last_request + timeout,
            "laser on {} µs after the last request (timeout {}) after {}",
            sim.now() - model.last_request,
            timeout,
            after
        );
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(192))]

    #[test]
    fn laser_is_never_on_when_it_must_be_off(
        ops in prop::collection::vec(op(), 1..60),
        miss in prop::option::of(0u32..6),
        trigger_latency_us in prop_oneof![Just(0u32), 0u32..100],
        start_position in 0i64..16_000,
    ) {
        let params = SimParams {
            camera: SimCamera { timer_latency_us: trigger_latency_us, miss_triggers: [miss, None, None, None], ..SimCamera::default() },
            start_position,
            ..SimParams::default()
        };
        let mut sim = SimRig::new(params);
        // The session opens first; a later random Hello may re-open it (or fail harmlessly).
        sim.rig_mut().handle_request(0, Request { seq: 0, command: Command::Hello { protocol_version: PROTOCOL_VERSION } });
        let mut model = Model { last_request: 0, estop: false, interlock_closed: true };
        let mut seq: Seq = 0;
        for op in &ops {
            let now = sim.now();
            match op {
                Op::Request(command) => {
                    seq = seq.wrapping_add(1);
                    sim.rig_mut().handle_request(now, Request { seq, command: command.clone() });
                    model.last_request = now;
                    let label = format!("{command:?}");
                    check(&sim, &model, &label)?;
                    if matches!(command, Command::Stop | Command::Disarm) {
                        prop_assert_eq!(sim.hw().lasers(), 0, "laser on right after {:?}", command);
                    }
                }
                Op::Estop(pressed) => {
                    sim.set_estop(now + 1, *pressed);
                    model.estop = *pressed;
                    check(&sim, &model, "e-stop change")?;
                }
                Op::Interlock(closed) => {
                    sim.set_interlock(now + 1, *closed);
                    model.interlock_closed = *closed;
                    check(&sim, &model, "interlock change")?;
                }
                Op::Stall => {
                    let moving = sim.rig().moving();
                    sim.rig_mut().handle_stall(now);
                    check(&sim, &model, "a stall")?;
                    prop_assert!(!sim.rig().moving());
                    if moving {
                        prop_assert!(!sim.rig().homed());
                        prop_assert_eq!(sim.rig().fault(), Some(Fault::StepStall));
                    }
                }
                Op::Wait(dt) => {
                    let end = now + dt;
                    while let Some(t) = sim.next_deadline().filter(|&t| t <= end) {
                        sim.advance_to(t);
                        check(&sim, &model, "a deadline")?;
                    }
                    sim.advance_to(end);
                    check(&sim, &model, "waiting")?;
                }
            }
            while sim.rig_mut().poll_message().is_some() {}
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    /// Line noise never panics the rig, never makes it emit light, and never stops it from
    /// answering the next good request.
    #[test]
    fn garbage_is_survived(noise in prop::collection::vec(any::<u8>(), 0..3000), chunk in 1usize..300) {
        let mut sim = SimRig::new(SimParams::default());
        for (i, part) in noise.chunks(chunk).enumerate() {
            sim.feed(i as u64 * 100, part);
            while sim.rig_mut().poll_message().is_some() {}
        }
        prop_assert_eq!(sim.hw().lasers(), 0);
        prop_assert_eq!(sim.hw().violations(), 0);
        let mut frame = [0u8; MAX_FRAME];
        let n = encode_request(&Request { seq: 7, command: Command::Status }, &mut frame).unwrap();
        let mut bytes = vec![0u8];
        bytes.extend_from_slice(&frame[..n]);
        let now = sim.now() + 100;
        sim.feed(now, &bytes);
        let mut out = [0u8; 4 * MAX_FRAME];
        let len = sim.drain(&mut out);
        let mut dec = FrameDecoder::new();
        let replies: Vec<RigMessage> = dec.decode(&out[..len]).collect();
        let answered = replies.iter().any(|m| matches!(m, RigMessage::Reply(Reply { seq: 7, .. })));
        prop_assert!(answered, "{:?}", replies);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    /// Replay requests for any `since` and `max`, framed among line noise, after any number of
    /// events (history empty, partly filled or overflowed): the rig never panics, every reply
    /// fits a frame (nothing dropped on transmit) and decodes, and the laser stays dark.
    #[test]
    fn replay_requests_among_noise_never_panic(
        moves in 0u32..45,
        asks in prop::collection::vec((any::<u32>(), any::<u8>(), prop::collection::vec(any::<u8>(), 0..40)), 1..12),
    ) {
        let mut sim = SimRig::new(SimParams::default());
        let mut now = 0;
        let mut frame = [0u8; MAX_FRAME];
        let mut out = [0u8; 64 * MAX_FRAME];
        let mut seq = 0;
        let mut send = |sim: &mut SimRig, now: u64, command: Command| {
            seq += 1;
            let n = encode_request(&Request { seq, command }, &mut frame).unwrap();
            sim.feed(now, &frame[..n]);
        };
        send(&mut sim, now, Command::Hello { protocol_version: PROTOCOL_VERSION });
        for _ in 0..moves {
            send(&mut sim, now, Command::Move(Move { target: MoveTarget::Relative(1), max_speed: 10_000, accel: 100_000 }));
            now += 10_000;
            sim.advance_to(now);
            sim.drain(&mut out);
        }
        let mut dec = FrameDecoder::new();
        for (since, max, noise) in asks {
            sim.feed(now, &noise);
            sim.feed(now, &[0]);
            send(&mut sim, now, Command::Replay { since, max });
            let len = sim.drain(&mut out);
            let msgs: Vec<RigMessage> = dec.decode(&out[..len]).collect();
            let replayed = msgs.iter().any(|m| matches!(m, RigMessage::Reply(Reply { result: Ok(Response::Events(r)), .. }) if r.events.len() <= REPLAY_BATCH));
            prop_assert!(replayed, "{:?}", msgs);
        }
        prop_assert_eq!(sim.rig().tx_dropped(), 0);
        prop_assert_eq!(sim.hw().lasers(), 0);
        prop_assert_eq!(sim.hw().violations(), 0);
    }
}
