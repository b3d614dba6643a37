//! The rig's firmware core: hardware-independent, sans-IO, `no_std`, no heap.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]
