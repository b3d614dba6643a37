//! Sufficient statistics of samples binned by distance: the fast mode's data and the start
//! values' data.
//!
//! Inside a bin, ln R_d is replaced by its second-order Taylor polynomial about the bin's mean
//! distance r̄: ln R_d(r̄ + x) ≈ L + g·x + ½h·x² (L = ln R_d(r̄), g and h its first and second
//! derivatives). With φ = (1, x, x²), v = (L − ȳ, g, h/2) and y = ln s − ȳ, the log objective
//! (Eq. 4) over the bin's samples is then exactly
//! Σ(φ·v − y)² = vᵀMv − 2vᵀb + Σy² = |U·v − z|² + (Σy² − |z|²),
//! with M = Σφφᵀ = UᵀU (Cholesky), b = Σφ·y and z = U⁻ᵀb. So three residuals per bin, U·v − z,
//! reproduce the exact objective up to the cubic term of ln R_d across one bin, and the constant
//! Σy² − |z|² (the scatter no quadratic explains) completes the exact cost for log E. The moments
//! are accumulated in one pass over the samples; the bin count is the speed/accuracy knob.

use super::isotropic::ln_positive;

/// One distance bin's sufficient statistics (see the module doc), in the units it was built in.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Bin {
    /// Number of samples n_b.
    pub n: f64,
    /// Mean distance r̄_b.
    pub r: f64,
    /// Mean ln s, ȳ_b.
    pub y: f64,
    /// Upper-triangular Cholesky factor U of M (module doc), row-major: u00, u01, u02, u11, u12,
    /// u22. Directions M cannot see (fewer than three distinct distances) have zero rows.
    pub u: [f64; 6],
    /// z = U⁻ᵀ·Σφ·(ln s − ȳ) (module doc).
    pub z: [f64; 3],
    /// Σ(ln s − ȳ)² − |z|² ≥ 0: the bin's scatter about its best quadratic.
    pub scatter: f64,
}

impl Bin {
    /// The same statistics for distances divided by `scale_r` and log values shifted by −`level`.
    pub fn normalised(self, scale_r: f64, level: f64) -> Self {
        let (s1, s2) = (1.0 / scale_r, 1.0 / (scale_r * scale_r));
        let u = self.u;
        Self {
            r: self.r * s1,
            y: self.y - level,
            // Column j of U multiplies the j-th derivative term, which scales with scale_r^j.
            u: [u[0], u[1] * s1, u[2] * s2, u[3] * s1, u[4] * s2, u[5] * s2],
            ..self
        }
    }

    /// Bin statistics from centred moments (x = r − r̄, y = ln s − ȳ, all per sample, divided by
    /// n): c2 = ⟨x²⟩, c3 = ⟨x³⟩, c4 = ⟨x⁴⟩, cxy = ⟨xy⟩, cx2y = ⟨x²y⟩, cyy = ⟨y²⟩.
    #[allow(clippy::too_many_arguments)]
    fn from_centred(
        n: f64,
        r: f64,
        y: f64,
        c2: f64,
        c3: f64,
        c4: f64,
        cxy: f64,
        cx2y: f64,
        cyy: f64,
    ) -> Self {
        // M = n·[[1, 0, c2], [0, c2, c3], [c2, c3, c4]], b = n·(0, cxy, cx2y).
        let u00 = n.sqrt();
        let mut u = [0.0; 6];
        let mut z = [0.0; 3];
        u[0] = u00;
        // A spread below 1e-12 of the bin's distance is one distance (rounding of equal r).
        let tiny = (r * r * 1e-24).max(f64::MIN_POSITIVE);
        if c2 > tiny {
            let u11 = (n * c2).sqrt();
            u[2] = n * c2 / u00;
            u[3] = u11;
            u[4] = n * c3 / u11;
            z[1] = n * cxy / u11;
            // Schur complement of the quadratic direction; ≤ 0 up to rounding = two distances.
            let s22 = n * c4 - u[2] * u[2] - u[4] * u[4];
            if s22 > 1e-9 * n * c4 {
                u[5] = s22.sqrt();
                z[2] = (n * cx2y - u[4] * z[1]) / u[5];
            }
        }
        let scatter = (n * cyy - z[1] * z[1] - z[2] * z[2]).max(0.0);
        Self {
            n,
            r,
            y,
            u,
            z,
            scatter,
        }
    }
}

