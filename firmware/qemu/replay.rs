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

/// Marks the start of the summary in the output.
pub const SUMMARY_MAGIC: &[u8] = b"\0SUMMARY";

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
    summary(rig, out);
    Ok(records)
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
