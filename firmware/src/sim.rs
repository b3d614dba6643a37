//! Simulated rig hardware: the exact firmware core driven by in-memory hardware and a virtual
//! clock, so the host (in-process, over a pseudo-terminal, in tests) talks to the same logic the
//! board runs.
//!
//! [`SimRig`] owns a [`Rig`] over [`SimHardware`]. Drive it with [`SimRig::feed`] (bytes from the
//! host at time `now`), [`SimRig::advance_to`] (let virtual or real time pass) and
//! [`SimRig::drain`] (bytes for the host). The hardware keeps bounded logs of laser, trigger and
//! galvo outputs (the newest entries, with a count of the older ones dropped) and counts any
//! output that breaks a safety rule as seen from the hardware side ([`SimHardware::violations`]).
//!
//! The simulated hardware is built from the same [`RigProfile`] the rig runs: its galvo is the
//! profile's DAC (code range, mirror settle), and its camera ([`SimCamera`]) has the profile's
//! read-out and raises an exposure-active output a fixed delay after each trigger it accepts,
//! for the window's exposure; it can be told to miss triggers.

use heapless::{Deque, HistoryBuf};
use subsurf_protocol::{Config, GalvoPoint, Inputs, MAX_FRAME, RigProfile, SaveError};

use crate::hal::{
    CameraEdge, CameraInput, CameraTrigger, ExposureWindow, GalvoDac, LaserOutputs, ProfileStore,
    RigInputs, StepSegment, Stepper,
};
use crate::rig::{Micros, Rig};

/// Entries kept per log.
pub const LOG_LEN: usize = 256;

/// The simulated step timer's queue holds as many segments as the core keeps in flight.
const STEP_QUEUE: usize = crate::planner::IN_FLIGHT;

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

/// The simulated camera's behaviour.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SimCamera {
    /// The board's exposure timer starts this long after the core's schedule (the rig task's
    /// wake-up latency): the trigger edge and the laser's on and off edges, all placed by that
    /// timer, come this much later than scheduled; the trigger edge is timestamped where it
    /// really was. 0 for an ideal board.
    pub timer_latency_us: u32,
    /// From the trigger edge to exposure-active rising, µs.
    pub exposure_delay_us: u32,
    /// Triggers (0-based, counted since boot) the camera ignores: a missed trigger.
    pub miss_triggers: [Option<u32>; 4],
}

impl Default for SimCamera {
    fn default() -> Self {
        Self {
            timer_latency_us: 0,
            exposure_delay_us: 15,
            miss_triggers: [None; 4],
        }
    }
}

/// How the simulated rig is built.
#[derive(Debug, Clone, Copy)]
pub struct SimParams {
    /// The rig profile (the rig runs it; the hardware is built from it).
    pub profile: RigProfile,
    /// Initial session settings.
    pub config: Config,
    /// This power-on's nonce.
    pub boot_nonce: u32,
    /// Physical turntable position at power-on, steps (homing finds the switch from here).
    pub start_position: i64,
    /// The home switch is active while the physical position modulo one revolution is below this.
    pub home_switch_width: u32,
    /// The camera.
    pub camera: SimCamera,
}

impl Default for SimParams {
    /// The documented wiring ([`RigProfile::DEFAULT`]): 16 000 steps/rev, external 16-bit galvo
    /// DAC, three laser channels.
    fn default() -> Self {
        let profile = RigProfile::DEFAULT;
        let steps_per_rev = profile.steps_per_rev().unwrap_or(16_000);
        Self {
            profile,
            config: Config::DEFAULT,
            boot_nonce: 0x5eed_0001,
            start_position: i64::from(steps_per_rev / 4),
            home_switch_width: 40,
            camera: SimCamera::default(),
        }
    }
}

impl SimParams {
    /// The same rig on the fallback galvo path (internal 12-bit DAC, 300 µs per 1000 codes).
    pub fn internal_dac() -> Self {
        let mut p = Self::default();
        p.profile.galvo = RigProfile::INTERNAL_DAC;
        p
    }
}

