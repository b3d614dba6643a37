//! The blocking driver: pumps a [`ClientCore`] over a [`ByteLink`] with the wall clock.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use subsurf_protocol::{
    Capture, Captured, Command, Config, DarkCapture, Event, EventKind, GalvoPoint, Hello, Move,
    MoveTarget, PROGRAM_CHUNK, PROTOCOL_VERSION, ProgramChunk, ProgramHeader, Response, RigError,
    RigProfile, RigState, Status,
};

use super::{ClientConfig, ClientCore, ClientStats, Outcome, RigClientError};
use crate::link::ByteLink;

/// How often [`RigClient`] polls the rig's status while waiting for an event that may have been
/// lost on the link.
const STATUS_POLL: Duration = Duration::from_millis(100);

/// A connected rig: typed calls, retransmission, heartbeats and the event stream.
///
/// Heartbeats and events only flow while the client is used: a program that wants to keep the rig
/// armed while doing other work calls [`RigClient::poll`] regularly (the rig disarms itself when
/// heartbeats stop, which is the safe default).
pub struct RigClient<L: ByteLink> {
    link: L,
    core: ClientCore,
    hello: Hello,
    rx: Vec<u8>,
    events: VecDeque<Event>,
    reboots: u32,
}

impl<L: ByteLink> std::fmt::Debug for RigClient<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RigClient")
            .field("link", &self.link.describe())
            .field("hello", &self.hello)
            .finish_non_exhaustive()
    }
}

impl<L: ByteLink> RigClient<L> {
    /// Handshake over `link`: checks the protocol version and learns the rig's capabilities.
    ///
    /// The heartbeat interval is then set to a quarter of the rig's heartbeat timeout (if that is
    /// shorter than `config.heartbeat_every`), so an attentive client never trips it.
    pub fn connect(link: L, config: ClientConfig) -> Result<Self, RigClientError> {
        let first_seq = rand::random::<u32>();
        Self::connect_with_seq(link, config, first_seq)
    }

    /// [`RigClient::connect`] with a chosen first sequence number (deterministic tests).
    pub fn connect_with_seq(
        mut link: L,
        config: ClientConfig,
        first_seq: u32,
    ) -> Result<Self, RigClientError> {
        // A lone delimiter flushes whatever half frame the rig may hold from a previous client.
        link.send(&[0])?;
        let core = ClientCore::new(config, link.now(), first_seq);
        let mut client = Self {
            link,
            core,
            hello: Hello {
                protocol_version: PROTOCOL_VERSION,
                firmware_version: subsurf_protocol::FirmwareVersion {
                    major: 0,
                    minor: 0,
                    patch: 0,
                },
                boot_nonce: 0,
                capabilities: subsurf_protocol::Capabilities {
                    steps_per_rev: 0,
                    galvo_max: 0,
                    laser_channels: 0,
                    max_speed: 0,
                    max_accel: 0,
                    max_exposure_us: 0,
                    min_exposure_us: 0,
                    camera_readout_us: 0,
                    max_program_points: 0,
                },
            },
            rx: vec![0; 4096],
            events: VecDeque::new(),
            reboots: 0,
        };
        client.hello = client.handshake()?;
        let status = client.status()?;
        client.core.sync_events(status.next_event_seq);
        let rig_config = client.get_config()?;
        let quarter = Duration::from_millis(u64::from(rig_config.heartbeat_timeout_ms) / 4);
        let mut config = *client.core.config();
        if let Some(every) = config.heartbeat_every
            && quarter < every
            && !quarter.is_zero()
        {
            config.heartbeat_every = Some(quarter);
            client.core.set_config(config);
        }
        Ok(client)
    }

