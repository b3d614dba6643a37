//! Safety, homing and camera inputs on EXTI, handled by one interrupt handler of our own on every
//! EXTI vector the board uses ([`Exti`]); embassy's EXTI driver is not used at all. (Embassy's
//! handler masks every line it sees pending until a task waits on it again: an exposure-active
//! edge arriving between our handler and embassy's masked that line for the rest of the boot, and
//! an e-stop press between two waits of its task raised no interrupt.)
//!
//! The e-stop (PB5, line 5) and the interlock (PB4, line 4) trigger on their unsafe (rising) edge
//! only, and the handler acts on the latched edge, not just the level it samples: a press shorter
//! than the interrupt's latency still parks the lasers and the trigger and stops the step timer
//! before anything else runs, and the core still sees it ([`latched`]) until the rig task has
//! passed it on. Releases are seen by the core's input polls (every millisecond). The home switch
//! (PA10, line 10) wakes the rig task on both edges; the camera's exposure-active output (PB6,
//! line 6) is timestamped on both edges in the handler.
use core::cell::RefCell;
use core::marker::PhantomData;
use core::sync::atomic::{AtomicBool, Ordering};

use embassy_stm32::Peri;
use embassy_stm32::gpio::{Input, Pull};
use embassy_stm32::interrupt::typelevel::{EXTI4, EXTI9_5, EXTI15_10, Handler, Interrupt};
use embassy_stm32::pac;
use embassy_stm32::peripherals as p;
use embassy_sync::blocking_mutex::CriticalSectionMutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::signal::Signal;
use heapless::Deque;
use subsurf_firmware::hal::CameraEdge;

use crate::outputs::BoardRegs;
use crate::safety::{SafetyEdges, SafetyPins};

const INTERLOCK_LINE: usize = 4;
const ESTOP_LINE: usize = 5;
const EXPOSURE_LINE: usize = 6;
const HOME_LINE: usize = 10;

/// Safety pins straight from the input data register: PB5 (e-stop) and PB4 (interlock), both NC
/// contacts to GND with pull-ups, so high = pressed / open / wire broken.
pub fn safety_pins() -> SafetyPins {
    let pb = pac::GPIOB.idr().read();
    SafetyPins {
        estop_high: pb.idr(5) == pac::gpio::vals::Idr::HIGH,
        interlock_high: pb.idr(4) == pac::gpio::vals::Idr::HIGH,
    }
}

/// An e-stop press latched by its edge, not yet passed on to the core.
static ESTOP_LATCHED: AtomicBool = AtomicBool::new(false);
/// An interlock opening latched by its edge, not yet passed on to the core.
static INTERLOCK_LATCHED: AtomicBool = AtomicBool::new(false);
/// Any input changed: the rig task re-reads the inputs.
pub static CHANGED: Signal<CriticalSectionRawMutex, ()> = Signal::new();

/// The unsafe edges latched since the rig task last passed them on.
pub fn latched() -> SafetyEdges {
    SafetyEdges {
        estop: ESTOP_LATCHED.load(Ordering::SeqCst),
        interlock: INTERLOCK_LATCHED.load(Ordering::SeqCst),
    }
}

/// Latch unsafe edges (the EXTI handler, through `gate::on_safety_interrupt`).
pub fn latch(edges: SafetyEdges) {
    if edges.estop {
        ESTOP_LATCHED.store(true, Ordering::SeqCst);
    }
    if edges.interlock {
        INTERLOCK_LATCHED.store(true, Ordering::SeqCst);
    }
}

/// The rig task handed the core the inputs with these edges in them (`handle_inputs`): forget
/// them (a new edge since then stays).
pub fn passed_on(edges: SafetyEdges) {
    if edges.estop {
        ESTOP_LATCHED.store(false, Ordering::SeqCst);
    }
    if edges.interlock {
        INTERLOCK_LATCHED.store(false, Ordering::SeqCst);
    }
}

/// The board's handler on EXTI4, EXTI9_5 and EXTI15_10: the light and motor cut-off first, then
/// the camera's timestamp, then a wake-up for the rig task.
pub struct Exti<I> {
    _irq: PhantomData<I>,
}

