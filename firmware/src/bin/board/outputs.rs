//! Laser enables and camera trigger (TIM8, hardware-timed exposures) and the galvo DAC (external
//! SPI DAC or the internal one): the board's actuators besides the stepper.
//!
//! Lasers R/G/B and the trigger are TIM8 channels 1, 3, 4 and 2 (PC6, PC8, PC9, PC7, see `pins`).
//! A timed exposure ([`CameraTiming::start`]) runs TIM8 once in one-pulse mode: the laser channel in
//! PWM mode 2 and the trigger "active on match", whose compare interrupt ([`TriggerInterrupt`])
//! moves it to "inactive on match" for the falling edge; the plan comes from `exposure.rs`, which a
//! host test checks against a tick-exact timer model. Outside a timed exposure the same channels
//! are driven by the forced-active/forced-inactive output modes. A laser pin is in
//! alternate-function mode only while its channel may emit; [`force_lasers_off`] puts every laser
//! pin back to a GPIO output at its inactive level, whatever the timer is doing.
use core::cell::Cell;
use core::sync::atomic::{AtomicBool, AtomicU8, AtomicU16, Ordering};

use embassy_stm32::Peri;
use embassy_stm32::dac::{Dac, DualValue};
use embassy_stm32::gpio::{Level, Output, OutputType, Speed};
use embassy_stm32::interrupt::typelevel::{Handler, Interrupt, TIM8_CC};
use embassy_stm32::mode::Blocking;
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{Ocm, Urs};
use embassy_stm32::peripherals as p;
use embassy_stm32::spi::{self, Spi};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::Timer;
use embassy_stm32::timer::simple_pwm::PwmPin;
use embassy_stm32::timer::{Ch1, Ch2, Ch3, Ch4};
use embassy_sync::blocking_mutex::CriticalSectionMutex;
use embassy_time::{Duration, Instant, block_for};

use crate::exposure::Plan;
use crate::galvo_map::{GalvoMap, GalvoOutput, Slew, ad5689_frames};
use crate::inputs::push_edge;
use crate::pins::{LASER_PINS, LASER_TIMER_CHANNELS, TRIGGER_TIMER_CHANNEL};
use crate::safety::{bsrr_inactive, moder_alternate, moder_output};
use subsurf_firmware::hal::CameraEdge;

/// Laser enables are active low (from the rig profile; read by the fault paths).
static LASER_ACTIVE_LOW: AtomicBool = AtomicBool::new(false);
/// Trigger channel state for the compare interrupt: 1 = rising edge armed, 0 = idle.
static TRIGGER_PHASE: AtomicU8 = AtomicU8::new(0);
/// Compare value of the trigger's falling edge in the running exposure.
static TRIGGER_OFF_CCR: AtomicU16 = AtomicU16::new(0);
/// Rig time (µs) at which the running exposure's trigger edge comes: the timer's start plus the
/// edge's count, so the edge's timestamp is exact, not the interrupt's.
static TRIGGER_EDGE_AT: CriticalSectionMutex<Cell<u64>> = CriticalSectionMutex::new(Cell::new(0));

/// Drive every laser enable to its inactive level and take the pins from the timer, through the
/// GPIO registers only: safe from any interrupt or fault handler, whoever owns the pins. Used by
/// every fault path (panic, HardFault, e-stop and interlock interrupts) before anything else.
pub fn force_lasers_off() {
    let active_low = LASER_ACTIVE_LOW.load(Ordering::Relaxed);
    for (port, pin) in LASER_PINS {
        // Output data first (takes effect the moment the pin becomes an output), then the mode.
        port.bsrr()
            .write_value(pac::gpio::regs::Bsrr(bsrr_inactive(pin, active_low)));
        port.moder().modify(|w| w.0 = moder_output(w.0, pin));
    }
}

