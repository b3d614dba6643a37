//! Camera intrinsics and extrinsics from views of a planar chessboard (Zhang 2000), and the
//! turntable axis from the same target seen at several turntable angles.
//!
//! Input is corner correspondences (board point in mm ↔ pixel), whatever found them: the
//! detector in [`super::detect`] for chessboard images, or another tool's output. Closed form
//! first (homographies → `B = K⁻ᵀK⁻¹` → `K` → poses), then Levenberg–Marquardt over `fx, fy, cx,
//! cy, k1, k2` and every pose by reprojection error.

use super::CalibError;
use super::lsq::minimize;
use crate::geometry::Camera;
use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, SVD, Vector3};
use serde::{Deserialize, Serialize};

/// The chessboard: inner corners per row and column, square size in mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ChessboardTarget {
    /// Inner corners along a row (x).
    pub cols: usize,
    /// Inner corners along a column (y).
    pub rows: usize,
    /// Square edge (mm).
    pub square_mm: f64,
}

impl ChessboardTarget {
    /// Board coordinates (mm, z = 0) of inner corner `(i, j)`, row-major order.
    pub fn points(&self) -> Vec<[f64; 2]> {
        let mut v = Vec::with_capacity(self.cols * self.rows);
        for j in 0..self.rows {
            for i in 0..self.cols {
                v.push([i as f64 * self.square_mm, j as f64 * self.square_mm]);
            }
        }
        v
    }
}

/// One view of the target: board points (mm) and where they were seen (pixels).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetView {
    /// Board coordinates, z = 0.
    pub board: Vec<[f64; 2]>,
    /// Pixel positions.
    pub pixels: Vec<[f64; 2]>,
}

/// A rigid pose: `camera = R · board + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation.
    pub r: Matrix3<f64>,
    /// Translation (mm).
    pub t: Vector3<f64>,
}

/// The result of [`fit_intrinsics`].
#[derive(Debug, Clone)]
pub struct IntrinsicsFit {
    /// `fx, fy, cx, cy`.
    pub k: [f64; 4],
    /// OpenCV `[k1, k2, p1, p2, k3]` (only k1, k2 are fitted).
    pub distortion: [f64; 5],
    /// Board pose of each view.
    pub poses: Vec<Pose>,
    /// RMS reprojection error (pixels).
    pub rms_px: f64,
}

fn normalizer(pts: &[[f64; 2]]) -> Matrix3<f64> {
    let n = pts.len() as f64;
    let (mx, my) = pts
        .iter()
        .fold((0.0, 0.0), |a, p| (a.0 + p[0] / n, a.1 + p[1] / n));
    let d = pts
        .iter()
        .map(|p| ((p[0] - mx).powi(2) + (p[1] - my).powi(2)).sqrt())
        .sum::<f64>()
        / n;
    let s = if d > 0.0 {
        std::f64::consts::SQRT_2 / d
    } else {
        1.0
    };
    Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0)
}

/// Normalised DLT homography board → pixel.
fn homography(v: &TargetView) -> Option<Matrix3<f64>> {
    let (tb, tp) = (normalizer(&v.board), normalizer(&v.pixels));
    let n = v.board.len();
    let mut a = DMatrix::zeros(2 * n, 9);
    for k in 0..n {
        let b = tb * Vector3::new(v.board[k][0], v.board[k][1], 1.0);
        let p = tp * Vector3::new(v.pixels[k][0], v.pixels[k][1], 1.0);
        let (x, y, u, w) = (b[0], b[1], p[0], p[1]);
        let r1 = [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u];
        let r2 = [0.0, 0.0, 0.0, -x, -y, -1.0, w * x, w * y, w];
        for c in 0..9 {
            a[(2 * k, c)] = r1[c];
            a[(2 * k + 1, c)] = r2[c];
        }
    }
    // Null vector = eigenvector of AᵀA with the smallest eigenvalue.
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))?;
    let h = eig.eigenvectors.column(imin);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let hm = tp.try_inverse()? * hn * tb;
    (hm[(2, 2)].abs() > 1e-15).then(|| hm / hm[(2, 2)])
}

fn vij(h: &Matrix3<f64>, i: usize, j: usize) -> [f64; 6] {
    let (hi, hj) = (h.column(i), h.column(j));
    [
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    ]
}

