//! Putting the board firmware on the rig's Nucleo-F446RE with the probe-rs library.
//!
//! Order of work, so nothing is touched with a file that cannot be right: [`FirmwareImage::inspect`]
//! checks the ELF (32-bit little-endian ARM, a vector table in the chip's flash, every loaded
//! section inside flash or RAM and none in the profile's sectors) before any probe is listed; then [`list_probes`] /
//! [`select_probe`] find the debug probe, [`flash_image`] erases, programs and resets, and
//! [`handshake`] asks the running firmware for its version over the serial link.
//!
//! The same inspection gives the firmware's flash and static RAM use for the CI size budget
//! ([`Budget`]).

use std::path::{Path, PathBuf};
use std::time::Duration;

use object::{Object, ObjectSection, SectionFlags, SectionKind};
use probe_rs::flashing::{ElfLoader, ElfOptions};
use probe_rs::probe::DebugProbeSelector;
use probe_rs::probe::list::Lister;
use probe_rs::{MemoryInterface, Permissions, Session};
use subsurf_protocol::{
    BoardRegisters, Command, FirmwareVersion, FrameDecoder, MAX_FRAME, PROTOCOL_VERSION, Request,
    Response, RigMessage, encode_request,
};

use crate::link::{ByteLink, LinkError};

/// The probe-rs target name of the rig's chip.
pub const DEFAULT_CHIP: &str = "STM32F446RETx";
/// STM32F446RE flash: 512 KiB at 0x0800_0000.
pub const FLASH: std::ops::Range<u64> = 0x0800_0000..0x0808_0000;
/// Flash sectors 1 and 2 (16 KiB each): the rig profile's record log (`firmware/board/memory.x`,
/// `store.rs`). No loaded section may lie there: flashing would overwrite the stored profile and
/// the next profile save would erase code.
pub const PROFILE_SECTORS: std::ops::Range<u64> = 0x0800_4000..0x0800_C000;
/// STM32F446RE SRAM: 128 KiB at 0x2000_0000.
pub const RAM: std::ops::Range<u64> = 0x2000_0000..0x2002_0000;
/// Where `cargo fw` puts the release firmware, relative to the workspace root.
pub const DEFAULT_ELF: &str = "target/thumbv7em-none-eabihf/firmware/subsurf-board";

/// Why flashing (or checking the image) failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FlashError {
    /// The firmware file could not be read.
    #[error("cannot read firmware image {path}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a parseable ELF object.
    #[error("{path} is not an ELF file: {reason}")]
    NotElf {
        /// The file.
        path: PathBuf,
        /// The parser's complaint.
        reason: String,
    },
    /// The ELF is for another machine than the rig's Cortex-M4 (e.g. the host binary).
    #[error(
        "{path} is built for {found}, not for the rig's 32-bit little-endian ARM Cortex-M4 \
         (build it with `cargo fw`)"
    )]
    WrongArchitecture {
        /// The file.
        path: PathBuf,
        /// What it is built for.
        found: String,
    },
    /// No `.vector_table` section at the start of flash: not a cortex-m-rt firmware image.
    #[error("{path} has no .vector_table section at {:#010x}: not a firmware image for this chip", FLASH.start)]
    NoVectorTable {
        /// The file.
        path: PathBuf,
    },
    /// A section that would be loaded lies outside the chip's flash and RAM.
    #[error(
        "{path}: section {section} at {address:#010x} (+{size} bytes) is outside the chip's flash and RAM"
    )]
    OutsideMemory {
        /// The file.
        path: PathBuf,
        /// Section name.
        section: String,
        /// Its address.
        address: u64,
        /// Its size.
        size: u64,
    },
    /// A loaded section lies in the profile's flash sectors.
    #[error(
        "{path}: section {section} at {address:#010x} (+{size} bytes) overlaps the rig profile's \
         flash sectors {:#010x}..{:#010x} (firmware/board/memory.x keeps code out of them)",
        PROFILE_SECTORS.start,
        PROFILE_SECTORS.end
    )]
    OverlapsProfile {
        /// The file.
        path: PathBuf,
        /// Section name.
        section: String,
        /// Its address.
        address: u64,
        /// Its size.
        size: u64,
    },
    /// No debug probe matched.
    #[error(
        "no debug probe found (looked for {looked_for}); is the Nucleo's ST-LINK plugged in over USB?"
    )]
    NoProbe {
        /// What was searched for.
        looked_for: String,
    },
    /// `--probe` matched several probes, or none was given and several are attached.
    #[error("{count} debug probes match; pick one with --probe SERIAL (see `subsurf probes`)")]
    AmbiguousProbe {
        /// How many matched.
        count: usize,
    },
    /// A probe-rs step (open, attach, erase/program, reset) failed.
    #[error("{step} failed: {message}")]
    Probe {
        /// Which step.
        step: &'static str,
        /// probe-rs's error, rendered.
        message: String,
    },
    /// A board register read back after the reset is not what the firmware sets (the bring-up
    /// checklist in docs/board.md lists the expected values).
    #[error("board registers differ from what the firmware sets: {0}")]
    BoardRegisters(String),
    /// The serial link failed during the handshake.
    #[error("handshake over the serial link failed")]
    Link(#[from] LinkError),
    /// The firmware did not answer the handshake in time.
    #[error("no handshake reply from the firmware within {0:?}")]
    NoReply(Duration),
    /// The firmware answered something other than a hello.
    #[error("unexpected handshake reply: {0}")]
    BadReply(String),
}

