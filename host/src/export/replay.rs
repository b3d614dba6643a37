//! Cycles' render of a scan frame with the exported material, computed in closed form: the
//! expectation of Cycles' Christensen-Burley disk step (`integrator/subsurface_disk.h`,
//! `closure/bssrdf.h` of Blender 4.0 to 5.0, and 3.4's with its exit factor), replayed on the
//! exported mesh with the exported attributes, the frame's camera and its laser spot.
//!
//! Why: a path tracer from the camera finds a laser spot half a pixel wide only when a disk
//! probe lands in it, so its frames are mostly grain (two seeds at 4,096 samples differ by more
//! than the conversion's own error: docs/export.md). What the export puts in front of a Cycles
//! user is the *expected* image, and that has a closed form: the conversion can then be judged
//! on every frame, without noise, by the same yardstick as the model — and the replay is itself
//! checked against Cycles' renders within their noise (`export-report.json`,
//! `replay_agreement_ring_log_e`).
//!
//! **What Cycles' disk step computes in expectation.** At the shading point P (where the camera
//! ray meets the mesh; geometric normal N_g, tangents T, B by Cycles' `make_orthonormals`), an
//! axis a ∈ {N, T, B} is picked with probability p = (½, ¼, ¼), a colour channel uniformly, a
//! disk radius r' from that channel's truncated Burley density, and every surface point x on the
//! probe's chord (within the sampled channel's `R_m = 16 d` of P) is weighted by
//! `eval(|x − P|) / pdf(r') · w_a`, with the power-heuristic weight
//! `w_a = p_a |n_x·a| / Σ_b (p_b |n_x·b|)²` (the disk densities left out: "cancelled"). Both
//! `eval` and `pdf` are *radial* densities (∫ dr = 1), where the disk's area density is
//! `pdf(r') / (2π r')`, so the estimator's expectation over the surface is
//!
//! `K(P, x) = Σ_a (p_a |n_x·a|)² / Σ_b (p_b |n_x·b|)² · eval(|x − P|) / (2π r_a) · ρ_a`,
//!
//! per unit area at x, with r_a = x's distance from P across axis a and ρ_a the share of the
//! disk density whose channel reaches x (`Σ_{c: 16 d_c > |x − P|} pdf_c(r_a) / Σ_c pdf_c(r_a)`).
//! On a plane, axis N alone sees x and r_a = |x − P|: `∫ K dA = 1`, the profile's
//! normalisation. On a curved surface r_a < |x − P|, and Cycles gathers more than the planar
//! profile would (a quarter more on the demo's sphere, docs/export.md): that is part of what
//! Cycles renders, so it is part of the replay.
//!
//! The light then arrives at x through a Lambertian lobe (its shading normal; 3.x also scales it
//! by `1 − ½ (1 − cos θ)⁵`), from the spot [`super::scene::laser_spot`] writes: a point
//! [`super::frames::STANDOFF_MM`] before x_i whose intensity falls as the cosine to its axis
//! inside a cone that lights the footprint. In the scan's units (the beam's power carries
//! `π · 10⁻⁶`, [`super::scene::beam_watts`]), the pixel is
//!
//! `L(P) = A(P) · Σ_j Φ_j K(P, x_j) · cos θ_s / cos θ_g`, with A the Base Color (the exported
//! colour × alpha × the exit Fresnel factor at P) and Φ_j the flux of the spot's ray j.
//!
//! Left out, each below the replay's use: Cycles' single precision, its pixel filter beyond the
//! box (the export sets a box one pixel wide; the replay averages 2 × 2 points per pixel), and
//! light bounced between surfaces (the scenes have a black world and one object).

use std::f64::consts::PI;

use super::frames::{FrameScene, FrameScenes, STANDOFF_MM};
use super::mesh::ExportMesh;
use crate::dataset::{Image, Mesh};
use crate::evaluate::images::{BoxError, MakeImage};
use crate::geometry::{
    Scene, V3, add_scaled, cross, dist, dot, normalize, sub, turntable_to_world, world_to_turntable,
};
use crate::pipeline::Context;

/// Cycles' `BURLEY_TRUNCATE`: the profile ends at 16 d.
const TRUNCATE: f64 = super::cycles::TRUNCATE;
/// The axis picks of the disk step: the normal half the time, each tangent a quarter.
const PICK: [f64; 3] = [0.5, 0.25, 0.25];
/// Rings and spokes of the laser cone's quadrature: the footprint is half a pixel, so this
/// resolves it far below what a pixel sees.
const CONE_RINGS: usize = 6;
const CONE_SPOKES: usize = 12;

