//! How much light Cycles' subsurface step gathers on this mesh, against how much the renderer
//! gathers: the geometry factor of the subsurface colour ([`super::ColourMode::Matched`]).
//!
//! Lit from the front (every source lit by a light along x_o's own normal, `cos = n_i · n_o`,
//! sources facing away dark), the renderer's exitance at x_o is
//! `B_front(x_o) = Σ_i R_d(x_i → x_o) A(x_i) max(0, n_i · n_o)` over the mesh (Euclidean
//! distances, the sources' own fall-offs, [`front_exitance`]). Cycles' Christensen–Burley step instead scales its
//! probe's weight by the albedo *at x_o* and finds the light by disk probes (King et al. 2013,
//! `intern/cycles/kernel/integrator/subsurface_disk.h`): on a plane it gathers exactly the
//! albedo, on a small or curved object more or less (probes that miss, hits far through the
//! object weighted by the ratio of the profile at the real distance to its density at the
//! disk's radius). [`disk_gain`] replays that step on the mesh — the three axes with their
//! probabilities 1/2, 1/4, 1/4, the radius drawn from one channel's truncated profile, every
//! hit along the probe with Cycles' power-heuristic weight, times the same front light at the
//! hit — with stratified samples instead of random ones, and returns the expected weight per
//! unit albedo. The matched colour is `B_front / gain`: lit from the front, Cycles' picture is
//! the renderer's, and on a flat homogeneous surface (gain 1, `B_front` the total diffuse
//! reflectance) it is the total diffuse reflectance itself.
//!
//! Why front light and not uniform light: Cycles weights a hit through the object by the profile
//! at the real distance over its density at the disk radius (`eval(r) / pdf(r')`, r' ≤ r), so on
//! an object no larger than the fall-off's reach it gathers much from the far side, which any
//! light that reaches x_o leaves dark. Matched under uniform light, the demo's 4 mm sphere
//! rendered 23 % too dark under its key light; matched under front light, within 1 %
//! (`docs/export.md`).

use rayon::prelude::*;

use super::cycles::{TRUNCATE, truncated_cdf};
use crate::geometry::{Scene, V3, add_scaled, cross, dot, normalize, sub};
use crate::modelfile::ModelFile;
use crate::progress::Progress;
use crate::render::{Falloffs, vertex_areas};

/// `B_front(x_o) = Σ_i R_d(x_i → x_o) A(x_i) max(0, n_i · n_o)`: the renderer's exitance when
/// every source is lit from x_o's own normal direction (a light in front of x_o; sources facing
/// away are dark), from the sources within [`Falloffs::cutoff`] of a 10⁻⁴ light share, plus x_o's
/// own area ([`Falloffs::disk_integral`], as the transport).
pub fn front_exitance(model: &ModelFile, progress: &dyn Progress) -> Vec<[f64; 3]> {
    let f = Falloffs::new(model);
    let n = model.len();
    let areas = vertex_areas(&model.positions, &model.triangles);
    let reach: Vec<f64> = (0..n).map(|i| f.cutoff(i, 1e-4)).collect();
    progress.start("front light", n as u64);
    (0..n)
        .into_par_iter()
        .map(|o| {
            progress.inc(1);
            let (xo, no) = (model.positions[o], model.normals[o]);
            let rho = (areas[o] / std::f64::consts::PI).sqrt();
            let mut b = if f.is_active(o) {
                f.disk_integral(o, rho)
            } else {
                [0.0; 3]
            };
            for i in 0..n {
                if i == o || !f.is_active(i) {
                    continue;
                }
                let c = dot(model.normals[i], no);
                if c <= 0.0 {
                    continue;
                }
                let r = crate::geometry::norm(sub(model.positions[i], xo));
                if r > reach[i] {
                    continue;
                }
                let l = f.ln_eval_mean(i, r);
                for k in 0..3 {
                    b[k] += l[k].exp() * areas[i] * c;
                }
            }
            b
        })
        .collect()
}

/// Stratified radii per axis and channel of [`disk_gain`].
pub const DISK_SAMPLES: usize = 48;

