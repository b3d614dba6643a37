//! Irradiance `E(x_i)` at every vertex, with shadows, and the area `A(x_i)` each vertex stands for.

use rayon::prelude::*;

use super::RenderError;
use super::fresnel::relative_transmittance;
use super::light::Light;
use crate::dataset::{Mesh, triangle_area};
use crate::geometry::Scene;

/// The mesh as shadow rays see it: the one [`Scene`] (its BVH, lift-off and shadow ray
/// [`Scene::unblocked`]) over the non-degenerate triangles; a mesh with none left is an error.
pub fn shadow_scene(positions: &[[f64; 3]], faces: &[[u32; 3]]) -> Result<Scene, RenderError> {
    let (mesh, _) = Mesh::new(positions.to_vec(), faces.to_vec());
    if mesh.triangles.is_empty() {
        return Err(RenderError::Degenerate);
    }
    Scene::new(mesh).map_err(|_| RenderError::Degenerate)
}

/// `A(x_i)`: a third of the area of every triangle around each vertex (the barycentric dual
/// area), mm². The areas sum to the mesh's area. Faces with out-of-range indices are ignored.
pub fn vertex_areas(positions: &[[f64; 3]], faces: &[[u32; 3]]) -> Vec<f64> {
    let mut a = vec![0.0; positions.len()];
    for &f in faces {
        if f.iter().any(|&i| i as usize >= positions.len()) {
            continue;
        }
        let t = triangle_area(positions, f);
        if t.is_finite() {
            for &i in &f {
                a[i as usize] += t / 3.0;
            }
        }
    }
    a
}

/// `E(x_i)` per channel at every vertex: the sum over lights of irradiance × `cos θ_i`, zero where
/// a shadow ray hits the mesh or the light is behind the surface, times the Fresnel transmission
/// into the material relative to normal incidence (when `eta` is given; see
/// [`relative_transmittance`](super::relative_transmittance)).
pub fn irradiance(
    positions: &[[f64; 3]],
    normals: &[[f64; 3]],
    lights: &[Light],
    scene: &Scene,
    eta: Option<f64>,
) -> Vec<[f64; 3]> {
    positions
        .par_iter()
        .zip(normals.par_iter())
        .map(|(&x, &n)| {
            let mut e = [0.0; 3];
            for light in lights {
                let Some(inc) = light.incidence(x) else {
                    continue;
                };
                let l = inc.to_light;
                let cos = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
                if cos <= 0.0 || !scene.unblocked(x, n, l, inc.distance) {
                    continue;
                }
                let t = eta.map_or(1.0, |eta| relative_transmittance(eta, cos));
                for (ec, ic) in e.iter_mut().zip(inc.irradiance) {
                    *ec += ic * cos * t;
                }
            }
            e
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::needless_range_loop, clippy::type_complexity)]
mod tests {
    use super::*;

    /// Two parallel unit squares: z = 0 facing up, and z = 1 above it.
    fn two_plates() -> (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let mut p = Vec::new();
        let mut f = Vec::new();
        for z in [0.0, 1.0] {
            let b = p.len() as u32;
            p.extend([
                [-1.0, -1.0, z],
                [1.0, -1.0, z],
                [1.0, 1.0, z],
                [-1.0, 1.0, z],
            ]);
            f.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
        }
        (p, vec![[0.0, 0.0, 1.0]; 8], f)
    }

    #[test]
    fn areas_sum_to_the_mesh_area() {
        let (p, _, f) = two_plates();
        let a = vertex_areas(&p, &f);
        assert!((a.iter().sum::<f64>() - 8.0).abs() < 1e-12);
    }

    #[test]
    fn the_upper_plate_shadows_the_lower_one() {
        let (p, n, f) = two_plates();
        let occ = shadow_scene(&p, &f).unwrap();
        let lights = ["dir:0,0,-1".parse().unwrap()];
        let e = irradiance(&p, &n, &lights, &occ, None);
        for v in 0..4 {
            assert_eq!(e[v], [0.0; 3], "lower vertex {v} is in shadow");
        }
        for v in 4..8 {
            assert!((e[v][0] - 1.0).abs() < 1e-12, "upper vertex {v} is lit");
        }
        // Light from below reaches neither (normals point up).
        let e = irradiance(&p, &n, &["dir:0,0,1".parse().unwrap()], &occ, None);
        assert!(e.iter().all(|x| *x == [0.0; 3]));
        // Oblique light: cos θ and the Fresnel factor below 1.
        let e = irradiance(&p, &n, &["dir:1,0,-1".parse().unwrap()], &occ, Some(1.3));
        let c = std::f64::consts::FRAC_1_SQRT_2;
        assert!(e[5][0] < c && e[5][0] > 0.9 * c);
    }

    #[test]
    fn a_mesh_of_only_degenerate_triangles_is_refused() {
        let p = vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
        assert!(matches!(
            shadow_scene(&p, &[[0, 1, 2]]),
            Err(RenderError::Degenerate)
        ));
    }
}
