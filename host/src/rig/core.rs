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
//!
//! Events are not acknowledged. The core delivers them in `event_seq` order, each exactly once:
//! it learns where the rig's counter stands from every `Status` reply (and from the events
//! themselves), and when one is missing it holds back the later ones and asks the rig for the
//! missing ones ([`Command::Replay`], an internal request like the heartbeat). Only events the
//! rig no longer keeps are skipped, and counted ([`ClientStats::gone_events`]). Until the first
//! `Status` after a `Hello` tells it the rig's counter, the core delivers no event at all: whatever
//! arrives then belongs to an earlier session.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use subsurf_protocol::{
    Command, DecoderStats, Event, EventReplay, FrameDecoder, MAX_FRAME, REPLAY_BATCH, Reply,
    Request, Response, RigError, RigMessage, Seq, encode_request,
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
// An `Events` reply makes `Replied` a few hundred bytes; completions are few and short-lived, so
// boxing would only add an allocation per request.
#[allow(clippy::large_enum_variant)]
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
    /// Events that did not arrive on their own (gaps in `event_seq`): recovered plus gone.
    pub lost_events: u64,
    /// Lost events delivered after all, from a [`Command::Replay`].
    pub recovered_events: u64,
    /// Lost events the rig no longer kept: skipped, never delivered.
    pub gone_events: u64,
    /// Replay requests sent.
    pub replays: u64,
    /// Events dropped because they came before the session's `Status` (an earlier session's).
    pub stale_events: u64,
    /// What the frame decoder dropped.
    pub decoder: DecoderStats,
}

/// Who started a request: the user (its completion is reported) or the core itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Origin {
    User,
    Heartbeat,
    Replay,
}

/// Most out-of-order events held back while a gap is being recovered; beyond this the gap is
/// given up (counted as gone) so memory stays bounded whatever the rig sends.
const MAX_HELD_EVENTS: usize = 4096;

/// Wrapping distance from `from` forward to `to`, `None` when `to` is behind `from`.
fn ahead(to: u32, from: u32) -> Option<u32> {
    let d = to.wrapping_sub(from);
    (d <= u32::MAX / 2).then_some(d)
}

#[derive(Debug)]
struct InFlight {
    seq: Seq,
    frame: Vec<u8>,
    first_sent: Instant,
    last_sent: Instant,
    attempts: u32,
    /// Only [`Origin::User`] requests report a completion.
    origin: Origin,
}

