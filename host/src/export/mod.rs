//! The captured material in another renderer: a model file exported for Blender's Cycles
//! (`subsurf export --format blender`, `docs/export.md`).
//!
//! 1. [`convert`]: per vertex, the fitted fall-off R_d(r) (Eq. 1/3/5/9; anisotropy averaged over
//!    its segments) becomes the Principled BSDF's subsurface colour and radius (Cycles'
//!    Christensen–Burley profile fitted in log space over the vertex's sampled range,
//!    [`cycles`]; the colour rule [`ColourRule`] chosen by how Cycles renders a scan's training
//!    frames; `TwoLobe`: a near and a slow BSDF mixed), with the conversion's log E per channel.
//! 2. [`mesh`]: the mesh with those parameters and alpha (Eq. 2/6) per vertex, or cut finer where
//!    the model has a face lattice of alpha.
//! 3. [`gltf`] + [`scene`] + `build_blend.py`: the files Blender reads — a binary glTF with the
//!    parameters as custom attributes, the lights and camera of the subsurf render in Blender's
//!    units, and the script that builds the node tree and the scene ([`blender`] runs it).
//! 4. [`compare`]: the same scene rendered by Cycles and by [`crate::render`], their mean
//!    relative pixel error and difference picture.
//! 5. [`volume`]: a volume model ([`crate::volume`]) needs no conversion: its medium becomes a
//!    Principled Volume inside its mesh, rendered by Cycles' volume scattering, and judged by a
//!    scan's frames beside subsurf's own trace ([`frames::Subject::Volume`]).
//!
//! Reads models only through [`ModelFile`] and [`crate::volume::VolumeModel`]. Touches files
//! only in [`Export::write`], [`volume`], [`compare`] and [`write_report`]; runs Blender only
//! in [`blender`].

pub mod blender;
pub mod choose;
pub mod convert;
pub mod cycles;
pub mod frames;
pub mod gather;
pub mod gltf;
pub mod mesh;
pub mod replay;
pub mod scene;
pub mod volume;

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::geometry::Camera;
use crate::modelfile::ModelFile;
use crate::progress::Progress;
use crate::render::{self, Light, RenderOptions};
use crate::report::{Figure, Report, Table, fmt};
pub use blender::{Blender, Kind, Run, find_blender, find_newest_blender, read_render};
pub use convert::{ColourRule, Source, VertexConversion};
pub use mesh::{ExportMesh, Refinement};

/// The build script's file name in an export folder.
pub const BUILD_SCRIPT: &str = "build_blend.py";
/// The mesh's file name.
pub const MESH_FILE: &str = "model.glb";
/// The scene description's file name.
pub const SCENE_FILE: &str = "scene.json";
/// The `.blend` the build script writes.
pub const BLEND_FILE: &str = "model.blend";
/// The export report's stem (`.json`, `.md`, `.html`).
pub const REPORT_STEM: &str = "export-report";

/// The format string of `scene.json`.
pub const SCENE_FORMAT: &str = "subsurf-blender-scene/1";

/// Why an export failed. Every variant names what is wrong.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// Reading or writing a file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The model or a value derived from it cannot be exported.
    #[error("cannot export: {0}")]
    Invalid(String),
    /// The camera has no Blender counterpart.
    #[error("camera: {0}")]
    Camera(String),
    /// Blender is missing, too old, or failed.
    #[error("Blender: {0}")]
    Blender(String),
    /// The renderer refused the model or the scene.
    #[error(transparent)]
    Render(#[from] render::RenderError),
    /// An image could not be read.
    #[error(transparent)]
    Image(crate::dataset::ImageError),
    /// A picture could not be drawn.
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    /// The report could not be written.
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
    /// A scan's frames could not be judged (`--scan`).
    #[error(transparent)]
    Evaluate(#[from] crate::evaluate::EvaluateError),
}

impl ExportError {
    fn io(path: &Path, source: std::io::Error) -> ExportError {
        ExportError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// What to do with alpha finer than the mesh (`face_alpha`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum LatticeMode {
    /// Cut the mesh at the lattice's level, alpha per lattice point ([`mesh::refined_mesh`]).
    Refine,
    /// Keep the model's mesh and the vertex alphas; the report says what the detail was worth.
    Drop,
}

/// What the export needs besides the model.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    /// Face lattice handling.
    pub lattice: LatticeMode,
    /// Relative refractive index of the exit Fresnel factor (the renderer's `eta`); `None` off.
    pub eta: Option<f64>,
    /// The scene's lights (the renderer's).
    pub lights: Vec<Light>,
    /// The scene's camera.
    pub camera: Camera,
    /// Cycles samples per pixel for renders of the scene.
    pub samples: u32,
    /// What the subsurface colour is.
    pub colour: ColourRule,
    /// Whether and under which light each vertex's colour is scaled by how much more (or less)
    /// Cycles' disk step gathers there than subsurf's renderer ([`gather`]).
    pub gather: GatherMode,
}

/// The gather correction of the export ([`gather`]): 1 on flat ground, below 1 on an object no
/// larger than the profile's reach, where Cycles gathers more.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum GatherMode {
    /// No correction: the colour rule's colour as it is.
    #[default]
    Off,
    /// Measured under a unit irradiance everywhere: a property of material and shape, right
    /// under any light to the extent the light is even on the profile's scale.
    Uniform,
    /// Measured under the exported scene's lights (uniform where they leave a vertex dark):
    /// Cycles then renders this scene as subsurf does, other lights less exactly.
    Lights,
}

