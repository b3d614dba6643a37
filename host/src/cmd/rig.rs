//! `subsurf rig …`: talk to the rig (or the simulated rig) by hand. Parsing only; the actions
//! are `subsurf::rig::manual`.

use std::path::PathBuf;

use anyhow::bail;
use subsurf::rig::load_profile;
use subsurf::rig::manual::{self, ManualAction, RigTarget};

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
    let action = match args.action {
        Action::ServeSim => {
            if args.port.is_some() || args.sim {
                bail!("`rig serve-sim` creates its own pseudo-terminal: drop --port/--sim");
            }
            let note = |line: &str| eprintln!("{line}");
            manual::serve_sim(profile.unwrap_or_default(), &mut std::io::stdout(), note)?;
            return Ok(());
        }
        Action::Profile {
            what: ProfileAction::Default { internal_dac },
        } => ManualAction::ProfileDefault { internal_dac },
        Action::Profile {
            what: ProfileAction::Check,
        } => ManualAction::ProfileCheck,
        Action::Hello => ManualAction::Hello,
        Action::Status => ManualAction::Status,
        Action::Home { timeout_ms } => ManualAction::Home { timeout_ms },
        Action::Move {
            to,
            by,
            speed,
            accel,
            timeout_ms,
        } => ManualAction::Move {
            to,
            by,
            speed,
            accel,
            timeout_ms,
        },
        Action::Galvo { x, y } => ManualAction::Galvo { x, y },
        Action::Laser { what } => match what {
            LaserAction::Arm => ManualAction::LaserArm,
            LaserAction::Disarm => ManualAction::LaserDisarm,
            LaserAction::On { channel, hold_ms } => ManualAction::LaserOn { channel, hold_ms },
            LaserAction::Off { channel } => ManualAction::LaserOff { channel },
        },
        Action::Capture {
            x,
            y,
            channel,
            exposure_us,
            trigger_us,
            settle_us,
        } => ManualAction::Capture {
            x,
            y,
            channel,
            exposure_us,
            trigger_us,
            settle_us,
        },
        Action::Stop => ManualAction::Stop,
        Action::ClearFault => ManualAction::ClearFault,
        Action::Profile {
            what: ProfileAction::Show,
        } => ManualAction::ProfileShow,
        Action::Profile {
            what: ProfileAction::Send,
        } => ManualAction::ProfileSend,
        Action::Selftest { yes, channel } => ManualAction::Selftest { yes, channel },
    };
    let target = RigTarget {
        port: args.port,
        baud: args.baud,
        sim: args.sim,
        reply_timeout_ms: args.reply_timeout_ms,
    };
    manual::run(&target, action, profile, |line| println!("{line}"))?;
    Ok(())
}
