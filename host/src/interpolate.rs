//! Harmonic interpolation over the mesh graph, for what is missing at some vertices (section 5:
//! "vertices for which no stable fit could be achieved were filtered out and interpolated from
//! neighboring vertices"; the pipeline's failed vertices, and alpha where no frame saw a texel).
//!
//! Every unknown vertex becomes the mean of its neighbours, known vertices held fixed: the
//! discrete Laplace equation, from a breadth-first initial guess. Plain values ([`harmonic`]) are
//! solved by conjugate gradients on the graph Laplacian, or on the default fit's path by a
//! sparse Cholesky factor of it kept while the known set holds ([`Laplace`]); vectors that hold one entry per
//! direction segment (Eq. 3) are only averaged in one frame: [`harmonic_aligned`] lets the caller
//! re-express a neighbour's vector in the frame of the vertex it is averaged into, so curves are
//! never averaged across a turn of the tangent frame, and solves by Gauss–Seidel sweeps.

use rayon::prelude::*;

/// Fills every `None` in `values` with the harmonic interpolation of the `Some` values over the
/// graph given by `neighbours` (which must be symmetric, as a mesh's edges are). Vertices not
/// connected to any known vertex stay `None`. All known vectors must have the same length.
/// `iterations` bounds the solve.
///
/// Conjugate gradients (Jacobi-preconditioned) rather than Gauss–Seidel: the Laplacian of a hole
/// d edges across has a condition number of order d², so Gauss–Seidel needs of order d² sweeps
/// to settle and CG of order d iterations. The cross-validation's fold fits leave holes a
/// turntable angle wide at every vertex without data, where Gauss–Seidel ran into its 2,000
/// sweeps and took three quarters of a default `subsurf fit` (sample-pebble); CG also ends
/// nearer the solution (relative residual 1e-13 against a sweep that moved nothing by 1e-12).
pub fn harmonic<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32],
    iterations: usize,
) -> Vec<Option<Vec<f64>>> {
    harmonic_with(
        values,
        neighbours,
        &Solve {
            iterations,
            ..Solve::default()
        },
    )
}

/// How [`harmonic_with`] solves: [`harmonic`]'s exact solve by default.
#[derive(Debug, Clone, Copy)]
pub struct Solve<'w> {
    /// At most this many iterations.
    pub iterations: usize,
    /// Conjugate gradients stop at this relative residual ([`RTOL`] by default).
    pub rtol: f64,
    /// A previous solution (of the same graph and vector length) for conjugate gradients to
    /// start from where it has a value, instead of the breadth-first guess: a start near the
    /// solution needs fewer iterations to the same residual. (The alpha rounds started from
    /// the previous round's texture until their fill was factored, [`Solve::direct`].)
    pub warm: Option<&'w [Option<Vec<f64>>]>,
    /// Only the unknown vertices connected through unknown vertices to one of these are
    /// solved; the others keep the breadth-first guess. A fold of the cross-validation reads
    /// the model only at the corners of its held-out frames' x_i: the rest of a solve is never
    /// read.
    pub only: Option<&'w [bool]>,
    /// Solve directly, by a sparse Cholesky factor of the Laplace rows kept here while the
    /// known set and the solved vertices stay the same ([`Laplace`]), instead of by conjugate
    /// gradients (`iterations`, `rtol` and `warm` then apply only where the factor cannot be
    /// had: vectors of different lengths).
    pub direct: Option<&'w FactorCache>,
}

impl Default for Solve<'_> {
    fn default() -> Self {
        Solve {
            iterations: 2000,
            rtol: RTOL,
            warm: None,
            only: None,
            direct: None,
        }
    }
}

/// [`harmonic`] solved as `solve` says.
pub fn harmonic_with<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32],
    solve: &Solve,
) -> Vec<Option<Vec<f64>>> {
    let no_turn = |_: usize, _: usize, _: &[f64]| None;
    let (mut out, mut order) = breadth_first(values, &neighbours, &no_turn);
    if let Some(only) = solve.only {
        order = connected_to(&order, only, &neighbours);
    }
    if let Some(cache) = solve.direct
        && direct(values, &mut out, &order, &neighbours, cache)
    {
        return out;
    }
    if let Some(warm) = solve.warm {
        for &v in &order {
            if let (Some(w), Some(o)) = (warm.get(v).and_then(Option::as_ref), out[v].as_mut())
                && w.len() == o.len()
                && w.iter().all(|x| x.is_finite())
            {
                o.copy_from_slice(w);
            }
        }
    }
    if !conjugate_gradients(&mut out, &order, &neighbours, solve.iterations, solve.rtol) {
        gauss_seidel(&mut out, &order, &neighbours, &no_turn, solve.iterations);
    }
    out
}

/// The vertices of `order` (unknown ones) connected through vertices of `order` to a vertex
/// marked in `only`, in the order of `order`: whole components of the unknown subgraph, so
/// every unknown neighbour of a kept vertex is kept and the Laplace system of the kept ones is
/// the one of the whole, restricted to the components that are read.
fn connected_to<'a>(
    order: &[usize],
    only: &[bool],
    neighbours: &impl Fn(usize) -> &'a [u32],
) -> Vec<usize> {
    let n = only
        .len()
        .max(order.iter().map(|&v| v + 1).max().unwrap_or(0));
    let mut unknown = vec![false; n];
    for &v in order {
        unknown[v] = true;
    }
    let mut keep = vec![false; n];
    let mut stack: Vec<usize> = order
        .iter()
        .copied()
        .filter(|&v| only.get(v).copied().unwrap_or(false))
        .collect();
    for &v in &stack {
        keep[v] = true;
    }
    while let Some(v) = stack.pop() {
        for &w in neighbours(v) {
            let w = w as usize;
            if w < n && unknown[w] && !keep[w] {
                keep[w] = true;
                stack.push(w);
            }
        }
    }
    order.iter().copied().filter(|&v| keep[v]).collect()
}

