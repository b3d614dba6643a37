//! The forward model of a laser frame through a scattering volume: photons traced from the laser's
//! ray into the medium inside the mesh, with next-event estimation towards the frame's pinhole
//! camera at every collision.
//!
//! The tracer starts at the laser because the frames are lit by a spot a fraction of a millimetre
//! wide: a camera-side path tracer must find that spot by next-event estimation towards a tiny
//! light, and most of its paths carry nothing. From the laser every path carries light and every
//! collision lands in some pixel.
//!
//! Each collision's contribution is recorded with what it depends on: the number of collisions
//! `k` up to it and the length `L` travelled in the medium (to it and on to the camera). The
//! image of a homogeneous medium (σ_t, α) then follows from the reference medium (σ_0, α_0) the
//! photons were traced in by the likelihood ratio of the path (perturbation Monte Carlo):
//!
//! ```text
//! w(σ, α) / w(σ_0, α_0) = (σ/σ_0)^k · (α/α_0)^k · exp(−(σ − σ_0) · L)
//! ```
//!
//! so one trace gives the images of every nearby medium, per colour channel, with their
//! derivatives in closed form and with common random numbers (two media compare without their
//! noise). The ratio's variance grows with the distance from the reference; the fit re-traces
//! at its estimate each round and keeps σ within a factor 2 and α below α_0.
//!
//! Written here rather than taken from a renderer: no Rust crate traces a participating medium
//! behind a triangle mesh, and the likelihood-ratio records are what make the fit affordable.

use super::dielectric::{RoughDielectric, Surface};
use crate::dataset::Image;
use crate::geometry::{
    Camera, Scene, V3, add_scaled, dist, dot, normalize, sub, world_to_turntable,
};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

/// The Gaussian reconstruction filter's standard deviation, pixels: Mitsuba 3's default film
/// filter (`gaussian`, stddev 0.5 px, radius 4 stddev), which the outside renderer's datasets
/// were made with.
pub const FILTER_STDDEV_PX: f64 = 0.5;
pub(super) const FILTER_RADIUS_PX: f64 = 4.0 * FILTER_STDDEV_PX;
/// Collisions after which a photon is given up: at α = 0.999 the survival to this depth is
/// below 1e-4 and what remains lies far beyond any judged ring.
pub(super) const MAX_COLLISIONS: u32 = 20_000;
/// A hit this close ahead of a crossing is that crossing again: the BVH's ray test reports the
/// triangle just crossed a few 1e-5 mm ahead, and a ray through a shared edge or vertex meets
/// each triangle there.
const PHANTOM_MM: f64 = 1e-3;
/// Step taken past a boundary crossing before the next cast, mm: far below any feature.
const STEP_MM: f64 = 1e-4;

/// The reference medium photons are traced in, and how they are traced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TraceSettings {
    /// Extinction coefficient of the reference medium, 1/mm.
    pub sigma_t: f64,
    /// Single-scattering albedo of the reference medium.
    pub albedo: f64,
    /// Henyey-Greenstein asymmetry (0: isotropic).
    pub g: f64,
    /// Photons per frame (1 W of laser power shared among them).
    pub photons: usize,
    /// Seed of the common random numbers: the same seed traces the same paths.
    pub seed: u64,
    /// The medium's boundary: index-matched, or a rough dielectric (`super::dielectric`).
    pub surface: Surface,
}

impl TraceSettings {
    /// The reference medium for a medium given channel by channel: σ_0 the geometric mean of
    /// the three σ (the likelihood ratio's variance grows with ln(σ/σ_0) on either side) and
    /// α_0 the largest albedo (the ratio (α/α_0)^k stays at most 1 and cannot blow up over
    /// many collisions).
    pub fn for_medium(
        sigma_t: [f64; 3],
        albedo: [f64; 3],
        g: f64,
        photons: usize,
        seed: u64,
    ) -> TraceSettings {
        TraceSettings {
            sigma_t: geo_mean(&sigma_t),
            albedo: albedo.iter().cloned().fold(0.0, f64::max),
            g,
            photons,
            seed,
            surface: super::dielectric::Surface::IndexMatched,
        }
    }
}

