//! A z-buffer rasteriser: per-vertex radiance → image, interpolated perspective-correctly.
//!
//! Hand-written (about 60 lines) because the crates that rasterise pull in a GPU stack; this one
//! needs only the OpenCV projection with distortion, applied to the vertices.

use crate::geometry::Camera;

/// A linear RGB image with a coverage mask (pixels where the object is seen).
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Row-major linear radiance per pixel.
    pub pixels: Vec<[f32; 3]>,
    /// True where a triangle covers the pixel centre.
    pub covered: Vec<bool>,
}

/// Draws the triangles `faces` of the mesh `positions` with per-vertex `values` through `camera`.
/// Triangles with a vertex behind the camera are skipped (objects sit in front of the rig's
/// cameras).
pub fn rasterise(
    camera: &Camera,
    positions: &[[f64; 3]],
    faces: &[[u32; 3]],
    values: &[[f64; 3]],
) -> Image {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut pixels = vec![[0.0f32; 3]; w * h];
    let mut covered = vec![false; w * h];
    // Depth as 1/z: larger is nearer; linear in screen space.
    let mut inv_z = vec![0.0f64; w * h];
    let proj: Vec<Option<([f64; 2], f64)>> = positions
        .iter()
        .map(|&p| {
            let c = camera.to_camera(p);
            camera.project_camera(c).map(|uv| (uv, c[2]))
        })
        .collect();
    for f in faces {
        let Some(idx) = f
            .iter()
            .map(|&i| positions.get(i as usize).map(|_| i as usize))
            .collect::<Option<Vec<_>>>()
        else {
            continue;
        };
        let (Some(a), Some(b), Some(c)) = (proj[idx[0]], proj[idx[1]], proj[idx[2]]) else {
            continue;
        };
        let (pa, pb, pc) = (a.0, b.0, c.0);
        let area = (pb[0] - pa[0]) * (pc[1] - pa[1]) - (pb[1] - pa[1]) * (pc[0] - pa[0]);
        if area.abs() < 1e-12 || !area.is_finite() {
            continue;
        }
        let minx = pa[0].min(pb[0]).min(pc[0]).ceil().max(0.0);
        let maxx = pa[0].max(pb[0]).max(pc[0]).floor().min(w as f64 - 1.0);
        let miny = pa[1].min(pb[1]).min(pc[1]).ceil().max(0.0);
        let maxy = pa[1].max(pb[1]).max(pc[1]).floor().min(h as f64 - 1.0);
        if minx > maxx || miny > maxy {
            continue;
        }
        let iz = [1.0 / a.1, 1.0 / b.1, 1.0 / c.1];
        let (va, vb, vc) = (values[idx[0]], values[idx[1]], values[idx[2]]);
        for y in miny as usize..=maxy as usize {
            for x in minx as usize..=maxx as usize {
                let p = [x as f64, y as f64];
                let edge = |s: [f64; 2], t: [f64; 2]| {
                    (t[0] - s[0]) * (p[1] - s[1]) - (t[1] - s[1]) * (p[0] - s[0])
                };
                let l0 = edge(pb, pc) / area;
                let l1 = edge(pc, pa) / area;
                let l2 = edge(pa, pb) / area;
                if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                    continue;
                }
                let z = l0 * iz[0] + l1 * iz[1] + l2 * iz[2];
                let k = y * w + x;
                if z <= inv_z[k] {
                    continue;
                }
                inv_z[k] = z;
                covered[k] = true;
                let (w0, w1, w2) = (l0 * iz[0] / z, l1 * iz[1] / z, l2 * iz[2] / z);
                for ch in 0..3 {
                    pixels[k][ch] = (w0 * va[ch] + w1 * vb[ch] + w2 * vc[ch]) as f32;
                }
            }
        }
    }
    Image {
        width: camera.width,
        height: camera.height,
        pixels,
        covered,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quad_fills_its_projection_and_the_nearer_quad_wins() {
        let cam =
            Camera::look_at_fov([0.0, 0.0, 10.0], [0.0; 3], [0.0, 1.0, 0.0], 60.0, 32, 32).unwrap();
        let mut p = Vec::new();
        let mut f = Vec::new();
        let mut v = Vec::new();
        for (z, s, val) in [(0.0, 1.0, 1.0), (1.0, 0.5, 2.0)] {
            let b = p.len() as u32;
            p.extend([[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]]);
            f.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
            v.extend([[val; 3]; 4]);
        }
        let img = rasterise(&cam, &p, &f, &v);
        let centre = 16 * 32 + 16;
        assert_eq!(
            img.pixels[centre], [2.0; 3],
            "the nearer, smaller quad covers the centre"
        );
        assert!(img.covered[centre] && !img.covered[0]);
        let n2 = img.pixels.iter().filter(|q| q[0] == 2.0).count();
        let n1 = img.pixels.iter().filter(|q| q[0] == 1.0).count();
        assert!(n1 > 0 && n2 > 0 && n1 > n2);
        // Triangles with bad indices are skipped, not a panic.
        let img = rasterise(&cam, &p, &[[0, 1, 99]], &v);
        assert!(img.covered.iter().all(|c| !c));
    }
}
