//! Hardware-timed exposure: the laser gate and the camera trigger of one capture come from one
//! timer in one-pulse mode, so their edges are placed by the counter, not by the executor. Free of
//! registers; `firmware/tests/board_model.rs` runs it against a tick-exact model of the timer.
//!
//! The camera starts integrating some time after its trigger edge (`trigger_latency_us`, from its
//! datasheet or measured with the exposure-active output) and then integrates `exposure_us`. The
//! laser must cover that whole window despite the latency, so the timer places:
//!
//! ```text
//! tick 0 = timer start      trigger_ccr                trigger_off_ccr        laser_off_ccr = ARR
//!   |‾‾‾‾ lead ‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾|‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾‾|____ laser
//!   |__________________________|‾‾‾‾‾‾ trigger_us ‾‾‾‾‾‾‾‾|_________________________________ trigger
//! ```
//!
//! The laser is already on (forced active) when the timer starts; its channel then runs "inactive
//! on match", so the timer alone ends it, at a fixed count after the trigger edge that covers the
//! trigger latency, the exposure and a tail. (PWM modes cannot do this in one-pulse mode: the
//! counter stops at 0 and re-evaluates the output; a match mode keeps its level.) The trigger
//! channel runs "active on match"; its compare interrupt moves it to "inactive on match" for the
//! falling edge, so both edges are hardware-placed as long as that interrupt runs within
//! `trigger_us` (hence [`MIN_TRIGGER_US`]). The timer is 16-bit, so long exposures use a coarser
//! tick (prescaler); the laser window only ever rounds longer and the trigger pulse never shorter.

/// Timer input clock, Hz (TIM8 on APB2: 2 × 84 MHz).
pub const TIMER_CLOCK_HZ: u32 = 168_000_000;
/// Largest counter value (16-bit timer).
pub const COUNTER_MAX: u32 = 0xffff;
/// Shortest trigger pulse: the compare interrupt that ends it must run within it.
pub const MIN_TRIGGER_US: u32 = 10;
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
    /// Trigger pulse shorter than [`MIN_TRIGGER_US`] or longer than the laser window after it.
    BadTrigger,
    /// The whole window does not fit the timer even at its coarsest tick.
    TooLong,
}

/// Register values for one exposure (the timer counts `0..=arr` once, then stops).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Plan {
    /// Prescaler register (tick = (psc + 1) / TIMER_CLOCK_HZ).
    pub psc: u16,
    /// Auto-reload: the timer stops when the counter wraps after `arr`.
    pub arr: u16,
    /// Trigger channel compare for the rising edge (active on match).
    pub trigger_ccr: u16,
    /// Trigger channel compare for the falling edge, written by the compare interrupt.
    pub trigger_off_ccr: u16,
    /// Laser channel compare (inactive on match): the laser goes off here.
    pub laser_off_ccr: u16,
    /// Length of one tick, ns.
    pub tick_ns: u32,
}

impl Plan {
    /// Times in µs from the timer start: (trigger rise, trigger fall, laser off).
    pub fn edges_us(&self) -> (u64, u64, u64) {
        let us = |ticks: u16| u64::from(ticks) * u64::from(self.tick_ns) / 1_000;
        (
            us(self.trigger_ccr),
            us(self.trigger_off_ccr),
            us(self.laser_off_ccr),
        )
    }
}

/// The timer plan for a window as the core announces it: trigger edge `lead_us` after the timer
/// start (the laser is on from the start), trigger pulse `trigger_us`, an exposure of
/// `exposure_us`, laser off `after_us` after the trigger edge (exposure, the camera's trigger
/// latency and a tail; at least the exposure).
pub fn plan_window(
    lead_us: u64,
    trigger_us: u32,
    exposure_us: u32,
    after_us: u64,
) -> Result<Plan, ExposureError> {
    if exposure_us < MIN_EXPOSURE_US || after_us < u64::from(exposure_us) {
        return Err(ExposureError::TooShort);
    }
    if trigger_us < MIN_TRIGGER_US || u64::from(trigger_us) >= after_us {
        return Err(ExposureError::BadTrigger);
    }
    // At least one tick before the trigger edge so the counter passes the match.
    let trigger_at_us = lead_us.max(1);
    let end_us = trigger_at_us + after_us;
    // Coarsest tick needed: ticks of `us_per_tick` µs (integer), so that `end` fits 16 bits.
    let us_per_tick = end_us.div_ceil(u64::from(COUNTER_MAX));
    let psc = (u64::from(TIMER_CLOCK_HZ / 1_000_000) * us_per_tick).saturating_sub(1);
    let psc = u16::try_from(psc).map_err(|_| ExposureError::TooLong)?;
    // The trigger edge rounds to a tick (at least 1), its pulse and the laser's time after it up.
    let trigger_ccr = (trigger_at_us / us_per_tick).max(1);
    let trigger_off_ccr = trigger_ccr + u64::from(trigger_us).div_ceil(us_per_tick);
    let laser_off_ccr = trigger_ccr + after_us.div_ceil(us_per_tick);
    let to16 = |v: u64| u16::try_from(v).map_err(|_| ExposureError::TooLong);
    Ok(Plan {
        psc,
        arr: to16(laser_off_ccr)?,
        trigger_ccr: to16(trigger_ccr)?,
        trigger_off_ccr: to16(trigger_off_ccr)?,
        laser_off_ccr: to16(laser_off_ccr)?,
        tick_ns: u32::try_from(us_per_tick * 1_000).map_err(|_| ExposureError::TooLong)?,
    })
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