/// Geometric mean of three positive values.
pub(crate) fn geo_mean(v: &[f64; 3]) -> f64 {
    (v.iter().map(|x| x.ln()).sum::<f64>() / 3.0).exp()
}

/// One frame's geometry in the object frame: the laser's entry point and direction and the
/// camera.
#[derive(Debug, Clone)]
pub struct FrameGeometry {
    /// The laser's entry point x_i on the mesh (object frame, mm).
    pub x_i: V3,
    /// Triangle of x_i.
    pub triangle: u32,
    /// Unit direction of the laser ray (object frame).
    pub dir: V3,
    /// The laser origin (object frame): the side the light comes from, for the inside test of
    /// open meshes.
    pub origin: V3,
    /// The frame's camera.
    pub camera: Camera,
    /// Its turntable angle, degrees.
    pub deg: f64,
    /// A beam wider than a ray: photons leave `origin` uniformly within this half-angle
    /// (radians) of `dir`, as from a spot light (an outside renderer's point spot, whose cone
    /// lights a disc of the surface). 0: every photon follows the ray to x_i.
    pub cone: f64,
}

impl FrameGeometry {
    /// The laser ray `origin → dir` (world frame at turntable angle `deg`) cast at the mesh;
    /// `None` where it misses.
    pub fn new(
        scene: &Scene,
        camera: &Camera,
        deg: f64,
        origin_world: V3,
        dir_world: V3,
    ) -> Option<FrameGeometry> {
        let origin = world_to_turntable(origin_world, deg);
        let dir = normalize(world_to_turntable(dir_world, deg))?;
        let hit = scene.cast(origin, dir, f64::MAX)?;
        Some(FrameGeometry {
            x_i: hit.point,
            triangle: hit.triangle,
            dir,
            origin,
            camera: camera.clone(),
            deg,
            cone: 0.0,
        })
    }

    /// Where photon's light enters: x_i along the ray, or for a cone a direction drawn
    /// uniformly in its solid angle and cast at the mesh (`None`: it misses).
    pub(super) fn launch(&self, scene: &Scene, rng: &mut impl Rng) -> Option<(V3, V3, u32)> {
        if self.cone <= 0.0 {
            return Some((self.x_i, self.dir, self.triangle));
        }
        let cos = 1.0 - rng.random::<f64>() * (1.0 - self.cone.cos());
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        let phi = 2.0 * std::f64::consts::PI * rng.random::<f64>();
        let (e1, e2) = frame_of(self.dir);
        let d: V3 = std::array::from_fn(|c| {
            sin * phi.cos() * e1[c] + sin * phi.sin() * e2[c] + cos * self.dir[c]
        });
        let d = normalize(d)?;
        let hit = scene.cast(self.origin, d, f64::MAX)?;
        Some((hit.point, d, hit.triangle))
    }
}

/// Two unit vectors completing `d` to an orthonormal frame.
pub(super) fn frame_of(d: V3) -> (V3, V3) {
    let a = if d[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let e1 = normalize(crate::geometry::cross(d, a)).unwrap_or([0.0, 0.0, 1.0]);
    (e1, crate::geometry::cross(d, e1))
}

/// One collision's next-event estimate towards the camera, in the reference medium.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Record {
    /// Pixel coordinates the collision projects to.
    pub u: f32,
    /// Row coordinate.
    pub v: f32,
    /// Collisions up to and including this one.
    pub k: u32,
    /// Length travelled inside the medium, to the collision and on to the camera, mm.
    pub length: f32,
    /// ln of the contribution to the pixel's radiance (W/(mm² sr) per W of laser) in the
    /// reference medium, before the reconstruction filter.
    pub ln_w: f32,
}

