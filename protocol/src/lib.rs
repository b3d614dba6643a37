//! Every message between the subsurf host and the rig.
//!
//! Contract: `no_std`, no allocation, no I/O, no panics reachable from input.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]
