//! Scanning: plan what to capture, drive the rig and a camera, and write a scan dataset
//! (`docs/scan-format.md`) that survives crashes and resumes (through the one writer,
//! `crate::dataset::DatasetWriter`).
//!
//! Dependencies point one way: `scan` uses `calib`, the rig client and the dataset writer; no
//! other module calls into `scan` except the commands and the demo.

pub mod acquire;
pub mod adaptive;
pub mod camera;
pub mod dark;
pub mod driver;
pub mod plan;
pub mod replay;
pub mod rigsource;
pub mod setup;
pub mod simcam;
