//! A heterogeneous medium grown from the frames: each frame's own homogeneous medium (the
//! medium the light around its x_i saw), spread through the object by a Gaussian kernel in
//! space and shrunk towards the whole scan's medium, on a grid of cells that the tracer then
//! renders as it is.
//!
//! The light of a laser frame of a dense, high-albedo object stays within a few millimetres of
//! x_i, so a frame's rings say little about the medium elsewhere: a frame alone fits a
//! homogeneous medium well (on sample-torus a frame's ring loss is 0.02-0.09 where one medium
//! for all frames leaves 0.37), and the object's medium is where those local media agree. How
//! far a frame's medium reaches (the kernel's width h) and how strongly the whole scan's medium
//! holds where few frames look (the shrinkage weight p) are the regulariser, chosen by
//! cross-validation over whole turntable angles of the training frames, the scan's medium
//! itself (no heterogeneity) among the candidates.

use super::fit::{FrameRings, Homogeneous, HomogeneousFit, VolumeFitError, fit_homogeneous};
use super::medium::{GridChannel, grid_image};
use super::trace::Boundary;
use crate::dataset::{Dataset, Image};
use crate::geometry::{Scene, V3, dist};

/// One frame's own medium.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalMedium {
    /// Frame index.
    pub frame: usize,
    /// Its x_i, object frame, mm.
    pub x_i: V3,
    /// (ln σ_t, ln(1 − α)) per channel.
    pub theta: [[f64; 2]; 3],
    /// Rings the frame's fit judged (green): its weight grows as their square root.
    pub rings: usize,
}

/// How the heterogeneous medium is grown and chosen.
#[derive(Debug, Clone)]
pub struct LocalFit {
    /// The whole scan's medium fit (also each frame's start).
    pub global: HomogeneousFit,
    /// Photons per frame and round of each frame's own fit.
    pub photons: usize,
    /// Rounds of each frame's own fit.
    pub rounds: usize,
    /// A frame's own fit must judge this many rings (green) to count.
    pub min_rings: usize,
    /// Kernel widths tried, mm.
    pub bandwidths: Vec<f64>,
    /// Shrinkage weights tried.
    pub shrinkage: Vec<f64>,
    /// Cells along the mesh's longest side (cubic cells).
    pub cells: usize,
    /// Photons per frame and channel of the cross-validation's traces.
    pub cv_photons: usize,
    /// Folds of the cross-validation (whole turntable angles).
    pub folds: usize,
}

/// A candidate's cross-validated ring loss.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    /// Kernel width, mm (`None`: the scan's homogeneous medium).
    pub bandwidth: Option<f64>,
    /// Shrinkage weight.
    pub shrinkage: f64,
    /// Mean squared log ratio of the held-out folds' ring sums (all channels).
    pub loss: f64,
    /// Rings judged.
    pub rings: usize,
}

/// The grown medium and how it was chosen.
#[derive(Debug, Clone)]
pub struct Grown {
    /// The whole scan's homogeneous medium.
    pub global: Homogeneous,
    /// Each usable frame's own medium.
    pub locals: Vec<LocalMedium>,
    /// Every candidate's cross-validated loss, the chosen one first.
    pub candidates: Vec<Candidate>,
    /// The chosen medium per channel.
    pub grid: [GridChannel; 3],
}

/// A homogeneous medium as (ln σ_t, ln(1 − α)) per channel.
pub(super) fn theta_of(m: &Homogeneous) -> [[f64; 2]; 3] {
    std::array::from_fn(|c| [m.sigma_t[c].ln(), (1.0 - m.albedo[c]).ln()])
}

/// The medium at `x`: the locals' kernel-weighted mean in (ln σ_t, ln(1 − α)), with the scan's
/// medium at weight `p`.
pub fn interpolate(
    locals: &[&LocalMedium],
    x: V3,
    h: f64,
    p: f64,
    global: &[[f64; 2]; 3],
) -> [[f64; 2]; 3] {
    let mut num = global.map(|t| [p * t[0], p * t[1]]);
    let mut den = p;
    for l in locals {
        let d = dist(l.x_i, x);
        let w = (-(d * d) / (2.0 * h * h)).exp() * (l.rings as f64).sqrt();
        den += w;
        for (n, t) in num.iter_mut().zip(&l.theta) {
            n[0] += w * t[0];
            n[1] += w * t[1];
        }
    }
    if den > 0.0 {
        num.map(|t| [t[0] / den, t[1] / den])
    } else {
        *global
    }
}

/// The grid over the mesh's bounds with each cell's medium from `value` at its centre.
pub fn grid_of(
    scene: &Scene,
    cells: usize,
    value: &dyn Fn(V3) -> [[f64; 2]; 3],
) -> [GridChannel; 3] {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &scene.mesh.positions {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let side = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max).max(1e-6);
    let cell = side / cells.max(1) as f64;
    let dims: [usize; 3] =
        std::array::from_fn(|a| (((hi[a] - lo[a]) / cell).ceil() as usize).max(1));
    let n = dims[0] * dims[1] * dims[2];
    let mut out: [GridChannel; 3] = std::array::from_fn(|_| GridChannel {
        origin: lo,
        cell_mm: [cell; 3],
        dims,
        sigma_t: Vec::with_capacity(n),
        albedo: Vec::with_capacity(n),
    });
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let c = [x, y, z];
                let centre: V3 = std::array::from_fn(|a| lo[a] + (c[a] as f64 + 0.5) * cell);
                let t = value(centre);
                for (ch, g) in out.iter_mut().enumerate() {
                    g.sigma_t.push(t[ch][0].exp());
                    g.albedo.push(1.0 - t[ch][1].exp());
                }
            }
        }
    }
    out
}

