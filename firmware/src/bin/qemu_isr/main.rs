//! The step interrupt's cost per step, counted in Cortex-M4 instructions under QEMU, and the
//! planner's cost per planned step.
//!
//! Run with `qemu-system-arm -M mps2-an386 -icount shift=0 ...`: with `-icount shift=0` every
//! guest instruction advances QEMU's virtual clock by exactly 1 ns, and SysTick counts that clock,
//! so SysTick ticks measure executed instructions (the ratio is calibrated against a loop of known
//! length). The interrupt body is the board's own (`pulse_train::on_interrupt` in the same
//! critical-section mutex, with the same register accesses, here on a block of RAM standing in
//! for TIM2 and GPIOA), run from a real exception (PendSV) so the entry and return code count too;
//! the loop that raises the exception is measured alone and subtracted. Exception stacking is
//! hardware, not instructions: BENCHMARKS.md adds its cycles.
//!
//! Exits 0 when the interrupt stays within [`ISR_BUDGET`] instructions per step (so CI notices a
//! regression), 1 otherwise.
#![no_std]
#![no_main]

#[path = "../board/pulse_train.rs"]
#[allow(dead_code)]
mod pulse_train;

use core::cell::RefCell;
use core::ptr::{addr_of_mut, read_volatile, write_volatile};
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use cortex_m::peripheral::SCB;
use cortex_m::peripheral::syst::SystClkSource;
use cortex_m_rt::{entry, exception};
use cortex_m_semihosting::{debug, hprintln};
use critical_section::Mutex;
use pulse_train::{Preload, PulseTrain, Push, StepTimer, TICKS_PER_US, on_interrupt};
use subsurf_firmware::hal::StepSegment;
use subsurf_firmware::planner::StepPlanner;
use subsurf_firmware::profile::Profile;

/// Most instructions per step the interrupt may take (CI fails above): with three cycles per
/// instruction and 24 of exception entry and return, 256 instructions stay under 800 cycles, 20 %
/// of a 168 MHz core at 40 kHz.
const ISR_BUDGET: u32 = 256;

/// Interrupts per measured chunk (the queue is refilled between chunks, untimed).
const CHUNK: u32 = 3_000;
const CHUNKS: u32 = 20;

static TRAIN: Mutex<RefCell<PulseTrain>> = Mutex::new(RefCell::new(PulseTrain::new()));
static PULSES: AtomicU32 = AtomicU32::new(0);
static DIR_INVERT: AtomicBool = AtomicBool::new(false);
/// PendSV runs the step interrupt (`true`) or returns at once (the loop's own cost).
static RUN_ISR: AtomicBool = AtomicBool::new(false);

/// RAM in place of TIM2's SR, ARR, CCR1, CR1, GPIOA's BSRR and TIM4's CNT (the update count).
#[repr(C)]
struct Regs {
    sr: u32,
    arr: u32,
    ccr: u32,
    cr1: u32,
    bsrr: u32,
    updates: u32,
}

static mut REGS: Regs = Regs {
    sr: 0,
    arr: 0,
    ccr: 0,
    cr1: 1,
    bsrr: 0,
    updates: 0,
};

fn regs() -> *mut Regs {
    addr_of_mut!(REGS)
}

/// The board's `Tim2`, register for register, on RAM.
struct RamTim;

impl StepTimer for RamTim {
    #[inline(always)]
    fn take_update(&mut self) -> bool {
        // SAFETY: REGS is plain RAM, touched only by this handler and the bench loop, never at
        // the same time (the loop waits for the exception).
        unsafe {
            let sr = addr_of_mut!((*regs()).sr);
            if read_volatile(sr) & 1 == 0 {
                return false;
            }
            write_volatile(sr, read_volatile(sr) & !1);
        }
        true
    }

    #[inline(always)]
    fn set_dir(&mut self, forward: bool) {
        let bit = if forward != DIR_INVERT.load(Ordering::Relaxed) {
            1 << 1
        } else {
            1 << 17
        };
        // SAFETY: as above.
        unsafe { write_volatile(addr_of_mut!((*regs()).bsrr), bit) };
    }