/// Which Cycles: its kernel's differences that reach the replay.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Kernel {
    /// Blender 3.x: the Principled BSDF's diffuse exit lobe is Lambert times
    /// `1 − ½ (1 − cos θ)⁵` (`PRINCIPLED_DIFFUSE_LAMBERT_EXIT`).
    V3,
    /// Blender 4.0 on (Principled v2): a plain Lambertian exit (`subsurface_shader_data_setup`).
    #[default]
    V4,
}

impl Kernel {
    /// The kernel of Blender `(major, minor)`.
    pub fn of(version: (u32, u32)) -> Kernel {
        if version.0 >= 4 {
            Kernel::V4
        } else {
            Kernel::V3
        }
    }
}

/// Cycles' `bssrdf_burley_pdf` (which its `bssrdf_eval` returns per channel): the truncated
/// Burley profile as a radial density, `(e^{−r/d} + e^{−r/(3d)}) / (4d) / CDF(16)` — the area
/// profile [`super::cycles::ln_profile`] times `2π r` — for `0 < r < 16 d`, else 0.
pub fn burley_radial(d: f64, r: f64) -> f64 {
    if d.is_nan() || d <= 0.0 || r <= 0.0 || r >= TRUNCATE * d {
        return 0.0;
    }
    2.0 * PI * r * super::cycles::ln_profile(r, d).exp()
}

/// Cycles' `make_orthonormals`: the tangents of the disk frame around `n`.
pub fn orthonormals(n: V3) -> (V3, V3) {
    let a = if n[0] != n[1] || n[0] != n[2] {
        [n[2] - n[1], n[0] - n[2], n[1] - n[0]]
    } else {
        [n[2] - n[1], n[0] + n[2], -n[1] - n[0]]
    };
    let a = normalize(a).unwrap_or([1.0, 0.0, 0.0]);
    (a, cross(n, a))
}

/// The expected weight per unit area (1/mm²) with which Cycles' disk step at `p` (disk frame
/// `axes` = [N_g, T, B], world frame) gathers light arriving at the surface point `x` (geometric
/// normal `n_x`), per channel of Burley shapes `d` (mm; a channel with d ≤ 0 is not sampled).
/// See the module doc for the formula.
pub fn disk_kernel(p: V3, axes: [V3; 3], x: V3, n_x: V3, d: [f64; 3]) -> [f64; 3] {
    let off = sub(x, p);
    let r = dist(x, p);
    let q = [0, 1, 2].map(|a| PICK[a] * dot(n_x, axes[a]).abs());
    let s2: f64 = q.iter().map(|v| v * v).sum();
    let mut k = [0.0; 3];
    if s2.is_nan() || s2 <= 0.0 {
        return k;
    }
    let eval = d.map(|dc| burley_radial(dc, r));
    for a in 0..3 {
        if q[a] == 0.0 {
            continue;
        }
        let along = dot(off, axes[a]);
        let r_a = (r * r - along * along).max(0.0).sqrt();
        if r_a.is_nan() || r_a <= 0.0 {
            continue;
        }
        let pdfs = d.map(|dc| burley_radial(dc, r_a));
        let all: f64 = pdfs.iter().sum();
        if all.is_nan() || all <= 0.0 {
            continue;
        }
        let reach: f64 = (0..3)
            .filter(|&c| d[c] > 0.0 && r < TRUNCATE * d[c])
            .map(|c| pdfs[c])
            .sum::<f64>()
            / all;
        let w = q[a] * q[a] / s2 * reach / (2.0 * PI * r_a);
        for c in 0..3 {
            k[c] += w * eval[c];
        }
    }
    k
}

/// A point of the laser's footprint: where one of the spot's rays meets the mesh (object
/// frame), its geometric normal, and the flux it brings (in the scan's units) times the exit
/// lobe's shading factor.
#[derive(Clone, Copy, Debug)]
struct Lit {
    x: V3,
    n_g: V3,
    flux: f64,
}