/// [`harmonic`] where `align(v, w, x)` re-expresses neighbour `w`'s vector `x` for vertex `v`
/// (`None`: use it as it is). The pipeline turns a neighbour's direction segments into `v`'s
/// tangent frame with it. Gauss–Seidel, at most `sweeps` sweeps: the turns make the operator
/// other than the symmetric Laplacian conjugate gradients need.
pub fn harmonic_aligned<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32],
    align: impl Fn(usize, usize, &[f64]) -> Option<Vec<f64>>,
    sweeps: usize,
) -> Vec<Option<Vec<f64>>> {
    let (mut out, order) = breadth_first(values, &neighbours, &align);
    gauss_seidel(&mut out, &order, &neighbours, &align, sweeps);
    out
}

/// The initial guess: each unknown vertex, in order of distance from the known set, takes the
/// mean of its already-assigned neighbours. Returns the guess and the unknown vertices it
/// reached, in that order.
fn breadth_first<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: &impl Fn(usize) -> &'a [u32],
    align: &impl Fn(usize, usize, &[f64]) -> Option<Vec<f64>>,
) -> (Vec<Option<Vec<f64>>>, Vec<usize>) {
    let n = values.len();
    let mut out: Vec<Option<Vec<f64>>> = values.to_vec();
    let fixed: Vec<bool> = values.iter().map(Option::is_some).collect();
    let mut frontier: Vec<usize> = (0..n).filter(|&v| fixed[v]).collect();
    let mut assigned = fixed;
    let mut order = Vec::new();
    let mut buf = Vec::new();
    while !frontier.is_empty() {
        let mut next = Vec::new();
        for &v in &frontier {
            for &w in neighbours(v) {
                let w = w as usize;
                if w < n && !assigned[w] {
                    assigned[w] = true;
                    next.push(w);
                }
            }
        }
        for &w in &next {
            out[w] = mean_into(&out, w, neighbours(w), align, &mut buf).then(|| buf.clone());
            order.push(w);
        }
        frontier = next;
    }
    (out, order)
}

/// The harmonic interpolation's weights at the unknown vertices `targets`: for each, the
/// known vertices and weights w with value(target) = Σ w · value(known), for any values of the
/// known vertices `known` (the same as [`harmonic_with`] gives, up to rounding: one factor of
/// the rows, [`Laplace`], solves for every target; conjugate gradients to `solve.rtol` where
/// it cannot be had). `None`
/// for a target that is known, or not connected to a known vertex.
///
/// Why: the Laplace system's matrix depends only on which vertices are known. A fold of the
/// cross-validation needs the interpolation at a few dozen vertices (the corners of its
/// held-out frames' x_i) in every round of every candidate, while the known set stays the
/// same: one solve per target, L_UU y = e_target (L_UU is symmetric), gives x_target =
/// yᵀ·b for every later right-hand side b, instead of a solve of the whole hole per round.
pub fn harmonic_weights<'a>(
    known: &[bool],
    neighbours: impl Fn(usize) -> &'a [u32],
    targets: &[usize],
    solve: &Solve,
) -> Vec<Option<Vec<(u32, f64)>>> {
    let n = known.len();
    let values: Vec<Option<Vec<f64>>> = known.iter().map(|&k| k.then(Vec::new)).collect();
    let no_turn = |_: usize, _: usize, _: &[f64]| None;
    let (_, order) = breadth_first(&values, &neighbours, &no_turn);
    let mut only = vec![false; n];
    for &t in targets {
        if let Some(o) = only.get_mut(t) {
            *o = true;
        }
    }
    let order = connected_to(&order, &only, &neighbours);
    let system = System::structure(n, &order, |w| known[w], &neighbours);
    let rows: Vec<Option<usize>> = targets
        .iter()
        .map(|&t| system.pos.get(t).copied().filter(|&p| p != usize::MAX))
        .collect();
    let cols: Vec<usize> = rows.iter().flatten().copied().collect();
    if cols.is_empty() || system.deg.iter().any(|&d| d <= 0.0) {
        return vec![None; targets.len()];
    }
    let len = cols.len();
    let nu = order.len();
    let mut b = vec![0.0; nu * len];
    for (c, &row) in cols.iter().enumerate() {
        b[row * len + c] = 1.0;
    }
    // One factor for every target (a fold's few dozen), where conjugate gradients ran the
    // whole hole once per four targets; they stay the fallback.
    let x: Vec<f64> = match Laplace::of_system(&system) {
        Some(f) => f.solve(&b, len),
        None => {
            let blocks = cg_blocks(&system, &b, len, |_, _| 0.0, solve.iterations, solve.rtol);
            (0..nu * len)
                .map(|k| blocks[k % len / LANES].x[k / len][k % len % LANES])
                .collect()
        }
    };
    let mut out = vec![None; targets.len()];
    let mut c = 0;
    for (slot, row) in out.iter_mut().zip(&rows) {
        if row.is_none() {
            continue;
        }
        let col = c;
        c += 1;
        let y = |i: usize| x[i * len + col];
        let mut w: std::collections::BTreeMap<u32, f64> = std::collections::BTreeMap::new();
        for (i, &v) in order.iter().enumerate() {
            let yi = y(i);
            if yi == 0.0 {
                continue;
            }
            for &u in neighbours(v) {
                if (u as usize) < n && known[u as usize] {
                    *w.entry(u).or_default() += yi;
                }
            }
        }
        if w.values().all(|x| x.is_finite()) {
            *slot = Some(w.into_iter().collect());
        }
    }
    out
}

/// The Laplace rows of the unknown vertices of one known set, factored: P·L_UU·Pᵀ = L·Lᵀ, P an
/// approximate-minimum-degree order (the `amd` crate), L by `nalgebra-sparse`.
///
/// Why a direct solve: the fills of a fit solve the same rows again and again with new
/// right-hand sides (the alpha texture in every round of every fold with the same known set,
/// a fold's interpolation weights for a few dozen targets at once). Conjugate gradients took
/// 168–188 iterations a solve on the 655,362-vertex pebble's level of detail (about 4,400
/// unknowns), a fifth of that fit's CPU; the factor of such a hole, in this order, costs
/// about what a few of those iterations do, and each further solve two sparse triangular
/// sweeps. It is exact up to rounding where conjugate gradients stopped at a residual.
pub struct Laplace {
    /// Each factor position's row (an index into the solved vertices).
    perm: Vec<usize>,
    chol: nalgebra_sparse::factorization::CscCholesky<f64>,
}

