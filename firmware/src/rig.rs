//! The rig state machine: requests in, replies and events out, hardware driven through
//! [`crate::hal`], time passed in as µs.
//!
//! Call order (quinn-proto style): feed inputs with [`Rig::handle_bytes`] (or
//! [`Rig::handle_request`]), [`Rig::handle_inputs`] when an input pin changes, and
//! [`Rig::handle_timeout`] when the time from [`Rig::poll_timeout`] has come; after any of them,
//! drain [`Rig::poll_transmit`] until it returns `None`. The core never blocks, never reads a clock
//! and never allocates.
//!
//! A pump loop (board task or host thread) looks like this:
//!
//! ```text
//! loop {
//!     let deadline = rig.poll_timeout();            // always Some: inputs are polled every 1 ms
//!     match wait_for(uart_rx, input_pin_change, deadline) {
//!         Rx(bytes)  => rig.handle_bytes(now(), bytes),
//!         PinChange  => rig.handle_inputs(now()),
//!         Timeout    => rig.handle_timeout(now()),  // counts the steps out, plans the next 10 ms
//!     }
//!     while let Some(n) = rig.poll_transmit(&mut frame) { uart_tx.write(&frame[..n]) }
//! }
//! ```
//!
//! Motion is planned ahead ([`crate::planner`]): the core hands the hardware compressed step
//! segments up to 10 ms before their time and counts each step into the position when its time
//! has come, so it wakes every few milliseconds during a move, never once per step. The home
//! switch is looked at on every input change (the board's switch raises an interrupt) and poll.
//!
//! All laser-safety rules live in [`Rig::laser_permitted`] and `Rig::sync_lasers`: no code path
//! writes the laser outputs except `sync_lasers`, which outputs nothing unless `laser_permitted`.

use heapless::{Deque, Vec};
use subsurf_protocol::{
    Capabilities, Capture, Captured, Command, Config, DarkCapture, Event, EventKind, EventReplay,
    ExposureActive, Fault, FirmwareVersion, FrameDecoder, GalvoPoint, HaltReason, Hello, Inputs,
    MAX_EXPOSURE_US, MAX_HEARTBEAT_TIMEOUT_MS, MAX_SETTLE_US, Move, MoveTarget, PROTOCOL_VERSION,
    ProgramChunk, ProgramHeader, REPLAY_BATCH, Reply, Request, Response, RigError, RigMessage,
    RigProfile, RigState, Seq, Status, encode_event, encode_reply,
};

use crate::hal::{CameraEdge, ExposureWindow, Hardware};
use crate::planner::StepPlanner;
use crate::profile::Profile;

/// Rig time: µs since boot.
pub type Micros = u64;

/// Most points one queued capture program can hold on this firmware.
pub const MAX_PROGRAM_POINTS: usize = 1024;

/// Outgoing messages buffered between two drains; beyond this, new messages are dropped and
/// counted ([`Rig::tx_dropped`]). Replies are recovered by retransmission, events by
/// [`Command::Replay`] from the event history.
pub const OUT_QUEUE: usize = 32;

/// Recent events the rig keeps for [`Command::Replay`]: a host that saw a gap in `event_seq`
/// gets them again as long as no more than this many events came after. 32 covers a whole
/// [`subsurf_protocol::REPLAY_BATCH`] round trip of a program at 1 kHz many times over, at
/// 32 × 80 bytes of RAM.
pub const EVENT_HISTORY: usize = 32;

/// Inputs are sampled at least this often (µs) even without pin-change notifications.
pub const INPUT_POLL_US: Micros = 1_000;

/// This firmware's version, from the crate version.
pub const FIRMWARE_VERSION: FirmwareVersion = FirmwareVersion {
    major: parse_u16(env!("CARGO_PKG_VERSION_MAJOR")),
    minor: parse_u16(env!("CARGO_PKG_VERSION_MINOR")),
    patch: parse_u16(env!("CARGO_PKG_VERSION_PATCH")),
};

const fn parse_u16(s: &str) -> u16 {
    match u16::from_str_radix(s, 10) {
        Ok(v) => v,
        Err(_) => 0,
    }
}

/// Galvo settle time for a jump from `from` to `to` under the profile's settle model:
/// `settle_min_us` plus `settle_per_kcode_us` per 1000 codes of the larger axis jump, saturating.
pub fn galvo_settle_us(profile: &RigProfile, from: GalvoPoint, to: GalvoPoint) -> u32 {
    let jump = u64::from(from.x.abs_diff(to.x).max(from.y.abs_diff(to.y)));
    let extra = jump.saturating_mul(u64::from(profile.galvo.settle_per_kcode_us)) / 1000;
    u32::try_from(u64::from(profile.galvo.settle_min_us).saturating_add(extra)).unwrap_or(u32::MAX)
}

/// Shortest time between two STEP edges the hardware emits, µs: the step timer's floor, or
/// STEP low at least as long as high.
pub const MIN_STEP_GAP_US: u32 = 10;

/// The shortest step gap for a profile's STEP pulse.
pub fn min_step_gap_us(profile: &RigProfile) -> u32 {
    MIN_STEP_GAP_US.max(u32::from(profile.motor.step_pulse_us).saturating_mul(2))
}

/// What a profile lets the host ask for (announced in [`Hello`]).
pub fn capabilities(profile: &RigProfile) -> Capabilities {
    Capabilities {
        steps_per_rev: profile.steps_per_rev().unwrap_or(1),
        galvo_max: profile.galvo_max(),
        laser_channels: profile
            .laser
            .channels
            .min(subsurf_protocol::MAX_LASER_CHANNELS),
        max_speed: profile.motor.max_speed,
        max_accel: profile.motor.max_accel,
        max_exposure_us: MAX_EXPOSURE_US,
        min_exposure_us: profile.camera.min_exposure_us,
        camera_readout_us: profile.camera.readout_us,
        max_program_points: u16::try_from(MAX_PROGRAM_POINTS).unwrap_or(u16::MAX),
    }
}

/// The phases of two-pass homing (approach = decreasing position).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum HomePhase {
    /// Started on the switch: slowly forward until it releases, then back off.
    LeaveSwitch,
    /// The switch released while leaving it: the steps already queued run out, then the
    /// back-off.
    LeftSwitch,
    /// Fast approach until the switch is seen (then a decelerating stop).
    Approach,
    /// Forward at the homing speed until the switch has been active and released again.
    Release,
    /// Forward `backoff_steps` more.
    BackOff,
    /// Slow approach until the switch reads active for `debounce_us`.
    SlowApproach,
    /// Forward back onto the switch edge found by the slow approach.
    Return,
    /// Decelerating after the fast approach saw the switch; then [`HomePhase::Release`].
    BrakeToRelease,
    /// Decelerating after the release pass saw the switch release; then [`HomePhase::BackOff`].
    BrakeToBackOff,
}

/// What a motion is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MotionKind {
    Move,
    Home {
        phase: HomePhase,
        /// The switch has been seen active in this phase.
        seen_active: bool,
        /// Slow approach: when the switch first read active, and the position then (the edge).
        active_since: Option<(Micros, i32)>,
    },
    /// Decelerating to rest after a halt; nothing follows.
    Stopping,
}

/// A turntable move (or homing pass) in progress. Step `i` of `profile` (1-based) is due at
/// `base + t(i) - t(base_index)`. Steps are planned ahead ([`crate::planner`]): `planned` is the
/// last one handed to the hardware, `computed` the last one whose ideal time the planner holds.
/// A decelerating stop jumps forward to the start of the profile's deceleration ramp at the speed
/// of the last planned step, so the ramp-down follows the steps already queued.
#[derive(Debug, Clone, Copy)]
struct Motion {
    profile: Profile,
    base: Micros,
    base_index: u32,
    /// The profile's time of `base_index`, µs (kept, not recomputed per step).
    base_t: Micros,
    /// Profile index of the last step whose ideal time went to the planner.
    computed: u32,
    /// Profile index of the last step handed to the hardware.
    planned: u32,
    /// No step past this index is planned (a pass cut short); `profile.steps()` normally.
    end: u32,
    forward: bool,
    kind: MotionKind,
}

