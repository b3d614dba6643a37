//! Line plots: the fall-off of one `x_i` (Figure 3) and speed/accuracy curves.

use std::path::Path;

use plotters::prelude::*;

use super::{PlotError, draw_err, register_font};

/// A named curve for [`falloff_plot`].
#[derive(Clone, Debug)]
pub struct Curve {
    /// Legend text.
    pub name: String,
    /// `(r, value)` points, drawn as a line.
    pub points: Vec<(f64, f64)>,
}

/// Figure 3: the samples `s(x_i, x_o)` of one lit point against distance `|x_o − x_i|` on a log
/// scale, with fitted curves (the sum of exponentials, the dipole) as lines. Non-positive and
/// non-finite values are left out (they have no logarithm).
pub fn falloff_plot(
    path: &Path,
    title: &str,
    samples: &[(f64, f64)],
    curves: &[Curve],
    size: (u32, u32),
) -> Result<(), PlotError> {
    register_font();
    let ok = |&(r, v): &(f64, f64)| r.is_finite() && v.is_finite() && v > 0.0 && r >= 0.0;
    let pts: Vec<(f64, f64)> = samples.iter().copied().filter(ok).collect();
    if pts.is_empty() {
        return Err(PlotError::Empty("no positive finite samples".into()));
    }
    let rmax = pts.iter().map(|p| p.0).fold(0.0, f64::max).max(1e-9);
    let vmin = pts.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    let vmax = pts.iter().map(|p| p.1).fold(0.0, f64::max);
    let (lo, hi) = (vmin / 3.0, vmax * 3.0);
    let e = draw_err(path);
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(&e)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..rmax * 1.02, (lo..hi).log_scale())
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc("|x_o − x_i| (mm)")
        .y_desc("R_d (log scale)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(&e)?;
    chart
        .draw_series(
            pts.iter()
                .map(|&(r, v)| Circle::new((r, v), 2, RGBColor(90, 90, 90).mix(0.5).filled())),
        )
        .map_err(&e)?
        .label("samples")
        .legend(|(x, y)| Circle::new((x + 10, y), 3, RGBColor(90, 90, 90).filled()));
    let colours = [
        RGBColor(200, 30, 30),
        RGBColor(30, 90, 200),
        RGBColor(20, 150, 60),
        RGBColor(160, 60, 170),
    ];
    for (k, c) in curves.iter().enumerate() {
        let colour = colours[k % colours.len()];
        let line: Vec<(f64, f64)> = c
            .points
            .iter()
            .copied()
            .filter(|&(r, v)| ok(&(r, v)) && v >= lo && v <= hi)
            .collect();
        chart
            .draw_series(LineSeries::new(line, colour.stroke_width(2)))
            .map_err(&e)?
            .label(c.name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(&e)?;
    root.present().map_err(&e)?;
    Ok(())
}

/// A speed/accuracy curve: wall time against error (log–log), one point per setting, with the
/// reference's time as a horizontal line. Points with zero error are drawn at the axis' floor.
pub fn tradeoff_curve(
    path: &Path,
    title: &str,
    points: &[(f64, f64)],
    reference_seconds: f64,
) -> Result<(), PlotError> {
    register_font();
    let pts: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|&(t, err)| t.is_finite() && t > 0.0 && err.is_finite())
        .collect();
    if pts.is_empty() {
        return Err(PlotError::Empty("no finite points".into()));
    }
    let (emax, epos) = error_span(pts.iter().map(|p| p.1));
    let efloor = if epos.is_finite() {
        epos / 3.0
    } else {
        emax / 100.0
    };
    let tmin = pts
        .iter()
        .map(|p| p.0)
        .fold(f64::INFINITY, f64::min)
        .min(reference_seconds);
    let tmax = pts
        .iter()
        .map(|p| p.0)
        .fold(0.0, f64::max)
        .max(reference_seconds);
    let e = draw_err(path);
    let root = BitMapBackend::new(path, (720, 480)).into_drawing_area();
    let mut chart = error_time_chart(
        &root,
        path,
        title,
        efloor..emax * 2.0,
        tmin / 2.0..tmax * 2.0,
        ("mean relative error", "wall time (s)"),
    )?;
    let line: Vec<(f64, f64)> = pts.iter().map(|&(t, err)| (err.max(efloor), t)).collect();
    chart
        .draw_series(LineSeries::new(line.clone(), BLUE.stroke_width(2)))
        .map_err(&e)?;
    chart
        .draw_series(line.iter().map(|&p| Circle::new(p, 4, BLUE.filled())))
        .map_err(&e)?
        .label("hierarchical")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, BLUE.filled()));
    chart
        .draw_series(LineSeries::new(
            vec![(efloor, reference_seconds), (emax * 2.0, reference_seconds)],
            RED.stroke_width(2),
        ))
        .map_err(&e)?
        .label("exact sum")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(&e)?;
    root.present().map_err(&e)?;
    Ok(())
}