/// Summary statistics of one per-vertex quantity per channel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct ChannelStats {
    /// Vertices counted.
    pub count: usize,
    /// Mean per channel.
    pub mean: [f64; 3],
    /// Median per channel.
    pub median: [f64; 3],
    /// 95th percentile per channel.
    pub p95: [f64; 3],
    /// Largest per channel.
    pub max: [f64; 3],
}

impl ChannelStats {
    fn of(values: impl Iterator<Item = [f64; 3]>) -> Option<ChannelStats> {
        let v: Vec<[f64; 3]> = values.filter(|x| x.iter().all(|y| y.is_finite())).collect();
        if v.is_empty() {
            return None;
        }
        let mut s = ChannelStats {
            count: v.len(),
            ..Default::default()
        };
        for c in 0..3 {
            let mut x: Vec<f64> = v.iter().map(|p| p[c]).collect();
            x.sort_by(f64::total_cmp);
            let q = |f: f64| x[((x.len() - 1) as f64 * f).round() as usize];
            s.mean[c] = x.iter().sum::<f64>() / x.len() as f64;
            s.median[c] = q(0.5);
            s.p95[c] = q(0.95);
            s.max[c] = x[x.len() - 1];
        }
        Some(s)
    }

    /// The mean over channels of the per-channel means.
    pub fn overall_mean(&self) -> f64 {
        self.mean.iter().sum::<f64>() / 3.0
    }
}

/// What the export had to leave out of the model, and what that costs.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Dropped {
    /// The model's direction segments m (Eq. 3) when m > 1: averaged, as Cycles' profile has no
    /// direction; then the log E of the averaged fall-off against the direction-dependent one.
    pub anisotropy: Option<(usize, ChannelStats)>,
    /// The face lattice's ln alpha detail when it was dropped (`LatticeMode::Drop`): RMS and
    /// largest |detail| over its points, the log error of leaving it out.
    pub lattice_detail: Option<(f64, f64)>,
}

/// The export's numbers: the report's JSON.
#[derive(Clone, Debug, Serialize)]
pub struct ExportSummary {
    /// `subsurf-export/1`.
    pub format: &'static str,
    /// The Cycles method the parameters are for.
    pub method: &'static str,
    /// What the subsurface colour is.
    pub colour_rule: ColourRule,
    /// Vertices of the model.
    pub vertices: usize,
    /// Vertices and triangles written.
    pub written: [usize; 2],
    /// Vertices by where their parameters came from: own fit, interpolated fit, filled from
    /// neighbours (no model), none.
    pub sources: [usize; 4],
    /// Subsurface colour (total diffuse reflectance) over vertices with a model.
    pub colour: Option<ChannelStats>,
    /// Subsurface radius, mm.
    pub radius_mm: Option<ChannelStats>,
    /// log E of the converted profile against the direction-averaged fitted one.
    pub conversion_log_e: Option<ChannelStats>,
    /// log E of the converted profile against the full model (with anisotropy when m > 1).
    pub total_log_e: Option<ChannelStats>,
    /// Mean ln(fitted / converted) over the outer quarter of each vertex's range.
    pub tail_excess: Option<ChannelStats>,
    /// Share of the fitted light beyond Cycles' truncation at 16 d (of the farthest lobe).
    pub beyond_truncation: Option<ChannelStats>,
    /// With two lobes: the slow lobe's radius, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub slow_radius_mm: Option<ChannelStats>,
    /// With two lobes: the slow lobe's share of the light (the Mix Shader's factor).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub slow_weight: Option<ChannelStats>,
    /// The face lattice's refinement.
    pub refinement: Refinement,
    /// What was left out.
    pub dropped: Dropped,
    /// The gather correction (`--gather`), when applied.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gather: Option<gather::GatherSummary>,
    /// Vertices with a subsurface colour above 1 in some channel (more light out than in: a
    /// calibration to check; Cycles takes it as it is).
    pub colour_above_one: usize,
}

/// A finished conversion, ready to be written.
#[derive(Clone, Debug)]
pub struct Export {
    /// Per vertex of the model.
    pub vertices: Vec<VertexConversion>,
    /// The mesh written.
    pub mesh: ExportMesh,
    /// Summary and what was dropped.
    pub summary: ExportSummary,
    /// Blender's scene description.
    pub scene: SceneFile,
}

/// `scene.json`.
#[derive(Clone, Debug, Serialize)]
pub struct SceneFile {
    /// [`SCENE_FORMAT`].
    pub format: &'static str,
    /// The mesh file, beside it.
    pub mesh: &'static str,
    /// The `.blend` the build script writes, beside it.
    pub blend: &'static str,
    /// The Principled BSDF's `subsurface_method`.
    pub method: &'static str,
    /// Subsurface lobes per point: 1, or 2 (a near and a slow Principled BSDF mixed by a Mix
    /// Shader, [`ColourRule::TwoLobe`]).
    pub lobes: u8,
    /// The exit Fresnel factor's relative index (`None`: no factor).
    pub exit_fresnel_ior: Option<f64>,
    /// The lights.
    pub lights: Vec<scene::BlenderLight>,
    /// The camera.
    pub camera: scene::BlenderCamera,
    /// Render settings.
    pub render: RenderSettings,
}

