//! What a fit did, for people: the tables of `fit-report.json` formatted, shared by `subsurf fit`
//! (its `fit-report.html`/`.md`) and `subsurf demo`.

use std::collections::BTreeMap;
use std::path::Path;

use super::fmt;
use super::{Figure, Report, Table};
use crate::pipeline::FitReport;

/// A map of reasons (serialized as snake_case) to counts as `high error 3, no data 12`, or
/// `none`.
pub fn reasons<K: serde::Serialize>(counts: &BTreeMap<K, usize>) -> String {
    let parts: Vec<String> = counts
        .iter()
        .filter(|(_, n)| **n > 0)
        .map(|(k, n)| {
            let name = serde_json::to_value(k)
                .ok()
                .and_then(|v| v.as_str().map(fmt::words))
                .unwrap_or_else(|| "other".into());
            format!("{name} {}", fmt::count(*n))
        })
        .collect();
    if parts.is_empty() {
        "none".into()
    } else {
        parts.join(", ")
    }
}

/// Vertices, frames and samples of a fit as a two-column table.
pub fn counts_table(r: &FitReport) -> Table {
    let mut t = Table::new(["", "count"]);
    let f = &r.frames;
    t.row(["vertices".to_string(), fmt::count(r.vertices)])
        .row([
            "  with their own fit".to_string(),
            fmt::count(r.vertices_fitted),
        ])
        .row([
            "  interpolated from neighbours".to_string(),
            fmt::count(r.vertices_interpolated),
        ])
        .row([
            "  without a model".to_string(),
            fmt::count(r.vertices_no_model),
        ])
        .row(["frames selected".to_string(), fmt::count(f.selected)])
        .row([
            "  registered (x_i on the object)".to_string(),
            fmt::count(f.registered),
        ])
        .row(["  used by a fit".to_string(), fmt::count(f.fitted)])
        .row([
            "  light positions / frames sharing one".to_string(),
            format!(
                "{} / {}",
                fmt::count(f.pooling.light_positions),
                fmt::count(f.pooling.pooled_frames)
            ),
        ])
        .row([
            "  no spot / off object / laser mismatch / unreadable".to_string(),
            format!(
                "{} / {} / {} / {}",
                fmt::count(f.no_spot),
                fmt::count(f.spot_off_object),
                fmt::count(f.laser_mismatch),
                fmt::count(f.unreadable)
            ),
        ])
        .row([
            "channel samples used".to_string(),
            fmt::count(r.samples.used as usize),
        ])
        .row([
            "  from other views of an x_i (pooled)".to_string(),
            fmt::count(r.samples.pooled as usize),
        ])
        .row([
            "  dropped: below noise / clipped / near x_i / uncovered".to_string(),
            format!(
                "{} / {} / {} / {}",
                fmt::count(r.samples.below_noise as usize),
                fmt::count(r.samples.saturated as usize),
                fmt::count(r.samples.excluded as usize),
                fmt::count(r.samples.uncovered as usize)
            ),
        ]);
    t
}

/// log E(x_i) (Eq. 8) of the fitted light positions, per channel: the in-sample error.
pub fn log_e_table(r: &FitReport) -> Table {
    let mut t = Table::new(["log E(x_i), Eq. 8", "red", "green", "blue"]);
    let row = |name: &str, v: [Option<f64>; 3]| {
        let mut cells = vec![name.to_string()];
        cells.extend(v.map(|x| fmt::opt(x, fmt::log_e)));
        cells
    };
    t.row(row("mean", r.log_e.mean));
    t.row(row("median", r.log_e.median));
    t
}

/// One cross-validated choice: every candidate's held-out error, its distance from the best
/// and the standard error of that, and which was chosen.
pub fn cv_table(c: &crate::pipeline::CvChoice) -> Table {
    let mut t = Table::new([
        c.name.as_str(),
        "held-out log E",
        "worse than the best",
        "standard error",
        "chosen",
    ]);
    for k in &c.candidates {
        t.row([
            k.value.clone(),
            fmt::opt(k.score, fmt::log_e),
            fmt::opt(k.worse_by, fmt::log_e),
            fmt::opt(k.se, fmt::log_e),
            if k.chosen { "yes" } else { "" }.to_string(),
        ]);
    }
    t
}

