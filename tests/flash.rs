//! `subsurf flash` / `subsurf probes`: the ELF checks and the probe paths, without hardware.
//!
//! Firmware images are crafted here byte by byte (a minimal ELF32 with section headers), so every
//! refusal is tested against a file that differs from an accepted one in exactly one respect.

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use probe_rs::probe::list::{Lister, ProbeListItem, ProbeLister};
use probe_rs::probe::{DebugProbeError, DebugProbeSelector, Probe, ProbeCreationError};
use subsurf::flash::{self, Budget, FirmwareImage, FlashError};

const EM_ARM: u16 = 40;
const EM_386: u16 = 3;
const SHT_PROGBITS: u32 = 1;
const SHT_STRTAB: u32 = 3;
const SHT_NOBITS: u32 = 8;
const SHF_WRITE: u32 = 1;
const SHF_ALLOC: u32 = 2;
const SHF_EXEC: u32 = 4;

struct Section {
    name: &'static str,
    kind: u32,
    flags: u32,
    addr: u32,
    size: u32,
}

struct ElfSpec {
    machine: u16,
    big_endian: bool,
    sections: Vec<Section>,
}

impl ElfSpec {
    /// A plausible firmware: vector table, code, initialised and zeroed RAM.
    fn firmware() -> Self {
        Self {
            machine: EM_ARM,
            big_endian: false,
            sections: vec![
                Section {
                    name: ".vector_table",
                    kind: SHT_PROGBITS,
                    flags: SHF_ALLOC,
                    addr: 0x0800_0000,
                    size: 0x1c4,
                },
                Section {
                    name: ".text",
                    kind: SHT_PROGBITS,
                    flags: SHF_ALLOC | SHF_EXEC,
                    addr: 0x0800_01c4,
                    size: 0x1000,
                },
                Section {
                    name: ".data",
                    kind: SHT_PROGBITS,
                    flags: SHF_ALLOC | SHF_WRITE,
                    addr: 0x2000_0000,
                    size: 0x20,
                },
                Section {
                    name: ".bss",
                    kind: SHT_NOBITS,
                    flags: SHF_ALLOC | SHF_WRITE,
                    addr: 0x2000_0020,
                    size: 0x400,
                },
            ],
        }
    }

    fn without(mut self, name: &str) -> Self {
        self.sections.retain(|s| s.name != name);
        self
    }

    fn moved(mut self, name: &str, addr: u32) -> Self {
        for s in &mut self.sections {
            if s.name == name {
                s.addr = addr;
            }
        }
        self
    }