/// Per channel, the exported attributes interpolated at a point of triangle `t` with weights `w`.
pub(super) fn lerp(values: &[[f64; 3]], t: [u32; 3], w: [f64; 3]) -> [f64; 3] {
    let mut out = [0.0; 3];
    for k in 0..3 {
        for (c, o) in out.iter_mut().enumerate() {
            *o += w[k] * values[t[k] as usize][c];
        }
    }
    out
}

/// The closed-form Cycles render of a scan's frames ([`MakeImage`]): judged like Cycles'
/// images, on the same samples and rings.
pub struct Replay<'a> {
    ctx: &'a Context<'a>,
    scenes: &'a FrameScenes,
    mesh: &'a ExportMesh,
    scene: Scene,
    exit_fresnel_ior: Option<f64>,
    kernel: Kernel,
}

impl std::fmt::Debug for Replay<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Replay")
            .field("frames", &self.scenes.frames.len())
            .field("kernel", &self.kernel)
            .finish()
    }
}

impl<'a> Replay<'a> {
    /// What the images are called in errors.
    pub const NAME: &'static str = "cycles-replay";

    /// The replay of `scenes` (written for the run `ctx`) with the exported `mesh` and exit
    /// Fresnel factor, in the Cycles `kernel`.
    pub fn new(
        ctx: &'a Context<'a>,
        scenes: &'a FrameScenes,
        mesh: &'a ExportMesh,
        exit_fresnel_ior: Option<f64>,
        kernel: Kernel,
    ) -> Result<Replay<'a>, super::ExportError> {
        let scene = Scene::new(Mesh {
            positions: mesh.positions.clone(),
            triangles: mesh.triangles.clone(),
            normals: mesh.normals.clone(),
        })
        .map_err(|e| super::ExportError::Invalid(format!("the exported mesh: {e}")))?;
        Ok(Replay {
            ctx,
            scenes,
            mesh,
            scene,
            exit_fresnel_ior,
            kernel,
        })
    }

    /// The spot's rays that meet the mesh, with their flux: the cone's solid angle in rings and
    /// spokes, each ray's share of the power `cos ψ dΩ` over the whole cone's (a ray that misses
    /// the object takes its share with it, as in Cycles).
    fn footprint(&self, s: &FrameScene) -> Vec<Lit> {
        let deg = s.turntable_deg;
        let Some(d) = normalize(s.laser_direction) else {
            return Vec::new();
        };
        let hit = turntable_to_world(s.x_i_mm, deg);
        let origin = add_scaled(hit, -STANDOFF_MM, d);
        let half = (s.footprint_mm / STANDOFF_MM).atan();
        let (e1, e2) = orthonormals(d);
        let flux_total = super::frames::LASER_POWER * s.exposure_s;
        let dpsi = half / CONE_RINGS as f64;
        let dphi = 2.0 * PI / CONE_SPOKES as f64;
        // ∫ cos ψ sin ψ dψ dφ over the cone: π sin² θ.
        let cone = PI * half.sin().powi(2);
        let mut out = Vec::new();
        for i in 0..CONE_RINGS {
            let psi = (i as f64 + 0.5) * dpsi;
            // The ring's exact share, so the rings sum to the cone's power.
            let (a, b) = (i as f64 * dpsi, (i + 1) as f64 * dpsi);
            let ring = PI * (b.sin().powi(2) - a.sin().powi(2)) / CONE_SPOKES as f64;
            for j in 0..CONE_SPOKES {
                let phi = (j as f64 + 0.5) * dphi;
                let (sp, cp) = psi.sin_cos();
                let dir =
                    [0, 1, 2].map(|k| cp * d[k] + sp * (phi.cos() * e1[k] + phi.sin() * e2[k]));
                let Some(h) = self.scene.cast_world(origin, dir, deg) else {
                    continue;
                };
                let (Some(n_g), Some(n_s)) = (
                    self.scene.face_normal(h.triangle),
                    self.scene.normal_at(h.triangle, h.point),
                ) else {
                    continue;
                };
                let to_light = world_to_turntable(dir.map(|v| -v), deg);
                let (cos_s, cos_g) = (dot(n_s, to_light), dot(n_g, to_light).abs());
                if !(cos_s > 0.0 && cos_g > 0.0) {
                    continue;
                }
                let exit = match self.kernel {
                    Kernel::V3 => 1.0 - 0.5 * (1.0 - cos_s).powi(5),
                    Kernel::V4 => 1.0,
                };
                out.push(Lit {
                    x: h.point,
                    n_g,
                    flux: flux_total * ring / cone * cos_s / cos_g * exit,
                });
            }
        }
        out
    }

    /// The expected radiance × exposure where the camera ray from `origin` along `dir` (world)
    /// meets the mesh, per channel; 0 where it misses.
    fn radiance(&self, origin: V3, dir: V3, deg: f64, lit: &[Lit]) -> [f64; 3] {
        let Some(h) = self.scene.cast_world(origin, dir, deg) else {
            return [0.0; 3];
        };
        let t = self.scene.mesh.triangles[h.triangle as usize];
        let w = self.scene.barycentric(h.triangle, h.point);
        let m = self.mesh;
        let Some(n_g) = self.scene.face_normal(h.triangle) else {
            return [0.0; 3];
        };
        // The disk frame in the world, where Cycles builds it.
        let n_w = turntable_to_world(n_g, deg);
        let (t_w, b_w) = orthonormals(n_w);
        let axes = [
            n_g,
            world_to_turntable(t_w, deg),
            world_to_turntable(b_w, deg),
        ];
        let fresnel = match self.exit_fresnel_ior {
            None => 1.0,
            Some(eta) => {
                let n_s = self.scene.normal_at(h.triangle, h.point).unwrap_or(n_g);
                let view = world_to_turntable(dir.map(|v| -v), deg);
                crate::render::relative_transmittance(eta, dot(n_s, view))
            }
        };
        let alpha = lerp(&m.alpha, t, w);
        let mut lobes = vec![(lerp(&m.colour, t, w), lerp(&m.radius_mm, t, w), 1.0)];
        if !m.slow_colour.is_empty() {
            let f = lerp(&m.slow_weight, t, w)[0];
            lobes[0].2 = 1.0 - f;
            lobes.push((lerp(&m.slow_colour, t, w), lerp(&m.slow_radius_mm, t, w), f));
        }
        let mut out = [0.0; 3];
        for (colour, radius, weight) in lobes {
            let d = radius.map(|r| r / super::cycles::RADIUS_PER_D);
            let mut k = [0.0; 3];
            for l in lit {
                let kk = disk_kernel(h.point, axes, l.x, l.n_g, d);
                for c in 0..3 {
                    k[c] += l.flux * kk[c];
                }
            }
            for c in 0..3 {
                out[c] += weight * colour[c] * alpha[c] * fresnel * k[c];
            }
        }
        out
    }
}