/// The histogram of the orders (n, m) chosen per light position ([`crate::order`]).
pub fn orders_table(r: &FitReport) -> Table {
    let mut t = Table::new([
        "terms n",
        "segments m",
        "light positions",
        "  of which the baseline's curve",
        "vertices with their own fit",
    ]);
    for c in &r.chosen_orders {
        t.row([
            c.terms.to_string(),
            c.segments.to_string(),
            fmt::count(c.light_positions),
            fmt::count(c.on_baseline),
            fmt::count(c.vertices),
        ]);
    }
    t
}

/// What the per-vertex order saved: `"14,336 numbers stored instead of 16,128 at n = 3, m = 1
/// (11 % fewer)"`.
pub fn model_size_line(r: &FitReport) -> String {
    let s = &r.model_size;
    let saved = if s.fixed_numbers > 0 {
        100.0 * (1.0 - s.numbers as f64 / s.fixed_numbers as f64)
    } else {
        0.0
    };
    format!(
        "{} numbers stored instead of {} at n = {}, m = {} for every vertex ({} % fewer)",
        fmt::count(s.numbers),
        fmt::count(s.fixed_numbers),
        s.max_terms,
        s.max_segments,
        fmt::sig(saved, 2)
    )
}

/// Wall time per stage.
pub fn stages_table(r: &FitReport) -> Table {
    let mut t = Table::new(["stage", "wall time"]);
    for (k, v) in &r.stage_seconds {
        t.row([k.clone(), fmt::seconds(*v)]);
    }
    t
}

/// The lines `subsurf fit` prints after a fit, its warnings first.
pub fn summary_lines(r: &FitReport) -> Vec<String> {
    let f = &r.frames;
    let lines = vec![
        format!(
            "{} vertices: {} fitted, {} interpolated, {} without model; failed before \
             interpolation: {}",
            fmt::count(r.vertices),
            fmt::count(r.vertices_fitted),
            fmt::count(r.vertices_interpolated),
            fmt::count(r.vertices_no_model),
            reasons(&r.failures)
        ),
        format!(
            "frames: {} selected = {} registered + {} registered but seen too grazing + {} no \
             spot + {} off object + {} laser mismatch + {} unreadable; {} used by fits{}",
            fmt::count(f.selected),
            fmt::count(f.registered),
            fmt::count(f.grazing),
            fmt::count(f.no_spot),
            fmt::count(f.spot_off_object),
            fmt::count(f.laser_mismatch),
            fmt::count(f.unreadable),
            fmt::count(f.fitted),
            if f.no_spot_frames.is_empty() {
                String::new()
            } else {
                format!(
                    "; no spot in frames {}",
                    crate::dataset::format_frame_list(&f.no_spot_frames)
                )
            }
        ),
        format!(
            "log E(x_i) (Eq. 8, in-sample) r / g / b: mean {}, median {}",
            fmt::rgb(r.log_e.mean, fmt::log_e),
            fmt::rgb(r.log_e.median, fmt::log_e)
        ),
        format!(
            "order per light position (n, m: light positions): {}; {}",
            if r.chosen_orders.is_empty() {
                "none".to_string()
            } else {
                r.chosen_orders
                    .iter()
                    .map(|c| {
                        format!(
                            "{}, {}: {} ({} on the baseline's curve)",
                            c.terms,
                            c.segments,
                            fmt::count(c.light_positions),
                            fmt::count(c.on_baseline)
                        )
                    })
                    .collect::<Vec<_>>()
                    .join("; ")
            },
            model_size_line(r)
        ),
        format!(
            "alpha (Eq. 6): {}; {} vertices from samples, {} interpolated",
            alpha_summary(&r.alpha),
            fmt::count(r.alpha.from_samples),
            fmt::count(r.alpha.interpolated)
        ),
        format!("alpha finer than the mesh: {}", lattice_summary(&r.alpha)),
        format!(
            "sample store: {}",
            r.sample_store.as_ref().map_or("none".into(), store_summary)
        ),
        format!(
            "stages: {}; peak RSS {}",
            r.stage_seconds
                .iter()
                .map(|(k, v)| format!("{k} {}", fmt::seconds(*v)))
                .collect::<Vec<_>>()
                .join(", "),
            fmt::opt(r.peak_rss_mib, |m| format!("{} MiB", fmt::sig(m, 3)))
        ),
        format!("reflectance check: {}", reflectance_summary(r)),
    ];
    let warnings = r.warnings.iter().map(|w| format!("warning: {w}"));
    warnings.chain(lines).collect()
}

