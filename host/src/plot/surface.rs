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
    /// One number per vertex, coloured by viridis over `range`; non-finite values are grey,
    /// which the legend names `missing` (shown when any value is missing).
    Scalar {
        /// Per-vertex values.
        values: Vec<f64>,
        /// Colour scale `(min, max)`.
        range: (f64, f64),
        /// Colour-bar caption.
        label: String,
        /// What a grey vertex means (e.g. `no fit`).
        missing: String,
    },
    /// A colour per vertex, linear RGB in [0, 1], with no legend (e.g. a material's colour).
    Rgb(Vec<[f64; 3]>),
    /// Three numbers per vertex shown as a colour, each channel `value / max` (e.g. alpha's R, G,
    /// B), with a scale: a black-to-white ramp from 0 to `max`, so a grey level reads as a value.
    Shades {
        /// Per-vertex values, one per channel.
        values: Vec<[f64; 3]>,
        /// The value shown as full intensity.
        max: f64,
        /// Scale caption.
        label: String,
    },
    /// One of a few categories per vertex, with a legend of swatches (a categorical quantity on a
    /// continuous colour bar reads as if it had values in between). An index past `legend` is grey.
    Categories {
        /// Per-vertex category, an index into `legend`.
        index: Vec<usize>,
        /// Per category: its name and colour (linear RGB in [0, 1]).
        legend: Vec<(String, [f64; 3])>,
    },
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

/// Grey of a vertex without a value.
const MISSING: [f64; 3] = [0.6, 0.6, 0.6];
/// Height of a panel's legend (colour bar, numbers, caption, the grey's swatch), pixels.
const LEGEND_H: u32 = 82;
/// Height of a panel's title row, pixels.
const PANEL_TITLE_H: u32 = 30;

/// The two directions a surface picture shows: `direction` and the opposite side, turned 180°
/// about the turntable axis (`z`) so the elevation stays and the far side is seen.
pub fn front_and_back(direction: [f64; 3]) -> [[f64; 3]; 2] {
    [direction, [-direction[0], -direction[1], direction[2]]]
}

/// Size in pixels of a [`surface_panels`] picture of `panels` panels, `panel_size` each, with
/// or without a title: per panel its title, the two views one above the other, its legend.
pub fn surface_picture_size(panels: u32, panel_size: (u32, u32), title: bool) -> (u32, u32) {
    let (pw, ph) = (
        panel_size.0.max(64),
        panel_size.1.max(PANEL_TITLE_H + LEGEND_H + 32),
    );
    let view_h = ph - PANEL_TITLE_H - LEGEND_H;
    (
        pw * panels,
        if title { 34 } else { 0 } + PANEL_TITLE_H + 2 * view_h + LEGEND_H,
    )
}

