//! The rig profile: the mechanics and I/O of one physical rig as data.
//!
//! The host keeps it in a file (`subsurf rig profile`), sends it with [`crate::Command::SetProfile`];
//! the board validates it ([`RigProfile::validate`]), persists it in flash and runs from it after
//! every reset; the simulator runs the same profile, so the tests exercise the board's galvo,
//! camera and motor model. Every field is bounded: [`RigProfile::validate`] is the single rule,
//! used by the host before sending and by the rig before accepting.

use serde::{Deserialize, Serialize};

/// Longest accepted heartbeat timeout, ms: a lost host leaves the laser on for at most this long.
pub const MAX_HEARTBEAT_TIMEOUT_MS: u32 = 5_000;

/// Longest a manual [`crate::Command::Laser`] may stay on, ms.
pub const MAX_MANUAL_LASER_MS: u32 = 60_000;

/// Longest accepted galvo settle time (fixed part, or per 1000 codes), µs.
pub const MAX_SETTLE_US: u32 = 1_000_000;

/// Shortest STEP pulse a profile may ask for, µs (opto-isolated drivers need ≥ 2.5 µs; the board's
/// timer resolution is 1 µs).
pub const MIN_STEP_PULSE_US: u16 = 2;

/// Longest STEP pulse, µs: what the board's step generator places (a longer one would be cut to
/// this without anyone knowing, so it is refused instead). Slow opto-isolated inputs need 5-10 µs.
pub const MAX_STEP_PULSE_US: u16 = 50;

/// Longest DIR set-up, µs: the board keeps DIR at least this long before the STEP edge after
/// a reversal. Every motion starts from rest, so its first step comes at least
/// `sqrt(2 / max_accel)` ≥ 447 µs after the previous motion's last one, far above this and
/// [`MAX_STEP_PULSE_US`] together.
pub const MAX_DIR_SETUP_US: u16 = 100;

/// Laser enables the board drives (TIM8 channels 1, 3 and 4: PC6, PC8, PC9). A profile with
/// more would announce channels that fire nothing, so it is refused.
pub const BOARD_LASER_CHANNELS: u8 = 3;

/// Shortest exposure any profile may allow, µs: below this the laser driver's rise time and the
/// timer's resolution dominate.
pub const MIN_EXPOSURE_FLOOR_US: u32 = 10;

/// Longest exposure, µs.
pub const MAX_EXPOSURE_US: u32 = 2_000_000;

/// How the galvo mirrors are driven.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GalvoOutput {
    /// External 16-bit SPI DAC (DAC8552-class) through a bipolar ±5/±10 V output stage: code
    /// 32768 = 0 V = mirror centred. The documented choice.
    ExternalDac16,
    /// The STM32's internal 12-bit DAC (PA4/PA5): buffered output swings about 0.2-3.1 V, and PA5
    /// is loaded by the Nucleo's LED LD2 (remove SB21). A fallback for bench tests.
    InternalDac12,
}

impl GalvoOutput {
    /// Largest code of this output (both axes).
    pub const fn max_code(self) -> u16 {
        match self {
            Self::ExternalDac16 => u16::MAX,
            Self::InternalDac12 => 4095,
        }
    }

    /// Mid-scale code: mirror centred (0 V behind a bipolar stage). Written at boot, never (0, 0).
    pub const fn center(self) -> u16 {
        self.max_code() / 2 + 1
    }
}

/// The turntable drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MotorProfile {
    /// Full steps per motor revolution (200 for a 1.8° motor).
    pub full_steps_per_rev: u16,
    /// Driver microstepping (1, 2, 4, ... 256).
    pub microsteps: u16,
    /// Motor revolutions per `gear_den` turntable revolutions (belt/gear ratio numerator).
    pub gear_num: u16,
    /// Gear ratio denominator.
    pub gear_den: u16,
    /// Fastest move, steps/s.
    pub max_speed: u32,
    /// Largest acceleration, steps/s².
    pub max_accel: u32,
    /// STEP pulse width, µs.
    pub step_pulse_us: u16,
    /// DIR set-up time before the first STEP edge after a reversal, µs (`0..=MAX_DIR_SETUP_US`;
    /// the board's step generator keeps it).
    pub dir_setup_us: u16,
    /// DIR high = decreasing position (motor wired the other way round).
    pub invert_dir: bool,
    /// STEP pulse is a low pulse (common-anode opto inputs).
    pub step_active_low: bool,
    /// EN low = driver enabled (A4988, DRV8825, TMC2209).
    pub enable_active_low: bool,
}

