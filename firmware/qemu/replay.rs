//! Replays a recorded host session against the firmware core and reports every byte the rig
//! sends back, followed by a summary of what the simulated hardware did.
//!
//! Shared, unchanged, by the Cortex-M4 test binary (`src/bin/qemu/main.rs`, run under QEMU) and
//! the host test (`tests/qemu_replay.rs`) through `#[path]`: both feed the same script through the
//! same core, so any difference in their outputs is a difference in how the core runs on the two
//! instruction sets (word size, alignment, float-free integer maths, postcard/COBS/CRC).
//!
//! Script format, a sequence of records, all integers little-endian:
//! `time_us: u64, kind: u8, len: u16, payload: [u8; len]` where `kind` is one of the `KIND_*`
//! constants; the payload is only used by [`KIND_BYTES`].

use subsurf_firmware::Micros;
use subsurf_firmware::sim::{SimParams, SimRig};
use subsurf_protocol::{
    Capture, Command, GalvoPoint, MAX_FRAME, Move, MoveTarget, PROTOCOL_VERSION, Request,
    SaveError, encode_request,
};

/// Seed and length of the pseudo-random session that follows the recorded script.
pub const NOISE_SEED: u64 = 0x5EED_F00D_CAFE_0001;
/// Requests in the pseudo-random session.
pub const NOISE_REQUESTS: u32 = 400;

/// Bytes from the host arrive.
pub const KIND_BYTES: u8 = 0;
/// Emergency stop pressed.
pub const KIND_ESTOP_PRESS: u8 = 1;
/// Emergency stop released.
pub const KIND_ESTOP_RELEASE: u8 = 2;
/// Enclosure interlock opened.
pub const KIND_INTERLOCK_OPEN: u8 = 3;
/// Enclosure interlock closed.
pub const KIND_INTERLOCK_CLOSE: u8 = 4;
/// Only let time pass.
pub const KIND_ADVANCE: u8 = 5;
/// Wire the simulated laser drivers: payload `[1]` active low, `[0]` active high (a profile that
/// says otherwise has the wrong polarity).
pub const KIND_LASER_WIRING: u8 = 7;
/// The next profile save fails: payload `[0]` erase, `[1]` program, `[2]` read-back.
pub const KIND_FAIL_SAVE: u8 = 8;
/// The board's step interrupt ran later than one period (its train stopped the timer): what the
/// board's rig task tells the core (`Rig::handle_step_late`).
pub const KIND_STEP_LATE: u8 = 9;

/// Marks the start of the summary in the output.
pub const SUMMARY_MAGIC: &[u8] = b"\0SUMMARY";
/// Marks the start of the pseudo-random session's replies in the output.
pub const NOISE_MAGIC: &[u8] = b"\0NOISE";

/// Why a script could not be replayed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScriptError {
    /// A record header or payload runs past the end of the script.
    Truncated {
        /// Byte offset of the record.
        at: usize,
    },
    /// Unknown record kind.
    UnknownKind {
        /// Byte offset of the record.
        at: usize,
    },
}

/// The simulated rig the replays run on (the default simulated hardware and settings).
pub fn new_rig() -> SimRig {
    SimRig::new(SimParams::default())
}

/// Replay `script` on `rig`, handing every output chunk to `out` in order. Returns the number of
/// records replayed.
#[allow(dead_code)] // the QEMU binary uses `replay_observed`
pub fn replay(
    rig: &mut SimRig,
    script: &[u8],
    out: &mut dyn FnMut(&[u8]),
) -> Result<usize, ScriptError> {
    replay_observed(rig, script, out, &mut |_, _| {})
}