fn pose_from_h(k: &Matrix3<f64>, h: &Matrix3<f64>) -> Option<Pose> {
    let ki = k.try_inverse()?;
    let (h1, h2, h3) = (ki * h.column(0), ki * h.column(1), ki * h.column(2));
    let mut lambda = 1.0 / h1.norm();
    // The board is in front of the camera.
    if (lambda * h3)[2] < 0.0 {
        lambda = -lambda;
    }
    let (r1, r2) = (lambda * h1, lambda * h2);
    let r3 = r1.cross(&r2);
    let q = Matrix3::from_columns(&[r1, r2, r3]);
    let svd = SVD::new(q, true, true);
    let r = svd.u? * svd.v_t?;
    Some(Pose { r, t: lambda * h3 })
}

/// The camera of an intrinsics fit `k = [fx, fy, cx, cy]`, `dist = [k1, k2]`: the one camera
/// model ([`Camera`], OpenCV distortion), in its own frame (extrinsics are the board poses).
fn intrinsics_camera(k: &[f64], dist: [f64; 2]) -> Camera {
    Camera {
        width: 1,
        height: 1,
        fx: k[0],
        fy: k[1],
        cx: k[2],
        cy: k[3],
        distortion: Some(vec![dist[0], dist[1], 0.0, 0.0, 0.0]),
        camera_from_world: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    }
}

/// Pixel of board point `b` (mm, z = 0) seen with `pose` through `camera`
/// ([`Camera::project_camera`]); NaN behind the camera, which the least-squares solver rejects.
fn project(camera: &Camera, pose: &Pose, b: [f64; 2]) -> [f64; 2] {
    let p = pose.r * Vector3::new(b[0], b[1], 0.0) + pose.t;
    camera
        .project_camera([p[0], p[1], p[2]])
        .unwrap_or([f64::NAN; 2])
}

/// Intrinsics (`fx, fy, cx, cy, k1, k2`) and the board pose of every view (Zhang's method).
pub fn fit_intrinsics(views: &[TargetView]) -> Result<IntrinsicsFit, CalibError> {
    let usable: Vec<&TargetView> = views
        .iter()
        .filter(|v| v.board.len() == v.pixels.len() && v.board.len() >= 6)
        .collect();
    if usable.len() < 3 {
        return Err(CalibError::TargetNotFound(format!(
            "intrinsics need the chessboard in at least 3 views at different tilts; it was found \
             in {} of {} images",
            usable.len(),
            views.len()
        )));
    }
    let hs: Vec<Matrix3<f64>> = usable
        .iter()
        .map(|v| homography(v))
        .collect::<Option<_>>()
        .ok_or_else(|| CalibError::NotEnoughData("a view's corners are degenerate".into()))?;
    let mut v = DMatrix::zeros(2 * hs.len(), 6);
    for (i, h) in hs.iter().enumerate() {
        let (a, b, c) = (vij(h, 0, 1), vij(h, 0, 0), vij(h, 1, 1));
        for j in 0..6 {
            v[(2 * i, j)] = a[j];
            v[(2 * i + 1, j)] = b[j] - c[j];
        }
    }
    let eig = (v.transpose() * &v).symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))
        .ok_or_else(|| CalibError::NotEnoughData("no homographies".into()))?;
    let b = eig.eigenvectors.column(imin);
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let fx = (lambda / b11).sqrt();
    let fy = (lambda * b11 / den).sqrt();
    let u0 = -b13 * fx * fx / lambda;
    if ![fx, fy, u0, v0].iter().all(|x| x.is_finite()) {
        return Err(CalibError::NotEnoughData(
            "the views are too similar (tilt the target differently in each view)".into(),
        ));
    }
    let k0 = Matrix3::new(fx, 0.0, u0, 0.0, fy, v0, 0.0, 0.0, 1.0);
    let poses: Vec<Pose> = hs
        .iter()
        .map(|h| pose_from_h(&k0, h))
        .collect::<Option<_>>()
        .ok_or_else(|| CalibError::NotEnoughData("a board pose is degenerate".into()))?;
    // Refine: [fx fy cx cy k1 k2] + 6 per view (rotation vector, translation).
    let mut p0 = vec![fx, fy, u0, v0, 0.0, 0.0];
    for p in &poses {
        let rv = Rotation3::from_matrix_unchecked(p.r).scaled_axis();
        p0.extend_from_slice(&[rv[0], rv[1], rv[2], p.t[0], p.t[1], p.t[2]]);
    }
    let pose_of = |p: &DVector<f64>, i: usize| Pose {
        r: Rotation3::new(Vector3::new(p[6 + 6 * i], p[7 + 6 * i], p[8 + 6 * i])).into_inner(),
        t: Vector3::new(p[9 + 6 * i], p[10 + 6 * i], p[11 + 6 * i]),
    };
    let residual = |p: &DVector<f64>| {
        let mut r = Vec::new();
        let camera = intrinsics_camera(&[p[0], p[1], p[2], p[3]], [p[4], p[5]]);
        for (i, v) in usable.iter().enumerate() {
            let pose = pose_of(p, i);
            for (b, px) in v.board.iter().zip(&v.pixels) {
                let q = project(&camera, &pose, *b);
                r.push(q[0] - px[0]);
                r.push(q[1] - px[1]);
            }
        }
        DVector::from_vec(r)
    };
    let (p, rms) = minimize(DVector::from_vec(p0), residual).ok_or_else(|| {
        CalibError::NotConverged("intrinsics: reprojection fit did not converge".into())
    })?;
    Ok(IntrinsicsFit {
        k: [p[0], p[1], p[2], p[3]],
        distortion: [p[4], p[5], 0.0, 0.0, 0.0],
        poses: (0..usable.len()).map(|i| pose_of(&p, i)).collect(),
        rms_px: rms,
    })
}

