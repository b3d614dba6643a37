//! Talking to the rig: a sans-IO protocol client ([`ClientCore`]) and a blocking driver over any
//! [`crate::link::ByteLink`] ([`RigClient`]).
//!
//! The client never knows whether the other end is the board, the simulated rig on a
//! pseudo-terminal, or the simulated rig in memory: that is the point of the protocol.

mod client;
mod core;

pub use client::RigClient;
pub use core::{ClientConfig, ClientCore, ClientStats, Completion, Outcome};

use subsurf_protocol::{PROTOCOL_VERSION, RigError};

use crate::link::LinkError;

/// Why a rig call failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RigClientError {
    /// The byte link failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// No reply at all: wrong port, rig off, wrong baud rate, or the link is too lossy.
    #[error("no reply from the rig on {link} to {command} after {attempts} attempts in {waited:?}")]
    NoReply {
        /// The link ([`crate::link::ByteLink::describe`]).
        link: String,
        /// The command that went unanswered.
        command: String,
        /// How often it was sent.
        attempts: u32,
        /// How long the client waited.
        waited: std::time::Duration,
    },
    /// The rig speaks another protocol version: update the firmware or the host.
    #[error(
        "protocol version mismatch: this host speaks version {host}, the rig speaks version {rig}; \
         flash matching firmware or use a matching subsurf"
    )]
    VersionMismatch {
        /// Our [`PROTOCOL_VERSION`].
        host: u16,
        /// The rig's.
        rig: u16,
    },
    /// The rig refused the command (nothing was executed).
    #[error("the rig refused {command}: {error:?}")]
    Rejected {
        /// The refused command.
        command: String,
        /// The rig's reason.
        error: RigError,
    },
    /// The rig answered with a response that does not belong to the command.
    #[error("unexpected answer to {command}: {response}")]
    UnexpectedResponse {
        /// The command.
        command: String,
        /// What came back.
        response: String,
    },
    /// A wait for an event (move done, capture) ran out.
    #[error("timed out after {waited:?} waiting for {what}")]
    EventTimeout {
        /// What was awaited.
        what: String,
        /// How long.
        waited: std::time::Duration,
    },
    /// The rig halted or faulted while an operation was awaited.
    #[error("the rig halted while waiting for {what}: {reason}")]
    Halted {
        /// What was awaited.
        what: String,
        /// The rig's halt reason or fault.
        reason: String,
    },
}

/// The protocol version this host speaks.
pub const HOST_PROTOCOL_VERSION: u16 = PROTOCOL_VERSION;
