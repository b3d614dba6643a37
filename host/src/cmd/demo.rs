//! `subsurf demo`: the main job end to end on built-in defaults, no hardware, no arguments.
//!
//! Simulated rig (the firmware's core, in virtual time as `scan --sim`) → `scan` of the built-in
//! object with the simulated camera, sampled as the material needs it (`scan::setup`: vertex spacing, pixel footprint, x_i
//! spacing and exposures all from the material's mean free path and brightness) → per-vertex fits
//! with every fifth frame held out (three solver presets: the speed/accuracy trade) → the fitted
//! model and the simulation's ground truth rendered under the same lights, and their difference →
//! held-out against in-sample error → fall-off plot, model maps → `report.md` and a
//! self-contained `report.html`, all in one folder.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use subsurf::calib::Calibration;
use subsurf::dataset::Dataset;
use subsurf::evaluate::evaluate_frames;
use subsurf::export::{self, ExportOptions, LatticeMode};
use subsurf::fit::{FitOptions, Preset, Terms};
use subsurf::modelfile::ModelFile;
use subsurf::pipeline::{
    FitReport, PipelineOptions, StoreOptions, fit_prepared, prepare, register_one,
};
use subsurf::render::{
    self, Camera, Image, Light, RenderOptions, ToneMapping, auto_exposure, relative_pixel_error,
};
use subsurf::report::{Figure, Report, Table, fmt};
use subsurf::rig::{ClientConfig, RigClient};
use subsurf::scan::driver::{ScanConfig, run};
use subsurf::scan::plan::{PlanOptions, PlanScene, coverage_plan};
use subsurf::scan::setup::{
    BUILTIN_RADIUS_MM, GROUND_TRUTH_FILE, builtin_image_size, builtin_object, builtin_target_mm,
    camera_from_spec, sim_exposures_s, sim_field, sim_noise_floor, write_ground_truth,
};

use super::progress::Bar;

/// Run the whole chain on the simulated rig and write the results into one folder.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output folder (created; files in it are overwritten).
    #[arg(long, default_value = "subsurf-demo")]
    out: PathBuf,
    /// Camera image size of the simulated scan (pixels per side). Default: the size whose pixel
    /// footprint resolves the material (`scan::setup::builtin_image_size`).
    #[arg(long)]
    size: Option<u32>,
    /// Every vertex gets a laser spot x_i this close (mm). Default: the spacing the held-out
    /// fidelity needs (`scan::setup::builtin_target_mm`); larger is a faster, coarser preview.
    #[arg(long)]
    target_mm: Option<f64>,
    /// Turntable angles of the scan.
    #[arg(long, default_value_t = 8)]
    angles: usize,
    /// Laser raster per side (coverage planner picks from it).
    #[arg(long, default_value_t = 24)]
    raster: usize,
    /// Every N-th frame is held out of the fit and used to judge it.
    #[arg(long, default_value_t = 5)]
    hold_out: usize,
    /// Size of the rendered pictures (pixels per side).
    #[arg(long, default_value_t = 480)]
    picture: u32,
    /// Cycles samples per pixel of the "in Blender" render (when Blender is present).
    #[arg(long, default_value_t = 32)]
    blender_samples: u32,
    /// Skip the "in Blender" render even when Blender is present.
    #[arg(long)]
    no_blender: bool,
}

fn bar(len: u64, msg: &str) -> Bar {
    let p = Bar::with_template("{msg:>12} {bar:40} {pos}/{len} {elapsed}");
    p.set_length(len);
    p.set_message(msg.to_string());
    p
}

/// One solver preset's fit, and how it did.
struct Fitted {
    name: &'static str,
    model: ModelFile,
    report: FitReport,
    fit_s: f64,
    /// Mean over channels of the mean log E on the training frames (same evaluator as held-out).
    in_sample: Option<f64>,
    in_sample_rgb: [Option<f64>; 3],
    /// … on the held-out frames.
    held_out: Option<f64>,
    held_out_rgb: [Option<f64>; 3],
    /// Mean relative pixel error of its key-light render against the ground truth's.
    render_error: Option<f64>,
    render_s: f64,
}

/// Mean log E over channels of `model` on `frames`, and per channel.
fn evaluate(
    ds: &Dataset,
    model: &ModelFile,
    frames: &[usize],
    opts: &PipelineOptions,
    msg: &str,
) -> Result<(Option<f64>, [Option<f64>; 3])> {
    let p = bar(0, msg);
    let (_, stats) = evaluate_frames(ds, model, frames, opts, &p)?;
    p.finish_and_clear();
    Ok((fmt::channel_mean(stats.mean), stats.mean))
}

