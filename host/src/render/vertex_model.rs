//! The per-vertex model as the renderer needs it: exactly the data of `docs/model-format.md`.

use super::RenderError;
use crate::model::Support;
use crate::modelfile::{ColourMode as FileColour, ModelFile, VertexStatus as FileStatus};

/// How colour is modelled (the `comment colour` header line of the model file).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColourMode {
    /// Eq. 5/9: one fall-off for all channels, scaled by `(1, s_g, s_b)`.
    Shared,
    /// Eq. 3 per channel: each channel has its own `c_kl`, `d_kl`.
    PerChannel,
}

/// Where a vertex's parameters came from (the `status` property of the model file).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VertexStatus {
    /// Fitted from its own samples.
    Fitted,
    /// Interpolated from neighbours because its own fit failed.
    Interpolated,
    /// No model: the vertex scatters no light as a source `x_i` (it still receives light as `x_o`).
    NoModel,
}

impl VertexStatus {
    /// Decodes the model file's `status` byte; unknown codes are treated as "no model" so that a
    /// newer file never makes the renderer invent light.
    pub fn from_code(code: u8) -> Self {
        match code {
            0 => Self::Fitted,
            1 => Self::Interpolated,
            _ => Self::NoModel,
        }
    }
}

/// A fitted object ready to render: the mesh in the object frame (millimetres) plus, per vertex,
/// the modulation texture `alpha(x_o)` (Eq. 2/6) and the fall-off parameters used when the vertex
/// is the light position `x_i` (Eq. 1/3/5/9), laid out exactly as the model file's `params` list.
#[derive(Clone, Debug)]
pub struct VertexModel {
    /// n, exponentials per segment (Eq. 1).
    pub terms: usize,
    /// m, direction segments (Eq. 3); 1 = isotropic.
    pub segments: usize,
    /// Shared colour (Eq. 5/9) or per channel (Eq. 3).
    pub colour: ColourMode,
    /// Vertex positions, mm.
    pub positions: Vec<[f64; 3]>,
    /// Unit vertex normals, pointing out of the object.
    pub normals: Vec<[f64; 3]>,
    /// `alpha(x_o)` per channel (Eq. 2/6).
    pub alpha: Vec<[f64; 3]>,
    /// Per-vertex status.
    pub status: Vec<VertexStatus>,
    /// `log E(x_i)` of the vertex's fit (Eq. 8), mean over channels; NaN where not fitted.
    pub log_e: Vec<f64>,
    /// Flat parameters, [`VertexModel::param_len`] per vertex, in the model file's order.
    pub params: Vec<f64>,
    /// Per vertex: the distances its fit sampled (`r_min`, `r_max` of `docs/model-format.md`),
    /// where its model is claimed ([`crate::model::support`]: below r_min R_d continues as the
    /// exponential with the model's value and slope there). [`Support::UNKNOWN`]: everywhere.
    pub support: Vec<Support>,
    /// The model's homogeneous baseline ([`crate::baseline`]): beyond a source's r_max the
    /// fall-off moves towards it, as in evaluation ([`crate::baseline::with_fallback`]), so a
    /// vertex whose samples stopped short does not render its own extrapolated tail. `None`: each
    /// vertex's model everywhere (files without a baseline, ground truth).
    pub baseline: Option<crate::baseline::Baseline>,
    /// Triangles as vertex indices.
    pub faces: Vec<[u32; 3]>,
}

impl VertexModel {
    /// Number of parameters per vertex: `2 + 2nm` (shared) or `6nm` (per channel).
    pub fn param_len(&self) -> usize {
        param_len(self.colour, self.terms, self.segments)
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the model has no vertices.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Axis-aligned bounding box of the vertices, `(min, max)`, mm.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for q in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        (lo, hi)
    }

    /// The parameters of vertex `i`.
    pub fn vertex_params(&self, i: usize) -> &[f64] {
        let l = self.param_len();
        &self.params[i * l..(i + 1) * l]
    }

