//! A real serial port (USB CDC, UART adapter, pseudo-terminal) as a [`ByteLink`].

use std::io::{ErrorKind, Read, Write};
use std::time::Duration;

use serialport::{SerialPort, SerialPortInfo, TTYPort};

use super::{ByteLink, LinkError};

/// A serial port opened by path, or one end of a pseudo-terminal pair.
#[derive(Debug)]
pub struct SerialLink {
    port: TTYPort,
    name: String,
    timeout: Duration,
}

impl SerialLink {
    /// Open `path` at `baud` (8N1, no flow control, raw).
    ///
    /// Pseudo-terminals ignore the baud rate; USB CDC devices mostly do too.
    pub fn open(path: &str, baud: u32) -> Result<Self, LinkError> {
        let port = serialport::new(path, baud)
            .timeout(Duration::from_millis(100))
            .open_native()
            .map_err(|source| LinkError::Open {
                path: path.to_owned(),
                baud,
                source,
            })?;
        Ok(Self {
            port,
            name: path.to_owned(),
            timeout: Duration::from_millis(100),
        })
    }

    /// A raw pseudo-terminal pair: `(controller, device)`.
    ///
    /// The device end has a path (`/dev/pts/N`, see [`SerialLink::path`]) that any serial client can
    /// open; whoever serves a simulated rig should keep the device end open too, so the
    /// controller end does not see end-of-file between clients.
    pub fn pty_pair() -> Result<(Self, Self), LinkError> {
        let (controller, device) = TTYPort::pair().map_err(LinkError::Pty)?;
        let path = device.name().unwrap_or_else(|| "pseudo-terminal".into());
        Ok((
            Self {
                port: controller,
                name: format!("pseudo-terminal controller of {path}"),
                timeout: Duration::from_millis(100),
            },
            Self {
                port: device,
                name: path,
                timeout: Duration::from_millis(100),
            },
        ))
    }

    /// The device path, when the port has one.
    pub fn path(&self) -> Option<String> {
        self.port.name()
    }

    fn io_error(&self, source: std::io::Error) -> LinkError {
        // A pseudo-terminal whose other side has gone reads EIO: that is a closed link.
        if source.raw_os_error() == Some(5) {
            LinkError::Closed {
                link: self.name.clone(),
            }
        } else {
            LinkError::Io {
                link: self.name.clone(),
                source,
            }
        }
    }
}

impl ByteLink for SerialLink {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let mut rest = bytes;
        while !rest.is_empty() {
            match self.port.write(rest) {
                Ok(0) => {
                    return Err(LinkError::Closed {
                        link: self.name.clone(),
                    });
                }
                Ok(n) => rest = &rest[n..],
                Err(e) if matches!(e.kind(), ErrorKind::Interrupted | ErrorKind::TimedOut) => {}
                Err(e) => return Err(self.io_error(e)),
            }
        }
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        if buf.is_empty() {
            return Ok(0);
        }
        if timeout != self.timeout {
            self.port.set_timeout(timeout).map_err(|e| LinkError::Io {
                link: self.name.clone(),
                source: e.into(),
            })?;
            self.timeout = timeout;
        }
        match self.port.read(buf) {
            Ok(0) => Err(LinkError::Closed {
                link: self.name.clone(),
            }),
            Ok(n) => Ok(n),
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::Interrupted) => Ok(0),
            Err(e) => Err(self.io_error(e)),
        }
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

/// The serial ports the operating system reports.
///
/// Built without libudev (`serialport` default features off), Linux enumeration walks
/// `/sys/class/tty` and only reports devices with a driver behind them: USB adapters and PCI
/// UARTs, not pseudo-terminals. Where `/sys/class/tty` does not exist (some containers) the list is
/// empty rather than a panic inside `serialport`.
pub fn list_ports() -> Result<Vec<SerialPortInfo>, LinkError> {
    if cfg!(target_os = "linux") && !std::path::Path::new("/sys/class/tty").is_dir() {
        return Ok(Vec::new());
    }
    serialport::available_ports().map_err(LinkError::List)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pty_pair_carries_bytes_both_ways() {
        let (mut host, mut dev) = SerialLink::pty_pair().expect("pty pair");
        assert!(dev.path().is_some_and(|p| p.starts_with("/dev/")));
        host.send(&[0, 1, 2, 255]).expect("send");
        let mut got = Vec::new();
        let mut buf = [0u8; 16];
        while got.len() < 4 {
            let n = dev.recv(&mut buf, Duration::from_secs(2)).expect("recv");
            assert!(n > 0, "timed out");
            got.extend_from_slice(&buf[..n]);
        }
        assert_eq!(got, vec![0, 1, 2, 255]);
        dev.send(b"ok").expect("send");
        let n = host.recv(&mut buf, Duration::from_secs(2)).expect("recv");
        assert_eq!(&buf[..n], b"ok");
        assert_eq!(
            host.recv(&mut buf, Duration::from_millis(5)).expect("recv"),
            0
        );
    }

    #[test]
    fn opening_a_missing_port_names_it() {
        let err = SerialLink::open("/dev/does-not-exist-subsurf", 115_200).expect_err("missing");
        assert!(
            err.to_string().contains("/dev/does-not-exist-subsurf"),
            "{err}"
        );
    }

    #[test]
    fn a_pty_path_can_be_opened_by_a_client() {
        let (mut controller, device) = SerialLink::pty_pair().expect("pty pair");
        let path = device.path().expect("path");
        let mut client = SerialLink::open(&path, 115_200).expect("open pty by path");
        client.send(b"ping").expect("send");
        let mut buf = [0u8; 8];
        let mut got = Vec::new();
        while got.len() < 4 {
            let n = controller
                .recv(&mut buf, Duration::from_secs(2))
                .expect("recv");
            assert!(n > 0);
            got.extend_from_slice(&buf[..n]);
        }
        assert_eq!(got, b"ping");
    }
}
