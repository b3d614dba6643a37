//! `subsurf rig selftest`: the bring-up check a user runs on a real bench, step by step.
//!
//! Each step talks to the rig through the ordinary [`RigClient`] and says PASS, FAIL or SKIP with
//! what it measured: handshake, profile (stored on the rig, read back from its flash, and the one
//! the file says) and config read-back, a fault left from before (cleared only when the person
//! says so), homing twice (the second homing reports where the new zero lay in the first one's
//! coordinates), a move whose step count the home switch checks (not the rig's own counter), a
//! capture whose trigger the camera's exposure-active output confirms (trigger loopback), a galvo
//! sweep with a confirmed capture at each point, the enclosure interlock (seen open, arming
//! refused), the laser cut with a laser actually on (the person opens the interlock while it
//! shines), and the e-stop (pressed while a laser shines, with consent to light).
//!
//! Nothing emits light before the person has agreed ([`Prompt::consent`]; `--yes` agrees in
//! advance). Steps a person must watch or do ask through the [`Prompt`]; with no one to ask
//! (`--yes`, CI) they are skipped.

use std::time::Duration;

use subsurf_protocol::{
    Capture, EventKind, Fault, GalvoPoint, HaltReason, MoveTarget, RigError, RigProfile, Status,
};

use super::{RigClient, RigClientError};
use crate::link::ByteLink;

/// Asks the person at the bench.
pub trait Prompt {
    /// Ask a yes/no question; `None` = nobody to ask (the step is skipped).
    fn confirm(&mut self, question: &str) -> Option<bool>;
    /// Tell them to do something and wait until they say it is done; `false` = skip.
    fn wait_for(&mut self, instruction: &str) -> bool;
    /// Ask before anything emits light; only an explicit yes (or `--yes`) lets it happen.
    fn consent(&mut self, question: &str) -> bool;
    /// Tell them to do something now, without waiting for them (the self-test keeps the link
    /// alive and watches the rig meanwhile); `false` = nobody there.
    fn tell(&mut self, instruction: &str) -> bool;
}

/// No one at the bench: every interactive step is skipped, and nothing emits light.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoPrompt;

impl Prompt for NoPrompt {
    fn confirm(&mut self, _question: &str) -> Option<bool> {
        None
    }
    fn wait_for(&mut self, _instruction: &str) -> bool {
        false
    }
    fn consent(&mut self, _question: &str) -> bool {
        false
    }
    fn tell(&mut self, _instruction: &str) -> bool {
        false
    }
}

/// `--yes`: light agreed to in advance (the beam path is safe), nobody watching: the steps that
/// need a person are skipped.
#[derive(Debug, Default, Clone, Copy)]
pub struct AssumeYes;

impl Prompt for AssumeYes {
    fn confirm(&mut self, _question: &str) -> Option<bool> {
        None
    }
    fn wait_for(&mut self, _instruction: &str) -> bool {
        false
    }
    fn consent(&mut self, _question: &str) -> bool {
        true
    }
    fn tell(&mut self, _instruction: &str) -> bool {
        false
    }
}

/// How a step ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Checked and right.
    Pass,
    /// Checked and wrong.
    Fail,
    /// Not checked (needs a person, no consent to light, or an earlier step failed).
    Skip,
}

/// One step's result.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StepReport {
    /// Short name.
    pub name: &'static str,
    /// How it ended.
    pub verdict: Verdict,
    /// What was measured or why it failed.
    pub detail: String,
}

/// Every step's result, in order.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SelftestReport {
    /// The steps.
    pub steps: Vec<StepReport>,
}

impl SelftestReport {
    /// Whether no step failed.
    pub fn passed(&self) -> bool {
        self.steps.iter().all(|s| s.verdict != Verdict::Fail)
    }

    /// Steps with this verdict.
    pub fn count(&self, v: Verdict) -> usize {
        self.steps.iter().filter(|s| s.verdict == v).count()
    }
}

/// What the self-test expects.
#[derive(Debug, Clone)]
pub struct SelftestOptions {
    /// The profile the rig should be running (from the host's profile file), if any.
    pub expect_profile: Option<RigProfile>,
    /// Give up on homing after this long.
    pub home_timeout: Duration,
    /// Laser channel for the captures and the laser cut.
    pub channel: u8,
    /// How long the person has to open the interlock while the laser is on.
    pub act_within: Duration,
}

impl Default for SelftestOptions {
    fn default() -> Self {
        Self {
            expect_profile: None,
            home_timeout: Duration::from_secs(120),
            channel: 0,
            act_within: Duration::from_secs(20),
        }
    }
}

struct Steps {
    report: SelftestReport,
    progress: Box<dyn FnMut(&StepReport)>,
}

impl Steps {
    fn record(&mut self, name: &'static str, verdict: Verdict, detail: String) {
        let step = StepReport {
            name,
            verdict,
            detail,
        };
        (self.progress)(&step);
        self.report.steps.push(step);
    }

    fn result(&mut self, name: &'static str, r: Result<String, String>) -> bool {
        match r {
            Ok(d) => {
                self.record(name, Verdict::Pass, d);
                true
            }
            Err(d) => {
                self.record(name, Verdict::Fail, d);
                false
            }
        }
    }

