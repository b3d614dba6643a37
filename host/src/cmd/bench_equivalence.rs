//! `subsurf bench equivalence`: the default fit against `--preset reference` (parsing and
//! printing only; the measurement is `subsurf::bench::equivalence`).
use anyhow::{Context, bail};
use std::path::PathBuf;

use subsurf::bench::equivalence::{run_case, table};

use super::progress::Bar;

/// The default fit against the reference preset (the exact path without the cuts) on
/// each scan, back to back from one sample store: CPU and wall time, and the equivalence
/// criteria of a cut (paired change of held-out log E on test frames and in the training
/// frames' cross-validation, the choices, RMS change of ln R_d and ln alpha).
#[derive(Debug, clap::Args)]
pub struct EquivalenceBench {
    /// A scan dataset (repeat for several); each with its own --test-frames, in order.
    #[arg(long, required = true)]
    scan: Vec<PathBuf>,
    /// The frames no fit sees, judged after it (e.g. `96-103`; `none` for none), one per
    /// --scan.
    #[arg(long, required = true)]
    test_frames: Vec<String>,
    /// Folds of the outer cross-validation of both procedures over the training frames (each
    /// fold fitted by both without it and judged on it); below 2: none.
    #[arg(long, default_value_t = subsurf::crossval::DEFAULT_FOLDS)]
    outer_folds: usize,
    /// Write the figures here (JSON).
    #[arg(long)]
    json: Option<PathBuf>,
}

pub fn bench_equivalence(a: EquivalenceBench) -> anyhow::Result<()> {
    if a.scan.len() != a.test_frames.len() {
        bail!(
            "{} --scan but {} --test-frames: give one --test-frames per --scan",
            a.scan.len(),
            a.test_frames.len()
        );
    }
    let bar = Bar::with_template("{msg:>16} {bar:30} {pos}/{len} {eta}");
    let mut cases = Vec::new();
    for (scan, spec) in a.scan.iter().zip(&a.test_frames) {
        let test = if spec == "none" {
            Vec::new()
        } else {
            subsurf::dataset::parse_frame_list(spec).map_err(anyhow::Error::msg)?
        };
        let name = scan.file_name().map_or_else(
            || scan.display().to_string(),
            |n| n.to_string_lossy().into(),
        );
        let case = run_case(&name, scan, &test, a.outer_folds, &bar)
            .with_context(|| format!("equivalence on {}", scan.display()))?;
        bar.finish();
        eprintln!("{name}: done");
        cases.push(case);
    }
    print!("{}", table(&cases));
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&cases)?)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
