//! `subsurf predict`: what the model says the camera of a frame sees.
use std::path::PathBuf;

use anyhow::Context;
use subsurf::dataset::{Dataset, write_exr};
use subsurf::evaluate::predict_frame;
use subsurf::modelfile::ModelFile;
use subsurf::pipeline::PipelineOptions;

/// Render the model's prediction of frame K (laser at that frame's x_i) as an OpenEXR image.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model (PLY written by `subsurf fit`).
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
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let ds =
        Dataset::open(&args.scan).with_context(|| format!("opening {}", args.scan.display()))?;
    let model = ModelFile::read(&args.model)
        .with_context(|| format!("reading {}", args.model.display()))?;
    let opts = PipelineOptions::for_dataset(&ds);
    let img = predict_frame(&ds, &model, args.frame, &opts)?;
    write_exr(&args.out, &img).with_context(|| format!("writing {}", args.out.display()))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
