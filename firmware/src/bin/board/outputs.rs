//! Laser enables, camera trigger and galvo DAC: the board's actuators besides the stepper.
use embassy_stm32::Peri;
use embassy_stm32::dac::{Dac, DualValue};
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::mode::Blocking;
use embassy_stm32::peripherals as p;

use crate::pins::LASER_PINS;

/// Largest galvo DAC code (12-bit DAC).
pub const GALVO_MAX: u16 = 4095;

/// Drive every laser enable low through the GPIO registers, whoever owns the pins. Used by every
/// fault path (panic, HardFault, e-stop and interlock edges) before anything else happens.
pub fn force_lasers_off() {
    for (port, pin) in LASER_PINS {
        port.bsrr().write(|w| w.set_br(pin, true));
    }
}

/// The laser enable outputs (R, G, B = channels 0, 1, 2), low from construction on.
pub struct Lasers {
    channels: [Output<'static>; 3],
}

impl Lasers {
    /// Take the pins and drive them low at once.
    pub fn new(
        r: Peri<'static, p::PB10>,
        g: Peri<'static, p::PA8>,
        b: Peri<'static, p::PA9>,
    ) -> Self {
        Self {
            channels: [
                Output::new(r, Level::Low, Speed::Low),
                Output::new(g, Level::Low, Speed::Low),
                Output::new(b, Level::Low, Speed::Low),
            ],
        }
    }

    /// Number of channels.
    pub const fn count(&self) -> u8 {
        3
    }

    /// Switch one channel; unknown channels are ignored (the core validated them).
    pub fn set(&mut self, channel: u8, on: bool) {
        if let Some(out) = self.channels.get_mut(usize::from(channel)) {
            out.set_level(if on { Level::High } else { Level::Low });
        }
    }
}

/// Camera trigger output (high = trigger).
pub struct CameraTrigger {
    out: Output<'static>,
}

impl CameraTrigger {
    /// Take the pin, low.
    pub fn new(pin: Peri<'static, p::PC7>) -> Self {
        Self {
            out: Output::new(pin, Level::Low, Speed::VeryHigh),
        }
    }

    /// Raise or drop the trigger line.
    pub fn set(&mut self, high: bool) {
        self.out
            .set_level(if high { Level::High } else { Level::Low });
    }
}

/// The two galvo axes on DAC1 (X = PA4, Y = PA5), updated together.
pub struct Galvo {
    dac: Dac<'static, Blocking>,
}

impl Galvo {
    /// Take the DAC and both pins; the mirrors start centred.
    pub fn new(
        dac: Peri<'static, p::DAC1>,
        x: Peri<'static, p::PA4>,
        y: Peri<'static, p::PA5>,
    ) -> Self {
        let mut galvo = Self {
            dac: Dac::new_blocking(dac, x, y),
        };
        galvo.set(GALVO_MAX / 2, GALVO_MAX / 2);
        galvo
    }

    /// Set both axes at once (codes are clamped to the 12-bit range).
    pub fn set(&mut self, x: u16, y: u16) {
        self.dac
            .set(DualValue::Bit12Right(x.min(GALVO_MAX), y.min(GALVO_MAX)));
    }
}
