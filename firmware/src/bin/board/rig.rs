//! The rig task: pumps the sans-IO core (`subsurf_firmware::Rig`) with link bytes, input changes
//! and its own deadlines, and implements the core's hardware traits on the board's drivers.
//!
//! Timing: every deadline the core asks for is run with `now` = that deadline. The core plans the
//! steps ahead (`subsurf_firmware::planner`): while a move runs it wakes every few milliseconds
//! and hands the step timer compressed segments for the next 10 ms, which the timer interrupt
//! emits on its own (never once per step in the executor). The core counts a step as done when
//! its planned time has come, so a move is finished only once its last step has left the timer.
//! A step that missed its time (the timer ran dry mid-motion) is a stall: the motion is stopped
//! and the core halted.
//!
//! Light: after every pass the task arms the light's deadline timer (`outputs::LightsOut`) a
//! little after the core's own laser-off deadline (`Rig::light_deadline`), so a stuck task cannot
//! keep a laser on; the exposure's edges are the timers' (`exposure.rs`). Safety edges the EXTI
//! interrupt latched are passed to the core as inputs and forgotten only once it has seen them.
use core::sync::atomic::{AtomicBool, Ordering};

use embassy_futures::select::{Either3, select3};
use embassy_stm32::pac;
use embassy_stm32::usart::{BufferedUart, BufferedUartRx, BufferedUartTx};
use embassy_time::{Duration, Instant, Timer};
use embedded_io_async::{Read, Write};
use static_cell::StaticCell;
use subsurf_firmware::hal::{
    CameraEdge, CameraInput, CameraTrigger, ExposureWindow, GalvoDac, LaserOutputs, ProfileStore,
    RigInputs, StepSegment, Stepper,
};
use subsurf_firmware::{Micros, Rig};
use subsurf_protocol::{
    Config, GalvoPoint, Inputs, MAX_FRAME, RigMessage, RigProfile, SaveError, encode_event,
    encode_reply,
};

use crate::exposure::{LaserCall, on_set_lasers, plan_window};
use crate::inputs::{self, InputPins};
use crate::notes::{self, Note, note};
use crate::outputs::{CameraIo, CameraTiming, Galvo, LightsOut, lights_out};
use crate::stepper::{StepGen, StepperIo};
use crate::store::Store;

/// The rig task wakes at least this often (the watchdog task expects it).
pub const MAX_SLEEP: Duration = Duration::from_millis(50);

/// Home switch is active low (from the rig profile).
static HOME_ACTIVE_LOW: AtomicBool = AtomicBool::new(true);

/// Rig clock: µs since boot, from the embassy time driver (TIM12).
fn now_us() -> Micros {
    Instant::now().as_micros()
}

/// Inputs straight from the pins, with the safety edges the EXTI interrupt latched: a press
/// shorter than a poll still reads as pressed until the core has seen it.
fn sample_inputs() -> Inputs {
    let pa = pac::GPIOA.idr().read();
    let safety = inputs::safety_pins();
    let latched = inputs::latched();
    Inputs {
        // PB5: NC contact to GND, pull-up: high = pressed or broken wire.
        estop: safety.estop_high || latched.estop,
        // PB4: NC contact to GND, pull-up: low = enclosure closed.
        interlock_closed: !safety.interlock_high && !latched.interlock,
        // PA10: the home switch, active level from the profile.
        home_switch: (pa.idr(10) == pac::gpio::vals::Idr::LOW)
            == HOME_ACTIVE_LOW.load(Ordering::Relaxed),
    }
}

/// The board's drivers as the core's hardware.
pub struct Hardware {
    pub stepper: StepGen,
    pub galvo: Galvo,
    pub camera: CameraTiming,
    store: Store,
    lights_out: LightsOut,
    _inputs: InputPins,
    /// Core time of the call in progress (set before every call into the core).
    pub now: Micros,
    /// Steps that missed their time since the last check.
    stalls: u32,
    /// Steps the core queued while the e-stop held the timer: never output, so a flush counts
    /// them as discarded.
    held: u32,
    /// Scheduled laser-off of the timed exposure in progress (until the core's laser-off).
    window_off_at: Option<Micros>,
    /// The profile the pins and timers are set up for (`None`: none known, nothing driven).
    applied: Option<RigProfile>,
}

