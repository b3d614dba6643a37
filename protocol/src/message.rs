//! The message set: host → rig [`Request`]s, rig → host [`RigMessage`]s (replies and events).
//!
//! Every type here is plain data with a fixed upper size (no `String`, no unbounded `Vec`), so a whole
//! message always fits into one frame of at most [`crate::MAX_FRAME`] bytes.

use heapless::Vec;
use serde::{Deserialize, Serialize};

use crate::profile::{ProfileError, RigProfile};

/// Version of this wire format. The rig refuses a [`Command::Hello`] with any other version
/// ([`RigError::UnknownVersion`]), so host and rig never talk past each other.
///
/// Version 2 appended [`Command::Replay`] and [`Response::Events`] (event recovery). Version 3
/// added sessions (a boot nonce in [`Hello`] and [`Status`]; nothing but `Hello` before one),
/// the [`RigProfile`] (`SetProfile`/`GetProfile`), camera confirmation in [`Captured`], and cut
/// [`Config`] down to the session's heartbeat. Version 4 appended
/// [`RigError::ProfileNotStored`]: a board without a stored profile does not know its laser and
/// trigger polarities and refuses to arm (see `docs/protocol.md`). Version 5 (more of what a real
/// bench needs) appended [`RigError::LaserPolarity`]: the board refuses to arm when its undriven
/// laser lines contradict the profile's polarity; [`RigError::ProfileNotSaved`] and
/// [`Command::GetStoredProfile`]: a `SetProfile` is answered only after flash reads it back;
/// [`Fault::StepLate`] and [`HaltReason::StepLate`]: a step interrupt later than one timer period
/// stops the motion. Version 6 appended [`Command::DarkCapture`]: the camera triggered with every
/// laser off, for the dark frames a scan measures its noise floor from (its [`Captured`] says
/// `lit` false; every earlier encoding is unchanged). Version 7 appended
/// [`Command::BoardRegisters`] and [`Response::BoardRegisters`]: the board's registers that only
/// hardware can show (brown-out level, flash accelerator, debug freeze, the step counter's
/// wiring), for the self-test.
pub const PROTOCOL_VERSION: u16 = 7;

/// Galvo points per [`Command::ProgramPoints`] chunk: 32 points of at most 6 bytes each keep the
/// chunk well inside [`crate::MAX_MESSAGE`].
pub const PROGRAM_CHUNK: usize = 32;

/// Number of laser channels a [`Command::Laser`] can address (bits of [`Status::lasers`]).
pub const MAX_LASER_CHANNELS: u8 = 8;

/// How many recent replies the rig keeps for answering retransmissions (see `docs/protocol.md`).
pub const REPLY_CACHE: usize = 4;

/// A request at most this far behind the newest executed `seq` (wrapping) and no longer in the
/// reply cache is a late duplicate: refused with [`RigError::StaleSequence`], never executed.
/// Farther back counts as new (a host that restarted without `Hello`).
pub const STALE_WINDOW: u32 = 64;

/// Most events one [`Response::Events`] carries: three of the largest event (about 70 bytes) plus
/// the reply's header stay inside [`crate::MAX_MESSAGE`] (pinned by `protocol/tests/wire.rs`).
pub const REPLAY_BATCH: usize = 3;

/// Request sequence number. The host increments it (wrapping) for every new request and reuses it
/// when it retransmits; the rig echoes it in the [`Reply`].
pub type Seq = u32;

/// One host → rig message. See `docs/protocol.md` for the sequence and retransmission rules.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Request {
    /// Echoed in the reply; a repeated `seq` is answered from the rig's reply cache, not re-run.
    pub seq: Seq,
    /// What the rig should do.
    pub command: Command,
}

