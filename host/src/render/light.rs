//! Light sources: point, spot and directional, several at once.

use super::RenderError;

/// A light illuminating the object, in the object frame (mm). Colours are linear RGB.
#[derive(Clone, Debug, PartialEq)]
pub enum Light {
    /// Isotropic point light: irradiance `I cos θ / d²`.
    Point {
        /// Position, mm.
        position: [f64; 3],
        /// Radiant intensity per channel.
        intensity: [f64; 3],
    },
    /// Spot light: a point light restricted to a cone, with a smooth edge between the inner and
    /// outer half-angles.
    Spot {
        /// Position, mm.
        position: [f64; 3],
        /// Unit axis of the cone (the direction light travels).
        direction: [f64; 3],
        /// Half-angle of full intensity, radians.
        inner: f64,
        /// Half-angle beyond which there is no light, radians.
        outer: f64,
        /// Radiant intensity per channel on the axis.
        intensity: [f64; 3],
    },
    /// Distant light: parallel rays, irradiance `E cos θ`.
    Directional {
        /// Unit direction the light travels.
        direction: [f64; 3],
        /// Irradiance per channel on a surface facing the light.
        irradiance: [f64; 3],
    },
}

fn parse_vec3(spec: &str, part: &str) -> Result<[f64; 3], RenderError> {
    let bad = |reason: String| RenderError::Light {
        spec: spec.to_string(),
        reason,
    };
    let v: Vec<f64> = part
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| bad(format!("`{part}` is not three numbers: {e}")))?;
    let [a, b, c] = v[..] else {
        return Err(bad(format!(
            "`{part}` is not three comma-separated numbers"
        )));
    };
    if !(a.is_finite() && b.is_finite() && c.is_finite()) {
        return Err(bad(format!("`{part}` is not finite")));
    }
    Ok([a, b, c])
}

fn unit(spec: &str, v: [f64; 3]) -> Result<[f64; 3], RenderError> {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if l.is_nan() || l <= 0.0 || !l.is_finite() {
        return Err(RenderError::Light {
            spec: spec.to_string(),
            reason: "direction has zero length".into(),
        });
    }
    Ok([v[0] / l, v[1] / l, v[2] / l])
}

impl std::str::FromStr for Light {
    type Err = RenderError;

    /// `point:X,Y,Z[:R,G,B]`, `spot:X,Y,Z:DX,DY,DZ:ANGLE_DEG[:R,G,B]` (the edge softens over the
    /// outer 20% of the angle) or `dir:DX,DY,DZ[:R,G,B]` (the direction light travels). Colour
    /// defaults to white 1.
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let bad = |reason: &str| RenderError::Light {
            spec: spec.to_string(),
            reason: reason.into(),
        };
        let parts: Vec<&str> = spec.split(':').collect();
        let colour = |i: usize| -> Result<[f64; 3], RenderError> {
            match parts.get(i) {
                None => Ok([1.0; 3]),
                Some(p) => {
                    let c = parse_vec3(spec, p)?;
                    if c.iter().any(|&x| x < 0.0) {
                        return Err(bad("colour must not be negative"));
                    }
                    Ok(c)
                }
            }
        };
        match parts[0] {
            "point" if (2..=3).contains(&parts.len()) => Ok(Light::Point {
                position: parse_vec3(spec, parts[1])?,
                intensity: colour(2)?,
            }),
            "spot" if (4..=5).contains(&parts.len()) => {
                let angle: f64 = parts[3]
                    .trim()
                    .parse()
                    .map_err(|_| bad("cone angle is not a number"))?;
                if !(angle > 0.0 && angle < 90.0) {
                    return Err(bad("cone half-angle must be in (0, 90) degrees"));
                }
                let outer = angle.to_radians();
                Ok(Light::Spot {
                    position: parse_vec3(spec, parts[1])?,
                    direction: unit(spec, parse_vec3(spec, parts[2])?)?,
                    inner: 0.8 * outer,
                    outer,
                    intensity: colour(4)?,
                })
            }
            "dir" | "directional" if (2..=3).contains(&parts.len()) => Ok(Light::Directional {
                direction: unit(spec, parse_vec3(spec, parts[1])?)?,
                irradiance: colour(2)?,
            }),
            _ => Err(bad(
                "expected point:X,Y,Z[:R,G,B], spot:X,Y,Z:DX,DY,DZ:DEG[:R,G,B] or dir:DX,DY,DZ[:R,G,B]",
            )),
        }
    }
}