/// What is in a firmware ELF and how much of the chip it uses.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FirmwareImage {
    /// The ELF file.
    pub path: PathBuf,
    /// Bytes programmed into flash (code, read-only data, vector table, initial values of `.data`).
    pub flash_bytes: u64,
    /// Static RAM (`.data` + `.bss` + `.uninit`): everything but the stack.
    pub ram_bytes: u64,
    /// Entry point (the reset handler).
    pub entry: u64,
}

impl FirmwareImage {
    /// Read and check a firmware ELF; refuses anything that is not for the rig's chip.
    pub fn inspect(path: &Path) -> Result<Self, FlashError> {
        let data = std::fs::read(path).map_err(|source| FlashError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(path, &data)
    }

    /// [`FirmwareImage::inspect`] on bytes already read.
    pub fn parse(path: &Path, data: &[u8]) -> Result<Self, FlashError> {
        let file = object::File::parse(data).map_err(|e| FlashError::NotElf {
            path: path.to_owned(),
            reason: e.to_string(),
        })?;
        if file.format() != object::BinaryFormat::Elf {
            return Err(FlashError::NotElf {
                path: path.to_owned(),
                reason: format!("{:?} object", file.format()),
            });
        }
        if file.architecture() != object::Architecture::Arm
            || file.is_64()
            || !file.is_little_endian()
        {
            return Err(FlashError::WrongArchitecture {
                path: path.to_owned(),
                found: format!(
                    "{:?}, {}-bit, {} endian",
                    file.architecture(),
                    if file.is_64() { 64 } else { 32 },
                    if file.is_little_endian() {
                        "little"
                    } else {
                        "big"
                    }
                ),
            });
        }
        let has_vectors = file
            .section_by_name(".vector_table")
            .is_some_and(|s| s.address() == FLASH.start && s.size() >= 8);
        if !has_vectors {
            return Err(FlashError::NoVectorTable {
                path: path.to_owned(),
            });
        }
        let mut flash_bytes = 0;
        let mut ram_bytes = 0;
        for section in file.sections() {
            let allocated = match section.flags() {
                SectionFlags::Elf { sh_flags } => sh_flags & u64::from(object::elf::SHF_ALLOC) != 0,
                _ => false,
            };
            if !allocated || section.size() == 0 {
                continue;
            }
            let (start, size) = (section.address(), section.size());
            let end = start.saturating_add(size);
            let in_flash = FLASH.start <= start && end <= FLASH.end;
            let in_ram = RAM.start <= start && end <= RAM.end;
            // Zero-initialised sections take no flash; initialised RAM sections (.data) are
            // copied from flash at start-up and so take both.
            let zero_init = section.kind() == SectionKind::UninitializedData;
            if in_flash && start < PROFILE_SECTORS.end && end > PROFILE_SECTORS.start {
                return Err(FlashError::OverlapsProfile {
                    path: path.to_owned(),
                    section: section.name().unwrap_or("?").to_owned(),
                    address: start,
                    size,
                });
            }
            if in_flash {
                flash_bytes += size;
            } else if in_ram {
                ram_bytes += size;
                if !zero_init {
                    flash_bytes += size;
                }
            } else {
                return Err(FlashError::OutsideMemory {
                    path: path.to_owned(),
                    section: section.name().unwrap_or("?").to_owned(),
                    address: start,
                    size,
                });
            }
        }
        Ok(Self {
            path: path.to_owned(),
            flash_bytes,
            ram_bytes,
            entry: file.entry(),
        })
    }
}

/// The firmware's memory budget: flash and static RAM ceilings the CI enforces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    /// Most flash bytes.
    pub flash: u64,
    /// Most static RAM bytes (the rest of the 128 KiB is stack headroom).
    pub ram: u64,
}

