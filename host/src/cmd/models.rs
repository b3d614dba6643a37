//! The model inputs `render`, `plot` and `export` share: a model file, or a built-in model by
//! name; the image size and camera of a render.

use anyhow::{Context, Result, bail};
use subsurf::modelfile::ModelFile;
use subsurf::render::{self, Camera, CameraSpec, Light};

/// Loads the model named by `--builtin`.
pub fn builtin(name: &str) -> Result<ModelFile> {
    match name.split_once(':') {
        None if name == "torus" => Ok(render::synthetic::marble_torus(160, 64)),
        Some(("torus", dims)) => {
            let (a, b) = dims.split_once(',').context("torus:NU,NV")?;
            Ok(render::synthetic::marble_torus(a.parse()?, b.parse()?))
        }
        _ => bail!("unknown built-in model `{name}` (known: torus, torus:NU,NV)"),
    }
}

/// Reads a model file and checks it as the renderer needs it.
pub fn load_model(path: &std::path::Path) -> Result<ModelFile> {
    let model =
        ModelFile::read(path).with_context(|| format!("reading model {}", path.display()))?;
    render::validate(&model).with_context(|| format!("model {}", path.display()))?;
    Ok(model)
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
    (lo, hi): ([f64; 3], [f64; 3]),
) -> Result<Camera> {
    let spec: CameraSpec = spec.parse()?;
    Ok(match spec {
        CameraSpec::Auto(dir) => Camera::framing(lo, hi, dir, size.0, size.1)?,
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

/// The lights of `--light` specs, or the renderer's default key and fill lights for `model`.
pub fn lights_or_default(specs: &[String], bounds: ([f64; 3], [f64; 3])) -> Result<Vec<Light>> {
    if specs.is_empty() {
        return Ok(Light::defaults_for(bounds));
    }
    Ok(specs
        .iter()
        .map(|s| s.parse::<Light>())
        .collect::<Result<_, _>>()?)
}