impl Motion {
    fn new(now: Micros, profile: Profile, forward: bool, kind: MotionKind) -> Self {
        Self {
            profile,
            base: now,
            base_index: 0,
            base_t: 0,
            computed: 0,
            planned: 0,
            end: profile.steps(),
            forward,
            kind,
        }
    }

    fn due(&self, i: u32) -> Micros {
        self.base
            .saturating_add(self.profile.step_time_us(i).saturating_sub(self.base_t))
    }

    /// The next ideal step time for the planner, `None` past `end`.
    fn next_ideal(&mut self) -> Option<Micros> {
        if self.computed >= self.end {
            return None;
        }
        self.computed += 1;
        Some(self.due(self.computed))
    }

    /// Decelerate to rest from the speed of the last planned step: continue on the profile's
    /// ramp-down after it. The caller drops the planner's pending ideal times.
    fn stop(&mut self) {
        let n = self.profile.steps();
        let k = self.planned;
        let d = k.min(self.profile.ramp_steps()).min(n.saturating_sub(k));
        let from = n.saturating_sub(d);
        if from > k {
            self.base = self.due(k);
            self.base_index = from;
            self.base_t = self.profile.step_time_us(from);
            self.planned = from;
        }
        self.computed = self.planned;
        self.end = n;
    }

    /// Plan nothing past the steps already queued.
    fn cut(&mut self) {
        self.end = self.planned;
        self.computed = self.planned;
    }
}

/// Phase of the capture in progress.
#[derive(Debug, Clone, Copy)]
enum Phase {
    /// Galvo settling (and camera reading out): laser on at `laser_on_at`.
    Settling,
    /// Laser on, trigger at `trigger_at`.
    Lit,
    /// Trigger given; laser off at `laser_off_at`.
    Exposing { trigger_high: bool },
    /// Laser off; waiting for the camera's exposure-active to drop, at most until `deadline`.
    Confirming { deadline: Micros },
}

/// The capture in progress.
#[derive(Debug, Clone, Copy)]
struct ActiveCapture {
    id: u32,
    program_index: Option<u16>,
    galvo: GalvoPoint,
    /// `None`: a dark capture, every laser off throughout.
    channel: Option<u8>,
    trigger_us: u32,
    exposure_us: u32,
    laser_on_at: Micros,
    trigger_at: Micros,
    laser_off_at: Micros,
    /// The trigger edge as the hardware timestamped it.
    trigger_edge: Option<Micros>,
    exposure_start: Option<Micros>,
    exposure_end: Option<Micros>,
    phase: Phase,
}

impl ActiveCapture {
    /// When the laser was really on. A board that times the window in hardware starts its timer
    /// when its task wakes, a little after the schedule, and the window moves with it: the laser
    /// comes on `trigger_at - laser_on_at` before the trigger edge the timer placed and goes off
    /// `laser_off_at - trigger_at` after it. The hardware's timestamp of that edge therefore says
    /// where the window lay; without one (software edges) the schedule is all there is.
    fn lit_window(&self) -> (Micros, Micros) {
        match self.trigger_edge {
            Some(edge) => (
                edge.saturating_sub(self.trigger_at.saturating_sub(self.laser_on_at)),
                edge.saturating_add(self.laser_off_at.saturating_sub(self.trigger_at)),
            ),
            None => (self.laser_on_at, self.laser_off_at),
        }
    }
}

/// A running program.
#[derive(Debug, Clone, Copy)]
struct ProgramRun {
    first_id: u32,
    next_index: u16,
    completed: u16,
    next_start: Micros,
}

/// The last replies, for answering retransmissions without executing twice.
#[derive(Debug, Default)]
struct ReplyCache {
    entries: Deque<Reply, { subsurf_protocol::REPLY_CACHE }>,
    newest: Option<Seq>,
}

impl ReplyCache {
    fn get(&self, seq: Seq) -> Option<&Reply> {
        self.entries.iter().find(|r| r.seq == seq)
    }

    /// Shortly behind the newest executed seq (wrapping) but not cached: a late duplicate.
    fn is_stale(&self, seq: Seq) -> bool {
        self.newest.is_some_and(|n| {
            let behind = n.wrapping_sub(seq);
            behind != 0 && behind <= subsurf_protocol::STALE_WINDOW
        })
    }

    fn insert(&mut self, reply: Reply) {
        self.newest = Some(reply.seq);
        if self.entries.is_full() {
            self.entries.pop_front();
        }
        // Cannot fail: a slot was just freed.
        let _ = self.entries.push_back(reply);
    }

    fn clear(&mut self) {
        self.entries.clear();
        self.newest = None;
    }
}

/// The rig: owns its hardware, speaks the protocol. See the module docs for the call order.
pub struct Rig<H: Hardware> {
    hw: H,
    profile: RigProfile,
    caps: Capabilities,
    config: Config,
    boot_nonce: u32,
    /// A `Hello` succeeded since boot.
    session: bool,
    /// The profile was stored (or set by the host): its laser and trigger polarities are the
    /// wiring's. Without one nothing may arm.
    profile_known: bool,
    decoder: FrameDecoder,
    out: Deque<RigMessage, OUT_QUEUE>,
    /// Events raised while a request executes: sent right after its reply.
    deferred: Deque<Event, 4>,
    /// The last [`EVENT_HISTORY`] events, oldest first, for [`Command::Replay`].
    history: Deque<Event, EVENT_HISTORY>,
    executing: bool,
    tx_dropped: u32,
    replies: ReplyCache,
    now: Micros,
    // Safety state.
    armed: bool,
    /// Manually switched-on channels ([`Command::Laser`]).
    lasers: u8,
    /// Since when a manual channel has been on.
    manual_since: Option<Micros>,
    /// What the laser outputs currently show.
    laser_output: u8,
    inputs: Inputs,
    fault: Option<Fault>,
    last_request_at: Micros,
    link_alive: bool,
    next_input_poll: Micros,
    // Turntable.
    /// Steps the hardware has emitted by now (each counted when its time came).
    position: i32,
    homed: bool,
    motion: Option<Motion>,
    /// The steps planned ahead and in the hardware's queue.
    planner: StepPlanner,
    /// Direction of the steps in flight.
    stepping_forward: bool,
    // Galvo, camera and captures.
    galvo: GalvoPoint,
    capture: Option<ActiveCapture>,
    /// The axis was homed when the current homing started (its coordinates still valid).
    rehoming: bool,
    /// Where the homing found the edge, in the coordinates before it.
    home_edge: Option<i32>,
    /// Exposure-active rising edges seen since boot.
    exposures: u32,
    /// The camera accepts its next trigger from here (last exposure end + read-out).
    camera_ready_at: Micros,
    program_header: Option<ProgramHeader>,
    program: Vec<GalvoPoint, MAX_PROGRAM_POINTS>,
    run: Option<ProgramRun>,
    next_capture_id: u32,
    next_event_seq: u32,
}

impl<H: Hardware> Rig<H> {
    /// A rig at rest: lasers off, trigger low, galvo centred, disarmed, position 0 (not homed), no
    /// session, running `profile` (the one the board stored). An invalid `profile` is replaced by
    /// [`RigProfile::DEFAULT`] and counts as none ([`Rig::new_unconfigured`]). `boot_nonce` should
    /// differ between resets (hardware RNG): the host detects a reboot by it.
    pub fn new(hw: H, profile: RigProfile, config: Config, boot_nonce: u32, now: Micros) -> Self {
        let known = profile.validate().is_ok();
        Self::build(hw, known.then_some(profile), config, boot_nonce, now)
    }

    /// A rig with no stored profile (a new board, unreadable flash): the documented defaults for
    /// the mechanics, but the laser and trigger polarities are unknown, so it refuses to arm
    /// ([`RigError::ProfileNotStored`]) until the host sets a profile.
    pub fn new_unconfigured(hw: H, config: Config, boot_nonce: u32, now: Micros) -> Self {
        Self::build(hw, None, config, boot_nonce, now)
    }