    #[inline(always)]
    fn preload(&mut self, p: Preload) {
        // SAFETY: as above.
        unsafe {
            write_volatile(addr_of_mut!((*regs()).arr), p.arr);
            write_volatile(addr_of_mut!((*regs()).ccr), p.ccr);
        }
    }

    #[inline(always)]
    fn stop(&mut self) {
        // SAFETY: as above.
        unsafe {
            let cr1 = addr_of_mut!((*regs()).cr1);
            write_volatile(cr1, read_volatile(cr1) & !1);
        }
    }

    #[inline(always)]
    fn updates(&mut self) -> u16 {
        // SAFETY: as above.
        unsafe { read_volatile(addr_of_mut!((*regs()).updates)) as u16 }
    }
}

/// The board's `StepInterrupt::on_interrupt`, on PendSV.
#[exception]
fn PendSV() {
    if !RUN_ISR.load(Ordering::Relaxed) {
        return;
    }
    critical_section::with(|cs| {
        let Ok(mut train) = TRAIN.borrow(cs).try_borrow_mut() else {
            return;
        };
        if let Some(update) = on_interrupt(&mut train, &mut RamTim)
            && update.stepped
        {
            PULSES.fetch_add(1, Ordering::Relaxed);
        }
    });
}

/// SysTick's current value (counts down, 24 bits).
fn systick() -> u32 {
    cortex_m::peripheral::SYST::get_current()
}

fn elapsed(start: u32, end: u32) -> u32 {
    start.wrapping_sub(end) & 0x00ff_ffff
}

/// Raise the update flag and the exception `n` times; SysTick ticks taken.
#[inline(never)]
fn pend_loop(n: u32) -> u32 {
    let start = systick();
    for _ in 0..n {
        // SAFETY: as in `RamTim`.
        unsafe {
            write_volatile(addr_of_mut!((*regs()).sr), 1);
            let updates = addr_of_mut!((*regs()).updates);
            write_volatile(updates, read_volatile(updates).wrapping_add(1));
        }
        SCB::set_pendsv();
        cortex_m::asm::dsb();
        cortex_m::asm::isb();
    }
    elapsed(start, systick())
}

/// `n` iterations of a two-instruction loop: 2n instructions, for the tick calibration.
#[inline(never)]
fn known_loop(n: u32) -> u32 {
    let start = systick();
    // SAFETY: a register-only countdown loop.
    unsafe {
        core::arch::asm!(
            "2:",
            "subs {0}, {0}, #1",
            "bne 2b",
            inout(reg) n => _,
            options(nomem, nostack),
        );
    }
    elapsed(start, systick())
}

/// Fill the train's queue with segments of an acceleration ramp and a cruise at 40 kHz.
fn fill(now: u64, next_at: &mut u64, k: &mut u32) {
    critical_section::with(|cs| {
        let mut train = TRAIN.borrow(cs).borrow_mut();
        while train.queued_segments() < pulse_train::QUEUE_LEN - 1 {
            // Alternate ramp segments (add = -1 tick per step) and cruise segments.
            let interval = 25 * TICKS_PER_US;
            let add = if k.is_multiple_of(2) { -1 } else { 0 };
            let seg = StepSegment {
                first_at: *next_at,
                interval,
                add,
                count: 100,
                forward: true,
            };
            *next_at = seg.last_at() + u64::from(interval);
            *k += 1;
            match train.push(&seg, now) {
                Push::Queued | Push::Start { .. } => {}
                Push::Full => break,
            }
        }
    });
}

