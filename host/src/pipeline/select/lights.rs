//! Light positions, the algorithm of stage `select` (section 5): "we select for each vertex in the mesh the closest light position x_i".
//! A vertex whose closest x_i is farther than a limit has no data (it is interpolated later).
//!
//! A light position is every frame that lit (nearly) the same point: "data is then collected from
//! all images in which a particular location on the object was illuminated yielding an incident
//! light position x_i" (section 5). [`pool`] joins the frames whose x_i agree within a
//! tolerance (other turntable angles, other cameras, other colour channels of the same spot).
use crate::geometry::{V3, dist};

/// One registered light position and the colour channels its frame measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Frame index in the dataset.
    pub frame: usize,
    /// The light position x_i (object frame).
    pub x_i: V3,
    /// Bit c set = the frame measured channel c.
    pub channels: u8,
}

/// One light position x_i: the frames whose x_i agree within the pooling tolerance.
#[derive(Debug, Clone, PartialEq)]
pub struct PooledLight {
    /// Indices into the pooled `lights`, in input order.
    pub members: Vec<u32>,
    /// The light position: the mean of the members' x_i.
    pub x_i: V3,
    /// Bit c set = some member measured channel c.
    pub channels: u8,
    /// The member whose x_i is closest to the mean (its triangle and normal stand for the light
    /// position's tangent frame).
    pub anchor: u32,
}

/// Pools `lights` into light positions: in input order, a light joins the light position whose
/// first member's x_i is closest to its own and within `tolerance_mm`, or starts a new one. Every
/// member lies within `tolerance_mm` of its light position's first member, so a light position
/// spans at most twice the tolerance, whatever order the frames come in. `tolerance_mm <= 0`
/// pools only identical x_i.
///
/// Greedy rather than single-linkage clustering: a chain of lights each close to the next
/// (a laser swept in small steps) must not become one light position spanning the whole sweep.
pub fn pool(lights: &[Light], tolerance_mm: f64) -> Vec<PooledLight> {
    let tol = if tolerance_mm.is_finite() {
        tolerance_mm.max(0.0)
    } else {
        0.0
    };
    let mut out: Vec<PooledLight> = Vec::new();
    for (k, l) in lights.iter().enumerate() {
        let best = out
            .iter()
            .enumerate()
            .map(|(i, p)| (i, dist(lights[p.members[0] as usize].x_i, l.x_i)))
            .filter(|(_, d)| *d <= tol)
            .min_by(|a, b| a.1.total_cmp(&b.1));
        match best {
            Some((i, _)) => {
                out[i].members.push(k as u32);
                out[i].channels |= l.channels;
            }
            None => out.push(PooledLight {
                members: vec![k as u32],
                x_i: l.x_i,
                channels: l.channels,
                anchor: k as u32,
            }),
        }
    }
    for p in &mut out {
        let n = p.members.len() as f64;
        let mut c = [0.0; 3];
        for &m in &p.members {
            for (a, b) in c.iter_mut().zip(lights[m as usize].x_i) {
                *a += b / n;
            }
        }
        p.x_i = c;
        p.anchor = p
            .members
            .iter()
            .copied()
            .min_by(|a, b| {
                dist(lights[*a as usize].x_i, c).total_cmp(&dist(lights[*b as usize].x_i, c))
            })
            .unwrap_or(p.members[0]);
    }
    out
}

/// For every vertex and channel, the index (into `lights`) of the closest light measuring that
/// channel within `max_distance_mm`, or `None`.
///
/// Brute force over all pairs, parallel over vertices: 20,000 vertices × 5,000 lights is 10⁸
/// distance evaluations, well under a second, so a spatial index would not pay for itself.
pub fn select(positions: &[V3], lights: &[Light], max_distance_mm: f64) -> Vec<[Option<u32>; 3]> {
    use rayon::prelude::*;
    positions
        .par_iter()
        .map(|p| {
            let mut best = [(f64::INFINITY, None); 3];
            for (k, l) in lights.iter().enumerate() {
                let d = dist(*p, l.x_i);
                for (c, b) in best.iter_mut().enumerate() {
                    if l.channels & (1 << c) != 0 && d < b.0 {
                        *b = (d, Some(k as u32));
                    }
                }
            }
            best.map(|(d, k)| if d <= max_distance_mm { k } else { None })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closest_light_per_channel_within_the_limit() {
        let lights = [
            Light {
                frame: 0,
                x_i: [0.0, 0.0, 0.0],
                channels: 0b111,
            },
            Light {
                frame: 5,
                x_i: [1.0, 0.0, 0.0],
                channels: 0b010,
            },
        ];
        let sel = select(&[[0.9, 0.0, 0.0], [10.0, 0.0, 0.0]], &lights, 2.0);
        assert_eq!(sel[0], [Some(0), Some(1), Some(0)]);
        assert_eq!(sel[1], [None, None, None]);
    }

    fn light(frame: usize, x: f64, channels: u8) -> Light {
        Light {
            frame,
            x_i: [x, 0.0, 0.0],
            channels,
        }
    }

    /// Lights within the tolerance of a light position's first member join it (channels
    /// united, x_i their mean); a chain of lights each within the tolerance of the next does not
    /// grow one light position beyond it.
    #[test]
    fn pooling_joins_nearby_lights_without_chaining() {
        let lights = [
            light(0, 0.0, 0b001),
            light(1, 10.0, 0b111),
            light(2, 0.2, 0b010),
            light(3, 0.4, 0b100),
            light(4, 0.6, 0b001),
            light(5, 10.1, 0b111),
        ];
        let p = pool(&lights, 0.45);
        assert_eq!(p.len(), 3);
        assert_eq!(p[0].members, vec![0, 2, 3]);
        assert_eq!(p[0].channels, 0b111);
        assert!((p[0].x_i[0] - 0.2).abs() < 1e-12);
        assert_eq!(p[0].anchor, 2);
        assert_eq!(p[1].members, vec![1, 5]);
        // 0.6 is within 0.45 of 0.4 but not of the light position's first member at 0.
        assert_eq!(p[2].members, vec![4]);
        // No tolerance: every light is its own light position.
        assert_eq!(pool(&lights, 0.0).len(), lights.len());
        assert_eq!(pool(&lights, f64::NAN).len(), lights.len());
    }
}
