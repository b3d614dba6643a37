//! Harmonic interpolation over the mesh graph, for what is missing at some vertices (section 5:
//! "vertices for which no stable fit could be achieved were filtered out and interpolated from
//! neighboring vertices"; the pipeline's failed vertices, and alpha where no frame saw a texel).
//!
//! Every unknown vertex becomes the mean of its neighbours, known vertices held fixed, solved by
//! Gauss–Seidel sweeps from a breadth-first initial guess. Vectors that hold one entry per
//! direction segment (Eq. 3) are only averaged in one frame: [`harmonic_aligned`] lets the caller
//! re-express a neighbour's vector in the frame of the vertex it is averaged into, so curves are
//! never averaged across a turn of the tangent frame.

/// Fills every `None` in `values` with the harmonic interpolation of the `Some` values over the
/// graph given by `neighbours`. Vertices not connected to any known vertex stay `None`. All known
/// vectors must have the same length.
pub fn harmonic<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32],
    sweeps: usize,
) -> Vec<Option<Vec<f64>>> {
    harmonic_aligned(values, neighbours, |_, _, _| None, sweeps)
}

/// [`harmonic`] where `align(v, w, x)` re-expresses neighbour `w`'s vector `x` for vertex `v`
/// (`None`: use it as it is). The pipeline turns a neighbour's direction segments into `v`'s
/// tangent frame with it.
pub fn harmonic_aligned<'a>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32],
    align: impl Fn(usize, usize, &[f64]) -> Option<Vec<f64>>,
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
            out[w] = mean_of(&out, w, neighbours(w), &align);
            order.push(w);
        }
        frontier = next;
    }
    for _ in 0..sweeps {
        let mut change: f64 = 0.0;
        for &v in &order {
            if let Some(m) = mean_of(&out, v, neighbours(v), &align) {
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

fn mean_of(
    vals: &[Option<Vec<f64>>],
    v: usize,
    nb: &[u32],
    align: &impl Fn(usize, usize, &[f64]) -> Option<Vec<f64>>,
) -> Option<Vec<f64>> {
    let mut acc: Option<Vec<f64>> = None;
    let mut count = 0.0;
    for &w in nb {
        if let Some(Some(x)) = vals.get(w as usize) {
            let aligned = align(v, w as usize, x);
            let x = aligned.as_deref().unwrap_or(x);
            match &mut acc {
                None => acc = Some(x.to_vec()),
                Some(a) if a.len() == x.len() => {
                    for (s, y) in a.iter_mut().zip(x) {
                        *s += y;
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
