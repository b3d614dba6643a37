//! The step timer's bookkeeping, free of registers so host tests run it against a model of the
//! timer (`firmware/tests/pulse_train.rs`) and the QEMU benchmark counts its instructions on a
//! Cortex-M4 (`src/bin/qemu_isr/main.rs`); both include this file through `#[path]`.
//!
//! Timer model (TIM2 in PWM mode 2, up-counting at [`TICKS_PER_US`] ticks per µs, ARR and CCR
//! preloaded): a period of `len` ticks runs the counter `0..len`; the output is high while
//! `counter >= ccr`, so a step period (`ccr = len - pulse`) ends with a STEP pulse and a blank
//! period (`ccr` above `len`) has none. At each update event (counter wrap) the preloaded
//! `arr`/`ccr` become active and the interrupt runs [`on_interrupt`].
//!
//! The core plans the steps ahead and compresses them into [`StepSegment`]s (Klipper's
//! `queue_step`: the first step at its time, then gaps of `interval`, `interval + add`, ...); the
//! rig task queues them here some milliseconds before they are due. The interrupt only emits: per
//! step it counts the step that ended, sets DIR, and preloads the period after next from the
//! segment being expanded (`len = next; next = gap; gap += add`). Its cost per step is measured in
//! instructions on a Cortex-M4 under QEMU (BENCHMARKS.md).
//!
//! Time: the train keeps the absolute time (ticks of the rig clock's PLL) at which its last
//! queued period ends, so a segment's first step lands exactly where the core put it, however late
//! the task queued it. A step that cannot be placed on time (the queue ran dry mid-motion because
//! the task was late by more than the planning horizon, the queue is full, or a reversal leaves
//! DIR less than its set-up time) is a stall: it is counted ([`PulseTrain::take_stalls`]) and the
//! rig faults instead of moving the motor off schedule without anyone knowing.
use heapless::Deque;
use subsurf_firmware::hal::StepSegment;

/// Timer ticks per µs: TIM2 counts its input clock (APB1 42 MHz × 2 = 84 MHz) undivided. The
/// core plans in the same ticks (`Stepper::TICKS_PER_US`).
pub const TICKS_PER_US: u32 = 84;
/// Default STEP high time, µs. Bare STEP/DIR drivers need 0.1–2 µs; opto-isolated inputs (the
/// common DM542/TB6600 class) need 2.5–5 µs, so 5 µs is the default.
pub const DEFAULT_PULSE_US: u32 = 5;
/// Accepted STEP high times, µs (the rig profile refuses others).
pub const PULSE_US_RANGE: core::ops::RangeInclusive<u32> = 2..=50;
/// Shortest period the interrupt keeps up with, µs: it has to write the preloads within one
/// period. The core's `MIN_STEP_GAP_US`.
pub const MIN_PERIOD_US: u32 = 10;
/// DIR is written by the interrupt at the start of the period that ends with the step; it may run
/// this late, which the DIR set-up must leave room for.
pub const DIR_LATENCY_US: u32 = 2;
/// Longest period, ticks (25 s; a longer pause between two steps idles the timer instead).
pub const MAX_PERIOD_TICKS: u32 = 0x7fff_ffff;
/// Queued segments: the core keeps at most 32 in flight (`planner::IN_FLIGHT`).
pub const QUEUE_LEN: usize = 32;

/// A segment as the interrupt expands it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Segment {
    /// Period before the first step, ticks.
    first: u32,
    /// Period before the second step, ticks.
    interval: u32,
    /// Change of the period from one step to the next, ticks.
    add: i32,
    /// Steps (≥ 1).
    count: u16,
    /// Direction of every step.
    forward: bool,
}

/// What one timer period does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Period {
    /// Ends with a pulse in this direction; lasts `len` ticks.
    Step {
        /// Direction.
        forward: bool,
        /// Period length, ticks.
        len: u32,
    },
    /// No pulse; the timer stops at its start unless steps arrived meanwhile.
    Blank,
}

const BLANK_TICKS: u32 = MIN_PERIOD_US * TICKS_PER_US;

/// Values for the timer's preload registers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Preload {
    /// Auto-reload (period length − 1).
    pub arr: u32,
    /// Compare value (the pulse starts when the counter reaches it).
    pub ccr: u32,
}

/// What the update interrupt must do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Update {
    /// The period that just ended carried a pulse (one step done).
    pub stepped: bool,
    /// Set DIR to this for the period that starts now.
    pub dir: Option<bool>,
    /// Write these preloads (the period after the one starting now); `None` = stop the counter.
    pub preload: Option<Preload>,
}

