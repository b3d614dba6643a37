//! The register words of the light cut-off, the state of the laser and trigger pins before the
//! profile is known, and the decision of the safety interrupt, free of registers so
//! `firmware/tests/board_model.rs` checks them on the host.
//!
//! The cut-off must work whoever owns the laser pins (a GPIO driver, the exposure timer in
//! alternate-function mode, or nobody after a fault), so it writes two registers per pin: BSRR to
//! the *inactive* level (high for active-low laser drivers) and then MODER back to general-purpose
//! output (in alternate-function mode the output data register, and so BSRR, does not reach the
//! pin). Before the profile is known the inactive level is not known either: the pin is then put
//! back to an input with no pull (high-impedance), and the external resistor the wiring documents
//! holds the driver at its off level, whichever polarity it has. A pin is never driven at a level
//! that depends on a guess.

/// A laser enable's or the trigger's polarity, as far as the board knows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Polarity {
    /// No profile read yet (or none stored): the pin stays high-impedance.
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

    /// For an atomic.
    pub const fn to_u8(self) -> u8 {
        match self {
            Self::Unknown => 0,
            Self::ActiveHigh => 1,
            Self::ActiveLow => 2,
        }
    }

    /// From [`Polarity::to_u8`].
    pub const fn from_u8(v: u8) -> Self {
        match v {
            1 => Self::ActiveHigh,
            2 => Self::ActiveLow,
            _ => Self::Unknown,
        }
    }
}

/// How to park an output pin at "off": first `bsrr` (if any), then MODER to `mode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Park {
    /// The BSRR word setting the output data register to the inactive level (written first, so
    /// it takes effect the moment the pin becomes an output).
    pub bsrr: Option<u32>,
    /// The pin's mode afterwards.
    pub mode: PinMode,
}

/// A GPIO pin's mode as MODER sets it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PinMode {
    /// Input, no pull: high-impedance (the external resistor decides the level).
    Input,
    /// Push-pull output at the output data register's level.
    Output,
    /// Driven by a timer channel.
    Alternate,
}

/// Park `pin` at off for `polarity`: driven at its inactive level when the polarity is known,
/// high-impedance when it is not.
pub const fn park(pin: u8, polarity: Polarity) -> Park {
    match polarity {
        Polarity::Unknown => Park {
            bsrr: None,
            mode: PinMode::Input,
        },
        Polarity::ActiveHigh => Park {
            bsrr: Some(bsrr_inactive(pin, false)),
            mode: PinMode::Output,
        },
        Polarity::ActiveLow => Park {
            bsrr: Some(bsrr_inactive(pin, true)),
            mode: PinMode::Output,
        },
    }
}

/// MODER with `pin` in `mode`, other pins untouched.
pub const fn moder_with(moder: u32, pin: u8, mode: PinMode) -> u32 {
    let bits = match mode {
        PinMode::Input => 0b00,
        PinMode::Output => 0b01,
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
    /// Drive every laser enable and the trigger inactive.
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

/// BSRR word driving `pin` to its inactive level (low unless the enable is active low).
pub const fn bsrr_inactive(pin: u8, active_low: bool) -> u32 {
    if active_low {
        1 << pin
    } else {
        1 << (pin + 16)
    }
}