/// Render settings in `scene.json`.
#[derive(Clone, Debug, Serialize)]
pub struct RenderSettings {
    /// Samples per pixel.
    pub samples: u32,
    /// Pixel filter width of a comparison render (`--compare`): point samples at the pixel
    /// centre, as the renderer's rasteriser.
    pub compare_filter_width: f64,
    /// Bounces of a comparison render: 0, light scattered once through the material (the
    /// renderer has no light bounced between surfaces; Cycles' subsurface step is not a bounce).
    pub compare_max_bounces: u32,
    /// Diffuse bounces of a comparison render.
    pub compare_diffuse_bounces: u32,
}

/// Writes `value` as pretty JSON to `dir/name` (the folder exists); returns the path.
fn write_json(dir: &Path, name: &str, value: &impl Serialize) -> Result<PathBuf, ExportError> {
    let p = dir.join(name);
    let json = serde_json::to_vec_pretty(value)
        .map_err(|e| ExportError::Invalid(format!("{name}: {e}")))?;
    std::fs::write(&p, json).map_err(|e| ExportError::io(&p, e))?;
    Ok(p)
}

/// Converts `model` (checked by [`render::validate`]) for Blender.
pub fn export(
    model: &ModelFile,
    opts: &ExportOptions,
    progress: &dyn Progress,
) -> Result<Export, ExportError> {
    render::validate(model)?;
    if let Some(eta) = opts.eta
        && !(eta > 0.0 && eta.is_finite())
    {
        return Err(ExportError::Invalid(format!("eta {eta} is not positive")));
    }
    if opts.samples == 0 {
        return Err(ExportError::Invalid("samples must be at least 1".into()));
    }
    let mut vertices = convert::convert_with(model, opts.colour, progress);
    let reference = match opts.gather {
        GatherMode::Off => None,
        GatherMode::Uniform => Some(gather::Reference::Uniform),
        GatherMode::Lights => Some(gather::Reference::Lights(&opts.lights, opts.eta)),
    };
    let gathered = match reference {
        Some(r) => {
            progress.start("gathering", model.len() as u64);
            let totals = convert::totals(model);
            let q = gather::Quadrature::default();
            Some(gather::correct(
                model,
                &mut vertices,
                &totals,
                r,
                q,
                progress,
            )?)
        }
        None => None,
    };
    let (mesh, refinement) = match opts.lattice {
        LatticeMode::Refine => mesh::refined_mesh(model, &vertices),
        LatticeMode::Drop => (mesh::vertex_mesh(model, &vertices), Refinement::default()),
    };
    let own = |v: &&VertexConversion| matches!(v.source, Source::Fitted | Source::Interpolated);
    let stats = |f: &dyn Fn(&VertexConversion) -> Option<[f64; 3]>| {
        ChannelStats::of(vertices.iter().filter(own).filter_map(f))
    };
    let m = model.shape.segments;
    let lattice_detail = match (&model.face_alpha, opts.lattice) {
        (Some(fa), LatticeMode::Drop) if !fa.is_flat() => {
            let d = fa.detail();
            let (mut sq, mut mx) = (0.0, 0.0f64);
            for p in d {
                for &x in p {
                    sq += (x as f64) * (x as f64);
                    mx = mx.max((x as f64).abs());
                }
            }
            Some(((sq / (3 * d.len()).max(1) as f64).sqrt(), mx))
        }
        _ => None,
    };
    let summary = ExportSummary {
        format: "subsurf-export/1",
        method: "BURLEY",
        colour_rule: opts.colour,
        vertices: model.len(),
        written: [mesh.positions.len(), mesh.triangles.len()],
        sources: [
            Source::Fitted,
            Source::Interpolated,
            Source::Filled,
            Source::None,
        ]
        .map(|s| vertices.iter().filter(|v| v.source == s).count()),
        colour: stats(&|v| Some(v.colour)),
        radius_mm: stats(&|v| Some(v.radius_mm)),
        conversion_log_e: stats(&|v| v.log_e),
        total_log_e: stats(&|v| v.total_log_e),
        tail_excess: stats(&|v| v.tail_excess),
        beyond_truncation: stats(&|v| v.beyond_truncation),
        slow_radius_mm: stats(&|v| v.slow.map(|l| l.radius_mm)),
        slow_weight: stats(&|v| v.slow.map(|l| [l.weight; 3])),
        refinement,
        dropped: Dropped {
            anisotropy: (m > 1)
                .then(|| stats(&|v| v.anisotropy_log_e).map(|s| (m, s)))
                .flatten(),
            lattice_detail,
        },
        gather: gathered,
        colour_above_one: vertices
            .iter()
            .filter(|v| v.colour.iter().any(|&c| c > 1.0))
            .count(),
    };
    if summary.sources[0] + summary.sources[1] == 0 {
        return Err(ExportError::Invalid(
            "no vertex of the model has a fall-off to convert".into(),
        ));
    }
    let scene = SceneFile {
        format: SCENE_FORMAT,
        mesh: MESH_FILE,
        blend: BLEND_FILE,
        method: "BURLEY",
        lobes: if opts.colour == ColourRule::TwoLobe {
            2
        } else {
            1
        },
        exit_fresnel_ior: opts.eta,
        lights: scene::lights(&opts.lights)?,
        camera: scene::camera(&opts.camera, model.bounds())?,
        render: RenderSettings {
            samples: opts.samples,
            compare_filter_width: 0.01,
            compare_max_bounces: 0,
            compare_diffuse_bounces: 0,
        },
    };
    Ok(Export {
        vertices,
        mesh,
        summary,
        scene,
    })
}