impl std::fmt::Debug for Laplace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Laplace")
            .field("rows", &self.perm.len())
            .field("factor_nnz", &self.chol.l().nnz())
            .finish()
    }
}

/// A [`Laplace`] factor kept from one solve to the next ([`Solve::direct`]), with what it
/// holds for: the input's known set and the solved vertices.
#[derive(Debug, Default)]
pub struct FactorCache(std::sync::Mutex<Option<(FactorKey, std::sync::Arc<Laplace>)>>);

/// The known set and the solved vertices of a [`FactorCache`]'s factor.
type FactorKey = (Vec<bool>, Vec<usize>);

impl Laplace {
    /// The factor of `system`'s rows; `None` where they are not positive definite or the order
    /// cannot be had (neither happens for rows built by [`System::structure`] over vertices
    /// connected to a known one).
    fn of_system(system: &System) -> Option<Laplace> {
        let nu = system.deg.len();
        if nu == 0 || nu >= i32::MAX as usize || system.deg.iter().any(|&d| d <= 0.0) {
            return None;
        }
        // AMD's pattern with the diagonal, each row sorted: AMD ignores the diagonal, but the
        // crate's own check assumes at least one entry per row (it subtracts the row count
        // from the entry count: an overflow where unknown vertices have no unknown neighbour,
        // as on small meshes).
        let mut a_p: Vec<i64> = Vec::with_capacity(nu + 1);
        let mut a_i: Vec<i64> = Vec::with_capacity(system.cols.len() + nu);
        a_p.push(0);
        for i in 0..nu {
            let row = a_i.len();
            a_i.push(i as i64);
            a_i.extend(
                system.cols[system.start[i]..system.start[i + 1]]
                    .iter()
                    .map(|&c| i64::from(c)),
            );
            a_i[row..].sort_unstable();
            a_p.push(a_i.len() as i64);
        }
        let (perm, inv, _) =
            amd::order::<i64>(nu as i64, &a_p, &a_i, &amd::Control::default()).ok()?;
        let perm: Vec<usize> = perm.iter().map(|&p| p as usize).collect();
        let inv: Vec<usize> = inv.iter().map(|&p| p as usize).collect();
        // A permutation, or no factor (conjugate gradients then).
        if perm.len() != nu
            || inv.len() != nu
            || perm
                .iter()
                .enumerate()
                .any(|(k, &p)| inv.get(p) != Some(&k))
        {
            return None;
        }
        let mut coo = nalgebra_sparse::CooMatrix::new(nu, nu);
        for i in 0..nu {
            coo.push(inv[i], inv[i], system.deg[i]);
            for &j in &system.cols[system.start[i]..system.start[i + 1]] {
                coo.push(inv[i], inv[j as usize], -1.0);
            }
        }
        let csc = nalgebra_sparse::CscMatrix::from(&coo);
        let chol = nalgebra_sparse::factorization::CscCholesky::factor(&csc).ok()?;
        Some(Laplace { perm, chol })
    }

    /// x with L_UU·x = b for `len` right-hand sides (row-major, one row per solved vertex).
    fn solve(&self, b: &[f64], len: usize) -> Vec<f64> {
        let nu = self.perm.len();
        let mut m = nalgebra::DMatrix::from_fn(nu, len, |k, c| b[self.perm[k] * len + c]);
        self.chol.solve_mut(&mut m);
        let mut x = vec![0.0; nu * len];
        for (k, &row) in self.perm.iter().enumerate() {
            for c in 0..len {
                x[row * len + c] = m[(k, c)];
            }
        }
        x
    }
}

/// [`harmonic_with`]'s solve of the vertices `order` by the factor in `cache` (made or remade
/// for this known set): `false`, `out` untouched, where the rows cannot be factored or the
/// vectors differ in length (the iterative paths' cases).
fn direct<'a>(
    values: &[Option<Vec<f64>>],
    out: &mut [Option<Vec<f64>>],
    order: &[usize],
    neighbours: &impl Fn(usize) -> &'a [u32],
    cache: &FactorCache,
) -> bool {
    let key: FactorKey = (values.iter().map(Option::is_some).collect(), order.to_vec());
    let lock = || {
        cache
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    };
    let held = lock()
        .as_ref()
        .filter(|(k, _)| *k == key)
        .map(|(_, f)| std::sync::Arc::clone(f));
    let (system, b, len) = match System::assemble(out, order, neighbours) {
        Assembly::Nothing => return true,
        Assembly::Unsupported => return false,
        Assembly::System { system, b, len } => (system, b, len),
    };
    let factor = match held {
        Some(f) => f,
        None => {
            let Some(f) = Laplace::of_system(&system).map(std::sync::Arc::new) else {
                return false;
            };
            *lock() = Some((key, std::sync::Arc::clone(&f)));
            f
        }
    };
    let x = factor.solve(&b, len);
    if x.iter().any(|v| !v.is_finite()) {
        return false;
    }
    for (i, &v) in order.iter().enumerate() {
        out[v] = Some(x[i * len..(i + 1) * len].to_vec());
    }
    true
}