/// Draws the mesh once per panel, side by side, each seen from `direction` (from the object
/// towards the eye) and, below, from the opposite side ([`front_and_back`]: one view never
/// shows the far side of an object), lightly shaded so the shape reads, with each panel's
/// legend under it. `panel_size` is one panel with one view, in pixels
/// ([`surface_picture_size`] gives the picture's).
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
    let n = panels.len() as u32;
    let (width, height) = surface_picture_size(n, panel_size, !title.is_empty());
    let pw = width / n;
    let title_h = if title.is_empty() { 0 } else { 34 };
    let view_h = (height - title_h - PANEL_TITLE_H - LEGEND_H) / 2;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for q in positions {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    let mut views = Vec::with_capacity(2);
    for (d, name) in front_and_back(direction)
        .into_iter()
        .zip(["front", "back (turned 180°)"])
    {
        let cam = Camera::framing(lo, hi, d, pw, view_h)?;
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
        views.push((cam, shade, name));
    }
    let e = draw_err(path);
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(&e)?;
    if title_h > 0 {
        // As large as fits the picture's width, down to 12 px.
        let mut size = 22.0;
        while size > 12.0
            && root
                .estimate_text_size(title, &("sans-serif", size).into_font().color(&BLACK))
                .map_err(&e)?
                .0
                + 20
                > width
        {
            size -= 1.0;
        }
        root.draw(&Text::new(
            title.to_string(),
            (10, 6),
            ("sans-serif", size).into_font().color(&BLACK),
        ))
        .map_err(&e)?;
    }
    let small = ("sans-serif", 12).into_font().color(&RGBColor(90, 90, 90));
    for (k, panel) in panels.iter().enumerate() {
        let x0 = k as u32 * pw;
        let y0 = title_h;
        let colours = panel_colours(&panel.data);
        if colours.len() != positions.len() {
            return Err(PlotError::Empty(format!(
                "panel `{}` has {} values for {} vertices",
                panel.title,
                colours.len(),
                positions.len()
            )));
        }
        root.draw(&Text::new(
            panel.title.clone(),
            (x0 as i32 + 8, y0 as i32 + 6),
            ("sans-serif", 16).into_font().color(&BLACK),
        ))
        .map_err(&e)?;
        for (row, (cam, shade, name)) in views.iter().enumerate() {
            let shaded: Vec<[f64; 3]> = colours
                .iter()
                .zip(shade)
                .map(|(c, s)| c.map(|v| v * s))
                .collect();
            let img = rasterise(cam, positions, faces, &shaded);
            let top = y0 + PANEL_TITLE_H + row as u32 * view_h;
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
                        root.draw_pixel(((x0 + xx) as i32, (top + yy) as i32), &c)
                            .map_err(&e)?;
                    }
                }
            }
            root.draw(&Text::new(
                name.to_string(),
                (x0 as i32 + 8, top as i32 + 2),
                small.clone(),
            ))
            .map_err(&e)?;
        }
        let by = (y0 + PANEL_TITLE_H + 2 * view_h + 8) as i32;
        legend(
            &root,
            &panel.data,
            (x0 as i32 + 16, (x0 + pw) as i32 - 16),
            by,
        )
        .map_err(&e)?;
    }
    root.present().map_err(&e)?;
    Ok(())
}

/// The colour of every vertex of a panel (linear RGB in [0, 1]).
fn panel_colours(data: &PanelData) -> Vec<[f64; 3]> {
    let unit = |v: f64| {
        if v.is_finite() {
            v.clamp(0.0, 1.0)
        } else {
            0.5
        }
    };
    match data {
        PanelData::Rgb(c) => c.iter().map(|c| c.map(unit)).collect(),
        PanelData::Shades { values, max, .. } => values
            .iter()
            .map(|c| c.map(|v| unit(v / max.max(1e-300))))
            .collect(),
        PanelData::Scalar { values, range, .. } => values
            .iter()
            .map(|&v| {
                if v.is_finite() {
                    let t = (v - range.0) / (range.1 - range.0).max(1e-300);
                    viridis(t).map(|c| c as f64 / 255.0)
                } else {
                    MISSING
                }
            })
            .collect(),
        PanelData::Categories { index, legend } => index
            .iter()
            .map(|&i| legend.get(i).map_or(MISSING, |(_, c)| *c))
            .collect(),
    }
}

fn rgb(c: [f64; 3]) -> RGBColor {
    let b = c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
    RGBColor(b[0], b[1], b[2])
}