impl Budget {
    /// 128 KiB flash, 48 KiB static RAM.
    pub const RIG: Budget = Budget {
        flash: 128 * 1024,
        ram: 48 * 1024,
    };

    /// Human-readable overruns, empty when the image fits.
    pub fn overruns(&self, image: &FirmwareImage) -> Vec<String> {
        let mut out = Vec::new();
        if image.flash_bytes > self.flash {
            out.push(format!(
                "flash {} bytes > budget {} bytes",
                image.flash_bytes, self.flash
            ));
        }
        if image.ram_bytes > self.ram {
            out.push(format!(
                "static RAM {} bytes > budget {} bytes",
                image.ram_bytes, self.ram
            ));
        }
        out
    }
}

/// One attached debug probe.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProbeEntry {
    /// Probe name (e.g. "STLink V2-1").
    pub identifier: String,
    /// USB vendor id.
    pub vendor_id: u16,
    /// USB product id.
    pub product_id: u16,
    /// USB serial number (the ST-LINK's is unique per board).
    pub serial_number: Option<String>,
    /// Whether this process may open it (udev rules on Linux).
    pub accessible: bool,
}

impl ProbeEntry {
    /// The `VID:PID[:SERIAL]` selector probe-rs opens.
    pub fn selector(&self) -> DebugProbeSelector {
        DebugProbeSelector {
            vendor_id: self.vendor_id,
            product_id: self.product_id,
            interface: None,
            serial_number: self.serial_number.clone(),
        }
    }
}

impl std::fmt::Display for ProbeEntry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {:04x}:{:04x}",
            self.identifier, self.vendor_id, self.product_id
        )?;
        if let Some(serial) = &self.serial_number {
            write!(f, " serial {serial}")?;
        }
        if !self.accessible {
            write!(f, " (permission denied: install probe-rs udev rules)")?;
        }
        Ok(())
    }
}

/// Every debug probe the lister sees (CMSIS-DAP v2, ST-LINK, J-Link, ... over USB).
pub fn list_probes(lister: &Lister) -> Vec<ProbeEntry> {
    lister
        .list_all_with_access()
        .into_iter()
        .map(|item| ProbeEntry {
            identifier: item.info.identifier.clone(),
            vendor_id: item.info.vendor_id,
            product_id: item.info.product_id,
            serial_number: item.info.serial_number.clone(),
            accessible: matches!(
                item.accessibility,
                probe_rs::probe::list::Accessibility::Accessible
            ),
        })
        .collect()
}