/// `bssrdf_burley_pdf`: the Burley profile as a density in r (`(e^{−r/d} + e^{−r/(3d)}) / (4d)`
/// over the truncated CDF), 0 at r = 0 and from 16 d on, as Cycles evaluates it.
fn burley_pdf(d: f64, r: f64) -> f64 {
    if r <= 0.0 || r >= TRUNCATE * d || d <= 0.0 {
        return 0.0;
    }
    let e3 = (-r / (3.0 * d)).exp();
    (e3 * e3 * e3 + e3) / (4.0 * d) / truncated_cdf()
}

/// The radius (in units of d) where the Burley CDF `1 − ¼e^{−x} − ¾e^{−x/3}` reaches `xi`
/// (`bssrdf_burley_root_find`, here by bisection in f64).
fn burley_root(xi: f64) -> f64 {
    let cdf = |x: f64| 1.0 - 0.25 * (-x).exp() - 0.75 * (-x / 3.0).exp();
    let (mut lo, mut hi) = (0.0, TRUNCATE);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if cdf(mid) < xi {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Cycles' `make_orthonormals`: two unit vectors completing `n` to a frame.
fn orthonormals(n: V3) -> (V3, V3) {
    let a = if n[0] != n[1] || n[0] != n[2] {
        [n[2] - n[1], n[0] - n[2], n[1] - n[0]]
    } else {
        [n[2] - n[1], n[0] + n[2], -n[1] - n[0]]
    };
    let a = normalize(a).unwrap_or([1.0, 0.0, 0.0]);
    let b = cross(n, a);
    (a, b)
}

/// Every hit of the segment `origin + t·dir`, `0 <= t <= t_max`, as `(point, triangle)`.
fn all_hits(scene: &Scene, origin: V3, dir: V3, t_max: f64, step: f64) -> Vec<(V3, u32)> {
    let mut out = Vec::new();
    let mut from = 0.0;
    while out.len() < 64 {
        let o = add_scaled(origin, from, dir);
        let Some(hit) = scene.cast(o, dir, t_max - from) else {
            break;
        };
        out.push((hit.point, hit.triangle));
        from += hit.t + step;
        if from >= t_max {
            break;
        }
    }
    out
}

/// +1 when triangle `t`'s vertex normals lean towards `n`, else −1 (the geometric normal's sign
/// is the winding's, the vertex normals say which side is out).
fn facing_sign(scene: &Scene, t: u32, n: V3) -> f64 {
    let Some(tri) = scene.mesh.triangles.get(t as usize) else {
        return -1.0;
    };
    let s: f64 = tri
        .iter()
        .map(|&v| dot(scene.mesh.normals[v as usize], n))
        .sum();
    if s > 0.0 { 1.0 } else { -1.0 }
}

/// The unit geometric normal of triangle `t`.
fn face_normal(scene: &Scene, t: u32) -> Option<V3> {
    let tri = scene.mesh.triangles.get(t as usize)?;
    let p = |k: usize| scene.mesh.positions[tri[k] as usize];
    normalize(cross(sub(p(1), p(0)), sub(p(2), p(0))))
}

/// The expected weight of Cycles' disk step per unit albedo at every vertex of `scene` (unit
/// vertex `normals`, the shading normals), per channel, for Burley shapes `d[v]` (mm, per
/// channel; Cycles takes the shading point's): 1 on a plane.
pub fn disk_gain(
    scene: &Scene,
    normals: &[[f64; 3]],
    d: &[[f64; 3]],
    progress: &dyn Progress,
) -> Vec<[f64; 3]> {
    let m = &scene.mesh;
    let step = 1e-7 * m.diagonal().max(1e-9);
    progress.start("Cycles' disk", m.positions.len() as u64);
    const GOLDEN: f64 = 0.618_033_988_749_894_9;
    (0..m.positions.len())
        .into_par_iter()
        .map(|v| {
            progress.inc(1);
            let dv = d[v];
            if !dv.iter().all(|x| *x > 0.0 && x.is_finite()) {
                return [1.0; 3];
            }
            let p = m.positions[v];
            let n = normals
                .get(v)
                .and_then(|&n| normalize(n))
                .unwrap_or([0.0, 0.0, 1.0]);
            let (t, b) = orthonormals(n);
            // (disk axis, its two tangents, pick pdfs of the three slots, probability).
            let axes = [
                (n, t, b, [0.5, 0.25, 0.25], 0.5),
                (t, n, b, [0.25, 0.5, 0.25], 0.25),
                (b, t, n, [0.25, 0.25, 0.5], 0.25),
            ];
            let mut gain = [0.0; 3];
            for (axis, dt, db, pick, p_axis) in axes {
                for &dk in &dv {
                    let rm = TRUNCATE * dk;
                    for s in 0..DISK_SAMPLES {
                        let xi = (s as f64 + 0.5) / DISK_SAMPLES as f64;
                        let r_disk = burley_root(xi * truncated_cdf()) * dk;
                        let phi = std::f64::consts::TAU * (0.5 + s as f64 * GOLDEN).fract();
                        let h = (rm * rm - r_disk * r_disk).max(0.0).sqrt();
                        let origin = add_scaled(
                            add_scaled(add_scaled(p, h, axis), r_disk * phi.cos(), dt),
                            r_disk * phi.sin(),
                            db,
                        );
                        let pdf_mix =
                            dv.iter().map(|&dd| burley_pdf(dd, r_disk)).sum::<f64>() / 3.0;
                        if pdf_mix <= 0.0 {
                            continue;
                        }
                        for (hit, tri) in all_hits(scene, origin, axis.map(|x| -x), 2.0 * h, step) {
                            let Some(ng) = face_normal(scene, tri) else {
                                continue;
                            };
                            let pn = pick[0] * dot(axis, ng).abs();
                            let pt = pick[1] * dot(dt, ng).abs();
                            let pb = pick[2] * dot(db, ng).abs();
                            let den = pn * pn + pt * pt + pb * pb;
                            if den <= 0.0 {
                                continue;
                            }
                            // Light from the vertex's own side: a hit facing away gets none.
                            let facing = dot(ng, n).abs() * facing_sign(scene, tri, n);
                            if facing <= 0.0 {
                                continue;
                            }
                            let w = pn / den * facing;
                            let r = crate::geometry::norm(sub(hit, p));
                            for c in 0..3 {
                                gain[c] +=
                                    p_axis / 3.0 / DISK_SAMPLES as f64 * w * burley_pdf(dv[c], r)
                                        / pdf_mix;
                            }
                        }
                    }
                }
            }
            gain
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::Mesh;

    fn plate(size: f64, n: usize) -> Scene {
        let mut p = Vec::new();
        let mut f = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                p.push([
                    size * (i as f64 / n as f64 - 0.5),
                    size * (j as f64 / n as f64 - 0.5),
                    0.0,
                ]);
            }
        }
        let w = (n + 1) as u32;
        for j in 0..n as u32 {
            for i in 0..n as u32 {
                let a = j * w + i;
                f.push([a, a + 1, a + w + 1]);
                f.push([a, a + w + 1, a + w]);
            }
        }
        let (mesh, _) = Mesh::new(p, f);
        Scene::new(mesh).unwrap()
    }

    /// On a plane much larger than the profile, Cycles' disk step gathers exactly the albedo;
    /// on a plane smaller than its reach, less.
    #[test]
    fn the_disk_step_gathers_the_albedo_on_a_plane() {
        let scene = plate(40.0, 8);
        let centre = scene.mesh.positions.len() / 2;
        let d = vec![[0.3, 0.5, 0.8]; scene.mesh.positions.len()];
        let up = vec![[0.0, 0.0, 1.0]; d.len()];
        let g = disk_gain(&scene, &up, &d, &());
        for c in 0..3 {
            assert!((g[centre][c] - 1.0).abs() < 0.01, "{:?}", g[centre]);
        }
        let small = plate(2.0, 4);
        let d = vec![[0.3, 0.5, 0.8]; small.mesh.positions.len()];
        let up = vec![[0.0, 0.0, 1.0]; d.len()];
        let g = disk_gain(&small, &up, &d, &());
        let c = small.mesh.positions.len() / 2;
        assert!(g[c][2] < g[c][0] && g[c][0] < 0.99, "{:?}", g[c]);
    }

    #[test]
    fn the_inverse_cdf_inverts() {
        for xi in [0.01, 0.3, 0.9, 0.99] {
            let x = burley_root(xi);
            let cdf = 1.0 - 0.25 * (-x).exp() - 0.75 * (-x / 3.0).exp();
            assert!((cdf - xi).abs() < 1e-12);
        }
    }
}
