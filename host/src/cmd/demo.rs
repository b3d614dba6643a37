//! `subsurf demo`: the main job end to end on built-in defaults, no hardware, no arguments.
//!
//! Simulated rig served on a pseudo-terminal → `scan` of the built-in object with the simulated
//! camera → per-vertex fit (isotropic, and anisotropic m = 4 for the error map) with
//! interpolation of failed vertices → renders under two lights → report and pictures in one folder.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use subsurf::calib::Calibration;
use subsurf::dataset::{Dataset, select_frames};
use subsurf::fit::{FitOptions, Terms};
use subsurf::link::SerialLink;
use subsurf::pipeline::{Context as FitContext, PipelineOptions, fit_dataset, register_one};
use subsurf::render::{self, Camera, Light, RenderOptions, VertexModel};
use subsurf::rig::{ClientConfig, RigClient};
use subsurf::scan::driver::{ScanConfig, run};
use subsurf::scan::plan::{PlanOptions, PlanScene, coverage_plan};
use subsurf::scan::setup::{builtin_object, camera_from_spec, obj_text};

use super::progress::Bar;

/// Run the whole chain on the simulated rig and write the results into one folder.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output folder (created; files in it are overwritten).
    #[arg(long, default_value = "subsurf-demo")]
    out: PathBuf,
    /// Camera image size of the simulated scan (pixels per side); smaller is faster.
    #[arg(long, default_value_t = 64)]
    size: u32,
    /// Turntable angles of the scan.
    #[arg(long, default_value_t = 6)]
    angles: usize,
    /// Laser raster per side (coverage planner picks from it).
    #[arg(long, default_value_t = 12)]
    raster: usize,
    /// Size of the rendered pictures (pixels per side).
    #[arg(long, default_value_t = 480)]
    picture: u32,
}

fn bar(len: u64, msg: &str) -> Bar {
    let p = Bar::with_template("{msg:>10} {bar:40} {pos}/{len} {elapsed}");
    p.set_length(len);
    p.set_message(msg.to_string());
    p
}

