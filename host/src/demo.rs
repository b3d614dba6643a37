//! `subsurf demo`: the main job end to end on built-in defaults, no hardware, no arguments.
//!
//! Simulated rig (the firmware's core, in virtual time as `scan --sim`) → `scan` of the built-in
//! object with the simulated camera, sampled as the material needs it (`scan::setup`: vertex
//! spacing, pixel footprint, x_i spacing and exposures all from the material's mean free path
//! and brightness) → per-vertex fits with every fifth frame held out (three solver presets: the
//! speed/accuracy trade) → the fitted model and the simulation's ground truth rendered under the
//! same lights, and their difference → with Blender, the model exported and rendered in Cycles,
//! judged against the same ground truth with Cycles' two-seed noise beside it →
//! held-out against in-sample error → fall-off plot, model maps → `report.md` and a
//! self-contained `report.html`, all in one folder.
//!
//! Here the run and what it measured ([`DemoRun`]); the report is assembled from that by
//! [`crate::report::demo`]. The command (`cmd/demo.rs`) only parses and draws progress.

use std::path::PathBuf;
use std::time::Instant;

use crate::calib::Calibration;
use crate::dataset::Dataset;
use crate::evaluate::{EvaluateError, evaluate_frames};
use crate::export::{self, ExportError, ExportOptions, LatticeMode};
use crate::fit::{FitOptions, Preset, Terms};
use crate::modelfile::{ModelFile, ModelFileError};
use crate::pipeline::{
    FitReport, PipelineError, PipelineOptions, StoreOptions, fit_prepared, prepare, register_one,
};
use crate::plot::{DifferenceStats, FalloffSummary, PlotError};
use crate::progress::Stages;
use crate::render::{
    self, Camera, Image, Light, RenderError, RenderOptions, ToneMapping, auto_exposure,
    relative_pixel_error,
};
use crate::report::fmt;
use crate::rig::{ClientConfig, RigClient, RigClientError};
use crate::scan::driver::{ScanConfig, ScanError, run as run_scan};
use crate::scan::plan::{PlanError, PlanOptions, PlanScene, coverage_plan};
use crate::scan::setup::{
    GROUND_TRUTH_FILE, builtin_image_size, builtin_object, builtin_target_mm, camera_from_spec,
    sim_exposures_s, sim_field, sim_noise_floor, write_ground_truth,
};

/// The demo's export scales the colour by Cycles' gather against subsurf's under the key light
/// it renders with ([`export::GatherMode::Lights`]): on the demo's 4 mm sphere, no larger than
/// the profile's reach, Cycles' disk step otherwise gathers a quarter more light than subsurf's
/// renderer and its picture is that much brighter than the truth (docs/export.md).
pub const GATHER: export::GatherMode = export::GatherMode::Lights;

/// The demo's settings (the command's flags; `None`: the built-in default).
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Output folder (created; files in it are overwritten).
    pub out: PathBuf,
    /// Camera image size of the simulated scan; `None`: `scan::setup::builtin_image_size`.
    pub size: Option<u32>,
    /// Laser spot spacing (mm); `None`: `scan::setup::builtin_target_mm`.
    pub target_mm: Option<f64>,
    /// Turntable angles of the scan.
    pub angles: usize,
    /// Laser raster per side (coverage planner picks from it).
    pub raster: usize,
    /// Every N-th frame is held out of the fit and used to judge it.
    pub hold_out: usize,
    /// Size of the rendered pictures (pixels per side).
    pub picture: u32,
    /// Cycles samples per pixel of the "in Blender" renders (two seeds: the second measures
    /// Cycles' own noise, shown beside its figure).
    pub blender_samples: u32,
    /// Skip the "in Blender" render even when Blender is present.
    pub no_blender: bool,
}