/// The per-vertex part of the report's JSON.
#[derive(Serialize)]
struct ReportJson<'a> {
    #[serde(flatten)]
    summary: &'a ExportSummary,
    comparison: Option<&'a Comparison>,
    /// Cycles judged by a scan's frames (`--scan --render`).
    #[serde(skip_serializing_if = "Option::is_none")]
    frames: Option<&'a frames::FramesComparison>,
    per_vertex: &'a [VertexConversion],
}

impl Export {
    /// Writes `model.glb`, `scene.json`, `build_blend.py` and `export-report.json` into `dir`
    /// (created); returns the files written.
    pub fn write(&self, dir: &Path) -> Result<Vec<PathBuf>, ExportError> {
        std::fs::create_dir_all(dir).map_err(|e| ExportError::io(dir, e))?;
        let generator = format!("subsurf {}", env!("CARGO_PKG_VERSION"));
        let glb = gltf::glb_bytes(&self.mesh, scene::METRES_PER_MM, &generator)?;
        let files: [(&str, Vec<u8>); 3] = [
            (MESH_FILE, glb),
            (
                SCENE_FILE,
                serde_json::to_vec_pretty(&self.scene)
                    .map_err(|e| ExportError::Invalid(format!("scene.json: {e}")))?,
            ),
            (BUILD_SCRIPT, BUILD_BLEND_PY.as_bytes().to_vec()),
        ];
        let mut written = Vec::new();
        for (name, bytes) in files {
            let p = dir.join(name);
            std::fs::write(&p, bytes).map_err(|e| ExportError::io(&p, e))?;
            written.push(p);
        }
        written.push(self.write_json(dir, None, None)?);
        Ok(written)
    }

    fn write_json(
        &self,
        dir: &Path,
        comparison: Option<&Comparison>,
        frames: Option<&frames::FramesComparison>,
    ) -> Result<PathBuf, ExportError> {
        let p = dir.join(format!("{REPORT_STEM}.json"));
        let json = serde_json::to_vec_pretty(&ReportJson {
            summary: &self.summary,
            comparison,
            frames,
            per_vertex: &self.vertices,
        })
        .map_err(|e| ExportError::Invalid(format!("report JSON: {e}")))?;
        std::fs::write(&p, json).map_err(|e| ExportError::io(&p, e))?;
        Ok(p)
    }

    /// What `subsurf export` prints of the conversion: the vertices and triangles written, the
    /// conversion's log E against the fitted profile, and what was dropped.
    pub fn summary_lines(&self) -> Vec<String> {
        let s = &self.summary;
        let mut out = vec![format!(
            "{} vertices → Cycles subsurface colour and radius ({} written, {} triangles)",
            fmt::count(s.vertices),
            fmt::count(s.written[0]),
            fmt::count(s.written[1])
        )];
        if let Some(st) = &s.conversion_log_e {
            out.push(format!(
                "conversion log E (converted profile against the fitted one): median {}, 95th \
                 percentile {}, largest {} (mean of R, G, B)",
                fmt::log_e(st.median.iter().sum::<f64>() / 3.0),
                fmt::log_e(st.p95.iter().sum::<f64>() / 3.0),
                fmt::log_e(st.max.iter().copied().fold(0.0, f64::max)),
            ));
        }
        if let Some(g) = &s.gather {
            out.push(format!(
                "gather factor ({} light): colour × {} (median; {} to {}, 5th to 95th \
                 percentile) on {} vertices; Cycles gathers {} of the planar total under \
                 uniform light, subsurf {} (median, green)",
                g.reference,
                fmt::sig(g.factor[0], 3),
                fmt::sig(g.factor[1], 3),
                fmt::sig(g.factor[2], 3),
                fmt::count(g.vertices),
                fmt::sig(g.median_gather[0], 3),
                fmt::sig(g.median_gather[1], 3),
            ));
        }
        out.extend(
            self.dropped_lines()
                .into_iter()
                .map(|l| format!("dropped: {l}")),
        );
        out
    }

    /// What the export dropped, in words (empty when nothing): printed by the command and shown
    /// in the report.
    pub fn dropped_lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        let s = &self.summary;
        if let Some((m, st)) = &s.dropped.anisotropy {
            out.push(format!(
                "anisotropy (Eq. 3, m = {m} segments) averaged over directions: Cycles' profile \
                 has none; log E of the averaged fall-off against the direction-dependent one: \
                 mean {} (R, G, B {}), 95th percentile {}",
                fmt::log_e(st.overall_mean()),
                st.mean.map(fmt::log_e).join(", "),
                fmt::log_e(st.p95.iter().copied().fold(0.0, f64::max))
            ));
        }
        if let Some((rms, max)) = s.dropped.lattice_detail {
            out.push(format!(
                "the face lattice of alpha (alpha finer than the mesh) dropped: its ln alpha \
                 detail, now 0, was RMS {} and at most {} (log error of leaving it out)",
                fmt::log_e(rms),
                fmt::log_e(max)
            ));
        }
        if s.refinement.level > 1 {
            out.push(format!(
                "the face lattice of alpha carried by cutting every face at level {} ({} \
                 triangles); shared edge points averaged the two faces' ln alpha (differed by \
                 at most {})",
                s.refinement.level,
                fmt::count(s.written[1]),
                fmt::log_e(s.refinement.max_edge_mismatch)
            ));
        }
        out
    }
}

/// The export's build script (`build_blend.py`, written into every export folder).
pub const BUILD_BLEND_PY: &str = include_str!("build_blend.py");