/// Everything the host can ask the rig to do.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Command {
    /// Handshake: the host's [`PROTOCOL_VERSION`]; answered with [`Response::Hello`]. Opens the
    /// session: until a `Hello` succeeds after a reset, every other command is refused with
    /// [`RigError::NoSession`].
    Hello {
        /// The host's protocol version.
        protocol_version: u16,
    },
    /// Keeps the link alive (any valid request does); answered with [`Response::Ack`].
    Heartbeat,
    /// Answered with [`Response::Status`].
    Status,
    /// Answered with [`Response::Config`].
    GetConfig,
    /// Replaces the rig's tunable settings; answered with [`Response::Ack`].
    SetConfig(Config),
    /// Two-pass homing (fast approach, back-off, slow approach, debounced); position 0 at the
    /// switch edge; [`EventKind::Homed`] when done.
    Home,
    /// Move the turntable; [`EventKind::MoveDone`] when done. The laser is forced off meanwhile.
    /// An absolute target needs a homed axis ([`RigError::NotHomed`]).
    Move(Move),
    /// Set the galvo DAC codes now.
    Galvo(GalvoPoint),
    /// Allow laser emission (refused with the interlock open, e-stop pressed, in fault, or with
    /// no profile stored).
    Arm,
    /// Forbid laser emission; all channels go off.
    Disarm,
    /// Switch one laser channel (armed and not moving only). "On" lasts at most the profile's
    /// `laser.manual_max_ms`, then the rig halts with [`HaltReason::LaserTimeout`].
    Laser {
        /// Channel index, `0..capabilities.laser_channels`.
        channel: u8,
        /// On or off; "off" is always accepted.
        on: bool,
    },
    /// One atomic capture; answered with [`Response::CaptureStarted`], then [`EventKind::Captured`].
    Capture(Capture),
    /// Start uploading a queued capture program (discards any previous one).
    ProgramLoad(ProgramHeader),
    /// One chunk of program points, in order.
    ProgramPoints(ProgramChunk),
    /// Run the fully uploaded program: one [`EventKind::Captured`] per point, then
    /// [`EventKind::ProgramDone`].
    ProgramRun,
    /// Laser off, disarm, abort any capture or program; a move decelerates to a stop (and the
    /// axis is no longer homed).
    Stop,
    /// Leave the fault state once its cause is gone (e.g. e-stop released).
    ClearFault,
    /// Send again the events from `event_seq = since` on (events are not acknowledged, so the
    /// host asks for the ones it saw a gap for); answered with [`Response::Events`].
    Replay {
        /// The first `event_seq` the host is missing.
        since: u32,
        /// At most this many events (the rig caps it at [`REPLAY_BATCH`]): on a noisy line a
        /// short reply gets through where a long one would not.
        max: u8,
    },
    /// Replace the rig profile (idle only): validated, lasers off and disarmed, written to the
    /// board's flash and read back; only then applied (the axis is no longer homed) and answered
    /// with [`Response::Ack`]. [`RigError::BadProfile`] or [`RigError::ProfileNotSaved`] (the
    /// old profile stays in force and in flash) otherwise (version 5: the reply waits for the
    /// verified write).
    SetProfile(RigProfile),
    /// The profile in force (RAM); answered with [`Response::Profile`].
    GetProfile,
    /// The profile the board's flash holds now, read from flash: what the next boot runs
    /// (version 5). Answered with [`Response::Profile`], or [`RigError::ProfileNotStored`].
    GetStoredProfile,
    /// One capture with every laser off (version 6): the camera's dark frame, from which the
    /// host measures its noise floor. Needs no arming and moves no mirror: it emits nothing (an open
    /// interlock still halts it, as any capture).
    /// Answered with [`Response::CaptureStarted`], then [`EventKind::Captured`] with `lit` false
    /// and channel 0.
    DarkCapture(DarkCapture),
    /// The board's registers the bring-up checklist compares with their expected values
    /// (version 7). Answered with [`Response::BoardRegisters`] (`None` from a rig without them,
    /// the simulated one).
    BoardRegisters,
}

/// A turntable move. Speeds in steps/s, acceleration in steps/s².
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Move {
    /// Where to go.
    pub target: MoveTarget,
    /// Cruise speed, steps/s (`1..=capabilities.max_speed`).
    pub max_speed: u32,
    /// Acceleration and deceleration, steps/s² (`1..=capabilities.max_accel`).
    pub accel: u32,
}

