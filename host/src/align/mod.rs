//! `subsurf align`: the user's mesh placed in the object frame from the scan itself (the paper's
//! first step, "register images to the mesh", for a mesh made by another scanner in its own pose
//! and units).
//!
//! The evidence ([`evidence`]): each frame's laser spot, found without the mesh, gives a camera
//! ray; crossed with the frame's laser ray it is a surface point in the world frame, turned into
//! the object frame by the frame's turntable angle. The estimate: a similarity transform (rotation,
//! translation, uniform scale) from the mesh file's frame to the object frame, from any starting
//! pose — global initialisation over principal-axis matchings ([`search`]), robust point-to-point
//! ICP with scale from each, the best few refined by robust point-to-plane ICP ([`icp`]). The
//! judgement: the residuals (mm, pixels, inlier share) against stated bounds; the pose's
//! uncertainty from the normal matrix, where a direction the spots cannot fix is either a symmetry
//! of the surface (reported: a body of revolution about the turntable axis needs no angle) or a
//! refusal; a second pose with a different surface that fits about as well is a refusal too.
//!
//! [`check`] is `subsurf fit`'s cheap test that a dataset's mesh is where its spots are.
//! Reads frames only through [`Dataset::read_frame`]; writes nothing (the command records the
//! result through [`Dataset::record_alignment`]).
use rayon::prelude::*;

use crate::dataset::{Alignment, Dataset, DatasetError, Mesh, Symmetry};
use crate::geometry::{GeometryError, Scene, V3, cross, dot, sub};
use crate::progress::Progress;

pub mod check;
mod depth;
pub mod evidence;
mod icp;
mod search;
mod similarity;

pub use check::{CheckError, MeshCheck, check_mesh, check_spots};
pub use depth::{DepthModel, REFRACTIVE_INDEX};
pub use evidence::{Evidence, EvidenceOptions, NoPoint, SpotPoint, spot_points, triangulate};
pub use similarity::Similarity;

use icp::{Mat7, Problem, Refined, displacement_rows, median};
use similarity::v;

/// Why the pose could not be estimated.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AlignError {
    /// The dataset could not be read.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// The mesh could not be prepared for queries.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// Too few frames gave a triangulated spot.
    #[error(
        "{points} of {frames} frames gave a laser spot on the frame's laser ray ({no_laser_ray} \
         without a laser ray in scan.json, {no_spot} without a spot, {rays_apart} whose brightest \
         pixel is off the laser ray); at least {needed} are needed to fix a pose"
    )]
    TooFewSpots {
        /// Points found.
        points: usize,
        /// Points needed.
        needed: usize,
        /// Frames looked at.
        frames: usize,
        /// Frames without a laser ray.
        no_laser_ray: usize,
        /// Frames without a spot.
        no_spot: usize,
        /// Frames whose spot was off the laser ray.
        rays_apart: usize,
    },
    /// The known scale is not a positive number.
    #[error("the scale must be a positive number (mesh units to mm), not {0}")]
    Scale(f64),
    /// No starting pose converged.
    #[error("no starting pose converged: the spot points are degenerate (on a line or a point)")]
    NoPose,
    /// The best pose leaves the spots too far from the surface.
    #[error(
        "the best pose leaves the spots {rms_px:.2} px ({rms_mm:.3} mm) RMS from the mesh surface \
         with {share_pct:.0} % of them inliers; the bounds are {max_rms_px} px and \
         {min_share_pct:.0} %: is this mesh the scanned object, and are the cameras and laser rays \
         in scan.json right?"
    )]
    Residuals {
        /// Inlier RMS, pixels.
        rms_px: f64,
        /// Inlier RMS, mm.
        rms_mm: f64,
        /// Inliers, percent.
        share_pct: f64,
        /// The bound on `rms_px`.
        max_rms_px: f64,
        /// The bound on `share_pct`.
        min_share_pct: f64,
    },
    /// A motion of the mesh that changes its surface leaves the residuals unchanged.
    #[error(
        "the spots do not fix the pose{}: {motion} moves the mesh's vertices by {} (one standard \
         deviation) without changing how well the spots fit, above the bound of {bound_mm:.3} mm \
         (a quarter pixel); add turntable angles or laser targets that reach the surface where it \
         constrains this motion",
        if *.planar { " (they all lie on one plane)" } else { "" },
        amount(*.sigma_mm)
    )]
    Undetermined {
        /// The free motion, in words.
        motion: String,
        /// Whether the spot points lie on a plane (to within a pixel footprint).
        planar: bool,
        /// RMS vertex displacement of one standard deviation along it, mm.
        sigma_mm: f64,
        /// The bound, mm.
        bound_mm: f64,
    },
    /// Two poses with different surfaces fit about equally well.
    #[error(
        "two poses fit the spots about equally well ({best_mm:.3} and {other_mm:.3} mm robust RMS) \
         but put the surface {apart_mm:.2} mm apart (RMS over the vertices); add turntable angles \
         or laser targets on the parts that tell them apart"
    )]
    Ambiguous {
        /// The best pose's robust RMS (the truncated score's square root), mm.
        best_mm: f64,
        /// The rival's.
        other_mm: f64,
        /// RMS distance of the rival's vertices from the best's surface, mm.
        apart_mm: f64,
    },
}