/// A panel's legend between `bx0` and `bx1` from `by` down: a colour bar with its ends' values
/// and caption (and the grey's swatch when a value is missing), a grey ramp for shades, or a
/// swatch per category.
fn legend<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    data: &PanelData,
    (bx0, bx1): (i32, i32),
    by: i32,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let font = ("sans-serif", 13).into_font().color(&BLACK);
    let width = (bx1 - bx0).max(1);
    let ramp = |colour: &dyn Fn(f64) -> RGBColor,
                lo: String,
                hi: String,
                label: &str|
     -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        for dx in 0..width {
            root.draw(&Rectangle::new(
                [(bx0 + dx, by), (bx0 + dx + 1, by + 14)],
                colour(dx as f64 / width as f64).filled(),
            ))?;
        }
        root.draw(&Rectangle::new(
            [(bx0, by), (bx1, by + 14)],
            BLACK.stroke_width(1),
        ))?;
        root.draw(&Text::new(lo, (bx0, by + 18), font.clone()))?;
        let (w, _) = root.estimate_text_size(&hi, &font)?;
        root.draw(&Text::new(hi, (bx1 - w as i32, by + 18), font.clone()))?;
        root.draw(&Text::new(label.to_string(), (bx0, by + 36), font.clone()))?;
        Ok(())
    };
    let swatch = |x: i32, y: i32, c: RGBColor, name: &str| -> Result<i32, _> {
        root.draw(&Rectangle::new([(x, y), (x + 12, y + 12)], c.filled()))?;
        root.draw(&Rectangle::new(
            [(x, y), (x + 12, y + 12)],
            BLACK.stroke_width(1),
        ))?;
        root.draw(&Text::new(name.to_string(), (x + 17, y), font.clone()))?;
        let (w, _) = root.estimate_text_size(name, &font)?;
        Ok(x + 17 + w as i32 + 14)
    };
    match data {
        PanelData::Rgb(_) => {}
        PanelData::Scalar {
            values,
            range,
            label,
            missing,
        } => {
            ramp(
                &|t| {
                    let c = viridis(t);
                    RGBColor(c[0], c[1], c[2])
                },
                format!("{:.3}", range.0),
                format!("{:.3}", range.1),
                label,
            )?;
            if values.iter().any(|v| !v.is_finite()) {
                swatch(bx0, by + 56, rgb(MISSING), missing)?;
            }
        }
        PanelData::Shades { max, label, .. } => {
            ramp(&|t| rgb([t; 3]), "0".into(), format!("{max:.3}"), label)?;
        }
        PanelData::Categories { legend, .. } => {
            // Swatches left to right, wrapping to the next line.
            let (mut x, mut y) = (bx0, by);
            for (name, c) in legend {
                let (w, _) = root.estimate_text_size(name, &font)?;
                if x > bx0 && x + 31 + w as i32 > bx1 {
                    (x, y) = (bx0, y + 20);
                }
                x = swatch(x, y, rgb(*c), name)?;
            }
        }
    }
    Ok(())
}

