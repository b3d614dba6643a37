//! Diffuse transport `B(x_o) = Σ_i R_d(x_i → x_o) E(x_i) A(x_i)`: the exact sum and the
//! hierarchical evaluation of Jensen & Buhler 2002.
//!
//! Jensen & Buhler cluster irradiance samples in an octree and, for each `x_o`, use a whole
//! cluster where it subtends a small solid angle. Their material is homogeneous, so a cluster is
//! one point with the summed flux. Here every `x_i` carries its own fall-off, so a cluster instead
//! stores its summed fall-off `F(r) = Σ_{i∈cluster} Φ_i R_i(r)` (Φ_i = E(x_i) A(x_i)) tabulated in
//! log space over distance; at distance `r` from the cluster's centroid it contributes `F(r)`.
//! Anisotropic sources (Eq. 3) enter clusters with their direction-averaged fall-off; near `x_o`,
//! where direction matters most, sources are summed one by one with their segment weights.
//!
//! The tables are hand-written rather than taken from a crate because they are the product's hot
//! loop and no crate offers heterogeneous-kernel clustering.

use rayon::prelude::*;

use super::falloff::{Falloffs, segment_weights};
use crate::model::TangentFrame;

/// The error bound of the hierarchical evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HierarchyParams {
    /// ε: a cluster is used as a whole when its area over the squared distance to it (the solid
    /// angle it subtends, sr) is below this (Jensen & Buhler 2002, §3.2).
    pub max_solid_angle: f64,
    /// Fraction of each source's total diffuse reflectance that may be dropped by not looking
    /// farther than its cutoff radius (see [`tail_cutoff`](super::tail_cutoff)).
    pub tail_tolerance: f64,
}

/// `--quality`: named points on the speed/accuracy curve (measured in BENCHMARKS.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Quality {
    /// Fastest; errors of a few per cent.
    Draft,
    /// The default: sub-per-cent errors at a fraction of the exact cost.
    Balanced,
    /// Close to the exact sum.
    Best,
}

impl Quality {
    /// The error bound this quality stands for.
    pub fn params(self) -> HierarchyParams {
        match self {
            Quality::Draft => HierarchyParams {
                max_solid_angle: 0.5,
                tail_tolerance: 1e-3,
            },
            Quality::Balanced => HierarchyParams {
                max_solid_angle: 0.2,
                tail_tolerance: 1e-3,
            },
            Quality::Best => HierarchyParams {
                max_solid_angle: 0.05,
                tail_tolerance: 1e-4,
            },
        }
    }
}

/// Work done by one evaluation, for benchmarks and reports.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TransportStats {
    /// Octree nodes.
    pub nodes: usize,
    /// Sources that emit (lit and with a model).
    pub sources: usize,
    /// Receivers evaluated.
    pub receivers: usize,
    /// Clusters used as a whole, summed over receivers.
    pub cluster_evals: u64,
    /// Single source evaluations, summed over receivers.
    pub point_evals: u64,
    /// Wall time building the octree and its tables, seconds.
    pub build_seconds: f64,
}

/// One lit scene: positions, fall-offs and the flux `Φ_i = E(x_i) A(x_i)` of every vertex.
pub struct Transport<'a> {
    positions: &'a [[f64; 3]],
    falloffs: &'a Falloffs,
    irradiance: &'a [[f64; 3]],
    power: Vec<[f64; 3]>,
    /// Radius of the disk with the vertex's area, for the self term.
    rho: Vec<f64>,
    /// Vertices that emit: a model and non-zero flux.
    sources: Vec<u32>,
    is_source: Vec<bool>,
    /// Tangent frames of the sources (anisotropic models only; Eq. 3).
    frames: Vec<TangentFrame>,
}