fn amount(mm: f64) -> String {
    if mm < 1e4 {
        format!("{mm:.3} mm")
    } else {
        "any amount".into()
    }
}

/// Settings and bounds of [`align`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct AlignOptions {
    /// How spots are found and triangulated.
    pub evidence: EvidenceOptions,
    /// Fewest triangulated spots to estimate a pose from (7 unknowns; the outlier rejection
    /// needs redundancy).
    pub min_spots: usize,
    /// Largest inlier RMS distance of the spots from the aligned surface, pixels.
    pub max_rms_px: f64,
    /// Smallest share of the spots that are inliers.
    pub min_inlier_share: f64,
    /// Largest pose uncertainty in any direction that is not a symmetry: one standard deviation
    /// of RMS vertex displacement, in pixel footprints at the object.
    pub max_pose_sigma_px: f64,
    /// The spot depth (how far inside the surface, along the laser ray, the camera sees a
    /// spot's centre: a translucent object's light comes from below its surface), mm: `None`
    /// estimates it with the pose, a number holds it (0 for an opaque object).
    pub spot_depth: Option<f64>,
    /// How the spot depth moves a spot point ([`DepthModel`]).
    pub depth_model: DepthModel,
    /// The scale from mesh units to mm when it is known (`subsurf align --scale`): `None`
    /// estimates it with the pose, a number holds it, so the search fits rotation and
    /// translation only (a mesh whose unit is known is not rescaled to fit noisy spots).
    pub scale: Option<f64>,
}

impl AlignOptions {
    /// Defaults for a dataset: spot threshold from its noise floor (10×, as registration's),
    /// saturation from `scan.json`.
    pub fn for_dataset(ds: &Dataset) -> AlignOptions {
        AlignOptions {
            evidence: EvidenceOptions {
                min_peak: 10.0 * ds.spec.noise_floor.unwrap_or(0.0),
                saturation: ds.spec.saturation,
                max_gap_px: 2.0,
            },
            min_spots: 12,
            max_rms_px: 1.0,
            min_inlier_share: 0.5,
            max_pose_sigma_px: 0.25,
            spot_depth: None,
            depth_model: DepthModel::Laser,
            scale: None,
        }
    }
}

/// One spot's residual under the chosen pose.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Residual {
    /// The frame.
    pub frame: usize,
    /// Distance of the triangulated point from the aligned surface, mm.
    pub mm: f64,
    /// The same in pixel footprints.
    pub px: f64,
    /// Whether the pose was fitted to it.
    pub inlier: bool,
    /// The nearest point of the aligned surface, object frame.
    pub at: V3,
}

/// The estimated pose and everything that judges it.
#[derive(Debug, Clone)]
pub struct Aligned {
    /// Source mesh frame → object frame.
    pub pose: Similarity,
    /// What `scan.json` records.
    pub record: Alignment,
    /// The source mesh moved by the pose (same vertices in the same order).
    pub mesh: Mesh,
    /// The spot points.
    pub evidence: Evidence,
    /// Per spot point, in the order of `evidence.points`.
    pub residuals: Vec<Residual>,
    /// Starting poses tried.
    pub hypotheses: usize,
    /// Distinct poses the search converged to (the chosen one included).
    pub distinct_poses: usize,
    /// The spot depth's model.
    pub depth_model: DepthModel,
    /// The depth's coefficients ([`DepthModel`]), mm.
    pub depth: [f64; 2],
}

impl Aligned {
    /// Per vertex of the aligned mesh, the spot whose surface point is nearest within `reach_mm`:
    /// its residual in pixels and whether it is an inlier (`None` where no spot is that close):
    /// what the picture of `subsurf align` colours.
    pub fn spots_on_mesh(&self, reach_mm: f64) -> Vec<Option<(f64, bool)>> {
        self.mesh
            .positions
            .par_iter()
            .map(|p| {
                self.residuals
                    .iter()
                    .map(|r| (crate::geometry::dist(*p, r.at), r))
                    .filter(|(d, _)| *d <= reach_mm)
                    .min_by(|a, b| a.0.total_cmp(&b.0))
                    .map(|(_, r)| (r.px, r.inlier))
            })
            .collect()
    }
}

/// Estimates the pose of the dataset's source mesh ([`Dataset::source_mesh`]) from the laser
/// spots of `frames`.
pub fn align(
    ds: &Dataset,
    frames: &[usize],
    opts: &AlignOptions,
    progress: &dyn Progress,
) -> Result<Aligned, AlignError> {
    let (name, source) = ds.source_mesh()?;
    let evidence = spot_points(ds, frames, &opts.evidence, progress)?;
    align_points(&source, &name, evidence, opts, progress)
}

