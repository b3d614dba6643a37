//! `subsurf fit`: a scan dataset in, a per-vertex model (`docs/model-format.md`) and
//! `fit-report.json` out.
use std::path::PathBuf;

use anyhow::{Context, anyhow};
use subsurf::crossval::{CvSettings, Segments, fit_scan_in};
use subsurf::fit::{Preset, Terms};
use subsurf::modelfile::ColourMode;
use subsurf::pipeline::{MAX_SEGMENTS, PipelineOptions, StoreOptions, prepare};

use super::progress::Bar;

/// Colour handling.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Colour {
    /// One fall-off with channel scales s_g, s_b (Eq. 9, the paper's choice for objects).
    Shared,
    /// Separate fall-off per channel (Eq. 3 per channel).
    PerChannel,
}

/// Speed/accuracy presets ([`PipelineOptions::with_preset`]: the same in `bench tradeoff`).
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum PresetArg {
    /// Exact fit on all samples, n = 3, isotropic (default).
    Exact,
    /// Fast previews (binned, subsampled), isotropic.
    Draft,
    /// Binned sufficient statistics, 4 direction segments.
    Balanced,
    /// Exact, automatic order, 8 direction segments.
    Best,
    /// The exact default as it was before issue 40's cuts (five folds for every choice, every
    /// round scored until two in a row do not lower the best, fills solved from scratch): the
    /// reference `subsurf bench equivalence` checks the default against.
    Reference,
}