/// The reflectance check ([`crate::pipeline::check`]) in one sentence.
pub fn reflectance_summary(r: &FitReport) -> String {
    match &r.reflectance_check {
        None => "none (exact fits)".to_string(),
        Some(c) => format!(
            "{} light positions fitted again exactly: diffuse reflectance within reach {} ± {} \
             (single positions ± {}, worst {}); {}",
            fmt::count(c.checked),
            signed_percent(c.mean),
            percent(c.standard_error),
            percent(c.spread),
            signed_percent(c.worst),
            if c.biased() {
                "biased".to_string()
            } else {
                format!("no bias beyond ±{}", percent(c.tolerance))
            }
        ),
    }
}

fn percent(x: f64) -> String {
    format!("{} %", fmt::sig(100.0 * x, 2))
}

fn signed_percent(x: f64) -> String {
    format!(
        "{}{} %",
        if x < 0.0 { "−" } else { "+" },
        fmt::sig(100.0 * x.abs(), 2)
    )
}

/// How the run's sample store came to be: opened from the cache, or extracted (and why a cache
/// of the same options was not used, if one could not be read).
fn store_summary(s: &crate::store::StoreReport) -> String {
    let how = if s.from_cache {
        format!("opened from the cache in {}", fmt::seconds(s.seconds))
    } else {
        format!(
            "{} frames decoded once in {}",
            fmt::count(s.frames_decoded),
            fmt::seconds(s.seconds)
        )
    };
    let mut out = format!(
        "{how}; {} vertex and {} lattice samples, {} frames spilled to disk",
        fmt::count(s.vertex_samples as usize),
        fmt::count(s.point_samples as usize),
        fmt::count(s.spilled)
    );
    if let Some(why) = &s.cache_rejected {
        out.push_str(&format!("; the cache was ignored: {why}"));
    }
    if let Some(why) = &s.not_cached {
        out.push_str(&format!("; not cached: {why}"));
    }
    out
}

/// Where a fit came from and went to, for its report.
#[derive(Clone, Debug)]
pub struct FitInputs<'a> {
    /// The scan dataset.
    pub scan: &'a Path,
    /// The model file written.
    pub model: &'a Path,
    /// Its size.
    pub model_bytes: u64,
    /// Pictures drawn beside the report (error map, model viewer).
    pub pictures: Vec<Figure>,
}

