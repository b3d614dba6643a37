//! The register words of the light cut-off, the laser and trigger pins' drive rule, and the
//! decision of the safety interrupt, free of registers so `firmware/tests/board_model.rs` checks
//! them on the host.
//!
//! **High-impedance is "off"; a pin is driven only to its active level, only inside a window.**
//! The documented wiring (README, "Laser enables and trigger") puts a resistor on every laser
//! enable and on the trigger that holds the line at its off level when nothing drives it: a
//! pull-up for an active-low input, a pull-down for an active-high one, to the driver's own
//! logic rail. So the cut-off never needs to know the polarity: it puts the pin back to an input
//! with no pull ([`park`], one MODER write per pin), and the resistor does the rest. The panic
//! and HardFault handlers, the e-stop and interlock interrupt and the light's deadline timer all
//! park this way, so a wrong stored polarity cannot make any of them drive the "on" level
//! (found on a real bench: they used to drive the stored "off" level, which a wrong polarity
//! made "on").
//!
//! Inside a window a pin drives its active level:
//! - active low: **open-drain** ([`output_type`]). The pin can only pull low; its "inactive" is
//!   released, so the exposure timer's edges stay in hardware and the only driven level is the
//!   active one.
//! - active high: push-pull (the F446's GPIO has no open-source mode, RM0390 §8.3). After the
//!   timer's match the pin drives low until it is parked again, which is the off level only if
//!   the wiring really is active high.
//!
//! What makes a wrong polarity harmless in both cases is checked before a pin is ever driven:
//! while parked, a line reads the level of its resistor, which is the wiring's off level. The
//! board reads it ([`idles_off`]) before it lets the core arm and before it connects a pin, and
//! refuses when the stored polarity says otherwise: a pull-up read under an "active high"
//! profile (or a pull-down under "active low") means the profile is wrong, and the board drives
//! nothing. The one case the check cannot catch, a line with no resistor at all (floating, it
//! reads either level), is the wiring the README forbids, and its bring-up checklist measures.

/// A laser enable's or the trigger's polarity, as far as the board knows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Polarity {
    /// No profile read yet (or none stored): the pin is never driven.
    Unknown,
    /// High = active.
    ActiveHigh,
    /// Low = active.
    ActiveLow,
}

impl Polarity {
    /// From a profile's `active_low`.
    pub const fn from_active_low(active_low: bool) -> Self {
        if active_low {
            Self::ActiveLow
        } else {
            Self::ActiveHigh
        }
    }
}

/// A GPIO pin's mode as MODER sets it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PinMode {
    /// Input, no pull: high-impedance (the external resistor decides the level).
    Input,
    /// Driven by a timer channel.
    Alternate,
}

/// A GPIO pin's output stage as OTYPER sets it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputType {
    /// Drives both levels.
    PushPull,
    /// Drives low only; "high" releases the line to its resistor.
    OpenDrain,
}

/// The mode a laser enable or the trigger is parked in, whatever the polarity: an input with no
/// pull. The wiring's resistor holds the line at its off level.
pub const PARKED: PinMode = PinMode::Input;

/// MODER with `pin` parked ([`PARKED`]), other pins untouched: the whole cut-off for one pin.
pub const fn park(moder: u32, pin: u8) -> u32 {
    moder_with(moder, pin, PARKED)
}

/// The output stage for a polarity: open-drain for active low (the pin never drives high, so
/// it never drives the off level), push-pull for active high; `None` while the polarity is
/// unknown (nothing may be driven).
pub const fn output_type(polarity: Polarity) -> Option<OutputType> {
    match polarity {
        Polarity::Unknown => None,
        Polarity::ActiveHigh => Some(OutputType::PushPull),
        Polarity::ActiveLow => Some(OutputType::OpenDrain),
    }
}

/// Whether a parked line that reads `reads_high` agrees with `polarity`: its resistor holds it at
/// the off level, high for active low, low for active high. `false` while the polarity is
/// unknown. The board drives a pin only when this holds.
pub const fn idles_off(polarity: Polarity, reads_high: bool) -> bool {
    match polarity {
        Polarity::Unknown => false,
        Polarity::ActiveHigh => !reads_high,
        Polarity::ActiveLow => reads_high,
    }
}

/// MODER with `pin` in `mode`, other pins untouched.
pub const fn moder_with(moder: u32, pin: u8, mode: PinMode) -> u32 {
    let bits = match mode {
        PinMode::Input => 0b00,
        PinMode::Alternate => 0b10,
    };
    let shift = 2 * pin as u32;
    (moder & !(0b11 << shift)) | (bits << shift)
}

/// Pin states the EXTI interrupt samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SafetyPins {
    /// E-stop input is high (NC contact open: pressed or wire broken).
    pub estop_high: bool,
    /// Interlock input is high (NC contact open: enclosure open or wire broken).
    pub interlock_high: bool,
}

/// Edges the EXTI lines latched (their pending bits): the e-stop's and the interlock's lines
/// trigger on the rising edge only, the unsafe one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct SafetyEdges {
    /// The e-stop opened (was pressed) since the last interrupt.
    pub estop: bool,
    /// The interlock opened since the last interrupt.
    pub interlock: bool,
}

/// What the EXTI interrupt does before anything else.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cut {
    /// Park every laser enable and the trigger (high-impedance: off by the wiring's resistors).
    pub lasers: bool,
    /// Stop the step timer (its queue stays, so the core's flush can count what was not output).
    pub stepper: bool,
}

/// The decision for any EXTI interrupt: the latched edges count even when the contact has bounced
/// back (a short press still stops everything, and the core sees it as a press), and the pins are
/// sampled too, whichever line fired (a bouncing contact may have cleared its pending bit on
/// another edge).
pub fn on_exti(edges: SafetyEdges, pins: SafetyPins) -> Cut {
    let estop = edges.estop || pins.estop_high;
    Cut {
        lasers: estop || edges.interlock || pins.interlock_high,
        stepper: estop,
    }
}

/// Whether the motor driver may be energised (EN driven to its active level): a profile known
/// (EN's polarity and the mechanics are the wiring's), the e-stop closed, and no e-stop fault
/// left. The core keeps `Fault::EmergencyStop` after a press until the host's `ClearFault`,
/// which it refuses while the e-stop is still open, so releasing the e-stop alone does not
/// energise the motor again.
pub fn enable_allowed(
    profile_known: bool,
    estop: bool,
    fault: Option<subsurf_protocol::Fault>,
) -> bool {
    profile_known && !estop && fault != Some(subsurf_protocol::Fault::EmergencyStop)
}
