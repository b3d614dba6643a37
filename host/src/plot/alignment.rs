//! The picture of `subsurf align`: the aligned mesh with the spots on it. In the library (not the
//! command) so the command stays a thin layer of flags and printing.

use std::path::Path;

use super::PlotError;
use super::surface::{MeshView, Panel, PanelData, surface_panels};
use crate::align::Aligned;

/// The aligned mesh with the spots on it: around each spot (within two median edges) its
/// residual in pixels, and which spots were inliers and which outliers.
pub fn alignment_picture(out: &Aligned, png: &Path) -> Result<(), PlotError> {
    let mesh = &out.mesh;
    let mut edges: Vec<f64> = mesh
        .triangles
        .iter()
        .flat_map(|t| {
            [(0, 1), (1, 2), (2, 0)].map(|(a, b)| {
                crate::geometry::dist(mesh.positions[t[a] as usize], mesh.positions[t[b] as usize])
            })
        })
        .collect();
    edges.sort_by(f64::total_cmp);
    let reach = 2.0 * edges.get(edges.len() / 2).copied().unwrap_or(1.0);
    let near = out.spots_on_mesh(reach);
    let values: Vec<f64> = near
        .iter()
        .map(|s| match s {
            Some((px, true)) => *px,
            _ => f64::NAN,
        })
        .collect();
    let top = values
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
        .max(1e-3);
    let kind: Vec<usize> = near
        .iter()
        .map(|s| match s {
            Some((_, true)) => 0,
            Some((_, false)) => 1,
            None => 2,
        })
        .collect();
    let rec = &out.record;
    surface_panels(
        png,
        &format!(
            "{} aligned: {} spots, RMS {:.3} px ({:.4} mm)",
            rec.source_mesh, rec.spots, rec.rms_px, rec.rms_mm
        ),
        MeshView {
            positions: &mesh.positions,
            normals: &mesh.normals,
            faces: &mesh.triangles,
        },
        &[
            Panel {
                title: "inlier spots: distance from the surface".into(),
                data: PanelData::Scalar {
                    values,
                    range: (0.0, top),
                    label: "residual, pixels".into(),
                    missing: "no inlier spot nearby".into(),
                },
            },
            Panel {
                title: format!(
                    "spots: {} inliers (blue), {} outliers (red)",
                    rec.inliers,
                    rec.spots - rec.inliers
                ),
                data: PanelData::Categories {
                    index: kind,
                    legend: vec![
                        ("inlier".into(), [0.2, 0.6, 0.9]),
                        ("outlier".into(), [0.9, 0.25, 0.2]),
                        ("no spot nearby".into(), [0.85, 0.85, 0.85]),
                    ],
                },
            },
        ],
        crate::render::DEFAULT_VIEW,
        (420, 440),
    )
}