/// Absolute or relative move target, in motor steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MoveTarget {
    /// Go to this step position.
    Absolute(i32),
    /// Go this many steps from the current position (out of range if the sum overflows i32).
    Relative(i32),
}

/// Galvo DAC codes for the two mirror axes, `0..=capabilities.galvo_max`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct GalvoPoint {
    /// X mirror code.
    pub x: u16,
    /// Y mirror code.
    pub y: u16,
}

/// One atomic capture: galvo → settle → laser on → camera trigger → expose → laser off.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Capture {
    /// Where to point the laser.
    pub galvo: GalvoPoint,
    /// Settle time after the galvo jump; `None` = computed by the rig from the jump size.
    pub settle_us: Option<u32>,
    /// Laser channel to fire.
    pub channel: u8,
    /// Exposure, µs (`capabilities.min_exposure_us..=capabilities.max_exposure_us`). The laser is
    /// on from the profile's `laser.lead_us` before the trigger edge to `laser.tail_us` after
    /// the exposure's nominal end.
    pub exposure_us: u32,
    /// Camera trigger pulse width, µs (`1..=exposure_us`).
    pub trigger_us: u32,
}

/// A capture with every laser off: the trigger timing of [`Capture`] without a laser or a galvo
/// point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DarkCapture {
    /// Exposure, µs (`capabilities.min_exposure_us..=capabilities.max_exposure_us`).
    pub exposure_us: u32,
    /// Camera trigger pulse width, µs (`1..=exposure_us`).
    pub trigger_us: u32,
}

/// Header of a queued capture program: the shared capture settings and the point count.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ProgramHeader {
    /// Number of points that will follow (`1..=capabilities.max_program_points`).
    pub len: u16,
    /// Laser channel for every capture.
    pub channel: u8,
    /// Settle time per point; `None` = from the jump size.
    pub settle_us: Option<u32>,
    /// Laser-on time per capture, µs.
    pub exposure_us: u32,
    /// Camera trigger pulse width, µs.
    pub trigger_us: u32,
    /// Minimum time between the starts of two consecutive captures, µs: at least `exposure_us`
    /// plus the profile's camera read-out ([`RigError::IntervalTooShort`] otherwise).
    pub interval_us: u32,
}

/// A run of program points starting at index `offset`. Chunks must arrive in order
/// (`offset` = points received so far); a repeated chunk is answered from the reply cache.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ProgramChunk {
    /// Index of the first point of this chunk within the program.
    pub offset: u16,
    /// The points.
    pub points: Vec<GalvoPoint, PROGRAM_CHUNK>,
}

/// The session's settings (read with [`Command::GetConfig`], written with [`Command::SetConfig`]);
/// back to [`Config::DEFAULT`] after a reset. Mechanics and I/O are the [`RigProfile`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Config {
    /// Without any valid request for this long, the rig turns the laser off, disarms and halts
    /// (`1..=`[`crate::MAX_HEARTBEAT_TIMEOUT_MS`]).
    pub heartbeat_timeout_ms: u32,
}

impl Config {
    /// Settings at power-on.
    pub const DEFAULT: Config = Config {
        heartbeat_timeout_ms: 2_000,
    };
}

impl Default for Config {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Rig → host: either a reply to a request or an unsolicited event.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RigMessage {
    /// Answer to the request with the same `seq`.
    Reply(Reply),
    /// Something happened on the rig.
    Event(Event),
}

/// The rig's answer to one request.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Reply {
    /// The request's sequence number.
    pub seq: Seq,
    /// What the request did, or why the rig refused it (nothing was executed then).
    pub result: Result<Response, RigError>,
}