/// Vertex subsample used to compare surfaces and carry uncertainties to the mesh.
const PROBE_VERTICES: usize = 2000;
/// A motion is a symmetry of the surface when it moves the vertices this much less off the
/// surface than it moves them.
const SYMMETRY_RATIO: f64 = 0.05;
/// Size of the finite motion of the symmetry test: this share of the mesh's RMS radius.
const PROBE_MOTION: f64 = 0.2;

/// [`align`] on points already triangulated: `source` named `source_name` in `scan.json`.
pub fn align_points(
    source: &Mesh,
    source_name: &str,
    evidence: Evidence,
    opts: &AlignOptions,
    progress: &dyn Progress,
) -> Result<Aligned, AlignError> {
    if let Some(s) = opts.scale
        && !(s.is_finite() && s > 0.0)
    {
        return Err(AlignError::Scale(s));
    }
    let n = evidence.points.len();
    if n < opts.min_spots.max(3) {
        return Err(AlignError::TooFewSpots {
            points: n,
            needed: opts.min_spots.max(3),
            frames: evidence.frames,
            no_laser_ray: evidence.no_laser_ray,
            no_spot: evidence.no_spot,
            rays_apart: evidence.rays_apart,
        });
    }
    let scene = Scene::new(source.clone())?;
    let footprint = median(
        &evidence
            .points
            .iter()
            .map(|p| p.footprint_mm)
            .collect::<Vec<_>>(),
    );
    let problem = Problem {
        scene: &scene,
        points: &evidence.points,
        orientation: orientation(source),
        floor_mm: 0.05 * footprint,
        cutoff_mm: 3.0 * footprint,
        scale: opts.scale,
        model: opts.depth_model,
    };
    let pts: Vec<V3> = evidence.points.iter().map(|p| p.point).collect();
    let starts = search::hypotheses(source, &pts, opts.scale);
    progress.start("pose search", starts.len() as u64);
    let mut tried: Vec<(Similarity, f64)> = starts
        .par_iter()
        .filter_map(|s| {
            let pose = problem.icp_points(*s, 40);
            progress.inc(1);
            let pose = pose?;
            Some((pose, problem.score(&problem.matches(&pose, &[0.0; 2]))))
        })
        .collect();
    tried.sort_by(|a, b| a.1.total_cmp(&b.1));
    let Some(&(_, first)) = tried.first() else {
        return Err(AlignError::NoPose);
    };
    // Refine every start that ended near the best, then keep the best refined one.
    let (depth0, fit_depth) = match opts.spot_depth {
        Some(d) => ([d, 0.0], false),
        None => ([0.0; 2], true),
    };
    let probe = probe_vertices(source);
    let mut finals: Vec<(Refined, f64)> = tried
        .iter()
        .filter(|(_, s)| *s <= 4.0 * first.max(1e-300))
        .take(12)
        .map(|(pose, _)| {
            let r = problem.refine(*pose, depth0, false, 100);
            let s = problem.score(&r.matches);
            (r, s)
        })
        .collect();
    finals.sort_by(|a, b| a.1.total_cmp(&b.1));
    if finals.is_empty() {
        return Err(AlignError::NoPose);
    }
    let (best, best_score) = finals.remove(0);
    // Distinct poses among the refined ones, and the best rival: a pose that puts the surface
    // elsewhere (by more than half a pixel and 3 sigma) yet fits about as well — its score, the
    // mean truncated squared distance, within one inlier variance of the best's. Judged after the
    // pose's own uncertainty, which names the cause when the evidence is degenerate.
    let mut distinct: Vec<Similarity> = vec![best.pose];
    let mut rival = None;
    for (r, s) in &finals {
        if distinct
            .iter()
            .any(|d| pose_distance(&probe, d, &r.pose) < 0.5 * footprint)
        {
            continue;
        }
        distinct.push(r.pose);
        if rival.is_none() && *s - best_score <= best.sigma_mm.powi(2) {
            let apart = surface_distance(&scene, &probe, &best.pose, &r.pose);
            if apart > (0.5 * footprint).max(3.0 * best.sigma_mm) {
                rival = Some((s.sqrt(), apart));
            }
        }
    }
    // The pose with the spots where they were seen; then, from there, the spot depth with the
    // pose (kept >= 0: freed from the start, with the outliers still in play, it would trade
    // inliers for a depth above the surface).
    let best = problem.refine(best.pose, depth0, false, 100);
    let best = if fit_depth {
        problem.refine(best.pose, [0.0; 2], true, 100)
    } else {
        best
    };
    let pose = best.pose;

    // Residuals.
    let residuals: Vec<Residual> = best
        .matches
        .iter()
        .zip(&evidence.points)
        .zip(&best.inlier)
        .map(|((m, sp), inl)| {
            let mm = m.map_or(f64::INFINITY, |m| m.d);
            Residual {
                frame: sp.frame,
                mm,
                px: mm / sp.footprint_mm,
                inlier: *inl,
                at: m.map_or(sp.point, |m| m.y),
            }
        })
        .collect();
    let inl: Vec<&Residual> = residuals.iter().filter(|r| r.inlier).collect();
    let rms = |f: &dyn Fn(&Residual) -> f64| {
        (inl.iter().map(|r| f(r).powi(2)).sum::<f64>() / inl.len().max(1) as f64).sqrt()
    };
    let (rms_mm, rms_px) = (rms(&|r| r.mm), rms(&|r| r.px));
    let share = inl.len() as f64 / n as f64;
    if !(rms_px <= opts.max_rms_px && share >= opts.min_inlier_share) {
        return Err(AlignError::Residuals {
            rms_px,
            rms_mm,
            share_pct: 100.0 * share,
            max_rms_px: opts.max_rms_px,
            min_share_pct: 100.0 * opts.min_inlier_share,
        });
    }

    // Symmetry and uncertainty.
    let axis = turntable_symmetry(&scene, &probe, &pose);
    let bound_mm = opts.max_pose_sigma_px * footprint;
    let (pose_sigma_mm, symmetric_motion) = uncertainty(
        &scene,
        &probe,
        &best,
        problem.free_depth(fit_depth),
        LeftOut {
            turntable_turn: axis == Some(Symmetry::TurntableAxis { fold: None }),
            scale: opts.scale.is_some(),
        },
        rms_mm.max(problem.floor_mm),
        bound_mm,
    )
    .map_err(|e| match e {
        AlignError::Undetermined {
            motion,
            sigma_mm,
            bound_mm,
            ..
        } => AlignError::Undetermined {
            motion,
            planar: search::point_moments(&pts).is_some_and(|(_, cov)| {
                cov.symmetric_eigenvalues().min().max(0.0).sqrt() < footprint
            }),
            sigma_mm,
            bound_mm,
        },
        e => e,
    })?;
    if let Some((other_mm, apart_mm)) = rival {
        return Err(AlignError::Ambiguous {
            best_mm: best_score.sqrt(),
            other_mm,
            apart_mm,
        });
    }
    let symmetry = match (axis, symmetric_motion) {
        (Some(a @ Symmetry::TurntableAxis { fold: None }), _) => Some(a),
        (_, Some(motion)) => Some(Symmetry::Other { motion }),
        (axis, None) => {
            let tol = (0.5 * footprint).max(3.0 * best.sigma_mm);
            let here = problem.score(&problem.matches(&pose, &best.depth));
            let fits = |p: &Similarity| {
                problem.score(&problem.matches(p, &best.depth)) - here <= best.sigma_mm.powi(2)
            };
            finite_symmetry(&scene, source, &probe, &pose, axis, tol, &fits)
        }
    };

    let (mesh, _) = Mesh::new(
        source.positions.iter().map(|p| pose.apply(*p)).collect(),
        source.triangles.clone(),
    );
    let r = pose.rotation;
    let record = Alignment {
        source_mesh: source_name.to_owned(),
        scale: pose.scale,
        rotation: std::array::from_fn(|i| std::array::from_fn(|j| r[(i, j)])),
        translation: [pose.translation.x, pose.translation.y, pose.translation.z],
        spots: n,
        inliers: inl.len(),
        inlier_share: share,
        rms_mm,
        rms_px,
        pose_sigma_mm,
        spot_depth_mm: best.depth[0],
        symmetry,
    };
    Ok(Aligned {
        pose,
        record,
        mesh,
        evidence,
        residuals,
        hypotheses: starts.len(),
        distinct_poses: distinct.len(),
        depth_model: opts.depth_model,
        depth: best.depth,
    })
}

