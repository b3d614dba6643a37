//! Wire-format tests: golden bytes pin the format; property tests prove round trips and the
//! decoder's robustness against noise, corruption and arbitrary chunking.

use proptest::collection::vec;
use proptest::prelude::*;
use subsurf_protocol::*;

// ---------------------------------------------------------------------------------------------
// Golden bytes, computed independently with Python (zlib.crc32 + a textbook COBS encoder).

#[test]
fn golden_heartbeat_request() {
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 1,
        command: Command::Heartbeat,
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(&out[..n], &[7, 1, 1, 40, 19, 197, 47, 0]);
}

#[test]
fn golden_hello_request_with_varint_seq() {
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 300,
        command: Command::Hello {
            protocol_version: 1,
        },
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(&out[..n], &[3, 172, 2, 6, 1, 89, 157, 122, 82, 0]);
}

#[test]
fn golden_error_reply() {
    let mut out = [0u8; MAX_FRAME];
    let reply = Reply {
        seq: 7,
        result: Err(RigError::NotArmed),
    };
    let n = encode_reply(&reply, &mut out).unwrap();
    assert_eq!(&out[..n], &[1, 8, 7, 1, 1, 78, 200, 23, 74, 0]);
}

/// Version 5 appended `LaserPolarity` as error variant 16; the earlier errors keep their bytes.
#[test]
fn golden_laser_polarity_reply() {
    let mut out = [0u8; MAX_FRAME];
    let reply = Reply {
        seq: 7,
        result: Err(RigError::LaserPolarity),
    };
    let n = encode_reply(&reply, &mut out).unwrap();
    assert_eq!(&out[..n], &[1, 8, 7, 1, 16, 188, 232, 167, 32, 0]);
}