/// Gauss–Seidel sweeps over `order` until no value moves by 1e-12 or `sweeps` ran.
fn gauss_seidel<'a>(
    out: &mut [Option<Vec<f64>>],
    order: &[usize],
    neighbours: &impl Fn(usize) -> &'a [u32],
    align: &impl Fn(usize, usize, &[f64]) -> Option<Vec<f64>>,
    sweeps: usize,
) {
    let mut m = Vec::new();
    for _ in 0..sweeps {
        let mut change: f64 = 0.0;
        for &v in order {
            if mean_into(out, v, neighbours(v), align, &mut m) {
                match &mut out[v] {
                    Some(old) if old.len() == m.len() => {
                        for (a, b) in old.iter_mut().zip(&m) {
                            change = change.max((*a - b).abs());
                            *a = *b;
                        }
                    }
                    slot => {
                        if let Some(old) = slot.as_ref() {
                            for (a, b) in old.iter().zip(&m) {
                                change = change.max((a - b).abs());
                            }
                        }
                        *slot = Some(m.clone());
                    }
                }
            }
        }
        if change < 1e-12 {
            break;
        }
    }
}

/// Solves the Laplace equation on the unknown vertices `order` (the rest of `out` held fixed)
/// by Jacobi-preconditioned conjugate gradients, one independent solve per vector component
/// sharing the sparse products, started from `out`. `false` (and `out` untouched) where the
/// vectors differ in length, which only the sweeps handle (they skip such neighbours).
fn conjugate_gradients<'a>(
    out: &mut [Option<Vec<f64>>],
    order: &[usize],
    neighbours: &impl Fn(usize) -> &'a [u32],
    iterations: usize,
    rtol: f64,
) -> bool {
    let (system, b, len) = match System::assemble(out, order, neighbours) {
        Assembly::Nothing => return true,
        Assembly::Unsupported => return false,
        Assembly::System { system, b, len } => (system, b, len),
    };
    // Each component is its own solve, one column per component; columns go LANES at a time
    // ([`Block`]), each lane doing the very arithmetic of its column alone, in the same order
    // (so the same bits as a column's own solve, on any number of threads: the test keeps
    // that solve), and every column runs until all have converged, as one solve of the whole
    // would. Why blocks: the fold fits of the cross-validation fill holes a turntable angle
    // wide, thousands of vertices times tens of columns for hundreds of iterations, once per
    // fold and round (a tenth of a default fit's cross-validation at 1024 px); a block reads
    // each row's neighbours once for its columns and its lanes vectorise. Four lanes: a hole of
    // 8,715 vertices and 40 columns took 385 ms by column, 255 ms in blocks of 8 (their five
    // vectors outgrow the cache) and 210 ms in blocks of 4 (release, 2 threads).
    let nu = order.len();
    let blocks = cg_blocks(
        &system,
        &b,
        len,
        |i, c| out[order[i]].as_ref().map_or(0.0, |g| g[c]),
        iterations,
        rtol,
    );
    drop(b);
    if blocks
        .iter()
        .any(|k| (0..nu).any(|i| k.x[i][..k.width].iter().any(|v| !v.is_finite())))
    {
        return false;
    }
    for (i, &v) in order.iter().enumerate() {
        out[v] = Some(
            blocks
                .iter()
                .flat_map(|k| k.x[i][..k.width].iter().copied())
                .collect(),
        );
    }
    true
}

/// Jacobi-preconditioned conjugate gradients on `system` for the right-hand sides `b` (`len`
/// columns, row-major), started from `x0(row, column)`: the blocks of [`LANES`] columns, each
/// lane its column's own solve.
fn cg_blocks(
    system: &System,
    b: &[f64],
    len: usize,
    x0: impl Fn(usize, usize) -> f64 + Sync,
    iterations: usize,
    rtol: f64,
) -> Vec<Block> {
    let nu = system.deg.len();
    let inv_deg: Vec<f64> = system.deg.iter().map(|d| 1.0 / d).collect();
    let mut blocks: Vec<Block> = (0..len.div_ceil(LANES))
        .into_par_iter()
        .map(|g| {
            let c0 = g * LANES;
            let width = LANES.min(len - c0);
            let lane = |f: &dyn Fn(usize) -> f64| -> Lane {
                std::array::from_fn(|l| if l < width { f(c0 + l) } else { 0.0 })
            };
            let bc: Vec<Lane> = (0..nu).map(|i| lane(&|c| b[i * len + c])).collect();
            let x: Vec<Lane> = (0..nu).map(|i| lane(&|c| x0(i, c))).collect();
            let mut r = vec![[0.0; LANES]; nu];
            // y = A x; its dot with x is not needed here.
            system.apply_dot(&x, &mut r);
            for (ri, bi) in r.iter_mut().zip(&bc) {
                for l in 0..LANES {
                    ri[l] = bi[l] - ri[l];
                }
            }
            let z: Vec<Lane> = r
                .iter()
                .zip(&inv_deg)
                .map(|(ri, k)| ri.map(|v| v * k))
                .collect();
            Block {
                width,
                b_norm: lane_dot(&bc, &bc).map(f64::sqrt),
                rz: lane_dot(&r, &z),
                rr: lane_dot(&r, &r),
                p: z,
                q: vec![[0.0; LANES]; nu],
                x,
                r,
            }
        })
        .collect();
    for _ in 0..iterations {
        let done = blocks.iter().all(|k| {
            (0..k.width).all(|l| k.rr[l].sqrt() <= rtol * k.b_norm[l].max(f64::MIN_POSITIVE))
        });
        if done {
            break;
        }
        blocks.par_iter_mut().for_each(|k| {
            let pq = system.apply_dot(&k.p, &mut k.q);
            let step: Lane =
                std::array::from_fn(|l| if pq[l] > 0.0 { k.rz[l] / pq[l] } else { 0.0 });
            let mut rz_new = [0.0; LANES];
            let mut rr = [0.0; LANES];
            // z = r / deg is not kept: p's update below takes the same product again.
            for (((x, r), (p, q)), &kd) in
                k.x.iter_mut()
                    .zip(k.r.iter_mut())
                    .zip(k.p.iter().zip(&k.q))
                    .zip(&inv_deg)
            {
                for l in 0..LANES {
                    x[l] += step[l] * p[l];
                    r[l] -= step[l] * q[l];
                    let z = r[l] * kd;
                    rz_new[l] += r[l] * z;
                    rr[l] += r[l] * r[l];
                }
            }
            let beta: Lane = std::array::from_fn(|l| {
                if k.rz[l] > 0.0 {
                    rz_new[l] / k.rz[l]
                } else {
                    0.0
                }
            });
            for ((p, r), &kd) in k.p.iter_mut().zip(&k.r).zip(&inv_deg) {
                for l in 0..LANES {
                    p[l] = r[l] * kd + beta[l] * p[l];
                }
            }
            k.rr = rr;
            k.rz = rz_new;
        });
    }
    blocks
}

