//! Robust ICP of the triangulated spot points against the mesh surface, with scale: the
//! point-to-point stage (closed-form [`Similarity::fit`] per iteration) of the global search and
//! the point-to-plane Gauss–Newton refinement, both with outliers rejected by a scale estimated
//! from the residuals themselves (3 × the MAD-based sigma, Huber weights inside). Closest points
//! come from [`Scene::closest`] on the mesh in its own frame: the points are mapped into it.
//!
//! Hand-written: the ICP variants of the field's crates fit rigid motions only and know nothing
//! of the scan's own outlier structure (spots past a limb, a laser grazing an edge).
use nalgebra::{SMatrix, SVector, Vector3};
use rayon::prelude::*;

use super::DepthModel;
use super::evidence::SpotPoint;
use super::similarity::{Similarity, a, v};
use crate::geometry::{Scene, V3, dot};

/// 7 × 7: [scale, rotation (3), translation (3)], the first four scaled by the points' radius so
/// every column is a length.
pub(crate) type Mat7 = SMatrix<f64, 7, 7>;
/// 9 × 9: the pose's 7 and the spot depth's two coefficients ([`DepthModel`]).
pub(crate) type Mat9 = SMatrix<f64, 9, 9>;
type Vec9 = SVector<f64, 9>;

/// The spot depth's coefficients, mm: the first is the depth itself (kept >= 0), the second
/// (when the model has one) its change with the angle of incidence.
pub(crate) type Depth = [f64; 2];

/// Inliers are within this many robust sigmas of the surface.
const INLIER_SIGMAS: f64 = 3.0;
/// Huber's constant in robust sigmas (95 % efficiency for Gaussian residuals).
const HUBER: f64 = 1.345;
/// A match whose surface faces away from the camera or the laser by more than this cosine
/// cannot be where the spot was seen.
const FACING_SLACK: f64 = -0.1;

/// One point's closest surface point under a pose, object frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Match {
    /// The surface point.
    pub y: V3,
    /// The surface's unit normal there (outwards when the orientation is known).
    pub m: V3,
    /// Distance of the spot point (moved by the spot depth) from it, mm.
    pub d: f64,
    /// The spot point moved by the spot depth: where the light entered, object frame.
    pub p: V3,
    /// The directions the depth's coefficients move the spot point along.
    pub b: [V3; 2],
    /// Could the camera and the laser both see this side of the surface?
    pub facing: bool,
}

/// The points against one mesh.
pub(crate) struct Problem<'a> {
    pub scene: &'a Scene,
    pub points: &'a [SpotPoint],
    /// +1 when the mesh's faces wind counter-clockwise seen from outside, -1 when the other way,
    /// 0 when it cannot be told (an open surface): the facing test is then skipped.
    pub orientation: f64,
    /// Smallest robust sigma, mm: a twentieth of the median pixel footprint (noise-free data
    /// would otherwise shrink it to nothing and call every point an outlier).
    pub floor_mm: f64,
    /// The score's truncation, mm: 3 pixel footprints.
    pub cutoff_mm: f64,
    /// The known scale (`subsurf align --scale`), held instead of estimated.
    pub scale: Option<f64>,
    /// How the spot depth moves a spot point.
    pub model: DepthModel,
}

/// The result of the point-to-plane refinement.
#[derive(Debug, Clone)]
pub(crate) struct Refined {
    pub pose: Similarity,
    /// The spot depth's coefficients ([`DepthModel`]), mm.
    pub depth: Depth,
    pub matches: Vec<Option<Match>>,
    pub inlier: Vec<bool>,
    /// Robust sigma of the final residuals, mm.
    pub sigma_mm: f64,
    /// Normal matrix of the inliers' point-to-plane rows (normalised pose columns, then the
    /// depth's two).
    pub info: Mat9,
    /// The centre and radius the columns are normalised by.
    pub centre: V3,
    pub radius: f64,
}