/// The ring sums of an image over a frame's rings (what [`FrameRings::data`] holds for the
/// frame's own image).
pub fn image_rings(frame: &FrameRings, img: &Image) -> Vec<[f64; 3]> {
    super::fit::ring_sums_of(&frame.pixel_ring, frame.rings, img, 1.0)
}

/// Squared log ratios of a frame's judged rings (the data's mean above `floor`, at least 4
/// pixels, the model's sum positive): their sum and count.
fn ring_loss(frame: &FrameRings, model: &[[f64; 3]], floor: f64) -> (f64, usize) {
    let (mut sum, mut n) = (0.0, 0);
    for (j, m) in model.iter().enumerate() {
        let cnt = frame.count[j];
        for (&mc, &d) in m.iter().zip(&frame.data[j]) {
            if cnt >= 4 && d > cnt as f64 * floor && mc > 0.0 {
                let r = (mc / d).ln();
                sum += r * r;
                n += 1;
            }
        }
    }
    (sum, n)
}

/// Grows the heterogeneous medium of `frames` (module docs). `progress` hears what each step
/// did, in words.
pub fn grow(
    ds: &Dataset,
    frames: &[usize],
    opts: &LocalFit,
    progress: &dyn Fn(&str),
) -> Result<Grown, VolumeFitError> {
    let scene = Scene::new(ds.mesh.clone())?;
    let boundary = Boundary::of(&scene);
    let global = fit_homogeneous(ds, frames, &opts.global, &|_, _| {})?;
    progress(&format!(
        "the scan's medium: sigma_t {:.3?} /mm, albedo {:.4?}",
        global.sigma_t, global.albedo
    ));
    let gtheta = theta_of(&global);
    let start = (
        (global.sigma_t.iter().map(|s| s.ln()).sum::<f64>() / 3.0).exp(),
        global.albedo[1],
    );
    let mut locals = Vec::new();
    let mut rings_of = Vec::new();
    for &k in frames {
        let Some(geo) = super::fit::frame_geometry(&scene, ds, k) else {
            continue;
        };
        let own = HomogeneousFit {
            photons: opts.photons,
            rounds: opts.rounds,
            start,
            ..opts.global.clone()
        };
        // A frame whose rings are all below the floor has no medium of its own.
        let Ok(m) = fit_homogeneous(ds, &[k], &own, &|_, _| {}) else {
            continue;
        };
        if m.loss[1].1 < opts.min_rings {
            continue;
        }
        let img = ds.read_frame(k)?;
        let exposure = ds.spec.frames[k].exposure_s;
        rings_of.push(FrameRings::new(&scene, geo.clone(), k, &img, exposure));
        locals.push(LocalMedium {
            frame: k,
            x_i: geo.x_i,
            theta: theta_of(&m),
            rings: m.loss[1].1,
        });
    }
    progress(&format!(
        "{} frames with a medium of their own",
        locals.len()
    ));
    let (folds, _) = crate::crossval::folds(
        ds,
        &locals.iter().map(|l| l.frame).collect::<Vec<_>>(),
        opts.folds,
    );
    let mut cands: Vec<(Option<f64>, f64)> = vec![(None, 0.0)];
    for &h in &opts.bandwidths {
        for &p in &opts.shrinkage {
            cands.push((Some(h), p));
        }
    }
    let mut scored = Vec::new();
    for (h, p) in cands {
        let (mut sum, mut n) = (0.0, 0usize);
        for fold in &folds {
            let train: Vec<&LocalMedium> =
                locals.iter().filter(|l| !fold.contains(&l.frame)).collect();
            let value = |x: V3| match h {
                Some(h) => interpolate(&train, x, h, p, &gtheta),
                None => gtheta,
            };
            let grid = grid_of(&scene, opts.cells, &value);
            for fr in rings_of.iter().filter(|f| fold.contains(&f.frame)) {
                let img = grid_image(
                    &scene,
                    boundary,
                    &fr.geo,
                    &grid,
                    opts.global.g,
                    opts.global.surface,
                    opts.cv_photons,
                    opts.global.seed ^ 0x5eed,
                    fr.frame,
                );
                let (s, k) = ring_loss(fr, &image_rings(fr, &img), opts.global.floor);
                sum += s;
                n += k;
            }
        }
        let loss = if n > 0 { sum / n as f64 } else { f64::INFINITY };
        progress(&format!(
            "cross-validation: h {h:?} mm, p {p}: ring loss {loss:.4} over {n} rings"
        ));
        scored.push(Candidate {
            bandwidth: h,
            shrinkage: p,
            loss,
            rings: n,
        });
    }
    scored.sort_by(|a, b| a.loss.total_cmp(&b.loss));
    let best = scored.first().cloned().ok_or(VolumeFitError::NoFrames)?;
    let all: Vec<&LocalMedium> = locals.iter().collect();
    let value = |x: V3| match best.bandwidth {
        Some(h) => interpolate(&all, x, h, best.shrinkage, &gtheta),
        None => gtheta,
    };
    let grid = grid_of(&scene, opts.cells, &value);
    Ok(Grown {
        global,
        locals,
        candidates: scored,
        grid,
    })
}
