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
//!         Timeout    => rig.handle_timeout(now()),  // takes every step due by now, even if late
//!     }
//!     while let Some(n) = rig.poll_transmit(&mut frame) { uart_tx.write(&frame[..n]) }
//! }
//! ```
//!
//! All laser-safety rules live in [`Rig::laser_permitted`] and `Rig::sync_lasers`: no code path
//! writes the laser outputs except `sync_lasers`, which outputs nothing unless `laser_permitted`.

use heapless::{Deque, Vec};
use subsurf_protocol::{
    Capabilities, Capture, Captured, Command, Config, Event, EventKind, EventReplay, Fault,
    FirmwareVersion, FrameDecoder, GalvoPoint, HaltReason, Hello, Inputs, Move, MoveTarget,
    PROTOCOL_VERSION, ProgramChunk, ProgramHeader, REPLAY_BATCH, Reply, Request, Response,
    RigError, RigMessage, RigState, Seq, Status, encode_event, encode_reply,
};

use crate::hal::Hardware;
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
/// 32 × 48 bytes of RAM.
pub const EVENT_HISTORY: usize = 32;

/// Inputs are sampled at least this often (µs) even without pin-change notifications.
pub const INPUT_POLL_US: Micros = 1_000;

/// Longest accepted galvo settle time, µs.
pub const MAX_SETTLE_US: u32 = 1_000_000;

/// Longest accepted heartbeat timeout, ms.
pub const MAX_HEARTBEAT_TIMEOUT_MS: u32 = 600_000;

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

/// Galvo settle time for a jump from `from` to `to`: `galvo_settle_min_us` plus
/// `galvo_settle_per_kcode_us` per 1000 codes of the larger axis jump, saturating.
pub fn galvo_settle_us(config: &Config, from: GalvoPoint, to: GalvoPoint) -> u32 {
    let jump = u64::from(from.x.abs_diff(to.x).max(from.y.abs_diff(to.y)));
    let extra = jump.saturating_mul(u64::from(config.galvo_settle_per_kcode_us)) / 1000;
    u32::try_from(u64::from(config.galvo_settle_min_us).saturating_add(extra)).unwrap_or(u32::MAX)
}

/// A turntable move (or homing run) in progress.
#[derive(Debug, Clone, Copy)]
struct Motion {
    profile: Profile,
    start: Micros,
    done: u32,
    forward: bool,
    homing: bool,
    next_due: Micros,
}

/// Phase of the capture in progress.
#[derive(Debug, Clone, Copy)]
enum Phase {
    Settling {
        until: Micros,
    },
    Exposing {
        triggered_at: Micros,
        trigger_low_at: Micros,
        laser_off_at: Micros,
        trigger_high: bool,
    },
}

/// The capture in progress.
#[derive(Debug, Clone, Copy)]
struct ActiveCapture {
    id: u32,
    program_index: Option<u16>,
    galvo: GalvoPoint,
    channel: u8,
    exposure_us: u32,
    trigger_us: u32,
    phase: Phase,
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
    caps: Capabilities,
    config: Config,
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
    /// What the laser outputs currently show.
    laser_output: u8,
    inputs: Inputs,
    fault: Option<Fault>,
    last_request_at: Micros,
    link_alive: bool,
    next_input_poll: Micros,
    // Turntable.
    position: i32,
    homed: bool,
    motion: Option<Motion>,
    // Galvo and captures.
    galvo: GalvoPoint,
    capture: Option<ActiveCapture>,
    program_header: Option<ProgramHeader>,
    program: Vec<GalvoPoint, MAX_PROGRAM_POINTS>,
    run: Option<ProgramRun>,
    next_capture_id: u32,
    next_event_seq: u32,
}

