//! The subsurf host library: everything the `subsurf` binary does, as typed, testable pieces.
//!
//! Modules follow the pipeline of Fuchs et al. 2005: the rig is driven (`link`, `rig`, `sim`,
//! `scan`), images become samples (`dataset`, `geometry`, `spot`, `pipeline`), samples
//! become a model (`model`, `fit`), and the model is rendered and judged (`render`, `plot`).
#![warn(missing_docs)]

pub mod align;
pub mod baseline;
pub mod bench;
pub mod calib;
pub mod crossval;
pub mod curves;
pub mod dataset;
pub mod demo;
pub mod evaluate;
pub mod export;
pub mod fit_scan;
pub mod flash;
pub mod geometry;
pub mod interpolate;
pub mod lattice;
pub mod link;
pub mod lod;
pub mod modelfile;
pub mod pipeline;
pub mod plot;
pub mod progress;
pub mod render;
pub mod report;
pub mod rig;
pub mod samples;
pub mod scan;
pub mod sim;
pub mod simulate;
pub mod spot;
pub mod store;
pub mod util;
pub mod validate;
pub mod volume;

/// The model and its fitting live in the `subsurf-model` crate (no files, no rig); re-exported
/// here so `subsurf::model` and `subsurf::fit` name them as before.
pub use subsurf_model::{fit, model, order};