impl<I: Interrupt> Handler<I> for Exti<I> {
    unsafe fn on_interrupt() {
        let exti = pac::EXTI;
        let mask =
            (1 << INTERLOCK_LINE) | (1 << ESTOP_LINE) | (1 << EXPOSURE_LINE) | (1 << HOME_LINE);
        let pending = exti.pr(0).read().0 & mask;
        // Clear exactly what was seen; an edge after this read stays pending for the next pass.
        exti.pr(0).write_value(pac::exti::regs::Lines(pending));
        let edges = SafetyEdges {
            estop: pending & (1 << ESTOP_LINE) != 0,
            interlock: pending & (1 << INTERLOCK_LINE) != 0,
        };
        // Park and stop first (the step timer through its registers only: the queue stays, so
        // the core's flush can count what was not output), then latch for the core.
        crate::gate::on_safety_interrupt(&mut BoardRegs, edges);
        if pending & (1 << EXPOSURE_LINE) != 0 {
            let at = embassy_time::Instant::now().as_micros();
            let high = pac::GPIOB.idr().read().idr(6) == pac::gpio::vals::Idr::HIGH;
            let active = high != EXPOSURE_ACTIVE_LOW.load(Ordering::Relaxed);
            push_edge(if active {
                CameraEdge::ExposureStart(at)
            } else {
                CameraEdge::ExposureEnd(at)
            });
        }
        if pending != 0 {
            CHANGED.signal(());
        }
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
                // No log here: a defmt line is a critical section of its own (`notes.rs`).
                crate::notes::count(crate::notes::Counter::EdgesDropped);
            }
            let _ = q.push_back(edge);
        }
    });
}

/// The oldest edge not yet taken.
pub fn pop_edge() -> Option<CameraEdge> {
    EDGES.lock(|q| q.try_borrow_mut().ok().and_then(|mut q| q.pop_front()))
}

/// The input pins, configured, their EXTI lines routed and unmasked.
pub struct InputPins {
    _estop: Input<'static>,
    _interlock: Input<'static>,
    _home: Input<'static>,
    _exposure: Input<'static>,
    _lines: (
        Peri<'static, p::EXTI4>,
        Peri<'static, p::EXTI5>,
        Peri<'static, p::EXTI6>,
        Peri<'static, p::EXTI10>,
    ),
}

/// The pins the inputs take.
pub struct InputParts {
    pub estop: Peri<'static, p::PB5>,
    pub interlock: Peri<'static, p::PB4>,
    pub home: Peri<'static, p::PA10>,
    pub exposure: Peri<'static, p::PB6>,
    /// The EXTI lines they use (owned so nothing else claims them).
    pub lines: (
        Peri<'static, p::EXTI4>,
        Peri<'static, p::EXTI5>,
        Peri<'static, p::EXTI6>,
        Peri<'static, p::EXTI10>,
    ),
}

impl InputPins {
    /// Pull-ups on the safety contacts and the home switch (polarity from the profile later),
    /// pull-down on exposure-active; EXTI lines routed (SYSCFG is clocked by embassy's init),
    /// triggers set, pending bits cleared, lines unmasked, vectors enabled.
    pub fn new(parts: InputParts, exposure_active_low: bool) -> Self {
        let pins = Self {
            _estop: Input::new(parts.estop, Pull::Up),
            _interlock: Input::new(parts.interlock, Pull::Up),
            _home: Input::new(parts.home, Pull::Up),
            _exposure: Input::new(parts.exposure, Pull::Down),
            _lines: parts.lines,
        };
        set_exposure_active_low(exposure_active_low);
        cortex_m::interrupt::free(|_| {
            let syscfg = pac::SYSCFG;
            // EXTICR[line / 4] field line % 4: port B = 1, port A = 0.
            for (line, port) in [
                (INTERLOCK_LINE, 1),
                (ESTOP_LINE, 1),
                (EXPOSURE_LINE, 1),
                (HOME_LINE, 0),
            ] {
                syscfg
                    .exticr(line / 4)
                    .modify(|w| w.set_exti(line % 4, port));
            }
            let exti = pac::EXTI;
            for line in [INTERLOCK_LINE, ESTOP_LINE, EXPOSURE_LINE, HOME_LINE] {
                exti.rtsr(0).modify(|w| w.set_line(line, true));
                // Safety lines latch only their unsafe (rising) edge.
                let both = line == EXPOSURE_LINE || line == HOME_LINE;
                exti.ftsr(0).modify(|w| w.set_line(line, both));
                exti.pr(0).write(|w| w.set_line(line, true));
                exti.imr(0).modify(|w| w.set_line(line, true));
            }
        });
        for enable in [EXTI4::unpend, EXTI9_5::unpend, EXTI15_10::unpend] {
            enable();
        }
        // Just below the step interrupt (`main`, "Interrupt priorities").
        EXTI4::set_priority(crate::PRIO_SAFETY);
        EXTI9_5::set_priority(crate::PRIO_SAFETY);
        EXTI15_10::set_priority(crate::PRIO_SAFETY);
        // SAFETY: the handlers are bound in `main`; they share only atomics, a critical-section
        // queue and registers with the tasks.
        unsafe {
            EXTI4::enable();
            EXTI9_5::enable();
            EXTI15_10::enable();
        }
        pins
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
