//! The simulated rig runner: the firmware core on the firmware's simulated hardware
//! (`subsurf_firmware::sim`), served behind any byte link.
//!
//! - [`VirtualRig`] wraps the firmware's `SimRig` and keeps *complete* logs of what the hardware
//!   did (the firmware keeps only its newest 256 entries per output, being `no_std`).
//! - [`SimLink`] steps a [`VirtualRig`] inline behind faulty [`crate::link::VirtualWire`]s in
//!   virtual time: deterministic, never sleeps. `subsurf rig --sim` and most tests use it.
//! - [`serve`], [`spawn`] and [`spawn_in_memory`] run a [`VirtualRig`] in real time over any
//!   [`crate::link::ByteLink`]: a pseudo-terminal for `subsurf rig serve-sim`, the pty tests and
//!   `subsurf bench rig`.

mod link;
mod serve;

pub use link::SimLink;
pub use serve::{SimServer, serve, serve_forever, spawn, spawn_in_memory};
pub use subsurf_firmware::sim::{LogEntry, SimHardware, SimParams};

use subsurf_firmware::Micros;
use subsurf_firmware::sim::{Log, SimRig};
use subsurf_protocol::{GalvoPoint, Status};

/// The firmware core on simulated hardware, with complete output logs.
///
/// Time is in µs since the rig's power-on and only moves forward. Feed it bytes with
/// [`VirtualRig::handle_input`], let time pass with [`VirtualRig::advance`], collect its frames
/// with [`VirtualRig::drain_output`]; [`VirtualRig::next_deadline_us`] says when it next wants to
/// run by itself.
pub struct VirtualRig {
    sim: SimRig,
    start_position: i64,
    /// Frames taken from the firmware after every step: its own queue holds only 32 messages.
    out: Vec<u8>,
    galvo: LogCopy<GalvoPoint>,
    lasers: LogCopy<u8>,
    trigger: LogCopy<bool>,
}

impl std::fmt::Debug for VirtualRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VirtualRig")
            .field("now_us", &self.sim.now())
            .field("status", &self.sim.rig().status())
            .finish_non_exhaustive()
    }
}

/// An unbounded copy of one of the firmware's bounded logs, taken after every step.
#[derive(Debug, Default)]
struct LogCopy<T> {
    entries: Vec<LogEntry<T>>,
    seen: u64,
    missed: u64,
}

impl<T: Copy> LogCopy<T> {
    fn sync(&mut self, log: &Log<T>) {
        let new = log.total().saturating_sub(self.seen);
        if new == 0 {
            return;
        }
        let kept: Vec<&LogEntry<T>> = log.entries().collect();
        let available = (kept.len() as u64).min(new);
        // More new entries than the firmware kept: the oldest of them are gone for good.
        self.missed += new - available;
        let skip = kept.len() - usize::try_from(available).unwrap_or(kept.len());
        self.entries.extend(kept.into_iter().skip(skip).copied());
        self.seen = log.total();
    }
}

impl Default for VirtualRig {
    fn default() -> Self {
        Self::new(SimParams::default())
    }
}

impl VirtualRig {
    /// A rig at time 0 with the given simulated hardware and settings.
    pub fn new(params: SimParams) -> Self {
        let mut rig = Self {
            sim: SimRig::new(params),
            start_position: params.start_position,
            out: Vec::new(),
            galvo: LogCopy::default(),
            lasers: LogCopy::default(),
            trigger: LogCopy::default(),
        };
        rig.sync_logs();
        rig
    }

    /// Copy new log entries and take queued frames: called after every step of the core.
    fn sync_logs(&mut self) {
        let out = &mut self.out;
        self.sim.drain_frames(|frame| out.extend_from_slice(frame));
        let hw = self.sim.hw();
        self.galvo.sync(hw.galvo_log());
        self.lasers.sync(hw.laser_log());
        self.trigger.sync(hw.trigger_log());
    }

    /// Bytes from the host arrive at `now_us`.
    pub fn handle_input(&mut self, now_us: Micros, bytes: &[u8]) {
        self.advance(now_us);
        self.sim.feed(now_us, bytes);
        self.sync_logs();
    }

    /// Let time pass up to `now_us`, one rig deadline at a time (so neither the firmware's
    /// bounded logs nor its bounded output queue overflow between two looks).
    pub fn advance(&mut self, now_us: Micros) {
        while let Some(t) = self.sim.next_deadline() {
            if t >= now_us {
                break;
            }
            // Runs everything due at `t` (or now, if `t` has passed already).
            self.sim.advance_to(t);
            self.sync_logs();
            if self.sim.next_deadline().is_some_and(|next| next <= t) {
                // A deadline that does not move: let the firmware's own guard handle the rest.
                break;
            }
        }
        self.sim.advance_to(now_us);
        self.sync_logs();
    }

    /// Append every frame the rig wants to send to `out`.
    pub fn drain_output(&mut self, out: &mut Vec<u8>) {
        self.sync_logs();
        out.append(&mut self.out);
    }

    /// When the rig next wants to run by itself, µs.
    pub fn next_deadline_us(&self) -> Option<Micros> {
        self.sim.next_deadline()
    }

    /// The rig's clock, µs since power-on: the virtual duration of everything so far.
    pub fn now_us(&self) -> Micros {
        self.sim.now()
    }

    /// The rig's status, as it would answer [`subsurf_protocol::Command::Status`].
    pub fn status(&self) -> Status {
        self.sim.rig().status()
    }

    /// The simulated hardware: physical position, outputs now, step count, safety violations.
    pub fn hardware(&self) -> &SimHardware {
        self.sim.hw()
    }

