//! Byte links between the host and a rig: a real serial port, or an in-memory duplex with faults.
//!
//! Everything above this module (the rig client, the simulated rig runner, the end-to-end tests)
//! speaks to a [`ByteLink`] and never learns which kind it got, so the same code paths run against
//! the board on `/dev/ttyACM0`, the simulated rig on a pseudo-terminal and a lossy in-memory wire.
//!
//! Faults (dropped, corrupted and duplicated bytes, latency) are injected by the sans-IO
//! [`FaultInjector`]; [`VirtualWire`] uses it with virtual time for deterministic tests and
//! [`MemoryLink`] with the wall clock for threaded ones.

mod fault;
mod faulty;
mod memory;
mod serial;

use std::time::{Duration, Instant};

pub use fault::{FaultConfig, FaultInjector, FaultStats, VirtualWire};
pub use faulty::FaultyLink;
pub use memory::MemoryLink;
pub use serial::{SerialLink, list_ports};

/// Why a link operation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LinkError {
    /// The serial port could not be opened (missing device, permissions, busy).
    #[error("cannot open serial port {path} at {baud} baud")]
    Open {
        /// The path that was tried.
        path: String,
        /// The requested baud rate.
        baud: u32,
        /// What the operating system said.
        #[source]
        source: serialport::Error,
    },
    /// A pseudo-terminal pair could not be created.
    #[error("cannot create a pseudo-terminal pair")]
    Pty(#[source] serialport::Error),
    /// Reading or writing failed.
    #[error("I/O error on {link}")]
    Io {
        /// Which link ([`ByteLink::describe`]).
        link: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The other end went away (in-memory peer dropped, pseudo-terminal closed).
    #[error("{link} was closed by the other end")]
    Closed {
        /// Which link ([`ByteLink::describe`]).
        link: String,
    },
    /// Listing serial ports failed.
    #[error("cannot list serial ports")]
    List(#[source] serialport::Error),
}

/// A bidirectional byte stream with a read timeout: what a serial port offers.
///
/// Implementations are blocking. `recv` returning `Ok(0)` means "nothing arrived in time", never
/// end of stream (that is [`LinkError::Closed`]).
pub trait ByteLink: Send {
    /// Write every byte of `bytes` (blocks until the link has accepted them).
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError>;
    /// Wait at most `timeout` for bytes and copy what is available into `buf`.
    ///
    /// Returns the number of bytes read; `Ok(0)` after the timeout.
    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError>;
    /// A human-readable name for error messages (a device path, `memory`).
    fn describe(&self) -> String;
    /// The link's clock. Real links use the wall clock; a simulated link with virtual time
    /// (`crate::sim::SimLink`) returns its virtual clock, and its `recv` advances it instead of
    /// sleeping, so everything timed against the link (retransmissions, heartbeats, waits) runs
    /// in virtual time.
    fn now(&self) -> Instant {
        Instant::now()
    }
}

impl<L: ByteLink + ?Sized> ByteLink for Box<L> {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        (**self).send(bytes)
    }
    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        (**self).recv(buf, timeout)
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
    fn now(&self) -> Instant {
        (**self).now()
    }
}