    fn build(
        mut hw: H,
        stored: Option<RigProfile>,
        config: Config,
        boot_nonce: u32,
        now: Micros,
    ) -> Self {
        let profile_known = stored.is_some();
        let profile = stored.unwrap_or(RigProfile::DEFAULT);
        let config = if config_ok(&config) {
            config
        } else {
            Config::DEFAULT
        };
        let center = profile.galvo.output.center();
        let galvo = GalvoPoint {
            x: center,
            y: center,
        };
        hw.set_lasers(0);
        hw.set_trigger(false);
        hw.set_galvo(galvo);
        let inputs = hw.read_inputs();
        let mut rig = Self {
            hw,
            caps: capabilities(&profile),
            profile,
            config,
            boot_nonce,
            session: false,
            profile_known,
            decoder: FrameDecoder::new(),
            out: Deque::new(),
            deferred: Deque::new(),
            history: Deque::new(),
            executing: false,
            tx_dropped: 0,
            replies: ReplyCache::default(),
            now,
            armed: false,
            lasers: 0,
            manual_since: None,
            laser_output: 0,
            inputs,
            fault: None,
            last_request_at: now,
            link_alive: false,
            next_input_poll: now,
            position: 0,
            homed: false,
            motion: None,
            planner: StepPlanner::new(H::TICKS_PER_US, min_step_gap_us(&profile)),
            stepping_forward: true,
            galvo,
            capture: None,
            rehoming: false,
            home_edge: None,
            exposures: 0,
            camera_ready_at: now,
            program_header: None,
            program: Vec::new(),
            run: None,
            next_capture_id: 0,
            next_event_seq: 0,
        };
        rig.apply_inputs(now, inputs);
        rig
    }

    // ------------------------------------------------------------------------------------------
    // Getters.

    /// The hardware (e.g. the simulator's logs).
    pub fn hw(&self) -> &H {
        &self.hw
    }

    /// The hardware, mutably (e.g. to change simulated inputs; call [`Rig::handle_inputs`] after).
    pub fn hw_mut(&mut self) -> &mut H {
        &mut self.hw
    }

    /// The limits announced in the handshake (derived from the profile).
    pub fn capabilities(&self) -> &Capabilities {
        &self.caps
    }

    /// The rig profile in force.
    pub fn profile(&self) -> &RigProfile {
        &self.profile
    }

    /// Whether the profile in force was stored or set by the host (its polarities are the
    /// wiring's); `false` for a board running the defaults because nothing valid was stored.
    pub fn profile_known(&self) -> bool {
        self.profile_known
    }

    /// The latest time any laser may still be on, µs, if one may be: the earliest of the heartbeat
    /// deadline, the manual laser's limit and the capture window's end. The core switches the
    /// lasers off by then on its own; a board arms a hardware timer a little after it, so the
    /// light goes off even if the executor that runs the core is stuck.
    pub fn light_deadline(&self) -> Option<Micros> {
        let window = self
            .capture
            .as_ref()
            .filter(|c| !matches!(c.phase, Phase::Confirming { .. }))
            .map(|c| c.laser_off_at);
        if self.laser_output == 0 && window.is_none() {
            return None;
        }
        let mut t = self.heartbeat_deadline();
        if let Some(d) = self.manual_deadline() {
            t = t.min(d);
        }
        if let Some(off) = window {
            t = t.min(off);
        }
        Some(t)
    }

    /// The current session settings.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// This boot's nonce.
    pub fn boot_nonce(&self) -> u32 {
        self.boot_nonce
    }

    /// Whether a host session is open (a `Hello` since boot).
    pub fn session_open(&self) -> bool {
        self.session
    }

    /// Laser channels currently emitting.
    pub fn laser_output(&self) -> u8 {
        self.laser_output
    }

    /// Whether the laser is armed.
    pub fn armed(&self) -> bool {
        self.armed
    }

    /// Whether the turntable is moving (including homing and decelerating stops).
    pub fn moving(&self) -> bool {
        self.motion.is_some()
    }

    /// Turntable position, steps (0 = home once homed).
    pub fn position(&self) -> i32 {
        self.position
    }

    /// Whether the axis is homed.
    pub fn homed(&self) -> bool {
        self.homed
    }

    /// Exposures the camera confirmed since boot.
    pub fn exposures(&self) -> u32 {
        self.exposures
    }

    /// The active fault.
    pub fn fault(&self) -> Option<Fault> {
        self.fault
    }

    /// Whether a request arrived within the heartbeat timeout.
    pub fn link_alive(&self) -> bool {
        self.link_alive
    }

    /// Outgoing messages dropped because the queue was full.
    pub fn tx_dropped(&self) -> u32 {
        self.tx_dropped
    }

    /// Statistics of the incoming frame decoder.
    pub fn rx_stats(&self) -> subsurf_protocol::DecoderStats {
        self.decoder.stats()
    }

    /// A status snapshot, as answered to [`Command::Status`].
    pub fn status(&self) -> Status {
        let state = if self.fault.is_some() {
            RigState::Fault
        } else if let Some(m) = &self.motion {
            if matches!(m.kind, MotionKind::Home { .. }) {
                RigState::Homing
            } else {
                RigState::Moving
            }
        } else if self.run.is_some() {
            RigState::Program
        } else if self.capture.is_some() {
            RigState::Capturing
        } else {
            RigState::Idle
        };
        Status {
            boot_nonce: self.boot_nonce,
            state,
            position: self.position,
            homed: self.homed,
            armed: self.armed,
            lasers: self.laser_output,
            galvo: self.galvo,
            inputs: self.inputs,
            fault: self.fault,
            next_capture_id: self.next_capture_id,
            exposures: self.exposures,
            next_event_seq: self.next_event_seq,
            program_received: u16::try_from(self.program.len()).unwrap_or(u16::MAX),
            program_len: self.program_header.map_or(0, |h| h.len),
            rx_dropped: self.decoder.stats().dropped(),
            uptime_us: self.now,
        }
    }

    // ------------------------------------------------------------------------------------------
    // Inputs.

    /// Bytes arrived from the host: decode every complete frame and execute its request.
    pub fn handle_bytes(&mut self, now: Micros, bytes: &[u8]) {
        let now = self.advance(now);
        let mut rest = bytes;
        while !rest.is_empty() {
            let (msg, r) = self.decoder.feed::<Request>(rest);
            rest = r;
            if let Some(req) = msg {
                self.handle_request(now, req);
            }
        }
    }

    /// Execute one already-decoded request (in-process use without framing).
    pub fn handle_request(&mut self, now: Micros, req: Request) {
        let now = self.advance(now);
        let is_hello = matches!(req.command, Command::Hello { .. });
        if is_hello {
            self.replies.clear();
        }
        let reply = if !self.session && !is_hello {
            // After a reset the host's request may be a retransmission of one the previous boot
            // already ran: refuse everything until the host has noticed and said Hello.
            Reply {
                seq: req.seq,
                result: Err(RigError::NoSession),
            }
        } else if let Some(cached) = self.replies.get(req.seq) {
            cached.clone()
        } else if self.replies.is_stale(req.seq) {
            // Not executed and not cached: the host already has (or gave up on) this reply.
            Reply {
                seq: req.seq,
                result: Err(RigError::StaleSequence),
            }
        } else {
            self.executing = true;
            let result = self.execute(now, req.command);
            self.executing = false;
            let reply = Reply {
                seq: req.seq,
                result,
            };
            self.replies.insert(reply.clone());
            reply
        };
        if reply.result.is_ok() {
            // Only an accepted request proves a host in session that is listening: a refused one
            // (no session, stale, out of range, ...) may come from a confused or stuck sender, and
            // must not keep light on.
            self.last_request_at = now;
            self.link_alive = true;
        }
        self.send(RigMessage::Reply(reply));
        // The reply precedes the events its command caused (e.g. a zero-length move's MoveDone).
        while let Some(event) = self.deferred.pop_front() {
            self.send(RigMessage::Event(event));
        }
        self.sync_lasers();
    }

    /// An input pin changed, or a camera edge was timestamped (or the caller wants the inputs
    /// sampled now).
    pub fn handle_inputs(&mut self, now: Micros) {
        let now = self.advance(now);
        let inputs = self.hw.read_inputs();
        self.apply_inputs(now, inputs);
        // The home switch changed, perhaps: homing looks at it now, not at the next poll.
        self.run_motion(now);
        self.take_camera_edges();
        self.run_capture_phases(now);
        self.sync_lasers();
    }

