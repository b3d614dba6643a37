//! A volume model for Blender: its medium as a Principled Volume inside its mesh, rendered by
//! Cycles' own volume scattering (`subsurf export --model M.json`, docs/volume.md, "Export").
//!
//! Why a volume needs no conversion: the empirical model's fall-off must be squeezed into
//! Cycles' Christensen-Burley profile (docs/export.md), but a scattering medium is what Cycles'
//! volume path tracer renders by the same physics as subsurf's tracer: extinction, albedo and
//! a Henyey-Greenstein phase function per point. Only the units change (mm to m) and the
//! parametrisation of Cycles' Principled Volume ([`principled_volume`]). So Cycles' render of a
//! scan's frames, judged by the frames ([`super::frames`], the ring yardstick), checks the model
//! and its export with an outside renderer, next to subsurf's own trace of the same frames.
//!
//! A grid whose cells differ is written cell by cell into float images that the material reads
//! by nearest lookup at the shading point's object coordinates, so Cycles sees the cells of
//! [`MediumGrid::cell_of`] inside the mesh's own boundary (a voxel file would give the medium a
//! staircase boundary at its voxel size). The same cells go to an OpenVDB file for other
//! renderers when the Blender that builds the scene carries the `openvdb` module.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::frames::{self, FramesComparison, Subject};
use super::scene::{self, BlenderCamera, BlenderLight, METRES_PER_MM};
use super::{BLEND_FILE, BUILD_BLEND_PY, BUILD_SCRIPT, Blender, ExportError, REPORT_STEM, Run};
use crate::dataset::Dataset;
use crate::geometry::Camera;
use crate::progress::Progress;
use crate::render::Light;
use crate::volume::VolumeModel;
use crate::volume::model::{BoundaryModel, MediumGrid};

/// The format string of a volume export's `scene.json`.
pub const VOLUME_SCENE_FORMAT: &str = "subsurf-blender-volume/1";

/// Cycles' bounces for a volume render: every scattering event is a volume bounce, and a
/// medium of albedo 0.99 scatters a hundred times on average before the light is absorbed;
/// 1024 (Cycles' largest) leaves a share of about 0.99¹⁰²⁴ ≈ 3·10⁻⁵ of the walks cut short.
pub const VOLUME_BOUNCES: u32 = 1024;

/// One medium in Cycles' Principled Volume's inputs (absorption colour and density, lengths in
/// metres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PrincipledVolume {
    /// `Density`, per metre: the largest channel's σ_t.
    pub density: f64,
    /// `Color`, linear.
    pub color: [f64; 3],
    /// `Absorption Color`, linear.
    pub absorption_color: [f64; 3],
}

/// Cycles' Principled Volume inputs of a medium of extinction `sigma_t_mm` (per mm) and
/// single-scattering `albedo`, per channel.
///
/// Cycles (kernel `svm_node_principled_volume`, the same in 3.4 and 5.0) makes of density D,
/// colour C and absorption colour A the scattering σ_s = C·D and the absorption
/// σ_a = max(1 − C, 0)·max(1 − √A, 0)·D. With D the largest σ_t, C = α σ_t / D, and
/// √A = 1 − (1 − α)σ_t / (D − α σ_t), each channel's σ_s and σ_a are subsurf's exactly; the
/// channel with the largest σ_t has A = 0 (black: Cycles' default).
pub fn principled_volume(
    sigma_t_mm: [f64; 3],
    albedo: [f64; 3],
) -> Result<PrincipledVolume, ExportError> {
    let d = sigma_t_mm.iter().copied().fold(0.0, f64::max);
    principled_volume_at(sigma_t_mm, albedo, d)
}

