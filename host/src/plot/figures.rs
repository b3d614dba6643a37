//! The paper's figures as one call each: Figure 3 (fall-off of one `x_i` with the exponential
//! and dipole fits) and Figures 4/5 (per-`x_i` error maps over the surface). Figures draw what
//! they are given: the fits come from [`crate::evaluate::compare_falloff`], never from here.

use std::path::Path;

use super::surface::{MeshView, Panel, PanelData, surface_panels};
use super::{Curve, PlotError, falloff_plot};
use crate::evaluate::FalloffComparison;
use crate::modelfile::ModelFile;

/// What Figure 3 showed: both fits' log E (Eq. 8) on the plotted samples.
#[derive(Clone, Debug, PartialEq)]
pub struct FalloffSummary {
    /// Samples plotted.
    pub samples: usize,
    /// log E of the sum of exponentials (Eq. 1), if it could be fitted.
    pub expsum_log_e: Option<f64>,
    /// log E of the dipole, if it could be fitted.
    pub dipole_log_e: Option<f64>,
}

/// Figure 3: the samples `(r, s)` of one lit point and both fits to them (the sum of
/// exponentials and the dipole, see [`crate::evaluate::compare_falloff`]) on a log scale. A fit
/// that failed is left out of the picture (and reported as `None`), not an error.
pub fn falloff_figure(
    path: &Path,
    title: &str,
    r: &[f64],
    s: &[f64],
    fits: &FalloffComparison,
) -> Result<FalloffSummary, PlotError> {
    let rmax = r
        .iter()
        .copied()
        .filter(|x| x.is_finite())
        .fold(0.0, f64::max);
    let grid: Vec<f64> = (0..200).map(|k| rmax * k as f64 / 199.0).collect();
    let mut curves = Vec::new();
    let (expsum, dipole) = (&fits.expsum, &fits.dipole);
    if let Some(f) = expsum {
        curves.push(Curve {
            name: format!(
                "sum of exponentials, n = {} (log E {:.3})",
                f.model.n(),
                f.log_e
            ),
            points: grid.iter().map(|&x| (x, f.model.eval(x))).collect(),
        });
    }
    if let Some(f) = dipole {
        curves.push(Curve {
            name: format!("dipole (log E {:.3})", f.log_e),
            points: grid
                .iter()
                .map(|&x| (x, f.scale * f.dipole.r_d(x)))
                .collect(),
        });
    }
    let pts: Vec<(f64, f64)> = r.iter().copied().zip(s.iter().copied()).collect();
    falloff_plot(path, title, &pts, &curves, (800, 520))?;
    Ok(FalloffSummary {
        samples: pts.len(),
        expsum_log_e: expsum.as_ref().map(|f| f.log_e),
        dipole_log_e: dipole.as_ref().map(|f| f.log_e),
    })
}

/// The error map's title: the log E stored per vertex is measured on the samples the fit used,
/// so it is in-sample (optimistic); `subsurf evaluate` judges held-out frames.
pub const ERROR_MAP_TITLE: &str =
    "In-sample reconstruction error per x_i (on the fit's own frames)";

/// Figures 4/5: `log E(x_i)` (Eq. 8, stored per vertex in the model file) over the surface, one
/// panel per model (e.g. isotropic against anisotropic) on one colour scale. The models must share
/// the mesh. Vertices without a fit are grey.
pub fn error_maps(
    path: &Path,
    models: &[(String, &ModelFile)],
    direction: [f64; 3],
    panel_size: (u32, u32),
) -> Result<(), PlotError> {
    let Some((_, first)) = models.first() else {
        return Err(PlotError::Empty("no model".into()));
    };
    let log_e =
        |m: &ModelFile| -> Vec<f64> { m.vertices.iter().map(|v| f64::from(v.log_e)).collect() };
    let mut all: Vec<f64> = models
        .iter()
        .flat_map(|(_, m)| log_e(m))
        .filter(|v| v.is_finite())
        .collect();
    if all.is_empty() {
        return Err(PlotError::Empty("no vertex has a log E".into()));
    }
    all.sort_by(f64::total_cmp);
    let lo = all[all.len() / 100];
    let hi = all[all.len() - 1 - all.len() / 100].max(lo + 1e-9);
    let mut panels = Vec::new();
    for (name, m) in models {
        if m.len() != first.len() {
            return Err(PlotError::Empty(format!(
                "model `{name}` has a different mesh"
            )));
        }
        let values = log_e(m);
        let fitted = values.iter().filter(|v| v.is_finite()).collect::<Vec<_>>();
        let mean = fitted.iter().copied().sum::<f64>() / fitted.len().max(1) as f64;
        panels.push(Panel {
            title: format!("{name}: mean log E {mean:.4}"),
            data: PanelData::Scalar {
                values,
                range: (lo, hi),
                label: "log E(x_i), Eq. 8".into(),
                missing: "no fit (no log E)".into(),
            },
        });
    }
    let mesh = MeshView {
        positions: &first.positions,
        normals: &first.normals,
        faces: &first.triangles,
    };
    surface_panels(path, ERROR_MAP_TITLE, mesh, &panels, direction, panel_size)
}