/// The error axis of the speed/accuracy plots: its top (at least 1e-6) and the smallest
/// positive error (infinite where none is), from which each plot sets the floor its log scale
/// draws an error of 0 at.
fn error_span(errors: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let emax = errors.clone().fold(0.0, f64::max).max(1e-6);
    let epos = errors.filter(|&v| v > 0.0).fold(f64::INFINITY, f64::min);
    (emax, epos)
}

/// A chart with both axes on a log scale, on a bitmap.
type LogLogChart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<LogCoord<f64>, LogCoord<f64>>>;

/// The log–log chart both speed/accuracy plots draw on: `root` cleared to white, error `x`
/// against wall time `y`, with their axis descriptions `desc`.
fn error_time_chart<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
    path: &Path,
    title: &str,
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    desc: (&str, &str),
) -> Result<LogLogChart<'a, 'b>, PlotError> {
    let e = draw_err(path);
    root.fill(&WHITE).map_err(&e)?;
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x.log_scale(), y.log_scale())
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc(desc.0)
        .y_desc(desc.1)
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(&e)?;
    Ok(chart)
}

/// One configuration of a speed/accuracy study for [`pareto_plot`].
#[derive(Clone, Debug, PartialEq)]
pub struct TradeoffPoint {
    /// Short label, drawn beside the point when it is on the Pareto front.
    pub label: String,
    /// Wall time, seconds (> 0).
    pub seconds: f64,
    /// Error against the reference (>= 0; 0 is drawn at the axis' floor).
    pub error: f64,
}

/// Indices of the points on the Pareto front (no other point is at least as fast and at least as
/// accurate, and strictly better in one), sorted by time. Non-finite points are never on it.
pub fn pareto_front(points: &[TradeoffPoint]) -> Vec<usize> {
    let ok = |p: &TradeoffPoint| p.seconds.is_finite() && p.error.is_finite();
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| {
            let a = &points[i];
            ok(a)
                && !points.iter().any(|b| {
                    ok(b)
                        && b.seconds <= a.seconds
                        && b.error <= a.error
                        && (b.seconds < a.seconds || b.error < a.error)
                })
        })
        .collect();
    front.sort_by(|&i, &j| points[i].seconds.total_cmp(&points[j].seconds));
    front
}

