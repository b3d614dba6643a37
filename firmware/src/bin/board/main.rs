//! subsurf rig firmware for the Nucleo-F446RE (STM32F446RE, Cortex-M4F).
//!
//! The board binary only owns the hardware and pumps the sans-IO core (`subsurf_firmware`): bytes
//! from the USART2 link go into the core, its frames go back out, its hardware calls land on the
//! drivers in this directory, and its next deadline becomes an embassy timer. Every decision lives
//! in the core; the binary adds the fault paths the core cannot see (panic, HardFault, NMI, any
//! unexpected interrupt, a stuck executor via the light's deadline timer and the independent
//! watchdog) and parks the lasers and the trigger at off on each of them (docs/board.md).
//!
//! Boot order: EN to the stored profile's disabled level (before the clocks), clocks, the flash
//! accelerator and the debug-halt freeze, then the rig profile from flash (a memory-mapped read, no
//! pin involved), then the laser and trigger timers set up for the profile's polarities. The pins themselves stay
//! high-impedance, as at reset, until a window drives one to its active level (the wiring's pull
//! resistors hold them off, whatever their polarity: `safety.rs`).
//!
//! Build: `cargo fw`; flash: `subsurf flash` (or `cargo fw-run` with the probe-rs CLI).
#![no_std]
#![no_main]

mod exposure;
mod flash_record;
mod galvo_map;
mod gate;
mod inputs;
mod notes;
mod outputs;
mod pins;
mod pulse_train;
mod rig;
mod safety;
mod stepper;
mod store;

use core::sync::atomic::{AtomicU32, Ordering};

use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_stm32::usart::{self, BufferedUart};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{bind_interrupts, interrupt, peripherals};
use embassy_time::{Duration, Timer};
use static_cell::StaticCell;

use crate::inputs::{InputParts, InputPins};
use crate::outputs::{
    CameraIo, CameraPins, CameraTiming, Galvo, GalvoPins, LightsOut, park_lights,
};
use crate::pins::Board;
use crate::stepper::{StepGen, StepperIo};
use crate::store::Store;

bind_interrupts!(struct Irqs {
    USART2 => usart::BufferedInterruptHandler<peripherals::USART2>;
    TIM2 => stepper::StepInterrupt;
    TIM5 => outputs::LightsOutInterrupt;
    // The board's own EXTI handler (the cut-off first); embassy's EXTI driver is not used.
    EXTI4 => inputs::Exti<interrupt::typelevel::EXTI4>;
    EXTI9_5 => inputs::Exti<interrupt::typelevel::EXTI9_5>;
    EXTI15_10 => inputs::Exti<interrupt::typelevel::EXTI15_10>;
});

/// Link baud rate: `SUBSURF_BAUD` at build time, 921600 by default (`subsurf rig --baud` must match).
pub const BAUD: u32 = parse_baud(option_env!("SUBSURF_BAUD"));

const fn parse_baud(text: Option<&str>) -> u32 {
    let Some(text) = text else {
        return 921_600;
    };
    let bytes = text.as_bytes();
    let mut value: u32 = 0;
    let mut i = 0;
    while i < bytes.len() {
        let digit = bytes[i];
        assert!(
            digit.is_ascii_digit(),
            "SUBSURF_BAUD must be a decimal number"
        );
        value = value * 10 + (digit - b'0') as u32;
        i += 1;
    }
    assert!(
        value >= 9600 && value <= 2_000_000,
        "SUBSURF_BAUD out of range"
    );
    value
}

