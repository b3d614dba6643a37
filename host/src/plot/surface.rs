//! Pictures on the mesh: per-vertex quantities (parameters, errors) as colour, seen through a
//! camera, side by side with colour bars. The error maps of Figures 4/5 and the model viewer.

use std::path::Path;

use plotters::prelude::*;

use super::{PlotError, draw_err, register_font};
use crate::modelfile::{ColourMode, ModelFile, VertexStatus};
use crate::render::{Camera, rasterise};

/// Viridis, as 9 stops interpolated linearly (hand-written: a 10-line table instead of turning on
/// a plotters feature the workspace does not enable).
pub fn viridis(t: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 9] = [
        [68.0, 1.0, 84.0],
        [71.0, 44.0, 122.0],
        [59.0, 81.0, 139.0],
        [44.0, 113.0, 142.0],
        [33.0, 144.0, 141.0],
        [39.0, 173.0, 129.0],
        [92.0, 200.0, 99.0],
        [170.0, 220.0, 50.0],
        [253.0, 231.0, 37.0],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    [0, 1, 2].map(|c| (STOPS[i][c] + f * (STOPS[i + 1][c] - STOPS[i][c])).round() as u8)
}

/// What one panel shows.
#[derive(Clone, Debug)]
pub enum PanelData {
    /// One number per vertex, coloured by viridis over `range`; non-finite values are grey.
    Scalar {
        /// Per-vertex values.
        values: Vec<f64>,
        /// Colour scale `(min, max)`.
        range: (f64, f64),
        /// Colour-bar caption.
        label: String,
    },
    /// A colour per vertex, linear RGB in [0, 1] (e.g. `alpha`).
    Rgb(Vec<[f64; 3]>),
}

/// One view of the mesh in a [`surface_panels`] picture.
#[derive(Clone, Debug)]
pub struct Panel {
    /// Caption above the view.
    pub title: String,
    /// The colours.
    pub data: PanelData,
}

/// The mesh a surface picture is drawn on (object frame, mm).
#[derive(Clone, Copy, Debug)]
pub struct MeshView<'a> {
    /// Vertex positions.
    pub positions: &'a [[f64; 3]],
    /// Unit vertex normals.
    pub normals: &'a [[f64; 3]],
    /// Triangles.
    pub faces: &'a [[u32; 3]],
}