/// Cycles' render of the exported scene against the renderer's render of the model.
#[derive(Clone, Debug, Serialize)]
pub struct Comparison {
    /// Mean relative pixel error of Cycles against the renderer over lit pixels (channels above
    /// 0.1 % of the renderer's brightest, [`render::relative_pixel_error`]).
    pub mean_relative_error: f64,
    /// Mean |Cycles − subsurf| / subsurf of the luminance ([`crate::plot::difference_picture`]).
    pub luminance_mean_abs: f64,
    /// Its 95th percentile.
    pub luminance_p95: f64,
    /// Mean signed luminance difference (Cycles brighter > 0).
    pub luminance_mean_signed: f64,
    /// Pixels covered by one render but not the other, over pixels covered by either.
    pub coverage_mismatch: f64,
    /// Cycles samples per pixel.
    pub samples: u32,
    /// Cycles' own noise: the mean relative pixel error between two renders of different seeds,
    /// divided by √2 (the part of `mean_relative_error` sampling alone explains).
    pub cycles_noise: Option<f64>,
    /// Wall time of the Cycles render, seconds.
    pub cycles_seconds: f64,
    /// Wall time of the renderer, seconds.
    pub subsurf_seconds: f64,
    /// Files: Cycles EXR and PNG, subsurf EXR and PNG, difference PNG.
    pub files: Vec<PathBuf>,
}

impl Comparison {
    /// The line `subsurf export --render` prints.
    pub fn line(&self) -> String {
        format!(
            "Cycles against subsurf's render: mean relative pixel error {} over lit pixels{}",
            fmt::percent(self.mean_relative_error, 1),
            self.cycles_noise
                .map(|n| format!(" (Cycles' own noise {})", fmt::percent(n, 1)))
                .unwrap_or_default()
        )
    }
}

/// The lit-pixel floor of the comparison: channels above this share of the renderer's
/// brightest pixel (the demo's).
pub const LIT_FLOOR: f64 = 1e-3;

/// Renders the exported scene (already written to `dir`) in Cycles with `--compare` and the
/// model with the renderer under the same lights and camera; writes `cycles.exr`/`.png`,
/// `subsurf.exr`/`.png` (one exposure, from subsurf's image) and `difference.png`. With
/// `noise`, a second Cycles render of another seed measures Cycles' sampling noise.
pub fn compare(
    model: &ModelFile,
    opts: &ExportOptions,
    render_options: &RenderOptions,
    blender: &Blender,
    dir: &Path,
    noise: bool,
) -> Result<Comparison, ExportError> {
    compare_with(model, opts, render_options, blender, dir, noise, &())
}

/// [`compare`], reporting its stages to `progress` (subsurf's render, then each Cycles render
/// sample by sample: together they take a minute, `subsurf export --render`'s longest wait).
#[allow(clippy::too_many_arguments)]
pub fn compare_with(
    model: &ModelFile,
    opts: &ExportOptions,
    render_options: &RenderOptions,
    blender: &Blender,
    dir: &Path,
    noise: bool,
    progress: &dyn Progress,
) -> Result<Comparison, ExportError> {
    progress.start("subsurf render", 0);
    let t0 = std::time::Instant::now();
    let out = render::render(
        model,
        &opts.lights,
        &opts.camera,
        &RenderOptions {
            eta: opts.eta,
            ..*render_options
        },
    )?;
    let subsurf_seconds = t0.elapsed().as_secs_f64();
    let cycles_exr = dir.join("cycles.exr");
    let t1 = std::time::Instant::now();
    progress.start("Cycles", u64::from(opts.samples));
    blender.run_with(
        dir,
        &Run {
            render: Some(cycles_exr.clone()),
            samples: Some(opts.samples),
            compare: true,
            threads: 0,
            seed: 0,
            frame: None,
            measure: None,
        },
        progress,
    )?;
    let cycles_seconds = t1.elapsed().as_secs_f64();
    let cycles = read_render(&cycles_exr)?;
    if (cycles.width, cycles.height) != (out.image.width, out.image.height) {
        return Err(ExportError::Blender(format!(
            "Cycles rendered {}x{}, the camera is {}x{}",
            cycles.width, cycles.height, out.image.width, out.image.height
        )));
    }
    let cycles_noise = if noise {
        let second = dir.join("cycles-seed1.exr");
        progress.start("Cycles, seed 1", u64::from(opts.samples));
        blender.run_with(
            dir,
            &Run {
                render: Some(second.clone()),
                samples: Some(opts.samples),
                compare: true,
                threads: 0,
                seed: 1,
                frame: None,
                measure: None,
            },
            progress,
        )?;
        let b = read_render(&second)?;
        let _ = std::fs::remove_file(&second);
        render::relative_pixel_error(&b, &cycles, LIT_FLOOR).map(|e| e / std::f64::consts::SQRT_2)
    } else {
        None
    };
    let mean_relative_error = render::relative_pixel_error(&cycles, &out.image, LIT_FLOOR)
        .ok_or_else(|| ExportError::Invalid("the renders have no lit pixel in common".into()))?;
    let subsurf_exr = dir.join("subsurf.exr");
    render::save_exr(&out.image, &subsurf_exr)?;
    let exposure = render::auto_exposure(&out.image);
    let (cycles_png, subsurf_png) = (dir.join("cycles.png"), dir.join("subsurf.png"));
    render::save_png(&cycles, Some(exposure), &cycles_png)?;
    render::save_png(&out.image, Some(exposure), &subsurf_png)?;
    let diff_png = dir.join("difference.png");
    let d = crate::plot::difference_picture_of(
        &diff_png,
        &cycles,
        &out.image,
        LIT_FLOOR,
        crate::plot::Compared {
            image: "Cycles",
            reference: "subsurf",
        },
    )?;
    let (mut either, mut one) = (0usize, 0usize);
    for (a, b) in cycles.covered.iter().zip(&out.image.covered) {
        if *a || *b {
            either += 1;
            if a != b {
                one += 1;
            }
        }
    }
    Ok(Comparison {
        mean_relative_error,
        luminance_mean_abs: d.mean_abs,
        luminance_p95: d.p95_abs,
        luminance_mean_signed: d.mean_signed,
        coverage_mismatch: one as f64 / either.max(1) as f64,
        samples: opts.samples,
        cycles_noise,
        cycles_seconds,
        subsurf_seconds,
        files: vec![cycles_exr, cycles_png, subsurf_exr, subsurf_png, diff_png],
    })
}