impl Bin {
    /// The bin's centred sums over its samples, (Σx², Σx³, Σx⁴, Σxy, Σx²y, Σy²) with
    /// x = r − r̄, y = ln s − ȳ, read back from U, z and the scatter (M = UᵀU, Σφy = Uᵀz,
    /// Σy² = scatter + |z|²). Exact where [`Bin::from_centred`] kept every direction; a bin
    /// whose spread it dropped as rounding gives zeros there, as its statistics say.
    fn centred_sums(&self) -> [f64; 6] {
        let (u, z) = (&self.u, &self.z);
        [
            u[1] * u[1] + u[3] * u[3],
            u[1] * u[2] + u[3] * u[4],
            u[2] * u[2] + u[4] * u[4] + u[5] * u[5],
            u[1] * z[0] + u[3] * z[1],
            u[2] * z[0] + u[4] * z[1] + u[5] * z[2],
            self.scatter + z[0] * z[0] + z[1] * z[1] + z[2] * z[2],
        ]
    }

    /// One bin holding the samples of `bins` (consecutive bins of one binning): their sums add
    /// once moved to the common centre by the parallel-axis rules (X = x + δ, Y = y + η with
    /// δ, η the offsets of a bin's means from the merged ones, and Σx = Σy = 0 in each bin).
    /// `None` for no samples.
    pub fn merged(bins: &[Bin]) -> Option<Bin> {
        let n: f64 = bins.iter().map(|b| b.n).sum();
        if n.is_nan() || n <= 0.0 {
            return None;
        }
        let r = bins.iter().map(|b| b.n * b.r).sum::<f64>() / n;
        let y = bins.iter().map(|b| b.n * b.y).sum::<f64>() / n;
        let mut t = [0.0f64; 6];
        for b in bins {
            let [sx2, sx3, sx4, sxy, sx2y, syy] = b.centred_sums();
            let (dx, dy, m) = (b.r - r, b.y - y, b.n);
            let dx2 = dx * dx;
            t[0] += sx2 + m * dx2;
            t[1] += sx3 + 3.0 * dx * sx2 + m * dx2 * dx;
            t[2] += sx4 + 4.0 * dx * sx3 + 6.0 * dx2 * sx2 + m * dx2 * dx2;
            t[3] += sxy + m * dx * dy;
            t[4] += sx2y + dy * sx2 + 2.0 * dx * sxy + m * dx2 * dy;
            t[5] += syy + m * dy * dy;
        }
        let [c2, c3, c4, cxy, cx2y, cyy] = t.map(|v| v / n);
        Some(Bin::from_centred(n, r, y, c2, c3, c4, cxy, cx2y, cyy))
    }
}

/// `bins` with every `factor` consecutive bins merged into one ([`Bin::merged`]): the coarse
/// level of the isotropic fit's coarse-to-fine solve, exact statistics of the same samples on
/// fewer, wider bins.
pub fn coarsen(bins: &[Bin], factor: usize) -> Vec<Bin> {
    bins.chunks(factor.max(1)).filter_map(Bin::merged).collect()
}

/// Samples binned and normalised for the isotropic fits.
#[derive(Debug, Clone, Default)]
pub struct Binned {
    /// Non-empty bins in increasing distance, distances divided by `scale_r`, ln s shifted by
    /// −`level`.
    pub bins: Vec<Bin>,
    /// Largest distance (the unit of the normalised distances).
    pub scale_r: f64,
    /// Mean ln s over all samples.
    pub level: f64,
}

/// Samples per block of the binning pass: the logarithms and bin indices of a block are computed
/// in tight loops the compiler vectorises, then scattered into the bins.
const BLOCK: usize = 64;

/// 1.5·2^52: adding it to a float in (−2^50, 2^50) leaves the rounded integer in the low
/// mantissa bits (the spacing of floats there is exactly 1).
const MAGIC: f64 = 6_755_399_441_055_744.0;

/// Bins cleaned samples (finite r ≥ 0, finite s > 0) into `count` distance bins over
/// [min r, max r], equal steps in √r (edges lo + (hi − lo)·(b/count)²: narrow bins near x_i,
/// where the fast terms bend ln R_d most, wide ones in the slowly varying tail). One pass over
/// the samples after a min/max scan; no sort, no per-sample allocation.
pub fn bin_samples(r: &[f64], s: &[f64], count: usize) -> Binned {
    bin_inner::<false>(r, s, &[], count).0
}