/// The report of `subsurf fit`.
pub fn fit_report(r: &FitReport, inputs: &FitInputs<'_>) -> Report {
    let mut rep = Report::new("subsurf fit");
    rep.paragraph(format!(
        "Scan `{}` → model `{}` ({}). {} of {} vertices have their own fit, {} are interpolated \
         from neighbours, {} have no model. Failed fits before interpolation: {}. Terms dropped \
         because the samples do not support them: {}; terms that hardly decay, held at the least \
         decay beside the others: {}.",
        inputs.scan.display(),
        inputs.model.display(),
        fmt::bytes(inputs.model_bytes),
        fmt::count(r.vertices_fitted),
        fmt::count(r.vertices),
        fmt::count(r.vertices_interpolated),
        fmt::count(r.vertices_no_model),
        reasons(&r.failures),
        reasons(&r.terms_dropped),
        fmt::count(r.terms_held),
    ));
    if !r.warnings.is_empty() {
        rep.heading("Warnings");
        for w in &r.warnings {
            rep.paragraph(format!("{w}."));
        }
    }
    rep.heading("Error");
    rep.table(
        log_e_table(r),
        Some(format!(
            "In-sample: each fitted light position x_i on its own samples ({} positions). A \
             model is judged by its error on frames it did not see: `subsurf fit \
             --exclude-frames` then `subsurf evaluate --frames`.",
            fmt::count(r.log_e.count)
        )),
    );
    rep.paragraph(format!(
        "Reflectance check (a preset's fits against exact fits of the same light positions, \
         compared by the diffuse reflectance 2π∫ r R_d(r) dr each predicts within reach): {}.",
        reflectance_summary(r)
    ));
    rep.heading("Model order");
    rep.table(
        orders_table(r),
        Some(format!(
            "\"Model only what the scene requires\": each light position's terms n and direction \
             segments m are chosen from its own samples (corrected Akaike \
             information criterion on the log residuals: fewer samples, smaller models; the \
             smallest model within 2 of the best; the smallest candidate is the homogeneous \
             baseline's curve with the position's own channel scales). {}.",
            model_size_line(r)
        )),
    );
    if let Some(cv) = &r.cross_validation {
        rep.heading("Choices (cross-validated)");
        rep.paragraph(format!(
            "{} ({} fits, {} s). Each candidate's error is the mean log E (Eq. 8) of the frames \
             of every fold, predicted by a fit of the other folds; the simplest candidate within \
             one standard error of the best is chosen.{}",
            cv.rule,
            fmt::count(cv.fits),
            fmt::sig(cv.seconds, 3),
            cv.skipped
                .as_ref()
                .map_or(String::new(), |w| format!(" {w}."))
        ));
        for c in &cv.choices {
            if c.candidates.is_empty() {
                // A choice with nothing to compare (the lattice where none was found).
                rep.paragraph(format!("{}: {} ({}).", c.name, c.chosen, c.rule));
                continue;
            }
            rep.table(
                cv_table(c),
                Some(format!("{}: {} chosen.", c.name, c.chosen)),
            );
        }
    }
    rep.heading("Data");
    rep.table(counts_table(r), None);
    rep.paragraph(format!(
        "Modulation texture alpha (Eq. 6): {}; {} vertices from their samples, {} \
         interpolated, {} at 1.",
        alpha_summary(&r.alpha),
        fmt::count(r.alpha.from_samples),
        fmt::count(r.alpha.interpolated),
        fmt::count(r.alpha.default_one)
    ));
    rep.paragraph(format!(
        "Alpha finer than the mesh (section 5, a per-face lattice, `face_alpha`): {}.",
        lattice_summary(&r.alpha)
    ));
    rep.heading("Time");
    rep.table(
        stages_table(r),
        Some(format!(
            "Peak memory {}.",
            fmt::opt(r.peak_rss_mib, |m| format!("{} MiB", fmt::sig(m, 3)))
        )),
    );
    if !inputs.pictures.is_empty() {
        rep.heading("Pictures");
        rep.figures(inputs.pictures.clone());
    }
    rep
}

/// The alpha rounds in one sentence: how many ran, whether they converged, and how much each
/// texel was shrunk towards alpha = 1 ([`crate::model::empirical_prior`]).
pub fn alpha_summary(a: &crate::pipeline::AlphaReport) -> String {
    let prior = |p: f64| {
        if p >= crate::model::ALPHA_PRIOR_MAX {
            "all (no texture above the noise)".to_string()
        } else {
            fmt::sig(p, 2)
        }
    };
    format!(
        "{} fit rounds on alpha-divided samples, {} (last RMS change of ln alpha {}); each texel \
         shrunk towards 1 by r / g / b {} pseudo-samples (the noise within a texel over the \
         texture's variance between texels)",
        a.rounds,
        if a.converged {
            "converged"
        } else {
            "stopped at the round limit (the rounds the cross-validation chose, or \
             --alpha-rounds) while alpha still moved"
        },
        fmt::sig(a.last_change, 2),
        a.prior.map(prior).join(" / ")
    )
}

