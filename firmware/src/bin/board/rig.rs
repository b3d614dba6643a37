//! The rig task: pumps the sans-IO core (`subsurf_firmware::Rig`) with link bytes, input changes
//! and its own deadlines, and implements the core's hardware traits on the board's drivers.
//!
//! Timing: every deadline the core asks for is run with `now` = that deadline, so each step the
//! core emits carries its scheduled time. Steps go to the hardware step generator with exactly the
//! scheduled spacing, one fixed [`STEP_PIPELINE_US`] later than scheduled (the queue that absorbs
//! the task's wake-up latency). Once the core reports a move finished, requests are held back until
//! the last queued step has left the timer, so nothing (a laser, a capture) overlaps a moving motor.
use core::sync::atomic::Ordering;

use embassy_futures::select::{Either, Either3, select, select3};
use embassy_stm32::pac;
use embassy_stm32::usart::{BufferedUart, BufferedUartRx, BufferedUartTx};
use embassy_time::{Duration, Instant, Timer, with_timeout};
use embedded_io_async::{Read, Write};
use static_cell::StaticCell;
use subsurf_firmware::hal::{
    CameraEdge, CameraInput, CameraTrigger, GalvoDac, LaserOutputs, RigInputs, Stepper,
};
use subsurf_firmware::{Micros, Rig};
use subsurf_protocol::{
    Config, EventKind, GalvoPoint, Inputs, MAX_FRAME, RigMessage, RigProfile, encode_event,
    encode_reply,
};

use crate::inputs;
use crate::outputs::{self, GALVO_MAX, Galvo, Lasers};
use crate::pulse_train::interval_for;
use crate::stepper::{self, StepGen};

/// The rig task wakes at least this often (the watchdog task expects it).
pub const MAX_SLEEP: Duration = Duration::from_millis(50);

/// Steps leave the timer this long after the core scheduled them (the first step of a motion is
/// started this far ahead; later ones keep their exact spacing).
pub const STEP_PIPELINE_US: u32 = 1_000;

/// The profile this board runs until one is sent: the documented wiring on the internal 12-bit
/// DAC (the output this binary drives), 300 µs per 1000 codes.
pub const PROFILE: RigProfile = RigProfile {
    galvo: RigProfile::INTERNAL_DAC,
    ..RigProfile::DEFAULT
};
const _: () = assert!(GALVO_MAX == PROFILE.galvo.output.max_code());

/// This boot's nonce. The F446 has no RNG: the chip's unique ID mixed with the µs clock when the
/// rig task starts (after clock and peripheral start-up, whose length jitters). Reboot detection
/// does not rest on it alone: until a `Hello`, the core refuses every request with `NoSession`.
fn boot_nonce() -> u32 {
    let uid = embassy_stm32::uid::uid();
    let mut h: u32 = 0x811c_9dc5;
    for b in uid.iter().chain((now_us() as u32).to_le_bytes().iter()) {
        h = (h ^ u32::from(*b)).wrapping_mul(0x0100_0193);
    }
    h
}

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
    pub lasers: Lasers,
    pub trigger: outputs::CameraTrigger,
    /// Core time of the call in progress (set before every call into the core).
    pub now: Micros,
    /// Scheduled time of the previous step.
    last_step_at: Micros,
}

impl Hardware {
    pub fn new(
        stepper: StepGen,
        galvo: Galvo,
        lasers: Lasers,
        trigger: outputs::CameraTrigger,
    ) -> Self {
        Self {
            stepper,
            galvo,
            lasers,
            trigger,
            now: 0,
            last_step_at: 0,
        }
    }
}

impl Stepper for Hardware {
    fn step(&mut self, forward: bool) {
        if sample_inputs().estop {
            // The e-stop task already stopped the timer; do not restart it before the core has
            // seen the e-stop and halted the motion.
            return;
        }
        let interval = interval_for(
            self.now,
            self.last_step_at,
            self.stepper.is_running(),
            STEP_PIPELINE_US,
            now_us().saturating_sub(self.now),
        );
        self.last_step_at = self.now;
        // The queue holds 12.8 ms of steps at full speed and the pipeline keeps 1 ms in it, so a
        // full queue means the timer stopped draining: give up after ~1 s rather than hang.
        for _ in 0..1_000 {
            if self.stepper.push(interval, forward) {
                return;
            }
            embassy_time::block_for(Duration::from_millis(1));
        }
        defmt::error!("step queue stuck; step dropped");
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
        for channel in 0..self.lasers.count() {
            self.lasers
                .set(channel, allowed && mask & (1 << channel) != 0);
        }
    }
}

impl CameraTrigger for Hardware {
    fn set_trigger(&mut self, high: bool) {
        self.trigger.set(high);
    }
}

impl CameraInput for Hardware {
    fn poll_camera_edge(&mut self) -> Option<CameraEdge> {
        inputs::take_exposure_edge()
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

/// The rig task.
#[embassy_executor::task]
pub async fn run(link: BufferedUart<'static>, hw: Hardware) {
    let (mut tx, mut rx): (BufferedUartTx<'static>, BufferedUartRx<'static>) = link.split();
    static RIG: StaticCell<Rig<Hardware>> = StaticCell::new();
    let nonce = boot_nonce();
    let rig = RIG.init_with(|| Rig::new(hw, PROFILE, Config::DEFAULT, nonce, now_us()));
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
        let wake = rig
            .poll_timeout()
            .unwrap_or(Micros::MAX)
            .min(now.saturating_add(MAX_SLEEP.as_micros()));
        let woke = select3(
            rx.read(&mut rx_buf),
            Timer::at(Instant::from_micros(wake)),
            inputs::CHANGED.wait(),
        )
        .await;
        // Deadlines that came while we slept run first, each at its own time: handling bytes at
        // the later wall-clock time first would make the core emit the missed steps as a burst.
        run_due(rig);
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
