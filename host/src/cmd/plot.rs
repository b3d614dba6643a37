//! `subsurf plot …`: the paper's figures and the model viewer as PNGs.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Subcommand;
use subsurf::curves::Curve;
use subsurf::modelfile::ModelFile;
use subsurf::render::CameraSpec;

use super::models::{builtin, load_model};

/// Draw a figure.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Debug, Subcommand)]
enum What {
    /// Figure 3: samples of one lit point on a log scale with the exponential and dipole fits.
    Falloff(FalloffArgs),
    /// Figures 4/5: per-x_i log E(x_i) over the surface, one panel per model (e.g. isotropic
    /// against anisotropic).
    Error(ErrorArgs),
    /// The model viewer: alpha, total reflectance, reach and status on the mesh.
    Model(ModelArgs),
}

#[derive(Debug, clap::Args)]
struct FalloffArgs {
    /// CSV as for `fit-curve`: header `r,value` (or `r,r_value,g_value,b_value`: the first
    /// channel is drawn), `#` comments allowed.
    csv: PathBuf,
    /// Relative refractive index of the dipole.
    #[arg(long, default_value_t = 1.3)]
    eta: f64,
    #[arg(long, default_value = "falloff.png")]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
struct ErrorArgs {
    /// Model files (same mesh), one panel each; label with `LABEL=PATH`.
    #[arg(long = "model", required = true)]
    models: Vec<String>,
    /// View direction `auto[:DX,DY,DZ]`.
    #[arg(long, default_value = "auto")]
    view: String,
    #[arg(long, default_value = "error-map.png")]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
struct ModelArgs {
    /// Model file; the built-in torus when left out.
    #[arg(long)]
    model: Option<PathBuf>,
    /// View direction `auto[:DX,DY,DZ]`.
    #[arg(long, default_value = "auto")]
    view: String,
    #[arg(long, default_value = "model.png")]
    out: PathBuf,
}

fn view(spec: &str) -> Result<[f64; 3]> {
    match spec.parse::<CameraSpec>()? {
        CameraSpec::Auto(d) => Ok(d),
        _ => bail!("--view takes auto[:DX,DY,DZ]"),
    }
}

/// The first curve of a fall-off file in `fit-curve`'s format ([`subsurf::curves`]): `r` and its
/// first channel.
fn read_csv(path: &std::path::Path) -> Result<(Vec<f64>, Vec<f64>)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let curves =
        subsurf::curves::parse(&text, false).with_context(|| path.display().to_string())?;
    match curves.into_iter().next() {
        Some(Curve {
            r, mut channels, ..
        }) if !r.is_empty() && !channels.is_empty() => Ok((r, channels.swap_remove(0))),
        _ => bail!("{}: no samples", path.display()),
    }
}

pub fn run(args: Args) -> Result<()> {
    match args.what {
        What::Falloff(a) => {
            let (r, s) = read_csv(&a.csv)?;
            let title = format!("Fall-off of one x_i: {}", a.csv.display());
            let fits = subsurf::evaluate::compare_falloff(&r, &s, a.eta);
            let sum = subsurf::plot::falloff_figure(&a.out, &title, &r, &s, &fits)?;
            println!(
                "{} samples; log E: sum of exponentials {}, dipole {}",
                sum.samples,
                sum.expsum_log_e
                    .map_or("no fit".into(), |v| format!("{v:.4}")),
                sum.dipole_log_e
                    .map_or("no fit".into(), |v| format!("{v:.4}"))
            );
            println!("wrote {}", a.out.display());
        }
        What::Error(a) => {
            let mut models: Vec<(String, ModelFile)> = Vec::new();
            for spec in &a.models {
                let (label, path) = match spec.split_once('=') {
                    Some((l, p)) => (l.to_string(), PathBuf::from(p)),
                    None => (spec.clone(), PathBuf::from(spec)),
                };
                models.push((label, load_model(&path)?));
            }
            let refs: Vec<(String, &ModelFile)> =
                models.iter().map(|(l, m)| (l.clone(), m)).collect();
            subsurf::plot::error_maps(&a.out, &refs, view(&a.view)?, (420, 420))?;
            println!("wrote {}", a.out.display());
        }
        What::Model(a) => {
            let model = match &a.model {
                Some(p) => load_model(p)?,
                None => builtin("torus")?,
            };
            subsurf::plot::model_viewer(&a.out, &model, view(&a.view)?, (360, 400))?;
            println!("wrote {}", a.out.display());
        }
    }
    Ok(())
}
