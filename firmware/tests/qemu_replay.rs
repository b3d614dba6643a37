//! The host half of the Cortex-M4 differential test.
//!
//! `scenario()` records a host session (handshake, moves, homing, captures, a capture program,
//! corrupted and truncated frames, a retransmission, e-stop, interlock, a lost heartbeat) as a
//! replay script; the replay then runs a seeded pseudo-random session (every request kind, bit
//! flips, truncations, split reads, line noise, safety inputs toggling) generated on the fly. This test runs it through the firmware core on the host and checks the result
//! against the two golden files the QEMU binary embeds (`firmware/qemu/script.bin`,
//! `firmware/qemu/expected.bin`); CI then runs the same script through the same core compiled for
//! thumbv7em under `qemu-system-arm -M mps2-an386` and requires byte-identical output.
//! Regenerate the golden files after a deliberate change with `SUBSURF_BLESS=1 cargo test -p
//! subsurf-firmware --test qemu_replay`.

#[path = "../qemu/replay.rs"]
#[allow(dead_code)]
mod replay;

use std::path::PathBuf;

use replay::*;
use subsurf_firmware::FIRMWARE_VERSION;
use subsurf_protocol::{
    Capture, Command, EventKind, FrameDecoder, GalvoPoint, HaltReason, MAX_FRAME, Move, MoveTarget,
    PROTOCOL_VERSION, ProgramChunk, ProgramHeader, Request, Response, RigError, RigMessage,
    RigProfile, SaveError, encode_request,
};

struct Script {
    bytes: Vec<u8>,
}

impl Script {
    fn record(&mut self, t: u64, kind: u8, payload: &[u8]) {
        self.bytes.extend_from_slice(&t.to_le_bytes());
        self.bytes.push(kind);
        self.bytes
            .extend_from_slice(&u16::try_from(payload.len()).unwrap().to_le_bytes());
        self.bytes.extend_from_slice(payload);
    }

    fn frame(seq: u32, command: Command) -> Vec<u8> {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode_request(&Request { seq, command }, &mut buf).expect("encodes");
        buf[..n].to_vec()
    }

    fn send(&mut self, t: u64, seq: u32, command: Command) {
        self.record(t, KIND_BYTES, &Self::frame(seq, command));
    }
}