/// Successful answers.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Response {
    /// Accepted; for long operations, completion comes as an event.
    Ack,
    /// Answer to [`Command::Hello`].
    Hello(Hello),
    /// Answer to [`Command::Status`].
    Status(Status),
    /// Answer to [`Command::GetConfig`].
    Config(Config),
    /// The capture was started with this id; [`EventKind::Captured`] carries the same id.
    CaptureStarted {
        /// Id of the capture (a rig-wide counter).
        capture_id: u32,
    },
    /// The program was started; its captures get ids `first_capture_id..first_capture_id + len`.
    ProgramStarted {
        /// Id of the program's first capture.
        first_capture_id: u32,
    },
    /// Answer to [`Command::Replay`].
    Events(EventReplay),
    /// Answer to [`Command::GetProfile`].
    Profile(RigProfile),
    /// Answer to [`Command::BoardRegisters`].
    BoardRegisters(Option<BoardRegisters>),
}

/// Registers of the STM32F446 that only the hardware can show, as the running firmware reads
/// them ([`Command::BoardRegisters`]; `subsurf flash` reads the same addresses through the
/// probe). [`BoardRegisters::checks`] compares each with the value the firmware sets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BoardRegisters {
    /// FLASH_OPTCR (0x4002_3C14): the option bytes, BOR_LEV in bits 3:2.
    pub flash_optcr: u32,
    /// FLASH_ACR (0x4002_3C00): wait states, prefetch, instruction and data caches.
    pub flash_acr: u32,
    /// DBGMCU_APB1_FZ (0xE004_2008): which APB1 timers and watchdogs a debug halt freezes.
    pub dbgmcu_apb1_fz: u32,
    /// DBGMCU_APB2_FZ (0xE004_200C): the same for APB2 (TIM8).
    pub dbgmcu_apb2_fz: u32,
    /// TIM2_CR2 (0x4000_0004): MMS, what TIM2 sends on its trigger output.
    pub tim2_cr2: u32,
    /// TIM4_SMCR (0x4000_0808): TIM4's slave mode and trigger input.
    pub tim4_smcr: u32,
}

/// One register compared with its expected value ([`BoardRegisters::checks`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RegisterCheck {
    /// Register and field, as the reference manual names them.
    pub name: &'static str,
    /// The register's address.
    pub address: u32,
    /// The bits that matter.
    pub mask: u32,
    /// Their expected value (within `mask`).
    pub expected: u32,
    /// What the expected value means.
    pub meaning: &'static str,
}

impl RegisterCheck {
    /// Whether `value` (the whole register) has the expected bits.
    pub const fn holds(&self, value: u32) -> bool {
        value & self.mask == self.expected
    }
}

impl BoardRegisters {
    /// What each register must hold on a board running this firmware (RM0390), in the order of
    /// [`BoardRegisters::values`]; the bring-up checklist lists the same (`docs/board.md`).
    pub const CHECKS: [RegisterCheck; 6] = [
        RegisterCheck {
            name: "FLASH_OPTCR.BOR_LEV",
            address: 0x4002_3C14,
            mask: 0b11 << 2,
            expected: 0b00 << 2,
            meaning: "brown-out reset level 3 (2.70 V falling)",
        },
        RegisterCheck {
            name: "FLASH_ACR.LATENCY/PRFTEN/ICEN/DCEN",
            address: 0x4002_3C00,
            mask: 0x0000_070F,
            expected: 0x0000_0705,
            meaning: "5 wait states, prefetch, instruction and data caches on",
        },
        RegisterCheck {
            name: "DBGMCU_APB1_FZ.TIM2/TIM3/TIM4/TIM5/IWDG",
            address: 0xE004_2008,
            mask: 0x0000_100F,
            expected: 0x0000_0005,
            meaning: "a halt freezes the step timer and its counter; the trigger and deadline \
                      timers and the watchdog run on",
        },
        RegisterCheck {
            name: "DBGMCU_APB2_FZ.TIM8",
            address: 0xE004_200C,
            mask: 0x0000_0002,
            expected: 0,
            meaning: "a halt leaves the laser timer running, so a timed window still ends",
        },
        RegisterCheck {
            name: "TIM2_CR2.MMS",
            address: 0x4000_0004,
            mask: 0b111 << 4,
            expected: 0b010 << 4,
            meaning: "TIM2's update event is its trigger output",
        },
        RegisterCheck {
            name: "TIM4_SMCR.TS/SMS",
            address: 0x4000_0808,
            mask: 0b111 << 4 | 0b111,
            expected: 0b001 << 4 | 0b111,
            meaning: "TIM4 counts TIM2's updates (ITR1, external clock mode 1)",
        },
    ];

