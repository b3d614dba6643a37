//! `subsurf fit`: a scan dataset in, a per-vertex model (`docs/model-format.md`) and
//! `fit-report.json` (with `.md`, `.html` and pictures) out: the fit's options from the
//! command's settings, the noise floor, the one pass over the frames, the mesh check, the
//! optional validation, the fit, and what is written and printed. The command only parses.
use std::path::{Path, PathBuf};

use crate::crossval::{CvSettings, Segments, fit_scan_in};
use crate::dataset::Dataset;
use crate::fit::{Preset, Terms};
use crate::modelfile::ColourMode;
use crate::pipeline::{MAX_SEGMENTS, PipelineOptions, StoreOptions, prepare};
use crate::progress::{Progress, Stages};

/// The fit's settings: the command's flags (`subsurf fit --help` explains each).
#[derive(Debug, Clone)]
pub struct FitScanSettings {
    /// The scan dataset (for messages and the report).
    pub scan: PathBuf,
    /// Output model (binary PLY).
    pub out: PathBuf,
    /// Output report (default: `fit-report.json` beside the model).
    pub report: Option<PathBuf>,
    /// Colour model.
    pub colour: ColourMode,
    /// Direction segments: a number, `auto`, or the preset's.
    pub segments: Option<String>,
    /// Folds of the cross-validation inside the fit (default: 5; 0 for draft unless
    /// `segments` is `auto`).
    pub cv_folds: Option<usize>,
    /// Early stopping of the folds' alpha rounds.
    pub cv_patience: usize,
    /// Exponential terms: a number, `auto`, or the preset's.
    pub terms: Option<String>,
    /// Fit every light position at the largest order.
    pub fixed_order: bool,
    /// Solver preset (`None`: exact).
    pub preset: Option<Preset>,
    /// `--preset reference`: the exact path without the cuts ([`crate::pipeline::Speed`],
    /// [`CvSettings::reference`]).
    pub reference: bool,
    /// Samples closer than this to x_i are dropped (mm).
    pub exclusion_radius: f64,
    /// A vertex whose closest x_i is farther than this has no data (mm).
    pub max_distance: f64,
    /// Frames whose x_i lie within this distance are one light position (mm).
    pub pool_distance: Option<f64>,
    /// Fits with log E above this are failures.
    pub max_log_e: f64,
    /// Outlier fits: log E above this multiple of the median fit's.
    pub outlier_factor: f64,
    /// Most extra alpha rounds.
    pub alpha_rounds: usize,
    /// Convergence of the alpha rounds.
    pub alpha_tolerance: f64,
    /// Eq. 6's t1 as a share of the brightest sample (`None`: chosen by cross-validation).
    pub alpha_t1_share: Option<f64>,
    /// alpha finer than the mesh (`None`: `auto`, judged by cross-validation).
    pub alpha_lattice: Option<crate::pipeline::AlphaLattice>,
    /// Eq. 6's shrinkage of alpha towards 1.
    pub alpha_shrinkage: f64,
    /// Frames seen more grazing than this at the spot are not fitted.
    pub spot_cos_min: f64,
    /// Largest disagreement between detected spot and laser ray (mm).
    pub laser_tolerance: f64,
    /// Override of the dataset's noise floor.
    pub noise_floor: Option<f64>,
    /// Drop samples whose neighbourhood is not covered by the surface.
    pub coverage_check: bool,
    /// Validate on held-out frames first.
    pub validate: bool,
    /// Memory for the sample store (MiB).
    pub memory: u64,
    /// Where the sample store's files go.
    pub cache: crate::pipeline::Cache,
    /// Skip the check that the laser spots lie on the mesh.
    pub skip_mesh_check: bool,
    /// Measure the noise floor also when scan.json gives one.
    pub check_noise_floor: bool,
    /// Do not draw the PNGs beside the report.
    pub no_pictures: bool,
    /// Fit every vertex of the mesh however much finer it is than the frames' pixels (the
    /// reference preset always does; [`crate::lod`]).
    pub full_mesh: bool,
}

