//! Laser enables and camera trigger (hardware-timed exposures), the light's deadline timer, and
//! the galvo DAC (external SPI DAC or the internal one): the board's actuators besides the
//! stepper.
//!
//! Lasers R/G/B are TIM8 channels 1, 3, 4 (PC6, PC8, PC9); the trigger is TIM3 channel 2 (PC7).
//! A timed exposure ([`CameraTiming::start`]) runs both timers once in one-pulse mode, started
//! together: the laser channels forced on and "inactive on match" at the window's end, the trigger
//! in PWM mode 2, so every edge is a counter's (the plan is `exposure.rs`, which a host test checks
//! against tick-exact timer models). Outside a timed exposure the same channels are driven by the
//! forced-active output mode.
//!
//! A laser or trigger pin is high-impedance (an input, no pull) whenever it is not inside a
//! window, and that is "off" whatever the polarity: the documented wiring's resistor holds each
//! line at its off level (`safety.rs`). It is in alternate-function mode only while its timer
//! drives it on; [`park_lights`] parks every pin by one MODER write (`gate.rs`),
//! whatever the timers do and whatever polarity is stored. Active-low pins are open-drain, so
//! they never drive high at all. Before a laser pin is connected, its parked line is read: a line
//! whose resistor holds the level the stored polarity calls "on" means the profile's polarity is
//! wrong, and the pin is not driven ([`CameraTiming::laser_lines_idle_off`], checked again before
//! the core may arm).
//!
//! The light's deadline ([`LightsOut`], TIM5): the core knows by when every laser must be off
//! (heartbeat, manual limit, the window's end: `Rig::light_deadline`); the rig task arms TIM5 a
//! little after that, and its interrupt parks the lasers and the trigger if the executor has not
//! done it by then (a stuck task cannot keep light on; the watchdog comes later).
use core::sync::atomic::{AtomicBool, Ordering};

use embassy_stm32::Peri;
use embassy_stm32::dac::{Dac, DualValue};
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::interrupt::typelevel::{Handler, Interrupt, TIM5};
use embassy_stm32::mode::Blocking;
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{Ocm, Urs};
use embassy_stm32::peripherals as p;
use embassy_stm32::spi::{self, Spi};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::Timer;

use crate::exposure::{LightsOutTimer, Plan, lights_out_timer};
use crate::galvo_map::{GalvoMap, GalvoOutput, ad5689_frames};
use crate::gate::{self, LASER_PIN_NUMBERS, Latched, LightRegs, TRIGGER_PIN_NUMBER};
use crate::pins::{LASER_TIMER_CHANNELS, TRIGGER_TIMER_CHANNEL};
use crate::safety::{OutputType, Polarity, SafetyEdges, SafetyPins, idles_off, output_type};
/// The deadline timer cut the light: no laser comes on again until the rig task re-arms it.
static LIGHTS_OUT: AtomicBool = AtomicBool::new(false);

/// TIM8's alternate function on PC6/8/9, TIM3's on PC7 (datasheet, alternate function map).
const TIM8_AF: u8 = 3;
const TIM3_AF: u8 = 2;

/// The board's registers as the connect and the cut see them (`gate.rs`).
pub struct BoardRegs;

