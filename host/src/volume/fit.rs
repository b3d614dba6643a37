//! A homogeneous medium (σ_t and α per channel) fitted to a scan's frames through the tracer.
//!
//! The fit compares rings, not pixels: each frame's judged pixels are grouped by the distance of
//! the surface point they see from x_i (log-spaced, four rings per factor e), and the loss is the
//! squared difference of the logs of the ring sums. A ring sums many pixels and many photons, so
//! the tracer's noise falls in it; a per-pixel loss of noisy predictions is biased (the log of a
//! noisy prediction is low on average), and the bias pulls α towards 1.
//!
//! Each channel's rings depend on its own (σ_t, α) only, so the three channels are fitted apart
//! from one trace: the records' likelihood ratios give every channel's rings and their
//! derivatives in closed form. Each round re-traces at the estimate so that the ratios stay
//! near 1.

use super::dielectric::Surface;
use super::trace::{Boundary, FrameGeometry, Record, TraceSettings, geo_mean, taps, trace_frame};
use crate::dataset::{Dataset, Image};
use crate::geometry::{
    Scene, V3, add_scaled, cross, dist, dot, normalize, sub, world_to_turntable,
};

/// Rings per factor e of distance from x_i.
pub const RINGS_PER_E: f64 = 4.0;
/// The innermost ring's inner edge, mm.
pub const RING_START_MM: f64 = 0.1;
/// Pixels closer than this to x_i are not judged (the spot itself: the laser's footprint and
/// the single scattering under it depend on the beam's shape, which the frames do not give).
pub const EXCLUDE_MM: f64 = 0.5;
/// Pixels farther than this from x_i are not judged.
pub const OUTER_MM: f64 = 15.0;

/// Gauss-Newton steps per round. Few: a step is taken from the records' likelihood ratios,
/// which are exact at the round's reference and grow heavy-tailed away from it (their typical
/// sum is low there), so a fit run to convergence within one trace stops short of the medium
/// that explains the frames. A couple of steps per fresh trace follow the valley of (σ, α)
/// instead (on sample-slab from 1.3/mm, 0.96 it reaches the published medium in about ten
/// rounds of 1,000 photons a frame).
pub const STEPS: usize = 2;

/// Records a ring needs in a round's trace to be judged in that round.
pub const MIN_RECORDS: usize = 50;

/// Ring index of a distance from x_i (`None` outside the judged band).
pub fn ring_of(d: f64) -> Option<u32> {
    (EXCLUDE_MM..=OUTER_MM)
        .contains(&d)
        .then(|| (RINGS_PER_E * (d / RING_START_MM).ln()).floor().max(0.0) as u32)
}

/// Inner edge of ring `j`, mm.
pub fn ring_edge(j: u32) -> f64 {
    RING_START_MM * (j as f64 / RINGS_PER_E).exp()
}

/// One frame as the fit sees it: its geometry, each pixel's ring (or none) and the data's ring
/// sums.
#[derive(Debug, Clone)]
pub struct FrameRings {
    /// Frame index in the dataset.
    pub frame: usize,
    /// The laser's entry and the camera.
    pub geo: FrameGeometry,
    /// Per pixel (row-major) its ring, `u32::MAX` for none.
    pub pixel_ring: Vec<u32>,
    /// Rings in this frame (`max ring + 1`).
    pub rings: usize,
    /// Per ring its judged pixels.
    pub count: Vec<usize>,
    /// Per ring and channel the data's sum of radiance.
    pub data: Vec<[f64; 3]>,
}

