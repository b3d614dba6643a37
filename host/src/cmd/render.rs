//! `subsurf render`: relight a fitted model and save the picture.

use std::path::PathBuf;

use anyhow::{Context, Result};

use super::models::{builtin, lights_or_default, load_model, parse_size, resolve_camera};
use subsurf::render::{self, Method, Quality, RenderOptions};

/// Render a model under point, spot and directional lights.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The fitted model (`docs/model-format.md`), as written by `subsurf fit`.
    #[arg(long, conflicts_with = "builtin")]
    model: Option<PathBuf>,
    /// Built-in model instead of a file: `torus` (veined-marble torus) or `torus:NU,NV`.
    #[arg(long, default_value = "torus")]
    builtin: String,
    /// A light: `point:X,Y,Z[:R,G,B]`, `spot:X,Y,Z:DX,DY,DZ:DEG[:R,G,B]`, `dir:DX,DY,DZ[:R,G,B]`
    /// (mm, object frame). Repeat for several lights. Default: a key light and a fill light.
    #[arg(long = "light")]
    lights: Vec<String>,
    /// `auto[:DX,DY,DZ]`, `lookat:EX,EY,EZ:TX,TY,TZ[:FOV]` or `scan.json[#K]` (OpenCV intrinsics;
    /// its own image size is used).
    #[arg(long, default_value = "auto")]
    camera: String,
    /// Image size `WxH` for auto and look-at cameras.
    #[arg(long, default_value = "512x512")]
    size: String,
    /// Speed/accuracy of the hierarchical transport.
    #[arg(long, value_enum, default_value_t = Quality::Balanced)]
    quality: Quality,
    /// Use the exact O(N²) sum (the reference) instead of the hierarchy.
    #[arg(long)]
    exact: bool,
    /// Relative refractive index for the Fresnel factors; 0 turns them off.
    #[arg(long, default_value_t = 1.3)]
    eta: f64,
    /// Fixed exposure (linear scale before the sRGB curve); automatic when left out.
    #[arg(long)]
    exposure: Option<f64>,
    /// Tone-mapped PNG to write.
    #[arg(long, default_value = "render.png")]
    out: PathBuf,
    /// Linear float EXR to write as well.
    #[arg(long)]
    exr: Option<PathBuf>,
}

pub fn run(args: Args) -> Result<()> {
    let model = match &args.model {
        Some(p) => load_model(p)?,
        None => builtin(&args.builtin)?,
    };
    let lights = lights_or_default(&args.lights, model.bounds())?;
    let camera = resolve_camera(&args.camera, parse_size(&args.size)?, model.bounds())?;
    let options = RenderOptions {
        method: if args.exact {
            Method::Exact
        } else {
            Method::Hierarchical(args.quality.params())
        },
        eta: (args.eta > 0.0).then_some(args.eta),
    };
    let out = render::render(&model, &lights, &camera, &options).context("rendering")?;
    render::save_png(&out.image, args.exposure, &args.out)?;
    println!(
        "{} vertices, {} lights: irradiance {:.2} s, transport {:.2} s, image {:.2} s",
        model.len(),
        lights.len(),
        out.seconds[0],
        out.seconds[1],
        out.seconds[2]
    );
    println!("wrote {}", args.out.display());
    if let Some(exr) = &args.exr {
        render::save_exr(&out.image, exr)?;
        println!("wrote {}", exr.display());
    }
    Ok(())
}