impl<'a> Transport<'a> {
    /// Prepares the transport. All slices have one entry per vertex.
    pub fn new(
        positions: &'a [[f64; 3]],
        normals: &'a [[f64; 3]],
        falloffs: &'a Falloffs,
        irradiance: &'a [[f64; 3]],
        areas: &[f64],
    ) -> Self {
        let n = positions.len();
        let mut power = Vec::with_capacity(n);
        let mut sources = Vec::new();
        let mut is_source = vec![false; n];
        for i in 0..n {
            let p = irradiance[i].map(|e| e * areas[i]);
            let lit = p.iter().any(|&x| x > 0.0) && p.iter().all(|x| x.is_finite());
            if lit && falloffs.is_active(i) {
                sources.push(i as u32);
                is_source[i] = true;
            }
            power.push(p);
        }
        let rho = areas
            .iter()
            .map(|a| (a / std::f64::consts::PI).sqrt())
            .collect();
        let frames = if falloffs.segments() > 1 {
            // The model at source x_i = vertex i is evaluated in the frame of x_i's own normal,
            // by the model's rule: the frame its segments were fitted in.
            normals.iter().map(|&n| falloffs.frame_at(n)).collect()
        } else {
            Vec::new()
        };
        Self {
            frames,
            positions,
            falloffs,
            irradiance,
            power,
            rho,
            sources,
            is_source,
        }
    }

    /// Number of emitting sources.
    pub fn source_count(&self) -> usize {
        self.sources.len()
    }

    /// The `x_o = x_i` term: the vertex's own light kept within the disk of its area.
    #[inline]
    fn self_term(&self, o: usize) -> [f64; 3] {
        let k = self.falloffs.disk_integral(o, self.rho[o]);
        let e = self.irradiance[o];
        [k[0] * e[0], k[1] * e[1], k[2] * e[2]]
    }

    #[inline]
    fn point_term(&self, i: usize, x_o: [f64; 3], r: f64, w: &mut [f64]) -> [f64; 3] {
        if w.len() > 1 {
            segment_weights(&self.frames[i], self.positions[i], x_o, w);
        }
        let rd = self.falloffs.eval(i, r, w);
        let p = self.power[i];
        [rd[0] * p[0], rd[1] * p[1], rd[2] * p[2]]
    }

    /// The reference: `B(x_o)` for each receiver vertex by the full sum over all sources, O(N²).
    pub fn exact(&self, receivers: &[usize]) -> Vec<[f64; 3]> {
        let m = self.falloffs.segments();
        receivers
            .par_iter()
            .map_init(
                || vec![1.0; m],
                |w, &o| {
                    let x = self.positions[o];
                    let mut b = if self.is_source[o] {
                        self.self_term(o)
                    } else {
                        [0.0; 3]
                    };
                    for &i in &self.sources {
                        let i = i as usize;
                        if i == o {
                            continue;
                        }
                        let r = dist(x, self.positions[i]);
                        let t = self.point_term(i, x, r, w);
                        b[0] += t[0];
                        b[1] += t[1];
                        b[2] += t[2];
                    }
                    b
                },
            )
            .collect()
    }

    /// `B(x_o)` for each receiver by the hierarchical evaluation under the error bound `params`.
    pub fn hierarchical(
        &self,
        params: HierarchyParams,
        receivers: &[usize],
    ) -> (Vec<[f64; 3]>, TransportStats) {
        let t0 = std::time::Instant::now();
        let tree = Octree::build(self, params);
        let build_seconds = t0.elapsed().as_secs_f64();
        let m = self.falloffs.segments();
        let eps = params.max_solid_angle.max(0.0);
        let counts: Vec<([f64; 3], u64, u64)> = receivers
            .par_iter()
            .map_init(
                || (vec![1.0; m], Vec::with_capacity(64)),
                |(w, stack), &o| tree.eval(self, o, eps, w, stack),
            )
            .collect();
        let mut stats = TransportStats {
            nodes: tree.nodes.len(),
            sources: self.sources.len(),
            receivers: receivers.len(),
            build_seconds,
            ..Default::default()
        };
        let b = counts
            .into_iter()
            .map(|(b, c, p)| {
                stats.cluster_evals += c;
                stats.point_evals += p;
                b
            })
            .collect();
        (b, stats)
    }
}

#[inline]
fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

/// Entries of a cluster's fall-off table; spaced quadratically (dense near 0, where fast terms
/// bend `ln F`), interpolated linearly in `r`, which is exact for a single exponential.
const TABLE: usize = 32;
/// Sources per leaf.
const LEAF: usize = 8;
/// Floor for `ln F` in tables, so interpolation never meets `-inf`.
const LN_FLOOR: f32 = -1e30;

struct Node {
    lo: [f64; 3],
    hi: [f64; 3],
    centroid: [f64; 3],
    /// Flux-weighted covariance of source positions: xx, yy, zz, xy, xz, yz (mm²).
    cov: [f64; 6],
    area: f64,
    /// Largest cutoff radius of its sources.
    r_cut: f64,
    /// Range into `Octree::order`.
    start: u32,
    end: u32,
    /// Children (indices into `nodes`), `u32::MAX` for none; all none in a leaf.
    children: [u32; 8],
    leaf: bool,
}