impl Record {
    /// ln of this record's contribution in the medium (σ, α), channel by channel: the
    /// likelihood ratio to the reference (module docs).
    pub fn ln_w_in(&self, reference: &TraceSettings, sigma_t: f64, albedo: f64) -> f64 {
        let k = self.k as f64;
        self.ln_w as f64
            + k * ((sigma_t / reference.sigma_t).ln() + (albedo / reference.albedo).ln())
            - (sigma_t - reference.sigma_t) * self.length as f64
    }
}

/// Inside and outside for the mesh. A closed mesh bounds its medium: a flight that crosses the
/// boundary leaves it. An open mesh (a slab's top face) bounds it on one side: a point is inside
/// when the ray from it towards the laser's origin crosses the surface an odd number of times,
/// so the medium lies behind the lit face, as far as the face reaches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Boundary {
    /// Every edge shared by two triangles.
    Closed,
    /// Some edge belongs to one triangle only.
    Open,
}

impl Boundary {
    /// The boundary kind of the scene's mesh.
    pub fn of(scene: &Scene) -> Boundary {
        let mut edges: std::collections::HashMap<(u32, u32), u32> = Default::default();
        for t in &scene.mesh.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        if edges.values().all(|&n| n == 2) {
            Boundary::Closed
        } else {
            Boundary::Open
        }
    }
}

/// The first hit of the ray from `p` along the unit direction `d` within `t_max`; after a
/// crossing (`skip`, the triangle crossed) hits on that triangle, and hits on any triangle
/// within [`PHANTOM_MM`] (its neighbours, through a shared edge), are that crossing again and
/// are stepped over: a straight line meets a plane once.
///
/// The cast is [`Scene::cast_strict`]: the photons' directions are random, so a ray through an
/// edge's crack has no weight, while the camera rays' retry from nudged origins, started on the
/// face just crossed, meets that face again at grazing exits and turns a photon leaving the
/// medium into one flying on inside it (on sample-torus's tube, one collision in 200 lay outside
/// the mesh).
pub(super) fn next_hit(
    scene: &Scene,
    mut p: V3,
    d: V3,
    mut t_max: f64,
    skip: Option<u32>,
) -> Option<(f64, V3, u32)> {
    // Most flights end deep inside, where no surface is near: the cast's answer is known.
    if t_max < scene.clearance(p) {
        return None;
    }
    let mut travelled = 0.0;
    for _ in 0..4 {
        let h = scene.cast_strict(p, d, t_max)?;
        if skip.is_some_and(|tri| h.t < PHANTOM_MM || h.triangle == tri) {
            p = add_scaled(h.point, STEP_MM, d);
            travelled += h.t + STEP_MM;
            t_max -= h.t + STEP_MM;
            if t_max <= 0.0 {
                return None;
            }
            continue;
        }
        return Some((travelled + h.t, h.point, h.triangle));
    }
    None
}

/// Number of surface crossings on the segment from `p` to `q`.
pub(super) fn crossings(scene: &Scene, p: V3, q: V3) -> usize {
    let Some(d) = normalize(sub(q, p)) else {
        return 0;
    };
    let mut left = dist(p, q);
    let (mut at, mut skip, mut n) = (p, None, 0);
    while let Some((t, hp, tri)) = next_hit(scene, at, d, left, skip) {
        n += 1;
        left -= t;
        at = hp;
        skip = Some(tri);
        if n > 64 {
            break;
        }
    }
    n
}

/// Where a photon is and which way it goes.
pub(super) struct Photon {
    pub(super) p: V3,
    pub(super) d: V3,
    /// The triangle last crossed (or entered through).
    pub(super) skip: Option<u32>,
}

/// Moves the photon `s` mm of medium along its direction: out through the boundary and back in
/// where the straight line meets the mesh again (index-matched: no refraction, no reflection).
/// `false` when it leaves for good.
pub(super) fn fly(scene: &Scene, ph: &mut Photon, s: f64) -> bool {
    fly_pieces(scene, ph, s, &mut |_, _, _| {})
}