/// [`bin_samples`] that also returns, per non-empty bin, the mean of a per-sample `aux` value
/// (the direction φ in the fast anisotropic mode).
pub(crate) fn bin_samples_aux(
    r: &[f64],
    s: &[f64],
    aux: &[f64],
    count: usize,
) -> (Binned, Vec<f64>) {
    bin_inner::<true>(r, s, aux, count)
}

/// The binning pass, monomorphised so the isotropic path carries no auxiliary sums, and run
/// under the SIMD dispatch (the logarithms and bin indices of a block vectorise to the CPU's
/// width, see [`super::simd`]).
fn bin_inner<const AUX: bool>(
    r: &[f64],
    s: &[f64],
    aux: &[f64],
    count: usize,
) -> (Binned, Vec<f64>) {
    super::simd::wide(BinPass::<AUX> { r, s, aux, count })
}

/// The arguments of [`bin_kernel`] as a [`super::simd::Kernel`].
struct BinPass<'a, const AUX: bool> {
    r: &'a [f64],
    s: &'a [f64],
    aux: &'a [f64],
    count: usize,
}

impl<const AUX: bool> super::simd::Kernel for BinPass<'_, AUX> {
    type Output = (Binned, Vec<f64>);
    #[inline(always)]
    fn run(self) -> Self::Output {
        bin_kernel::<AUX>(self.r, self.s, self.aux, self.count)
    }
}