/// +1 when the mesh encloses positive volume with its faces as wound (outward normals), -1
/// when negative, 0 when it encloses too little to tell (an open sheet).
fn orientation(mesh: &Mesh) -> f64 {
    let Some((c, cov)) = search::surface_moments(mesh) else {
        return 0.0;
    };
    let c = [c.x, c.y, c.z];
    let vol: f64 = mesh
        .triangles
        .iter()
        .map(|t| {
            let [p, q, r] = t.map(|i| sub(mesh.positions[i as usize], c));
            dot(p, cross(q, r)) / 6.0
        })
        .sum();
    // Compare with the volume of the surface's own extent (the covariance's box).
    let extent = cov.trace().sqrt().powi(3);
    if vol.is_nan() || vol.abs() <= 0.01 * extent {
        0.0
    } else {
        vol.signum()
    }
}

/// Up to [`PROBE_VERTICES`] vertices of the mesh, evenly strided (its own frame).
fn probe_vertices(mesh: &Mesh) -> Vec<V3> {
    let step = mesh.positions.len().div_ceil(PROBE_VERTICES).max(1);
    mesh.positions
        .iter()
        .zip(&mesh.normals)
        .step_by(step)
        .filter(|(_, n)| **n != [0.0; 3])
        .map(|(p, _)| *p)
        .collect()
}

/// RMS distance the probe vertices move between two poses, mm.
fn pose_distance(probe: &[V3], a: &Similarity, b: &Similarity) -> f64 {
    let s: f64 = probe
        .iter()
        .map(|p| (v(a.apply(*p)) - v(b.apply(*p))).norm_squared())
        .sum();
    (s / probe.len().max(1) as f64).sqrt()
}