impl Hardware {
    pub fn new(
        stepper: StepGen,
        galvo: Galvo,
        camera: CameraTiming,
        store: Store,
        lights_out: LightsOut,
        inputs: InputPins,
    ) -> Self {
        Self {
            stepper,
            galvo,
            camera,
            store,
            lights_out,
            _inputs: inputs,
            now: 0,
            stalls: 0,
            held: 0,
            window_off_at: None,
            applied: None,
        }
    }

    /// Put the board's I/O in line with a rig profile: STEP/DIR/EN, laser and trigger polarity,
    /// the galvo path, the camera's and the home switch's polarity. The core changes the profile
    /// only while idle, so nothing in flight changes shape.
    pub fn apply_profile(&mut self, profile: &RigProfile) {
        self.applied = Some(*profile);
        self.stepper.configure(StepperIo::from(&profile.motor));
        self.camera.configure(CameraIo {
            channels: profile.laser.channels,
            laser_active_low: profile.laser.active_low,
            trigger_active_low: profile.camera.trigger_active_low,
        });
        self.galvo.set_output(profile.galvo.output);
        inputs::set_exposure_active_low(profile.camera.exposure_active_low);
        HOME_ACTIVE_LOW.store(profile.homing.switch_active_low, Ordering::Relaxed);
        let pull = if profile.homing.switch_active_low {
            pac::gpio::vals::Pupdr::PULL_UP
        } else {
            pac::gpio::vals::Pupdr::PULL_DOWN
        };
        pac::GPIOA.pupdr().modify(|w| w.set_pupdr(10, pull));
    }
}

impl Stepper for Hardware {
    const TICKS_PER_US: u32 = crate::pulse_train::TICKS_PER_US;

    fn queue(&mut self, segment: StepSegment) -> bool {
        if sample_inputs().estop {
            // The EXTI interrupt stopped the timer; do not restart it before the core has seen
            // the e-stop and flushed.
            self.held = self.held.saturating_add(u32::from(segment.count));
            return true;
        }
        // Never blocks: a step that cannot be placed on time counts as a stall.
        let queued = self.stepper.queue(&segment, now_us());
        self.stalls = self.stalls.saturating_add(self.stepper.take_stalls());
        queued
    }

    fn flush(&mut self) -> u32 {
        let held = core::mem::take(&mut self.held);
        self.stepper.flush().saturating_add(held)
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
        // interlock open; the pins are checked again here, at the last moment, and nothing comes
        // on after the deadline timer cut the light.
        let inputs = sample_inputs();
        let allowed = !inputs.estop && inputs.interlock_closed && !lights_out();
        let window = self.window_off_at.take();
        let call = on_set_lasers(window, self.now, self.camera.timed_running(), allowed, mask);
        match call {
            LaserCall::LeaveToTimer => {}
            LaserCall::Apply(mask) => self.camera.set_lasers(mask, now_us()),
        }
    }

    fn lines_idle_off(&mut self, active_low: bool) -> bool {
        self.camera
            .laser_lines_idle_off(crate::safety::Polarity::from_active_low(active_low))
    }
}

impl CameraTrigger for Hardware {
    fn set_trigger(&mut self, high: bool) {
        if self.window_off_at.is_some() {
            // The timer owns this capture's trigger: a software edge now (the timer may already
            // be done) would be a second trigger, an extra image.
            return;
        }
        self.camera.set_trigger(high);
    }

    fn arm_window(&mut self, window: &ExposureWindow) {
        let lead = window.trigger_at.saturating_sub(window.laser_on_at);
        let after = window.laser_off_at.saturating_sub(window.trigger_at);
        match plan_window(lead, window.trigger_us, window.exposure_us, after) {
            Ok(plan) => {
                if self.camera.start(&plan, window.channel_mask, now_us()) {
                    let (rise, fall, off) = plan.edges_ns();
                    note(Note::TimedExposure(rise, fall, off));
                    self.window_off_at = Some(window.laser_off_at);
                }
            }
            Err(e) => note(Note::Untimeable(e)),
        }
    }
}

impl CameraInput for Hardware {
    fn poll_camera_edge(&mut self) -> Option<CameraEdge> {
        // The trigger edge the counter placed, once its time has come, then the camera's.
        if let Some(at) = self.camera.take_trigger_edge(now_us()) {
            return Some(CameraEdge::Trigger(at));
        }
        inputs::pop_edge()
    }
}

