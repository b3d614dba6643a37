//! The difference between two renders of one scene (a fitted model against the ground truth under
//! the same light and camera) as a picture: signed relative difference per pixel on a diverging
//! colour scale with a colour bar, and the numbers that summarise it.

use std::path::Path;

use plotters::prelude::*;

use super::{PlotError, draw_err, register_font};
use crate::render::Image;

/// What the difference picture shows, in numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DifferenceStats {
    /// Pixels compared (covered in both, truth above the floor).
    pub pixels: usize,
    /// Mean of |model − truth| / truth over those pixels (luminance).
    pub mean_abs: f64,
    /// 95th percentile of the same.
    pub p95_abs: f64,
    /// Mean of (model − truth) / truth: overall too bright (> 0) or too dark (< 0).
    pub mean_signed: f64,
    /// The colour scale runs from −range to +range.
    pub range: f64,
}

/// Blue (model darker) – white – red (model brighter), `t` in [−1, 1].
fn diverging(t: f64) -> RGBColor {
    const NEG: [f64; 3] = [33.0, 102.0, 172.0];
    const POS: [f64; 3] = [178.0, 24.0, 43.0];
    const MID: [f64; 3] = [247.0, 247.0, 247.0];
    let t = if t.is_finite() {
        t.clamp(-1.0, 1.0)
    } else {
        0.0
    };
    let end = if t < 0.0 { NEG } else { POS };
    let a = t.abs();
    let c = [0, 1, 2].map(|k| (MID[k] + a * (end[k] - MID[k])).round() as u8);
    RGBColor(c[0], c[1], c[2])
}

fn luminance(p: &[f32; 3]) -> f64 {
    0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64
}

/// The smallest of 5 %, 10 %, 20 %, 50 %, 100 %, 200 % at or above `x`.
fn nice_range(x: f64) -> f64 {
    [0.05, 0.1, 0.2, 0.5, 1.0, 2.0]
        .into_iter()
        .find(|&r| r >= x)
        .unwrap_or(2.0)
}

/// What the two images of a difference picture are, for its caption `(image − reference) /
/// reference`: a model against the ground truth, or Cycles against subsurf's render (a caption
/// that called the latter "model against truth" misled the reader).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Compared<'a> {
    /// The image judged (`model` in `difference_picture`).
    pub image: &'a str,
    /// The one it is judged against (`truth`).
    pub reference: &'a str,
}

impl Compared<'_> {
    /// The caption under the colour bar.
    pub fn caption(&self) -> String {
        format!("({} − {r}) / {r}", self.image, r = self.reference)
    }
}

/// Draws `(model − truth) / truth` of the luminance per pixel. Pixels not covered by both images,
/// or where the truth is darker than `floor` × its brightest pixel, are grey (a relative
/// difference says nothing there). The colour scale is symmetric, from the 95th percentile of
/// |difference| rounded up to 5, 10, 20, 50, 100 or 200 %.
pub fn difference_picture(
    path: &Path,
    model: &Image,
    truth: &Image,
    floor: f64,
) -> Result<DifferenceStats, PlotError> {
    difference_picture_of(
        path,
        model,
        truth,
        floor,
        Compared {
            image: "model",
            reference: "truth",
        },
    )
}