/// Why the fit stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitScanError {
    /// A setting is out of range, or the mesh is not where the scan's laser spots are.
    #[error("{0}")]
    Invalid(String),
    /// A step failed; `what` names it, `source` says why.
    #[error("{what}")]
    Step {
        /// The step (e.g. `fitting scan/`).
        what: String,
        /// Why.
        #[source]
        source: Box<FitScanError>,
    },
    /// A file or folder could not be written.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The report could not be serialised.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// Reading the frames or fitting failed.
    #[error(transparent)]
    Pipeline(#[from] crate::pipeline::PipelineError),
    /// Judging the validation fit failed.
    #[error(transparent)]
    Evaluate(#[from] crate::evaluate::EvaluateError),
    /// The model could not be written.
    #[error(transparent)]
    Model(#[from] crate::modelfile::ModelFileError),
    /// The mesh could not be coarsened to the frames' level of detail, or the model prolonged.
    #[error(transparent)]
    Lod(#[from] crate::lod::LodError),
    /// A picture could not be drawn.
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    /// The report could not be written.
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
}

crate::util::step_context!(FitScanError);

/// Panel size of the error map, pixels.
const ERROR_PANEL: (u32, u32) = (420, 420);
/// … of the model picture.
const MODEL_PANEL: (u32, u32) = (360, 400);

/// The pictures of a fit, beside the report: the per-vertex error map log E(x_i) (Eq. 8, Figures
/// 4/5) and the model viewer (alpha, total reflectance, reach, fitted/interpolated/no-model).
fn pictures(
    model: &crate::modelfile::ModelFile,
    report: &Path,
) -> Result<Vec<PathBuf>, FitScanError> {
    let stem = report
        .file_stem()
        .map_or_else(|| "fit".into(), |s| s.to_string_lossy().into_owned());
    let error_png = report.with_file_name(format!("{stem}-error-map.png"));
    let model_png = report.with_file_name(format!("{stem}-model.png"));
    let view = crate::render::DEFAULT_VIEW;
    crate::plot::error_maps(&error_png, &[("fit".to_string(), model)], view, ERROR_PANEL)
        .step(|| format!("drawing {}", error_png.display()))?;
    crate::plot::model_viewer(&model_png, model, view, MODEL_PANEL)
        .step(|| format!("drawing {}", model_png.display()))?;
    Ok(vec![error_png, model_png])
}

/// Spots farther than this many pixel footprints (median) from the mesh get a warning.
const MESH_WARN_PX: f64 = 1.0;

/// The laser spots the extraction pass detected (the sample store's records, so no frame is read
/// for it) against the mesh surface (`crate::align::check_spots`): an error when their median
/// distance exceeds the laser tolerance (registration would refuse most of them anyway, and the
/// rest land on the wrong vertices), a warning above [`MESH_WARN_PX`] pixels.
fn mesh_check<U: Stages>(
    run: &crate::pipeline::Context,
    frames: &[usize],
    scan: &Path,
    ui: &U,
) -> Result<crate::align::MeshCheck, FitScanError> {
    let bound = run.opts.spot.laser_tolerance_mm;
    let spots: Vec<(usize, crate::spot::Spot)> = run
        .store()
        .map(|s| {
            frames
                .iter()
                .filter_map(|&k| Some((k, s.record(k)?.spot?)))
                .collect()
        })
        .unwrap_or_default();
    let c = crate::align::check_spots(run.ds, &run.scene, &spots, 2.0, bound);
    let align = format!("subsurf align --scan {}", scan.display());
    if c.far() {
        return Err(FitScanError::Invalid(format!(
            "the scan's laser spots lie a median {:.2} mm ({:.1} px) from the mesh surface, beyond \
             the bound of {bound} mm (--laser-tolerance; {} of {} spots farther): the mesh is not \
             in the turntable frame (another pose or unit?). Run `{align}` first, or \
             --skip-mesh-check to fit anyway",
            c.median_mm,
            c.median_px,
            (c.far_share * c.spots as f64).round(),
            c.spots
        )));
    }
    if c.conclusive() && c.median_px > MESH_WARN_PX {
        ui.warn(&format!(
            "warning: the scan's laser spots lie a median {:.2} mm ({:.1} px) from the mesh \
             surface; above {MESH_WARN_PX} px the mesh may be slightly off the turntable frame: \
             `{align}` estimates its pose from the spots",
            c.median_mm, c.median_px
        ));
    }
    Ok(c)
}

/// Fits `frames` of `ds` as `args` says, writes the model, its report and pictures, and
/// prints the summary through `ui` (its one progress stage, its lines and warnings).
pub fn fit_scan<U: Stages>(
    ds: &Dataset,
    frames: &[usize],
    args: &FitScanSettings,
    ui: &U,
) -> Result<(), FitScanError> {
    // A mesh far finer than the frames' pixels is fitted at the level of detail they support
    // and the model prolonged to every vertex at the end (crate::lod).
    let given = ds;
    let mut lod = crate::lod::supported(given);
    let coarse = match &mut lod {
        Some(l) if l.should_coarsen() && !args.full_mesh && !args.reference => {
            let bar = ui.stage(0, "level of detail");
            bar.start(
                &format!(
                    "level of detail: clustering {} vertices at the {:.3} mm pixel footprint",
                    l.vertices, l.pixel_footprint_mm
                ),
                0,
            );
            let c = crate::lod::coarsen(&given.mesh, l)
                .step(|| format!("coarsening the mesh of {}", args.scan.display()))?;
            ui.finish(bar);
            l.fitted_vertices = c.mesh.positions.len();
            l.coarsened = true;
            ui.say(&format!(
                "level of detail: the mesh has {} vertices, the frames support about {} (one per \
                 {:.3} mm pixel footprint): fitting {} and prolonging the model (--full-mesh: all)",
                l.vertices, l.supported_vertices, l.pixel_footprint_mm, l.fitted_vertices
            ));
            Some(given.with_mesh(c.mesh))
        }
        _ => None,
    };
    let ds = coarse.as_ref().unwrap_or(given);
    let preset = args.preset;
    let (mut opts, mut fit) = PipelineOptions::for_dataset(ds).with_preset(preset);
    // The dataset's floor (scan.json's, else measured from the training frames: a floor read
    // from frames the fit is later judged on would carry their pixels into the fit) is the
    // protocol its folds are judged by; --noise-floor changes only what this fit reads.
    let mut floor = crate::pipeline::noise_floor(ds, frames, false)
        .step(|| format!("the noise floor of {}", args.scan.display()))?;
    let protocol = PipelineOptions::evaluation_protocol(ds).with_noise_floor(floor.value);
    opts = opts.with_noise_floor(args.noise_floor.unwrap_or(floor.value));
    if floor.measured.is_some() {
        ui.warn(&format!(
            "noise floor: {:.3e}, measured from the frames (scan.json gives none)",
            floor.value
        ));
    }
    opts.samples.exclusion_radius_mm = args.exclusion_radius;
    opts.samples.coverage = args.coverage_check;
    opts.max_select_mm = args.max_distance;
    opts.pool_mm = args.pool_distance;
    opts.max_log_e = args.max_log_e;
    opts.outlier_factor = args.outlier_factor;
    opts.alpha_rounds = args.alpha_rounds;
    opts.alpha_tolerance = args.alpha_tolerance;
    opts.alpha_window.t1_share = args
        .alpha_t1_share
        .unwrap_or(crate::pipeline::ALPHA_T1_SHARE);
    opts.alpha_lattice = args
        .alpha_lattice
        .unwrap_or(crate::pipeline::AlphaLattice::Auto);
    opts.alpha_shrinkage = args.alpha_shrinkage;
    opts.spot_cos_min = args.spot_cos_min;
    if args.fixed_order {
        opts.order = None;
    }
    opts.spot.laser_tolerance_mm = args.laser_tolerance;
    opts.model.colour = args.colour;
    let segments = match args.segments.as_deref() {
        None => Segments::Fixed(opts.model.segments),
        Some("auto") => Segments::Auto,
        Some(m) => Segments::Fixed(
            m.parse()
                .ok()
                .filter(|m| (1..=MAX_SEGMENTS).contains(m))
                .ok_or_else(|| {
                    FitScanError::Invalid(format!(
                        "--segments must be 1..={MAX_SEGMENTS} or auto, got {m:?}"
                    ))
                })?,
        ),
    };
    let folds = args.cv_folds.unwrap_or(
        if args.preset == Some(Preset::Draft) && segments != Segments::Auto {
            0
        } else {
            crate::crossval::DEFAULT_FOLDS
        },
    );
    let base = if args.reference {
        opts.speed = crate::pipeline::Speed::Reference;
        CvSettings::reference()
    } else {
        CvSettings::default()
    };
    let cv = CvSettings {
        folds,
        segments,
        rounds: true,
        patience: args.cv_patience,
        t1: args.alpha_t1_share.is_none(),
        lattice: args.alpha_lattice.is_none(),
        ..base
    };
    match args.terms.as_deref() {
        None => {}
        Some("auto") => {
            fit.terms = Terms::Auto {
                max: crate::model::MAX_TERMS,
                tolerance: 0.01,
            }
        }
        Some(n) => {
            fit.terms = Terms::Fixed(
                n.parse()
                    .ok()
                    .filter(|n| (1..=crate::model::MAX_TERMS).contains(n))
                    .ok_or_else(|| {
                        FitScanError::Invalid(format!("--terms must be 1..=4 or auto, got {n:?}"))
                    })?,
            )
        }
    }
    let bar = ui.stage(0, "");
    let store = StoreOptions {
        budget: usize::try_from(args.memory.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
        cache: args.cache.clone(),
    };
    // One pass over the frames: the validation fit, its held-out frames and the fit on
    // everything all read the samples from it.
    let run = prepare(ds, frames, &opts, &store, &bar)
        .step(|| format!("reading the frames of {}", args.scan.display()))?;
    let mesh_check = if args.skip_mesh_check {
        None
    } else {
        Some(mesh_check(&run, frames, &args.scan, ui)?)
    };
    // The cross-validation's folds and --validate's held-out frames are judged by the dataset's
    // evaluation protocol, whatever this fit's own sample rules (the run itself when they agree).
    // A floor scan.json gives is checked against the frames when asked (it reads frames again:
    // the one decode per frame holds otherwise).
    if ds.spec.noise_floor.is_some() && args.check_noise_floor {
        if let Ok(checked) = crate::pipeline::noise_floor(ds, frames, true) {
            floor = checked;
        }
        if let Some(w) = &floor.warning {
            ui.warn(&format!("warning: {w}"));
        }
    }
    let judge = crate::pipeline::judge_context(&run, frames, Some(&protocol), &store, &bar)
        .step(|| format!("reading the frames of {} to judge", args.scan.display()))?;
    let validation = if args.validate {
        let holdout = crate::validate::holdout(ds, frames);
        let v = fit_scan_in(&run, &judge, &holdout.training, &cv, &fit, &bar)
            .step(|| format!("validation fit of {}", args.scan.display()))?;
        let v = crate::validate::judge(&judge, &v.model, holdout, v.report.log_e, &bar)
            .step(|| "judging the validation fit on the held-out frames".into())?;
        Some(v)
    } else {
        None
    };
    let out = fit_scan_in(&run, &judge, frames, &cv, &fit, &bar)
        .step(|| format!("fitting {}", args.scan.display()))?;
    ui.finish(bar);
    let report_dir = args.report.as_deref().and_then(Path::parent);
    for dir in [args.out.parent(), report_dir].into_iter().flatten() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).step(|| format!("creating {}", dir.display()))?;
        }
    }
    let mut out = out;
    if let Some(c) = &coarse {
        let bar = ui.stage(0, "prolonging the model to the mesh");
        bar.start(
            &format!(
                "prolonging the model from {} to {} vertices",
                c.mesh.positions.len(),
                given.mesh.positions.len()
            ),
            0,
        );
        out.model = crate::lod::prolong(&out.model, &c.mesh, &given.mesh).step(|| {
            format!(
                "prolonging the model to the mesh of {}",
                args.scan.display()
            )
        })?;
        ui.finish(bar);
    }
    out.model
        .write(&args.out)
        .step(|| format!("writing {}", args.out.display()))?;
    let bytes = std::fs::metadata(&args.out).map(|m| m.len()).unwrap_or(0);
    let report_path = args
        .report
        .clone()
        .unwrap_or_else(|| args.out.with_file_name("fit-report.json"));
    let mut json = serde_json::to_value(&out.report)?;
    json["model_bytes"] = bytes.into();
    json["model"] = args.out.display().to_string().into();
    json["fit_options"] = serde_json::to_value(&fit)?;
    json["noise_floor"] = serde_json::to_value(&floor)?;
    if let Some(l) = &lod {
        json["level_of_detail"] = serde_json::to_value(l)?;
    }
    if let Some(v) = &validation {
        json["validation"] = serde_json::to_value(v)?;
    }
    if let Some(c) = &mesh_check {
        json["mesh_check"] = serde_json::to_value(c)?;
    }
    if let Some(cv) = &out.report.cross_validation {
        ui.say(&format!(
            "cross-validation: {} ({} fits, {:.1} s)",
            cv.rule, cv.fits, cv.seconds
        ));
        if let Some(why) = &cv.skipped {
            ui.say(&format!("  {why}"));
        }
        for c in &cv.choices {
            if c.candidates.is_empty() {
                ui.say(&format!("  {}: {} ({})", c.name, c.chosen, c.rule));
                continue;
            }
            ui.say(&format!(
                "  {}: {} chosen; held-out log E per candidate {}",
                c.name,
                c.chosen,
                c.candidates
                    .iter()
                    .map(|k| format!(
                        "{}: {}{}",
                        k.value,
                        k.score.map_or("-".into(), crate::report::fmt::log_e),
                        k.worse_by.zip(k.se).filter(|(d, _)| *d > 0.0).map_or(
                            String::new(),
                            |(d, se)| format!(
                                " (+{} ± {})",
                                crate::report::fmt::log_e(d),
                                crate::report::fmt::log_e(se)
                            )
                        )
                    ))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
    }
    // The model is already on disk: a picture that cannot be drawn is reported after the report
    // is written, so no result is lost.
    let drawn = if args.no_pictures {
        Ok(Vec::new())
    } else {
        pictures(&out.model, &report_path)
    };
    if let Ok(p) = &drawn {
        json["pictures"] = p
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .into();
    }
    // Peak memory of the whole process, after the model (and pictures) were written; the
    // pipeline's own `peak_rss_mib` is taken at its end.
    if let Some(m) = crate::util::peak_rss_mib() {
        json["process_peak_rss_mib"] = m.into();
    }
    if let Some(c) = crate::util::cpu_seconds() {
        json["process_cpu_s"] = c.into();
    }
    std::fs::write(&report_path, serde_json::to_string_pretty(&json)?)
        .step(|| format!("writing {}", report_path.display()))?;
    let drawn = drawn?;
    for line in crate::report::fit::summary_lines(&out.report) {
        ui.say(&line);
    }
    let r = &out.report;
    let f = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.4}"));
    if let Some(b) = &r.baseline {
        ui.say(&format!(
            "homogeneous baseline (one isotropic fall-off for every x_i, {} terms, {} samples, r {:.2}..{:.2} mm): log E(x_i) mean r/g/b {} {} {}",
            b.terms,
            b.samples,
            b.r_range[0],
            b.r_range[1],
            f(b.log_e.mean[0]),
            f(b.log_e.mean[1]),
            f(b.log_e.mean[2])
        ));
    }
    for k in &r.alpha.round_log {
        ui.say(&format!(
            "  round {}: training objective {:.6e} (last kept round {:.6e}; fits against the alpha they were fitted to {:.6e}; {} light positions kept their previous fit) {}",
            k.round,
            k.objective,
            k.previous,
            k.fitted,
            k.fits_kept_previous,
            if k.kept { "kept" } else { "discarded" }
        ));
    }
    if let Some(v) = &validation {
        ui.say(&format!(
            "validation: {} frames held out ({}), {} evaluated; {}",
            v.holdout.frames.len(),
            crate::validate::frame_list(&v.holdout.frames),
            v.evaluated,
            v.holdout.rule
        ));
        ui.say("  mean log E(x_i)          red      green    blue");
        let row = |name: &str, st: &crate::pipeline::LogEStats| {
            ui.say(&format!(
                "  {name:<22} {:8} {:8} {:8}",
                f(st.mean[0]),
                f(st.mean[1]),
                f(st.mean[2])
            ))
        };
        row("held out (trust this)", &v.held_out);
        if let Some(b) = &v.baseline_held_out {
            row("baseline, held out", b);
        }
        row("in-sample", &v.in_sample);
        ui.say(&format!(
            "  (then fitted on all {} frames)",
            r.frames.selected
        ));
    }
    ui.say(&format!(
        "model {} ({}); report {}",
        args.out.display(),
        crate::report::fmt::bytes(bytes),
        report_path.display()
    ));
    // The same figures for people: fit-report.md (terminals) and a self-contained
    // fit-report.html (pictures embedded), beside fit-report.json.
    let figures = drawn
        .iter()
        .zip([
            "log E(x_i) per vertex (Eq. 8)",
            "the model: alpha, reflectance, reach, status",
        ])
        .map(|(p, c)| crate::report::Figure {
            path: p.clone(),
            caption: c.into(),
        })
        .collect();
    let inputs = crate::report::fit::FitInputs {
        scan: &args.scan,
        model: &args.out,
        model_bytes: bytes,
        pictures: figures,
    };
    let stem = report_path
        .file_stem()
        .map_or_else(|| "fit-report".into(), |s| s.to_string_lossy().into_owned());
    let dir = report_path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or_else(|| Path::new("."));
    let [md, html] = crate::report::fit::fit_report(&out.report, &inputs).write(dir, &stem)?;
    ui.say(&format!("wrote {} and {}", md.display(), html.display()));
    for p in &drawn {
        ui.say(&format!("wrote {}", p.display()));
    }
    Ok(())
}
