//! Chessboard corners in images, and simulated images of the target.
//!
//! `calib-targets` (a maintained pure-Rust detector) was not adopted: its sub-crates were not in
//! the local crate cache and its build cost on this machine was not tried within the schedule.
//! This is a compact detector for the job instead: saddle points of the
//! smoothed image (negative Hessian determinant) → sub-pixel saddle of a fitted quadratic → a
//! lattice grown from the most central corner with locally updated grid vectors → the unique
//! orientation given by handedness (the printed side faces the camera) and the colour of the
//! first square (black). `cols + rows` must be odd so a half turn is distinguishable; every
//! failure says what was not found.

use super::CalibError;
use super::target::{ChessboardTarget, Pose, TargetView};
use crate::geometry::Camera;
use nalgebra::{Matrix6, Vector3, Vector6};
use std::collections::{HashMap, VecDeque};

/// A grey image, row-major, values in `[0, 1]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Gray {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Samples.
    pub data: Vec<f32>,
}

impl Gray {
    fn at(&self, x: i64, y: i64) -> f32 {
        let x = x.clamp(0, self.width as i64 - 1) as usize;
        let y = y.clamp(0, self.height as i64 - 1) as usize;
        self.data[y * self.width + x]
    }

    /// Converts an RGB or grey float image (any range) to grey, scaled to a maximum of 1.
    pub fn from_linear(width: usize, height: usize, channels: usize, data: &[f32]) -> Self {
        let mut g: Vec<f32> = data
            .chunks(channels.max(1))
            .map(|c| c.iter().sum::<f32>() / c.len() as f32)
            .collect();
        let max = g
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0f32, f32::max);
        for v in &mut g {
            *v = if v.is_finite() && max > 0.0 {
                *v / max
            } else {
                0.0
            };
        }
        Gray {
            width,
            height,
            data: g,
        }
    }
}

/// The camera `subsurf calib simulate` renders its chessboard images with: 320×240 pixels,
/// f = 400 px, 600 mm from the platter centre at 35° elevation, looking at it with `+z` up.
pub fn simulated_camera() -> Camera {
    let el = 35f64.to_radians();
    let eye = [0.0, -600.0 * el.cos(), 600.0 * el.sin()];
    // Never degenerate: the eye is 600 mm from the target and off the z axis.
    Camera::look_at(eye, [0.0; 3], [0.0, 0.0, 1.0], 400.0, 320, 240).unwrap_or_else(|| {
        unreachable!("a fixed camera 600 mm off the platter centre is never degenerate")
    })
}

/// Renders the board (printed side towards `−z` of the board frame, black first square) seen
/// by `camera` (intrinsics only; no distortion) at `pose` (camera ← board), 4×4 supersampled.
/// A white margin of 0.6 squares surrounds the squares; beyond it the background is 0.3.
pub fn render_board(camera: &Camera, target: &ChessboardTarget, pose: &Pose) -> Gray {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let rt = pose.r.transpose();
    let s = target.square_mm;
    let mut data = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    let u = x as f64 - 0.375 + 0.25 * sx as f64;
                    let v = y as f64 - 0.375 + 0.25 * sy as f64;
                    let d = Vector3::new(
                        (u - camera.cx) / camera.fx,
                        (v - camera.cy) / camera.fy,
                        1.0,
                    );
                    // Ray camera-origin + t d in board frame: rt (t d - pose.t); z = 0.
                    let o = -(rt * pose.t);
                    let db = rt * d;
                    let val = if db[2].abs() < 1e-12 {
                        0.3
                    } else {
                        let t = -o[2] / db[2];
                        if t <= 0.0 {
                            0.3
                        } else {
                            let bx = o[0] + t * db[0];
                            let by = o[1] + t * db[1];
                            let a = (bx / s).floor() as i64 + 1;
                            let b = (by / s).floor() as i64 + 1;
                            let (na, nb) = (target.cols as i64, target.rows as i64);
                            if (0..=na).contains(&a) && (0..=nb).contains(&b) {
                                if (a + b) % 2 == 0 { 0.05 } else { 0.95 }
                            } else if bx > -1.6 * s
                                && by > -1.6 * s
                                && bx < (na as f64 + 0.6) * s
                                && by < (nb as f64 + 0.6) * s
                            {
                                0.95
                            } else {
                                0.3
                            }
                        }
                    };
                    acc += val;
                }
            }
            data[y * w + x] = (acc / 16.0) as f32;
        }
    }
    Gray {
        width: w,
        height: h,
        data,
    }
}

