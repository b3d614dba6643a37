//! The step generator's bookkeeping, free of registers so a host test can run it against a model
//! of the timer (`firmware/tests/pulse_train.rs` includes this file through `#[path]`).
//!
//! Timer model (TIM2 in PWM mode 2, up-counting, ARR and CCR preloaded): a period of `len` ticks
//! runs the counter `0..len`; the output is high while `counter >= ccr`, so a step period
//! (`ccr = len - pulse`) ends with a STEP pulse and a blank period (`ccr` above `len`) has none.
//! At each update event (counter wrap) the preloaded `arr`/`ccr` become active and the interrupt
//! calls [`PulseTrain::on_update`], which says what to do next.
//!
//! Steps are queued as segments `(interval, count, add)`, as Klipper's `queue_step` does
//! (`src/stepper.c`): the first step comes `interval` ticks after the previous one, and each of
//! the following `count - 1` steps comes `add` ticks later than the spacing before it. The
//! interrupt expands them one period at a time, so the feeding task wakes once per batch of steps
//! (every [`BATCH_US`] at most while a move runs), not once per step. Consecutive steps merge into
//! the newest queued segment whenever they continue its arithmetic progression exactly, so the
//! compression is lossless: every pulse lands on its tick.
//!
//! Time: the train keeps the absolute time (rig µs = timer ticks, both counted from the same PLL)
//! at which its last queued period ends. A step is pushed with its absolute target; while the train
//! runs, its interval is the target minus that end, so the spacing is exact however late the push.
//! A step whose target comes too soon to be placed (the timer ran dry mid-motion because the
//! feeder was late by more than the pipeline, or the queue is full) is a stall: it is counted
//! ([`PulseTrain::take_stalls`]) and the rig raises it as a fault instead of moving the motor off
//! schedule without anyone knowing.
use heapless::Deque;

/// Default STEP high time, ticks (µs). Bare STEP/DIR drivers need 0.1–2 µs; opto-isolated inputs
/// (the common DM542/TB6600 class) need 2.5–5 µs, so 5 µs is the default.
pub const DEFAULT_PULSE_TICKS: u32 = 5;
/// Accepted STEP high times, ticks.
pub const PULSE_TICKS_RANGE: core::ops::RangeInclusive<u32> = 2..=50;
/// Shortest period the interrupt keeps up with, ticks (its work takes ~1 µs at 168 MHz). The
/// shortest step interval is this or twice the pulse width, whichever is longer (STEP low at least
/// as long as high): 100 kHz with the default pulse.
pub const MIN_PERIOD_TICKS: u32 = 10;
/// Longest interval one timer period takes.
pub const MAX_INTERVAL_TICKS: u32 = 0x7fff_ffff;
/// Queued segments. Worst case (every step its own segment, during acceleration) this holds
/// 128 steps: 3.2 ms at 40 kHz, three times the pipeline.
pub const QUEUE_LEN: usize = 128;
/// A step may replace a preloaded blank period only while the current period has more than this
/// many ticks left (the register writes take well under one tick).
pub const PATCH_MARGIN_TICKS: u32 = 3;
/// While a move runs, the feeding task wakes at most this often and queues every step that came
/// due meanwhile (each with its own scheduled time). Must stay well below the pipeline.
pub const BATCH_US: u64 = 400;

/// The shortest step interval for a pulse width.
pub const fn min_interval(pulse_ticks: u32) -> u32 {
    let twice = pulse_ticks.saturating_mul(2);
    if twice > MIN_PERIOD_TICKS {
        twice
    } else {
        MIN_PERIOD_TICKS
    }
}

/// A run of steps in one direction: `count` steps, the first `interval` ticks after the previous
/// step, each following interval `add` ticks longer than the one before.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Segment {
    /// Ticks before the first step.
    pub interval: u32,
    /// Steps in the segment (≥ 1).
    pub count: u16,
    /// Change of the interval from one step to the next, ticks.
    pub add: i32,
    /// Direction of every step.
    pub forward: bool,
}