/// [`replay`], calling `observe(kind, false)` before and `observe(kind, true)` after each record
/// (the QEMU binary measures the stack per record kind with it).
pub fn replay_observed(
    rig: &mut SimRig,
    script: &[u8],
    out: &mut dyn FnMut(&[u8]),
    observe: &mut dyn FnMut(u8, bool),
) -> Result<usize, ScriptError> {
    let mut at = 0;
    let mut records = 0;
    let mut last: Micros = 0;
    while at < script.len() {
        let header = script
            .get(at..at + 11)
            .ok_or(ScriptError::Truncated { at })?;
        let mut time = [0u8; 8];
        time.copy_from_slice(&header[..8]);
        let time = Micros::from_le_bytes(time);
        let kind = header[8];
        let len = usize::from(u16::from_le_bytes([header[9], header[10]]));
        let payload = script
            .get(at + 11..at + 11 + len)
            .ok_or(ScriptError::Truncated { at })?;
        observe(kind, false);
        match kind {
            KIND_BYTES => rig.feed(time, payload),
            KIND_ESTOP_PRESS => rig.set_estop(time, true),
            KIND_ESTOP_RELEASE => rig.set_estop(time, false),
            KIND_INTERLOCK_OPEN => rig.set_interlock(time, false),
            KIND_INTERLOCK_CLOSE => rig.set_interlock(time, true),
            KIND_ADVANCE => rig.advance_to(time),
            KIND_LASER_WIRING => {
                rig.advance_to(time);
                let active_low = payload.first().is_some_and(|&b| b != 0);
                rig.rig_mut().hw_mut().set_laser_wiring(active_low);
            }
            KIND_STEP_LATE => {
                rig.advance_to(time);
                let now = rig.now();
                rig.rig_mut().handle_step_late(now);
            }
            KIND_FAIL_SAVE => {
                rig.advance_to(time);
                let error = match payload.first() {
                    Some(0) => SaveError::Erase,
                    Some(1) => SaveError::Program,
                    _ => SaveError::Verify,
                };
                rig.rig_mut().hw_mut().fail_next_save(error);
            }
            _ => return Err(ScriptError::UnknownKind { at }),
        }
        rig.drain_frames(|frame| out(frame));
        observe(kind, true);
        last = last.max(time);
        at += 11 + len;
        records += 1;
    }
    rig.advance_to(last);
    rig.drain_frames(|frame| out(frame));
    out(NOISE_MAGIC);
    observe(KIND_NOISE, false);
    noise_session(rig, last, NOISE_SEED, NOISE_REQUESTS, out);
    observe(KIND_NOISE, true);
    summary(rig, out);
    Ok(records)
}

/// Not a script record: marks the pseudo-random session for `observe`.
pub const KIND_NOISE: u8 = 6;

