//! `subsurf rig …`: talk to the rig (or the simulated rig) by hand.

use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use subsurf::link::{ByteLink, SerialLink};
use subsurf::rig::selftest::{self, Prompt, SelftestOptions, Verdict};
use subsurf::rig::{ClientConfig, RigClient, load_profile, profile_json};
use subsurf::sim::{SimLink, SimParams, VirtualRig};
use subsurf_protocol::{Capture, GalvoPoint, MoveTarget, RigProfile, Status};

/// Drive the rig over a serial port (`--port`) or the built-in simulated rig (`--sim`).
///
/// The rig turns its laser off and disarms when the host stops sending heartbeats, so every
/// invocation leaves the laser safe when it exits; `laser on` therefore holds the laser on for
/// `--hold-ms` and then switches it off again.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Serial port of the rig (e.g. /dev/ttyACM0, or the path `rig serve-sim` printed).
    #[arg(long, global = true, conflicts_with = "sim")]
    port: Option<String>,
    /// Baud rate (ignored by USB CDC devices and pseudo-terminals).
    #[arg(long, global = true, default_value_t = 115_200)]
    baud: u32,
    /// Use the simulated rig inside this process (virtual time) instead of a serial port.
    #[arg(long, global = true)]
    sim: bool,
    /// How long to wait for each reply before giving up, in milliseconds.
    #[arg(long, global = true, default_value_t = 2000)]
    reply_timeout_ms: u64,
    /// The rig profile file (JSON: mechanics, galvo, camera, lasers, homing; start from
    /// `subsurf rig profile default`). The simulated rig runs it; `profile send` sends it;
    /// `selftest` checks the rig runs it. Default: the documented wiring.
    #[arg(long, global = true)]
    profile: Option<PathBuf>,
    #[command(subcommand)]
    action: Action,
}

#[derive(Debug, clap::Subcommand)]
enum Action {
    /// Handshake: protocol and firmware version, capabilities.
    Hello,
    /// Position, state, laser, inputs, counters.
    Status,
    /// Seek the home switch and wait until homed.
    Home {
        /// Give up waiting after this many milliseconds.
        #[arg(long, default_value_t = 60_000)]
        timeout_ms: u64,
    },
    /// Move the turntable and wait until the move is done.
    Move {
        /// Absolute target position in steps.
        #[arg(
            long,
            allow_hyphen_values = true,
            conflicts_with = "by",
            required_unless_present = "by"
        )]
        to: Option<i32>,
        /// Relative move in steps.
        #[arg(long, allow_hyphen_values = true)]
        by: Option<i32>,
        /// Cruise speed, steps/s (default: a quarter of the rig's maximum).
        #[arg(long)]
        speed: Option<u32>,
        /// Acceleration, steps/s² (default: a quarter of the rig's maximum).
        #[arg(long)]
        accel: Option<u32>,
        /// Give up waiting after this many milliseconds.
        #[arg(long, default_value_t = 60_000)]
        timeout_ms: u64,
    },
    /// Point the galvo at DAC codes X Y.
    Galvo {
        /// X mirror code.
        x: u16,
        /// Y mirror code.
        y: u16,
    },
    /// Arm, disarm, or switch a laser channel.
    Laser {
        #[command(subcommand)]
        what: LaserAction,
    },
    /// One atomic capture (arms the laser for it and disarms afterwards).
    Capture {
        /// Galvo X code.
        #[arg(long, default_value_t = 0)]
        x: u16,
        /// Galvo Y code.
        #[arg(long, default_value_t = 0)]
        y: u16,
        /// Laser channel.
        #[arg(long, default_value_t = 0)]
        channel: u8,
        /// Laser-on time, µs.
        #[arg(long, default_value_t = 10_000)]
        exposure_us: u32,
        /// Camera trigger pulse, µs.
        #[arg(long, default_value_t = 100)]
        trigger_us: u32,
        /// Galvo settle time, µs (default: computed by the rig from the jump).
        #[arg(long)]
        settle_us: Option<u32>,
    },
    /// Laser off, disarm, halt the motor.
    Stop,
    /// Leave the fault state (e-stop released, homing or step fault dealt with); says which
    /// fault it cleared.
    ClearFault,
    /// The rig profile: show the rig's, print the default, check or send a file.
    Profile {
        #[command(subcommand)]
        what: ProfileAction,
    },
    /// Bring-up check for a real bench: handshake, profile (stored, and the file's) and config
    /// read-back, home twice and compare, a move whose count the home switch checks,
    /// trigger/exposure-active loopback, galvo sweep, the interlock, the laser cut with a laser
    /// on, the e-stop. Asks before anything emits light and before clearing a fault. Exits
    /// non-zero when a step fails.
    Selftest {
        /// Agree to laser light in advance (the beam path is safe) and ask nothing else: steps
        /// that need someone watching or acting (move seen, sweep seen, interlock, laser cut,
        /// e-stop) are skipped. Without it and without a terminal, nothing emits light.
        #[arg(long)]
        yes: bool,
        /// Laser channel for the test captures.
        #[arg(long, default_value_t = 0)]
        channel: u8,
    },
    /// Serve the simulated rig on a new pseudo-terminal until killed; prints its path first.
    ServeSim,
}