impl<H: Hardware> Rig<H> {
    /// A rig at rest: lasers off, trigger low, galvo at 0, disarmed, position 0 (not homed).
    /// `capabilities.laser_channels` is capped at 8 and `max_program_points` at
    /// [`MAX_PROGRAM_POINTS`].
    pub fn new(mut hw: H, mut capabilities: Capabilities, config: Config, now: Micros) -> Self {
        capabilities.laser_channels = capabilities
            .laser_channels
            .min(subsurf_protocol::MAX_LASER_CHANNELS);
        capabilities.max_program_points = capabilities
            .max_program_points
            .min(u16::try_from(MAX_PROGRAM_POINTS).unwrap_or(u16::MAX));
        hw.set_lasers(0);
        hw.set_trigger(false);
        hw.set_galvo(GalvoPoint::default());
        let inputs = hw.read_inputs();
        let mut rig = Self {
            hw,
            caps: capabilities,
            config,
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
            laser_output: 0,
            inputs,
            fault: None,
            last_request_at: now,
            link_alive: false,
            next_input_poll: now,
            position: 0,
            homed: false,
            motion: None,
            galvo: GalvoPoint::default(),
            capture: None,
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

    /// The fixed limits announced in the handshake.
    pub fn capabilities(&self) -> &Capabilities {
        &self.caps
    }

    /// The current tunable settings.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Laser channels currently emitting.
    pub fn laser_output(&self) -> u8 {
        self.laser_output
    }

    /// Whether the laser is armed.
    pub fn armed(&self) -> bool {
        self.armed
    }

    /// Whether the turntable is moving (including homing).
    pub fn moving(&self) -> bool {
        self.motion.is_some()
    }

    /// Turntable position, steps (0 = home once homed).
    pub fn position(&self) -> i32 {
        self.position
    }

    /// When the next motor step is due, µs (for a board that programs a hardware timer per step;
    /// [`Rig::poll_timeout`] already includes it).
    pub fn next_step_due(&self) -> Option<Micros> {
        self.motion.as_ref().map(|m| m.next_due)
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
            if m.homing {
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
            state,
            position: self.position,
            homed: self.homed,
            armed: self.armed,
            lasers: self.laser_output,
            galvo: self.galvo,
            inputs: self.inputs,
            fault: self.fault,
            next_capture_id: self.next_capture_id,
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
        self.last_request_at = now;
        self.link_alive = true;
        let is_hello = matches!(req.command, Command::Hello { .. });
        if is_hello {
            self.replies.clear();
        }
        let reply = if let Some(cached) = self.replies.get(req.seq) {
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
        self.send(RigMessage::Reply(reply));
        // The reply precedes the events its command caused (e.g. a zero-length move's MoveDone).
        while let Some(event) = self.deferred.pop_front() {
            self.send(RigMessage::Event(event));
        }
        self.sync_lasers();
    }

    /// An input pin changed (or the caller wants the inputs sampled now).
    pub fn handle_inputs(&mut self, now: Micros) {
        let now = self.advance(now);
        let inputs = self.hw.read_inputs();
        self.apply_inputs(now, inputs);
        self.sync_lasers();
    }

    /// Time passed: run every step, capture phase, program capture and safety check due by `now`.
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
                self.abort(now, HaltReason::HeartbeatLost, true);
            }
        }
        self.run_motion(now);
        // Each pass advances a capture phase or starts a program capture; a few passes settle
        // everything due at one instant (zero settle time, back-to-back program points).
        for _ in 0..4 {
            if !self.run_capture(now) {
                break;
            }
        }
        self.sync_lasers();
    }

    // ------------------------------------------------------------------------------------------
    // Outputs.

    /// When [`Rig::handle_timeout`] should be called next.
    pub fn poll_timeout(&self) -> Option<Micros> {
        let mut t = self.next_input_poll;
        if let Some(m) = &self.motion {
            t = t.min(m.next_due);
        }
        if let Some(c) = &self.capture {
            t = t.min(match c.phase {
                Phase::Settling { until } => until,
                Phase::Exposing {
                    trigger_low_at,
                    laser_off_at,
                    trigger_high,
                    ..
                } => {
                    if trigger_high {
                        trigger_low_at.min(laser_off_at)
                    } else {
                        laser_off_at
                    }
                }
            });
        } else if let Some(r) = &self.run {
            t = t.min(r.next_start);
        }
        if self.link_alive {
            t = t.min(self.heartbeat_deadline());
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

    /// Write the laser outputs: the manual channels plus the exposing capture's channel, or
    /// nothing when [`Rig::laser_permitted`] is false. The only caller of `set_lasers`.
    fn sync_lasers(&mut self) {
        let wanted = if self.laser_permitted() {
            let capture = match &self.capture {
                Some(ActiveCapture {
                    channel,
                    phase: Phase::Exposing { .. },
                    ..
                }) => 1u8.checked_shl(u32::from(*channel)).unwrap_or(0),
                _ => 0,
            };
            (self.lasers | capture) & self.channel_mask()
        } else {
            self.lasers = 0;
            0
        };
        if wanted != self.laser_output {
            self.hw.set_lasers(wanted);
            self.laser_output = wanted;
        }
    }

    /// Stop laser work (and the motor when `stop_motion`), disarm, and report why.
    fn abort(&mut self, now: Micros, reason: HaltReason, stop_motion: bool) {
        #[cfg(feature = "defmt")]
        defmt::warn!("halt at {=u64} us: {}", now, reason);
        let was_active = self.armed
            || self.lasers != 0
            || self.capture.is_some()
            || self.run.is_some()
            || (stop_motion && self.motion.is_some());
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
        if stop_motion {
            self.motion = None;
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
            self.abort(now, HaltReason::EmergencyStop, true);
        } else if !inputs.interlock_closed
            && (self.armed || self.lasers != 0 || self.capture.is_some() || self.run.is_some())
        {
            self.abort(now, HaltReason::InterlockOpen, false);
        }
    }

    fn heartbeat_deadline(&self) -> Micros {
        self.last_request_at
            .saturating_add(u64::from(self.config.heartbeat_timeout_ms).saturating_mul(1000))
    }

    // ------------------------------------------------------------------------------------------
    // Helpers.

    fn advance(&mut self, now: Micros) -> Micros {
        self.now = self.now.max(now);
        self.now
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
        let exposure_ok = (1..=self.caps.max_exposure_us).contains(&exposure_us);
        let trigger_ok = (1..=exposure_us).contains(&trigger_us);
        let settle_ok = settle_us.is_none_or(|s| s <= MAX_SETTLE_US);
        if !(exposure_ok && trigger_ok && settle_ok) {
            return Err(RigError::OutOfRange);
        }
        Ok(())
    }

    fn check_config(&self, c: &Config) -> Result<(), RigError> {
        let ok = (1..=MAX_HEARTBEAT_TIMEOUT_MS).contains(&c.heartbeat_timeout_ms)
            && c.galvo_settle_min_us <= MAX_SETTLE_US
            && c.galvo_settle_per_kcode_us <= MAX_SETTLE_US
            && (1..=self.caps.max_speed).contains(&c.home_speed)
            && (1..=self.caps.max_accel).contains(&c.home_accel)
            && c.home_max_steps >= 1;
        if ok {
            Ok(())
        } else {
            Err(RigError::OutOfRange)
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
                Ok(Response::Hello(Hello {
                    protocol_version: PROTOCOL_VERSION,
                    firmware_version: FIRMWARE_VERSION,
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
                self.check_config(&config)?;
                self.config = config;
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
                self.lasers |= bit;
                Ok(Response::Ack)
            }
            Command::Capture(c) => self.start_single_capture(now, c),
            Command::ProgramLoad(header) => self.load_program(header),
            Command::ProgramPoints(chunk) => self.add_program_points(chunk),
            Command::ProgramRun => self.run_program(now),
            Command::Stop => {
                self.abort(now, HaltReason::Stop, true);
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

    fn start_motion(&mut self, now: Micros, profile: Profile, forward: bool, homing: bool) {
        // The laser goes dark before the first step: manual channels are switched off for good.
        self.lasers = 0;
        self.motion = Some(Motion {
            profile,
            start: now,
            done: 0,
            forward,
            homing,
            next_due: now.saturating_add(profile.step_time_us(1)),
        });
        self.sync_lasers();
    }

    fn start_move(&mut self, now: Micros, mv: Move) -> Result<Response, RigError> {
        self.check_not_faulted()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        let speed_ok = (1..=self.caps.max_speed).contains(&mv.max_speed);
        let accel_ok = (1..=self.caps.max_accel).contains(&mv.accel);
        if !(speed_ok && accel_ok) {
            return Err(RigError::OutOfRange);
        }
        let target = match mv.target {
            MoveTarget::Absolute(t) => t,
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
        self.start_motion(now, profile, delta > 0, false);
        Ok(Response::Ack)
    }

    fn start_home(&mut self, now: Micros) -> Result<Response, RigError> {
        self.check_not_faulted()?;
        if self.busy() {
            return Err(RigError::Busy);
        }
        if self.hw.read_inputs().home_switch {
            self.finish_home(now);
            return Ok(Response::Ack);
        }
        let speed = self.config.home_speed.min(self.caps.max_speed);
        let accel = self.config.home_accel.min(self.caps.max_accel);
        let profile =
            Profile::new(self.config.home_max_steps, speed, accel).ok_or(RigError::OutOfRange)?;
        self.homed = false;
        self.start_motion(now, profile, false, true);
        Ok(Response::Ack)
    }

    fn finish_home(&mut self, now: Micros) {
        self.position = 0;
        self.homed = true;
        self.emit(now, EventKind::Homed);
    }

    /// Take every step due by `now`; finish the move or homing run when complete.
    fn run_motion(&mut self, now: Micros) {
        let Some(mut m) = self.motion.take() else {
            return;
        };
        while m.done < m.profile.steps() && m.next_due <= now {
            if m.homing && self.hw.read_inputs().home_switch {
                self.finish_home(now);
                return;
            }
            self.hw.step(m.forward);
            self.position = if m.forward {
                self.position.saturating_add(1)
            } else {
                self.position.saturating_sub(1)
            };
            m.done += 1;
            let due = m
                .start
                .saturating_add(m.profile.step_time_us(m.done.saturating_add(1)));
            m.next_due = m.next_due.max(due);
        }
        if m.done < m.profile.steps() {
            self.motion = Some(m);
        } else if !m.homing {
            self.emit(
                now,
                EventKind::MoveDone {
                    position: self.position,
                },
            );
        } else if self.hw.read_inputs().home_switch {
            self.finish_home(now);
        } else {
            self.fault = Some(Fault::HomingFailed);
            self.abort(now, HaltReason::HomingFailed, true);
        }
    }

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
        self.start_capture(now, capture_id, None, c);
        Ok(Response::CaptureStarted { capture_id })
    }

    fn start_capture(&mut self, now: Micros, id: u32, program_index: Option<u16>, c: Capture) {
        let settle = c
            .settle_us
            .unwrap_or_else(|| galvo_settle_us(&self.config, self.galvo, c.galvo));
        self.hw.set_galvo(c.galvo);
        self.galvo = c.galvo;
        // Manual channels go off: during a capture only its own channel may emit.
        self.lasers = 0;
        self.capture = Some(ActiveCapture {
            id,
            program_index,
            galvo: c.galvo,
            channel: c.channel,
            exposure_us: c.exposure_us,
            trigger_us: c.trigger_us,
            phase: Phase::Settling {
                until: now.saturating_add(u64::from(settle)),
            },
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
            Phase::Settling { until } if now >= until => {
                c.phase = Phase::Exposing {
                    triggered_at: now,
                    trigger_low_at: now.saturating_add(u64::from(c.trigger_us)),
                    laser_off_at: now.saturating_add(u64::from(c.exposure_us)),
                    trigger_high: true,
                };
                self.capture = Some(c);
                // Laser on, then trigger: the camera must see the spot from its first row.
                self.sync_lasers();
                self.hw.set_trigger(true);
                true
            }
            Phase::Exposing {
                triggered_at,
                trigger_low_at,
                laser_off_at,
                trigger_high,
            } => {
                let mut changed = false;
                if trigger_high && now >= trigger_low_at {
                    self.hw.set_trigger(false);
                    c.phase = Phase::Exposing {
                        triggered_at,
                        trigger_low_at,
                        laser_off_at,
                        trigger_high: false,
                    };
                    self.capture = Some(c);
                    changed = true;
                }
                if now >= laser_off_at {
                    if let Phase::Exposing {
                        trigger_high: true, ..
                    } = c.phase
                    {
                        self.hw.set_trigger(false);
                    }
                    self.capture = None;
                    self.sync_lasers();
                    if c.program_index.is_some()
                        && let Some(run) = self.run.as_mut()
                    {
                        run.completed = run.completed.saturating_add(1);
                    }
                    self.emit(
                        now,
                        EventKind::Captured(Captured {
                            capture_id: c.id,
                            program_index: c.program_index,
                            triggered_at_us: triggered_at,
                            galvo: c.galvo,
                            channel: c.channel,
                        }),
                    );
                    changed = true;
                }
                changed
            }
            Phase::Settling { .. } => false,
        }
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
        self.start_capture(now, id, Some(index), capture);
        true
    }
}