/// Columns [`conjugate_gradients`] solves at once, one per lane.
const LANES: usize = 4;

/// One value of each of a block's columns.
type Lane = [f64; LANES];

/// The rows of the Laplacian system of [`conjugate_gradients`]: row i is
/// deg(i)·x_i − Σ x_j over its unknown neighbours j.
struct System {
    /// The unknown neighbours of each row (indices into the unknowns), row after row.
    cols: Vec<u32>,
    /// Where each row's neighbours start in `cols` (one more entry: the end).
    start: Vec<usize>,
    /// deg(i): the neighbours with a value (unknown or known), as the mean counts them.
    deg: Vec<f64>,
    /// Each vertex's row (`usize::MAX`: not an unknown).
    pos: Vec<usize>,
}

/// What [`System::assemble`] found.
enum Assembly {
    /// Nothing to solve: no vector known, or no vertex unknown.
    Nothing,
    /// Vectors of different lengths, or an unknown vertex without a neighbour: the sweeps' case.
    Unsupported,
    /// The rows, the right-hand sides (`len` per row, row-major) and the vectors' length.
    System {
        system: System,
        b: Vec<f64>,
        len: usize,
    },
}

/// The convergence test of [`conjugate_gradients`]: residual norm below this share of the
/// right-hand side's.
pub const RTOL: f64 = 1e-13;

impl System {
    /// The rows deg(v)·x_v − Σ_{w unknown} x_w = Σ_{w known} x_w of the unknown vertices
    /// `order`, the known ones' values taken from `out`.
    fn assemble<'a>(
        out: &[Option<Vec<f64>>],
        order: &[usize],
        neighbours: &impl Fn(usize) -> &'a [u32],
    ) -> Assembly {
        let n = out.len();
        let Some(len) = out.iter().flatten().map(Vec::len).next() else {
            return Assembly::Nothing;
        };
        if order.is_empty() {
            return Assembly::Nothing;
        }
        if out.iter().flatten().any(|x| x.len() != len) {
            return Assembly::Unsupported;
        }
        let system = System::structure(n, order, |w| out[w].is_some(), neighbours);
        let nu = order.len();
        let mut b = vec![0.0; nu * len];
        for (i, &v) in order.iter().enumerate() {
            for &w in neighbours(v) {
                let w = w as usize;
                if w < n
                    && system.pos[w] == usize::MAX
                    && let Some(x) = &out[w]
                {
                    for (bc, xc) in b[i * len..(i + 1) * len].iter_mut().zip(x) {
                        *bc += xc;
                    }
                }
            }
        }
        if system.deg.iter().any(|&d| d <= 0.0) {
            return Assembly::Unsupported;
        }
        Assembly::System { system, b, len }
    }

    /// The rows of the unknown vertices `order` of a graph of `n` vertices, `known(w)` telling
    /// which of the others hold a value (counted in deg, as the mean counts them).
    fn structure<'a>(
        n: usize,
        order: &[usize],
        known: impl Fn(usize) -> bool,
        neighbours: &impl Fn(usize) -> &'a [u32],
    ) -> System {
        let mut pos = vec![usize::MAX; n];
        for (i, &v) in order.iter().enumerate() {
            pos[v] = i;
        }
        let nu = order.len();
        let mut cols: Vec<u32> = Vec::new();
        let mut start = Vec::with_capacity(nu + 1);
        let mut deg = vec![0.0; nu];
        for (i, &v) in order.iter().enumerate() {
            start.push(cols.len());
            for &w in neighbours(v) {
                let w = w as usize;
                if w >= n {
                    continue;
                }
                if pos[w] != usize::MAX {
                    cols.push(pos[w] as u32);
                    deg[i] += 1.0;
                } else if known(w) {
                    deg[i] += 1.0;
                }
            }
        }
        start.push(cols.len());
        System {
            cols,
            start,
            deg,
            pos,
        }
    }

    /// y = A x and Σ_i x_i·y_i (in the order of i, as [`lane_dot`]), lane by lane: one pass.
    fn apply_dot(&self, x: &[Lane], y: &mut [Lane]) -> Lane {
        let mut s = [0.0; LANES];
        for (i, (yi, xi)) in y.iter_mut().zip(x).enumerate() {
            let d = self.deg[i];
            for l in 0..LANES {
                yi[l] = d * xi[l];
            }
            for &j in &self.cols[self.start[i]..self.start[i + 1]] {
                let xj = &x[j as usize];
                for l in 0..LANES {
                    yi[l] -= xj[l];
                }
            }
            for l in 0..LANES {
                s[l] += xi[l] * yi[l];
            }
        }
        s
    }
}

/// Σ_i a_i·b_i per lane, in the order of i.
fn lane_dot(a: &[Lane], b: &[Lane]) -> Lane {
    let mut s = [0.0; LANES];
    for (ai, bi) in a.iter().zip(b) {
        for l in 0..LANES {
            s[l] += ai[l] * bi[l];
        }
    }
    s
}

/// A block of [`LANES`] columns' conjugate-gradient state ([`conjugate_gradients`]); lanes
/// from `width` on are padding (all zero: they stay so).
struct Block {
    width: usize,
    x: Vec<Lane>,
    r: Vec<Lane>,
    p: Vec<Lane>,
    q: Vec<Lane>,
    rz: Lane,
    rr: Lane,
    b_norm: Lane,
}