/// Fit the per-vertex subsurface-scattering model to a scan (section 5).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scan dataset: its folder or its `scan.json`.
    #[arg(long)]
    pub scan: PathBuf,
    /// Output model (binary PLY).
    #[arg(long, default_value = "model.ply")]
    pub out: PathBuf,
    /// Output report (default: `fit-report.json` beside the model).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Frames to use, e.g. `3,17,40-59` (default: all).
    #[arg(long)]
    pub frames: Option<String>,
    /// Frames to hold out of the fit.
    #[arg(long)]
    pub exclude_frames: Option<String>,
    /// Colour model.
    #[arg(long, value_enum, default_value = "shared")]
    pub colour: Colour,
    /// Direction segments m (Eq. 3); 1 = isotropic; `auto` chooses m among 1, 2, 4, 8 by
    /// cross-validation (`--cv-folds`): the simplest whose held-out error is within one standard
    /// error of the best (the candidates are in the report's `cross_validation`). Default: the
    /// preset's (1 for exact).
    #[arg(long)]
    pub segments: Option<String>,
    /// Folds of the cross-validation inside the fit (whole turntable angles, or spread raster
    /// positions on a one-angle scan): each fold's frames are predicted by a fit of the others,
    /// which chooses `--segments auto` and the number of alpha rounds. 0 or 1: no
    /// cross-validation (the rounds run to `--alpha-rounds` or convergence). Default: 5; 0 for
    /// `--preset draft` unless `--segments auto` (a preview does not pay for the fold fits,
    /// which cost several times the fit itself: BENCHMARKS.md).
    #[arg(long)]
    pub cv_folds: Option<usize>,
    /// The folds' alpha rounds stop once this many rounds in a row have not lowered the best
    /// cross-validated error by half a standard error (early stopping; the report lists the
    /// rounds scored). 0: score every round up to `--alpha-rounds`. Default: 2 (with
    /// `--preset reference`, any lower error counts).
    #[arg(long)]
    pub cv_patience: Option<usize>,
    /// Exponential terms n (Eq. 1): the largest n a light position may use (each chooses its
    /// own n and m, see `--fixed-order`), or `auto` for the smallest order within 1 % of the
    /// best. Default: the preset's (3 for exact).
    #[arg(long)]
    pub terms: Option<String>,
    /// Fit every light position at the largest n and m (`--terms`, `--segments`) instead of
    /// choosing each one's order from its samples (AICc, `subsurf_model::order`).
    #[arg(long)]
    pub fixed_order: bool,
    /// Solver preset.
    #[arg(long, value_enum, default_value = "exact")]
    pub preset: PresetArg,
    /// Samples closer than this to x_i are dropped (mm).
    #[arg(long, default_value_t = 0.5)]
    pub exclusion_radius: f64,
    /// A vertex whose closest x_i is farther than this has no data (mm).
    #[arg(long, default_value_t = 2.0)]
    pub max_distance: f64,
    /// Frames whose laser spots x_i lie within this distance (mm) are one light position, fitted
    /// together (default: half the mesh's median edge length; 0: only identical x_i).
    #[arg(long)]
    pub pool_distance: Option<f64>,
    /// Fits with log E (Eq. 8) above this are failures, interpolated from neighbours.
    #[arg(long, default_value_t = 1.0)]
    pub max_log_e: f64,
    /// Fits with log E above this multiple of the median fit's (and above 0.03) are outliers,
    /// interpolated from neighbours (`inf` disables).
    #[arg(long, default_value_t = 3.0)]
    pub outlier_factor: f64,
    /// At most this many extra fit rounds on samples divided by the previous round's alpha
    /// (Eq. 6); they stop early when alpha has converged (`--alpha-tolerance`).
    #[arg(long, default_value_t = 8)]
    pub alpha_rounds: usize,
    /// Convergence of the alpha rounds: RMS change of ln alpha between rounds.
    #[arg(long, default_value_t = 2e-3)]
    pub alpha_tolerance: f64,
    /// Eq. 6's upper threshold t1 as a share of each light position's brightest sample: brighter
    /// samples (near x_i, not yet multiple scattering) do not enter alpha ("inf", the default:
    /// none).
    /// By default chosen per scan by cross-validation, none against 0.3
    /// (`crossval::T1_CANDIDATE`); given, it is fixed.
    #[arg(long)]
    pub alpha_t1_share: Option<f64>,
    /// alpha finer than the mesh (section 5's "higher resolution texture"): `auto` estimates
    /// Eq. 6 per point of a per-face lattice whose level follows the pixel footprint (at most
    /// 8) and writes it (`face_alpha`) where the images show detail above the noise; a number
    /// 1..=8 caps the level; `off` keeps alpha per vertex only. By default `auto`, and the
    /// lattice found is written only when the cross-validation's folds, judged at surface
    /// points, say it predicts better than alpha per vertex; given, it is fixed (not judged).
    #[arg(long)]
    pub alpha_lattice: Option<subsurf::pipeline::AlphaLattice>,
    /// Eq. 6's shrinkage of alpha towards 1, as a multiple of the empirical-Bayes pseudo-count
    /// (the noise within a texel over the texture's variance between texels): 1 = the empirical
    /// one, 0 = none (the plain geometric mean of s / R_d), `inf` = no texture (alpha = 1).
    #[arg(long, default_value_t = 1.0)]
    pub alpha_shrinkage: f64,
    /// Frames whose laser spot the camera sees more grazing than this (cos θ at the spot) are
    /// not fitted, nor evaluated with the model: their spot is foreshortened and x_i least
    /// certain. Registration keeps spots down to cos θ = 0.1.
    #[arg(long, default_value_t = subsurf::registration::SPOT_COS_MIN)]
    pub spot_cos_min: f64,
    /// Largest disagreement between detected spot and laser ray (mm).
    #[arg(long, default_value_t = 2.0)]
    pub laser_tolerance: f64,
    /// Override the dataset's noise floor.
    #[arg(long)]
    pub noise_floor: Option<f64>,
    /// Drop samples whose bilinear neighbourhood is not covered by the surface at x_o (a pixel
    /// centre seeing the background or another surface, counted as `samples.uncovered`). Off by
    /// default: it helps simulated scans seen past open boundaries, not the outside datasets.
    #[arg(long)]
    pub coverage_check: bool,
    /// Validate first: hold out a spread of frames (whole turntable angles when the scan has at
    /// least 4), fit the rest, report held-out Table-1 statistics next to the in-sample ones and
    /// the homogeneous baseline's, then fit on everything (`docs/validation.md`).
    #[arg(long)]
    pub validate: bool,
    /// Memory for the sample store (MiB): the samples of every frame are read once and kept in
    /// memory up to this, the rest read back from the store's files per use.
    #[arg(long, default_value_t = (subsurf::store::DEFAULT_BUDGET >> 20) as u64)]
    pub memory: u64,
    /// Where the sample store's files go: `dataset` (`.subsurf-cache/` in the dataset, reused by
    /// later fits of the same frames with the same extraction options), a directory, or `off`.
    #[arg(long, default_value = "dataset")]
    pub cache: subsurf::pipeline::Cache,
    /// Skip the check that the scan's laser spots (as the extraction pass detected them) lie on
    /// the mesh surface (a mesh in another pose or unit fails it: run `subsurf align` first).
    #[arg(long)]
    pub skip_mesh_check: bool,
    /// Measure the noise floor from the frames also when scan.json gives one, and warn when the
    /// two differ by more than 2x (reads up to 16 frames a second time; without a floor in
    /// scan.json it is always measured).
    #[arg(long)]
    pub check_noise_floor: bool,
    /// Do not draw the PNGs beside the report (`<report>-error-map.png`: log E(x_i) per vertex,
    /// Eq. 8; `<report>-model.png`: alpha, reflectance, reach and vertex status).
    #[arg(long)]
    pub no_pictures: bool,
}

