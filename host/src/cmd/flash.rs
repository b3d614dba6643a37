//! `subsurf flash`: check the firmware ELF, flash it through a debug probe, reset, and confirm the
//! firmware's version with a handshake over the serial link.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use probe_rs::probe::list::Lister;
use subsurf::flash::{self, Budget, DEFAULT_CHIP, DEFAULT_ELF, FirmwareImage};
use subsurf::link::SerialLink;

/// Flash the rig's Nucleo-F446RE with the board firmware.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Firmware ELF; without it, `cargo fw` builds target/thumbv7em-none-eabihf/firmware/subsurf-board.
    #[arg(long)]
    elf: Option<PathBuf>,
    /// probe-rs chip name.
    #[arg(long, default_value = DEFAULT_CHIP)]
    chip: String,
    /// Serial number of the debug probe to use (see `subsurf probes`); needed with several probes.
    #[arg(long)]
    probe: Option<String>,
    /// Serial port of the rig link for the handshake (default: the ST-LINK's virtual COM port).
    #[arg(long)]
    port: Option<String>,
    /// Link baud rate (the firmware's `SUBSURF_BAUD`, 921600 by default).
    #[arg(long, default_value_t = 921_600)]
    baud: u32,
    /// Only check the ELF and print its flash/RAM use against the budget; touch no probe.
    #[arg(long)]
    check: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let elf = match args.elf {
        Some(path) => path,
        None => {
            let status =
                std::process::Command::new(std::env::var("CARGO").unwrap_or("cargo".into()))
                    .arg("fw")
                    .status()
                    .context("running `cargo fw` to build the firmware (or pass --elf PATH)")?;
            if !status.success() {
                bail!("`cargo fw` failed ({status}); fix the build or pass --elf PATH");
            }
            PathBuf::from(DEFAULT_ELF)
        }
    };
    if args.check {
        let image = FirmwareImage::inspect(&elf)?;
        println!(
            "{}: flash {} bytes ({:.1} KiB of {} KiB budget), static RAM {} bytes ({:.1} KiB of {} KiB budget)",
            elf.display(),
            image.flash_bytes,
            image.flash_bytes as f64 / 1024.0,
            Budget::RIG.flash / 1024,
            image.ram_bytes,
            image.ram_bytes as f64 / 1024.0,
            Budget::RIG.ram / 1024,
        );
        let over = Budget::RIG.overruns(&image);
        if !over.is_empty() {
            bail!("firmware over budget: {}", over.join("; "));
        }
        return Ok(());
    }

    let lister = Lister::new();
    let (image, probe) = flash::prepare(&elf, &lister, args.probe.as_deref())?;
    eprintln!(
        "flashing {} ({} bytes) to {} via {probe}",
        elf.display(),
        image.flash_bytes,
        args.chip
    );
    flash::flash_image(&lister, &probe, &args.chip, &image, |step| {
        eprintln!("  {step}")
    })?;

    let port = match args.port {
        Some(port) => port,
        None => find_link_port(probe.serial_number.as_deref())?,
    };
    // Give the firmware time to boot and the USB virtual COM port time to settle after reset.
    std::thread::sleep(Duration::from_millis(300));
    let mut link = SerialLink::open(&port, args.baud)?;
    let version = flash::handshake(&mut link, Duration::from_secs(3)).with_context(|| {
        format!(
            "confirming the firmware runs, on {port} at {} baud",
            args.baud
        )
    })?;
    let expected = flash::expected_firmware_version();
    if version != expected {
        bail!(
            "the board answers with firmware {}.{}.{}, expected {}.{}.{}: flashing did not take?",
            version.major,
            version.minor,
            version.patch,
            expected.major,
            expected.minor,
            expected.patch
        );
    }
    println!(
        "firmware {}.{}.{} running on {port}",
        version.major, version.minor, version.patch
    );
    Ok(())
}

/// The ST-LINK's virtual COM port: a USB serial port from ST (0483) with the probe's serial number,
/// or the only ST port there is.
fn find_link_port(probe_serial: Option<&str>) -> anyhow::Result<String> {
    let ports = subsurf::link::list_ports()?;
    let st: Vec<_> = ports
        .iter()
        .filter_map(|p| match &p.port_type {
            serialport::SerialPortType::UsbPort(usb) if usb.vid == 0x0483 => {
                Some((p.port_name.clone(), usb.serial_number.clone()))
            }
            _ => None,
        })
        .collect();
    if let Some((name, _)) = st
        .iter()
        .find(|(_, serial)| probe_serial.is_some() && serial.as_deref() == probe_serial)
    {
        return Ok(name.clone());
    }
    match st.as_slice() {
        [(name, _)] => Ok(name.clone()),
        [] => bail!(
            "flashed, but found no ST-LINK virtual COM port for the handshake; pass --port PATH"
        ),
        _ => bail!("flashed, but several ST serial ports are attached; pass --port PATH"),
    }
}
