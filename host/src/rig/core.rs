//! The rig client as a sans-IO state machine: bytes and `now` in, bytes, completions and events out.
//!
//! Call order (the blocking [`super::RigClient`] and the deterministic test harness both follow it):
//! 1. [`ClientCore::start`] queues a command and returns its sequence number.
//! 2. Drain [`ClientCore::poll_transmit`] onto the link.
//! 3. Feed whatever the link delivered to [`ClientCore::handle_input`], and call
//!    [`ClientCore::handle_timeout`] whenever [`ClientCore::poll_timeout`] has passed.
//! 4. Collect [`ClientCore::poll_completion`] and [`ClientCore::poll_event`]; go to 2.
//!
//! Reliability is stop-and-wait: exactly one request is on the wire at a time and it is
//! retransmitted with the same sequence number until its reply arrives or `give_up_after` passes.
//! The rig answers a retransmission from its reply cache without executing it again, so every
//! command runs at most once and commands run in the order they were started.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use subsurf_protocol::{
    Command, DecoderStats, Event, FrameDecoder, MAX_FRAME, Reply, Request, Response, RigError,
    RigMessage, Seq, encode_request,
};

/// Timing of retransmissions and heartbeats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClientConfig {
    /// Resend the request in flight when no reply came for this long.
    pub retransmit_after: Duration,
    /// Fail the request when no reply came for this long since it was first sent.
    pub give_up_after: Duration,
    /// Send a heartbeat when the link has been idle this long (`None`: never).
    pub heartbeat_every: Option<Duration>,
}

impl Default for ClientConfig {
    /// Values for a real serial line: a request and its reply take well under 10 ms at 115200 baud.
    fn default() -> Self {
        Self {
            retransmit_after: Duration::from_millis(50),
            give_up_after: Duration::from_secs(2),
            heartbeat_every: Some(Duration::from_millis(200)),
        }
    }
}

/// How a started command ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// The rig executed it (or refused it with a typed error, then it executed nothing).
    Replied(Result<Response, RigError>),
    /// No reply within `give_up_after`: the rig may or may not have executed it.
    TimedOut {
        /// How often the request was sent.
        attempts: u32,
    },
}

/// A finished command: its sequence number and outcome.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Completion {
    /// The sequence number [`ClientCore::start`] returned.
    pub seq: Seq,
    /// What happened.
    pub outcome: Outcome,
}

/// Counters for diagnostics and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ClientStats {
    /// Requests sent for the first time.
    pub requests: u64,
    /// Retransmissions.
    pub retransmits: u64,
    /// Requests that were given up.
    pub timeouts: u64,
    /// Heartbeats sent.
    pub heartbeats: u64,
    /// Replies for no request in flight (duplicates, answers to given-up requests).
    pub stray_replies: u64,
    /// Events received twice (duplicated frames) and ignored.
    pub duplicate_events: u64,
    /// Events the rig sent that never arrived (gaps in `event_seq`).
    pub lost_events: u64,
    /// What the frame decoder dropped.
    pub decoder: DecoderStats,
}

#[derive(Debug)]
struct InFlight {
    seq: Seq,
    frame: Vec<u8>,
    first_sent: Instant,
    last_sent: Instant,
    attempts: u32,
    /// A heartbeat the client sent by itself: its completion is not reported.
    internal: bool,
}

/// The host side of the protocol, without I/O or clock. See the module documentation.
#[derive(Debug)]
pub struct ClientCore {
    config: ClientConfig,
    decoder: FrameDecoder,
    next_seq: Seq,
    queue: VecDeque<(Seq, Command, bool)>,
    in_flight: Option<InFlight>,
    transmit: VecDeque<Vec<u8>>,
    completions: VecDeque<Completion>,
    events: VecDeque<Event>,
    next_event_seq: Option<u32>,
    last_activity: Instant,
    stats: ClientStats,
}

impl ClientCore {
    /// A client whose first request gets sequence number `first_seq`.
    ///
    /// Pick `first_seq` at random per session: a rig that is still running answers a request
    /// whose number it has just seen from its reply cache, so a new session must not reuse the
    /// last one's numbers.
    pub fn new(config: ClientConfig, now: Instant, first_seq: Seq) -> Self {
        Self {
            config,
            decoder: FrameDecoder::new(),
            next_seq: first_seq,
            queue: VecDeque::new(),
            in_flight: None,
            transmit: VecDeque::new(),
            completions: VecDeque::new(),
            events: VecDeque::new(),
            next_event_seq: None,
            last_activity: now,
            stats: ClientStats::default(),
        }
    }