impl ProfileStore for Hardware {
    /// Write the record, then read flash back through the same path a boot takes: `Ok` only
    /// when it returns this profile (`flash_record::store_profile`). The core calls this inside
    /// `SetProfile` while idle and dark and answers with the outcome. A profile flash already
    /// holds is not written again (no wear, no erase stall).
    fn store_profile(&mut self, profile: &RigProfile) -> Result<(), SaveError> {
        match crate::flash_record::store_profile(&mut self.store, profile) {
            Ok(()) => {
                defmt::info!("rig profile in flash, read back");
                // Applied now, before the core runs the next request of the same received
                // chunk.
                self.apply_profile(profile);
                Ok(())
            }
            Err(e) => {
                defmt::error!("rig profile not stored: {}", e);
                Err(e)
            }
        }
    }

    fn stored_profile(&mut self) -> Option<RigProfile> {
        stored_profile(&self.store)
    }
}

impl RigInputs for Hardware {
    fn read_inputs(&mut self) -> Inputs {
        sample_inputs()
    }

    fn board_registers(&mut self) -> Option<subsurf_protocol::BoardRegisters> {
        Some(subsurf_protocol::BoardRegisters {
            flash_optcr: pac::FLASH.optcr().read().0,
            flash_acr: pac::FLASH.acr().read().0,
            dbgmcu_apb1_fz: pac::DBGMCU.apb1fzr().read().0,
            dbgmcu_apb2_fz: pac::DBGMCU.apb2fzr().read().0,
            tim2_cr2: pac::TIM2.cr2().read().0,
            tim4_smcr: pac::TIM4.smcr().read().0,
        })
    }
}