/// Pick the probe to flash with: the one with serial `serial`, or the only one attached.
pub fn select_probe(probes: &[ProbeEntry], serial: Option<&str>) -> Result<ProbeEntry, FlashError> {
    let matching: Vec<&ProbeEntry> = probes
        .iter()
        .filter(|p| serial.is_none_or(|s| p.serial_number.as_deref() == Some(s)))
        .collect();
    let looked_for = match serial {
        Some(s) => format!("a USB debug probe with serial number {s}"),
        None => "any USB debug probe: ST-LINK (0483:3748/374b/374e/374f/3752/3753), CMSIS-DAP v2, \
                 J-Link, ESP USB-JTAG, FTDI"
            .to_owned(),
    };
    match matching.as_slice() {
        [] => Err(FlashError::NoProbe {
            looked_for: if probes.is_empty() {
                looked_for
            } else {
                format!(
                    "{looked_for}; attached: {}",
                    probes
                        .iter()
                        .map(ToString::to_string)
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            },
        }),
        [one] => Ok((*one).clone()),
        many => Err(FlashError::AmbiguousProbe { count: many.len() }),
    }
}

fn probe_err(step: &'static str) -> impl FnOnce(probe_rs::Error) -> FlashError {
    move |e| FlashError::Probe {
        step,
        message: e.to_string(),
    }
}

/// Erase, program and verify `image` on `chip` through `probe`, then reset the core so the new
/// firmware runs, and read back, once it has booted, the registers only hardware can show
/// ([`BoardRegisters`]: brown-out level, flash accelerator, debug freeze, the step counter's
/// wiring). `progress` hears about each step and each register with its expected value;
/// [`FlashError::BoardRegisters`] when one differs.
pub fn flash_image(
    lister: &Lister,
    probe: &ProbeEntry,
    chip: &str,
    image: &FirmwareImage,
    mut progress: impl FnMut(&str),
) -> Result<BoardRegisters, FlashError> {
    progress("opening probe");
    let opened = lister
        .open(probe.selector())
        .map_err(|e| FlashError::Probe {
            step: "opening the probe",
            message: e.to_string(),
        })?;
    progress("attaching to the chip");
    let mut session: Session = opened
        .attach(chip, Permissions::default())
        .map_err(probe_err("attaching to the chip"))?;
    progress("erasing and programming flash");
    probe_rs::flashing::download_file(&mut session, &image.path, ElfLoader(ElfOptions::default()))
        .map_err(|e| FlashError::Probe {
            step: "programming flash",
            message: e.to_string(),
        })?;
    progress("resetting");
    let mut core = session.core(0).map_err(probe_err("resetting the core"))?;
    core.reset().map_err(probe_err("resetting the core"))?;
    // The firmware sets these up within its first milliseconds (and programs the brown-out
    // option byte on its first boot); the probe reads them while it runs.
    std::thread::sleep(BOOT_SETTLE);
    progress("reading the board's registers");
    let registers = read_board_registers(|address| core.read_word_32(u64::from(address)))
        .map_err(probe_err("reading the board's registers"))?;
    let lines = register_lines(&registers);
    for (_, line) in &lines {
        progress(line);
    }
    let differ: Vec<String> = lines
        .into_iter()
        .filter(|(ok, _)| !ok)
        .map(|(_, line)| line)
        .collect();
    if differ.is_empty() {
        Ok(registers)
    } else {
        Err(FlashError::BoardRegisters(differ.join("; ")))
    }
}

/// How long the firmware is given to boot before its registers are read.
const BOOT_SETTLE: Duration = Duration::from_millis(500);

/// The registers of [`BoardRegisters::CHECKS`], each read with `read` (a probe's memory read).
pub fn read_board_registers<E>(
    mut read: impl FnMut(u32) -> Result<u32, E>,
) -> Result<BoardRegisters, E> {
    let mut values = [0u32; 6];
    for (value, check) in values.iter_mut().zip(BoardRegisters::CHECKS) {
        *value = read(check.address)?;
    }
    Ok(BoardRegisters::from_values(values))
}

/// One line per register check: name, value, expected bits and what they mean, `ok` or
/// `DIFFERS`.
pub fn register_lines(registers: &BoardRegisters) -> Vec<(bool, String)> {
    registers
        .checks()
        .iter()
        .map(|(check, value, holds)| {
            (
                *holds,
                format!(
                    "{}: {value:#010x}, bits {:#x} expected {:#x} ({}): {}",
                    check.name,
                    value & check.mask,
                    check.expected,
                    check.meaning,
                    if *holds { "ok" } else { "DIFFERS" }
                ),
            )
        })
        .collect()
}

/// Send a hello and wait for the firmware's answer: the running firmware's version.
///
/// Bytes that are not a frame (boot noise, a half frame from before the reset) are skipped; only
/// a reply with the hello's sequence number counts.
pub fn handshake(
    link: &mut dyn ByteLink,
    timeout: Duration,
) -> Result<FirmwareVersion, FlashError> {
    const SEQ: u32 = 0x5EED;
    let request = Request {
        seq: SEQ,
        command: Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        },
    };
    let mut frame = [0u8; MAX_FRAME];
    let len = encode_request(&request, &mut frame)
        .map_err(|e| FlashError::BadReply(format!("cannot encode hello: {e:?}")))?;
    let mut decoder = FrameDecoder::new();
    // The link's clock, so a simulated link in virtual time never sleeps.
    let deadline = link.now() + timeout;
    let mut next_send = link.now();
    let mut buf = [0u8; 256];
    while link.now() < deadline {
        if link.now() >= next_send {
            // A leading delimiter ends whatever half frame the firmware may hold.
            link.send(&[0])?;
            link.send(&frame[..len])?;
            next_send = link.now() + Duration::from_millis(250);
        }
        let n = link.recv(&mut buf, Duration::from_millis(50))?;
        for message in decoder.decode::<RigMessage>(buf.get(..n).unwrap_or(&[])) {
            if let RigMessage::Reply(reply) = message
                && reply.seq == SEQ
            {
                return match reply.result {
                    Ok(Response::Hello(hello)) => Ok(hello.firmware_version),
                    other => Err(FlashError::BadReply(format!("{other:?}"))),
                };
            }
        }
    }
    Err(FlashError::NoReply(timeout))
}