/// Version 5: `ProfileNotSaved(Verify)` is error variant 17 with its cause (variant 3), and
/// `GetStoredProfile` command variant 20.
#[test]
fn golden_profile_not_saved_reply_and_stored_profile_request() {
    let mut out = [0u8; MAX_FRAME];
    let reply = Reply {
        seq: 7,
        result: Err(RigError::ProfileNotSaved(SaveError::Verify)),
    };
    let n = encode_reply(&reply, &mut out).unwrap();
    assert_eq!(&out[..n], &[1, 9, 7, 1, 17, 3, 57, 215, 231, 144, 0]);
    let req = Request {
        seq: 1,
        command: Command::GetStoredProfile,
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(&out[..n], &[7, 1, 20, 195, 247, 24, 66, 0]);
}

#[test]
fn golden_relative_move() {
    let mut out = [0u8; MAX_FRAME];
    let mv = Move {
        target: MoveTarget::Relative(-2),
        max_speed: 1000,
        accel: 500,
    };
    let req = Request {
        seq: 0,
        command: Command::Move(mv),
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(
        &out[..n],
        &[1, 12, 6, 1, 3, 232, 7, 244, 3, 119, 73, 83, 117, 0]
    );
}

/// Version 2's event recovery, appended to the enums: `Replay` is command variant 17.
#[test]
fn golden_replay_request() {
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 5,
        command: Command::Replay { since: 300, max: 5 },
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(&out[..n], &[10, 5, 17, 172, 2, 5, 158, 122, 89, 116, 0]);
}

/// `Events` is response variant 6: oldest, next_event_seq, then a length-prefixed event list.
#[test]
fn golden_events_reply() {
    let mut out = [0u8; MAX_FRAME];
    let mut events = heapless::Vec::new();
    events
        .push(Event {
            event_seq: 3,
            timestamp_us: 99,
            kind: EventKind::Homed { previous: None },
        })
        .unwrap();
    events
        .push(Event {
            event_seq: 4,
            timestamp_us: 1000,
            kind: EventKind::MoveDone { position: -2 },
        })
        .unwrap();
    let reply = Reply {
        seq: 9,
        result: Ok(Response::Events(EventReplay {
            oldest: 3,
            next_event_seq: 5,
            events,
        })),
    };
    let n = encode_reply(&reply, &mut out).unwrap();
    assert_eq!(
        &out[..n],
        &[
            1, 2, 9, 8, 6, 3, 5, 2, 3, 99, 2, 10, 4, 232, 7, 1, 3, 181, 30, 112, 171, 0
        ]
    );
}

/// Version 3: `IntervalTooShort { min_us }` is error variant 14.
#[test]
fn golden_interval_too_short_reply() {
    let mut out = [0u8; MAX_FRAME];
    let reply = Reply {
        seq: 7,
        result: Err(RigError::IntervalTooShort { min_us: 10_020 }),
    };
    let n = encode_reply(&reply, &mut out).unwrap();
    assert_eq!(&out[..n], &[1, 10, 7, 1, 14, 164, 78, 166, 34, 207, 234, 0]);
}

/// Version 3's `Captured`: trigger edge, exposure-active delay and duration, exposure count, lit.
#[test]
fn golden_captured_event() {
    let mut out = [0u8; MAX_FRAME];
    let event = Event {
        event_seq: 3,
        timestamp_us: 1000,
        kind: EventKind::Captured(Captured {
            capture_id: 4,
            program_index: Some(2),
            triggered_at_us: 990,
            exposure: Some(ExposureActive {
                delay_us: 15,
                duration_us: 100,
            }),
            exposure_count: 5,
            lit: true,
            galvo: GalvoPoint { x: 300, y: 2 },
            channel: 1,
        }),
    };
    let n = encode_event(&event, &mut out).unwrap();
    assert_eq!(
        &out[..n],
        &[
            5, 1, 3, 232, 7, 19, 4, 1, 2, 222, 7, 1, 15, 100, 5, 1, 172, 2, 2, 1, 64, 89, 31, 63, 0
        ]
    );
}

/// Version 6's `DarkCapture` (command variant 21): exposure and trigger pulse, no laser.
#[test]
fn golden_dark_capture() {
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 7,
        command: Command::DarkCapture(DarkCapture {
            exposure_us: 20_000,
            trigger_us: 100,
        }),
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(
        &out[..n],
        &[11, 7, 21, 160, 156, 1, 100, 120, 69, 97, 238, 0]
    );
}

/// Version 3's `SetProfile` (command variant 18) with the documented wiring's profile.
#[test]
fn golden_set_default_profile() {
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 2,
        command: Command::SetProfile(RigProfile::DEFAULT),
    };
    let n = encode_request(&req, &mut out).unwrap();
    assert_eq!(
        &out[..n],
        &[
            16, 2, 18, 200, 1, 16, 5, 1, 160, 156, 1, 192, 154, 12, 5, 5, 1, 2, 1, 8, 100, 20, 144,
            78, 20, 208, 15, 1, 2, 3, 24, 50, 50, 144, 78, 192, 62, 192, 184, 2, 232, 7, 200, 1,
            208, 15, 208, 140, 1, 1, 16, 154, 12, 134, 0
        ]
    );
}

#[test]
fn default_profile_is_valid_and_bounds_are_enforced() {
    let p = RigProfile::DEFAULT;
    assert_eq!(p.validate(), Ok(()));
    assert_eq!(p.steps_per_rev(), Some(16_000));
    assert_eq!(p.galvo_max(), u16::MAX);
    let mut internal = p;
    internal.galvo = RigProfile::INTERNAL_DAC;
    assert_eq!(internal.validate(), Ok(()));
    assert_eq!(internal.galvo_max(), 4095);
    assert_eq!(internal.galvo.output.center(), 2048);
    let mut bad = p;
    bad.motor.gear_den = 3;
    assert_eq!(bad.validate(), Err(ProfileError::Gearing));
    let mut bad = p;
    bad.motor.step_pulse_us = 1;
    assert_eq!(bad.validate(), Err(ProfileError::StepTiming));
    // What the board cannot do is refused, not clamped or ignored (as its first power-on
    // showed).
    let mut bad = p;
    bad.motor.step_pulse_us = MAX_STEP_PULSE_US + 1;
    bad.motor.max_speed = 1_000;
    assert_eq!(bad.validate(), Err(ProfileError::StepTiming));
    let mut bad = p;
    bad.motor.dir_setup_us = MAX_DIR_SETUP_US + 1;
    assert_eq!(bad.validate(), Err(ProfileError::StepTiming));
    let mut bad = p;
    bad.laser.channels = BOARD_LASER_CHANNELS + 1;
    assert_eq!(bad.validate(), Err(ProfileError::Laser));
    let mut bad = p;
    bad.camera.min_exposure_us = 1;
    assert_eq!(bad.validate(), Err(ProfileError::Camera));
    let mut bad = p;
    bad.laser.manual_max_ms = MAX_MANUAL_LASER_MS + 1;
    assert_eq!(bad.validate(), Err(ProfileError::Laser));
    let mut bad = p;
    bad.homing.slow_speed = bad.homing.speed + 1;
    assert_eq!(bad.validate(), Err(ProfileError::Homing));
}

#[test]
fn reply_and_event_encoders_match_rig_message() {
    let reply = Reply {
        seq: 9,
        result: Ok(Response::CaptureStarted { capture_id: 4 }),
    };
    let event = Event {
        event_seq: 3,
        timestamp_us: 99,
        kind: EventKind::Homed { previous: None },
    };
    let (mut a, mut b) = ([0u8; MAX_FRAME], [0u8; MAX_FRAME]);
    let n = encode_reply(&reply, &mut a).unwrap();
    let m = encode_frame(&RigMessage::Reply(reply), &mut b).unwrap();
    assert_eq!(&a[..n], &b[..m]);
    let n = encode_event(&event, &mut a).unwrap();
    let m = encode_frame(&RigMessage::Event(event), &mut b).unwrap();
    assert_eq!(&a[..n], &b[..m]);
}

#[test]
fn encode_reports_small_buffer() {
    let req = Request {
        seq: 1,
        command: Command::Heartbeat,
    };
    for len in 0..8 {
        let mut out = [0u8; 8];
        assert_eq!(
            encode_request(&req, &mut out[..len]),
            Err(EncodeError::BufferTooSmall)
        );
    }
}

#[test]
fn largest_messages_fit_in_a_frame() {
    let mut out = [0u8; MAX_FRAME];
    let far = GalvoPoint {
        x: u16::MAX,
        y: u16::MAX,
    };
    let mut points = heapless::Vec::new();
    while points.push(far).is_ok() {}
    let chunk = Command::ProgramPoints(ProgramChunk {
        offset: u16::MAX,
        points,
    });
    let n = encode_request(
        &Request {
            seq: u32::MAX,
            command: chunk,
        },
        &mut out,
    )
    .unwrap();
    assert!(n <= MAX_FRAME);
    let status = Status {
        boot_nonce: u32::MAX,
        exposures: u32::MAX,
        state: RigState::Fault,
        position: i32::MIN,
        homed: true,
        armed: true,
        lasers: u8::MAX,
        galvo: far,
        inputs: Inputs {
            estop: true,
            interlock_closed: true,
            home_switch: true,
        },
        fault: Some(Fault::HomingFailed),
        next_capture_id: u32::MAX,
        next_event_seq: u32::MAX,
        program_received: u16::MAX,
        program_len: u16::MAX,
        rx_dropped: u32::MAX,
        uptime_us: u64::MAX,
    };
    let reply = Reply {
        seq: u32::MAX,
        result: Ok(Response::Status(status)),
    };
    assert!(encode_reply(&reply, &mut out).unwrap() <= MAX_FRAME);
    // A full replay of the largest event there is.
    let largest = Event {
        event_seq: u32::MAX,
        timestamp_us: u64::MAX,
        kind: EventKind::Captured(Captured {
            capture_id: u32::MAX,
            program_index: Some(u16::MAX),
            triggered_at_us: u64::MAX,
            exposure: Some(ExposureActive {
                delay_us: u32::MAX,
                duration_us: u32::MAX,
            }),
            exposure_count: u32::MAX,
            lit: true,
            galvo: far,
            channel: u8::MAX,
        }),
    };
    let mut events = heapless::Vec::new();
    while events.push(largest.clone()).is_ok() {}
    assert_eq!(events.len(), REPLAY_BATCH);
    let reply = Reply {
        seq: u32::MAX,
        result: Ok(Response::Events(EventReplay {
            oldest: u32::MAX,
            next_event_seq: u32::MAX,
            events,
        })),
    };
    assert!(encode_reply(&reply, &mut out).unwrap() <= MAX_FRAME);
    // The largest profile there is.
    let mut profile = RigProfile::DEFAULT;
    profile.motor = MotorProfile {
        full_steps_per_rev: u16::MAX,
        microsteps: u16::MAX,
        gear_num: u16::MAX,
        gear_den: u16::MAX,
        max_speed: u32::MAX,
        max_accel: u32::MAX,
        step_pulse_us: u16::MAX,
        dir_setup_us: u16::MAX,
        invert_dir: true,
        step_active_low: true,
        enable_active_low: true,
    };
    profile.camera.readout_us = u32::MAX;
    profile.homing.max_steps = u32::MAX;
    let reply = Reply {
        seq: u32::MAX,
        result: Ok(Response::Profile(profile)),
    };
    assert!(encode_reply(&reply, &mut out).unwrap() <= MAX_FRAME);
}

#[test]
fn oversize_run_is_dropped_and_counted_then_resyncs() {
    let mut dec = FrameDecoder::new();
    let junk = [0x55u8; 3 * MAX_FRAME];
    assert_eq!(dec.feed::<Request>(&junk), (None, &[][..]));
    let mut out = [0u8; MAX_FRAME];
    let req = Request {
        seq: 5,
        command: Command::Status,
    };
    let n = encode_request(&req, &mut out).unwrap();
    // The junk has no delimiter, so the first frame's delimiter closes the oversize run.
    assert_eq!(dec.decode::<Request>(&out[..n]).count(), 0);
    assert_eq!(dec.stats().oversize, 1);
    assert_eq!(
        dec.decode::<Request>(&out[..n]).collect::<Vec<_>>(),
        vec![req]
    );
    assert_eq!(dec.stats().frames, 1);
}

#[test]
fn valid_crc_but_unparseable_is_malformed() {
    let mut out = [0u8; MAX_FRAME];
    // Ten 0xff bytes: a u32 varint that never terminates.
    let n = encode_frame(&[0xffu8; 10], &mut out).unwrap();
    let mut dec = FrameDecoder::new();
    assert_eq!(dec.decode::<Request>(&out[..n]).count(), 0);
    assert_eq!(dec.stats().malformed, 1);
    assert_eq!(dec.stats().dropped(), 1);
    // Trailing bytes after a complete message are malformed too.
    let n = encode_frame(
        &(
            Request {
                seq: 1,
                command: Command::Stop,
            },
            7u8,
        ),
        &mut out,
    )
    .unwrap();
    assert_eq!(dec.decode::<Request>(&out[..n]).count(), 0);
    assert_eq!(dec.stats().malformed, 2);
}

#[test]
fn empty_frames_are_ignored_and_not_counted() {
    let mut dec = FrameDecoder::new();
    assert_eq!(dec.decode::<Request>(&[0, 0, 0]).count(), 0);
    assert_eq!(dec.stats(), DecoderStats::default());
    // One byte plus delimiter: too short to hold a CRC.
    assert_eq!(dec.decode::<Request>(&[2, 7, 0]).count(), 0);
    assert_eq!(dec.stats().corrupt, 1);
}

// ---------------------------------------------------------------------------------------------
// Strategies.

fn galvo() -> impl Strategy<Value = GalvoPoint> {
    (any::<u16>(), any::<u16>()).prop_map(|(x, y)| GalvoPoint { x, y })
}

fn config() -> impl Strategy<Value = Config> {
    any::<u32>().prop_map(|heartbeat_timeout_ms| Config {
        heartbeat_timeout_ms,
    })
}

fn profile() -> impl Strategy<Value = RigProfile> {
    (
        any::<[u16; 6]>(),
        any::<[u32; 16]>(),
        any::<[bool; 8]>(),
        any::<u8>(),
    )
        .prop_map(|(h, w, b, channels)| RigProfile {
            motor: MotorProfile {
                full_steps_per_rev: h[0],
                microsteps: h[1],
                gear_num: h[2],
                gear_den: h[3],
                max_speed: w[0],
                max_accel: w[1],
                step_pulse_us: h[4],
                dir_setup_us: h[5],
                invert_dir: b[0],
                step_active_low: b[1],
                enable_active_low: b[2],
            },
            galvo: GalvoProfile {
                output: if b[3] {
                    GalvoOutput::ExternalDac16
                } else {
                    GalvoOutput::InternalDac12
                },
                settle_min_us: w[2],
                settle_per_kcode_us: w[3],
            },
            camera: CameraProfile {
                readout_us: w[4],
                min_exposure_us: w[5],
                confirm_timeout_us: w[6],
                trigger_active_low: b[4],
                exposure_active_low: b[5],
            },
            laser: LaserProfile {
                channels,
                active_low: b[6],
                lead_us: w[7],
                tail_us: w[8],
                manual_max_ms: w[9],
            },
            homing: HomingProfile {
                speed: w[10],
                accel: w[11],
                slow_speed: w[12],
                backoff_steps: w[13],
                debounce_us: w[14],
                max_steps: w[15],
                switch_active_low: b[7],
            },
        })
}

fn capture() -> impl Strategy<Value = Capture> {
    (
        galvo(),
        any::<Option<u32>>(),
        any::<u8>(),
        any::<u32>(),
        any::<u32>(),
    )
        .prop_map(
            |(galvo, settle_us, channel, exposure_us, trigger_us)| Capture {
                galvo,
                settle_us,
                channel,
                exposure_us,
                trigger_us,
            },
        )
}

fn command() -> impl Strategy<Value = Command> {
    let target = prop_oneof![
        any::<i32>().prop_map(MoveTarget::Absolute),
        any::<i32>().prop_map(MoveTarget::Relative)
    ];
    let header = (
        any::<u16>(),
        any::<u8>(),
        any::<Option<u32>>(),
        any::<[u32; 3]>(),
    )
        .prop_map(|(len, channel, settle_us, v)| ProgramHeader {
            len,
            channel,
            settle_us,
            exposure_us: v[0],
            trigger_us: v[1],
            interval_us: v[2],
        });
    let chunk = (any::<u16>(), vec(galvo(), 0..=PROGRAM_CHUNK)).prop_map(|(offset, pts)| {
        Command::ProgramPoints(ProgramChunk {
            offset,
            points: heapless::Vec::from_slice(&pts).unwrap_or_default(),
        })
    });
    prop_oneof![
        any::<u16>().prop_map(|protocol_version| Command::Hello { protocol_version }),
        Just(Command::Heartbeat),
        Just(Command::Status),
        Just(Command::GetConfig),
        config().prop_map(Command::SetConfig),
        Just(Command::Home),
        (target, any::<u32>(), any::<u32>()).prop_map(|(target, max_speed, accel)| Command::Move(
            Move {
                target,
                max_speed,
                accel
            }
        )),
        galvo().prop_map(Command::Galvo),
        Just(Command::Arm),
        Just(Command::Disarm),
        (any::<u8>(), any::<bool>()).prop_map(|(channel, on)| Command::Laser { channel, on }),
        capture().prop_map(Command::Capture),
        header.prop_map(Command::ProgramLoad),
        chunk,
        Just(Command::ProgramRun),
        Just(Command::Stop),
        Just(Command::ClearFault),
        (any::<u32>(), any::<u8>()).prop_map(|(since, max)| Command::Replay { since, max }),
        profile().prop_map(Command::SetProfile),
        Just(Command::GetProfile),
        Just(Command::GetStoredProfile),
        (any::<u32>(), any::<u32>()).prop_map(|(exposure_us, trigger_us)| Command::DarkCapture(
            DarkCapture {
                exposure_us,
                trigger_us
            }
        )),
    ]
}

fn request() -> impl Strategy<Value = Request> {
    (any::<u32>(), command()).prop_map(|(seq, command)| Request { seq, command })
}

fn fault() -> impl Strategy<Value = Fault> {
    prop_oneof![
        Just(Fault::EmergencyStop),
        Just(Fault::HomingFailed),
        Just(Fault::StepStall),
        Just(Fault::StepLate)
    ]
}

fn rig_error() -> impl Strategy<Value = RigError> {
    prop_oneof![
        any::<u16>().prop_map(|rig| RigError::UnknownVersion { rig }),
        Just(RigError::NotArmed),
        Just(RigError::InterlockOpen),
        Just(RigError::EmergencyStop),
        fault().prop_map(RigError::Faulted),
        Just(RigError::Busy),
        Just(RigError::OutOfRange),
        Just(RigError::NoSuchChannel),
        Just(RigError::ProgramIncomplete),
        Just(RigError::StaleSequence),
        Just(RigError::NoSession),
        Just(RigError::NotHomed),
        Just(RigError::BadProfile(ProfileError::Camera)),
        any::<u32>().prop_map(|min_us| RigError::ExposureTooShort { min_us }),
        any::<u32>().prop_map(|min_us| RigError::IntervalTooShort { min_us }),
        Just(RigError::ProfileNotStored),
        Just(RigError::LaserPolarity),
        prop_oneof![
            Just(SaveError::Encode),
            Just(SaveError::Erase),
            Just(SaveError::Program),
            Just(SaveError::Verify)
        ]
        .prop_map(RigError::ProfileNotSaved),
    ]
}

fn status() -> impl Strategy<Value = Status> {
    let state = prop_oneof![
        Just(RigState::Idle),
        Just(RigState::Homing),
        Just(RigState::Moving),
        Just(RigState::Capturing),
        Just(RigState::Program),
        Just(RigState::Fault),
    ];
    (
        state,
        any::<i32>(),
        any::<[bool; 5]>(),
        any::<u8>(),
        galvo(),
        proptest::option::of(fault()),
        any::<[u32; 5]>(),
        any::<[u16; 2]>(),
        any::<u64>(),
    )
        .prop_map(
            |(state, position, b, lasers, galvo, fault, c, p, uptime_us)| Status {
                boot_nonce: c[3],
                exposures: c[4],
                state,
                position,
                homed: b[0],
                armed: b[1],
                lasers,
                galvo,
                inputs: Inputs {
                    estop: b[2],
                    interlock_closed: b[3],
                    home_switch: b[4],
                },
                fault,
                next_capture_id: c[0],
                next_event_seq: c[1],
                program_received: p[0],
                program_len: p[1],
                rx_dropped: c[2],
                uptime_us,
            },
        )
}

fn response() -> impl Strategy<Value = Response> {
    let caps = (any::<[u32; 6]>(), any::<u16>(), any::<u8>(), any::<u16>()).prop_map(
        |(v, galvo_max, laser_channels, max_program_points)| Capabilities {
            steps_per_rev: v[0],
            galvo_max,
            laser_channels,
            max_speed: v[1],
            max_accel: v[2],
            max_exposure_us: v[3],
            min_exposure_us: v[4],
            camera_readout_us: v[5],
            max_program_points,
        },
    );
    let hello =
        (any::<[u16; 4]>(), any::<u32>(), caps).prop_map(|(v, boot_nonce, capabilities)| {
            Response::Hello(Hello {
                protocol_version: v[0],
                firmware_version: FirmwareVersion {
                    major: v[1],
                    minor: v[2],
                    patch: v[3],
                },
                boot_nonce,
                capabilities,
            })
        });
    prop_oneof![
        Just(Response::Ack),
        hello,
        status().prop_map(Response::Status),
        config().prop_map(Response::Config),
        any::<u32>().prop_map(|capture_id| Response::CaptureStarted { capture_id }),
        any::<u32>().prop_map(|first_capture_id| Response::ProgramStarted { first_capture_id }),
        profile().prop_map(Response::Profile),
    ]
}

fn rig_message() -> impl Strategy<Value = RigMessage> {
    let reason = prop_oneof![
        Just(HaltReason::Stop),
        Just(HaltReason::EmergencyStop),
        Just(HaltReason::InterlockOpen),
        Just(HaltReason::HeartbeatLost),
        Just(HaltReason::HomingFailed),
        Just(HaltReason::LaserTimeout),
        Just(HaltReason::StepStall),
        Just(HaltReason::StepLate),
    ];
    let captured = (
        any::<u32>(),
        any::<Option<u16>>(),
        any::<u64>(),
        any::<Option<(u32, u32)>>(),
        any::<(u32, bool)>(),
        galvo(),
        any::<u8>(),
    )
        .prop_map(
            |(
                capture_id,
                program_index,
                triggered_at_us,
                e,
                (exposure_count, lit),
                galvo,
                channel,
            )| {
                EventKind::Captured(Captured {
                    capture_id,
                    program_index,
                    triggered_at_us,
                    exposure: e.map(|(delay_us, duration_us)| ExposureActive {
                        delay_us,
                        duration_us,
                    }),
                    exposure_count,
                    lit,
                    galvo,
                    channel,
                })
            },
        );
    let kind = prop_oneof![
        captured,
        any::<i32>().prop_map(|position| EventKind::MoveDone { position }),
        any::<Option<i32>>().prop_map(|previous| EventKind::Homed { previous }),
        (any::<u16>(), any::<bool>()).prop_map(|(completed, finished)| EventKind::ProgramDone {
            completed,
            finished
        }),
        reason.prop_map(|reason| EventKind::Halted { reason }),
    ];
    let event = (any::<u32>(), any::<u64>(), kind)
        .prop_map(|(event_seq, timestamp_us, kind)| Event {
            event_seq,
            timestamp_us,
            kind,
        })
        .boxed();
    let replay = (
        any::<u32>(),
        any::<u32>(),
        vec(event.clone(), 0..=REPLAY_BATCH),
    )
        .prop_map(|(oldest, next_event_seq, events)| {
            Ok(Response::Events(EventReplay {
                oldest,
                next_event_seq,
                events: heapless::Vec::from_slice(&events).unwrap_or_default(),
            }))
        });
    let result = prop_oneof![response().prop_map(Ok), replay, rig_error().prop_map(Err)];
    prop_oneof![
        (any::<u32>(), result).prop_map(|(seq, result)| RigMessage::Reply(Reply { seq, result })),
        event.prop_map(RigMessage::Event),
    ]
}

fn frame_of<T: serde::Serialize>(msg: &T) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    let n = encode_frame(msg, &mut out).expect("every message fits in a frame");
    out[..n].to_vec()
}