/// What [`PulseTrain::push`] needs done to the timer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Push {
    /// Queued; the interrupt will load it.
    Queued,
    /// The queue is full: nothing changed (counted as a stall).
    Full,
    /// The timer was idle: set DIR, load `first` into the active registers (update generation),
    /// then `next` into the preloads, and start counting from 0.
    Start {
        /// DIR for the first period.
        dir: bool,
        /// The first period.
        first: Preload,
        /// The period after it.
        next: Preload,
    },
}

/// Segment being expanded by the interrupt.
#[derive(Clone, Copy, Debug)]
struct Expanding {
    /// The next period, ticks.
    next: u32,
    /// The one after it.
    gap: u32,
    add: i32,
    left: u16,
    forward: bool,
}

/// Queue and period state shared by the interrupt and the feeding task.
#[derive(Debug)]
pub struct PulseTrain {
    queue: Deque<Segment, QUEUE_LEN>,
    expanding: Option<Expanding>,
    running: bool,
    current: Period,
    next: Period,
    pulse_ticks: u32,
    dir_setup_ticks: u32,
    /// Absolute time (ticks) at which the last queued period ends.
    end_at: u64,
    /// Direction of the last queued step.
    last_forward: bool,
    stalls: u32,
    /// The hardware's update count ([`StepTimer::updates`]) at the end of the last interrupt, or
    /// at the start ([`PulseTrain::started`]); `None` before any start.
    last_seen: Option<u16>,
    /// Interrupts that came after the next update event had already happened.
    overruns: u32,
}

impl Default for PulseTrain {
    fn default() -> Self {
        Self::new()
    }
}

/// The step timer's registers as the update interrupt touches them: the board's TIM2 and DIR pin,
/// or a model (host tests, the QEMU benchmark).
pub trait StepTimer {
    /// Whether an update event is pending; clears the flag.
    fn take_update(&mut self) -> bool;
    /// Drive DIR for the period that starts now.
    fn set_dir(&mut self, forward: bool);
    /// Write the preload registers (the period after the one that starts now).
    fn preload(&mut self, preload: Preload);
    /// Stop the counter.
    fn stop(&mut self);
    /// Update events the hardware itself counted since the timer started, wrapping (the board:
    /// TIM4 clocked by TIM2's update TRGO, RM0390 §17.3.15 "Timer synchronization").
    fn updates(&mut self) -> u16;
}

/// The step timer as a start touches it (the board's TIM2, or a model in the host tests).
pub trait StartTimer: StepTimer {
    /// The timer is idle: set DIR, load `first` into the active registers (an update
    /// generation, which the hardware's update count may count too) and `next` into the
    /// preloads, the output in its pulse mode; the counter not running yet.
    fn load(&mut self, dir: bool, first: Preload, next: Preload);
    /// Start counting from 0.
    fn run(&mut self);
}

/// Queue `segment` (the rig task, with interrupts masked): into the train, and when the timer
/// was idle, start it. A start takes the hardware's update count as the baseline of the overrun
/// check *before* the counter runs, so the first interrupt after it is checked like every other:
/// one that comes only after the second update event (the first period replayed on stale
/// preloads) is an overrun. Without the baseline the first interrupt would only take the count,
/// and a late one would pass unseen. `false` when the queue is full.
pub fn queue(
    train: &mut PulseTrain,
    timer: &mut impl StartTimer,
    segment: &StepSegment,
    now: u64,
) -> bool {
    match train.push(segment, now) {
        Push::Queued => true,
        Push::Full => false,
        Push::Start { dir, first, next } => {
            timer.load(dir, first, next);
            train.started(timer.updates());
            timer.run();
            true
        }
    }
}

/// The whole update interrupt: a period ended; count its step, set DIR for the period that
/// starts, preload the one after it or stop. Bounded, constant work per step: no division, no
/// loop, no step-time computation.
#[inline(always)]
pub fn on_interrupt(train: &mut PulseTrain, timer: &mut impl StepTimer) -> Option<Update> {
    if !timer.take_update() {
        return None;
    }
    let update = train.on_update();
    if let Some(forward) = update.dir {
        timer.set_dir(forward);
    }
    match update.preload {
        Some(p) => timer.preload(p),
        None => timer.stop(),
    }
    // Read after the preloads are written: if the hardware counted the following update by now,
    // this interrupt (or its preload write) came later than one period and the timer ran, or may
    // have run, a period on stale preloads: an extra, uncounted pulse. Klipper's "Timer too
    // close": stop here (and drop the flag that update raised); the rig task reports it and the
    // core faults, position unknown.
    if !train.count_update(timer.updates()) {
        timer.stop();
        let _ = timer.take_update();
        return Some(Update {
            stepped: update.stepped,
            dir: None,
            preload: None,
        });
    }
    Some(update)
}

