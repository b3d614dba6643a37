//! Simulated rig hardware: the exact firmware core driven by in-memory hardware and a virtual
//! clock, so the host (in-process, over a pseudo-terminal, in tests) talks to the same logic the
//! board runs.
//!
//! [`SimRig`] owns a [`Rig`] over [`SimHardware`]. Drive it with [`SimRig::feed`] (bytes from the
//! host at time `now`), [`SimRig::advance_to`] (let virtual or real time pass) and
//! [`SimRig::drain`] (bytes for the host). The hardware keeps bounded logs of laser, trigger and
//! galvo outputs (the newest entries, with a count of the older ones dropped) and counts any
//! output that breaks a safety rule as seen from the hardware side ([`SimHardware::violations`]).

use heapless::HistoryBuf;
use subsurf_protocol::{Capabilities, Config, GalvoPoint, Inputs, MAX_FRAME};

use crate::hal::{CameraTrigger, GalvoDac, LaserOutputs, RigInputs, Stepper};
use crate::rig::{MAX_PROGRAM_POINTS, Micros, Rig};

/// Entries kept per log.
pub const LOG_LEN: usize = 256;

/// One logged output change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LogEntry<T> {
    /// Virtual time of the change, µs.
    pub at: Micros,
    /// The new output value.
    pub value: T,
}

/// A bounded log keeping the newest [`LOG_LEN`] entries.
#[derive(Debug, Clone)]
pub struct Log<T: Copy> {
    buf: HistoryBuf<LogEntry<T>, LOG_LEN>,
    total: u64,
}

impl<T: Copy> Default for Log<T> {
    fn default() -> Self {
        Self {
            buf: HistoryBuf::new(),
            total: 0,
        }
    }
}

impl<T: Copy> Log<T> {
    fn push(&mut self, at: Micros, value: T) {
        self.buf.write(LogEntry { at, value });
        self.total = self.total.saturating_add(1);
    }

    /// Kept entries, oldest first.
    pub fn entries(&self) -> impl Iterator<Item = &LogEntry<T>> {
        self.buf.oldest_ordered()
    }

    /// The newest entry.
    pub fn last(&self) -> Option<&LogEntry<T>> {
        self.buf.recent()
    }

    /// Entries ever logged.
    pub fn total(&self) -> u64 {
        self.total
    }

    /// Older entries no longer kept.
    pub fn dropped(&self) -> u64 {
        self.total.saturating_sub(self.buf.len() as u64)
    }
}

/// How the simulated rig is built.
#[derive(Debug, Clone, Copy)]
pub struct SimParams {
    /// What the rig announces.
    pub capabilities: Capabilities,
    /// Initial settings.
    pub config: Config,
    /// Physical turntable position at power-on, steps (homing finds the switch from here).
    pub start_position: i64,
    /// The home switch is active while the physical position modulo one revolution is below this.
    pub home_switch_width: u32,
}

impl Default for SimParams {
    /// A plausible rig: 16 000 steps/rev, 16-bit galvo, three laser channels.
    fn default() -> Self {
        let steps_per_rev = 16_000;
        Self {
            capabilities: Capabilities {
                steps_per_rev,
                galvo_max: u16::MAX,
                laser_channels: 3,
                max_speed: 20_000,
                max_accel: 200_000,
                max_exposure_us: 2_000_000,
                max_program_points: MAX_PROGRAM_POINTS as u16,
            },
            config: Config {
                heartbeat_timeout_ms: 2_000,
                galvo_settle_min_us: 100,
                galvo_settle_per_kcode_us: 20,
                home_speed: 8_000,
                home_accel: 40_000,
                home_max_steps: steps_per_rev + steps_per_rev / 8,
            },
            start_position: i64::from(steps_per_rev / 4),
            home_switch_width: 40,
        }
    }
}

