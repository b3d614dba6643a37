//! The end-to-end tests: one integration-test binary (`e2e`, a test target of the `subsurf`
//! package), one module per area, ripgrep style.
//!
//! Why one binary in the host package: every integration-test file used to be its own ~200 MB
//! link; one binary links once. It belongs to the `subsurf` package because only that package's
//! integration tests get `CARGO_BIN_EXE_subsurf`, the path of the binary they run. Run one area
//! with `cargo test -p subsurf --test e2e acquire_kill::`.
//!
//! Shared pieces: `fixture` (the scan set-ups built once and shared), `harness` (the scripted rig
//! session over lossy links), `render_common` (the render tests' helpers).

mod fixture;
mod harness;
mod render_common;

mod architecture;

mod acquire_adaptive;
mod acquire_faults;
mod acquire_kill;
mod acquire_link;
mod acquire_sim;
mod align;
mod crossval;
mod curved;
mod demo;
mod export;
mod fit_aniso;
mod fit_curve;
mod fit_pictures;
mod fit_presets;
mod fit_scale;
mod flash;
mod guide;
mod objects;
mod outside;
mod render;
mod render_plots;
mod render_slab;
mod render_tradeoff;
mod rig_cli;
mod rig_link;
mod scan;
mod scan_fit;
mod store;
mod texture;
mod volume;
mod volume_dielectric;