/// Median of a slice (NaN for none).
pub(crate) fn median(x: &[f64]) -> f64 {
    let mut s: Vec<f64> = x.iter().copied().filter(|x| !x.is_nan()).collect();
    if s.is_empty() {
        return f64::NAN;
    }
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

impl Problem<'_> {
    /// Every point's closest surface point under `pose`, each point first moved back by the
    /// spot depth `depth` ([`DepthModel`]). A model that depends on the surface's normal takes
    /// it from the point moved along its laser ray by the depth, then looks again.
    pub fn matches(&self, pose: &Similarity, depth: &Depth) -> Vec<Option<Match>> {
        self.points
            .par_iter()
            .map(|sp| {
                let closest = |p: V3| {
                    let c = self.scene.closest(pose.invert(p), f64::INFINITY)?;
                    let n = self.scene.face_normal(c.triangle)?;
                    Some((c, pose.turn(n)))
                };
                let along_laser = surface_point(sp, depth[0]);
                let (b, (c, m)) = if self.model.needs_normal() {
                    let (_, m0) = closest(along_laser)?;
                    let b = self.model.directions(sp, m0);
                    let p = add(sp.point, depth, &b);
                    (b, closest(p)?)
                } else {
                    let b = self.model.directions(sp, [0.0; 3]);
                    (b, closest(add(sp.point, depth, &b))?)
                };
                let p = add(sp.point, depth, &b);
                let y = pose.apply(c.point);
                let facing = self.orientation == 0.0
                    || (self.orientation * dot(m, sp.to_camera) > FACING_SLACK
                        && self.orientation * dot(m, sp.to_laser) > FACING_SLACK);
                let m = if self.orientation < 0.0 {
                    m.map(|x| -x)
                } else {
                    m
                };
                Some(Match {
                    y,
                    m,
                    d: c.distance * pose.scale,
                    p,
                    b,
                    facing,
                })
            })
            .collect()
    }

    /// Robust sigma of distances (MAD of a half-normal), floored.
    pub fn sigma(&self, d: &[f64]) -> f64 {
        (1.4826 * median(d)).max(self.floor_mm)
    }

    /// The pose's score, lower is better: the mean over all points of the squared distance
    /// truncated at the cutoff, a match on a side neither camera nor laser could see counting
    /// as the cutoff. Comparable between poses (every point counts, nothing is rescaled).
    pub fn score(&self, matches: &[Option<Match>]) -> f64 {
        let c2 = self.cutoff_mm * self.cutoff_mm;
        let total: f64 = matches
            .iter()
            .map(|m| match m {
                Some(m) if m.facing => (m.d * m.d).min(c2),
                _ => c2,
            })
            .sum();
        total / self.points.len().max(1) as f64
    }

    /// Robust weights of distances: 0 beyond 3 sigma, Huber inside.
    fn weights(&self, matches: &[Option<Match>]) -> (Vec<f64>, f64) {
        let d: Vec<f64> = matches
            .iter()
            .map(|m| m.map_or(f64::NAN, |m| m.d))
            .collect();
        let sigma = self.sigma(&d);
        let w = d
            .iter()
            .map(|&d| {
                if d.is_nan() || d > INLIER_SIGMAS * sigma {
                    0.0
                } else if d <= HUBER * sigma {
                    1.0
                } else {
                    HUBER * sigma / d
                }
            })
            .collect();
        (w, sigma)
    }

    /// Point-to-point ICP with scale from `start`: closest points, robust weights, the weighted
    /// similarity from the surface points (mesh frame) to the spot points, until the pose stops
    /// moving or `iterations` are spent. `None` if the pairs degenerate.
    pub fn icp_points(&self, start: Similarity, iterations: usize) -> Option<Similarity> {
        let mut pose = start;
        for _ in 0..iterations {
            let matches = self.matches(&pose, &[0.0; 2]);
            let (w, _) = self.weights(&matches);
            let mut from = Vec::with_capacity(w.len());
            let mut to = Vec::with_capacity(w.len());
            let mut ws = Vec::with_capacity(w.len());
            for ((m, sp), wi) in matches.iter().zip(self.points).zip(&w) {
                if let Some(m) = m
                    && *wi > 0.0
                {
                    from.push(pose.invert(m.y));
                    to.push(sp.point);
                    ws.push(*wi);
                }
            }
            let next = Similarity::fit_with_scale(&from, &to, &ws, self.scale)?;
            let moved = self.largest_move(&pose, &next, &from);
            pose = next;
            if moved < 1e-3 * self.floor_mm {
                break;
            }
        }
        Some(pose)
    }

    /// The largest distance any of `probe` (mesh frame) moves between two poses, mm.
    fn largest_move(&self, a_: &Similarity, b: &Similarity, probe: &[V3]) -> f64 {
        probe
            .iter()
            .map(|p| (v(a_.apply(*p)) - v(b.apply(*p))).norm())
            .fold(0.0, f64::max)
    }

    /// The centre and RMS radius of the spot points: the columns' normalisation.
    pub fn frame(&self) -> (V3, f64) {
        let n = self.points.len().max(1) as f64;
        let c = self
            .points
            .iter()
            .fold(Vector3::zeros(), |acc, p| acc + v(p.point))
            / n;
        let r = (self
            .points
            .iter()
            .map(|p| (v(p.point) - c).norm_squared())
            .sum::<f64>()
            / n)
            .sqrt()
            .max(1e-9);
        (a(c), r)
    }

    /// Point-to-plane Levenberg–Marquardt refinement from `start`, iteratively reweighted: per
    /// outer iteration the robust sigma, the inliers (within 3 sigma) and their Huber weights are
    /// fixed, and a step is taken only when it lowers
    /// the inliers' Huber cost of their distances from the surface (else the damping grows). With
    /// `fit_depth` the spot depth's coefficients are estimated with the pose (from `depth`, the
    /// depth itself kept >= 0: the light comes from below the surface, never above), else held
    /// at `depth`. The damping keeps null directions of the normal matrix (a symmetry, or a pose
    /// the points cannot fix) where the start put them; the caller judges them from `info`.
    pub fn refine(
        &self,
        start: Similarity,
        depth: Depth,
        fit_depth: bool,
        iterations: usize,
    ) -> Refined {
        let (centre, radius) = self.frame();
        let cv = v(centre);
        let (mut pose, mut depth) = (start, depth);
        let mut lambda = 1e-4;
        let mut matches = self.matches(&pose, &depth);
        for _ in 0..iterations {
            let (w, sigma) = self.weights(&matches);
            let mask: Vec<bool> = w.iter().map(|w| *w > 0.0).collect();
            let cost = |m: &[Option<Match>]| huber_cost(m, &mask, HUBER * sigma);
            let before = cost(&matches);
            let (info, rhs) = normal_equations(&matches, &w, cv, radius);
            let mut accepted = false;
            for _ in 0..12 {
                let Some((next, next_depth)) =
                    self.lm_step(&info, &rhs, lambda, pose, depth, fit_depth, centre, radius)
                else {
                    break;
                };
                let m = self.matches(&next, &next_depth);
                let after = cost(&m);
                if after < before {
                    let gain = before - after;
                    pose = next;
                    depth = next_depth;
                    matches = m;
                    lambda = (lambda / 10.0).max(1e-9);
                    accepted = gain > 1e-12 * before.max(f64::MIN_POSITIVE);
                    break;
                }
                lambda *= 10.0;
            }
            if !accepted {
                break;
            }
        }
        let (w, sigma_mm) = self.weights(&matches);
        let inlier: Vec<bool> = w.iter().map(|w| *w > 0.0).collect();
        let ones: Vec<f64> = inlier.iter().map(|i| f64::from(u8::from(*i))).collect();
        let (info, _) = normal_equations(&matches, &ones, cv, radius);
        Refined {
            pose,
            depth,
            matches,
            inlier,
            sigma_mm,
            info,
            centre,
            radius,
        }
    }

    /// Which of the depth's two coefficients are estimated.
    pub fn free_depth(&self, fit_depth: bool) -> [bool; 2] {
        [fit_depth, fit_depth && self.model.terms() > 1]
    }

    /// One damped step: `(H + λ·diag(H))·x = −g` (Marquardt's scaling, plus a floor so null
    /// directions stay put), the depth's coefficients held when they are not fitted, and the
    /// depth itself held at zero when the free step would take it below. `None` when the system
    /// cannot be solved.
    #[allow(clippy::too_many_arguments)]
    fn lm_step(
        &self,
        info: &Mat9,
        rhs: &Vec9,
        lambda: f64,
        pose: Similarity,
        depth: Depth,
        fit_depth: bool,
        centre: V3,
        radius: f64,
    ) -> Option<(Similarity, Depth)> {
        let free = self.free_depth(fit_depth);
        // Held unknowns (depth coefficients not free, the scale when known) get a zero step.
        let solve = |free: [bool; 2]| {
            let (mut a, mut b) = (*info, *rhs);
            let held = [
                (!free[0]).then_some(7),
                (!free[1]).then_some(8),
                self.scale.map(|_| 0),
            ];
            for k in held.into_iter().flatten() {
                a.row_mut(k).fill(0.0);
                a.column_mut(k).fill(0.0);
                a[(k, k)] = 1.0;
                b[k] = 0.0;
            }
            let floor = 1e-12 * a.trace().max(f64::MIN_POSITIVE);
            for k in 0..9 {
                a[(k, k)] += lambda * a[(k, k)] + floor;
            }
            a.cholesky().map(|c| c.solve(&b))
        };
        let mut step = solve(free)?;
        if free[0] && depth[0] - step[7] < 0.0 {
            // Held at zero: the step that takes it there, the rest solved with it held.
            step = solve([false, free[1]])?;
            step[7] = depth[0];
        }
        let delta: [f64; 7] =
            std::array::from_fn(|k| if k < 4 { -step[k] / radius } else { -step[k] });
        let next = pose.moved(&delta, centre);
        let next_depth = [depth[0] - step[7], depth[1] - step[8]];
        (next.is_finite() && next_depth.iter().all(|d| d.is_finite())).then_some((next, next_depth))
    }
}

