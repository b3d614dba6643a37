//! Fresnel transmission through the object's boundary (the `F_t` factors of Jensen et al. 2001).

/// Unpolarised Fresnel transmittance `F_t = 1 − F_r` for light arriving from air at a smooth
/// boundary with relative index `eta` (material / air) at `cos_theta` to the normal. By
/// reciprocity the same factor applies to light leaving towards a viewer at that angle.
pub fn fresnel_transmittance(eta: f64, cos_theta: f64) -> f64 {
    let ci = cos_theta.clamp(0.0, 1.0);
    if ci == 0.0 {
        return 0.0;
    }
    let si2 = 1.0 - ci * ci;
    let st2 = si2 / (eta * eta);
    if st2 >= 1.0 {
        return 0.0;
    }
    let ct = (1.0 - st2).sqrt();
    let rs = (ci - eta * ct) / (ci + eta * ct);
    let rp = (eta * ci - ct) / (eta * ci + ct);
    1.0 - 0.5 * (rs * rs + rp * rp)
}

/// `F_t(θ) / F_t(0)`: the transmission relative to normal incidence.
///
/// The fitted `R_d` comes from a laser hitting the surface and a camera looking at it, so it
/// already contains one transmission in and one out at the capture angles (near normal, §4.1). The
/// renderer therefore applies only how transmission changes with angle, so a measured model is not
/// dimmed twice; at normal incidence both ends are exactly 1.
pub fn relative_transmittance(eta: f64, cos_theta: f64) -> f64 {
    fresnel_transmittance(eta, cos_theta) / fresnel_transmittance(eta, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_incidence_matches_the_closed_form() {
        let eta: f64 = 1.5;
        let r0 = ((eta - 1.0) / (eta + 1.0)).powi(2);
        assert!((fresnel_transmittance(eta, 1.0) - (1.0 - r0)).abs() < 1e-12);
        assert!((relative_transmittance(eta, 1.0) - 1.0).abs() < 1e-15);
    }

    #[test]
    fn transmission_falls_to_zero_at_grazing_and_is_monotone() {
        let mut last = 1.0;
        for k in (0..=100).rev() {
            let t = fresnel_transmittance(1.3, k as f64 / 100.0);
            assert!(t <= last + 1e-12 && (0.0..=1.0).contains(&t));
            last = t;
        }
        assert_eq!(fresnel_transmittance(1.3, 0.0), 0.0);
        assert_eq!(fresnel_transmittance(1.3, -0.5), 0.0);
    }
}
