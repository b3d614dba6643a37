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
/// Shortest exposure the hardware honours: below this the camera's own minimum (and the timer's
/// 1 µs resolution) make the laser window, not the exposure, decide the light.
pub const MIN_EXPOSURE_US: u32 = 20;

/// Margins around one exposure, µs (part of the board's settings).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Margins {
    /// Laser on this long before the trigger edge (laser rise time, speckle settling).
    pub lead_us: u32,
    /// Trigger edge to start of integration, camera's worst case.
    pub trigger_latency_us: u32,
    /// Laser stays on this long after the exposure should have ended (camera jitter).
    pub tail_us: u32,
}

impl Margins {
    /// Defaults for a typical machine-vision camera (a few µs trigger latency and jitter).
    pub const DEFAULT: Self = Self {
        lead_us: 20,
        trigger_latency_us: 20,
        tail_us: 20,
    };
}

/// Why an exposure cannot be timed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
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

/// The timer plan for an exposure of `exposure_us` with a trigger pulse of `trigger_us`: laser on
/// `lead_us` before the trigger edge and off `trigger_latency_us + exposure_us + tail_us` after it.
pub fn plan(exposure_us: u32, trigger_us: u32, m: Margins) -> Result<Plan, ExposureError> {
    if exposure_us < MIN_EXPOSURE_US {
        return Err(ExposureError::TooShort);
    }
    let after = u64::from(m.trigger_latency_us) + u64::from(exposure_us) + u64::from(m.tail_us);
    plan_window(u64::from(m.lead_us), trigger_us, after)
}

/// The timer plan for a window given as the core announces it: trigger edge `lead_us` after the
/// timer start (the laser is on from the start), trigger pulse `trigger_us`, laser off `after_us`
/// after the trigger edge.
pub fn plan_window(lead_us: u64, trigger_us: u32, after_us: u64) -> Result<Plan, ExposureError> {
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