/// In-memory rig hardware with output logs.
#[derive(Debug, Clone)]
pub struct SimHardware {
    clock: Micros,
    profile: RigProfile,
    camera: SimCamera,
    /// Triggers seen since boot.
    triggers: u32,
    /// The camera accepts a trigger from here on.
    camera_ready_at: Micros,
    /// Exposure of the window the core announced last.
    window_exposure_us: u32,
    /// Edges timestamped but not yet taken by the core, in time order.
    edges: Deque<CameraEdge, 8>,
    /// The mirror reaches its commanded position at this time.
    galvo_settled_at: Micros,
    /// Laser switched on while the mirror was still moving.
    unsettled_exposures: u32,
    /// Exposures the camera took.
    exposures: u32,
    /// Whether a laser was on for the whole of every exposure so far (checked at both edges).
    unlit_exposures: u32,
    /// The step queue: planned segments, emitted each step at its time (the board's step timer).
    step_queue: Deque<StepSegment, STEP_QUEUE>,
    /// Steps of the front segment already emitted.
    front_emitted: u16,
    /// Time (ticks) and direction of the last step emitted.
    last_step: Option<(u64, bool)>,
    /// The gap between the last two steps, µs.
    last_gap_us: Option<Micros>,
    /// The fastest the motor ran, steps/s, when a flush stopped it dead with steps still queued.
    fastest_hard_stop: u32,
    steps_per_rev: u32,
    home_switch_width: u32,
    position: i64,
    steps: u64,
    segments: u64,
    min_step_interval_us: Option<Micros>,
    galvo: GalvoPoint,
    lasers: u8,
    /// How the simulated laser drivers are wired, when it differs from the profile's claim
    /// (`None`: as the profile says).
    laser_wired_active_low: Option<bool>,
    /// The simulated flash: the profile a reset would bring back.
    stored: Option<RigProfile>,
    /// The next saves fail so (a worn or locked flash), oldest first.
    failing_saves: Deque<SaveError, 4>,
    /// Profile saves that completed.
    saves: u32,
    trigger: bool,
    estop: bool,
    interlock_closed: bool,
    violations: u32,
    lit_from: Micros,
    lit_until: Micros,
    laser_log: Log<u8>,
    trigger_log: Log<bool>,
    galvo_log: Log<GalvoPoint>,
}

