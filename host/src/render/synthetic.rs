//! Built-in heterogeneous test objects with a known model, for benchmarks, tests and the demo.

use crate::modelfile::{ColourMode, ModelFile, ModelShape, NO_RANGE, VertexModel, VertexStatus};

/// Marble-like veins: a smooth pseudo-random field in [0, 1] with thin bright bands.
fn veins(p: [f64; 3]) -> f64 {
    let t = 0.11 * p[0]
        + 0.07 * p[1]
        + 0.05 * p[2]
        + 0.8 * (0.13 * p[1] + 0.9 * (0.09 * p[2]).sin()).sin()
        + 0.5 * (0.17 * p[0] - 0.11 * p[2]).cos();
    let s = (3.0 * t).sin();
    s * s * s * s
}

/// A torus (major radius 30 mm, minor 12 mm, axis +z) of `nu × nv` vertices whose scattering
/// varies like veined marble: the fall-off rate (Eq. 1, n = 2 plus a slow third term), the
/// channel scales (Eq. 9) and `alpha` change along the veins. Non-convex, so it shadows itself.
pub fn marble_torus(nu: usize, nv: usize) -> ModelFile {
    let (big, small) = (30.0, 12.0);
    let nu = nu.max(3);
    let nv = nv.max(3);
    let mut positions = Vec::with_capacity(nu * nv);
    let mut normals = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        let u = std::f64::consts::TAU * i as f64 / nu as f64;
        for j in 0..nv {
            let v = std::f64::consts::TAU * j as f64 / nv as f64;
            let n = [u.cos() * v.cos(), u.sin() * v.cos(), v.sin()];
            positions.push([
                (big + small * v.cos()) * u.cos(),
                (big + small * v.cos()) * u.sin(),
                small + small * v.sin(),
            ]);
            normals.push(n);
        }
    }
    let mut faces = Vec::with_capacity(2 * nu * nv);
    let id = |i: usize, j: usize| ((i % nu) * nv + (j % nv)) as u32;
    for i in 0..nu {
        for j in 0..nv {
            faces.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
            faces.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
        }
    }
    from_field(positions, normals, faces)
}

/// Assigns the veined-marble model to a mesh.
pub fn from_field(
    positions: Vec<[f64; 3]>,
    normals: Vec<[f64; 3]>,
    faces: Vec<[u32; 3]>,
) -> ModelFile {
    let mut vertices = Vec::with_capacity(positions.len());
    for p in &positions {
        let v = veins(*p);
        // Veins scatter less far (faster fall-off) and are warmer.
        let rate = 1.0 + 1.5 * v;
        let params = vec![
            0.85 - 0.25 * v,
            0.7 - 0.3 * v,
            0.6,
            -2.5 * rate,
            0.25,
            -0.8 * rate,
            0.01,
            -0.25 * rate,
        ];
        let a = 0.9 + 0.1 * (0.7 * p[0]).sin() * (0.6 * p[1]).cos();
        vertices.push(VertexModel {
            alpha: [a as f32; 3],
            status: VertexStatus::Fitted,
            log_e: f32::NAN,
            terms: 3,
            segments: 1,
            params,
            r_range: NO_RANGE,
        });
    }
    ModelFile {
        shape: ModelShape {
            terms: 3,
            segments: 1,
            colour: ColourMode::Shared,
        },
        positions,
        normals,
        triangles: faces,
        vertices,
        baseline: None,
        frame: crate::model::FrameRule::CURRENT,
        face_alpha: None,
        fitted_with: None,
        fitted_frames: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_torus_is_a_valid_model_of_the_requested_size() {
        let m = marble_torus(20, 10);
        crate::render::validate(&m).unwrap();
        assert_eq!(m.len(), 200);
        assert_eq!(m.triangles.len(), 400);
    }
}