/// [`principled_volume`] with a given density `d_mm` (per mm, at least the largest σ_t): a
/// grid's cells share one density, the grid's largest σ_t, so that Cycles' majorant is that
/// density and each cell's colours carry its own σ_s and σ_a.
fn principled_volume_at(
    sigma_t_mm: [f64; 3],
    albedo: [f64; 3],
    d_mm: f64,
) -> Result<PrincipledVolume, ExportError> {
    if sigma_t_mm.iter().any(|s| !(s.is_finite() && *s > 0.0))
        || albedo
            .iter()
            .any(|a| !(a.is_finite() && (0.0..=1.0).contains(a)))
    {
        return Err(ExportError::Invalid(format!(
            "a medium of σ_t {sigma_t_mm:?} /mm and albedo {albedo:?}: σ_t must be positive and \
             the albedo within [0, 1]"
        )));
    }
    if !(d_mm.is_finite() && sigma_t_mm.iter().all(|s| *s <= d_mm)) {
        return Err(ExportError::Invalid(format!(
            "a Principled Volume density of {d_mm} /mm is below the medium's σ_t {sigma_t_mm:?} /mm"
        )));
    }
    let d = d_mm;
    let color = [0, 1, 2].map(|c| albedo[c] * sigma_t_mm[c] / d);
    let absorption_color = [0, 1, 2].map(|c| {
        let free = d - albedo[c] * sigma_t_mm[c];
        let share = if free > 0.0 {
            ((1.0 - albedo[c]) * sigma_t_mm[c] / free).clamp(0.0, 1.0)
        } else {
            // α = 1 and σ_t = D: no absorption whatever A is.
            1.0
        };
        (1.0 - share).powi(2)
    });
    Ok(PrincipledVolume {
        density: d / METRES_PER_MM,
        color,
        absorption_color,
    })
}

/// What light does at the mesh, in Cycles' terms.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum BlenderBoundary {
    /// No surface shader: Cycles' rays cross the surface unbent into the volume.
    IndexMatched,
    /// A Glass BSDF (GGX) of index `ior` and Cycles roughness `roughness` (= √α of the model's
    /// GGX α: Cycles squares its roughness).
    Glass {
        /// Index of refraction.
        ior: f64,
        /// Cycles' roughness.
        roughness: f64,
    },
}

/// A grid whose cells differ, as the material's lookup reads it.
#[derive(Clone, Debug, Serialize)]
pub struct BlenderGrid {
    /// Minimum corner, object frame, metres.
    pub origin_m: [f64; 3],
    /// Cell size, metres.
    pub cell_m: [f64; 3],
    /// Cells along x, y, z.
    pub dims: [usize; 3],
    /// Per cell (x fastest, then y, then z), its Principled Volume inputs.
    pub cells: Vec<PrincipledVolume>,
}

/// Render settings of a volume scene.
#[derive(Clone, Debug, Serialize)]
pub struct VolumeRender {
    /// Samples per pixel.
    pub samples: u32,
    /// [`VOLUME_BOUNCES`].
    pub bounces: u32,
}

/// `scene.json` of a volume export.
#[derive(Clone, Debug, Serialize)]
pub struct VolumeScene {
    /// [`VOLUME_SCENE_FORMAT`].
    pub format: &'static str,
    /// `"volume"`: the build script's switch.
    pub kind: &'static str,
    /// The `.blend` the build script writes, beside it.
    pub blend: &'static str,
    /// The mesh's vertices, object frame, metres.
    pub vertices_m: Vec<[f64; 3]>,
    /// The mesh's triangles.
    pub triangles: Vec<[u32; 3]>,
    /// An open mesh (a slab's top face) closed by extruding it this far behind its face (mm):
    /// Cycles fills only what a closed surface bounds ([`closed`]). `None`: closed already.
    pub extruded_mm: Option<f64>,
    /// The medium where it is uniform (the grid's first cell otherwise).
    pub medium: PrincipledVolume,
    /// The cells, where they differ.
    pub grid: Option<BlenderGrid>,
    /// Henyey-Greenstein g (Principled Volume's `Anisotropy`).
    pub anisotropy: f64,
    /// The boundary.
    pub boundary: BlenderBoundary,
    /// The model's medium in its own units, for the reader.
    pub sigma_t_per_mm: [f64; 3],
    /// The model's single-scattering albedo.
    pub albedo: [f64; 3],
    /// Lights of the scene (not of a scan frame's, which has its laser).
    pub lights: Vec<BlenderLight>,
    /// Camera of the scene.
    pub camera: BlenderCamera,
    /// Render settings.
    pub render: VolumeRender,
}

