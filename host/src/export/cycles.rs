//! What Blender 3.4's Cycles computes for the Principled BSDF's subsurface scattering, read from
//! its kernel (`intern/cycles/kernel/closure/bssrdf.h`, `svm/closure.h`,
//! `integrator/subsurface_disk.h` of Blender 3.4.1), and the one-parameter fit of its profile to
//! a fitted fall-off.
//!
//! **The profile.** Christensen & Burley (2015), "Approximate Reflectance Profiles for Efficient
//! Subsurface Scattering", Eq. 3: `R(r) = A (e^{−r/d} + e^{−r/(3d)}) / (8π d r)`, whose integral
//! over the plane, `∫ R 2πr dr`, is `A`: the total diffuse reflectance. Their paper fits the
//! shape parameter to the albedo, `d = ℓ / s(A)`, for three set-ups (searchlight:
//! `s = 1.85 − A + 7|A − 0.8|³`; diffuse surface transmission: `s = 1.9 − A + 3.5 (A − 0.8)²`;
//! diffuse mean free path: `s = 3.5 + 100 (A − 0.33)⁴`).
//!
//! **What Blender 3.4 does with it** (the Principled BSDF, `subsurface_method = BURLEY`):
//! - the closure's radius is `Subsurface Radius × Subsurface` (`svm/closure.h`) and its albedo
//!   `Subsurface Color × Subsurface + Base Color × (1 − Subsurface)`: the export sets
//!   Subsurface = 1, so radius and colour are the attributes themselves;
//! - `bssrdf_setup_radius` scales the radius by `0.25/π` for Burley (and for Random Walk
//!   (Fixed Radius)) — and that is all: `bssrdf_burley_setup`, which would divide by the
//!   diffuse-transmission `s(A)`, is never called in 3.4. So **`d = radius / (4π)`, whatever the
//!   albedo**, and the albedo only scales the profile;
//! - `bssrdf_burley_eval` is `(e^{−r/d} + e^{−r/(3d)}) / (4d)` (the profile times `2πr / A`),
//!   truncated at `r = 16 d` and renormalised by the truncated CDF (0.99638), so the light a
//!   point scatters is exactly `A`;
//! - entry and exit: no Fresnel factor where the camera ray enters (3.4 never calls
//!   `bsdf_principled_diffuse_compute_entry_fresnel`), and at the point where light arrives a
//!   Lambertian lobe times `1 − ½ (1 − cos θ_i)⁵` (`PRINCIPLED_DIFFUSE_LAMBERT_EXIT`).
//!
//! Checked in Blender itself: a half-lit slab rendered in Cycles 3.4.1 (the edge response of the
//! profile) fits `d = 0.078 · radius` (1/(4π) = 0.0796) at every albedo from 0.1 to 0.95, to its
//! sampling noise, and its plateau is `A·E/π` within 0.3 % (`docs/export.md`).
//!
//! The random walk (`RANDOM_WALK`, Blender's default) is a volume walk whose coefficients come
//! from the albedo by another fit (Wrenninge et al.) and, for the default method, from an IOR
//! (`bssrdf_setup_radius`: `radius · sqrt(3 (1 − α'))` with α' a dipole inversion of the albedo):
//! its surface profile has no closed form, is not C&B's shape at low albedo, and its scale moves
//! with the albedo — so the subsurface colour, which alpha modulates, would change the
//! fall-off's reach. The export targets Burley, whose profile it can fit exactly.

use std::f64::consts::PI;

/// Cycles' radius per Burley shape parameter `d`: `bssrdf_setup_radius` multiplies the radius by
/// `0.25 · M_1_PI_F`, so `radius = 4π d`.
pub const RADIUS_PER_D: f64 = 4.0 * PI;

/// Cycles' Christensen-Burley response as measured in one Blender version (`subsurf export
/// --measure-cycles`, [`super::Blender::measure`]: the half-lit slab's edge response at albedos
/// 0.1 to 0.95, 256 samples; the same at every albedo, as the kernel says).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeasuredBurley {
    /// The version measured.
    pub blender: &'static str,
    /// The fitted `d` over the Subsurface Radius (the kernel: 1/(4π) = 0.0796).
    pub d_per_radius: f64,
    /// The lit plateau · π / albedo (the kernel: 1).
    pub plateau: f64,
}