/// The model viewer's status categories and their colours, in [`VertexStatus`] order.
pub const STATUS_LEGEND: [(&str, [f64; 3]); 3] = [
    ("fitted", [0.17, 0.50, 0.72]),
    ("interpolated", [0.99, 0.68, 0.38]),
    ("no model", [0.84, 0.15, 0.16]),
];

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
    let status: Vec<usize> = model
        .vertices
        .iter()
        .map(|v| match v.status {
            VertexStatus::Fitted => 0,
            VertexStatus::Interpolated => 1,
            VertexStatus::NoModel => 2,
        })
        .collect();
    let panels = vec![
        Panel {
            title: "alpha(x_o), Eq. 6".into(),
            data: PanelData::Shades {
                values: alpha,
                max: amax,
                label: "alpha per channel (R, G, B as colour)".into(),
            },
        },
        Panel {
            title: "total diffuse reflectance (G)".into(),
            data: PanelData::Scalar {
                range: range(&total),
                values: total,
                label: "∫ R_d 2πr dr".into(),
                missing: "no model".into(),
            },
        },
        Panel {
            title: "reach 1/|d| of slowest term".into(),
            data: PanelData::Scalar {
                range: range(&reach),
                values: reach,
                label: "mm".into(),
                missing: "no model".into(),
            },
        },
        Panel {
            title: "status".into(),
            data: PanelData::Categories {
                index: status,
                legend: STATUS_LEGEND
                    .iter()
                    .map(|(n, c)| (n.to_string(), *c))
                    .collect(),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::DEFAULT_VIEW;
    use image::RgbImage;

    fn open(p: &Path) -> RgbImage {
        image::open(p).unwrap().to_rgb8()
    }

    /// Pixels of `img` in columns `xs` and rows `ys` for which `f` holds.
    fn count(
        img: &RgbImage,
        xs: std::ops::Range<u32>,
        ys: std::ops::Range<u32>,
        f: impl Fn([u8; 3]) -> bool,
    ) -> usize {
        ys.flat_map(|y| xs.clone().map(move |x| (x, y)))
            .filter(|&(x, y)| f(img.get_pixel(x, y).0))
            .count()
    }

    /// A picture shows the far side too. A sphere red on the side away from the view
    /// and blue towards it: the front view is blue, the view below it (turned 180°) red.
    #[test]
    fn the_far_side_is_shown_below_the_front() {
        let mesh = crate::simulate::SimObject::Sphere {
            radius: 10.0,
            rings: 24,
        }
        .mesh();
        let away = [DEFAULT_VIEW[0], DEFAULT_VIEW[1], 0.0];
        let index: Vec<usize> = mesh
            .positions
            .iter()
            .map(|p| usize::from(p[0] * away[0] + p[1] * away[1] < 0.0))
            .collect();
        let legend = vec![
            ("near".to_string(), [0.0, 0.0, 1.0]),
            ("far".to_string(), [1.0, 0.0, 0.0]),
        ];
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("s.png");
        let size = (300, 320);
        surface_panels(
            &png,
            "",
            MeshView {
                positions: &mesh.positions,
                normals: &mesh.normals,
                faces: &mesh.triangles,
            },
            &[Panel {
                title: "side".into(),
                data: PanelData::Categories { index, legend },
            }],
            DEFAULT_VIEW,
            size,
        )
        .unwrap();
        let img = open(&png);
        assert_eq!(img.dimensions(), surface_picture_size(1, size, false));
        let view_h = size.1 - PANEL_TITLE_H - LEGEND_H;
        let (front, back) = (
            PANEL_TITLE_H..PANEL_TITLE_H + view_h,
            PANEL_TITLE_H + view_h..PANEL_TITLE_H + 2 * view_h,
        );
        let red = |c: [u8; 3]| c[0] > 80 && c[2] < 20;
        let blue = |c: [u8; 3]| c[2] > 80 && c[0] < 20;
        let (front_red, back_red) = (
            count(&img, 0..300, front.clone(), red),
            count(&img, 0..300, back.clone(), red),
        );
        let (front_blue, back_blue) = (
            count(&img, 0..300, front, blue),
            count(&img, 0..300, back, blue),
        );
        assert!(
            back_red > 2000 && back_red > 4 * front_red,
            "{front_red} {back_red}"
        );
        assert!(
            front_blue > 2000 && front_blue > 4 * back_blue,
            "{front_blue} {back_blue}"
        );
    }

    /// The model viewer's status has a legend of swatches, not a 0–2 colour bar, and
    /// alpha has a scale (a grey ramp from 0).
    #[test]
    fn status_has_swatches_and_alpha_a_scale() {
        let mut model = crate::render::synthetic::marble_torus(24, 12);
        model.vertices[5].status = VertexStatus::Interpolated;
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("m.png");
        let size = (300, 340);
        model_viewer(&png, &model, DEFAULT_VIEW, size).unwrap();
        let img = open(&png);
        let (w, h) = surface_picture_size(4, size, true);
        assert_eq!(img.dimensions(), (w, h));
        let legend = h - LEGEND_H..h;
        let status = 3 * 300..4 * 300;
        for (name, c) in STATUS_LEGEND {
            let want = rgb(c);
            let n = count(&img, status.clone(), legend.clone(), |p| {
                p == [want.0, want.1, want.2]
            });
            assert!(n >= 100, "{name}: {n} swatch pixels");
        }
        let mid = viridis(0.5);
        assert_eq!(count(&img, status, legend.clone(), |p| p == mid), 0);
        // Alpha's legend: a ramp of greys from black, with numbers.
        let greys = count(&img, 0..300, legend, |p| {
            p[0] == p[1] && p[1] == p[2] && p[0] > 20 && p[0] < 235
        });
        assert!(greys > 1000, "{greys}");
    }

    /// Where a scalar panel has grey vertices its legend names them; with none, no
    /// swatch.
    #[test]
    fn missing_values_have_a_legend() {
        let mut model = crate::render::synthetic::marble_torus(24, 12);
        for v in &mut model.vertices {
            v.log_e = 0.05;
        }
        let dir = tempfile::tempdir().unwrap();
        let grey = rgb(MISSING);
        let swatches = |model: &ModelFile| {
            let png = dir.path().join("e.png");
            super::super::error_maps(&png, &[("fit".into(), model)], DEFAULT_VIEW, (300, 320))
                .unwrap();
            let img = open(&png);
            let h = img.height();
            count(&img, 0..300, h - LEGEND_H..h, |p| {
                p == [grey.0, grey.1, grey.2]
            })
        };
        // (A few anti-aliased pixels of the numbers may match the grey.)
        let none = swatches(&model);
        assert!(none < 20, "{none}");
        model.vertices[3].log_e = f32::NAN;
        assert!(swatches(&model) >= 100);
        assert!(super::super::ERROR_MAP_TITLE.starts_with("In-sample"));
    }
}
