//! Hardware-timed exposure: the laser gate and the camera trigger of one capture come from two
//! timers in one-pulse mode, started together, so all their edges are placed by counters, not by
//! the executor and not by an interrupt. Free of registers; `firmware/tests/board_model.rs` runs
//! it against tick-exact models of the two timers.
//!
//! The camera starts integrating some time after its trigger edge (`trigger_latency_us`, from its
//! datasheet or measured with the exposure-active output) and then integrates `exposure_us`. The
//! laser must cover that whole window despite the latency, so the timers place:
//!
//! ```text
//! start = 0            trigger rise            trigger fall          laser off (TIM8 ARR)
//!   |‾‾‾‾ lead ‾‾‾‾‾‾‾‾‾‾‾‾|‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾|____ laser (TIM8)
//!   |______________________|‾‾‾‾‾‾ trigger_us ‾‾‾‾‾‾‾|_____________________________________ trigger (TIM3)
//! ```
//!
//! TIM8 (the laser channels): the laser is on (forced active) when the timer starts and its
//! channel runs "inactive on match" at the end count, so the timer alone ends it, a fixed time
//! after the trigger edge that covers the trigger latency, the exposure and a tail. TIM3 channel 2
//! (the trigger, on the same pin PC7): PWM mode 2, active from its compare count until the counter
//! wraps, where one-pulse mode stops it at 0 and the output falls. Both edges of the trigger are
//! the counter's: no compare interrupt has to run within the pulse, and a late interrupt can no
//! longer leave the trigger high until the next capture. The timers are 16-bit, so long exposures
//! use a coarser tick (prescaler); the laser window only ever rounds longer and the trigger pulse
//! never shorter.

/// TIM8's input clock, Hz (APB2: 2 × 84 MHz).
pub const LASER_CLOCK_HZ: u32 = 168_000_000;
/// TIM3's input clock, Hz (APB1: 2 × 42 MHz).
pub const TRIGGER_CLOCK_HZ: u32 = 84_000_000;
/// Largest counter value (16-bit timers).
pub const COUNTER_MAX: u32 = 0xffff;
/// Shortest exposure the board times: the protocol's floor (the rig profile's
/// `camera.min_exposure_us` may only raise it); below it the timer's 1 µs resolution and the laser
/// driver's rise time, not the exposure, decide the light.
pub const MIN_EXPOSURE_US: u32 = subsurf_protocol::MIN_EXPOSURE_FLOOR_US;

/// Why an exposure cannot be timed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum ExposureError {
    /// Shorter than [`MIN_EXPOSURE_US`].
    TooShort,
    /// No trigger pulse, or one longer than the laser window after it.
    BadTrigger,
    /// The whole window does not fit a timer even at its coarsest tick.
    TooLong,
}

/// One timer's registers for one pulse: it counts `0..=arr` once at a tick of `tick_ns`, then
/// stops at 0.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OnePulse {
    /// Prescaler register (tick = (psc + 1) / clock).
    pub psc: u16,
    /// Auto-reload: the counter stops when it wraps after `arr`.
    pub arr: u16,
    /// Compare value: the laser's off count (TIM8), the trigger's rise count (TIM3).
    pub ccr: u16,
    /// Length of one tick, ns.
    pub tick_ns: u32,
}

impl OnePulse {
    /// Time of count `ticks` after the start, ns.
    pub fn at_ns(&self, ticks: u32) -> u64 {
        u64::from(ticks) * u64::from(self.tick_ns)
    }

    /// When the counter wraps and stops, ns.
    pub fn end_ns(&self) -> u64 {
        self.at_ns(u32::from(self.arr) + 1)
    }
}

/// Register values for one exposure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Plan {
    /// TIM8, laser channels: forced on at the start, off at `ccr` (= `arr`).
    pub laser: OnePulse,
    /// TIM3 channel 2, the trigger: active from `ccr` until the counter wraps after `arr`.
    pub trigger: OnePulse,
}

impl Plan {
    /// Times from the start, ns: (trigger rise, trigger fall, laser off).
    pub fn edges_ns(&self) -> (u64, u64, u64) {
        (
            self.trigger.at_ns(u32::from(self.trigger.ccr)),
            self.trigger.end_ns(),
            self.laser.at_ns(u32::from(self.laser.ccr)),
        )
    }
}

/// A one-pulse timer at `clock_hz` whose tick is a whole number of µs, coarse enough for `end_us`.
fn tick_for(clock_hz: u32, end_us: u64) -> Result<(u16, u64), ExposureError> {
    let us_per_tick = end_us.div_ceil(u64::from(COUNTER_MAX)).max(1);
    let psc = (u64::from(clock_hz / 1_000_000) * us_per_tick).saturating_sub(1);
    let psc = u16::try_from(psc).map_err(|_| ExposureError::TooLong)?;
    Ok((psc, us_per_tick))
}