    fn bytes(&self) -> Vec<u8> {
        let be = self.big_endian;
        let u16b = |v: u16| if be { v.to_be_bytes() } else { v.to_le_bytes() };
        let u32b = |v: u32| if be { v.to_be_bytes() } else { v.to_le_bytes() };
        // Section name table: "\0" + names + ".shstrtab".
        let mut strtab = vec![0u8];
        let mut name_offsets = Vec::new();
        for s in &self.sections {
            name_offsets.push(strtab.len() as u32);
            strtab.extend_from_slice(s.name.as_bytes());
            strtab.push(0);
        }
        let shstrtab_name = strtab.len() as u32;
        strtab.extend_from_slice(b".shstrtab\0");
        // Layout: header, section contents, string table, section headers.
        let mut body = Vec::new();
        let mut offsets = Vec::new();
        for s in &self.sections {
            offsets.push(52 + body.len() as u32);
            if s.kind != SHT_NOBITS {
                body.extend(std::iter::repeat_n(0xA5u8, s.size as usize));
            }
        }
        let strtab_offset = 52 + body.len() as u32;
        body.extend_from_slice(&strtab);
        while body.len() % 4 != 0 {
            body.push(0);
        }
        let shoff = 52 + body.len() as u32;
        let shnum = self.sections.len() as u16 + 2;

        let mut out = Vec::new();
        out.extend_from_slice(&[0x7f, b'E', b'L', b'F', 1, if be { 2 } else { 1 }, 1, 0]);
        out.extend_from_slice(&[0; 8]);
        out.extend_from_slice(&u16b(2)); // ET_EXEC
        out.extend_from_slice(&u16b(self.machine));
        out.extend_from_slice(&u32b(1));
        out.extend_from_slice(&u32b(0x0800_01c5)); // entry (thumb)
        out.extend_from_slice(&u32b(0)); // no program headers
        out.extend_from_slice(&u32b(shoff));
        out.extend_from_slice(&u32b(0x0500_0400)); // EABI5, hard float
        out.extend_from_slice(&u16b(52));
        out.extend_from_slice(&u16b(32));
        out.extend_from_slice(&u16b(0));
        out.extend_from_slice(&u16b(40));
        out.extend_from_slice(&u16b(shnum));
        out.extend_from_slice(&u16b(shnum - 1));
        assert_eq!(out.len(), 52);
        out.extend_from_slice(&body);
        let mut header = |name: u32, kind: u32, flags: u32, addr: u32, off: u32, size: u32| {
            for v in [name, kind, flags, addr, off, size, 0, 0, 4, 0] {
                out.extend_from_slice(&u32b(v));
            }
        };
        header(0, 0, 0, 0, 0, 0);
        for ((s, name), off) in self.sections.iter().zip(&name_offsets).zip(&offsets) {
            header(*name, s.kind, s.flags, s.addr, *off, s.size);
        }
        header(
            shstrtab_name,
            SHT_STRTAB,
            0,
            0,
            strtab_offset,
            strtab.len() as u32,
        );
        out
    }
}

fn parse(spec: &ElfSpec) -> Result<FirmwareImage, FlashError> {
    FirmwareImage::parse(Path::new("crafted.elf"), &spec.bytes())
}

#[test]
fn crafted_firmware_is_accepted_and_measured() {
    let image = parse(&ElfSpec::firmware()).expect("a valid firmware image");
    // Flash: vector table + text + initial values of .data. RAM: .data + .bss.
    assert_eq!(image.flash_bytes, 0x1c4 + 0x1000 + 0x20);
    assert_eq!(image.ram_bytes, 0x20 + 0x400);
    assert_eq!(image.entry, 0x0800_01c5);
    assert!(Budget::RIG.overruns(&image).is_empty());
}

#[test]
fn host_executable_is_refused_as_wrong_architecture() {
    let exe = std::env::current_exe().expect("test binary path");
    let err = FirmwareImage::inspect(&exe).unwrap_err();
    assert!(matches!(err, FlashError::WrongArchitecture { .. }), "{err}");
    assert!(err.to_string().contains("cargo fw"), "{err}");
}

#[test]
fn non_arm_and_big_endian_elves_are_refused() {
    let x86 = ElfSpec {
        machine: EM_386,
        ..ElfSpec::firmware()
    };
    assert!(matches!(
        parse(&x86),
        Err(FlashError::WrongArchitecture { .. })
    ));
    let big = ElfSpec {
        big_endian: true,
        ..ElfSpec::firmware()
    };
    let err = parse(&big).unwrap_err();
    assert!(matches!(err, FlashError::WrongArchitecture { .. }), "{err}");
    assert!(err.to_string().contains("big endian"), "{err}");
}

#[test]
fn missing_or_misplaced_vector_table_is_refused() {
    let none = ElfSpec::firmware().without(".vector_table");
    assert!(matches!(
        parse(&none),
        Err(FlashError::NoVectorTable { .. })
    ));
    let elsewhere = ElfSpec::firmware().moved(".vector_table", 0x0801_0000);
    assert!(matches!(
        parse(&elsewhere),
        Err(FlashError::NoVectorTable { .. })
    ));
}

#[test]
fn sections_outside_flash_and_ram_are_refused() {
    // 0x1000_0000 is the F4's CCM-less hole: nothing to load there on an STM32F446.
    let spec = ElfSpec::firmware().moved(".text", 0x1000_0000);
    match parse(&spec) {
        Err(FlashError::OutsideMemory {
            section, address, ..
        }) => {
            assert_eq!(section, ".text");
            assert_eq!(address, 0x1000_0000);
        }
        other => panic!("expected OutsideMemory, got {other:?}"),
    }
}

