//! One call from a model, lights and a camera to an image.

use std::time::Instant;

use super::RenderError;
use super::falloff::Falloffs;
use super::fresnel::relative_transmittance;
use super::hierarchy::{HierarchyParams, Quality, Transport, TransportStats};
use super::irradiance::{irradiance, shadow_scene, vertex_areas};
use super::light::Light;
use super::raster::{Image, rasterise};
use crate::geometry::Camera;
use crate::modelfile::ModelFile;

/// How `B(x_o)` is summed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Method {
    /// The exact O(N²) sum: the reference.
    Exact,
    /// Octree clustering and distance cutoff under an error bound.
    Hierarchical(HierarchyParams),
}

/// Render settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    /// Exact or hierarchical transport.
    pub method: Method,
    /// Relative index of refraction for the Fresnel factors at entry and exit (relative to normal
    /// incidence); `None` leaves Fresnel out.
    pub eta: Option<f64>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            method: Method::Hierarchical(Quality::Balanced.params()),
            eta: Some(1.3),
        }
    }
}

/// A finished render and how it was made.
#[derive(Clone, Debug)]
pub struct RenderOutput {
    /// The linear image.
    pub image: Image,
    /// `E(x_i)` per vertex (transmitted irradiance).
    pub irradiance: Vec<[f64; 3]>,
    /// `B(x_o)` per vertex: radiant exitance before `alpha` and the exit Fresnel factor.
    pub exitance: Vec<[f64; 3]>,
    /// Outgoing radiance towards the camera per vertex (what the image interpolates).
    pub radiance: Vec<[f64; 3]>,
    /// Work of the transport step.
    pub stats: TransportStats,
    /// Wall time of irradiance, transport and rasterisation, seconds.
    pub seconds: [f64; 3],
}

/// Irradiance and transport of every vertex, without a camera.
#[derive(Clone, Debug)]
pub struct Transported {
    /// `E(x_i)` per vertex (transmitted irradiance).
    pub irradiance: Vec<[f64; 3]>,
    /// `B(x_o)` per vertex.
    pub exitance: Vec<[f64; 3]>,
    /// Work of the transport step.
    pub stats: TransportStats,
    /// Wall time of irradiance and transport, seconds.
    pub seconds: [f64; 2],
}

/// Irradiance and transport only: `E(x_i)` and `B(x_o)` for every vertex of a model.
pub fn light_transport(
    model: &ModelFile,
    lights: &[Light],
    options: &RenderOptions,
) -> Result<Transported, RenderError> {
    super::validate(model)?;
    if let Some(eta) = options.eta
        && !(eta > 0.0 && eta.is_finite())
    {
        return Err(RenderError::Option {
            what: "eta",
            reason: format!("{eta} is not positive"),
        });
    }
    let t0 = Instant::now();
    let scene = shadow_scene(&model.positions, &model.triangles)?;
    let e = irradiance(
        &model.positions,
        &model.normals,
        lights,
        &scene,
        options.eta,
    );
    let areas = vertex_areas(&model.positions, &model.triangles);
    let t1 = Instant::now();
    let falloffs = Falloffs::new(model);
    let transport = Transport::new(&model.positions, &model.normals, &falloffs, &e, &areas);
    let all: Vec<usize> = (0..model.len()).collect();
    let (b, stats) = match options.method {
        Method::Exact => {
            let b = transport.exact(&all);
            let stats = TransportStats {
                sources: transport.source_count(),
                receivers: all.len(),
                point_evals: (transport.source_count() * all.len()) as u64,
                ..Default::default()
            };
            (b, stats)
        }
        Method::Hierarchical(p) => transport.hierarchical(p, &all),
    };
    let t2 = Instant::now();
    Ok(Transported {
        irradiance: e,
        exitance: b,
        stats,
        seconds: [(t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64()],
    })
}

/// Renders `model` under `lights` as `camera` sees it.
///
/// Outgoing radiance `L(x_o) = alpha(x_o) F_t(θ_o) B(x_o) / π` (Eq. 2 with a diffuse exit, the
/// Fresnel factor relative to normal incidence), `B(x_o) = Σ_i R_d(x_i → x_o) E(x_i) A(x_i)` with
/// the parameters of `x_i`.
pub fn render(
    model: &ModelFile,
    lights: &[Light],
    camera: &Camera,
    options: &RenderOptions,
) -> Result<RenderOutput, RenderError> {
    let Transported {
        irradiance: e,
        exitance: b,
        stats,
        seconds: [t_e, t_b],
    } = light_transport(model, lights, options)?;
    let t0 = Instant::now();
    let eye = camera.center();
    let radiance: Vec<[f64; 3]> = (0..model.len())
        .map(|v| {
            let x = model.positions[v];
            let n = model.normals[v];
            let d = [eye[0] - x[0], eye[1] - x[1], eye[2] - x[2]];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-300);
            let cos = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / l;
            let ft = options
                .eta
                .map_or(1.0, |eta| relative_transmittance(eta, cos.max(0.0)));
            let a = model.vertices[v].alpha.map(f64::from);
            [0, 1, 2].map(|c| a[c] * ft * b[v][c] / std::f64::consts::PI)
        })
        .collect();
    // A validated model can still have a fall-off too large to represent near its source (c huge
    // where d is steep): say so instead of writing an image of infinities and NaNs.
    if let Some((v, c)) = radiance.iter().enumerate().find_map(|(v, l)| {
        l.iter()
            .position(|x| !(x.is_finite() && x.abs() <= f64::from(f32::MAX)))
            .map(|c| (v, l[c]))
    }) {
        return Err(RenderError::InvalidValue {
            vertex: v,
            what: "outgoing radiance (the model's fall-off is too large to represent)",
            value: c,
        });
    }
    let image = rasterise(camera, &model.positions, &model.triangles, &radiance);
    let t_r = t0.elapsed().as_secs_f64();
    Ok(RenderOutput {
        image,
        irradiance: e,
        exitance: b,
        radiance,
        stats,
        seconds: [t_e, t_b, t_r],
    })
}

/// Mean relative error of `image` against `reference` over the channels of covered pixels whose
/// reference value is above `floor` times the reference's largest value (darker pixels are left
/// out: a relative error there says nothing about the picture). `None` when no pixel qualifies or
/// the sizes differ.
pub fn relative_pixel_error(image: &Image, reference: &Image, floor: f64) -> Option<f64> {
    if image.width != reference.width || image.height != reference.height {
        return None;
    }
    let max = reference
        .pixels
        .iter()
        .zip(&reference.covered)
        .filter(|(_, c)| **c)
        .flat_map(|(p, _)| p.iter().map(|&v| v as f64))
        .fold(0.0, f64::max);
    let (mut sum, mut n) = (0.0, 0usize);
    for k in 0..reference.pixels.len() {
        if !reference.covered[k] {
            continue;
        }
        for c in 0..3 {
            let r = reference.pixels[k][c] as f64;
            if r > floor * max && r > 0.0 {
                sum += ((image.pixels[k][c] as f64 - r) / r).abs();
                n += 1;
            }
        }
    }
    (n > 0).then(|| sum / n as f64)
}