/// Replayed frames made once, in parallel, and kept ([`Replay::kept`]): several judges read
/// each image, and a replayed frame costs a path tracer's worth of ray casts.
pub struct Kept {
    images: Vec<(usize, Result<Image, String>)>,
}

impl MakeImage for Kept {
    fn make(&self, k: usize) -> Result<Image, BoxError> {
        match self.images.iter().find(|(f, _)| *f == k) {
            Some((_, Ok(img))) => Ok(img.clone()),
            Some((_, Err(e))) => Err(e.clone().into()),
            None => Err(format!("frame {k} was not replayed").into()),
        }
    }
}

impl Replay<'_> {
    /// Every frame of `frames` replayed now and kept.
    pub fn kept(&self, frames: &[usize]) -> Kept {
        use rayon::prelude::*;
        Kept {
            images: frames
                .par_iter()
                .map(|&k| (k, self.make(k).map_err(|e| e.to_string())))
                .collect(),
        }
    }
}

impl MakeImage for Replay<'_> {
    fn make(&self, k: usize) -> Result<Image, BoxError> {
        let s = self
            .scenes
            .frames
            .iter()
            .find(|s| s.frame == k)
            .ok_or_else(|| format!("frame {k} has no scene"))?;
        let f = self
            .ctx
            .ds
            .spec
            .frames
            .get(k)
            .ok_or_else(|| format!("frame {k} is not in the dataset"))?;
        let cam = self.ctx.camera(f.camera);
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut img = Image::new(w, h, 3);
        let lit = self.footprint(s);
        if lit.is_empty() {
            return Ok(img);
        }
        // The render border's pixels (Cycles leaves the rest black).
        let [x0, x1, y0, y1] = s.border.unwrap_or([0.0, 1.0, 0.0, 1.0]);
        let (wf, hf) = (w as f64, h as f64);
        let i0 = ((x0 * wf).floor() as usize).min(w);
        let i1 = ((x1 * wf).ceil() as usize).min(w);
        let j0 = (((1.0 - y1) * hf).floor() as usize).min(h);
        let j1 = (((1.0 - y0) * hf).ceil() as usize).min(h);
        let rows: Vec<(usize, Vec<[f64; 3]>)> = {
            use rayon::prelude::*;
            (j0..j1)
                .into_par_iter()
                .map(|j| {
                    let row = (i0..i1)
                        .map(|i| {
                            let mut sum = [0.0; 3];
                            // The box filter one pixel wide: 2 × 2 points of the pixel's area.
                            for (du, dv) in
                                [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)]
                            {
                                let Some((o, d)) = cam.ray(i as f64 + du, j as f64 + dv) else {
                                    continue;
                                };
                                let v = self.radiance(o, d, s.turntable_deg, &lit);
                                for c in 0..3 {
                                    sum[c] += 0.25 * v[c];
                                }
                            }
                            sum
                        })
                        .collect();
                    (j, row)
                })
                .collect()
        };
        for (j, row) in rows {
            for (n, v) in row.into_iter().enumerate() {
                let i = i0 + n;
                for (c, &vc) in v.iter().enumerate() {
                    let x = vc as f32;
                    img.data[(j * w + i) * 3 + c] = if x.is_finite() { x } else { 0.0 };
                }
            }
        }
        Ok(img)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a plane the disk step gathers the profile's whole light: ∫ K dA = 1 for every channel,
    /// whatever the orientation of the plane in the world (the tangent axes see nothing of it).
    #[test]
    fn on_a_plane_the_kernel_integrates_to_one() {
        let n = normalize([0.3, -0.2, 0.9]).unwrap();
        let (t, b) = orthonormals(n);
        let d = [0.2, 0.5, 1.0];
        let p = [1.0, 2.0, 3.0];
        // ∫ K 2π r dr over the plane, in ln r (the profile is e^{−r/d}/r near 0).
        let (lo, hi, steps) = (1e-6f64.ln(), 20.0f64.ln(), 4000);
        let h = (hi - lo) / steps as f64;
        let mut sum = [0.0; 3];
        for s in 0..steps {
            let r = (lo + (s as f64 + 0.5) * h).exp();
            // A point at distance r in the plane, along a direction between t and b.
            let x = add_scaled(add_scaled(p, r * 0.6, t), r * 0.8, b);
            let k = disk_kernel(p, [n, t, b], x, n, d);
            for c in 0..3 {
                sum[c] += k[c] * 2.0 * PI * r * r * h;
            }
        }
        for (c, s) in sum.iter().enumerate() {
            assert!((s - 1.0).abs() < 2e-3, "channel {c}: {s}");
        }
    }

    /// Where x lies off the plane of P (a curved surface), Cycles' projected disk radius is
    /// shorter than the distance and the gathered weight larger than the planar profile's.
    #[test]
    fn off_the_plane_cycles_gathers_more_than_the_profile() {
        let n = [0.0, 0.0, 1.0];
        let (t, b) = orthonormals(n);
        let d = [0.5; 3];
        // x 1 mm away across, 0.5 mm below, its normal tilted: a sphere's curvature.
        let x = [1.0, 0.0, -0.5];
        let n_x = normalize([0.5, 0.0, 1.0]).unwrap();
        let k = disk_kernel([0.0; 3], [n, t, b], x, n_x, d);
        let r = dist(x, [0.0; 3]);
        let planar = burley_radial(0.5, r) / (2.0 * PI * r);
        assert!(k[0] > planar, "{} against {planar}", k[0]);
        // Beyond every channel's 16 d nothing is gathered.
        let far = disk_kernel([0.0; 3], [n, t, b], [9.0, 0.0, 0.0], n, d);
        assert_eq!(far, [0.0; 3]);
    }

    /// The radial profile is a density: ∫_0^{16 d} dr = 1.
    #[test]
    fn the_truncated_profile_is_a_radial_density() {
        let d = 0.7;
        let steps = 200_000;
        let h = TRUNCATE * d / steps as f64;
        let s: f64 = (0..steps)
            .map(|i| burley_radial(d, (i as f64 + 0.5) * h) * h)
            .sum();
        assert!((s - 1.0).abs() < 1e-6, "{s}");
        assert_eq!(burley_radial(d, 16.0 * d), 0.0);
    }
}