    /// The step generator ran dry while steps were due (board: its timer interrupt saw an empty
    /// queue mid-move): the position is unknown, so fault, stop at once and drop `homed`.
    pub fn handle_stall(&mut self, now: Micros) {
        let now = self.advance(now);
        if self.motion.is_none() {
            return;
        }
        self.fault = Some(Fault::StepStall);
        self.abort(now, HaltReason::StepStall, Halt::Emergency);
    }

    /// The step interrupt ran later than one timer period (board: its hardware update count ran
    /// ahead of the interrupts; Klipper's "Timer too close"), so a period may have repeated on
    /// stale preloads: a step nobody counted. The board has stopped the timer; fault, stop
    /// everything at once, forget `homed` and report [`HaltReason::StepLate`].
    pub fn handle_step_late(&mut self, now: Micros) {
        let now = self.advance(now);
        self.fault = Some(Fault::StepLate);
        self.homed = false;
        self.rehoming = false;
        self.abort(now, HaltReason::StepLate, Halt::Emergency);
    }

    /// Time passed: count the steps emitted, plan more, run every capture phase, program capture
    /// and safety check due by `now`.
    pub fn handle_timeout(&mut self, now: Micros) {
        let now = self.advance(now);
        if now >= self.next_input_poll {
            self.next_input_poll = now.saturating_add(INPUT_POLL_US);
            let inputs = self.hw.read_inputs();
            self.apply_inputs(now, inputs);
        }
        if self.link_alive && now >= self.heartbeat_deadline() {
            self.link_alive = false;
            if self.armed || self.lasers != 0 || self.busy() {
                self.abort(now, HaltReason::HeartbeatLost, Halt::Decelerate);
            }
        }
        if self.lasers != 0 && self.manual_deadline().is_some_and(|d| now >= d) {
            self.abort(now, HaltReason::LaserTimeout, Halt::KeepMoving);
        }
        self.run_motion(now);
        self.take_camera_edges();
        self.run_capture_phases(now);
        self.sync_lasers();
    }

    fn run_capture_phases(&mut self, now: Micros) {
        // Each pass advances a capture phase or starts a program capture; a few passes settle
        // everything due at one instant (zero settle time, back-to-back program points).
        for _ in 0..6 {
            if !self.run_capture(now) {
                break;
            }
        }
    }

    // ------------------------------------------------------------------------------------------
    // Outputs.

    /// When [`Rig::handle_timeout`] should be called next.
    pub fn poll_timeout(&self) -> Option<Micros> {
        let mut t = self.next_input_poll;
        if let Some(m) = &self.motion {
            if let Some(refill) = self.planner.refill_at() {
                t = t.min(refill);
            }
            if m.planned >= m.end {
                // Finish the motion when its last step is out.
                t = t.min(self.planner.last_due().unwrap_or(self.now));
            }
            if let MotionKind::Home {
                active_since: Some((since, _)),
                ..
            } = m.kind
            {
                t = t.min(since.saturating_add(u64::from(self.profile.homing.debounce_us)));
            }
        }
        if let Some(c) = &self.capture {
            t = t.min(match c.phase {
                Phase::Settling => c.laser_on_at,
                Phase::Lit => c.trigger_at,
                Phase::Exposing { trigger_high } => {
                    let low = c.trigger_at.saturating_add(u64::from(c.trigger_us));
                    if trigger_high {
                        low.min(c.laser_off_at)
                    } else {
                        c.laser_off_at
                    }
                }
                Phase::Confirming { deadline } => deadline,
            });
        } else if let Some(r) = &self.run {
            t = t.min(r.next_start);
        }
        if self.link_alive {
            t = t.min(self.heartbeat_deadline());
        }
        if self.lasers != 0
            && let Some(d) = self.manual_deadline()
        {
            t = t.min(d);
        }
        Some(t)
    }

    /// Encode the next outgoing frame into `buf` and return its length; `None` if nothing is
    /// queued or `buf` is shorter than the frame (use [`subsurf_protocol::MAX_FRAME`] bytes).
    pub fn poll_transmit(&mut self, buf: &mut [u8]) -> Option<usize> {
        loop {
            let msg = self.out.front()?;
            let encoded = match msg {
                RigMessage::Reply(r) => encode_reply(r, buf),
                RigMessage::Event(e) => encode_event(e, buf),
            };
            match encoded {
                Ok(n) => {
                    self.out.pop_front();
                    return Some(n);
                }
                Err(subsurf_protocol::EncodeError::BufferTooSmall) => return None,
                Err(_) => {
                    // Cannot happen (every message fits a frame); drop rather than wedge.
                    self.out.pop_front();
                    self.tx_dropped = self.tx_dropped.saturating_add(1);
                }
            }
        }
    }

    /// Take the next outgoing message unencoded (in-process use without framing).
    pub fn poll_message(&mut self) -> Option<RigMessage> {
        self.out.pop_front()
    }

    // ------------------------------------------------------------------------------------------
    // Safety: the only place that decides whether light may leave the rig.

    /// Whether any laser may emit right now: armed, no fault, e-stop released, interlock closed,
    /// turntable still, and the host heard from within the heartbeat timeout.
    pub fn laser_permitted(&self) -> bool {
        self.armed
            && self.fault.is_none()
            && !self.inputs.estop
            && self.inputs.interlock_closed
            && self.motion.is_none()
            && self.link_alive
    }

    /// Write the laser outputs: the manual channels plus the lit capture's channel, or nothing
    /// when [`Rig::laser_permitted`] is false. The only caller of `set_lasers`.
    fn sync_lasers(&mut self) {
        let wanted = if self.laser_permitted() {
            let capture = match &self.capture {
                Some(ActiveCapture {
                    channel: Some(channel),
                    phase: Phase::Lit | Phase::Exposing { .. },
                    ..
                }) => 1u8.checked_shl(u32::from(*channel)).unwrap_or(0),
                _ => 0,
            };
            (self.lasers | capture) & self.channel_mask()
        } else {
            self.lasers = 0;
            0
        };
        if self.lasers == 0 {
            self.manual_since = None;
        }
        if wanted != self.laser_output {
            self.hw.set_lasers(wanted);
            self.laser_output = wanted;
        }
    }

    /// Stop laser work, disarm, and report why; what happens to a motion depends on `halt`. A
    /// halt that cuts a motion clears `homed`.
    fn abort(&mut self, now: Micros, reason: HaltReason, halt: Halt) {
        // No log here: a halt may come in the middle of a decelerating stop, and a defmt line
        // masks interrupts (the step interrupt's too) for as long as it takes; the board logs
        // the `Halted` event it sends instead, once the motion is over.
        let moving = self
            .motion
            .as_ref()
            .is_some_and(|m| m.kind != MotionKind::Stopping);
        let cuts_motion = moving && halt != Halt::KeepMoving;
        let was_active = self.armed
            || self.lasers != 0
            || self.capture.is_some()
            || self.run.is_some()
            || cuts_motion;
        self.armed = false;
        self.lasers = 0;
        if self.capture.take().is_some() {
            self.hw.set_trigger(false);
        }
        if let Some(run) = self.run.take() {
            self.emit(
                now,
                EventKind::ProgramDone {
                    completed: run.completed,
                    finished: false,
                },
            );
        }
        match halt {
            Halt::KeepMoving => {}
            Halt::Decelerate => {
                if let Some(m) = self.motion.as_mut() {
                    m.kind = MotionKind::Stopping;
                    m.stop();
                    self.planner.clear_pending();
                    self.run_motion(now);
                }
            }
            Halt::Emergency => {
                self.motion = None;
                self.flush_steps();
            }
        }
        if cuts_motion {
            self.homed = false;
            self.rehoming = false;
        }
        self.sync_lasers();
        if was_active || reason != HaltReason::Stop {
            self.emit(now, EventKind::Halted { reason });
        }
    }

    fn apply_inputs(&mut self, now: Micros, inputs: Inputs) {
        self.inputs = inputs;
        if inputs.estop && self.fault != Some(Fault::EmergencyStop) {
            self.fault = Some(Fault::EmergencyStop);
            self.abort(now, HaltReason::EmergencyStop, Halt::Emergency);
            // Bench e-stops cut the drivers' power: a motor without holding torque may have been
            // turned by hand, so the position is lost even when nothing was moving (grbl's alarm
            // and Klipper's shutdown force homing again too).
            self.homed = false;
            self.rehoming = false;
        } else if !inputs.interlock_closed && (self.light_work() || self.moving_on()) {
            // grbl's safety door: the feed is held (decelerated to rest), the light cut.
            self.abort(now, HaltReason::InterlockOpen, Halt::Decelerate);
        }
    }

