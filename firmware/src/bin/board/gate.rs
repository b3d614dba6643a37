//! The laser and trigger pins' connect and cut, written once over a register seam
//! ([`LightRegs`]): the board implements it on GPIOC, GPIOB and the latched safety flags
//! (`outputs.rs`), and `firmware/tests/board_model.rs` on a model of those registers whose
//! e-stop edge or window end fires between any two accesses, so the host runs this very code.
//!
//! **No window between a safety check and a connect.** Connecting a pin is a read-modify-write
//! of MODER; the e-stop's EXTI handler and the deadline timer's handler park pins with their own
//! MODER writes. A check of the safety inputs made before the connect (the rig task's, the
//! core's) and a connect outside a critical section let a park land in between and be written
//! back over: the laser lit with the e-stop open until the next rig pass. [`connect`] therefore
//! runs, with interrupts masked, one sequence: read the e-stop and interlock pins, the edges the
//! EXTI handler latched and the deadline timer's cut; refuse (and park) if any says stop; read
//! each laser's parked line against the stored polarity; then write MODER once. An interrupt that
//! comes during it runs right after and parks; one that came before it is seen by it.
//!
//! Every fault path parks through [`park_all`] (one MODER write: all four pins back to inputs,
//! the wiring's resistors hold them off whatever the polarity, `safety.rs`).

use super::safety::{
    PinMode, Polarity, SafetyEdges, SafetyPins, idles_off, moder_with, on_exti, park,
};

/// GPIOC pin numbers of the laser enables R, G, B (TIM8 channels 1, 3, 4).
pub const LASER_PIN_NUMBERS: [u8; 3] = [6, 8, 9];
/// GPIOC pin number of the camera trigger (TIM3 channel 2).
pub const TRIGGER_PIN_NUMBER: u8 = 7;

/// What may stop the light, as the handlers latched it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Latched {
    /// Unsafe edges the EXTI handler latched and the core has not seen yet.
    pub edges: SafetyEdges,
    /// The light's deadline timer cut the light (until the rig task re-arms it).
    pub lights_out: bool,
}

/// The registers and flags the connect and the cut touch. All light pins are on GPIOC.
pub trait LightRegs {
    /// GPIOC's MODER.
    fn moder(&mut self) -> u32;
    /// Write GPIOC's MODER.
    fn set_moder(&mut self, moder: u32);
    /// GPIOC's input data register.
    fn idr(&mut self) -> u32;
    /// The e-stop and interlock pins (GPIOB's input data register).
    fn safety_pins(&mut self) -> SafetyPins;
    /// The latched safety edges and the deadline timer's cut.
    fn latched(&mut self) -> Latched;
    /// Latch unsafe edges for the core (the EXTI handler).
    fn latch(&mut self, edges: SafetyEdges);
    /// Mark the light cut by the deadline timer.
    fn cut_light(&mut self);
    /// Stop the exposure timers (TIM8, TIM3), registers only.
    fn stop_exposure_timers(&mut self);
    /// Stop the step timer, registers only (its queue stays for the core's flush).
    fn stop_steps(&mut self);
    /// Run `f` with every interrupt masked.
    fn masked<R>(&mut self, f: impl FnOnce(&mut Self) -> R) -> R;
}

/// MODER with every laser pin and the trigger parked.
pub const fn parked_all(moder: u32) -> u32 {
    let mut m = moder;
    let mut i = 0;
    while i < LASER_PIN_NUMBERS.len() {
        m = park(m, LASER_PIN_NUMBERS[i]);
        i += 1;
    }
    park(m, TRIGGER_PIN_NUMBER)
}

/// Park every laser enable and the trigger (one MODER write). With interrupts masked, so a task
/// calling it cannot write back a connect an interrupt made meanwhile (nothing connects from an
/// interrupt, but the rule is one: MODER changes are never interrupted).
pub fn park_all(regs: &mut impl LightRegs) {
    regs.masked(|r| {
        let m = r.moder();
        r.set_moder(parked_all(m));
    });
}