    fn skip_all(&mut self, names: &[&'static str], why: &str) {
        for &name in names {
            self.record(name, Verdict::Skip, why.to_owned());
        }
    }
}

fn err(e: RigClientError) -> String {
    e.to_string()
}

/// The registers only the hardware can show, each with its expected value (the bring-up
/// checklist, `docs/board.md`): one step per register, skipped on a rig without registers.
fn board_registers<L: ByteLink>(rig: &mut RigClient<L>, s: &mut Steps) {
    match rig.board_registers() {
        Ok(Some(regs)) => {
            for (check, value, holds) in regs.checks() {
                let detail = format!(
                    "{:#010x} (bits {:#010x}: {:#x}, expected {:#x}: {})",
                    value,
                    check.mask,
                    value & check.mask,
                    check.expected,
                    check.meaning
                );
                let verdict = if holds { Verdict::Pass } else { Verdict::Fail };
                s.record(check.name, verdict, detail);
            }
        }
        Ok(None) => {
            for check in subsurf_protocol::BoardRegisters::CHECKS {
                s.record(check.name, Verdict::Skip, "no registers on this rig".into());
            }
        }
        Err(e) => {
            let why = err(e);
            for check in subsurf_protocol::BoardRegisters::CHECKS {
                s.record(check.name, Verdict::Fail, why.clone());
            }
        }
    }
}

/// The steps that move the turntable.
const MOTION_STEPS: [&str; 4] = [
    "home",
    "home twice and compare",
    "move seen",
    "step count by the home switch",
];
/// The e-stop's cut with a laser on.
const LASER_ESTOP: &str = "laser cut by the e-stop";
/// The steps that emit light.
const LIGHT_STEPS: [&str; 5] = [
    "trigger and exposure-active loopback",
    "galvo sweep",
    "galvo sweep seen",
    "laser cut by the interlock",
    LASER_ESTOP,
];

/// Run the self-test; `progress` sees each step as it ends. Leaves the rig stopped, disarmed.
pub fn run<L: ByteLink>(
    rig: &mut RigClient<L>,
    prompt: &mut dyn Prompt,
    options: &SelftestOptions,
    progress: Box<dyn FnMut(&StepReport)>,
) -> SelftestReport {
    let mut s = Steps {
        report: SelftestReport::default(),
        progress,
    };
    let hello = *rig.hello();
    let v = hello.firmware_version;
    s.record(
        "handshake",
        Verdict::Pass,
        format!(
            "protocol {}, firmware {}.{}.{}, boot nonce {:#010x}",
            hello.protocol_version, v.major, v.minor, v.patch, hello.boot_nonce
        ),
    );
    board_registers(rig, &mut s);
    let polarity_ok = profile_read_back(rig, options, &mut s);
    s.result(
        "config read-back",
        rig.get_config()
            .map_err(err)
            .map(|c| format!("heartbeat timeout {} ms", c.heartbeat_timeout_ms)),
    );
    if !existing_fault(rig, prompt, &mut s) {
        s.skip_all(&MOTION_STEPS, "the rig is in fault");
        s.skip_all(&LIGHT_STEPS, "the rig is in fault");
        finish(rig);
        return s.report;
    }
    motion(rig, prompt, options, &mut s);
    let caps = rig.hello().capabilities;
    let consent = polarity_ok
        && prompt.consent(&format!(
            "The next steps switch laser channel {} on: captures at the centre and at four points \
         of the galvo range (a quarter in from each end), then a laser held on while you open \
         the enclosure interlock. Is the beam path enclosed, or is everyone wearing eye \
         protection?",
            options.channel
        ));
    if consent {
        light(rig, prompt, options, &caps, &mut s);
    } else if !polarity_ok {
        s.skip_all(
            &LIGHT_STEPS,
            "the laser polarity does not match the wiring (see \"profile stored\")",
        );
    } else {
        s.skip_all(
            &LIGHT_STEPS,
            "no one agreed to laser light (answer y, or pass --yes when the beam path is safe)",
        );
    }
    interlock(rig, prompt, &mut s);
    if consent {
        laser_cut(rig, prompt, options, &mut s);
    }
    estop(rig, prompt, options, consent, &mut s);
    finish(rig);
    s.report
}

fn finish<L: ByteLink>(rig: &mut RigClient<L>) {
    let _ = rig.stop();
    let _ = rig.disarm();
}

/// The profile the rig runs (valid, the file's) and whether it is stored at all: a board without
/// one keeps its lasers and trigger high-impedance and refuses to arm. Arming also checks the
/// laser wiring against the profile's polarity, with no light (the board reads its undriven
/// laser lines, which the wiring's resistors hold at their off level): returns `false` when the
/// polarity is wrong, and the self-test then asks for no light at all.
fn profile_read_back<L: ByteLink>(
    rig: &mut RigClient<L>,
    options: &SelftestOptions,
    s: &mut Steps,
) -> bool {
    let profile = rig.get_profile().map_err(err);
    s.result(
        "profile read-back",
        profile.and_then(|p| {
            p.validate()
                .map_err(|e| format!("the rig runs an invalid profile: {e:?}"))?;
            match &options.expect_profile {
                Some(want) if *want != p => Err(format!(
                    "the rig runs another profile than the file: rig {p:?}, file {want:?} \
                     (send it with `subsurf rig profile send`)"
                )),
                _ => Ok(format!(
                    "{} steps/rev, galvo {:?}, {} lasers, camera read-out {} us",
                    p.steps_per_rev().unwrap_or(0),
                    p.galvo.output,
                    p.laser.channels,
                    p.camera.readout_us
                )),
            }
        }),
    );
    // Arming emits nothing by itself; it is how the rig says whether it knows its wiring.
    let mut polarity_ok = true;
    let stored = match rig.arm() {
        Ok(()) => Ok("stored: the lasers' and trigger's polarities are known".to_owned()),
        Err(RigClientError::Rejected {
            error: RigError::ProfileNotStored,
            ..
        }) => Err(
            "no profile is stored on the rig: its lasers and trigger stay off \
                   (high-impedance) until you send yours with `subsurf rig --profile rig.json \
                   profile send`"
                .to_owned(),
        ),
        Err(RigClientError::Rejected {
            error: RigError::LaserPolarity,
            ..
        }) => {
            polarity_ok = false;
            Err(
                "the laser lines, undriven, sit at the level the profile calls \"on\": \
                 laser.active_low is not the wiring's, or a pull resistor is missing (README, \
                 laser wiring). The rig drives nothing and this self-test asks for no light; fix \
                 the profile or the wiring and send the profile again"
                    .to_owned(),
            )
        }
        Err(RigClientError::Rejected { error, .. }) => Ok(format!(
            "not checked: arming refused for another reason ({error:?})"
        )),
        Err(e) => Err(err(e)),
    };
    let _ = rig.disarm();
    s.result("profile stored", stored);
    // What flash holds, read from flash: the profile the next boot runs must be the one in force.
    let in_flash = match (rig.get_stored_profile(), rig.get_profile()) {
        (Ok(stored), Ok(running)) if stored == running => {
            Ok("flash holds the profile in force: a reset keeps it".to_owned())
        }
        (Ok(stored), Ok(running)) => Err(format!(
            "flash holds another profile than the one in force (a reset would bring it back): \
             flash {stored:?}, running {running:?}; send yours again with `subsurf rig profile send`"
        )),
        (
            Err(RigClientError::Rejected {
                error: RigError::ProfileNotStored,
                ..
            }),
            _,
        ) => Err("flash holds no valid profile of this firmware's layout".to_owned()),
        (Err(e), _) | (_, Err(e)) => Err(err(e)),
    };
    s.result("profile in flash", in_flash);
    polarity_ok
}

/// A fault left from before the self-test: cleared only when the person says its cause is gone.
/// Returns whether the rig is out of fault.
fn existing_fault<L: ByteLink>(
    rig: &mut RigClient<L>,
    prompt: &mut dyn Prompt,
    s: &mut Steps,
) -> bool {
    let fault = match rig.status() {
        Ok(st) => st.fault,
        Err(e) => {
            s.record("fault before the self-test", Verdict::Fail, err(e));
            return false;
        }
    };
    let Some(fault) = fault else {
        return true;
    };
    let why = fault_cause(fault);
    match prompt.confirm(&format!(
        "The rig reports fault {fault:?} from before this self-test ({why}). Is its cause dealt \
         with, and may the self-test clear it?"
    )) {
        Some(true) => match rig.clear_fault() {
            Ok(()) => {
                s.record(
                    "fault before the self-test",
                    Verdict::Pass,
                    format!("{fault:?} cleared, as you confirmed"),
                );
                true
            }
            Err(e) => {
                s.record("fault before the self-test", Verdict::Fail, err(e));
                false
            }
        },
        _ => {
            s.record(
                "fault before the self-test",
                Verdict::Fail,
                format!(
                    "the rig is in fault {fault:?} ({why}); not cleared: check the cause, then \
                     `subsurf rig clear-fault`"
                ),
            );
            false
        }
    }
}

fn fault_cause(fault: Fault) -> &'static str {
    match fault {
        Fault::EmergencyStop => "the e-stop was pressed or its wire is broken",
        Fault::HomingFailed => "homing did not find the switch",
        Fault::StepStall => "the step generator ran dry mid-move: steps were lost",
        Fault::StepLate => {
            "the step interrupt ran later than one step period: a step may have been repeated"
        }
        _ => "see `subsurf rig status`",
    }
}

