//! The report of `subsurf demo` (`report.md`, `report.html`), assembled from what the run
//! measured ([`crate::demo::DemoRun`]): kept apart from the run so the wording and the tables
//! can change without touching the scan, the fits or the renders.
use std::path::Path;

use super::{Figure, Report, Table, fmt};
use crate::demo::DemoRun;
use crate::render;
use crate::scan::setup::BUILTIN_RADIUS_MM;

/// A picture written into the report's folder.
fn figure(path: &Path, caption: impl Into<String>) -> Figure {
    Figure {
        path: path.to_path_buf(),
        caption: caption.into(),
    }
}

/// `5` → `5th`, `2` → `2nd`.
fn ordinal(n: usize) -> String {
    let suffix = match (n % 10, n % 100) {
        (1, 11) | (2, 12) | (3, 13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

/// The demo's report, for terminals (report.md) and browsers (report.html).
pub fn demo_report(run: &DemoRun) -> Report {
    let args = &run.options;
    let out = &args.out;
    let fits = &run.fits;
    let shown_fit = run.shown();
    let (truth_held, truth_held_rgb) = run.truth_held;
    let (truth_in, truth_in_rgb) = run.truth_in;
    let (held, train) = (&run.held, &run.train);
    let mfp = run.mean_free_path;
    let size = run.size;
    let mut rep = Report::new("subsurf demo");
    rep.paragraph(format!(
        "A simulated rig scanned the built-in object ({} frames in {}); the \
         per-vertex model (Fuchs et al. 2005, isotropic Eq. 9 with the modulation texture, Eq. \
         2/6) was fitted on {} of them and judged on the {} it never saw, then rendered next to \
         the simulation's ground truth under the same lights. Whole run: {}.",
        fmt::count(run.n_frames),
        fmt::seconds(run.scan_s),
        fmt::count(train.len()),
        fmt::count(held.len()),
        fmt::seconds(run.total_s)
    ));
    let mut headline = Table::new(["", "log E, Eq. 8 (mean over R, G, B)"]);
    headline
        .row([
            "fitted model on the held-out frames".to_string(),
            fmt::opt(shown_fit.held_out, fmt::log_e),
        ])
        .row([
            "fitted model on the frames it was fitted to".to_string(),
            fmt::opt(shown_fit.in_sample, fmt::log_e),
        ])
        .row([
            "ground truth on the held-out frames (the floor: noise, registration)".to_string(),
            fmt::opt(truth_held, fmt::log_e),
        ]);
    rep.table(
        headline,
        Some(
            "log E is the RMS of the log ratio of predicted to measured scattered light, Table 1 \
             of the paper: 0.01 ≈ 1 % error. Held-out error is the honest one; the ground \
             truth's own error on the same frames is the best any model can do."
                .into(),
        ),
    );

    rep.heading("Ground truth, model, difference");
    rep.paragraph(format!(
        "Each row: the simulation's true material and the fitted model rendered by the same \
         renderer (hierarchical transport, balanced quality) under the same light, camera and \
         exposure, then (model − truth) / truth per pixel. Tone mapping: exposure chosen from the \
         ground truth's image so that the {:.1}th percentile of the brightest channel is white, \
         linear up to {}, a smooth highlight shoulder above, sRGB; the same exposure for the \
         model, so brightness differences show. The `.exr` beside each PNG holds the linear \
         radiance, unscaled. Largest clipped share of lit pixels in any render: {}.",
        100.0 * render::WHITE_QUANTILE,
        render::SHOULDER_KNEE,
        fmt::percent(run.clip_max, 2)
    ));
    let mut diff_rows = Table::new([
        "light",
        "mean |model − truth| / truth",
        "95th percentile",
        "mean signed",
    ]);
    for c in &run.comparisons {
        let light_name = &c.light_name;
        let d = &c.difference;
        diff_rows.row([
            light_name.to_string(),
            fmt::percent(d.mean_abs, 1),
            fmt::percent(d.p95_abs, 1),
            fmt::percent(d.mean_signed, 1),
        ]);
        let mut row = vec![
            figure(&c.truth_png, format!("Ground truth, {light_name}")),
            figure(
                &c.model_png,
                format!("Fitted model, {light_name}, same exposure"),
            ),
            figure(
                &c.difference_png,
                format!(
                    "Difference, {light_name}: red = model brighter, blue = darker, scale ±{}",
                    fmt::percent(d.range, 0)
                ),
            ),
        ];
        if let Some((png, difference)) = &c.blender {
            row.insert(
                2,
                figure(
                    png,
                    "In Blender: the exported model in Cycles, key light, same camera and exposure",
                ),
            );
            row.push(figure(
                difference,
                "Blender − truth: (Cycles − ground truth) / ground truth, the same measure as \
                 the model's difference",
            ));
        }
        rep.figures(row);
    }
    diff_rows
        .header
        .push("in Blender: mean |Cycles − truth| / truth".into());
    for (k, row) in diff_rows.rows.iter_mut().enumerate() {
        row.push(match (&run.in_blender, k) {
            (Some(b), 0) => fmt::percent(b.truth_difference.mean_abs, 1),
            _ => fmt::MISSING.to_string(),
        });
    }
    rep.table(
        diff_rows,
        Some(
            "Luminance over lit pixels (truth above 0.1 % of its brightest). In Blender: the \
             exported model in Cycles under the key light against the same ground truth."
                .into(),
        ),
    );
    if let Some(b) = &run.in_blender {
        let c = &b.comparison;
        let mut t = Table::new([
            "key light, against the ground truth",
            "mean relative pixel error",
        ]);
        t.row([
            "subsurf's render of the fitted model".to_string(),
            fmt::opt(shown_fit.render_error, |x| fmt::percent(x, 1)),
        ])
        .row([
            format!(
                "Cycles' render of the exported model ({} samples)",
                fmt::count(c.samples as usize)
            ),
            fmt::percent(b.against_truth, 1),
        ])
        .row([
            "Cycles' own noise (two seeds, ÷ √2)".to_string(),
            fmt::opt(c.cycles_noise, |x| fmt::percent(x, 1)),
        ])
        .row([
            "Cycles against subsurf's render (same model)".to_string(),
            fmt::percent(c.mean_relative_error, 1),
        ]);
        rep.table(
            t,
            Some(format!(
                "Per channel over lit pixels (truth above 0.1 % of its brightest), the measure \
                 of the speed-and-accuracy table's render column. The exported model (`subsurf \
                 export`'s default conversion, `{}` subsurface colour scaled by `--gather {}`: \
                 per-vertex colour and radius of Cycles' Principled BSDF, docs/export.md) \
                 rendered in Cycles ({}, \
                 two seeds) under the key light; the noise row is the part of Cycles' figure \
                 its sampling alone explains. Export and report: `{}/`.",
                serde_json::to_value(b.colour)
                    .ok()
                    .and_then(|v| v.as_str().map(str::to_string))
                    .unwrap_or_default(),
                serde_json::to_value(b.gather)
                    .ok()
                    .and_then(|v| v.as_str().map(str::to_string))
                    .unwrap_or_default(),
                fmt::seconds(c.cycles_seconds),
                b.dir.strip_prefix(out).unwrap_or(&b.dir).display()
            )),
        );
    } else {
        rep.paragraph(
            "In Blender: — (Blender was not found or `--no-blender` was given; `subsurf export` \
             writes the scene for it).",
        );
    }
    let mut render_rows = Table::new([
        "picture",
        "light",
        "exposure",
        "lit pixels",
        "clipped",
        "render time",
    ]);
    for r in &run.renders {
        render_rows.row([
            format!("`{}` (+ `.exr`)", r.name),
            format!("{}, {}", r.light_name, r.what),
            format!("x{}", fmt::sig(r.tone.exposure, 3)),
            fmt::count(r.tone.lit_pixels),
            fmt::percent(r.tone.clipped, 2),
            fmt::seconds(r.seconds),
        ]);
    }
    rep.table(render_rows, None);

    rep.heading("Held-out against in-sample error");
    let mut errors = Table::new(["model", "frames", "red", "green", "blue", "mean"]);
    for (name, n, rgb, mean) in [
        (
            "fitted (exact), held out",
            held.len(),
            shown_fit.held_out_rgb,
            shown_fit.held_out,
        ),
        (
            "fitted (exact), in sample",
            train.len(),
            shown_fit.in_sample_rgb,
            shown_fit.in_sample,
        ),
        (
            "ground truth, held out",
            held.len(),
            truth_held_rgb,
            truth_held,
        ),
        (
            "ground truth, in sample",
            train.len(),
            truth_in_rgb,
            truth_in,
        ),
    ] {
        let mut c = vec![name.to_string(), fmt::count(n)];
        c.extend(rgb.map(|x| fmt::opt(x, fmt::log_e)));
        c.push(fmt::opt(mean, fmt::log_e));
        errors.row(c);
    }
    rep.table(
        errors,
        Some(format!(
            "Mean log E (Eq. 8) per frame: `subsurf evaluate` on every {} frame (held out of \
             the fit) and on the others. In-sample error below held-out error is what a model \
             that fits its noise would show; the gap is the price of predicting new light \
             positions.",
            ordinal(args.hold_out)
        )),
    );

    rep.heading("Speed and accuracy");
    let mut trade = Table::new([
        "fit preset",
        "fit time",
        "vertices with own fit",
        "log E in sample",
        "log E held out",
        "key-light render vs truth",
        "render time",
    ]);
    for f in fits {
        trade.row([
            if f.name == "exact" {
                "exact (shown)".to_string()
            } else {
                f.name.to_string()
            },
            fmt::seconds(f.fit_s),
            fmt::count(f.report.vertices_fitted),
            fmt::opt(f.in_sample, fmt::log_e),
            fmt::opt(f.held_out, fmt::log_e),
            fmt::opt(f.render_error, |x| fmt::percent(x, 1)),
            fmt::seconds(f.render_s),
        ]);
    }
    trade.row([
        "ground truth".to_string(),
        fmt::MISSING.to_string(),
        fmt::count(run.truth_vertices),
        fmt::opt(truth_in, fmt::log_e),
        fmt::opt(truth_held, fmt::log_e),
        fmt::percent(0.0, 1),
        fmt::MISSING.to_string(),
    ]);
    rep.table(
        trade,
        Some(format!(
            "Same scan and training frames for every preset: draft bins the samples in 8 \
                 distances and uses every second one, balanced bins in 16, exact fits every \
                 sample (all n = 3). Fit time: from the sample store, the frames decoded once \
                 beforehand for all presets ({}, timed apart). Render vs truth: mean relative \
                 pixel error of the key-light render against the ground truth's (pixels above \
                 0.1 % of the brightest). `subsurf bench tradeoff` measures the same trade over \
                 scan densities and render qualities.",
            fmt::seconds(run.decode_s)
        )),
    );

    rep.heading("Fall-off");
    if let Some((f, k, sum)) = &run.falloff {
        rep.figures(vec![figure(
            f,
            format!(
                "Figure 3: the green samples of frame {k} ({} samples) against distance from x_i, \
                 with a sum of exponentials (log E {}) and the dipole (log E {}) fitted to them.",
                fmt::count(sum.samples),
                fmt::opt(sum.expsum_log_e, fmt::log_e),
                fmt::opt(sum.dipole_log_e, fmt::log_e)
            ),
        )]);
    } else {
        rep.paragraph("No frame had enough samples for a fall-off plot.");
    }

    rep.heading("The model");
    rep.figures(vec![figure(
        &run.model_png,
        "Model maps: modulation texture alpha, total reflectance, reach of the fall-off, and \
         which vertices were fitted, interpolated or left without a model.",
    )]);
    rep.figures(vec![figure(
        &run.error_map_png,
        "log E(x_i) (Eq. 8) per fitted light position, exact and draft presets on one scale; \
             grey: no fit of its own.",
    )]);
    rep.table(super::fit::counts_table(&shown_fit.report), None);
    rep.paragraph(format!(
        "Failed fits before interpolation: {}. Terms dropped because the samples do not support \
         them: {}. Alpha (Eq. 6): {}.",
        super::fit::reasons(&shown_fit.report.failures),
        super::fit::reasons(&shown_fit.report.terms_dropped),
        super::fit::alpha_summary(&shown_fit.report.alpha)
    ));

    rep.heading("Scan");
    let mut scan_t = Table::new(["", "value", "why"]);
    scan_t
        .row([
            "object".to_string(),
            format!(
                "sphere, r = {} mm, {} vertices",
                BUILTIN_RADIUS_MM,
                fmt::count(run.mesh_vertices)
            ),
            format!(
                "vertex spacing ≤ 1 mean free path ({} mm) of the material",
                fmt::sig(mfp, 2)
            ),
        ])
        .row([
            "camera".to_string(),
            format!("{size} × {size} px"),
            "pixel footprint ≤ ½ mean free path".to_string(),
        ])
        .row([
            "laser positions".to_string(),
            format!(
                "{} frames at {} turntable angles, x_i within {} mm of every vertex",
                fmt::count(run.n_frames),
                args.angles,
                fmt::sig(run.target_mm, 2)
            ),
            format!(
                "{} mean free paths: what held-out prediction needs",
                fmt::sig(run.target_mm / mfp, 2)
            ),
        ])
        .row([
            "exposures".to_string(),
            run.exposures
                .iter()
                .map(|s| format!("{} ms", fmt::sig(s * 1e3, 3)))
                .collect::<Vec<_>>()
                .join(" + "),
            "HDR: the spot unclipped, the brightest scattered light just below clipping"
                .to_string(),
        ])
        .row([
            "noise floor".to_string(),
            fmt::sig(run.noise_floor.unwrap_or(0.0), 2),
            "one pixel's SNR = 50 at the longest exposure".to_string(),
        ]);
    rep.table(
        scan_t,
        Some(format!(
            "Rig: the firmware's core on simulated hardware, in virtual time; the same scan on \
             the rig would take {} (turntable moves, galvo settling, exposures). Dataset: \
             `scan/` (with `ground-truth.ply`).",
            fmt::seconds(run.rig_seconds)
        )),
    );

    rep.heading("Time");
    let mut time_t = Table::new(["stage", "wall time"]);
    for (k, v) in &run.timings {
        if fits.iter().any(|f| f.name == *k) {
            time_t.row([format!("fit, {k} preset"), fmt::seconds(*v)]);
            if let Some((_, e)) = run.evaluations.iter().find(|(n, _)| n == k) {
                time_t.row([
                    format!("evaluation of the {k} fit (held-out and in-sample frames)"),
                    fmt::seconds(*e),
                ]);
            }
        } else {
            time_t.row([(*k).to_string(), fmt::seconds(*v)]);
        }
    }
    time_t.row(["whole demo".to_string(), fmt::seconds(run.total_s)]);
    rep.table(
        time_t,
        Some(format!("{} worker threads.", rayon::current_num_threads())),
    );
    rep.paragraph(
        "Files: `model.ply` (the model, docs/model-format.md), `fit-report.json`, \
         `render-*.png` + `.exr`, `falloff.png`, `error-map.png`, `model.png`, `scan/`, and \
         with Blender `blender/` (the export, its report and the Cycles render; \
         `render-blender-key-light.png` and `render-difference-blender-key-light.png` here).",
    );
    rep
}

#[cfg(test)]
mod tests {
    use super::ordinal;

    #[test]
    fn ordinals() {
        assert_eq!(ordinal(5), "5th");
        assert_eq!(ordinal(2), "2nd");
        assert_eq!(ordinal(11), "11th");
        assert_eq!(ordinal(21), "21st");
    }
}