/// How a volume model is exported.
#[derive(Clone, Debug)]
pub struct VolumeExportOptions {
    /// Lights of the scene.
    pub lights: Vec<Light>,
    /// Camera of the scene.
    pub camera: Camera,
    /// Cycles samples per pixel.
    pub samples: u32,
    /// Render in Cycles: a volume is rendered by a scan's frames, so this asks for a scan.
    pub render: bool,
}

/// `model`'s scene for Blender.
pub fn volume_scene(
    model: &VolumeModel,
    opts: &VolumeExportOptions,
) -> Result<VolumeScene, ExportError> {
    model
        .validate()
        .map_err(|e| ExportError::Invalid(format!("the volume model: {e}")))?;
    if opts.samples == 0 {
        return Err(ExportError::Invalid("samples must be at least 1".into()));
    }
    let grid = &model.grid;
    let medium = principled_volume(grid.sigma_t[0], grid.albedo[0])?;
    let cells = (!grid.is_uniform())
        .then(|| blender_grid(grid))
        .transpose()?;
    let boundary = match model.boundary {
        BoundaryModel::IndexMatched => BlenderBoundary::IndexMatched,
        BoundaryModel::Dielectric { ior, roughness } => BlenderBoundary::Glass {
            ior,
            roughness: roughness.sqrt(),
        },
    };
    let min_sigma = grid
        .sigma_t
        .iter()
        .flat_map(|s| s.iter().copied())
        .fold(f64::INFINITY, f64::min);
    let (vertices, triangles, extruded_mm) = closed(&model.mesh, min_sigma);
    Ok(VolumeScene {
        format: VOLUME_SCENE_FORMAT,
        kind: "volume",
        blend: BLEND_FILE,
        vertices_m: vertices
            .iter()
            .map(|v| v.map(|x| x * METRES_PER_MM))
            .collect(),
        triangles,
        extruded_mm,
        medium,
        grid: cells,
        anisotropy: model.g,
        boundary,
        sigma_t_per_mm: grid.sigma_t[0],
        albedo: grid.albedo[0],
        lights: scene::lights(&opts.lights)?,
        camera: scene::camera(&opts.camera, model.mesh.bounds())?,
        render: VolumeRender {
            samples: opts.samples,
            bounces: VOLUME_BOUNCES,
        },
    })
}

/// Mean free paths of the least dense channel behind an open face: light that deep is
/// e^(−30) of what entered, before any absorption.
pub const EXTRUDE_FREE_PATHS: f64 = 30.0;