/// A whole-chain speed/accuracy study: every configuration as a point (error against time,
/// log–log), the Pareto front joined by a line with its points labelled. Returns the front's
/// indices ([`pareto_front`]).
pub fn pareto_plot(
    path: &Path,
    title: &str,
    points: &[TradeoffPoint],
    size: (u32, u32),
) -> Result<Vec<usize>, PlotError> {
    register_font();
    let ok: Vec<&TradeoffPoint> = points
        .iter()
        .filter(|p| p.seconds.is_finite() && p.seconds > 0.0 && p.error.is_finite())
        .collect();
    if ok.is_empty() {
        return Err(PlotError::Empty("no finite points".into()));
    }
    let front = pareto_front(points);
    let (emax, epos) = error_span(ok.iter().map(|p| p.error));
    let efloor = if epos.is_finite() {
        (epos / 3.0).min(emax / 10.0)
    } else {
        emax / 100.0
    };
    let tmin = ok.iter().map(|p| p.seconds).fold(f64::INFINITY, f64::min);
    let tmax = ok.iter().map(|p| p.seconds).fold(0.0, f64::max);
    let e = draw_err(path);
    let root = BitMapBackend::new(path, size).into_drawing_area();
    let mut chart = error_time_chart(
        &root,
        path,
        title,
        efloor..emax * 3.0,
        tmin / 1.5..tmax * 1.5,
        (
            "mean relative pixel error against the reference",
            "wall time, whole chain (s)",
        ),
    )?;
    let at = |p: &TradeoffPoint| (p.error.max(efloor), p.seconds);
    chart
        .draw_series(
            ok.iter()
                .map(|p| Circle::new(at(p), 4, BLUE.mix(0.5).filled())),
        )
        .map_err(&e)?
        .label("configuration")
        .legend(|(x, y)| Circle::new((x + 10, y), 4, BLUE.mix(0.5).filled()));
    let line: Vec<(f64, f64)> = front.iter().map(|&i| at(&points[i])).collect();
    chart
        .draw_series(LineSeries::new(line.clone(), RED.stroke_width(2)))
        .map_err(&e)?
        .label("Pareto front")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
    chart
        .draw_series(line.iter().map(|&p| Circle::new(p, 6, RED.filled())))
        .map_err(&e)?;
    chart
        .draw_series(front.iter().map(|&i| {
            Text::new(
                points[i].label.clone(),
                at(&points[i]),
                ("sans-serif", 12).into_font(),
            )
        }))
        .map_err(&e)?;
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(&e)?;
    root.present().map_err(&e)?;
    Ok(front)
}

/// One planner's learning curve for [`learning_curves`]: `(frames, rig seconds, error, half
/// width of its 95 % interval)` per point (a non-finite half-width: no interval drawn).
#[derive(Clone, Debug, PartialEq)]
pub struct LearningCurve {
    /// Legend text.
    pub name: String,
    /// The points, in acquisition order.
    pub points: Vec<(f64, f64, f64, f64)>,
}