impl LightRegs for BoardRegs {
    #[inline(always)]
    fn moder(&mut self) -> u32 {
        pac::GPIOC.moder().read().0
    }
    #[inline(always)]
    fn set_moder(&mut self, moder: u32) {
        pac::GPIOC
            .moder()
            .write_value(pac::gpio::regs::Moder(moder));
    }
    #[inline(always)]
    fn idr(&mut self) -> u32 {
        pac::GPIOC.idr().read().0
    }
    #[inline(always)]
    fn safety_pins(&mut self) -> SafetyPins {
        crate::inputs::safety_pins()
    }
    #[inline(always)]
    fn latched(&mut self) -> Latched {
        Latched {
            edges: crate::inputs::latched(),
            lights_out: LIGHTS_OUT.load(Ordering::SeqCst),
        }
    }
    #[inline(always)]
    fn latch(&mut self, edges: SafetyEdges) {
        crate::inputs::latch(edges);
    }
    #[inline(always)]
    fn cut_light(&mut self) {
        LIGHTS_OUT.store(true, Ordering::SeqCst);
    }
    #[inline(always)]
    fn stop_exposure_timers(&mut self) {
        stop_exposure_timers();
    }
    #[inline(always)]
    fn stop_steps(&mut self) {
        crate::stepper::fault_stop();
    }
    #[inline(always)]
    fn masked<R>(&mut self, f: impl FnOnce(&mut Self) -> R) -> R {
        cortex_m::interrupt::free(|_| f(self))
    }
}

/// Park every laser enable and the trigger at off (high-impedance: the wiring's resistors hold
/// the off levels) and take the pins from the timers, by one MODER write: safe from any
/// interrupt or fault handler, whoever owns the pins, and independent of the stored polarity.
/// Every fault path (panic, HardFault, NMI, any unexpected interrupt, the e-stop and interlock
/// interrupt, the deadline timer) runs it before anything else.
pub fn park_lights() {
    gate::park_all(&mut BoardRegs);
}

/// Park laser pin `channel` alone.
fn park_laser(channel: usize) {
    if channel < LASER_PIN_NUMBERS.len() {
        gate::park_some(&mut BoardRegs, 1 << channel, false);
    }
}

/// Whether laser pin `channel` is connected to its timer (driven).
fn laser_connected(channel: usize) -> bool {
    LASER_PIN_NUMBERS
        .get(channel)
        .is_some_and(|&pin| gate::connected(BoardRegs.moder(), pin))
}

/// Whether laser pin `channel`, parked, reads the off level `polarity` expects (its resistor's
/// level). Meaningful only while the pin is parked.
fn laser_idles_off(channel: usize, polarity: Polarity) -> bool {
    LASER_PIN_NUMBERS
        .get(channel)
        .is_some_and(|&pin| idles_off(polarity, (BoardRegs.idr() >> pin) & 1 != 0))
}

/// OTYPER for `pin`: open-drain for an active-low line, push-pull for an active-high one.
fn set_output_type(port: pac::gpio::Gpio, pin: u8, polarity: Polarity) {
    let ot = match output_type(polarity) {
        Some(OutputType::PushPull) => pac::gpio::vals::Ot::PUSH_PULL,
        // Unknown: nothing is driven anyway; open-drain is the stage that cannot drive high.
        Some(OutputType::OpenDrain) | None => pac::gpio::vals::Ot::OPEN_DRAIN,
    };
    port.otyper().modify(|w| w.set_ot(usize::from(pin), ot));
}

/// Stop both exposure timers (registers only).
fn stop_exposure_timers() {
    pac::TIM8.cr1().modify(|w| w.set_cen(false));
    pac::TIM3.cr1().modify(|w| w.set_cen(false));
}

fn set_laser_ocm(channel: usize, mode: Ocm) {
    pac::TIM8
        .ccmr_output(channel / 2)
        .modify(|w| w.set_ocm(channel % 2, mode));
}

fn set_trigger_ocm(mode: Ocm) {
    let ch = TRIGGER_TIMER_CHANNEL;
    pac::TIM3
        .ccmr_output(ch / 2)
        .modify(|w| w.set_ocm(ch % 2, mode));
}

/// Alternate function `af`, open-drain until the polarity is known, fast edges, no pull on `pin`
/// of `port`; MODER untouched (the pin stays what it is until it is parked or connected).
fn prepare_pin(port: pac::gpio::Gpio, pin: u8, af: u8) {
    let n = usize::from(pin);
    port.afr(n / 8).modify(|w| w.set_afr(n % 8, af));
    port.otyper()
        .modify(|w| w.set_ot(n, pac::gpio::vals::Ot::OPEN_DRAIN));
    port.ospeedr()
        .modify(|w| w.set_ospeedr(n, pac::gpio::vals::Ospeedr::HIGH_SPEED));
    port.pupdr()
        .modify(|w| w.set_pupdr(n, pac::gpio::vals::Pupdr::FLOATING));
}

