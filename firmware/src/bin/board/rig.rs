//! The rig task: pumps the sans-IO core (`subsurf_firmware::Rig`) with link bytes, input changes
//! and its own deadlines, and implements the core's hardware traits on the board's drivers.
//!
//! Timing: every deadline the core asks for is run with `now` = that deadline, so each step the
//! core emits carries its scheduled time. Steps go to the hardware step generator with their
//! absolute target, one fixed [`STEP_PIPELINE_US`] after the scheduled time (the queue that absorbs
//! the task's wake-up latency). While a move runs the task wakes at most every
//! [`crate::pulse_train::BATCH_US`] and queues every step due meanwhile, so the executor wakes once
//! per batch, not once per step; the timer interrupt expands the queued segments. A step that
//! missed its time (the timer ran dry mid-motion) is a stall: the motion is stopped and the core
//! halted. Once the core reports a move finished, requests are held back until the last queued
//! step has left the timer, so nothing (a laser, a capture) overlaps a moving motor.
use core::sync::atomic::Ordering;

use embassy_futures::select::{Either, Either3, select, select3};
use embassy_stm32::pac;
use embassy_stm32::usart::{BufferedUart, BufferedUartRx, BufferedUartTx};
use embassy_time::{Duration, Instant, Timer, with_timeout};
use embedded_io_async::{Read, Write};
use static_cell::StaticCell;
use subsurf_firmware::hal::{CameraTrigger, GalvoDac, LaserOutputs, RigInputs, Stepper};
use subsurf_firmware::rig::MAX_PROGRAM_POINTS;
use subsurf_firmware::{Micros, Rig};
use subsurf_protocol::{
    Capabilities, Config, EventKind, GalvoPoint, Inputs, MAX_FRAME, RigMessage, encode_event,
    encode_reply,
};

use crate::inputs;
use crate::outputs::{CameraTiming, Galvo};
use crate::pulse_train::batch_wake;
use crate::stepper::{self, StepGen};

/// The rig task wakes at least this often (the watchdog task expects it).
pub const MAX_SLEEP: Duration = Duration::from_millis(50);

/// Steps leave the timer this long after the core scheduled them (the first step of a motion is
/// started this far ahead; later ones keep their exact spacing).
pub const STEP_PIPELINE_US: u64 = 1_000;

/// What this board announces: a 200-step motor at 1/16 microstepping through a 5:1 belt
/// (16 000 steps per turntable revolution), three laser channels; `galvo_max` comes from the galvo
/// output in use.
pub fn capabilities(galvo_max: u16, laser_channels: u8) -> Capabilities {
    Capabilities {
        steps_per_rev: 16_000,
        galvo_max,
        laser_channels,
        max_speed: 40_000,
        max_accel: 400_000,
        max_exposure_us: 2_000_000,
        max_program_points: MAX_PROGRAM_POINTS as u16,
    }
}

/// Settings at power-on (the host may change them with `SetConfig`).
pub const CONFIG: Config = Config {
    heartbeat_timeout_ms: 2_000,
    galvo_settle_min_us: 100,
    galvo_settle_per_kcode_us: 300,
    home_speed: 8_000,
    home_accel: 40_000,
    home_max_steps: 16_000 + 2_000,
};

/// Rig clock: µs since boot, from the embassy time driver (TIM12).
fn now_us() -> Micros {
    Instant::now().as_micros()
}

/// Safety inputs straight from the pins (not the EXTI tasks' flags, which lag by a task switch).
fn sample_inputs() -> Inputs {
    let pa = pac::GPIOA.idr().read();
    let pb = pac::GPIOB.idr().read();
    Inputs {
        // PB5: NC contact to GND, pull-up: high = pressed or broken wire.
        estop: pb.idr(5) == pac::gpio::vals::Idr::HIGH,
        // PB4: NC contact to GND, pull-up: low = enclosure closed.
        interlock_closed: pb.idr(4) == pac::gpio::vals::Idr::LOW,
        // PA10: switch to GND, pull-up: low = at home.
        home_switch: pa.idr(10) == pac::gpio::vals::Idr::LOW,
    }
}

/// The board's drivers as the core's hardware.
pub struct Hardware {
    pub stepper: StepGen,
    pub galvo: Galvo,
    pub camera: CameraTiming,
    /// Core time of the call in progress (set before every call into the core).
    pub now: Micros,
    /// Steps that missed their time since the last check.
    stalls: u32,
    /// The motion in progress stalled: its remaining steps are not emitted.
    stalled: bool,
}

impl Hardware {
    pub fn new(stepper: StepGen, galvo: Galvo, camera: CameraTiming) -> Self {
        Self {
            stepper,
            galvo,
            camera,
            now: 0,
            stalls: 0,
            stalled: false,
        }
    }
}

impl Stepper for Hardware {
    fn step(&mut self, forward: bool) {
        if sample_inputs().estop || self.stalled {
            // The EXTI interrupt already stopped the timer; do not restart it before the core
            // has seen the e-stop and halted the motion.
            return;
        }
        // Never blocks: a step that cannot be placed on time counts as a stall.
        self.stepper
            .push(self.now.saturating_add(STEP_PIPELINE_US), forward, now_us());
        self.stalls = self.stalls.saturating_add(self.stepper.take_stalls());
    }
}

impl GalvoDac for Hardware {
    fn set_galvo(&mut self, point: GalvoPoint) {
        self.galvo.set(point.x, point.y);
    }
}

