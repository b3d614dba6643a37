//! Built-in objects for simulated scans, in the object frame (sitting on the platter, `z >= 0`).
use crate::dataset::Mesh;

/// A built-in object.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum SimObject {
    /// The top face of a square slab at `z = 0` (the planar case of section 4): `n × n` vertices
    /// spaced `size / (n - 1)`.
    Slab {
        /// Edge length, mm.
        size: f64,
        /// Vertices per edge.
        n: usize,
    },
    /// A UV sphere resting on the platter.
    Sphere {
        /// Radius, mm.
        radius: f64,
        /// Rings from pole to pole (longitude segments are twice this).
        rings: usize,
    },
    /// A torus lying on the platter: non-convex, it occludes itself.
    Torus {
        /// Distance from the axis to the tube centre, mm.
        major: f64,
        /// Tube radius, mm.
        minor: f64,
        /// Segments around the tube (around the axis there are twice as many).
        segments: usize,
    },
    /// A pebble with no symmetry at all (no rotation about any axis and no mirror maps it onto
    /// itself): a star-shaped blob, egg-shaped along x with two skewed bulges, about
    /// `size × 0.67·size × 0.47·size`, resting on the platter. What `subsurf align` must place
    /// in a unique pose.
    Blob {
        /// Length along x, mm (roughly).
        size: f64,
        /// Rings from pole to pole of the underlying sphere (longitude segments are twice this).
        rings: usize,
    },
}

impl SimObject {
    /// Triangulates the object (counter-clockwise seen from outside).
    pub fn mesh(&self) -> Mesh {
        let (pos, tris) = match *self {
            SimObject::Slab { size, n } => slab(size, n.max(2)),
            SimObject::Sphere { radius, rings } => sphere(radius, rings.max(3)),
            SimObject::Torus {
                major,
                minor,
                segments,
            } => torus(major, minor, segments.max(3)),
            SimObject::Blob { size, rings } => blob(size, rings.max(3)),
        };
        Mesh::new(pos, tris).0
    }

    /// Centre and radius of a sphere that bounds the object.
    pub fn bounds(&self) -> ([f64; 3], f64) {
        match *self {
            SimObject::Slab { size, .. } => ([0.0; 3], size * std::f64::consts::FRAC_1_SQRT_2),
            SimObject::Sphere { radius, .. } => ([0.0, 0.0, radius], radius),
            SimObject::Torus { major, minor, .. } => ([0.0, 0.0, minor], major + minor),
            SimObject::Blob { size, rings } => {
                // Its box's centre and the farthest vertex from it (the shape has no closed form).
                let (pos, _) = blob(size, rings.max(3));
                let mut lo = [f64::INFINITY; 3];
                let mut hi = [f64::NEG_INFINITY; 3];
                for p in &pos {
                    for k in 0..3 {
                        lo[k] = lo[k].min(p[k]);
                        hi[k] = hi[k].max(p[k]);
                    }
                }
                let c: [f64; 3] = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
                let r = pos
                    .iter()
                    .map(|p| crate::geometry::dist(*p, c))
                    .fold(0.0, f64::max);
                (c, r)
            }
        }
    }
}

type Tris = (Vec<[f64; 3]>, Vec<[u32; 3]>);

fn slab(size: f64, n: usize) -> Tris {
    let step = size / (n - 1) as f64;
    let half = size / 2.0;
    let mut pos = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            pos.push([i as f64 * step - half, j as f64 * step - half, 0.0]);
        }
    }
    let mut tris = Vec::new();
    let n32 = n as u32;
    for j in 0..n32 - 1 {
        for i in 0..n32 - 1 {
            let a = j * n32 + i;
            tris.push([a, a + 1, a + n32 + 1]);
            tris.push([a, a + n32 + 1, a + n32]);
        }
    }
    (pos, tris)
}