pub fn run_demo(args: &Args) -> Result<Vec<PathBuf>> {
    let t0 = Instant::now();
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut report = String::from("# subsurf demo\n\n");
    let mut written = Vec::new();

    // 1. The simulated rig on a pseudo-terminal, reached like a serial port.
    let (controller, device) = SerialLink::pty_pair().context("creating a pseudo-terminal")?;
    let path = device.path().context("pseudo-terminal without a path")?;
    let _server = subsurf::sim::spawn(controller, subsurf::sim::SimParams::default())
        .context("starting the simulated rig")?;
    let link = SerialLink::open(&path, 921_600).with_context(|| format!("opening {path}"))?;
    let mut rig = RigClient::connect(link, ClientConfig::default())
        .context("handshake with the simulated rig")?;
    println!("simulated rig on {path}");

    // 2. Scan the built-in object with the simulated camera.
    let obj = builtin_object();
    let mesh = obj.mesh();
    let (centre, radius) = obj.bounds();
    let calib = Calibration::builtin_for(centre, radius, args.size);
    let scene = PlanScene::new(&mesh.positions, &mesh.triangles, &calib)?;
    let plan = coverage_plan(
        &scene,
        &PlanOptions {
            angles: args.angles,
            raster: args.raster,
            target_mm: 2.0,
            exposures_s: vec![0.2],
            ..PlanOptions::default()
        },
    )?;
    let scan_dir = out.join("scan");
    if scan_dir.exists() {
        std::fs::remove_dir_all(&scan_dir)
            .with_context(|| format!("clearing {}", scan_dir.display()))?;
    }
    let cfg = ScanConfig::new(scan_dir.clone(), plan, calib.clone(), obj_text(&mesh));
    let mut camera = camera_from_spec("sim", &mesh, &calib, 7, std::time::Duration::from_secs(10))?;
    let p = bar(cfg.plan.frame_count() as u64, "scan");
    let ts = Instant::now();
    let summary = run(&cfg, &mut rig, camera.as_mut(), &p)?;
    p.finish_and_clear();
    drop(rig);
    let scan_s = ts.elapsed().as_secs_f64();
    println!("scanned {} frames in {scan_s:.1} s", summary.frames_written);
    writeln!(
        report,
        "## Scan\n\nBuilt-in object (sphere, r = {} mm, {} vertices), simulated rig on pseudo-terminal \
         `{path}`, simulated camera {}x{} px: {} frames in {scan_s:.1} s. Dataset: `scan/`.\n",
        subsurf::scan::setup::BUILTIN_RADIUS_MM,
        mesh.positions.len(),
        args.size,
        args.size,
        summary.frames_written
    )?;

    // 3. Fit: isotropic shared colour (Eq. 9, as the paper's §5), and anisotropic m = 4.
    let ds = Dataset::open(&scan_dir).context("reading the scan back")?;
    let frames = select_frames(ds.spec.frames.len(), None, None).map_err(|e| anyhow!(e))?;
    let mut fits = Vec::new();
    for segments in [1usize, 4] {
        let mut opts = PipelineOptions::for_dataset(&ds);
        opts.model.segments = segments;
        let p = bar(
            0,
            if segments == 1 {
                "fit iso"
            } else {
                "fit aniso"
            },
        );
        let tf = Instant::now();
        // Few samples per x_i on this small scan: let the fitter drop terms it cannot support
        // ("the number of exponents n was reduced", §5) rather than extrapolate a fast term.
        let fit_options = FitOptions {
            terms: Terms::Auto {
                max: 3,
                tolerance: 0.05,
            },
            ..FitOptions::default()
        };
        let fitted = fit_dataset(&ds, &frames, &opts, &fit_options, &p)?;
        p.finish_and_clear();
        let name = if segments == 1 {
            "model.ply"
        } else {
            "model-aniso.ply"
        };
        fitted.model.write(&out.join(name))?;
        written.push(out.join(name));
        let r = &fitted.report;
        writeln!(
            report,
            "## Fit ({})\n\n{} vertices: {} fitted, {} interpolated, {} without model; mean log E (R, G, B) = \
             {:?}; {:.1} s. Model: `{name}`.\n",
            if segments == 1 {
                "isotropic, Eq. 9"
            } else {
                "anisotropic, m = 4, Eq. 3/5"
            },
            r.vertices,
            r.vertices_fitted,
            r.vertices_interpolated,
            r.vertices_no_model,
            r.log_e.mean,
            tf.elapsed().as_secs_f64()
        )?;
        std::fs::write(
            out.join(if segments == 1 {
                "fit-report.json"
            } else {
                "fit-report-aniso.json"
            }),
            serde_json::to_string_pretty(r)?,
        )?;
        fits.push(VertexModel::from_model_file(&fitted.model));
    }
    let iso = &fits[0];
    iso.validate()?;

    // 4. Render under two lights.
    let (lo, hi) = iso.bounds();
    let cam = Camera::framing(lo, hi, render::DEFAULT_VIEW, args.picture, args.picture)?;
    let lights_sets: [(&str, Vec<Light>); 2] = [
        ("render-key-light.png", super::render::default_lights(iso)),
        (
            "render-back-light.png",
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
    for (name, lights) in &lights_sets {
        let r = render::render(iso, lights, &cam, &RenderOptions::default())?;
        render::save_png(&r.image, None, &out.join(name))?;
        render::save_exr(&r.image, &out.join(name).with_extension("exr"))?;
        written.push(out.join(name));
        writeln!(
            report,
            "Rendered `{name}` (+ linear `.exr`): {} light(s), transport {:.2} s.\n",
            lights.len(),
            r.seconds[1]
        )?;
    }

    // 5. Pictures: Figure 3 from one scanned frame, error maps, model viewer.
    let ctx = FitContext::new(&ds, PipelineOptions::for_dataset(&ds))?;
    // The frame whose x_i has the most green samples.
    let mut best: Option<(usize, Vec<f64>, Vec<f64>)> = None;
    for k in 0..ds.spec.frames.len() {
        let Ok(reg) = register_one(&ctx, k) else {
            continue;
        };
        let Ok((samples, _)) = ctx.samples(&reg) else {
            continue;
        };
        let (r, s): (Vec<f64>, Vec<f64>) = samples
            .iter()
            .filter(|s| s.valid & 2 != 0)
            .map(|s| (s.r, s.value[1]))
            .unzip();
        if best.as_ref().is_none_or(|b| b.1.len() < r.len()) {
            best = Some((k, r, s));
        }
    }
    let mut plotted = false;
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
        writeln!(
            report,
            "Figure 3 (`falloff.png`): frame {k}, {} samples; log E sum of exponentials {:?}, dipole {:?}.\n",
            sum.samples, sum.expsum_log_e, sum.dipole_log_e
        )?;
        written.push(f);
        plotted = true;
    }
    if !plotted {
        writeln!(report, "No frame had enough samples for a fall-off plot.\n")?;
    }
    let e = out.join("error-map.png");
    subsurf::plot::error_maps(
        &e,
        &[
            ("isotropic".into(), &fits[0]),
            ("anisotropic, m = 4".into(), &fits[1]),
        ],
        render::DEFAULT_VIEW,
        (360, 380),
    )?;
    written.push(e);
    let m = out.join("model.png");
    subsurf::plot::model_viewer(&m, iso, render::DEFAULT_VIEW, (300, 340))?;
    written.push(m);
    writeln!(
        report,
        "Error maps: `error-map.png` (log E(x_i), Eq. 8, isotropic vs anisotropic). Model viewer: `model.png`.\n\n\
         Total wall time {:.1} s.",
        t0.elapsed().as_secs_f64()
    )?;
    let rp = out.join("report.md");
    std::fs::write(&rp, report).with_context(|| format!("writing {}", rp.display()))?;
    written.insert(0, rp);
    Ok(written)
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