struct Octree {
    nodes: Vec<Node>,
    /// Source vertex indices, grouped by node.
    order: Vec<u32>,
    /// Per-source cutoff radius, by vertex index.
    r_cut: Vec<f64>,
    /// `ln F(r_g)` per node: `TABLE × 3` f32.
    tables: Vec<f32>,
    /// Largest distance the tables cover.
    r_max: f64,
}

impl Octree {
    fn build(t: &Transport<'_>, params: HierarchyParams) -> Self {
        let n = t.positions.len();
        let mut r_cut = vec![0.0; n];
        let cuts: Vec<(u32, f64)> = t
            .sources
            .par_iter()
            .map(|&i| (i, t.falloffs.cutoff(i as usize, params.tail_tolerance)))
            .collect();
        for (i, r) in cuts {
            r_cut[i as usize] = r;
        }
        let mut order = t.sources.clone();
        let mut tree = Octree {
            nodes: Vec::new(),
            order: Vec::new(),
            r_cut,
            tables: Vec::new(),
            r_max: 0.0,
        };
        if order.is_empty() {
            return tree;
        }
        let (lo, hi) = bbox(t.positions, &order);
        let diag = dist(lo, hi);
        let max_cut = order
            .iter()
            .map(|&i| tree.r_cut[i as usize])
            .fold(0.0, f64::max);
        // Receivers may sit anywhere on the mesh, so the table spans the whole object unless the
        // cutoff is shorter.
        let (mlo, mhi) = bbox_all(t.positions);
        tree.r_max = max_cut.min(dist(mlo, mhi).max(diag)).max(1e-9);
        tree.build_node(t, &mut order, 0, 0);
        tree.order = order;
        tree.fill_tables(t);
        tree
    }

    fn build_node(
        &mut self,
        t: &Transport<'_>,
        order: &mut [u32],
        offset: usize,
        depth: u32,
    ) -> u32 {
        let (lo, hi) = bbox(t.positions, order);
        let mut area = 0.0;
        let mut wsum = 0.0;
        let mut c = [0.0; 3];
        let mut rc: f64 = 0.0;
        for &i in order.iter() {
            let i = i as usize;
            area += t.rho[i] * t.rho[i] * std::f64::consts::PI;
            // Flux-weighted (luminance of Φ) centroid, as Jensen & Buhler: a half-lit cluster's
            // light comes from its lit half.
            let w = flux_weight(t.power[i]);
            wsum += w;
            for (ck, pk) in c.iter_mut().zip(t.positions[i]) {
                *ck += w * pk;
            }
            rc = rc.max(self.r_cut[i]);
        }
        let centroid = c.map(|x| x / wsum);
        // Flux-weighted covariance of positions about the centroid, for the spread correction.
        let mut cov = [0.0; 6];
        for &i in order.iter() {
            let i = i as usize;
            let w = flux_weight(t.power[i]) / wsum;
            let d = [0, 1, 2].map(|k| t.positions[i][k] - centroid[k]);
            let prod = [
                d[0] * d[0],
                d[1] * d[1],
                d[2] * d[2],
                d[0] * d[1],
                d[0] * d[2],
                d[1] * d[2],
            ];
            for (a, p) in cov.iter_mut().zip(prod) {
                *a += w * p;
            }
        }
        let me = self.nodes.len() as u32;
        self.nodes.push(Node {
            lo,
            hi,
            centroid,
            cov,
            area,
            r_cut: rc,
            start: offset as u32,
            end: (offset + order.len()) as u32,
            children: [u32::MAX; 8],
            leaf: true,
        });
        if order.len() <= LEAF || depth >= 32 || dist(lo, hi) == 0.0 {
            return me;
        }
        let mid = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let octant = |i: u32| -> usize {
            let p = t.positions[i as usize];
            (p[0] > mid[0]) as usize
                | ((p[1] > mid[1]) as usize) << 1
                | ((p[2] > mid[2]) as usize) << 2
        };
        order.sort_unstable_by_key(|&i| octant(i));
        let mut children = [u32::MAX; 8];
        let mut s = 0;
        while s < order.len() {
            let q = octant(order[s]);
            let mut e = s;
            while e < order.len() && octant(order[e]) == q {
                e += 1;
            }
            children[q] = self.build_node(t, &mut order[s..e], offset + s, depth + 1);
            s = e;
        }
        let node = &mut self.nodes[me as usize];
        node.children = children;
        node.leaf = false;
        me
    }