    /// The registers in the order of [`BoardRegisters::CHECKS`].
    pub const fn values(&self) -> [u32; 6] {
        [
            self.flash_optcr,
            self.flash_acr,
            self.dbgmcu_apb1_fz,
            self.dbgmcu_apb2_fz,
            self.tim2_cr2,
            self.tim4_smcr,
        ]
    }

    /// The registers from their values in the order of [`BoardRegisters::CHECKS`].
    pub const fn from_values(v: [u32; 6]) -> Self {
        Self {
            flash_optcr: v[0],
            flash_acr: v[1],
            dbgmcu_apb1_fz: v[2],
            dbgmcu_apb2_fz: v[3],
            tim2_cr2: v[4],
            tim4_smcr: v[5],
        }
    }

    /// Each check with the value read and whether it holds.
    pub fn checks(&self) -> [(RegisterCheck, u32, bool); 6] {
        let values = self.values();
        let mut out = [(Self::CHECKS[0], 0, false); 6];
        for (slot, (check, value)) in out.iter_mut().zip(Self::CHECKS.iter().zip(values)) {
            *slot = (*check, value, check.holds(value));
        }
        out
    }
}

/// Events sent again from the rig's bounded event history (answer to [`Command::Replay`]).
///
/// The rig keeps only its most recent events: events from `since` up to `oldest` (wrapping) have
/// been overwritten and are gone for good. `events` holds the kept events from
/// `max(since, oldest)` on, in order, at most [`REPLAY_BATCH`]; the host asks again from the one
/// after the last if that is still before `next_event_seq`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct EventReplay {
    /// `event_seq` of the oldest event the rig still holds (= `next_event_seq` when it holds none).
    pub oldest: u32,
    /// `event_seq` the rig's next event will get.
    pub next_event_seq: u32,
    /// The events, consecutive and in `event_seq` order.
    pub events: Vec<Event, REPLAY_BATCH>,
}

/// Handshake answer: what the rig is and can do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Hello {
    /// The rig's [`PROTOCOL_VERSION`].
    pub protocol_version: u16,
    /// Firmware build version.
    pub firmware_version: FirmwareVersion,
    /// Random per power-on: a change means the rig reset (its homing, program and reply cache are
    /// gone) and the host must handshake and home again.
    pub boot_nonce: u32,
    /// Hardware limits.
    pub capabilities: Capabilities,
}

/// Semantic version of the firmware.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FirmwareVersion {
    /// Major.
    pub major: u16,
    /// Minor.
    pub minor: u16,
    /// Patch.
    pub patch: u16,
}

/// Fixed hardware limits of the rig, announced in the handshake.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Capabilities {
    /// Motor steps (microsteps) per turntable revolution.
    pub steps_per_rev: u32,
    /// Largest galvo DAC code (both axes).
    pub galvo_max: u16,
    /// Number of laser channels.
    pub laser_channels: u8,
    /// Largest accepted move speed, steps/s.
    pub max_speed: u32,
    /// Largest accepted acceleration, steps/s².
    pub max_accel: u32,
    /// Longest accepted exposure, µs.
    pub max_exposure_us: u32,
    /// Shortest accepted exposure, µs (the profile's `camera.min_exposure_us`).
    pub min_exposure_us: u32,
    /// Camera read-out after each exposure, µs (the profile's `camera.readout_us`).
    pub camera_readout_us: u32,
    /// Most points in one queued capture program.
    pub max_program_points: u16,
}

/// What the rig is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RigState {
    /// Nothing in progress.
    Idle,
    /// Seeking the home switch.
    Homing,
    /// Turntable moving.
    Moving,
    /// Running one atomic capture.
    Capturing,
    /// Running a queued capture program.
    Program,
    /// Stopped by a fault; see [`Status::fault`].
    Fault,
}

