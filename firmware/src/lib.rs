//! The rig's firmware core: hardware-independent, sans-IO, `no_std`, no heap.
//!
//! Contract: deterministic; no clock, no I/O, no embassy. Time comes in as µs ([`rig::Micros`]),
//! bytes come in through [`Rig::handle_bytes`] and go out through [`Rig::poll_transmit`], and the
//! hardware is reached only through the traits in [`hal`]. The board binary and the host's
//! simulated rig ([`sim`]) only pump it.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing
    )
)]

#[cfg(test)]
extern crate std;

pub mod hal;
pub mod planner;
pub mod profile;
pub mod rig;
pub mod sim;
pub mod stepcompress;

pub use hal::Hardware;
pub use rig::{FIRMWARE_VERSION, Micros, Rig, galvo_settle_us};
