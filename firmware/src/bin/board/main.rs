//! subsurf rig firmware for the Nucleo-F446RE (STM32F446RE, Cortex-M4F).
//!
//! The board binary only owns the hardware and pumps the sans-IO core (`subsurf_firmware`): bytes
//! from the USART2 link go into the core, its frames go back out, its hardware calls land on the
//! drivers in this directory, and its next deadline becomes an embassy timer. Every decision lives
//! in the core; the binary adds the fault paths the core cannot see (panic, HardFault, a hung
//! executor via the independent watchdog) and drives the lasers low on each of them.
//!
//! Build: `cargo fw`; flash: `subsurf flash` (or `cargo fw-run` with the probe-rs CLI).
#![no_std]
#![no_main]

// The timed-exposure path is driven by the core's exposure window (ExposureWindow, landing with
// the rig profile); until then captures use the software edges.
#[allow(dead_code)]
mod exposure;
mod galvo_map;
mod inputs;
mod outputs;
mod pins;
mod pulse_train;
mod rig;
mod safety;
mod stepper;

use core::sync::atomic::{AtomicU32, Ordering};

use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_stm32::exti::{self, ExtiInput};
use embassy_stm32::gpio::Pull;
use embassy_stm32::usart::{self, BufferedUart};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{bind_interrupts, interrupt, peripherals};
use embassy_time::{Duration, Timer};
use static_cell::StaticCell;

use crate::galvo_map::{GalvoMap, GalvoOutput};
use crate::outputs::{CameraTiming, Galvo, force_lasers_off};
use crate::pins::Board;
use crate::stepper::{StepGen, StepperIo};

bind_interrupts!(struct Irqs {
    USART2 => usart::BufferedInterruptHandler<peripherals::USART2>;
    TIM2 => stepper::StepInterrupt;
    TIM8_CC => outputs::TriggerInterrupt;
    // The laser cut-off runs first, in the interrupt, then embassy wakes the input tasks.
    EXTI4 => inputs::SafetyCut<interrupt::typelevel::EXTI4>,
        exti::InterruptHandler<interrupt::typelevel::EXTI4>;
    EXTI9_5 => inputs::SafetyCut<interrupt::typelevel::EXTI9_5>,
        exti::InterruptHandler<interrupt::typelevel::EXTI9_5>;
    EXTI15_10 => inputs::SafetyCut<interrupt::typelevel::EXTI15_10>,
        exti::InterruptHandler<interrupt::typelevel::EXTI15_10>;
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

/// Galvo output path: the external SPI DAC, or the internal DAC with `SUBSURF_GALVO=internal` at
/// build time.
const GALVO_OUTPUT: GalvoOutput = match option_env!("SUBSURF_GALVO") {
    Some(v) if const_eq(v, "internal") => GalvoOutput::InternalDac,
    Some(v) if const_eq(v, "spi") => GalvoOutput::ExternalSpi,
    None => GalvoOutput::ExternalSpi,
    Some(_) => panic!("SUBSURF_GALVO must be `spi` or `internal`"),
};

const fn const_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    let mut i = 0;
    while i < a.len() {
        if a[i] != b[i] {
            return false;
        }
        i += 1;
    }
    true
}

/// Watchdog timeout: a hung executor or a stalled rig task resets the chip after this long.
const WATCHDOG_TIMEOUT_US: u32 = 500_000;
/// Incremented by the rig task every loop; the watchdog task only pets while it moves.
pub static RIG_ALIVE: AtomicU32 = AtomicU32::new(0);

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    let p = embassy_stm32::init(clock_config());
    let board = Board::new(p);
    // First thing after the clocks: laser enables parked at their inactive level, trigger idle.
    let camera = CameraTiming::new(
        board.camera_timer,
        board.laser_r,
        board.camera_trigger,
        board.laser_g,
        board.laser_b,
        3,
        false,
        false,
    );
    defmt::info!(
        "subsurf firmware {} on STM32F446RE, link {} baud",
        env!("CARGO_PKG_VERSION"),
        BAUD
    );

    let mut watchdog = IndependentWatchdog::new(board.watchdog, WATCHDOG_TIMEOUT_US);
    watchdog.unleash();
    spawner.spawn(defmt::unwrap!(watchdog_task(watchdog)));

    let mut stepper = StepGen::new(
        board.step_timer,
        board.step,
        board.dir,
        board.enable,
        StepperIo {
            pulse_us: 5,
            step_active_low: false,
            invert_dir: false,
            enable_active_low: true,
        },
    );
    // Holding torque from here on keeps the position.
    stepper.set_enabled(true);
    let galvo = match GALVO_OUTPUT {
        GalvoOutput::ExternalSpi => Galvo::external(
            board.galvo_spi,
            board.galvo_sck,
            board.galvo_mosi,
            board.galvo_sync,
            GalvoMap::for_output(GALVO_OUTPUT),
        ),
        GalvoOutput::InternalDac => Galvo::internal(
            board.dac,
            board.galvo_x,
            board.galvo_y,
            GalvoMap::for_output(GALVO_OUTPUT),
        ),
    };

    let estop = ExtiInput::new(board.estop, board.estop_exti, Pull::Up, Irqs);
    let interlock = ExtiInput::new(board.interlock, board.interlock_exti, Pull::Up, Irqs);
    let home = ExtiInput::new(board.home, board.home_exti, Pull::Up, Irqs);
    let exposure = ExtiInput::new(board.exposure, board.exposure_exti, Pull::Down, Irqs);
    spawner.spawn(defmt::unwrap!(inputs::estop(estop)));
    spawner.spawn(defmt::unwrap!(inputs::interlock(interlock)));
    spawner.spawn(defmt::unwrap!(inputs::home(home)));
    spawner.spawn(defmt::unwrap!(inputs::exposure(exposure)));

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

    let hardware = rig::Hardware::new(stepper, galvo, camera);
    spawner.spawn(defmt::unwrap!(rig::run(link, hardware)));
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
/// lasers low.
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

/// Lasers low and stepper stopped, then report the panic over defmt and fault (probe-rs stops
/// there with a backtrace; without a debugger the watchdog resets the chip). panic-probe is not
/// used because it cannot switch the lasers off first.
#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    force_lasers_off();
    stepper::fault_stop();
    defmt::error!("panic: {}", defmt::Display2Format(info));
    cortex_m::asm::udf()
}

/// Any fault (bad memory access, undefined instruction, the panic above): lasers low, stepper
/// stopped, then wait for the watchdog reset.
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    force_lasers_off();
    stepper::fault_stop();
    loop {
        cortex_m::asm::nop();
    }
}
