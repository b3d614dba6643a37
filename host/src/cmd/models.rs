//! The model inputs `render` and `plot` share: a model file, or a built-in model by name.

use anyhow::{Context, Result, bail};
use subsurf::modelfile::ModelFile;
use subsurf::render;

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