/// Turntable axis and the world frame it defines.
#[derive(Debug, Clone)]
pub struct TurntableFit {
    /// Axis direction (camera frame, unit, pointing to the board's side = up).
    pub direction: Vector3<f64>,
    /// Axis point on the board plane at the first view (camera frame, mm).
    pub point: Vector3<f64>,
    /// The camera's extrinsics in the world frame this axis defines.
    pub camera_from_world: [[f64; 4]; 4],
    /// RMS distance (mm) between the board corners and their positions predicted by rotating
    /// the first view about the fitted axis.
    pub rms_mm: f64,
}

/// The turntable axis from the board lying on the platter, seen at turntable angles `deg[k]`
/// (board poses from [`fit_intrinsics`]).
///
/// The relative motions `Q_k = R_k R_0ᵀ` are rotations about the axis; their axes give the
/// direction (averaged, sign fixed by the measured angle direction), and `s_k = (I − Q_k) p`
/// gives a point `p` on it (least squares). The world origin is where the axis meets the board
/// plane of the first view, world `x` points along the board's `x` projected off the axis.
pub fn fit_turntable_axis(poses: &[Pose], deg: &[f64]) -> Result<TurntableFit, CalibError> {
    if poses.len() < 3 || poses.len() != deg.len() {
        return Err(CalibError::NotEnoughData(format!(
            "the turntable axis needs the target at 3 or more turntable angles; got {} views \
             with {} angles",
            poses.len(),
            deg.len()
        )));
    }
    let (r0, t0) = (poses[0].r, poses[0].t);
    let mut dir = Vector3::zeros();
    let mut m = DMatrix::zeros(3 * (poses.len() - 1), 3);
    let mut rhs = DVector::zeros(3 * (poses.len() - 1));
    for (k, p) in poses.iter().enumerate().skip(1) {
        let q = p.r * r0.transpose();
        let s = p.t - q * t0;
        let rv = Rotation3::from_matrix_unchecked(q).scaled_axis();
        // scaled_axis has its angle in [0, π]: orient it by the sign of the turn wrapped to
        // (−180°, 180°]; half turns are ambiguous and left out of the direction.
        let wrapped = (deg[k] - deg[0] + 180.0).rem_euclid(360.0) - 180.0;
        if wrapped.abs() > 1e-6 && wrapped.abs() < 170.0 {
            dir += rv * wrapped.signum();
        }
        let iq = Matrix3::identity() - q;
        for a in 0..3 {
            for b in 0..3 {
                m[(3 * (k - 1) + a, b)] = iq[(a, b)];
            }
            rhs[3 * (k - 1) + a] = s[a];
        }
    }
    if dir.norm() < 1e-6 {
        return Err(CalibError::NotEnoughData(
            "the target did not rotate between views (did the turntable move?)".into(),
        ));
    }
    let a = dir.normalize();
    let svd = m.svd(true, true);
    let p = svd
        .solve(&rhs, 1e-9)
        .map_err(|e| CalibError::NotEnoughData(e.into()))?;
    let p = Vector3::new(p[0], p[1], p[2]);
    // Intersect the axis with the first board plane (normal r0 z through t0).
    let n = r0.column(2).into_owned();
    let den = n.dot(&a);
    if den.abs() < 1e-6 {
        return Err(CalibError::NotEnoughData(
            "the target stands parallel to the axis; lay it on the platter".into(),
        ));
    }
    let origin = p + a * (n.dot(&(t0 - p)) / den);
    // World frame in camera coordinates: z = axis, x = board x without its axis component.
    let bx = r0.column(0).into_owned();
    let x = (bx - a * a.dot(&bx)).normalize();
    let y = a.cross(&x);
    let r_cw = Matrix3::from_columns(&[x, y, a]); // camera ← world rotation
    let mut cfw = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            cfw[i][j] = r_cw[(i, j)];
        }
        cfw[i][3] = origin[i];
    }
    cfw[3][3] = 1.0;
    // Check: corners of view 0 rotated about the axis must land on view k's corners.
    let mut se = 0.0;
    let mut cnt = 0.0;
    for (k, pk) in poses.iter().enumerate() {
        let rot = Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(a),
            (deg[k] - deg[0]).to_radians(),
        );
        for b in [[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]] {
            let x0 = r0 * Vector3::new(b[0], b[1], 0.0) + t0;
            let pred = rot * (x0 - origin) + origin;
            let meas = pk.r * Vector3::new(b[0], b[1], 0.0) + pk.t;
            se += (pred - meas).norm_squared();
            cnt += 1.0;
        }
    }
    Ok(TurntableFit {
        direction: a,
        point: origin,
        camera_from_world: cfw,
        rms_mm: (se / cnt).sqrt(),
    })
}

