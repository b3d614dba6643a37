//! A rough dielectric boundary: the medium's surface as GGX (Trowbridge-Reitz) microfacets
//! between the medium's index of refraction inside and air outside, and the light tracer's
//! photons through it.
//!
//! The BSDF is Walter, Marschner, Li and Torrance's (2007) microfacet dielectric with Smith's
//! separable shadowing-masking G = G1(ω_i) G1(ω_o), the exact unpolarised Fresnel reflectance of
//! a dielectric at the microfacet, and sampling of the visible normals (Heitz 2018) with the
//! reflection or refraction chosen by Fresnel: the same model, convention and sampler as
//! Mitsuba 3's `roughdielectric` with `distribution: ggx` and one `alpha` (the GGX width α,
//! not a "roughness" that is squared first), which `tests/volume_dielectric.rs` checks value by value.
//!
//! Directions are in the surface's local frame, the normal +z pointing outside (into air), and
//! both point away from the surface. `wi` is the direction the path came from, `wo` the one it
//! goes on to, as in Mitsuba. The two transport modes differ in refraction only: radiance
//! crossing into a denser medium is compressed into a smaller solid angle, so a camera-side
//! path's BTDF carries the factor (η_i/η_o)² ([`Transport::Radiance`]), while the power a light
//! tracer carries (importance's adjoint) does not ([`Transport::Importance`]); the importance
//! BTDF is the radiance BTDF with its arguments swapped (Veach 1997, ch. 5; PBRT v4's
//! non-symmetric scattering). The light tracer samples and evaluates in importance mode.
//!
//! With a dielectric boundary the camera cannot be reached from a point in the medium by a
//! straight line (it would refract on the way out), so the next events go from the surface:
//! wherever a photon meets the boundary (from inside, and where the laser enters), its light
//! is sent to the pinhole through the BSDF towards the camera, if the straight line from there
//! to the camera leaves the mesh for good. Collisions in the medium only scatter. The records
//! keep their meaning (collisions k and medium length L), so the likelihood ratios of
//! [`Record::ln_w_in`] still give every nearby medium: the surface's events do not depend on
//! σ_t or α.

use super::medium::{GridChannel, add_to};
use super::trace::{
    Boundary, FILTER_RADIUS_PX, FrameGeometry, MAX_COLLISIONS, Record, TraceSettings, crossings,
    frame_of, next_hit, photon_seed, sample_hg,
};
use crate::geometry::{
    Camera, Scene, V3, add_scaled, cross, dist, dot, normalize, sub, turntable_to_world,
    world_to_turntable,
};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use std::f64::consts::PI;

/// Surface events after which a photon is given up (internal reflections that never end).
const MAX_SURFACE_EVENTS: u32 = 10_000;

/// Tentative collisions (real and, in a grid, null ones) after which a photon is given up.
const MAX_TENTATIVE: u32 = 200_000;

/// What happens to light where it meets the mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Surface {
    /// No refraction and no reflection: a photon leaves along its straight line and re-enters
    /// where that line meets the mesh again (a `null` boundary).
    IndexMatched,
    /// A rough dielectric, air outside ([`RoughDielectric`]).
    RoughDielectric {
        /// Index of refraction of the medium inside (outside 1).
        ior: f64,
        /// GGX width α of the microfacet normals (Mitsuba's `alpha`).
        alpha: f64,
    },
}

/// Which quantity a path carries through a refraction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    /// Radiance, traced from the camera: the BTDF carries (η_i/η_o)².
    Radiance,
    /// Importance's adjoint, the power traced from the light: no η² factor.
    Importance,
}

/// The exact unpolarised Fresnel reflectance of a dielectric and the refracted cosine.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fresnel {
    /// Reflectance (1 under total internal reflection).
    pub r: f64,
    /// Cosine of the refracted direction with the normal, signed opposite to the incident one.
    pub cos_t: f64,
    /// Relative index of refraction η_t / η_i across the crossing.
    pub eta_it: f64,
    /// Its inverse η_i / η_t.
    pub eta_ti: f64,
}

/// Fresnel at incidence cosine `cos_i` (positive: from outside) on an interface of relative
/// index `eta` (inside over outside).
pub fn fresnel(cos_i: f64, eta: f64) -> Fresnel {
    let (eta_it, eta_ti) = if cos_i >= 0.0 {
        (eta, 1.0 / eta)
    } else {
        (1.0 / eta, eta)
    };
    let cos_t2 = 1.0 - (1.0 - cos_i * cos_i) * eta_ti * eta_ti;
    let ci = cos_i.abs();
    let ct = cos_t2.max(0.0).sqrt();
    let r = if eta == 1.0 {
        0.0
    } else if ci == 0.0 {
        1.0
    } else {
        let a_s = (ci - eta_it * ct) / (ci + eta_it * ct);
        let a_p = (ct - eta_it * ci) / (ct + eta_it * ci);
        0.5 * (a_s * a_s + a_p * a_p)
    };
    Fresnel {
        r,
        cos_t: if cos_i >= 0.0 { -ct } else { ct },
        eta_it,
        eta_ti,
    }
}