impl Segment {
    /// Interval before the last step of the segment (`None` if it leaves the valid range).
    fn last_interval(&self) -> Option<u32> {
        let steps = i64::from(self.count).checked_sub(1)?;
        let last = i64::from(self.interval) + i64::from(self.add) * steps;
        u32::try_from(last).ok()
    }

    /// Extend the segment by a step `interval` after its last one, if that continues it exactly.
    fn try_extend(&mut self, interval: u32, forward: bool) -> bool {
        if forward != self.forward || self.count == u16::MAX {
            return false;
        }
        let Some(last) = self.last_interval() else {
            return false;
        };
        let step = i64::from(interval) - i64::from(last);
        let Ok(step) = i32::try_from(step) else {
            return false;
        };
        if self.count == 1 {
            self.add = step;
        } else if step != self.add {
            return false;
        }
        self.count += 1;
        true
    }
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

impl Period {
    /// Length in ticks.
    pub fn len(self) -> u32 {
        match self {
            Period::Step { len, .. } => len,
            Period::Blank => MIN_PERIOD_TICKS,
        }
    }
}

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
    /// The queue is half empty or the train ended: wake the feeder.
    pub refill: bool,
}

/// What [`PulseTrain::push`] needs done to the timer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Push {
    /// Queued (or merged into the newest segment); the interrupt will load it.
    Queued,
    /// The queue is full: nothing changed (counted as a stall).
    Full,
    /// Overwrite the preload registers with this (the step replaces a preloaded blank period).
    Patch(Preload),
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
    interval: u32,
    left: u16,
    add: i32,
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
    /// Absolute time (ticks) at which the last queued period ends.
    end_at: u64,
    stalls: u32,
}

impl Default for PulseTrain {
    fn default() -> Self {
        Self::new()
    }
}

impl PulseTrain {
    /// Idle, empty, default pulse width.
    pub const fn new() -> Self {
        Self {
            queue: Deque::new(),
            expanding: None,
            running: false,
            current: Period::Blank,
            next: Period::Blank,
            pulse_ticks: DEFAULT_PULSE_TICKS,
            end_at: 0,
            stalls: 0,
        }
    }

    /// Whether the timer is counting.
    pub fn running(&self) -> bool {
        self.running
    }

    /// STEP high time, ticks.
    pub fn pulse_ticks(&self) -> u32 {
        self.pulse_ticks
    }