/// The per-vertex map of the export (`export-map.png`): subsurface colour × alpha, radius, the
/// conversion's log E, and with anisotropy its cost.
pub fn draw_map(model: &ModelFile, export: &Export, path: &Path) -> Result<(), ExportError> {
    use crate::plot::{MeshView, Panel, PanelData, surface_panels};
    let v = &export.vertices;
    let mean = |x: [f64; 3]| x.iter().sum::<f64>() / 3.0;
    let colour: Vec<[f64; 3]> = v
        .iter()
        .zip(&model.vertices)
        .map(|(c, m)| [0, 1, 2].map(|k| (c.colour[k] * m.alpha[k] as f64).clamp(0.0, 1.0)))
        .collect();
    let radius: Vec<f64> = v
        .iter()
        .map(|c| {
            if c.source == Source::None {
                f64::NAN
            } else {
                mean(c.radius_mm)
            }
        })
        .collect();
    let range_of = |x: &[f64]| {
        let f: Vec<f64> = x.iter().copied().filter(|y| y.is_finite()).collect();
        let lo = f.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = f.iter().copied().fold(0.0, f64::max);
        if lo.is_finite() && hi > lo {
            (lo, hi)
        } else {
            (0.0, hi.max(1e-9))
        }
    };
    let log_e: Vec<f64> = v.iter().map(|c| c.log_e.map_or(f64::NAN, mean)).collect();
    let mut panels = vec![
        Panel {
            title: "subsurface colour × alpha".into(),
            data: PanelData::Rgb(colour),
        },
        Panel {
            title: "subsurface radius".into(),
            data: PanelData::Scalar {
                range: range_of(&radius),
                values: radius,
                label: "mm (mean of R, G, B)".into(),
                missing: "no model".into(),
            },
        },
        Panel {
            title: "conversion log E".into(),
            data: PanelData::Scalar {
                range: (0.0, range_of(&log_e).1),
                values: log_e,
                label: "Eq. 8, mean of R, G, B".into(),
                missing: "no conversion".into(),
            },
        },
    ];
    if export.summary.dropped.anisotropy.is_some() {
        let a: Vec<f64> = v
            .iter()
            .map(|c| c.anisotropy_log_e.map_or(f64::NAN, mean))
            .collect();
        panels.push(Panel {
            title: "anisotropy averaged".into(),
            data: PanelData::Scalar {
                range: (0.0, range_of(&a).1),
                values: a,
                label: "log E vs Eq. 3".into(),
                missing: "no anisotropy".into(),
            },
        });
    }
    surface_panels(
        path,
        "",
        MeshView {
            positions: &model.positions,
            normals: &model.normals,
            faces: &model.triangles,
        },
        &panels,
        render::DEFAULT_VIEW,
        (300, 340),
    )?;
    Ok(())
}