/// Home twice and compare; a move the person watches; its step count checked by the home switch.
fn motion<L: ByteLink>(
    rig: &mut RigClient<L>,
    prompt: &mut dyn Prompt,
    options: &SelftestOptions,
    s: &mut Steps,
) {
    let caps = rig.hello().capabilities;
    let homed = home(rig, options.home_timeout);
    if !s.result("home", homed.map(|_| "homed".to_owned())) {
        s.skip_all(&MOTION_STEPS[1..], "homing failed");
        return;
    }
    // The second homing says where its zero lay in the first one's coordinates.
    let away = i32::try_from(caps.steps_per_rev / 3).unwrap_or(1000).max(1);
    let second = move_to(rig, away, &caps)
        .and_then(|_| home(rig, options.home_timeout))
        .and_then(|previous| check_zero(previous, "homing is not repeatable"));
    s.result(
        "home twice and compare",
        second.map(|p| format!("second zero {p} steps from the first (after {away} steps away)")),
    );
    // A move by a known count: the person sees the angle (the gearing), the home switch checks
    // the count (the rig's own counter proves nothing: it counts what it was told).
    let steps = i32::try_from(caps.steps_per_rev / 8).unwrap_or(100).max(1);
    if let Err(e) = move_to(rig, steps, &caps) {
        s.record("move seen", Verdict::Fail, e);
        s.record(
            "step count by the home switch",
            Verdict::Skip,
            "the move failed".into(),
        );
        return;
    }
    match prompt.confirm(&format!(
        "Did the turntable turn by 1/8 of a revolution ({steps} steps)?"
    )) {
        Some(true) => s.record("move seen", Verdict::Pass, "confirmed".into()),
        Some(false) => s.record(
            "move seen",
            Verdict::Fail,
            "check steps per revolution, microstepping and gear ratio in the profile".into(),
        ),
        None => s.record("move seen", Verdict::Skip, "nobody to ask".into()),
    }
    let back = home(rig, options.home_timeout)
        .and_then(|previous| check_zero(previous, "steps were lost or gained on the way"));
    s.result(
        "step count by the home switch",
        back.map(|p| {
            format!(
                "{steps} steps out, and the home switch was {p} steps from where the count put it"
            )
        }),
    );
}