    /// Set the STEP high time (clamped to [`PULSE_TICKS_RANGE`]); only while idle, so no period
    /// in flight changes shape. Returns whether it was applied.
    pub fn set_pulse_ticks(&mut self, ticks: u32) -> bool {
        if self.running {
            return false;
        }
        self.pulse_ticks = ticks.clamp(*PULSE_TICKS_RANGE.start(), *PULSE_TICKS_RANGE.end());
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

    /// Forget everything and go idle (the caller stops the timer); keeps the pulse width and the
    /// stall count.
    pub fn clear(&mut self) {
        let (pulse_ticks, stalls) = (self.pulse_ticks, self.stalls);
        *self = Self::new();
        self.pulse_ticks = pulse_ticks;
        self.stalls = stalls;
    }

    fn preload_for(&self, period: Period) -> Preload {
        match period {
            Period::Step { len, .. } => Preload {
                arr: len - 1,
                ccr: len - self.pulse_ticks,
            },
            Period::Blank => Preload {
                arr: MIN_PERIOD_TICKS - 1,
                ccr: u32::MAX,
            },
        }
    }

    /// The next step period from the segment in expansion or the queue (`Blank` if none).
    fn take_period(&mut self) -> Period {
        if self.expanding.is_none_or(|e| e.left == 0) {
            self.expanding = self.queue.pop_front().map(|s| Expanding {
                interval: s.interval,
                left: s.count,
                add: s.add,
                forward: s.forward,
            });
        }
        let Some(e) = self.expanding.as_mut().filter(|e| e.left > 0) else {
            return Period::Blank;
        };
        let len = e.interval;
        e.left -= 1;
        e.interval = u32::try_from(i64::from(e.interval) + i64::from(e.add)).unwrap_or(0);
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
                    refill: true,
                };
            }
            Period::Blank => None,
        };
        self.next = self.take_period();
        if self.next == Period::Blank {
            // Ran out of steps: a blank period follows, the train's end moves past it.
            self.end_at += u64::from(Period::Blank.len());
        }
        Update {
            stepped,
            dir,
            preload: Some(self.preload_for(self.next)),
            refill: self.queue.len() <= QUEUE_LEN / 2,
        }
    }

    /// The interval for a step whose pulse must rise at `target` (absolute ticks), after the end
    /// of the train at `end`; a target too soon is a stall and gets the shortest interval.
    fn interval_to(&mut self, target: u64, end: u64) -> u32 {
        let wanted = target.saturating_add(u64::from(self.pulse_ticks));
        let min = min_interval(self.pulse_ticks);
        match wanted.checked_sub(end).map(u32::try_from) {
            Some(Ok(interval)) if interval >= min => interval.min(MAX_INTERVAL_TICKS),
            Some(Err(_)) => MAX_INTERVAL_TICKS,
            _ => {
                self.stalls = self.stalls.saturating_add(1);
                min
            }
        }
    }

    /// Add a step whose STEP pulse must rise at `target` (absolute ticks). `now` is the time now,
    /// `counter` the timer's counter and `update_pending` its update flag (an update happened whose
    /// interrupt has not run yet), all read with interrupts masked.
    pub fn push(
        &mut self,
        target: u64,
        forward: bool,
        now: u64,
        counter: u32,
        update_pending: bool,
    ) -> Push {
        if self.running {
            let left = self.current.len().saturating_sub(counter.saturating_add(1));
            if self.next == Period::Blank
                && !self.has_steps()
                && !update_pending
                && left > PATCH_MARGIN_TICKS
            {
                // The preloaded blank is replaced: the train ends where the current period does.
                let end = self.end_at.saturating_sub(u64::from(Period::Blank.len()));
                let len = self.interval_to(target, end);
                self.next = Period::Step { forward, len };
                self.end_at = end + u64::from(len);
                return Push::Patch(self.preload_for(self.next));
            }
            let interval = self.interval_to(target, self.end_at);
            if let Some(back) = self.queue.back_mut()
                && back.try_extend(interval, forward)
            {
                self.end_at += u64::from(interval);
                return Push::Queued;
            }
            let segment = Segment {
                interval,
                count: 1,
                add: 0,
                forward,
            };
            return match self.queue.push_back(segment) {
                Ok(()) => {
                    self.end_at += u64::from(interval);
                    Push::Queued
                }
                Err(_) => {
                    self.stalls = self.stalls.saturating_add(1);
                    Push::Full
                }
            };
        }
        let len = self.interval_to(target, now);
        self.current = Period::Step { forward, len };
        self.end_at = now + u64::from(len);
        self.expanding = None;
        self.next = self.take_period();
        if self.next == Period::Blank {
            self.end_at += u64::from(Period::Blank.len());
        }
        self.running = true;
        Push::Start {
            dir: forward,
            first: self.preload_for(self.current),
            next: self.preload_for(self.next),
        }
    }
}

/// When the feeding task should wake next: at the core's `deadline`, except that while a move
/// runs (`deadline` is the next step's) it sleeps at least until `last_wake + BATCH_US`, taking
/// the steps due meanwhile together. Steps still land on time: the pipeline is longer than the
/// batch.
pub fn batch_wake(deadline: u64, deadline_is_step: bool, last_wake: u64) -> u64 {
    if deadline_is_step {
        deadline.max(last_wake.saturating_add(BATCH_US))
    } else {
        deadline
    }
}