/// Laser and trigger wiring (from the rig profile).
#[derive(Clone, Copy, Debug)]
pub struct CameraIo {
    /// Laser channels wired (at most 3 on this board).
    pub channels: u8,
    /// Laser enables are active low.
    pub laser_active_low: bool,
    /// Trigger is active low.
    pub trigger_active_low: bool,
}

/// Lasers (TIM8) and the camera trigger (TIM3).
pub struct CameraTiming {
    _tim8: Timer<'static, p::TIM8>,
    _tim3: Timer<'static, p::TIM3>,
    _pins: (
        Peri<'static, p::PC6>,
        Peri<'static, p::PC7>,
        Peri<'static, p::PC8>,
        Peri<'static, p::PC9>,
    ),
    /// Channels wired; 0 until the profile is known (nothing is driven then).
    channels: u8,
    /// The laser enables' stored polarity.
    laser_polarity: Polarity,
    /// A timed exposure is (or was last) running.
    timed: bool,
    /// The trigger edge of the running exposure (rig µs), until it is reported.
    edge_at: Option<u64>,
}

/// The four pins, taken as they are at reset (inputs).
pub struct CameraPins {
    pub laser_r: Peri<'static, p::PC6>,
    pub trigger: Peri<'static, p::PC7>,
    pub laser_g: Peri<'static, p::PC8>,
    pub laser_b: Peri<'static, p::PC9>,
}

impl CameraTiming {
    /// Take TIM8, TIM3 and the four pins, which stay high-impedance as at reset; with `io` (the
    /// stored profile's wiring) their output stages and timer polarities are set up for it. No
    /// pin is driven on the way.
    pub fn new(
        tim8: Peri<'static, p::TIM8>,
        tim3: Peri<'static, p::TIM3>,
        pins: CameraPins,
        io: Option<CameraIo>,
    ) -> Self {
        // Timers clocked, their outputs idle before any pin could reach them.
        let tim8_ = Timer::new(tim8);
        let tim3_ = Timer::new(tim3);
        for pin in LASER_PIN_NUMBERS {
            prepare_pin(pac::GPIOC, pin, TIM8_AF);
        }
        prepare_pin(pac::GPIOC, TRIGGER_PIN_NUMBER, TIM3_AF);
        let t8 = pac::TIM8;
        t8.cr1().modify(|w| {
            w.set_opm(true);
            w.set_urs(Urs::COUNTER_ONLY);
        });
        for ch in 0..4 {
            set_laser_ocm(ch, Ocm::FORCE_INACTIVE);
        }
        t8.bdtr().modify(|w| w.set_moe(true));
        let t3 = pac::TIM3;
        t3.cr1().modify(|w| {
            w.set_opm(true);
            w.set_urs(Urs::COUNTER_ONLY);
        });
        set_trigger_ocm(Ocm::FORCE_INACTIVE);
        let mut camera = Self {
            _tim8: tim8_,
            _tim3: tim3_,
            _pins: (pins.laser_r, pins.trigger, pins.laser_g, pins.laser_b),
            channels: 0,
            laser_polarity: Polarity::Unknown,
            timed: false,
            edge_at: None,
        };
        if let Some(io) = io {
            camera.configure(io);
        }
        camera
    }

