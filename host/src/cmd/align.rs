//! `subsurf align`: place the dataset's mesh (any pose, any unit) in the object frame from the
//! scan's own laser spots, write the aligned copy beside it and record the transform in
//! `scan.json`.
use std::path::PathBuf;

use anyhow::Context;
use subsurf::align::{AlignOptions, DepthModel, align};

use super::progress::Bar;

/// Align the scan's mesh to the turntable frame from the laser spots (rotation, translation,
/// uniform scale), then `subsurf fit` uses the aligned mesh.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scan dataset: its folder or its `scan.json`. Its mesh may be in any pose and unit;
    /// once aligned, aligning again starts from the same original file.
    #[arg(long)]
    pub scan: PathBuf,
    /// Frames whose spots are used, e.g. `0-95` (default: all).
    #[arg(long)]
    pub frames: Option<String>,
    /// Frames left out (e.g. the frames a fit will hold out).
    #[arg(long)]
    pub exclude_frames: Option<String>,
    /// Refuse when the spots' inlier RMS distance from the aligned surface exceeds this, pixels.
    #[arg(long, default_value_t = 1.0)]
    pub max_rms_px: f64,
    /// Refuse when fewer spots than this are inliers, as a share.
    #[arg(long, default_value_t = 0.5)]
    pub min_inlier_share: f64,
    /// Refuse with fewer triangulated spots than this.
    #[arg(long, default_value_t = 12)]
    pub min_spots: usize,
    /// Refuse when a motion that changes the surface is fixed to no better than this (one
    /// standard deviation of vertex displacement), pixels.
    #[arg(long, default_value_t = 0.25)]
    pub max_pose_sigma_px: f64,
    /// A spot counts when its camera ray passes this close to the frame's laser ray, pixels.
    #[arg(long, default_value_t = 2.0)]
    pub max_gap_px: f64,
    /// How far inside the surface, along the laser ray, the camera sees a spot's centre (mm):
    /// `auto` estimates it with the pose (translucent objects glow from below their surface),
    /// a number holds it (0 for an opaque object).
    #[arg(long, default_value = "auto")]
    pub spot_depth: String,
    /// How a spot is moved back to the surface: `laser`, `incidence` or `refracted` (index 1.5).
    #[arg(long, default_value = "laser")]
    pub spot_depth_model: DepthModel,
    /// The scale from mesh units to mm when it is known (1000 for a mesh in metres, 25.4 in
    /// inches): held instead of estimated, so the search fits rotation and translation only.
    #[arg(long)]
    pub scale: Option<f64>,
    /// Override the dataset's noise floor (spots must peak 10× above it).
    #[arg(long)]
    pub noise_floor: Option<f64>,
    /// Estimate and print, but write nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Do not draw the picture of the spots on the aligned mesh (`<mesh>.aligned.png` beside
    /// the aligned mesh: each spot's residual in pixels around where it lies, outliers apart).
    #[arg(long)]
    pub no_picture: bool,
    /// Print one JSON object (the record, the evidence, every spot's residual).
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (ds, frames) = super::open_frames(
        &args.scan,
        args.frames.as_deref(),
        args.exclude_frames.as_deref(),
    )?;
    let mut opts = AlignOptions::for_dataset(&ds);
    if let Some(f) = args.noise_floor {
        opts.evidence.min_peak = 10.0 * f;
    }
    opts.evidence.max_gap_px = args.max_gap_px;
    opts.min_spots = args.min_spots;
    opts.max_rms_px = args.max_rms_px;
    opts.min_inlier_share = args.min_inlier_share;
    opts.max_pose_sigma_px = args.max_pose_sigma_px;
    let depth = args.spot_depth.as_str();
    let mm = depth.parse::<f64>().ok().filter(|d| d.is_finite());
    opts.spot_depth = match (depth, mm) {
        ("auto", _) => None,
        (_, Some(d)) => Some(d),
        _ => anyhow::bail!("--spot-depth must be `auto` or a number of mm, not {depth:?}"),
    };
    opts.depth_model = args.spot_depth_model;
    opts.scale = args.scale;
    let bar = if args.json {
        Bar::hidden()
    } else {
        Bar::with_template("align {msg} {bar:40} {pos}/{len}")
    };
    let out = align(&ds, &frames, &opts, &bar);
    bar.finish_and_clear();
    let out = out.with_context(|| format!("aligning the mesh of {}", args.scan.display()))?;
    let written = if args.dry_run {
        None
    } else {
        Some(
            ds.record_alignment(&out.mesh, &out.record)
                .context("recording the alignment")?,
        )
    };
    let picture = match &written {
        Some(mesh_path) if !args.no_picture => {
            let png = mesh_path.with_extension("png");
            subsurf::plot::alignment_picture(&out, &png)
                .with_context(|| format!("drawing {}", png.display()))?;
            Some(png)
        }
        _ => None,
    };
    let rec = &out.record;
    if args.json {
        let v = serde_json::json!({
            "alignment": rec,
            "aligned_mesh": written,
            "picture": picture,
            "evidence": {
                "frames": out.evidence.frames,
                "spots": out.evidence.points.len(),
                "no_laser_ray": out.evidence.no_laser_ray,
                "no_spot": out.evidence.no_spot,
                "rays_apart": out.evidence.rays_apart,
            },
            "hypotheses": out.hypotheses,
            "distinct_poses": out.distinct_poses,
            "spot_depth": {"model": out.depth_model, "mm": out.depth},
            "residuals": out.residuals,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let t = rec.translation;
    println!(
        "pose of {}: scale {:.6} (mesh units to mm), rotation {}, translation \
         ({:.3}, {:.3}, {:.3}) mm",
        rec.source_mesh,
        rec.scale,
        out.pose.rotation_in_words(),
        t[0],
        t[1],
        t[2]
    );
    let ev = &out.evidence;
    println!(
        "spots: {} of {} frames ({} without a spot, {} off the laser ray, {} without a laser ray); \
         {} inliers ({:.0} %)",
        rec.spots,
        ev.frames,
        ev.no_spot,
        ev.rays_apart,
        ev.no_laser_ray,
        rec.inliers,
        100.0 * rec.inlier_share
    );
    println!(
        "residuals: RMS {:.4} mm = {:.3} px from the aligned surface (bound {} px); pose \
         uncertainty {:.4} mm at the vertices; spots seen {:.3} mm below the surface",
        rec.rms_mm, rec.rms_px, args.max_rms_px, rec.pose_sigma_mm, rec.spot_depth_mm
    );
    if let Some(sym) = &rec.symmetry {
        println!("symmetry: {sym}");
    }
    match written {
        Some(p) => {
            println!(
                "wrote {}; scan.json now names it as the mesh (`subsurf fit` uses it)",
                p.display()
            );
            if let Some(png) = picture {
                println!("picture: {}", png.display());
            }
        }
        None => println!("dry run: nothing written"),
    }
    Ok(())
}