/// Panel size of the error map and of the model picture, pixels.
const ERROR_PANEL: (u32, u32) = (420, 420);
const MODEL_PANEL: (u32, u32) = (360, 400);

/// The pictures of a fit, beside the report: the per-vertex error map log E(x_i) (Eq. 8, Figures
/// 4/5) and the model viewer (alpha, total reflectance, reach, fitted/interpolated/no-model).
fn pictures(
    model: &subsurf::modelfile::ModelFile,
    report: &std::path::Path,
) -> anyhow::Result<Vec<PathBuf>> {
    let stem = report
        .file_stem()
        .map_or_else(|| "fit".into(), |s| s.to_string_lossy().into_owned());
    let error_png = report.with_file_name(format!("{stem}-error-map.png"));
    let model_png = report.with_file_name(format!("{stem}-model.png"));
    let view = subsurf::render::DEFAULT_VIEW;
    subsurf::plot::error_maps(&error_png, &[("fit".to_string(), model)], view, ERROR_PANEL)
        .with_context(|| format!("drawing {}", error_png.display()))?;
    subsurf::plot::model_viewer(&model_png, model, view, MODEL_PANEL)
        .with_context(|| format!("drawing {}", model_png.display()))?;
    Ok(vec![error_png, model_png])
}

/// Spots farther than this many pixel footprints (median) from the mesh get a warning.
const MESH_WARN_PX: f64 = 1.0;

