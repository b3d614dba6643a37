//! The model inputs `render` and `plot` share: a model file, or a built-in model by name.

use anyhow::{Context, Result, bail};
use subsurf::render::{self, VertexModel};

/// Loads the model named by `--builtin`.
pub fn builtin(name: &str) -> Result<VertexModel> {
    match name.split_once(':') {
        None if name == "torus" => Ok(render::synthetic::marble_torus(160, 64)),
        Some(("torus", dims)) => {
            let (a, b) = dims.split_once(',').context("torus:NU,NV")?;
            Ok(render::synthetic::marble_torus(a.parse()?, b.parse()?))
        }
        _ => bail!("unknown built-in model `{name}` (known: torus, torus:NU,NV)"),
    }
}

/// Reads a model file into the renderer's form and checks it.
pub fn load_model(path: &std::path::Path) -> Result<VertexModel> {
    let file = subsurf::modelfile::ModelFile::read(path)
        .with_context(|| format!("reading model {}", path.display()))?;
    let model = VertexModel::from_model_file(&file);
    model
        .validate()
        .with_context(|| format!("model {}", path.display()))?;
    Ok(model)
}