    fn r_at(&self, g: usize) -> f64 {
        let u = g as f64 / (TABLE - 1) as f64;
        self.r_max * u * u
    }

    /// Tables bottom-up: leaves from their sources, inner nodes as log-sum-exp of their children.
    fn fill_tables(&mut self, t: &Transport<'_>) {
        let nn = self.nodes.len();
        self.tables = vec![LN_FLOOR; nn * TABLE * 3];
        let rs: Vec<f64> = (0..TABLE).map(|g| self.r_at(g)).collect();
        // Leaves in parallel.
        let leaf_tables: Vec<(usize, Vec<f32>)> = (0..nn)
            .into_par_iter()
            .filter(|&k| self.nodes[k].leaf)
            .map(|k| {
                let node = &self.nodes[k];
                let members = &self.order[node.start as usize..node.end as usize];
                let mut out = vec![LN_FLOOR; TABLE * 3];
                let mut terms: Vec<[f64; 3]> = Vec::with_capacity(members.len());
                for (g, &r) in rs.iter().enumerate() {
                    terms.clear();
                    for &i in members {
                        let i = i as usize;
                        let l = t.falloffs.ln_eval_mean(i, r);
                        let p = t.power[i];
                        terms.push([l[0] + p[0].ln(), l[1] + p[1].ln(), l[2] + p[2].ln()]);
                    }
                    for ch in 0..3 {
                        out[g * 3 + ch] = lse(terms.iter().map(|v| v[ch])) as f32;
                    }
                }
                (k, out)
            })
            .collect();
        for (k, tab) in leaf_tables {
            self.tables[k * TABLE * 3..(k + 1) * TABLE * 3].copy_from_slice(&tab);
        }
        // Children always have larger indices than their parent: go backwards.
        for k in (0..nn).rev() {
            if self.nodes[k].leaf {
                continue;
            }
            let kids: Vec<usize> = self.nodes[k]
                .children
                .iter()
                .filter(|&&c| c != u32::MAX)
                .map(|&c| c as usize)
                .collect();
            for j in 0..TABLE * 3 {
                let v = lse(kids.iter().map(|&c| self.tables[c * TABLE * 3 + j] as f64));
                self.tables[k * TABLE * 3 + j] = v as f32;
            }
        }
    }

    fn slope(&self, tab: &[f32], g: usize, ch: usize) -> f64 {
        let (a, b) = (tab[g * 3 + ch] as f64, tab[(g + 1) * 3 + ch] as f64);
        (b - a) / (self.r_at(g + 1) - self.r_at(g))
    }

    /// The contribution of node `k` to a receiver at offset `v = x_o − centroid` (`rc = |v|`):
    /// `F(rc)` from the log table (linear interpolation of `ln F` in `r`), times a second-order
    /// correction for the cluster's spread — the mean of `F(|x_o − x_i|)` over the sources, with
    /// `r_i ≈ rc − u·δ + |δ_⊥|²/(2rc)`, is `F(rc)(1 + g'σ_⊥²/(2rc) + (g'' + g'²)σ_∥²/2)` with
    /// `g = ln F` and σ² the flux-weighted variances along and across the direction `u`.
    #[inline]
    fn cluster(&self, k: usize, v: [f64; 3], rc: f64) -> [f64; 3] {
        if rc > self.r_max {
            return [0.0; 3];
        }
        let u = (rc / self.r_max).sqrt() * (TABLE - 1) as f64;
        let g = (u.floor() as usize).min(TABLE - 2);
        let (r0, r1) = (self.r_at(g), self.r_at(g + 1));
        let f = ((rc - r0) / (r1 - r0)).clamp(0.0, 1.0);
        let tab = &self.tables[k * TABLE * 3..(k + 1) * TABLE * 3];
        let c = &self.nodes[k].cov;
        let un = v.map(|x| x / rc.max(1e-300));
        let par = un[0] * un[0] * c[0]
            + un[1] * un[1] * c[1]
            + un[2] * un[2] * c[2]
            + 2.0 * (un[0] * un[1] * c[3] + un[0] * un[2] * c[4] + un[1] * un[2] * c[5]);
        let perp = (c[0] + c[1] + c[2] - par).max(0.0);
        let (gp, gn) = (g.saturating_sub(1), (g + 1).min(TABLE - 2));
        let mid = |j: usize| 0.5 * (self.r_at(j) + self.r_at(j + 1));
        let mut out = [0.0; 3];
        for (ch, o) in out.iter_mut().enumerate() {
            let a = tab[g * 3 + ch] as f64;
            let b = tab[(g + 1) * 3 + ch] as f64;
            let base = (a + f * (b - a)).exp();
            if base == 0.0 {
                continue;
            }
            let g1 = self.slope(tab, g, ch);
            let g2 = if gn > gp {
                (self.slope(tab, gn, ch) - self.slope(tab, gp, ch)) / (mid(gn) - mid(gp))
            } else {
                0.0
            };
            let corr = 1.0 + g1 * perp / (2.0 * rc) + 0.5 * (g2 + g1 * g1) * par;
            *o = base * corr.clamp(0.25, 4.0);
        }
        out
    }