fn check_zero(previous: Option<i32>, otherwise: &str) -> Result<i32, String> {
    match previous {
        Some(p) if p.abs() <= 1 => Ok(p),
        Some(p) => Err(format!(
            "the switch was {p} steps from where it should be: {otherwise} (check the switch, \
             its debounce, the homing speeds and the driver's current)"
        )),
        None => Err("the rig did not report the zero's offset".into()),
    }
}

/// Trigger loopback and galvo sweep: laser light, agreed to.
fn light<L: ByteLink>(
    rig: &mut RigClient<L>,
    prompt: &mut dyn Prompt,
    options: &SelftestOptions,
    caps: &subsurf_protocol::Capabilities,
    s: &mut Steps,
) {
    // Trigger loopback: one capture at the centre, confirmed by exposure-active.
    let center = caps.galvo_max / 2 + 1;
    let loopback = capture_at(rig, options.channel, center, center, caps);
    s.result("trigger and exposure-active loopback", loopback);
    // Galvo sweep: a square a quarter in from the ends of the range, then the centre: it shows
    // both axes and their directions without aiming the beam at the edge of the field.
    let (lo, hi) = (caps.galvo_max / 4, caps.galvo_max - caps.galvo_max / 4);
    let points = [(lo, lo), (hi, lo), (hi, hi), (lo, hi), (center, center)];
    let mut sweep = Ok(());
    for (x, y) in points {
        if let Err(e) = capture_at(rig, options.channel, x, y, caps) {
            sweep = Err(format!("at ({x}, {y}): {e}"));
            break;
        }
    }
    let sweep_ok = s.result(
        "galvo sweep",
        sweep.map(|()| {
            format!(
                "square {lo}..={hi} and the centre of 0..={}, each capture confirmed",
                caps.galvo_max
            )
        }),
    );
    if sweep_ok {
        match prompt.confirm("Did the laser spot visit four corners of a square, then the centre?")
        {
            Some(true) => s.record("galvo sweep seen", Verdict::Pass, "confirmed".into()),
            Some(false) => s.record(
                "galvo sweep seen",
                Verdict::Fail,
                "check the galvo output path (SPI DAC / internal DAC) in the profile and the \
                 wiring"
                    .into(),
            ),
            None => s.record("galvo sweep seen", Verdict::Skip, "nobody to ask".into()),
        }
    } else {
        s.record("galvo sweep seen", Verdict::Skip, "the sweep failed".into());
    }
}

/// The interlock without light: seen open, arming refused, seen closed again.
fn interlock<L: ByteLink>(rig: &mut RigClient<L>, prompt: &mut dyn Prompt, s: &mut Steps) {
    if !prompt.wait_for("Open the enclosure interlock (the lid), then press Enter") {
        s.record("interlock", Verdict::Skip, "nobody to open it".into());
        return;
    }
    let open = rig.status().map_err(err).and_then(|st| {
        if st.inputs.interlock_closed {
            return Err(
                "the rig still reads the interlock closed: check its wiring (NC \
                        contact to GND, D5/PB4)"
                    .to_owned(),
            );
        }
        match rig.arm() {
            Err(RigClientError::Rejected {
                error: RigError::InterlockOpen,
                ..
            }) => Ok("seen open; arming refused".to_owned()),
            Ok(()) => {
                let _ = rig.disarm();
                Err("the rig armed with the interlock open".to_owned())
            }
            Err(e) => Err(err(e)),
        }
    });
    s.result("interlock", open);
    close_interlock(rig, prompt, s);
}

fn close_interlock<L: ByteLink>(rig: &mut RigClient<L>, prompt: &mut dyn Prompt, s: &mut Steps) {
    if !prompt.wait_for("Close the enclosure interlock again, then press Enter") {
        return;
    }
    match rig.status() {
        Ok(st) if st.inputs.interlock_closed => {}
        Ok(_) => s.record(
            "interlock closed again",
            Verdict::Fail,
            "the rig still reads it open".into(),
        ),
        Err(e) => s.record("interlock closed again", Verdict::Fail, err(e)),
    }
}