/// The lattice pass in one sentence: whether a lattice was written, its levels, the points
/// with data, the prior and the RMS detail per channel ([`crate::pipeline::detail`]).
pub fn lattice_summary(a: &crate::pipeline::AlphaReport) -> String {
    let Some(l) = &a.lattice else {
        return "off (alpha per vertex only)".into();
    };
    let levels = |m: &std::collections::BTreeMap<u8, usize>| {
        m.iter()
            .map(|(k, n)| format!("{} at {k}", fmt::count(*n)))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let prior = |p: f64| {
        if p >= crate::model::ALPHA_PRIOR_MAX {
            "cap".to_string()
        } else {
            fmt::sig(p, 2)
        }
    };
    format!(
        "{}; faces by level (rule, at most {}): {}; {} points between the vertices, with data \
         r / g / b {}; detail shrunk by {} pseudo-samples, RMS detail (ln alpha) {}",
        if l.written {
            format!("written, faces by level {}", levels(&l.levels))
        } else if l.kept_by_cv == Some(false) {
            "not written (the cross-validation's folds, judged at surface points, found it \
             predicts no better than alpha per vertex)"
                .to_string()
        } else {
            "not written (no detail above the noise: the images do not support a texture finer \
             than the mesh)"
                .to_string()
        },
        l.max_level,
        levels(&l.levels_by_rule),
        fmt::count(l.points),
        l.points_with_data.map(fmt::count).join(" / "),
        l.prior.map(prior).join(" / "),
        l.rms_detail.map(|x| fmt::sig(x, 2)).join(" / ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::FailReason;

    #[test]
    fn fit_summaries_have_no_debug_values_or_long_digit_runs() {
        let mut r = FitReport {
            vertices: 12_345,
            vertices_fitted: 12_000,
            ..FitReport::default()
        };
        r.failures.insert(FailReason::HighError, 3);
        r.failures.insert(FailReason::NoData, 342);
        r.log_e.mean = [Some(0.046_712_345_678_901), None, Some(0.012)];
        r.log_e.median = [Some(0.04), Some(0.1), Some(0.012)];
        r.alpha.last_change = 0.001_234_567_891;
        r.stage_seconds.insert("fit".into(), 1.234_567_891);
        r.reflectance_check = Some(crate::pipeline::check::ReflectanceCheck {
            checked: 16,
            tolerance: 0.03,
            ratios: vec![0.87; 16],
            mean: -0.130_000_000_1,
            standard_error: 0.004_567_891,
            spread: 0.018_271_564,
            worst: -0.134_567_891,
            ..Default::default()
        });
        r.warnings = r.derive_warnings();
        r.cross_validation = Some(crate::pipeline::CvReport {
            rule: "5 folds of whole turntable angles".into(),
            fits: 20,
            seconds: 61.234_567_89,
            choices: vec![crate::pipeline::CvChoice {
                name: "segments".into(),
                chosen: "4".into(),
                candidates: ["1", "4"]
                    .iter()
                    .map(|v| crate::pipeline::CvCandidate {
                        value: v.to_string(),
                        score: Some(0.146_123_456_789),
                        worse_by: Some(0.000_123_456_789),
                        se: Some(0.000_045_678_912),
                        chosen: *v == "4",
                        ..Default::default()
                    })
                    .collect(),
                ..Default::default()
            }],
            ..Default::default()
        });
        let lines = summary_lines(&r).join("\n");
        // No baseline, and a bias beyond the tolerance and the noise: both said first.
        assert!(
            lines.starts_with("warning: no homogeneous baseline"),
            "{lines}"
        );
        assert!(
            lines.contains(
                "warning: the preset's fits of 16 light positions predict 13.0 ± 0.5 % less"
            ),
            "{lines}"
        );
        assert!(
            lines.contains(
                "within reach −13 % ± 0.46 % (single positions ± 1.8 %, worst −13 %); biased"
            ),
            "{lines}"
        );
        assert!(lines.contains("12,345 vertices"), "{lines}");
        assert!(lines.contains("no data 342, high error 3"), "{lines}");
        assert!(lines.contains("mean 0.0467 / – / 0.0120"), "{lines}");
        let md = fit_report(
            &r,
            &FitInputs {
                scan: Path::new("scan"),
                model: Path::new("model.ply"),
                model_bytes: 123_456,
                pictures: Vec::new(),
            },
        )
        .to_markdown(Path::new("."));
        assert!(md.contains("Choices (cross-validated)"), "{md}");
        assert!(md.contains("segments: 4 chosen"), "{md}");
        for text in [&lines, &md] {
            assert!(!text.contains("Some("), "{text}");
            assert!(!text.contains("None"), "{text}");
            let longest = text
                .split(|c: char| !c.is_ascii_digit())
                .map(str::len)
                .max()
                .unwrap_or(0);
            assert!(longest <= 6, "{text}");
        }
    }
}