/// `mesh` as a closed surface: itself if every edge is shared by two triangles; else (an open
/// mesh, as a slab's top face) the face extruded behind itself along its mean normal, with side
/// walls along its open edges and a bottom, by the larger of its bounding box's diagonal and
/// [`EXTRUDE_FREE_PATHS`] free paths of `min_sigma_t`; with that depth.
///
/// Why: subsurf's tracer takes an open face to bound a medium behind it as far as the face
/// reaches (docs/volume.md), but a renderer's volume is what a closed surface encloses: an open
/// mesh would render black. Behind the face the two agree up to where the extruded walls stand
/// and the tracer's medium goes on (the tracer's prism runs towards the laser, the walls along
/// the face's normal), which for a slab lit near its middle is light the frames barely hold.
pub fn closed(
    mesh: &crate::volume::VolumeMesh,
    min_sigma_t: f64,
) -> (Vec<[f64; 3]>, Vec<[u32; 3]>, Option<f64>) {
    use std::collections::HashMap;
    let (v, t) = (&mesh.vertices, &mesh.triangles);
    let mut uses: HashMap<(u32, u32), usize> = HashMap::new();
    for tri in t {
        for e in 0..3 {
            let (a, b) = (tri[e], tri[(e + 1) % 3]);
            *uses.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    if uses.values().all(|&n| n == 2) {
        return (v.clone(), t.clone(), None);
    }
    // The mean normal, area-weighted (the cross products' sum), and the depth.
    let mut n = [0.0; 3];
    for tri in t {
        let [a, b, c] = tri.map(|i| v[i as usize]);
        let (e1, e2) = (
            [0, 1, 2].map(|k| b[k] - a[k]),
            [0, 1, 2].map(|k| c[k] - a[k]),
        );
        let x = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        (0..3).for_each(|k| n[k] += x[k]);
    }
    let len = n.iter().map(|x| x * x).sum::<f64>().sqrt();
    let n = if len > 0.0 {
        n.map(|x| x / len)
    } else {
        [0.0, 0.0, 1.0]
    };
    let (lo, hi) = mesh.bounds();
    let diagonal = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
    let depth = diagonal.max(EXTRUDE_FREE_PATHS / min_sigma_t);
    let m = v.len() as u32;
    let mut vertices = v.clone();
    vertices.extend(v.iter().map(|p| [0, 1, 2].map(|k| p[k] - depth * n[k])));
    let mut triangles = t.clone();
    triangles.extend(t.iter().map(|&[a, b, c]| [a + m, c + m, b + m]));
    for tri in t {
        for e in 0..3 {
            let (a, b) = (tri[e], tri[(e + 1) % 3]);
            if uses[&(a.min(b), a.max(b))] == 1 {
                // The wall runs along the open edge the other way round, as a neighbour would.
                triangles.push([b, a, a + m]);
                triangles.push([b, a + m, b + m]);
            }
        }
    }
    (vertices, triangles, Some(depth))
}

fn blender_grid(grid: &MediumGrid) -> Result<BlenderGrid, ExportError> {
    // One density for every cell, the grid's largest σ_t: the cells' colours and absorption
    // colours then carry their differences, and Cycles' majorant is that density.
    let d = grid
        .sigma_t
        .iter()
        .flat_map(|s| s.iter().copied())
        .fold(0.0, f64::max);
    let cells = grid
        .sigma_t
        .iter()
        .zip(&grid.albedo)
        .map(|(s, a)| principled_volume_at(*s, *a, d))
        .collect::<Result<Vec<_>, ExportError>>()?;
    Ok(BlenderGrid {
        origin_m: grid.origin.map(|x| x * METRES_PER_MM),
        cell_m: grid.cell_mm.map(|x| x * METRES_PER_MM),
        dims: grid.dims,
        cells,
    })
}

/// Writes `scene.json` and `build_blend.py` of `scene` into `dir` (created); returns them.
pub fn write_volume_scene(dir: &Path, scene: &VolumeScene) -> Result<Vec<PathBuf>, ExportError> {
    std::fs::create_dir_all(dir).map_err(|e| ExportError::io(dir, e))?;
    let json = serde_json::to_vec_pretty(scene)
        .map_err(|e| ExportError::Invalid(format!("scene.json: {e}")))?;
    let mut out = Vec::new();
    for (name, bytes) in [
        (super::SCENE_FILE, json),
        (BUILD_SCRIPT, BUILD_BLEND_PY.as_bytes().to_vec()),
    ] {
        let p = dir.join(name);
        std::fs::write(&p, bytes).map_err(|e| ExportError::io(&p, e))?;
        out.push(p);
    }
    Ok(out)
}

/// What a volume export did: its scene, and Cycles judged by a scan's frames when asked.
#[derive(Clone, Debug, Serialize)]
pub struct VolumeExport {
    /// The format of the report.
    pub format: &'static str,
    /// The Blender that built the `.blend` (None: none was run).
    pub blender: Option<String>,
    /// The medium as Cycles takes it, and the boundary.
    pub medium: PrincipledVolume,
    /// The model's own medium.
    pub sigma_t_per_mm: [f64; 3],
    /// The model's own albedo.
    pub albedo: [f64; 3],
    /// Cells of the grid (1: uniform).
    pub cells: usize,
    /// The boundary.
    pub boundary: BlenderBoundary,
    /// Cycles judged by the scan's frames beside subsurf's trace.
    pub frames: Option<FramesComparison>,
    /// Files written.
    pub files: Vec<PathBuf>,
}

/// The scan whose frames Cycles renders and is judged by.
#[derive(Clone, Debug)]
pub struct FramesRun<'a> {
    /// The scan.
    pub ds: &'a Dataset,
    /// Its frames.
    pub frames: &'a [usize],
    /// A second seed's renders (Cycles' own noise).
    pub noise: bool,
    /// Photons per frame of subsurf's own trace.
    pub photons: usize,
    /// The sample store.
    pub store: crate::pipeline::StoreOptions,
}

/// The whole of `subsurf export --model VOLUME.json`: the scene written into `dir`, the
/// `.blend` built by `blender` when there is one, and with `run` the scan's frames rendered
/// in Cycles and judged beside subsurf's own trace; the report written as
/// `export-report.json`.
pub fn export_volume(
    model: &VolumeModel,
    opts: &VolumeExportOptions,
    dir: &Path,
    blender: Option<&Blender>,
    run: Option<FramesRun>,
    progress: &dyn Progress,
) -> Result<VolumeExport, ExportError> {
    if opts.render && run.is_none() {
        return Err(ExportError::Invalid(
            "a volume model is rendered by a scan's frames: give --scan S [--frames F]".into(),
        ));
    }
    let scene = volume_scene(model, opts)?;
    let mut files = write_volume_scene(dir, &scene)?;
    let mut frames = None;
    let asked = run.is_some();
    if let (Some(b), Some(r)) = (blender, run) {
        let subject = Subject::Volume {
            model,
            photons: r.photons,
        };
        let (_, cmp) = frames::render_and_judge(
            r.ds,
            subject,
            r.frames,
            opts.samples,
            b,
            dir,
            r.noise,
            &r.store,
            progress,
        )?;
        files.push(dir.join(frames::FRAMES_FILE));
        files.push(dir.join(frames::FRAMES_DIR));
        frames = Some(cmp);
    } else if asked {
        return Err(ExportError::Blender(
            "rendering a scan's frames needs Blender".into(),
        ));
    }
    if let Some(b) = blender {
        b.run(dir, &Run::default())?;
        files.push(dir.join(BLEND_FILE));
    }
    let report = VolumeExport {
        format: "subsurf-volume-export/1",
        blender: blender.map(|b| b.version_line.clone()),
        medium: scene.medium,
        sigma_t_per_mm: scene.sigma_t_per_mm,
        albedo: scene.albedo,
        cells: model.grid.cells(),
        boundary: scene.boundary,
        frames,
        files: files.clone(),
    };
    let p = dir.join(format!("{REPORT_STEM}.json"));
    let json = serde_json::to_vec_pretty(&report)
        .map_err(|e| ExportError::Invalid(format!("the report: {e}")))?;
    std::fs::write(&p, json).map_err(|e| ExportError::io(&p, e))?;
    let mut report = report;
    report.files.push(p);
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Cycles' own arithmetic (kernel `svm_node_principled_volume`): σ_s and σ_a per channel,
    /// per metre.
    fn cycles(p: &PrincipledVolume) -> ([f64; 3], [f64; 3]) {
        let s = p.color.map(|c| c * p.density);
        let a = [0, 1, 2].map(|c| {
            (1.0 - p.color[c]).max(0.0) * (1.0 - p.absorption_color[c].sqrt()).max(0.0) * p.density
        });
        (s, a)
    }

    #[test]
    fn cycles_reads_back_the_medium_per_channel() {
        for (st, al) in [
            ([2.14, 2.16, 2.15], [0.974, 0.973, 0.964]),
            ([2.0, 2.0, 2.0], [0.99, 0.985, 0.98]),
            ([0.5, 7.3, 1.5], [0.2, 1.0, 0.0]),
        ] {
            let p = principled_volume(st, al).unwrap();
            let (s, a) = cycles(&p);
            for c in 0..3 {
                let (ws, wa) = (al[c] * st[c] * 1e3, (1.0 - al[c]) * st[c] * 1e3);
                assert!(
                    (s[c] - ws).abs() < 1e-9 * ws.max(1.0),
                    "{c}: σ_s {} vs {ws}",
                    s[c]
                );
                assert!(
                    (a[c] - wa).abs() < 1e-9 * wa.max(1.0),
                    "{c}: σ_a {} vs {wa}",
                    a[c]
                );
            }
            assert!(p.color.iter().all(|c| (0.0..=1.0).contains(c)));
            assert!(p.absorption_color.iter().all(|c| (0.0..=1.0).contains(c)));
        }
    }

    #[test]
    fn every_cell_of_a_grid_reads_back_under_one_density() {
        let mut grid = MediumGrid::homogeneous([0.0; 3], [2.0, 1.0, 1.0], [1.0; 3], [0.9; 3]);
        grid.dims = [2, 1, 1];
        grid.cell_mm = [1.0, 1.0, 1.0];
        grid.sigma_t = vec![[1.0, 2.0, 3.0], [4.0, 0.5, 2.5]];
        grid.albedo = vec![[0.9, 0.5, 0.99], [0.3, 1.0, 0.8]];
        let b = blender_grid(&grid).unwrap();
        for (k, p) in b.cells.iter().enumerate() {
            assert_eq!(p.density, 4000.0);
            let (s, a) = cycles(p);
            for c in 0..3 {
                let (st, al) = (grid.sigma_t[k][c] * 1e3, grid.albedo[k][c]);
                assert!((s[c] - al * st).abs() < 1e-9 * st, "cell {k} {c}");
                assert!((a[c] - (1.0 - al) * st).abs() < 1e-9 * st, "cell {k} {c}");
            }
        }
    }

    #[test]
    fn an_open_face_is_closed_behind_itself_and_a_closed_mesh_is_kept() {
        use crate::geometry::shapes;
        use crate::volume::VolumeMesh;
        let block = VolumeMesh::of(&shapes::block([0.0; 3], [1.0; 3]));
        let (v, t, d) = closed(&block, 2.0);
        assert_eq!(
            (v, t, d),
            (block.vertices.clone(), block.triangles.clone(), None)
        );
        // A square face in z = 0 of 2 × 2 quads, its normal up.
        let mut vertices = Vec::new();
        for j in 0..3 {
            for i in 0..3 {
                vertices.push([i as f64, j as f64, 0.0]);
            }
        }
        let mut triangles = Vec::new();
        for j in 0..2u32 {
            for i in 0..2u32 {
                let a = j * 3 + i;
                triangles.push([a, a + 1, a + 4]);
                triangles.push([a, a + 4, a + 3]);
            }
        }
        let face = VolumeMesh {
            vertices,
            triangles,
        };
        let (v, t, d) = closed(&face, 2.0);
        assert_eq!(d, Some(15.0));
        assert!(v[9..].iter().all(|p| (p[2] + 15.0).abs() < 1e-12));
        // Closed and consistently wound: every directed edge once, its reverse once.
        let mut directed = std::collections::HashMap::new();
        for tri in &t {
            for e in 0..3 {
                *directed.entry((tri[e], tri[(e + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &n) in &directed {
            assert_eq!(n, 1, "edge {a}-{b}");
            assert_eq!(
                directed.get(&(b, a)),
                Some(&1),
                "edge {a}-{b} has no neighbour"
            );
        }
        // Outward: the enclosed volume by the divergence theorem is positive, 2 × 2 × 15.
        let vol: f64 = t
            .iter()
            .map(|&[a, b, c]| {
                let (p, q, r) = (v[a as usize], v[b as usize], v[c as usize]);
                (p[0] * (q[1] * r[2] - q[2] * r[1]) - p[1] * (q[0] * r[2] - q[2] * r[0])
                    + p[2] * (q[0] * r[1] - q[1] * r[0]))
                    / 6.0
            })
            .sum();
        assert!((vol - 60.0).abs() < 1e-9, "{vol}");
    }

    #[test]
    fn a_medium_out_of_range_is_refused() {
        assert!(principled_volume([0.0, 1.0, 1.0], [0.5; 3]).is_err());
        assert!(principled_volume([1.0; 3], [0.5, f64::NAN, 0.5]).is_err());
        assert!(principled_volume([1.0; 3], [1.5, 0.5, 0.5]).is_err());
    }
}