/// Interrupt priorities (NVIC, 4 bits on the STM32F446; lower is more urgent). The step
/// interrupt (TIM2, `stepper.rs`) alone at `P0`, as grbl keeps its step ISR above everything: it
/// must write the next period's preloads within the running period (≥ 10 µs), and only a
/// critical section can delay it now; TIM4's hardware count of its updates reports any delay
/// beyond one period (`Fault::StepLate`). Then the safety cut-offs (e-stop, interlock and
/// exposure EXTI lines, the light's deadline TIM5), the time driver (TIM12: it must run within
/// half its 65.5 ms period), and the link's USART last (its FIFO-less receiver overruns after one
/// character, 11 µs at 921600 baud, but a lost frame is retransmitted).
pub const PRIO_SAFETY: interrupt::Priority = interrupt::Priority::P1;
/// The time driver's interrupt.
const PRIO_TIME: interrupt::Priority = interrupt::Priority::P2;
/// The link's interrupt.
const PRIO_LINK: interrupt::Priority = interrupt::Priority::P3;

/// Watchdog timeout: a hung executor or a stalled rig task resets the chip after this long.
const WATCHDOG_TIMEOUT_US: u32 = 500_000;
/// Incremented by the rig task every loop; the watchdog task only pets while it moves.
pub static RIG_ALIVE: AtomicU32 = AtomicU32::new(0);

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    // Before anything else, clocks included: EN to the stored profile's "disabled" level (or left
    // high-impedance with none stored, where the wiring's external pull holds it disabled).
    stepper::hold_enable_disabled_at_reset();
    let p = embassy_stm32::init(clock_config());
    enable_flash_accelerator();
    freeze_steps_on_halt();
    // The time driver's interrupt (TIM12 shares its vector with TIM8's break, unused), below the
    // step and safety interrupts; see `PRIO_SAFETY`.
    {
        use embassy_stm32::interrupt::InterruptExt;
        interrupt::TIM8_BRK_TIM12.set_priority(PRIO_TIME);
    }
    hardfault_runs_first();
    ensure_brown_out_level();
    let board = Board::new(p);
    // The profile first: its laser and trigger polarities decide how a window drives the pins.
    // Outside a window (and for ever, with nothing stored) those pins stay inputs, as at reset.
    let store = Store::new(board.flash);
    let stored = rig::stored_profile(&store);
    let camera = CameraTiming::new(
        board.camera_timer,
        board.trigger_timer,
        CameraPins {
            laser_r: board.laser_r,
            trigger: board.camera_trigger,
            laser_g: board.laser_g,
            laser_b: board.laser_b,
        },
        stored.map(|p| CameraIo {
            channels: p.laser.channels,
            laser_active_low: p.laser.active_low,
            trigger_active_low: p.camera.trigger_active_low,
        }),
    );
    let profile = stored.unwrap_or(subsurf_protocol::RigProfile::DEFAULT);
    defmt::info!(
        "subsurf firmware {} on STM32F446RE, link {} baud",
        env!("CARGO_PKG_VERSION"),
        BAUD
    );

    let mut watchdog = IndependentWatchdog::new(board.watchdog, WATCHDOG_TIMEOUT_US);
    watchdog.unleash();
    spawner.spawn(defmt::unwrap!(watchdog_task(watchdog)));

    let stepper = StepGen::new(
        board.step_timer,
        board.step_counter,
        board.step,
        board.dir,
        board.enable,
        StepperIo::from(&profile.motor),
        stored.is_some(),
    );
    // EN stays released (no holding torque) until the rig task has a stored profile, reads the
    // e-stop closed and no e-stop fault is left (`rig::follow_enable`): no motion on guessed
    // mechanics, none before the e-stop input is even set up. With no profile stored EN is not
    // driven at all (the wiring's pull holds the driver disabled).
    let galvo = Galvo::new(
        GalvoPins {
            spi: board.galvo_spi,
            sck: board.galvo_sck,
            mosi: board.galvo_mosi,
            sync: board.galvo_sync,
            dac: board.dac,
            x: board.galvo_x,
            y: board.galvo_y,
        },
        profile.galvo.output,
    );
    let inputs = InputPins::new(
        InputParts {
            estop: board.estop,
            interlock: board.interlock,
            home: board.home,
            exposure: board.exposure,
            lines: (
                board.interlock_exti,
                board.estop_exti,
                board.exposure_exti,
                board.home_exti,
            ),
        },
        profile.camera.exposure_active_low,
    );
    let lights_out = LightsOut::new(board.deadline_timer);

    static TX_BUF: StaticCell<[u8; 1024]> = StaticCell::new();
    static RX_BUF: StaticCell<[u8; 1024]> = StaticCell::new();
    let mut link_config = usart::Config::default();
    link_config.baudrate = BAUD;
    let link = defmt::unwrap!(BufferedUart::new(
        board.usart,
        board.usart_rx,
        board.usart_tx,
        TX_BUF.init([0; 1024]),
        RX_BUF.init([0; 1024]),
        Irqs,
        link_config,
    ));
    {
        use embassy_stm32::interrupt::InterruptExt;
        interrupt::USART2.set_priority(PRIO_LINK);
    }

    let mut hardware = rig::Hardware::new(stepper, galvo, camera, store, lights_out, inputs);
    if let Some(profile) = stored {
        hardware.apply_profile(&profile);
    }
    spawner.spawn(defmt::unwrap!(rig::run(
        link,
        hardware,
        stored,
        boot_nonce()
    )));
}

