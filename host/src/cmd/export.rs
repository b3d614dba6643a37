//! `subsurf export`: a model for another renderer (Blender's Cycles), checked by rendering it
//! there when Blender is present.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

use super::models::{builtin, lights_or_default, load_model, parse_size, resolve_camera};
use super::progress::Bar;
use subsurf::export::choose::ColourArg;
use subsurf::export::{self, ExportOptions, GatherMode, LatticeMode};
use subsurf::render::{Method, Quality, RenderOptions};

/// The renderers `export` writes for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Blender 3.4+ (Cycles): binary glTF with custom attributes, the scene, the script that
    /// builds the node tree; the `.blend` when Blender is present.
    Blender,
}

/// Export a model for Blender's Cycles: Burley subsurface per vertex, or a Principled Volume.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The fitted model (`docs/model-format.md`).
    #[arg(long, conflicts_with = "builtin")]
    model: Option<PathBuf>,
    /// Built-in model instead of a file: `torus` or `torus:NU,NV`.
    #[arg(long, default_value = "torus")]
    builtin: String,
    /// What to write for.
    #[arg(long, value_enum, default_value_t = Format::Blender)]
    format: Format,
    /// Output folder (created; files in it are overwritten).
    #[arg(long)]
    out: PathBuf,
    /// Alpha finer than the mesh (`face_alpha`): refine the mesh, or drop the detail.
    #[arg(long, value_enum, default_value_t = LatticeMode::Refine)]
    lattice: LatticeMode,
    /// A light of the scene (as `subsurf render --light`); default: the render's key and fill.
    #[arg(long = "light")]
    lights: Vec<String>,
    /// The scene's camera (as `subsurf render --camera`).
    #[arg(long, default_value = "auto")]
    camera: String,
    /// Image size `WxH` of the scene.
    #[arg(long, default_value = "512x512")]
    size: String,
    /// Relative refractive index of the exit Fresnel factor (as `subsurf render`); 0: none.
    #[arg(long, default_value_t = 1.3)]
    eta: f64,
    /// Cycles samples per pixel.
    #[arg(long, default_value_t = 64)]
    samples: u32,
    /// What the subsurface colour is (docs/export.md).
    #[arg(long, value_enum, default_value_t = ColourArg::Fitted)]
    colour: ColourArg,
    /// Scale the colour by how Cycles gathers light on the model's shape against subsurf.
    #[arg(long, value_enum, default_value_t = GatherMode::Off)]
    gather: GatherMode,
    /// Blender executable (default: `$SUBSURF_BLENDER`, else `blender` on the PATH).
    #[arg(long)]
    blender: Option<PathBuf>,
    /// Only measure the Blender's subsurface response (the half-lit slab's edge response per
    /// method and albedo, `--samples` per pixel) into OUT/cycles-response.json.
    #[arg(long, conflicts_with_all = ["render", "no_blender"])]
    measure_cycles: bool,
    /// Do not run Blender even if it is installed (no `.blend`).
    #[arg(long, conflicts_with = "render")]
    no_blender: bool,
    /// Also render the scene in Cycles and compare it with subsurf's render of the model
    /// (`cycles.exr`, `subsurf.exr`, `difference.png`, the error in the report). Needs Blender.
    #[arg(long)]
    render: bool,
    /// With `--render`: render Cycles twice (two seeds) to measure its sampling noise.
    #[arg(long, requires = "render")]
    noise: bool,
    /// Speed/accuracy of subsurf's render for `--render`.
    #[arg(long, value_enum, default_value_t = Quality::Balanced)]
    quality: Quality,
    /// The model's scan: with `--render`, Cycles renders its frames (`--frames`: camera,
    /// exposure, laser, turntable) into `OUT/frames/`, judged by the frames beside subsurf's
    /// model or trace; with `--colour auto`, its training frames choose the colour.
    #[arg(long)]
    scan: Option<PathBuf>,
    /// Frames of `--scan` to render, e.g. `96-103` (default: all).
    #[arg(long, requires = "scan")]
    frames: Option<String>,
    /// Where the sample store's files go with `--scan` (`dataset`, a directory, `off`), as
    /// `subsurf evaluate --cache`.
    #[arg(long, default_value = "dataset")]
    cache: subsurf::pipeline::Cache,
    /// Photons per frame of a volume model's own trace beside Cycles' (`--scan`; default as
    /// `subsurf evaluate`'s).
    #[arg(long)]
    photons: Option<usize>,
}