    /// Apply polarities and the channel count (from the rig profile): parks every pin first, then
    /// sets each one's output stage (open-drain when active low) and its timer channel's
    /// polarity. Nothing is driven.
    pub fn configure(&mut self, io: CameraIo) {
        self.set_lasers(0, 0);
        self.set_trigger(false);
        park_lights();
        let laser = Polarity::from_active_low(io.laser_active_low);
        let trigger = Polarity::from_active_low(io.trigger_active_low);
        for pin in LASER_PIN_NUMBERS {
            set_output_type(pac::GPIOC, pin, laser);
        }
        set_output_type(pac::GPIOC, TRIGGER_PIN_NUMBER, trigger);
        pac::TIM8.ccer().modify(|w| {
            for ch in LASER_TIMER_CHANNELS {
                w.set_ccp(ch, io.laser_active_low);
                w.set_cce(ch, true);
            }
        });
        pac::TIM3.ccer().modify(|w| {
            w.set_ccp(TRIGGER_TIMER_CHANNEL, io.trigger_active_low);
            w.set_cce(TRIGGER_TIMER_CHANNEL, true);
        });
        self.laser_polarity = laser;
        self.channels = io.channels.min(subsurf_protocol::BOARD_LASER_CHANNELS);
    }

    /// Whether every wired laser line agrees with the stored polarity: a parked pin reads its
    /// resistor's level, which must be the off level (`safety::idles_off`); a connected one was
    /// checked when it was connected. `false` while no profile is known, or for a polarity other
    /// than the one the pins are set up for.
    pub fn laser_lines_idle_off(&self, polarity: Polarity) -> bool {
        self.channels > 0
            && polarity == self.laser_polarity
            && (0..usize::from(self.channels))
                .all(|i| laser_connected(i) || laser_idles_off(i, polarity))
    }

    /// Connect laser channels `mask` (their timer channels' output modes already set) and, with
    /// `trigger`, the trigger, in the one critical section of `gate::connect` that re-reads the
    /// safety inputs and the latched cuts; a laser whose parked line contradicts the stored
    /// polarity is not connected (noted for the log).
    fn connect(&self, mask: u8, trigger: bool) -> gate::Connected {
        let done = gate::connect(&mut BoardRegs, mask, trigger, self.laser_polarity);
        let wrong = mask & !done.lasers;
        if !done.refused && wrong != 0 {
            crate::notes::note(crate::notes::Note::LaserPolarity(wrong));
        }
        done
    }

    /// Park the pins once a timed exposure's timers have stopped on their own (the laser went off
    /// at its match; an active-high pin still drives its low "off" until parked).
    pub fn park_when_done(&mut self) {
        if self.timed && !pac::TIM8.cr1().read().cen() && !pac::TIM3.cr1().read().cen() {
            self.timed = false;
            for ch in LASER_TIMER_CHANNELS {
                set_laser_ocm(ch, Ocm::FORCE_INACTIVE);
            }
            set_trigger_ocm(Ocm::FORCE_INACTIVE);
            park_lights();
        }
    }

    /// Stop a timed exposure; the trigger goes inactive, the lasers keep their levels until
    /// changed. A trigger edge that had not come yet is not reported.
    fn stop_timer(&mut self, now_us: u64) {
        stop_exposure_timers();
        set_trigger_ocm(Ocm::FORCE_INACTIVE);
        if self.edge_at.is_some_and(|at| at > now_us) {
            self.edge_at = None;
        }
        self.timed = false;
    }

    /// Software control: bit `i` of `mask` = laser channel `i` on. Ends any timed exposure.
    /// Nothing comes on while the polarity is unknown, after the deadline timer cut the light, or
    /// while a safety input or latched edge says stop (checked in the connect's critical section).
    pub fn set_lasers(&mut self, mask: u8, now_us: u64) {
        self.stop_timer(now_us);
        let lights_out = LIGHTS_OUT.load(Ordering::SeqCst);
        let mut want = 0u8;
        for (i, ch) in LASER_TIMER_CHANNELS.into_iter().enumerate() {
            let on = !lights_out && i < usize::from(self.channels) && mask & (1 << i) != 0;
            if on {
                set_laser_ocm(ch, Ocm::FORCE_ACTIVE);
                want |= 1 << i;
            } else {
                set_laser_ocm(ch, Ocm::FORCE_INACTIVE);
                park_laser(i);
            }
        }
        if want == 0 {
            return;
        }
        let done = self.connect(want, false);
        for (i, ch) in LASER_TIMER_CHANNELS.into_iter().enumerate() {
            if want & !done.lasers & (1 << i) != 0 {
                set_laser_ocm(ch, Ocm::FORCE_INACTIVE);
            }
        }
    }