/// FLASH_OPTCR.BOR_LEV for brown-out reset level 3 (RM0390 §3.7.1: 0b00 = level 3, 0b11 = off,
/// the factory setting, which leaves only the power-on/power-down reset at about 1.7 V).
const BOR_LEVEL_3: u8 = 0b00;

/// Brown-out reset at level 3 (VBOR3, 2.70 V typical falling, STM32F446 datasheet "Embedded
/// reset and power control block characteristics"): 168 MHz with 5 flash wait states is only
/// specified for VDD 2.7–3.6 V (RM0390 Table 5, "Number of wait states according to CPU clock
/// frequency"), and so is the ×32 erase the profile store uses. Below that the chip may execute
/// garbage with the laser pins in any state, so it must be held in reset instead. The option byte
/// is written here once per board (it survives resets, power cycles and reflashing), before the
/// watchdog runs, and takes effect at the next reset; `defmt` logs the level at every boot.
fn ensure_brown_out_level() {
    let f = embassy_stm32::pac::FLASH;
    let level = f.optcr().read().bor_lev();
    if level == BOR_LEVEL_3 {
        defmt::info!("brown-out reset at level 3 (2.7 V)");
        return;
    }
    defmt::warn!(
        "brown-out reset level {=u8} (BOR_LEV), not 3: programming the option byte",
        level
    );
    cortex_m::interrupt::free(|_| {
        while f.sr().read().bsy() {}
        if f.optcr().read().optlock() {
            f.optkeyr().write_value(0x0819_2A3B);
            f.optkeyr().write_value(0x4C5D_6E7F);
        }
        f.optcr().modify(|w| w.set_bor_lev(BOR_LEVEL_3));
        f.optcr().modify(|w| w.set_optstrt(true));
        while f.sr().read().bsy() {}
        f.optcr().modify(|w| w.set_optlock(true));
    });
    if f.optcr().read().bor_lev() != BOR_LEVEL_3 {
        defmt::error!("brown-out level not programmed (option bytes locked?)");
    }
}

/// Survives a reset (not a power cycle): counts resets, so the boot nonce differs after every
/// watchdog or software reset even where RAM contents repeat.
#[unsafe(link_section = ".uninit.BOOT_COUNT")]
static mut BOOT_COUNT: core::mem::MaybeUninit<u32> = core::mem::MaybeUninit::uninit();