/// Raw state of the rig's safety and homing inputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Inputs {
    /// Emergency stop pressed.
    pub estop: bool,
    /// Enclosure interlock closed (laser allowed).
    pub interlock_closed: bool,
    /// Home switch active.
    pub home_switch: bool,
}

/// A snapshot of the rig (answer to [`Command::Status`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Status {
    /// The rig's [`Hello::boot_nonce`]: a change means it reset.
    pub boot_nonce: u32,
    /// What the rig is doing.
    pub state: RigState,
    /// Current turntable position, steps.
    pub position: i32,
    /// Whether position 0 is the home switch.
    pub homed: bool,
    /// Laser armed.
    pub armed: bool,
    /// Bit `i` set = laser channel `i` emitting.
    pub lasers: u8,
    /// Current galvo codes.
    pub galvo: GalvoPoint,
    /// Safety and homing inputs.
    pub inputs: Inputs,
    /// The active fault, if any.
    pub fault: Option<Fault>,
    /// Id the next capture will get (= captures completed or started so far).
    pub next_capture_id: u32,
    /// Exposures the camera confirmed since boot ([`Captured::exposure_count`] of the last).
    pub exposures: u32,
    /// Sequence number the next event will get: lets the host detect lost events.
    pub next_event_seq: u32,
    /// Points of the loaded program received so far / its length.
    pub program_received: u16,
    /// Length of the loaded program (0 = none).
    pub program_len: u16,
    /// Frames the rig's decoder dropped (corrupt, oversize, malformed).
    pub rx_dropped: u32,
    /// Rig clock, µs since boot.
    pub uptime_us: u64,
}

/// Why the rig refused a request. Nothing was executed when a request gets an error.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum RigError {
    /// The host's protocol version is not the rig's.
    UnknownVersion {
        /// The rig's version.
        rig: u16,
    },
    /// Laser command while disarmed.
    NotArmed,
    /// Arming or laser command with the enclosure interlock open.
    InterlockOpen,
    /// Emergency stop is pressed.
    EmergencyStop,
    /// The rig is in fault; send [`Command::ClearFault`] once the cause is gone.
    Faulted(Fault),
    /// Another operation is in progress (move, homing, capture, program).
    Busy,
    /// A parameter is outside the announced capabilities, or a relative move overflows.
    OutOfRange,
    /// No such laser channel.
    NoSuchChannel,
    /// Program chunk out of order, or running a program that is not completely uploaded.
    ProgramIncomplete,
    /// A request older than the rig's reply cache (already executed, its reply is gone).
    StaleSequence,
    /// No session: the rig reset since the host's last `Hello` (handshake and home again).
    NoSession,
    /// An absolute move before the axis was homed (or after a halt cut a motion).
    NotHomed,
    /// The profile sent with [`Command::SetProfile`] is out of range.
    BadProfile(ProfileError),
    /// Exposure shorter than the hardware honours.
    ExposureTooShort {
        /// The shortest accepted exposure, µs.
        min_us: u32,
    },
    /// Program interval shorter than exposure plus camera read-out.
    IntervalTooShort {
        /// The shortest accepted interval for this exposure, µs.
        min_us: u32,
    },
    /// `Arm` before the rig knows its laser and trigger polarities: no valid profile is stored
    /// (a new board, or flash the firmware cannot read). The board keeps those pins
    /// high-impedance until a profile is set with [`Command::SetProfile`] (version 4). Since
    /// version 5 also `Home` and `Move` (the board keeps the motor driver's EN released), and
    /// [`Command::GetStoredProfile`] with nothing stored.
    ProfileNotStored,
    /// `Arm` while a laser enable, undriven, sits at the level the profile calls "on": the
    /// wiring's resistor holds every line at its off level, so the profile's `laser.active_low`
    /// is not the wiring's (or a resistor is missing). Nothing is driven (version 5).
    LaserPolarity,
    /// [`Command::SetProfile`] could not be stored: the write failed or did not read back as
    /// sent. The profile in force and in flash is the old one (version 5).
    ProfileNotSaved(SaveError),
}