/// The checks `subsurf flash` runs before programming anything, in order: the image first (a
/// wrong file is refused without listing, let alone opening, a probe), then the probe.
pub fn prepare(
    elf: &Path,
    lister: &Lister,
    serial: Option<&str>,
) -> Result<(FirmwareImage, ProbeEntry), FlashError> {
    let image = FirmwareImage::inspect(elf)?;
    let probe = select_probe(&list_probes(lister), serial)?;
    Ok((image, probe))
}

/// The version the host expects the firmware to report: the workspace version both are built from.
pub fn expected_firmware_version() -> FirmwareVersion {
    let part = |s: &str| s.parse::<u16>().unwrap_or(0);
    let mut it = env!("CARGO_PKG_VERSION").split(['.', '-', '+']);
    FirmwareVersion {
        major: it.next().map_or(0, part),
        minor: it.next().map_or(0, part),
        patch: it.next().map_or(0, part),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn probe(serial: Option<&str>) -> ProbeEntry {
        ProbeEntry {
            identifier: "STLink V2-1".into(),
            vendor_id: 0x0483,
            product_id: 0x374b,
            serial_number: serial.map(Into::into),
            accessible: true,
        }
    }

    #[test]
    fn select_probe_by_serial_or_only_one() {
        let probes = [probe(Some("A1")), probe(Some("B2"))];
        assert_eq!(select_probe(&probes, Some("B2")).unwrap(), probes[1]);
        assert!(matches!(
            select_probe(&probes, None),
            Err(FlashError::AmbiguousProbe { count: 2 })
        ));
        assert_eq!(select_probe(&probes[..1], None).unwrap(), probes[0]);
        let err = select_probe(&probes, Some("C3")).unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("serial number C3") && text.contains("serial A1"),
            "{text}"
        );
    }

    #[test]
    fn no_probe_names_what_was_looked_for() {
        let text = select_probe(&[], None).unwrap_err().to_string();
        assert!(
            text.contains("no debug probe found") && text.contains("ST-LINK"),
            "{text}"
        );
    }

    #[test]
    fn budget_reports_each_overrun() {
        let image = FirmwareImage {
            path: "x".into(),
            flash_bytes: 200 * 1024,
            ram_bytes: 10,
            entry: 0,
        };
        let over = Budget::RIG.overruns(&image);
        assert_eq!(over.len(), 1, "{over:?}");
        assert!(over[0].starts_with("flash"));
        let fits = FirmwareImage {
            flash_bytes: 1000,
            ..image
        };
        assert!(Budget::RIG.overruns(&fits).is_empty());
    }

    /// The probe reads each checked address once, in order; a correctly set-up board passes
    /// every check, a board at the factory brown-out setting (BOR off) fails that one.
    #[test]
    fn board_registers_are_read_at_their_addresses_and_checked() {
        let good = |address: u32| -> Result<u32, ()> {
            Ok(match address {
                0x4002_3C14 => 0x0FFF_AAE1,
                0x4002_3C00 => 0x0000_0705,
                0xE004_2008 => 0x0000_0005,
                0xE004_200C => 0,
                0x4000_0004 => 0x0000_0020,
                0x4000_0808 => 0x0000_0017,
                _ => return Err(()),
            })
        };
        let regs = read_board_registers(good).unwrap();
        let lines = register_lines(&regs);
        assert_eq!(lines.len(), 6);
        assert!(lines.iter().all(|(ok, _)| *ok), "{lines:?}");
        let factory = read_board_registers(|a| {
            good(a).map(|v| if a == 0x4002_3C14 { v | 0b1100 } else { v })
        })
        .unwrap();
        let lines = register_lines(&factory);
        assert!(!lines[0].0 && lines[0].1.contains("BOR_LEV") && lines[0].1.ends_with("DIFFERS"));
        assert!(lines[1..].iter().all(|(ok, _)| *ok));
        // Caches off (embassy's clock set-up alone): the accelerator check fails.
        let slow =
            read_board_registers(|a| good(a).map(|v| if a == 0x4002_3C00 { 0x5 } else { v }))
                .unwrap();
        assert!(!register_lines(&slow)[1].0);
    }

    #[test]
    fn expected_version_is_the_workspace_version() {
        let v = expected_firmware_version();
        assert_eq!(
            format!("{}.{}.{}", v.major, v.minor, v.patch),
            env!("CARGO_PKG_VERSION")
        );
    }
}
