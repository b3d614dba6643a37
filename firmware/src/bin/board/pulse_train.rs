//! The step generator's bookkeeping, free of registers so a host test can run it against a model
//! of the timer (`firmware/tests/pulse_train.rs` includes this file through `#[path]`).
//!
//! Timer model (TIM2 in PWM mode 2, up-counting, ARR and CCR preloaded): a period of `len` ticks
//! runs the counter `0..len`; the output is high while `counter >= ccr`, so a step period
//! (`ccr = len - PULSE_TICKS`) ends with a STEP pulse and a blank period (`ccr` above `len`) has
//! none. At each update event (counter wrap) the preloaded `arr`/`ccr` become active and the
//! interrupt calls [`PulseTrain::on_update`], which says what to do next.
use heapless::Deque;

/// STEP high time, ticks (µs). STEP/DIR drivers need 0.1–2 µs; 3 µs suits all common ones.
pub const PULSE_TICKS: u32 = 3;
/// Shortest interval between two steps, ticks: 100 kHz, five times the 20 kHz target.
pub const MIN_INTERVAL_TICKS: u32 = 10;
/// Longest interval one timer period takes.
pub const MAX_INTERVAL_TICKS: u32 = 0x7fff_ffff;
/// Queued steps: 12.8 ms at 20 kHz.
pub const QUEUE_LEN: usize = 256;
/// A step may replace a preloaded blank period only while the current period has more than this
/// many ticks left (the register writes take well under one tick).
pub const PATCH_MARGIN_TICKS: u32 = 3;

/// A queued step: the interval before its pulse, and its direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QueuedStep {
    /// Ticks from the previous pulse (or from the start) to this one.
    pub interval: u32,
    /// Direction of this step.
    pub forward: bool,
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
            Period::Blank => MIN_INTERVAL_TICKS,
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

/// The preload registers for a period.
pub fn preload_for(period: Period) -> Preload {
    match period {
        Period::Step { len, .. } => Preload {
            arr: len - 1,
            ccr: len - PULSE_TICKS,
        },
        Period::Blank => Preload {
            arr: MIN_INTERVAL_TICKS - 1,
            ccr: u32::MAX,
        },
    }
}

fn period_of(step: Option<QueuedStep>) -> Period {
    match step {
        Some(s) => Period::Step {
            forward: s.forward,
            len: s.interval.clamp(MIN_INTERVAL_TICKS, MAX_INTERVAL_TICKS),
        },
        None => Period::Blank,
    }
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
    /// Queued; the interrupt will load it.
    Queued,
    /// The queue is full: nothing changed.
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

/// Queue and period state shared by the interrupt and the feeding task.
#[derive(Debug)]
pub struct PulseTrain {
    queue: Deque<QueuedStep, QUEUE_LEN>,
    running: bool,
    current: Period,
    next: Period,
}

impl Default for PulseTrain {
    fn default() -> Self {
        Self::new()
    }
}

impl PulseTrain {
    /// Idle, empty.
    pub const fn new() -> Self {
        Self {
            queue: Deque::new(),
            running: false,
            current: Period::Blank,
            next: Period::Blank,
        }
    }

    /// Whether the timer is counting.
    pub fn running(&self) -> bool {
        self.running
    }

    /// Forget everything and go idle (the caller stops the timer).
    pub fn clear(&mut self) {
        *self = Self::new();
    }

    /// An update event happened: the next period became active.
    pub fn on_update(&mut self) -> Update {
        let stepped = matches!(self.current, Period::Step { .. });
        self.current = self.next;
        let dir = match self.current {
            Period::Step { forward, .. } => Some(forward),
            Period::Blank if self.queue.is_empty() => {
                self.running = false;
                self.next = Period::Blank;
                return Update {
                    stepped,
                    dir: None,
                    preload: None,
                    refill: true,
                };
            }
            // Steps arrived after the blank period was preloaded: the next one's interval counts
            // from the previous pulse, so the blank period's length comes off it.
            Period::Blank => {
                let step = self.queue.pop_front().map(|s| QueuedStep {
                    interval: s.interval.saturating_sub(Period::Blank.len()),
                    ..s
                });
                self.next = period_of(step);
                return Update {
                    stepped,
                    dir: None,
                    preload: Some(preload_for(self.next)),
                    refill: self.queue.len() <= QUEUE_LEN / 2,
                };
            }
        };
        self.next = period_of(self.queue.pop_front());
        Update {
            stepped,
            dir,
            preload: Some(preload_for(self.next)),
            refill: self.queue.len() <= QUEUE_LEN / 2,
        }
    }

    /// Add a step. `counter` is the timer's counter now and `update_pending` its update flag (an
    /// update happened whose interrupt has not run yet), both read with interrupts masked.
    pub fn push(&mut self, step: QueuedStep, counter: u32, update_pending: bool) -> Push {
        if self.running {
            let left = self.current.len().saturating_sub(counter.saturating_add(1));
            if self.next == Period::Blank
                && self.queue.is_empty()
                && !update_pending
                && left > PATCH_MARGIN_TICKS
            {
                self.next = period_of(Some(step));
                return Push::Patch(preload_for(self.next));
            }
            return match self.queue.push_back(step) {
                Ok(()) => Push::Queued,
                Err(_) => Push::Full,
            };
        }
        self.current = period_of(Some(step));
        self.next = period_of(self.queue.pop_front());
        self.running = true;
        Push::Start {
            dir: step.forward,
            first: preload_for(self.current),
            next: preload_for(self.next),
        }
    }
}

/// The interval to queue for a step the core scheduled at `scheduled` (µs) and the task pushes
/// `lateness` µs after that. While the timer runs: the exact spacing from the previous step
/// (scheduled at `last_step_at`). From idle: the rest of the `pipeline` lead, so the pulse still
/// lands at `scheduled + pipeline`. Either way every pulse comes one constant `pipeline` after the
/// core's schedule, as long as the task is less than `pipeline − MIN_INTERVAL_TICKS` late.
pub fn interval_for(
    scheduled: u64,
    last_step_at: u64,
    running: bool,
    pipeline: u32,
    lateness: u64,
) -> u32 {
    if running {
        u32::try_from(scheduled.saturating_sub(last_step_at))
            .unwrap_or(u32::MAX)
            .max(MIN_INTERVAL_TICKS)
    } else {
        let lateness = u32::try_from(lateness).unwrap_or(u32::MAX);
        pipeline.saturating_sub(lateness).max(MIN_INTERVAL_TICKS)
    }
}