/// Each pixel's bin around x_i: the ring of the surface point the pixel's centre sees (the first
/// hit of the camera ray, through the camera's distortion as the tracer projects with it), by its
/// distance from x_i, split into `sectors` equal sectors of azimuth about the laser's direction
/// (bin `ring · sectors + sector`; with one sector the bin is the ring), so that light that leaves
/// one side of the spot brighter than the other is seen as such (a ring sum averages a vein on
/// one side with the clear medium on the other). The sectors start from the turntable's axis
/// projected across the beam (its x axis where the beam runs along it).
pub fn pixel_bins(scene: &Scene, geo: &FrameGeometry, sectors: usize) -> Vec<u32> {
    let cam = &geo.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let sectors = sectors.max(1);
    let (e1, e2) = beam_frame(geo.dir);
    (0..w * h)
        .map(|p| {
            let (i, j) = ((p % w) as f64, (p / w) as f64);
            let Some((origin, world_dir)) = cam.ray(i, j) else {
                return u32::MAX;
            };
            let Some(d) = normalize(world_to_turntable(world_dir, geo.deg)) else {
                return u32::MAX;
            };
            let Some(hit) = scene.cast(world_to_turntable(origin, geo.deg), d, f64::MAX) else {
                return u32::MAX;
            };
            let Some(ring) = ring_of(dist(hit.point, geo.x_i)) else {
                return u32::MAX;
            };
            let o = sub(hit.point, geo.x_i);
            let (a, b) = (dot(o, e1), dot(o, e2));
            let turn = (b.atan2(a) / std::f64::consts::TAU).rem_euclid(1.0);
            let sector = ((turn * sectors as f64) as usize).min(sectors - 1);
            ring * sectors as u32 + sector as u32
        })
        .collect()
}