    /// Software control of the trigger line (captures the timers cannot time).
    pub fn set_trigger(&mut self, high: bool) {
        if self.timed_running() {
            // The timer owns the edges of the running exposure.
            return;
        }
        if high && self.channels > 0 && !LIGHTS_OUT.load(Ordering::SeqCst) {
            set_trigger_ocm(Ocm::FORCE_ACTIVE);
            if !self.connect(0, true).trigger {
                set_trigger_ocm(Ocm::FORCE_INACTIVE);
            }
        } else {
            set_trigger_ocm(Ocm::FORCE_INACTIVE);
            gate::park_some(&mut BoardRegs, 0, true);
        }
    }

    /// Whether a timed exposure is still running.
    pub fn timed_running(&self) -> bool {
        self.timed && pac::TIM8.cr1().read().cen()
    }

    /// The running exposure's trigger edge, once its time has come (the counter placed it).
    pub fn take_trigger_edge(&mut self, now_us: u64) -> Option<u64> {
        let at = self.edge_at.filter(|&at| at <= now_us)?;
        self.edge_at = None;
        Some(at)
    }

    /// Run one timed exposure now per `plan`: laser channels `mask` on from now (forced active)
    /// until TIM8's match turns them off, the trigger pulse from TIM3. Returns `false` (nothing
    /// started) while the wiring is unknown or the light is cut.
    pub fn start(&mut self, plan: &Plan, mask: u8, now_us: u64) -> bool {
        self.stop_timer(now_us);
        if self.channels == 0 || LIGHTS_OUT.load(Ordering::SeqCst) {
            return false;
        }
        let t8 = pac::TIM8;
        t8.psc().write_value(plan.laser.psc);
        t8.arr().write(|w| w.set_arr(plan.laser.arr));
        t8.cnt().write(|w| w.set_cnt(0));
        // Load PSC/ARR (no update interrupt: URS = counter only), clear stale flags.
        t8.egr().write(|w| w.set_ug(true));
        t8.sr().write_value(pac::timer::regs::SrAdv(0));
        let t3 = pac::TIM3;
        t3.psc().write_value(plan.trigger.psc);
        t3.arr().write(|w| w.set_arr(plan.trigger.arr));
        t3.ccr(TRIGGER_TIMER_CHANNEL)
            .write(|w| w.set_ccr(plan.trigger.ccr));
        t3.cnt().write(|w| w.set_cnt(0));
        t3.egr().write(|w| w.set_ug(true));
        t3.sr().write_value(pac::timer::regs::SrGp16(0));
        // PWM mode 2 with the counter at 0 below the compare: inactive until the rise.
        set_trigger_ocm(Ocm::PWM_MODE2);
        let mut want = 0u8;
        for (i, ch) in LASER_TIMER_CHANNELS.into_iter().enumerate() {
            t8.ccr(ch).write(|w| w.set_ccr(plan.laser.ccr));
            if i < usize::from(self.channels) && mask & (1 << i) != 0 {
                // On now; the match mode keeps that level until the counter reaches the end.
                set_laser_ocm(ch, Ocm::FORCE_ACTIVE);
                want |= 1 << i;
            } else {
                set_laser_ocm(ch, Ocm::FORCE_INACTIVE);
                park_laser(i);
            }
        }
        let done = self.connect(want, true);
        if done.refused {
            for ch in LASER_TIMER_CHANNELS {
                set_laser_ocm(ch, Ocm::FORCE_INACTIVE);
            }
            set_trigger_ocm(Ocm::FORCE_INACTIVE);
            return false;
        }
        for (i, ch) in LASER_TIMER_CHANNELS.into_iter().enumerate() {
            if want & (1 << i) != 0 {
                let mode = if done.lasers & (1 << i) != 0 {
                    Ocm::INACTIVE_ON_MATCH
                } else {
                    Ocm::FORCE_INACTIVE
                };
                set_laser_ocm(ch, mode);
            }
        }
        self.timed = true;
        // Both counters start within a few cycles of each other.
        let started = cortex_m::interrupt::free(|_| {
            t8.cr1().modify(|w| w.set_cen(true));
            t3.cr1().modify(|w| w.set_cen(true));
            embassy_time::Instant::now().as_micros()
        });
        let (rise_ns, _, _) = plan.edges_ns();
        self.edge_at = Some(started + rise_ns / 1_000);
        true
    }
}

