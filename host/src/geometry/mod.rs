//! Rig geometry: the one camera model ([`Camera`], exactly the `scan.json` camera), the turntable,
//! and the one [`Scene`]: ray casts against the mesh (BVH of `parry3d-f64`), interpolated normals,
//! lift-off, occlusion, the visibility rule (its grazing threshold a parameter) and adjacency.
//!
//! Frames (see `docs/scan-format.md`): the object frame is the turntable at angle 0; a mesh point
//! `p` sits in the world at `R_z(θ)·p`. Everything here is plain `[f64; 3]`; parry's glam types
//! stay inside [`Scene`]: nothing else in the workspace builds a parry mesh.
use parry3d_f64::math::Vector as PVec;
use parry3d_f64::query::{PointQueryWithLocation, Ray, RayCast};
use parry3d_f64::shape::TriMesh;

use crate::dataset::Mesh;

mod camera;
mod clearance;
mod coverage;
pub mod shapes;
mod surface;
pub use camera::Camera;
pub use coverage::CoverageMap;
pub use surface::SurfacePoints;

/// A 3-vector in millimetres.
pub type V3 = [f64; 3];

/// `a - b`.
pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
/// `a + s·b`.
pub fn add_scaled(a: V3, s: f64, b: V3) -> V3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}
/// Dot product.
pub fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
/// Cross product.
pub fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
/// Euclidean length.
pub fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
/// `|a - b|`, the distance `|x_o - x_i|` of Eq. 1.
pub fn dist(a: V3, b: V3) -> f64 {
    norm(sub(a, b))
}
/// `a / |a|`, or `None` for a zero or non-finite vector.
pub fn normalize(a: V3) -> Option<V3> {
    let l = norm(a);
    (l > 0.0 && l.is_finite()).then(|| a.map(|x| x / l))
}

/// Rotation of the turntable by `deg` about `+z` (counter-clockwise seen from above):
/// object frame → world frame.
pub fn turntable_to_world(p: V3, deg: f64) -> V3 {
    let (s, c) = deg.to_radians().sin_cos();
    [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]]
}
/// Inverse of [`turntable_to_world`]: world frame → object frame.
pub fn world_to_turntable(p: V3, deg: f64) -> V3 {
    turntable_to_world(p, -deg)
}

/// Where a ray met the mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray, mm.
    pub t: f64,
    /// The point, object frame.
    pub point: V3,
    /// Index of the triangle hit.
    pub triangle: u32,
}

/// The point of the mesh closest to a query point ([`Scene::closest`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Closest {
    /// The closest surface point, object frame.
    pub point: V3,
    /// Index of the triangle that holds it.
    pub triangle: u32,
    /// Distance from the query point, mm.
    pub distance: f64,
}

/// A vertex seen by a camera, with where it lands in the image. Also a surface point of a
/// [`SurfacePoints`] ([`Scene::visible_points`]): then `vertex` is the index into that point
/// array, not a mesh vertex.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Visible {
    /// Vertex index (for [`Scene::visible_points`]: surface-point index).
    pub vertex: u32,
    /// Pixel column coordinate (pixel centres at integers).
    pub u: f64,
    /// Pixel row coordinate.
    pub v: f64,
}

/// Why a scene could not be built.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GeometryError {
    /// The BVH builder rejected the mesh.
    #[error("cannot build the ray-casting structure: {0}")]
    Bvh(String),
}

/// The mesh ready for queries: BVH, normals, adjacency (compressed rows). The one place a ray
/// meets the mesh: processing, the scan planner, the simulator and the renderer all cast here.
pub struct Scene {
    /// The mesh (object frame).
    pub mesh: Mesh,
    bvh: TriMesh,
    adj_start: Vec<u32>,
    adj: Vec<u32>,
    eps: f64,
    /// [`Scene::lift_off`]'s distance: 1e-5 of the mesh's diagonal.
    lift: f64,
    /// [`Scene::clearance`]'s grid, built on its first query.
    clearance: std::sync::OnceLock<clearance::Clearance>,
}