/// RMS distance of the probe vertices under pose `b` from the surface under pose `a`, mm.
fn surface_distance(scene: &Scene, probe: &[V3], a: &Similarity, b: &Similarity) -> f64 {
    let s: f64 = probe
        .par_iter()
        .map(|p| {
            scene
                .closest(a.invert(b.apply(*p)), f64::INFINITY)
                .map_or(f64::INFINITY, |c| (c.distance * a.scale).powi(2))
        })
        .sum();
    (s / probe.len().max(1) as f64).sqrt()
}

/// Is `b` the same surface as `a` (a symmetry), measured against how far it moves the vertices?
fn same_surface(scene: &Scene, probe: &[V3], a: &Similarity, b: &Similarity) -> bool {
    let moved = pose_distance(probe, a, b);
    moved > 0.0 && surface_distance(scene, probe, a, b) < SYMMETRY_RATIO * moved
}

/// Motions [`uncertainty`] leaves out of the analysis.
#[derive(Debug, Clone, Copy)]
struct LeftOut {
    /// The rotation about the turntable axis (a symmetry of the surface).
    turntable_turn: bool,
    /// The scale (known, not estimated).
    scale: bool,
}

/// The pose's uncertainty carried to the vertices, and the free motion that is a symmetry (if
/// any). The spot depth is marginalised out of the normal matrix (Schur complement); a
/// rotation about the turntable axis that leaves the surface unchanged (`turntable_turn`) is
/// projected out: it is free by construction and, tested as an eigendirection, it would come
/// mixed with whatever its neighbours in the spectrum are; a known scale (`scale`) is
/// projected out too, as it is not estimated. Each remaining eigendirection is
/// weighed by the vertex displacement one standard deviation along it causes; one above
/// `bound_mm` must be a symmetry of the surface too (tested by a finite motion along it) or the
/// pose is undetermined.
fn uncertainty(
    scene: &Scene,
    probe: &[V3],
    best: &Refined,
    free_depth: [bool; 2],
    left_out: LeftOut,
    sigma_mm: f64,
    bound_mm: f64,
) -> Result<(f64, Option<String>), AlignError> {
    use nalgebra::{DMatrix, DVector};
    let pose = &best.pose;
    let h = &best.info;
    let mut info: Mat7 = h.fixed_view::<7, 7>(0, 0).into_owned();
    let free: Vec<usize> = free_depth
        .iter()
        .zip([7, 8])
        .filter(|(f, _)| **f)
        .map(|(_, k)| k)
        .collect();
    if !free.is_empty() {
        let k = free.len();
        let d = nalgebra::DMatrix::from_fn(k, k, |i, j| h[(free[i], free[j])]);
        let c = nalgebra::DMatrix::from_fn(7, k, |i, j| h[(i, free[j])]);
        if let Some(di) = d.try_inverse() {
            let s = &c * di * c.transpose();
            info -= Mat7::from_fn(|i, j| s[(i, j)]);
        }
    }
    let verts: Vec<V3> = probe.iter().map(|p| pose.apply(*p)).collect();
    let mut g = Mat7::zeros();
    for x in &verts {
        let d = displacement_rows(*x, best.centre, best.radius);
        g += d.transpose() * d;
    }
    g /= verts.len().max(1) as f64;
    // The basis the analysis works in: the normalised motions orthogonal to those left out —
    // the rotation about the turntable axis (ω = z; about the centre c that is τ = z × c) and
    // the known scale (σ), which are orthogonal to each other.
    let c = best.centre;
    let out: Vec<DVector<f64>> = [
        left_out.turntable_turn.then(|| {
            DVector::from_column_slice(&[0.0, 0.0, 0.0, best.radius, -c[1], c[0], 0.0]).normalize()
        }),
        left_out
            .scale
            .then(|| DVector::from_column_slice(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])),
    ]
    .into_iter()
    .flatten()
    .collect();
    let basis: DMatrix<f64> = if out.is_empty() {
        DMatrix::identity(7, 7)
    } else {
        let mut proj = DMatrix::<f64>::identity(7, 7);
        for u in &out {
            proj -= u * u.transpose();
        }
        let svd = proj.svd(true, false);
        let uu = svd.u.unwrap_or_else(|| DMatrix::identity(7, 7));
        let mut cols: Vec<usize> = (0..7).collect();
        cols.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
        let keep = 7 - out.len();
        DMatrix::from_columns(
            &cols[..keep]
                .iter()
                .map(|&k| uu.column(k))
                .collect::<Vec<_>>(),
        )
    };
    let to_d = |m: &Mat7| DMatrix::from_column_slice(7, 7, m.as_slice());
    let hb = basis.transpose() * to_d(&info) * &basis;
    let gb = basis.transpose() * to_d(&g) * &basis;
    let rho = rms_radius(&verts);
    let eig = hb.symmetric_eigen();
    let mut var = 0.0;
    let mut symmetric = None;
    for k in 0..eig.eigenvalues.len() {
        let qb = eig.eigenvectors.column(k).into_owned();
        let lambda = eig.eigenvalues[k];
        let disp = (qb.transpose() * &gb * &qb)[(0, 0)].max(0.0).sqrt();
        let sd = if lambda > 0.0 {
            sigma_mm / lambda.sqrt() * disp
        } else {
            f64::INFINITY
        };
        if sd <= bound_mm {
            var += sd * sd;
            continue;
        }
        let q = &basis * qb;
        let step = PROBE_MOTION * rho / disp.max(1e-300);
        let delta: [f64; 7] = std::array::from_fn(|i| {
            let x = step * q[i];
            if i < 4 { x / best.radius } else { x }
        });
        let moved = pose.moved(&delta, best.centre);
        let text = describe(&delta, best.centre);
        if same_surface(scene, probe, pose, &moved) {
            symmetric.get_or_insert(text);
        } else {
            return Err(AlignError::Undetermined {
                motion: text,
                planar: false,
                sigma_mm: sd,
                bound_mm,
            });
        }
    }
    Ok((var.sqrt(), symmetric))
}

