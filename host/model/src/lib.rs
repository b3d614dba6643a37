//! The empirical model of Fuchs, Goesele, Chen and Seidel (2005) and its fitting.
//!
//! Contract: pure functions of their inputs. This crate never touches files, clocks, threads, a
//! serial port or a probe, so it builds and tests alone and researchers can use it without the
//! rig. `model` is the model as validated data with its evaluation (Eq. 1, 3, 5, 6, 7, 8, 9);
//! `fit` fits it (and the Jensen 2001 dipole) to samples.
#![warn(missing_docs)]

pub mod fit;
pub mod model;
pub mod order;