/// Why the demo stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DemoError {
    /// A setting is out of range, or the scan too small to hold frames out.
    #[error("{0}")]
    Invalid(String),
    /// A step failed; `what` names it, `source` says why.
    #[error("{what}")]
    Step {
        /// The step (e.g. `handshake with the simulated rig`).
        what: String,
        /// Why.
        #[source]
        source: Box<DemoError>,
    },
    /// A file or folder could not be written.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The fit report could not be serialised.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The simulated rig failed.
    #[error(transparent)]
    Rig(#[from] RigClientError),
    /// The scan could not be planned.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The simulated camera could not be made.
    #[error(transparent)]
    Camera(#[from] crate::scan::camera::CameraError),
    /// The scan failed.
    #[error(transparent)]
    Scan(#[from] ScanError),
    /// The scan could not be read back.
    #[error(transparent)]
    Dataset(#[from] crate::dataset::DatasetError),
    /// A model file could not be read or written.
    #[error(transparent)]
    Model(#[from] ModelFileError),
    /// Decoding or fitting failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// Judging a model failed.
    #[error(transparent)]
    Evaluate(#[from] EvaluateError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// A picture could not be drawn.
    #[error(transparent)]
    Plot(#[from] PlotError),
    /// Exporting or rendering in Blender failed.
    #[error(transparent)]
    Export(#[from] ExportError),
    /// The report could not be written.
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
}

crate::util::step_context!(DemoError);

/// One solver preset's fit, and how it did.
#[derive(Debug, Clone)]
pub struct Fitted {
    /// The preset's name (`draft`, `balanced`, `exact`).
    pub name: &'static str,
    /// The fitted model.
    pub model: ModelFile,
    /// The fit's report.
    pub report: FitReport,
    /// Fit time from the sample store (s).
    pub fit_s: f64,
    /// Mean over channels of the mean log E on the training frames (same evaluator as held-out).
    pub in_sample: Option<f64>,
    /// … per channel.
    pub in_sample_rgb: [Option<f64>; 3],
    /// … on the held-out frames.
    pub held_out: Option<f64>,
    /// … per channel.
    pub held_out_rgb: [Option<f64>; 3],
    /// Mean relative pixel error of its key-light render against the ground truth's.
    pub render_error: Option<f64>,
    /// Its key-light render's time (s).
    pub render_s: f64,
}

/// One rendered picture of the comparison (a row of the report's render table).
#[derive(Debug, Clone)]
pub struct RenderedPicture {
    /// File name in the output folder (the PNG; the `.exr` beside it).
    pub name: String,
    /// The light's name.
    pub light_name: String,
    /// `ground truth` or `fitted model`.
    pub what: String,
    /// How it was tone mapped.
    pub tone: ToneMapping,
    /// Render time (s).
    pub seconds: f64,
}

/// Ground truth and model under one light, and their difference.
#[derive(Debug, Clone)]
pub struct LightComparison {
    /// The light's name.
    pub light_name: String,
    /// The ground truth's picture.
    pub truth_png: PathBuf,
    /// The model's picture, same exposure.
    pub model_png: PathBuf,
    /// The difference picture.
    pub difference_png: PathBuf,
    /// What the difference picture shows.
    pub difference: DifferenceStats,
    /// The Cycles picture and its difference from the ground truth (key light, with Blender).
    pub blender: Option<(PathBuf, PathBuf)>,
}

/// The shown model exported to Blender and rendered by Cycles under the key light, judged
/// against the ground truth as subsurf's render is: the question is which renderer is closer
/// to the real material, not how close the two renderers are to each other.
#[derive(Debug, Clone)]
pub struct InBlender {
    /// Cycles against subsurf's render of the same model, with Cycles' two-seed noise.
    pub comparison: export::Comparison,
    /// The export's folder.
    pub dir: PathBuf,
    /// The conversion used (the export's default).
    pub colour: export::ColourRule,
    /// The gather correction used ([`GATHER`]).
    pub gather: export::GatherMode,
    /// Mean relative pixel error of Cycles' render against the ground truth's over lit pixels:
    /// the measure of [`Fitted::render_error`], so the two stand side by side.
    pub against_truth: f64,
    /// The (Cycles − truth) / truth difference picture's statistics.
    pub truth_difference: DifferenceStats,
}

/// Everything the demo measured, for its report.
#[derive(Debug, Clone)]
pub struct DemoRun {
    /// The settings it ran with.
    pub options: DemoOptions,
    /// Camera image size used.
    pub size: u32,
    /// Laser spot spacing used (mm).
    pub target_mm: f64,
    /// Vertices of the built-in object's mesh.
    pub mesh_vertices: usize,
    /// The material's shortest mean free path (mm).
    pub mean_free_path: f64,
    /// Exposures of every frame (s).
    pub exposures: Vec<f64>,
    /// The scan's noise floor.
    pub noise_floor: Option<f64>,
    /// Frames scanned.
    pub n_frames: usize,
    /// Wall time of the scan (s).
    pub scan_s: f64,
    /// The same scan's time on the rig (s).
    pub rig_seconds: f64,
    /// The frames fitted.
    pub train: Vec<usize>,
    /// The frames held out.
    pub held: Vec<usize>,
    /// Decode of the training frames into the sample store (s).
    pub decode_s: f64,
    /// The presets' fits: draft, balanced, exact (the shown model is the last).
    pub fits: Vec<Fitted>,
    /// The ground truth's vertices.
    pub truth_vertices: usize,
    /// The ground truth's mean log E on the held-out frames, and per channel.
    pub truth_held: (Option<f64>, [Option<f64>; 3]),
    /// … on the training frames.
    pub truth_in: (Option<f64>, [Option<f64>; 3]),
    /// The rendered pictures, in order.
    pub renders: Vec<RenderedPicture>,
    /// Ground truth against model per light (key light first).
    pub comparisons: Vec<LightComparison>,
    /// Largest clipped share of lit pixels in any render.
    pub clip_max: f64,
    /// Cycles' render of the exported model against the ground truth (with Blender).
    pub in_blender: Option<InBlender>,
    /// Figure 3: its picture, the frame and what it showed.
    pub falloff: Option<(PathBuf, usize, FalloffSummary)>,
    /// The model maps picture.
    pub model_png: PathBuf,
    /// The error maps picture.
    pub error_map_png: PathBuf,
    /// Wall time per stage (a preset's name: its fit).
    pub timings: Vec<(&'static str, f64)>,
    /// Evaluation time per preset (held-out and in-sample frames).
    pub evaluations: Vec<(&'static str, f64)>,
    /// Wall time of the whole demo (s).
    pub total_s: f64,
}

impl DemoRun {
    /// The fit shown (the exact preset, the `subsurf fit` default).
    pub fn shown(&self) -> &Fitted {
        &self.fits[self.fits.len() - 1]
    }
}

/// Mean log E over channels of `model` on `frames`, and per channel.
fn evaluate<U: Stages>(
    ui: &U,
    ds: &Dataset,
    model: &ModelFile,
    frames: &[usize],
    opts: &PipelineOptions,
    msg: &str,
) -> Result<(Option<f64>, [Option<f64>; 3]), DemoError> {
    let p = ui.stage(0, msg);
    let (_, stats) = evaluate_frames(ds, model, frames, opts, &p)?;
    ui.finish(p);
    Ok((fmt::channel_mean(stats.mean), stats.mean))
}

/// Runs the demo into `opts.out` and writes its report there; returns the files written
/// (`report.md`, `report.html` first).
pub fn run_demo<U: Stages>(opts: &DemoOptions, ui: &U) -> Result<Vec<PathBuf>, DemoError> {
    let t0 = Instant::now();
    let (run, mut written) = measure(opts, ui, t0)?;
    let rep = crate::report::demo::demo_report(&run);
    let [md, html] = rep.write(&opts.out, "report")?;
    written.insert(0, html);
    written.insert(0, md);
    Ok(written)
}

/// Stages 1–5 of the demo: what the report shows, and the files written.
fn measure<U: Stages>(
    args: &DemoOptions,
    ui: &U,
    t0: Instant,
) -> Result<(DemoRun, Vec<PathBuf>), DemoError> {
    let out = &args.out;
    std::fs::create_dir_all(out).step(|| format!("creating {}", out.display()))?;
    let mut written = Vec::new();
    let mut timings: Vec<(&'static str, f64)> = Vec::new();
    // Evaluating a preset's model (held-out and in-sample frames), timed apart from its fit.
    let mut evaluations: Vec<(&'static str, f64)> = Vec::new();

    // 1. The simulated rig: the firmware's core on simulated hardware, in virtual time (as
    //    `scan --sim`): the exposures the material needs (seconds per frame) cost no wall time.
    let link =
        crate::sim::SimLink::clean(crate::sim::VirtualRig::new(crate::sim::SimParams::default()));
    let mut rig = RigClient::connect(link, ClientConfig::default())
        .step(|| "handshake with the simulated rig".into())?;
    ui.say("simulated rig (firmware core, virtual time)");

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
        return Err(DemoError::Invalid(format!(
            "--target-mm must be a positive distance, got {target_mm}"
        )));
    }
    if args.hold_out < 2 {
        return Err(DemoError::Invalid(
            "--hold-out must be at least 2 (every N-th frame is held out)".into(),
        ));
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
        std::fs::remove_dir_all(&scan_dir).step(|| format!("clearing {}", scan_dir.display()))?;
    }
    let mut cfg = ScanConfig::new(
        scan_dir.clone(),
        plan,
        calib.clone(),
        crate::dataset::obj_bytes(&mesh),
    );
    cfg.noise_floor = Some(sim_noise_floor(&exposures));
    let mut camera = camera_from_spec("sim", &mesh, &calib, 7, std::time::Duration::from_secs(10))?;
    let p = ui.stage(cfg.plan.frame_count() as u64, "scan");
    let summary = run_scan(&cfg, &mut rig, camera.as_mut(), &p)?;
    ui.finish(p);
    drop(rig);
    write_ground_truth(&mesh, &scan_dir).step(|| "writing the ground truth".into())?;
    let scan_s = ts.elapsed().as_secs_f64();
    timings.push(("scan (simulated camera, rig in virtual time)", scan_s));
    ui.say(&format!(
        "scanned {} frames in {} (rig time {})",
        summary.frames_written,
        fmt::seconds(scan_s),
        fmt::seconds(summary.rig_seconds)
    ));

    // 3. Fits on all frames but every `hold_out`-th, with three solver presets.
    let ds = Dataset::open(&scan_dir).step(|| "reading the scan back".into())?;
    let n_frames = ds.spec.frames.len();
    let held: Vec<usize> = (0..n_frames)
        .filter(|k| k % args.hold_out == 2 % args.hold_out)
        .collect();
    let train: Vec<usize> = (0..n_frames)
        .filter(|k| k % args.hold_out != 2 % args.hold_out)
        .collect();
    if held.is_empty() || train.is_empty() {
        return Err(DemoError::Invalid(format!(
            "the scan has {n_frames} frames: too few to hold some out"
        )));
    }
    let opts = PipelineOptions::for_dataset(&ds);
    let truth_file = ModelFile::read(&scan_dir.join(GROUND_TRUTH_FILE))?;
    let presets: [(&'static str, FitOptions); 3] = [
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
    let p = ui.stage(0, "decode");
    let td = Instant::now();
    let run = prepare(&ds, &train, &opts, &StoreOptions::default(), &p)
        .step(|| "decoding the training frames into the sample store".into())?;
    ui.finish(p);
    let decode_s = td.elapsed().as_secs_f64();
    timings.push(("decode of the training frames (sample store)", decode_s));
    let mut fits = Vec::new();
    for (name, fit_options) in presets {
        let p = ui.stage(0, &format!("fit {name}"));
        let tf = Instant::now();
        let fitted = fit_prepared(&run, &train, &fit_options, &p)
            .step(|| format!("fitting the scan ({name} preset)"))?;
        ui.finish(p);
        let fit_s = tf.elapsed().as_secs_f64();
        timings.push((name, fit_s));
        let tv = Instant::now();
        let (held_out, held_out_rgb) =
            evaluate(ui, &ds, &fitted.model, &held, &opts, "log E held out")?;
        let (in_sample, in_sample_rgb) =
            evaluate(ui, &ds, &fitted.model, &train, &opts, "log E in sample")?;
        evaluations.push((name, tv.elapsed().as_secs_f64()));
        ui.say(&format!(
            "fit ({name}): {} s, log E held out {}, in sample {}",
            fmt::sig(fit_s, 3),
            fmt::opt(held_out, fmt::log_e),
            fmt::opt(in_sample, fmt::log_e)
        ));
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
    let truth_held = evaluate(
        ui,
        &ds,
        &truth_file,
        &held,
        &opts,
        "log E of the truth, held out",
    )?;
    let truth_in = evaluate(
        ui,
        &ds,
        &truth_file,
        &train,
        &opts,
        "log E of the truth, in sample",
    )?;
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
    let mut renders = Vec::new();
    let mut comparisons = Vec::new();
    let mut clip_max: f64 = 0.0;
    let mut key_truth: Option<Image> = None;
    let mut key_exposure = 1.0;
    for (slug, light_name, light) in &lights {
        let rt = render::render(truth, light, &cam, &ropts)?;
        let rm = render::render(&model, light, &cam, &ropts)?;
        let exposure = auto_exposure(&rt.image);
        let mut save =
            |name: String, img: &Image, secs: f64, what: &str| -> Result<ToneMapping, DemoError> {
                let png = out.join(&name);
                let tone = render::save_png(img, Some(exposure), &png)?;
                render::save_exr(img, &png.with_extension("exr"))?;
                written.push(png);
                renders.push(RenderedPicture {
                    name,
                    light_name: light_name.to_string(),
                    what: what.to_string(),
                    tone,
                    seconds: secs,
                });
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
        let d = crate::plot::difference_picture(&diff_png, &rm.image, &rt.image, 1e-3)?;
        written.push(diff_png.clone());
        comparisons.push(LightComparison {
            light_name: light_name.to_string(),
            truth_png: out.join(format!("render-truth-{slug}.png")),
            model_png: out.join(format!("render-{slug}.png")),
            difference_png: diff_png,
            difference: d,
            blender: None,
        });
        if *slug == "key-light" {
            key_truth = Some(rt.image);
            key_exposure = exposure;
        }
    }
    // 4b. The shown model exported for Blender and rendered there under the key light and the
    //    same camera (Cycles, `export::compare`, two seeds), judged against the ground truth's
    //    render as subsurf's render is; against subsurf's render too (the export's report).
    // A Blender that is there but unusable (too old, broken) does not stop the demo: the
    // column stays empty and the reason is printed.
    let blender = if args.no_blender {
        None
    } else {
        export::find_newest_blender().unwrap_or_else(|e| {
            ui.say(&format!("not rendering in Blender: {e}"));
            None
        })
    };
    let mut in_blender: Option<InBlender> = None;
    if let (Some(b), Some((_, _, key)), Some(kt)) = (&blender, lights.first(), &key_truth) {
        let tb = Instant::now();
        let dir = out.join("blender");
        // The conversion a user gets (`subsurf export`'s default): the demo judges what is
        // imported into Blender against the simulation's true material, not against subsurf.
        let colour = export::ColourRule::default();
        let opts = ExportOptions {
            lattice: LatticeMode::Refine,
            eta: ropts.eta,
            lights: key.clone(),
            camera: cam.clone(),
            samples: args.blender_samples,
            colour,
            gather: GATHER,
        };
        let p = ui.stage(0, "export");
        let exported = export::export(&model, &opts, &p)?;
        ui.finish(p);
        exported.write(&dir)?;
        ui.say(&format!(
            "rendering the exported model in {} (Cycles, {} samples, two seeds)",
            b.version_line, args.blender_samples
        ));
        // Two seeds: the second gives Cycles' own noise in the same measure as the figure, so a
        // reader sees how much of Cycles' distance from the truth is grain.
        let c = export::compare(&model, &opts, &ropts, b, &dir, true)
            .step(|| "rendering the exported model in Blender".into())?;
        export::write_report(&model, &exported, Some(&c), None, Some(b), &dir)?;
        let cycles = export::read_render(&dir.join("cycles.exr"))?;
        let against_truth = relative_pixel_error(&cycles, kt, 1e-3).ok_or_else(|| {
            DemoError::Invalid("Cycles' render and the ground truth share no lit pixel".into())
        })?;
        let diff_png = out.join("render-difference-blender-key-light.png");
        let truth_difference = crate::plot::difference_picture_of(
            &diff_png,
            &cycles,
            kt,
            1e-3,
            crate::plot::Compared {
                image: "Cycles",
                reference: "ground truth",
            },
        )?;
        written.push(diff_png.clone());
        ui.say(&format!(
            "in Blender: mean relative pixel error against the ground truth {} (Cycles' own \
             noise {}; against subsurf's render {})",
            fmt::percent(against_truth, 1),
            fmt::opt(c.cycles_noise, |x| fmt::percent(x, 1)),
            fmt::percent(c.mean_relative_error, 1)
        ));
        // The Cycles picture beside the others: same exposure as the key-light row.
        let png = out.join("render-blender-key-light.png");
        render::save_png(&cycles, Some(key_exposure), &png)?;
        written.push(png.clone());
        if let Some(row) = comparisons.first_mut() {
            row.blender = Some((png, diff_png));
        }
        timings.push((
            "export to Blender and Cycles renders (two seeds)",
            tb.elapsed().as_secs_f64(),
        ));
        in_blender = Some(InBlender {
            comparison: c,
            dir,
            colour,
            gather: GATHER,
            against_truth,
            truth_difference,
        });
    } else if blender.is_none() && !args.no_blender {
        ui.say("no Blender found: the report's \"in Blender\" column stays empty");
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
    let ctx = crate::pipeline::prepare(&ds, &train, &opts, &Default::default(), &())?;
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
        let fits = crate::evaluate::compare_falloff(&r, &s, 1.3);
        let sum = crate::plot::falloff_figure(
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
    crate::plot::error_maps(
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
    crate::plot::model_viewer(&m, &model, render::DEFAULT_VIEW, (300, 340))?;
    written.push(m.clone());
    timings.push(("plots", tp.elapsed().as_secs_f64()));
    let total_s = t0.elapsed().as_secs_f64();

    let run = DemoRun {
        options: args.clone(),
        size,
        target_mm,
        mesh_vertices: mesh.positions.len(),
        mean_free_path: 1.0 / sim_field().steepest_falloff(),
        exposures,
        noise_floor: cfg.noise_floor,
        n_frames,
        scan_s,
        rig_seconds: summary.rig_seconds,
        train,
        held,
        decode_s,
        fits,
        truth_vertices: truth.len(),
        truth_held,
        truth_in,
        renders,
        comparisons,
        clip_max,
        in_blender,
        falloff,
        model_png: m,
        error_map_png: e,
        timings,
        evaluations,
        total_s,
    };
    Ok((run, written))
}