/// One sampled direction of the BSDF.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BsdfSample {
    /// The direction sampled (local frame).
    pub wo: V3,
    /// BSDF · |cos θ_o| / pdf in the transport mode asked for.
    pub weight: f64,
    /// Its probability density per solid angle.
    pub pdf: f64,
    /// Reflected (same side as `wi`) rather than refracted.
    pub reflected: bool,
}

/// A GGX rough dielectric between a medium of relative index `eta` (below, local z < 0) and
/// the outside (above).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoughDielectric {
    /// Index inside over index outside.
    pub eta: f64,
    /// GGX width α.
    pub alpha: f64,
}

impl RoughDielectric {
    /// The GGX distribution of microfacet normals D(m), 1/sr (∫ D cos θ_m dω = 1).
    pub fn d(&self, m: V3) -> f64 {
        if m[2] <= 0.0 {
            return 0.0;
        }
        let a2 = self.alpha * self.alpha;
        let t = (m[0] * m[0] + m[1] * m[1]) / a2 + m[2] * m[2];
        let d = 1.0 / (PI * a2 * t * t);
        if d * m[2] > 1e-20 { d } else { 0.0 }
    }

    /// Smith's masking of microfacet `m` seen from `v`: 0 when `v` sees the facet's back.
    pub fn g1(&self, v: V3, m: V3) -> f64 {
        if dot(v, m) * v[2] <= 0.0 {
            return 0.0;
        }
        let xy = self.alpha * self.alpha * (v[0] * v[0] + v[1] * v[1]);
        if xy == 0.0 {
            return 1.0;
        }
        2.0 / (1.0 + (1.0 + xy / (v[2] * v[2])).sqrt())
    }

    /// The density of the visible normals seen from `v` (upper hemisphere), per solid angle
    /// of `m`: G1(v, m) |v·m| D(m) / cos θ_v.
    pub fn visible_pdf(&self, v: V3, m: V3) -> f64 {
        if v[2] <= 0.0 {
            return 0.0;
        }
        self.g1(v, m) * dot(v, m).abs() * self.d(m) / v[2]
    }

