//! The object as a scattering volume: a medium of extinction σ_t and single-scattering albedo α
//! per colour channel inside the mesh, with a Henyey-Greenstein phase function, behind an
//! index-matched boundary.
//!
//! Where the empirical model (Eq. 1–9) is a fall-off in the surface distance |x_i − x_o| fitted
//! per vertex, a volume is the physics the frames were made by: light that bends round a
//! curved part, passes through a thin one or is caught in a concavity follows from the medium
//! and the mesh, with nothing to fit per vertex. Its parameters are the medium's, in the
//! dataset's units (mm, 1/mm), so any path tracer renders it as it is.
//!
//! - [`trace`]: the forward model, photons from the laser's ray with next-event estimation to
//!   the frame's pinhole camera, and likelihood-ratio records that give the images of every
//!   nearby medium from one trace.
//! - [`fit`]: a homogeneous medium (six numbers) fitted to a scan's frames by ring sums around
//!   x_i, and its predicted frames.
//! - [`dielectric`]: a rough dielectric boundary instead of the index-matched one (GGX
//!   microfacets, Fresnel, refraction), with the tracer's photons through it.
//! - [`model`]: the volume model and its file (JSON, docs/model-format.md), and its predicted
//!   frames ([`predict_model`]).

pub mod dielectric;
pub mod fit;
pub mod gridfit;
pub mod local;
pub mod medium;
pub mod model;
pub mod trace;

pub use model::{
    BoundaryModel, FitInfo, MediumGrid, TracedFrames, VolumeError, VolumeMesh, VolumeModel,
    predict_model,
};