fn scenario() -> Vec<u8> {
    let mut s = Script { bytes: Vec::new() };
    let ms = 1_000;
    // Line noise before the handshake, then the handshake in the same chunk.
    let mut hello = vec![0x13, 0x37, 0xff, 0x00];
    hello.extend(Script::frame(
        1,
        Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        },
    ));
    s.record(ms, KIND_BYTES, &hello);
    s.send(2 * ms, 2, Command::GetConfig);
    s.send(2 * ms + 10, 3, Command::Status);
    s.send(3 * ms, 4, Command::Arm);
    s.send(
        4 * ms,
        5,
        Command::Laser {
            channel: 0,
            on: true,
        },
    );
    s.send(
        5 * ms,
        6,
        Command::Laser {
            channel: 0,
            on: false,
        },
    );
    s.send(
        6 * ms,
        7,
        Command::Move(Move {
            target: MoveTarget::Relative(1_600),
            max_speed: 8_000,
            accel: 40_000,
        }),
    );
    s.send(500 * ms, 8, Command::Heartbeat);
    let capture = Capture {
        galvo: GalvoPoint { x: 1_000, y: 2_000 },
        settle_us: None,
        channel: 1,
        exposure_us: 1_000,
        trigger_us: 100,
    };
    s.send(510 * ms, 9, Command::Capture(capture));
    // A frame with one corrupted byte, then half a frame cut off by a delimiter.
    let mut corrupt = Script::frame(10, Command::Status);
    corrupt[3] ^= 0x40;
    s.record(520 * ms, KIND_BYTES, &corrupt);
    let status = Script::frame(11, Command::Status);
    let mut cut = status[..status.len() / 2].to_vec();
    cut.push(0);
    cut.extend_from_slice(&status);
    s.record(521 * ms, KIND_BYTES, &cut);
    // A retransmission of the capture: answered from the reply cache, not run again.
    s.send(522 * ms, 9, Command::Capture(capture));
    s.send(
        530 * ms,
        12,
        Command::ProgramLoad(ProgramHeader {
            len: 3,
            channel: 2,
            settle_us: Some(200),
            exposure_us: 500,
            trigger_us: 50,
            interval_us: 11_000,
        }),
    );
    let points = [(0, 0), (4_000, 100), (65_535, 65_535)]
        .into_iter()
        .map(|(x, y)| GalvoPoint { x, y })
        .collect();
    s.send(
        531 * ms,
        13,
        Command::ProgramPoints(ProgramChunk { offset: 0, points }),
    );
    s.send(532 * ms, 14, Command::ProgramRun);
    s.send(
        600 * ms,
        15,
        Command::Move(Move {
            target: MoveTarget::Relative(-400),
            max_speed: 20_000,
            accel: 200_000,
        }),
    );
    s.record(601 * ms, KIND_ESTOP_PRESS, &[]);
    s.send(630 * ms, 16, Command::Status);
    s.send(640 * ms, 17, Command::ClearFault);
    s.record(650 * ms, KIND_ESTOP_RELEASE, &[]);
    s.send(650 * ms + 1, 18, Command::ClearFault);
    s.record(660 * ms, KIND_INTERLOCK_OPEN, &[]);
    s.send(660 * ms + 1, 19, Command::Arm);
    s.record(661 * ms, KIND_INTERLOCK_CLOSE, &[]);
    s.send(
        670 * ms,
        20,
        Command::Hello {
            protocol_version: PROTOCOL_VERSION + 1,
        },
    );
    s.send(680 * ms, 21, Command::Arm);
    s.send(
        681 * ms,
        22,
        Command::Laser {
            channel: 0,
            on: true,
        },
    );
    // The host goes quiet: the heartbeat timeout turns the laser off.
    s.record(3_000 * ms, KIND_ADVANCE, &[]);
    s.send(3_010 * ms, 23, Command::Status);
    s.send(3_020 * ms, 24, Command::Home);
    s.send(4_500 * ms, 25, Command::Heartbeat);
    s.send(6_000 * ms, 26, Command::Heartbeat);
    s.send(6_000 * ms + 1, 27, Command::Status);
    // Lasers wired active low under the default (active-high) profile, as on a real bench. The
    // rig refuses to arm, so no laser command is accepted; wired right again, it arms.
    s.record(6_010 * ms, KIND_LASER_WIRING, &[1]);
    s.send(6_010 * ms + 1, 28, Command::Arm);
    s.send(
        6_010 * ms + 2,
        29,
        Command::Laser {
            channel: 0,
            on: true,
        },
    );
    s.record(6_020 * ms, KIND_LASER_WIRING, &[0]);
    s.send(6_020 * ms + 1, 30, Command::Arm);
    s.send(6_020 * ms + 2, 31, Command::Disarm);
    // Finding E: a save whose read-back fails is refused and changes nothing; the next one is
    // acknowledged, and flash holds it.
    let mut profile = RigProfile::DEFAULT;
    profile.motor.microsteps = 32;
    s.record(6_030 * ms, KIND_FAIL_SAVE, &[2]);
    s.send(6_030 * ms + 1, 32, Command::SetProfile(profile));
    s.send(6_030 * ms + 2, 33, Command::GetStoredProfile);
    s.send(6_030 * ms + 3, 34, Command::SetProfile(profile));
    s.send(6_030 * ms + 4, 35, Command::GetStoredProfile);
    // Finding C: the step interrupt late by more than a period mid-move: the motion stops at
    // once, the fault and the halt are reported, the axis is no longer homed.
    s.send(6_040 * ms, 36, Command::Home);
    s.send(7_000 * ms, 37, Command::Heartbeat);
    s.send(8_000 * ms, 38, Command::Heartbeat);
    s.send(
        8_000 * ms + 1,
        39,
        Command::Move(Move {
            target: MoveTarget::Relative(4_000),
            max_speed: 8_000,
            accel: 40_000,
        }),
    );
    s.record(8_100 * ms, KIND_STEP_LATE, &[]);
    s.send(8_100 * ms + 1, 40, Command::Status);
    s.send(8_100 * ms + 2, 41, Command::ClearFault);
    s.bytes
}

