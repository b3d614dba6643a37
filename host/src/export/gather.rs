//! How much light Cycles' disk step gathers at each vertex, against how much subsurf's renderer
//! gathers there, and the per-vertex colour factor that makes the two agree (`--gather`).
//!
//! Why: the two renderers integrate the same profile differently over a curved surface.
//! subsurf's renderer sums `R_d(|x_i − x_o|) E_i A_i` over the mesh with Euclidean distances.
//! Cycles' disk step weights each surface point its probes meet by the profile at the real
//! distance over the density at the *disk* radius, which is shorter on a curved surface, and
//! its probes also reach the far side of an object smaller than the profile's reach. Under
//! light from every side a vertex of the demo's 4 mm sphere gathers 0.88 of the profile's
//! planar total in subsurf and 1.12 in Cycles: Cycles' picture is a quarter brighter than the
//! truth. On a plane, or wherever the surface is flat on the profile's scale, both gather the
//! profile's total and the factor is 1.
//!
//! **The measure.** Both renderers under the same reference light, a unit irradiance at every
//! surface point (light from every side, so the factor belongs to the material and the shape,
//! not to one scene's lights):
//! - subsurf: `G_s(x_o) = Σ_i R_d(x_i → x_o) A_i`, the renderer's own transport
//!   ([`crate::render::Transport`]) with `E = 1`;
//! - Cycles: `G_c(P)`, the expectation of its disk step per unit Base Color with `E = 1`,
//!   computed by quadrature over the step's own random choices (axis, channel, disk radius in
//!   its inverse CDF, angle), every probe cast through the mesh and every hit weighted as
//!   `integrator/subsurface_disk.h` weights it ([`super::replay::disk_kernel`]'s terms, here
//!   sampled where the kernel has its singularities rather than summed over vertices);
//! - the factor `g = G_s / (T · G_c)`, T the vertex's planar total (what both would gather on
//!   a plane), multiplies every lobe's colour. It keeps the colour rule's own choice on flat
//!   ground (`fitted` is not T on purpose) and takes out only the renderers' difference in
//!   gathering.
//!
//! The uniform reference leaves out how one scene distributes its light (under a key light the
//! lit side gathers less from the dark side than under light from everywhere) and the two
//! renderers' light-side difference (subsurf's Fresnel transmittance at entry, Cycles' plain
//! Lambertian lobe): [`Reference::Lights`] measures under the scene's own lights instead, so
//! both are in the factor, for that scene. On the demo (docs/export.md) Cycles against the
//! truth is 22.9 % without a factor, 8.5 % with the uniform one and 7.1 % with the lights' one
//! at 128 samples (noise 6.3 %); 6.1 % and 4.3 % at 512 (noise 2.7 %).

use std::f64::consts::PI;

use rayon::prelude::*;

use super::convert::VertexConversion;
use super::cycles::{RADIUS_PER_D, TRUNCATE, truncated_cdf};
use super::replay::{burley_radial, lerp, orthonormals};
use crate::dataset::Mesh;
use crate::geometry::{Scene, V3, add_scaled, dist, dot};
use crate::modelfile::ModelFile;
use crate::progress::Progress;
use crate::render::{Falloffs, Light, Transport, irradiance, shadow_scene, vertex_areas};

/// The axis picks of the disk step: the normal half the time, each tangent a quarter.
const PICK: [f64; 3] = [0.5, 0.25, 0.25];

/// Cycles' `BSSRDF_MIN_RADIUS`: a channel with a smaller radius is a diffuse BSDF, not sampled.
const MIN_RADIUS: f64 = 1e-8;

/// The quadrature of the disk step's expectation: disk radii (midpoints in the truncated CDF)
/// and angles per axis and channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Quadrature {
    /// Disk radii, equal steps of the truncated Burley CDF.
    pub radii: usize,
    /// Angles around the axis.
    pub angles: usize,
}

