//! Irradiance `E(x_i)` at every vertex, with shadows, and the area `A(x_i)` each vertex stands for.

use parry3d_f64::math::Vector;
use parry3d_f64::query::{Ray, RayCast};
use parry3d_f64::shape::TriMesh;
use rayon::prelude::*;

use super::RenderError;
use super::fresnel::relative_transmittance;
use super::light::Light;

/// The mesh as an occluder for shadow rays: parry's BVH over the non-degenerate triangles.
/// Our `[f64; 3]` points become parry's glamx vectors only here.
pub struct Occluder {
    mesh: TriMesh,
    /// Offset of shadow-ray origins along the normal, mm, so a vertex does not shadow itself.
    epsilon: f64,
}

impl Occluder {
    /// Builds the BVH. Degenerate (zero-area) triangles are left out; a mesh with none left is an
    /// error.
    pub fn new(positions: &[[f64; 3]], faces: &[[u32; 3]]) -> Result<Self, RenderError> {
        let vertices: Vec<Vector> = positions
            .iter()
            .map(|p| Vector::new(p[0], p[1], p[2]))
            .collect();
        let n = positions.len();
        let indices: Vec<[u32; 3]> = faces
            .iter()
            .copied()
            .filter(|f| f.iter().all(|&i| (i as usize) < n) && triangle_area(positions, *f) > 0.0)
            .collect();
        if indices.is_empty() {
            return Err(RenderError::Degenerate);
        }
        let (lo, hi) = bounds(positions);
        let diag =
            ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt();
        let mesh = TriMesh::new(vertices, indices).map_err(|_| RenderError::Degenerate)?;
        Ok(Self {
            mesh,
            epsilon: 1e-5 * diag.max(1e-9),
        })
    }

    /// True when nothing blocks the segment from `x` (pushed off the surface along `normal`)
    /// towards `dir` for `distance` mm.
    pub fn unblocked(&self, x: [f64; 3], normal: [f64; 3], dir: [f64; 3], distance: f64) -> bool {
        let e = self.epsilon;
        let origin = Vector::new(
            x[0] + normal[0] * e,
            x[1] + normal[1] * e,
            x[2] + normal[2] * e,
        );
        let ray = Ray::new(origin, Vector::new(dir[0], dir[1], dir[2]));
        let max = if distance.is_finite() {
            distance - 2.0 * e
        } else {
            f64::MAX
        };
        !self.mesh.intersects_local_ray(&ray, max)
    }
}

fn bounds(p: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for q in p {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    (lo, hi)
}

fn triangle_area(p: &[[f64; 3]], f: [u32; 3]) -> f64 {
    let (a, b, c) = (p[f[0] as usize], p[f[1] as usize], p[f[2] as usize]);
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let x = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
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
    occluder: &Occluder,
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
                if cos <= 0.0 || !occluder.unblocked(x, n, l, inc.distance) {
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
        let occ = Occluder::new(&p, &f).unwrap();
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
            Occluder::new(&p, &[[0, 1, 2]]),
            Err(RenderError::Degenerate)
        ));
    }
}
