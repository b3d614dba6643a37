//! `subsurf rig …` by hand: connecting to the rig (a serial port or the simulated rig in
//! virtual time), each action and what it prints, the self-test's terminal prompt, and the
//! simulated rig served on a pseudo-terminal. The command only parses its flags.
//!
//! The rig turns its laser off and disarms when the host stops sending heartbeats, so every
//! invocation leaves the laser safe when it exits; `LaserOn` therefore holds the laser on for
//! its time and then switches it off again.

use std::io::BufRead;
use std::time::Duration;

use subsurf_protocol::{Capture, GalvoPoint, MoveTarget, RigProfile, Status};

use super::selftest::{self, Prompt, SelftestOptions, Verdict};
use super::{ClientConfig, ProfileFileError, RigClient, RigClientError, profile_json};
use crate::link::{ByteLink, LinkError, SerialLink};
use crate::sim::{SimLink, SimParams, VirtualRig};

/// What to do on the rig once connected.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ManualAction {
    /// Handshake: protocol and firmware version, capabilities.
    Hello,
    /// Position, state, laser, inputs, counters.
    Status,
    /// Seek the home switch and wait until homed (at most `timeout_ms`).
    Home {
        /// Give up waiting after this many milliseconds.
        timeout_ms: u64,
    },
    /// Move the turntable (exactly one of `to`, `by`) and wait until the move is done.
    Move {
        /// Absolute target position in steps.
        to: Option<i32>,
        /// Relative move in steps.
        by: Option<i32>,
        /// Cruise speed, steps/s (default: a quarter of the rig's maximum).
        speed: Option<u32>,
        /// Acceleration, steps/s² (default: a quarter of the rig's maximum).
        accel: Option<u32>,
        /// Give up waiting after this many milliseconds.
        timeout_ms: u64,
    },
    /// Point the galvo at DAC codes.
    Galvo {
        /// X mirror code.
        x: u16,
        /// Y mirror code.
        y: u16,
    },
    /// Allow emission.
    LaserArm,
    /// Forbid emission (all channels off).
    LaserDisarm,
    /// Arm, switch `channel` on for `hold_ms`, then off and disarm.
    LaserOn {
        /// Laser channel.
        channel: u8,
        /// How long to keep it on, milliseconds.
        hold_ms: u64,
    },
    /// Switch `channel` off.
    LaserOff {
        /// Laser channel.
        channel: u8,
    },
    /// One atomic capture (arms the laser for it and disarms afterwards).
    Capture {
        /// Galvo X code.
        x: u16,
        /// Galvo Y code.
        y: u16,
        /// Laser channel.
        channel: u8,
        /// Laser-on time, µs.
        exposure_us: u32,
        /// Camera trigger pulse, µs.
        trigger_us: u32,
        /// Galvo settle time, µs (`None`: computed by the rig from the jump).
        settle_us: Option<u32>,
    },
    /// Laser off, disarm, halt the motor.
    Stop,
    /// Leave the fault state; says which fault it cleared.
    ClearFault,
    /// Print the profile the rig runs.
    ProfileShow,
    /// Print the profile of the documented wiring (no rig needed).
    ProfileDefault {
        /// The internal 12-bit DAC galvo path instead of the external SPI DAC.
        internal_dac: bool,
    },
    /// Validate the `--profile` file (no rig needed).
    ProfileCheck,
    /// Send the `--profile` file to the rig.
    ProfileSend,
    /// The bring-up check (`rig selftest`).
    Selftest {
        /// Agree to laser light in advance and ask nothing else.
        yes: bool,
        /// Laser channel for the test captures.
        channel: u8,
    },
}

/// Which rig to talk to.
#[derive(Debug, Clone)]
pub struct RigTarget {
    /// Serial port of the rig.
    pub port: Option<String>,
    /// Baud rate.
    pub baud: u32,
    /// The simulated rig inside this process instead of a serial port.
    pub sim: bool,
    /// How long to wait for each reply, milliseconds.
    pub reply_timeout_ms: u64,
}