impl MotorProfile {
    /// Microsteps per turntable revolution, `None` when the gear ratio does not divide evenly or
    /// the count overflows.
    pub fn steps_per_rev(&self) -> Option<u32> {
        let motor = u64::from(self.full_steps_per_rev) * u64::from(self.microsteps);
        let num = motor.checked_mul(u64::from(self.gear_num))?;
        let den = u64::from(self.gear_den);
        if den == 0 || num % den != 0 {
            return None;
        }
        u32::try_from(num / den)
            .ok()
            .filter(|s| *s > 0 && *s <= i32::MAX as u32)
    }
}

/// The galvo mirrors: output path and settle model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct GalvoProfile {
    /// Which DAC.
    pub output: GalvoOutput,
    /// Settle time for a zero-length jump, µs.
    pub settle_min_us: u32,
    /// Extra settle time per 1000 codes of the larger axis jump, µs (scale it with the code
    /// range: the internal 12-bit DAC needs about 16× the 16-bit figure for the same angle).
    pub settle_per_kcode_us: u32,
}

/// The camera's trigger input and exposure-active output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct CameraProfile {
    /// Time after an exposure ends before the camera accepts the next trigger, µs (sensor
    /// read-out). Capture programs refuse intervals shorter than exposure + read-out.
    pub readout_us: u32,
    /// Shortest exposure the hardware honours, µs (at least [`MIN_EXPOSURE_FLOOR_US`]).
    pub min_exposure_us: u32,
    /// Longest the camera may take from the trigger edge to raising exposure-active (and from the
    /// laser going off to dropping it), µs; beyond it the capture counts as unconfirmed.
    pub confirm_timeout_us: u32,
    /// Trigger line is active low.
    pub trigger_active_low: bool,
    /// Exposure-active (strobe) output is active low.
    pub exposure_active_low: bool,
}

/// The laser channels and their window around the exposure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LaserProfile {
    /// Laser channels wired (`1..=BOARD_LASER_CHANNELS`).
    pub channels: u8,
    /// Enable lines are active low.
    pub active_low: bool,
    /// Laser on this long before the trigger edge, µs (covers the camera's trigger latency).
    pub lead_us: u32,
    /// Laser kept on this long after the nominal exposure end, µs.
    pub tail_us: u32,
    /// A manual `Laser { on: true }` goes off by itself after this long, ms
    /// (`1..=MAX_MANUAL_LASER_MS`).
    pub manual_max_ms: u32,
}

/// Two-pass homing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct HomingProfile {
    /// First (fast) approach speed, steps/s.
    pub speed: u32,
    /// Acceleration of the fast approach and back-off, steps/s².
    pub accel: u32,
    /// Second approach speed, steps/s: slow enough to stop within one step.
    pub slow_speed: u32,
    /// Back-off past the switch's release point before the slow approach, steps.
    pub backoff_steps: u32,
    /// The switch must read active this long before it counts, µs.
    pub debounce_us: u32,
    /// Homing faults after this many steps in any one pass.
    pub max_steps: u32,
    /// Home switch is active low (switch to GND with pull-up).
    pub switch_active_low: bool,
}

/// Everything about one physical rig (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RigProfile {
    /// Turntable drive.
    pub motor: MotorProfile,
    /// Galvo output and settle model.
    pub galvo: GalvoProfile,
    /// Camera timing.
    pub camera: CameraProfile,
    /// Lasers.
    pub laser: LaserProfile,
    /// Homing.
    pub homing: HomingProfile,
}

/// Which profile field is out of range ([`RigProfile::validate`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ProfileError {
    /// Steps per revolution not a whole number in `1..=i32::MAX`.
    Gearing,
    /// Speed or acceleration zero or above the step generator's limits.
    MotorLimits,
    /// STEP pulse or DIR set-up outside `MIN_STEP_PULSE_US..=MAX_STEP_PULSE_US` µs /
    /// `0..=MAX_DIR_SETUP_US` µs, or the pulse longer than half the fastest step period.
    StepTiming,
    /// Galvo settle above [`MAX_SETTLE_US`].
    GalvoSettle,
    /// Camera timing out of range.
    Camera,
    /// Laser channel count, window margins or manual limit out of range.
    Laser,
    /// Homing speeds, back-off, debounce or step limit out of range.
    Homing,
}

/// Fastest step rate the board's step generator is specified for, steps/s.
pub const MAX_STEP_RATE: u32 = 50_000;

impl RigProfile {
    /// The key of this struct's postcard layout: CRC-32 of its shape (struct and field names,
    /// field types, in order, and each enum's variants with their wire indices), which
    /// `protocol/tests/profile_layout.rs` computes from the `Serialize` impl and requires to be
    /// this constant. The board's flash record carries it, so a record written by a firmware
    /// with another layout (a field changed, or an enum's variants reordered, which postcard
    /// writes as indices) reads as "no profile stored" instead of being decoded into the wrong
    /// fields or variants.
    pub const LAYOUT: u32 = 0xa77a_36a9;