/// The light's deadline on TIM5 (32-bit, 1 µs ticks, one-pulse): its update interrupt is the
/// backstop of the core's own laser-off deadlines.
pub struct LightsOut {
    _timer: Timer<'static, p::TIM5>,
    /// The deadline armed (rig µs), if any.
    armed: Option<u64>,
}

impl LightsOut {
    /// Take TIM5, stopped, its interrupt enabled.
    pub fn new(tim: Peri<'static, p::TIM5>) -> Self {
        let mut timer = Timer::new(tim);
        timer.set_tick_freq(Hertz(1_000_000));
        let t = pac::TIM5;
        t.cr1().modify(|w| {
            w.set_opm(true);
            w.set_urs(Urs::COUNTER_ONLY);
        });
        t.dier().modify(|w| w.set_uie(true));
        TIM5::set_priority(crate::PRIO_SAFETY);
        TIM5::unpend();
        // SAFETY: the handler is bound in `main`; it shares only atomics and registers.
        unsafe { TIM5::enable() };
        Self {
            _timer: timer,
            armed: None,
        }
    }

    /// Follow the core's light deadline (`None`: no light possible, the timer stops). Re-arming
    /// with a deadline still ahead lifts a cut: the core has caught up with it.
    pub fn follow(&mut self, deadline: Option<u64>, now_us: u64) {
        if deadline == self.armed {
            return;
        }
        self.armed = deadline;
        let t = pac::TIM5;
        t.cr1().modify(|w| w.set_cen(false));
        match lights_out_timer(deadline, now_us) {
            LightsOutTimer::Stop => LIGHTS_OUT.store(false, Ordering::SeqCst),
            LightsOutTimer::FireIn { ticks, lift } => {
                if lift {
                    LIGHTS_OUT.store(false, Ordering::SeqCst);
                }
                t.arr().write_value(ticks);
                t.cnt().write_value(0);
                t.egr().write(|w| w.set_ug(true));
                t.sr().modify(|w| w.set_uif(false));
                t.cr1().modify(|w| w.set_cen(true));
            }
        }
    }
}

/// TIM5's update: the core's deadline passed long ago and the light is still allowed: cut it.
pub struct LightsOutInterrupt;

impl Handler<TIM5> for LightsOutInterrupt {
    unsafe fn on_interrupt() {
        let t = pac::TIM5;
        if !t.sr().read().uif() {
            return;
        }
        t.sr().modify(|w| w.set_uif(false));
        gate::on_lights_out(&mut BoardRegs);
    }
}

/// Whether the deadline timer has cut the light (and the core has not caught up yet).
pub fn lights_out() -> bool {
    LIGHTS_OUT.load(Ordering::SeqCst)
}

/// SPI clock for the external DAC (APB1 42 MHz / 4; the AD5689R takes up to 50 MHz).
const SPI_HZ: u32 = 10_000_000;