fn decode_all<T: serde::de::DeserializeOwned>(dec: &mut FrameDecoder, bytes: &[u8]) -> Vec<T> {
    dec.decode(bytes).collect()
}

// ---------------------------------------------------------------------------------------------
// Properties.

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn every_request_round_trips(req in request()) {
        let bytes = frame_of(&req);
        prop_assert!(bytes.len() <= MAX_FRAME);
        prop_assert_eq!(bytes.iter().filter(|&&b| b == 0).count(), 1);
        let mut dec = FrameDecoder::new();
        prop_assert_eq!(decode_all::<Request>(&mut dec, &bytes), vec![req]);
        prop_assert_eq!(dec.stats().dropped(), 0);
    }

    #[test]
    fn every_rig_message_round_trips(msg in rig_message()) {
        let bytes = frame_of(&msg);
        prop_assert!(bytes.len() <= MAX_FRAME);
        let mut typed = [0u8; MAX_FRAME];
        let n = match &msg {
            RigMessage::Reply(r) => encode_reply(r, &mut typed),
            RigMessage::Event(e) => encode_event(e, &mut typed),
        }.unwrap();
        prop_assert_eq!(&typed[..n], &bytes[..]);
        let mut dec = FrameDecoder::new();
        prop_assert_eq!(decode_all::<RigMessage>(&mut dec, &bytes), vec![msg]);
    }

    #[test]
    fn decoder_never_panics_on_arbitrary_bytes(
        bytes in vec(any::<u8>(), 0..2048),
        cut in any::<prop::sample::Index>(),
    ) {
        let mut dec = FrameDecoder::new();
        let at = cut.index(bytes.len() + 1);
        let _ = decode_all::<Request>(&mut dec, &bytes[..at]);
        let _ = decode_all::<Request>(&mut dec, &bytes[at..]);
        let mut dec = FrameDecoder::new();
        let _ = decode_all::<RigMessage>(&mut dec, &bytes);
    }

    #[test]
    fn never_yields_an_unsent_frame(
        reqs in vec(request(), 1..8),
        flips in vec((any::<prop::sample::Index>(), 1u8..=255), 1..6),
    ) {
        let mut stream: Vec<u8> = reqs.iter().flat_map(frame_of).collect();
        for (at, mask) in flips {
            let i = at.index(stream.len());
            stream[i] ^= mask;
        }
        let mut dec = FrameDecoder::new();
        for got in decode_all::<Request>(&mut dec, &stream) {
            prop_assert!(reqs.contains(&got), "decoder invented {:?}", got);
        }
    }

    #[test]
    fn resyncs_within_one_frame_after_noise(
        noise in vec(any::<u8>(), 0..600),
        reqs in vec(request(), 2..8),
    ) {
        let mut stream = noise.clone();
        for r in &reqs {
            stream.extend(frame_of(r));
        }
        let mut dec = FrameDecoder::new();
        let got = decode_all::<Request>(&mut dec, &stream);
        // The first frame may merge with trailing noise; every later one must come through.
        let n = got.len();
        prop_assert!(n >= reqs.len() - 1);
        prop_assert_eq!(&got[n - (reqs.len() - 1)..], &reqs[1..]);
    }

    #[test]
    fn split_at_every_boundary_decodes_identically(reqs in vec(request(), 1..4)) {
        let stream: Vec<u8> = reqs.iter().flat_map(frame_of).collect();
        for cut in 0..=stream.len() {
            let mut dec = FrameDecoder::new();
            let mut got = decode_all::<Request>(&mut dec, &stream[..cut]);
            got.extend(decode_all::<Request>(&mut dec, &stream[cut..]));
            prop_assert_eq!(&got, &reqs);
        }
        // And one byte at a time.
        let mut dec = FrameDecoder::new();
        let got: Vec<Request> =
            stream.chunks(1).flat_map(|c| decode_all::<Request>(&mut dec, c)).collect();
        prop_assert_eq!(got, reqs);
    }

    #[test]
    fn every_drop_is_counted(reqs in vec(request(), 1..10), corrupt in vec(any::<bool>(), 10)) {
        let mut stream = Vec::new();
        let mut corrupted = 0u32;
        for (r, c) in reqs.iter().zip(&corrupt) {
            let mut f = frame_of(r);
            if *c {
                // Flip a byte inside the frame (never the delimiter): CRC or COBS must catch it.
                let mid = f.len() / 2;
                f[mid] ^= 0x5a;
                if f[mid] == 0 { f[mid] = 0x01; }
                corrupted += 1;
            }
            stream.extend(f);
        }
        let mut dec = FrameDecoder::new();
        let got = decode_all::<Request>(&mut dec, &stream);
        let s = dec.stats();
        // A flipped non-delimiter byte keeps the frame count; CRC-32 or COBS rejects the frame.
        prop_assert_eq!(s.frames as usize, got.len());
        prop_assert_eq!(s.frames, reqs.len() as u32 - corrupted);
        prop_assert_eq!(s.dropped(), corrupted);
    }
}
