//! What the renderer checks and prepares of a model. The model is the model file's type
//! ([`ModelFile`], `docs/model-format.md`): the renderer owns no model type of its own, only the
//! checks its arithmetic relies on ([`validate`]) and the one layout its inner loops read
//! ([`uniform_params`], consumed by [`super::Falloffs`]).

use super::RenderError;
use crate::modelfile::{ColourMode, ModelFile, VertexStatus};

/// Checks every invariant the renderer relies on: a non-empty mesh, the shape within the format's
/// limits, finite positions, unit normals, finite non-negative alpha and sampled ranges, finite
/// `c > 0`, `d < 0` (so `R_d → 0` as `r → ∞`, §3.1) and scales ≥ 0, face indices in range, and the
/// model file's own consistency ([`ModelFile::check`]). Errors name the vertex.
pub fn validate(model: &ModelFile) -> Result<(), RenderError> {
    let n = model.positions.len();
    if n == 0 {
        return Err(RenderError::Empty("vertices"));
    }
    if model.triangles.is_empty() {
        return Err(RenderError::Empty("faces"));
    }
    let shape = model.shape;
    if shape.terms == 0 || shape.terms > 8 || shape.segments == 0 || shape.segments > 64 {
        return Err(RenderError::Shape(format!(
            "{} terms, {} segments (allowed 1..=8 terms, 1..=64 segments)",
            shape.terms, shape.segments
        )));
    }
    for (what, found) in [
        ("normals", model.normals.len()),
        ("vertices", model.vertices.len()),
    ] {
        if found != n {
            return Err(RenderError::Length {
                what,
                expected: n,
                found,
            });
        }
    }
    for (v, vm) in model.vertices.iter().enumerate() {
        let bad = |what: &'static str, value: f64| RenderError::InvalidValue {
            vertex: v,
            what,
            value,
        };
        for &x in model.positions[v].iter() {
            if !x.is_finite() {
                return Err(bad("position", x));
            }
        }
        let nm = model.normals[v];
        let len = (nm[0] * nm[0] + nm[1] * nm[1] + nm[2] * nm[2]).sqrt();
        if !len.is_finite() || (len - 1.0).abs() > 1e-3 {
            return Err(bad("normal length", len));
        }
        for &a in vm.alpha.iter() {
            if !a.is_finite() || a < 0.0 {
                return Err(bad("alpha", a.into()));
            }
        }
        for r in vm.r_range {
            if !(r.is_finite() && r >= 0.0) {
                return Err(bad("sampled range", r.into()));
            }
        }
        if vm.status == VertexStatus::NoModel {
            continue;
        }
        let terms = match shape.colour {
            ColourMode::Shared => {
                for &s in vm.params.iter().take(2) {
                    if !s.is_finite() || s < 0.0 {
                        return Err(bad("channel scale", s));
                    }
                }
                vm.params.get(2..).unwrap_or(&[])
            }
            ColourMode::PerChannel => &vm.params[..],
        };
        for cd in terms.chunks_exact(2) {
            if !cd[0].is_finite() || cd[0] <= 0.0 {
                return Err(bad("c", cd[0]));
            }
            if !cd[1].is_finite() || cd[1] >= 0.0 {
                return Err(bad("d", cd[1]));
            }
        }
    }
    for (f, face) in model.triangles.iter().enumerate() {
        for &index in face {
            if index as usize >= n {
                return Err(RenderError::FaceIndex {
                    face: f,
                    index,
                    vertices: n,
                });
            }
        }
    }
    model.check().map_err(|e| RenderError::Shape(e.to_string()))
}

/// Every vertex's parameters in one layout, as the renderer's inner loops read them.
#[derive(Clone, Debug)]
pub(crate) struct UniformParams {
    /// n: terms per curve (the file's n, or more where a widened vertex needs up to 2n).
    pub terms: usize,
    /// m: the file's segments.
    pub segments: usize,
    /// [`param_len`] values per vertex in the model file's order; vertices with fewer terms are
    /// padded with `c = 0` terms; vertices without a model hold a neutral placeholder.
    pub params: Vec<f64>,
}

impl UniformParams {
    /// The parameters of vertex `i`.
    pub fn vertex(&self, i: usize, colour: ColourMode) -> &[f64] {
        let l = param_len(colour, self.terms, self.segments);
        &self.params[i * l..(i + 1) * l]
    }
}