/// The turntable axis refined against the images: views `first..` of `intr` (whose corners are
/// `views[first..]`) show the board lying on the platter at angles `deg`. Starting from
/// [`fit_turntable_axis`], Levenberg–Marquardt adjusts the first board pose and the axis
/// (direction, and its point across the axis) so that rotating the board about the axis
/// reprojects onto every corner seen — one rigid model for all views instead of one pose each.
pub fn fit_turntable(
    intr: &IntrinsicsFit,
    views: &[TargetView],
    first: usize,
    deg: &[f64],
) -> Result<TurntableFit, CalibError> {
    let poses = intr.poses.get(first..).unwrap_or(&[]);
    let init = fit_turntable_axis(poses, deg)?;
    let views = views.get(first..).unwrap_or(&[]);
    let a0 = init.direction;
    let e1 = a0
        .cross(&if a0[0].abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        })
        .normalize();
    let e2 = a0.cross(&e1);
    let (r0, t0) = (poses[0].r, poses[0].t);
    let rv0 = Rotation3::from_matrix_unchecked(r0).scaled_axis();
    // [rv(3), t(3), axis tilt along e1, e2 (2), point shift along e1, e2 (2)]
    let p0 = DVector::from_vec(vec![
        rv0[0], rv0[1], rv0[2], t0[0], t0[1], t0[2], 0.0, 0.0, 0.0, 0.0,
    ]);
    let model = |p: &DVector<f64>| {
        let r = Rotation3::new(Vector3::new(p[0], p[1], p[2])).into_inner();
        let t = Vector3::new(p[3], p[4], p[5]);
        let a = (a0 + e1 * p[6] + e2 * p[7]).normalize();
        let q = init.point + e1 * p[8] + e2 * p[9];
        (r, t, a, q)
    };
    let camera = intrinsics_camera(&intr.k, [intr.distortion[0], intr.distortion[1]]);
    let residual = |p: &DVector<f64>| {
        let (r, t, a, q) = model(p);
        let mut res = Vec::new();
        for (v, d) in views.iter().zip(deg) {
            let rot = Rotation3::from_axis_angle(
                &nalgebra::Unit::new_normalize(a),
                (d - deg[0]).to_radians(),
            )
            .into_inner();
            let pose = Pose {
                r: rot * r,
                t: rot * (t - q) + q,
            };
            for (b, px) in v.board.iter().zip(&v.pixels) {
                let pr = project(&camera, &pose, *b);
                res.push(pr[0] - px[0]);
                res.push(pr[1] - px[1]);
            }
        }
        DVector::from_vec(res)
    };
    let (p, _) = minimize(p0, residual).ok_or_else(|| {
        CalibError::NotConverged("turntable axis: the joint fit did not converge".into())
    })?;
    let (r, t, a, q) = model(&p);
    let mut refined: Vec<Pose> = Vec::new();
    for d in deg {
        let rot = Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(a),
            (d - deg[0]).to_radians(),
        )
        .into_inner();
        refined.push(Pose {
            r: rot * r,
            t: rot * (t - q) + q,
        });
    }
    fit_turntable_axis(&refined, deg)
}