/// [`fly`], calling `piece(start, direction, length)` with each stretch of medium flown (a grid
/// fit counts the length per cell).
pub(super) fn fly_pieces(
    scene: &Scene,
    ph: &mut Photon,
    mut s: f64,
    piece: &mut dyn FnMut(V3, V3, f64),
) -> bool {
    let mut inside = true;
    for _ in 0..64 {
        let reach = if inside { s } else { f64::MAX };
        match next_hit(scene, ph.p, ph.d, reach, ph.skip) {
            Some((t, hp, tri)) => {
                if inside {
                    piece(ph.p, ph.d, t);
                    s -= t;
                }
                ph.p = hp;
                ph.skip = Some(tri);
                inside = !inside;
            }
            None if inside => {
                piece(ph.p, ph.d, s);
                ph.p = add_scaled(ph.p, s, ph.d);
                ph.skip = None;
                return true;
            }
            None => return false,
        }
    }
    false
}

/// The sum of `depth(start, direction, length)` over the pieces of medium on the straight line
/// from `p` (inside) to `q` (outside the mesh): their length, or their optical depth in a
/// heterogeneous medium; `None` when the line never leaves the medium.
pub(super) fn medium_depth(
    scene: &Scene,
    p: V3,
    q: V3,
    depth: &dyn Fn(V3, V3, f64) -> f64,
) -> Option<f64> {
    let d = normalize(sub(q, p))?;
    let mut left = dist(p, q);
    let (mut at, mut skip, mut inside, mut len) = (p, None, true, 0.0);
    for _ in 0..64 {
        match next_hit(scene, at, d, left, skip) {
            Some((t, hp, tri)) => {
                if inside {
                    len += depth(at, d, t);
                }
                left -= t;
                at = hp;
                skip = Some(tri);
                inside = !inside;
            }
            None => return (!inside).then_some(len),
        }
    }
    None
}

/// Henyey-Greenstein phase function, 1/sr, of the cosine between the propagation directions
/// before and after scattering.
pub fn hg(cos: f64, g: f64) -> f64 {
    let den = 1.0 + g * g - 2.0 * g * cos;
    (1.0 - g * g) / (4.0 * std::f64::consts::PI * den * den.sqrt())
}

/// A direction scattered from `d` by Henyey-Greenstein with asymmetry `g`.
pub(super) fn sample_hg(d: V3, g: f64, rng: &mut impl Rng) -> V3 {
    let (x1, x2): (f64, f64) = (rng.random(), rng.random());
    let cos = if g.abs() < 1e-4 {
        1.0 - 2.0 * x1
    } else {
        let f = (1.0 - g * g) / (1.0 - g + 2.0 * g * x1);
        ((1.0 + g * g - f * f) / (2.0 * g)).clamp(-1.0, 1.0)
    };
    let sin = (1.0 - cos * cos).max(0.0).sqrt();
    let phi = 2.0 * std::f64::consts::PI * x2;
    let (e1, e2) = frame_of(d);
    let mut o = [0.0; 3];
    for c in 0..3 {
        o[c] = sin * phi.cos() * e1[c] + sin * phi.sin() * e2[c] + cos * d[c];
    }
    normalize(o).unwrap_or(d)
}