    /// The timing in force.
    pub fn config(&self) -> &ClientConfig {
        &self.config
    }

    /// Change the timing (e.g. the heartbeat after reading the rig's heartbeat timeout).
    pub fn set_config(&mut self, config: ClientConfig) {
        self.config = config;
    }

    /// Counters so far.
    pub fn stats(&self) -> ClientStats {
        ClientStats {
            decoder: self.decoder.stats(),
            ..self.stats
        }
    }

    /// Whether no command is queued or in flight.
    pub fn is_idle(&self) -> bool {
        self.in_flight.is_none() && self.queue.is_empty()
    }

    /// Queue `command`; returns the sequence number its [`Completion`] will carry.
    pub fn start(&mut self, now: Instant, command: Command) -> Seq {
        self.enqueue(now, command, false)
    }

    /// Expect the next event to have this `event_seq` (from [`subsurf_protocol::Status`]), so
    /// duplicates and gaps are recognised from the first event on.
    pub fn sync_events(&mut self, next_event_seq: u32) {
        self.next_event_seq = Some(next_event_seq);
    }

    fn enqueue(&mut self, now: Instant, command: Command, internal: bool) -> Seq {
        let seq = self.next_seq;
        self.next_seq = self.next_seq.wrapping_add(1);
        self.queue.push_back((seq, command, internal));
        self.send_next(now);
        seq
    }

    fn send_next(&mut self, now: Instant) {
        if self.in_flight.is_some() {
            return;
        }
        let Some((seq, command, internal)) = self.queue.pop_front() else {
            return;
        };
        let mut buf = [0u8; MAX_FRAME];
        let frame = match encode_request(&Request { seq, command }, &mut buf) {
            Ok(n) => buf.get(..n).unwrap_or_default().to_vec(),
            // Every command is bounded well below MAX_MESSAGE (protocol invariant); should one
            // not be, it fails like a lost request instead of being sent truncated.
            Err(_) => {
                self.stats.timeouts += 1;
                if !internal {
                    self.completions.push_back(Completion {
                        seq,
                        outcome: Outcome::TimedOut { attempts: 0 },
                    });
                }
                return self.send_next(now);
            }
        };
        self.transmit.push_back(frame.clone());
        self.stats.requests += 1;
        if internal {
            self.stats.heartbeats += 1;
        }
        self.last_activity = now;
        self.in_flight = Some(InFlight {
            seq,
            frame,
            first_sent: now,
            last_sent: now,
            attempts: 1,
            internal,
        });
    }