/// Hand laser pin `channel` to the timer (its output now decides the level).
fn connect_laser(channel: usize) {
    if let Some(&(port, pin)) = LASER_PINS.get(channel) {
        port.moder().modify(|w| w.0 = moder_alternate(w.0, pin));
    }
}

fn set_ocm(channel: usize, mode: Ocm) {
    pac::TIM8
        .ccmr_output(channel / 2)
        .modify(|w| w.set_ocm(channel % 2, mode));
}

/// The camera trigger's compare interrupt: at the rising edge, schedule the falling one.
pub struct TriggerInterrupt;

impl Handler<TIM8_CC> for TriggerInterrupt {
    unsafe fn on_interrupt() {
        let tim = pac::TIM8;
        let ch = TRIGGER_TIMER_CHANNEL;
        if !tim.sr().read().ccif(ch) {
            return;
        }
        tim.sr().modify(|w| w.set_ccif(ch, false));
        if TRIGGER_PHASE.swap(0, Ordering::SeqCst) == 1 {
            tim.ccr(ch)
                .write(|w| w.set_ccr(TRIGGER_OFF_CCR.load(Ordering::SeqCst)));
            set_ocm(ch, Ocm::INACTIVE_ON_MATCH);
            push_edge(CameraEdge::Trigger(TRIGGER_EDGE_AT.lock(Cell::get)));
        }
    }
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

/// Lasers and camera trigger on TIM8.
pub struct CameraTiming {
    _timer: Timer<'static, p::TIM8>,
    _r: PwmPin<'static, p::TIM8, Ch1>,
    _trigger: PwmPin<'static, p::TIM8, Ch2>,
    _g: PwmPin<'static, p::TIM8, Ch3>,
    _b: PwmPin<'static, p::TIM8, Ch4>,
    channels: u8,
    /// A timed exposure is (or was last) running.
    timed: bool,
}

impl CameraTiming {
    /// Take TIM8 and the four pins; lasers parked at their inactive level on GPIO, trigger idle.
    pub fn new(
        tim: Peri<'static, p::TIM8>,
        laser_r: Peri<'static, p::PC6>,
        trigger: Peri<'static, p::PC7>,
        laser_g: Peri<'static, p::PC8>,
        laser_b: Peri<'static, p::PC9>,
        io: CameraIo,
    ) -> Self {
        LASER_ACTIVE_LOW.store(io.laser_active_low, Ordering::SeqCst);
        let timer = Timer::new(tim);
        let r = PwmPin::new(laser_r, OutputType::PushPull);
        let g = PwmPin::new(laser_g, OutputType::PushPull);
        let b = PwmPin::new(laser_b, OutputType::PushPull);
        // The pins are alternate-function now, with the timer's outputs still disabled: park the
        // lasers on GPIO at once.
        force_lasers_off();
        let trigger = PwmPin::new(trigger, OutputType::PushPull);
        let tim = pac::TIM8;
        tim.cr1().modify(|w| {
            w.set_opm(true);
            w.set_urs(Urs::COUNTER_ONLY);
        });
        for ch in 0..4 {
            set_ocm(ch, Ocm::FORCE_INACTIVE);
        }
        tim.bdtr().modify(|w| w.set_moe(true));
        tim.dier()
            .modify(|w| w.set_ccie(TRIGGER_TIMER_CHANNEL, true));
        TIM8_CC::unpend();
        // SAFETY: the handler is bound in `main`; it shares only atomics with this driver.
        unsafe { TIM8_CC::enable() };
        let mut camera = Self {
            _timer: timer,
            _r: r,
            _trigger: trigger,
            _g: g,
            _b: b,
            channels: 0,
            timed: false,
        };
        camera.configure(io);
        camera
    }