/// Huber cost of the masked points' distances with threshold `k`.
fn huber_cost(matches: &[Option<Match>], mask: &[bool], k: f64) -> f64 {
    matches
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .map(|(m, _)| match m {
            Some(m) if m.d <= k => 0.5 * m.d * m.d,
            Some(m) => k * (m.d - 0.5 * k),
            None => f64::INFINITY,
        })
        .sum()
}

/// The triangulated point moved back along its laser ray by `depth`: where the light entered
/// under [`DepthModel::Laser`]. In a translucent object the camera sees the spot's centroid
/// below the surface (measured on sample-torus: the triangulated points lie 0.01–0.21 mm inside
/// the true surface, median 0.15 mm); the depth is estimated with the pose.
pub(crate) fn surface_point(sp: &SpotPoint, depth: f64) -> V3 {
    crate::geometry::add_scaled(sp.point, depth, sp.to_laser)
}

/// `p + depth[0]·b[0] + depth[1]·b[1]`.
fn add(p: V3, depth: &Depth, b: &[V3; 2]) -> V3 {
    crate::geometry::add_scaled(
        crate::geometry::add_scaled(p, depth[0], b[0]),
        depth[1],
        b[1],
    )
}

/// One point-to-plane row: e = m·(y − p) for the spot's surface point p (moved by the spot
/// depth), and its gradient in the normalised motion [σ·ρ, ω·ρ, τ] about `centre` (y moves by
/// σ(y − c) + ω × (y − c) + τ) and in the depth's coefficients (p moves along `b`).
fn row(m: &Match, centre: Vector3<f64>, radius: f64) -> (Vec9, f64) {
    let (mv, yc) = (v(m.m), v(m.y) - centre);
    let e = mv.dot(&(v(m.y) - v(m.p)));
    let r = yc.cross(&mv) / radius;
    let j = Vec9::from_column_slice(&[
        mv.dot(&yc) / radius,
        r.x,
        r.y,
        r.z,
        mv.x,
        mv.y,
        mv.z,
        -mv.dot(&v(m.b[0])),
        -mv.dot(&v(m.b[1])),
    ]);
    (j, e)
}