/// Draws the mesh once per panel, side by side, seen from `direction` (from the object towards
/// the eye), lightly shaded so the shape reads, with a colour bar under each scalar panel.
/// `panel_size` is the size of one panel in pixels.
pub fn surface_panels(
    path: &Path,
    title: &str,
    mesh: MeshView<'_>,
    panels: &[Panel],
    direction: [f64; 3],
    panel_size: (u32, u32),
) -> Result<(), PlotError> {
    register_font();
    let MeshView {
        positions,
        normals,
        faces,
    } = mesh;
    if positions.is_empty() || faces.is_empty() || panels.is_empty() {
        return Err(PlotError::Empty(
            "a surface picture needs vertices, faces and a panel".into(),
        ));
    }
    let (pw, ph) = (panel_size.0.max(64), panel_size.1.max(96));
    let (title_h, bar_h) = (if title.is_empty() { 0 } else { 34 }, 64u32);
    let view_h = ph - 30 - bar_h;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for q in positions {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    let cam = Camera::framing(lo, hi, direction, pw, view_h)?;
    let eye = cam.center();
    let shade: Vec<f64> = positions
        .iter()
        .zip(normals)
        .map(|(x, n)| {
            let d = [eye[0] - x[0], eye[1] - x[1], eye[2] - x[2]];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
            let c = ((n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / l).abs();
            0.55 + 0.45 * c
        })
        .collect();
    let n = panels.len() as u32;
    let e = draw_err(path);
    let root = BitMapBackend::new(path, (pw * n, ph + title_h)).into_drawing_area();
    root.fill(&WHITE).map_err(&e)?;
    if title_h > 0 {
        root.draw(&Text::new(
            title.to_string(),
            (10, 6),
            ("sans-serif", 22).into_font().color(&BLACK),
        ))
        .map_err(&e)?;
    }
    for (k, panel) in panels.iter().enumerate() {
        let x0 = k as u32 * pw;
        let y0 = title_h;
        let colours: Vec<[f64; 3]> = match &panel.data {
            PanelData::Rgb(c) => c
                .iter()
                .map(|c| {
                    c.map(|v| {
                        if v.is_finite() {
                            v.clamp(0.0, 1.0)
                        } else {
                            0.5
                        }
                    })
                })
                .collect(),
            PanelData::Scalar { values, range, .. } => values
                .iter()
                .map(|&v| {
                    if v.is_finite() {
                        let t = (v - range.0) / (range.1 - range.0).max(1e-300);
                        viridis(t).map(|c| c as f64 / 255.0)
                    } else {
                        [0.6, 0.6, 0.6]
                    }
                })
                .collect(),
        };
        if colours.len() != positions.len() {
            return Err(PlotError::Empty(format!(
                "panel `{}` has {} values for {} vertices",
                panel.title,
                colours.len(),
                positions.len()
            )));
        }
        let shaded: Vec<[f64; 3]> = colours
            .iter()
            .zip(&shade)
            .map(|(c, s)| c.map(|v| v * s))
            .collect();
        let img = rasterise(&cam, positions, faces, &shaded);
        root.draw(&Text::new(
            panel.title.clone(),
            (x0 as i32 + 8, y0 as i32 + 6),
            ("sans-serif", 16).into_font().color(&BLACK),
        ))
        .map_err(&e)?;
        for yy in 0..view_h {
            for xx in 0..pw {
                let i = (yy * pw + xx) as usize;
                if img.covered[i] {
                    let p = img.pixels[i];
                    let c = RGBColor(
                        (p[0].clamp(0.0, 1.0) * 255.0) as u8,
                        (p[1].clamp(0.0, 1.0) * 255.0) as u8,
                        (p[2].clamp(0.0, 1.0) * 255.0) as u8,
                    );
                    root.draw_pixel(((x0 + xx) as i32, (y0 + 30 + yy) as i32), &c)
                        .map_err(&e)?;
                }
            }
        }
        if let PanelData::Scalar { range, label, .. } = &panel.data {
            let by = (y0 + 30 + view_h + 8) as i32;
            let (bx0, bx1) = (x0 as i32 + 16, (x0 + pw) as i32 - 16);
            let width = (bx1 - bx0).max(1);
            for dx in 0..width {
                let c = viridis(dx as f64 / width as f64);
                root.draw(&Rectangle::new(
                    [(bx0 + dx, by), (bx0 + dx + 1, by + 14)],
                    RGBColor(c[0], c[1], c[2]).filled(),
                ))
                .map_err(&e)?;
            }
            let font = ("sans-serif", 13).into_font().color(&BLACK);
            root.draw(&Text::new(
                format!("{:.3}", range.0),
                (bx0, by + 18),
                font.clone(),
            ))
            .map_err(&e)?;
            let right = format!("{:.3}", range.1);
            root.draw(&Text::new(
                right.clone(),
                (bx1 - 7 * right.len() as i32, by + 18),
                font.clone(),
            ))
            .map_err(&e)?;
            root.draw(&Text::new(label.clone(), (bx0, by + 36), font))
                .map_err(&e)?;
        }
    }
    root.present().map_err(&e)?;
    Ok(())
}

/// The model viewer: `alpha(x_o)` as colour, the total diffuse reflectance `∫R_d 2πr dr` of each
/// `x_i` (green channel, Eq. 9) and its reach `1/|d_slowest|` (mm) on the mesh, plus which
/// vertices were fitted, interpolated or have no model.
pub fn model_viewer(
    path: &Path,
    model: &ModelFile,
    direction: [f64; 3],
    panel_size: (u32, u32),
) -> Result<(), PlotError> {
    crate::render::validate(model)?;
    let falloffs = crate::render::Falloffs::new(model);
    let total: Vec<f64> = (0..model.len())
        .map(|v| {
            if model.vertices[v].status == VertexStatus::NoModel {
                f64::NAN
            } else {
                falloffs.disk_integral(v, f64::INFINITY)[1]
            }
        })
        .collect();
    let reach: Vec<f64> = (0..model.len())
        .map(|v| {
            if model.vertices[v].status == VertexStatus::NoModel {
                return f64::NAN;
            }
            let p = &model.vertices[v].params[..];
            let terms = match model.shape.colour {
                ColourMode::Shared => p.get(2..).unwrap_or(&[]),
                ColourMode::PerChannel => p,
            };
            terms
                .chunks_exact(2)
                .map(|cd| -1.0 / cd[1])
                .fold(0.0, f64::max)
        })
        .collect();
    let range = |v: &[f64]| {
        let mut f: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        f.sort_by(f64::total_cmp);
        if f.is_empty() {
            return (0.0, 1.0);
        }
        let lo = f[f.len() / 50];
        let hi = f[(f.len() - 1) - f.len() / 50];
        if hi > lo {
            (lo, hi)
        } else {
            (lo - 0.5, lo + 0.5)
        }
    };
    let alpha: Vec<[f64; 3]> = model
        .vertices
        .iter()
        .map(|v| v.alpha.map(f64::from))
        .collect();
    let amax = alpha
        .iter()
        .flat_map(|a| a.iter())
        .fold(0.0f64, |m, &x| m.max(x))
        .max(1e-12);
    let status: Vec<f64> = model
        .vertices
        .iter()
        .map(|v| match v.status {
            VertexStatus::Fitted => 0.0,
            VertexStatus::Interpolated => 1.0,
            VertexStatus::NoModel => 2.0,
        })
        .collect();
    let panels = vec![
        Panel {
            title: "alpha(x_o), Eq. 6".into(),
            data: PanelData::Rgb(alpha.iter().map(|a| a.map(|x| x / amax)).collect()),
        },
        Panel {
            title: "total diffuse reflectance (G)".into(),
            data: PanelData::Scalar {
                range: range(&total),
                values: total,
                label: "∫ R_d 2πr dr".into(),
            },
        },
        Panel {
            title: "reach 1/|d| of slowest term".into(),
            data: PanelData::Scalar {
                range: range(&reach),
                values: reach,
                label: "mm".into(),
            },
        },
        Panel {
            title: "status".into(),
            data: PanelData::Scalar {
                values: status,
                range: (0.0, 2.0),
                label: "0 fitted, 1 interpolated, 2 none".into(),
            },
        },
    ];
    surface_panels(
        path,
        "subsurf model",
        MeshView {
            positions: &model.positions,
            normals: &model.normals,
            faces: &model.triangles,
        },
        &panels,
        direction,
        panel_size,
    )
}
