//! The spot depth's model: how the camera's view of a laser spot lies below the surface of a
//! translucent object, as the motion that takes a triangulated spot point back to where the
//! laser entered. Measured on sample-pebble against its true mesh (BENCHMARKS.md, "`subsurf
//! align`"), the spots lie 0.02–0.29 mm inside the surface along the normal, the same at the
//! same geometry, but no model here explains that spread better than one depth along the laser
//! ray (the default): the others are there to test a material on.
use super::evidence::SpotPoint;
use crate::geometry::{V3, dot};

/// How the camera's view of a spot lies below the surface: the direction (or directions) the
/// spot depth moves a triangulated spot point back to where the light entered. In a translucent
/// object the spot's light comes from below its surface, so the camera ray through the spot's
/// centre meets the laser ray below the surface; a model that does not know it fits the mesh
/// into the spots (smaller, or deeper), and the depth trades against the scale and the height.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum DepthModel {
    /// One depth along every laser ray.
    Laser,
    /// Along the laser ray, by a depth that changes with the angle of incidence:
    /// `d0 + d1·(1 − cos θ_i)`, θ_i between the laser ray and the surface normal.
    Incidence,
    /// The spot's light seen from a depth along the refracted beam, through the refracting
    /// surface (refractive index [`REFRACTIVE_INDEX`]): where the camera ray through it then
    /// crosses the laser ray. With index 1 it is [`DepthModel::Laser`].
    Refracted,
}

/// The refractive index [`DepthModel::Refracted`] assumes: glass, jade, marble, wax and skin lie
/// within 1.4–1.6.
pub const REFRACTIVE_INDEX: f64 = 1.5;

impl DepthModel {
    /// Every model, the default first.
    pub const ALL: [DepthModel; 3] = [
        DepthModel::Laser,
        DepthModel::Incidence,
        DepthModel::Refracted,
    ];

    /// Its name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            DepthModel::Laser => "laser",
            DepthModel::Incidence => "incidence",
            DepthModel::Refracted => "refracted",
        }
    }

    /// How many coefficients it has.
    pub fn terms(self) -> usize {
        match self {
            DepthModel::Incidence => 2,
            _ => 1,
        }
    }

    /// Whether its directions depend on the surface normal.
    pub(crate) fn needs_normal(self) -> bool {
        self != DepthModel::Laser
    }

    /// The directions its coefficients move the spot point `sp` along, per mm, `normal` the
    /// surface's unit normal near it (either sign: it is turned towards the camera).
    pub fn directions(self, sp: &SpotPoint, normal: V3) -> [V3; 2] {
        let n = if dot(normal, sp.to_camera) < 0.0 {
            normal.map(|x| -x)
        } else {
            normal
        };
        let l = sp.to_laser;
        match self {
            DepthModel::Laser => [l, [0.0; 3]],
            DepthModel::Incidence => {
                let grazing = 1.0 - dot(n, l).clamp(0.0, 1.0);
                [l, l.map(|x| x * grazing)]
            }
            DepthModel::Refracted => [
                refracted(l, sp.to_camera, n, REFRACTIVE_INDEX).unwrap_or(l),
                [0.0; 3],
            ],
        }
    }
}

impl std::str::FromStr for DepthModel {
    type Err = String;

    fn from_str(s: &str) -> Result<DepthModel, String> {
        DepthModel::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                format!("the spot depth model is laser, incidence or refracted, not {s:?}")
            })
    }
}

/// The motion per mm of depth that takes the triangulated point back to where the laser
/// entered, when the spot's light comes from a depth along the refracted beam and leaves through
/// the surface (flat near the spot, outward normal `n`, index `eta`) towards the camera: the
/// laser enters at y and refracts along T; the light from y + D·T leaves the surface at e,
/// refracted towards the camera (`c`, unit, towards it); the camera ray through e passes
/// closest to the laser line (`l`, unit, towards the laser) at the triangulated point p, and
/// y − p is D times the returned vector. `None` for a ray on the far side of the surface.
fn refracted(l: V3, c: V3, n: V3, eta: f64) -> Option<V3> {
    use crate::geometry::{add_scaled, norm};
    let (ln, cn) = (dot(l, n), dot(c, n));
    if !(ln > 0.0 && cn > 0.0) {
        return None;
    }
    let (lt, ct) = (add_scaled(l, -ln, n), add_scaled(c, -cn, n));
    let tn = (1.0 - (norm(lt) / eta).powi(2)).max(0.0).sqrt();
    let un = (1.0 - (norm(ct) / eta).powi(2)).max(0.0).sqrt();
    if un <= 1e-9 {
        return None;
    }
    // The refracted beam T (inwards) and the inside direction u of the light leaving to the
    // camera; e − y = T + (depth of T's point / u's rise)·u, tangential.
    let t = add_scaled(lt.map(|x| -x / eta), -tn, n);
    let u = add_scaled(ct.map(|x| x / eta), un, n);
    let a = add_scaled(t, tn / un, u);
    back_from(l, c, a)
}

/// The motion that takes the triangulated point back to the laser's entry point y when the
/// camera ray passes through y + `a` (`a` along the surface): the camera ray's point closest to
/// the laser line is y + a + τ·c.
fn back_from(l: V3, c: V3, a: V3) -> Option<V3> {
    let b = dot(c, l);
    let den = 1.0 - b * b;
    if den <= 1e-12 {
        return None;
    }
    let tau = (b * dot(l, a) - dot(c, a)) / den;
    let w = crate::geometry::add_scaled(a, tau, c).map(|x| -x);
    w.iter().all(|x| x.is_finite()).then_some(w)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{add_scaled, normalize};

    /// With index 1 the refracted model is the laser's: the light from a depth along the beam
    /// is seen straight through the surface, on the laser ray.
    #[test]
    fn an_index_of_one_sees_the_spot_on_the_laser_ray() {
        let n = [0.0, 0.0, 1.0];
        let l = normalize([0.3, -0.2, 0.9]).unwrap();
        let c = normalize([-0.4, 0.1, 0.8]).unwrap();
        let w = refracted(l, c, n, 1.0).unwrap();
        assert!(crate::geometry::dist(w, l) < 1e-12, "{w:?}");
        // With 1.5 the depth moves the point less along the normal (the beam is bent
        // towards the normal and the view of it lifted), and a ray from behind gives none.
        let w = refracted(l, c, n, 1.5).unwrap();
        assert!(dot(w, n) > 0.0 && dot(w, n) < dot(l, n), "{w:?}");
        assert!(refracted(add_scaled([0.0; 3], -1.0, l), c, n, 1.5).is_none());
        assert_eq!("incidence".parse::<DepthModel>(), Ok(DepthModel::Incidence));
        assert!("camera".parse::<DepthModel>().is_err());
    }
}
