//! Safety and homing inputs on EXTI. The e-stop and interlock cut-off happens in the interrupt
//! itself: [`SafetyCut`] is bound ahead of embassy's EXTI handler on every EXTI vector the board
//! uses, samples both safety pins and, on an unsafe level, drives the lasers inactive (and on
//! e-stop stops the step timer) before anything else runs, whatever the executor is doing. Then
//! embassy's handler wakes the tasks below, which update the flags and wake the rig task so the
//! core halts, disarms and reports.
use core::marker::PhantomData;
use core::sync::atomic::{AtomicBool, Ordering};

use embassy_stm32::exti::ExtiInput;
use embassy_stm32::interrupt::typelevel::{Handler, Interrupt};
use embassy_stm32::mode::Async;
use embassy_stm32::pac;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;

use crate::outputs::force_lasers_off;
use crate::safety::{SafetyPins, on_exti};
use crate::stepper;

/// Safety pins straight from the input data register: PB5 (e-stop) and PB4 (interlock), both NC
/// contacts to GND with pull-ups, so high = pressed / open / wire broken.
pub fn safety_pins() -> SafetyPins {
    let pb = pac::GPIOB.idr().read();
    SafetyPins {
        estop_high: pb.idr(5) == pac::gpio::vals::Idr::HIGH,
        interlock_high: pb.idr(4) == pac::gpio::vals::Idr::HIGH,
    }
}

/// First handler on the EXTI vectors: the laser cut-off, before embassy's handler and before any
/// task runs.
pub struct SafetyCut<I> {
    _irq: PhantomData<I>,
}

impl<I: Interrupt> Handler<I> for SafetyCut<I> {
    unsafe fn on_interrupt() {
        let cut = on_exti(safety_pins());
        if cut.lasers {
            force_lasers_off();
        }
        if cut.stepper {
            stepper::force_stop();
        }
    }
}

/// Emergency stop pressed (or its wire broken).
pub static ESTOP: AtomicBool = AtomicBool::new(true);
/// Enclosure interlock closed.
pub static INTERLOCK_CLOSED: AtomicBool = AtomicBool::new(false);
/// Home switch active.
pub static HOME: AtomicBool = AtomicBool::new(false);
/// Camera reports an exposure in progress.
pub static EXPOSING: AtomicBool = AtomicBool::new(false);
/// Any input changed: the rig task re-reads the flags.
pub static CHANGED: Signal<CriticalSectionRawMutex, ()> = Signal::new();

fn store(flag: &AtomicBool, value: bool) {
    if flag.swap(value, Ordering::SeqCst) != value {
        CHANGED.signal(());
    }
}

/// E-stop: normally-closed contact to GND with pull-up, so high = pressed or wire broken.
#[embassy_executor::task]
pub async fn estop(mut pin: ExtiInput<'static, Async>) {
    loop {
        let pressed = pin.is_high();
        if pressed {
            // Already done by `SafetyCut` in the interrupt; repeated for the state at start-up.
            force_lasers_off();
            stepper::force_stop();
            defmt::warn!("emergency stop");
        }
        store(&ESTOP, pressed);
        pin.wait_for_any_edge().await;
    }
}

/// Interlock: normally-closed contact to GND with pull-up, so high = enclosure open.
#[embassy_executor::task]
pub async fn interlock(mut pin: ExtiInput<'static, Async>) {
    loop {
        let closed = pin.is_low();
        if !closed {
            force_lasers_off();
            defmt::warn!("interlock open");
        }
        store(&INTERLOCK_CLOSED, closed);
        pin.wait_for_any_edge().await;
    }
}

/// Home switch to GND with pull-up: low = at home.
#[embassy_executor::task]
pub async fn home(mut pin: ExtiInput<'static, Async>) {
    loop {
        store(&HOME, pin.is_low());
        pin.wait_for_any_edge().await;
    }
}

/// Optional camera strobe ("exposure active", high while exposing); logged for diagnostics.
#[embassy_executor::task]
pub async fn exposure(mut pin: ExtiInput<'static, Async>) {
    loop {
        let exposing = pin.is_high();
        if EXPOSING.swap(exposing, Ordering::SeqCst) != exposing {
            defmt::debug!("camera exposing: {}", exposing);
        }
        pin.wait_for_any_edge().await;
    }
}
