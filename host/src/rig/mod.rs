//! Talking to the rig: a sans-IO protocol client ([`ClientCore`]) and a blocking driver over any
//! [`crate::link::ByteLink`] ([`RigClient`]).
//!
//! The client never knows whether the other end is the board, the simulated rig on a
//! pseudo-terminal, or the simulated rig in memory: that is the point of the protocol.

mod client;
mod core;
pub mod manual;
pub mod selftest;

pub use client::RigClient;
pub use core::{ClientConfig, ClientCore, ClientStats, Completion, Outcome};

use std::path::Path;

use subsurf_protocol::{PROTOCOL_VERSION, ProfileError, RigError, RigProfile};

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
    /// The rig reset since the handshake (its boot nonce changed, or it refused a request with
    /// `NoSession`): the client has handshaken again, but homing, the loaded program and the
    /// command that got this error are gone. Home again and redo the command.
    #[error(
        "the rig rebooted (boot nonce {old:#010x} -> {new:#010x}) while {command} was sent; \
         the session was re-opened: home again and repeat"
    )]
    Rebooted {
        /// The command that found the rig rebooted.
        command: String,
        /// The previous boot's nonce.
        old: u32,
        /// The new boot's nonce.
        new: u32,
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

/// Why a rig profile file could not be used.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ProfileFileError {
    /// The file could not be read or written.
    #[error("rig profile {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        source: std::io::Error,
    },
    /// Not a rig profile (JSON syntax, a missing or misspelt field).
    #[error("rig profile {path} is not a valid profile: {source}")]
    Parse {
        /// The file.
        path: String,
        /// What serde_json said (with line and column).
        source: serde_json::Error,
    },
    /// A field is out of range.
    #[error("rig profile {path}: {error:?} is out of range (see docs/protocol.md, RigProfile)")]
    Invalid {
        /// The file.
        path: String,
        /// Which group of fields.
        error: ProfileError,
    },
}

/// Read and validate a rig profile file (JSON; `subsurf rig profile default` writes one for the
/// documented wiring to start from). Unknown fields are refused, so a misspelt one is not
/// silently ignored.
pub fn load_profile(path: &Path) -> Result<RigProfile, ProfileFileError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| ProfileFileError::Io {
        path: name.clone(),
        source,
    })?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|source| ProfileFileError::Parse {
            path: name.clone(),
            source,
        })?;
    // Round-trip through the typed profile and back: any key the type does not have differs.
    let profile: RigProfile =
        serde_json::from_value(value.clone()).map_err(|source| ProfileFileError::Parse {
            path: name.clone(),
            source,
        })?;
    if serde_json::to_value(profile).ok().as_ref() != Some(&value) {
        let unknown = serde::de::Error::custom(
            "unknown or duplicate fields (compare with `subsurf rig profile default`)",
        );
        return Err(ProfileFileError::Parse {
            path: name,
            source: unknown,
        });
    }
    profile
        .validate()
        .map_err(|error| ProfileFileError::Invalid { path: name, error })?;
    Ok(profile)
}

/// A profile as the pretty JSON [`load_profile`] reads.
pub fn profile_json(profile: &RigProfile) -> String {
    serde_json::to_string_pretty(profile).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profile_files_round_trip_and_bad_ones_are_clear_errors() {
        let d = tempfile::tempdir().expect("tempdir");
        let p = d.path().join("rig.json");
        std::fs::write(&p, profile_json(&RigProfile::DEFAULT)).expect("write");
        assert_eq!(load_profile(&p).expect("loads"), RigProfile::DEFAULT);
        let text =
            profile_json(&RigProfile::DEFAULT).replace("\"microsteps\": 16", "\"microsteps\": 0");
        std::fs::write(&p, text).expect("write");
        let e = load_profile(&p).expect_err("invalid").to_string();
        assert!(e.contains("Gearing"), "{e}");
        let text = profile_json(&RigProfile::DEFAULT).replace("\"microsteps\"", "\"micro_steps\"");
        std::fs::write(&p, text).expect("write");
        let e = load_profile(&p).expect_err("misspelt").to_string();
        assert!(e.contains("microsteps") || e.contains("unknown"), "{e}");
        let e = load_profile(&d.path().join("none.json"))
            .expect_err("missing")
            .to_string();
        assert!(e.contains("none.json"), "{e}");
    }
}