    /// Laser work is armed or under way.
    fn light_work(&self) -> bool {
        self.armed || self.lasers != 0 || self.capture.is_some() || self.run.is_some()
    }

    /// A move or homing pass is under way (not the ramp-down of one already halted).
    fn moving_on(&self) -> bool {
        self.motion
            .as_ref()
            .is_some_and(|m| m.kind != MotionKind::Stopping)
    }

    fn heartbeat_deadline(&self) -> Micros {
        self.last_request_at
            .saturating_add(u64::from(self.config.heartbeat_timeout_ms).saturating_mul(1000))
    }

    fn manual_deadline(&self) -> Option<Micros> {
        self.manual_since.map(|t| {
            t.saturating_add(u64::from(self.profile.laser.manual_max_ms).saturating_mul(1000))
        })
    }

    // ------------------------------------------------------------------------------------------
    // Helpers.

    fn advance(&mut self, now: Micros) -> Micros {
        self.now = self.now.max(now);
        self.count_steps(self.now);
        self.now
    }

    /// Take the steps the hardware has emitted by `now` onto the position.
    fn count_steps(&mut self, now: Micros) {
        let done = self.planner.take_due(now);
        self.step_position(done);
    }

    fn step_position(&mut self, steps: u32) {
        let d = i32::try_from(steps).unwrap_or(i32::MAX);
        self.position = if self.stepping_forward {
            self.position.saturating_add(d)
        } else {
            self.position.saturating_sub(d)
        };
    }

    fn busy(&self) -> bool {
        self.motion.is_some() || self.capture.is_some() || self.run.is_some()
    }

    fn channel_mask(&self) -> u8 {
        1u16.checked_shl(u32::from(self.caps.laser_channels))
            .map_or(u8::MAX, |m| u8::try_from(m - 1).unwrap_or(u8::MAX))
    }

    fn send(&mut self, msg: RigMessage) {
        if self.out.push_back(msg).is_err() {
            self.tx_dropped = self.tx_dropped.saturating_add(1);
        }
    }

    fn emit(&mut self, now: Micros, kind: EventKind) {
        let event = Event {
            event_seq: self.next_event_seq,
            timestamp_us: now,
            kind,
        };
        self.next_event_seq = self.next_event_seq.wrapping_add(1);
        if self.history.is_full() {
            self.history.pop_front();
        }
        // Cannot fail: a slot was just freed.
        let _ = self.history.push_back(event.clone());
        if self.executing {
            if let Err(event) = self.deferred.push_back(event) {
                self.send(RigMessage::Event(event));
            }
        } else {
            self.send(RigMessage::Event(event));
        }
    }

    /// Refuse actuation in fault or with the e-stop pressed.
    fn check_not_faulted(&self) -> Result<(), RigError> {
        if let Some(f) = self.fault {
            return Err(RigError::Faulted(f));
        }
        if self.inputs.estop {
            return Err(RigError::EmergencyStop);
        }
        Ok(())
    }

    /// Conditions for starting laser work (manual laser, capture, program).
    fn check_laser_ready(&self) -> Result<(), RigError> {
        self.check_not_faulted()?;
        if !self.inputs.interlock_closed {
            return Err(RigError::InterlockOpen);
        }
        if !self.armed {
            return Err(RigError::NotArmed);
        }
        Ok(())
    }

    fn check_galvo(&self, p: GalvoPoint) -> Result<(), RigError> {
        if p.x > self.caps.galvo_max || p.y > self.caps.galvo_max {
            return Err(RigError::OutOfRange);
        }
        Ok(())
    }

    fn check_capture_settings(
        &self,
        channel: u8,
        settle_us: Option<u32>,
        exposure_us: u32,
        trigger_us: u32,
    ) -> Result<(), RigError> {
        if channel >= self.caps.laser_channels {
            return Err(RigError::NoSuchChannel);
        }
        if exposure_us < self.caps.min_exposure_us {
            return Err(RigError::ExposureTooShort {
                min_us: self.caps.min_exposure_us,
            });
        }
        let exposure_ok = exposure_us <= self.caps.max_exposure_us;
        let trigger_ok = (1..=exposure_us).contains(&trigger_us);
        let settle_ok = settle_us.is_none_or(|s| s <= MAX_SETTLE_US);
        if !(exposure_ok && trigger_ok && settle_ok) {
            return Err(RigError::OutOfRange);
        }
        Ok(())
    }

    /// Stop dead: discard the queued steps the hardware has not emitted yet; the ones it did are
    /// counted. Returns how many were discarded.
    fn flush_steps(&mut self) -> u32 {
        if self.planner.idle() {
            return 0;
        }
        let dropped = self.hw.flush();
        let emitted = self.planner.flushed(dropped, self.now);
        self.step_position(emitted);
        dropped
    }

    /// Take every camera edge the hardware timestamped: count exposures, note the capture's.
    fn take_camera_edges(&mut self) {
        // Bounded: a flood of edges is taken over several calls.
        for _ in 0..16 {
            let Some(edge) = self.hw.poll_camera_edge() else {
                break;
            };
            let capture = self.capture.as_mut();
            match edge {
                CameraEdge::Trigger(at) => {
                    if let Some(c) = capture
                        && matches!(c.phase, Phase::Exposing { .. })
                        && c.trigger_edge.is_none()
                    {
                        c.trigger_edge = Some(at);
                    }
                }
                CameraEdge::ExposureStart(at) => {
                    self.exposures = self.exposures.wrapping_add(1);
                    if let Some(c) = capture
                        && !matches!(c.phase, Phase::Settling)
                        && c.exposure_start.is_none()
                    {
                        c.exposure_start = Some(at);
                    }
                }
                CameraEdge::ExposureEnd(at) => {
                    self.camera_ready_at = self
                        .camera_ready_at
                        .max(at.saturating_add(u64::from(self.profile.camera.readout_us)));
                    if let Some(c) = capture
                        && c.exposure_start.is_some()
                        && c.exposure_end.is_none()
                    {
                        c.exposure_end = Some(at);
                    }
                }
            }
        }
    }

    // ------------------------------------------------------------------------------------------
    // Commands.