    /// Apply polarities and the channel count (from the rig profile): lasers off first.
    pub fn configure(&mut self, io: CameraIo) {
        self.set_lasers(0);
        self.set_trigger(false);
        LASER_ACTIVE_LOW.store(io.laser_active_low, Ordering::SeqCst);
        force_lasers_off();
        pac::TIM8.ccer().modify(|w| {
            for ch in LASER_TIMER_CHANNELS {
                w.set_ccp(ch, io.laser_active_low);
                w.set_cce(ch, true);
            }
            w.set_ccp(TRIGGER_TIMER_CHANNEL, io.trigger_active_low);
            w.set_cce(TRIGGER_TIMER_CHANNEL, true);
        });
        self.channels = io.channels.min(subsurf_protocol::BOARD_LASER_CHANNELS);
    }

    /// Stop a timed exposure (outputs keep their levels until changed).
    fn stop_timer(&mut self) {
        pac::TIM8.cr1().modify(|w| w.set_cen(false));
        TRIGGER_PHASE.store(0, Ordering::SeqCst);
        self.timed = false;
    }

    /// Software control: bit `i` of `mask` = laser channel `i` on. Ends any timed exposure.
    pub fn set_lasers(&mut self, mask: u8) {
        self.stop_timer();
        for (i, ch) in LASER_TIMER_CHANNELS.into_iter().enumerate() {
            let on = i < usize::from(self.channels) && mask & (1 << i) != 0;
            if on {
                set_ocm(ch, Ocm::FORCE_ACTIVE);
                connect_laser(i);
            } else {
                set_ocm(ch, Ocm::FORCE_INACTIVE);
            }
        }
        if mask == 0 {
            force_lasers_off();
        }
    }

    /// Software control of the trigger line.
    pub fn set_trigger(&mut self, high: bool) {
        if self.timed && pac::TIM8.cr1().read().cen() {
            // The timer owns the edges of the running exposure.
            return;
        }
        set_ocm(
            TRIGGER_TIMER_CHANNEL,
            if high {
                Ocm::FORCE_ACTIVE
            } else {
                Ocm::FORCE_INACTIVE
            },
        );
    }

    /// Whether a timed exposure is still running.
    pub fn timed_running(&self) -> bool {
        self.timed && pac::TIM8.cr1().read().cen()
    }