    /// Bytes received from the rig, in any chunking.
    pub fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        let mut input = bytes;
        while !input.is_empty() {
            let (msg, rest) = self.decoder.feed::<RigMessage>(input);
            input = rest;
            match msg {
                Some(RigMessage::Reply(reply)) => self.handle_reply(now, reply),
                Some(RigMessage::Event(event)) => self.handle_event(event),
                None => {}
            }
        }
    }

    fn handle_reply(&mut self, now: Instant, reply: Reply) {
        match self.in_flight.take() {
            Some(f) if f.seq == reply.seq => {
                if !f.internal {
                    self.completions.push_back(Completion {
                        seq: f.seq,
                        outcome: Outcome::Replied(reply.result),
                    });
                }
                self.send_next(now);
            }
            other => {
                self.in_flight = other;
                self.stats.stray_replies += 1;
            }
        }
    }

    fn handle_event(&mut self, event: Event) {
        if let Some(expected) = self.next_event_seq {
            // Wrapping comparison: "behind" means a duplicate of something already delivered.
            let ahead = event.event_seq.wrapping_sub(expected);
            if ahead > u32::MAX / 2 {
                self.stats.duplicate_events += 1;
                return;
            }
            self.stats.lost_events += u64::from(ahead);
        }
        self.next_event_seq = Some(event.event_seq.wrapping_add(1));
        self.events.push_back(event);
    }

    /// Retransmit, give up or send a heartbeat, as due at `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        if let Some(f) = &mut self.in_flight {
            if now.duration_since(f.first_sent) >= self.config.give_up_after {
                let (seq, attempts, internal) = (f.seq, f.attempts, f.internal);
                self.in_flight = None;
                self.stats.timeouts += 1;
                if !internal {
                    self.completions.push_back(Completion {
                        seq,
                        outcome: Outcome::TimedOut { attempts },
                    });
                }
                self.send_next(now);
            } else if now.duration_since(f.last_sent) >= self.config.retransmit_after {
                f.last_sent = now;
                f.attempts += 1;
                self.transmit.push_back(f.frame.clone());
                self.stats.retransmits += 1;
                self.last_activity = now;
            }
            return;
        }
        if self.queue.is_empty()
            && let Some(every) = self.config.heartbeat_every
            && now.duration_since(self.last_activity) >= every
        {
            self.enqueue(now, Command::Heartbeat, true);
        }
    }

    /// When [`ClientCore::handle_timeout`] should next be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match &self.in_flight {
            Some(f) => Some(
                (f.last_sent + self.config.retransmit_after)
                    .min(f.first_sent + self.config.give_up_after),
            ),
            None => self.config.heartbeat_every.map(|e| self.last_activity + e),
        }
    }

    /// The next frame to write to the link.
    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.transmit.pop_front()
    }

    /// The next finished command.
    pub fn poll_completion(&mut self) -> Option<Completion> {
        self.completions.pop_front()
    }

    /// The next rig event, in the order the rig sent them, duplicates removed.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use subsurf_protocol::{
        Captured, EventKind, FrameDecoder, GalvoPoint, encode_event, encode_reply,
    };

    use super::*;

    fn reply_bytes(seq: Seq, result: Result<Response, RigError>) -> Vec<u8> {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode_reply(&Reply { seq, result }, &mut buf).expect("encode");
        buf[..n].to_vec()
    }

    fn event_bytes(event_seq: u32) -> Vec<u8> {
        let event = Event {
            event_seq,
            timestamp_us: 5,
            kind: EventKind::Captured(Captured {
                capture_id: event_seq,
                program_index: None,
                triggered_at_us: 3,
                galvo: GalvoPoint { x: 1, y: 2 },
                channel: 0,
            }),
        };
        let mut buf = [0u8; MAX_FRAME];
        let n = encode_event(&event, &mut buf).expect("encode");
        buf[..n].to_vec()
    }

    fn sent_request(core: &mut ClientCore) -> Request {
        let frame = core.poll_transmit().expect("a frame to send");
        let mut dec = FrameDecoder::new();
        dec.decode::<Request>(&frame).next().expect("a request")
    }

    fn config() -> ClientConfig {
        ClientConfig {
            retransmit_after: Duration::from_millis(10),
            give_up_after: Duration::from_millis(100),
            heartbeat_every: Some(Duration::from_millis(50)),
        }
    }

    #[test]
    fn one_request_at_a_time_in_order() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 7);
        let a = core.start(t0, Command::Status);
        let b = core.start(t0, Command::Arm);
        assert_eq!((a, b), (7, 8));
        assert_eq!(sent_request(&mut core).seq, 7);
        assert!(core.poll_transmit().is_none(), "second waits for the first");
        core.handle_input(t0, &reply_bytes(7, Ok(Response::Ack)));
        assert_eq!(
            core.poll_completion(),
            Some(Completion {
                seq: 7,
                outcome: Outcome::Replied(Ok(Response::Ack))
            })
        );
        let req = sent_request(&mut core);
        assert_eq!((req.seq, req.command), (8, Command::Arm));
    }

    #[test]
    fn retransmits_with_the_same_seq_then_gives_up() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.start(t0, Command::Home);
        let first = core.poll_transmit().expect("sent");
        let mut t = t0;
        let mut resent = 0;
        while core.poll_completion().is_none() {
            t = core.poll_timeout().expect("deadline");
            core.handle_timeout(t);
            while let Some(frame) = core.poll_transmit() {
                assert_eq!(frame, first);
                resent += 1;
            }
            assert!(t <= t0 + Duration::from_secs(1));
        }
        assert_eq!(resent, 9);
        assert_eq!(core.stats().timeouts, 1);
        assert!(t >= t0 + Duration::from_millis(100));
    }

    #[test]
    fn stray_and_duplicate_replies_are_ignored() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.start(t0, Command::Status);
        core.poll_transmit();
        core.handle_input(t0, &reply_bytes(0, Ok(Response::Ack)));
        assert!(core.poll_completion().is_none());
        let r = reply_bytes(1, Err(RigError::Busy));
        core.handle_input(t0, &[r.clone(), r].concat());
        assert_eq!(
            core.poll_completion().map(|c| c.outcome),
            Some(Outcome::Replied(Err(RigError::Busy)))
        );
        assert!(core.poll_completion().is_none());
        assert_eq!(core.stats().stray_replies, 2);
    }

    #[test]
    fn heartbeat_when_idle_and_not_reported() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        assert_eq!(core.poll_timeout(), Some(t0 + Duration::from_millis(50)));
        let t = t0 + Duration::from_millis(50);
        core.handle_timeout(t);
        let req = sent_request(&mut core);
        assert_eq!(req.command, Command::Heartbeat);
        core.handle_input(t, &reply_bytes(req.seq, Ok(Response::Ack)));
        assert!(core.poll_completion().is_none());
        assert_eq!(core.stats().heartbeats, 1);
    }

    #[test]
    fn events_dedup_and_count_gaps_in_any_chunking() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        let stream = [
            event_bytes(10),
            event_bytes(10),
            event_bytes(11),
            event_bytes(14),
        ]
        .concat();
        for byte in &stream {
            core.handle_input(t0, std::slice::from_ref(byte));
        }
        let seqs: Vec<u32> = std::iter::from_fn(|| core.poll_event())
            .map(|e| e.event_seq)
            .collect();
        assert_eq!(seqs, vec![10, 11, 14]);
        let stats = core.stats();
        assert_eq!((stats.duplicate_events, stats.lost_events), (1, 2));
    }

    /// A test double of the rig's reply cache (docs/protocol.md): executes each new `seq` once,
    /// answers the last four again from the cache. Lets the client's retransmission be tested
    /// over a lossy wire without the firmware core.
    struct CachingEcho {
        decoder: FrameDecoder,
        cache: VecDeque<(Seq, Vec<u8>)>,
        executed: Vec<Command>,
    }

    impl CachingEcho {
        fn handle(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
            let mut input = bytes;
            while !input.is_empty() {
                let (req, rest) = self.decoder.feed::<Request>(input);
                input = rest;
                let Some(req) = req else { continue };
                if let Some((_, frame)) = self.cache.iter().find(|(s, _)| *s == req.seq) {
                    out.extend_from_slice(frame);
                    continue;
                }
                self.executed.push(req.command);
                let frame = reply_bytes(req.seq, Ok(Response::Ack));
                out.extend_from_slice(&frame);
                self.cache.push_back((req.seq, frame));
                if self.cache.len() > 4 {
                    self.cache.pop_front();
                }
            }
        }
    }

    #[test]
    fn lossy_wire_every_command_once_in_order() {
        use crate::link::{FaultConfig, VirtualWire};
        let t0 = Instant::now();
        let mut now = t0;
        let cfg = ClientConfig {
            heartbeat_every: None,
            give_up_after: Duration::from_secs(10),
            ..config()
        };
        let mut core = ClientCore::new(cfg, now, u32::MAX - 50);
        let mut rig = CachingEcho {
            decoder: FrameDecoder::new(),
            cache: VecDeque::new(),
            executed: Vec::new(),
        };
        let latency = FaultConfig::lossy(11).with_delay(Duration::from_micros(300), Duration::ZERO);
        let mut to_rig = VirtualWire::new(latency);
        let mut to_host = VirtualWire::new(FaultConfig {
            seed: 12,
            ..latency
        });
        let commands: Vec<Command> = (0..2000u16)
            .map(|i| Command::Galvo(GalvoPoint { x: i, y: 0 }))
            .collect();
        let mut done = 0;
        let mut buf = Vec::new();
        for c in &commands {
            core.start(now, c.clone());
        }
        while done < commands.len() {
            while let Some(frame) = core.poll_transmit() {
                to_rig.send(now, &frame);
            }
            let next = [
                core.poll_timeout(),
                to_rig.next_arrival(),
                to_host.next_arrival(),
            ]
            .into_iter()
            .flatten()
            .min()
            .expect("something pending");
            now = now.max(next);
            buf.clear();
            if to_rig.receive(now, &mut buf) > 0 {
                let mut out = Vec::new();
                rig.handle(&buf, &mut out);
                to_host.send(now, &out);
            }
            buf.clear();
            if to_host.receive(now, &mut buf) > 0 {
                core.handle_input(now, &buf);
            }
            core.handle_timeout(now);
            while let Some(c) = core.poll_completion() {
                assert_eq!(c.outcome, Outcome::Replied(Ok(Response::Ack)));
                done += 1;
            }
        }
        assert_eq!(rig.executed, commands);
        assert!(core.stats().retransmits > 100, "{:?}", core.stats());
        assert!(to_rig.stats().duplicated_frames > 5);
    }
}
