//! Steps planned ahead: a motion's ideal step times go in, compressed [`StepSegment`]s go to the
//! hardware's step queue some milliseconds before they are due, and the steps the hardware has
//! emitted by now come back out as position, counted from the same segment arithmetic the
//! hardware uses (so core and timer agree step for step, without the hardware reporting).
//!
//! This is grbl's split (the interrupt executes, it never plans; a planner keeps a buffer filled
//! ahead of it) with Klipper's compression ([`crate::stepcompress`]): the rig task wakes every few
//! milliseconds to top the queue up to [`PLAN_AHEAD_US`] ahead, never once per step.

use heapless::Deque;

use crate::hal::StepSegment;
use crate::rig::Micros;
use crate::stepcompress::{MAX_STEP_ERROR_US, compress};

/// Steps are handed to the hardware up to this far ahead of their time, µs. A decelerating stop
/// starts after them, so this is also how long a stop may take to begin.
pub const PLAN_AHEAD_US: Micros = 10_000;

/// The queue is topped up once less than this much of it is left, µs (so the task wakes about
/// every `PLAN_AHEAD_US - REFILL_AT_US` while a move runs, not once per step).
pub const REFILL_AT_US: Micros = 5_000;

/// Ideal step times kept ahead of the compressor: the longest run it can find.
pub const PENDING: usize = 256;

/// Segments handed to the hardware and not yet all emitted (the hardware's queue must hold this
/// many).
pub const IN_FLIGHT: usize = 32;

/// The planner's state between wakes.
#[derive(Debug)]
pub struct StepPlanner {
    /// Ideal times (ticks) of the next steps not yet handed to the hardware.
    pending: Pending,
    /// Segments handed to the hardware whose steps are not all due yet, oldest first.
    in_flight: Deque<StepSegment, IN_FLIGHT>,
    /// Steps of the front segment already counted as done.
    front_done: u16,
    /// When the last planned step comes (its segment's time), ticks.
    last_at: u64,
    /// The ideal time of the last step put into `pending`, ticks (ideal times are kept strictly
    /// increasing: the profile is monotone only up to a µs of rounding).
    last_ideal: u64,
    ticks_per_us: u64,
    /// Shortest gap the hardware emits, ticks.
    min_gap: u64,
}

impl StepPlanner {
    /// An idle planner for a step clock of `ticks_per_us`, never placing two steps closer than
    /// `min_gap_us`.
    pub fn new(ticks_per_us: u32, min_gap_us: u32) -> Self {
        let ticks_per_us = u64::from(ticks_per_us.max(1));
        Self {
            pending: Pending::new(),
            in_flight: Deque::new(),
            front_done: 0,
            last_at: 0,
            last_ideal: 0,
            ticks_per_us,
            min_gap: u64::from(min_gap_us) * ticks_per_us,
        }
    }

    /// Change the shortest gap (a new profile's STEP pulse); only while idle.
    pub fn set_min_gap_us(&mut self, min_gap_us: u32) {
        self.min_gap = u64::from(min_gap_us) * self.ticks_per_us;
    }

    /// Rig time in ticks.
    pub fn ticks(&self, t: Micros) -> u64 {
        t.saturating_mul(self.ticks_per_us)
    }

    /// No step is queued in the hardware or waiting in the buffer.
    pub fn idle(&self) -> bool {
        self.in_flight.is_empty() && self.pending.is_empty()
    }

    /// Ideal step times computed but not yet handed to the hardware.
    pub fn pending_len(&self) -> usize {
        self.pending.as_slice().len()
    }

    /// Every planned step is due.
    pub fn drained(&self) -> bool {
        self.in_flight.is_empty()
    }

    /// Forget the ideal times not yet planned (the motion changed course).
    pub fn clear_pending(&mut self) {
        self.pending.clear();
        self.last_ideal = self.last_at;
    }

    /// When the planner must run again to keep the hardware fed (µs), if steps are waiting: when
    /// the next one comes within [`REFILL_AT_US`] of its time, or (every slot taken) when the
    /// oldest segment in flight has been emitted.
    pub fn refill_at(&self) -> Option<Micros> {
        let next = self.pending.front()?;
        let at = (next / self.ticks_per_us).saturating_sub(PLAN_AHEAD_US - REFILL_AT_US);
        match self.in_flight.front() {
            Some(s) if self.in_flight.is_full() => {
                Some(at.max(s.last_at().div_ceil(self.ticks_per_us)))
            }
            _ => Some(at),
        }
    }

    /// When the last planned step is due (µs), if any is in flight.
    pub fn last_due(&self) -> Option<Micros> {
        self.in_flight
            .back()
            .map(|s| s.last_at().div_ceil(self.ticks_per_us))
    }