    /// A homogeneous model: every vertex gets the same shared-colour isotropic fall-off
    /// `(1, s_g, s_b) Σ_k c_k e^{d_k r}` (Eq. 9) and `alpha = 1`. Used for slabs and tests.
    pub fn homogeneous(
        positions: Vec<[f64; 3]>,
        normals: Vec<[f64; 3]>,
        faces: Vec<[u32; 3]>,
        scales: [f64; 2],
        terms: &[(f64, f64)],
    ) -> Self {
        let n = positions.len();
        let mut one = vec![scales[0], scales[1]];
        for &(c, d) in terms {
            one.extend([c, d]);
        }
        let params = one.iter().copied().cycle().take(one.len() * n).collect();
        Self {
            terms: terms.len(),
            segments: 1,
            colour: ColourMode::Shared,
            positions,
            normals,
            alpha: vec![[1.0; 3]; n],
            status: vec![VertexStatus::Fitted; n],
            log_e: vec![f64::NAN; n],
            params,
            support: vec![Support::UNKNOWN; n],
            baseline: None,
            faces,
        }
    }

    /// The renderer's view of a model file. Vertices that use fewer than the file's `n` terms are
    /// padded with `c = 0` terms so every vertex has the same layout; a vertex with fewer than
    /// the file's m segments is widened to m exactly ([`crate::order::widen`]: its curves at the
    /// m directions, up to 2n terms each), so the renderer's Eq. 3 blend equals its own model.
    pub fn from_model_file(file: &ModelFile) -> Self {
        let shape = file.shape;
        let m = shape.segments;
        let colour = match shape.colour {
            FileColour::Shared => ColourMode::Shared,
            FileColour::PerChannel => ColourMode::PerChannel,
        };
        // Per vertex with fewer segments than the file's: scales and the widened curves
        // (`[c, d, …]` per curve).
        type Widened = (Vec<f64>, Vec<Vec<f64>>);
        let widened: Vec<Option<Widened>> = file
            .vertices
            .iter()
            .map(|v| {
                if v.status == FileStatus::NoModel || v.segments as usize >= m {
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
        let mut params = Vec::with_capacity(file.vertices.len() * len);
        for (v, wide) in file.vertices.iter().zip(&widened) {
            let k = v.terms as usize;
            let head = if colour == ColourMode::Shared { 2 } else { 0 };
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
            if v.status == FileStatus::NoModel
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
        let status = file
            .vertices
            .iter()
            .map(|v| match v.status {
                FileStatus::Fitted => VertexStatus::Fitted,
                FileStatus::Interpolated => VertexStatus::Interpolated,
                FileStatus::NoModel => VertexStatus::NoModel,
            })
            .collect();
        Self {
            terms: n,
            segments: m,
            colour,
            positions: file.positions.clone(),
            normals: file.normals.clone(),
            alpha: file
                .vertices
                .iter()
                .map(|v| v.alpha.map(f64::from))
                .collect(),
            status,
            log_e: file.vertices.iter().map(|v| f64::from(v.log_e)).collect(),
            params,
            support: file.vertices.iter().map(|v| v.support()).collect(),
            baseline: file
                .baseline
                .as_ref()
                .and_then(|b| b.baseline(file.shape.colour)),
            faces: file.triangles.clone(),
        }
    }

    /// Checks every invariant the renderer relies on: array lengths, finite numbers, `c > 0`,
    /// `d < 0` (so `R_d → 0` as `r → ∞`, §3.1), face indices in range.
    pub fn validate(&self) -> Result<(), RenderError> {
        let n = self.positions.len();
        if n == 0 {
            return Err(RenderError::Empty("vertices"));
        }
        if self.faces.is_empty() {
            return Err(RenderError::Empty("faces"));
        }
        if self.terms == 0 || self.terms > 8 || self.segments == 0 || self.segments > 64 {
            return Err(RenderError::Shape(format!(
                "{} terms, {} segments (allowed 1..=8 terms, 1..=64 segments)",
                self.terms, self.segments
            )));
        }
        for (what, found) in [
            ("normals", self.normals.len()),
            ("alpha", self.alpha.len()),
            ("status", self.status.len()),
            ("log_e", self.log_e.len()),
            ("support", self.support.len()),
        ] {
            if found != n {
                return Err(RenderError::Length {
                    what,
                    expected: n,
                    found,
                });
            }
        }
        let pl = self.param_len();
        if self.params.len() != n * pl {
            return Err(RenderError::Length {
                what: "params",
                expected: n * pl,
                found: self.params.len(),
            });
        }
        for v in 0..n {
            let bad = |what: &'static str, value: f64| RenderError::InvalidValue {
                vertex: v,
                what,
                value,
            };
            for &x in self.positions[v].iter() {
                if !x.is_finite() {
                    return Err(bad("position", x));
                }
            }
            let nm = self.normals[v];
            let len = (nm[0] * nm[0] + nm[1] * nm[1] + nm[2] * nm[2]).sqrt();
            if !len.is_finite() || (len - 1.0).abs() > 1e-3 {
                return Err(bad("normal length", len));
            }
            for &a in self.alpha[v].iter() {
                if !a.is_finite() || a < 0.0 {
                    return Err(bad("alpha", a));
                }
            }
            let sup = self.support[v];
            for r in [sup.r_min, sup.r_max] {
                if !(r.is_finite() && r >= 0.0) {
                    return Err(bad("sampled range", r));
                }
            }
            if self.status[v] == VertexStatus::NoModel {
                continue;
            }
            let p = self.vertex_params(v);
            let terms = match self.colour {
                ColourMode::Shared => {
                    for &s in &p[..2] {
                        if !s.is_finite() || s < 0.0 {
                            return Err(bad("channel scale", s));
                        }
                    }
                    &p[2..]
                }
                ColourMode::PerChannel => p,
            };
            for cd in terms.chunks_exact(2) {
                // c = 0 is a padding term (a vertex that uses fewer than n terms).
                if !cd[0].is_finite() || cd[0] < 0.0 {
                    return Err(bad("c", cd[0]));
                }
                if !cd[1].is_finite() || cd[1] >= 0.0 {
                    return Err(bad("d", cd[1]));
                }
            }
        }
        for (f, face) in self.faces.iter().enumerate() {
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
        Ok(())
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

    fn tri() -> VertexModel {
        VertexModel::homogeneous(
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
        m.validate().unwrap();
        assert_eq!(m.param_len(), 6);
        assert_eq!(m.vertex_params(2), &[0.5, 0.25, 1.0, -1.0, 0.1, -0.1]);
    }

    #[test]
    fn invalid_models_are_refused_with_the_vertex_named() {
        let mut m = tri();
        m.params[3] = 0.5; // d > 0: R_d would grow without bound
        assert!(matches!(
            m.validate(),
            Err(RenderError::InvalidValue {
                vertex: 0,
                what: "d",
                ..
            })
        ));
        let mut m = tri();
        m.positions[1][2] = f64::NAN;
        assert!(matches!(
            m.validate(),
            Err(RenderError::InvalidValue { vertex: 1, .. })
        ));
        let mut m = tri();
        m.faces[0][2] = 7;
        assert!(matches!(
            m.validate(),
            Err(RenderError::FaceIndex { index: 7, .. })
        ));
        let mut m = tri();
        m.alpha.pop();
        assert!(matches!(
            m.validate(),
            Err(RenderError::Length { what: "alpha", .. })
        ));
        let mut m = tri();
        m.status[0] = VertexStatus::NoModel;
        m.params[3] = f64::NAN; // ignored: the vertex has no model
        m.validate().unwrap();
    }
}