#[derive(Debug, clap::Subcommand)]
enum ProfileAction {
    /// Print the profile the rig runs (JSON, the file format).
    Show,
    /// Print the profile of the documented wiring (JSON), to start a profile file from.
    Default {
        /// The internal 12-bit DAC galvo path instead of the external SPI DAC.
        #[arg(long)]
        internal_dac: bool,
    },
    /// Validate the --profile file without a rig.
    Check,
    /// Send the --profile file to the rig (the board stores it in flash); the axis must be
    /// homed again afterwards.
    Send,
}

#[derive(Debug, clap::Subcommand)]
enum LaserAction {
    /// Allow emission.
    Arm,
    /// Forbid emission (all channels off).
    Disarm,
    /// Arm, switch CHANNEL on for --hold-ms, then off and disarm.
    On {
        /// Laser channel.
        channel: u8,
        /// How long to keep it on, milliseconds.
        #[arg(long, default_value_t = 1000)]
        hold_ms: u64,
    },
    /// Switch CHANNEL off.
    Off {
        /// Laser channel.
        channel: u8,
    },
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let profile = match &args.profile {
        Some(path) => Some(load_profile(path)?),
        None => None,
    };
    match &args.action {
        Action::ServeSim => {
            if args.port.is_some() || args.sim {
                bail!("`rig serve-sim` creates its own pseudo-terminal: drop --port/--sim");
            }
            return serve_sim(profile.unwrap_or_default());
        }
        Action::Profile {
            what: ProfileAction::Default { internal_dac },
        } => {
            let mut p = RigProfile::DEFAULT;
            if *internal_dac {
                p.galvo = RigProfile::INTERNAL_DAC;
            }
            println!("{}", profile_json(&p));
            return Ok(());
        }
        Action::Profile {
            what: ProfileAction::Check,
        } => {
            let Some(p) = profile else {
                bail!("`rig profile check` checks the file given with --profile FILE");
            };
            println!(
                "profile ok: {} steps per revolution, galvo {:?} (codes 0..={}), {} lasers, \
                 camera read-out {} us",
                p.steps_per_rev().unwrap_or(0),
                p.galvo.output,
                p.galvo_max(),
                p.laser.channels,
                p.camera.readout_us
            );
            return Ok(());
        }
        _ => {}
    }
    let config = ClientConfig {
        give_up_after: Duration::from_millis(args.reply_timeout_ms),
        ..ClientConfig::default()
    };
    let (link, what): (Box<dyn ByteLink>, String) = match (&args.port, args.sim) {
        (Some(path), false) => (
            Box::new(SerialLink::open(path, args.baud)?),
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
        _ => bail!("say which rig: --port PATH (see `subsurf ports`) or --sim"),
    };
    let mut rig = RigClient::connect(link, config).with_context(|| {
        format!("connecting to {what} (is it powered, and is this the right port and baud rate?)")
    })?;
    act(&mut rig, args.action, profile).with_context(|| format!("talking to {what}"))
}

/// Asks on the terminal.
struct TerminalPrompt;

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

fn act(
    rig: &mut RigClient<Box<dyn ByteLink>>,
    action: Action,
    profile: Option<RigProfile>,
) -> anyhow::Result<()> {
    match action {
        Action::Hello => {
            let h = rig.hello();
            let v = h.firmware_version;
            let c = h.capabilities;
            println!("protocol version: {}", h.protocol_version);
            println!("firmware version: {}.{}.{}", v.major, v.minor, v.patch);
            println!("boot nonce: {:#010x}", h.boot_nonce);
            println!("steps per revolution: {}", c.steps_per_rev);
            println!("galvo codes: 0..={}", c.galvo_max);
            println!("laser channels: {}", c.laser_channels);
            println!("max speed: {} steps/s", c.max_speed);
            println!("max acceleration: {} steps/s^2", c.max_accel);
            println!(
                "exposure: {}..={} us, camera read-out {} us",
                c.min_exposure_us, c.max_exposure_us, c.camera_readout_us
            );
            println!("max program points: {}", c.max_program_points);
        }
        Action::Status => print_status(&rig.status()?),
        Action::Home { timeout_ms } => {
            rig.home()?;
            let s = rig.wait_idle(Duration::from_millis(timeout_ms))?;
            println!("homed: {} at position {}", s.homed, s.position);
        }
        Action::Move {
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
                _ => bail!("give exactly one of --to and --by"),
            };
            rig.start_move(target, speed, accel)?;
            let s = rig.wait_idle(Duration::from_millis(timeout_ms))?;
            println!("position: {}", s.position);
        }
        Action::Galvo { x, y } => {
            rig.galvo(x, y)?;
            println!("galvo: {x} {y}");
        }
        Action::Laser { what } => match what {
            LaserAction::Arm => {
                rig.arm()?;
                println!("armed (the rig disarms when this program exits and heartbeats stop)");
            }
            LaserAction::Disarm => {
                rig.disarm()?;
                println!("disarmed");
            }
            LaserAction::On { channel, hold_ms } => {
                rig.arm()?;
                rig.laser(channel, true)?;
                println!("laser {channel} on for {hold_ms} ms");
                rig.poll(Duration::from_millis(hold_ms))?;
                rig.laser(channel, false)?;
                rig.disarm()?;
                println!("laser {channel} off, disarmed");
            }
            LaserAction::Off { channel } => {
                rig.laser(channel, false)?;
                println!("laser {channel} off");
            }
        },
        Action::Capture {
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
            println!(
                "capture {}: triggered at {} us, galvo {} {}, channel {}",
                c.capture_id, c.triggered_at_us, c.galvo.x, c.galvo.y, c.channel
            );
            match c.exposure {
                Some(e) => println!(
                    "camera exposure {}: {} us after the trigger, {} us long, {}",
                    c.exposure_count,
                    e.delay_us,
                    e.duration_us,
                    if c.lit {
                        "lit throughout"
                    } else {
                        "NOT lit throughout (raise the laser margins in the profile)"
                    }
                ),
                None => println!(
                    "camera exposure NOT confirmed: no exposure-active edge (missed trigger?)"
                ),
            }
        }
        Action::Stop => {
            rig.stop()?;
            println!("stopped: laser off, disarmed, motor halted");
        }
        Action::ClearFault => match rig.status()?.fault {
            None => println!("no fault to clear"),
            Some(fault) => {
                rig.clear_fault()?;
                println!("cleared fault {fault:?} (home again before absolute moves)");
            }
        },
        Action::Profile { what } => match what {
            ProfileAction::Show => println!("{}", profile_json(&rig.get_profile()?)),
            ProfileAction::Send => {
                let Some(p) = profile else {
                    bail!("`rig profile send` sends the file given with --profile FILE");
                };
                rig.set_profile(p)?;
                println!(
                    "profile sent: {} steps per revolution; home the rig again",
                    rig.hello().capabilities.steps_per_rev
                );
            }
            ProfileAction::Default { .. } | ProfileAction::Check => {
                bail!("handled before connecting")
            }
        },
        Action::Selftest { yes, channel } => {
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
                Box::new(|step| {
                    let tag = match step.verdict {
                        Verdict::Pass => "PASS",
                        Verdict::Fail => "FAIL",
                        Verdict::Skip => "SKIP",
                    };
                    println!("{tag} {}: {}", step.name, step.detail);
                }),
            );
            println!(
                "selftest: {} passed, {} failed, {} skipped",
                report.count(Verdict::Pass),
                report.count(Verdict::Fail),
                report.count(Verdict::Skip)
            );
            if !report.passed() {
                bail!("the self-test failed (see the FAIL lines above)");
            }
        }
        Action::ServeSim => bail!("serve-sim is handled before connecting"),
    }
    Ok(())
}

