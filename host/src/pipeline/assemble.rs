//! Stage `assemble`: the model file (`docs/model-format.md`) from the vertices' own fits, the
//! interpolated ones and alpha(x_o), with the vertex counts of the report.
//!
//! Owns the per-vertex status; never fits, never reads frames.
use crate::dataset::Dataset;
use crate::modelfile::{ModelFile, ModelShape, NO_RANGE, VertexModel, VertexStatus};

use super::error::OwnFit;
use super::fill::Refit;
use super::findings::{FitReport, ModelSize};

/// The numbers `model` stores and those of the same model with every vertex at n = `max_terms`
/// (the file's largest n when unknown) and m = `max_segments`.
pub fn model_size(model: &ModelFile, max_terms: Option<usize>, max_segments: usize) -> ModelSize {
    let n = max_terms.unwrap_or(model.shape.terms);
    let with_model = model.vertices.iter().filter(|v| !v.params.is_empty());
    ModelSize {
        numbers: with_model.clone().map(|v| v.params.len()).sum(),
        fixed_numbers: with_model.count() * model.shape.param_count_m(n, max_segments),
        max_terms: n,
        max_segments,
    }
}

/// The model: every vertex fitted, interpolated or without a model, in mesh order.
pub fn model_file(
    ds: &Dataset,
    shape: ModelShape,
    own: &[Option<OwnFit>],
    refits: &[Option<Refit>],
    alpha: &[[f64; 3]],
    report: &mut FitReport,
) -> ModelFile {
    let vertices = own
        .iter()
        .zip(refits)
        .zip(alpha)
        .map(|((own, refit), a)| {
            let alpha = a.map(|x| x as f32);
            match (own, refit) {
                (Some(o), _) => {
                    report.vertices_fitted += 1;
                    VertexModel {
                        alpha,
                        status: VertexStatus::Fitted,
                        log_e: o.log_e,
                        terms: o.terms as u8,
                        segments: o.segments as u8,
                        params: o.params.clone(),
                        r_range: o.r_range.map(|x| x as f32),
                    }
                }
                (None, Some(r)) => {
                    report.vertices_interpolated += 1;
                    VertexModel {
                        alpha,
                        status: VertexStatus::Interpolated,
                        log_e: f32::NAN,
                        terms: r.terms as u8,
                        segments: r.segments as u8,
                        params: r.params.clone(),
                        r_range: r.r_range.map(|x| x as f32),
                    }
                }
                (None, None) => {
                    report.vertices_no_model += 1;
                    VertexModel {
                        alpha,
                        status: VertexStatus::NoModel,
                        log_e: f32::NAN,
                        terms: 0,
                        segments: 0,
                        params: Vec::new(),
                        r_range: NO_RANGE,
                    }
                }
            }
        })
        .collect();
    ModelFile {
        shape,
        positions: ds.mesh.positions.clone(),
        normals: ds.mesh.normals.clone(),
        triangles: ds.mesh.triangles.clone(),
        vertices,
        baseline: None,
        // Every fit measures directions with `TangentFrame::from_normal` (the `select` stage).
        frame: crate::model::FrameRule::CURRENT,
        face_alpha: None,
        fitted_with: None,
        fitted_frames: None,
    }
}