/// Park the laser pins of `mask` (bit `i` = channel `i`) and, with `trigger`, the trigger.
pub fn park_some(regs: &mut impl LightRegs, mask: u8, trigger: bool) {
    regs.masked(|r| {
        let mut m = r.moder();
        for (i, pin) in LASER_PIN_NUMBERS.into_iter().enumerate() {
            if mask & (1 << i) != 0 {
                m = park(m, pin);
            }
        }
        if trigger {
            m = park(m, TRIGGER_PIN_NUMBER);
        }
        r.set_moder(m);
    });
}

/// Whether `pin` is in alternate-function mode (its timer drives it).
pub const fn connected(moder: u32, pin: u8) -> bool {
    (moder >> (2 * pin as u32)) & 0b11 == 0b10
}

/// Which pins [`connect`] connected.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Connected {
    /// Laser channels connected to their timer (bit `i` = channel `i`).
    pub lasers: u8,
    /// The trigger is connected to its timer.
    pub trigger: bool,
    /// Nothing was connected because a safety input, a latched edge or the deadline's cut said
    /// stop.
    pub refused: bool,
}

/// Whether anything latched or read now forbids light.
pub fn light_forbidden(pins: SafetyPins, latched: Latched) -> bool {
    pins.estop_high
        || pins.interlock_high
        || latched.edges.estop
        || latched.edges.interlock
        || latched.lights_out
}

/// Connect laser channels `lasers` (bit `i` = channel `i`) and, with `trigger`, the trigger to
/// their timers, in one critical section that first re-reads the safety inputs and the latched
/// cuts: if any says stop, nothing is connected and the requested pins are parked. A laser whose
/// parked line reads the level `polarity` calls "on" (a wrong stored polarity) is not connected
/// (`safety::idles_off`); one already connected stays. The caller sets the timer channels' output
/// modes first.
pub fn connect(
    regs: &mut impl LightRegs,
    lasers: u8,
    trigger: bool,
    polarity: Polarity,
) -> Connected {
    regs.masked(|r| {
        let pins = r.safety_pins();
        let latched = r.latched();
        let moder = r.moder();
        if light_forbidden(pins, latched) {
            let mut m = moder;
            for (i, pin) in LASER_PIN_NUMBERS.into_iter().enumerate() {
                if lasers & (1 << i) != 0 {
                    m = park(m, pin);
                }
            }
            if trigger {
                m = park(m, TRIGGER_PIN_NUMBER);
            }
            r.set_moder(m);
            return Connected {
                refused: true,
                ..Connected::default()
            };
        }
        let idr = r.idr();
        let mut m = moder;
        let mut done = Connected::default();
        for (i, pin) in LASER_PIN_NUMBERS.into_iter().enumerate() {
            if lasers & (1 << i) == 0 {
                continue;
            }
            let reads_high = (idr >> pin) & 1 != 0;
            if connected(moder, pin) || idles_off(polarity, reads_high) {
                m = moder_with(m, pin, PinMode::Alternate);
                done.lasers |= 1 << i;
            }
        }
        if trigger {
            m = moder_with(m, TRIGGER_PIN_NUMBER, PinMode::Alternate);
            done.trigger = true;
        }
        if m != moder {
            r.set_moder(m);
        }
        done
    })
}

/// The EXTI handler's cut for the safety lines whose edges are `edges` (their pending bits): the
/// pins sampled too (a bounce may have cleared a pending bit on another edge), lasers and
/// trigger parked and the step timer stopped before anything else, then the edges latched for
/// the core.
pub fn on_safety_interrupt(regs: &mut impl LightRegs, edges: SafetyEdges) {
    let cut = on_exti(edges, regs.safety_pins());
    if cut.lasers {
        park_all(regs);
    }
    if cut.stepper {
        regs.stop_steps();
    }
    if edges.estop || edges.interlock {
        regs.latch(edges);
    }
}

/// The light's deadline timer fired: cut first (latched, so no connect succeeds until the rig
/// task re-arms it), stop the exposure timers, park.
pub fn on_lights_out(regs: &mut impl LightRegs) {
    regs.cut_light();
    regs.stop_exposure_timers();
    park_all(regs);
}
