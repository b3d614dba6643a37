//! Safety and homing inputs on EXTI. The e-stop and interlock cut-off happens in the interrupt
//! itself: [`SafetyCut`] is bound ahead of embassy's EXTI handler on every EXTI vector the board
//! uses, samples both safety pins and, on an unsafe level, drives the lasers inactive (and on
//! e-stop stops the step timer) before anything else runs, whatever the executor is doing. Then
//! embassy's handler wakes the tasks below, which update the flags and wake the rig task so the
//! core halts, disarms and reports.
use core::cell::RefCell;
use core::marker::PhantomData;
use core::sync::atomic::{AtomicBool, Ordering};

use embassy_stm32::Peri;
use embassy_stm32::exti::ExtiInput;
use embassy_stm32::gpio::{Input, Pull};
use embassy_stm32::interrupt::typelevel::{Handler, Interrupt};
use embassy_stm32::mode::Async;
use embassy_stm32::pac;
use embassy_stm32::peripherals as p;
use embassy_sync::blocking_mutex::CriticalSectionMutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use heapless::Deque;
use subsurf_firmware::hal::CameraEdge;

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
            // Registers only: the queue stays, so the core's flush can count what was not output.
            stepper::fault_stop();
        }
    }
}

/// Emergency stop pressed (or its wire broken).
pub static ESTOP: AtomicBool = AtomicBool::new(true);
/// Enclosure interlock closed.
pub static INTERLOCK_CLOSED: AtomicBool = AtomicBool::new(false);
/// Home switch active.
pub static HOME: AtomicBool = AtomicBool::new(false);
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
            stepper::fault_stop();
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

/// Edges not yet taken by the rig task. 16 covers several brackets between two wakes; when full,
/// the oldest is dropped and counted.
static EDGES: CriticalSectionMutex<RefCell<Deque<CameraEdge, 16>>> =
    CriticalSectionMutex::new(RefCell::new(Deque::new()));
/// Exposure-active output is active low (from the rig profile).
static EXPOSURE_ACTIVE_LOW: AtomicBool = AtomicBool::new(false);

/// Queue an edge (from an interrupt or a task).
pub fn push_edge(edge: CameraEdge) {
    EDGES.lock(|q| {
        if let Ok(mut q) = q.try_borrow_mut() {
            if q.is_full() {
                q.pop_front();
                defmt::warn!("camera edge queue full; oldest dropped");
            }
            let _ = q.push_back(edge);
        }
    });
}

/// The oldest edge not yet taken.
pub fn pop_edge() -> Option<CameraEdge> {
    EDGES.lock(|q| q.try_borrow_mut().ok().and_then(|mut q| q.pop_front()))
}

/// The camera's exposure-active output on PB6, EXTI line 6 on both edges, always unmasked and
/// handled by [`ExposureEdge`] (not by an embassy task: embassy masks a line between its task's
/// waits, and an exposure's end must not be lost while the executor is busy).
pub struct ExposureInput {
    _pin: Input<'static>,
    _line: Peri<'static, p::EXTI6>,
}

impl ExposureInput {
    /// Take PB6 (pull-down: an unconnected output reads inactive for active-high cameras).
    pub fn new(
        pin: Peri<'static, p::PB6>,
        line: Peri<'static, p::EXTI6>,
        active_low: bool,
    ) -> Self {
        let pin = Input::new(pin, Pull::Down);
        set_exposure_active_low(active_low);
        cortex_m::interrupt::free(|_| {
            // EXTICR2 holds lines 4..7; line 6 from port B (1).
            pac::SYSCFG.exticr(1).modify(|w| w.set_exti(2, 1));
            pac::EXTI.rtsr(0).modify(|w| w.set_line(6, true));
            pac::EXTI.ftsr(0).modify(|w| w.set_line(6, true));
            pac::EXTI.pr(0).write(|w| w.set_line(6, true));
            pac::EXTI.imr(0).modify(|w| w.set_line(6, true));
        });
        Self {
            _pin: pin,
            _line: line,
        }
    }
}

/// Exposure-active polarity (from the rig profile): the pull resistor follows, so an unconnected
/// input reads inactive.
pub fn set_exposure_active_low(active_low: bool) {
    EXPOSURE_ACTIVE_LOW.store(active_low, Ordering::SeqCst);
    let pull = if active_low {
        pac::gpio::vals::Pupdr::PULL_UP
    } else {
        pac::gpio::vals::Pupdr::PULL_DOWN
    };
    pac::GPIOB.pupdr().modify(|w| w.set_pupdr(6, pull));
}

/// Second handler on EXTI9_5 (after [`SafetyCut`], before embassy's): timestamps exposure-active
/// edges and clears line 6's pending bit, so embassy never sees (or masks) it.
pub struct ExposureEdge;

impl Handler<embassy_stm32::interrupt::typelevel::EXTI9_5> for ExposureEdge {
    unsafe fn on_interrupt() {
        if !pac::EXTI.pr(0).read().line(6) {
            return;
        }
        pac::EXTI.pr(0).write(|w| w.set_line(6, true));
        let at = embassy_time::Instant::now().as_micros();
        let high = pac::GPIOB.idr().read().idr(6) == pac::gpio::vals::Idr::HIGH;
        let active = high != EXPOSURE_ACTIVE_LOW.load(Ordering::Relaxed);
        push_edge(if active {
            CameraEdge::ExposureStart(at)
        } else {
            CameraEdge::ExposureEnd(at)
        });
        CHANGED.signal(());
    }
}