#[entry]
fn main() -> ! {
    let mut p = cortex_m::Peripherals::take().unwrap_or_else(|| {
        loop {
            cortex_m::asm::nop();
        }
    });
    p.SYST.set_clock_source(SystClkSource::Core);
    p.SYST.set_reload(0x00ff_ffff);
    p.SYST.clear_current();
    p.SYST.enable_counter();

    // Instructions per SysTick tick.
    let calib_n = 1_000_000;
    let ticks = known_loop(calib_n).max(1);
    let per_tick = f64::from(2 * calib_n) / f64::from(ticks);

    // Start the train, then measure the bare loop and the loop with the interrupt in chunks.
    let (mut next_at, mut k) = (1_000 * u64::from(TICKS_PER_US), 0u32);
    fill(0, &mut next_at, &mut k);
    let (mut base, mut full) = (0u64, 0u64);
    for _ in 0..CHUNKS {
        fill(0, &mut next_at, &mut k);
        RUN_ISR.store(false, Ordering::Relaxed);
        base += u64::from(pend_loop(CHUNK));
        // The untimed updates above were not handled: take the hardware count as handled.
        // SAFETY: as in `RamTim`.
        let seen = unsafe { read_volatile(addr_of_mut!((*regs()).updates)) } as u16;
        critical_section::with(|cs| TRAIN.borrow(cs).borrow_mut().sync_updates(seen));
        RUN_ISR.store(true, Ordering::Relaxed);
        full += u64::from(pend_loop(CHUNK));
    }
    let calls = f64::from(CHUNK * CHUNKS);
    let steps = PULSES.load(Ordering::Relaxed);
    let isr = (full.saturating_sub(base)) as f64 * per_tick / calls;

    // The planner: one default move (20 000 steps/s, 200 000 steps/s², 16 000 steps) planned
    // ahead as the rig task does, every 5 ms of its time.
    let profile = Profile::new(16_000, 20_000, 200_000);
    let mut planner = StepPlanner::new(TICKS_PER_US, 10);
    let (mut planned, mut segments, mut plan_ticks) = (0u32, 0u32, 0u64);
    if let Some(profile) = profile {
        let mut index = 1u32;
        let mut now = 0u64;
        while planned < profile.steps() && now < 10_000_000 {
            planner.take_due(now);
            let mut ideal = || {
                (index <= profile.steps()).then(|| {
                    let t = profile.step_time_us(index);
                    index += 1;
                    t
                })
            };
            let mut queue = |_s: StepSegment| {
                segments += 1;
                true
            };
            let start = systick();
            planned += planner.refill(now, true, &mut ideal, &mut queue);
            plan_ticks += u64::from(elapsed(start, systick()));
            now += 5_000;
        }
    }
    let plan = plan_ticks as f64 * per_tick / f64::from(planned.max(1));
    // Of which the profile's ideal step times alone.
    let mut ideal_ticks = 0u64;
    let mut sink = 0u64;
    if let Some(profile) = profile {
        let start = systick();
        for k in 1..=profile.steps() {
            sink = sink.wrapping_add(profile.step_time_us(core::hint::black_box(k)));
            if k % 1_000 == 0 {
                ideal_ticks += u64::from(elapsed(start, systick()));
            }
        }
        ideal_ticks = u64::from(elapsed(start, systick())).max(ideal_ticks.min(1));
    }
    core::hint::black_box(sink);
    let ideal = ideal_ticks as f64 * per_tick / f64::from(planned.max(1));

    hprintln!(
        "subsurf-qemu-isr: {} instructions per SysTick tick (calibration)",
        per_tick
    );
    hprintln!(
        "subsurf-qemu-isr: step interrupt {} instructions per step ({} interrupts, {} steps counted, budget {})",
        isr,
        CHUNK * CHUNKS,
        steps,
        ISR_BUDGET
    );
    hprintln!(
        "subsurf-qemu-isr: planner {} instructions per planned step, {} of them the profile's step time ({} steps in {} segments)",
        plan,
        ideal,
        planned,
        segments
    );
    let ok = isr > 0.0 && isr <= f64::from(ISR_BUDGET) && steps >= CHUNK * CHUNKS - 10;
    debug::exit(if ok {
        debug::EXIT_SUCCESS
    } else {
        debug::EXIT_FAILURE
    });
    #[allow(clippy::empty_loop)]
    loop {}
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    hprintln!("subsurf-qemu-isr: panic: {}", info);
    debug::exit(debug::EXIT_FAILURE);
    #[allow(clippy::empty_loop)]
    loop {}
}