    /// The documented wiring (README): 200-step motor, 1/16 microstepping, 5:1 belt (16 000
    /// steps per revolution), external 16-bit galvo DAC, three lasers, a machine-vision camera
    /// with a 10 ms read-out.
    pub const DEFAULT: RigProfile = RigProfile {
        motor: MotorProfile {
            full_steps_per_rev: 200,
            microsteps: 16,
            gear_num: 5,
            gear_den: 1,
            max_speed: 20_000,
            max_accel: 200_000,
            step_pulse_us: 5,
            dir_setup_us: 5,
            invert_dir: false,
            step_active_low: false,
            enable_active_low: true,
        },
        galvo: GalvoProfile {
            output: GalvoOutput::ExternalDac16,
            settle_min_us: 100,
            settle_per_kcode_us: 20,
        },
        camera: CameraProfile {
            readout_us: 10_000,
            min_exposure_us: 20,
            confirm_timeout_us: 2_000,
            trigger_active_low: false,
            exposure_active_low: false,
        },
        laser: LaserProfile {
            channels: 3,
            active_low: false,
            lead_us: 50,
            tail_us: 50,
            manual_max_ms: 10_000,
        },
        homing: HomingProfile {
            speed: 8_000,
            accel: 40_000,
            slow_speed: 1_000,
            backoff_steps: 200,
            debounce_us: 2_000,
            max_steps: 18_000,
            switch_active_low: true,
        },
    };

    /// The fallback galvo path: the STM32's internal 12-bit DAC, 300 µs per 1000 codes.
    pub const INTERNAL_DAC: GalvoProfile = GalvoProfile {
        output: GalvoOutput::InternalDac12,
        settle_min_us: 100,
        settle_per_kcode_us: 300,
    };

    /// Microsteps per turntable revolution (`None` if the profile is invalid).
    pub fn steps_per_rev(&self) -> Option<u32> {
        self.motor.steps_per_rev()
    }

    /// Largest galvo code.
    pub fn galvo_max(&self) -> u16 {
        self.galvo.output.max_code()
    }

    /// Check every field against its bounds; the rig refuses a profile that fails.
    pub fn validate(&self) -> Result<(), ProfileError> {
        let m = &self.motor;
        if m.steps_per_rev().is_none() || m.microsteps == 0 {
            return Err(ProfileError::Gearing);
        }
        if !(1..=MAX_STEP_RATE).contains(&m.max_speed) || !(1..=10_000_000).contains(&m.max_accel) {
            return Err(ProfileError::MotorLimits);
        }
        // The pulse must fit in half the shortest step period.
        let half_period = 500_000 / m.max_speed;
        if !(MIN_STEP_PULSE_US..=MAX_STEP_PULSE_US).contains(&m.step_pulse_us)
            || u32::from(m.step_pulse_us) > half_period
            || m.dir_setup_us > MAX_DIR_SETUP_US
        {
            return Err(ProfileError::StepTiming);
        }
        if self.galvo.settle_min_us > MAX_SETTLE_US
            || self.galvo.settle_per_kcode_us > MAX_SETTLE_US
        {
            return Err(ProfileError::GalvoSettle);
        }
        let c = &self.camera;
        if c.readout_us > 10_000_000
            || !(MIN_EXPOSURE_FLOOR_US..=MAX_EXPOSURE_US).contains(&c.min_exposure_us)
            || !(1..=1_000_000).contains(&c.confirm_timeout_us)
        {
            return Err(ProfileError::Camera);
        }
        let l = &self.laser;
        if !(1..=BOARD_LASER_CHANNELS).contains(&l.channels)
            || l.lead_us > 100_000
            || l.tail_us > 100_000
            || !(1..=MAX_MANUAL_LASER_MS).contains(&l.manual_max_ms)
        {
            return Err(ProfileError::Laser);
        }
        let h = &self.homing;
        let speed_ok = |v: u32| (1..=m.max_speed).contains(&v);
        if !speed_ok(h.speed)
            || !speed_ok(h.slow_speed)
            || h.slow_speed > h.speed
            || !(1..=m.max_accel).contains(&h.accel)
            || h.backoff_steps > h.max_steps
            || h.debounce_us > 1_000_000
            || h.max_steps == 0
        {
            return Err(ProfileError::Homing);
        }
        Ok(())
    }
}

impl Default for RigProfile {
    fn default() -> Self {
        Self::DEFAULT
    }
}