/// The host side of the protocol, without I/O or clock. See the module documentation.
#[derive(Debug)]
pub struct ClientCore {
    config: ClientConfig,
    decoder: FrameDecoder,
    next_seq: Seq,
    queue: VecDeque<(Seq, Command, Origin)>,
    in_flight: Option<InFlight>,
    transmit: VecDeque<Vec<u8>>,
    completions: VecDeque<Completion>,
    events: VecDeque<Event>,
    /// The next `event_seq` to deliver; `None` until synced with the rig's counter.
    next_event_seq: Option<u32>,
    /// The rig's counter as last heard of (status, replay, or one past the newest event).
    rig_next_event_seq: Option<u32>,
    /// Events that arrived ahead of a gap, by `event_seq`; at most [`MAX_HELD_EVENTS`].
    held: BTreeMap<u32, Event>,
    /// Whether a [`Command::Replay`] is queued or in flight.
    replay_outstanding: bool,
    /// Events to ask for per replay: halved when a replay needed retransmitting (long replies
    /// are what a noisy line loses), doubled up to [`REPLAY_BATCH`] when one got through at once.
    replay_batch: u8,
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
            rig_next_event_seq: None,
            held: BTreeMap::new(),
            replay_outstanding: false,
            replay_batch: REPLAY_BATCH as u8,
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
            lost_events: self.stats.recovered_events + self.stats.gone_events,
            ..self.stats
        }
    }

    /// Whether events the rig has sent are still missing (a replay is under way): a caller that
    /// waits for an event should keep pumping rather than conclude it was lost.
    pub fn recovering_events(&self) -> bool {
        let Some(expected) = self.next_event_seq else {
            return false;
        };
        !self.held.is_empty()
            || self
                .rig_next_event_seq
                .and_then(|n| ahead(n, expected))
                .is_some_and(|d| d > 0)
    }

    /// Whether no command is queued or in flight.
    pub fn is_idle(&self) -> bool {
        self.in_flight.is_none() && self.queue.is_empty()
    }

    /// Queue `command`; returns the sequence number its [`Completion`] will carry.
    pub fn start(&mut self, now: Instant, command: Command) -> Seq {
        self.enqueue(now, command, Origin::User)
    }

    /// Expect the next event to have this `event_seq` (from [`subsurf_protocol::Status`]), so
    /// duplicates and gaps are recognised from the first event on. The core also does this by
    /// itself from the first `Status` reply after a `Hello`.
    pub fn sync_events(&mut self, next_event_seq: u32) {
        self.next_event_seq = Some(next_event_seq);
        self.rig_next_event_seq = Some(next_event_seq);
        self.held.clear();
    }

    /// Forget the event position: a new session (a `Hello` reply) starts unsynced, so nothing
    /// queued from the previous one is delivered.
    fn unsync_events(&mut self) {
        self.next_event_seq = None;
        self.rig_next_event_seq = None;
        self.held.clear();
        self.stats.stale_events += self.events.len() as u64;
        self.events.clear();
    }

    fn enqueue(&mut self, now: Instant, command: Command, origin: Origin) -> Seq {
        let seq = self.next_seq;
        self.next_seq = self.next_seq.wrapping_add(1);
        self.queue.push_back((seq, command, origin));
        self.send_next(now);
        seq
    }

    fn send_next(&mut self, now: Instant) {
        if self.in_flight.is_some() {
            return;
        }
        let Some((seq, command, origin)) = self.queue.pop_front() else {
            return;
        };
        let mut buf = [0u8; MAX_FRAME];
        let frame = match encode_request(&Request { seq, command }, &mut buf) {
            Ok(n) => buf.get(..n).unwrap_or_default().to_vec(),
            // Every command is bounded well below MAX_MESSAGE (protocol invariant); should one
            // not be, it fails like a lost request instead of being sent truncated.
            Err(_) => {
                self.stats.timeouts += 1;
                self.report_timeout(seq, 0, origin);
                return self.send_next(now);
            }
        };
        self.transmit.push_back(frame.clone());
        self.stats.requests += 1;
        match origin {
            Origin::Heartbeat => self.stats.heartbeats += 1,
            Origin::Replay => self.stats.replays += 1,
            Origin::User => {}
        }
        self.last_activity = now;
        self.in_flight = Some(InFlight {
            seq,
            frame,
            first_sent: now,
            last_sent: now,
            attempts: 1,
            origin,
        });
    }

    fn report_timeout(&mut self, seq: Seq, attempts: u32, origin: Origin) {
        match origin {
            Origin::User => self.completions.push_back(Completion {
                seq,
                outcome: Outcome::TimedOut { attempts },
            }),
            // Asked again by `handle_timeout` while the gap persists.
            Origin::Replay => self.replay_outstanding = false,
            Origin::Heartbeat => {}
        }
    }

    /// Bytes received from the rig, in any chunking.
    pub fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        let mut input = bytes;
        while !input.is_empty() {
            let (msg, rest) = self.decoder.feed::<RigMessage>(input);
            input = rest;
            match msg {
                Some(RigMessage::Reply(reply)) => self.handle_reply(now, reply),
                Some(RigMessage::Event(event)) => {
                    self.accept_event(event, false);
                    self.request_replay_if_needed(now);
                }
                None => {}
            }
        }
    }

    fn handle_reply(&mut self, now: Instant, reply: Reply) {
        match self.in_flight.take() {
            Some(f) if f.seq == reply.seq => {
                if f.origin == Origin::Replay {
                    self.replay_batch = if f.attempts > 1 {
                        (self.replay_batch / 2).max(1)
                    } else {
                        self.replay_batch.saturating_mul(2).min(REPLAY_BATCH as u8)
                    };
                }
                self.observe_reply(f.origin, &reply.result);
                if f.origin == Origin::User {
                    self.completions.push_back(Completion {
                        seq: f.seq,
                        outcome: Outcome::Replied(reply.result),
                    });
                }
                self.request_replay_if_needed(now);
                self.send_next(now);
            }
            other => {
                self.in_flight = other;
                self.stats.stray_replies += 1;
            }
        }
    }

    /// What a reply tells the event machinery: a `Hello` starts a new session, a `Status` syncs
    /// or reveals missing events, an `Events` reply delivers them.
    fn observe_reply(&mut self, origin: Origin, result: &Result<Response, RigError>) {
        match result {
            // A new session, or a rig that reset without one (its event counter restarted):
            // either way the old position is meaningless and the next `Status` syncs it.
            Ok(Response::Hello(_)) | Err(RigError::NoSession) => self.unsync_events(),
            Ok(Response::Status(status)) => match self.next_event_seq {
                None => self.sync_events(status.next_event_seq),
                Some(_) => self.note_rig_counter(status.next_event_seq),
            },
            Ok(Response::Events(replay)) => self.handle_replay(replay),
            _ => {}
        }
        if origin == Origin::Replay {
            self.replay_outstanding = false;
            if !matches!(result, Ok(Response::Events(_))) {
                // A rig that cannot replay (it refused): what is missing stays missing.
                if let Some(target) = self.rig_next_event_seq {
                    self.skip_to(target);
                }
            }
        }
    }

    /// The rig's counter is at least `next`.
    fn note_rig_counter(&mut self, next: u32) {
        match self.rig_next_event_seq {
            Some(known) if ahead(next, known).is_none() => {}
            _ => self.rig_next_event_seq = Some(next),
        }
    }

    /// One event from the link (`replayed = false`) or from a replay: delivered if it is the next
    /// one, held if it is ahead of a gap, ignored if it was delivered already.
    fn accept_event(&mut self, event: Event, replayed: bool) {
        let Some(expected) = self.next_event_seq else {
            self.stats.stale_events += 1;
            return;
        };
        self.note_rig_counter(event.event_seq.wrapping_add(1));
        match ahead(event.event_seq, expected) {
            None => self.stats.duplicate_events += 1,
            Some(0) => {
                if replayed {
                    self.stats.recovered_events += 1;
                }
                self.deliver(event);
            }
            Some(_) => {
                if self.held.contains_key(&event.event_seq) {
                    self.stats.duplicate_events += 1;
                    return;
                }
                if replayed {
                    self.stats.recovered_events += 1;
                }
                self.held.insert(event.event_seq, event);
                if self.held.len() > MAX_HELD_EVENTS {
                    // Bounded memory: give up the oldest gap.
                    if let Some(first) = self.first_held() {
                        self.skip_to(first);
                    }
                }
            }
        }
    }

    /// Deliver `event` (the expected one) and every held event that now follows on.
    fn deliver(&mut self, event: Event) {
        let mut next = event.event_seq.wrapping_add(1);
        self.events.push_back(event);
        while let Some(e) = self.held.remove(&next) {
            self.events.push_back(e);
            next = next.wrapping_add(1);
        }
        self.next_event_seq = Some(next);
    }

    /// The held event nearest after the expected one.
    fn first_held(&self) -> Option<u32> {
        let expected = self.next_event_seq?;
        self.held
            .keys()
            .copied()
            .min_by_key(|k| k.wrapping_sub(expected))
    }

    /// Give up every missing event before `target` (counted as gone); held ones are delivered.
    fn skip_to(&mut self, target: u32) {
        while let Some(expected) = self.next_event_seq {
            let Some(gap) = ahead(target, expected).filter(|d| *d > 0) else {
                return;
            };
            match self.first_held() {
                Some(h) if h.wrapping_sub(expected) < gap => {
                    self.stats.gone_events += u64::from(h.wrapping_sub(expected));
                    if let Some(e) = self.held.remove(&h) {
                        self.deliver(e);
                    }
                }
                _ => {
                    self.stats.gone_events += u64::from(gap);
                    self.next_event_seq = Some(target);
                    if let Some(e) = self.held.remove(&target) {
                        self.deliver(e);
                    }
                    return;
                }
            }
        }
    }

    fn handle_replay(&mut self, replay: &EventReplay) {
        let Some(before) = self.next_event_seq else {
            return;
        };
        // The rig's own word on its counter replaces what we inferred (it may have restarted).
        if ahead(replay.next_event_seq, before).is_none() {
            self.sync_events(replay.next_event_seq);
            return;
        }
        self.rig_next_event_seq = Some(replay.next_event_seq);
        // Nothing can be held from beyond the rig's counter (a corrupted-yet-valid frame).
        self.held
            .retain(|k, _| ahead(replay.next_event_seq, *k).is_some_and(|d| d > 0));
        // Events before the rig's oldest kept one are gone.
        if ahead(replay.oldest, before).is_some() {
            self.skip_to(replay.oldest);
        }
        for event in &replay.events {
            self.accept_event(event.clone(), true);
        }
        if self.next_event_seq == Some(before) {
            // No progress although the rig says more exist: never loop on a confused rig.
            self.skip_to(replay.next_event_seq);
        }
    }

    /// Ask the rig for the events missing before the held ones or before its counter.
    fn request_replay_if_needed(&mut self, now: Instant) {
        if self.replay_outstanding || !self.recovering_events() {
            return;
        }
        let Some(since) = self.next_event_seq else {
            return;
        };
        self.replay_outstanding = true;
        // Queued like any request: sequence numbers must reach the rig in increasing order.
        let max = self.replay_batch;
        self.enqueue(now, Command::Replay { since, max }, Origin::Replay);
    }

    /// Retransmit, give up or send a heartbeat, as due at `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        if let Some(f) = &mut self.in_flight {
            if now.duration_since(f.first_sent) >= self.config.give_up_after {
                let (seq, attempts, origin) = (f.seq, f.attempts, f.origin);
                self.in_flight = None;
                self.stats.timeouts += 1;
                self.report_timeout(seq, attempts, origin);
                self.request_replay_if_needed(now);
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
            self.enqueue(now, Command::Heartbeat, Origin::Heartbeat);
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
        let event = event(event_seq);
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

    fn event(event_seq: u32) -> Event {
        Event {
            event_seq,
            timestamp_us: 5,
            kind: EventKind::Captured(Captured {
                capture_id: event_seq,
                program_index: None,
                triggered_at_us: 3,
                exposure: None,
                exposure_count: 0,
                lit: false,
                galvo: GalvoPoint { x: 1, y: 2 },
                channel: 0,
            }),
        }
    }

    fn replay_bytes(seq: Seq, oldest: u32, next: u32, events: &[u32]) -> Vec<u8> {
        let mut batch = heapless::Vec::new();
        for &e in events {
            batch.push(event(e)).expect("batch size");
        }
        reply_bytes(
            seq,
            Ok(Response::Events(EventReplay {
                oldest,
                next_event_seq: next,
                events: batch,
            })),
        )
    }

    fn delivered(core: &mut ClientCore) -> Vec<u32> {
        std::iter::from_fn(|| core.poll_event())
            .map(|e| e.event_seq)
            .collect()
    }

    #[test]
    fn events_before_sync_are_stale_after_sync_deduplicated_in_any_chunking() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.handle_input(t0, &event_bytes(3));
        assert!(
            delivered(&mut core).is_empty(),
            "unsynced: an earlier session's"
        );
        core.sync_events(10);
        let stream = [
            event_bytes(9),
            event_bytes(10),
            event_bytes(10),
            event_bytes(11),
        ]
        .concat();
        for byte in &stream {
            core.handle_input(t0, std::slice::from_ref(byte));
        }
        assert_eq!(delivered(&mut core), vec![10, 11]);
        let stats = core.stats();
        assert_eq!((stats.stale_events, stats.duplicate_events), (1, 2));
        assert_eq!((stats.lost_events, stats.replays), (0, 0));
        assert!(core.poll_transmit().is_none(), "no gap, no replay");
    }

    #[test]
    fn a_gap_is_replayed_and_delivered_in_order_exactly_once() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.sync_events(10);
        core.handle_input(
            t0,
            &[event_bytes(10), event_bytes(13), event_bytes(14)].concat(),
        );
        assert_eq!(
            delivered(&mut core),
            vec![10],
            "13 and 14 wait for 11 and 12"
        );
        assert!(core.recovering_events());
        let req = sent_request(&mut core);
        assert_eq!(req.command, Command::Replay { since: 11, max: 3 });
        // A retransmitted 13 meanwhile is still only one 13.
        core.handle_input(t0, &event_bytes(13));
        core.handle_input(t0, &replay_bytes(req.seq, 2, 15, &[11, 12, 13]));
        assert_eq!(delivered(&mut core), vec![11, 12, 13, 14]);
        assert!(!core.recovering_events());
        assert!(core.poll_completion().is_none(), "internal request");
        let stats = core.stats();
        assert_eq!((stats.recovered_events, stats.gone_events), (2, 0));
        assert_eq!((stats.lost_events, stats.duplicate_events), (2, 2));
        assert!(core.poll_transmit().is_none());
    }

    #[test]
    fn a_status_reveals_a_lost_last_event_and_long_gaps_take_several_replays() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        let s = core.start(t0, Command::Status);
        sent_request(&mut core);
        let mut status = crate::sim::VirtualRig::new(crate::sim::SimParams::default()).status();
        status.next_event_seq = 20;
        core.handle_input(t0, &reply_bytes(s, Ok(Response::Status(status))));
        assert!(core.poll_completion().is_some());
        assert!(!core.recovering_events(), "the first status syncs");
        // Nothing arrives, but the next status says eight events were sent.
        let s = core.start(t0, Command::Status);
        sent_request(&mut core);
        status.next_event_seq = 28;
        core.handle_input(t0, &reply_bytes(s, Ok(Response::Status(status))));
        core.poll_completion();
        let req = sent_request(&mut core);
        assert_eq!(req.command, Command::Replay { since: 20, max: 3 });
        // The rig keeps only from 22 on: 20 and 21 are gone.
        core.handle_input(t0, &replay_bytes(req.seq, 22, 28, &[22, 23, 24]));
        let req = sent_request(&mut core);
        assert_eq!(req.command, Command::Replay { since: 25, max: 3 });
        core.handle_input(t0, &replay_bytes(req.seq, 22, 28, &[25, 26, 27]));
        assert_eq!(delivered(&mut core), (22..28).collect::<Vec<_>>());
        let stats = core.stats();
        assert_eq!((stats.gone_events, stats.recovered_events), (2, 6));
        assert_eq!(stats.replays, 2);
        assert!(!core.recovering_events());
    }

    #[test]
    fn a_hello_starts_a_new_session_without_the_old_events() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.sync_events(0);
        core.handle_input(t0, &event_bytes(0));
        let h = core.start(
            t0,
            Command::Hello {
                protocol_version: 2,
            },
        );
        sent_request(&mut core);
        let hello = subsurf_protocol::Hello {
            protocol_version: 2,
            firmware_version: subsurf_protocol::FirmwareVersion {
                major: 0,
                minor: 1,
                patch: 0,
            },
            boot_nonce: 1,
            capabilities: subsurf_protocol::Capabilities {
                steps_per_rev: 3200,
                galvo_max: 4095,
                laser_channels: 1,
                max_speed: 1000,
                max_accel: 1000,
                max_exposure_us: 1000,
                min_exposure_us: 20,
                camera_readout_us: 0,
                max_program_points: 10,
            },
        };
        core.handle_input(t0, &reply_bytes(h, Ok(Response::Hello(hello))));
        core.handle_input(t0, &event_bytes(1));
        assert!(delivered(&mut core).is_empty());
        assert_eq!(core.stats().stale_events, 2);
    }

    /// A rig that reset: its counter restarts at 0. Once the host knows (a `NoSession` refusal),
    /// the new session's events are delivered, none dropped as duplicates of the old ones.
    #[test]
    fn after_a_reboot_the_new_sessions_events_are_not_duplicates() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.sync_events(0);
        for i in 0..40 {
            core.handle_input(t0, &event_bytes(i));
        }
        assert_eq!(delivered(&mut core).len(), 40);
        let h = core.start(t0, Command::Heartbeat);
        sent_request(&mut core);
        core.handle_input(t0, &reply_bytes(h, Err(RigError::NoSession)));
        let s = core.start(t0, Command::Status);
        sent_request(&mut core);
        let mut status = crate::sim::VirtualRig::new(crate::sim::SimParams::default()).status();
        status.next_event_seq = 0;
        status.boot_nonce = 2;
        core.handle_input(t0, &reply_bytes(s, Ok(Response::Status(status))));
        for i in 0..3 {
            core.handle_input(t0, &event_bytes(i));
        }
        assert_eq!(delivered(&mut core), vec![0, 1, 2]);
        assert_eq!(core.stats().duplicate_events, 0);
    }

    #[test]
    fn a_rig_that_cannot_replay_ends_the_recovery() {
        let t0 = Instant::now();
        let mut core = ClientCore::new(config(), t0, 1);
        core.sync_events(0);
        core.handle_input(t0, &event_bytes(3));
        let req = sent_request(&mut core);
        core.handle_input(t0, &reply_bytes(req.seq, Err(RigError::OutOfRange)));
        assert_eq!(delivered(&mut core), vec![3]);
        assert_eq!(core.stats().gone_events, 3);
        assert!(!core.recovering_events());
    }

    /// Answers every request the core sent: `Replay` from a history that keeps events from
    /// `oldest` on, anything else with `Ack`. Returns whether anything was answered.
    fn answer_replays(core: &mut ClientCore, t: Instant, oldest: u32, next: u32) -> bool {
        let mut any = false;
        while let Some(frame) = core.poll_transmit() {
            any = true;
            let mut dec = FrameDecoder::new();
            let req: Request = dec.decode(&frame).next().expect("a request");
            let bytes = match req.command {
                Command::Replay { since, max } => {
                    let from = since.max(oldest);
                    let to = next.min(from + u32::from(max.max(1)).min(REPLAY_BATCH as u32));
                    let ids: Vec<u32> = (from..to).collect();
                    replay_bytes(req.seq, oldest, next, &ids)
                }
                _ => reply_bytes(req.seq, Ok(Response::Ack)),
            };
            core.handle_input(t, &bytes);
        }
        any
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(1024))]

        /// Whatever subset of the events arrives, duplicated anywhere, the caller gets each one
        /// exactly once and in order; those older than the rig's history are counted as gone
        /// and nothing else is skipped.
        #[test]
        fn any_loss_pattern_is_recovered_in_order_exactly_once(
            n in 1u32..120,
            fate in proptest::collection::vec(0u8..10, 120),
            kept in 1u32..60,
        ) {
            let t0 = Instant::now();
            let mut core = ClientCore::new(config(), t0, 1);
            core.sync_events(0);
            let mut delivered_seqs = Vec::new();
            for i in 0..n {
                let oldest = (i + 1).saturating_sub(kept);
                // 0..3: lost; 3: duplicated; else arrives once.
                match fate[i as usize] {
                    0..=2 => {}
                    3 => core.handle_input(t0, &[event_bytes(i), event_bytes(i)].concat()),
                    _ => core.handle_input(t0, &event_bytes(i)),
                }
                while answer_replays(&mut core, t0, oldest, i + 1) {}
                delivered_seqs.extend(std::iter::from_fn(|| core.poll_event()).map(|e| e.event_seq));
            }
            // The last events may have been lost with nothing after them: a status tells.
            let s = core.start(t0, Command::Status);
            sent_request(&mut core);
            let mut status = crate::sim::VirtualRig::new(crate::sim::SimParams::default()).status();
            status.next_event_seq = n;
            core.handle_input(t0, &reply_bytes(s, Ok(Response::Status(status))));
            while answer_replays(&mut core, t0, n.saturating_sub(kept), n) {}
            delivered_seqs.extend(std::iter::from_fn(|| core.poll_event()).map(|e| e.event_seq));
            let stats = core.stats();
            proptest::prop_assert!(!core.recovering_events());
            proptest::prop_assert!(delivered_seqs.windows(2).all(|w| w[0] < w[1]), "{:?}", delivered_seqs);
            proptest::prop_assert_eq!(delivered_seqs.len() as u64 + stats.gone_events, u64::from(n));
            let lost = fate[..n as usize].iter().filter(|f| **f < 3).count() as u64;
            proptest::prop_assert_eq!(stats.lost_events, lost);
            // Exactly the events the rig no longer held when the client learnt of them are gone
            // (replies are never lost here): a run of losses is revealed by the next arrival i,
            // when the history starts at i + 1 − kept, or by the final status, when it starts
            // at n − kept; whatever of the run lies before that start is gone, the rest replayed.
            let mut gone = 0u64;
            let mut run: Option<u32> = None;
            for i in 0..n {
                if fate[i as usize] < 3 {
                    run.get_or_insert(i);
                } else if let Some(start) = run.take() {
                    gone += u64::from((i + 1).saturating_sub(kept).saturating_sub(start));
                }
            }
            if let Some(start) = run {
                gone += u64::from(n.saturating_sub(kept).saturating_sub(start));
            }
            proptest::prop_assert_eq!(stats.gone_events, gone, "{:?}", stats);
        }
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
