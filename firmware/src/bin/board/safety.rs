//! The register words of the laser cut-off and the decision of the safety interrupt, free of
//! registers so `firmware/tests/board_model.rs` checks them on the host.
//!
//! The cut-off must work whoever owns the laser pins (a GPIO driver, the exposure timer in
//! alternate-function mode, or nobody after a fault), so it writes two registers per pin: MODER
//! back to general-purpose output (in alternate-function mode the output data register, and so
//! BSRR, does not reach the pin) and BSRR to the *inactive* level, which is high for active-low
//! laser drivers.

/// Pin states the EXTI interrupt samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SafetyPins {
    /// E-stop input is high (NC contact open: pressed or wire broken).
    pub estop_high: bool,
    /// Interlock input is high (NC contact open: enclosure open or wire broken).
    pub interlock_high: bool,
}

/// What the EXTI interrupt does before anything else.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cut {
    /// Drive every laser enable inactive.
    pub lasers: bool,
    /// Stop the step timer and drop its queue.
    pub stepper: bool,
}

/// The decision for any EXTI interrupt: the pins are sampled whichever line fired (a bouncing
/// contact may have cleared its pending bit on another edge), and an unsafe level cuts at once.
pub fn on_exti(pins: SafetyPins) -> Cut {
    Cut {
        lasers: pins.estop_high || pins.interlock_high,
        stepper: pins.estop_high,
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

/// MODER with `pin` switched to general-purpose output (01), other pins untouched.
pub const fn moder_output(moder: u32, pin: u8) -> u32 {
    let shift = 2 * pin as u32;
    (moder & !(0b11 << shift)) | (0b01 << shift)
}

/// MODER with `pin` switched to alternate function (10), other pins untouched.
pub const fn moder_alternate(moder: u32, pin: u8) -> u32 {
    let shift = 2 * pin as u32;
    (moder & !(0b11 << shift)) | (0b10 << shift)
}
