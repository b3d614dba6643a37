//! `subsurf simulate`: write a synthetic scan dataset with ground truth beside it.
use std::path::PathBuf;

use anyhow::Context;
use subsurf::simulate::{SimConfig, SimObject, simulate};

/// Built-in objects.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Object {
    /// The top face of a 20 mm slab (section 4's planar case).
    Slab,
    /// A sphere of radius 10 mm.
    Sphere,
    /// A torus (non-convex, self-occluding).
    Torus,
    /// An asymmetric pebble about 30 × 20 × 14 mm: no rotation or mirror maps it onto itself.
    Blob,
}

/// Write a simulated scan (`docs/scan-format.md`) plus `ground-truth.ply` and `ground-truth.json`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output dataset directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Built-in object.
    #[arg(long, value_enum, default_value = "sphere")]
    pub object: Object,
    /// Approximate number of mesh vertices.
    #[arg(long, default_value_t = 2000)]
    pub vertices: usize,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 128)]
    pub size: u32,
    /// Turntable steps over 360 degrees.
    #[arg(long, default_value_t = 4)]
    pub angles: usize,
    /// Laser raster per axis (raster × raster laser positions per angle).
    #[arg(long, default_value_t = 8)]
    pub raster: usize,
    /// Number of cameras (slab: 1 by default, otherwise 3).
    #[arg(long)]
    pub cameras: Option<usize>,
    /// One camera straight above the platter (400 mm up) at this pixel footprint (mm at z = 0),
    /// --size pixels square, instead of the orbiting cameras; the laser raster is narrowed to
    /// 85 % of the view. With a view inside the slab (size × footprint < 20 mm) no boundary is
    /// seen: samples at boundary vertices read the background in their bilinear neighbourhood.
    #[arg(long, value_name = "MM_PER_PIXEL")]
    pub top_down: Option<f64>,
    /// Perfect sensor: no shot or read noise, no clipping.
    #[arg(long)]
    pub noise_free: bool,
    /// Standard deviation of the misregistration of x_i, mm.
    #[arg(long, default_value_t = 0.0)]
    pub misregistration: f64,
    /// Anisotropy of the material in [0, 1).
    #[arg(long)]
    pub anisotropy: Option<f64>,
    /// Heterogeneity (log-amplitude of the marble veins on the parameters).
    #[arg(long)]
    pub heterogeneity: Option<f64>,
    /// Log-amplitude of the modulation texture alpha(x_o) (Eq. 2) along the veins: ln alpha
    /// spans this much (0.8x green, 1.2x blue); 0 = alpha is 1. At most 10. Default 0.2.
    #[arg(long)]
    pub alpha_amplitude: Option<f64>,
    /// Wavelength of the marble veins, mm (default 25). The one pattern drives alpha, the
    /// parameters (--heterogeneity) and the anisotropy's strength; below about two mesh edge
    /// lengths alpha varies finer than the mesh (a texture the face lattice of `fit
    /// --alpha-lattice` can hold; ground-truth.ply holds it at level 8).
    #[arg(long)]
    pub vein_wavelength: Option<f64>,
    /// Seed of the noise and the vein pattern.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Write PFM frames instead of OpenEXR.
    #[arg(long)]
    pub pfm: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let root = |n: f64| n.max(9.0).sqrt().round() as usize;
    let object = match args.object {
        Object::Slab => SimObject::Slab {
            size: 20.0,
            n: root(args.vertices as f64),
        },
        Object::Sphere => SimObject::Sphere {
            radius: 10.0,
            rings: root(args.vertices as f64 / 2.0),
        },
        Object::Torus => SimObject::Torus {
            major: 10.0,
            minor: 4.0,
            segments: root(args.vertices as f64 / 2.0),
        },
        Object::Blob => SimObject::Blob {
            size: 30.0,
            rings: root(args.vertices as f64 / 2.0),
        },
    };
    let mut cfg = SimConfig::for_object(object, args.size, args.angles, args.raster);
    if let (Some(n), subsurf::simulate::CameraRig::Orbit { count, .. }) =
        (args.cameras, &mut cfg.cameras)
    {
        *count = n.max(1);
    }
    if let Some(mm) = args.top_down {
        cfg = cfg
            .top_down(mm)
            .map_err(|e| anyhow::anyhow!("--top-down: {e}"))?;
    }
    if args.noise_free {
        cfg = cfg.noise_free();
    }
    cfg.sensor.misregistration_mm = args.misregistration;
    if let Some(a) = args.anisotropy {
        cfg.field.anisotropy = a;
    }
    if let Some(h) = args.heterogeneity {
        cfg.field.heterogeneity = h;
    }
    if let Some(a) = args.alpha_amplitude {
        cfg.field.alpha_amplitude = a;
    }
    if let Some(w) = args.vein_wavelength {
        cfg.field.vein_wavelength = w;
    }
    cfg.seed = args.seed;
    cfg.field.seed = args.seed;
    cfg.pfm = args.pfm;
    let bar = super::progress::Bar::with_template("simulate {bar:40} {pos}/{len} frames {eta}");
    let t = std::time::Instant::now();
    let summary = simulate(&cfg, &args.out, &bar)
        .with_context(|| format!("simulating into {}", args.out.display()))?;
    bar.finish_and_clear();
    println!(
        "wrote {} frames ({} without a laser hit), {} vertices to {} in {:.1} s",
        summary.frames,
        summary.frames_without_hit,
        summary.vertices,
        args.out.display(),
        t.elapsed().as_secs_f64()
    );
    Ok(())
}