    fn execute(&mut self, now: Micros, command: Command) -> Result<Response, RigError> {
        match command {
            Command::Hello { protocol_version } => {
                if protocol_version != PROTOCOL_VERSION {
                    return Err(RigError::UnknownVersion {
                        rig: PROTOCOL_VERSION,
                    });
                }
                self.session = true;
                Ok(Response::Hello(Hello {
                    protocol_version: PROTOCOL_VERSION,
                    firmware_version: FIRMWARE_VERSION,
                    boot_nonce: self.boot_nonce,
                    capabilities: self.caps,
                }))
            }
            Command::Heartbeat => Ok(Response::Ack),
            Command::Status => Ok(Response::Status(self.status())),
            Command::GetConfig => Ok(Response::Config(self.config)),
            Command::SetConfig(config) => {
                if self.busy() {
                    return Err(RigError::Busy);
                }
                if !config_ok(&config) {
                    return Err(RigError::OutOfRange);
                }
                self.config = config;
                Ok(Response::Ack)
            }
            Command::GetProfile => Ok(Response::Profile(self.profile)),
            Command::GetStoredProfile => self
                .hw
                .stored_profile()
                .map(Response::Profile)
                .ok_or(RigError::ProfileNotStored),
            Command::SetProfile(profile) => {
                if self.busy() || !self.planner.idle() {
                    return Err(RigError::Busy);
                }
                profile.validate().map_err(RigError::BadProfile)?;
                // Dark and disarmed before the write (an erase stalls every interrupt on the
                // board), whatever its outcome; the reply waits for flash to read the profile
                // back: a failed save leaves the old profile in force, the one a reset would
                // bring back.
                self.armed = false;
                self.lasers = 0;
                self.sync_lasers();
                self.hw
                    .store_profile(&profile)
                    .map_err(RigError::ProfileNotSaved)?;
                if profile.galvo.output != self.profile.galvo.output {
                    let c = profile.galvo.output.center();
                    self.galvo = GalvoPoint { x: c, y: c };
                    self.hw.set_galvo(self.galvo);
                }
                self.profile = profile;
                self.profile_known = true;
                self.caps = capabilities(&profile);
                self.planner.set_min_gap_us(min_step_gap_us(&profile));
                self.homed = false;
                self.program.clear();
                self.program_header = None;
                Ok(Response::Ack)
            }
            Command::Home => self.start_home(now),
            Command::Move(mv) => self.start_move(now, mv),
            Command::Galvo(p) => {
                if self.capture.is_some() || self.run.is_some() {
                    return Err(RigError::Busy);
                }
                self.check_not_faulted()?;
                self.check_galvo(p)?;
                self.hw.set_galvo(p);
                self.galvo = p;
                Ok(Response::Ack)
            }
            Command::Arm => {
                self.check_not_faulted()?;
                if !self.inputs.interlock_closed {
                    return Err(RigError::InterlockOpen);
                }
                if !self.profile_known {
                    return Err(RigError::ProfileNotStored);
                }
                // A wrong polarity (its "off" is the laser's "on") is caught here, before
                // anything asks for light.
                if !self.hw.lines_idle_off(self.profile.laser.active_low) {
                    return Err(RigError::LaserPolarity);
                }
                self.armed = true;
                Ok(Response::Ack)
            }
            Command::Disarm => {
                self.armed = false;
                self.lasers = 0;
                Ok(Response::Ack)
            }
            Command::Laser { channel, on } => {
                if channel >= self.caps.laser_channels {
                    return Err(RigError::NoSuchChannel);
                }
                let bit = 1u8.checked_shl(u32::from(channel)).unwrap_or(0);
                if !on {
                    self.lasers &= !bit;
                    return Ok(Response::Ack);
                }
                self.check_laser_ready()?;
                if self.busy() {
                    return Err(RigError::Busy);
                }
                if self.lasers == 0 {
                    self.manual_since = Some(now);
                }
                self.lasers |= bit;
                Ok(Response::Ack)
            }
            Command::Capture(c) => self.start_single_capture(now, c),
            Command::DarkCapture(c) => self.start_dark_capture(now, c),
            Command::ProgramLoad(header) => self.load_program(header),
            Command::ProgramPoints(chunk) => self.add_program_points(chunk),
            Command::ProgramRun => self.run_program(now),
            Command::Stop => {
                self.abort(now, HaltReason::Stop, Halt::Decelerate);
                Ok(Response::Ack)
            }
            Command::ClearFault => {
                if self.inputs.estop {
                    return Err(RigError::EmergencyStop);
                }
                self.fault = None;
                Ok(Response::Ack)
            }
            Command::Replay { since, max } => Ok(Response::Events(self.replay(since, max))),
            Command::BoardRegisters => Ok(Response::BoardRegisters(self.hw.board_registers())),
            // The protocol enum is non-exhaustive: a newer host command this firmware predates.
            #[allow(unreachable_patterns)]
            _ => Err(RigError::OutOfRange),
        }
    }

    /// Up to `max` (at most [`REPLAY_BATCH`]) kept events from `since` on (or from the oldest
    /// kept one, when `since` was overwritten). Read-only: replaying changes nothing on the rig.
    fn replay(&self, since: u32, max: u8) -> EventReplay {
        let next = self.next_event_seq;
        let oldest = self.history.front().map_or(next, |e| e.event_seq);
        // Wrapping distance from the next event back to `since`: within the kept window, the
        // kept events from `since` on are the last `back` ones; farther back (or "ahead" of the
        // rig, a confused host), everything kept is newer than `since`.
        let kept = self.history.len();
        let back = usize::try_from(next.wrapping_sub(since)).unwrap_or(usize::MAX);
        let skip = kept.saturating_sub(back.min(kept));
        let mut events = Vec::new();
        let take = usize::from(max).clamp(1, REPLAY_BATCH);
        for e in self.history.iter().skip(skip).take(take) {
            // Cannot fail: at most REPLAY_BATCH are taken.
            let _ = events.push(e.clone());
        }
        EventReplay {
            oldest,
            next_event_seq: next,
            events,
        }
    }

    fn start_motion(&mut self, now: Micros, profile: Profile, forward: bool, kind: MotionKind) {
        // The laser goes dark before the first step: manual channels are switched off for good.
        self.lasers = 0;
        // A motion starts from rest after the last one's steps are all out (its first step comes
        // sqrt(2/accel) ≥ 447 µs later, past any DIR set-up).
        self.planner.clear_pending();
        self.stepping_forward = forward;
        self.motion = Some(Motion::new(now, profile, forward, kind));
        self.sync_lasers();
        self.run_motion(now);
    }

    /// Motion needs the enclosure shut (grbl's safety door).
    fn check_motion_ready(&self) -> Result<(), RigError> {
        self.check_not_faulted()?;
        if !self.inputs.interlock_closed {
            return Err(RigError::InterlockOpen);
        }
        // No guessed mechanics: the board keeps EN released until a profile is stored, so a
        // motion now would only count steps nobody makes.
        if !self.profile_known {
            return Err(RigError::ProfileNotStored);
        }
        Ok(())
    }

    fn start_move(&mut self, now: Micros, mv: Move) -> Result<Response, RigError> {
        self.check_motion_ready()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        let speed_ok = (1..=self.caps.max_speed).contains(&mv.max_speed);
        let accel_ok = (1..=self.caps.max_accel).contains(&mv.accel);
        if !(speed_ok && accel_ok) {
            return Err(RigError::OutOfRange);
        }
        let target = match mv.target {
            MoveTarget::Absolute(t) => {
                if !self.homed {
                    return Err(RigError::NotHomed);
                }
                t
            }
            MoveTarget::Relative(d) => self.position.checked_add(d).ok_or(RigError::OutOfRange)?,
        };
        let delta = i64::from(target) - i64::from(self.position);
        let steps = u32::try_from(delta.unsigned_abs()).map_err(|_| RigError::OutOfRange)?;
        if steps == 0 {
            self.emit(
                now,
                EventKind::MoveDone {
                    position: self.position,
                },
            );
            return Ok(Response::Ack);
        }
        let profile = Profile::new(steps, mv.max_speed, mv.accel).ok_or(RigError::OutOfRange)?;
        self.start_motion(now, profile, delta > 0, MotionKind::Move);
        Ok(Response::Ack)
    }

    fn home_kind(phase: HomePhase) -> MotionKind {
        MotionKind::Home {
            phase,
            seen_active: false,
            active_since: None,
        }
    }

    /// Start a homing pass: `fast` passes use the homing speed, the others the slow speed.
    fn start_home_pass(&mut self, now: Micros, phase: HomePhase, steps: u32) -> bool {
        let h = self.profile.homing;
        let (speed, forward) = match phase {
            HomePhase::Approach => (h.speed, false),
            HomePhase::SlowApproach => (h.slow_speed, false),
            HomePhase::Release => (h.speed, true),
            HomePhase::LeaveSwitch
            | HomePhase::LeftSwitch
            | HomePhase::BackOff
            | HomePhase::Return => (h.slow_speed, true),
            // Never started as passes (they are the stops of the fast passes).
            HomePhase::BrakeToRelease => (h.speed, false),
            HomePhase::BrakeToBackOff => (h.speed, true),
        };
        let Some(profile) = Profile::new(steps, speed, h.accel) else {
            return false;
        };
        self.start_motion(now, profile, forward, Self::home_kind(phase));
        true
    }

    fn start_home(&mut self, now: Micros) -> Result<Response, RigError> {
        self.check_motion_ready()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        self.rehoming = self.homed;
        self.homed = false;
        self.home_edge = None;
        let max = self.profile.homing.max_steps;
        let phase = if self.hw.read_inputs().home_switch {
            HomePhase::LeaveSwitch
        } else {
            HomePhase::Approach
        };
        if !self.start_home_pass(now, phase, max) {
            return Err(RigError::OutOfRange);
        }
        Ok(Response::Ack)
    }