/// In-memory rig hardware with output logs.
#[derive(Debug, Clone)]
pub struct SimHardware {
    clock: Micros,
    steps_per_rev: u32,
    home_switch_width: u32,
    position: i64,
    steps: u64,
    last_step_at: Option<Micros>,
    min_step_interval_us: Option<Micros>,
    galvo: GalvoPoint,
    lasers: u8,
    trigger: bool,
    estop: bool,
    interlock_closed: bool,
    violations: u32,
    laser_log: Log<u8>,
    trigger_log: Log<bool>,
    galvo_log: Log<GalvoPoint>,
}

impl SimHardware {
    /// Hardware at `start_position`, e-stop released, interlock closed.
    pub fn new(steps_per_rev: u32, start_position: i64, home_switch_width: u32) -> Self {
        Self {
            clock: 0,
            steps_per_rev: steps_per_rev.max(1),
            home_switch_width,
            position: start_position,
            steps: 0,
            last_step_at: None,
            min_step_interval_us: None,
            galvo: GalvoPoint::default(),
            lasers: 0,
            trigger: false,
            estop: false,
            interlock_closed: true,
            violations: 0,
            laser_log: Log::default(),
            trigger_log: Log::default(),
            galvo_log: Log::default(),
        }
    }

    /// Physical turntable position, steps (not reset by homing).
    pub fn position(&self) -> i64 {
        self.position
    }

    /// Steps taken in total.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Shortest time between two consecutive steps seen so far, µs.
    pub fn min_step_interval_us(&self) -> Option<Micros> {
        self.min_step_interval_us
    }

    /// Galvo output now.
    pub fn galvo(&self) -> GalvoPoint {
        self.galvo
    }

    /// Laser outputs now (bit per channel).
    pub fn lasers(&self) -> u8 {
        self.lasers
    }

    /// Trigger output now.
    pub fn trigger(&self) -> bool {
        self.trigger
    }

    /// Whether the home switch is active at the current position.
    pub fn home_switch(&self) -> bool {
        self.position.rem_euclid(i64::from(self.steps_per_rev)) < i64::from(self.home_switch_width)
    }

    /// Press or release the emergency stop (tell the rig with [`SimRig::set_estop`]).
    pub fn set_estop(&mut self, pressed: bool) {
        self.estop = pressed;
    }

    /// Close or open the enclosure interlock.
    pub fn set_interlock(&mut self, closed: bool) {
        self.interlock_closed = closed;
    }

    /// Safety breaches seen at the outputs: a step while a laser emits, or a laser switched on
    /// with the e-stop pressed or the interlock open. Always 0 for a correct core.
    pub fn violations(&self) -> u32 {
        self.violations
    }

    /// Laser output changes.
    pub fn laser_log(&self) -> &Log<u8> {
        &self.laser_log
    }

    /// Trigger output changes.
    pub fn trigger_log(&self) -> &Log<bool> {
        &self.trigger_log
    }

    /// Galvo output changes.
    pub fn galvo_log(&self) -> &Log<GalvoPoint> {
        &self.galvo_log
    }

    fn violation(&mut self) {
        self.violations = self.violations.saturating_add(1);
    }
}

impl Stepper for SimHardware {
    fn step(&mut self, forward: bool) {
        if self.lasers != 0 {
            self.violation();
        }
        if let Some(prev) = self.last_step_at {
            let gap = self.clock.saturating_sub(prev);
            self.min_step_interval_us = Some(self.min_step_interval_us.map_or(gap, |m| m.min(gap)));
        }
        self.last_step_at = Some(self.clock);
        self.steps = self.steps.saturating_add(1);
        self.position = if forward {
            self.position.saturating_add(1)
        } else {
            self.position.saturating_sub(1)
        };
    }
}

impl GalvoDac for SimHardware {
    fn set_galvo(&mut self, point: GalvoPoint) {
        self.galvo = point;
        self.galvo_log.push(self.clock, point);
    }
}

impl LaserOutputs for SimHardware {
    fn set_lasers(&mut self, mask: u8) {
        if mask != 0 && (self.estop || !self.interlock_closed) {
            self.violation();
        }
        self.lasers = mask;
        self.laser_log.push(self.clock, mask);
    }
}