/// The laser cut with a laser actually on: the person opens the interlock while it shines; the
/// rig must switch it off at once and say why.
fn laser_cut<L: ByteLink>(
    rig: &mut RigClient<L>,
    prompt: &mut dyn Prompt,
    options: &SelftestOptions,
    s: &mut Steps,
) {
    const NAME: &str = "laser cut by the interlock";
    let instruction = format!(
        "Laser {} comes ON now: open the enclosure interlock within {} s; the rig must switch \
         it off at once",
        options.channel,
        options.act_within.as_secs()
    );
    if !prompt.tell(&instruction) {
        s.record(NAME, Verdict::Skip, "nobody to open the interlock".into());
        return;
    }
    let lit = rig
        .arm()
        .and_then(|()| rig.laser(options.channel, true))
        .map_err(err);
    if let Err(e) = lit {
        let _ = rig.disarm();
        s.record(
            NAME,
            Verdict::Fail,
            format!("could not switch the laser on: {e}"),
        );
        return;
    }
    let outcome = watch_cut(rig, options.act_within);
    let _ = rig.laser(options.channel, false);
    let _ = rig.disarm();
    let verdict = outcome.and_then(|st| {
        if st.lasers != 0 {
            return Err(format!(
                "the interlock is open but lasers {:#b} still emit",
                st.lasers
            ));
        }
        match prompt.confirm("Did the laser go off the moment the interlock opened?") {
            Some(false) => Err(
                "you saw it stay on: the laser is not switched by the rig's \
                                enable output (check the driver's TTL input and its polarity)"
                    .to_owned(),
            ),
            Some(true) => Ok("off when the interlock opened (rig and you agree)".to_owned()),
            None => Ok("off when the interlock opened (the rig's outputs)".to_owned()),
        }
    });
    s.result(NAME, verdict);
    close_interlock(rig, prompt, s);
}

/// Keep the link alive while the person acts; the rig's status once it halted for the interlock.
fn watch_cut<L: ByteLink>(rig: &mut RigClient<L>, within: Duration) -> Result<Status, String> {
    watch_halt(
        rig,
        within,
        HaltReason::InterlockOpen,
        "the interlock was not opened",
        |st| !st.inputs.interlock_closed && st.lasers == 0,
    )
}

/// Keep the link alive while the person acts; the rig's status once it halted for `reason` (or
/// once its status shows `done`, should the halt event be lost).
fn watch_halt<L: ByteLink>(
    rig: &mut RigClient<L>,
    within: Duration,
    reason: HaltReason,
    not_done: &str,
    done: impl Fn(&Status) -> bool,
) -> Result<Status, String> {
    let deadline = rig.link().now() + within;
    loop {
        let left = deadline.saturating_duration_since(rig.link().now());
        if left.is_zero() {
            return Err(format!("{not_done} within {within:?}"));
        }
        match rig
            .next_event(left.min(Duration::from_millis(100)))
            .map_err(err)?
        {
            Some(e) => match e.kind {
                EventKind::Halted { reason: r } if r == reason => {
                    return rig.status().map_err(err);
                }
                EventKind::Halted { reason: r } => {
                    return Err(format!(
                        "the laser went off for another reason ({r:?}) before the person acted"
                    ));
                }
                _ => {}
            },
            None => {
                let st = rig.status().map_err(err)?;
                if done(&st) {
                    // The halt event may have been lost; the status says the same.
                    return Ok(st);
                }
            }
        }
    }
}

fn home<L: ByteLink>(rig: &mut RigClient<L>, timeout: Duration) -> Result<Option<i32>, String> {
    rig.home().map_err(err)?;
    let deadline = rig.link().now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(rig.link().now());
        if left.is_zero() {
            return Err(format!("not homed within {timeout:?}"));
        }
        match rig
            .next_event(left.min(Duration::from_millis(200)))
            .map_err(err)?
        {
            Some(e) => match e.kind {
                EventKind::Homed { previous } => return Ok(previous),
                EventKind::Halted { reason } => return Err(format!("halted: {reason:?}")),
                _ => {}
            },
            None => {
                let st = rig.status().map_err(err)?;
                if let Some(f) = st.fault {
                    return Err(format!("fault: {f:?}"));
                }
            }
        }
    }
}

fn move_to<L: ByteLink>(
    rig: &mut RigClient<L>,
    target: i32,
    caps: &subsurf_protocol::Capabilities,
) -> Result<i32, String> {
    rig.start_move(
        MoveTarget::Absolute(target),
        (caps.max_speed / 4).max(1),
        (caps.max_accel / 4).max(1),
    )
    .map_err(err)?;
    let st = rig.wait_idle(Duration::from_secs(60)).map_err(err)?;
    Ok(st.position)
}