fn to16(v: u64) -> Result<u16, ExposureError> {
    u16::try_from(v).map_err(|_| ExposureError::TooLong)
}

/// The timer plan for a window as the core announces it: trigger edge `lead_us` after the start
/// (the laser is on from the start), trigger pulse `trigger_us`, an exposure of `exposure_us`,
/// laser off `after_us` after the trigger edge (exposure, the camera's trigger latency and a tail;
/// at least the exposure).
pub fn plan_window(
    lead_us: u64,
    trigger_us: u32,
    exposure_us: u32,
    after_us: u64,
) -> Result<Plan, ExposureError> {
    if exposure_us < MIN_EXPOSURE_US || after_us < u64::from(exposure_us) {
        return Err(ExposureError::TooShort);
    }
    // A trigger as long as the window after it (`tail_us = 0`, a level-triggered camera with
    // `trigger_us = exposure_us`) is timed too: the two counters are independent, the trigger
    // just falls on the laser's last tick. It used to fall back to software edges (found on a
    // real bench).
    if trigger_us == 0 || u64::from(trigger_us) > after_us {
        return Err(ExposureError::BadTrigger);
    }
    // The trigger: rise at least one tick in (the counter must pass the compare), rounded down;
    // the pulse rounded up.
    let trigger_at_us = lead_us.max(1);
    let (psc, us3) = tick_for(TRIGGER_CLOCK_HZ, trigger_at_us + u64::from(trigger_us) + 1)?;
    let rise = (trigger_at_us / us3).max(1);
    let end = rise + u64::from(trigger_us).div_ceil(us3);
    let trigger = OnePulse {
        psc,
        arr: to16(end - 1)?,
        ccr: to16(rise)?,
        tick_ns: u32::try_from(us3 * 1_000).map_err(|_| ExposureError::TooLong)?,
    };
    // The laser: off `after_us` after the trigger's real rise, rounded up.
    let rise_us = rise * us3;
    let (psc, us8) = tick_for(LASER_CLOCK_HZ, rise_us + after_us)?;
    let off = (rise_us + after_us).div_ceil(us8);
    let laser = OnePulse {
        psc,
        arr: to16(off)?,
        ccr: to16(off)?,
        tick_ns: u32::try_from(us8 * 1_000).map_err(|_| ExposureError::TooLong)?,
    };
    Ok(Plan { laser, trigger })
}

/// What the board does with the core's `set_lasers(mask)` while a timed exposure may be running.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LaserCall {
    /// The core's scheduled laser-off of a timed exposure whose timer still runs: the timer ends
    /// it on its own count (it started a little after the core's schedule, so cutting now would
    /// shorten the tail by that much).
    LeaveToTimer,
    /// Drive these channels now (stopping any timed exposure): an abort, a safety cut or an
    /// ordinary software change.
    Apply(u8),
}

/// The decision for `set_lasers(mask)` at core time `now`: `window_off_at` is the scheduled
/// laser-off of the armed exposure, `timer_running` whether its timer still counts, `allowed`
/// whether the safety pins permit light at all.
pub fn on_set_lasers(
    window_off_at: Option<u64>,
    now: u64,
    timer_running: bool,
    allowed: bool,
    mask: u8,
) -> LaserCall {
    let scheduled_end = window_off_at.is_some_and(|off| now >= off);
    if allowed && mask == 0 && scheduled_end && timer_running {
        LaserCall::LeaveToTimer
    } else {
        LaserCall::Apply(if allowed { mask } else { 0 })
    }
}

/// The light's deadline timer (TIM5, 1 µs ticks, one-pulse) fires this long after the core's own
/// laser-off deadline: the executor normally gets there first, and only a stuck one leaves it to
/// the timer.
pub const LIGHTS_OUT_GRACE_US: u64 = 20_000;

/// What the light's deadline timer should do for the core's deadline (`None`: no light possible).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightsOutTimer {
    /// Stopped: nothing may shine.
    Stop,
    /// Fire after this many µs (at least 1, so a deadline long past still fires at once); the
    /// light is not cut yet (`lift` = the deadline is still ahead: a cut the core has caught up
    /// with may be lifted).
    FireIn {
        /// Reload value, µs.
        ticks: u32,
        /// The core's deadline is still ahead.
        lift: bool,
    },
}

/// The timer's setting for the core's deadline at `now` (both rig µs).
pub fn lights_out_timer(deadline: Option<u64>, now: u64) -> LightsOutTimer {
    match deadline {
        None => LightsOutTimer::Stop,
        Some(at) => {
            let left = at
                .saturating_add(LIGHTS_OUT_GRACE_US)
                .saturating_sub(now)
                .clamp(1, u64::from(u32::MAX - 1));
            LightsOutTimer::FireIn {
                ticks: u32::try_from(left).unwrap_or(u32::MAX - 1),
                lift: at > now,
            }
        }
    }
}
