//! `subsurf render`: relight a fitted model and save the picture.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};

use super::models::{builtin, load_model};
use subsurf::render::{self, Camera, CameraSpec, Light, Method, Quality, RenderOptions};

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

/// `WxH` → (W, H).
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("size `{s}` is not WxH"))?;
    let (w, h): (u32, u32) = (w.trim().parse()?, h.trim().parse()?);
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        bail!("size `{s}` must be 1..=16384 per side");
    }
    Ok((w, h))
}

/// Resolves a camera spec, reading the JSON file if it names one.
pub fn resolve_camera(
    spec: &str,
    size: (u32, u32),
    model: &subsurf::modelfile::ModelFile,
) -> Result<Camera> {
    let spec: CameraSpec = spec.parse()?;
    Ok(match spec {
        CameraSpec::Auto(dir) => {
            let (lo, hi) = model.bounds();
            Camera::framing(lo, hi, dir, size.0, size.1)?
        }
        CameraSpec::LookAt {
            eye,
            target,
            fov_deg,
        } => Camera::look_at_fov(eye, target, [0.0, 0.0, 1.0], fov_deg, size.0, size.1)?,
        CameraSpec::File { path, index } => {
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("reading {}", path.display()))?;
            Camera::from_json(&text, index)
                .with_context(|| format!("camera in {}", path.display()))?
        }
    })
}

pub fn run(args: Args) -> Result<()> {
    let model = match &args.model {
        Some(p) => load_model(p)?,
        None => builtin(&args.builtin)?,
    };
    let lights = if args.lights.is_empty() {
        Light::defaults_for(model.bounds())
    } else {
        args.lights
            .iter()
            .map(|s| s.parse::<Light>())
            .collect::<Result<_, _>>()?
    };
    let camera = resolve_camera(&args.camera, parse_size(&args.size)?, &model)?;
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