/// Why a profile save failed ([`RigError::ProfileNotSaved`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum SaveError {
    /// The profile does not fit a flash record.
    Encode,
    /// The flash controller reported an error erasing a sector.
    Erase,
    /// The flash controller reported an error programming the record.
    Program,
    /// The write completed but flash does not read back the profile sent.
    Verify,
}

/// Conditions that stop the rig until [`Command::ClearFault`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Fault {
    /// Emergency stop was pressed.
    EmergencyStop,
    /// Homing ran `homing.max_steps` in one pass without the switch changing.
    HomingFailed,
    /// The step generator ran dry while a move was in progress (steps lost: position unknown).
    StepStall,
    /// The step interrupt ran later than one timer period, so the timer may have repeated a
    /// period: a step nobody counted (Klipper's "Timer too close"). Position unknown (version 5).
    StepLate,
}

/// Unsolicited rig → host message. `event_seq` increases by one per event, so the host can tell
/// when one was lost on the link (and reconcile through [`Command::Status`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Event {
    /// Per-rig event counter (wrapping).
    pub event_seq: u32,
    /// Rig clock when the event was emitted, µs since boot.
    pub timestamp_us: u64,
    /// What happened.
    pub kind: EventKind,
}

/// What an [`Event`] reports.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum EventKind {
    /// A capture finished (laser off again).
    Captured(Captured),
    /// A move finished at this position.
    MoveDone {
        /// Final position, steps.
        position: i32,
    },
    /// Homing finished; position is now 0 at the home switch's edge.
    Homed {
        /// Where the new zero lay in the previous homing's coordinates, when the axis was
        /// homed before and nothing cut a motion since: 0 (±1 step) on a repeatable rig, the
        /// drift otherwise. `subsurf rig selftest` homes twice and reports it.
        previous: Option<i32>,
    },
    /// A queued program finished or was aborted after `completed` captures.
    ProgramDone {
        /// Captures run.
        completed: u16,
        /// Whether all points were captured.
        finished: bool,
    },
    /// Work in progress was aborted and the laser forced off and disarmed.
    Halted {
        /// Why.
        reason: HaltReason,
    },
}

/// What the camera's exposure-active output showed for one capture, relative to the trigger edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ExposureActive {
    /// From the trigger edge to exposure-active rising, µs.
    pub delay_us: u32,
    /// Exposure-active high time, µs.
    pub duration_us: u32,
}

/// One finished capture.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Captured {
    /// Capture id (from [`Response::CaptureStarted`] or [`Response::ProgramStarted`]).
    pub capture_id: u32,
    /// Index within the running program, `None` for an atomic capture.
    pub program_index: Option<u16>,
    /// Rig clock at the trigger edge as the hardware timestamped it, µs.
    pub triggered_at_us: u64,
    /// The camera's confirmation; `None` = no exposure-active edge within the profile's
    /// `camera.confirm_timeout_us` (a missed trigger: no image for this capture).
    pub exposure: Option<ExposureActive>,
    /// Confirmed exposures since boot, this one included: the camera's own frame counter
    /// (minus its count at boot) must equal it, which is how images are matched to captures.
    pub exposure_count: u32,
    /// Whether the laser was on for the whole confirmed exposure.
    pub lit: bool,
    /// Where the laser pointed.
    pub galvo: GalvoPoint,
    /// Which channel fired (0 for a [`Command::DarkCapture`], whose `lit` is false: none did).
    pub channel: u8,
}

/// Why the rig halted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum HaltReason {
    /// [`Command::Stop`].
    Stop,
    /// Emergency stop pressed.
    EmergencyStop,
    /// Enclosure interlock opened.
    InterlockOpen,
    /// No request within `heartbeat_timeout_ms`.
    HeartbeatLost,
    /// Homing failed.
    HomingFailed,
    /// A manual laser stayed on for the profile's `laser.manual_max_ms`.
    LaserTimeout,
    /// The step generator stalled ([`Fault::StepStall`]).
    StepStall,
    /// The step interrupt was late ([`Fault::StepLate`]).
    StepLate,
}