/// Code in the profile's flash sectors (0x0800_4000..0x0800_C000) would be
/// overwritten by the next profile save, and flashing it would destroy the stored profile.
#[test]
fn sections_in_the_profile_sectors_are_refused() {
    // Ending exactly where sector 1 starts is fine.
    assert!(parse(&ElfSpec::firmware().moved(".text", 0x0800_3000)).is_ok());
    for addr in [0x0800_3800, 0x0800_4000, 0x0800_bff0] {
        match parse(&ElfSpec::firmware().moved(".text", addr)) {
            Err(FlashError::OverlapsProfile {
                section, address, ..
            }) => {
                assert_eq!(section, ".text");
                assert_eq!(address, u64::from(addr));
            }
            other => panic!("{addr:#x}: expected OverlapsProfile, got {other:?}"),
        }
    }
    assert!(parse(&ElfSpec::firmware().moved(".text", 0x0800_C000)).is_ok());
}

#[test]
fn garbage_and_missing_files_are_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let text = dir.path().join("notes.txt");
    std::fs::write(&text, "not an elf at all").expect("write");
    assert!(matches!(
        FirmwareImage::inspect(&text),
        Err(FlashError::NotElf { .. })
    ));
    // A truncated firmware: the header promises section headers that are not there.
    let mut truncated = ElfSpec::firmware().bytes();
    truncated.truncate(200);
    assert!(FirmwareImage::parse(Path::new("t.elf"), &truncated).is_err());
    assert!(matches!(
        FirmwareImage::inspect(&dir.path().join("missing.elf")),
        Err(FlashError::Read { .. })
    ));
}

/// A probe lister that sees no probes and counts how often it is asked.
#[derive(Debug, Default)]
struct CountingLister {
    calls: Arc<AtomicUsize>,
}

impl ProbeLister for CountingLister {
    fn open(&self, _selector: &DebugProbeSelector) -> Result<Probe, DebugProbeError> {
        self.calls.fetch_add(1, Ordering::SeqCst);
        Err(DebugProbeError::ProbeCouldNotBeCreated(
            ProbeCreationError::NotFound,
        ))
    }

    fn list_with_access(&self, _selector: Option<&DebugProbeSelector>) -> Vec<ProbeListItem> {
        self.calls.fetch_add(1, Ordering::SeqCst);
        Vec::new()
    }
}

#[test]
fn wrong_elf_is_refused_before_any_probe_is_touched() {
    let calls = Arc::new(AtomicUsize::new(0));
    let lister = Lister::with_lister(Box::new(CountingLister {
        calls: calls.clone(),
    }));
    let exe = std::env::current_exe().expect("test binary path");
    let err = flash::prepare(&exe, &lister, None).unwrap_err();
    assert!(matches!(err, FlashError::WrongArchitecture { .. }), "{err}");
    assert_eq!(
        calls.load(Ordering::SeqCst),
        0,
        "the probe lister was consulted"
    );
}

#[test]
fn no_probe_is_a_clear_error_after_the_image_passed() {
    let calls = Arc::new(AtomicUsize::new(0));
    let lister = Lister::with_lister(Box::new(CountingLister {
        calls: calls.clone(),
    }));
    let dir = tempfile::tempdir().expect("temp dir");
    let elf = dir.path().join("fw.elf");
    std::fs::write(&elf, ElfSpec::firmware().bytes()).expect("write");
    let err = flash::prepare(&elf, &lister, None).unwrap_err();
    assert!(matches!(err, FlashError::NoProbe { .. }), "{err}");
    assert!(err.to_string().contains("ST-LINK"), "{err}");
    assert_eq!(calls.load(Ordering::SeqCst), 1);
    assert!(flash::list_probes(&lister).is_empty());
}