fn capture_at<L: ByteLink>(
    rig: &mut RigClient<L>,
    channel: u8,
    x: u16,
    y: u16,
    caps: &subsurf_protocol::Capabilities,
) -> Result<String, String> {
    rig.arm().map_err(err)?;
    let before = rig.status().map_err(err)?.exposures;
    let exposure_us = caps.min_exposure_us.max(1_000);
    let c = rig
        .capture(
            Capture {
                galvo: GalvoPoint { x, y },
                settle_us: None,
                channel,
                exposure_us,
                trigger_us: 10.min(exposure_us),
            },
            Duration::from_secs(5),
        )
        .map_err(err);
    let _ = rig.disarm();
    let c = c?;
    let Some(e) = c.exposure else {
        return Err(
            "the camera's exposure-active output never rose: check the trigger and \
             exposure-active wiring (or loop TRIG to EXPOSURE with a wire to test the board)"
                .into(),
        );
    };
    if c.exposure_count != before.wrapping_add(1) {
        return Err(format!(
            "exposure count {} after {before}: the camera exposed without a trigger",
            c.exposure_count
        ));
    }
    if !c.lit {
        return Err(format!(
            "the laser did not cover the exposure ({} us after the trigger, {} us long): raise \
             laser.lead_us / laser.tail_us",
            e.delay_us, e.duration_us
        ));
    }
    Ok(format!(
        "trigger at {} us, exposure {} us after it for {} us, count {}",
        c.triggered_at_us, e.delay_us, e.duration_us, c.exposure_count
    ))
}