impl PulseTrain {
    /// Idle, empty, default pulse width, no DIR set-up.
    pub const fn new() -> Self {
        Self {
            queue: Deque::new(),
            expanding: None,
            running: false,
            current: Period::Blank,
            next: Period::Blank,
            pulse_ticks: DEFAULT_PULSE_US * TICKS_PER_US,
            dir_setup_ticks: 0,
            end_at: 0,
            last_forward: true,
            stalls: 0,
            last_seen: None,
            overruns: 0,
        }
    }

    /// One more update event handled; `seen` is the hardware's count at the end of this
    /// interrupt. `false` when it moved by more than one since the last interrupt (or since the
    /// start's baseline): the following update came before this interrupt had written its
    /// preloads (counted as an overrun). A difference, not an absolute: the baseline is read
    /// after the start's own update generation has reached the counter.
    pub fn count_update(&mut self, seen: u16) -> bool {
        let last = self.last_seen.replace(seen);
        match last {
            Some(prev) if seen.wrapping_sub(prev) != 1 => {
                self.overruns = self.overruns.saturating_add(1);
                false
            }
            _ => true,
        }
    }

    /// Interrupts later than one period since the last call (and resets the count).
    pub fn take_overruns(&mut self) -> u32 {
        core::mem::take(&mut self.overruns)
    }

    /// The timer is about to run from a start; `baseline` is the hardware's update count now
    /// (after the start's own update generation): the first interrupt must see exactly one more.
    pub fn started(&mut self, baseline: u16) {
        self.last_seen = Some(baseline);
    }

    /// Take the hardware's update count as the last one seen (a benchmark that raises updates
    /// without handling them syncs here).
    #[allow(dead_code)] // the QEMU benchmark's
    pub fn sync_updates(&mut self, seen: u16) {
        self.last_seen = Some(seen);
    }

    /// Whether the timer is counting.
    pub fn running(&self) -> bool {
        self.running
    }

    /// STEP high time, ticks.
    pub fn pulse_ticks(&self) -> u32 {
        self.pulse_ticks
    }

    /// Set the STEP high time and the DIR set-up, µs (the pulse clamped to [`PULSE_US_RANGE`],
    /// which the profile already enforces); only while idle, so no period in flight changes
    /// shape. Returns whether it was applied.
    pub fn set_timing(&mut self, pulse_us: u32, dir_setup_us: u32) -> bool {
        if self.running {
            return false;
        }
        let pulse = pulse_us.clamp(*PULSE_US_RANGE.start(), *PULSE_US_RANGE.end());
        self.pulse_ticks = pulse * TICKS_PER_US;
        self.dir_setup_ticks = dir_setup_us.saturating_mul(TICKS_PER_US);
        true
    }

    /// Steps that could not be placed on schedule since the last call (and resets the count).
    pub fn take_stalls(&mut self) -> u32 {
        core::mem::take(&mut self.stalls)
    }

    /// Segments waiting in the queue (not counting the one being expanded).
    pub fn queued_segments(&self) -> usize {
        self.queue.len()
    }

    /// Forget everything and go idle (the caller stops the timer); keeps the timing and the
    /// stall count.
    fn clear(&mut self) {
        self.queue.clear();
        self.expanding = None;
        self.running = false;
        self.current = Period::Blank;
        self.next = Period::Blank;
    }

    /// Stop here: forget every step whose pulse has not started yet and return how many (the
    /// caller stops the timer and forces STEP low first). `counter` is the timer's counter: the
    /// current period's pulse already started if it reached the compare value, and then counts as
    /// emitted. Keeps the timing and the stall count.
    pub fn flush(&mut self, counter: u32) -> u32 {
        let mut dropped: u64 = 0;
        if self.running {
            if let Period::Step { len, .. } = self.current
                && counter < len.saturating_sub(self.pulse_ticks)
            {
                dropped += 1;
            }
            if let Period::Step { .. } = self.next {
                dropped += 1;
            }
        }
        dropped += self.expanding.map_or(0, |e| u64::from(e.left));
        dropped += self.queue.iter().map(|s| u64::from(s.count)).sum::<u64>();
        self.clear();
        u32::try_from(dropped).unwrap_or(u32::MAX)
    }

    fn preload_for(&self, period: Period) -> Preload {
        match period {
            Period::Step { len, .. } => Preload {
                arr: len - 1,
                ccr: len - self.pulse_ticks,
            },
            Period::Blank => Preload {
                arr: BLANK_TICKS - 1,
                ccr: u32::MAX,
            },
        }
    }