    /// Plan ahead: top the buffer up from `ideal` (the motion's next ideal step times, µs, `None`
    /// at its end), then hand every run whose first step is due by `now + PLAN_AHEAD_US` to
    /// `queue` (the hardware; `false` = its queue is full). Returns the steps planned.
    pub fn refill(
        &mut self,
        now: Micros,
        forward: bool,
        ideal: &mut dyn FnMut() -> Option<Micros>,
        queue: &mut dyn FnMut(StepSegment) -> bool,
    ) -> u32 {
        let horizon = self.ticks(now.saturating_add(PLAN_AHEAD_US));
        let err = MAX_STEP_ERROR_US * self.ticks_per_us;
        let mut planned = 0u32;
        // Bounded: every pass plans at least one step or stops.
        for _ in 0..PENDING * 4 {
            while !self.pending.is_full() {
                let Some(t) = ideal() else { break };
                let t = self.ticks(t).max(self.last_ideal.saturating_add(1));
                self.last_ideal = t;
                self.pending.push(t);
            }
            let points = self.pending.as_slice();
            let Some(&first) = points.first() else { break };
            if first > horizon || self.in_flight.is_full() {
                break;
            }
            // Only the steps inside the horizon: a stop must not wait behind a long run.
            let within = points.iter().take_while(|&&t| t <= horizon).count().max(1);
            let run = compress(
                points.get(..within).unwrap_or(points),
                self.last_at,
                err,
                self.min_gap,
            );
            let first_at = self.last_at.saturating_add(run.interval);
            let segment = StepSegment {
                first_at,
                interval: if run.count > 1 {
                    u32::try_from(i64::try_from(run.interval).unwrap_or(0) + i64::from(run.add))
                        .unwrap_or(u32::MAX)
                } else {
                    0
                },
                add: run.add,
                count: run.count,
                forward,
            };
            if !queue(segment) {
                break;
            }
            // Cannot fail: checked for room above.
            let _ = self.in_flight.push_back(segment);
            self.last_at = segment.last_at();
            self.pending.consume(usize::from(run.count));
            planned = planned.saturating_add(u32::from(run.count));
        }
        planned
    }

    /// Steps that have come due since the last call (by `now`).
    pub fn take_due(&mut self, now: Micros) -> u32 {
        let t = self.ticks(now);
        let mut done = 0u32;
        while let Some(front) = self.in_flight.front() {
            let due = front.due_by(t);
            done += u32::from(due.saturating_sub(self.front_done));
            if due < front.count {
                self.front_done = due;
                break;
            }
            self.in_flight.pop_front();
            self.front_done = 0;
        }
        done
    }

    /// The hardware dropped `dropped` queued steps (a flush at `now`): everything in flight is
    /// gone, and the last step the motor really took came no later than `now` (not at the last
    /// planned step's time, which may lie ahead). Returns the steps it did emit that were not
    /// counted yet.
    pub fn flushed(&mut self, dropped: u32, now: Micros) -> u32 {
        let mut left = 0u32;
        for (i, s) in self.in_flight.iter().enumerate() {
            let done = if i == 0 { self.front_done } else { 0 };
            left = left.saturating_add(u32::from(s.count.saturating_sub(done)));
        }
        self.in_flight.clear();
        self.front_done = 0;
        self.last_at = self.last_at.min(self.ticks(now));
        self.clear_pending();
        left.saturating_sub(dropped)
    }
}

/// A fixed buffer of ideal step times consumed from the front, compacted when it fills.
#[derive(Debug)]
struct Pending {
    buf: [u64; PENDING],
    start: usize,
    end: usize,
}

impl Pending {
    const fn new() -> Self {
        Self {
            buf: [0; PENDING],
            start: 0,
            end: 0,
        }
    }

    fn is_empty(&self) -> bool {
        self.start == self.end
    }

    fn is_full(&self) -> bool {
        self.end - self.start == PENDING
    }

    fn clear(&mut self) {
        self.start = 0;
        self.end = 0;
    }

    fn front(&self) -> Option<u64> {
        self.as_slice().first().copied()
    }

    fn as_slice(&self) -> &[u64] {
        self.buf.get(self.start..self.end).unwrap_or(&[])
    }

    fn push(&mut self, t: u64) {
        if self.end == PENDING && self.start > 0 {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        if let Some(slot) = self.buf.get_mut(self.end) {
            *slot = t;
            self.end += 1;
        }
    }

    fn consume(&mut self, n: usize) {
        self.start = (self.start + n).min(self.end);
        if self.start == self.end {
            self.clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::profile::Profile;
    use std::vec::Vec;

    fn plan_move(p: &mut StepPlanner, start: Micros, steps: u32) -> Vec<StepSegment> {
        let profile = Profile::new(steps, 5_000, 50_000).unwrap();
        let mut k = 0;
        let mut out = Vec::new();
        p.refill(
            start,
            true,
            &mut || {
                k += 1;
                (k <= steps).then(|| start + profile.step_time_us(k))
            },
            &mut |s| {
                out.push(s);
                true
            },
        );
        out
    }

    /// A flush drops steps planned ahead; the next motion starts from now, not from the last
    /// dropped step (which lay in the future): its steps are on time and in order.
    #[test]
    fn after_a_flush_the_next_motion_plans_from_now() {
        let mut p = StepPlanner::new(84, 10);
        let first = plan_move(&mut p, 0, 400);
        assert!(!first.is_empty());
        // At 10 ms, steps up to 20 ms are queued; flush them.
        let planned: u32 = first.iter().map(|s| u32::from(s.count)).sum();
        p.take_due(10_000);
        p.flushed(planned / 2, 10_000);
        assert!(p.idle());
        let next = plan_move(&mut p, 10_000, 3);
        let at = next.first().expect("planned").first_at;
        // The move's first step: sqrt(2/a) = 6325 µs after its start, within the error.
        assert!((16_320 * 84..=16_325 * 84).contains(&at), "{at}");
    }
}