/// The laser spots the extraction pass detected (the sample store's records, so no frame is read
/// for it) against the mesh surface (`subsurf::align::check_spots`): an error when their median
/// distance exceeds the laser tolerance (registration would refuse most of them anyway, and the
/// rest land on the wrong vertices), a warning above [`MESH_WARN_PX`] pixels.
fn mesh_check(
    run: &subsurf::pipeline::Context,
    frames: &[usize],
    scan: &std::path::Path,
) -> anyhow::Result<subsurf::align::MeshCheck> {
    let bound = run.opts.spot.laser_tolerance_mm;
    let spots: Vec<(usize, subsurf::registration::Spot)> = run
        .store()
        .map(|s| {
            frames
                .iter()
                .filter_map(|&k| Some((k, s.record(k)?.spot?)))
                .collect()
        })
        .unwrap_or_default();
    let c = subsurf::align::check_spots(run.ds, &run.scene, &spots, 2.0, bound);
    let align = format!("subsurf align --scan {}", scan.display());
    if c.far() {
        anyhow::bail!(
            "the scan's laser spots lie a median {:.2} mm ({:.1} px) from the mesh surface, beyond \
             the bound of {bound} mm (--laser-tolerance; {} of {} spots farther): the mesh is not \
             in the turntable frame (another pose or unit?). Run `{align}` first, or \
             --skip-mesh-check to fit anyway",
            c.median_mm,
            c.median_px,
            (c.far_share * c.spots as f64).round(),
            c.spots
        );
    }
    if c.conclusive() && c.median_px > MESH_WARN_PX {
        eprintln!(
            "warning: the scan's laser spots lie a median {:.2} mm ({:.1} px) from the mesh \
             surface; above {MESH_WARN_PX} px the mesh may be slightly off the turntable frame: \
             `{align}` estimates its pose from the spots",
            c.median_mm, c.median_px
        );
    }
    Ok(c)
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (ds, frames) = super::open_frames(
        &args.scan,
        args.frames.as_deref(),
        args.exclude_frames.as_deref(),
    )?;
    let preset = match args.preset {
        PresetArg::Exact | PresetArg::Reference => None,
        PresetArg::Draft => Some(Preset::Draft),
        PresetArg::Balanced => Some(Preset::Balanced),
        PresetArg::Best => Some(Preset::Best),
    };
    let (mut opts, mut fit) = PipelineOptions::for_dataset(&ds).with_preset(preset);
    // The dataset's floor (scan.json's, else measured from its frames) is the evaluation
    // protocol's; --noise-floor changes only what this fit reads.
    let all: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let mut floor = subsurf::pipeline::noise_floor(&ds, &all, false)
        .with_context(|| format!("the noise floor of {}", args.scan.display()))?;
    let protocol = PipelineOptions::evaluation_protocol(&ds).with_noise_floor(floor.value);
    opts = opts.with_noise_floor(args.noise_floor.unwrap_or(floor.value));
    if floor.measured.is_some() {
        eprintln!(
            "noise floor: {:.3e}, measured from the frames (scan.json gives none)",
            floor.value
        );
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
        .unwrap_or(subsurf::pipeline::ALPHA_T1_SHARE);
    opts.alpha_lattice = args
        .alpha_lattice
        .unwrap_or(subsurf::pipeline::AlphaLattice::Auto);
    opts.alpha_shrinkage = args.alpha_shrinkage;
    opts.spot_cos_min = args.spot_cos_min;
    if args.fixed_order {
        opts.order = None;
    }
    opts.spot.laser_tolerance_mm = args.laser_tolerance;
    opts.model.colour = match args.colour {
        Colour::Shared => ColourMode::Shared,
        Colour::PerChannel => ColourMode::PerChannel,
    };
    let segments = match args.segments.as_deref() {
        None => Segments::Fixed(opts.model.segments),
        Some("auto") => Segments::Auto,
        Some(m) => Segments::Fixed(
            m.parse()
                .ok()
                .filter(|m| (1..=MAX_SEGMENTS).contains(m))
                .ok_or_else(|| {
                    anyhow!("--segments must be 1..={MAX_SEGMENTS} or auto, got {m:?}")
                })?,
        ),
    };
    let folds = args.cv_folds.unwrap_or(
        if matches!(args.preset, PresetArg::Draft) && segments != Segments::Auto {
            0
        } else {
            subsurf::crossval::DEFAULT_FOLDS
        },
    );
    let base = if matches!(args.preset, PresetArg::Reference) {
        opts.speed = subsurf::pipeline::Speed::Reference;
        CvSettings::reference()
    } else {
        CvSettings::default()
    };
    let cv = CvSettings {
        folds,
        segments,
        rounds: true,
        patience: args.cv_patience.unwrap_or(base.patience),
        t1: args.alpha_t1_share.is_none(),
        lattice: args.alpha_lattice.is_none(),
        ..base
    };
    match args.terms.as_deref() {
        None => {}
        Some("auto") => {
            fit.terms = Terms::Auto {
                max: subsurf::model::MAX_TERMS,
                tolerance: 0.01,
            }
        }
        Some(n) => {
            fit.terms = Terms::Fixed(
                n.parse()
                    .ok()
                    .filter(|n| (1..=subsurf::model::MAX_TERMS).contains(n))
                    .ok_or_else(|| anyhow!("--terms must be 1..=4 or auto, got {n:?}"))?,
            )
        }
    }
    let bar = Bar::with_template("{msg:>12} {bar:40} {pos}/{len} {eta}");
    let store = StoreOptions {
        budget: usize::try_from(args.memory.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
        cache: args.cache.clone(),
    };
    // One pass over the frames: the validation fit, its held-out frames and the fit on
    // everything all read the samples from it.
    let run = prepare(&ds, &frames, &opts, &store, &bar)
        .with_context(|| format!("reading the frames of {}", args.scan.display()))?;
    let mesh_check = if args.skip_mesh_check {
        None
    } else {
        Some(mesh_check(&run, &frames, &args.scan)?)
    };
    // The cross-validation's folds and --validate's held-out frames are judged by the dataset's
    // evaluation protocol, whatever this fit's own sample rules (the run itself when they agree).
    // A floor scan.json gives is checked against the frames when asked (it reads frames again:
    // the one decode per frame holds otherwise).
    if ds.spec.noise_floor.is_some() && args.check_noise_floor {
        if let Ok(checked) = subsurf::pipeline::noise_floor(&ds, &all, true) {
            floor = checked;
        }
        if let Some(w) = &floor.warning {
            eprintln!("warning: {w}");
        }
    }
    let judge = subsurf::pipeline::judge_context(&run, &frames, Some(&protocol), &store, &bar)
        .with_context(|| format!("reading the frames of {} to judge", args.scan.display()))?;
    let validation = if args.validate {
        let holdout = subsurf::validate::holdout(&ds, &frames);
        let v = fit_scan_in(&run, &judge, &holdout.training, &cv, &fit, &bar)
            .with_context(|| format!("validation fit of {}", args.scan.display()))?;
        let v = subsurf::validate::judge(&judge, &v.model, holdout, v.report.log_e, &bar)
            .context("judging the validation fit on the held-out frames")?;
        Some(v)
    } else {
        None
    };
    let out = fit_scan_in(&run, &judge, &frames, &cv, &fit, &bar)
        .with_context(|| format!("fitting {}", args.scan.display()))?;
    bar.finish_and_clear();
    let report_dir = args.report.as_deref().and_then(std::path::Path::parent);
    for dir in [args.out.parent(), report_dir].into_iter().flatten() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    out.model
        .write(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let bytes = std::fs::metadata(&args.out).map(|m| m.len()).unwrap_or(0);
    let report_path = args
        .report
        .unwrap_or_else(|| args.out.with_file_name("fit-report.json"));
    let mut json = serde_json::to_value(&out.report)?;
    json["model_bytes"] = bytes.into();
    json["model"] = args.out.display().to_string().into();
    json["fit_options"] = serde_json::to_value(&fit)?;
    json["noise_floor"] = serde_json::to_value(&floor)?;
    if let Some(v) = &validation {
        json["validation"] = serde_json::to_value(v)?;
    }
    if let Some(c) = &mesh_check {
        json["mesh_check"] = serde_json::to_value(c)?;
    }
    if let Some(cv) = &out.report.cross_validation {
        println!(
            "cross-validation: {} ({} fits, {:.1} s)",
            cv.rule, cv.fits, cv.seconds
        );
        if let Some(why) = &cv.skipped {
            println!("  {why}");
        }
        for c in &cv.choices {
            if c.candidates.is_empty() {
                println!("  {}: {} ({})", c.name, c.chosen, c.rule);
                continue;
            }
            println!(
                "  {}: {} chosen; held-out log E per candidate {}",
                c.name,
                c.chosen,
                c.candidates
                    .iter()
                    .map(|k| format!(
                        "{}: {}{}",
                        k.value,
                        k.score.map_or("-".into(), subsurf::report::fmt::log_e),
                        k.worse_by.zip(k.se).filter(|(d, _)| *d > 0.0).map_or(
                            String::new(),
                            |(d, se)| format!(
                                " (+{} ± {})",
                                subsurf::report::fmt::log_e(d),
                                subsurf::report::fmt::log_e(se)
                            )
                        )
                    ))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
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
    if let Some(m) = subsurf::util::peak_rss_mib() {
        json["process_peak_rss_mib"] = m.into();
    }
    if let Some(c) = subsurf::util::cpu_seconds() {
        json["process_cpu_s"] = c.into();
    }
    std::fs::write(&report_path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    let drawn = drawn?;
    for line in subsurf::report::fit::summary_lines(&out.report) {
        println!("{line}");
    }
    let r = &out.report;
    let f = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.4}"));
    if let Some(b) = &r.baseline {
        println!(
            "homogeneous baseline (one isotropic fall-off for every x_i, {} terms, {} samples, r {:.2}..{:.2} mm): log E(x_i) mean r/g/b {} {} {}",
            b.terms,
            b.samples,
            b.r_range[0],
            b.r_range[1],
            f(b.log_e.mean[0]),
            f(b.log_e.mean[1]),
            f(b.log_e.mean[2])
        );
    }
    for k in &r.alpha.round_log {
        println!(
            "  round {}: training objective {:.6e} (last kept round {:.6e}; fits against the alpha they were fitted to {:.6e}; {} light positions kept their previous fit) {}",
            k.round,
            k.objective,
            k.previous,
            k.fitted,
            k.fits_kept_previous,
            if k.kept { "kept" } else { "discarded" }
        );
    }
    if let Some(v) = &validation {
        println!(
            "validation: {} frames held out ({}), {} evaluated; {}",
            v.holdout.frames.len(),
            subsurf::validate::frame_list(&v.holdout.frames),
            v.evaluated,
            v.holdout.rule
        );
        println!("  mean log E(x_i)          red      green    blue");
        let row = |name: &str, st: &subsurf::pipeline::LogEStats| {
            println!(
                "  {name:<22} {:8} {:8} {:8}",
                f(st.mean[0]),
                f(st.mean[1]),
                f(st.mean[2])
            )
        };
        row("held out (trust this)", &v.held_out);
        if let Some(b) = &v.baseline_held_out {
            row("baseline, held out", b);
        }
        row("in-sample", &v.in_sample);
        println!("  (then fitted on all {} frames)", r.frames.selected);
    }
    println!(
        "model {} ({}); report {}",
        args.out.display(),
        subsurf::report::fmt::bytes(bytes),
        report_path.display()
    );
    // The same figures for people: fit-report.md (terminals) and a self-contained
    // fit-report.html (pictures embedded), beside fit-report.json.
    let figures = drawn
        .iter()
        .zip([
            "log E(x_i) per vertex (Eq. 8)",
            "the model: alpha, reflectance, reach, status",
        ])
        .map(|(p, c)| subsurf::report::Figure {
            path: p.clone(),
            caption: c.into(),
        })
        .collect();
    let inputs = subsurf::report::fit::FitInputs {
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
        .unwrap_or_else(|| std::path::Path::new("."));
    let [md, html] = subsurf::report::fit::fit_report(&out.report, &inputs).write(dir, &stem)?;
    println!("wrote {} and {}", md.display(), html.display());
    for p in &drawn {
        println!("wrote {}", p.display());
    }
    Ok(())
}