/// Two unit vectors across the beam `dir`: the turntable's axis (z) with its part along the beam
/// taken out (x where the beam is within 25 degrees of the axis), and the beam crossed with it.
fn beam_frame(dir: V3) -> (V3, V3) {
    let axis = if dir[2].abs() < 0.9 {
        [0.0, 0.0, 1.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let e1 = normalize(add_scaled(axis, -dot(axis, dir), dir)).unwrap_or([1.0, 0.0, 0.0]);
    (e1, cross(dir, e1))
}

impl FrameRings {
    /// The frame's rings and the data's sums from its image (radiance, as
    /// [`Dataset::read_frame`] gives it divided by the exposure).
    pub fn new(
        scene: &Scene,
        geo: FrameGeometry,
        frame: usize,
        img: &Image,
        exposure_s: f64,
    ) -> FrameRings {
        FrameRings::with_sectors(scene, geo, frame, img, exposure_s, 1)
    }

    /// [`FrameRings::new`] with each ring split into `sectors` ([`pixel_bins`]).
    pub fn with_sectors(
        scene: &Scene,
        geo: FrameGeometry,
        frame: usize,
        img: &Image,
        exposure_s: f64,
        sectors: usize,
    ) -> FrameRings {
        let pixel_ring = pixel_bins(scene, &geo, sectors);
        let rings = pixel_ring
            .iter()
            .filter(|&&r| r != u32::MAX)
            .map(|&r| r as usize + 1)
            .max()
            .unwrap_or(0);
        let mut count = vec![0; rings];
        for &r in pixel_ring.iter().filter(|&&r| r != u32::MAX) {
            count[r as usize] += 1;
        }
        let data = ring_sums_of(&pixel_ring, rings, img, exposure_s);
        FrameRings {
            frame,
            geo,
            pixel_ring,
            rings,
            count,
            data,
        }
    }
}

/// Per ring and channel the sum of an image's radiance (its values divided by `exposure_s`)
/// over the pixels `pixel_ring` puts in the ring; values that are not finite are left out.
pub fn ring_sums_of(
    pixel_ring: &[u32],
    rings: usize,
    img: &Image,
    exposure_s: f64,
) -> Vec<[f64; 3]> {
    let mut data = vec![[0.0; 3]; rings];
    for (p, &r) in pixel_ring.iter().enumerate() {
        if r == u32::MAX {
            continue;
        }
        for (c, d) in data[r as usize].iter_mut().enumerate() {
            let ch = if img.channels == 3 { c } else { 0 };
            let v = img.data[p * img.channels + ch] as f64 / exposure_s;
            if v.is_finite() {
                *d += v;
            }
        }
    }
    data
}

/// A record's share of one ring: the filter's taps that land on the ring's pixels, summed.
#[derive(Debug, Clone, Copy)]
pub struct RingRecord {
    /// Global ring index (over all frames).
    pub ring: u32,
    /// Collisions.
    pub k: u32,
    /// Medium length, mm.
    pub length: f32,
    /// ln of the contribution to the ring's sum in the reference medium.
    pub ln_w: f32,
}

/// Into `share`, the rings a point at pixel coordinates (u, v) lands on through the filter's
/// taps, each with the taps' weight on the ring's pixels summed (rings of `pixel_ring`, an image
/// of `w` × `h`).
pub(super) fn ring_shares(
    pixel_ring: &[u32],
    u: f64,
    v: f64,
    w: usize,
    h: usize,
    share: &mut Vec<(u32, f64)>,
) {
    share.clear();
    for (p, t) in taps(u, v, w, h) {
        let ring = pixel_ring[p];
        if ring == u32::MAX {
            continue;
        }
        match share.iter_mut().find(|s| s.0 == ring) {
            Some(s) => s.1 += t,
            None => share.push((ring, t)),
        }
    }
}

/// The frames' records distributed over their rings.
pub fn ring_records(frame: &FrameRings, first_ring: u32, records: &[Record]) -> Vec<RingRecord> {
    let (w, h) = (
        frame.geo.camera.width as usize,
        frame.geo.camera.height as usize,
    );
    let mut out = Vec::with_capacity(records.len());
    let mut share: Vec<(u32, f64)> = Vec::with_capacity(4);
    for r in records {
        ring_shares(&frame.pixel_ring, r.u as f64, r.v as f64, w, h, &mut share);
        for &(ring, t) in &share {
            out.push(RingRecord {
                ring: first_ring + ring,
                k: r.k,
                length: r.length,
                ln_w: r.ln_w + t.ln() as f32,
            });
        }
    }
    out
}

/// The ring sums of one channel in the medium (σ, α), with their derivatives in
/// (ln σ, ln(1 − α)).
fn ring_sums(
    recs: &[RingRecord],
    rings: usize,
    reference: &TraceSettings,
    sigma: f64,
    albedo: f64,
) -> Vec<[f64; 3]> {
    use rayon::prelude::*;
    let a = (sigma / reference.sigma_t).ln() + (albedo / reference.albedo).ln();
    let b = sigma - reference.sigma_t;
    let da2 = -(1.0 - albedo) / albedo;
    recs.par_chunks(1 << 16)
        .fold(
            || vec![[0.0; 3]; rings],
            |mut acc, chunk| {
                for r in chunk {
                    let (k, l) = (r.k as f64, r.length as f64);
                    let e = (r.ln_w as f64 + k * a - b * l).exp();
                    let s = &mut acc[r.ring as usize];
                    s[0] += e;
                    s[1] += e * (k - sigma * l);
                    s[2] += e * k * da2;
                }
                acc
            },
        )
        .reduce(
            || vec![[0.0; 3]; rings],
            |mut x, y| {
                for (a, b) in x.iter_mut().zip(&y) {
                    for c in 0..3 {
                        a[c] += b[c];
                    }
                }
                x
            },
        )
}

/// What the fit is given.
#[derive(Debug, Clone)]
pub struct HomogeneousFit {
    /// Photons per frame and round.
    pub photons: usize,
    /// Rounds of trace-and-fit.
    pub rounds: usize,
    /// Henyey-Greenstein asymmetry, held fixed.
    pub g: f64,
    /// The start: extinction 1/mm and albedo for every channel.
    pub start: (f64, f64),
    /// A ring's mean radiance must exceed this (the data's noise floor) to be judged.
    pub floor: f64,
    /// Seed of the common random numbers.
    pub seed: u64,
    /// The boundary the medium is traced behind, held fixed.
    pub surface: Surface,
}

/// The fitted medium.
#[derive(Debug, Clone, PartialEq)]
pub struct Homogeneous {
    /// Extinction per channel, 1/mm.
    pub sigma_t: [f64; 3],
    /// Single-scattering albedo per channel.
    pub albedo: [f64; 3],
    /// Henyey-Greenstein asymmetry.
    pub g: f64,
    /// The boundary it lies behind.
    pub surface: Surface,
    /// Per channel the ring loss at the end (mean squared log ratio) and the rings judged.
    pub loss: [(f64, usize); 3],
}

/// Why a volume fit could not run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VolumeFitError {
    /// No frame has a laser ray that meets the mesh.
    #[error("no frame to fit: none of the frames given has a laser ray that meets the mesh")]
    NoFrames,
    /// No ring is above the floor in some channel.
    #[error("channel {0}: no ring of any frame is above the noise floor")]
    NoRings(usize),
    /// A grid fit was started from a homogeneous medium traced behind another boundary than
    /// its own: the start and the grid must share the surface.
    #[error("the grid's boundary is not the one its homogeneous start was fitted behind")]
    BoundaryMismatch,
    /// The dataset could not be read.
    #[error(transparent)]
    Dataset(#[from] crate::dataset::DatasetError),
    /// The mesh could not be prepared.
    #[error(transparent)]
    Geometry(#[from] crate::geometry::GeometryError),
}

/// The frames' geometry from the dataset's laser rays (frames without one, or whose ray misses
/// the mesh, are left out).
pub fn frame_geometry(scene: &Scene, ds: &Dataset, k: usize) -> Option<FrameGeometry> {
    let f = ds.spec.frames.get(k)?;
    let laser = f.laser.as_ref()?;
    let cam = ds.spec.cameras.get(f.camera)?;
    FrameGeometry::new(scene, cam, f.turntable_deg, laser.origin, laser.direction)
}

/// The frames' rings, each in `sectors` ([`pixel_bins`]; frames whose laser ray misses the mesh
/// left out).
pub(super) fn frame_rings(
    scene: &Scene,
    ds: &Dataset,
    frames: &[usize],
    sectors: usize,
) -> Result<Vec<FrameRings>, VolumeFitError> {
    let mut out = Vec::new();
    for &k in frames {
        let Some(geo) = frame_geometry(scene, ds, k) else {
            continue;
        };
        let img = ds.read_frame(k)?;
        let exposure = ds.spec.frames[k].exposure_s;
        out.push(FrameRings::with_sectors(
            scene, geo, k, &img, exposure, sectors,
        ));
    }
    Ok(out)
}

/// Per channel the judged rings: (global ring, ln of the data's sum).
pub(super) type ChannelRings = [Vec<(usize, f64)>; 3];

/// Per channel the rings judged: (global ring over all `frames`, ln of the data's sum), the
/// data's mean above `floor` and at least 4 pixels; each frame's first global ring; the rings
/// in all.
pub(super) fn judged_rings(frames: &[FrameRings], floor: f64) -> (ChannelRings, Vec<u32>, usize) {
    let mut data: ChannelRings = Default::default();
    let mut first = Vec::with_capacity(frames.len());
    let mut total = 0usize;
    for f in frames {
        first.push(total as u32);
        for j in 0..f.rings {
            for (c, d) in data.iter_mut().enumerate() {
                let n = f.count[j];
                if n >= 4 && f.data[j][c] > n as f64 * floor {
                    d.push((total + j, f.data[j][c].ln()));
                }
            }
        }
        total += f.rings;
    }
    (data, first, total)
}

/// Fits a homogeneous medium to the frames `frames` of `ds` (module docs).
pub fn fit_homogeneous(
    ds: &Dataset,
    frames: &[usize],
    opts: &HomogeneousFit,
    progress: &dyn Fn(usize, &Homogeneous),
) -> Result<Homogeneous, VolumeFitError> {
    let scene = Scene::new(ds.mesh.clone())?;
    let boundary = Boundary::of(&scene);
    let judged = frame_rings(&scene, ds, frames, 1)?;
    if judged.is_empty() {
        return Err(VolumeFitError::NoFrames);
    }
    let (data, first, total) = judged_rings(&judged, opts.floor);
    for (c, d) in data.iter().enumerate() {
        if d.is_empty() {
            return Err(VolumeFitError::NoRings(c));
        }
    }
    let mut model = Homogeneous {
        sigma_t: [opts.start.0; 3],
        albedo: [opts.start.1; 3],
        g: opts.g,
        surface: opts.surface,
        loss: [(f64::INFINITY, 0); 3],
    };
    for round in 0..opts.rounds {
        let sigma0 = geo_mean(&model.sigma_t);
        let alpha_max = model.albedo.iter().cloned().fold(0.0, f64::max);
        // Not `TraceSettings::for_medium`: the fit keeps each α at most the reference's, so the
        // reference albedo sits halfway from the largest estimate to 1, leaving α room to rise.
        let reference = TraceSettings {
            sigma_t: sigma0,
            albedo: 1.0 - 0.5 * (1.0 - alpha_max),
            g: opts.g,
            photons: opts.photons,
            seed: opts.seed ^ round as u64,
            surface: opts.surface,
        };
        let mut recs = Vec::new();
        for (fi, f) in judged.iter().enumerate() {
            let r = trace_frame(&scene, boundary, &f.geo, &reference, f.frame);
            recs.extend(ring_records(f, first[fi], &r));
        }
        // Rings the trace reached with too few records to be more than noise are left out of
        // this round (a ring the trace left dark would read as infinitely far off).
        let mut hits = vec![0usize; total];
        for r in &recs {
            hits[r.ring as usize] += 1;
        }
        for (c, rings_c) in data.iter().enumerate() {
            let judged: Vec<(usize, f64)> = rings_c
                .iter()
                .copied()
                .filter(|&(ring, _)| hits[ring] >= MIN_RECORDS)
                .collect();
            if judged.is_empty() {
                return Err(VolumeFitError::NoRings(c));
            }
            let (s, a, loss) = fit_channel(
                &recs,
                total,
                &judged,
                &reference,
                (model.sigma_t[c], model.albedo[c]),
            );
            model.sigma_t[c] = s;
            model.albedo[c] = a;
            model.loss[c] = (loss, judged.len());
        }
        progress(round, &model);
    }
    Ok(model)
}

/// One channel's (σ, α) by damped Gauss-Newton on the rings' log ratios, in (ln σ, ln(1 − α)),
/// kept inside the box where the records' likelihood ratios stay bounded (σ within a factor 2
/// of the reference, α at most the reference's). Two parameters in a box: a damped
/// Gauss-Newton with projection is a few lines, where the least-squares crates have no bounds.
fn fit_channel(
    recs: &[RingRecord],
    rings: usize,
    data: &[(usize, f64)],
    reference: &TraceSettings,
    start: (f64, f64),
) -> (f64, f64, f64) {
    let lo = [
        (reference.sigma_t / 2.0).ln(),
        (1.0 - reference.albedo).ln(),
    ];
    let hi = [(reference.sigma_t * 2.0).ln(), (0.5f64).ln()];
    let clamp = |t: [f64; 2]| [t[0].clamp(lo[0], hi[0]), t[1].clamp(lo[1], hi[1])];
    let eval = |t: [f64; 2]| {
        let (s, a) = (t[0].exp(), 1.0 - t[1].exp());
        let sums = ring_sums(recs, rings, reference, s, a);
        let mut loss = 0.0;
        let (mut jtj, mut jtr) = ([[0.0; 2]; 2], [0.0; 2]);
        for &(ring, ln_d) in data {
            let m = sums[ring];
            // A ring the trace left dark counts as far below the data, with no gradient.
            let (res, g) = if m[0] > 0.0 {
                (m[0].ln() - ln_d, [m[1] / m[0], m[2] / m[0]])
            } else {
                (-(f64::MAX.ln()), [0.0, 0.0])
            };
            loss += res * res;
            for x in 0..2 {
                jtr[x] += g[x] * res;
                for y in 0..2 {
                    jtj[x][y] += g[x] * g[y];
                }
            }
        }
        (loss / data.len() as f64, jtj, jtr)
    };
    let mut t = clamp([start.0.ln(), (1.0 - start.1).max(1e-12).ln()]);
    let (mut loss, mut jtj, mut jtr) = eval(t);
    let mut lambda = 1e-3;
    for _ in 0..STEPS {
        let a = [
            [jtj[0][0] * (1.0 + lambda) + 1e-12, jtj[0][1]],
            [jtj[1][0], jtj[1][1] * (1.0 + lambda) + 1e-12],
        ];
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        if det.abs() < 1e-300 || !det.is_finite() {
            break;
        }
        let step = [
            -(a[1][1] * jtr[0] - a[0][1] * jtr[1]) / det,
            -(a[0][0] * jtr[1] - a[1][0] * jtr[0]) / det,
        ];
        let next = clamp([t[0] + step[0], t[1] + step[1]]);
        let (l2, j2, r2) = eval(next);
        if l2 < loss {
            let moved = (next[0] - t[0]).abs() + (next[1] - t[1]).abs();
            (t, loss, jtj, jtr) = (next, l2, j2, r2);
            lambda = (lambda / 3.0).max(1e-9);
            if moved < 1e-6 {
                break;
            }
        } else {
            lambda *= 4.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    (t[0].exp(), 1.0 - t[1].exp(), loss)
}

/// The frames `frames` of `ds` predicted in the medium `model` with `photons` per frame, as
/// images (radiance per watt of laser, the dataset's units); frames whose laser ray misses the
/// mesh come out black.
pub fn predict(
    ds: &Dataset,
    frames: &[usize],
    model: &Homogeneous,
    photons: usize,
    seed: u64,
) -> Result<Vec<(usize, Image)>, VolumeFitError> {
    let scene = Scene::new(ds.mesh.clone())?;
    let boundary = Boundary::of(&scene);
    frames
        .iter()
        .map(|&k| {
            Ok((
                k,
                predict_in(&scene, boundary, ds, k, model, photons, seed)?,
            ))
        })
        .collect()
}

/// Frame `k` of `ds` predicted in the medium `model` inside the mesh of `scene` ([`predict`]).
pub fn predict_in(
    scene: &Scene,
    boundary: Boundary,
    ds: &Dataset,
    k: usize,
    model: &Homogeneous,
    photons: usize,
    seed: u64,
) -> Result<Image, VolumeFitError> {
    let reference = TraceSettings {
        surface: model.surface,
        ..TraceSettings::for_medium(model.sigma_t, model.albedo, model.g, photons, seed)
    };
    frame_image(scene, ds, k, &|geo, w, h| {
        let r = trace_frame(scene, boundary, geo, &reference, k);
        super::trace::image(&r, &reference, model.sigma_t, model.albedo, w, h)
    })
}

/// Frame `k`'s image drawn by `draw` (given the frame's geometry and the image's size), black
/// where the frame's laser ray misses the mesh; an error for a frame or camera the scan lacks.
pub fn frame_image(
    scene: &Scene,
    ds: &Dataset,
    k: usize,
    draw: &dyn Fn(&FrameGeometry, usize, usize) -> Image,
) -> Result<Image, VolumeFitError> {
    let f = ds
        .spec
        .frames
        .get(k)
        .ok_or_else(|| crate::dataset::DatasetError::Invalid(format!("no frame {k}")))?;
    let cam =
        ds.spec.cameras.get(f.camera).ok_or_else(|| {
            crate::dataset::DatasetError::Invalid(format!("frame {k}: no camera"))
        })?;
    let (w, h) = (cam.width as usize, cam.height as usize);
    Ok(match frame_geometry(scene, ds, k) {
        Some(geo) => draw(&geo, w, h),
        None => Image::new(w, h, 3),
    })
}

/// The ring sums of `records` (one frame's trace in `reference`) in the medium (σ_t, α) per
/// channel: what [`FrameRings::data`] holds for the frame's own image.
pub fn model_rings(
    frame: &FrameRings,
    records: &[Record],
    reference: &TraceSettings,
    sigma_t: [f64; 3],
    albedo: [f64; 3],
) -> Vec<[f64; 3]> {
    let recs = ring_records(frame, 0, records);
    let mut out = vec![[0.0; 3]; frame.rings];
    for c in 0..3 {
        for (j, s) in ring_sums(&recs, frame.rings, reference, sigma_t[c], albedo[c])
            .iter()
            .enumerate()
        {
            out[j][c] = s[0];
        }
    }
    out
}