/// A number that differs from one boot to the next, for the core's sessions (the host detects a
/// reboot by it). The STM32F446 has no hardware RNG: this mixes a reset counter kept in
/// uninitialised RAM (random after power-on, incremented by every reset), the chip's unique ID and
/// the boot time so far, through FNV-1a.
fn boot_nonce() -> u32 {
    // SAFETY: single-threaded start-up, before any task runs; the static is only touched here,
    // and any bit pattern is a valid u32.
    let count = unsafe {
        let slot = &mut *core::ptr::addr_of_mut!(BOOT_COUNT);
        let next = slot.assume_init_read().wrapping_add(1);
        slot.write(next);
        next
    };
    let uid = embassy_stm32::uid::uid();
    let now = embassy_time::Instant::now().as_ticks();
    let mut hash: u32 = 0x811c_9dc5;
    for byte in count
        .to_le_bytes()
        .iter()
        .chain(uid.iter())
        .chain(now.to_le_bytes().iter())
    {
        hash = (hash ^ u32::from(*byte)).wrapping_mul(0x0100_0193);
    }
    hash
}

/// 168 MHz from the internal oscillator (no dependency on the ST-LINK's 8 MHz clock output):
/// HSI 16 MHz / 8 × 168 / 2. APB1 = 42 MHz (timers 84 MHz), APB2 = 84 MHz.
fn clock_config() -> embassy_stm32::Config {
    use embassy_stm32::rcc::{
        AHBPrescaler, APBPrescaler, Pll, PllMul, PllPDiv, PllPreDiv, PllQDiv, PllSource, Sysclk,
    };
    let mut config = embassy_stm32::Config::default();
    config.rcc.hsi = true;
    config.rcc.pll_src = PllSource::HSI;
    config.rcc.pll = Some(Pll {
        prediv: PllPreDiv::DIV8,
        mul: PllMul::MUL168,
        divp: Some(PllPDiv::DIV2),
        divq: Some(PllQDiv::DIV7),
        divr: None,
    });
    config.rcc.ahb_pre = AHBPrescaler::DIV1;
    config.rcc.apb1_pre = APBPrescaler::DIV4;
    config.rcc.apb2_pre = APBPrescaler::DIV2;
    config.rcc.sys = Sysclk::PLL1_P;
    config
}

/// Pets the independent watchdog while the rig task keeps looping (it wakes at least every
/// [`rig::MAX_SLEEP`]); a stuck task or executor stops the petting and the chip resets with the
/// laser pins inputs (their reset state: off by the wiring's resistors).
#[embassy_executor::task]
async fn watchdog_task(mut watchdog: IndependentWatchdog<'static, peripherals::IWDG>) {
    let mut last = RIG_ALIVE.load(Ordering::Relaxed);
    let mut stalled_for = Duration::from_ticks(0);
    loop {
        Timer::after_millis(100).await;
        let now = RIG_ALIVE.load(Ordering::Relaxed);
        if now != last {
            last = now;
            stalled_for = Duration::from_ticks(0);
        } else {
            stalled_for += Duration::from_millis(100);
        }
        // Before the rig task has started (or if it stalls), give it a grace period once.
        if stalled_for < rig::MAX_SLEEP * 2 {
            watchdog.pet();
        }
    }
}

/// Lasers and trigger parked (high-impedance) and stepper stopped, then report the panic over defmt and fault
/// (probe-rs stops there with a backtrace; without a debugger the watchdog resets the chip).
/// panic-probe is not used because it cannot switch the lasers off first.
#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    park_lights();
    stepper::fault_stop();
    defmt::error!("panic: {}", defmt::Display2Format(info));
    cortex_m::asm::udf()
}

/// Any fault (bad memory access, undefined instruction, the panic above): lasers and trigger
/// parked (high-impedance), stepper stopped, then wait for the watchdog reset.
///
/// Under a debug probe the pins are parked first too: the probe's vector catch on HardFault
/// (DEMCR.VC_HARDERR, which `probe-rs run` sets) would halt the core *before* this handler, with a
/// laser left on by its timer, so `main` clears it ([`hardfault_runs_first`]) and this handler
/// breaks into the attached debugger itself once the pins are parked.
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    park_and_wait()
}