fn print_status(s: &Status) {
    println!("state: {:?}", s.state);
    println!("position: {} (homed: {})", s.position, s.homed);
    println!("armed: {}, lasers on: {:#010b}", s.armed, s.lasers);
    println!("galvo: {} {}", s.galvo.x, s.galvo.y);
    println!(
        "inputs: estop {}, interlock closed {}, home switch {}",
        s.inputs.estop, s.inputs.interlock_closed, s.inputs.home_switch
    );
    match s.fault {
        Some(f) => println!("fault: {f:?}"),
        None => println!("fault: none"),
    }
    println!("boot nonce: {:#010x}", s.boot_nonce);
    println!(
        "next capture id: {}, camera exposures: {}",
        s.next_capture_id, s.exposures
    );
    println!(
        "program: {}/{} points loaded",
        s.program_received, s.program_len
    );
    println!("frames dropped by the rig: {}", s.rx_dropped);
    println!("rig uptime: {:.3} s", s.uptime_us as f64 / 1e6);
}

fn serve_sim(profile: RigProfile) -> anyhow::Result<()> {
    let (controller, device) =
        SerialLink::pty_pair().context("creating a pseudo-terminal for the simulated rig")?;
    let path = device
        .path()
        .context("the pseudo-terminal has no device path")?;
    let mut out = std::io::stdout().lock();
    writeln!(out, "{path}").context("writing the pseudo-terminal path")?;
    out.flush().context("flushing stdout")?;
    drop(out);
    eprintln!("serving the simulated rig on {path} until killed");
    // Keeping the device end open means the controller never sees end-of-file between clients.
    let _device = device;
    let params = SimParams {
        profile,
        ..SimParams::default()
    };
    subsurf::sim::serve_forever(controller, params).context("serving the simulated rig")?;
    Ok(())
}
