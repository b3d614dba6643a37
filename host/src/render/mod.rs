//! Rendering the fitted model: relighting a per-vertex empirical BSSRDF (paper §3, §5.1). The model
//! is the model file's type, [`crate::modelfile::ModelFile`] (the renderer has none of its own);
//! each source's Eq. 3 directions are in the tangent frame of its vertex normal by the file's
//! frame rule, the frame its segments were fitted in.
//!
//! The pipeline is the one of Jensen & Buhler 2002, with the paper's empirical `R_d` in place of the
//! dipole:
//!
//! 1. [`irradiance`]: the irradiance `E(x_i)` at every vertex from point, spot and directional
//!    [`Light`]s, shadowed by ray casts against the mesh ([`crate::geometry::Scene`]), with Fresnel transmission
//!    into the surface, and the area `A(x_i)` each vertex stands for.
//! 2. [`Transport`]: the radiant exitance `B(x_o) = Σ_i R_d(x_i → x_o) E(x_i) A(x_i)` with the
//!    parameters of the source vertex `x_i` (Eq. 1/3/5/9), either as the exact O(N²) sum (the
//!    reference) or hierarchically (an octree of irradiance samples, clusters used where they subtend
//!    a small solid angle, plus a distance cutoff where the fall-off's remaining energy drops below a
//!    tolerance). Outgoing radiance adds `alpha(x_o)` (Eq. 2) and Fresnel transmission out.
//! 3. [`rasterise`]: a z-buffered image of the per-vertex radiance through the one camera model
//!    ([`crate::geometry::Camera`], as in `docs/scan-format.md`; `camera` only frames it: look-at,
//!    automatic framing, JSON), saved as a tone-mapped PNG and a linear EXR.
//!
//! Everything here is pure computation on in-memory data except [`save_png`] / [`save_exr`].

mod camera;
mod falloff;
mod fresnel;
mod hierarchy;
mod irradiance;
mod light;
mod model;
mod output;
mod raster;
mod scene;
pub mod synthetic;

/// The one camera model, re-exported: the renderer draws through it, `camera` only frames it.
pub use crate::geometry::Camera;
pub use camera::{CameraSpec, DEFAULT_VIEW};
pub use falloff::{Falloffs, segment_weights, tail_cutoff};
pub use fresnel::{fresnel_transmittance, relative_transmittance};
pub use hierarchy::{HierarchyParams, Quality, Transport, TransportStats};
pub use irradiance::{irradiance, shadow_scene, vertex_areas};
pub use light::Light;
pub use model::validate;
pub use output::{
    ImageStats, SHOULDER_CLIP, SHOULDER_KNEE, ToneMapping, WHITE_QUANTILE, auto_exposure,
    image_stats, save_exr, save_png, shoulder, tone_map, tone_map_with,
};
pub use raster::{Image, rasterise};
pub use scene::{
    Method, RenderOptions, RenderOutput, Transported, light_transport, relative_pixel_error,
    relative_pixel_errors, render,
};

/// Why a render could not be made. Every variant names the offending input.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The model has no vertices or no faces, so there is nothing to light or to see.
    #[error("the model has no {0}")]
    Empty(&'static str),
    /// A per-vertex array does not have one entry per vertex.
    #[error("model array `{what}` has {found} entries, expected {expected}")]
    Length {
        /// Which array.
        what: &'static str,
        /// Entries expected (the vertex count, or vertices × parameters).
        expected: usize,
        /// Entries found.
        found: usize,
    },
    /// A number in the model is NaN or infinite, or breaks the model's constraints (c > 0, d < 0).
    #[error("vertex {vertex}: invalid {what} ({value})")]
    InvalidValue {
        /// Vertex index.
        vertex: usize,
        /// Which quantity.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// The model's shape (terms, segments) is outside what the format allows.
    #[error("unsupported model shape: {0}")]
    Shape(String),
    /// A face refers to a vertex that does not exist.
    #[error("face {face} refers to vertex {index}, but the model has {vertices} vertices")]
    FaceIndex {
        /// Face index.
        face: usize,
        /// The bad vertex index.
        index: u32,
        /// Vertex count.
        vertices: usize,
    },
    /// No face of the mesh has a non-zero area, so no ray can hit it.
    #[error("the mesh has no non-degenerate triangle")]
    Degenerate,
    /// A light specification could not be parsed or is physically meaningless.
    #[error("light `{spec}`: {reason}")]
    Light {
        /// The text given.
        spec: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A camera specification could not be parsed or is degenerate.
    #[error("camera: {0}")]
    Camera(String),
    /// An option is out of its range.
    #[error("option {what}: {reason}")]
    Option {
        /// Which option.
        what: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// Writing or encoding an image failed.
    #[error("writing {path}: {source}")]
    Image {
        /// The file that was being written.
        path: std::path::PathBuf,
        /// The encoder's error.
        source: image::ImageError,
    },
    /// Writing a linear OpenEXR failed.
    #[error("{0}")]
    Exr(crate::dataset::ImageError),
}