/// An interrupt or exception nothing was bound to (cortex-m-rt's default would spin at that
/// vector's priority, maybe above the light's deadline timer, with a laser on until the
/// watchdog): park every output first, then wait for the watchdog as a HardFault does.
#[cortex_m_rt::exception]
unsafe fn DefaultHandler(_irqn: i16) -> ! {
    park_and_wait()
}

/// The non-maskable interrupt (on this chip: the clock security system, unused, or a pended
/// NMI): the same.
#[cortex_m_rt::exception]
unsafe fn NonMaskableInt() -> ! {
    park_and_wait()
}

/// Every fault vector: lasers and trigger parked, stepper stopped, through registers only; then
/// a breakpoint when a debugger is attached, else a spin until the watchdog resets the chip.
fn park_and_wait() -> ! {
    park_lights();
    stepper::fault_stop();
    // SAFETY: a read of the core's debug status register.
    let debugger = unsafe { (*cortex_m::peripheral::DCB::PTR).dhcsr.read() } & 1 != 0;
    if debugger {
        cortex_m::asm::bkpt();
    }
    loop {
        cortex_m::asm::nop();
    }
}

/// FLASH_ACR with the ART accelerator on: prefetch, instruction and data caches (RM0390 §3.4.2).
/// embassy-stm32's clock set-up writes the whole register with the wait states only, which turns
/// all three off; at 168 MHz and 5 wait states every flash fetch would stall the step interrupt.
/// Caches are reset while off, then enabled. The profile store's own erase resets the data cache
/// again afterwards (`store.rs`), so a read-back never sees stale data.
fn enable_flash_accelerator() {
    let f = embassy_stm32::pac::FLASH;
    f.acr().modify(|w| {
        w.set_icen(false);
        w.set_dcen(false);
    });
    f.acr().modify(|w| {
        w.set_icrst(true);
        w.set_dcrst(true);
    });
    f.acr().modify(|w| {
        w.set_icrst(false);
        w.set_dcrst(false);
    });
    f.acr().modify(|w| {
        w.set_prften(true);
        w.set_icen(true);
        w.set_dcen(true);
    });
}

/// What a debug halt stops (DBGMCU_APB1_FZ / APB2_FZ, RM0390 §33.16.4-5), written at every boot
/// since a probe's own configuration may have set other bits:
/// - the step timer and its update counter (TIM2, TIM4) freeze: TIM2 would otherwise replay its
///   last preloaded period for the whole halt, stepping the motor with nobody feeding it;
/// - the laser and trigger timers (TIM8, TIM3) keep running, so a timed window that is on at the
///   halt still ends at its match in hardware (frozen, it would hold its laser on);
/// - the light's deadline timer (TIM5) keeps counting (its cut runs at once on resume) and the
///   independent watchdog keeps running, so a halt longer than its timeout resets the chip and
///   every pin returns to its reset state (off). A laser switched on by software (`laser on`)
///   has no timer to end it: on this silicon nothing but that watchdog reset turns it off
///   during a halt (the bring-up checklist says so).
fn freeze_steps_on_halt() {
    let d = embassy_stm32::pac::DBGMCU;
    d.apb1fzr().modify(|w| {
        w.set_tim2(true);
        w.set_tim4(true);
        w.set_tim3(false);
        w.set_tim5(false);
        w.set_iwdg(false);
    });
    d.apb2fzr().modify(|w| w.set_tim8(false));
}

/// Clear the debugger's vector catch on HardFault (DEMCR bit 10, VC_HARDERR; ARMv7-M ARM
/// C1.6.5), so a fault always runs [`HardFault`], which parks the pins before it halts.
fn hardfault_runs_first() {
    // SAFETY: a read-modify-write of DEMCR at start-up, before any task runs; only the
    // vector-catch bit changes.
    unsafe {
        let dcb = &*cortex_m::peripheral::DCB::PTR;
        dcb.demcr.modify(|w| w & !(1 << 10));
    }
}