/// Learning curves side by side: `y_desc` (an error, or an error's paired difference to a
/// reference, which separates curves that the frames' own spread would hide) against frames
/// (left) and against rig time (right), one line per planner with each point's 95 % interval as
/// an error bar, each curve's points nudged sideways by a little so the bars do not hide each
/// other; `band` draws dashed lines at ±band (a declared margin) where given, and then the y axis
/// is asinh(y / band) (labelled in y): linear within a few margins of zero, where planners that
/// matter differ, logarithmic beyond, so one planner's far-off point does not flatten the others.
/// Non-finite points are left out.
pub fn learning_curves(
    path: &Path,
    title: &str,
    y_desc: &str,
    curves: &[LearningCurve],
    band: Option<f64>,
) -> Result<(), PlotError> {
    register_font();
    type P = (f64, f64, f64, f64);
    let finite = |p: &&P| p.0.is_finite() && p.1.is_finite() && p.2.is_finite();
    let all: Vec<P> = curves
        .iter()
        .flat_map(|c| c.points.iter().filter(finite).copied())
        .collect();
    if all.is_empty() {
        return Err(PlotError::Empty("no finite learning-curve point".into()));
    }
    let b = band.filter(|b| b.is_finite() && *b > 0.0);
    // The axis transform and its inverse for the labels.
    let fwd = move |y: f64| b.map_or(y, |b| (y / b).asinh());
    let back = move |v: f64| b.map_or(v, |b| b * v.sinh());
    let half = |p: &P| if p.3.is_finite() { p.3.abs() } else { 0.0 };
    // A point as drawn: (y, low, high) on the axis' scale.
    let drawn = |p: &P| (fwd(p.2), fwd(p.2 - half(p)), fwd(p.2 + half(p)));
    let max = |f: fn(&P) -> f64| all.iter().map(f).fold(0.0, f64::max);
    let (fmax, tmax) = (max(|p| p.0).max(1.0), max(|p| p.1).max(1e-3));
    let edge = b.map_or(0.0, fwd);
    let emin = all.iter().map(|p| drawn(p).1).fold(-edge, f64::min);
    let emax = all.iter().map(|p| drawn(p).2).fold(edge, f64::max);
    let pad = 0.05 * (emax - emin).max(1e-3);
    let e = draw_err(path);
    let root = BitMapBackend::new(path, (1200, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(&e)?;
    let root = root.titled(title, ("sans-serif", 20)).map_err(&e)?;
    let (left, right) = root.split_horizontally(600);
    let colours = [
        BLUE,
        RED,
        GREEN,
        MAGENTA,
        CYAN,
        BLACK,
        RGBColor(230, 140, 0),
        RGBColor(120, 60, 160),
        RGBColor(140, 90, 40),
    ];
    let n = curves.len().max(1) as f64;
    for (area, by_time) in [(&left, false), (&right, true)] {
        let xmax = if by_time { tmax } else { fmax };
        let mut chart = ChartBuilder::on(area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..xmax * 1.05, (emin - pad)..(emax + pad))
            .map_err(&e)?;
        chart
            .configure_mesh()
            .x_desc(if by_time { "rig time (s)" } else { "frames" })
            .y_desc(y_desc)
            .y_label_formatter(&|v| format!("{:.3}", back(*v)))
            .draw()
            .map_err(&e)?;
        if b.is_some() {
            for y in [-edge, edge] {
                chart
                    .draw_series(DashedLineSeries::new(
                        vec![(0.0, y), (xmax * 1.05, y)],
                        6,
                        4,
                        BLACK.mix(0.6).stroke_width(1),
                    ))
                    .map_err(&e)?;
            }
        }
        for (i, c) in curves.iter().enumerate() {
            let colour = colours[i % colours.len()];
            let nudge = (i as f64 - (n - 1.0) / 2.0) * 0.006 * xmax;
            let pts: Vec<(f64, (f64, f64, f64))> = c
                .points
                .iter()
                .filter(finite)
                .map(|p| ((if by_time { p.1 } else { p.0 }) + nudge, drawn(p)))
                .collect();
            chart
                .draw_series(LineSeries::new(
                    pts.iter().map(|p| (p.0, p.1.0)),
                    colour.stroke_width(2),
                ))
                .map_err(&e)?
                .label(c.name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            chart
                .draw_series(
                    pts.iter()
                        .filter(|p| p.1.2 > p.1.1)
                        .map(|&(x, (_, lo, hi))| {
                            PathElement::new(vec![(x, lo), (x, hi)], colour.stroke_width(1))
                        }),
                )
                .map_err(&e)?;
            // The bars' caps, a hundredth of the axis wide.
            let cap = 0.01 * xmax;
            for end in [1usize, 2] {
                chart
                    .draw_series(pts.iter().filter(|p| p.1.2 > p.1.1).map(|&(x, y)| {
                        let y = if end == 1 { y.1 } else { y.2 };
                        PathElement::new(vec![(x - cap, y), (x + cap, y)], colour.stroke_width(1))
                    }))
                    .map_err(&e)?;
            }
            chart
                .draw_series(
                    pts.iter()
                        .map(|&p| Circle::new((p.0, p.1.0), 3, colour.filled())),
                )
                .map_err(&e)?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(&e)?;
    }
    root.present().map_err(&e)?;
    Ok(())
}
