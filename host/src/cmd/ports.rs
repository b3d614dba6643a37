//! `subsurf ports`: the serial ports this machine reports.

use anyhow::Context;
use serialport::SerialPortType;

/// List serial ports (USB adapters, on-board UARTs) to pass to `subsurf rig --port`.
#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<()> {
    let ports = subsurf::link::list_ports().context("listing serial ports")?;
    if ports.is_empty() {
        println!("no serial ports found");
    }
    for port in &ports {
        let kind = match &port.port_type {
            SerialPortType::UsbPort(usb) => {
                let mut s = format!("usb {:04x}:{:04x}", usb.vid, usb.pid);
                for part in [&usb.manufacturer, &usb.product, &usb.serial_number]
                    .into_iter()
                    .flatten()
                {
                    s.push(' ');
                    s.push_str(part);
                }
                s
            }
            SerialPortType::PciPort => "pci".into(),
            SerialPortType::BluetoothPort => "bluetooth".into(),
            SerialPortType::Unknown => "unknown".into(),
        };
        println!("{}\t{kind}", port.port_name);
    }
    // Without libudev (serialport's default features are off) Linux enumeration only sees devices
    // with a driver in /sys/class/tty: say so, so an empty list is not mistaken for "no rig".
    if cfg!(target_os = "linux") {
        eprintln!(
            "note: listed from /sys/class/tty without libudev; pseudo-terminals (e.g. from \
             `subsurf rig serve-sim`) and some adapters are not listed but can still be opened \
             with --port PATH"
        );
    }
    Ok(())
}