    /// A visible normal seen from `v` (upper hemisphere) from two uniform numbers (Heitz 2018).
    pub fn sample_visible(&self, v: V3, u: [f64; 2]) -> V3 {
        let a = self.alpha;
        let vh = normalize([a * v[0], a * v[1], v[2]]).unwrap_or([0.0, 0.0, 1.0]);
        let len2 = vh[0] * vh[0] + vh[1] * vh[1];
        let t1 = if len2 > 0.0 {
            let l = len2.sqrt();
            [-vh[1] / l, vh[0] / l, 0.0]
        } else {
            [1.0, 0.0, 0.0]
        };
        let t2 = cross(vh, t1);
        let r = u[0].sqrt();
        let phi = 2.0 * PI * u[1];
        let p1 = r * phi.cos();
        let s = 0.5 * (1.0 + vh[2]);
        let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
        let p3 = (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
        let nh: V3 = std::array::from_fn(|c| p1 * t1[c] + p2 * t2[c] + p3 * vh[c]);
        normalize([a * nh[0], a * nh[1], nh[2].max(1e-12)]).unwrap_or([0.0, 0.0, 1.0])
    }

    /// The half-vector of a pair (turned to the upper hemisphere), whether it is a reflection,
    /// and the relative index η_o/η_i of the crossing (1 for a reflection).
    fn half(&self, wi: V3, wo: V3) -> Option<(V3, bool, f64)> {
        if wi[2] == 0.0 {
            return None;
        }
        let reflect = wi[2] * wo[2] > 0.0;
        let eta = if wi[2] > 0.0 {
            self.eta
        } else {
            1.0 / self.eta
        };
        let s = if reflect { 1.0 } else { eta };
        let m = normalize(add_scaled(wi, s, wo))?;
        let m = if m[2] < 0.0 { m.map(|x| -x) } else { m };
        Some((m, reflect, eta))
    }

    /// The BSDF times |cos θ_o| for light between `wi` (where the path came from) and `wo`.
    pub fn eval(&self, wi: V3, wo: V3, mode: Transport) -> f64 {
        let Some((m, reflect, eta)) = self.half(wi, wo) else {
            return 0.0;
        };
        let d = self.d(m);
        let f = fresnel(dot(wi, m), self.eta).r;
        let g = self.g1(wi, m) * self.g1(wo, m);
        let cos_i = wi[2];
        if reflect {
            return f * d * g / (4.0 * cos_i.abs());
        }
        let scale = match mode {
            Transport::Radiance => 1.0 / (eta * eta),
            Transport::Importance => 1.0,
        };
        let (im, om) = (dot(wi, m), dot(wo, m));
        let den = im + eta * om;
        let v = scale * (1.0 - f) * d * g * eta * eta * im * om / (cos_i * den * den);
        if v.is_finite() { v.abs() } else { 0.0 }
    }

    /// The density, per solid angle, of [`sample`](Self::sample) choosing `wo` from `wi`.
    pub fn pdf(&self, wi: V3, wo: V3) -> f64 {
        let Some((m, reflect, eta)) = self.half(wi, wo) else {
            return 0.0;
        };
        let (im, om) = (dot(wi, m), dot(wo, m));
        if im * wi[2] <= 0.0 || om * wo[2] <= 0.0 {
            return 0.0;
        }
        let jacobian = if reflect {
            1.0 / (4.0 * om)
        } else {
            eta * eta * om / ((im + eta * om) * (im + eta * om))
        };
        let up = if wi[2] < 0.0 { wi.map(|x| -x) } else { wi };
        let f = fresnel(im, self.eta).r;
        let choice = if reflect { f } else { 1.0 - f };
        let p = self.visible_pdf(up, m) * choice * jacobian.abs();
        if p.is_finite() { p } else { 0.0 }
    }

    /// A direction from `wi` by three uniform numbers: a visible normal, then reflection with
    /// the Fresnel reflectance's probability, else refraction. `None` where nothing goes on
    /// (a grazing `wi`, or a reflection below the surface: the microfacet masks it).
    pub fn sample(&self, wi: V3, u: [f64; 3], mode: Transport) -> Option<BsdfSample> {
        let cos_i = wi[2];
        if cos_i == 0.0 {
            return None;
        }
        let up = if cos_i < 0.0 { wi.map(|x| -x) } else { wi };
        let m = self.sample_visible(up, [u[1], u[2]]);
        let pdf_m = self.visible_pdf(up, m);
        if pdf_m <= 0.0 {
            return None;
        }
        let im = dot(wi, m);
        let fr = fresnel(im, self.eta);
        let reflected = u[0] <= fr.r;
        let (wo, mut weight, pdf) = if reflected {
            let wo: V3 = std::array::from_fn(|c| 2.0 * im * m[c] - wi[c]);
            (wo, 1.0, pdf_m * fr.r / (4.0 * dot(wo, m)).abs())
        } else {
            let wo: V3 =
                std::array::from_fn(|c| m[c] * (im * fr.eta_ti + fr.cos_t) - wi[c] * fr.eta_ti);
            let om = dot(wo, m);
            let den = im + fr.eta_it * om;
            let jacobian = fr.eta_it * fr.eta_it * om / (den * den);
            let factor = match mode {
                Transport::Radiance => fr.eta_ti * fr.eta_ti,
                Transport::Importance => 1.0,
            };
            (wo, factor, pdf_m * (1.0 - fr.r) * jacobian.abs())
        };
        weight *= self.g1(wo, m);
        (weight > 0.0 && weight.is_finite() && pdf > 0.0 && pdf.is_finite()).then_some(BsdfSample {
            wo,
            weight,
            pdf,
            reflected,
        })
    }
}

/// A local frame at a surface point: tangents and the normal pointing outside.
struct LocalFrame {
    t: V3,
    b: V3,
    n: V3,
}

impl LocalFrame {
    fn new(n: V3) -> LocalFrame {
        let (t, b) = frame_of(n);
        LocalFrame { t, b, n }
    }
    fn to_local(&self, v: V3) -> V3 {
        [dot(v, self.t), dot(v, self.b), dot(v, self.n)]
    }
    fn to_world(&self, v: V3) -> V3 {
        std::array::from_fn(|c| v[0] * self.t[c] + v[1] * self.b[c] + v[2] * self.n[c])
    }
}

/// The camera a frame's next events go to, in the object frame.
struct Pinhole<'a> {
    cam: &'a Camera,
    deg: f64,
    centre: V3,
}