/// Builds the camera model from an intrinsics fit and a turntable fit.
pub fn camera_model(width: u32, height: u32, intr: &IntrinsicsFit, axis: &TurntableFit) -> Camera {
    Camera {
        width,
        height,
        fx: intr.k[0],
        fy: intr.k[1],
        cx: intr.k[2],
        cy: intr.k[3],
        distortion: Some(intr.distortion.to_vec()),
        camera_from_world: axis.camera_from_world,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot(ax: [f64; 3]) -> Matrix3<f64> {
        Rotation3::new(Vector3::from(ax)).into_inner()
    }

    /// Pixels of `board` seen with pose and intrinsics, with deterministic sub-pixel noise.
    fn view(
        k: &[f64; 4],
        dist: [f64; 2],
        pose: &Pose,
        t: &ChessboardTarget,
        seed: u32,
    ) -> TargetView {
        let mut s = seed;
        let camera = intrinsics_camera(k, dist);
        let board = t.points();
        let pixels = board
            .iter()
            .map(|b| {
                let mut q = project(&camera, pose, *b);
                for c in &mut q {
                    s = s.wrapping_mul(1_103_515_245).wrapping_add(12345);
                    *c += 0.2 * ((s >> 8) as f64 / (1u32 << 24) as f64 - 0.5);
                }
                q
            })
            .collect();
        TargetView { board, pixels }
    }

    #[test]
    fn zhang_recovers_intrinsics_and_the_axis() {
        let k = [1500.0, 1490.0, 330.0, 245.0];
        let dist = [-0.05, 0.01];
        let t = ChessboardTarget {
            cols: 9,
            rows: 6,
            square_mm: 25.0,
        };
        // Free-hand tilted views for intrinsics.
        let mut views = Vec::new();
        for (i, ax) in [
            [0.5, 0.1, 0.0],
            [-0.45, 0.2, 0.1],
            [0.1, -0.5, -0.1],
            [0.2, 0.45, 0.3],
            [-0.3, -0.4, 0.6],
            [0.4, -0.3, -0.5],
        ]
        .iter()
        .enumerate()
        {
            let pose = Pose {
                r: rot(*ax),
                t: Vector3::new(-100.0, -62.0, 500.0 + 20.0 * i as f64),
            };
            views.push(view(&k, dist, &pose, &t, i as u32));
        }
        // The board lying on the turntable, camera looking down at 30°.
        let axis_cam = Vector3::new(
            0.0,
            -0.5f64.cos() * 0.0 - 30f64.to_radians().cos(),
            -30f64.to_radians().sin(),
        )
        .normalize();
        let centre = Vector3::new(5.0, 20.0, 550.0);
        let board_r0 = {
            // board z = axis (lying flat), board x arbitrary perpendicular.
            let x = axis_cam.cross(&Vector3::new(1.0, 0.0, 0.0)).normalize();
            let y = axis_cam.cross(&x);
            Matrix3::from_columns(&[x, y, axis_cam])
        };
        let offset = Vector3::new(-100.0, -62.0, 0.0);
        let angles = [0.0, 30.0, 60.0, 90.0];
        for (i, d) in angles.iter().enumerate() {
            let q = Rotation3::from_axis_angle(
                &nalgebra::Unit::new_normalize(axis_cam),
                f64::to_radians(*d),
            )
            .into_inner();
            let pose = Pose {
                r: q * board_r0,
                t: centre + q * (board_r0 * offset),
            };
            views.push(view(&k, dist, &pose, &t, 100 + i as u32));
        }
        let first_axis_view = views.len() - angles.len();
        {}
        let fit = fit_intrinsics(&views).unwrap();
        for (got, want) in fit.k.iter().zip(k) {
            assert!((got / want - 1.0).abs() < 0.005, "{:?} vs {k:?}", fit.k);
        }
        assert!(fit.rms_px < 0.2, "{}", fit.rms_px);
        let axis = fit_turntable_axis(&fit.poses[first_axis_view..], &angles).unwrap();
        let err = axis.direction.angle(&axis_cam).to_degrees();
        assert!(err < 0.1, "axis off by {err}°");
        assert!((axis.point - centre).norm() < 1.0, "{:?}", axis.point);
    }

    #[test]
    fn too_few_views_say_what_is_missing() {
        let e = fit_intrinsics(&[]).unwrap_err().to_string();
        assert!(e.contains("found in 0 of 0 images"), "{e}");
        let e = fit_turntable_axis(&[], &[]).unwrap_err().to_string();
        assert!(e.contains("3 or more turntable angles"), "{e}");
    }
}