    fn eval(
        &self,
        t: &Transport<'_>,
        o: usize,
        eps: f64,
        w: &mut [f64],
        stack: &mut Vec<u32>,
    ) -> ([f64; 3], u64, u64) {
        let x = t.positions[o];
        let mut b = if t.is_source[o] {
            t.self_term(o)
        } else {
            [0.0; 3]
        };
        let (mut clusters, mut points) = (0u64, 0u64);
        if self.nodes.is_empty() {
            return (b, 0, 0);
        }
        stack.clear();
        stack.push(0);
        while let Some(k) = stack.pop() {
            let node = &self.nodes[k as usize];
            let dbox = box_distance(x, node.lo, node.hi);
            if dbox > node.r_cut {
                continue;
            }
            if node.leaf {
                for &i in &self.order[node.start as usize..node.end as usize] {
                    let i = i as usize;
                    if i == o {
                        continue;
                    }
                    let r = dist(x, t.positions[i]);
                    if r > self.r_cut[i] {
                        continue;
                    }
                    let v = t.point_term(i, x, r, w);
                    b[0] += v[0];
                    b[1] += v[1];
                    b[2] += v[2];
                    points += 1;
                }
                continue;
            }
            let off = [
                x[0] - node.centroid[0],
                x[1] - node.centroid[1],
                x[2] - node.centroid[2],
            ];
            let rc = (off[0] * off[0] + off[1] * off[1] + off[2] * off[2]).sqrt();
            if dbox > 0.0 && node.area < eps * rc * rc {
                let v = self.cluster(k as usize, off, rc);
                b[0] += v[0];
                b[1] += v[1];
                b[2] += v[2];
                clusters += 1;
                continue;
            }
            stack.extend(node.children.iter().copied().filter(|&c| c != u32::MAX));
        }
        (b, clusters, points)
    }
}

/// Weight of a source in its cluster's centroid: the luminance of its flux.
#[inline]
fn flux_weight(p: [f64; 3]) -> f64 {
    (0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]).max(1e-300)
}

fn lse(it: impl Iterator<Item = f64> + Clone) -> f64 {
    let mx = it.clone().fold(f64::NEG_INFINITY, f64::max);
    if !mx.is_finite() || mx <= LN_FLOOR as f64 {
        return LN_FLOOR as f64;
    }
    mx + it.map(|v| (v - mx).exp()).sum::<f64>().ln()
}