    /// Steps the turntable moved from where it was at power-on (counts every executed move).
    pub fn turned_steps(&self) -> i64 {
        self.sim.hw().position() - self.start_position
    }

    /// Every galvo DAC write, oldest first (including the one at power-on).
    pub fn galvo_log(&self) -> &[LogEntry<GalvoPoint>] {
        &self.galvo.entries
    }

    /// Every change of the laser outputs (bit per channel), oldest first.
    pub fn laser_log(&self) -> &[LogEntry<u8>] {
        &self.lasers.entries
    }

    /// Every change of the camera trigger line, oldest first.
    pub fn trigger_log(&self) -> &[LogEntry<bool>] {
        &self.trigger.entries
    }

    /// Times of the camera trigger's rising edges, µs.
    pub fn triggers(&self) -> Vec<Micros> {
        self.trigger
            .entries
            .iter()
            .filter(|e| e.value)
            .map(|e| e.at)
            .collect()
    }

    /// Log entries lost because more happened between two looks than the firmware's logs hold
    /// (only possible when serving in real time on a starved thread). 0 means the logs are
    /// complete.
    pub fn missed_log_entries(&self) -> u64 {
        self.galvo.missed + self.lasers.missed + self.trigger.missed
    }

    /// Press or release the simulated emergency stop now.
    pub fn set_estop(&mut self, pressed: bool) {
        let now = self.sim.now();
        self.sim.set_estop(now, pressed);
        self.sync_logs();
    }

    /// Wire the simulated laser drivers active low or high, whatever the profile says.
    pub fn set_laser_wiring(&mut self, active_low: bool) {
        self.sim.rig_mut().hw_mut().set_laser_wiring(active_low);
    }

    /// Close or open the simulated enclosure interlock now.
    pub fn set_interlock(&mut self, closed: bool) {
        let now = self.sim.now();
        self.sim.set_interlock(now, closed);
        self.sync_logs();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logs_stay_complete_past_the_firmware_log_size() {
        use subsurf_protocol::{Command, Request, encode_request};
        let mut rig = VirtualRig::default();
        let mut t = 0;
        let mut buf = [0u8; subsurf_protocol::MAX_FRAME];
        let hello = Command::Hello {
            protocol_version: subsurf_protocol::PROTOCOL_VERSION,
        };
        let n = encode_request(
            &Request {
                seq: 10_000,
                command: hello,
            },
            &mut buf,
        )
        .expect("encode");
        rig.handle_input(t, &buf[..n]);
        for i in 0..1000u16 {
            let mut buf = [0u8; subsurf_protocol::MAX_FRAME];
            let command = Command::Galvo(GalvoPoint { x: i, y: 1 });
            let n = encode_request(
                &Request {
                    seq: u32::from(i),
                    command,
                },
                &mut buf,
            )
            .expect("encode");
            t += 100;
            rig.handle_input(t, &buf[..n]);
            let mut out = Vec::new();
            rig.drain_output(&mut out);
            assert!(!out.is_empty(), "a reply");
        }
        // Power-on write plus 1000 commanded writes.
        assert_eq!(rig.galvo_log().len(), 1001);
        assert_eq!(rig.missed_log_entries(), 0);
        assert_eq!(rig.galvo_log()[1000].value, GalvoPoint { x: 999, y: 1 });
    }

    #[test]
    fn one_long_advance_loses_no_event() {
        use subsurf_protocol::{
            Command, EventKind, FrameDecoder, ProgramChunk, ProgramHeader, Request, RigMessage,
            encode_request,
        };
        let mut params = SimParams::default();
        params.profile.camera.readout_us = 100;
        let mut rig = VirtualRig::new(params);
        let mut seq = 0;
        let mut send = |rig: &mut VirtualRig, command: Command| {
            let mut buf = [0u8; subsurf_protocol::MAX_FRAME];
            seq += 1;
            let n = encode_request(&Request { seq, command }, &mut buf).expect("encode");
            let now = rig.now_us() + 10;
            rig.handle_input(now, &buf[..n]);
        };
        let len = 200u16;
        send(
            &mut rig,
            Command::Hello {
                protocol_version: subsurf_protocol::PROTOCOL_VERSION,
            },
        );
        send(&mut rig, Command::Arm);
        send(
            &mut rig,
            Command::ProgramLoad(ProgramHeader {
                len,
                channel: 0,
                settle_us: Some(1),
                exposure_us: 20,
                trigger_us: 1,
                interval_us: 120,
            }),
        );
        for offset in (0..len).step_by(subsurf_protocol::PROGRAM_CHUNK) {
            let mut points = heapless::Vec::new();
            for i in offset..(offset + 32).min(len) {
                points.push(GalvoPoint { x: i, y: i }).expect("chunk");
            }
            send(
                &mut rig,
                Command::ProgramPoints(ProgramChunk { offset, points }),
            );
        }
        send(&mut rig, Command::ProgramRun);
        // Far more than the firmware's 32-message queue happens in this one call.
        rig.advance(rig.now_us() + 1_000_000);
        let mut out = Vec::new();
        rig.drain_output(&mut out);
        let mut decoder = FrameDecoder::new();
        let captured = decoder
            .decode::<RigMessage>(&out)
            .filter(
                |m| matches!(m, RigMessage::Event(e) if matches!(e.kind, EventKind::Captured(_))),
            )
            .count();
        assert_eq!(captured, usize::from(len));
        assert_eq!(rig.triggers().len(), usize::from(len));
        assert_eq!(rig.missed_log_entries(), 0);
    }
}