/// Writes the export report (`export-report.json`, `.md`, `.html`) into `dir`: the mapping's
/// numbers, what was dropped, the map, and the comparison when there is one.
pub fn write_report(
    model: &ModelFile,
    export: &Export,
    comparison: Option<&Comparison>,
    frames: Option<&frames::FramesComparison>,
    blender: Option<&Blender>,
    dir: &Path,
) -> Result<Vec<PathBuf>, ExportError> {
    let mut written = vec![export.write_json(dir, comparison, frames)?];
    let map = dir.join("export-map.png");
    draw_map(model, export, &map)?;
    written.push(map.clone());
    let s = &export.summary;
    let mut rep = Report::new("subsurf export for Blender (Cycles)");
    rep.paragraph(format!(
        "{} vertices converted into the Principled BSDF's subsurface colour (the total diffuse \
         reflectance of each vertex's fall-off, Eq. 1/3/5/9) and subsurface radius (Cycles' \
         Christensen–Burley profile, method `BURLEY`, fitted in log space over the vertex's \
         sampled distances; Blender 3.4 uses d = radius / 4π whatever the colour). alpha (Eq. \
         2/6) multiplies the colour in the node tree. Written: `{MESH_FILE}` ({} vertices, {} \
         triangles, metres), `{SCENE_FILE}`, `{BUILD_SCRIPT}`{}. See docs/export.md.",
        fmt::count(s.vertices),
        fmt::count(s.written[0]),
        fmt::count(s.written[1]),
        match blender {
            Some(b) => format!(", and `{BLEND_FILE}` by {}", b.version_line),
            None => format!(
                " (no Blender found: run `blender -b --python {BUILD_SCRIPT}` to make \
                 `{BLEND_FILE}`)"
            ),
        }
    ));
    let mut t = Table::new(["per vertex", "red", "green", "blue", "how"]);
    /// A summary row: name, median per channel, format, how it is made.
    type Row<'a> = (&'a str, Option<[f64; 3]>, fn(f64) -> String, &'a str);
    let rows: [Row; 6] = [
        (
            "subsurface colour (median)",
            s.colour.map(|x| x.median),
            |x| fmt::sig(x, 3),
            "∫ R̄_d(r) 2πr dr, the averaged fall-off's total reflectance",
        ),
        (
            "subsurface radius, mm (median)",
            s.radius_mm.map(|x| x.median),
            |x| fmt::sig(x, 3),
            "4π d, d fitted to ln R̄_d",
        ),
        (
            "conversion log E (median)",
            s.conversion_log_e.map(|x| x.median),
            fmt::log_e,
            "RMS ln(converted / fitted) over the sampled range",
        ),
        (
            "conversion log E (95th percentile)",
            s.conversion_log_e.map(|x| x.p95),
            fmt::log_e,
            "",
        ),
        (
            "tail excess (median)",
            s.tail_excess.map(|x| x.median),
            |x| fmt::sig(x, 2),
            "mean ln(fitted / converted), outer quarter: > 0 is light a slow term carries further",
        ),
        (
            "light beyond 16 d (median)",
            s.beyond_truncation.map(|x| x.median),
            |x| fmt::percent(x, 2),
            "Cycles truncates its profile there",
        ),
    ];
    for (name, v, f, how) in rows {
        if let Some(v) = v {
            let mut cells = vec![name.to_string()];
            cells.extend(v.map(f));
            cells.push(how.to_string());
            t.row(cells);
        }
    }
    rep.table(
        t,
        Some(format!(
            "Vertices with a fall-off: {} fitted, {} interpolated; {} without a model took \
             their neighbours' parameters, {} stay black. Colours above 1: {}.",
            fmt::count(s.sources[0]),
            fmt::count(s.sources[1]),
            fmt::count(s.sources[2]),
            fmt::count(s.sources[3]),
            fmt::count(s.colour_above_one)
        )),
    );
    rep.heading("What Cycles cannot carry");
    let dropped = export.dropped_lines();
    if dropped.is_empty() {
        rep.paragraph("Nothing of the model was dropped: isotropic, alpha per vertex.");
    }
    for l in dropped {
        rep.paragraph(l);
    }
    rep.figures(vec![Figure {
        path: map,
        caption: "Per vertex: subsurface colour × alpha, radius, the conversion's log E (and \
                  the anisotropy's, when averaged)."
            .into(),
    }]);
    if let Some(c) = comparison {
        rep.heading("Rendered in Blender");
        let fig = |i: usize, caption: &str| Figure {
            path: c.files[i].clone(),
            caption: caption.into(),
        };
        rep.figures(vec![
            fig(3, "subsurf's renderer"),
            fig(1, "Cycles (Blender), same lights, camera and exposure"),
            fig(
                4,
                "(Cycles − subsurf) / subsurf of the luminance: red = Cycles brighter",
            ),
        ]);
        let mut t = Table::new(["", "value"]);
        t.row([
            "mean relative pixel error, lit pixels".to_string(),
            fmt::percent(c.mean_relative_error, 1),
        ])
        .row([
            "of which Cycles' sampling noise".to_string(),
            fmt::opt(c.cycles_noise, |x| fmt::percent(x, 1)),
        ])
        .row([
            "luminance: mean |difference|, 95th percentile, mean signed".to_string(),
            format!(
                "{}, {}, {}",
                fmt::percent(c.luminance_mean_abs, 1),
                fmt::percent(c.luminance_p95, 1),
                fmt::percent(c.luminance_mean_signed, 1)
            ),
        ])
        .row([
            "pixels covered by one render only".to_string(),
            fmt::percent(c.coverage_mismatch, 2),
        ])
        .row([
            "Cycles samples, time".to_string(),
            format!("{}, {}", c.samples, fmt::seconds(c.cycles_seconds)),
        ]);
        rep.table(
            t,
            Some(
                "Cycles rendered with `build_blend.py --compare`: pixel centres point-sampled \
                 and no light bounced between surfaces, as subsurf's renderer draws."
                    .into(),
            ),
        );
    }
    if let Some(f) = frames {
        frames_section(&mut rep, f);
    }
    let [md, html] = rep.write(dir, REPORT_STEM)?;
    written.push(md);
    written.push(html);
    Ok(written)
}

/// `log E` of three channels as `r / g / b`.
fn rgb(x: [Option<f64>; 3]) -> String {
    x.map(|v| fmt::opt(v, fmt::log_e)).join(" / ")
}