pub fn run(args: Args) -> Result<()> {
    let Format::Blender = args.format;
    if args.measure_cycles {
        let b = export::find_blender(args.blender.as_deref())?.context("no Blender found")?;
        print!("{}", b.measure(&args.out, args.samples)?.text());
        return Ok(());
    }
    let blender = match args.no_blender {
        true => None,
        false => export::find_blender(args.blender.as_deref())?,
    };
    if args.render && blender.is_none() {
        bail!(
            "--render needs Blender: none found (--blender PATH, ${}, or `blender` on the PATH)",
            export::blender::BLENDER_ENV
        );
    }
    if args.scan.is_some() && !args.render && args.colour != ColourArg::Auto {
        bail!("--scan is read with --render (its frames rendered) or --colour auto");
    }
    let open = |s: &PathBuf| super::open_frames(s, args.frames.as_deref(), None);
    let scan = args.scan.as_ref().map(open).transpose()?;
    if let Some(p) = args.model.as_deref()
        && subsurf::volume::model::is_volume_file(p)
    {
        return volume(&args, p, blender.as_ref(), scan.as_ref());
    }
    let model = match &args.model {
        Some(p) => load_model(p)?,
        None => builtin(&args.builtin)?,
    };
    let transport = Method::Hierarchical(args.quality.params());
    let opts = ExportOptions {
        lattice: args.lattice,
        eta: (args.eta > 0.0).then_some(args.eta),
        lights: lights_or_default(&args.lights, model.bounds())?,
        camera: resolve_camera(&args.camera, parse_size(&args.size)?, model.bounds())?,
        samples: args.samples,
        colour: args.colour.rule(), // with `auto`, replaced by the choice below
        gather: args.gather,
    };
    let bar = Bar::with_template("{msg:>12} {bar:40} {pos}/{len} {elapsed}");
    let store = subsurf::pipeline::StoreOptions::cached(args.cache.clone());
    let auto = match (args.colour, &scan) {
        (ColourArg::Auto, Some((ds, _))) => Some((ds, blender.as_ref().map(|b| b.version))),
        (ColourArg::Auto, None) => bail!("--colour auto needs --scan (the model's scan)"),
        _ => None,
    };
    let (exported, choice) = export::choose::export_choosing(&model, &opts, auto, &store, &bar)
        .context("converting the model")?;
    bar.finish_and_clear();
    let mut written = exported.write(&args.out)?;
    if let Some(c) = &choice {
        print!("{}", c.text());
        written.push(c.write(&args.out)?);
    }
    for line in exported.summary_lines() {
        println!("{line}");
    }
    let mut comparison = None;
    let mut frames = None;
    let bar = Bar::with_template("{msg:>16} {bar:40} {pos}/{len} {elapsed}");
    match &blender {
        Some(b) => {
            if let (true, Some((ds, list))) = (args.render, &scan) {
                let (n, seeds) = (list.len(), if args.noise { ", two seeds" } else { "" });
                let (dir, v) = (ds.dir.display(), &b.version_line);
                println!(
                    "rendering {n} frames of {dir} in {v} (Cycles, {} samples{seeds})…",
                    args.samples
                );
                let (_, cmp) = export::frames::render_and_judge(
                    ds,
                    export::frames::Subject::Empirical(&model, Some(&exported)),
                    list,
                    args.samples,
                    b,
                    &args.out,
                    args.noise,
                    &store,
                    &bar,
                )
                .context("rendering the scan's frames in Cycles")?;
                bar.finish_and_clear();
                print!("{}", export::frames_text(&cmp));
                written.push(args.out.join(export::frames::FRAMES_FILE));
                written.push(args.out.join(export::frames::FRAMES_DIR));
                frames = Some(cmp);
                b.run(&args.out, &export::Run::default())?;
            } else if args.render {
                println!(
                    "rendering in {} (Cycles, {} samples)…",
                    b.version_line, args.samples
                );
                let ropts = RenderOptions {
                    method: transport,
                    eta: opts.eta,
                };
                let c = export::compare_with(&model, &opts, &ropts, b, &args.out, args.noise, &bar);
                bar.finish_and_clear();
                let c = c?;
                println!("{}", c.line());
                written.extend(c.files.iter().cloned());
                comparison = Some(c);
            } else {
                b.run(&args.out, &export::Run::default())?;
            }
            written.push(args.out.join(export::BLEND_FILE));
        }
        None if args.no_blender => {}
        None => println!(
            "no Blender found: run `blender -b --python {}` in {} to make the .blend",
            export::BUILD_SCRIPT,
            args.out.display()
        ),
    }
    written.extend(export::write_report(
        &model,
        &exported,
        comparison.as_ref(),
        frames.as_ref(),
        blender.as_ref(),
        &args.out,
    )?);
    written.dedup();
    println!("wrote into {}:", args.out.display());
    for f in written {
        println!("  {}", f.display());
    }
    Ok(())
}

/// A volume model: its medium as a Principled Volume, judged by `--scan`'s frames if given.
fn volume(
    args: &Args,
    path: &std::path::Path,
    blender: Option<&export::Blender>,
    scan: Option<&(subsurf::dataset::Dataset, Vec<usize>)>,
) -> Result<()> {
    let model = subsurf::volume::VolumeModel::read(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let b = model.mesh.bounds();
    let opts = export::volume::VolumeExportOptions {
        lights: lights_or_default(&args.lights, b)?,
        camera: resolve_camera(&args.camera, parse_size(&args.size)?, b)?,
        samples: args.samples,
        render: args.render,
    };
    let run = scan.map(|(ds, frames)| export::volume::FramesRun {
        ds,
        frames,
        noise: args.noise,
        photons: subsurf::evaluate::run::volume_photons(&model, args.photons),
        store: subsurf::pipeline::StoreOptions::cached(args.cache.clone()),
    });
    let bar = Bar::with_template("{msg:>16} {bar:40} {pos}/{len} {elapsed}");
    let r = export::volume::export_volume(&model, &opts, &args.out, blender, run, &bar);
    bar.finish_and_clear();
    let r = r.context("exporting the volume model")?;
    r.frames
        .iter()
        .for_each(|f| print!("{}", export::frames_text(f)));
    println!("wrote into {}:", args.out.display());
    r.files.iter().for_each(|f| println!("  {}", f.display()));
    Ok(())
}