    /// Run one timed exposure now per `plan`: laser channels `mask` on from now (forced active)
    /// until the timer's match turns them off, the trigger pulse on its matches.
    pub fn start(&mut self, plan: &Plan, mask: u8) {
        self.stop_timer();
        let tim = pac::TIM8;
        tim.psc().write_value(plan.psc);
        tim.arr().write(|w| w.set_arr(plan.arr));
        tim.ccr(TRIGGER_TIMER_CHANNEL)
            .write(|w| w.set_ccr(plan.trigger_ccr));
        set_ocm(TRIGGER_TIMER_CHANNEL, Ocm::FORCE_INACTIVE);
        TRIGGER_OFF_CCR.store(plan.trigger_off_ccr, Ordering::SeqCst);
        tim.cnt().write(|w| w.set_cnt(0));
        // Load PSC/ARR (no update interrupt: URS = counter only), clear stale flags.
        tim.egr().write(|w| w.set_ug(true));
        tim.sr().write_value(pac::timer::regs::SrAdv(0));
        for (i, ch) in LASER_TIMER_CHANNELS.into_iter().enumerate() {
            tim.ccr(ch).write(|w| w.set_ccr(plan.laser_off_ccr));
            if i < usize::from(self.channels) && mask & (1 << i) != 0 {
                // On now; the match mode keeps that level until the counter reaches the end.
                set_ocm(ch, Ocm::FORCE_ACTIVE);
                connect_laser(i);
                set_ocm(ch, Ocm::INACTIVE_ON_MATCH);
            } else {
                set_ocm(ch, Ocm::FORCE_INACTIVE);
            }
        }
        set_ocm(TRIGGER_TIMER_CHANNEL, Ocm::ACTIVE_ON_MATCH);
        TRIGGER_PHASE.store(1, Ordering::SeqCst);
        self.timed = true;
        let edge_in_ns = u64::from(plan.trigger_ccr) * u64::from(plan.tick_ns);
        let started = Instant::now().as_micros();
        tim.cr1().modify(|w| w.set_cen(true));
        TRIGGER_EDGE_AT.lock(|at| at.set(started + edge_in_ns / 1_000));
    }
}

/// SPI clock for the external DAC (APB1 42 MHz / 4; the AD5689R takes up to 50 MHz).
const SPI_HZ: u32 = 10_000_000;
/// Boot ramp: largest DAC step per write, and the pause between writes.
const RAMP_STEP_16: u16 = 1_024;
const RAMP_PAUSE: Duration = Duration::from_millis(1);

/// The AD5689R on SPI2 with /SYNC on a GPIO.
struct SpiDac {
    spi: Spi<'static, Blocking, spi::mode::Master>,
    sync: Output<'static>,
}

/// The two galvo axes, updated together, on the external SPI DAC or the internal DAC (both are
/// set up at boot; the rig profile picks one, and can switch it without a reset).
pub struct Galvo {
    spi: SpiDac,
    internal: Dac<'static, Blocking>,
    map: GalvoMap,
    slew: Slew,
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

fn slew_step(output: GalvoOutput) -> u16 {
    match output {
        GalvoOutput::ExternalDac16 => RAMP_STEP_16,
        // The same angle per write on the 12-bit DAC.
        GalvoOutput::InternalDac12 => RAMP_STEP_16 / 16,
    }
}

impl Galvo {
    /// Both paths; nothing moves until the first command, which the boot ramp brings from the
    /// centre smoothly. The external DAC powers up at mid-scale (RSTSEL high) and is not written
    /// before that; the internal one is set to the centre of its linear window at once.
    pub fn new(pins: GalvoPins, output: GalvoOutput) -> Self {
        let mut config = spi::Config::default();
        config.mode = spi::MODE_1;
        config.frequency = Hertz(SPI_HZ);
        let spi = Spi::new_blocking_txonly(pins.spi, pins.sck, pins.mosi, config);
        let mut internal = Dac::new_blocking(pins.dac, pins.x, pins.y);
        let (cx, cy) = GalvoMap::for_output(GalvoOutput::InternalDac12).centre();
        internal.set(DualValue::Bit12Right(cx, cy));
        let map = GalvoMap::for_output(output);
        Self {
            spi: SpiDac {
                spi,
                sync: Output::new(pins.sync, Level::High, Speed::VeryHigh),
            },
            internal,
            slew: Slew::new(map.centre(), slew_step(output)),
            map,
        }
    }

    /// Switch the output path (from a new rig profile): the new path ramps from its centre.
    pub fn set_output(&mut self, output: GalvoOutput) {
        if output != self.map.output {
            self.map = GalvoMap::for_output(output);
            self.slew = Slew::new(self.map.centre(), slew_step(output));
        }
    }

    fn write(&mut self, (a, b): (u16, u16)) {
        match self.map.output {
            GalvoOutput::ExternalDac16 => {
                for frame in ad5689_frames(a, b) {
                    self.spi.sync.set_low();
                    if self.spi.spi.blocking_write(&frame).is_err() {
                        defmt::warn!("galvo DAC write failed");
                    }
                    self.spi.sync.set_high();
                }
            }
            GalvoOutput::InternalDac12 => self.internal.set(DualValue::Bit12Right(a, b)),
        }
    }

    /// Set both axes (protocol codes, clamped). The first command after boot is ramped from the
    /// centre in small steps; later ones go straight out (the core waits the settle time).
    pub fn set(&mut self, x: u16, y: u16) {
        let target = self.map.dac_codes(x, y);
        // Bounded: the ramp ends after full scale / step writes; afterwards one write.
        for _ in 0..=u32::from(u16::MAX) {
            let ramping = self.slew.ramping();
            let Some(next) = self.slew.next(target) else {
                return;
            };
            self.write(next);
            if ramping && next != target {
                block_for(RAMP_PAUSE);
            }
        }
    }
}