/// The report's section on a scan's frames rendered in Cycles.
fn frames_section(rep: &mut Report, f: &frames::FramesComparison) {
    rep.heading("Cycles judged by the scan's frames");
    rep.paragraph(format!(
        "Each frame rendered in Cycles with the exported material ({} samples, seed 0): the \
         frame's camera, image size and exposure, the object turned by its turntable angle, the \
         laser as a spot light {} mm before x_i along the frame's laser ray lighting a disk one \
         pixel across, its power the scan's unit times the exposure. The renders are judged \
         like a model (`subsurf evaluate --images`): the same samples, exclusion radius, noise \
         floor ({}) \
         and Eq. 8 as subsurf's own model, whose log E is beside them. The noise column is a \
         second seed's render against the first (two renders' noise: √2 times one's).",
        f.samples,
        frames::STANDOFF_MM,
        fmt::sig(f.noise_floor, 3)
    ));
    let mut t = Table::new([
        "frame",
        "Cycles log E (r / g / b)",
        "subsurf log E",
        "Cycles noise",
        "rings: Cycles / subsurf / noise (green)",
        "black samples",
        "seconds",
    ]);
    let g = |v: [Option<f64>; 3]| fmt::opt(v[1], |x| fmt::sig(x, 3));
    for r in &f.per_frame {
        t.row([
            format!("{}{}", r.frame, if r.fitted { " (fitted)" } else { "" }),
            rgb(r.cycles_log_e),
            rgb(r.subsurf_log_e),
            r.noise_log_e.map(rgb).unwrap_or_else(|| "–".into()),
            format!(
                "{} / {} / {}",
                g(r.cycles_ring_log_e),
                g(r.subsurf_ring_log_e),
                r.noise_ring_log_e.map(g).unwrap_or_else(|| "–".into())
            ),
            format!("{} of {}", r.unlit, r.samples),
            fmt::sig(r.seconds, 3),
        ]);
    }
    t.row([
        "mean".to_string(),
        rgb(f.cycles_mean_log_e),
        rgb(f.subsurf_mean_log_e),
        f.noise_mean_log_e.map(rgb).unwrap_or_else(|| "–".into()),
        format!(
            "{} / {} / {}",
            g(f.cycles_ring_mean_log_e),
            g(f.subsurf_ring_mean_log_e),
            f.noise_ring_mean_log_e.map(g).unwrap_or_else(|| "–".into())
        ),
        String::new(),
        fmt::sig(f.cycles_seconds, 3),
    ]);
    rep.table(
        t,
        Some(format!(
            "Cycles' mean log E over subsurf's (green): {}; on the rings {}. Frames marked \
             fitted were used by the model's fit (in-sample for both). Skipped: {}.",
            fmt::opt(f.ratio_green, |x| fmt::sig(x, 3)),
            fmt::opt(f.ring_ratio_green, |x| fmt::sig(x, 3)),
            if f.skipped.is_empty() {
                "none".to_string()
            } else {
                f.skipped
                    .iter()
                    .map(|s| format!("{} ({})", s.frame, s.reason))
                    .collect::<Vec<_>>()
                    .join("; ")
            }
        )),
    );
}

/// The frames' comparison as the command prints it.
pub fn frames_text(f: &frames::FramesComparison) -> String {
    use std::fmt::Write as _;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "frame        Cycles log E (r / g / b)     subsurf log E (r / g / b)    Cycles noise"
    );
    for r in &f.per_frame {
        let _ = writeln!(
            o,
            "{:<12} {:<28} {:<28} {}",
            format!("{}{}", r.frame, if r.fitted { " (fitted)" } else { "" }),
            rgb(r.cycles_log_e),
            rgb(r.subsurf_log_e),
            r.noise_log_e.map(rgb).unwrap_or_else(|| "–".into())
        );
    }
    let _ = writeln!(
        o,
        "{:<12} {:<28} {:<28} {}",
        "mean",
        rgb(f.cycles_mean_log_e),
        rgb(f.subsurf_mean_log_e),
        f.noise_mean_log_e.map(rgb).unwrap_or_else(|| "–".into())
    );
    let _ = writeln!(
        o,
        "rings (Eq. 8 over ring means of linear radiance around x_i):"
    );
    for r in &f.per_frame {
        let _ = writeln!(
            o,
            "{:<12} {:<28} {:<28} {}",
            r.frame,
            rgb(r.cycles_ring_log_e),
            rgb(r.subsurf_ring_log_e),
            r.noise_ring_log_e.map(rgb).unwrap_or_else(|| "–".into())
        );
    }
    let _ = writeln!(
        o,
        "{:<12} {:<28} {:<28} {}",
        "ring mean",
        rgb(f.cycles_ring_mean_log_e),
        rgb(f.subsurf_ring_mean_log_e),
        f.noise_ring_mean_log_e
            .map(rgb)
            .unwrap_or_else(|| "–".into())
    );
    let _ = writeln!(
        o,
        "rings: Cycles / subsurf (green) {}",
        fmt::opt(f.ring_ratio_green, |x| fmt::sig(x, 3))
    );
    if let Some(a) = f.agreement_ring_mean_log_e {
        let _ = writeln!(
            o,
            "rings, Cycles against subsurf's trace of the same medium: {} (per frame {})",
            rgb(a),
            f.per_frame
                .iter()
                .map(|r| r
                    .agreement_ring_log_e
                    .map(rgb)
                    .unwrap_or_else(|| "–".into()))
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    if let (Some(a), Some(b), Some(c)) = (
        f.replay_mean_log_e,
        f.replay_ring_mean_log_e,
        f.replay_agreement_ring_mean_log_e,
    ) {
        let _ = writeln!(
            o,
            "Cycles' expected render (closed-form replay): log E {}, rings {} (replay / \
             subsurf, green {}); Cycles' render against it, rings {} (per frame {})",
            rgb(a),
            rgb(b),
            fmt::opt(f.replay_ring_ratio_green, |x| fmt::sig(x, 3)),
            rgb(c),
            f.per_frame
                .iter()
                .map(|r| r
                    .replay
                    .map(|p| rgb(p.cycles_ring_log_e))
                    .unwrap_or_else(|| "–".into()))
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    let _ = writeln!(
        o,
        "Cycles / subsurf (green): {}; {} frames skipped; Cycles {}",
        fmt::opt(f.ratio_green, |x| fmt::sig(x, 3)),
        f.skipped.len(),
        fmt::seconds(f.cycles_seconds)
    );
    o
}