fn rms_radius(pts: &[V3]) -> f64 {
    let n = pts.len().max(1) as f64;
    let c = pts
        .iter()
        .fold(nalgebra::Vector3::zeros(), |a, p| a + v(*p))
        / n;
    (pts.iter().map(|p| (v(*p) - c).norm_squared()).sum::<f64>() / n).sqrt()
}

/// A small motion `[σ, ω, τ]` about `centre` in words: its rotation axis (direction and a point
/// on it), or its translation, or the scale.
fn describe(delta: &[f64; 7], centre: V3) -> String {
    let w = nalgebra::Vector3::new(delta[1], delta[2], delta[3]);
    let t = nalgebra::Vector3::new(delta[4], delta[5], delta[6]);
    let f = |x: nalgebra::Vector3<f64>| format!("({:.2}, {:.2}, {:.2})", x.x, x.y, x.z);
    // Displacement at unit distance: the rotation's and the scale's against the translation's.
    let (rw, rs, rt) = (w.norm(), delta[0].abs(), t.norm());
    if rs >= rw && rs * 10.0 >= rt {
        "the scale".into()
    } else if rw * 10.0 >= rt {
        let c = v(centre) + w.cross(&t) / (rw * rw);
        format!(
            "a rotation about the axis along {} through {} mm",
            f(w / rw),
            f(c)
        )
    } else {
        format!("a translation along {}", f(t / rt))
    }
}

/// Whether the aligned surface is unchanged by rotations about the turntable axis: by several
/// unrelated angles (continuous), else by 360°/n for the largest n up to 12.
fn turntable_symmetry(scene: &Scene, probe: &[V3], pose: &Similarity) -> Option<Symmetry> {
    let by = |deg: f64| same_surface(scene, probe, pose, &pose.turned_about_axis(deg));
    if [37.0, 101.0, 211.0].iter().all(|d| by(*d)) {
        return Some(Symmetry::TurntableAxis { fold: None });
    }
    (2..=12u32)
        .rev()
        .find(|k| by(360.0 / f64::from(*k)))
        .map(|k| Symmetry::TurntableAxis { fold: Some(k) })
}

/// Most rotations a finite symmetry is counted up to (the icosahedron's 60).
const MAX_ROTATIONS: usize = 60;

/// The finite group of rotations that leave the aligned surface unchanged, when it is more than
/// the turntable's own `axis` fold: found among the half and quarter turns about the surface's
/// principal axes (through its centroid: any rotation that maps a surface onto itself maps its
/// principal axes onto principal axes, so with three distinct moments these are all of them)
/// and the turntable's turns, each checked on the surface, then closed under composition. An
/// ellipsoid with three distinct axes has four; the turntable's fold alone would report two.
/// A rotation counts when it puts the surface within `tol_mm` (RMS) of itself and the spots
/// `fit` the turned pose as well as the found one: the converse of a rival (which fits as well
/// but puts the surface elsewhere), so a nearly symmetric pebble whose spots tell its half turn
/// apart is not called symmetric.
fn finite_symmetry(
    scene: &Scene,
    source: &Mesh,
    probe: &[V3],
    pose: &Similarity,
    axis: Option<Symmetry>,
    tol_mm: f64,
    fits: &dyn Fn(&Similarity) -> bool,
) -> Option<Symmetry> {
    use nalgebra::{Rotation3, Vector3};
    let (cm, covm) = search::surface_moments(source)?;
    let centre = v(pose.apply([cm.x, cm.y, cm.z]));
    let axes = pose.rotation * search::axes(&covm);
    let about = |r: nalgebra::Matrix3<f64>, c: Vector3<f64>| Similarity {
        scale: 1.0,
        rotation: r,
        translation: c - r * c,
    };
    let mut candidates: Vec<Similarity> = search::axis_rotations()
        .into_iter()
        .map(|s| about(axes * s * axes.transpose(), centre))
        .collect();
    if let Some(Symmetry::TurntableAxis { fold: Some(k) }) = axis {
        candidates.extend((1..k).map(|j| {
            let r = Rotation3::from_axis_angle(
                &Vector3::z_axis(),
                360f64.to_radians() / f64::from(k) * f64::from(j),
            );
            about(r.into_inner(), Vector3::zeros())
        }));
    }
    let rho = rms_radius(probe).max(1e-300) * pose.scale;
    let same = |a: &Similarity, b: &Similarity| {
        pose_distance(probe, &pose.then(a), &pose.then(b)) < 0.05 * rho
    };
    let mut group = vec![Similarity::identity()];
    for g in candidates {
        if !group.iter().any(|h| same(h, &g))
            && surface_distance(scene, probe, pose, &pose.then(&g)) < tol_mm
            && fits(&pose.then(&g))
        {
            group.push(g);
        }
    }
    // Close under composition: the product of two symmetries is one.
    let mut k = 0;
    while k < group.len() && group.len() < MAX_ROTATIONS {
        for j in 0..group.len() {
            let g = group[k].then(&group[j]);
            if !group.iter().any(|h| same(h, &g)) {
                group.push(g);
            }
        }
        k += 1;
    }
    let poses = group.len() as u32;
    match axis {
        Some(Symmetry::TurntableAxis { fold: Some(k) }) if poses <= k => axis,
        _ if poses <= 1 => None,
        _ => Some(Symmetry::Rotations {
            poses,
            turns: group[1..].iter().filter_map(turn_of).collect(),
        }),
    }
}