    /// Back off `backoff_steps` slowly, then the slow approach.
    fn start_backoff(&mut self, now: Micros) {
        let h = self.profile.homing;
        let ok = if h.backoff_steps == 0 {
            self.start_home_pass(now, HomePhase::SlowApproach, h.max_steps)
        } else {
            self.start_home_pass(now, HomePhase::BackOff, h.backoff_steps)
        };
        if !ok {
            self.homing_failed(now);
        }
    }

    fn finish_home(&mut self, now: Micros) {
        self.position = 0;
        self.homed = true;
        let previous = if self.rehoming { self.home_edge } else { None };
        self.emit(now, EventKind::Homed { previous });
    }

    fn homing_failed(&mut self, now: Micros) {
        self.fault = Some(Fault::HomingFailed);
        self.abort(now, HaltReason::HomingFailed, Halt::Emergency);
    }

    /// The switch as it reads now (position = the steps emitted by now); `Some(next)` ends the
    /// pass (with what follows). Checked on every input change and input poll, not per step:
    /// the board's home switch raises an interrupt.
    fn homing_check(&mut self, now: Micros, m: &mut Motion) -> Option<HomeNext> {
        let MotionKind::Home {
            phase,
            seen_active,
            active_since,
        } = &mut m.kind
        else {
            return None;
        };
        let active = self.hw.read_inputs().home_switch;
        let h = self.profile.homing;
        match *phase {
            HomePhase::LeaveSwitch => (!active).then_some(HomeNext::CutThen(HomePhase::LeftSwitch)),
            HomePhase::Release => {
                *seen_active |= active;
                (!active && *seen_active).then_some(HomeNext::StopThen(HomePhase::BrakeToBackOff))
            }
            HomePhase::Approach => active.then_some(HomeNext::StopThen(HomePhase::BrakeToRelease)),
            HomePhase::SlowApproach => {
                if !active {
                    // Bounce: start over.
                    *active_since = None;
                    return None;
                }
                let (since, edge) = *active_since.get_or_insert((now, self.position));
                if now.saturating_sub(since) >= u64::from(h.debounce_us) {
                    Some(HomeNext::Found(edge))
                } else {
                    None
                }
            }
            HomePhase::LeftSwitch
            | HomePhase::BackOff
            | HomePhase::Return
            | HomePhase::BrakeToRelease
            | HomePhase::BrakeToBackOff => None,
        }
    }

    /// Look at the home switch, plan steps ahead, and finish the move or homing pass once its
    /// last step is out.
    fn run_motion(&mut self, now: Micros) {
        let Some(mut m) = self.motion.take() else {
            return;
        };
        if let Some(next) = self.homing_check(now, &mut m) {
            self.homing_next(now, m, next);
            return;
        }
        // Top the queue up once it runs low (not on every wake: a run of steps ends where the
        // planning horizon did, so planning in bigger bites gives longer runs).
        if self.planner.refill_at().is_none_or(|t| now >= t) {
            let planner = &mut self.planner;
            let hw = &mut self.hw;
            planner.refill(now, m.forward, &mut || m.next_ideal(), &mut |segment| {
                hw.queue(segment)
            });
        }
        let pending = u32::try_from(self.planner.pending_len()).unwrap_or(u32::MAX);
        m.planned = m.computed.saturating_sub(pending);
        if m.planned < m.end || !self.planner.drained() {
            // Steps still to plan or still in the hardware's queue.
            self.motion = Some(m);
            return;
        }
        self.planner.clear_pending();
        match m.kind {
            MotionKind::Move => self.emit(
                now,
                EventKind::MoveDone {
                    position: self.position,
                },
            ),
            MotionKind::Stopping => {}
            MotionKind::Home { phase, .. } => match phase {
                HomePhase::BackOff => {
                    let max = self.profile.homing.max_steps;
                    if !self.start_home_pass(now, HomePhase::SlowApproach, max) {
                        self.homing_failed(now);
                    }
                }
                HomePhase::BrakeToRelease => {
                    let max = self.profile.homing.max_steps;
                    if !self.start_home_pass(now, HomePhase::Release, max) {
                        self.homing_failed(now);
                    }
                }
                HomePhase::LeftSwitch | HomePhase::BrakeToBackOff => self.start_backoff(now),
                HomePhase::Return => self.finish_home(now),
                HomePhase::LeaveSwitch
                | HomePhase::Approach
                | HomePhase::Release
                | HomePhase::SlowApproach => self.homing_failed(now),
            },
        }
    }

    fn homing_next(&mut self, now: Micros, mut m: Motion, next: HomeNext) {
        match next {
            HomeNext::CutThen(phase) => {
                // Slow: the steps already queued run out, then the next pass starts from rest.
                m.cut();
                self.planner.clear_pending();
                m.kind = Self::home_kind(phase);
                self.motion = Some(m);
                self.run_motion(now);
            }
            HomeNext::StopThen(brake) => {
                // Seen at speed: the steps already queued run out and a deceleration ramp follows
                // them, from their speed to rest (never a dead stop at speed); the slow pass
                // measures the edge.
                m.stop();
                self.planner.clear_pending();
                m.kind = Self::home_kind(brake);
                self.motion = Some(m);
                self.run_motion(now);
            }
            HomeNext::Found(edge) => {
                // At the slow speed the motor stops within a step: drop what is queued.
                self.flush_steps();
                self.home_edge = Some(edge);
                // The edge is `past` steps back (position decreases on approach).
                let past = u32::try_from(i64::from(edge) - i64::from(self.position)).unwrap_or(0);
                if past == 0 {
                    self.finish_home(now);
                } else {
                    self.position = -i32::try_from(past).unwrap_or(i32::MAX);
                    if !self.start_home_pass(now, HomePhase::Return, past) {
                        self.homing_failed(now);
                    }
                }
            }
        }
    }
}

impl<H: Hardware> Rig<H> {
    fn start_single_capture(&mut self, now: Micros, c: Capture) -> Result<Response, RigError> {
        self.check_not_faulted()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        self.check_capture_settings(c.channel, c.settle_us, c.exposure_us, c.trigger_us)?;
        self.check_galvo(c.galvo)?;
        self.check_laser_ready()?;
        let capture_id = self.next_capture_id;
        self.next_capture_id = self.next_capture_id.wrapping_add(1);
        self.start_capture(now, capture_id, None, c, true);
        Ok(Response::CaptureStarted { capture_id })
    }

    /// A capture with every laser off (the camera's dark frame): the timing checks of a capture,
    /// none of the laser's (it needs no arming: it emits nothing; an open interlock halts it
    /// as any capture), the mirrors left where they are.
    fn start_dark_capture(&mut self, now: Micros, c: DarkCapture) -> Result<Response, RigError> {
        self.check_not_faulted()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        self.check_capture_settings(0, None, c.exposure_us, c.trigger_us)?;
        let capture_id = self.next_capture_id;
        self.next_capture_id = self.next_capture_id.wrapping_add(1);
        let at = Capture {
            galvo: self.galvo,
            settle_us: Some(0),
            channel: 0,
            exposure_us: c.exposure_us,
            trigger_us: c.trigger_us,
        };
        self.start_capture(now, capture_id, None, at, false);
        Ok(Response::CaptureStarted { capture_id })
    }

    /// Plan the window: laser on once the galvo has settled and the camera has read out (less
    /// the laser lead), trigger `lead_us` later, laser off `tail_us` after the nominal exposure.
    /// `lit` false: a dark capture, the same timing with every laser off.
    fn start_capture(
        &mut self,
        now: Micros,
        id: u32,
        program_index: Option<u16>,
        c: Capture,
        lit: bool,
    ) {
        let settle = c
            .settle_us
            .unwrap_or_else(|| galvo_settle_us(&self.profile, self.galvo, c.galvo));
        self.hw.set_galvo(c.galvo);
        self.galvo = c.galvo;
        // Manual channels go off: during a capture only its own channel may emit.
        self.lasers = 0;
        let lead = u64::from(self.profile.laser.lead_us);
        let laser_on_at = now
            .saturating_add(u64::from(settle))
            .max(self.camera_ready_at.saturating_sub(lead));
        let trigger_at = laser_on_at.saturating_add(lead);
        let laser_off_at = trigger_at
            .saturating_add(u64::from(c.exposure_us))
            .saturating_add(u64::from(self.profile.laser.tail_us));
        self.capture = Some(ActiveCapture {
            id,
            program_index,
            galvo: c.galvo,
            channel: lit.then_some(c.channel),
            trigger_us: c.trigger_us,
            exposure_us: c.exposure_us,
            laser_on_at,
            trigger_at,
            laser_off_at,
            trigger_edge: None,
            exposure_start: None,
            exposure_end: None,
            phase: Phase::Settling,
        });
        self.sync_lasers();
    }