impl std::fmt::Debug for Scene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scene")
            .field("vertices", &self.mesh.positions.len())
            .field("triangles", &self.mesh.triangles.len())
            .finish()
    }
}

impl Scene {
    /// Builds the BVH and the vertex adjacency.
    pub fn new(mesh: Mesh) -> Result<Scene, GeometryError> {
        let verts: Vec<PVec> = mesh
            .positions
            .iter()
            .map(|p| PVec::new(p[0], p[1], p[2]))
            .collect();
        let bvh = TriMesh::new(verts, mesh.triangles.clone())
            .map_err(|e| GeometryError::Bvh(format!("{e:?}")))?;
        let n = mesh.positions.len();
        let mut lists: Vec<Vec<u32>> = vec![Vec::new(); n];
        for t in &mesh.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                lists[a as usize].push(b);
                lists[b as usize].push(a);
            }
        }
        let mut adj_start = Vec::with_capacity(n + 1);
        let mut adj = Vec::new();
        adj_start.push(0);
        for mut l in lists {
            l.sort_unstable();
            l.dedup();
            adj.extend(l);
            adj_start.push(adj.len() as u32);
        }
        let diagonal = mesh.diagonal();
        let eps = (diagonal * 1e-7).max(1e-9);
        Ok(Scene {
            mesh,
            bvh,
            adj_start,
            adj,
            eps,
            lift: 1e-5 * diagonal,
            clearance: std::sync::OnceLock::new(),
        })
    }

    /// A lower bound of `p`'s distance to the surface (0 where it is not known): a ray from `p`
    /// shorter than it meets no triangle. Built on the first call (a fraction of a second for
    /// thousands of triangles); the volume tracer skips its flights' casts by it.
    pub fn clearance(&self, p: V3) -> f64 {
        self.clearance
            .get_or_init(|| clearance::Clearance::build(self))
            .at(p)
    }

    /// The vertices sharing an edge with vertex `v`.
    pub fn neighbours(&self, v: usize) -> &[u32] {
        &self.adj[self.adj_start[v] as usize..self.adj_start[v + 1] as usize]
    }

    /// First hit of the ray `origin + t·dir` (object frame, `dir` need not be unit) with
    /// `0 <= t <= t_max`, `t` in mm along the normalised direction.
    pub fn cast(&self, origin: V3, dir: V3, t_max: f64) -> Option<Hit> {
        let d = normalize(dir)?;
        let first = self.cast_strict(origin, d, t_max);
        if first.is_some() {
            return first;
        }
        // A ray through a shared edge or vertex can slip between the triangles' boundary tests
        // (aligned cameras put pixel centres exactly on grid vertices). Retry with the origin
        // nudged sideways by a distance far below any feature of the mesh.
        let e1 = normalize(cross(d, [0.0, 0.0, 1.0]))
            .or_else(|| normalize(cross(d, [1.0, 0.0, 0.0])))?;
        let e2 = cross(d, e1);
        let h = 10.0 * self.eps;
        [e1, e2, e1.map(|x| -x), e2.map(|x| -x)]
            .iter()
            .find_map(|e| self.cast_strict(add_scaled(origin, h, *e), d, t_max))
            .map(|hit| Hit {
                point: add_scaled(origin, hit.t, d),
                ..hit
            })
    }

    /// The first hit of the ray from `origin` along the unit direction `d` within `t_max`,
    /// without [`Scene::cast`]'s retry from nudged origins. For rays that start on the surface
    /// (a photon that has just crossed it): there a sideways nudge can put the origin behind the
    /// face just left, and at grazing incidence the nudged ray meets that face again a
    /// millimetre's fraction ahead, a crossing that is not there.
    pub fn cast_strict(&self, origin: V3, d: V3, t_max: f64) -> Option<Hit> {
        let ray = Ray::new(
            PVec::new(origin[0], origin[1], origin[2]),
            PVec::new(d[0], d[1], d[2]),
        );
        let hit = self.bvh.cast_local_ray_and_get_normal(&ray, t_max, false)?;
        let t = hit.time_of_impact;
        Some(Hit {
            t,
            point: add_scaled(origin, t, d),
            triangle: hit.subshape,
        })
    }

    /// Casts a ray given in the world frame at turntable angle `deg`; the hit is in the object frame.
    pub fn cast_world(&self, origin: V3, dir: V3, deg: f64) -> Option<Hit> {
        self.cast(
            world_to_turntable(origin, deg),
            world_to_turntable(dir, deg),
            f64::MAX,
        )
    }

    /// The surface point nearest to `p` (object frame) within `max_dist` (infinite: anywhere),
    /// with its triangle: the query of point-to-surface distances (`align`'s ICP, the fit's
    /// mesh check, tests that measure a surface's distance). `None` for a non-finite `p` or
    /// nothing within `max_dist`.
    pub fn closest(&self, p: V3, max_dist: f64) -> Option<Closest> {
        if !p.iter().all(|x| x.is_finite()) {
            return None;
        }
        let q = PVec::new(p[0], p[1], p[2]);
        let (proj, (triangle, _)) = self
            .bvh
            .project_local_point_and_get_location_with_max_dist(q, false, max_dist)?;
        let point = [proj.point.x, proj.point.y, proj.point.z];
        Some(Closest {
            point,
            triangle,
            distance: dist(point, p),
        })
    }

    /// Unit geometric normal of triangle `tri` (counter-clockwise seen from outside); `None`
    /// for an index out of range. The plane of point-to-plane distances, where
    /// [`Scene::normal_at`] is the shading normal.
    pub fn face_normal(&self, tri: u32) -> Option<V3> {
        let t = self.mesh.triangles.get(tri as usize)?;
        let [a, b, c] = t.map(|i| self.mesh.positions[i as usize]);
        normalize(cross(sub(b, a), sub(c, a)))
    }

    /// Barycentric weights of `p` in triangle `tri` (clamped to the triangle, summing to 1).
    pub fn barycentric(&self, tri: u32, p: V3) -> [f64; 3] {
        let t = self.mesh.triangles[tri as usize];
        let [a, b, c] = t.map(|i| self.mesh.positions[i as usize]);
        let (v0, v1, v2) = (sub(b, a), sub(c, a), sub(p, a));
        let (d00, d01, d11) = (dot(v0, v0), dot(v0, v1), dot(v1, v1));
        let (d20, d21) = (dot(v2, v0), dot(v2, v1));
        let den = d00 * d11 - d01 * d01;
        if den.is_nan() || den == 0.0 {
            return [1.0 / 3.0; 3];
        }
        let v = ((d11 * d20 - d01 * d21) / den).clamp(0.0, 1.0);
        let w = ((d00 * d21 - d01 * d20) / den).clamp(0.0, 1.0 - v);
        [1.0 - v - w, v, w]
    }

    /// Is the segment from `p` (on the surface) to `q` free of the mesh?
    pub fn unoccluded(&self, p: V3, q: V3) -> bool {
        let Some(d) = normalize(sub(q, p)) else {
            return true;
        };
        let len = dist(p, q);
        // Start well off the surface: `cast` retries a miss with its origin nudged sideways by
        // 10·eps, which from a start only 4·eps off the surface lands below it at grazing
        // angles, where the surface itself then "occludes" the ray (this hid every vertex
        // facing the camera at more than ~20° from the normal). 100·eps keeps the nudged origin
        // above the surface down to ~6° from the tangent, beyond any grazing limit in use.
        let start = add_scaled(p, 100.0 * self.eps, d);
        self.cast(start, d, len - 200.0 * self.eps).is_none()
    }

    /// Unit normal at point `p` of triangle `tri`: the vertex normals interpolated
    /// barycentrically, as shading sees it; `None` where they cancel.
    pub fn normal_at(&self, tri: u32, p: V3) -> Option<V3> {
        let t = self.mesh.triangles[tri as usize];
        let w = self.barycentric(tri, p);
        let mut n = [0.0; 3];
        for k in 0..3 {
            n = add_scaled(n, w[k], self.mesh.normals[t[k] as usize]);
        }
        normalize(n)
    }

    /// `p` moved off the surface along the normal `n` by far less than any feature of the mesh
    /// (1e-5 of its diagonal) — but more than the sideways nudge [`Scene::cast`] retries a missed
    /// ray with, so that retry cannot start under the surface and report `p`'s own triangle as an
    /// occluder (which happens for grazing rays).
    pub fn lift_off(&self, p: V3, n: V3) -> V3 {
        add_scaled(p, self.lift, n)
    }

    /// The visibility rule, the one every stage uses (registration's spot, the samples' x_o, the
    /// scan planner's prediction): the camera sees the surface point `p` (object frame, unit
    /// normal `n`) at turntable angle `deg` when `p` faces the camera with `cos θ >= cos_min`
    /// (θ between `n` and the direction to the camera centre), projects inside the image, and
    /// nothing occludes the segment from `p` lifted off the surface ([`Scene::lift_off`]) to the
    /// camera centre. Returns where `p` lands in the image.
    pub fn sees(&self, cam: &Camera, deg: f64, p: V3, n: V3, cos_min: f64) -> Option<[f64; 2]> {
        let c_obj = world_to_turntable(cam.center(), deg);
        let to_cam = normalize(sub(c_obj, p))?;
        let facing = dot(n, to_cam);
        if facing.is_nan() || facing < cos_min {
            return None;
        }
        let [u, v] = cam.project(turntable_to_world(p, deg))?;
        if !cam.inside(u, v) {
            return None;
        }
        self.unoccluded(self.lift_off(p, n), c_obj)
            .then_some([u, v])
    }

    /// Vertices of the mesh the camera sees at turntable angle `deg` by the rule of
    /// [`Scene::sees`] with grazing limit `cos_min`.
    pub fn visible_vertices(&self, cam: &Camera, deg: f64, cos_min: f64) -> Vec<Visible> {
        use rayon::prelude::*;
        (0..self.mesh.positions.len())
            .into_par_iter()
            .filter_map(|i| {
                let p = self.mesh.positions[i];
                let n = self.mesh.normals[i];
                let [u, v] = self.sees(cam, deg, p, n, cos_min)?;
                Some(Visible {
                    vertex: i as u32,
                    u,
                    v,
                })
            })
            .collect()
    }

    /// Surface points of `pts` the camera sees at turntable angle `deg`, by exactly the rule of
    /// [`Scene::sees`] with grazing limit `cos_min` at each point's position and interpolated
    /// normal; `Visible::vertex` is the point's index in `pts`. Every point is tested on its own
    /// (no shortcut from the corners' visibility: a face whose corners are hidden can show its
    /// interior past a thin occluder); the facing and projection tests come before the one ray
    /// cast, so points facing away cost no ray.
    pub fn visible_points(
        &self,
        pts: &SurfacePoints,
        cam: &Camera,
        deg: f64,
        cos_min: f64,
    ) -> Vec<Visible> {
        use rayon::prelude::*;
        (0..pts.len() as u32)
            .into_par_iter()
            .filter_map(|i| self.sees_point(pts, i, cam, deg, cos_min))
            .collect()
    }

    /// [`Scene::visible_points`] over the points `which` of `pts` only (indices into `pts`, in
    /// the order given): for callers that need a subset (the lattice pass skips the corners,
    /// which are the vertices).
    pub fn visible_points_of(
        &self,
        pts: &SurfacePoints,
        which: &[u32],
        cam: &Camera,
        deg: f64,
        cos_min: f64,
    ) -> Vec<Visible> {
        use rayon::prelude::*;
        which
            .par_iter()
            .filter_map(|&i| self.sees_point(pts, i, cam, deg, cos_min))
            .collect()
    }

    fn sees_point(
        &self,
        pts: &SurfacePoints,
        i: u32,
        cam: &Camera,
        deg: f64,
        cos_min: f64,
    ) -> Option<Visible> {
        let k = i as usize;
        let [u, v] = self.sees(cam, deg, *pts.positions.get(k)?, pts.normals[k], cos_min)?;
        Some(Visible { vertex: i, u, v })
    }

    /// Do the four pixel centres a bilinear read at `(u, v)` weights (those with a non-zero
    /// weight, [`crate::dataset::bilinear_taps`]) all see the surface at `x_o` (object frame) in
    /// the view of `map`? Each centre's ray must hit the mesh within the map's tolerance of
    /// `x_o`'s own distance from the camera (in pixel footprints at `x_o`, see
    /// [`CoverageMap::new`]); a centre seeing the background or another surface makes the read
    /// a mix, not a sample of `x_o` (section 5's s(x_i, x_o)). `false` outside the image.
    pub fn covers(&self, map: &CoverageMap, u: f64, v: f64, x_o: V3) -> bool {
        let cam = &map.cam;
        let Some(taps) =
            crate::dataset::bilinear_taps(cam.width as usize, cam.height as usize, u, v)
        else {
            return false;
        };
        let t0 = dist(map.centre, x_o);
        let footprint = t0 / cam.fx.min(cam.fy);
        let tol = map.tolerance_px * footprint;
        taps.iter().filter(|tap| tap.2 > 0.0).all(|&(i, j, _)| {
            let t = map.depth(i, j, || {
                let (o, d) = cam.ray(i as f64, j as f64)?;
                Some(self.cast_world(o, d, map.deg)?.t)
            });
            (t - t0).abs() <= tol
        })
    }

    /// A shadow ray: is the ray from `p` lifted off the surface along `n`, towards the unit
    /// direction `dir`, free of the mesh for `distance` mm (infinite: for ever)? One BVH query,
    /// no retry: lighting calls it once per vertex and light.
    pub fn unblocked(&self, p: V3, n: V3, dir: V3, distance: f64) -> bool {
        let o = self.lift_off(p, n);
        let ray = Ray::new(
            PVec::new(o[0], o[1], o[2]),
            PVec::new(dir[0], dir[1], dir[2]),
        );
        let max = if distance.is_finite() {
            distance - 2.0 * self.lift
        } else {
            f64::MAX
        };
        !self.bvh.intersects_local_ray(&ray, max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn grid(n: usize, step: f64) -> Mesh {
        let mut pos = Vec::new();
        let half = (n - 1) as f64 * step / 2.0;
        for j in 0..n {
            for i in 0..n {
                pos.push([i as f64 * step - half, j as f64 * step - half, 0.0]);
            }
        }
        let mut tris = Vec::new();
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = (j * n + i) as u32;
                tris.push([a, a + 1, a + n as u32 + 1]);
                tris.push([a, a + n as u32 + 1, a + n as u32]);
            }
        }
        Mesh::new(pos, tris).0
    }

    /// A 5 × 5 grid of 1 mm at z = 0 with a triangular roof at z = 1 over its centre.
    fn roofed_grid(roof: [V3; 3]) -> Scene {
        let mut m = grid(5, 1.0);
        let base = m.positions.len() as u32;
        m.positions.extend(roof);
        m.triangles.push([base, base + 1, base + 2]);
        Scene::new(Mesh::new(m.positions, m.triangles).0).unwrap()
    }

    /// A 200 × 200 pixel camera 100 mm above the origin looking down, 0.1 mm per pixel there.
    fn looking_down() -> Camera {
        Camera {
            width: 200,
            height: 200,
            fx: 1000.0,
            fy: 1000.0,
            cx: 99.5,
            cy: 99.5,
            distortion: None,
            camera_from_world: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, -1.0, 0.0, 0.0],
                [0.0, 0.0, -1.0, 100.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    }

    #[test]
    fn turntable_rotates_counter_clockwise() {
        let p = turntable_to_world([1.0, 0.0, 2.0], 90.0);
        assert!(dist(p, [0.0, 1.0, 2.0]) < 1e-12);
        assert!(dist(world_to_turntable(p, 90.0), [1.0, 0.0, 2.0]) < 1e-12);
    }

    #[test]
    fn rays_hit_the_grid_and_adjacency_is_symmetric() {
        let s = Scene::new(grid(5, 1.0)).unwrap();
        // Rays exactly through grid vertices and edges hit too.
        for (x, y) in [(0.0, 0.0), (1.0, 0.0), (0.5, 0.5), (0.5, 0.0), (-1.0, 1.0)] {
            assert!(
                s.cast([x, y, 10.0], [0.0, 0.0, -1.0], 100.0).is_some(),
                "{x} {y}"
            );
        }
        let h = s.cast([0.3, 0.2, 10.0], [0.0, 0.0, -1.0], 100.0).unwrap();
        assert!((h.t - 10.0).abs() < 1e-9);
        assert!(dist(h.point, [0.3, 0.2, 0.0]) < 1e-9);
        let b = s.barycentric(h.triangle, h.point);
        assert!((b.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!(s.cast([0.3, 0.2, 10.0], [0.0, 0.0, 1.0], 100.0).is_none());
        for v in 0..25 {
            for &w in s.neighbours(v) {
                assert!(s.neighbours(w as usize).contains(&(v as u32)));
            }
        }
        assert_eq!(s.neighbours(12).len(), 6);
    }

    #[test]
    fn occluded_and_grazing_vertices_are_not_visible() {
        // A grid at z=0 and a small roof at z=1 over its centre.
        let s = roofed_grid([[-0.6, -0.6, 1.0], [0.6, -0.6, 1.0], [0.0, 0.7, 1.0]]);
        let spec = looking_down();
        let cam = spec.clone();
        let vis = s.visible_vertices(&cam, 0.0, 0.1);
        let ids: Vec<u32> = vis.iter().map(|v| v.vertex).collect();
        assert!(!ids.contains(&12), "centre vertex is under the roof");
        assert!(ids.contains(&0));
        // Seen from the side (camera on +x looking along -x), the flat grid is grazing.
        let side = Camera {
            camera_from_world: [
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, -1.0, 0.0],
                [-1.0, 0.0, 0.0, 100.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
            ..spec
        };
        let vis = s.visible_vertices(&side, 0.0, 0.1);
        assert!(vis.iter().all(|v| v.vertex >= 25));
    }

    /// A sample's bilinear neighbourhood must see the surface at the sample point: beside an
    /// occluding roof (the point itself visible, one row of its neighbourhood on the roof 1 mm
    /// = 10 pixel footprints nearer) and on an open mesh's boundary (half the neighbourhood on
    /// the background) it is not covered; in the middle of a face it is, and so is a face seen
    /// at 55° from its normal (inside the grazing limit cos 0.5: depth changes by tan 55° = 1.4
    /// footprints per pixel there).
    #[test]
    fn a_neighbourhood_is_covered_only_by_the_surface_at_the_point() {
        let s = roofed_grid([[-0.6, -0.6, 1.0], [0.6, -0.6, 1.0], [0.0, 0.7, 1.0]]);
        let cam = looking_down();
        let map = CoverageMap::new(&cam, 0.0, 0.5);
        let up = [0.0, 0.0, 1.0];
        let at = |p: V3| {
            let uv = s.sees(&cam, 0.0, p, up, 0.5).expect("the point is seen");
            s.covers(&map, uv[0], uv[1], p)
        };
        // Beside the roof: seen, but row 105 of its neighbourhood (v = 105.7) sees the roof.
        assert!(!at([0.0, -0.62, 0.0]), "occluding limb");
        // On the boundary (u = 119.5): columns 120 and beyond see the background.
        assert!(!at([2.0, 1.3, 0.0]), "open boundary");
        // Inside a face, away from both.
        assert!(at([1.3, 1.3, 0.0]), "middle of a face");
        assert!(at([-1.25, 1.45, 0.0]), "middle of a face");

        let flat = Scene::new(grid(41, 0.25)).unwrap();
        let target = [0.3, 0.2, 0.0];
        let (sn, cs) = 55f64.to_radians().sin_cos();
        let eye = [target[0] + 100.0 * sn, target[1], 100.0 * cs];
        let tilted = Camera::look_at(eye, target, [0.0, 0.0, 1.0], 1000.0, 200, 200).unwrap();
        let map = CoverageMap::new(&tilted, 0.0, 0.5);
        let [u, v] = flat
            .sees(&tilted, 0.0, target, up, 0.5)
            .expect("seen at 55°");
        assert!(flat.covers(&map, u, v, target), "grazing but covered");
        // A point 2 mm off the surface (11 footprints nearer) is not what those pixels see.
        assert!(!flat.covers(&map, u, v, [target[0], target[1], 2.0]));
    }

    /// Surface points obey exactly the vertices' rule: at level 1 (the corners) the visible
    /// points are the visible vertices of each face, at the same pixels; between the vertices,
    /// points under the roof are hidden and points outside it seen.
    #[test]
    fn surface_points_are_visible_by_the_vertices_rule() {
        let s = roofed_grid([[-1.2, -1.2, 1.0], [1.2, -1.2, 1.0], [0.0, 1.4, 1.0]]);
        let cam = looking_down();
        let faces = s.mesh.triangles.len();
        let corners = SurfacePoints::lattice(&s.mesh, &vec![1; faces]).unwrap();
        let verts = s.visible_vertices(&cam, 0.0, 0.1);
        let pts = s.visible_points(&corners, &cam, 0.0, 0.1);
        for f in 0..faces {
            for p in corners.face_points(f) {
                let vx = s.mesh.triangles[f][match corners.bary[p] {
                    [1.0, _, _] => 0,
                    [_, 1.0, _] => 1,
                    _ => 2,
                }];
                let want = verts.iter().find(|v| v.vertex == vx);
                let got = pts.iter().find(|v| v.vertex == p as u32);
                assert_eq!(
                    want.map(|v| (v.u, v.v)),
                    got.map(|v| (v.u, v.v)),
                    "face {f}"
                );
            }
        }
        let fine = SurfacePoints::lattice(&s.mesh, &vec![4; faces]).unwrap();
        let seen: Vec<bool> = {
            let mut b = vec![false; fine.len()];
            for v in s.visible_points(&fine, &cam, 0.0, 0.1) {
                b[v.vertex as usize] = true;
            }
            b
        };
        let (mut hidden, mut shown) = (0, 0);
        for (p, &x) in fine.positions.iter().enumerate() {
            if fine.face[p] as usize == faces - 1 {
                assert!(seen[p], "the roof is seen");
            } else if x[0].abs() < 0.4 && x[1].abs() < 0.4 {
                assert!(!seen[p], "under the roof: {x:?}");
                hidden += 1;
            } else if x[0].abs() > 1.5 || x[1].abs() > 1.5 {
                assert!(seen[p], "outside the roof: {x:?}");
                shown += 1;
            }
        }
        assert!(hidden >= 9 && shown > 100, "{hidden} {shown}");
    }
}