    /// The next step period from the segment in expansion or the queue (`Blank` if none).
    fn take_period(&mut self) -> Period {
        if self.expanding.is_none_or(|e| e.left == 0) {
            self.expanding = self.queue.pop_front().map(|s| Expanding {
                next: s.first,
                gap: s.interval,
                add: s.add,
                left: s.count,
                forward: s.forward,
            });
        }
        let Some(e) = self.expanding.as_mut().filter(|e| e.left > 0) else {
            return Period::Blank;
        };
        let len = e.next;
        e.left -= 1;
        e.next = e.gap;
        e.gap = e.gap.wrapping_add_signed(e.add);
        Period::Step {
            forward: e.forward,
            len,
        }
    }

    fn has_steps(&self) -> bool {
        !self.queue.is_empty() || self.expanding.is_some_and(|e| e.left > 0)
    }

    /// An update event happened: the next period became active.
    pub fn on_update(&mut self) -> Update {
        let stepped = matches!(self.current, Period::Step { .. });
        self.current = self.next;
        let dir = match self.current {
            Period::Step { forward, .. } => Some(forward),
            Period::Blank if !self.has_steps() => {
                self.running = false;
                self.next = Period::Blank;
                return Update {
                    stepped,
                    dir: None,
                    preload: None,
                };
            }
            Period::Blank => None,
        };
        self.next = self.take_period();
        if self.next == Period::Blank {
            // Ran out of steps: a blank period follows, the train's end moves past it.
            self.end_at += u64::from(BLANK_TICKS);
        }
        Update {
            stepped,
            dir,
            preload: Some(self.preload_for(self.next)),
        }
    }

    /// The shortest period that may end with a step in direction `forward` after the last queued
    /// one: STEP low at least as long as high, the interrupt's floor, and after a reversal DIR's
    /// set-up (DIR changes at the period's start, the pulse comes at its end).
    fn min_len(&self, forward: bool) -> u32 {
        let floor = (MIN_PERIOD_US * TICKS_PER_US).max(self.pulse_ticks * 2);
        if forward == self.last_forward {
            floor
        } else {
            floor.max(self.pulse_ticks + self.dir_setup_ticks + DIR_LATENCY_US * TICKS_PER_US)
        }
    }

    /// The length of the period ending with a step that must rise at `rise` (absolute ticks), after
    /// the train's end at `end`; a step too soon is a stall and gets the shortest period.
    fn period_to(&mut self, rise: u64, end: u64, forward: bool) -> u32 {
        let wanted = rise.saturating_add(u64::from(self.pulse_ticks));
        let min = self.min_len(forward);
        match wanted.checked_sub(end).map(u32::try_from) {
            Some(Ok(len)) if len >= min => len.min(MAX_PERIOD_TICKS),
            Some(Err(_)) => MAX_PERIOD_TICKS,
            _ => {
                self.stalls = self.stalls.saturating_add(1);
                min
            }
        }
    }

    /// Add a segment the core planned (times in absolute ticks). `now` is the time now, read with
    /// interrupts masked like the rest of the call.
    pub fn push(&mut self, segment: &StepSegment, now: u64) -> Push {
        if segment.count == 0 {
            return Push::Queued;
        }
        let forward = segment.forward;
        if self.running {
            if self.queue.is_full() {
                self.stalls = self.stalls.saturating_add(u32::from(segment.count));
                return Push::Full;
            }
            let first = self.period_to(segment.first_at, self.end_at, forward);
            let queued = Segment {
                first,
                interval: segment.interval,
                add: segment.add,
                count: segment.count,
                forward,
            };
            // Cannot fail: checked for room above.
            let _ = self.queue.push_back(queued);
            self.end_at += u64::from(first) + (segment.last_at() - segment.first_at);
            self.last_forward = forward;
            return Push::Queued;
        }
        let len = self.period_to(segment.first_at, now, forward);
        self.current = Period::Step { forward, len };
        self.end_at = now + u64::from(len) + (segment.last_at() - segment.first_at);
        self.last_forward = forward;
        self.expanding = Some(Expanding {
            next: segment.interval,
            gap: segment.interval.wrapping_add_signed(segment.add),
            add: segment.add,
            left: segment.count - 1,
            forward,
        });
        self.next = self.take_period();
        if self.next == Period::Blank {
            self.end_at += u64::from(BLANK_TICKS);
        }
        self.running = true;
        // No baseline until the caller has taken the hardware's count ([`PulseTrain::started`],
        // done by [`queue`]): until then the first interrupt would only take the count.
        self.last_seen = None;
        Push::Start {
            dir: forward,
            first: self.preload_for(self.current),
            next: self.preload_for(self.next),
        }
    }
}