fn bbox(p: &[[f64; 3]], idx: &[u32]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &i in idx {
        let q = p[i as usize];
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    (lo, hi)
}

fn bbox_all(p: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for q in p {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    (lo, hi)
}

#[inline]
fn box_distance(x: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> f64 {
    let mut s = 0.0;
    for k in 0..3 {
        let d = (lo[k] - x[k]).max(0.0).max(x[k] - hi[k]);
        s += d * d;
    }
    s.sqrt()
}

#[cfg(test)]
#[allow(clippy::needless_range_loop, clippy::type_complexity)]
mod tests {
    use super::*;
    use crate::modelfile::{ModelFile, VertexStatus};
    use crate::render::vertex_areas;

    /// A wavy sheet with a heterogeneous model: fall-off rate and colour vary over the surface.
    fn sheet(nx: usize) -> (ModelFile, Vec<[f64; 3]>) {
        let mut p = Vec::new();
        let mut nrm = Vec::new();
        for j in 0..nx {
            for i in 0..nx {
                let (x, y) = (i as f64 * 0.5, j as f64 * 0.5);
                p.push([x, y, 0.3 * (0.4 * x).sin()]);
                let dz = 0.3 * 0.4 * (0.4 * x).cos();
                let l = (1.0 + dz * dz).sqrt();
                nrm.push([-dz / l, 0.0, 1.0 / l]);
            }
        }
        let mut f = Vec::new();
        for j in 0..nx - 1 {
            for i in 0..nx - 1 {
                let a = (j * nx + i) as u32;
                let b = a + 1;
                let c = a + nx as u32;
                f.extend([[a, b, c + 1], [a, c + 1, c]]);
            }
        }
        let mut m =
            ModelFile::homogeneous(p.clone(), nrm, f, [0.6, 0.3], &[(1.0, -2.0), (0.1, -0.4)]);
        for v in 0..m.len() {
            let q = &mut m.vertices[v].params;
            let s = 1.0 + 0.5 * (0.7 * p[v][0]).sin() * (0.5 * p[v][1]).cos();
            q[3] *= s;
            q[5] *= s;
            q[0] *= s;
        }
        // Light everything, brighter on one side.
        let e = p.iter().map(|q| [1.0 + 0.1 * q[0], 1.0, 0.5]).collect();
        (m, e)
    }

    #[test]
    fn hierarchical_converges_to_the_exact_sum() {
        let (m, e) = sheet(24);
        let f = Falloffs::new(&m);
        let a = vertex_areas(&m.positions, &m.triangles);
        let t = Transport::new(&m.positions, &m.normals, &f, &e, &a);
        let rec: Vec<usize> = (0..m.len()).collect();
        let exact = t.exact(&rec);
        let mut last = f64::INFINITY;
        for eps in [0.5, 0.1, 0.01] {
            let (h, stats) = t.hierarchical(
                HierarchyParams {
                    max_solid_angle: eps,
                    tail_tolerance: 1e-6,
                },
                &rec,
            );
            assert!(stats.cluster_evals > 0 || eps < 0.05);
            let err = rec
                .iter()
                .map(|&o| {
                    (0..3)
                        .map(|c| (h[o][c] / exact[o][c] - 1.0).abs())
                        .fold(0.0, f64::max)
                })
                .fold(0.0, f64::max);
            assert!(err <= last * 1.01 + 1e-9, "eps {eps}: {err} after {last}");
            last = err;
        }
        assert!(last < 2e-3, "max relative error at eps 0.01: {last}");
        // With no clustering and no cutoff the two are the same sum.
        let (h, stats) = t.hierarchical(
            HierarchyParams {
                max_solid_angle: 0.0,
                tail_tolerance: 0.0,
            },
            &rec,
        );
        assert_eq!(stats.cluster_evals, 0);
        for o in rec {
            for c in 0..3 {
                assert!((h[o][c] / exact[o][c] - 1.0).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn unlit_and_modelless_vertices_emit_nothing() {
        let (mut m, mut e) = sheet(6);
        for v in 0..m.len() {
            if v % 2 == 0 {
                e[v] = [0.0; 3];
            }
        }
        let none = &mut m.vertices[1];
        none.status = VertexStatus::NoModel;
        (none.terms, none.segments) = (0, 0);
        none.params.clear();
        let f = Falloffs::new(&m);
        let a = vertex_areas(&m.positions, &m.triangles);
        let t = Transport::new(&m.positions, &m.normals, &f, &e, &a);
        assert_eq!(t.source_count(), m.len() / 2 - 1);
        let b = t.exact(&[0, 1, 3]);
        assert!(
            b.iter()
                .all(|x| x.iter().all(|&v| v > 0.0 && v.is_finite()))
        );
        // Nothing lit: nothing comes out.
        let dark = vec![[0.0; 3]; m.len()];
        let t = Transport::new(&m.positions, &m.normals, &f, &dark, &a);
        let (h, _) = t.hierarchical(Quality::Draft.params(), &[0, 5]);
        assert_eq!(h, vec![[0.0; 3]; 2]);
    }

    /// Fit, evaluation and rendering measure Eq. 3's directions in one frame: the fit's
    /// (`TangentFrame::from_normal` at x_i's normal, the `select` stage), evaluation's (the model
    /// file's rule at x_i's normal, `ModelFile::frame_at`, after a write and read back) and the
    /// renderer's (each source's frame from its vertex normal) are the same frame, for normals all
    /// over the sphere (the old rule's seam at |n_x| = 0.9 included), and the direction of the
    /// fit's segment l gets all of the renderer's weight on segment l. A file of format 3 renders
    /// in its old frame.
    #[test]
    fn fit_evaluation_and_render_agree_on_a_segments_direction() {
        use crate::model::{FrameRule, hat_weights};
        use crate::render::segment_weights;
        let m = 8;
        let normals: Vec<[f64; 3]> = (0..40)
            .map(|k| {
                let z = -0.95 + 1.9 * k as f64 / 39.0;
                let a = 2.4 * k as f64;
                let s = (1.0 - z * z).sqrt();
                [s * a.cos(), s * a.sin(), z]
            })
            .chain([[0.92, 0.3, 0.25], [0.89, 0.3, 0.34], [0.0, 0.0, 1.0]])
            .map(|n: [f64; 3]| {
                let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                n.map(|x| x / l)
            })
            .collect();
        let nv = normals.len();
        let positions: Vec<[f64; 3]> = (0..nv).map(|k| [k as f64 * 5.0, 0.0, 0.0]).collect();
        let mut file = ModelFile::homogeneous(
            positions.clone(),
            normals.clone(),
            vec![[0, 1, 2]],
            [1.0, 1.0],
            &[(1.0, -1.0)],
        );
        file.shape.segments = m;
        for v in &mut file.vertices {
            v.segments = m as u8;
            v.params = [1.0, 1.0]
                .into_iter()
                .chain((0..m).flat_map(|l| [1.0, -1.0 - l as f64]))
                .collect();
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.ply");
        file.write(&path).unwrap();
        let read = ModelFile::read(&path).unwrap();
        assert_eq!(read.frame, FrameRule::CURRENT);
        let e = vec![[1.0; 3]; nv];
        let areas = vec![1.0; nv];
        let f = Falloffs::new(&read);
        let t = Transport::new(&read.positions, &read.normals, &f, &e, &areas);
        for (i, &n) in normals.iter().enumerate() {
            let fit = TangentFrame::from_normal(n).unwrap();
            let eval = read.frame_at(n).unwrap();
            assert_eq!(fit, eval, "normal {n:?}");
            assert_eq!(fit, t.frames[i], "normal {n:?}");
            let x_i = positions[i];
            for l in 0..m {
                let phi = std::f64::consts::TAU * l as f64 / m as f64;
                let x_o =
                    [0, 1, 2].map(|k| x_i[k] + 2.0 * (phi.cos() * fit.t[k] + phi.sin() * fit.b[k]));
                // The fit bins this sample into segment l ...
                let (_, got) = fit.polar(x_i, x_o);
                let w = hat_weights(got.unwrap(), m);
                assert!(
                    w.iter().any(|&(k, x)| k == l && (x - 1.0).abs() < 1e-9),
                    "{w:?}"
                );
                // ... evaluation reads segment l there ...
                let model =
                    crate::modelfile::model_of(&read.shape, 1, &read.vertices[i].params).unwrap();
                let (r, phi_eval) = eval.polar(x_i, x_o);
                let ln = model.ln_eval(r, phi_eval)[0];
                assert!(
                    (ln - (-(1.0 + l as f64) * 2.0)).abs() < 1e-6,
                    "eval {ln} at l {l}"
                );
                // ... and so does the renderer.
                let mut ws = vec![0.0; m];
                segment_weights(&t.frames[i], x_i, x_o, &mut ws);
                assert!(
                    (ws[l] - 1.0).abs() < 1e-9,
                    "render weights {ws:?} for l {l}"
                );
            }
        }
        // The same file as format 3: read with the old rule, rendered in the old frame.
        let mut old = file.clone();
        old.frame = FrameRule::ReferenceAxis;
        let f_old = Falloffs::new(&old);
        let t_old = Transport::new(&old.positions, &old.normals, &f_old, &e, &areas);
        let seam = nv - 3;
        assert_eq!(
            t_old.frames[seam],
            TangentFrame::with_rule(FrameRule::ReferenceAxis, normals[seam]).unwrap()
        );
        assert_ne!(t_old.frames[seam], t.frames[seam]);
    }
}