fn blur(g: &Gray, sigma: f64) -> Gray {
    let r = (3.0 * sigma).ceil() as i64;
    let k: Vec<f32> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let ks: f32 = k.iter().sum();
    let pass = |src: &Gray, dx: i64, dy: i64| {
        let mut out = src.clone();
        for y in 0..src.height as i64 {
            for x in 0..src.width as i64 {
                let mut a = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    let o = i as i64 - r;
                    a += kv * src.at(x + o * dx, y + o * dy);
                }
                out.data[y as usize * src.width + x as usize] = a / ks;
            }
        }
        out
    };
    pass(&pass(g, 1, 0), 0, 1)
}

/// Sub-pixel saddle: least-squares quadratic over a 5×5 window, its stationary point.
fn saddle(g: &Gray, x: i64, y: i64) -> Option<[f64; 2]> {
    let mut ata = Matrix6::<f64>::zeros();
    let mut atb = Vector6::<f64>::zeros();
    for dy in -2..=2i64 {
        for dx in -2..=2i64 {
            let (fx, fy) = (dx as f64, dy as f64);
            let row = Vector6::new(fx * fx, fx * fy, fy * fy, fx, fy, 1.0);
            let v = g.at(x + dx, y + dy) as f64;
            ata += row * row.transpose();
            atb += row * v;
        }
    }
    let c = ata.try_inverse()? * atb;
    let (a, b, cc, d, e) = (c[0], c[1], c[2], c[3], c[4]);
    let det = 4.0 * a * cc - b * b;
    if det >= 0.0 {
        return None; // not a saddle
    }
    let ox = (-2.0 * cc * d + b * e) / det;
    let oy = (-2.0 * a * e + b * d) / det;
    (ox.abs() <= 1.0 && oy.abs() <= 1.0).then_some([x as f64 + ox, y as f64 + oy])
}

/// Refines a corner like OpenCV's `cornerSubPix`: every edge gradient `g` at `p` near the corner
/// `q` is orthogonal to `p − q`, so `q = (Σ g gᵀ)⁻¹ Σ g gᵀ p` over a Gaussian-weighted window.
fn refine(g: &Gray, start: [f64; 2]) -> Option<[f64; 2]> {
    let mut q = start;
    for _ in 0..6 {
        let (cx, cy) = (q[0].round() as i64, q[1].round() as i64);
        let mut a = nalgebra::Matrix2::<f64>::zeros();
        let mut b = nalgebra::Vector2::<f64>::zeros();
        for dy in -5..=5i64 {
            for dx in -5..=5i64 {
                let (x, y) = (cx + dx, cy + dy);
                let gx = (g.at(x + 1, y) - g.at(x - 1, y)) as f64 / 2.0;
                let gy = (g.at(x, y + 1) - g.at(x, y - 1)) as f64 / 2.0;
                let w = (-((x as f64 - q[0]).powi(2) + (y as f64 - q[1]).powi(2)) / 18.0).exp();
                let gg = nalgebra::Matrix2::new(gx * gx, gx * gy, gx * gy, gy * gy) * w;
                a += gg;
                b += gg * nalgebra::Vector2::new(x as f64, y as f64);
            }
        }
        let n = a.try_inverse()? * b;
        let moved = (n[0] - q[0]).hypot(n[1] - q[1]);
        q = [n[0], n[1]];
        if (q[0] - start[0]).hypot(q[1] - start[1]) > 2.0 {
            return None;
        }
        if moved < 1e-3 {
            break;
        }
    }
    Some(q)
}