/// The body of [`bin_inner`], inlined into its SIMD dispatch (and called directly, for the
/// baseline, by the test that compares the two).
#[inline(always)]
pub(crate) fn bin_kernel<const AUX: bool>(
    r: &[f64],
    s: &[f64],
    aux: &[f64],
    count: usize,
) -> (Binned, Vec<f64>) {
    let count = count.max(1);
    let len = if AUX {
        r.len().min(s.len()).min(aux.len())
    } else {
        r.len().min(s.len())
    };
    let (r, s) = (&r[..len], &s[..len]);
    // Min and max over four independent lanes (one lane's compare chain would serialise).
    let (mut lo4, mut hi4) = ([f64::INFINITY; 4], [f64::NEG_INFINITY; 4]);
    let quads = r.chunks_exact(4);
    let rest = quads.remainder();
    for q in quads {
        for l in 0..4 {
            lo4[l] = if q[l] < lo4[l] { q[l] } else { lo4[l] };
            hi4[l] = if q[l] > hi4[l] { q[l] } else { hi4[l] };
        }
    }
    let (mut lo, mut hi) = (lo4[0], hi4[0]);
    for &v in lo4.iter().chain(rest) {
        lo = lo.min(v);
    }
    for &v in hi4.iter().chain(rest) {
        hi = hi.max(v);
    }
    if !(lo.is_finite() && hi.is_finite()) || len == 0 {
        return (Binned::default(), Vec::new());
    }
    let span = hi - lo;
    let c = count as f64;
    let inv_span = if span > 0.0 { 1.0 / span } else { 0.0 };
    let edges: Vec<f64> = (0..count)
        .map(|b| lo + span * (b as f64 / c) * (b as f64 / c))
        .collect();
    // ln s is accumulated relative to the first sample's so the raw moments do not cancel.
    let y0 = ln_positive(s[0]);
    // Raw sums per bin relative to the bin's left edge: n, x, x², x³, x⁴, y, xy, x²y, y².
    let mut acc = vec![[0.0f64; 9]; count];
    let mut aux_sum = vec![0.0f64; if AUX { count } else { 0 }];
    let mut yb = [0.0f64; BLOCK];
    let mut ib = [0usize; BLOCK];
    let last = (count - 1) as f64;
    // The last, short block is padded (r = lo, s = 1, never scattered) so that the logarithm
    // and index loops always run BLOCK times: with the trip count unknown the compiler left
    // the logarithms scalar (perf annotate, the AVX-512 build).
    let (mut rpad, mut spad) = ([lo; BLOCK], [1.0f64; BLOCK]);
    for (block, (rc, sc)) in r.chunks(BLOCK).zip(s.chunks(BLOCK)).enumerate() {
        let k = rc.len();
        let (rc, sc): (&[f64; BLOCK], &[f64; BLOCK]) = match (rc.try_into(), sc.try_into()) {
            (Ok(rc), Ok(sc)) => (rc, sc),
            _ => {
                rpad[..k].copy_from_slice(rc);
                spad[..k].copy_from_slice(sc);
                (&rpad, &spad)
            }
        };
        for j in 0..BLOCK {
            yb[j] = ln_positive(sc[j]) - y0;
        }
        for j in 0..BLOCK {
            // ⌊t⌋ for t ∈ [0, count] by the 1.5·2^52 bit trick (round(t − ½) lands in the low
            // mantissa bits): unlike a saturating float→int cast it vectorises. A sample exactly
            // on an edge may go to either neighbour, which the moments do not mind; the index
            // is clamped again where it is used.
            // (Clamped to last + ¼, not last: round(last − ½) would tie to an even index.)
            let t = (c * ((rc[j] - lo) * inv_span).sqrt()).min(last + 0.25) - 0.5 + MAGIC;
            ib[j] = (t.to_bits() & 0xffff_ffff) as usize;
        }
        for j in 0..k {
            let b = ib[j].min(count - 1);
            let x = rc[j] - edges[b];
            let y = yb[j];
            let x2 = x * x;
            let a = &mut acc[b];
            a[0] += 1.0;
            a[1] += x;
            a[2] += x2;
            a[3] += x2 * x;
            a[4] += x2 * x2;
            a[5] += y;
            a[6] += x * y;
            a[7] += x2 * y;
            a[8] += y * y;
            if AUX {
                aux_sum[b] += aux[block * BLOCK + j];
            }
        }
    }
    let total: f64 = acc.iter().map(|a| a[5]).sum();
    let level = y0 + total / len as f64;
    let scale_r = hi;
    let aux_mean: Vec<f64> = if AUX {
        acc.iter()
            .zip(&aux_sum)
            .filter(|(a, _)| a[0] > 0.0)
            .map(|(a, x)| x / a[0])
            .collect()
    } else {
        Vec::new()
    };
    let bins = acc
        .iter()
        .zip(&edges)
        .filter(|(a, _)| a[0] > 0.0)
        .map(|(a, &edge)| {
            let n = a[0];
            let [m1, m2, m3, m4, my, mxy, mx2y, myy] =
                [a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8]].map(|v| v / n);
            let c2 = (m2 - m1 * m1).max(0.0);
            let c3 = m3 - 3.0 * m1 * m2 + 2.0 * m1 * m1 * m1;
            let c4 = (m4 - 4.0 * m1 * m3 + 6.0 * m1 * m1 * m2 - 3.0 * m1 * m1 * m1 * m1).max(0.0);
            let cxy = mxy - m1 * my;
            let cx2y = mx2y - 2.0 * m1 * mxy + m1 * m1 * my - my * c2;
            let cyy = (myy - my * my).max(0.0);
            Bin::from_centred(n, edge + m1, y0 + my, c2, c3, c4, cxy, cx2y, cyy)
                .normalised(scale_r, level)
        })
        .collect();
    (
        Binned {
            bins,
            scale_r,
            level,
        },
        aux_mean,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// |U·v − z|² + scatter against the direct sum of (v·φ − y)² over a bin's samples.
    fn quadratic_cost(b: &Bin, v: [f64; 3]) -> f64 {
        let u = b.u;
        let rho = [
            u[0] * v[0] + u[1] * v[1] + u[2] * v[2] - b.z[0],
            u[3] * v[1] + u[4] * v[2] - b.z[1],
            u[5] * v[2] - b.z[2],
        ];
        rho.iter().map(|v| v * v).sum::<f64>() + b.scatter
    }

    #[test]
    fn moments_reproduce_the_quadratic_objective() {
        let r: Vec<f64> = (0..100).map(|i| 0.5 + i as f64 * 0.37 % 10.0).collect();
        let s: Vec<f64> = r
            .iter()
            .map(|v| (-0.5 * v + (v * 7.0).sin()).exp())
            .collect();
        let binned = bin_samples(&r, &s, 4);
        assert_eq!(binned.bins.iter().map(|b| b.n).sum::<f64>(), 100.0);
        let (scale, level) = (binned.scale_r, binned.level);
        let mean_ln = s.iter().map(|v| v.ln()).sum::<f64>() / 100.0;
        assert!((level - mean_ln).abs() < 1e-12 && scale == r.iter().cloned().fold(0.0, f64::max));
        let lo = r.iter().cloned().fold(f64::INFINITY, f64::min);
        for (bi, b) in binned.bins.iter().enumerate() {
            let sel: Vec<(f64, f64)> = r
                .iter()
                .zip(&s)
                .filter(|(v, _)| ((4.0 * ((**v - lo) / (scale - lo)).sqrt()) as usize).min(3) == bi)
                .map(|(a, b)| (a / scale, b.ln() - level))
                .collect();
            let n = sel.len() as f64;
            let mr = sel.iter().map(|p| p.0).sum::<f64>() / n;
            let my = sel.iter().map(|p| p.1).sum::<f64>() / n;
            assert_eq!(b.n, n);
            assert!((b.r - mr).abs() < 1e-12 && (b.y - my).abs() < 1e-12);
            for v in [[0.1, -0.3, 2.0], [-0.2, 1.5, -4.0], [0.0, 0.0, 0.0]] {
                let direct: f64 = sel
                    .iter()
                    .map(|p| {
                        let x = p.0 - mr;
                        (v[0] + v[1] * x + v[2] * x * x - (p.1 - my)).powi(2)
                    })
                    .sum();
                let got = quadratic_cost(b, v);
                assert!(
                    (got - direct).abs() < 1e-9 * (1.0 + direct),
                    "{got} {direct}"
                );
            }
        }
    }

    /// Merging every 4 of 64 bins gives the statistics of binning the same samples into 16
    /// (the same edges: (4k/64)² = (k/16)²): counts, means, and the quadratic objective of every
    /// bin.
    #[test]
    fn merged_bins_are_the_coarser_binning() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut uniform = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        let r: Vec<f64> = (0..3000).map(|_| 40.0 * uniform().powi(2)).collect();
        let s: Vec<f64> = r
            .iter()
            .map(|&v| (2.0 * (-3.0 * v).exp() + (-0.2 * v).exp()) * (1.0 + 0.05 * uniform()))
            .collect();
        let fine = bin_samples(&r, &s, 64);
        let coarse = bin_samples(&r, &s, 16);
        let merged = coarsen(&fine.bins, 4);
        assert_eq!(merged.len(), coarse.bins.len());
        assert!(merged.len() == 16);
        for (m, c) in merged.iter().zip(&coarse.bins) {
            assert_eq!(m.n, c.n);
            assert!(
                (m.r - c.r).abs() < 1e-13 && (m.y - c.y).abs() < 1e-12,
                "{m:?} {c:?}"
            );
            for v in [[0.1, -0.3, 2.0], [-0.2, 1.5, -4.0], [0.0, 0.0, 0.0]] {
                let (a, b) = (quadratic_cost(m, v), quadratic_cost(c, v));
                assert!((a - b).abs() < 1e-9 * (1.0 + b), "{a} {b}");
            }
        }
        assert!(Bin::merged(&[]).is_none());
        // One bin alone: its sums read back from U, z and the scatter give it again.
        for b in &fine.bins {
            let m = Bin::merged(&[*b]).unwrap();
            assert!(m.n == b.n, "{m:?} {b:?}");
            assert!(
                (m.r - b.r).abs() <= 1e-15 && (m.y - b.y).abs() <= 1e-14,
                "{m:?} {b:?}"
            );
            for (p, q) in m.u.iter().chain(&m.z).zip(b.u.iter().chain(&b.z)) {
                assert!((p - q).abs() <= 1e-10 * (1.0 + q.abs()), "{m:?} {b:?}");
            }
            assert!((m.scatter - b.scatter).abs() <= 1e-12 * (1.0 + b.scatter));
        }
    }

    #[test]
    fn one_distance_is_one_bin() {
        let binned = bin_samples(&[2.0; 5], &[1.0; 5], 8);
        assert_eq!(binned.bins.len(), 1);
        assert_eq!(binned.bins[0].u[3], 0.0);
        assert_eq!(binned.bins[0].u[5], 0.0);
    }

    #[test]
    fn two_distances_have_no_quadratic_direction() {
        let r = [1.0, 1.0, 1.2, 1.2];
        let s = [1.0, 1.1, 0.7, 0.8];
        let b = bin_samples(&r, &s, 1).bins[0];
        assert!(b.u[3] > 0.0 && b.u[5] == 0.0 && b.z[2] == 0.0);
        assert!(b.scatter.is_finite() && b.scatter >= 0.0);
    }
}