fn run_on_host(script: &[u8]) -> Vec<u8> {
    let mut rig = new_rig();
    let mut out = Vec::new();
    replay(&mut rig, script, &mut |b| out.extend_from_slice(b)).expect("script replays");
    out
}

fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("qemu")
        .join(name)
}

#[test]
fn golden_files_are_what_the_host_core_produces() {
    let script = scenario();
    let expected = run_on_host(&script);
    if std::env::var_os("SUBSURF_BLESS").is_some() {
        std::fs::write(golden("script.bin"), &script).expect("write script.bin");
        std::fs::write(golden("expected.bin"), &expected).expect("write expected.bin");
    }
    let on_disk_script = std::fs::read(golden("script.bin")).expect("read script.bin");
    let on_disk_expected = std::fs::read(golden("expected.bin")).expect("read expected.bin");
    assert!(
        on_disk_script == script,
        "firmware/qemu/script.bin is stale: rerun with SUBSURF_BLESS=1"
    );
    assert!(
        on_disk_expected == expected,
        "firmware/qemu/expected.bin differs from the host core's replies ({} vs {} bytes): the \
         core changed; rerun with SUBSURF_BLESS=1 if that was intended",
        on_disk_expected.len(),
        expected.len()
    );
}

#[test]
fn the_scenario_exercises_every_path_it_claims() {
    let out = run_on_host(&scenario());
    let find = |magic: &[u8]| {
        out.windows(magic.len())
            .position(|w| w == magic)
            .expect("marker present")
    };
    let (noise, summary) = (find(NOISE_MAGIC), find(SUMMARY_MAGIC));
    let mut decoder = FrameDecoder::new();
    let messages: Vec<RigMessage> = decoder.decode(&out[..noise]).collect();
    assert_eq!(decoder.stats().dropped(), 0, "the rig sent a bad frame");
    // The pseudo-random session gets answers too, all well-formed.
    let mut decoder = FrameDecoder::new();
    let noisy: Vec<RigMessage> = decoder
        .decode(&out[noise + NOISE_MAGIC.len()..summary])
        .collect();
    assert_eq!(decoder.stats().dropped(), 0, "the rig sent a bad frame");
    assert!(
        noisy.len() > 200,
        "{} replies to the noise session",
        noisy.len()
    );
    // Event replays (protocol version 2), the largest replies, are part of the comparison.
    let replays = noisy
        .iter()
        .filter(|m| {
            matches!(m, RigMessage::Reply(subsurf_protocol::Reply { result: Ok(Response::Events(r)), .. })
                if !r.events.is_empty())
        })
        .count();
    assert!(replays >= 3, "{replays} non-empty event replays");

    let reply = |seq: u32| {
        messages
            .iter()
            .filter_map(|m| match m {
                RigMessage::Reply(r) if r.seq == seq => Some(r.result.clone()),
                _ => None,
            })
            .collect::<Vec<_>>()
    };
    match &reply(1)[..] {
        [Ok(Response::Hello(h))] => assert_eq!(h.firmware_version, FIRMWARE_VERSION),
        other => panic!("hello: {other:?}"),
    }
    // The retransmitted capture got the same answer twice and ran once.
    let captures = reply(9);
    assert_eq!(captures.len(), 2);
    assert_eq!(captures[0], captures[1]);
    assert!(reply(10).is_empty(), "the corrupted frame was answered");
    assert_eq!(reply(11).len(), 1);
    assert!(matches!(&reply(19)[..], [Err(RigError::InterlockOpen)]));
    assert!(matches!(
        &reply(20)[..],
        [Err(RigError::UnknownVersion { .. })]
    ));
    // A wrong laser polarity: no arming, no light.
    assert!(matches!(&reply(28)[..], [Err(RigError::LaserPolarity)]));
    assert!(matches!(&reply(29)[..], [Err(RigError::NotArmed)]));
    assert!(matches!(&reply(30)[..], [Ok(Response::Ack)]));
    // A save is acknowledged only once flash reads it back.
    assert!(matches!(
        &reply(32)[..],
        [Err(RigError::ProfileNotSaved(SaveError::Verify))]
    ));
    assert!(matches!(&reply(33)[..], [Ok(Response::Profile(p))] if *p == RigProfile::DEFAULT));
    assert!(matches!(&reply(34)[..], [Ok(Response::Ack)]));
    assert!(matches!(&reply(35)[..], [Ok(Response::Profile(p))] if p.motor.microsteps == 32));
    // A late step interrupt stops the move and is reported.
    assert!(
        matches!(&reply(39)[..], [Ok(Response::Ack)]),
        "{:?}",
        reply(39)
    );
    match &reply(40)[..] {
        [Ok(Response::Status(st))] => {
            assert_eq!(st.fault, Some(subsurf_protocol::Fault::StepLate));
            assert!(!st.homed, "still homed after a late step interrupt");
            assert_eq!(st.state, subsurf_protocol::RigState::Fault);
        }
        other => panic!("status after the late interrupt: {other:?}"),
    }
    assert!(matches!(&reply(41)[..], [Ok(Response::Ack)]));

    let events: Vec<&EventKind> = messages
        .iter()
        .filter_map(|m| match m {
            RigMessage::Event(e) => Some(&e.kind),
            _ => None,
        })
        .collect();
    let count = |f: &dyn Fn(&EventKind) -> bool| events.iter().filter(|e| f(e)).count();
    assert_eq!(count(&|e| matches!(e, EventKind::Captured(_))), 4);
    assert_eq!(count(&|e| matches!(e, EventKind::MoveDone { .. })), 1);
    assert_eq!(count(&|e| matches!(e, EventKind::Homed { .. })), 2);
    assert_eq!(
        count(&|e| matches!(
            e,
            EventKind::Halted {
                reason: HaltReason::EmergencyStop
            }
        )),
        1
    );
    assert_eq!(
        count(&|e| matches!(
            e,
            EventKind::Halted {
                reason: HaltReason::HeartbeatLost
            }
        )),
        1
    );
    assert_eq!(
        count(&|e| matches!(
            e,
            EventKind::Halted {
                reason: HaltReason::StepLate
            }
        )),
        1
    );

    let mut rig = new_rig();
    replay(&mut rig, &scenario(), &mut |_| {}).expect("replays");
    assert_eq!(rig.hw().violations(), 0);
    assert_eq!(rig.hw().lasers(), 0, "laser left on");
    assert!(rig.rig().rx_stats().dropped() >= 2);
}

#[test]
fn broken_scripts_are_errors_not_panics() {
    let mut rig = new_rig();
    let script = scenario();
    assert!(matches!(
        replay(&mut rig, &script[..5], &mut |_| {}),
        Err(ScriptError::Truncated { at: 0 })
    ));
    let mut bad = script[..11].to_vec();
    bad[8] = 99;
    bad[9] = 0;
    bad[10] = 0;
    assert!(matches!(
        replay(&mut new_rig(), &bad, &mut |_| {}),
        Err(ScriptError::UnknownKind { at: 0 })
    ));
}