fn sphere(r: f64, rings: usize) -> Tris {
    use std::f64::consts::PI;
    let seg = 2 * rings;
    let mut pos = vec![[0.0, 0.0, 2.0 * r]];
    for k in 1..rings {
        let th = PI * k as f64 / rings as f64;
        for s in 0..seg {
            let ph = 2.0 * PI * s as f64 / seg as f64;
            pos.push([
                r * th.sin() * ph.cos(),
                r * th.sin() * ph.sin(),
                r + r * th.cos(),
            ]);
        }
    }
    pos.push([0.0, 0.0, 0.0]);
    let bottom = (pos.len() - 1) as u32;
    let at = |k: usize, s: usize| (1 + (k - 1) * seg + s % seg) as u32;
    let mut tris = Vec::new();
    for s in 0..seg {
        tris.push([0, at(1, s), at(1, s + 1)]);
        tris.push([bottom, at(rings - 1, s + 1), at(rings - 1, s)]);
    }
    for k in 1..rings - 1 {
        for s in 0..seg {
            let (a, b, c, d) = (at(k, s), at(k, s + 1), at(k + 1, s), at(k + 1, s + 1));
            tris.push([a, c, d]);
            tris.push([a, d, b]);
        }
    }
    (pos, tris)
}

fn torus(big: f64, small: f64, segs: usize) -> Tris {
    use std::f64::consts::PI;
    let nu = 2 * segs;
    let nv = segs;
    let mut pos = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        let u = 2.0 * PI * i as f64 / nu as f64;
        for j in 0..nv {
            let v = 2.0 * PI * j as f64 / nv as f64;
            let rr = big + small * v.cos();
            pos.push([rr * u.cos(), rr * u.sin(), small + small * v.sin()]);
        }
    }
    let at = |i: usize, j: usize| ((i % nu) * nv + j % nv) as u32;
    let mut tris = Vec::new();
    for i in 0..nu {
        for j in 0..nv {
            let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
            tris.push([a, b, d]);
            tris.push([a, d, c]);
        }
    }
    (pos, tris)
}

/// The unit sphere of [`sphere`] pushed radially by `1 + Σ` low-order terms that share no
/// symmetry (a dipole along x makes the egg, the products of two axes skew it), then stretched
/// to `size × 0.67·size × 0.47·size` and set on the platter (lowest vertex at z = 0). The
/// terms sum to at most 0.57 in size, so the radius stays positive and the shape star-shaped
/// about its centre: every ray from it crosses the surface once, the mesh never folds.
fn blob(size: f64, rings: usize) -> Tris {
    let (unit, tris) = sphere(1.0, rings);
    let axes = [0.5 * size, 0.335 * size, 0.235 * size];
    let mut pos: Vec<[f64; 3]> = unit
        .iter()
        .map(|p| {
            // `sphere` rests on the platter: its centre is at z = r = 1.
            let d = [p[0], p[1], p[2] - 1.0];
            let r = 1.0 + 0.2 * d[0] + 0.15 * d[0] * d[1] - 0.12 * d[1] * d[2]
                + 0.1 * (d[1] * d[1] - d[2] * d[2]) * d[0];
            std::array::from_fn(|k| axes[k] * r * d[k])
        })
        .collect();
    let lowest = pos.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min);
    for p in &mut pos {
        p[2] -= lowest;
    }
    (pos, tris)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{dot, sub};

    #[test]
    fn normals_point_outwards_and_no_face_is_dropped() {
        for obj in [
            SimObject::Slab { size: 10.0, n: 5 },
            SimObject::Sphere {
                radius: 5.0,
                rings: 8,
            },
            SimObject::Torus {
                major: 6.0,
                minor: 2.0,
                segments: 8,
            },
            SimObject::Blob {
                size: 30.0,
                rings: 10,
            },
        ] {
            let (pos, tris) = match obj {
                SimObject::Slab { size, n } => slab(size, n),
                SimObject::Sphere { radius, rings } => sphere(radius, rings),
                SimObject::Torus {
                    major,
                    minor,
                    segments,
                } => torus(major, minor, segments),
                SimObject::Blob { size, rings } => blob(size, rings),
            };
            let (m, r) = Mesh::new(pos, tris.clone());
            assert_eq!(m.triangles.len(), tris.len(), "{obj:?} {r:?}");
            let (c, _) = obj.bounds();
            for (p, n) in m.positions.iter().zip(&m.normals) {
                match obj {
                    SimObject::Slab { .. } => assert!(n[2] > 0.99),
                    SimObject::Sphere { .. } | SimObject::Blob { .. } => {
                        assert!(dot(sub(*p, c), *n) > 0.0)
                    }
                    SimObject::Torus { major, .. } => {
                        let l = (p[0] * p[0] + p[1] * p[1]).sqrt();
                        let centre = [p[0] / l * major, p[1] / l * major, c[2]];
                        assert!(dot(sub(*p, centre), *n) > 0.0);
                    }
                }
            }
        }
    }
}