/// Send every message the core has queued. (A halt needs nothing here: the core decelerates a
/// stopped motion through its own steps and flushes the step queue on an emergency.)
async fn transmit(rig: &mut Rig<Hardware>, tx: &mut BufferedUartTx<'static>, frame: &mut [u8]) {
    while let Some(message) = rig.poll_message() {
        let encoded = match &message {
            RigMessage::Reply(reply) => encode_reply(reply, frame),
            RigMessage::Event(event) => encode_event(event, frame),
        };
        let Ok(n) = encoded else {
            note(Note::Oversized);
            continue;
        };
        if let RigMessage::Event(subsurf_protocol::Event {
            kind: subsurf_protocol::EventKind::Halted { reason },
            ..
        }) = &message
        {
            note(Note::Halt(*reason));
        }
        if let Some(bytes) = frame.get(..n)
            && tx.write_all(bytes).await.is_err()
        {
            note(Note::Link);
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

/// Energise the motor driver only with a stored profile (its EN polarity and mechanics are the
/// wiring's), the e-stop reading closed and its fault cleared; release it otherwise. Releasing
/// the e-stop alone does not energise it again: the core keeps `Fault::EmergencyStop` until the
/// host's `ClearFault` (which it refuses while the e-stop is still open), and only then does EN
/// come back. Holding torque keeps the position from then on; a press forgets it anyway
/// (`homed` cleared).
fn follow_enable(rig: &mut Rig<Hardware>) {
    let want =
        crate::safety::enable_allowed(rig.profile_known(), sample_inputs().estop, rig.fault());
    if rig.hw().stepper.energised() != want {
        note(Note::Motor(want));
        rig.hw_mut().stepper.set_enabled(want);
    }
}

/// A step interrupt ran after the following update event (the train stopped the timer): the
/// core faults with `StepLate`, clears `homed` and reports it (the timer repeated a stale
/// period: a step nobody counted).
fn check_overruns(rig: &mut Rig<Hardware>) {
    let overruns = rig.hw_mut().stepper.take_overruns();
    if overruns > 0 {
        note(Note::StepLate(overruns));
        let now = now_us();
        rig.hw_mut().now = now;
        rig.handle_step_late(now);
        if rig.hw().stepper.is_running() {
            let _ = rig.hw_mut().flush();
        }
    }
}

/// Hand step stalls to the core (fault, emergency stop, `homed` cleared). Also a stall: the
/// e-stop interrupt stopped the timer under a queued motion, or steps were held back, and the
/// e-stop is released before the core saw it (a glitch): those steps would never be output.
fn check_stalls(rig: &mut Rig<Hardware>) {
    let stalls = core::mem::take(&mut rig.hw_mut().stalls);
    let stopped =
        (rig.hw().stepper.stopped_under_motion() || rig.hw().held > 0) && !sample_inputs().estop;
    if stalls > 0 || stopped {
        note(Note::StepStall(stalls, rig.hw().stepper.queued_segments()));
        let now = now_us();
        rig.hw_mut().now = now;
        rig.handle_stall(now);
        if rig.hw().stepper.is_running() {
            // Not in a motion the core knows of: drop the queue here.
            let _ = rig.hw_mut().flush();
        }
    }
}

/// Put the board's I/O in line with the profile the core runs, as soon as it knows one (the core
/// accepts a new one only while idle).
fn apply_profile(rig: &mut Rig<Hardware>) {
    let profile = *rig.profile();
    if rig.profile_known() && rig.hw().applied != Some(profile) {
        rig.hw_mut().apply_profile(&profile);
    }
}

/// Keep the light's deadline timer a little behind the core's own laser-off deadline.
fn follow_light_deadline(rig: &mut Rig<Hardware>) {
    let deadline = rig.light_deadline();
    rig.hw_mut().lights_out.follow(deadline, now_us());
}

/// Hand the core the inputs now (a pin changed, or an edge was latched), then forget the edges
/// it has seen.
fn pass_inputs(rig: &mut Rig<Hardware>) {
    let edges = inputs::latched();
    let now = now_us();
    rig.hw_mut().now = now;
    rig.handle_inputs(now);
    inputs::passed_on(edges);
}

/// The profile stored in flash, if a valid one of this firmware's layout is
/// (`flash_record::decode_profile`).
pub fn stored_profile(store: &Store) -> Option<RigProfile> {
    let mut buf = [0u8; crate::flash_record::MAX_PAYLOAD];
    let profile = store
        .load(&mut buf)
        .and_then(crate::flash_record::decode_profile);
    match profile {
        Some(_) => defmt::info!("rig profile from flash"),
        None => defmt::warn!(
            "no valid rig profile in flash: documented defaults, lasers and trigger left \
             high-impedance until a profile is sent"
        ),
    }
    profile
}

/// The rig task.
#[embassy_executor::task]
pub async fn run(
    link: BufferedUart<'static>,
    hw: Hardware,
    stored: Option<RigProfile>,
    boot_nonce: u32,
) {
    let (mut tx, mut rx): (BufferedUartTx<'static>, BufferedUartRx<'static>) = link.split();
    static RIG: StaticCell<Rig<Hardware>> = StaticCell::new();
    let rig = RIG.init_with(|| match stored {
        Some(profile) => Rig::new(hw, profile, Config::DEFAULT, boot_nonce, now_us()),
        None => Rig::new_unconfigured(hw, Config::DEFAULT, boot_nonce, now_us()),
    });
    let mut rx_buf = [0u8; 64];
    let mut frame = [0u8; MAX_FRAME];
    let mut last_fault = None;
    defmt::info!("rig ready");
    loop {
        crate::RIG_ALIVE.fetch_add(1, Ordering::Relaxed);
        transmit(rig, &mut tx, &mut frame).await;
        follow_light_deadline(rig);
        if rig.fault() != last_fault {
            last_fault = rig.fault();
            note(Note::Fault(last_fault));
        }
        if !rig.hw().stepper.is_running() {
            // Log lines only while no step is emitted (`notes.rs`).
            notes::drain();
        }

        let now = now_us();
        let deadline = rig.poll_timeout().unwrap_or(Micros::MAX);
        let wake = deadline.min(now.saturating_add(MAX_SLEEP.as_micros()));
        let woke = select3(
            rx.read(&mut rx_buf),
            Timer::at(Instant::from_micros(wake)),
            inputs::CHANGED.wait(),
        )
        .await;
        // Deadlines that came while we slept run first, each at its own time.
        run_due(rig);
        rig.hw_mut().camera.park_when_done();
        follow_enable(rig);
        check_overruns(rig);
        check_stalls(rig);
        match woke {
            Either3::First(Ok(n)) => {
                let now = now_us();
                rig.hw_mut().now = now;
                rig.handle_bytes(now, rx_buf.get(..n).unwrap_or(&[]));
                apply_profile(rig);
            }
            Either3::First(Err(_)) => note(Note::Link),
            Either3::Second(()) => {}
            Either3::Third(()) => pass_inputs(rig),
        }
        if inputs::latched() != crate::safety::SafetyEdges::default() {
            // An edge latched while the core ran: let it see it now.
            pass_inputs(rig);
        }
    }
}