    /// Advance the capture in progress or start the next program capture; `true` if anything
    /// changed.
    fn run_capture(&mut self, now: Micros) -> bool {
        let Some(mut c) = self.capture else {
            return self.start_program_capture(now);
        };
        match c.phase {
            Phase::Settling if now >= c.laser_on_at => {
                c.phase = Phase::Lit;
                self.capture = Some(c);
                self.sync_lasers();
                // A dark capture's window is timed too, with no channel in it: the camera's
                // exposure is the same as a lit one's.
                if self.laser_output != 0 || c.channel.is_none() {
                    let window = ExposureWindow {
                        channel_mask: if c.channel.is_some() {
                            self.laser_output
                        } else {
                            0
                        },
                        laser_on_at: now,
                        trigger_at: c.trigger_at,
                        trigger_us: c.trigger_us,
                        exposure_us: c.exposure_us,
                        laser_off_at: c.laser_off_at,
                    };
                    self.hw.arm_window(&window);
                }
                true
            }
            Phase::Lit if now >= c.trigger_at => {
                c.phase = Phase::Exposing { trigger_high: true };
                self.capture = Some(c);
                self.hw.set_trigger(true);
                true
            }
            Phase::Exposing { trigger_high } => {
                let mut changed = false;
                let low_at = c.trigger_at.saturating_add(u64::from(c.trigger_us));
                if trigger_high && now >= low_at.min(c.laser_off_at) {
                    self.hw.set_trigger(false);
                    c.phase = Phase::Exposing {
                        trigger_high: false,
                    };
                    changed = true;
                }
                if now >= c.laser_off_at {
                    c.phase = Phase::Confirming {
                        deadline: now
                            .saturating_add(u64::from(self.profile.camera.confirm_timeout_us)),
                    };
                    self.capture = Some(c);
                    self.sync_lasers();
                    // The camera's edges may already be in.
                    self.take_camera_edges();
                    return true;
                }
                self.capture = Some(c);
                changed
            }
            Phase::Confirming { deadline } => {
                let done = c.exposure_end.is_some() || now >= deadline;
                if done {
                    self.finish_capture(now, c);
                }
                done
            }
            Phase::Settling | Phase::Lit => false,
        }
    }

    fn finish_capture(&mut self, now: Micros, c: ActiveCapture) {
        self.capture = None;
        if c.program_index.is_some()
            && let Some(run) = self.run.as_mut()
        {
            run.completed = run.completed.saturating_add(1);
        }
        let triggered_at = c.trigger_edge.unwrap_or(c.trigger_at);
        let exposure = match (c.exposure_start, c.exposure_end) {
            (Some(start), Some(end)) => Some(ExposureActive {
                delay_us: u32::try_from(start.saturating_sub(triggered_at)).unwrap_or(u32::MAX),
                duration_us: u32::try_from(end.saturating_sub(start)).unwrap_or(u32::MAX),
            }),
            _ => None,
        };
        let (lit_from, lit_until) = c.lit_window();
        let lit = c.channel.is_some()
            && matches!((c.exposure_start, c.exposure_end),
            (Some(start), Some(end)) if start >= lit_from && end <= lit_until);
        if exposure.is_none() {
            // No image will come for this capture: the camera is ready again only after the
            // timeout (a late exposure would be counted anyway).
            self.camera_ready_at = self.camera_ready_at.max(now);
        }
        self.emit(
            now,
            EventKind::Captured(Captured {
                capture_id: c.id,
                program_index: c.program_index,
                triggered_at_us: triggered_at,
                exposure,
                exposure_count: self.exposures,
                lit,
                galvo: c.galvo,
                // A dark capture fired none: `lit` says so, 0 keeps the encoding of version 5.
                channel: c.channel.unwrap_or(0),
            }),
        );
    }

    fn load_program(&mut self, header: ProgramHeader) -> Result<Response, RigError> {
        if self.run.is_some() {
            return Err(RigError::Busy);
        }
        if header.len == 0 || header.len > self.caps.max_program_points {
            return Err(RigError::OutOfRange);
        }
        self.check_capture_settings(
            header.channel,
            header.settle_us,
            header.exposure_us,
            header.trigger_us,
        )?;
        // Back-to-back triggers faster than the camera reads out would be dropped by the camera
        // (or worse, silently merged): refuse them here.
        let min_interval = header
            .exposure_us
            .saturating_add(self.profile.camera.readout_us);
        if header.interval_us < min_interval {
            return Err(RigError::IntervalTooShort {
                min_us: min_interval,
            });
        }
        self.program.clear();
        self.program_header = Some(header);
        Ok(Response::Ack)
    }

    fn add_program_points(&mut self, chunk: ProgramChunk) -> Result<Response, RigError> {
        if self.run.is_some() {
            return Err(RigError::Busy);
        }
        let header = self.program_header.ok_or(RigError::ProgramIncomplete)?;
        if usize::from(chunk.offset) != self.program.len() {
            return Err(RigError::ProgramIncomplete);
        }
        if self.program.len() + chunk.points.len() > usize::from(header.len) {
            return Err(RigError::OutOfRange);
        }
        for p in &chunk.points {
            self.check_galvo(*p)?;
        }
        self.program
            .extend_from_slice(&chunk.points)
            .map_err(|_| RigError::OutOfRange)?;
        Ok(Response::Ack)
    }

    fn run_program(&mut self, now: Micros) -> Result<Response, RigError> {
        self.check_not_faulted()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        let header = self.program_header.ok_or(RigError::ProgramIncomplete)?;
        if self.program.len() != usize::from(header.len) {
            return Err(RigError::ProgramIncomplete);
        }
        self.check_laser_ready()?;
        let first_id = self.next_capture_id;
        self.next_capture_id = self.next_capture_id.wrapping_add(u32::from(header.len));
        self.run = Some(ProgramRun {
            first_id,
            next_index: 0,
            completed: 0,
            next_start: now,
        });
        Ok(Response::ProgramStarted {
            first_capture_id: first_id,
        })
    }

    /// Start the next program capture if one is due; finish the program after its last point.
    fn start_program_capture(&mut self, now: Micros) -> bool {
        let (Some(mut run), Some(header)) = (self.run, self.program_header) else {
            return false;
        };
        if now < run.next_start {
            return false;
        }
        let Some(&point) = self.program.get(usize::from(run.next_index)) else {
            self.run = None;
            self.emit(
                now,
                EventKind::ProgramDone {
                    completed: run.completed,
                    finished: true,
                },
            );
            return true;
        };
        let index = run.next_index;
        run.next_index = index.saturating_add(1);
        run.next_start = now.saturating_add(u64::from(header.interval_us));
        self.run = Some(run);
        let capture = Capture {
            galvo: point,
            settle_us: header.settle_us,
            channel: header.channel,
            exposure_us: header.exposure_us,
            trigger_us: header.trigger_us,
        };
        let id = run.first_id.wrapping_add(u32::from(index));
        self.start_capture(now, id, Some(index), capture, true);
        true
    }
}

/// How a halt treats a motion in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Halt {
    /// Leave it running (manual laser timeout: lasers only).
    KeepMoving,
    /// Decelerate to rest (stop request, lost heartbeat, interlock opened).
    Decelerate,
    /// Stop dead and discard queued steps (e-stop, stall, homing failure).
    Emergency,
}

/// What ends a homing pass.
#[derive(Debug, Clone, Copy)]
enum HomeNext {
    /// Plan no more steps; once the queued ones are out, this phase's successor.
    CutThen(HomePhase),
    /// Decelerate after the queued steps, then this phase's successor.
    StopThen(HomePhase),
    /// The switch edge, at this position.
    Found(i32),
}

fn config_ok(c: &Config) -> bool {
    (1..=MAX_HEARTBEAT_TIMEOUT_MS).contains(&c.heartbeat_timeout_ms)
}
