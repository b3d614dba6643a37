//! The small hardware traits the core drives. The board binary implements them on pins, timers
//! and the DAC; [`crate::sim`] implements them in memory. Implementations do no timing and make no
//! decisions: the core tells them what to output and when, and they report back only what the
//! hardware timestamped (camera edges) or could not do (steps discarded by a flush).

use subsurf_protocol::{GalvoPoint, Inputs, RigProfile, SaveError};

use crate::rig::Micros;

/// A run of steps in one direction, planned ahead by the core and emitted by the hardware's step
/// timer (Klipper's `queue_step`): the first step at `first_at`, the second `interval` ticks
/// later, every later gap `add` ticks longer than the one before. Times are in the stepper's
/// ticks ([`Stepper::TICKS_PER_US`] per µs of rig time, counted from the same boot as
/// [`Micros`]); "a step at `t`" means its STEP pulse starts at `t`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepSegment {
    /// The first step, absolute ticks.
    pub first_at: u64,
    /// Gap from the first step to the second, ticks (unused for a single step).
    pub interval: u32,
    /// Change of the gap from one step to the next, ticks.
    pub add: i32,
    /// Steps (≥ 1).
    pub count: u16,
    /// Direction of every step (`true` = increasing position).
    pub forward: bool,
}

impl StepSegment {
    /// Time of step `j` (0-based), ticks.
    pub fn step_at(&self, j: u16) -> u64 {
        let j = i128::from(j);
        let t = i128::from(self.first_at)
            + i128::from(self.interval) * j
            + i128::from(self.add) * j * (j - 1).max(0) / 2;
        u64::try_from(t).unwrap_or(0)
    }

    /// Time of its last step, ticks.
    pub fn last_at(&self) -> u64 {
        self.step_at(self.count.saturating_sub(1))
    }

    /// Steps whose time has come by `t` (ticks).
    pub fn due_by(&self, t: u64) -> u16 {
        if self.count == 0 || self.first_at > t {
            return 0;
        }
        // Step times increase with `j`: the largest `j` with `step_at(j) <= t`, by bisection.
        let (mut lo, mut hi) = (0u16, self.count - 1);
        while lo < hi {
            let mid = lo + (hi - lo).div_ceil(2);
            if self.step_at(mid) <= t {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        lo + 1
    }
}

/// Turntable stepper driver: a queue of planned [`StepSegment`]s that the hardware emits on its
/// own time base, so the core plans steps ahead and never runs once per step.
pub trait Stepper {
    /// Step-clock ticks per µs of rig time.
    const TICKS_PER_US: u32;

    /// Append a segment to the step queue; `false` if the queue is full (nothing was queued, the
    /// core offers it again later). Segments follow each other in time.
    fn queue(&mut self, segment: StepSegment) -> bool;

    /// Discard every queued step that has not left the pin yet and return how many were
    /// discarded (the core takes them off its position): an emergency halt, or the home switch
    /// found by the slow approach.
    fn flush(&mut self) -> u32;
}

/// Galvo mirror DAC.
pub trait GalvoDac {
    /// Output these codes on both axes now.
    fn set_galvo(&mut self, point: GalvoPoint);
}

/// Laser enable outputs.
pub trait LaserOutputs {
    /// Drive the laser channels: bit `i` set = channel `i` emitting. Only the core's single safety
    /// gate calls this.
    fn set_lasers(&mut self, mask: u8);

    /// Whether every wired laser enable, left undriven, sits at the off level of a profile with
    /// `active_low`: the documented wiring holds each line at its off level by a resistor, so a
    /// line at the other level means the profile's polarity is not the wiring's. The board reads
    /// its parked pins; the core refuses to arm when this is `false`
    /// ([`subsurf_protocol::RigError::LaserPolarity`]).
    fn lines_idle_off(&mut self, active_low: bool) -> bool;
}

/// One capture's timed window, all times absolute rig µs: laser `channel_mask` on at
/// `laser_on_at`, trigger active from `trigger_at` for `trigger_us`, laser off at `laser_off_at`.
/// The core announces it when the laser goes on ([`CameraTrigger::arm_window`]) and still calls
/// `set_trigger`/`set_lasers` at each edge: a board with a one-pulse timer starts the timer from
/// the window and treats those calls as the software back-stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExposureWindow {
    /// Laser channels of the capture.
    pub channel_mask: u8,
    /// Laser on.
    pub laser_on_at: Micros,
    /// Trigger rising edge.
    pub trigger_at: Micros,
    /// Trigger pulse width, µs.
    pub trigger_us: u32,
    /// Nominal exposure, µs (a simulated camera exposes this long).
    pub exposure_us: u32,
    /// Laser off.
    pub laser_off_at: Micros,
}

/// Camera trigger output.
pub trait CameraTrigger {
    /// Drive the trigger line (`true` = active).
    fn set_trigger(&mut self, high: bool);

    /// The capture's window, announced when its laser goes on (see [`ExposureWindow`]).
    fn arm_window(&mut self, _window: &ExposureWindow) {}
}

/// What the hardware timestamped on the camera lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraEdge {
    /// The trigger line went active (timer capture of the real edge).
    Trigger(Micros),
    /// The camera's exposure-active output went active.
    ExposureStart(Micros),
    /// The camera's exposure-active output went inactive.
    ExposureEnd(Micros),
}

impl CameraEdge {
    /// When it happened.
    pub fn at(&self) -> Micros {
        match *self {
            Self::Trigger(t) | Self::ExposureStart(t) | Self::ExposureEnd(t) => t,
        }
    }
}

/// The camera's timestamped edges (board: EXTI/timer-capture interrupt into a small queue).
pub trait CameraInput {
    /// The oldest edge not yet taken, if any (only edges that already happened).
    fn poll_camera_edge(&mut self) -> Option<CameraEdge>;
}

/// Home switch, emergency stop and enclosure interlock inputs.
pub trait RigInputs {
    /// Sample all inputs now.
    fn read_inputs(&mut self) -> Inputs;
    /// The chip's registers the bring-up checklist checks (the board only; a simulated rig has
    /// none).
    fn board_registers(&mut self) -> Option<subsurf_protocol::BoardRegisters> {
        None
    }
}

/// Where the rig profile survives a reset (the board's flash).
pub trait ProfileStore {
    /// Store `profile` for the next boot, read it back and compare: `Ok` only when what the store
    /// returns now is `profile`. Blocking: the core calls it only while the rig is idle with the
    /// lasers off (an erase stalls every interrupt on the board), and replies to `SetProfile`
    /// with its outcome.
    fn store_profile(&mut self, profile: &RigProfile) -> Result<(), SaveError>;

    /// The profile the store returns now (what the next boot runs), if a valid one.
    fn stored_profile(&mut self) -> Option<RigProfile>;
}

/// Everything the rig needs; implemented automatically for any type with all seven traits.
pub trait Hardware:
    Stepper + GalvoDac + LaserOutputs + CameraTrigger + CameraInput + RigInputs + ProfileStore
{
}

impl<T: Stepper + GalvoDac + LaserOutputs + CameraTrigger + CameraInput + RigInputs + ProfileStore>
    Hardware for T
{
}