/// The versions measured. The export writes `radius = 4π d` and the albedo as the colour in
/// every version: each row is within 1 % of that (a unit test checks).
pub const MEASURED_BURLEY: [MeasuredBurley; 4] = [
    MeasuredBurley {
        blender: "3.4.1",
        d_per_radius: 0.0803,
        plateau: 1.0015,
    },
    MeasuredBurley {
        blender: "4.2.23 LTS",
        d_per_radius: 0.0796,
        plateau: 1.0005,
    },
    MeasuredBurley {
        blender: "4.5.15 LTS",
        d_per_radius: 0.0796,
        plateau: 1.0005,
    },
    MeasuredBurley {
        blender: "5.0.1",
        d_per_radius: 0.0794,
        plateau: 1.0000,
    },
];

/// Cycles truncates the Burley profile at `BURLEY_TRUNCATE · d` (`bssrdf.h`).
pub const TRUNCATE: f64 = 16.0;

/// The share of the Burley profile's light within the truncation radius, `BURLEY_TRUNCATE_CDF`
/// (`bssrdf.h`): `1 − ¼ e^{−16} − ¾ e^{−16/3}`. Cycles divides by it, so the light inside
/// `16 d` is the whole albedo.
pub fn truncated_cdf() -> f64 {
    1.0 - 0.25 * (-TRUNCATE).exp() - 0.75 * (-TRUNCATE / 3.0).exp()
}

/// `ln` of Cycles' Burley profile per unit albedo at distance `r > 0` (mm⁻², like `R_d`):
/// `ln[(e^{−r/d} + e^{−r/(3d)}) / (8π d r)]` renormalised by [`truncated_cdf`], for `r < 16 d`;
/// beyond that Cycles has no light, and this returns the untruncated form (the fit needs a
/// finite value there; the report says how much light lies beyond, see
/// [`energy_beyond_truncation`]). Written as `−r/(3d) + ln(1 + e^{−2r/(3d)})`, finite where both
/// exponentials underflow.
pub fn ln_profile(r: f64, d: f64) -> f64 {
    let x = r / (3.0 * d);
    -x + (-2.0 * x).exp().ln_1p() - (8.0 * PI * d * r).ln() - truncated_cdf().ln()
}