impl SimHardware {
    /// Hardware for `profile` at `start_position`, e-stop released, interlock closed; the mirror
    /// rests centred (where the board's output stage puts it before the first DAC write).
    pub fn new(
        profile: RigProfile,
        camera: SimCamera,
        start_position: i64,
        home_switch_width: u32,
    ) -> Self {
        let c = profile.galvo.output.center();
        Self {
            clock: 0,
            profile,
            camera,
            triggers: 0,
            camera_ready_at: 0,
            window_exposure_us: 0,
            edges: Deque::new(),
            galvo_settled_at: 0,
            unsettled_exposures: 0,
            exposures: 0,
            unlit_exposures: 0,
            step_queue: Deque::new(),
            front_emitted: 0,
            last_step: None,
            last_gap_us: None,
            fastest_hard_stop: 0,
            steps_per_rev: profile.steps_per_rev().unwrap_or(1).max(1),
            home_switch_width,
            position: start_position,
            steps: 0,
            segments: 0,
            min_step_interval_us: None,
            galvo: GalvoPoint { x: c, y: c },
            lasers: 0,
            laser_wired_active_low: None,
            stored: Some(profile),
            failing_saves: Deque::new(),
            saves: 0,
            trigger: false,
            estop: false,
            interlock_closed: true,
            violations: 0,
            lit_from: 0,
            lit_until: 0,
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

    /// Step segments the core queued so far.
    pub fn segments(&self) -> u64 {
        self.segments
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

    /// Wire the simulated laser drivers active low or high, whatever the profile says (a profile
    /// with the wrong polarity: the rig must refuse to arm).
    pub fn set_laser_wiring(&mut self, active_low: bool) {
        self.laser_wired_active_low = Some(active_low);
    }

    /// Make the next profile save fail with `error` (and the one after, if called again).
    pub fn fail_next_save(&mut self, error: SaveError) {
        let _ = self.failing_saves.push_back(error);
    }

    /// Profile saves that completed (flash writes).
    pub fn saves(&self) -> u32 {
        self.saves
    }

    /// Forget the stored profile (a blank flash).
    pub fn erase_stored_profile(&mut self) {
        self.stored = None;
    }

    /// Close or open the enclosure interlock.
    pub fn set_interlock(&mut self, closed: bool) {
        self.interlock_closed = closed;
    }

    /// When the next queued step comes, µs (the motor moves then).
    pub fn next_step_at(&self) -> Option<Micros> {
        let s = self.step_queue.front()?;
        Some(
            s.step_at(self.front_emitted)
                .div_ceil(u64::from(Self::TICKS_PER_US)),
        )
    }

    /// The fastest the motor was running when something stopped it dead with steps still queued
    /// (a flush), steps/s; 0 if that never happened. An e-stop does it on purpose; homing must
    /// not at more than its slow speed.
    pub fn fastest_hard_stop(&self) -> u32 {
        self.fastest_hard_stop
    }

    /// Move the motor for every queued step due by now, checking each as the board's driver
    /// would see it.
    fn drain_steps(&mut self) {
        let now = self.clock.saturating_mul(u64::from(Self::TICKS_PER_US));
        // Bounded by the queue: every pass emits a step or leaves.
        while let Some(front) = self.step_queue.front().copied() {
            if self.front_emitted >= front.count {
                self.step_queue.pop_front();
                self.front_emitted = 0;
                continue;
            }
            let at = front.step_at(self.front_emitted);
            if at > now {
                break;
            }
            self.front_emitted += 1;
            self.emit_step(at, front.forward);
        }
    }

    fn emit_step(&mut self, at: u64, forward: bool) {
        let ticks = u64::from(Self::TICKS_PER_US);
        if self.lasers != 0 {
            self.violation();
        }
        if let Some((prev, prev_forward)) = self.last_step {
            let gap_us = at.saturating_sub(prev) / ticks;
            self.last_gap_us = Some(gap_us);
            self.min_step_interval_us =
                Some(self.min_step_interval_us.map_or(gap_us, |m| m.min(gap_us)));
            // DIR must settle before the STEP edge after a reversal.
            let setup = u64::from(self.profile.motor.dir_setup_us)
                + u64::from(self.profile.motor.step_pulse_us);
            if forward != prev_forward && gap_us < setup {
                self.violation();
            }
        }
        self.last_step = Some((at, forward));
        self.steps = self.steps.saturating_add(1);
        self.move_motor(forward);
    }

    /// Laser switched on for a capture while the mirror (the profile's settle model) was still
    /// moving: the spot smeared across the image.
    pub fn unsettled_exposures(&self) -> u32 {
        self.unsettled_exposures
    }

    /// Exposures the simulated camera took.
    pub fn exposures(&self) -> u32 {
        self.exposures
    }

    /// Triggers the camera saw.
    pub fn triggers(&self) -> u32 {
        self.triggers
    }

    /// The earliest camera edge not yet taken by the core (when the rig must look again).
    pub fn next_camera_edge(&self) -> Option<Micros> {
        self.edges.front().map(CameraEdge::at)
    }

    /// Camera exposures during which no laser was on at start or end.
    pub fn unlit_exposures(&self) -> u32 {
        self.unlit_exposures
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

impl SimHardware {
    fn move_motor(&mut self, forward: bool) {
        self.position = if forward {
            self.position.saturating_add(1)
        } else {
            self.position.saturating_sub(1)
        };
    }

    fn push_edge(&mut self, edge: CameraEdge) {
        if self.edges.push_back(edge).is_err() {
            // A camera flooding edges: the oldest is lost (the core counts what it sees).
            self.edges.pop_front();
            let _ = self.edges.push_back(edge);
        }
    }
}

impl Stepper for SimHardware {
    /// The board's step clock (TIM2 at 84 MHz), so the simulator runs the board's segments.
    const TICKS_PER_US: u32 = 84;

    fn queue(&mut self, segment: StepSegment) -> bool {
        self.drain_steps();
        let queued = self.step_queue.push_back(segment).is_ok();
        self.segments = self.segments.saturating_add(u64::from(queued));
        queued
    }

    fn flush(&mut self) -> u32 {
        self.drain_steps();
        let mut dropped = 0u32;
        for (i, s) in self.step_queue.iter().enumerate() {
            let done = if i == 0 { self.front_emitted } else { 0 };
            dropped = dropped.saturating_add(u32::from(s.count.saturating_sub(done)));
        }
        if dropped > 0
            && let Some(gap) = self.last_gap_us
        {
            let speed = u32::try_from(1_000_000 / gap.max(1)).unwrap_or(u32::MAX);
            self.fastest_hard_stop = self.fastest_hard_stop.max(speed);
        }
        self.step_queue.clear();
        self.front_emitted = 0;
        dropped
    }
}

impl GalvoDac for SimHardware {
    fn set_galvo(&mut self, point: GalvoPoint) {
        // The physical mirror: the profile's settle model (the board's DAC and galvo).
        let settle = crate::rig::galvo_settle_us(&self.profile, self.galvo, point);
        self.galvo_settled_at = self.clock.saturating_add(u64::from(settle));
        self.galvo = point;
        self.galvo_log.push(self.clock, point);
    }
}

impl LaserOutputs for SimHardware {
    fn set_lasers(&mut self, mask: u8) {
        if mask != 0 && (self.estop || !self.interlock_closed) {
            self.violation();
        }
        if mask != 0 && self.lasers == 0 && self.clock < self.galvo_settled_at {
            self.unsettled_exposures = self.unsettled_exposures.saturating_add(1);
        }
        self.lasers = mask;
        self.laser_log.push(self.clock, mask);
    }

    fn lines_idle_off(&mut self, active_low: bool) -> bool {
        self.laser_wired_active_low
            .is_none_or(|wired| wired == active_low)
    }
}

impl ProfileStore for SimHardware {
    fn store_profile(&mut self, profile: &RigProfile) -> Result<(), SaveError> {
        // The board's erase stalls every interrupt: never while anything moves or shines.
        if self.lasers != 0 || !self.step_queue.is_empty() {
            self.violation();
        }
        if let Some(error) = self.failing_saves.pop_front() {
            // A failed erase or write leaves no readable new record; the old one stays.
            return Err(error);
        }
        self.stored = Some(*profile);
        self.saves = self.saves.saturating_add(1);
        Ok(())
    }

    fn stored_profile(&mut self) -> Option<RigProfile> {
        self.stored
    }
}

impl CameraTrigger for SimHardware {
    fn set_trigger(&mut self, high: bool) {
        let rising = high && !self.trigger;
        self.trigger = high;
        self.trigger_log.push(self.clock, high);
        if !rising {
            return;
        }
        let edge = self
            .clock
            .saturating_add(u64::from(self.camera.timer_latency_us));
        let index = self.triggers;
        self.triggers = self.triggers.saturating_add(1);
        self.push_edge(CameraEdge::Trigger(edge));
        let missed = self.camera.miss_triggers.contains(&Some(index));
        if missed || edge < self.camera_ready_at {
            return;
        }
        let start = edge.saturating_add(u64::from(self.camera.exposure_delay_us));
        let end = start.saturating_add(u64::from(self.window_exposure_us.max(1)));
        self.camera_ready_at = end.saturating_add(u64::from(self.profile.camera.readout_us));
        self.exposures = self.exposures.saturating_add(1);
        // Lit at both ends, judged from the window the core announced.
        if !(self.lit_from <= start && end <= self.lit_until) {
            self.unlit_exposures = self.unlit_exposures.saturating_add(1);
        }
        self.push_edge(CameraEdge::ExposureStart(start));
        self.push_edge(CameraEdge::ExposureEnd(end));
    }

    fn arm_window(&mut self, window: &ExposureWindow) {
        // The light really is on where the board's timer puts it: the whole window late by the
        // timer's start latency.
        let late = u64::from(self.camera.timer_latency_us);
        self.window_exposure_us = window.exposure_us;
        self.lit_from = window.laser_on_at.saturating_add(late);
        self.lit_until = window.laser_off_at.saturating_add(late);
    }
}

impl CameraInput for SimHardware {
    fn poll_camera_edge(&mut self) -> Option<CameraEdge> {
        if self.edges.front()?.at() <= self.clock {
            self.edges.pop_front()
        } else {
            None
        }
    }
}

impl RigInputs for SimHardware {
    fn read_inputs(&mut self) -> Inputs {
        self.drain_steps();
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
            params.profile,
            params.camera,
            params.start_position,
            params.home_switch_width,
        );
        Self {
            rig: Rig::new(hw, params.profile, params.config, params.boot_nonce, 0),
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
        let hw = self.rig.hw();
        [
            self.rig.poll_timeout(),
            hw.next_camera_edge(),
            hw.next_step_at(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Let time pass up to `now`, running every deadline on the way at its exact time.
    pub fn advance_to(&mut self, now: Micros) {
        let now = now.max(self.now);
        while let Some(t) = self.next_deadline() {
            if t > now {
                break;
            }
            let t = t.max(self.now);
            let switch = self.rig.hw().home_switch();
            self.set_clock(t);
            if self.rig.hw().home_switch() != switch {
                // The board's home switch raises an interrupt: the core hears of it at once.
                self.rig.handle_inputs(t);
            }
            self.take_camera_edges(t);
            if self.rig.poll_timeout().is_some_and(|d| d <= t) {
                self.rig.handle_timeout(t);
            }
            // A zero-latency trigger's own edge is due at once.
            self.take_camera_edges(t);
            if self.next_deadline().is_some_and(|next| next <= t) {
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

    /// The board's camera interrupt: edges due by `t` go into the core at `t`.
    fn take_camera_edges(&mut self, t: Micros) {
        if self.rig.hw().next_camera_edge().is_some_and(|e| e <= t) {
            self.rig.handle_inputs(t);
        }
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
        let hw = self.rig.hw_mut();
        hw.clock = self.now;
        hw.drain_steps();
    }
}