/// Finds the inner corners of `target` in `img`, in board order (row-major, as
/// [`ChessboardTarget::points`]).
pub fn detect_chessboard(img: &Gray, target: &ChessboardTarget) -> Result<TargetView, CalibError> {
    if (target.cols + target.rows).is_multiple_of(2) || target.cols < 2 || target.rows < 2 {
        return Err(CalibError::Invalid(format!(
            "a {}x{} board is ambiguous under a half turn: use inner corner counts with an odd \
             sum (e.g. 9x6)",
            target.cols, target.rows
        )));
    }
    let b = blur(img, 1.2);
    let (w, h) = (b.width as i64, b.height as i64);
    // Saddle response = −det(Hessian).
    let mut resp = vec![0.0f32; b.data.len()];
    for y in 2..h - 2 {
        for x in 2..w - 2 {
            let c = b.at(x, y);
            let ixx = b.at(x + 1, y) + b.at(x - 1, y) - 2.0 * c;
            let iyy = b.at(x, y + 1) + b.at(x, y - 1) - 2.0 * c;
            let ixy = (b.at(x + 1, y + 1) - b.at(x + 1, y - 1) - b.at(x - 1, y + 1)
                + b.at(x - 1, y - 1))
                / 4.0;
            resp[(y * w + x) as usize] = (ixy * ixy - ixx * iyy).max(0.0);
        }
    }
    let max = resp.iter().copied().fold(0.0f32, f32::max);
    if max <= 0.0 {
        return Err(CalibError::TargetNotFound(
            "no chessboard corners (saddle points) in the image".into(),
        ));
    }
    let mut cands: Vec<[f64; 2]> = Vec::new();
    for y in 3..h - 3 {
        for x in 3..w - 3 {
            let v = resp[(y * w + x) as usize];
            if v < 0.15 * max {
                continue;
            }
            let mut is_max = true;
            'n: for dy in -3..=3i64 {
                for dx in -3..=3i64 {
                    let o = resp[((y + dy) * w + x + dx) as usize];
                    if o > v || (o == v && (dy, dx) < (0, 0)) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if is_max
                && let Some(p) = saddle(&b, x, y)
                && let Some(p) = refine(&b, p)
            {
                cands.push(p);
            }
        }
    }
    let want = target.cols * target.rows;
    if cands.len() < want {
        return Err(CalibError::TargetNotFound(format!(
            "found {} corner-like points, a {}x{} chessboard has {want} inner corners (is the \
             whole board in view and in focus?)",
            cands.len(),
            target.cols,
            target.rows
        )));
    }
    let (seed, bases) = bases(&cands);
    let mut best: Option<HashMap<(i64, i64), usize>> = None;
    for (u, v) in bases {
        let grid = grow_lattice(&cands, seed, u, v);
        let (_, _, ni, nj, complete) = extent(&grid);
        let fits = (ni, nj) == (target.cols, target.rows) || (ni, nj) == (target.rows, target.cols);
        if complete && fits {
            return orient(&grid, &cands, img, target);
        }
        if best.as_ref().is_none_or(|b| grid.len() > b.len()) {
            best = Some(grid);
        }
    }
    let (_, _, ni, nj, complete) = best.as_ref().map_or((0, 0, 0, 0, false), extent);
    Err(CalibError::TargetNotFound(format!(
        "found a {ni}x{nj} grid of corners{}, expected the {}x{} chessboard (check --board, and that the whole board is visible)",
        if complete { "" } else { " with gaps" },
        target.cols,
        target.rows
    )))
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// Two lattice vectors (pixels).
type Basis = ([f64; 2], [f64; 2]);

/// Candidate lattice bases at the most central corner: pairs of vectors to its nearest
/// neighbours that are clearly not collinear. Sheared bases also grow complete lattices, so
/// the caller keeps the basis whose lattice is the board's rectangle.
fn bases(c: &[[f64; 2]]) -> (usize, Vec<Basis>) {
    let n = c.len() as f64;
    let centre = c
        .iter()
        .fold([0.0, 0.0], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
    let seed = (0..c.len())
        .min_by(|&a, &b| dist2(c[a], centre).total_cmp(&dist2(c[b], centre)))
        .unwrap_or(0);
    let mut near: Vec<usize> = (0..c.len()).filter(|&k| k != seed).collect();
    near.sort_by(|&a, &b| dist2(c[a], c[seed]).total_cmp(&dist2(c[b], c[seed])));
    let d: Vec<[f64; 2]> = near
        .iter()
        .take(8)
        .map(|&k| [c[k][0] - c[seed][0], c[k][1] - c[seed][1]])
        .collect();
    let mut out = Vec::new();
    for a in 0..d.len() {
        for b in a + 1..d.len() {
            let (u, v) = (d[a], d[b]);
            let cr = (u[0] * v[1] - u[1] * v[0]).abs();
            if cr > 0.3 * u[0].hypot(u[1]) * v[0].hypot(v[1]) {
                out.push((u, v));
            }
        }
    }
    (seed, out)
}

/// Assigns integer lattice coordinates by growing from `seed` with basis `(u, v)`, updating the
/// basis locally from every corner found (perspective changes the spacing across the board).
fn grow_lattice(
    c: &[[f64; 2]],
    seed: usize,
    u: [f64; 2],
    v: [f64; 2],
) -> HashMap<(i64, i64), usize> {
    let sub = |a: [f64; 2], b: [f64; 2]| [a[0] - b[0], a[1] - b[1]];
    let mut grid: HashMap<(i64, i64), usize> = HashMap::new();
    let mut used = vec![false; c.len()];
    grid.insert((0, 0), seed);
    used[seed] = true;
    let mut queue = VecDeque::from([((0i64, 0i64), u, v)]);
    while let Some(((i, j), u, v)) = queue.pop_front() {
        let Some(&pk) = grid.get(&(i, j)) else {
            continue;
        };
        let p = c[pk];
        for (di, dj) in [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)] {
            if grid.contains_key(&(i + di, j + dj)) {
                continue;
            }
            let step = [
                di as f64 * u[0] + dj as f64 * v[0],
                di as f64 * u[1] + dj as f64 * v[1],
            ];
            let pred = [p[0] + step[0], p[1] + step[1]];
            let tol = 0.3 * step[0].hypot(step[1]);
            let best = (0..c.len())
                .filter(|&k| !used[k])
                .min_by(|&a, &b| dist2(c[a], pred).total_cmp(&dist2(c[b], pred)));
            if let Some(k) = best
                && dist2(c[k], pred).sqrt() < tol
            {
                used[k] = true;
                grid.insert((i + di, j + dj), k);
                let actual = sub(c[k], p);
                let (nu, nv) = if di != 0 {
                    ([actual[0] * di as f64, actual[1] * di as f64], v)
                } else {
                    (u, [actual[0] * dj as f64, actual[1] * dj as f64])
                };
                queue.push_back(((i + di, j + dj), nu, nv));
            }
        }
    }
    grid
}

/// The lattice's bounding box `(i0, j0, ni, nj)` and whether every position in it is filled.
fn extent(grid: &HashMap<(i64, i64), usize>) -> (i64, i64, usize, usize, bool) {
    let (mut i0, mut i1, mut j0, mut j1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
    for &(i, j) in grid.keys() {
        i0 = i0.min(i);
        i1 = i1.max(i);
        j0 = j0.min(j);
        j1 = j1.max(j);
    }
    let (ni, nj) = ((i1 - i0 + 1).max(0) as usize, (j1 - j0 + 1).max(0) as usize);
    (i0, j0, ni, nj, grid.len() == ni * nj)
}

/// Picks the one lattice symmetry that matches the board's size, handedness and first colour.
fn orient(
    grid: &HashMap<(i64, i64), usize>,
    c: &[[f64; 2]],
    img: &Gray,
    t: &ChessboardTarget,
) -> Result<TargetView, CalibError> {
    let (i0, j0, ni, nj, _) = extent(grid);
    let (cols, rows) = (t.cols, t.rows);
    let corner = |i: i64, j: i64| grid.get(&(i, j)).map_or([f64::NAN; 2], |&k| c[k]);
    // The 8 symmetries: (transpose, flip i, flip j). Map board (a, b) → lattice (i, j).
    let mut found = Vec::new();
    for transpose in [false, true] {
        for fi in [false, true] {
            for fj in [false, true] {
                let (bi, bj) = if transpose { (nj, ni) } else { (ni, nj) };
                if (bi, bj) != (cols, rows) {
                    continue;
                }
                let map = move |a: usize, b: usize| -> (i64, i64) {
                    let (mut x, mut y) = (a as i64, b as i64);
                    if fi {
                        x = cols as i64 - 1 - x;
                    }
                    if fj {
                        y = rows as i64 - 1 - y;
                    }
                    if transpose {
                        (i0 + y, j0 + x)
                    } else {
                        (i0 + x, j0 + y)
                    }
                };
                let p00 = corner_at(map(0, 0), &corner);
                let p10 = corner_at(map(1, 0), &corner);
                let p01 = corner_at(map(0, 1), &corner);
                let p11 = corner_at(map(1, 1), &corner);
                let u = [p10[0] - p00[0], p10[1] - p00[1]];
                let v = [p01[0] - p00[0], p01[1] - p00[1]];
                // Printed side seen: board x → image x, board y → image y without mirroring.
                if u[0] * v[1] - u[1] * v[0] <= 0.0 {
                    continue;
                }
                let m = [
                    (p00[0] + p10[0] + p01[0] + p11[0]) / 4.0,
                    (p00[1] + p10[1] + p01[1] + p11[1]) / 4.0,
                ];
                let dark = img.at(m[0].round() as i64, m[1].round() as i64) < 0.5;
                if dark {
                    found.push(map);
                }
            }
        }
    }
    let Some(map) = found.first() else {
        return Err(CalibError::TargetNotFound(
            "the corner grid was found but not the board's orientation (first square black, \
             printed side towards the camera)"
                .into(),
        ));
    };
    let board = t.points();
    let mut pixels = Vec::with_capacity(board.len());
    for b in 0..rows {
        for a in 0..cols {
            pixels.push(corner_at(map(a, b), &corner));
        }
    }
    Ok(TargetView { board, pixels })
}

fn corner_at(ij: (i64, i64), corner: &impl Fn(i64, i64) -> [f64; 2]) -> [f64; 2] {
    corner(ij.0, ij.1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Rotation3};

    fn cam() -> Camera {
        let mut c =
            Camera::look_at([0.0, -1.0, 0.0], [0.0; 3], [0.0, 0.0, 1.0], 400.0, 320, 240).unwrap();
        c.cx = 161.3;
        c.cy = 118.7;
        c
    }

    pub(crate) fn board_pose(t: &ChessboardTarget, ax: [f64; 3], dist: f64) -> Pose {
        // Printed side (−z) towards the camera: board z points away, along +z of the camera.
        let r: Matrix3<f64> = Rotation3::new(Vector3::from(ax)).into_inner();
        let centre = Vector3::new(
            t.square_mm * (t.cols as f64 - 1.0) / 2.0,
            t.square_mm * (t.rows as f64 - 1.0) / 2.0,
            0.0,
        );
        Pose {
            r,
            t: Vector3::new(0.0, 0.0, dist) - r * centre,
        }
    }

    #[test]
    fn finds_every_corner_in_order_to_a_tenth_of_a_pixel() {
        let t = ChessboardTarget {
            cols: 9,
            rows: 6,
            square_mm: 20.0,
        };
        let c = cam();
        let pose = board_pose(&t, [0.3, -0.2, 0.15], 700.0);
        let img = render_board(&c, &t, &pose);
        let view = detect_chessboard(&img, &t).unwrap();
        assert_eq!(view.pixels.len(), 54);
        for (b, px) in view.board.iter().zip(&view.pixels) {
            let p = pose.r * Vector3::new(b[0], b[1], 0.0) + pose.t;
            let want = [c.fx * p[0] / p[2] + c.cx, c.fy * p[1] / p[2] + c.cy];
            assert!(dist2(want, *px).sqrt() < 0.1, "{b:?}: {px:?} vs {want:?}");
        }
    }

    #[test]
    fn a_missing_or_wrong_board_is_named() {
        let t = ChessboardTarget {
            cols: 9,
            rows: 6,
            square_mm: 20.0,
        };
        let c = cam();
        let blank = Gray {
            width: 320,
            height: 240,
            data: vec![0.5; 320 * 240],
        };
        let e = detect_chessboard(&blank, &t).unwrap_err().to_string();
        assert!(e.contains("no chessboard corners"), "{e}");
        let img = render_board(&c, &t, &board_pose(&t, [0.1, 0.1, 0.0], 700.0));
        let wrong = ChessboardTarget {
            cols: 7,
            rows: 4,
            square_mm: 20.0,
        };
        let e = detect_chessboard(&img, &wrong).unwrap_err().to_string();
        assert!(e.contains("9x6") || e.contains("6x9"), "{e}");
        assert!(e.contains("expected the 7x4"), "{e}");
    }

    #[test]
    fn simulated_images_give_intrinsics_and_turntable_axis() {
        use super::super::target::{fit_intrinsics, fit_turntable};
        let t = ChessboardTarget {
            cols: 9,
            rows: 6,
            square_mm: 30.0,
        };
        let c = simulated_camera();
        let mut views = Vec::new();
        for ax in [
            [0.4, 0.1, 0.0],
            [-0.4, 0.2, 0.1],
            [0.1, -0.45, -0.1],
            [0.25, 0.35, 0.3],
            [-0.3, -0.3, 0.5],
        ] {
            let img = render_board(&c, &t, &board_pose(&t, ax, 520.0));
            views.push(detect_chessboard(&img, &t).unwrap());
        }
        // The board lying on the platter (printed side up, so its z points down), centred on
        // the axis, at four turntable angles.
        let m = c.camera_from_world;
        let r_cw = Matrix3::from_fn(|i, j| m[i][j]);
        let t_cw = Vector3::new(m[0][3], m[1][3], m[2][3]);
        let r_wb = Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);
        let t_wb = Vector3::new(-120.0, 75.0, 0.0);
        let angles = [0.0, 60.0, 120.0, 180.0, 240.0, 300.0];
        for d in angles {
            let rz =
                Rotation3::from_axis_angle(&Vector3::z_axis(), f64::to_radians(d)).into_inner();
            let pose = Pose {
                r: r_cw * rz * r_wb,
                t: r_cw * rz * t_wb + t_cw,
            };
            views.push(detect_chessboard(&render_board(&c, &t, &pose), &t).unwrap());
        }
        let fit = fit_intrinsics(&views).unwrap();
        let want = [c.fx, c.fy, c.cx, c.cy];
        for (g, w) in fit.k.iter().zip(want) {
            assert!((g / w - 1.0).abs() < 0.005, "{:?} vs {want:?}", fit.k);
        }
        let axis = fit_turntable(&fit, &views, 5, &angles).unwrap();
        let true_axis = r_cw * Vector3::z();
        let err = axis.direction.angle(&true_axis).to_degrees();
        assert!(err < 0.1, "axis off by {err}°");
        assert!(
            (axis.point - t_cw).norm() < 2.0,
            "{:?} vs {t_cw:?}",
            axis.point
        );
    }
}