impl Pinhole<'_> {
    /// The next event from a surface point towards the camera: pixel coordinates and ln of the
    /// BSDF (importance mode, times the cosine) times the pinhole's radiance factor; `None`
    /// when the camera is on the medium's side of the surface, outside the image, or the
    /// straight line to it meets the mesh again.
    fn surface_event(
        &self,
        scene: &Scene,
        bsdf: &RoughDielectric,
        p: V3,
        tri: u32,
        frame: &LocalFrame,
        wi: V3,
    ) -> Option<([f64; 2], f64)> {
        let to_cam = normalize(sub(self.centre, p))?;
        let wo = frame.to_local(to_cam);
        if wo[2] <= 0.0 {
            return None;
        }
        let c = self.cam.to_camera(turntable_to_world(p, self.deg));
        let uv = self.cam.project_camera(c)?;
        let (w, h) = (self.cam.width as f64, self.cam.height as f64);
        let r = FILTER_RADIUS_PX;
        if uv[0] < -0.5 - r || uv[1] < -0.5 - r || uv[0] > w - 0.5 + r || uv[1] > h - 0.5 + r {
            return None;
        }
        let f = bsdf.eval(wi, wo, Transport::Importance);
        if f <= 0.0 {
            return None;
        }
        let range = dist(self.centre, p);
        if next_hit(scene, p, to_cam, range, Some(tri)).is_some() {
            return None;
        }
        // As a collision's next event: a point of intensity I (W/sr) at distance r reads in a
        // pinhole pixel as the radiance I f_x f_y r / z³; here I = power · f · |cos θ_o|.
        let ln = f.ln() + range.ln() - 3.0 * c[2].ln();
        ln.is_finite().then_some((uv, ln))
    }
}

/// Traces one frame's photons through a rough dielectric boundary in the reference medium and
/// returns every surface event's next-event record that lands in the image.
pub(super) fn trace_frame(
    scene: &Scene,
    boundary: Boundary,
    geo: &FrameGeometry,
    settings: &TraceSettings,
    bsdf: RoughDielectric,
    frame: usize,
) -> Vec<Record> {
    walk_frame(
        scene,
        boundary,
        geo,
        settings,
        None,
        bsdf,
        frame,
        &Vec::new,
        &|out: &mut Vec<Record>, uv, ln, w| {
            out.push(Record {
                u: uv[0] as f32,
                v: uv[1] as f32,
                k: w.k,
                length: w.length as f32,
                ln_w: ln as f32,
            });
        },
        &|mut a, mut b| {
            a.append(&mut b);
            a
        },
    )
}

/// What [`trace_grid_frame`] hands each surface event to: the accumulator, pixel coordinates,
/// ln of the contribution and the path's cells (cell, real collisions, medium length).
pub(super) type EmitFn<'a, T> = dyn Fn(&mut T, [f64; 2], f64, &[(u32, u32, f64)]) + Sync + 'a;

/// Traces one frame's photons through a rough dielectric boundary in the grid medium `grid`
/// (one channel; free flights by delta tracking) and hands every surface event that lands in
/// the image to `emit`: pixel coordinates, ln of its contribution to the pixel's radiance per
/// watt of laser (before the reconstruction filter), and the path's cells so far (cell, real
/// collisions there, medium length through it). A photon's events go to one accumulator made
/// by `init`; `merge` joins them.
#[allow(clippy::too_many_arguments)]
pub(super) fn trace_grid_frame<T: Send>(
    scene: &Scene,
    boundary: Boundary,
    geo: &FrameGeometry,
    grid: &GridChannel,
    g: f64,
    bsdf: RoughDielectric,
    photons: usize,
    seed: u64,
    frame: usize,
    init: &(dyn Fn() -> T + Sync),
    emit: &EmitFn<'_, T>,
    merge: &(dyn Fn(T, T) -> T + Sync),
) -> T {
    let major = grid.majorant();
    if !(major > 0.0 && major.is_finite()) {
        return init();
    }
    // The walk reads only g, the photons and the seed from these in a grid (σ_t and α come
    // from the cells).
    let settings = TraceSettings::for_medium([major; 3], [1.0; 3], g, photons, seed);
    walk_frame(
        scene,
        boundary,
        geo,
        &settings,
        Some((grid, major)),
        bsdf,
        frame,
        init,
        &|out, uv, ln, w| emit(out, uv, ln, &w.path),
        merge,
    )
}

/// What [`walk_frame`] hands each surface event to, with the photon's state.
type WalkEmit<'a, T> = dyn Fn(&mut T, [f64; 2], f64, &Walk) + Sync + 'a;