fn normal_equations(
    matches: &[Option<Match>],
    w: &[f64],
    centre: Vector3<f64>,
    radius: f64,
) -> (Mat9, Vec9) {
    let mut info = Mat9::zeros();
    let mut rhs = Vec9::zeros();
    for (m, wi) in matches.iter().zip(w) {
        let Some(m) = m else { continue };
        if *wi <= 0.0 {
            continue;
        }
        let (j, e) = row(m, centre, radius);
        info += *wi * j * j.transpose();
        rhs += *wi * e * j;
    }
    (info, rhs)
}

/// The 3 × 7 map from a normalised motion to the displacement of the point `x` (object frame).
pub(crate) fn displacement_rows(x: V3, centre: V3, radius: f64) -> SMatrix<f64, 3, 7> {
    let r = (v(x) - v(centre)) / radius;
    SMatrix::<f64, 3, 7>::from_row_slice(&[
        r.x, 0.0, r.z, -r.y, 1.0, 0.0, 0.0, //
        r.y, -r.z, 0.0, r.x, 0.0, 1.0, 0.0, //
        r.z, r.y, -r.x, 0.0, 0.0, 0.0, 1.0,
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn displacement_rows_are_the_linearised_motion() {
        let (x, c, rho) = ([3.0, -1.0, 2.0], [0.5, 0.5, 0.5], 4.0);
        let delta = [0.01, 0.02, -0.03, 0.015, 0.1, -0.2, 0.05];
        let moved = Similarity::identity().moved(
            &std::array::from_fn(|k| if k < 4 { delta[k] / rho } else { delta[k] }),
            c,
        );
        let exact = v(moved.apply(x)) - v(x);
        let lin = displacement_rows(x, c, rho) * SVector::<f64, 7>::from_column_slice(&delta);
        assert!((exact - lin).norm() < 1e-3, "{exact} {lin}");
        assert!(median(&[3.0, 1.0, 2.0, f64::NAN]) == 2.0);
    }
}