    fn handshake(&mut self) -> Result<Hello, RigClientError> {
        let reply = self.call_raw(Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        })?;
        // A new session: events queued so far belong to the previous one. The core delivers
        // none until the next `Status` tells it the rig's event counter.
        self.events.clear();
        hello_from_reply(reply)
    }

    /// What the rig announced in the handshake.
    pub fn hello(&self) -> &Hello {
        &self.hello
    }

    /// Protocol counters (retransmissions, lost events, decoder drops).
    pub fn stats(&self) -> ClientStats {
        self.core.stats()
    }

    /// The link, e.g. to read its fault statistics.
    pub fn link(&self) -> &L {
        &self.link
    }

    /// Send `command` and wait for its reply (retransmitting as needed); the rig's typed refusal
    /// is the inner `Err`.
    pub fn call_raw(
        &mut self,
        command: Command,
    ) -> Result<Result<Response, RigError>, RigClientError> {
        let name = format!("{command:?}");
        let started = self.link.now();
        let seq = self.core.start(started, command);
        loop {
            while let Some(done) = self.core.poll_completion() {
                if done.seq != seq {
                    continue;
                }
                return match done.outcome {
                    Outcome::Replied(result) => Ok(result),
                    Outcome::TimedOut { attempts } => Err(RigClientError::NoReply {
                        link: self.link.describe(),
                        command: name,
                        attempts,
                        waited: self.link.now().duration_since(started),
                    }),
                };
            }
            // The core always has a deadline while a request is in flight.
            self.pump(self.link.now() + Duration::from_secs(1))?;
        }
    }

    /// Send `command`; a refusal becomes [`RigClientError::Rejected`]. A rig that reset since
    /// the handshake (it refuses with `NoSession`, or a status shows another boot nonce) is
    /// handshaken again and the call fails with [`RigClientError::Rebooted`]: the command may
    /// have been lost with the reset and the rig has forgotten its homing.
    pub fn call(&mut self, command: Command) -> Result<Response, RigClientError> {
        let name = format!("{command:?}");
        match self.call_raw(command)? {
            Err(RigError::NoSession) => Err(self.rehandshake(name)),
            Ok(Response::Status(s)) if s.boot_nonce != self.hello.boot_nonce => {
                Err(self.rehandshake(name))
            }
            Ok(r) => Ok(r),
            Err(error) => Err(RigClientError::Rejected {
                command: name,
                error,
            }),
        }
    }

    /// After a detected reset: open a new session (its events start from the rig's new counter,
    /// none of them dropped as duplicates of the old session's) and say so.
    fn rehandshake(&mut self, command: String) -> RigClientError {
        let old = self.hello.boot_nonce;
        match self.handshake() {
            Ok(hello) => {
                self.hello = hello;
                self.reboots += 1;
                if let Ok(Ok(Response::Status(_))) = self.call_raw(Command::Status) {
                    // The core synced its event position from this status.
                }
                RigClientError::Rebooted {
                    command,
                    old,
                    new: hello.boot_nonce,
                }
            }
            Err(e) => e,
        }
    }

    /// Resets of the rig this client noticed (and recovered the session from).
    pub fn reboots(&self) -> u32 {
        self.reboots
    }

    fn call_ack(&mut self, command: Command) -> Result<(), RigClientError> {
        let name = format!("{command:?}");
        match self.call(command)? {
            Response::Ack => Ok(()),
            other => Err(unexpected(name, other)),
        }
    }

    /// Write pending frames, wait for input until the core's next deadline or `until`, process it.
    fn pump(&mut self, until: Instant) -> Result<(), RigClientError> {
        self.flush()?;
        let now = self.link.now();
        let wake = self.core.poll_timeout().map_or(until, |t| t.min(until));
        let n = self
            .link
            .recv(&mut self.rx, wake.saturating_duration_since(now))?;
        let now = self.link.now();
        if n > 0 {
            self.core.handle_input(now, &self.rx[..n]);
        }
        self.core.handle_timeout(now);
        while let Some(event) = self.core.poll_event() {
            self.events.push_back(event);
        }
        self.flush()
    }

    fn flush(&mut self) -> Result<(), RigClientError> {
        while let Some(frame) = self.core.poll_transmit() {
            self.link.send(&frame)?;
        }
        Ok(())
    }

    /// Keep the link alive and collect events for up to `timeout`.
    pub fn poll(&mut self, timeout: Duration) -> Result<(), RigClientError> {
        let until = self.link.now() + timeout;
        loop {
            self.pump(until)?;
            if self.link.now() >= until {
                return Ok(());
            }
        }
    }

    /// The next rig event, waiting up to `timeout` (heartbeats keep flowing meanwhile).
    pub fn next_event(&mut self, timeout: Duration) -> Result<Option<Event>, RigClientError> {
        let until = self.link.now() + timeout;
        loop {
            if let Some(event) = self.events.pop_front() {
                return Ok(Some(event));
            }
            if self.link.now() >= until {
                return Ok(None);
            }
            self.pump(until)?;
        }
    }

    /// Handshake again (e.g. to print it); the version check applies.
    pub fn hello_again(&mut self) -> Result<Hello, RigClientError> {
        let hello = self.handshake()?;
        self.hello = hello;
        // Resynchronises the event stream (see `handshake`).
        self.status()?;
        Ok(hello)
    }

    /// A snapshot of the rig.
    pub fn status(&mut self) -> Result<Status, RigClientError> {
        match self.call(Command::Status)? {
            Response::Status(s) => Ok(s),
            other => Err(unexpected("Status", other)),
        }
    }

    /// The rig's tunable settings.
    pub fn get_config(&mut self) -> Result<Config, RigClientError> {
        match self.call(Command::GetConfig)? {
            Response::Config(c) => Ok(c),
            other => Err(unexpected("GetConfig", other)),
        }
    }

    /// Replace the rig's tunable settings.
    pub fn set_config(&mut self, config: Config) -> Result<(), RigClientError> {
        self.call_ack(Command::SetConfig(config))
    }

    /// The rig profile in force (mechanics and I/O).
    pub fn get_profile(&mut self) -> Result<RigProfile, RigClientError> {
        match self.call(Command::GetProfile)? {
            Response::Profile(p) => Ok(p),
            other => Err(unexpected("GetProfile", other)),
        }
    }

    /// The board's registers the bring-up checklist checks (brown-out level, flash accelerator,
    /// debug freeze, the step counter's wiring); `None` from a rig without them (simulated).
    pub fn board_registers(
        &mut self,
    ) -> Result<Option<subsurf_protocol::BoardRegisters>, RigClientError> {
        match self.call(Command::BoardRegisters)? {
            Response::BoardRegisters(r) => Ok(r),
            other => Err(unexpected("BoardRegisters", other)),
        }
    }

    /// The profile the rig's flash holds (read from flash: what its next boot runs);
    /// `RigError::ProfileNotStored` when none is.
    pub fn get_stored_profile(&mut self) -> Result<RigProfile, RigClientError> {
        match self.call(Command::GetStoredProfile)? {
            Response::Profile(p) => Ok(p),
            other => Err(unexpected("GetStoredProfile", other)),
        }
    }

    /// Send a rig profile (validated here first; the rig validates again and persists it) and
    /// handshake again so [`RigClient::hello`] shows the capabilities it implies.
    pub fn set_profile(&mut self, profile: RigProfile) -> Result<(), RigClientError> {
        if let Err(error) = profile.validate() {
            return Err(RigClientError::Rejected {
                command: "SetProfile".into(),
                error: RigError::BadProfile(error),
            });
        }
        self.call_ack(Command::SetProfile(profile))?;
        self.hello_again()?;
        Ok(())
    }

    /// An explicit heartbeat (the client also sends them by itself while it is pumped).
    pub fn heartbeat(&mut self) -> Result<(), RigClientError> {
        self.call_ack(Command::Heartbeat)
    }

    /// Start homing; see [`RigClient::wait_idle`].
    pub fn home(&mut self) -> Result<(), RigClientError> {
        self.call_ack(Command::Home)
    }

    /// Start a move; see [`RigClient::wait_idle`].
    pub fn start_move(
        &mut self,
        target: MoveTarget,
        max_speed: u32,
        accel: u32,
    ) -> Result<(), RigClientError> {
        self.call_ack(Command::Move(Move {
            target,
            max_speed,
            accel,
        }))
    }

    /// Point the galvo.
    pub fn galvo(&mut self, x: u16, y: u16) -> Result<(), RigClientError> {
        self.call_ack(Command::Galvo(GalvoPoint { x, y }))
    }

    /// Allow laser emission.
    pub fn arm(&mut self) -> Result<(), RigClientError> {
        self.call_ack(Command::Arm)
    }

    /// Forbid laser emission.
    pub fn disarm(&mut self) -> Result<(), RigClientError> {
        self.call_ack(Command::Disarm)
    }

    /// Switch one laser channel (the rig must be armed to switch it on).
    pub fn laser(&mut self, channel: u8, on: bool) -> Result<(), RigClientError> {
        self.call_ack(Command::Laser { channel, on })
    }

    /// Laser off, disarm, halt the motor, abort captures and programs.
    pub fn stop(&mut self) -> Result<(), RigClientError> {
        self.call_ack(Command::Stop)
    }

    /// Leave the fault state once its cause is gone.
    pub fn clear_fault(&mut self) -> Result<(), RigClientError> {
        self.call_ack(Command::ClearFault)
    }

    /// Start one atomic capture; returns its id (see [`RigClient::wait_captured`]).
    pub fn start_capture(&mut self, capture: Capture) -> Result<u32, RigClientError> {
        match self.call(Command::Capture(capture))? {
            Response::CaptureStarted { capture_id } => Ok(capture_id),
            other => Err(unexpected("Capture", other)),
        }
    }

    /// One capture with every laser off (the camera's dark frame), waited for.
    pub fn dark_capture(
        &mut self,
        dark: DarkCapture,
        timeout: Duration,
    ) -> Result<Captured, RigClientError> {
        let id = match self.call(Command::DarkCapture(dark))? {
            Response::CaptureStarted { capture_id } => capture_id,
            other => return Err(unexpected("DarkCapture", other)),
        };
        self.wait_captured(id, timeout)
    }

    /// One capture, waited for: returns the rig's report with the trigger timestamp.
    pub fn capture(
        &mut self,
        capture: Capture,
        timeout: Duration,
    ) -> Result<Captured, RigClientError> {
        let id = self.start_capture(capture)?;
        self.wait_captured(id, timeout)
    }

    /// Upload a queued capture program in chunks; the rig keeps it until run or replaced.
    pub fn load_program(
        &mut self,
        header: ProgramHeader,
        points: &[GalvoPoint],
    ) -> Result<(), RigClientError> {
        self.call_ack(Command::ProgramLoad(header))?;
        for (i, chunk) in points.chunks(PROGRAM_CHUNK).enumerate() {
            let mut v = heapless::Vec::new();
            for p in chunk {
                // chunks() never yields more than PROGRAM_CHUNK points.
                let _ = v.push(*p);
            }
            let offset =
                u16::try_from(i * PROGRAM_CHUNK).map_err(|_| RigClientError::Rejected {
                    command: "ProgramPoints".into(),
                    error: RigError::OutOfRange,
                })?;
            self.call_ack(Command::ProgramPoints(ProgramChunk { offset, points: v }))?;
        }
        Ok(())
    }

    /// Run the uploaded program; returns the id of its first capture. Events follow.
    pub fn run_program(&mut self) -> Result<u32, RigClientError> {
        match self.call(Command::ProgramRun)? {
            Response::ProgramStarted { first_capture_id } => Ok(first_capture_id),
            other => Err(unexpected("ProgramRun", other)),
        }
    }

    /// Wait until capture `id` has finished and return its report.
    ///
    /// A `Captured` event lost on the link is recovered: the status polls made here tell the
    /// client that the rig's event counter moved on, and it asks the rig to replay the missing
    /// events. Only when the rig no longer keeps the event (more than
    /// `subsurf_firmware::rig::EVENT_HISTORY` events later) does this notice from the status
    /// (the capture counter moved past `id`, the rig is idle, nothing is being recovered) and
    /// report [`RigClientError::EventTimeout`] early rather than waiting for the full timeout.
    pub fn wait_captured(
        &mut self,
        id: u32,
        timeout: Duration,
    ) -> Result<Captured, RigClientError> {
        let what = format!("capture {id}");
        let started = self.link.now();
        let mut next_poll = started + STATUS_POLL;
        loop {
            while let Some(event) = self.events.pop_front() {
                match event.kind {
                    EventKind::Captured(c) if c.capture_id == id => return Ok(c),
                    EventKind::Halted { reason } => {
                        return Err(RigClientError::Halted {
                            what,
                            reason: format!("{reason:?}"),
                        });
                    }
                    _ => {}
                }
            }
            let now = self.link.now();
            if now.duration_since(started) >= timeout {
                return Err(RigClientError::EventTimeout {
                    what,
                    waited: now.duration_since(started),
                });
            }
            if now >= next_poll {
                next_poll = now + STATUS_POLL;
                let s = self.status()?;
                if self.events.is_empty()
                    && !self.core.recovering_events()
                    && s.state != RigState::Capturing
                    && s.state != RigState::Program
                    && s.next_capture_id.wrapping_sub(id) as i32 > 0
                {
                    return Err(RigClientError::EventTimeout {
                        what: format!(
                            "{what} (finished on the rig, its event was lost and is no longer kept)"
                        ),
                        waited: now.duration_since(started),
                    });
                }
            }
            self.pump((started + timeout).min(next_poll))?;
        }
    }

    /// Wait until the rig is idle again (after a move, homing, capture or program) and return its
    /// status. Uses events when they arrive and status polls otherwise; a fault is an error.
    pub fn wait_idle(&mut self, timeout: Duration) -> Result<Status, RigClientError> {
        let started = self.link.now();
        loop {
            let s = self.status()?;
            match s.state {
                RigState::Idle => return Ok(s),
                RigState::Fault => {
                    return Err(RigClientError::Halted {
                        what: "the rig to become idle".into(),
                        reason: format!("{:?}", s.fault),
                    });
                }
                _ => {}
            }
            let now = self.link.now();
            if now.duration_since(started) >= timeout {
                return Err(RigClientError::EventTimeout {
                    what: format!("the rig to become idle (it is {:?})", s.state),
                    waited: now.duration_since(started),
                });
            }
            // Wake early on any event that could mean "done".
            let until = (now + STATUS_POLL).min(started + timeout);
            while self.link.now() < until {
                let before = self.events.len();
                self.pump(until)?;
                if self.events.iter().skip(before).any(|e| {
                    matches!(
                        e.kind,
                        EventKind::MoveDone { .. }
                            | EventKind::Homed { .. }
                            | EventKind::Halted { .. }
                            | EventKind::ProgramDone { .. }
                            | EventKind::Captured(_)
                    )
                }) {
                    break;
                }
            }
        }
    }

    /// Give the link back (after a final [`RigClient::stop`], typically).
    pub fn into_link(self) -> L {
        self.link
    }
}

