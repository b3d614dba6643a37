//! The small hardware traits the core drives. The board binary implements them on pins, timers
//! and the DAC; [`crate::sim`] implements them in memory. Implementations do no timing and make no
//! decisions: the core tells them what to output and when, and they report back only what the
//! hardware timestamped (camera edges) or could not do (steps discarded by a flush).

use subsurf_protocol::{GalvoPoint, Inputs};

use crate::rig::Micros;

/// Turntable stepper driver.
pub trait Stepper {
    /// Emit one step pulse in the given direction (`forward` = increasing position). A board may
    /// queue it (a step timer a fixed pipeline delay behind the core).
    fn step(&mut self, forward: bool);

    /// Discard every step handed to [`Stepper::step`] that has not left the pin yet and return
    /// how many were discarded (the core takes them off its position). Called when the home switch
    /// is seen and on an emergency halt. Hardware without a queue returns 0.
    fn flush(&mut self) -> u32 {
        0
    }
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
}

/// Everything the rig needs; implemented automatically for any type with all six traits.
pub trait Hardware:
    Stepper + GalvoDac + LaserOutputs + CameraTrigger + CameraInput + RigInputs
{
}

impl<T: Stepper + GalvoDac + LaserOutputs + CameraTrigger + CameraInput + RigInputs> Hardware
    for T
{
}