impl Default for Quadrature {
    /// 16 × 8 per axis and channel (1,152 probes per vertex): on a 4 mm sphere within 1 % of
    /// 32 × 16 (the test `the_quadrature_has_converged_on_a_sphere`).
    fn default() -> Self {
        Quadrature {
            radii: 16,
            angles: 8,
        }
    }
}

/// `x` with `1 − ¼ e^{−x} − ¾ e^{−x/3} = u` (the Burley CDF in units of d), by bisection: the
/// CDF is monotone, and 60 halvings of [0, 16] are below f64's resolution.
fn burley_inverse_cdf(u: f64) -> f64 {
    let cdf = |x: f64| 1.0 - 0.25 * (-x).exp() - 0.75 * (-x / 3.0).exp();
    let (mut lo, mut hi) = (0.0, TRUNCATE);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if cdf(mid) < u {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Every hit of the segment `origin + t·dir`, `0 ≤ t ≤ t_max`, with the mesh (`dir` unit).
fn hits(scene: &Scene, origin: V3, dir: V3, t_max: f64, out: &mut Vec<(V3, u32)>) {
    out.clear();
    let step = 1e-7 * t_max.max(1e-6);
    let mut t0 = 0.0;
    // A probe crosses a closed mesh an even number of times; 16 is far beyond any object here.
    for _ in 0..16 {
        let o = add_scaled(origin, t0, dir);
        let Some(h) = scene.cast_strict(o, dir, t_max - t0) else {
            return;
        };
        out.push((h.point, h.triangle));
        t0 += h.t + step;
        if t0 >= t_max {
            return;
        }
    }
}

/// `G_c` per vertex and channel: the expectation of Cycles' Christensen-Burley disk step at each
/// vertex `P` (disk frame from its normal) per unit Base Color, the light arriving at the hit
/// points as `irradiance` (per vertex, interpolated over the hit triangle), for Burley shapes
/// `d` (mm) per vertex. On a plane with unit irradiance it is 1 in every channel.
pub fn cycles_gather(
    scene: &Scene,
    d: &[[f64; 3]],
    irradiance: &[&[[f64; 3]]],
    q: Quadrature,
    progress: &dyn Progress,
) -> Vec<Vec<[f64; 3]>> {
    let mesh = &scene.mesh;
    let n = mesh.positions.len();
    progress.set_length(n as u64);
    let (x, trig) = nodes(q);
    (0..n)
        .into_par_iter()
        .map_init(Vec::new, |buf, i| {
            let g = gather_one(scene, d, irradiance, i, &x, &trig, buf);
            progress.inc(1);
            g
        })
        .collect()
}

/// The quadrature's nodes: disk radii per unit `d` (midpoints of equal steps of the truncated
/// CDF) and the angles' `(sin, cos)`.
fn nodes(q: Quadrature) -> (Vec<f64>, Vec<(f64, f64)>) {
    let cdf16 = truncated_cdf();
    let x = (0..q.radii)
        .map(|k| burley_inverse_cdf((k as f64 + 0.5) / q.radii as f64 * cdf16))
        .collect();
    let trig = (0..q.angles)
        .map(|j| (2.0 * PI * (j as f64 + 0.5) / q.angles as f64).sin_cos())
        .collect();
    (x, trig)
}

fn gather_one(
    scene: &Scene,
    d: &[[f64; 3]],
    irradiance: &[&[[f64; 3]]],
    i: usize,
    x: &[f64],
    trig: &[(f64, f64)],
    buf: &mut Vec<(V3, u32)>,
) -> Vec<[f64; 3]> {
    let mesh = &scene.mesh;
    let p = mesh.positions[i];
    let dv = d[i];
    let sampled: Vec<usize> = (0..3)
        .filter(|&c| dv[c] * RADIUS_PER_D >= MIN_RADIUS)
        .collect();
    let mut g = vec![[0.0; 3]; irradiance.len()];
    if sampled.is_empty() {
        return g;
    }
    let nc = sampled.len() as f64;
    let nrm = mesh.normals[i];
    let (t, b) = orthonormals(nrm);
    let axes = [nrm, t, b];
    let per_probe = 1.0 / (nc * x.len() as f64 * trig.len() as f64);
    for a in 0..3 {
        let (u, v) = (axes[(a + 1) % 3], axes[(a + 2) % 3]);
        for &c in &sampled {
            let rm = TRUNCATE * dv[c];
            for &xk in x {
                let r_disk = xk * dv[c];
                let h = (rm * rm - r_disk * r_disk).max(0.0).sqrt();
                // The disk density at r': the channels' radial densities averaged.
                let pdf = sampled
                    .iter()
                    .map(|&c2| burley_radial(dv[c2], r_disk))
                    .sum::<f64>()
                    / nc;
                if pdf.is_nan() || pdf <= 0.0 {
                    continue;
                }
                for &(s, co) in trig {
                    let disk = [0, 1, 2].map(|k| r_disk * (co * u[k] + s * v[k]));
                    let origin = [0, 1, 2].map(|k| p[k] + h * axes[a][k] + disk[k]);
                    let dir = axes[a].map(|w| -w);
                    hits(scene, origin, dir, 2.0 * h, buf);
                    for &(hp, tri) in buf.iter() {
                        let Some(nh) = scene.face_normal(tri) else {
                            continue;
                        };
                        let pd = [0, 1, 2].map(|k| PICK[k] * dot(nh, axes[k]).abs());
                        let s2: f64 = pd.iter().map(|v| v * v).sum();
                        if s2.is_nan() || s2 <= 0.0 {
                            continue;
                        }
                        let w = pd[a] / s2 * PICK[a];
                        let r = dist(hp, p);
                        let k = [0, 1, 2].map(|ch| burley_radial(dv[ch], r) / pdf * w * per_probe);
                        for (gf, field) in g.iter_mut().zip(irradiance) {
                            let e = lerp(
                                field,
                                scene.mesh.triangles[tri as usize],
                                scene.barycentric(tri, hp),
                            );
                            for ch in 0..3 {
                                gf[ch] += k[ch] * e[ch];
                            }
                        }
                    }
                }
            }
        }
    }
    g
}

/// The light both renderers gather under when the factor is measured.
#[derive(Clone, Copy, Debug)]
pub enum Reference<'a> {
    /// A unit irradiance at every surface point.
    Uniform,
    /// The scene's lights, as each renderer lights the surface (subsurf with its light-side
    /// Fresnel factor of relative index `eta`, Cycles' 4.x kernel with a Lambertian lobe);
    /// where a vertex gathers less than [`DARK`] of the brightest, the uniform factor, and
    /// elsewhere held within [`SCENE_RANGE`] of it. Cycles 3.x's light-side lobe
    /// (`1 − ½ (1 − cos θ)⁵`, 0.98 at 60°) is not in it.
    Lights(&'a [Light], Option<f64>),
}

/// Below this share of the brightest vertex's gather a scene factor is a ratio of two small
/// numbers, decided by how the scene's light falls rather than by the material: the uniform
/// factor is used there.
pub const DARK: f64 = 0.01;

/// A scene factor is held within this ratio of the uniform one either way: beyond it (a vertex
/// in shadow lit only through the material from a bright neighbour with other parameters) it
/// would say more about where the light falls than about how the renderers gather, and a colour
/// scaled tenfold for one scene is wrong for any other.
pub const SCENE_RANGE: f64 = 2.0;

/// What the gathering did, for the report.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct GatherSummary {
    /// The reference light: `uniform` or `lights`.
    pub reference: &'static str,
    /// Probes per vertex, axis and channel: `[radii, angles]`.
    pub quadrature: [usize; 2],
    /// Vertices whose colour was scaled.
    pub vertices: usize,
    /// Channels whose scene factor was held to [`SCENE_RANGE`] of the uniform one.
    pub clamped: usize,
    /// The factor's median, 5th and 95th percentile over those vertices and channels.
    pub factor: [f64; 3],
    /// Median over vertices of Cycles' gather `G_c` and of subsurf's `G_s / T` under uniform
    /// light (green).
    pub median_gather: [f64; 2],
}

/// Multiplies each vertex's colours (both lobes) by `g = G_s / (T · G_c)` (see the module doc)
/// and says what it did. Vertices without a model of their own, or where a factor is not
/// finite and positive, keep their colour.
pub fn correct(
    model: &ModelFile,
    vertices: &mut [VertexConversion],
    totals: &[Option<[f64; 3]>],
    reference: Reference<'_>,
    q: Quadrature,
    progress: &dyn Progress,
) -> Result<GatherSummary, super::ExportError> {
    let (mesh, _) = Mesh::new(model.positions.clone(), model.triangles.clone());
    let scene = Scene::new(mesh)
        .map_err(|e| super::ExportError::Invalid(format!("the model's mesh: {e}")))?;
    let n = model.len();
    let ones = vec![[1.0; 3]; n];
    // The irradiance each renderer sees: uniform first, then (for `Lights`) the scene's, as
    // subsurf and as Cycles light the surface.
    let mut e_s = vec![ones.clone()];
    let mut e_c = vec![ones];
    if let Reference::Lights(lights, eta) = reference {
        let shadows = shadow_scene(&model.positions, &model.triangles)?;
        let at = |eta| irradiance(&model.positions, &model.normals, lights, &shadows, eta);
        e_s.push(at(eta));
        e_c.push(at(None));
    }
    let falloffs = Falloffs::new(model);
    let areas = vertex_areas(&model.positions, &model.triangles);
    // The exact sum is O(N²) but about a fifth of this step on a 6,162-vertex model (2.3 of
    // 12.8 s), the Cycles-side gather below the rest: the hierarchical sum would save little and
    // add its own error to the correction.
    let all: Vec<usize> = (0..n).collect();
    let g_s: Vec<Vec<[f64; 3]>> = e_s
        .iter()
        .map(|e| Transport::new(&model.positions, &model.normals, &falloffs, e, &areas).exact(&all))
        .collect();
    let fields: Vec<&[[f64; 3]]> = e_c.iter().map(Vec::as_slice).collect();
    // One lobe's gather per vertex; a second lobe's with its own shape.
    let d_near: Vec<[f64; 3]> = vertices
        .iter()
        .map(|v| v.radius_mm.map(|r| r / RADIUS_PER_D))
        .collect();
    let g_near = cycles_gather(&scene, &d_near, &fields, q, progress);
    let g_slow = if vertices.iter().any(|v| v.slow.is_some()) {
        let d_slow: Vec<[f64; 3]> = vertices
            .iter()
            .map(|v| {
                v.slow
                    .map_or(v.radius_mm, |s| s.radius_mm)
                    .map(|r| r / RADIUS_PER_D)
            })
            .collect();
        Some(cycles_gather(&scene, &d_slow, &fields, q, &()))
    } else {
        None
    };
    let lights = matches!(reference, Reference::Lights(..));
    // The brightest vertex's gather under the scene's lights, for the `DARK` test.
    let bright = g_s
        .get(1)
        .into_iter()
        .flatten()
        .flat_map(|g| g.iter().copied())
        .filter(|x| x.is_finite())
        .fold(0.0, f64::max);
    let mut factors = Vec::new();
    let mut gc_green = Vec::new();
    let mut gs_green = Vec::new();
    let mut count = 0;
    let mut clamped = 0;
    for (i, v) in vertices.iter_mut().enumerate() {
        let (Some(t), true) = (
            totals.get(i).copied().flatten(),
            matches!(
                v.source,
                super::Source::Fitted | super::Source::Interpolated
            ),
        ) else {
            continue;
        };
        // Cycles' gather of the vertex's light as exported: the lobes' colours weighted by
        // their mix and their own gathers, over the same without the gathers.
        let factor = |f: usize, c: usize| -> f64 {
            let (cycles, plane) = match (v.slow, &g_slow) {
                (Some(s), Some(gs)) => {
                    let near = (1.0 - s.weight) * v.colour[c];
                    let slow = s.weight * s.colour[c];
                    (near * g_near[i][f][c] + slow * gs[i][f][c], near + slow)
                }
                _ => (v.colour[c] * g_near[i][f][c], v.colour[c]),
            };
            g_s[f][i][c] / (t[c] * cycles / plane)
        };
        let mut f = [1.0; 3];
        let mut ok = true;
        for c in 0..3 {
            let k = factor(0, c);
            if !(k.is_finite() && k > 0.0) {
                ok = false;
                break;
            }
            f[c] = k;
            if lights && g_s[1][i][c] > DARK * bright {
                let kl = factor(1, c);
                if kl.is_finite() && kl > 0.0 {
                    let held = kl.clamp(k / SCENE_RANGE, k * SCENE_RANGE);
                    clamped += usize::from(held != kl);
                    f[c] = held;
                }
            }
        }
        if !ok {
            continue;
        }
        count += 1;
        gc_green.push(g_near[i][0][1]);
        gs_green.push(g_s[0][i][1] / t[1]);
        factors.extend(f);
        v.colour.iter_mut().zip(f).for_each(|(c, k)| *c *= k);
        if let Some(s) = v.slow.as_mut() {
            s.colour.iter_mut().zip(f).for_each(|(c, k)| *c *= k);
        }
    }
    for xs in [&mut factors, &mut gc_green, &mut gs_green] {
        xs.sort_by(f64::total_cmp);
    }
    let pct = |xs: &[f64], p: f64| -> f64 {
        if xs.is_empty() {
            return 1.0;
        }
        xs[((xs.len() - 1) as f64 * p).round() as usize]
    };
    Ok(GatherSummary {
        reference: if lights { "lights" } else { "uniform" },
        quadrature: [q.radii, q.angles],
        vertices: count,
        clamped,
        factor: [pct(&factors, 0.5), pct(&factors, 0.05), pct(&factors, 0.95)],
        median_gather: [pct(&gc_green, 0.5), pct(&gs_green, 0.5)],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::shapes;

    fn sphere_scene(radius: f64) -> Scene {
        Scene::new(shapes::icosphere(radius, 5)).unwrap()
    }

    /// The inverse CDF inverts the CDF.
    #[test]
    fn the_inverse_cdf_inverts() {
        for u in [0.01, 0.3, 0.5, 0.9, 0.99] {
            let x = burley_inverse_cdf(u);
            let back = 1.0 - 0.25 * (-x).exp() - 0.75 * (-x / 3.0).exp();
            assert!((back - u).abs() < 1e-12, "{u} {x} {back}");
        }
    }

    /// On a sphere far larger than the profile's reach the disk step gathers the profile's
    /// planar total (the plane's normalisation), and on one no larger than the reach it gathers
    /// more: the two ends of what the factor corrects.
    #[test]
    fn a_large_sphere_gathers_the_planar_total_and_a_small_one_more() {
        let big = sphere_scene(50.0);
        let d = vec![[0.2; 3]; big.mesh.positions.len()];
        let ones = vec![[1.0; 3]; big.mesh.positions.len()];
        let q = Quadrature::default();
        let g = gather_one_at(&big, &d, &ones, q, 100);
        assert!((g - 1.0).abs() < 0.02, "large sphere: {g}");
        let small = sphere_scene(4.0);
        let d = vec![[1.2; 3]; small.mesh.positions.len()];
        let ones = vec![[1.0; 3]; small.mesh.positions.len()];
        let g = gather_one_at(&small, &d, &ones, q, 100);
        assert!(g > 1.1, "small sphere: {g}");
    }

    /// Finer quadrature moves the gather on a small sphere by less than 1 %.
    #[test]
    fn the_quadrature_has_converged_on_a_sphere() {
        let s = sphere_scene(4.0);
        let d = vec![[1.2, 0.8, 0.5]; s.mesh.positions.len()];
        let ones = vec![[1.0; 3]; s.mesh.positions.len()];
        let coarse = gather_one_at(&s, &d, &ones, Quadrature::default(), 200);
        let fine = gather_one_at(
            &s,
            &d,
            &ones,
            Quadrature {
                radii: 32,
                angles: 16,
            },
            200,
        );
        assert!((coarse / fine - 1.0).abs() < 0.01, "{coarse} {fine}");
    }

    /// A coarse quadrature: the tests check the factor's sense and size, not its last digit.
    const TEST_Q: Quadrature = Quadrature {
        radii: 8,
        angles: 4,
    };

    /// The factor each vertex's green colour got from [`correct`] with the rule `Total`.
    fn factors(model: &ModelFile, reference: Reference<'_>) -> (Vec<f64>, GatherSummary) {
        let before = super::super::convert::convert(model, &());
        let mut after = before.clone();
        let totals = super::super::convert::totals(model);
        let s = correct(model, &mut after, &totals, reference, TEST_Q, &()).unwrap();
        let f = before
            .iter()
            .zip(&after)
            .map(|(b, a)| a.colour[1] / b.colour[1])
            .collect();
        (f, s)
    }

    /// On flat ground both renderers gather the profile's planar total: in the middle of a
    /// plate ten reaches wide the factor is 1.
    #[test]
    fn on_a_plate_the_factor_is_one_away_from_its_edges() {
        let n = 41u32;
        let mut p = Vec::new();
        let mut f = Vec::new();
        for j in 0..n {
            for i in 0..n {
                p.push([i as f64 * 0.25, j as f64 * 0.25, 0.0]);
            }
        }
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = j * n + i;
                f.push([a, a + 1, a + n + 1]);
                f.push([a, a + n + 1, a + n]);
            }
        }
        let count = p.len();
        let m = ModelFile::homogeneous(
            p,
            vec![[0.0, 0.0, 1.0]; count],
            f,
            [0.8, 0.5],
            &[(0.5, -4.0)],
        );
        let (k, s) = factors(&m, Reference::Uniform);
        let mid = (n / 2 * n + n / 2) as usize;
        assert!((k[mid] - 1.0).abs() < 0.03, "{} {s:?}", k[mid]);
    }

    /// On a sphere no larger than the profile's reach subsurf's renderer gathers less than
    /// Cycles' disk step (0.69 against 0.85 of the planar total here): every factor is below 1.
    /// Under a light from one side the factor is measured under that light.
    #[test]
    fn on_a_small_sphere_the_factor_darkens() {
        let mesh = shapes::icosphere(4.0, 3);
        let m = ModelFile::homogeneous(
            mesh.positions.clone(),
            mesh.normals.clone(),
            mesh.triangles.clone(),
            [0.8, 0.5],
            &[(0.01, -0.3)],
        );
        let (uniform, s) = factors(&m, Reference::Uniform);
        assert_eq!(s.vertices, m.len(), "{s:?}");
        assert!(uniform.iter().all(|&k| k > 0.3 && k < 0.97), "{s:?}");
        let light = [Light::Point {
            position: [0.0, 0.0, 40.0],
            intensity: [1600.0; 3],
        }];
        let (lit, s) = factors(&m, Reference::Lights(&light, Some(1.3)));
        assert_eq!(s.reference, "lights");
        assert!(lit.iter().all(|k| k.is_finite() && *k > 0.0));
        let near = (0..m.len())
            .max_by(|&a, &b| m.positions[a][2].total_cmp(&m.positions[b][2]))
            .unwrap();
        assert!(
            lit[near] != uniform[near] && lit[near] < 1.0,
            "{}",
            lit[near]
        );
    }

    fn gather_one_at(s: &Scene, d: &[[f64; 3]], e: &[[f64; 3]], q: Quadrature, i: usize) -> f64 {
        let (x, trig) = nodes(q);
        gather_one(s, d, &[e], i, &x, &trig, &mut Vec::new())[0][1]
    }
}