impl CameraTrigger for SimHardware {
    fn set_trigger(&mut self, high: bool) {
        self.trigger = high;
        self.trigger_log.push(self.clock, high);
    }
}

impl RigInputs for SimHardware {
    fn read_inputs(&mut self) -> Inputs {
        Inputs {
            estop: self.estop,
            interlock_closed: self.interlock_closed,
            home_switch: self.home_switch(),
        }
    }
}

/// The firmware core on simulated hardware with a virtual clock that only moves forward.
pub struct SimRig {
    rig: Rig<SimHardware>,
    now: Micros,
}

impl Default for SimRig {
    fn default() -> Self {
        Self::new(SimParams::default())
    }
}

impl SimRig {
    /// A rig at time 0.
    pub fn new(params: SimParams) -> Self {
        let hw = SimHardware::new(
            params.capabilities.steps_per_rev,
            params.start_position,
            params.home_switch_width,
        );
        Self {
            rig: Rig::new(hw, params.capabilities, params.config, 0),
            now: 0,
        }
    }

    /// Virtual time, µs.
    pub fn now(&self) -> Micros {
        self.now
    }

    /// When something next happens on the rig by itself (step, capture phase, input poll,
    /// heartbeat timeout).
    pub fn next_deadline(&self) -> Option<Micros> {
        self.rig.poll_timeout()
    }

    /// Let time pass up to `now`, running every deadline on the way at its exact time.
    pub fn advance_to(&mut self, now: Micros) {
        let now = now.max(self.now);
        while let Some(t) = self.rig.poll_timeout() {
            if t > now {
                break;
            }
            let t = t.max(self.now);
            self.set_clock(t);
            self.rig.handle_timeout(t);
            if self.rig.poll_timeout().is_some_and(|next| next <= t) {
                // Everything due at `t` is handled within one call; a deadline that does not move
                // would be a core bug, so move time instead of spinning.
                self.set_clock(t.saturating_add(1).min(now));
                if self.now == t {
                    break;
                }
            }
        }
        self.set_clock(now);
    }

    /// Bytes from the host arrive at `now` (time first advances to `now`).
    pub fn feed(&mut self, now: Micros, bytes: &[u8]) {
        self.advance_to(now);
        self.rig.handle_bytes(self.now, bytes);
    }

    /// Write as many whole outgoing frames into `out` as fit; returns the bytes written.
    pub fn drain(&mut self, out: &mut [u8]) -> usize {
        let mut n = 0;
        while let Some(rest) = out.get_mut(n..) {
            match self.rig.poll_transmit(rest) {
                Some(len) => n += len,
                None => break,
            }
        }
        n
    }

    /// Drain everything into a closure, one frame at a time.
    pub fn drain_frames(&mut self, mut f: impl FnMut(&[u8])) {
        let mut buf = [0u8; MAX_FRAME];
        while let Some(n) = self.rig.poll_transmit(&mut buf) {
            f(buf.get(..n).unwrap_or(&[]));
        }
    }

    /// Press or release the e-stop at `now`.
    pub fn set_estop(&mut self, now: Micros, pressed: bool) {
        self.advance_to(now);
        self.rig.hw_mut().set_estop(pressed);
        self.rig.handle_inputs(self.now);
    }

    /// Close or open the enclosure interlock at `now`.
    pub fn set_interlock(&mut self, now: Micros, closed: bool) {
        self.advance_to(now);
        self.rig.hw_mut().set_interlock(closed);
        self.rig.handle_inputs(self.now);
    }

    /// The simulated hardware (positions, outputs, logs).
    pub fn hw(&self) -> &SimHardware {
        self.rig.hw()
    }

    /// The core.
    pub fn rig(&self) -> &Rig<SimHardware> {
        &self.rig
    }

    /// The core, mutably (e.g. [`Rig::handle_request`] / [`Rig::poll_message`] without framing).
    pub fn rig_mut(&mut self) -> &mut Rig<SimHardware> {
        &mut self.rig
    }

    fn set_clock(&mut self, t: Micros) {
        self.now = self.now.max(t);
        self.rig.hw_mut().clock = self.now;
    }
}
