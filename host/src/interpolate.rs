//! Interpolation of failed vertices from their mesh neighbours (section 5: "vertices for which no
//! stable fit could be achieved were filtered out and interpolated from neighboring vertices").
//!
//! Harmonic interpolation over the mesh graph: every unknown vertex becomes the mean of its
//! neighbours, with fitted vertices held fixed, solved by Gauss–Seidel sweeps from a
//! breadth-first initial guess. Parameters are interpolated in log space (ln c, ln −d, ln s), so
//! the result always satisfies c > 0, d < 0, s > 0.
use crate::modelfile::{ColourMode, ModelShape};

/// Maps a vertex's parameters to log space (see the module doc).
pub fn to_log(shape: &ModelShape, params: &[f64]) -> Vec<f64> {
    let skip = if shape.colour == ColourMode::Shared {
        2
    } else {
        0
    };
    params
        .iter()
        .enumerate()
        .map(|(k, &p)| {
            if k < skip || (k - skip) % 2 == 0 {
                p.ln()
            } else {
                (-p).ln()
            }
        })
        .collect()
}

/// Inverse of [`to_log`].
pub fn from_log(shape: &ModelShape, logs: &[f64]) -> Vec<f64> {
    let skip = if shape.colour == ColourMode::Shared {
        2
    } else {
        0
    };
    logs.iter()
        .enumerate()
        .map(|(k, &l)| {
            if k < skip || (k - skip) % 2 == 0 {
                l.exp()
            } else {
                -l.exp()
            }
        })
        .collect()
}

/// Fills every `None` in `values` with the harmonic interpolation of the `Some` values over the
/// graph given by `neighbours`. Vertices not connected to any known vertex stay `None`. All known
/// vectors must have the same length.
pub fn harmonic<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32],
    sweeps: usize,
) -> Vec<Option<Vec<f64>>> {
    let n = values.len();
    let mut out: Vec<Option<Vec<f64>>> = values.to_vec();
    let fixed: Vec<bool> = values.iter().map(Option::is_some).collect();
    // Breadth-first initial guess: each unknown vertex, in order of distance from the known set,
    // takes the mean of its already-assigned neighbours.
    let mut frontier: Vec<usize> = (0..n).filter(|&v| fixed[v]).collect();
    let mut assigned = fixed.clone();
    let mut order = Vec::new();
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
            out[w] = mean_of(&out, neighbours(w));
            order.push(w);
        }
        frontier = next;
    }
    for _ in 0..sweeps {
        let mut change: f64 = 0.0;
        for &v in &order {
            if let Some(m) = mean_of(&out, neighbours(v)) {
                if let Some(old) = &out[v] {
                    for (a, b) in old.iter().zip(&m) {
                        change = change.max((a - b).abs());
                    }
                }
                out[v] = Some(m);
            }
        }
        if change < 1e-12 {
            break;
        }
    }
    out
}

fn mean_of(vals: &[Option<Vec<f64>>], nb: &[u32]) -> Option<Vec<f64>> {
    let mut acc: Option<Vec<f64>> = None;
    let mut count = 0.0;
    for &w in nb {
        if let Some(Some(v)) = vals.get(w as usize) {
            match &mut acc {
                None => acc = Some(v.clone()),
                Some(a) if a.len() == v.len() => {
                    for (x, y) in a.iter_mut().zip(v) {
                        *x += y;
                    }
                }
                Some(_) => continue,
            }
            count += 1.0;
        }
    }
    acc.map(|a| a.into_iter().map(|x| x / count).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn log_space_round_trips_and_keeps_signs() {
        let shape = ModelShape {
            terms: 2,
            segments: 1,
            colour: ColourMode::Shared,
        };
        let p = vec![0.8, 0.5, 2.0, -3.0, 0.1, -0.2];
        let l = to_log(&shape, &p);
        let back = from_log(&shape, &l);
        for (a, b) in p.iter().zip(&back) {
            assert!((a - b).abs() < 1e-12);
        }
    }
}
