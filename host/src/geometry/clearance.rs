//! A lower bound of a point's distance to the mesh, read from a grid of exact distances.
//!
//! A photon in a medium flies a few tenths of a millimetre between collisions, and each
//! flight asks whether the surface lies within it: a ray cast through the BVH, most of a
//! trace's time. Deep inside the object the answer is always no. The distance to the surface is
//! 1-Lipschitz, so the exact distance at the nearest node of a grid, less the point's distance
//! to that node, bounds the point's own from below: a flight shorter than that bound meets no
//! surface, and the cast can be skipped with its answer known. Written here because parry
//! answers the distance query exactly but has no cached field of it; the grid is built on the
//! first query, so only the volume tracer pays for it.

use super::{Scene, V3, dist};
use rayon::prelude::*;

/// Nodes along the mesh's bounding box's diagonal: a node every 1/96 of it (0.4 mm on a 40 mm
/// object, a fraction of a mean free path of the media the tracer fits).
const NODES_PER_DIAGONAL: f64 = 96.0;

/// At most this many nodes (16 MB of distances), whatever the box's proportions.
const MAX_NODES: usize = 2_000_000;

/// The distances at the nodes of a regular grid over the mesh's bounding box (one spacing
/// beyond it on every side).
pub(super) struct Clearance {
    origin: V3,
    h: f64,
    n: [usize; 3],
    d: Vec<f64>,
}

impl Clearance {
    /// The grid of `scene`'s mesh; an empty one (every bound 0) for an empty or degenerate mesh.
    pub(super) fn build(scene: &Scene) -> Clearance {
        let empty = Clearance {
            origin: [0.0; 3],
            h: 1.0,
            n: [0; 3],
            d: Vec::new(),
        };
        if scene.mesh.triangles.is_empty() {
            return empty;
        }
        let (lo, hi) = scene.mesh.bounds();
        let diag = dist(lo, hi);
        if !(diag > 0.0 && diag.is_finite()) {
            return empty;
        }
        let mut h = diag / NODES_PER_DIAGONAL;
        let count = |h: f64| -> [usize; 3] {
            std::array::from_fn(|c| ((hi[c] - lo[c]) / h).ceil() as usize + 3)
        };
        while count(h).iter().product::<usize>() > MAX_NODES {
            h *= 1.25;
        }
        let n = count(h);
        let origin: V3 = std::array::from_fn(|c| lo[c] - h);
        let d: Vec<f64> = (0..n[0] * n[1] * n[2])
            .into_par_iter()
            .map(|i| {
                let (x, y, z) = (i % n[0], (i / n[0]) % n[1], i / (n[0] * n[1]));
                let p = [
                    origin[0] + x as f64 * h,
                    origin[1] + y as f64 * h,
                    origin[2] + z as f64 * h,
                ];
                scene.closest(p, f64::INFINITY).map_or(0.0, |c| c.distance)
            })
            .collect();
        Clearance { origin, h, n, d }
    }

    /// A lower bound of `p`'s distance to the mesh (0 outside the grid or where unknown).
    pub(super) fn at(&self, p: V3) -> f64 {
        let mut idx = [0usize; 3];
        let mut node = [0.0; 3];
        for c in 0..3 {
            let f = ((p[c] - self.origin[c]) / self.h).round();
            if !(f >= 0.0 && f < self.n[c] as f64) {
                return 0.0;
            }
            idx[c] = f as usize;
            node[c] = self.origin[c] + f * self.h;
        }
        let i = idx[0] + self.n[0] * (idx[1] + self.n[1] * idx[2]);
        // Less a hair for the rounding of the two distances.
        let bound = self.d[i] - dist(p, node) - 1e-9 * (1.0 + self.d[i]);
        bound.max(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a block and an ellipsoid the bound never exceeds the exact distance, and deep inside it
    /// is most of it.
    #[test]
    fn the_bound_is_below_the_distance_and_close_to_it_inside() {
        use rand::{Rng, SeedableRng};
        for (mesh, half) in [
            (
                crate::geometry::shapes::block([-10.0, -6.0, -3.0], [10.0, 6.0, 3.0]),
                [10.0, 6.0, 3.0],
            ),
            (
                crate::geometry::shapes::ellipsoid([15.0, 10.0, 7.0], 4),
                [15.0, 10.0, 7.0],
            ),
        ] {
            let scene = Scene::new(mesh).unwrap();
            let grid = Clearance::build(&scene);
            let mut rng = rand::rngs::StdRng::seed_from_u64(3);
            let (mut deep, mut close) = (0, 0);
            for _ in 0..20_000 {
                // Over the box and a margin beyond it, where the grid ends.
                let p: V3 = std::array::from_fn(|c| rng.random_range(-1.2..1.2) * half[c]);
                let exact = scene.closest(p, f64::INFINITY).unwrap().distance;
                let bound = grid.at(p);
                assert!(bound <= exact, "{p:?}: bound {bound} above {exact}");
                if exact > 1.0 && p.iter().zip(&half).all(|(x, h)| x.abs() < *h) {
                    deep += 1;
                    close += usize::from(bound > 0.6 * exact);
                }
            }
            assert!(deep > 1000 && close * 10 >= deep * 9, "{close} of {deep}");
        }
    }
}
