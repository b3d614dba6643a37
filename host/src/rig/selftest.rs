//! `subsurf rig selftest`: the bring-up check a user runs on a real bench, step by step.
//!
//! Each step talks to the rig through the ordinary [`RigClient`] and says PASS, FAIL or SKIP with
//! what it measured: handshake, profile and config read-back, homing twice (the second homing
//! reports where the new zero lay in the first one's coordinates), a move and its step count, a
//! capture whose trigger the camera's exposure-active output confirms (trigger loopback), a galvo
//! sweep over the corners of the range with a confirmed capture at each, and the e-stop. Steps a
//! person must watch ask through a [`Prompt`]; with no one to ask (`--yes`, CI) they are skipped.

use std::time::Duration;

use subsurf_protocol::{Capture, EventKind, GalvoPoint, MoveTarget, RigProfile};

use super::{RigClient, RigClientError};
use crate::link::ByteLink;

/// Asks the person at the bench.
pub trait Prompt {
    /// Ask a yes/no question; `None` = nobody to ask (the step is skipped).
    fn confirm(&mut self, question: &str) -> Option<bool>;
    /// Tell them to do something and wait until they say it is done; `false` = skip.
    fn wait_for(&mut self, instruction: &str) -> bool;
}

/// No one at the bench: every interactive step is skipped.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoPrompt;

impl Prompt for NoPrompt {
    fn confirm(&mut self, _question: &str) -> Option<bool> {
        None
    }
    fn wait_for(&mut self, _instruction: &str) -> bool {
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
    /// Not checked (needs a person, or an earlier step failed).
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
    /// Laser channel for the captures.
    pub channel: u8,
}

impl Default for SelftestOptions {
    fn default() -> Self {
        Self {
            expect_profile: None,
            home_timeout: Duration::from_secs(120),
            channel: 0,
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
}

fn err(e: RigClientError) -> String {
    e.to_string()
}

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
    let profile = rig.get_profile().map_err(err);
    let ok = s.result(
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
    let _ = ok;
    s.result(
        "config read-back",
        rig.get_config()
            .map_err(err)
            .map(|c| format!("heartbeat timeout {} ms", c.heartbeat_timeout_ms)),
    );
    let status = rig.status();
    if let Ok(st) = &status
        && st.fault.is_some()
    {
        let _ = rig.clear_fault();
    }
    // Home twice: the second homing says where its zero lay in the first one's coordinates.
    let caps = rig.hello().capabilities;
    let homed = home(rig, options.home_timeout);
    let first_ok = s.result("home", homed.map(|_| "homed".to_owned()));
    if first_ok {
        let away = i32::try_from(caps.steps_per_rev / 3).unwrap_or(1000).max(1);
        let second = move_to(rig, away, &caps)
            .and_then(|_| home(rig, options.home_timeout))
            .and_then(|previous| match previous {
                Some(p) if p.abs() <= 1 => Ok(format!(
                    "second zero {p} steps from the first (after {away} steps away)"
                )),
                Some(p) => Err(format!(
                    "second zero {p} steps from the first: homing is not repeatable (check the \
                     switch, its debounce and the homing speeds in the profile)"
                )),
                None => Err("the rig did not report the second zero's offset".into()),
            });
        s.result("home twice and compare", second);
        let steps = i32::try_from(caps.steps_per_rev / 8).unwrap_or(100).max(1);
        let moved = move_to(rig, steps, &caps).and_then(|pos| {
            if pos == steps {
                Ok(format!("{steps} steps, position {pos}"))
            } else {
                Err(format!("asked for position {steps}, the rig is at {pos}"))
            }
        });
        if s.result("move and step count", moved) {
            match prompt.confirm(&format!(
                "Did the turntable turn by 1/8 of a revolution ({steps} steps)?"
            )) {
                Some(true) => s.record("move seen", Verdict::Pass, "confirmed".into()),
                Some(false) => s.record(
                    "move seen",
                    Verdict::Fail,
                    "check steps per revolution, microstepping and gear ratio in the profile"
                        .into(),
                ),
                None => s.record("move seen", Verdict::Skip, "nobody to ask".into()),
            }
        }
    } else {
        s.record(
            "home twice and compare",
            Verdict::Skip,
            "homing failed".into(),
        );
        s.record("move and step count", Verdict::Skip, "not homed".into());
    }
    // Trigger loopback: one capture at the centre, confirmed by exposure-active.
    let center = caps.galvo_max / 2 + 1;
    let loopback = capture_at(rig, options.channel, center, center, &caps);
    s.result("trigger and exposure-active loopback", loopback);
    // Galvo sweep: the corners and the centre, a confirmed capture at each.
    let m = caps.galvo_max;
    let corners = [(0, 0), (m, 0), (m, m), (0, m), (center, center)];
    let mut sweep = Ok(String::new());
    for (x, y) in corners {
        match capture_at(rig, options.channel, x, y, &caps) {
            Ok(_) => {}
            Err(e) => {
                sweep = Err(format!("at ({x}, {y}): {e}"));
                break;
            }
        }
    }
    let sweep_ok = s.result(
        "galvo sweep",
        sweep.map(|_| format!("corners of 0..={m} and the centre, each capture confirmed")),
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
    }
    estop(rig, prompt, &mut s);
    let _ = rig.stop();
    let _ = rig.disarm();
    s.report
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

fn estop<L: ByteLink>(rig: &mut RigClient<L>, prompt: &mut dyn Prompt, s: &mut Steps) {
    if !prompt.wait_for("Press the emergency stop, then press Enter") {
        s.record("e-stop", Verdict::Skip, "nobody to press it".into());
        return;
    }
    let pressed = rig.status().map_err(err);
    match pressed {
        Ok(st) if st.inputs.estop && st.fault.is_some() && st.lasers == 0 => {
            s.record(
                "e-stop",
                Verdict::Pass,
                "seen pressed: fault raised, lasers off".into(),
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
            Ok(()) => s.record("e-stop release", Verdict::Pass, "fault cleared".into()),
            Err(e) => s.record("e-stop release", Verdict::Fail, err(e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::ClientConfig;
    use crate::sim::{SimLink, SimParams, VirtualRig};

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
    }

    #[test]
    fn a_healthy_simulated_rig_passes() {
        let r = selftest(SimParams::default(), &mut Yes);
        assert!(r.passed(), "{r:?}");
        assert_eq!(verdict(&r, "move seen"), Verdict::Pass);
        assert_eq!(verdict(&r, "e-stop"), Verdict::Skip);
    }

    #[test]
    fn a_camera_that_misses_its_trigger_fails_the_loopback() {
        let mut params = SimParams::default();
        params.camera.miss_triggers = [Some(0), None, None, None];
        let r = selftest(params, &mut NoPrompt);
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
        let r = selftest(params, &mut NoPrompt);
        assert_eq!(
            verdict(&r, "trigger and exposure-active loopback"),
            Verdict::Fail
        );
    }
}