/// The model's parameters in one layout for all vertices. Vertices that use fewer than the file's
/// n terms are padded with `c = 0` terms; a vertex with fewer than the file's m segments is
/// widened to m exactly ([`crate::order::widen`]: its curves at the m directions, up to 2n terms
/// each), so the renderer's Eq. 3 blend equals the vertex's own model.
pub(crate) fn uniform_params(file: &ModelFile) -> UniformParams {
    let shape = file.shape;
    let m = shape.segments;
    let colour = shape.colour;
    // Per vertex with fewer segments than the file's: scales and the widened curves
    // (`[c, d, …]` per curve).
    type Widened = (Vec<f64>, Vec<Vec<f64>>);
    let widened: Vec<Option<Widened>> = file
        .vertices
        .iter()
        .map(|v| {
            if v.status == VertexStatus::NoModel || v.segments as usize >= m {
                return None;
            }
            let model = crate::modelfile::model_of(&shape, v.terms as usize, &v.params).ok()?;
            let (head, blocks) = match &model {
                crate::model::ColourModel::Shared { falloff, s_g, s_b } => {
                    (vec![*s_g, *s_b], vec![falloff])
                }
                crate::model::ColourModel::PerChannel { channels } => {
                    (Vec::new(), channels.iter().collect())
                }
            };
            let curves = blocks
                .into_iter()
                .flat_map(|a| crate::order::widen(a, m))
                .map(|e| e.terms.iter().flat_map(|t| [t.c, t.d]).collect())
                .collect();
            Some((head, curves))
        })
        .collect();
    let n = widened
        .iter()
        .flatten()
        .flat_map(|(_, c)| c.iter().map(|t: &Vec<f64>| t.len() / 2))
        .fold(shape.terms, usize::max);
    let len = param_len(colour, n, m);
    let blocks = if colour == ColourMode::Shared { 1 } else { 3 };
    let head = if colour == ColourMode::Shared { 2 } else { 0 };
    let mut params = Vec::with_capacity(file.vertices.len() * len);
    for (v, wide) in file.vertices.iter().zip(&widened) {
        let k = v.terms as usize;
        if let Some((scales, curves)) = wide {
            params.extend_from_slice(scales);
            for c in curves {
                params.extend_from_slice(c);
                for _ in c.len() / 2..n {
                    params.extend([0.0, -1.0]);
                }
            }
            continue;
        }
        if v.status == VertexStatus::NoModel
            || k == 0
            || k > n
            || v.params.len() != head + blocks * m * 2 * k
        {
            // No usable parameters: a neutral placeholder; the status keeps it dark.
            params.extend(std::iter::repeat_n([1.0, -1.0], len / 2).flatten());
            if head == 2 {
                let at = params.len() - len;
                params[at] = 1.0;
                params[at + 1] = 1.0;
            }
            continue;
        }
        params.extend_from_slice(&v.params[..head]);
        for b in 0..blocks * m {
            let src = &v.params[head + b * 2 * k..head + (b + 1) * 2 * k];
            params.extend_from_slice(src);
            for _ in k..n {
                params.extend([0.0, -1.0]);
            }
        }
    }
    UniformParams {
        terms: n,
        segments: m,
        params,
    }
}

/// Parameters per vertex for a model shape (see `docs/model-format.md`).
pub(crate) fn param_len(colour: ColourMode, terms: usize, segments: usize) -> usize {
    match colour {
        ColourMode::Shared => 2 + 2 * terms * segments,
        ColourMode::PerChannel => 6 * terms * segments,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri() -> ModelFile {
        ModelFile::homogeneous(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            vec![[0.0, 0.0, 1.0]; 3],
            vec![[0, 1, 2]],
            [0.5, 0.25],
            &[(1.0, -1.0), (0.1, -0.1)],
        )
    }

    #[test]
    fn homogeneous_model_is_valid_and_laid_out_like_the_file() {
        let m = tri();
        validate(&m).unwrap();
        let u = uniform_params(&m);
        assert_eq!(param_len(m.shape.colour, u.terms, u.segments), 6);
        assert_eq!(
            u.vertex(2, m.shape.colour),
            &[0.5, 0.25, 1.0, -1.0, 0.1, -0.1]
        );
    }

    #[test]
    fn invalid_models_are_refused_with_the_vertex_named() {
        let mut m = tri();
        m.vertices[0].params[3] = 0.5; // d > 0: R_d would grow without bound
        assert!(matches!(
            validate(&m),
            Err(RenderError::InvalidValue {
                vertex: 0,
                what: "d",
                ..
            })
        ));
        let mut m = tri();
        m.positions[1][2] = f64::NAN;
        assert!(matches!(
            validate(&m),
            Err(RenderError::InvalidValue { vertex: 1, .. })
        ));
        let mut m = tri();
        m.triangles[0][2] = 7;
        assert!(matches!(
            validate(&m),
            Err(RenderError::FaceIndex { index: 7, .. })
        ));
        let mut m = tri();
        m.vertices.pop();
        assert!(matches!(
            validate(&m),
            Err(RenderError::Length {
                what: "vertices",
                ..
            })
        ));
        let mut m = tri();
        m.vertices[0].params.push(1.0); // a count that disagrees with n and m
        assert!(matches!(validate(&m), Err(RenderError::Shape(_))));
        let mut m = tri();
        m.vertices[0].status = VertexStatus::NoModel;
        m.vertices[0].terms = 0;
        m.vertices[0].segments = 0;
        m.vertices[0].params.clear();
        validate(&m).unwrap();
    }
}