/// The seed of photon `n` of frame `frame`: independent streams, the same for every medium.
pub(super) fn photon_seed(seed: u64, frame: usize, n: usize) -> u64 {
    let mut z = seed ^ ((frame as u64) << 40) ^ (n as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Traces one frame's photons in the reference medium and returns every collision's
/// next-event record that lands in the image (behind a rough dielectric, every surface
/// event's: `super::dielectric`). `frame` only seeds the random numbers.
pub fn trace_frame(
    scene: &Scene,
    boundary: Boundary,
    geo: &FrameGeometry,
    settings: &TraceSettings,
    frame: usize,
) -> Vec<Record> {
    if let Surface::RoughDielectric { ior, alpha } = settings.surface {
        let bsdf = RoughDielectric { eta: ior, alpha };
        return super::dielectric::trace_frame(scene, boundary, geo, settings, bsdf, frame);
    }
    let cam = &geo.camera;
    let centre = world_to_turntable(cam.center(), geo.deg);
    let ln_power = -(settings.photons.max(1) as f64).ln();
    let ln_fxfy = (cam.fx * cam.fy).ln();
    let (sigma0, albedo0, g) = (settings.sigma_t, settings.albedo, settings.g);
    (0..settings.photons)
        .into_par_iter()
        .fold(Vec::new, |mut out, n| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(photon_seed(settings.seed, frame, n));
            let Some((entry, dir, tri)) = geo.launch(scene, &mut rng) else {
                return out;
            };
            let mut ph = Photon {
                p: entry,
                d: dir,
                skip: Some(tri),
            };
            let mut length = 0.0;
            for k in 1..=MAX_COLLISIONS {
                let x: f64 = rng.random();
                let s = -(1.0 - x).ln() / sigma0;
                if !fly(scene, &mut ph, s) {
                    break;
                }
                length += s;
                if boundary == Boundary::Open
                    && crossings(scene, ph.p, geo.origin).is_multiple_of(2)
                {
                    // Beyond the open face's reach: not part of the medium.
                    break;
                }
                // Next event towards the pinhole.
                if let Some(r) = nee(scene, cam, geo.deg, centre, &ph, g, &|_, _, t| t) {
                    let l_cam = r.2;
                    out.push(Record {
                        u: r.0[0] as f32,
                        v: r.0[1] as f32,
                        k,
                        length: (length + l_cam) as f32,
                        ln_w: (ln_power + albedo0.ln() + r.1 + ln_fxfy - sigma0 * l_cam) as f32,
                    });
                }
                // Absorption by survival: the weight stays 1 and α_0^(k-1) is the chance to be here.
                if rng.random::<f64>() >= albedo0 {
                    break;
                }
                ph.d = sample_hg(ph.d, g, &mut rng);
                ph.skip = None;
            }
            out
        })
        .reduce(Vec::new, |mut a, mut b| {
            a.append(&mut b);
            a
        })
}

/// The next event from the photon's collision towards the camera: pixel coordinates, ln of the
/// phase function times the pinhole's radiance factor, and the medium to cross: the sum of
/// `depth` over its pieces (their length, or their optical depth).
pub(super) fn nee(
    scene: &Scene,
    cam: &Camera,
    deg: f64,
    centre: V3,
    ph: &Photon,
    g: f64,
    depth: &dyn Fn(V3, V3, f64) -> f64,
) -> Option<([f64; 2], f64, f64)> {
    let to_cam = normalize(sub(centre, ph.p))?;
    let world = crate::geometry::turntable_to_world(ph.p, deg);
    let c = cam.to_camera(world);
    let uv = cam.project_camera(c)?;
    let (w, h) = (cam.width as f64, cam.height as f64);
    let r = FILTER_RADIUS_PX;
    if uv[0] < -0.5 - r || uv[1] < -0.5 - r || uv[0] > w - 0.5 + r || uv[1] > h - 0.5 + r {
        return None;
    }
    let l_cam = medium_depth(scene, ph.p, centre, depth)?;
    // A point of intensity I (W/sr) at distance r seen by a pinhole pixel of solid angle
    // cos³θ / (f_x f_y) reads as the radiance I / r² / Ω = I f_x f_y r / z³.
    let range = dist(centre, ph.p);
    let z = c[2];
    let ln = hg(dot(ph.d, to_cam), g).ln() + range.ln() - 3.0 * z.ln();
    ln.is_finite().then_some((uv, ln, l_cam))
}

/// The filter's taps for a point at pixel coordinates (u, v): pixel index and weight, the
/// weights summing to 1 over the pixels inside the image (the energy that falls outside it is
/// lost, as on a sensor).
pub fn taps(u: f64, v: f64, width: usize, height: usize) -> impl Iterator<Item = (usize, f64)> {
    let r = FILTER_RADIUS_PX;
    let g = move |x: f64| {
        let s2 = 2.0 * FILTER_STDDEV_PX * FILTER_STDDEV_PX;
        ((-x * x / s2).exp() - (-r * r / s2).exp()).max(0.0)
    };
    let (i0, i1) = ((u - r).ceil().max(0.0) as i64, (u + r).floor() as i64);
    let (j0, j1) = ((v - r).ceil().max(0.0) as i64, (v + r).floor() as i64);
    // The filter's total over a whole pixel lattice, so that a point's weights sum to 1 before
    // the image's edge cuts them.
    let full: f64 = {
        let (fi0, fi1) = ((u - r).ceil() as i64, (u + r).floor() as i64);
        let (fj0, fj1) = ((v - r).ceil() as i64, (v + r).floor() as i64);
        let sx: f64 = (fi0..=fi1).map(|i| g(i as f64 - u)).sum();
        let sy: f64 = (fj0..=fj1).map(|j| g(j as f64 - v)).sum();
        sx * sy
    };
    let (w, h) = (width as i64, height as i64);
    (j0..=j1.min(h - 1)).flat_map(move |j| {
        (i0..=i1.min(w - 1)).filter_map(move |i| {
            let wt = g(i as f64 - u) * g(j as f64 - v) / full;
            (wt > 0.0 && full > 0.0).then_some(((j * w + i) as usize, wt))
        })
    })
}

/// The frame's image in the medium (σ_t, α) per channel, from the records of a trace in
/// `reference`.
pub fn image(
    records: &[Record],
    reference: &TraceSettings,
    sigma_t: [f64; 3],
    albedo: [f64; 3],
    width: usize,
    height: usize,
) -> Image {
    let mut img = Image::new(width, height, 3);
    for r in records {
        let w: [f64; 3] =
            std::array::from_fn(|c| r.ln_w_in(reference, sigma_t[c], albedo[c]).exp());
        for (p, t) in taps(r.u as f64, r.v as f64, width, height) {
            for (px, wc) in img.data[p * 3..p * 3 + 3].iter_mut().zip(&w) {
                *px += (wc * t) as f32;
            }
        }
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::shapes;

    /// The phase function integrates to 1 over the sphere and its samples have mean cosine g.
    #[test]
    fn henyey_greenstein_is_normalised_and_sampled_with_its_mean_cosine() {
        for g in [0.0, 0.3, 0.8, -0.5] {
            let n = 20_000;
            let integral: f64 = (0..n)
                .map(|i| {
                    let c = -1.0 + 2.0 * (i as f64 + 0.5) / n as f64;
                    hg(c, g) * 2.0 * std::f64::consts::PI * 2.0 / n as f64
                })
                .sum();
            assert!((integral - 1.0).abs() < 1e-3, "g {g}: {integral}");
            let mut rng = rand::rngs::StdRng::seed_from_u64(1);
            let m: f64 = (0..n)
                .map(|_| sample_hg([0.0, 0.0, 1.0], g, &mut rng)[2])
                .sum::<f64>()
                / n as f64;
            assert!((m - g).abs() < 0.02, "g {g}: mean cosine {m}");
        }
    }

    /// A box [-20, 20]² × [-20, 0] mm.
    fn block() -> Scene {
        Scene::new(shapes::block([-20.0, -20.0, -20.0], [20.0, 20.0, 0.0])).unwrap()
    }

    /// The images of a medium reweighted from a trace in another (the likelihood ratio) agree
    /// with a trace in that medium itself, within the noise; and the same seed traces the same
    /// paths.
    #[test]
    fn a_reweighted_trace_matches_a_trace_in_the_medium_itself() {
        let scene = block();
        assert_eq!(Boundary::of(&scene), Boundary::Closed);
        let cam = Camera::look_at(
            [0.0, -40.0, 110.0],
            [0.0; 3],
            [0.0, 1.0, 0.0],
            300.0,
            48,
            48,
        )
        .unwrap();
        let geo =
            FrameGeometry::new(&scene, &cam, 0.0, [0.0, 0.0, 50.0], [0.0, 0.0, -1.0]).unwrap();
        let at = |sigma_t: f64, albedo: f64, seed: u64| TraceSettings {
            sigma_t,
            albedo,
            g: 0.2,
            photons: 4000,
            seed,
            surface: Surface::IndexMatched,
        };
        let reference = at(1.5, 0.95, 3);
        let recs = trace_frame(&scene, Boundary::Closed, &geo, &reference, 0);
        assert_eq!(
            recs,
            trace_frame(&scene, Boundary::Closed, &geo, &reference, 0)
        );
        let total = |img: &Image| img.data.iter().map(|&x| x as f64).sum::<f64>();
        let moved = image(&recs, &reference, [1.2; 3], [0.9; 3], 48, 48);
        let direct_settings = at(1.2, 0.9, 4);
        let direct = trace_frame(&scene, Boundary::Closed, &geo, &direct_settings, 0);
        let direct = image(&direct, &direct_settings, [1.2; 3], [0.9; 3], 48, 48);
        let (a, b) = (total(&moved), total(&direct));
        assert!(b > 0.0 && (a / b - 1.0).abs() < 0.03, "{a} vs {b}");
        // And the medium matters: a lower albedo is darker by far more than the noise.
        let dark = image(&recs, &reference, [1.5; 3], [0.8; 3], 48, 48);
        assert!(total(&dark) < 0.7 * total(&image(&recs, &reference, [1.5; 3], [0.95; 3], 48, 48)));
    }

    /// The filter's taps sum to 1 inside the image and lose what falls outside it.
    #[test]
    fn filter_taps_conserve_the_light_inside_the_image() {
        let s: f64 = taps(10.3, 7.8, 32, 32).map(|t| t.1).sum();
        assert!((s - 1.0).abs() < 1e-12, "{s}");
        // On the image's edge (pixel coordinate -0.5) half the filter lies outside.
        let edge: f64 = taps(-0.5, 10.0, 32, 32).map(|t| t.1).sum();
        assert!((edge - 0.5).abs() < 1e-12, "{edge}");
    }

    /// A photon that leaves a face at a grazing angle has left: nothing is met again just past
    /// the face. (Re-casting from origins nudged sideways, as camera rays may, put one behind
    /// the face and met it again a few micrometres on.)
    #[test]
    fn a_grazing_exit_is_not_met_again() {
        let scene = block();
        let mut again = Vec::new();
        for deg in [0.1, 0.2, 0.5, 1.0, 2.0] {
            for k in 0..16 {
                let az = 2.0 * std::f64::consts::PI * (k as f64 + 0.3) / 16.0;
                let e = f64::to_radians(deg);
                let d = [e.cos() * az.cos(), e.cos() * az.sin(), e.sin()];
                let exit = [0.31 + 0.1 * k as f64, 0.17 - 0.05 * k as f64, 0.0];
                let start = add_scaled(exit, -1.0, d);
                let Some((t, hp, tri)) = next_hit(&scene, start, d, 5.0, None) else {
                    panic!("{deg}° {az}: the exit is not found");
                };
                assert!((t - 1.0).abs() < 1e-9, "{t}");
                if let Some(h) = next_hit(&scene, hp, d, f64::MAX, Some(tri)) {
                    again.push((deg, k, h.0));
                }
                let mut ph = Photon {
                    p: start,
                    d,
                    skip: None,
                };
                if fly(&scene, &mut ph, 5.0) {
                    again.push((deg, k, -1.0));
                }
            }
        }
        assert!(again.is_empty(), "met again: {again:?}");
    }
}