/// xorshift64*: a tiny deterministic generator, identical on every target.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// A pseudo-random host that sends every kind of request, some with flipped bits, truncated, or
/// split across reads, with line noise in between, and pokes the e-stop and interlock now and
/// then. Generated on the fly (no allocation), so the QEMU binary and the host test see the same
/// bytes without storing them.
pub fn noise_session(
    rig: &mut SimRig,
    start: Micros,
    seed: u64,
    requests: u32,
    out: &mut dyn FnMut(&[u8]),
) {
    let mut rng = Rng(seed | 1);
    let mut t = start;
    let mut frame = [0u8; MAX_FRAME];
    for i in 0..requests {
        t += 200 + rng.below(3_000);
        let point = GalvoPoint {
            x: rng.below(70_000) as u16,
            y: rng.below(70_000) as u16,
        };
        let command = match rng.below(15) {
            0 => Command::Status,
            1 => Command::Heartbeat,
            2 => Command::GetConfig,
            3 => Command::Galvo(point),
            4 => Command::Arm,
            5 => Command::Disarm,
            6 => Command::Laser {
                channel: rng.below(5) as u8,
                on: rng.below(2) == 0,
            },
            7 => Command::Move(Move {
                target: MoveTarget::Relative(rng.below(400) as i32 - 200),
                max_speed: 500 + rng.below(25_000) as u32,
                accel: 5_000 + rng.below(300_000) as u32,
            }),
            8 => Command::Capture(Capture {
                galvo: point,
                settle_us: if rng.below(2) == 0 {
                    None
                } else {
                    Some(rng.below(2_000) as u32)
                },
                channel: rng.below(4) as u8,
                exposure_us: 1 + rng.below(3_000) as u32,
                trigger_us: 1 + rng.below(500) as u32,
            }),
            9 => Command::Stop,
            10 => Command::ClearFault,
            11 => Command::Hello {
                protocol_version: PROTOCOL_VERSION,
            },
            12 => Command::Move(Move {
                target: MoveTarget::Absolute(rng.below(2_000) as i32 - 1_000),
                max_speed: rng.below(30_000) as u32,
                accel: rng.below(400_000) as u32,
            }),
            13 => Command::Replay {
                since: rng.below(80) as u32,
                max: rng.below(8) as u8,
            },
            _ => Command::Home,
        };
        // Mostly fresh sequence numbers, sometimes a retransmission of the previous one.
        let seq = if rng.below(10) == 0 { i } else { i + 1 };
        let request = Request {
            seq: 10_000 + seq,
            command,
        };
        let Ok(len) = encode_request(&request, &mut frame) else {
            continue;
        };
        let bytes = &mut frame[..len];
        match rng.below(16) {
            0 => {
                let at = rng.below(len as u64) as usize;
                bytes[at] ^= 1 << rng.below(8);
            }
            1 => {
                let cut = rng.below(len as u64) as usize;
                rig.feed(t, &bytes[..cut]);
                rig.feed(t, &[0]);
            }
            2 => {
                let mut noise = [0u8; 16];
                for b in &mut noise {
                    *b = rng.next() as u8;
                }
                rig.feed(t, &noise[..1 + rng.below(16) as usize]);
            }
            3 => match rng.below(4) {
                0 => rig.set_estop(t, true),
                1 => rig.set_estop(t, false),
                2 => rig.set_interlock(t, false),
                _ => rig.set_interlock(t, true),
            },
            _ => {}
        }
        // Deliver in one piece or split at a random point.
        let split = rng.below(len as u64 + 1) as usize;
        rig.feed(t, &bytes[..split]);
        rig.feed(t + 50, &bytes[split..]);
        rig.drain_frames(|f| out(f));
        // Let a move or capture progress between some requests.
        if rng.below(4) == 0 {
            t += rng.below(100_000);
            rig.advance_to(t);
            rig.drain_frames(|f| out(f));
        }
    }
    rig.set_estop(t, false);
    rig.set_interlock(t, true);
    t += 3_000_000;
    rig.advance_to(t);
    rig.drain_frames(|f| out(f));
}

fn summary(rig: &SimRig, out: &mut dyn FnMut(&[u8])) {
    let hw = rig.hw();
    out(SUMMARY_MAGIC);
    out(&hw.position().to_le_bytes());
    out(&hw.steps().to_le_bytes());
    out(&hw
        .min_step_interval_us()
        .unwrap_or(Micros::MAX)
        .to_le_bytes());
    out(&hw.violations().to_le_bytes());
    out(&rig.rig().rx_stats().dropped().to_le_bytes());
    out(&rig.rig().tx_dropped().to_le_bytes());
    out(&hw.laser_log().total().to_le_bytes());
    out(&hw.trigger_log().total().to_le_bytes());
    out(&hw.galvo_log().total().to_le_bytes());
    // The newest output changes with their times: the capture sequence's µs timing.
    for e in hw.laser_log().entries() {
        out(&e.at.to_le_bytes());
        out(&[e.value]);
    }
    for e in hw.trigger_log().entries() {
        out(&e.at.to_le_bytes());
        out(&[u8::from(e.value)]);
    }
    for e in hw.galvo_log().entries() {
        out(&e.at.to_le_bytes());
        out(&e.value.x.to_le_bytes());
        out(&e.value.y.to_le_bytes());
    }
}