/// A picture written into the report's folder.
fn figure(path: &Path, caption: impl Into<String>) -> Figure {
    Figure {
        path: path.to_path_buf(),
        caption: caption.into(),
    }
}

pub fn run_demo(args: &Args) -> Result<Vec<PathBuf>> {
    let t0 = Instant::now();
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut written = Vec::new();
    let mut timings: Vec<(&str, f64)> = Vec::new();
    // Evaluating a preset's model (held-out and in-sample frames), timed apart from its fit.
    let mut evaluations: Vec<(&str, f64)> = Vec::new();

    // 1. The simulated rig: the firmware's core on simulated hardware, in virtual time (as
    //    `scan --sim`): the exposures the material needs (seconds per frame) cost no wall time.
    let link = subsurf::sim::SimLink::clean(subsurf::sim::VirtualRig::new(
        subsurf::sim::SimParams::default(),
    ));
    let mut rig = RigClient::connect(link, ClientConfig::default())
        .context("handshake with the simulated rig")?;
    println!("simulated rig (firmware core, virtual time)");

    // 2. Scan the built-in object with the simulated camera, sampled as `scan --sim` does: the
    //    vertex spacing, pixel footprint and x_i spacing from the material's shortest mean free
    //    path, the exposures from its brightest scattered light and the laser spot.
    let ts = Instant::now();
    let obj = builtin_object();
    let mesh = obj.mesh();
    let (centre, radius) = obj.bounds();
    let size = args.size.unwrap_or_else(builtin_image_size);
    let target_mm = args.target_mm.unwrap_or_else(builtin_target_mm);
    if !(target_mm.is_finite() && target_mm > 0.0) {
        anyhow::bail!("--target-mm must be a positive distance, got {target_mm}");
    }
    if args.hold_out < 2 {
        anyhow::bail!("--hold-out must be at least 2 (every N-th frame is held out)");
    }
    let calib = Calibration::builtin_for(centre, radius, size);
    let scene = PlanScene::new(&mesh.positions, &mesh.triangles, &calib)?;
    let exposures = sim_exposures_s();
    let plan = coverage_plan(
        &scene,
        &PlanOptions {
            angles: args.angles,
            raster: args.raster,
            target_mm,
            exposures_s: exposures.clone(),
            ..PlanOptions::default()
        },
    )?;
    let scan_dir = out.join("scan");
    if scan_dir.exists() {
        std::fs::remove_dir_all(&scan_dir)
            .with_context(|| format!("clearing {}", scan_dir.display()))?;
    }
    let mut cfg = ScanConfig::new(
        scan_dir.clone(),
        plan,
        calib.clone(),
        subsurf::dataset::obj_bytes(&mesh),
    );
    cfg.noise_floor = Some(sim_noise_floor(&exposures));
    let mut camera = camera_from_spec("sim", &mesh, &calib, 7, std::time::Duration::from_secs(10))?;
    let p = bar(cfg.plan.frame_count() as u64, "scan");
    let summary = run(&cfg, &mut rig, camera.as_mut(), &p)?;
    p.finish_and_clear();
    drop(rig);
    write_ground_truth(&mesh, &scan_dir).context("writing the ground truth")?;
    let scan_s = ts.elapsed().as_secs_f64();
    timings.push(("scan (simulated camera, rig in virtual time)", scan_s));
    println!(
        "scanned {} frames in {} (rig time {})",
        summary.frames_written,
        fmt::seconds(scan_s),
        fmt::seconds(summary.rig_seconds)
    );

    // 3. Fits on all frames but every `hold_out`-th, with three solver presets.
    let ds = Dataset::open(&scan_dir).context("reading the scan back")?;
    let n_frames = ds.spec.frames.len();
    let held: Vec<usize> = (0..n_frames)
        .filter(|k| k % args.hold_out == 2 % args.hold_out)
        .collect();
    let train: Vec<usize> = (0..n_frames)
        .filter(|k| k % args.hold_out != 2 % args.hold_out)
        .collect();
    if held.is_empty() || train.is_empty() {
        anyhow::bail!("the scan has {n_frames} frames: too few to hold some out");
    }
    let opts = PipelineOptions::for_dataset(&ds);
    let truth_file = ModelFile::read(&scan_dir.join(GROUND_TRUTH_FILE))?;
    let presets: [(&str, FitOptions); 3] = [
        ("draft", Preset::Draft.options()),
        ("balanced", Preset::Balanced.options()),
        (
            "exact",
            FitOptions {
                terms: Terms::Fixed(3),
                ..FitOptions::default()
            },
        ),
    ];
    // The one decode of the training frames into the sample store, timed on its own: every
    // preset then fits from the same store, so no preset's time holds the decode (before, the
    // first preset's did, and draft looked slower than balanced).
    let p = bar(0, "decode");
    let td = Instant::now();
    let run = prepare(&ds, &train, &opts, &StoreOptions::default(), &p)
        .context("decoding the training frames into the sample store")?;
    p.finish_and_clear();
    let decode_s = td.elapsed().as_secs_f64();
    timings.push(("decode of the training frames (sample store)", decode_s));
    let mut fits = Vec::new();
    for (name, fit_options) in presets {
        let p = bar(0, &format!("fit {name}"));
        let tf = Instant::now();
        let fitted = fit_prepared(&run, &train, &fit_options, &p)
            .with_context(|| format!("fitting the scan ({name} preset)"))?;
        p.finish_and_clear();
        let fit_s = tf.elapsed().as_secs_f64();
        timings.push((name, fit_s));
        let tv = Instant::now();
        let (held_out, held_out_rgb) = evaluate(&ds, &fitted.model, &held, &opts, "held out")?;
        let (in_sample, in_sample_rgb) = evaluate(&ds, &fitted.model, &train, &opts, "in sample")?;
        evaluations.push((name, tv.elapsed().as_secs_f64()));
        println!(
            "fit ({name}): {} s, log E held out {}, in sample {}",
            fmt::sig(fit_s, 3),
            fmt::opt(held_out, fmt::log_e),
            fmt::opt(in_sample, fmt::log_e)
        );
        fits.push(Fitted {
            name,
            model: fitted.model,
            report: fitted.report,
            fit_s,
            in_sample,
            in_sample_rgb,
            held_out,
            held_out_rgb,
            render_error: None,
            render_s: 0.0,
        });
    }
    let te = Instant::now();
    let (truth_held, truth_held_rgb) = evaluate(&ds, &truth_file, &held, &opts, "truth")?;
    let (truth_in, truth_in_rgb) = evaluate(&ds, &truth_file, &train, &opts, "truth")?;
    timings.push((
        "ground truth's error (the floor)",
        te.elapsed().as_secs_f64(),
    ));
    // The model shown is the exact fit (the `subsurf fit` default).
    let shown = fits.len() - 1;
    fits[shown].model.write(&out.join("model.ply"))?;
    written.push(out.join("model.ply"));
    std::fs::write(
        out.join("fit-report.json"),
        serde_json::to_string_pretty(&fits[shown].report)?,
    )?;
    let model = fits[shown].model.clone();
    render::validate(&model)?;
    let truth = &truth_file;

    // 4. Ground truth and model under the same lights, the same camera, the same exposure
    //    (chosen from the ground truth's image), and their difference.
    let tr = Instant::now();
    let (lo, hi) = truth.bounds();
    let cam = Camera::framing(lo, hi, render::DEFAULT_VIEW, args.picture, args.picture)?;
    let lights: [(&str, &str, Vec<Light>); 2] = [
        (
            "key-light",
            "key light",
            Light::defaults_for(truth.bounds()),
        ),
        (
            "back-light",
            "back light",
            vec![Light::Point {
                position: [
                    centre[0] - 2.0 * radius,
                    centre[1] + 5.0 * radius,
                    centre[2] + 2.0 * radius,
                ],
                intensity: [900.0 * radius * radius; 3],
            }],
        ),
    ];
    let ropts = RenderOptions::default();
    let mut render_rows = Table::new([
        "picture",
        "light",
        "exposure",
        "lit pixels",
        "clipped",
        "render time",
    ]);
    let mut compare_figures = Vec::new();
    let mut diff_rows = Table::new([
        "light",
        "mean |model − truth| / truth",
        "95th percentile",
        "mean signed",
    ]);
    let mut clip_max: f64 = 0.0;
    let mut key_truth: Option<Image> = None;
    let mut key_exposure = 1.0;
    for (slug, light_name, light) in &lights {
        let rt = render::render(truth, light, &cam, &ropts)?;
        let rm = render::render(&model, light, &cam, &ropts)?;
        let exposure = auto_exposure(&rt.image);
        let mut save = |name: String, img: &Image, secs: f64, what: &str| -> Result<ToneMapping> {
            let png = out.join(&name);
            let tone = render::save_png(img, Some(exposure), &png)?;
            render::save_exr(img, &png.with_extension("exr"))?;
            written.push(png);
            render_rows.row([
                format!("`{name}` (+ `.exr`)"),
                format!("{light_name}, {what}"),
                format!("x{}", fmt::sig(tone.exposure, 3)),
                fmt::count(tone.lit_pixels),
                fmt::percent(tone.clipped, 2),
                fmt::seconds(secs),
            ]);
            Ok(tone)
        };
        let tt = save(
            format!("render-truth-{slug}.png"),
            &rt.image,
            rt.seconds.iter().sum(),
            "ground truth",
        )?;
        let tm = save(
            format!("render-{slug}.png"),
            &rm.image,
            rm.seconds.iter().sum(),
            "fitted model",
        )?;
        clip_max = clip_max.max(tt.clipped).max(tm.clipped);
        let diff_png = out.join(format!("render-difference-{slug}.png"));
        let d = subsurf::plot::difference_picture(&diff_png, &rm.image, &rt.image, 1e-3)?;
        written.push(diff_png.clone());
        diff_rows.row([
            light_name.to_string(),
            fmt::percent(d.mean_abs, 1),
            fmt::percent(d.p95_abs, 1),
            fmt::percent(d.mean_signed, 1),
        ]);
        compare_figures.push(vec![
            figure(
                &out.join(format!("render-truth-{slug}.png")),
                format!("Ground truth, {light_name}"),
            ),
            figure(
                &out.join(format!("render-{slug}.png")),
                format!("Fitted model, {light_name}, same exposure"),
            ),
            figure(
                &diff_png,
                format!(
                    "Difference, {light_name}: red = model brighter, blue = darker, scale ±{}",
                    fmt::percent(d.range, 0)
                ),
            ),
        ]);
        if *slug == "key-light" {
            key_truth = Some(rt.image);
            key_exposure = exposure;
        }
    }
    // 4b. The shown model exported for Blender and rendered there under the key light and the
    //    same camera (Cycles, `export::compare`), against subsurf's render of the same model.
    // A Blender that is there but unusable (too old, broken) does not stop the demo: the
    // column stays empty and the reason is printed.
    let blender = if args.no_blender {
        None
    } else {
        export::find_blender(None).unwrap_or_else(|e| {
            println!("not rendering in Blender: {e}");
            None
        })
    };
    let mut in_blender: Option<(export::Comparison, PathBuf)> = None;
    if let (Some(b), Some((_, _, key))) = (&blender, lights.first()) {
        let tb = Instant::now();
        let dir = out.join("blender");
        let opts = ExportOptions {
            lattice: LatticeMode::Refine,
            eta: ropts.eta,
            lights: key.clone(),
            camera: cam.clone(),
            samples: args.blender_samples,
            // The demo compares Cycles with subsurf's own render, where the total reflectance
            // T is what makes the two agree under uniform light.
            colour: export::ColourRule::Total,
        };
        let p = bar(0, "export");
        let exported = export::export(&model, &opts, &p)?;
        p.finish_and_clear();
        exported.write(&dir)?;
        println!(
            "rendering the exported model in {} (Cycles, {} samples)",
            b.version_line, args.blender_samples
        );
        let c = export::compare(&model, &opts, &ropts, b, &dir, false)
            .context("rendering the exported model in Blender")?;
        export::write_report(&model, &exported, Some(&c), None, Some(b), &dir)?;
        println!(
            "in Blender: mean relative pixel error against subsurf's render {}",
            fmt::percent(c.mean_relative_error, 1)
        );
        // The Cycles picture beside the others: same exposure as the key-light row.
        let cycles = export::read_render(&dir.join("cycles.exr"))?;
        let png = out.join("render-blender-key-light.png");
        render::save_png(&cycles, Some(key_exposure), &png)?;
        written.push(png.clone());
        if let Some(row) = compare_figures.first_mut() {
            row.insert(
                2,
                figure(
                    &png,
                    "In Blender: the exported model in Cycles, key light, same camera and exposure",
                ),
            );
            row.push(figure(
                &dir.join("difference.png"),
                "Blender − subsurf: (Cycles − subsurf's render) / subsurf's render, same model",
            ));
        }
        timings.push((
            "export to Blender and Cycles render",
            tb.elapsed().as_secs_f64(),
        ));
        in_blender = Some((c, dir));
    } else if blender.is_none() && !args.no_blender {
        println!("no Blender found: the report's \"in Blender\" column stays empty");
    }
    // Every preset's model under the key light against the truth: the render column of the trade.
    if let (Some(kt), Some((_, _, key))) = (&key_truth, lights.first()) {
        for f in &mut fits {
            let r = render::render(&f.model, key, &cam, &ropts)?;
            f.render_s = r.seconds.iter().sum();
            f.render_error = relative_pixel_error(&r.image, kt, 1e-3);
        }
    }
    timings.push(("renders and differences", tr.elapsed().as_secs_f64()));

    // 5. Pictures: Figure 3 from one scanned frame, error maps, model viewer.
    let tp = Instant::now();
    // The fits' run (its sample store from the dataset's cache: no frame is decoded again).
    let ctx = subsurf::pipeline::prepare(&ds, &train, &opts, &Default::default(), &())?;
    // The training frame whose x_i has the most green samples.
    let mut best: Option<(usize, Vec<f64>, Vec<f64>)> = None;
    for &k in train.iter().step_by(3) {
        let Ok(reg) = register_one(&ctx, k) else {
            continue;
        };
        let Ok(fs) = ctx.samples(&reg) else {
            continue;
        };
        let (r, s): (Vec<f64>, Vec<f64>) = fs
            .samples
            .iter()
            .filter(|s| s.valid & 2 != 0)
            .map(|s| (s.r, s.value[1]))
            .unzip();
        if best.as_ref().is_none_or(|b| b.1.len() < r.len()) {
            best = Some((k, r, s));
        }
    }
    let mut falloff = None;
    if let Some((k, r, s)) = best.filter(|b| b.1.len() >= 8) {
        let f = out.join("falloff.png");
        let fits = subsurf::evaluate::compare_falloff(&r, &s, 1.3);
        let sum = subsurf::plot::falloff_figure(
            &f,
            &format!("Fall-off of frame {k}'s x_i (green)"),
            &r,
            &s,
            &fits,
        )?;
        written.push(f.clone());
        falloff = Some((f, k, sum));
    }
    let e = out.join("error-map.png");
    let draft_vm = &fits[0].model;
    subsurf::plot::error_maps(
        &e,
        &[
            ("exact preset (shown)".into(), &model),
            ("draft preset".into(), draft_vm),
        ],
        render::DEFAULT_VIEW,
        (360, 380),
    )?;
    written.push(e.clone());
    let m = out.join("model.png");
    subsurf::plot::model_viewer(&m, &model, render::DEFAULT_VIEW, (300, 340))?;
    written.push(m.clone());
    timings.push(("plots", tp.elapsed().as_secs_f64()));
    let total_s = t0.elapsed().as_secs_f64();

    // 6. The report, for terminals (report.md) and browsers (report.html).
    let shown_fit = &fits[shown];
    let mfp = 1.0 / sim_field().steepest_falloff();
    let mut rep = Report::new("subsurf demo");
    rep.paragraph(format!(
        "A simulated rig scanned the built-in object ({} frames in {}); the \
         per-vertex model (Fuchs et al. 2005, isotropic Eq. 9 with the modulation texture, Eq. \
         2/6) was fitted on {} of them and judged on the {} it never saw, then rendered next to \
         the simulation's ground truth under the same lights. Whole run: {}.",
        fmt::count(n_frames),
        fmt::seconds(scan_s),
        fmt::count(train.len()),
        fmt::count(held.len()),
        fmt::seconds(total_s)
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
        fmt::percent(clip_max, 2)
    ));
    for row in compare_figures {
        rep.figures(row);
    }
    diff_rows
        .header
        .push("in Blender: mean |Cycles − model| / model".into());
    for (k, row) in diff_rows.rows.iter_mut().enumerate() {
        row.push(match (&in_blender, k) {
            (Some((c, _)), 0) => fmt::percent(c.mean_relative_error, 1),
            _ => fmt::MISSING.to_string(),
        });
    }
    rep.table(
        diff_rows,
        Some(match &in_blender {
            Some((c, dir)) => format!(
                "Over lit pixels (truth above 0.1 % of its brightest). In Blender: the model \
                 exported by `subsurf export` (per-vertex subsurface colour and radius of \
                 Cycles' Principled BSDF, docs/export.md) rendered in Cycles ({} samples, {}) \
                 under the key light, against subsurf's render of the same model, per channel \
                 over lit pixels; Cycles' own sampling noise is part of it. Export and \
                 report: `{}/`.",
                c.samples,
                fmt::seconds(c.cycles_seconds),
                dir.strip_prefix(out).unwrap_or(dir).display()
            ),
            None => "Over lit pixels (truth above 0.1 % of its brightest). In Blender: — \
                     (Blender was not found; `subsurf export` writes the scene for it)."
                .into(),
        }),
    );
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
    for f in &fits {
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
        fmt::count(truth.len()),
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
            fmt::seconds(decode_s)
        )),
    );

    rep.heading("Fall-off");
    if let Some((f, k, sum)) = &falloff {
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
        &m,
        "Model maps: modulation texture alpha, total reflectance, reach of the fall-off, and \
         which vertices were fitted, interpolated or left without a model.",
    )]);
    rep.figures(vec![figure(
        &e,
        "log E(x_i) (Eq. 8) per fitted light position, exact and draft presets on one scale; \
             grey: no fit of its own.",
    )]);
    rep.table(subsurf::report::fit::counts_table(&shown_fit.report), None);
    rep.paragraph(format!(
        "Failed fits before interpolation: {}. Terms dropped because the samples do not support \
         them: {}. Alpha (Eq. 6): {}.",
        subsurf::report::fit::reasons(&shown_fit.report.failures),
        subsurf::report::fit::reasons(&shown_fit.report.terms_dropped),
        subsurf::report::fit::alpha_summary(&shown_fit.report.alpha)
    ));

    rep.heading("Scan");
    let mut scan_t = Table::new(["", "value", "why"]);
    scan_t
        .row([
            "object".to_string(),
            format!(
                "sphere, r = {} mm, {} vertices",
                BUILTIN_RADIUS_MM,
                fmt::count(mesh.positions.len())
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
                fmt::count(n_frames),
                args.angles,
                fmt::sig(target_mm, 2)
            ),
            format!(
                "{} mean free paths: what held-out prediction needs",
                fmt::sig(target_mm / mfp, 2)
            ),
        ])
        .row([
            "exposures".to_string(),
            exposures
                .iter()
                .map(|s| format!("{} ms", fmt::sig(s * 1e3, 3)))
                .collect::<Vec<_>>()
                .join(" + "),
            "HDR: the spot unclipped, the brightest scattered light just below clipping"
                .to_string(),
        ])
        .row([
            "noise floor".to_string(),
            fmt::sig(cfg.noise_floor.unwrap_or(0.0), 2),
            "one pixel's SNR = 50 at the longest exposure".to_string(),
        ]);
    rep.table(
        scan_t,
        Some(format!(
            "Rig: the firmware's core on simulated hardware, in virtual time; the same scan on \
             the rig would take {} (turntable moves, galvo settling, exposures). Dataset: \
             `scan/` (with `ground-truth.ply`).",
            fmt::seconds(summary.rig_seconds)
        )),
    );

    rep.heading("Time");
    let mut time_t = Table::new(["stage", "wall time"]);
    for (k, v) in &timings {
        if fits.iter().any(|f| f.name == *k) {
            time_t.row([format!("fit, {k} preset"), fmt::seconds(*v)]);
            if let Some((_, e)) = evaluations.iter().find(|(n, _)| n == k) {
                time_t.row([
                    format!("evaluation of the {k} fit (held-out and in-sample frames)"),
                    fmt::seconds(*e),
                ]);
            }
        } else {
            time_t.row([(*k).to_string(), fmt::seconds(*v)]);
        }
    }
    time_t.row(["whole demo".to_string(), fmt::seconds(total_s)]);
    rep.table(
        time_t,
        Some(format!("{} worker threads.", rayon::current_num_threads())),
    );
    rep.paragraph(
        "Files: `model.ply` (the model, docs/model-format.md), `fit-report.json`, \
         `render-*.png` + `.exr`, `falloff.png`, `error-map.png`, `model.png`, `scan/`, and \
         with Blender `blender/` (the export, its report and the Cycles render).",
    );
    let [md, html] = rep.write(out, "report").map_err(|e| anyhow!(e))?;
    written.insert(0, html);
    written.insert(0, md);
    Ok(written)
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

pub fn run_cmd(args: Args) -> Result<()> {
    let files = run_demo(&args)?;
    println!("demo results in {}:", display(&args.out));
    for f in files {
        println!("  {}", display(&f));
    }
    Ok(())
}

fn display(p: &Path) -> String {
    p.display().to_string()
}
