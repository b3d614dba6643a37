//! `subsurf predict`: what the model says the camera of a frame sees.
use std::path::PathBuf;

use anyhow::Context;
use subsurf::dataset::{Dataset, write_exr};
use subsurf::evaluate::run::{AnyModel, predict_any};

/// Render the model's prediction of frame K (laser at that frame's x_i) as an OpenEXR image.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model written by `subsurf fit`: the empirical model (PLY) or a volume (JSON).
    #[arg(long)]
    pub model: PathBuf,
    /// The scan dataset: its folder or its `scan.json`.
    #[arg(long)]
    pub scan: PathBuf,
    /// Frame index.
    #[arg(long)]
    pub frame: usize,
    /// Output image (.exr).
    #[arg(long)]
    pub out: PathBuf,
    /// Photons of a volume model's prediction (default 1 million; 4 million behind a dielectric).
    #[arg(long)]
    pub photons: Option<usize>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let ds =
        Dataset::open(&args.scan).with_context(|| format!("opening {}", args.scan.display()))?;
    let model = AnyModel::read(&args.model)?;
    let img = predict_any(&ds, &model, args.frame, args.photons)?;
    write_exr(&args.out, &img).with_context(|| format!("writing {}", args.out.display()))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