impl LaserOutputs for Hardware {
    fn set_lasers(&mut self, mask: u8) {
        // Defence in depth: the core already refuses light with the e-stop pressed or the
        // interlock open; the pins are checked again here, at the last moment.
        let inputs = sample_inputs();
        let allowed = !inputs.estop && inputs.interlock_closed;
        self.camera.set_lasers(if allowed { mask } else { 0 });
    }
}

impl CameraTrigger for Hardware {
    fn set_trigger(&mut self, high: bool) {
        self.camera.set_trigger(high);
    }
}

impl RigInputs for Hardware {
    fn read_inputs(&mut self) -> Inputs {
        sample_inputs()
    }
}

/// Send every message the core has queued. A `Halted` event also empties the step queue: the
/// core stopped the motion (stop request, heartbeat loss, fault), so the steps still waiting in
/// the step pipeline must not run either.
async fn transmit(rig: &mut Rig<Hardware>, tx: &mut BufferedUartTx<'static>, frame: &mut [u8]) {
    while let Some(message) = rig.poll_message() {
        let encoded = match &message {
            RigMessage::Reply(reply) => encode_reply(reply, frame),
            RigMessage::Event(event) => {
                if let EventKind::Halted { reason } = event.kind {
                    stepper::force_stop();
                    defmt::warn!("halted: {}", reason);
                }
                encode_event(event, frame)
            }
        };
        let Ok(n) = encoded else {
            defmt::error!("message does not fit a frame; dropped");
            continue;
        };
        if let Some(bytes) = frame.get(..n)
            && tx.write_all(bytes).await.is_err()
        {
            defmt::warn!("link write failed");
        }
    }
}

/// Run every deadline that has come, each at its own scheduled time.
fn run_due(rig: &mut Rig<Hardware>) {
    let now = now_us();
    // Bounded: a deadline that does not move would otherwise spin here forever.
    for _ in 0..256 {
        match rig.poll_timeout() {
            Some(due) if due <= now => {
                rig.hw_mut().now = due;
                rig.handle_timeout(due);
            }
            _ => break,
        }
    }
}

/// Stop the motion after a step stall: the motor is off its schedule, so the core halts it (as a
/// `Stop` would) and the host sees the halt.
fn check_stalls(rig: &mut Rig<Hardware>) {
    let stalls = core::mem::take(&mut rig.hw_mut().stalls);
    if stalls > 0 {
        let queued = rig.hw().stepper.queued_segments();
        stepper::force_stop();
        defmt::error!(
            "step stall: {} steps missed their time ({} segments queued); motion halted",
            stalls,
            queued
        );
        rig.hw_mut().stalled = true;
    }
    if !rig.moving() {
        rig.hw_mut().stalled = false;
    }
}

/// The rig task.
#[embassy_executor::task]
pub async fn run(link: BufferedUart<'static>, hw: Hardware) {
    let (mut tx, mut rx): (BufferedUartTx<'static>, BufferedUartRx<'static>) = link.split();
    static RIG: StaticCell<Rig<Hardware>> = StaticCell::new();
    let caps = capabilities(hw.galvo.max_code(), hw.camera.channels());
    let rig = RIG.init_with(|| Rig::new(hw, caps, CONFIG, now_us()));
    let mut last_wake = now_us();
    let mut rx_buf = [0u8; 64];
    let mut frame = [0u8; MAX_FRAME];
    let mut last_fault = None;
    defmt::info!("rig ready");
    loop {
        crate::RIG_ALIVE.fetch_add(1, Ordering::Relaxed);
        transmit(rig, &mut tx, &mut frame).await;
        if rig.fault() != last_fault {
            last_fault = rig.fault();
            defmt::warn!("fault: {}", last_fault);
        }

        if !rig.moving() && rig.hw().stepper.is_running() {
            // The core is done with the move but the last steps are still in the timer: hold
            // requests back, watch only the inputs, until the motor really stands still.
            let wait = select(stepper::REFILL.wait(), inputs::CHANGED.wait());
            let changed = matches!(with_timeout(MAX_SLEEP, wait).await, Ok(Either::Second(())));
            run_due(rig);
            if changed {
                let now = now_us();
                rig.hw_mut().now = now;
                rig.handle_inputs(now);
            }
            continue;
        }

        let now = now_us();
        let deadline = rig.poll_timeout().unwrap_or(Micros::MAX);
        // While a move runs, take its steps in batches (one wake per batch, not per step).
        let is_step = rig.moving() && rig.next_step_due() == Some(deadline);
        let wake =
            batch_wake(deadline, is_step, last_wake).min(now.saturating_add(MAX_SLEEP.as_micros()));
        let woke = select3(
            rx.read(&mut rx_buf),
            Timer::at(Instant::from_micros(wake)),
            inputs::CHANGED.wait(),
        )
        .await;
        last_wake = now_us();
        // Deadlines that came while we slept run first, each at its own time: handling bytes at
        // the later wall-clock time first would make the core emit the missed steps as a burst.
        run_due(rig);
        check_stalls(rig);
        match woke {
            Either3::First(Ok(n)) => {
                let now = now_us();
                rig.hw_mut().now = now;
                rig.handle_bytes(now, rx_buf.get(..n).unwrap_or(&[]));
            }
            Either3::First(Err(e)) => defmt::warn!("link read error: {}", e),
            Either3::Second(()) => {}
            Either3::Third(()) => {
                let now = now_us();
                rig.hw_mut().now = now;
                rig.handle_inputs(now);
            }
        }
    }
}