/// The fraction of a fall-off's total diffuse reflectance that lies beyond `rho`, from its
/// cumulative integral: `1 − cumulative(rho) / total`.
pub fn energy_beyond_truncation(cumulative_at_rho: f64, total: f64) -> f64 {
    if total > 0.0 {
        (1.0 - cumulative_at_rho / total).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Disney's exit lobe in Cycles 3.4 relative to Lambert, `1 − ½ (1 − cos θ_i)⁵`, at the point
/// where light enters the material (`bsdf_principled_diffuse_compute_brdf`,
/// `PRINCIPLED_DIFFUSE_LAMBERT_EXIT`); 1 at normal incidence.
pub fn disney_entry_factor(cos_theta: f64) -> f64 {
    1.0 - 0.5 * (1.0 - cos_theta.clamp(0.0, 1.0)).powi(5)
}

/// The best Burley shape `d` (mm) for a fall-off with total reflectance `total` sampled as
/// `ln_target[k]` at distances `r[k]`: the `d` minimising `Σ_k (ln total + ln_profile(r_k, d) −
/// ln_target_k)²`, with its RMS residual (log E of the converted profile, Eq. 8's measure).
///
/// One parameter on a bounded interval: a scan of `ln d` over four decades either side of the
/// sampled range, then golden-section search in the best cell. Hand-written (20 lines) because
/// the objective is one-dimensional and may have a second local minimum a derivative-based
/// solver would stop at; the scan finds the basin, the golden section only polishes it.
pub fn fit_shape(r: &[f64], ln_target: &[f64], total: f64) -> Option<(f64, f64)> {
    if r.is_empty() || r.len() != ln_target.len() || !(total > 0.0 && total.is_finite()) {
        return None;
    }
    let ln_a = total.ln();
    let cost = |ln_d: f64| -> f64 {
        let d = ln_d.exp();
        r.iter()
            .zip(ln_target)
            .map(|(&r, &y)| {
                let e = ln_a + ln_profile(r, d) - y;
                e * e
            })
            .sum::<f64>()
    };
    let (lo, hi) = r
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
    if !(lo > 0.0 && hi.is_finite()) {
        return None;
    }
    let x = minimise_1d(cost, (lo * 1e-4).ln(), (hi * 1e4).ln())?;
    let c = cost(x);
    let d = x.exp();
    let rms = (c / r.len() as f64).sqrt();
    (d.is_finite() && rms.is_finite()).then_some((d, rms))
}

/// The best Burley profile `A · R(r; d)` for a fall-off sampled as `ln_target[k]` at distances
/// `r[k]` with its amplitude free: `(d, A, rms)` minimising `Σ_k (ln A + ln_profile(r_k, d) −
/// ln_target_k)²`. For each `d` the best `ln A` is the mean residual (closed form), so the
/// search is [`fit_shape`]'s over `d` alone.
///
/// Why: with `A` fixed to the fall-off's total reflectance T, a fall-off whose slow term holds
/// much of T puts all of it within Cycles' short profile, too bright near x_i (1.3–1.6×
/// on sample-torus) and black beyond 16 d. A free `A` matches the profile over the sampled
/// distances in Eq. 8's own measure, giving up the light no Burley shape can place.
pub fn fit_shape_free(r: &[f64], ln_target: &[f64]) -> Option<(f64, f64, f64)> {
    if r.is_empty() || r.len() != ln_target.len() {
        return None;
    }
    let n = r.len() as f64;
    let ln_a = |d: f64| -> f64 {
        r.iter()
            .zip(ln_target)
            .map(|(&r, &y)| y - ln_profile(r, d))
            .sum::<f64>()
            / n
    };
    // Given d, the residuals about their mean are what fit_shape's cost sees with A = e^{mean}.
    let (lo, hi) = r
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
    if !(lo > 0.0 && hi.is_finite()) {
        return None;
    }
    let cost = |ln_d: f64| -> f64 {
        let d = ln_d.exp();
        let a = ln_a(d);
        r.iter()
            .zip(ln_target)
            .map(|(&r, &y)| {
                let e = a + ln_profile(r, d) - y;
                e * e
            })
            .sum::<f64>()
    };
    let ln_d = minimise_1d(cost, (lo * 1e-4).ln(), (hi * 1e4).ln())?;
    let d = ln_d.exp();
    let a = ln_a(d).exp();
    let rms = (cost(ln_d) / n).sqrt();
    (d.is_finite() && a.is_finite() && a > 0.0 && rms.is_finite()).then_some((d, a, rms))
}

/// Two Burley lobes with the slow lobe's share of the light fixed: `A [(1 − s) R(r; d_near) +
/// s R(r; d_slow)]` fitted to `ln_target[k]` at `r[k]` in log space, `d_near ≤ d_slow`; returns
/// `(d_near, d_slow, A, rms)`.
///
/// Why the share is fixed and the amplitude free: the share is the fitted terms' split of the
/// light ("weights split T the way the fitted c_k split it"), while the amplitude is
/// fitted as [`fit_shape_free`]'s (on sample-torus's training frames a free amplitude beat T,
/// docs/export.md). For given shapes the best `ln A` is the mean residual (closed form); the two
/// shapes are found on a grid over two decades beyond the distances either side, then
/// polished one at a time by [`minimise_1d`]; the one-lobe fit (both lobes at its `d`) is the
/// starting point, so the result is never worse than it over the same distances.
pub fn fit_two_lobes(r: &[f64], ln_target: &[f64], share: f64) -> Option<(f64, f64, f64, f64)> {
    if !(0.0..=1.0).contains(&share) {
        return None;
    }
    let (d0, _, _) = fit_shape_free(r, ln_target)?;
    let n = r.len() as f64;
    let (lo, hi) = r
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
    let shape = |r: f64, d1: f64, d2: f64| -> f64 {
        let (a, b) = (
            (1.0 - share).ln() + ln_profile(r, d1),
            share.ln() + ln_profile(r, d2),
        );
        let m = a.max(b);
        if m.is_finite() {
            m + ((a - m).exp() + (b - m).exp()).ln()
        } else {
            m
        }
    };
    let cost_ln_a = |d1: f64, d2: f64| -> (f64, f64) {
        let res: Vec<f64> = r
            .iter()
            .zip(ln_target)
            .map(|(&r, &y)| y - shape(r, d1, d2))
            .collect();
        let ln_a = res.iter().sum::<f64>() / n;
        (res.iter().map(|e| (e - ln_a).powi(2)).sum::<f64>(), ln_a)
    };
    // A grid over ln d_near ≤ ln d_slow (coordinate descent from the one-lobe fit alone stops
    // where both lobes are one), then coordinate polishing within a cell either side.
    const GRID: usize = 48;
    let (a, b) = ((lo * 1e-2).min(d0).ln(), (hi * 1e2).max(d0).ln());
    let h = (b - a) / (GRID - 1) as f64;
    let (mut l1, mut l2, mut best) = (d0.ln(), d0.ln(), cost_ln_a(d0, d0).0);
    for i in 0..GRID {
        for j in i..GRID {
            let (x1, x2) = (a + h * i as f64, a + h * j as f64);
            let c = cost_ln_a(x1.exp(), x2.exp()).0;
            if c < best {
                (l1, l2, best) = (x1, x2, c);
            }
        }
    }
    for _ in 0..2 {
        l1 = minimise_1d(|x| cost_ln_a(x.exp(), l2.exp()).0, l1 - h, (l1 + h).min(l2))?;
        l2 = minimise_1d(|x| cost_ln_a(l1.exp(), x.exp()).0, (l2 - h).max(l1), l2 + h)?;
    }
    let (d1, d2) = (l1.exp(), l2.exp());
    let (c, ln_a) = cost_ln_a(d1, d2);
    let amp = ln_a.exp();
    let rms = (c / n).sqrt();
    (d1.is_finite() && d2.is_finite() && amp.is_finite() && amp > 0.0 && rms.is_finite())
        .then_some((d1, d2, amp, rms))
}

/// The minimum of `cost` over `[a, b]`: a scan of 160 steps, then golden-section search in the
/// best cell (`None` when no step's cost is finite). [`fit_shape`] and [`fit_shape_free`]
/// search with it.
fn minimise_1d(cost: impl Fn(f64) -> f64, a: f64, b: f64) -> Option<f64> {
    const STEPS: usize = 160;
    let step = (b - a) / STEPS as f64;
    let (mut best, mut best_cost) = (a, f64::INFINITY);
    for k in 0..=STEPS {
        let x = a + step * k as f64;
        let c = cost(x);
        if c < best_cost {
            (best, best_cost) = (x, c);
        }
    }
    if !best_cost.is_finite() {
        return None;
    }
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut x0, mut x1) = (best - step, best + step);
    let (mut p, mut q) = (x1 - g * (x1 - x0), x0 + g * (x1 - x0));
    let (mut cp, mut cq) = (cost(p), cost(q));
    for _ in 0..60 {
        if cp < cq {
            x1 = q;
            (q, cq) = (p, cp);
            p = x1 - g * (x1 - x0);
            cp = cost(p);
        } else {
            x0 = p;
            (p, cp) = (q, cq);
            q = x0 + g * (x1 - x0);
            cq = cost(q);
        }
    }
    let x = 0.5 * (x0 + x1);
    Some(if cost(x) <= best_cost { x } else { best })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every Blender measured scatters as the export assumes: d = radius / (4π), plateau the
    /// albedo / π, within 1 %.
    #[test]
    fn every_measured_blender_is_the_kernels_burley() {
        for m in MEASURED_BURLEY {
            assert!((m.d_per_radius * RADIUS_PER_D - 1.0).abs() < 0.01, "{m:?}");
            assert!((m.plateau - 1.0).abs() < 0.01, "{m:?}");
        }
    }

    /// ∫ R 2πr dr over (0, 16 d) of the renormalised profile is 1 (the albedo), by Simpson in
    /// ln r; Cycles' constant is what the closed form gives.
    #[test]
    fn the_truncated_profile_integrates_to_the_albedo() {
        assert!((truncated_cdf() - 0.996_379_009_370_832_8).abs() < 1e-12);
        let d: f64 = 0.7;
        let (a, b) = ((1e-9 * d).ln(), (TRUNCATE * d).ln());
        let n = 4000;
        let h = (b - a) / n as f64;
        let f = |u: f64| {
            let r = u.exp();
            ln_profile(r, d).exp() * 2.0 * PI * r * r
        };
        let mut s = f(a) + f(b);
        for k in 1..n {
            s += f(a + h * k as f64) * if k % 2 == 1 { 4.0 } else { 2.0 };
        }
        let total = s * h / 3.0;
        assert!((total - 1.0).abs() < 1e-6, "{total}");
    }

    /// A Burley profile is recovered exactly from its own samples; a sum of two exponentials
    /// with a slow second term is not, and the residual says so.
    #[test]
    fn the_fit_recovers_a_burley_profile_and_reports_what_it_cannot_represent() {
        let r: Vec<f64> = (0..32).map(|k| 0.2 * 1.12f64.powi(k)).collect();
        for d in [0.05, 0.4, 3.0] {
            let y: Vec<f64> = r.iter().map(|&r| 0.6f64.ln() + ln_profile(r, d)).collect();
            let (got, rms) = fit_shape(&r, &y, 0.6).unwrap();
            assert!((got / d - 1.0).abs() < 1e-6, "{got} vs {d}");
            assert!(rms < 1e-6, "{rms}");
        }
        let y: Vec<f64> = r
            .iter()
            .map(|&r| (0.5 * (-2.0 * r).exp() + 0.002 * (-0.1 * r).exp()).ln())
            .collect();
        let total = 2.0 * PI * (0.5 / 4.0 + 0.002 / 0.01);
        let (_, rms) = fit_shape(&r, &y, total).unwrap();
        assert!(
            rms > 0.3,
            "a slow second term is beyond one Burley shape: {rms}"
        );
        assert!(fit_shape(&[], &[], 1.0).is_none());
        // With the amplitude free, a Burley profile of any albedo is recovered, and the slow
        // term's fall-off is matched better than with A = T (in log E over the range).
        let y: Vec<f64> = r
            .iter()
            .map(|&r| 0.3f64.ln() + ln_profile(r, 0.4))
            .collect();
        let (d, a, rms) = fit_shape_free(&r, &y).unwrap();
        assert!((d / 0.4 - 1.0).abs() < 1e-5 && (a / 0.3 - 1.0).abs() < 1e-5 && rms < 1e-5);
        let slow: Vec<f64> = r
            .iter()
            .map(|&r| (0.5 * (-2.0 * r).exp() + 0.002 * (-0.1 * r).exp()).ln())
            .collect();
        let (_, fixed) = fit_shape(&r, &slow, total).unwrap();
        let (_, _, free) = fit_shape_free(&r, &slow).unwrap();
        assert!(free < fixed, "{free} vs {fixed}");
        assert!(fit_shape_free(&[], &[]).is_none());
        assert!(fit_shape(&[1.0], &[0.0], f64::NAN).is_none());
    }

    /// Two Burley lobes with the share given are recovered from their own sum; on a fall-off
    /// with a slow second term the pair fits better than one lobe with its amplitude free.
    #[test]
    fn two_lobes_are_recovered_and_fit_a_slow_term_better_than_one() {
        let r: Vec<f64> = (0..32).map(|k| 0.2 * 1.12f64.powi(k)).collect();
        let (share, d1, d2, a) = (0.3, 0.2, 2.0, 0.8);
        let y: Vec<f64> = r
            .iter()
            .map(|&r| {
                (a * ((1.0 - share) * ln_profile(r, d1).exp() + share * ln_profile(r, d2).exp()))
                    .ln()
            })
            .collect();
        let (g1, g2, ga, rms) = fit_two_lobes(&r, &y, share).unwrap();
        // To the grid's and the polish's resolution (a hundredth in ln A over the range).
        assert!(rms < 1e-2, "{rms}");
        assert!(
            (g1 / d1 - 1.0).abs() < 0.05 && (g2 / d2 - 1.0).abs() < 0.05,
            "{g1} {g2}"
        );
        assert!((ga / a - 1.0).abs() < 0.05, "{ga}");
        let slow: Vec<f64> = r
            .iter()
            .map(|&r| (0.5 * (-2.0 * r).exp() + 0.002 * (-0.1 * r).exp()).ln())
            .collect();
        let (_, _, one) = fit_shape_free(&r, &slow).unwrap();
        // The terms' own split of the light: 2π c / d² each.
        let share = (0.002 / 0.01) / (0.5 / 4.0 + 0.002 / 0.01);
        let (n, s, _, two) = fit_two_lobes(&r, &slow, share).unwrap();
        assert!(two < one && n <= s, "{two} vs {one}");
        assert!(fit_two_lobes(&r, &slow, 1.5).is_none());
        assert!(fit_two_lobes(&[], &[], 0.5).is_none());
    }

    #[test]
    fn disney_exit_lobe_is_one_at_normal_incidence_and_half_at_grazing() {
        assert_eq!(disney_entry_factor(1.0), 1.0);
        assert!((disney_entry_factor(0.0) - 0.5).abs() < 1e-15);
    }
}