/// [`difference_picture`] with the two images named in the caption.
pub fn difference_picture_of(
    path: &Path,
    model: &Image,
    truth: &Image,
    floor: f64,
    names: Compared<'_>,
) -> Result<DifferenceStats, PlotError> {
    if model.width != truth.width || model.height != truth.height {
        return Err(PlotError::Empty(format!(
            "renders of different sizes: {}x{} and {}x{}",
            model.width, model.height, truth.width, truth.height
        )));
    }
    let max = truth
        .pixels
        .iter()
        .zip(&truth.covered)
        .filter(|(_, c)| **c)
        .map(|(p, _)| luminance(p))
        .filter(|x| x.is_finite())
        .fold(0.0, f64::max);
    let rel: Vec<Option<f64>> = (0..truth.pixels.len())
        .map(|k| {
            let t = luminance(&truth.pixels[k]);
            let m = luminance(&model.pixels[k]);
            (truth.covered[k] && model.covered[k] && t > floor * max && t > 0.0 && m.is_finite())
                .then(|| (m - t) / t)
        })
        .collect();
    let mut abs: Vec<f64> = rel.iter().flatten().map(|x| x.abs()).collect();
    if abs.is_empty() {
        return Err(PlotError::Empty("no lit pixel to compare".into()));
    }
    abs.sort_by(f64::total_cmp);
    let n = abs.len();
    let p95 = abs[((n - 1) as f64 * 0.95).round() as usize];
    let range = nice_range(p95);
    let stats = DifferenceStats {
        pixels: n,
        mean_abs: abs.iter().sum::<f64>() / n as f64,
        p95_abs: p95,
        mean_signed: rel.iter().flatten().sum::<f64>() / n as f64,
        range,
    };

    register_font();
    let (w, h) = (truth.width, truth.height);
    let bar_h = 78u32;
    let width = w.max(420);
    let e = draw_err(path);
    let root = BitMapBackend::new(path, (width, h + bar_h)).into_drawing_area();
    root.fill(&RGBColor(24, 24, 28)).map_err(&e)?;
    let x0 = ((width - w) / 2) as i32;
    for y in 0..h {
        for x in 0..w {
            let k = (y * w + x) as usize;
            let c = match rel[k] {
                Some(d) => diverging(d / range),
                None if truth.covered[k] => RGBColor(110, 110, 110),
                None => continue,
            };
            root.draw_pixel((x0 + x as i32, y as i32), &c).map_err(&e)?;
        }
    }
    let (bx0, bx1) = (16i32, width as i32 - 16);
    let by = h as i32 + 8;
    let bw = (bx1 - bx0).max(1);
    for dx in 0..bw {
        let t = 2.0 * dx as f64 / bw as f64 - 1.0;
        root.draw(&Rectangle::new(
            [(bx0 + dx, by), (bx0 + dx + 1, by + 12)],
            diverging(t).filled(),
        ))
        .map_err(&e)?;
    }
    let style = ("sans-serif", 13).into_font().color(&WHITE);
    let pct = |x: f64| format!("{}{:.0} %", if x > 0.0 { "+" } else { "" }, 100.0 * x);
    for (x, label) in [
        (bx0, pct(-range)),
        (bx0 + bw / 2 - 4, "0".to_string()),
        (bx1 - 44, pct(range)),
    ] {
        root.draw(&Text::new(label, (x, by + 15), style.clone()))
            .map_err(&e)?;
    }
    let caption = names.caption();
    let (cw, _) = root.estimate_text_size(&caption, &style).map_err(&e)?;
    root.draw(&Text::new(
        caption,
        ((width as i32 - cw as i32) / 2, by + 32),
        style.clone(),
    ))
    .map_err(&e)?;
    // The grey's legend: a swatch and what it means.
    let grey = "not compared: too dark, or outside one image";
    let (gw, _) = root.estimate_text_size(grey, &style).map_err(&e)?;
    let gx = (width as i32 - gw as i32 - 18) / 2;
    root.draw(&Rectangle::new(
        [(gx, by + 52), (gx + 12, by + 64)],
        RGBColor(110, 110, 110).filled(),
    ))
    .map_err(&e)?;
    root.draw(&Text::new(grey, (gx + 18, by + 51), style))
        .map_err(&e)?;
    root.present().map_err(&e)?;
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(v: f32, n: u32) -> Image {
        Image {
            width: n,
            height: n,
            pixels: vec![[v; 3]; (n * n) as usize],
            covered: (0..n * n).map(|k| k % n > 2).collect(),
        }
    }

    #[test]
    fn a_uniformly_darker_model_reads_as_a_negative_difference() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.png");
        let s = difference_picture(&p, &flat(0.5, 300), &flat(1.0, 300), 1e-3).unwrap();
        assert_eq!(s.pixels, 300 * 297);
        assert!((s.mean_signed + 0.5).abs() < 1e-9 && (s.mean_abs - 0.5).abs() < 1e-9);
        assert_eq!(s.range, 0.5);
        let img = image::open(&p).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (420, 378));
        // Full blue where the model is half as bright as the truth.
        assert_eq!(img.get_pixel(210, 150).0, [33, 102, 172]);
        assert!(difference_picture(&p, &flat(1.0, 10), &flat(1.0, 11), 1e-3).is_err());
    }

    /// The caption names what was compared (Cycles against subsurf for `export
    /// --render`), and the picture draws that caption, not "model − truth".
    #[test]
    fn the_caption_names_the_two_images() {
        let cycles = Compared {
            image: "Cycles",
            reference: "subsurf",
        };
        assert!(
            cycles.caption().starts_with("(Cycles − subsurf) / subsurf"),
            "{}",
            cycles.caption()
        );
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
        let (m, t) = (flat(0.5, 300), flat(1.0, 300));
        difference_picture(&a, &m, &t, 1e-3).unwrap();
        difference_picture_of(&b, &m, &t, 1e-3, cycles).unwrap();
        let (a, b) = (
            image::open(&a).unwrap().to_rgb8(),
            image::open(&b).unwrap().to_rgb8(),
        );
        let differs = |y0: u32, y1: u32| {
            (y0..y1).any(|y| (0..420).any(|x| a.get_pixel(x, y) != b.get_pixel(x, y)))
        };
        // The same picture and colour bar, another caption.
        assert!(!differs(0, 300 + 30));
        assert!(differs(300 + 36, 300 + 56));
    }
}