/// The handshake's verdict: the rig's [`Hello`] if it speaks our protocol version.
fn hello_from_reply(reply: Result<Response, RigError>) -> Result<Hello, RigClientError> {
    match reply {
        Ok(Response::Hello(hello)) if hello.protocol_version == PROTOCOL_VERSION => Ok(hello),
        Ok(Response::Hello(hello)) => Err(RigClientError::VersionMismatch {
            host: PROTOCOL_VERSION,
            rig: hello.protocol_version,
        }),
        Err(RigError::UnknownVersion { rig }) => Err(RigClientError::VersionMismatch {
            host: PROTOCOL_VERSION,
            rig,
        }),
        Err(error) => Err(RigClientError::Rejected {
            command: "Hello".into(),
            error,
        }),
        Ok(other) => Err(unexpected("Hello", other)),
    }
}

fn unexpected(command: impl Into<String>, response: Response) -> RigClientError {
    RigClientError::UnexpectedResponse {
        command: command.into(),
        response: format!("{response:?}"),
    }
}

#[cfg(test)]
mod tests {
    use subsurf_protocol::{Capabilities, FirmwareVersion};

    use super::*;

    fn hello(protocol_version: u16) -> Hello {
        Hello {
            protocol_version,
            firmware_version: FirmwareVersion {
                major: 1,
                minor: 2,
                patch: 3,
            },
            boot_nonce: 1,
            capabilities: Capabilities {
                steps_per_rev: 3200,
                galvo_max: 4095,
                laser_channels: 2,
                max_speed: 1000,
                max_accel: 1000,
                max_exposure_us: 1_000_000,
                min_exposure_us: 20,
                camera_readout_us: 0,
                max_program_points: 100,
            },
        }
    }

    #[test]
    fn version_mismatch_is_a_clear_error_either_way() {
        let ours = hello(PROTOCOL_VERSION);
        assert_eq!(
            hello_from_reply(Ok(Response::Hello(ours))).expect("same version"),
            ours
        );
        let newer = PROTOCOL_VERSION + 1;
        for reply in [
            Ok(Response::Hello(hello(newer))),
            Err(RigError::UnknownVersion { rig: newer }),
        ] {
            let err = hello_from_reply(reply).expect_err("mismatch");
            assert!(matches!(err, RigClientError::VersionMismatch { rig, .. } if rig == newer));
            let text = err.to_string();
            assert!(text.contains("version mismatch") && text.contains(&newer.to_string()));
        }
        assert!(matches!(
            hello_from_reply(Ok(Response::Ack)),
            Err(RigClientError::UnexpectedResponse { .. })
        ));
    }
}