/// One frame's photons walked through the boundary, in the medium of `settings` or in `grid`
/// (with its majorant): every surface event that lands in the image goes to `emit` with ln of
/// its whole contribution (the photon's share of 1 W, its BSDF weights, the pinhole's factor).
#[allow(clippy::too_many_arguments)]
fn walk_frame<T: Send>(
    scene: &Scene,
    boundary: Boundary,
    geo: &FrameGeometry,
    settings: &TraceSettings,
    grid: Option<(&GridChannel, f64)>,
    bsdf: RoughDielectric,
    frame: usize,
    init: &(dyn Fn() -> T + Sync),
    emit: &WalkEmit<'_, T>,
    merge: &(dyn Fn(T, T) -> T + Sync),
) -> T {
    let pinhole = Pinhole {
        cam: &geo.camera,
        deg: geo.deg,
        centre: world_to_turntable(geo.camera.center(), geo.deg),
    };
    let ln_power = -(settings.photons.max(1) as f64).ln();
    let ln_fxfy = (geo.camera.fx * geo.camera.fy).ln();
    (0..settings.photons)
        .into_par_iter()
        .fold(init, |mut out, n| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(photon_seed(settings.seed, frame, n));
            if let Some((entry, dir, tri)) = geo.launch(scene, &mut rng) {
                let photon = Walk {
                    p: entry,
                    d: dir,
                    on: Some(tri),
                    skip: Some(tri),
                    inside: false,
                    k: 0,
                    length: 0.0,
                    ln_beta: 0.0,
                    path: Vec::new(),
                };
                photon.run(
                    scene,
                    boundary,
                    geo,
                    settings,
                    grid,
                    &bsdf,
                    &pinhole,
                    &mut rng,
                    &mut |uv, w: &Walk, ln| {
                        emit(&mut out, uv, ln_power + w.ln_beta + ln + ln_fxfy, w);
                    },
                );
            }
            out
        })
        .reduce(init, merge)
}

/// One photon's state between events.
struct Walk {
    p: V3,
    d: V3,
    /// The triangle the photon stands on (a surface event is due), if any.
    on: Option<u32>,
    /// The triangle last crossed or reflected from.
    skip: Option<u32>,
    /// In the medium.
    inside: bool,
    /// Collisions so far.
    k: u32,
    /// Medium length travelled, mm.
    length: f64,
    /// ln of the photon's weight: the BSDF samples' weights (1 in the medium).
    ln_beta: f64,
    /// In a grid medium, the cells of the path so far: (cell, real collisions there, medium
    /// length through it in mm), what a grid fit's likelihood ratios need (`super::gridfit`);
    /// empty in a homogeneous medium, whose `k` and `length` say it all.
    path: Vec<(u32, u32, f64)>,
}