/// The mean of `v`'s neighbours' vectors (each re-expressed by `align`) into `acc`; `false`
/// where no neighbour has one. Neighbours whose vector differs in length from the first are
/// skipped.
fn mean_into(
    vals: &[Option<Vec<f64>>],
    v: usize,
    nb: &[u32],
    align: &impl Fn(usize, usize, &[f64]) -> Option<Vec<f64>>,
    acc: &mut Vec<f64>,
) -> bool {
    acc.clear();
    let mut count = 0.0;
    for &w in nb {
        if let Some(Some(x)) = vals.get(w as usize) {
            let aligned = align(v, w as usize, x);
            let x = aligned.as_deref().unwrap_or(x);
            if count == 0.0 {
                acc.extend_from_slice(x);
            } else if acc.len() == x.len() {
                for (s, y) in acc.iter_mut().zip(x) {
                    *s += y;
                }
            } else {
                continue;
            }
            count += 1.0;
        }
    }
    for a in acc.iter_mut() {
        *a /= count;
    }
    count > 0.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The solve as it was, one column at a time: the reference the blocks are held to.
    fn conjugate_gradients_by_column<'a>(
        out: &mut [Option<Vec<f64>>],
        order: &[usize],
        neighbours: &impl Fn(usize) -> &'a [u32],
        iterations: usize,
    ) -> bool {
        let (
            System {
                cols, start, deg, ..
            },
            b,
            len,
        ) = match System::assemble(out, order, neighbours) {
            Assembly::Nothing => return true,
            Assembly::Unsupported => return false,
            Assembly::System { system, b, len } => (system, b, len),
        };
        let nu = order.len();
        // Each component is its own solve: one column per component, the columns in parallel. Each
        // column's arithmetic is the same, in the same order, on any number of threads (the same
        // bits), and every column runs until all have converged, as one solve of the whole would.
        let inv_deg: Vec<f64> = deg.iter().map(|d| 1.0 / d).collect();
        let apply = |x: &[f64], y: &mut [f64]| {
            for (i, yi) in y.iter_mut().enumerate() {
                *yi = deg[i] * x[i];
                for &j in &cols[start[i]..start[i + 1]] {
                    *yi -= x[j as usize];
                }
            }
        };
        let dot = |a: &[f64], b: &[f64]| -> f64 {
            let mut s = 0.0;
            for (ai, bi) in a.iter().zip(b) {
                s += ai * bi;
            }
            s
        };
        let mut columns: Vec<Column> = (0..len)
            .into_par_iter()
            .map(|c| {
                let bc: Vec<f64> = (0..nu).map(|i| b[i * len + c]).collect();
                let x: Vec<f64> = order
                    .iter()
                    .map(|&v| out[v].as_ref().map_or(0.0, |g| g[c]))
                    .collect();
                let mut r = vec![0.0; nu];
                apply(&x, &mut r);
                for (ri, bi) in r.iter_mut().zip(&bc) {
                    *ri = bi - *ri;
                }
                let z: Vec<f64> = r.iter().zip(&inv_deg).map(|(ri, k)| ri * k).collect();
                Column {
                    b_norm: dot(&bc, &bc).sqrt(),
                    rz: dot(&r, &z),
                    rr: dot(&r, &r),
                    p: z.clone(),
                    q: vec![0.0; nu],
                    x,
                    r,
                    z,
                }
            })
            .collect();
        drop(b);
        for _ in 0..iterations {
            let done = columns
                .iter()
                .all(|k| k.rr.sqrt() <= RTOL * k.b_norm.max(f64::MIN_POSITIVE));
            if done {
                break;
            }
            columns.par_iter_mut().for_each(|k| {
                apply(&k.p, &mut k.q);
                let pq = dot(&k.p, &k.q);
                let step = if pq > 0.0 { k.rz / pq } else { 0.0 };
                let mut rz_new = 0.0;
                k.rr = 0.0;
                for (i, &kd) in inv_deg.iter().enumerate() {
                    k.x[i] += step * k.p[i];
                    k.r[i] -= step * k.q[i];
                    k.z[i] = k.r[i] * kd;
                    rz_new += k.r[i] * k.z[i];
                    k.rr += k.r[i] * k.r[i];
                }
                let beta = if k.rz > 0.0 { rz_new / k.rz } else { 0.0 };
                for (pi, zi) in k.p.iter_mut().zip(&k.z) {
                    *pi = zi + beta * *pi;
                }
                k.rz = rz_new;
            });
        }
        if columns.iter().any(|k| k.x.iter().any(|v| !v.is_finite())) {
            return false;
        }
        for (i, &v) in order.iter().enumerate() {
            out[v] = Some(columns.iter().map(|k| k.x[i]).collect());
        }
        true
    }

    /// One component's conjugate-gradient state ([`conjugate_gradients`]).
    struct Column {
        x: Vec<f64>,
        r: Vec<f64>,
        z: Vec<f64>,
        p: Vec<f64>,
        q: Vec<f64>,
        rz: f64,
        rr: f64,
        b_norm: f64,
    }

    proptest! {
        /// The blocked solve is each column's own solve to the bit: random graphs (paths,
        /// loops, islands, vertices without known neighbours), unknowns and column counts
        /// around the block width, and too few iterations to converge.
        #[test]
        fn blocks_solve_each_column_to_the_bit(
            n in 2usize..60,
            edges in proptest::collection::vec((0u32..60, 0u32..60), 0..150),
            known in proptest::collection::vec(proptest::option::weighted(0.4, -1e3f64..1e3), 60),
            len in 1usize..20,
            iterations in proptest::sample::select(vec![0usize, 1, 3, 40, 2000]),
        ) {
            let mut adj: Vec<Vec<u32>> = vec![Vec::new(); n];
            for (a, b) in edges {
                let (a, b) = (a as usize % n, b as usize % n);
                if a != b && !adj[a].contains(&(b as u32)) {
                    adj[a].push(b as u32);
                    adj[b].push(a as u32);
                }
            }
            let vals: Vec<Option<Vec<f64>>> = (0..n)
                .map(|v| known[v].map(|x| (0..len).map(|c| x * (c as f64 + 1.0).sqrt() - c as f64).collect()))
                .collect();
            let no_turn = |_: usize, _: usize, _: &[f64]| None;
            let nb = |v: usize| &adj[v][..];
            let (start, order) = breadth_first(&vals, &nb, &no_turn);
            let (mut a, mut b) = (start.clone(), start);
            let ok_a = conjugate_gradients(&mut a, &order, &nb, iterations, RTOL);
            let ok_b = conjugate_gradients_by_column(&mut b, &order, &nb, iterations);
            prop_assert_eq!(ok_a, ok_b);
            let bits = |o: &[Option<Vec<f64>>]| -> Vec<Option<Vec<u64>>> {
                o.iter().map(|x| x.as_ref().map(|x| x.iter().map(|v| v.to_bits()).collect())).collect()
            };
            prop_assert_eq!(bits(&a), bits(&b));
        }
    }

    /// x² − y² is harmonic on the 4-neighbour grid (its discrete Laplacian is 2 − 2), so with the
    /// boundary known the interior must come out as x² − y² itself; a 40 × 40 hole is where the
    /// sweeps' d² convergence shows (they stop 1e-12 per sweep short, far from the solution).
    /// The 4-neighbour graph of a k × k grid, vertex i·k + j.
    fn grid_adjacency(k: usize) -> Vec<Vec<u32>> {
        let id = |i: usize, j: usize| (i * k + j) as u32;
        (0..k * k)
            .map(|v| {
                let (i, j) = (v / k, v % k);
                let mut nb = Vec::new();
                if i > 0 {
                    nb.push(id(i - 1, j));
                }
                if i + 1 < k {
                    nb.push(id(i + 1, j));
                }
                if j > 0 {
                    nb.push(id(i, j - 1));
                }
                if j + 1 < k {
                    nb.push(id(i, j + 1));
                }
                nb
            })
            .collect()
    }

    #[test]
    fn a_grid_hole_is_filled_with_the_discrete_harmonic_function() {
        let k = 42usize;
        let adj = grid_adjacency(k);
        let f = |v: usize| {
            let (x, y) = ((v / k) as f64, (v % k) as f64);
            vec![x * x - y * y, 1.0 + 0.5 * x - 2.0 * y]
        };
        let border = |v: usize| {
            let (i, j) = (v / k, v % k);
            i == 0 || j == 0 || i + 1 == k || j + 1 == k
        };
        let vals: Vec<Option<Vec<f64>>> = (0..k * k).map(|v| border(v).then(|| f(v))).collect();
        let out = harmonic(&vals, |v| &adj[v], 2000);
        for (v, got) in out.iter().enumerate() {
            let got = got.as_ref().unwrap();
            for (g, w) in got.iter().zip(f(v)) {
                assert!(
                    (g - w).abs() < 1e-8 * (1.0 + w.abs()),
                    "vertex {v}: {g} vs {w}"
                );
            }
        }
        // Gauss–Seidel stopped after 200 sweeps is still far off in the middle.
        let gs = harmonic_aligned(&vals, |v| &adj[v], |_, _, _| None, 200);
        let mid = (k / 2) * k + k / 2;
        let err = (gs[mid].as_ref().unwrap()[0] - f(mid)[0]).abs();
        assert!(err > 1e-3, "Gauss–Seidel already converged ({err})");
    }

    /// Two holes in a grid: the weights of the known vertices at a few targets reproduce the
    /// full solve there for any known values, a solve restricted to the targets' hole gives
    /// them too, and a warm start from the solution changes nothing beyond the tolerance.
    #[test]
    fn weights_and_restricted_solves_agree_with_the_full_solve() {
        let k = 30usize;
        let id = |i: usize, j: usize| (i * k + j) as u32;
        let adj = grid_adjacency(k);
        // Known: the border and the middle column; two holes either side of it.
        let known: Vec<bool> = (0..k * k)
            .map(|v| {
                let (i, j) = (v / k, v % k);
                i == 0 || j == 0 || i + 1 == k || j + 1 == k || j == k / 2
            })
            .collect();
        let vals: Vec<Option<Vec<f64>>> = (0..k * k)
            .map(|v| {
                let (x, y) = ((v / k) as f64, (v % k) as f64);
                known[v].then(|| vec![(0.3 * x).sin() + y, 2.0 - 0.1 * x * y])
            })
            .collect();
        let full = harmonic(&vals, |v| &adj[v], 2000);
        let targets = [id(5, 5) as usize, id(20, 7) as usize, id(3, 3) as usize];
        let weights = harmonic_weights(&known, |v| &adj[v], &targets, &Solve::default());
        for (&t, w) in targets.iter().zip(&weights) {
            let w = w.as_ref().expect("a target in a hole has weights");
            assert!(w.iter().all(|&(u, _)| known[u as usize]));
            let sum: f64 = w.iter().map(|x| x.1).sum();
            assert!((sum - 1.0).abs() < 1e-9, "weights sum to {sum}");
            let want = full[t].as_ref().unwrap();
            for (c, want) in want.iter().enumerate() {
                let got: f64 = w
                    .iter()
                    .map(|&(u, x)| x * vals[u as usize].as_ref().unwrap()[c])
                    .sum();
                assert!((got - want).abs() < 1e-9, "{t}/{c}: {got} vs {want}");
            }
        }
        // A known vertex has no weights of its own.
        let known_target =
            harmonic_weights(&known, |v| &adj[v], &[id(0, 3) as usize], &Solve::default());
        assert!(known_target[0].is_none());
        // Restricted to the left hole: the same values there, the right hole not solved.
        let mut only = vec![false; k * k];
        only[id(5, 5) as usize] = true;
        let part = harmonic_with(
            &vals,
            |v| &adj[v],
            &Solve {
                only: Some(&only),
                ..Solve::default()
            },
        );
        let (l, r) = (id(10, 4) as usize, id(10, 20) as usize);
        for c in 0..2 {
            let (a, b) = (part[l].as_ref().unwrap()[c], full[l].as_ref().unwrap()[c]);
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        assert!(
            (part[r].as_ref().unwrap()[0] - full[r].as_ref().unwrap()[0]).abs() > 1e-6,
            "the right hole kept its breadth-first guess"
        );
        // Warm from the solution with a loose tolerance: within it of the full solve.
        let warm = harmonic_with(
            &vals,
            |v| &adj[v],
            &Solve {
                warm: Some(&full),
                rtol: 1e-9,
                ..Solve::default()
            },
        );
        for (a, b) in warm.iter().zip(&full) {
            if let (Some(a), Some(b)) = (a, b) {
                for (x, y) in a.iter().zip(b) {
                    assert!((x - y).abs() < 1e-7, "{x} vs {y}");
                }
            }
        }
    }

    /// The factored solve gives conjugate gradients' solution (to the exact tolerance) on two
    /// holes of a grid, keeps its factor for new values of the same known set, makes a new one
    /// when the known set changes, and leaves vectors of different lengths to the sweeps.
    #[test]
    fn the_factored_solve_is_the_conjugate_gradients_one_and_is_kept_per_known_set() {
        let k = 30usize;
        let adj = grid_adjacency(k);
        let known: Vec<bool> = (0..k * k)
            .map(|v| {
                let (i, j) = (v / k, v % k);
                i == 0 || j == 0 || i + 1 == k || j + 1 == k || j == k / 2 || (i == 7 && j > 20)
            })
            .collect();
        let vals = |a: f64| -> Vec<Option<Vec<f64>>> {
            (0..k * k)
                .map(|v| {
                    let (x, y) = ((v / k) as f64, (v % k) as f64);
                    known[v].then(|| vec![(a * x).sin() + y, 2.0 - 0.1 * x * y, a])
                })
                .collect()
        };
        let cache = FactorCache::default();
        let direct = Solve {
            direct: Some(&cache),
            ..Solve::default()
        };
        let close = |a: &[Option<Vec<f64>>], b: &[Option<Vec<f64>>]| {
            for (v, (x, y)) in a.iter().zip(b).enumerate() {
                match (x, y) {
                    (Some(x), Some(y)) => {
                        for (p, q) in x.iter().zip(y) {
                            assert!((p - q).abs() < 1e-10, "vertex {v}: {p} vs {q}");
                        }
                    }
                    (None, None) => {}
                    _ => panic!("vertex {v}: filled in one solve only"),
                }
            }
        };
        let first = vals(0.3);
        close(
            &harmonic_with(&first, |v| &adj[v], &direct),
            &harmonic(&first, |v| &adj[v], 2000),
        );
        let held = cache
            .0
            .lock()
            .unwrap()
            .clone()
            .expect("the factor is kept")
            .1;
        // New values, the same known set: the same factor, the new solution.
        let second = vals(0.7);
        close(
            &harmonic_with(&second, |v| &adj[v], &direct),
            &harmonic(&second, |v| &adj[v], 2000),
        );
        let again = cache.0.lock().unwrap().clone().unwrap().1;
        assert!(
            std::sync::Arc::ptr_eq(&held, &again),
            "the factor was remade"
        );
        // One vertex more known: a new factor, still the right solution.
        let mut third = vals(0.7);
        third[10 * k + 5] = Some(vec![5.0, 5.0, 5.0]);
        close(
            &harmonic_with(&third, |v| &adj[v], &direct),
            &harmonic(&third, |v| &adj[v], 2000),
        );
        let remade = cache.0.lock().unwrap().clone().unwrap().1;
        assert!(
            !std::sync::Arc::ptr_eq(&held, &remade),
            "a stale factor was used"
        );
        // Every other vertex known (a checkerboard): no unknown vertex has an unknown
        // neighbour, so the rows are the diagonal alone.
        let board: Vec<Option<Vec<f64>>> = (0..k * k)
            .map(|v| {
                (v / k + v % k)
                    .is_multiple_of(2)
                    .then(|| vec![v as f64, 1.0])
            })
            .collect();
        close(
            &harmonic_with(&board, |v| &adj[v], &direct),
            &harmonic(&board, |v| &adj[v], 2000),
        );
        // Vectors of different lengths: the sweeps' result, as without the factor.
        let mut mixed = vals(0.3);
        mixed[0] = Some(vec![1.0]);
        close(
            &harmonic_with(&mixed, |v| &adj[v], &direct),
            &harmonic(&mixed, |v| &adj[v], 2000),
        );
    }

    #[test]
    fn a_path_is_filled_linearly_and_islands_stay_empty() {
        // 0 - 1 - 2 - 3 - 4, plus an isolated vertex 5.
        let adj: Vec<Vec<u32>> = vec![vec![1], vec![0, 2], vec![1, 3], vec![2, 4], vec![3], vec![]];
        let vals = vec![Some(vec![0.0]), None, None, None, Some(vec![4.0]), None];
        let out = harmonic(&vals, |v| &adj[v], 10_000);
        for k in 0..5 {
            assert!(
                (out[k].as_ref().unwrap()[0] - k as f64).abs() < 1e-9,
                "{out:?}"
            );
        }
        assert!(out[5].is_none());
    }

    #[test]
    fn aligned_neighbours_are_averaged_in_the_receiving_vertex_s_frame() {
        // 0 - 1 - 2 with vertex 2's two-entry vector stored in a frame turned by one entry: its
        // alignment swaps the entries, so the middle vertex averages like with like.
        let adj: Vec<Vec<u32>> = vec![vec![1], vec![0, 2], vec![1]];
        let vals = vec![Some(vec![1.0, 3.0]), None, Some(vec![3.0, 1.0])];
        let plain = harmonic(&vals, |v| &adj[v], 100);
        assert_eq!(plain[1], Some(vec![2.0, 2.0]));
        let aligned = harmonic_aligned(
            &vals,
            |v| &adj[v],
            |_, w, x| (w == 2).then(|| vec![x[1], x[0]]),
            100,
        );
        assert_eq!(aligned[1], Some(vec![1.0, 3.0]));
    }
}