/// The AD5689R on SPI2 with /SYNC on a GPIO.
struct SpiDac {
    spi: Spi<'static, Blocking, spi::mode::Master>,
    sync: Output<'static>,
}

/// The internal DAC's peripheral and pins, until the internal path is first selected.
struct InternalParts {
    dac: Peri<'static, p::DAC1>,
    x: Peri<'static, p::PA4>,
    y: Peri<'static, p::PA5>,
}

/// The two galvo axes, updated together, on the external SPI DAC or the internal DAC (the rig
/// profile picks one, and can switch it without a reset). The internal DAC is only switched on
/// once the internal path is chosen, and off again when it is left: on the external path PA4/PA5
/// are not driven (PA5 also carries the Nucleo's LED).
pub struct Galvo {
    spi: SpiDac,
    internal: Option<Dac<'static, Blocking>>,
    parts: Option<InternalParts>,
    map: GalvoMap,
}

/// Pins and peripherals of both galvo paths.
pub struct GalvoPins {
    pub spi: Peri<'static, p::SPI2>,
    pub sck: Peri<'static, p::PB13>,
    pub mosi: Peri<'static, p::PB15>,
    pub sync: Peri<'static, p::PB12>,
    pub dac: Peri<'static, p::DAC1>,
    pub x: Peri<'static, p::PA4>,
    pub y: Peri<'static, p::PA5>,
}

impl Galvo {
    /// Both paths; nothing is written until the core's first command (the centre, where the
    /// external DAC powered up: RSTSEL high puts the AD5689R at mid-scale).
    pub fn new(pins: GalvoPins, output: GalvoOutput) -> Self {
        let mut config = spi::Config::default();
        config.mode = spi::MODE_1;
        config.frequency = Hertz(SPI_HZ);
        let spi = Spi::new_blocking_txonly(pins.spi, pins.sck, pins.mosi, config);
        let mut galvo = Self {
            spi: SpiDac {
                spi,
                sync: Output::new(pins.sync, Level::High, Speed::VeryHigh),
            },
            internal: None,
            parts: Some(InternalParts {
                dac: pins.dac,
                x: pins.x,
                y: pins.y,
            }),
            map: GalvoMap::for_output(GalvoOutput::ExternalDac16),
        };
        galvo.set_output(output);
        galvo
    }

    /// Switch the output path (from a rig profile): the internal DAC on only while it is the
    /// path.
    pub fn set_output(&mut self, output: GalvoOutput) {
        self.map = GalvoMap::for_output(output);
        let live = crate::galvo_map::internal_dac_live(output);
        if live
            && self.internal.is_none()
            && let Some(parts) = self.parts.take()
        {
            let mut dac = Dac::new_blocking(parts.dac, parts.x, parts.y);
            let (cx, cy) = self.map.centre();
            dac.set(DualValue::Bit12Right(cx, cy));
            self.internal = Some(dac);
        }
        if let Some(dac) = self.internal.as_mut() {
            dac.ch1().set_enable(live);
            dac.ch2().set_enable(live);
        }
    }

    /// Set both axes (protocol codes, clamped): one write, no waiting (the core waits the
    /// mirrors' settle time before it lights the spot). About 8 µs on the SPI DAC.
    pub fn set(&mut self, x: u16, y: u16) {
        let (a, b) = self.map.dac_codes(x, y);
        match self.map.output {
            GalvoOutput::ExternalDac16 => {
                for frame in ad5689_frames(a, b) {
                    self.spi.sync.set_low();
                    if self.spi.spi.blocking_write(&frame).is_err() {
                        crate::notes::note(crate::notes::Note::GalvoWrite);
                    }
                    self.spi.sync.set_high();
                }
            }
            GalvoOutput::InternalDac12 => {
                if let Some(dac) = self.internal.as_mut() {
                    dac.set(DualValue::Bit12Right(a, b));
                }
            }
        }
    }
}