/// A rotation `x ↦ R·x + t` as its angle, axis and a point on the axis (a half turn included:
/// [`similarity::axis_angle`]).
fn turn_of(g: &Similarity) -> Option<crate::dataset::Turn> {
    let (axis, angle) = similarity::axis_angle(&g.rotation)?;
    // The point on the axis nearest the origin: (I − R)·p = t restricted to the plane ⟂ axis,
    // solved in the least-squares sense.
    let m = nalgebra::Matrix3::identity() - g.rotation;
    let p = m.svd(true, true).solve(&g.translation, 1e-9).ok()?;
    let p = p - axis * axis.dot(&p);
    Some(crate::dataset::Turn {
        degrees: angle.to_degrees(),
        axis: [axis.x, axis.y, axis.z],
        through: [p.x, p.y, p.z],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::shapes::ellipsoid;
    use crate::simulate::SimObject;
    use nalgebra::{Rotation3, Vector3};

    /// Spot points on the top of `mesh` (object frame), as a camera and laser above it would
    /// find them: every `stride`-th vertex facing up, jittered along its normal by a
    /// deterministic `noise_mm`, every 10th one replaced by an outlier 5 mm off.
    fn spots(mesh: &Mesh, stride: usize, noise_mm: f64) -> Evidence {
        let mut points = Vec::new();
        for (k, (p, n)) in mesh.positions.iter().zip(&mesh.normals).enumerate() {
            if k % stride != 0 || n[2] < 0.2 {
                continue;
            }
            let j = points.len();
            let jitter = noise_mm * ((j as f64 * 2.399).sin());
            let off = if j % 10 == 9 { 5.0 } else { jitter };
            points.push(SpotPoint {
                frame: j,
                point: crate::geometry::add_scaled(*p, off, *n),
                gap_mm: 0.0,
                footprint_mm: 0.4,
                to_camera: *n,
                to_laser: *n,
                uv: [0.0; 2],
            });
        }
        Evidence {
            frames: points.len(),
            points,
            ..Evidence::default()
        }
    }

    fn moved(mesh: &Mesh, t: &Similarity) -> Mesh {
        Mesh::new(
            mesh.positions.iter().map(|p| t.apply(*p)).collect(),
            mesh.triangles.clone(),
        )
        .0
    }

    fn opts() -> AlignOptions {
        AlignOptions {
            evidence: EvidenceOptions {
                min_peak: 0.0,
                saturation: None,
                max_gap_px: 2.0,
            },
            min_spots: 12,
            max_rms_px: 1.0,
            min_inlier_share: 0.5,
            max_pose_sigma_px: 0.25,
            spot_depth: None,
            depth_model: DepthModel::Laser,
            scale: None,
        }
    }

    /// Into metres, turned and shifted: the user's mesh in its own frame.
    fn user_pose() -> Similarity {
        Similarity {
            scale: 1e-3,
            rotation: Rotation3::from_euler_angles(2.1, -0.7, 1.3).into_inner(),
            translation: Vector3::new(0.031, -0.047, 0.012),
        }
    }

    fn rms_from(truth: &Mesh, aligned: &Mesh) -> f64 {
        let scene = Scene::new(truth.clone()).unwrap();
        let s: f64 = aligned
            .positions
            .iter()
            .map(|p| scene.closest(*p, f64::INFINITY).unwrap().distance.powi(2))
            .sum();
        (s / aligned.positions.len() as f64).sqrt()
    }

    #[test]
    fn an_asymmetric_mesh_in_metres_and_any_pose_is_placed_uniquely() {
        let truth = SimObject::Blob {
            size: 30.0,
            rings: 16,
        }
        .mesh();
        let ev = spots(&truth, 1, 0.03);
        let user = moved(&truth, &user_pose());
        let out = align_points(&user, "object.obj", ev, &opts(), &()).unwrap();
        let rms = rms_from(&truth, &out.mesh);
        assert!(rms < 0.02, "{rms} {:?}", out.record);
        // Vertex for vertex, not only surface to surface: the pose is unique.
        let worst = out
            .mesh
            .positions
            .iter()
            .zip(&truth.positions)
            .map(|(a, b)| crate::geometry::dist(*a, *b))
            .fold(0.0, f64::max);
        assert!(worst < 0.05, "{worst}");
        assert!((out.record.scale - 1000.0).abs() < 2.0, "{:?}", out.record);
        assert_eq!(out.record.symmetry, None);
        assert!(out.record.inlier_share > 0.85 && out.record.inlier_share < 0.95);
        assert!(out.record.rms_mm < 0.05 && out.record.pose_sigma_mm < 0.05);
    }

    /// An ellipsoid with three distinct axes has four proper symmetries (the identity
    /// and a half turn about each axis), not the two that the turntable axis alone shows; lying
    /// tilted off the axis it has no turntable symmetry at all and still four.
    #[test]
    fn an_ellipsoid_has_four_poses_not_two() {
        let upright = ellipsoid([15.0, 10.0, 6.0], 3);
        let tilted = moved(
            &upright,
            &Similarity {
                scale: 1.0,
                rotation: Rotation3::from_euler_angles(0.4, 0.3, 0.9).into_inner(),
                translation: Vector3::new(3.0, -2.0, 8.0),
            },
        );
        for (name, truth) in [("upright", upright), ("tilted", tilted)] {
            let ev = spots(&truth, 1, 0.03);
            let user = moved(&truth, &user_pose());
            let out = align_points(&user, "object.obj", ev, &opts(), &()).unwrap();
            assert!(
                rms_from(&truth, &out.mesh) < 0.03,
                "{name} {:?}",
                out.record
            );
            match &out.record.symmetry {
                Some(Symmetry::Rotations { poses: 4, turns }) => {
                    assert_eq!(turns.len(), 3, "{name}");
                    for t in turns {
                        assert!((t.degrees - 180.0).abs() < 1.0, "{name} {t:?}");
                    }
                }
                s => panic!("{name}: {s:?}"),
            }
            let words = out.record.symmetry.as_ref().unwrap().to_string();
            assert!(words.starts_with("4 poses"), "{words}");
        }
    }

    /// `--scale`: a known scale is held, not estimated. Told 1 % more than the truth, the pose
    /// keeps exactly that scale (an estimate would return ~1000); told the truth, it places the
    /// mesh as well as the free search does.
    #[test]
    fn a_known_scale_is_held() {
        let truth = SimObject::Blob {
            size: 30.0,
            rings: 16,
        }
        .mesh();
        let ev = spots(&truth, 1, 0.03);
        let user = moved(&truth, &user_pose());
        let mut o = opts();
        o.scale = Some(1000.0);
        let out = align_points(&user, "object.obj", ev.clone(), &o, &()).unwrap();
        assert_eq!(out.record.scale, 1000.0);
        assert!(rms_from(&truth, &out.mesh) < 0.02, "{:?}", out.record);
        assert_eq!(out.record.symmetry, None);
        o.scale = Some(1010.0);
        o.max_rms_px = 10.0;
        o.max_pose_sigma_px = 10.0;
        let off = align_points(&user, "object.obj", ev.clone(), &o, &()).unwrap();
        assert_eq!(off.record.scale, 1010.0);
        o.scale = Some(-1.0);
        let e = align_points(&user, "object.obj", ev, &o, &()).unwrap_err();
        assert!(matches!(e, AlignError::Scale(_)), "{e}");
    }

    #[test]
    fn a_torus_is_placed_and_its_symmetry_about_the_axis_reported() {
        let truth = SimObject::Torus {
            major: 13.0,
            minor: 6.0,
            segments: 24,
        }
        .mesh();
        let ev = spots(&truth, 2, 0.03);
        let user = moved(&truth, &user_pose());
        let out = align_points(&user, "object.obj", ev, &opts(), &()).unwrap();
        let rms = rms_from(&truth, &out.mesh);
        assert!(rms < 0.03, "{rms} {:?}", out.record);
        assert_eq!(
            out.record.symmetry,
            Some(Symmetry::TurntableAxis { fold: None })
        );
    }

    #[test]
    fn spots_on_a_plane_do_not_fix_a_slab_and_few_spots_fix_nothing() {
        let truth = SimObject::Slab { size: 20.0, n: 21 }.mesh();
        let ev = spots(&truth, 4, 0.0);
        let user = moved(&truth, &user_pose());
        let e = align_points(&user, "object.obj", ev.clone(), &opts(), &()).unwrap_err();
        assert!(matches!(e, AlignError::Undetermined { .. }), "{e}");
        let mut few = ev;
        few.points.truncate(8);
        let e = align_points(&user, "object.obj", few, &opts(), &()).unwrap_err();
        assert!(
            matches!(e, AlignError::TooFewSpots { points: 8, .. }),
            "{e}"
        );
    }
}