impl Walk {
    #[allow(clippy::too_many_arguments)]
    fn run(
        mut self,
        scene: &Scene,
        boundary: Boundary,
        geo: &FrameGeometry,
        settings: &TraceSettings,
        grid: Option<(&GridChannel, f64)>,
        bsdf: &RoughDielectric,
        pinhole: &Pinhole,
        rng: &mut impl Rng,
        emit: &mut dyn FnMut([f64; 2], &Walk, f64),
    ) {
        let (sigma0, albedo0, g) = (settings.sigma_t, settings.albedo, settings.g);
        // In a grid, free flights by delta tracking against its largest σ_t (`super::medium`).
        let rate = grid.map_or(sigma0, |(_, major)| major);
        let mut surface_events = 0;
        let mut tentative = 0;
        loop {
            if let Some(tri) = self.on.take() {
                surface_events += 1;
                if surface_events > MAX_SURFACE_EVENTS {
                    return;
                }
                let Some(nf) = scene.face_normal(tri) else {
                    return;
                };
                // The normal that points outside: along the photon's way when it leaves.
                let c = dot(nf, self.d);
                if c == 0.0 {
                    return;
                }
                let n = if (c > 0.0) == self.inside {
                    nf
                } else {
                    nf.map(|x| -x)
                };
                let frame = LocalFrame::new(n);
                let wi = frame.to_local(self.d.map(|x| -x));
                if let Some((uv, ln)) = pinhole.surface_event(scene, bsdf, self.p, tri, &frame, wi)
                {
                    emit(uv, &self, ln);
                }
                let u = [rng.random(), rng.random(), rng.random()];
                let Some(s) = bsdf.sample(wi, u, Transport::Importance) else {
                    return;
                };
                let Some(d) = normalize(frame.to_world(s.wo)) else {
                    return;
                };
                self.ln_beta += s.weight.ln();
                self.d = d;
                self.inside = s.wo[2] < 0.0;
                self.skip = Some(tri);
                continue;
            }
            if !self.inside {
                match next_hit(scene, self.p, self.d, f64::MAX, self.skip) {
                    Some((_, hp, tri)) => {
                        self.p = hp;
                        self.on = Some(tri);
                        continue;
                    }
                    None => return,
                }
            }
            let x: f64 = rng.random();
            let s = -(1.0 - x).ln() / rate;
            let hit = next_hit(scene, self.p, self.d, s, self.skip);
            let flown = hit.map_or(s, |h| h.0);
            if let Some((gr, _)) = grid {
                let path = &mut self.path;
                gr.for_each_cell(self.p, self.d, flown, &mut |c, l| add_to(path, c, 0, l));
            }
            self.length += flown;
            if let Some((_, hp, tri)) = hit {
                self.p = hp;
                self.on = Some(tri);
                continue;
            }
            self.p = add_scaled(self.p, s, self.d);
            self.skip = None;
            tentative += 1;
            if tentative > MAX_TENTATIVE {
                return;
            }
            if boundary == Boundary::Open && crossings(scene, self.p, geo.origin).is_multiple_of(2)
            {
                // Beyond the open face's reach: not part of the medium.
                return;
            }
            let albedo = match grid {
                Some((gr, _)) => {
                    // Delta tracking: a null collision leaves the photon on its way.
                    let cell = gr.index(gr.cell3(self.p));
                    if rng.random::<f64>() * rate >= gr.sigma_t[cell] {
                        continue;
                    }
                    add_to(&mut self.path, cell, 1, 0.0);
                    gr.albedo[cell]
                }
                None => albedo0,
            };
            self.k += 1;
            if self.k > MAX_COLLISIONS {
                return;
            }
            // Absorption by survival: the weight stays and α^k is the chance to go on.
            if rng.random::<f64>() >= albedo {
                return;
            }
            self.d = sample_hg(self.d, g, rng);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ETA: f64 = 1.55;

    fn bsdf(alpha: f64) -> RoughDielectric {
        RoughDielectric { eta: ETA, alpha }
    }

    /// A unit direction at polar angle `theta` from +z (π − θ below) and azimuth `phi`.
    fn dir(theta: f64, phi: f64) -> V3 {
        [
            theta.sin() * phi.cos(),
            theta.sin() * phi.sin(),
            theta.cos(),
        ]
    }

    /// ∫ `f` over the directions on `wi`'s side (`same`) or the other one, by a quadrature
    /// in polar coordinates about `centre` that is dense near it (θ = π u²), for lobes too
    /// narrow for a uniform grid.
    fn lobe_integral(f: &dyn Fn(V3) -> f64, centre: V3, upper: bool, n: usize) -> f64 {
        let (t, b) = frame_of(centre);
        let mut sum = 0.0;
        for i in 0..n {
            let u = (i as f64 + 0.5) / n as f64;
            let theta = PI * u * u;
            let dtheta = 2.0 * PI * u / n as f64;
            for j in 0..n {
                let phi = 2.0 * PI * (j as f64 + 0.5) / n as f64;
                let l = dir(theta, phi);
                let w: V3 = std::array::from_fn(|c| l[0] * t[c] + l[1] * b[c] + l[2] * centre[c]);
                if (w[2] > 0.0) == upper {
                    sum += f(w) * theta.sin() * dtheta * 2.0 * PI / n as f64;
                }
            }
        }
        sum
    }

    /// The mirror and the refracted directions of `wi` about the macro normal.
    fn specular(wi: V3) -> (V3, Option<V3>) {
        let mirror = [-wi[0], -wi[1], wi[2]];
        let fr = fresnel(wi[2], ETA);
        let n = [0.0, 0.0, 1.0];
        let refracted = (fr.r < 1.0).then(|| {
            std::array::from_fn(|c| n[c] * (wi[2] * fr.eta_ti + fr.cos_t) - wi[c] * fr.eta_ti)
        });
        (mirror, refracted)
    }

    /// Normal incidence gives ((η − 1)/(η + 1))² from either side, the reflectance is the same
    /// for a pair of angles related by Snell's law (Stokes), and beyond the critical angle
    /// inside all of it is reflected.
    #[test]
    fn fresnel_is_exact_at_normal_incidence_reciprocal_and_totally_reflects() {
        let r0 = ((ETA - 1.0) / (ETA + 1.0)).powi(2);
        assert!((fresnel(1.0, ETA).r - r0).abs() < 1e-15);
        assert!((fresnel(-1.0, ETA).r - r0).abs() < 1e-15);
        for cos in [0.9, 0.5, 0.2, 0.05] {
            let out = fresnel(cos, ETA);
            let back = fresnel(out.cos_t, ETA);
            assert!((out.r - back.r).abs() < 1e-12, "{cos}: {out:?} {back:?}");
            assert!((back.cos_t - cos).abs() < 1e-12);
        }
        let critical = (1.0 / ETA).asin();
        assert_eq!(fresnel(-(critical + 0.01).cos(), ETA).r, 1.0);
        assert!(fresnel(-(critical - 0.01).cos(), ETA).r < 1.0);
        assert_eq!(fresnel(0.3, 1.0).r, 0.0);
    }

    /// As the roughness vanishes (α 0.002: at 0.02 the reflectance from inside near the
    /// critical angle is visibly the average of a convex F over the facets' tilts, 0.116 for
    /// 0.103 at 34°) the lobes become the smooth interface's: the reflected energy
    /// is the Fresnel reflectance, the refracted one 1 − F in importance mode and (1 − F) times
    /// (η_i/η_t)² in radiance mode (the solid angle's compression); at GGX α = 0.2 reflection
    /// and refraction together never exceed 1 (single scattering loses some: 0.80 from inside
    /// at 57°, beyond the critical angle, where reflections into the facets' backs are lost).
    #[test]
    fn energy_follows_fresnel_as_the_roughness_vanishes_and_never_exceeds_one() {
        for (theta, upper) in [
            (0.1, true),
            (0.7, true),
            (1.2, true),
            (0.3, false),
            (0.6, false),
            (1.0, false),
        ] {
            let wi = if upper {
                dir(theta, 0.4)
            } else {
                dir(PI - theta, 0.4)
            };
            let fr = fresnel(wi[2], ETA);
            let (mirror, refracted) = specular(wi);
            let b = bsdf(0.002);
            let r = lobe_integral(
                &|w| b.eval(wi, w, Transport::Importance),
                mirror,
                upper,
                900,
            );
            eprintln!("θ {theta} outside {upper}: R {r} vs F {}", fr.r);
            assert!(
                (r - fr.r).abs() < 0.02 * fr.r.max(0.05),
                "θ {theta} {upper}: R {r} vs F {}",
                fr.r
            );
            let below = !upper;
            match refracted {
                Some(t_dir) => {
                    let t =
                        lobe_integral(&|w| b.eval(wi, w, Transport::Importance), t_dir, below, 900);
                    assert!(
                        (t - (1.0 - fr.r)).abs() < 0.015,
                        "θ {theta} {upper}: T {t} vs {}",
                        1.0 - fr.r
                    );
                    let tr =
                        lobe_integral(&|w| b.eval(wi, w, Transport::Radiance), t_dir, below, 900);
                    let want = (1.0 - fr.r) * fr.eta_ti * fr.eta_ti;
                    assert!(
                        (tr / want - 1.0).abs() < 0.015,
                        "θ {theta} {upper}: T radiance {tr} vs {want}"
                    );
                }
                None => assert!(fr.r == 1.0),
            }
            let b = bsdf(0.2);
            let both = lobe_integral(
                &|w| b.eval(wi, w, Transport::Importance),
                mirror,
                upper,
                600,
            ) + refracted.map_or(0.0, |t_dir| {
                lobe_integral(&|w| b.eval(wi, w, Transport::Importance), t_dir, below, 600)
            });
            assert!(
                both <= 1.0 + 2e-3 && both > 0.75,
                "θ {theta} {upper}: R + T {both}"
            );
        }
    }

    /// Reflection is symmetric in its two directions; refraction's radiance BSDF divided by
    /// the square of the index on the side of `wi` is symmetric (Veach's generalised
    /// reciprocity), and the importance BSDF is the radiance one with its arguments swapped
    /// (the adjoint).
    #[test]
    fn reflection_is_reciprocal_and_refraction_is_its_adjoint_with_eta_squared() {
        let b = bsdf(0.2);
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let index = |w: V3| if w[2] > 0.0 { 1.0 } else { ETA };
        let mut checked = 0;
        for _ in 0..2000 {
            let a = dir(
                (rng.random::<f64>() * 2.0 - 1.0).acos(),
                2.0 * PI * rng.random::<f64>(),
            );
            let c = dir(
                (rng.random::<f64>() * 2.0 - 1.0).acos(),
                2.0 * PI * rng.random::<f64>(),
            );
            let f = |x: V3, y: V3, mode| b.eval(x, y, mode) / y[2].abs();
            let (rad_ac, rad_ca) = (f(a, c, Transport::Radiance), f(c, a, Transport::Radiance));
            let imp_ac = f(a, c, Transport::Importance);
            let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * x.abs().max(y.abs()) + 1e-300;
            assert!(close(imp_ac, rad_ca), "{a:?} {c:?}: {imp_ac} vs {rad_ca}");
            assert!(
                close(rad_ac / index(a).powi(2), rad_ca / index(c).powi(2)),
                "{a:?} {c:?}"
            );
            if a[2] * c[2] > 0.0 {
                assert!(close(rad_ac, imp_ac));
            }
            checked += (rad_ac > 0.0) as usize;
        }
        assert!(checked > 1000, "{checked}");
    }

    /// The sampler draws directions with the density `pdf` says (bin by bin against a
    /// quadrature of `pdf`), each sample's weight is eval / pdf at its direction, and the mean
    /// weight, the Monte Carlo estimate of ∫ f |cos θ_o| dω, is that integral by quadrature.
    #[test]
    fn sampling_follows_the_pdf_and_weighs_by_eval_over_pdf() {
        let n = 200_000;
        let (nc, np) = (8usize, 4usize);
        for alpha in [0.2, 0.5] {
            let b = bsdf(alpha);
            for (theta, phi) in [
                (0.2, 0.0),
                (1.0, 1.0),
                (1.4, 2.0),
                (PI - 0.3, 0.5),
                (PI - 0.9, 3.0),
            ] {
                let wi = dir(theta, phi);
                // The quadrature over the sphere, uniform in cos θ and φ.
                let (qc, qp) = (1200usize, 400usize);
                let mut bins = vec![0.0; nc * np];
                let mut albedo = [0.0; 2];
                for i in 0..qc {
                    let cos = -1.0 + 2.0 * (i as f64 + 0.5) / qc as f64;
                    for j in 0..qp {
                        let ph = 2.0 * PI * (j as f64 + 0.5) / qp as f64;
                        let w = dir(cos.acos(), ph);
                        let dw = 2.0 / qc as f64 * 2.0 * PI / qp as f64;
                        bins[bin(w, nc, np)] += b.pdf(wi, w) * dw;
                        albedo[0] += b.eval(wi, w, Transport::Importance) * dw;
                        albedo[1] += b.eval(wi, w, Transport::Radiance) * dw;
                    }
                }
                let mut rng = rand::rngs::StdRng::seed_from_u64(11);
                let mut counts = vec![0usize; nc * np];
                let mut mean = [0.0; 2];
                for _ in 0..n {
                    let u = [rng.random(), rng.random(), rng.random()];
                    for (m, mode) in [Transport::Importance, Transport::Radiance]
                        .into_iter()
                        .enumerate()
                    {
                        let Some(s) = b.sample(wi, u, mode) else {
                            continue;
                        };
                        let (f, p) = (b.eval(wi, s.wo, mode), b.pdf(wi, s.wo));
                        assert!((s.pdf / p - 1.0).abs() < 1e-9, "{wi:?} {s:?}: pdf {p}");
                        assert!(
                            (s.weight / (f / p) - 1.0).abs() < 1e-9,
                            "{wi:?} {s:?}: {f} / {p}"
                        );
                        assert_eq!(s.reflected, s.wo[2] * wi[2] > 0.0);
                        mean[m] += s.weight / n as f64;
                        if m == 0 {
                            counts[bin(s.wo, nc, np)] += 1;
                        }
                    }
                }
                for (k, (&c, &p)) in counts.iter().zip(&bins).enumerate() {
                    let frac = c as f64 / n as f64;
                    let tol = 5.0 * (p.max(1e-4) / n as f64).sqrt() + 2e-3 * p + 1e-4;
                    assert!(
                        (frac - p).abs() < tol,
                        "α {alpha} wi {wi:?} bin {k}: {frac} vs {p}"
                    );
                }
                for m in 0..2 {
                    let sd = 3.0 / (n as f64).sqrt() * if m == 1 { ETA * ETA } else { 1.0 };
                    assert!(
                        (mean[m] - albedo[m]).abs() < sd + 2e-3 * albedo[m],
                        "α {alpha} wi {wi:?} mode {m}: {} vs {}",
                        mean[m],
                        albedo[m]
                    );
                }
            }
        }
    }

    /// A direction's bin: `nc` bands of cos θ, `np` of φ.
    fn bin(w: V3, nc: usize, np: usize) -> usize {
        let c = (((w[2] + 1.0) / 2.0 * nc as f64) as usize).min(nc - 1);
        let phi = w[1].atan2(w[0]).rem_euclid(2.0 * PI);
        let p = ((phi / (2.0 * PI) * np as f64) as usize).min(np - 1);
        c * np + p
    }
}