/// The e-stop; with consent to light, pressed while a laser shines (a cut never
/// seen with a laser on is not a checked cut), the cut watched like the interlock's.
fn estop<L: ByteLink>(
    rig: &mut RigClient<L>,
    prompt: &mut dyn Prompt,
    options: &SelftestOptions,
    light: bool,
    s: &mut Steps,
) {
    let pressed = if light {
        let instruction = format!(
            "Laser {} comes ON now: press the emergency stop within {} s; the rig must switch \
             it off at once",
            options.channel,
            options.act_within.as_secs()
        );
        if !prompt.tell(&instruction) {
            s.record("e-stop", Verdict::Skip, "nobody to press it".into());
            return;
        }
        // Events of the steps before (the interlock's halt) are not this step's.
        while let Ok(Some(_)) = rig.next_event(Duration::ZERO) {}
        let lit = rig
            .arm()
            .and_then(|()| rig.laser(options.channel, true))
            .map_err(err);
        if let Err(e) = lit {
            let _ = rig.disarm();
            s.record(
                LASER_ESTOP,
                Verdict::Fail,
                format!("could not switch the laser on: {e}"),
            );
            return;
        }
        let outcome = watch_halt(
            rig,
            options.act_within,
            HaltReason::EmergencyStop,
            "the e-stop was not pressed",
            |st| st.inputs.estop && st.lasers == 0,
        );
        let _ = rig.laser(options.channel, false);
        let _ = rig.disarm();
        s.result(
            LASER_ESTOP,
            outcome.clone().and_then(|st| {
                if st.lasers != 0 {
                    return Err(format!(
                        "the e-stop is pressed but lasers {:#b} still emit",
                        st.lasers
                    ));
                }
                match prompt.confirm("Did the laser go off the moment the e-stop was pressed?") {
                    Some(false) => Err("you saw it stay on: the laser is not switched by the \
                                        rig's enable output"
                        .to_owned()),
                    _ => Ok("off when the e-stop was pressed".to_owned()),
                }
            }),
        );
        outcome
    } else {
        if !prompt.wait_for("Press the emergency stop, then press Enter") {
            s.record("e-stop", Verdict::Skip, "nobody to press it".into());
            return;
        }
        rig.status().map_err(err)
    };
    match pressed {
        Ok(st) if st.inputs.estop && st.fault.is_some() && st.lasers == 0 => {
            s.record(
                "e-stop",
                Verdict::Pass,
                "seen pressed: fault raised, lasers off, home position forgotten".into(),
            );
        }
        Ok(st) => {
            s.record(
                "e-stop",
                Verdict::Fail,
                format!(
                    "the rig reads e-stop {} with fault {:?}: check the e-stop wiring (NC \
                     contact to GND)",
                    st.inputs.estop, st.fault
                ),
            );
            return;
        }
        Err(e) => {
            s.record("e-stop", Verdict::Fail, e);
            return;
        }
    }
    if prompt.wait_for("Release the emergency stop, then press Enter") {
        match rig.clear_fault() {
            Ok(()) => s.record(
                "e-stop release",
                Verdict::Pass,
                "released; the e-stop fault this step raised was cleared".into(),
            ),
            Err(e) => s.record("e-stop release", Verdict::Fail, err(e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};
    use std::time::Instant;

    use super::*;
    use crate::link::LinkError;
    use crate::rig::ClientConfig;
    use crate::sim::{SimLink, SimParams, VirtualRig};

    /// What the person at the simulated bench does to the rig.
    #[derive(Debug, Clone, Copy)]
    enum Act {
        Interlock(bool),
        Estop(bool),
    }

    /// Acts the person will do: after a delay from when the link first sees them, on the link's
    /// virtual clock.
    type Todo = Arc<Mutex<Vec<(Duration, Option<Instant>, Act)>>>;

    /// The simulated rig's link with a person's hands on the rig: every act whose time has come
    /// is done before the link is used.
    struct Bench {
        link: SimLink,
        todo: Todo,
    }

    impl Bench {
        fn act(&mut self) {
            let now = self.link.now();
            let mut due = Vec::new();
            self.todo.lock().unwrap().retain_mut(|(delay, at, act)| {
                let at = *at.get_or_insert(now + *delay);
                if at <= now {
                    due.push(*act);
                    false
                } else {
                    true
                }
            });
            for act in due {
                match act {
                    Act::Interlock(closed) => self.link.rig_mut().set_interlock(closed),
                    Act::Estop(pressed) => self.link.rig_mut().set_estop(pressed),
                }
            }
        }
    }

    impl ByteLink for Bench {
        fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
            self.act();
            self.link.send(bytes)
        }
        fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
            self.act();
            self.link.recv(buf, timeout)
        }
        fn describe(&self) -> String {
            self.link.describe()
        }
        fn now(&self) -> Instant {
            self.link.now()
        }
    }

    /// A person who agrees to light (or not), answers yes, and does what they are told: at once
    /// when asked to do it and press Enter, 300 ms later when told while a laser shines.
    struct Person {
        todo: Todo,
        light: bool,
        asked: Vec<String>,
    }

    impl Person {
        fn schedule(&mut self, instruction: &str, after: Duration) {
            let act = if instruction.starts_with("Open the enclosure interlock")
                || instruction.contains("open the enclosure interlock")
            {
                Act::Interlock(false)
            } else if instruction.starts_with("Close the enclosure interlock") {
                Act::Interlock(true)
            } else if instruction.starts_with("Press the emergency stop")
                || instruction.contains("press the emergency stop")
            {
                Act::Estop(true)
            } else if instruction.starts_with("Release the emergency stop") {
                Act::Estop(false)
            } else {
                panic!("unexpected instruction: {instruction}");
            };
            self.todo.lock().unwrap().push((after, None, act));
        }
    }

    impl Prompt for Person {
        fn confirm(&mut self, question: &str) -> Option<bool> {
            self.asked.push(question.to_owned());
            Some(true)
        }
        fn wait_for(&mut self, instruction: &str) -> bool {
            self.schedule(instruction, Duration::ZERO);
            true
        }
        fn consent(&mut self, question: &str) -> bool {
            self.asked.push(question.to_owned());
            self.light
        }
        fn tell(&mut self, instruction: &str) -> bool {
            self.schedule(instruction, Duration::from_millis(300));
            true
        }
    }

    /// The self-test over the simulated rig with a person at the bench who agrees to light or
    /// not; `prepare` sets the rig up first. The report, the rig afterwards, and what was asked.
    fn at_bench(
        params: SimParams,
        prepare: impl FnOnce(&mut VirtualRig),
        light: bool,
    ) -> (SelftestReport, SimLink, Vec<String>) {
        let todo: Todo = Arc::default();
        let mut link = SimLink::clean(VirtualRig::new(params));
        prepare(link.rig_mut());
        let bench = Bench {
            link,
            todo: todo.clone(),
        };
        let mut rig = RigClient::connect_with_seq(bench, ClientConfig::default(), 1).expect("rig");
        let mut person = Person {
            todo,
            light,
            asked: Vec::new(),
        };
        let report = run(
            &mut rig,
            &mut person,
            &SelftestOptions::default(),
            Box::new(|_| {}),
        );
        (report, rig.into_link().link, person.asked)
    }

    /// The interlock is checked, and the laser cut with a laser on; every
    /// step passes on a healthy rig with a person there.
    #[test]
    fn with_a_person_the_interlock_and_a_laser_cut_with_the_laser_on_pass() {
        let (r, link, _) = at_bench(SimParams::default(), |_| {}, true);
        assert!(r.passed(), "{r:#?}");
        for step in [
            "interlock",
            "laser cut by the interlock",
            LASER_ESTOP,
            "e-stop",
            "e-stop release",
            "step count by the home switch",
        ] {
            assert_eq!(verdict(&r, step), Verdict::Pass, "{step}: {r:#?}");
        }
        // The laser really was on when the interlock opened, and went off with it.
        let rig = link.rig();
        let lit: Vec<_> = rig
            .laser_log()
            .windows(2)
            .filter(|w| w[0].value != 0 && w[1].value == 0)
            .map(|w| w[1].at - w[0].at)
            .collect();
        assert!(
            lit.iter().any(|&on| on >= 250_000),
            "no laser held on: {lit:?}"
        );
        assert_eq!(rig.hardware().violations(), 0);
    }

    /// Finding 9: the laser was fired (at full-scale corners) without asking.
    #[test]
    fn nothing_emits_light_before_the_person_agrees() {
        let (r, link, asked) = at_bench(SimParams::default(), |_| {}, false);
        assert!(
            asked.iter().any(|q| q.contains("eye protection")),
            "{asked:?}"
        );
        for step in LIGHT_STEPS {
            assert_eq!(verdict(&r, step), Verdict::Skip, "{step}");
        }
        assert!(
            link.rig().laser_log().iter().all(|e| e.value == 0),
            "light without consent: {:?}",
            link.rig().laser_log()
        );
        // The interlock is still checked (no light needed).
        assert_eq!(verdict(&r, "interlock"), Verdict::Pass);
    }

    /// A profile whose laser polarity is not the wiring's lit the laser at
    /// every boot and at `profile send`. The self-test catches it with no light: the arming
    /// check fails, and no light step asks for consent or switches a laser on.
    #[test]
    fn a_wrong_laser_polarity_fails_before_any_light_is_asked_for() {
        let wrong = !RigProfile::DEFAULT.laser.active_low;
        let (r, link, asked) = at_bench(
            SimParams::default(),
            |rig| rig.set_laser_wiring(wrong),
            true,
        );
        assert_eq!(verdict(&r, "profile stored"), Verdict::Fail, "{r:#?}");
        assert!(!r.passed());
        assert!(
            !asked.iter().any(|q| q.contains("eye protection")),
            "consent asked: {asked:?}"
        );
        for step in LIGHT_STEPS {
            assert_eq!(verdict(&r, step), Verdict::Skip, "{step}");
        }
        assert!(
            link.rig().laser_log().iter().all(|e| e.value == 0),
            "light with a wrong polarity: {:?}",
            link.rig().laser_log()
        );
        // The same bench wired as the profile says passes that step.
        let right = RigProfile::DEFAULT.laser.active_low;
        let (r, _, _) = at_bench(
            SimParams::default(),
            |rig| rig.set_laser_wiring(right),
            true,
        );
        assert_eq!(verdict(&r, "profile stored"), Verdict::Pass, "{r:#?}");
    }

    /// Finding 9: a fault from before the self-test was cleared without a word.
    #[test]
    fn a_fault_from_before_is_cleared_only_when_the_person_says_so() {
        let pressed_and_released = |rig: &mut VirtualRig| {
            rig.set_estop(true);
            rig.set_estop(false);
        };
        let link = SimLink::clean({
            let mut rig = VirtualRig::new(SimParams::default());
            pressed_and_released(&mut rig);
            rig
        });
        let mut rig = RigClient::connect_with_seq(link, ClientConfig::default(), 1).expect("rig");
        let r = run(
            &mut rig,
            &mut AssumeYes,
            &SelftestOptions::default(),
            Box::new(|_| {}),
        );
        assert_eq!(verdict(&r, "fault before the self-test"), Verdict::Fail);
        assert_eq!(verdict(&r, "home"), Verdict::Skip);
        assert!(
            rig.status().unwrap().fault.is_some(),
            "cleared without asking"
        );
        // With a person who says its cause is dealt with: cleared, and the report says so.
        let (r, _, asked) = at_bench(SimParams::default(), pressed_and_released, true);
        assert!(
            asked.iter().any(|q| q.contains("EmergencyStop")),
            "{asked:?}"
        );
        let step = r
            .steps
            .iter()
            .find(|s| s.name == "fault before the self-test")
            .unwrap();
        assert_eq!(step.verdict, Verdict::Pass);
        assert!(step.detail.contains("cleared"), "{step:?}");
        assert!(r.passed(), "{r:#?}");
    }

    fn selftest(params: SimParams, prompt: &mut dyn Prompt) -> SelftestReport {
        let link = SimLink::clean(VirtualRig::new(params));
        let mut rig = RigClient::connect_with_seq(link, ClientConfig::default(), 1).expect("rig");
        run(
            &mut rig,
            prompt,
            &SelftestOptions::default(),
            Box::new(|_| {}),
        )
    }

    fn verdict(r: &SelftestReport, name: &str) -> Verdict {
        r.steps
            .iter()
            .find(|s| s.name == name)
            .map(|s| s.verdict)
            .unwrap_or_else(|| panic!("no step {name}: {r:?}"))
    }

    /// Says yes to everything and presses nothing.
    struct Yes;
    impl Prompt for Yes {
        fn confirm(&mut self, _q: &str) -> Option<bool> {
            Some(true)
        }
        fn wait_for(&mut self, _i: &str) -> bool {
            false
        }
        fn consent(&mut self, _q: &str) -> bool {
            true
        }
        fn tell(&mut self, _i: &str) -> bool {
            false
        }
    }

    #[test]
    fn a_healthy_simulated_rig_passes() {
        let r = selftest(SimParams::default(), &mut Yes);
        assert!(r.passed(), "{r:?}");
        assert_eq!(verdict(&r, "move seen"), Verdict::Pass);
        assert_eq!(verdict(&r, "step count by the home switch"), Verdict::Pass);
        assert_eq!(verdict(&r, "e-stop"), Verdict::Skip);
        assert_eq!(verdict(&r, "interlock"), Verdict::Skip);
    }

    #[test]
    fn a_camera_that_misses_its_trigger_fails_the_loopback() {
        let mut params = SimParams::default();
        params.camera.miss_triggers = [Some(0), None, None, None];
        let r = selftest(params, &mut AssumeYes);
        assert!(!r.passed());
        assert_eq!(
            verdict(&r, "trigger and exposure-active loopback"),
            Verdict::Fail
        );
    }

    #[test]
    fn a_laser_window_without_margins_fails_under_trigger_latency() {
        let mut params = SimParams::default();
        params.camera.timer_latency_us = 40;
        params.profile.laser.lead_us = 0;
        params.profile.laser.tail_us = 0;
        let r = selftest(params, &mut AssumeYes);
        assert_eq!(
            verdict(&r, "trigger and exposure-active loopback"),
            Verdict::Fail
        );
    }
}
