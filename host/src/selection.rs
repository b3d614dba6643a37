//! Selection (section 5): "we select for each vertex in the mesh the closest light position x_i".
//! A vertex whose closest x_i is farther than a limit has no data (it is interpolated later).
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
}
