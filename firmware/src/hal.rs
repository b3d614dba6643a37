//! The small hardware traits the core drives. The board binary implements them on pins, timers
//! and the DAC; [`crate::sim`] implements them in memory. Implementations do no timing and make no
//! decisions: the core tells them what to output and when.

use subsurf_protocol::{GalvoPoint, Inputs};

/// Turntable stepper driver.
pub trait Stepper {
    /// Emit one step pulse in the given direction (`forward` = increasing position).
    fn step(&mut self, forward: bool);
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

/// Camera trigger output.
pub trait CameraTrigger {
    /// Drive the trigger line (`true` = active).
    fn set_trigger(&mut self, high: bool);
}

/// Home switch, emergency stop and enclosure interlock inputs.
pub trait RigInputs {
    /// Sample all inputs now.
    fn read_inputs(&mut self) -> Inputs;
}

/// Everything the rig needs; implemented automatically for any type with all five traits.
pub trait Hardware: Stepper + GalvoDac + LaserOutputs + CameraTrigger + RigInputs {}

impl<T: Stepper + GalvoDac + LaserOutputs + CameraTrigger + RigInputs> Hardware for T {}