/// What a light delivers at a point: unit direction towards the light, distance to it (infinite
/// for directional light), and irradiance per channel on a surface facing it.
pub(crate) struct Incidence {
    pub to_light: [f64; 3],
    pub distance: f64,
    pub irradiance: [f64; 3],
}

impl Light {
    /// The default lighting of a render of an object with bounding box `(lo, hi)`: a warm key
    /// light above front-left and a dim cool fill from the right, placed relative to the
    /// object's size (irradiance about 1 at the object). `subsurf render` without `--light`,
    /// the demo and `bench tradeoff` light with it.
    pub fn defaults_for((lo, hi): ([f64; 3], [f64; 3])) -> Vec<Light> {
        let c = [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k]));
        let r = (0..3)
            .map(|k| (hi[k] - lo[k]).powi(2))
            .sum::<f64>()
            .sqrt()
            .max(1e-3);
        let d = 3.0 * r;
        let i = d * d; // irradiance ≈ 1 at the object
        vec![
            Light::Point {
                position: [c[0] - 0.6 * d, c[1] - 0.7 * d, c[2] + 0.8 * d],
                intensity: [i, 0.95 * i, 0.85 * i],
            },
            Light::Directional {
                direction: [-0.8, 0.3, -0.5],
                irradiance: [0.15, 0.17, 0.2],
            },
        ]
    }

    pub(crate) fn incidence(&self, x: [f64; 3]) -> Option<Incidence> {
        let towards = |p: [f64; 3]| {
            let v = [p[0] - x[0], p[1] - x[1], p[2] - x[2]];
            let d = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            (v, d)
        };
        match *self {
            Light::Point {
                position,
                intensity,
            } => {
                let (v, d) = towards(position);
                if d.is_nan() || d <= 0.0 {
                    return None;
                }
                let k = 1.0 / (d * d);
                Some(Incidence {
                    to_light: [v[0] / d, v[1] / d, v[2] / d],
                    distance: d,
                    irradiance: intensity.map(|i| i * k),
                })
            }
            Light::Spot {
                position,
                direction,
                inner,
                outer,
                intensity,
            } => {
                let (v, d) = towards(position);
                if d.is_nan() || d <= 0.0 {
                    return None;
                }
                let l = [v[0] / d, v[1] / d, v[2] / d];
                let cos_axis = -(l[0] * direction[0] + l[1] * direction[1] + l[2] * direction[2]);
                let angle = cos_axis.clamp(-1.0, 1.0).acos();
                if angle >= outer {
                    return None;
                }
                let edge = if angle <= inner {
                    1.0
                } else {
                    let t = (outer - angle) / (outer - inner);
                    t * t * (3.0 - 2.0 * t)
                };
                let k = edge / (d * d);
                Some(Incidence {
                    to_light: l,
                    distance: d,
                    irradiance: intensity.map(|i| i * k),
                })
            }
            Light::Directional {
                direction,
                irradiance,
            } => Some(Incidence {
                to_light: direction.map(|c| -c),
                distance: f64::INFINITY,
                irradiance,
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_and_bad_specs_say_why() {
        let l: Light = "point:0,0,100:2,2,2".parse().unwrap();
        assert_eq!(
            l,
            Light::Point {
                position: [0.0, 0.0, 100.0],
                intensity: [2.0; 3]
            }
        );
        let l: Light = "dir:0,0,-2".parse().unwrap();
        assert!(matches!(
            l,
            Light::Directional {
                direction: [0.0, 0.0, -1.0],
                ..
            }
        ));
        let l: Light = "spot:0,0,100:0,0,-1:30:1,0.5,0.2".parse().unwrap();
        assert!(matches!(
            l,
            Light::Spot {
                intensity: [1.0, 0.5, 0.2],
                ..
            }
        ));
        for bad in [
            "",
            "point",
            "point:1,2",
            "dir:0,0,0",
            "spot:0,0,1:0,0,-1:120",
            "lamp:1,2,3",
            "point:1,2,nan",
        ] {
            assert!(bad.parse::<Light>().is_err(), "{bad}");
        }
    }

    #[test]
    fn point_light_follows_the_inverse_square_law_and_spots_have_a_cone() {
        let l: Light = "point:0,0,10".parse().unwrap();
        let a = l.incidence([0.0; 3]).unwrap();
        assert!((a.irradiance[0] - 0.01).abs() < 1e-15 && (a.distance - 10.0).abs() < 1e-12);
        let s: Light = "spot:0,0,10:0,0,-1:10".parse().unwrap();
        assert!(s.incidence([0.0; 3]).is_some());
        assert!(s.incidence([10.0, 0.0, 0.0]).is_none());
    }
}