/// Why a rig command failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ManualError {
    /// The flags do not say what to do, or the self-test failed.
    #[error("{0}")]
    Invalid(String),
    /// A step failed; `what` names it, `source` says why.
    #[error("{what}")]
    Step {
        /// The step (e.g. `talking to the simulated rig`).
        what: String,
        /// Why.
        #[source]
        source: Box<ManualError>,
    },
    /// The rig failed or did not answer.
    #[error(transparent)]
    Rig(#[from] RigClientError),
    /// The serial port or pseudo-terminal failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// Writing the pseudo-terminal's path failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The profile file could not be read.
    #[error(transparent)]
    Profile(#[from] ProfileFileError),
}

/// Names the step that failed, as `anyhow::Context` does in the binary.
fn step(what: String) -> impl FnOnce(ManualError) -> ManualError {
    move |e| ManualError::Step {
        what,
        source: Box::new(e),
    }
}

/// The profile of the documented wiring (`rig profile default`), with the internal 12-bit DAC
/// galvo path when `internal_dac`.
pub fn default_profile(internal_dac: bool) -> RigProfile {
    let mut p = RigProfile::DEFAULT;
    if internal_dac {
        p.galvo = RigProfile::INTERNAL_DAC;
    }
    p
}

/// `rig profile check`'s line for a valid profile file.
pub fn profile_check_line(p: &RigProfile) -> String {
    format!(
        "profile ok: {} steps per revolution, galvo {:?} (codes 0..={}), {} lasers, \
         camera read-out {} us",
        p.steps_per_rev().unwrap_or(0),
        p.galvo.output,
        p.galvo_max(),
        p.laser.channels,
        p.camera.readout_us
    )
}

/// Does `action`: the profile actions that need no rig at once, the others on the rig
/// `target` reaches (the simulated rig runs `profile`); errors say which rig.
pub fn run(
    target: &RigTarget,
    action: ManualAction,
    profile: Option<RigProfile>,
    say: fn(&str),
) -> Result<(), ManualError> {
    match action {
        ManualAction::ProfileDefault { internal_dac } => {
            say(&profile_json(&default_profile(internal_dac)));
            Ok(())
        }
        ManualAction::ProfileCheck => {
            let Some(p) = profile else {
                return Err(ManualError::Invalid(
                    "`rig profile check` checks the file given with --profile FILE".into(),
                ));
            };
            say(&profile_check_line(&p));
            Ok(())
        }
        action => connect_and_act(target, action, profile, say),
    }
}

/// Connects to `target` (the simulated rig runs `profile`) and does `action`; errors say
/// which rig.
pub fn connect_and_act(
    target: &RigTarget,
    action: ManualAction,
    profile: Option<RigProfile>,
    say: fn(&str),
) -> Result<(), ManualError> {
    let config = ClientConfig {
        give_up_after: Duration::from_millis(target.reply_timeout_ms),
        ..ClientConfig::default()
    };
    let (link, what): (Box<dyn ByteLink>, String) = match (&target.port, target.sim) {
        (Some(path), false) => (
            Box::new(SerialLink::open(path, target.baud)?),
            format!("the rig on {path}"),
        ),
        // In-process and in virtual time: moves and exposures finish at once.
        (None, true) => {
            let params = SimParams {
                profile: profile.unwrap_or_default(),
                ..SimParams::default()
            };
            (
                Box::new(SimLink::clean(VirtualRig::new(params))),
                "the simulated rig".to_owned(),
            )
        }
        _ => {
            return Err(ManualError::Invalid(
                "say which rig: --port PATH (see `subsurf ports`) or --sim".into(),
            ));
        }
    };
    let mut rig = RigClient::connect(link, config)
        .map_err(ManualError::from)
        .map_err(step(format!(
            "connecting to {what} (is it powered, and is this the right port and baud rate?)"
        )))?;
    act(&mut rig, action, profile, say).map_err(step(format!("talking to {what}")))
}

/// `rig serve-sim`: serves the simulated rig (running `profile`) on a new pseudo-terminal
/// until killed. Its path goes to `out` first (flushed: a client reads it from there), then
/// `note` says so.
pub fn serve_sim(
    profile: RigProfile,
    out: &mut dyn std::io::Write,
    note: fn(&str),
) -> Result<(), ManualError> {
    let (controller, device) = SerialLink::pty_pair()
        .map_err(ManualError::from)
        .map_err(step(
            "creating a pseudo-terminal for the simulated rig".into(),
        ))?;
    let path = device
        .path()
        .ok_or_else(|| ManualError::Invalid("the pseudo-terminal has no device path".into()))?;
    writeln!(out, "{path}")
        .map_err(ManualError::from)
        .map_err(step("writing the pseudo-terminal path".into()))?;
    out.flush()
        .map_err(ManualError::from)
        .map_err(step("flushing stdout".into()))?;
    note(&format!("serving the simulated rig on {path} until killed"));
    // Keeping the device end open means the controller never sees end-of-file between clients.
    let _device = device;
    let params = SimParams {
        profile,
        ..SimParams::default()
    };
    crate::sim::serve_forever(controller, params)
        .map_err(ManualError::from)
        .map_err(step("serving the simulated rig".into()))?;
    Ok(())
}

/// Asks on the terminal (stderr, stdin): the self-test's prompt when a person is there.
pub struct TerminalPrompt;

impl Prompt for TerminalPrompt {
    fn consent(&mut self, question: &str) -> bool {
        eprint!("{question} [y/N] ");
        let mut line = String::new();
        if std::io::stdin().lock().read_line(&mut line).is_err() {
            return false;
        }
        matches!(line.trim().to_ascii_lowercase().as_str(), "y" | "yes")
    }
    fn tell(&mut self, instruction: &str) -> bool {
        eprintln!("{instruction}");
        true
    }
    fn confirm(&mut self, question: &str) -> Option<bool> {
        eprint!("{question} [y/n/s(kip)] ");
        let mut line = String::new();
        std::io::stdin().lock().read_line(&mut line).ok()?;
        match line.trim().to_ascii_lowercase().as_str() {
            "y" | "yes" => Some(true),
            "n" | "no" => Some(false),
            _ => None,
        }
    }
    fn wait_for(&mut self, instruction: &str) -> bool {
        eprint!("{instruction} (or type s and Enter to skip) ");
        let mut line = String::new();
        if std::io::stdin().lock().read_line(&mut line).is_err() {
            return false;
        }
        !line.trim().eq_ignore_ascii_case("s")
    }
}

/// Does `action` on the connected rig; `profile` is the `--profile` file's (sent by
/// `ProfileSend`, expected by `Selftest`); `say` prints a line for the user.
pub fn act(
    rig: &mut RigClient<Box<dyn ByteLink>>,
    action: ManualAction,
    profile: Option<RigProfile>,
    say: fn(&str),
) -> Result<(), ManualError> {
    match action {
        ManualAction::Hello => {
            let h = rig.hello();
            let v = h.firmware_version;
            let c = h.capabilities;
            say(&format!("protocol version: {}", h.protocol_version));
            say(&format!(
                "firmware version: {}.{}.{}",
                v.major, v.minor, v.patch
            ));
            say(&format!("boot nonce: {:#010x}", h.boot_nonce));
            say(&format!("steps per revolution: {}", c.steps_per_rev));
            say(&format!("galvo codes: 0..={}", c.galvo_max));
            say(&format!("laser channels: {}", c.laser_channels));
            say(&format!("max speed: {} steps/s", c.max_speed));
            say(&format!("max acceleration: {} steps/s^2", c.max_accel));
            say(&format!(
                "exposure: {}..={} us, camera read-out {} us",
                c.min_exposure_us, c.max_exposure_us, c.camera_readout_us
            ));
            say(&format!("max program points: {}", c.max_program_points));
        }
        ManualAction::Status => {
            for line in status_lines(&rig.status()?) {
                say(&line);
            }
        }
        ManualAction::Home { timeout_ms } => {
            rig.home()?;
            let s = rig.wait_idle(Duration::from_millis(timeout_ms))?;
            say(&format!("homed: {} at position {}", s.homed, s.position));
        }
        ManualAction::Move {
            to,
            by,
            speed,
            accel,
            timeout_ms,
        } => {
            let caps = rig.hello().capabilities;
            let speed = speed.unwrap_or((caps.max_speed / 4).max(1));
            let accel = accel.unwrap_or((caps.max_accel / 4).max(1));
            let target = match (to, by) {
                (Some(to), None) => MoveTarget::Absolute(to),
                (None, Some(by)) => MoveTarget::Relative(by),
                _ => {
                    return Err(ManualError::Invalid(
                        "give exactly one of --to and --by".into(),
                    ));
                }
            };
            rig.start_move(target, speed, accel)?;
            let s = rig.wait_idle(Duration::from_millis(timeout_ms))?;
            say(&format!("position: {}", s.position));
        }
        ManualAction::Galvo { x, y } => {
            rig.galvo(x, y)?;
            say(&format!("galvo: {x} {y}"));
        }
        ManualAction::LaserArm => {
            rig.arm()?;
            say("armed (the rig disarms when this program exits and heartbeats stop)");
        }
        ManualAction::LaserDisarm => {
            rig.disarm()?;
            say("disarmed");
        }
        ManualAction::LaserOn { channel, hold_ms } => {
            rig.arm()?;
            rig.laser(channel, true)?;
            say(&format!("laser {channel} on for {hold_ms} ms"));
            rig.poll(Duration::from_millis(hold_ms))?;
            rig.laser(channel, false)?;
            rig.disarm()?;
            say(&format!("laser {channel} off, disarmed"));
        }
        ManualAction::LaserOff { channel } => {
            rig.laser(channel, false)?;
            say(&format!("laser {channel} off"));
        }
        ManualAction::Capture {
            x,
            y,
            channel,
            exposure_us,
            trigger_us,
            settle_us,
        } => {
            rig.arm()?;
            let result = rig.capture(
                Capture {
                    galvo: GalvoPoint { x, y },
                    settle_us,
                    channel,
                    exposure_us,
                    trigger_us,
                },
                Duration::from_millis(u64::from(exposure_us / 1000) + 5000),
            );
            // Disarm even when the capture failed; report the capture's error first.
            let disarmed = rig.disarm();
            let c = result?;
            disarmed?;
            say(&format!(
                "capture {}: triggered at {} us, galvo {} {}, channel {}",
                c.capture_id, c.triggered_at_us, c.galvo.x, c.galvo.y, c.channel
            ));
            match c.exposure {
                Some(e) => say(&format!(
                    "camera exposure {}: {} us after the trigger, {} us long, {}",
                    c.exposure_count,
                    e.delay_us,
                    e.duration_us,
                    if c.lit {
                        "lit throughout"
                    } else {
                        "NOT lit throughout (raise the laser margins in the profile)"
                    }
                )),
                None => {
                    say("camera exposure NOT confirmed: no exposure-active edge (missed trigger?)")
                }
            }
        }
        ManualAction::Stop => {
            rig.stop()?;
            say("stopped: laser off, disarmed, motor halted");
        }
        ManualAction::ClearFault => match rig.status()?.fault {
            None => say("no fault to clear"),
            Some(fault) => {
                rig.clear_fault()?;
                say(&format!(
                    "cleared fault {fault:?} (home again before absolute moves)"
                ));
            }
        },
        ManualAction::ProfileShow => say(&profile_json(&rig.get_profile()?)),
        ManualAction::ProfileSend => {
            let Some(p) = profile else {
                return Err(ManualError::Invalid(
                    "`rig profile send` sends the file given with --profile FILE".into(),
                ));
            };
            rig.set_profile(p)?;
            say(&format!(
                "profile sent: {} steps per revolution; home the rig again",
                rig.hello().capabilities.steps_per_rev
            ));
        }
        ManualAction::Selftest { yes, channel } => {
            use std::io::IsTerminal;
            let options = SelftestOptions {
                expect_profile: profile,
                channel,
                ..SelftestOptions::default()
            };
            let mut no_prompt = selftest::NoPrompt;
            let mut assume_yes = selftest::AssumeYes;
            let mut terminal = TerminalPrompt;
            let prompt: &mut dyn Prompt = if yes {
                &mut assume_yes
            } else if std::io::stdin().is_terminal() {
                &mut terminal
            } else {
                &mut no_prompt
            };
            let report = selftest::run(
                rig,
                prompt,
                &options,
                Box::new(move |step| {
                    let tag = match step.verdict {
                        Verdict::Pass => "PASS",
                        Verdict::Fail => "FAIL",
                        Verdict::Skip => "SKIP",
                    };
                    say(&format!("{tag} {}: {}", step.name, step.detail));
                }),
            );
            say(&format!(
                "selftest: {} passed, {} failed, {} skipped",
                report.count(Verdict::Pass),
                report.count(Verdict::Fail),
                report.count(Verdict::Skip)
            ));
            if !report.passed() {
                return Err(ManualError::Invalid(
                    "the self-test failed (see the FAIL lines above)".into(),
                ));
            }
        }
        ManualAction::ProfileDefault { .. } | ManualAction::ProfileCheck => {
            return Err(ManualError::Invalid("handled before connecting".into()));
        }
    }
    Ok(())
}

/// The rig's status as lines for a person.
pub fn status_lines(s: &Status) -> Vec<String> {
    let mut lines = Vec::new();
    let mut say = |l: &str| lines.push(l.to_string());
    say(&format!("state: {:?}", s.state));
    say(&format!("position: {} (homed: {})", s.position, s.homed));
    say(&format!(
        "armed: {}, lasers on: {:#010b}",
        s.armed, s.lasers
    ));
    say(&format!("galvo: {} {}", s.galvo.x, s.galvo.y));
    say(&format!(
        "inputs: estop {}, interlock closed {}, home switch {}",
        s.inputs.estop, s.inputs.interlock_closed, s.inputs.home_switch
    ));
    match s.fault {
        Some(f) => say(&format!("fault: {f:?}")),
        None => say("fault: none"),
    }
    say(&format!("boot nonce: {:#010x}", s.boot_nonce));
    say(&format!(
        "next capture id: {}, camera exposures: {}",
        s.next_capture_id, s.exposures
    ));
    say(&format!(
        "program: {}/{} points loaded",
        s.program_received, s.program_len
    ));
    say(&format!("frames dropped by the rig: {}", s.rx_dropped));
    say(&format!("rig uptime: {:.3} s", s.uptime_us as f64 / 1e6));
    lines
}