#[test]
fn flash_command_without_a_matching_probe_exits_nonzero() {
    let dir = tempfile::tempdir().expect("temp dir");
    let elf = dir.path().join("fw.elf");
    std::fs::write(&elf, ElfSpec::firmware().bytes()).expect("write");
    // A serial number no real probe has, so a developer's attached board is never touched.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(["flash", "--probe", "no-such-probe-serial-0000", "--elf"])
        .arg(&elf)
        .output()
        .expect("run subsurf");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no debug probe found") && stderr.contains("no-such-probe-serial-0000"),
        "{stderr}"
    );
}

#[test]
fn flash_check_reports_size_and_refuses_host_binaries() {
    let dir = tempfile::tempdir().expect("temp dir");
    let elf = dir.path().join("fw.elf");
    std::fs::write(&elf, ElfSpec::firmware().bytes()).expect("write");
    let ok = std::process::Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(["flash", "--check", "--elf"])
        .arg(&elf)
        .output()
        .expect("run subsurf");
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let stdout = String::from_utf8_lossy(&ok.stdout);
    assert!(stdout.contains("flash 4580 bytes"), "{stdout}");
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .args(["flash", "--check", "--elf", env!("CARGO_BIN_EXE_subsurf")])
        .output()
        .expect("run subsurf");
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("not for the rig"));
}

#[test]
fn probes_command_runs_without_hardware() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_subsurf"))
        .arg("probes")
        .output()
        .expect("run subsurf");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The simulated rig (the firmware core on simulated hardware) behind a link with a virtual
/// clock: what `subsurf flash` talks to after the reset, minus the USB.
struct SimBoard {
    rig: subsurf_firmware::sim::SimRig,
    start: std::time::Instant,
    now_us: u64,
    /// Bytes the board "boots" with before it answers (noise on the line).
    noise: Vec<u8>,
    /// A board that never answers (wrong firmware, wrong port).
    mute: bool,
}

impl SimBoard {
    fn new() -> Self {
        Self {
            rig: subsurf_firmware::sim::SimRig::default(),
            start: std::time::Instant::now(),
            now_us: 0,
            noise: vec![0x55, 0xaa, 0x00, 0x17],
            mute: false,
        }
    }
}

impl subsurf::link::ByteLink for SimBoard {
    fn send(&mut self, bytes: &[u8]) -> Result<(), subsurf::link::LinkError> {
        if !self.mute {
            self.rig.feed(self.now_us, bytes);
        }
        Ok(())
    }

    fn recv(
        &mut self,
        buf: &mut [u8],
        timeout: std::time::Duration,
    ) -> Result<usize, subsurf::link::LinkError> {
        self.now_us += u64::try_from(timeout.as_micros()).unwrap_or(u64::MAX);
        self.rig.advance_to(self.now_us);
        let mut n = 0;
        for b in std::mem::take(&mut self.noise) {
            buf[n] = b;
            n += 1;
        }
        n += self.rig.drain(&mut buf[n..]);
        Ok(n)
    }

    fn describe(&self) -> String {
        "simulated board".into()
    }

    fn now(&self) -> std::time::Instant {
        self.start + std::time::Duration::from_micros(self.now_us)
    }
}

#[test]
fn handshake_reads_the_firmware_version_through_line_noise() {
    let mut board = SimBoard::new();
    let version = flash::handshake(&mut board, std::time::Duration::from_secs(3)).expect("hello");
    assert_eq!(version, subsurf_firmware::FIRMWARE_VERSION);
    assert_eq!(version, flash::expected_firmware_version());
}

#[test]
fn handshake_with_a_silent_board_times_out_in_virtual_time() {
    let mut board = SimBoard::new();
    board.mute = true;
    let wall = std::time::Instant::now();
    let err = flash::handshake(&mut board, std::time::Duration::from_secs(3)).unwrap_err();
    assert!(matches!(err, FlashError::NoReply(_)), "{err}");
    assert!(
        wall.elapsed() < std::time::Duration::from_secs(2),
        "slept on the wall clock"
    );
}
