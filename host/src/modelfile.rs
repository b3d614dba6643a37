//! The model file (`docs/model-format.md`, `subsurf-model/6`): a binary little-endian PLY holding
//! the mesh and, per vertex, the fitted parameters of the light position `x_i` (Eq. 1/3/5/9), the
//! modulation texture `alpha(x_o)` (Eq. 2/6), a status and the fit's `log E(x_i)` (Eq. 8), plus
//! the tangent-frame rule its Eq. 3 segments are defined in, and optionally alpha finer than the
//! mesh (the per-face lattice of [`crate::lattice`], elements `face_alpha` and
//! `face_alpha_point`).
//!
//! Since version 6 every element has a fixed size per row (variable-length parameter lists live
//! in an element of their own, one scalar row per value), because common mesh readers (trimesh,
//! Open3D, Blender) read a binary PLY as fixed-size records and refuse a vertex element whose
//! rows differ in length.
//!
//! [`ModelFile`] is the one per-vertex model type: what the pipeline assembles, what evaluation
//! reads, and what the renderer and the plots take (the renderer prepares its inner-loop layout
//! from it in `render::Falloffs`, it keeps no model type of its own).
//!
//! Writing refuses non-finite parameters, so every number in a written model is finite.
use rayon::prelude::*;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

/// The magic comment that marks a subsurf model.
pub const MODEL_FORMAT: &str = "subsurf-model/6";

/// Earlier formats still read: version 1 wrote the `params` count as `uchar`, which wrapped for
/// models of more than 255 values (shared colour with n = 3 and m = 64 has 386); versions 1 and 2
/// have no per-vertex `segments` (every vertex has the header's m); versions 1–3 have no
/// `comment frame` line: their segments are in the frame of [`FrameRule::ReferenceAxis`], and they
/// read with it, so they evaluate and render exactly as before; versions 1–4 have no `face_alpha`
/// element (alpha at the vertices only); versions 1–5 hold the parameters as a list inside the
/// vertex element (and version 5 the lattice detail as lists inside `face_alpha`), which mesh
/// tools that read fixed-size records refuse. Reading is by element and property name, so every
/// layout reads whatever its version comment says.
const OLD_FORMATS: [&str; 5] = [
    "subsurf-model/1",
    "subsurf-model/2",
    "subsurf-model/3",
    "subsurf-model/4",
    "subsurf-model/5",
];

pub use crate::model::FrameRule;

/// Why a model file could not be read or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ModelFileError {
    /// File system error.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not a subsurf model PLY or is damaged.
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The model to be written is inconsistent (sizes, non-finite numbers).
    #[error("refusing to write model: {0}")]
    Invalid(String),
}

/// How colour is modelled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColourMode {
    /// One fall-off for all channels with scales `s_g`, `s_b` (Eq. 5 and 9).
    Shared,
    /// Separate parameters per channel (Eq. 3 per channel).
    PerChannel,
}

/// The shape shared by all vertices of a model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct ModelShape {
    /// `n`, the largest number of exponentials per segment (Eq. 1); a vertex may use fewer.
    pub terms: usize,
    /// `m`, direction segments (Eq. 3); 1 = isotropic.
    pub segments: usize,
    /// Colour handling.
    pub colour: ColourMode,
}

impl ModelShape {
    /// Number of parameters of a vertex that uses `n` terms and the header's m segments.
    pub fn param_count(&self, n: usize) -> usize {
        self.param_count_m(n, self.segments)
    }

    /// Number of parameters of a vertex that uses `n` terms and `m` segments.
    pub fn param_count_m(&self, n: usize, m: usize) -> usize {
        match self.colour {
            ColourMode::Shared => 2 + 2 * n * m,
            ColourMode::PerChannel => 3 * 2 * n * m,
        }
    }
}

/// What a vertex's model is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[repr(u8)]
pub enum VertexStatus {
    /// Fitted from its own closest light position.
    Fitted = 0,
    /// Interpolated from fitted mesh neighbours (the fit failed or there was no data).
    Interpolated = 1,
    /// No model: nothing fitted is connected to this vertex.
    NoModel = 2,
}

impl VertexStatus {
    /// The status a file's byte stands for (its `repr`); `None` for a byte no version writes.
    fn from_byte(b: u8) -> Option<VertexStatus> {
        match b {
            0 => Some(VertexStatus::Fitted),
            1 => Some(VertexStatus::Interpolated),
            2 => Some(VertexStatus::NoModel),
            _ => None,
        }
    }
}

/// log E as a file holds it, read: version 2 on writes NO_LOG_E (-1) where version 1 wrote NaN,
/// both meaning "no fit of its own" (NaN in memory).
fn log_e_read(x: f32) -> f32 {
    if x >= 0.0 { x } else { f32::NAN }
}

/// One vertex's model.
#[derive(Debug, Clone, PartialEq)]
pub struct VertexModel {
    /// Eq. 2/6: modulation texture alpha(x_o) per channel.
    pub alpha: [f32; 3],
    /// Fitted, interpolated or none.
    pub status: VertexStatus,
    /// Eq. 8: log E(x_i) of this vertex's fit, mean over channels; NaN if not fitted.
    pub log_e: f32,
    /// Number of exponential terms this vertex uses (0 for [`VertexStatus::NoModel`]).
    pub terms: u8,
    /// Direction segments m this vertex uses, 1..= the header's m (0 for
    /// [`VertexStatus::NoModel`]); files before version 3 read as the header's m.
    pub segments: u8,
    /// Parameters in the order of `docs/model-format.md`.
    pub params: Vec<f64>,
    /// `[r_min, r_max]` (mm): the distances |x_o − x_i| the fit's samples covered. The model is
    /// claimed as [`crate::model::support`] says (below r_min ln R_d continues linearly).
    /// `r_max <= r_min` (e.g. `[0, 0]`, what files without the properties read as) means
    /// unknown: the model is used as is everywhere.
    pub r_range: [f32; 2],
}

impl VertexModel {
    /// Where this vertex's model is claimed (its sampled range).
    pub fn support(&self) -> crate::model::Support {
        crate::model::Support::new(self.r_range[0] as f64, self.r_range[1] as f64)
    }
}

/// `log_e` as written for a vertex without a fit of its own (interpolated, no model): log E is
/// never negative, so -1 says "none" while every number in the file stays finite.
pub const NO_LOG_E: f32 = -1.0;

/// The sampled range of a model without one (ground truth, old files): used as is everywhere.
pub const NO_RANGE: [f32; 2] = [0.0, 0.0];

/// A whole model: mesh plus per-vertex models.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFile {
    /// Shape of the model.
    pub shape: ModelShape,
    /// Vertex positions (object frame, mm).
    pub positions: Vec<[f64; 3]>,
    /// Unit vertex normals.
    pub normals: Vec<[f64; 3]>,
    /// Triangles.
    pub triangles: Vec<[u32; 3]>,
    /// One model per vertex.
    pub vertices: Vec<VertexModel>,
    /// The homogeneous baseline (one isotropic fall-off for the whole object, `docs/model-format.md`,
    /// [`crate::baseline`]); `None` in files written without one.
    pub baseline: Option<BaselineParams>,
    /// The rule of the tangent frame (Eq. 3) the segments are defined in (`comment frame`):
    /// [`FrameRule::MinimalRotation`] for every fit since version 4, [`FrameRule::ReferenceAxis`]
    /// for files before it.
    pub frame: FrameRule,
    /// alpha finer than the mesh (section 5's "higher resolution texture"): per face, ln alpha
    /// relative to the interpolated vertex alphas ([`crate::lattice::FaceAlpha`]); `None` in
    /// files without the `face_alpha` element (alpha at the vertices only).
    pub face_alpha: Option<crate::lattice::FaceAlpha>,
    /// The rules the model's samples were read by (`comment fitted …`), which `subsurf evaluate`
    /// judges it by unless told otherwise; `None` in files without the line (written before it,
    /// or not by a fit: ground truth).
    pub fitted_with: Option<FitRecord>,
    /// The frames the model's fit was given (`comment fitted_frames …`): `subsurf evaluate`
    /// reports them apart, as in-sample, from frames the fit never saw. `None` in files without
    /// the line (written before it, or not by a fit: ground truth).
    pub fitted_frames: Option<Vec<usize>>,
}

/// What a model was fitted with that judging it depends on: how its frames were registered
/// and sampled (header line `comment fitted key=value …`, `docs/model-format.md`). Readers that
/// do not know the line skip it as any comment; keys this version does not know are skipped.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FitRecord {
    /// The radiance noise floor: samples below it dropped, Eq. 8's threshold t, spots 10× above.
    pub noise_floor: f64,
    /// Samples closer than this to x_i (mm) were dropped.
    pub exclusion_radius_mm: f64,
    /// The samples' grazing limit (cos θ at x_o).
    pub cos_min: f64,
    /// The coverage check of the samples' pixel neighbourhoods.
    pub coverage: bool,
    /// The largest disagreement between detected spot and laser ray (mm).
    pub laser_tolerance_mm: f64,
    /// Frames whose spot the camera saw more grazing than this (cos θ) were not fitted.
    pub spot_cos_min: f64,
}

/// The header lines `comment fitted_frames <ranges>` of a fit's frames, each under the reader's
/// line limit (a long list of holes takes several lines; the reader joins them).
fn fitted_frames_lines(frames: &[usize]) -> String {
    let list = crate::dataset::format_frame_list(frames);
    let mut out = String::new();
    let mut line = String::new();
    for part in list.split(',').filter(|p| !p.is_empty()) {
        if !line.is_empty() && line.len() + part.len() > 900 {
            out += &format!("comment fitted_frames {line}\n");
            line.clear();
        }
        if !line.is_empty() {
            line.push(',');
        }
        line += part;
    }
    if !line.is_empty() || frames.is_empty() {
        // An empty fit (no frame) still says so: `-` is no frame.
        out += &format!(
            "comment fitted_frames {}\n",
            if line.is_empty() { "-" } else { &line }
        );
    }
    out
}

impl FitRecord {
    fn header_line(&self) -> String {
        format!(
            "comment fitted noise_floor={} exclusion_radius_mm={} cos_min={} coverage={} \
             laser_tolerance_mm={} spot_cos_min={}\n",
            self.noise_floor,
            self.exclusion_radius_mm,
            self.cos_min,
            u8::from(self.coverage),
            self.laser_tolerance_mm,
            self.spot_cos_min
        )
    }

    /// The record of `key=value` words; `None` when a known key is missing or not a finite
    /// number.
    fn parse(words: &[&str]) -> Option<FitRecord> {
        let get = |key: &str| -> Option<f64> {
            words
                .iter()
                .find_map(|w| w.strip_prefix(key)?.strip_prefix('='))
                .and_then(|v| v.parse::<f64>().ok())
                .filter(|v| v.is_finite())
        };
        Some(FitRecord {
            noise_floor: get("noise_floor")?,
            exclusion_radius_mm: get("exclusion_radius_mm")?,
            cos_min: get("cos_min")?,
            coverage: get("coverage")? != 0.0,
            laser_tolerance_mm: get("laser_tolerance_mm")?,
            spot_cos_min: get("spot_cos_min")?,
        })
    }
}

/// The homogeneous baseline as the file holds it (header line `comment baseline <n> <r_min>
/// <r_max> <params...>`): the parameters of one isotropic (m = 1) vertex model in the file's
/// colour mode.
#[derive(Debug, Clone, PartialEq)]
pub struct BaselineParams {
    /// Terms n.
    pub terms: usize,
    /// Parameters in the order of a vertex's `params` with m = 1.
    pub params: Vec<f64>,
    /// `[r_min, r_max]` of the pooled samples, mm.
    pub r_range: [f64; 2],
}

impl BaselineParams {
    /// The colour model, validated.
    pub fn model(
        &self,
        colour: ColourMode,
    ) -> Result<crate::model::ColourModel, crate::model::ModelError> {
        let shape = ModelShape {
            terms: self.terms,
            segments: 1,
            colour,
        };
        model_of(&shape, self.terms, &self.params)
    }

    /// The baseline as prediction uses it.
    pub fn baseline(&self, colour: ColourMode) -> Option<crate::baseline::Baseline> {
        Some(crate::baseline::Baseline {
            model: self.model(colour).ok()?,
            r_range: self.r_range,
        })
    }

    fn header_line(&self) -> String {
        let mut l = format!(
            "comment baseline {} {} {}",
            self.terms, self.r_range[0], self.r_range[1]
        );
        for p in &self.params {
            l.push_str(&format!(" {p}"));
        }
        l.push('\n');
        l
    }

    fn parse(words: &[&str], colour: Option<ColourMode>) -> Option<BaselineParams> {
        let terms: usize = words.first()?.parse().ok()?;
        let nums: Vec<f64> = words[1..]
            .iter()
            .map(|w| w.parse().ok())
            .collect::<Option<_>>()?;
        if nums.len() < 2 || nums.iter().any(|x| !x.is_finite()) {
            return None;
        }
        let b = BaselineParams {
            terms,
            params: nums[2..].to_vec(),
            r_range: [nums[0], nums[1]],
        };
        // Checked against the colour mode once the header is read (it may come later).
        let _ = colour;
        Some(b)
    }
}

impl ModelFile {
    /// The tangent frame of the model at a light position with normal `normal` (x_i's own
    /// normal: the vertex normal at a vertex, the interpolated one between vertices), by the
    /// file's rule; `None` for a degenerate normal.
    pub fn frame_at(&self, normal: [f64; 3]) -> Option<crate::model::TangentFrame> {
        crate::model::TangentFrame::with_rule(self.frame, normal).ok()
    }

    /// alpha(x_o) (Eq. 2/6) per channel at barycentric coordinates `bary` of triangle `tri`:
    /// the barycentric interpolation of the corners' vertex alphas, times exp of the face
    /// lattice's detail there when the model has one (`docs/model-format.md`). `[1; 3]` for a
    /// triangle outside the mesh.
    pub fn alpha_at(&self, tri: usize, bary: [f64; 3]) -> [f64; 3] {
        let Some(t) = self.triangles.get(tri) else {
            return [1.0; 3];
        };
        let mut a = [0.0; 3];
        for (j, &v) in t.iter().enumerate() {
            let av = self.vertices.get(v as usize).map_or([1.0; 3], |m| m.alpha);
            for c in 0..3 {
                a[c] += bary[j] * av[c] as f64;
            }
        }
        if let Some(fa) = &self.face_alpha {
            let d = fa.detail_at(tri, bary);
            for c in 0..3 {
                a[c] *= d[c].exp();
            }
        }
        a
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the model has no vertices.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Axis-aligned bounding box of the vertices, `(min, max)`, mm.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for q in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        (lo, hi)
    }

    /// A homogeneous model: every vertex gets the same shared-colour isotropic fall-off
    /// `(1, s_g, s_b) Σ_k c_k e^{d_k r}` (Eq. 9) and `alpha = 1`, no sampled range (the model
    /// everywhere). Used for slabs, renders of known materials and tests.
    pub fn homogeneous(
        positions: Vec<[f64; 3]>,
        normals: Vec<[f64; 3]>,
        triangles: Vec<[u32; 3]>,
        scales: [f64; 2],
        terms: &[(f64, f64)],
    ) -> Self {
        let mut params = vec![scales[0], scales[1]];
        for &(c, d) in terms {
            params.extend([c, d]);
        }
        let one = VertexModel {
            alpha: [1.0; 3],
            status: VertexStatus::Fitted,
            log_e: f32::NAN,
            terms: terms.len().min(u8::MAX as usize) as u8,
            segments: 1,
            params,
            r_range: NO_RANGE,
        };
        Self {
            shape: ModelShape {
                terms: terms.len(),
                segments: 1,
                colour: ColourMode::Shared,
            },
            vertices: vec![one; positions.len()],
            positions,
            normals,
            triangles,
            baseline: None,
            frame: FrameRule::CURRENT,
            face_alpha: None,
            fitted_with: None,
            fitted_frames: None,
        }
    }

    /// Checks sizes and finiteness (the invariant of every written file).
    pub fn check(&self) -> Result<(), ModelFileError> {
        let n = self.positions.len();
        let bad = |m: String| Err(ModelFileError::Invalid(m));
        if self.normals.len() != n || self.vertices.len() != n {
            return bad("positions, normals and vertex models differ in length".into());
        }
        if self.shape.terms == 0 || self.shape.terms > 8 || self.shape.segments == 0 {
            return bad(format!("unsupported shape {:?}", self.shape));
        }
        // In parallel, the first bad vertex reported: a prolonged model has 650,000 vertices
        // and is checked when built, written and read back.
        let vertex = |(i, v): (usize, &VertexModel)| -> Option<String> {
            let m = v.segments as usize;
            let want = if v.status == VertexStatus::NoModel {
                0
            } else {
                self.shape.param_count_m(v.terms as usize, m)
            };
            if v.params.len() != want
                || v.terms as usize > self.shape.terms
                || (v.status != VertexStatus::NoModel && !(1..=self.shape.segments).contains(&m))
            {
                return Some(format!(
                    "vertex {i}: {} parameters for {} terms and {m} segments",
                    v.params.len(),
                    v.terms
                ));
            }
            if v.params.iter().any(|p| !p.is_finite())
                || v.alpha.iter().any(|a| !a.is_finite())
                || v.r_range.iter().any(|r| !(r.is_finite() && *r >= 0.0))
            {
                return Some(format!(
                    "vertex {i}: non-finite parameter, alpha or sampled range"
                ));
            }
            None
        };
        if let Some(message) = self
            .vertices
            .par_iter()
            .enumerate()
            .with_min_len(4096)
            .find_map_first(vertex)
        {
            return bad(message);
        }
        if let Some(b) = &self.baseline
            && (b.r_range.iter().any(|r| !r.is_finite()) || b.model(self.shape.colour).is_err())
        {
            return bad("invalid baseline".into());
        }
        if self
            .triangles
            .par_iter()
            .with_min_len(4096)
            .any(|t| t.iter().any(|&i| i as usize >= n))
        {
            return bad("triangle index out of range".into());
        }
        if let Some(fa) = &self.face_alpha
            && fa.faces() != self.triangles.len()
        {
            return bad(format!(
                "face alpha for {} faces, the mesh has {}",
                fa.faces(),
                self.triangles.len()
            ));
        }
        Ok(())
    }

    /// Writes the binary PLY, then reads it back and compares before it reports success: a file
    /// that cannot be read back (the fate of version 1's wrapped counts) is never left behind as
    /// if it were the fit. The bytes go to a temporary file beside `path`, renamed over it only
    /// after the read-back matched.
    pub fn write(&self, path: &Path) -> Result<(), ModelFileError> {
        let out = self.to_bytes()?;
        let io = |source| ModelFileError::Io {
            path: path.to_path_buf(),
            source,
        };
        let mut tmp_name = path.file_name().unwrap_or_default().to_os_string();
        tmp_name.push(".partial");
        let tmp = path.with_file_name(tmp_name);
        // The bytes are parsed back while they are written (a prolonged model of 650,000
        // vertices is about 100 MB: the two took a second one after the other), and the file
        // is then read back and compared with them: what is on disk is what reads back as this
        // model.
        let (written, back) = rayon::join(
            || -> Result<(), ModelFileError> {
                let mut f = std::fs::File::create(&tmp).map_err(io)?;
                f.write_all(&out).map_err(io)?;
                f.sync_all().map_err(io)
            },
            || {
                ModelFile::parse(&mut &out[..], out.len(), &tmp)
                    .and_then(|m| m.encode_checked(Layout::Rows))
            },
        );
        if let Err(e) = written {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
        let same = back.and_then(|b| Ok(b == out && same_bytes(&tmp, &out).map_err(io)?));
        match same {
            Ok(true) => std::fs::rename(&tmp, path).map_err(io),
            Ok(false) => {
                let _ = std::fs::remove_file(&tmp);
                Err(ModelFileError::Format {
                    path: path.to_path_buf(),
                    message: "the written model reads back differently; nothing was written".into(),
                })
            }
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                Err(e)
            }
        }
    }

    /// The file's bytes (`docs/model-format.md`, the current version).
    pub fn to_bytes(&self) -> Result<Vec<u8>, ModelFileError> {
        self.encode(Layout::Rows)
    }

    /// The bytes in `layout`: [`Layout::Rows`] is the current version; [`Layout::Lists`] is
    /// version 5's layout (kept to test that such files still read).
    fn encode(&self, layout: Layout) -> Result<Vec<u8>, ModelFileError> {
        self.check()?;
        self.encode_checked(layout)
    }

    /// [`ModelFile::encode`] of a model already checked (one just read: `parse` checks it).
    fn encode_checked(&self, layout: Layout) -> Result<Vec<u8>, ModelFileError> {
        if let Some(v) = self
            .vertices
            .iter()
            .find(|v| v.params.len() > u16::MAX as usize)
        {
            return Err(ModelFileError::Format {
                path: std::path::PathBuf::new(),
                message: format!(
                    "{} parameters in one vertex: at most {}",
                    v.params.len(),
                    u16::MAX
                ),
            });
        }
        let colour = match self.shape.colour {
            ColourMode::Shared => "shared",
            ColourMode::PerChannel => "per-channel",
        };
        let lists = layout == Layout::Lists;
        let param_total: usize = self.vertices.iter().map(|v| v.params.len()).sum();
        let (magic, params_prop, params_element) = if lists {
            (
                "subsurf-model/5",
                "property list ushort double params\n",
                String::new(),
            )
        } else {
            (
                MODEL_FORMAT,
                "property ushort param_count\n",
                format!("element param {param_total}\nproperty double value\n"),
            )
        };
        let face_alpha_elements = match &self.face_alpha {
            None => String::new(),
            Some(_) if lists => format!(
                "element face_alpha {}\nproperty uchar level\n\
                 property list ushort float detail_r\nproperty list ushort float detail_g\n\
                 property list ushort float detail_b\n",
                self.triangles.len()
            ),
            Some(fa) => format!(
                "element face_alpha {}\nproperty uchar level\nelement face_alpha_point {}\n\
                 property float detail_r\nproperty float detail_g\nproperty float detail_b\n",
                self.triangles.len(),
                (0..fa.faces())
                    .map(|f| fa.face_detail(f).len())
                    .sum::<usize>()
            ),
        };
        let mut out = Vec::with_capacity(
            self.positions.len() * 80 + param_total * 8 + self.triangles.len() * 13,
        );
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment {magic}\ncomment terms {}\n\
             comment segments {}\ncomment colour {colour}\ncomment frame {}\n{}element vertex {}\n\
             property double x\nproperty double y\nproperty double z\n\
             property double nx\nproperty double ny\nproperty double nz\n\
             property float alpha_r\nproperty float alpha_g\nproperty float alpha_b\n\
             property uchar status\nproperty float log_e\nproperty uchar terms\n\
             property uchar segments\n{params_prop}\
             property float r_min\nproperty float r_max\nelement face {}\n\
             property list uchar int vertex_indices\n{params_element}{face_alpha_elements}\
             end_header\n",
            self.shape.terms,
            self.shape.segments,
            self.frame.name(),
            self.baseline
                .as_ref()
                .map_or(String::new(), BaselineParams::header_line)
                + &self
                    .fitted_with
                    .as_ref()
                    .map_or(String::new(), FitRecord::header_line)
                + &self
                    .fitted_frames
                    .as_deref()
                    .map_or(String::new(), fitted_frames_lines),
            self.positions.len(),
            self.triangles.len(),
        );
        out.extend_from_slice(header.as_bytes());
        // A vertex's record; version 5 (lists) puts its parameters before the sampled range.
        let vertex = |i: usize, v: &VertexModel, out: &mut dyn Sink| {
            let mut put = |b: &[u8]| out.put(b);
            for x in self.positions[i].iter().chain(&self.normals[i]) {
                put(&x.to_le_bytes());
            }
            for a in v.alpha {
                put(&a.to_le_bytes());
            }
            put(&[v.status as u8]);
            // Every number in the file is finite: a vertex without its own fit (log E is a
            // non-negative error) is written as the documented -1, read back as NaN ("none").
            let log_e = if v.log_e.is_finite() {
                v.log_e
            } else {
                NO_LOG_E
            };
            put(&log_e.to_le_bytes());
            put(&[v.terms, v.segments]);
            // Checked above: at most u16::MAX values.
            put(&(v.params.len() as u16).to_le_bytes());
            if lists {
                for p in &v.params {
                    put(&p.to_le_bytes());
                }
            }
            for r in v.r_range {
                put(&r.to_le_bytes());
            }
        };
        let face = |t: &[u32; 3], out: &mut dyn Sink| {
            out.put(&[3]);
            for i in t {
                out.put(&(*i as i32).to_le_bytes());
            }
        };
        if lists {
            for (i, v) in self.vertices.iter().enumerate() {
                vertex(i, v, &mut out);
            }
            for t in &self.triangles {
                face(t, &mut out);
            }
        } else {
            // Records of one size: encoded in parallel, each into its own slot (a prolonged
            // model is 100 MB, and every fit writes one and encodes it again to check it).
            let (n, f) = (self.vertices.len(), self.triangles.len());
            let start = out.len();
            out.resize(start + n * VERTEX_RECORD + f * FACE_RECORD, 0);
            let (vs, fs) = out[start..].split_at_mut(n * VERTEX_RECORD);
            vs.par_chunks_mut(VERTEX_RECORD)
                .zip(self.vertices.par_iter().enumerate())
                .with_min_len(4096)
                .for_each(|(s, (i, v))| vertex(i, v, &mut SliceSink(s, 0)));
            fs.par_chunks_mut(FACE_RECORD)
                .zip(self.triangles.par_iter())
                .with_min_len(4096)
                .for_each(|(s, t)| face(t, &mut SliceSink(s, 0)));
        }
        if !lists {
            for p in self.vertices.iter().flat_map(|v| &v.params) {
                out.extend_from_slice(&p.to_le_bytes());
            }
        }
        if let Some(fa) = &self.face_alpha {
            for f in 0..fa.faces() {
                out.push(fa.level(f));
                if lists {
                    let d = fa.face_detail(f);
                    for c in 0..3 {
                        // At most 45 points (level 8): the ushort count cannot wrap.
                        out.extend_from_slice(&(d.len() as u16).to_le_bytes());
                        for p in d {
                            out.extend_from_slice(&p[c].to_le_bytes());
                        }
                    }
                }
            }
            if !lists {
                for p in (0..fa.faces()).flat_map(|f| fa.face_detail(f)) {
                    for x in p {
                        out.extend_from_slice(&x.to_le_bytes());
                    }
                }
            }
        }
        Ok(out)
    }

    /// Reads a model written by [`ModelFile::write`] (properties are looked up by name, so a
    /// tool that reorders or adds properties keeps the file readable).
    pub fn read(path: &Path) -> Result<ModelFile, ModelFileError> {
        let f = std::fs::File::open(path).map_err(|source| ModelFileError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let len = f.metadata().map_or(0, |m| m.len());
        Self::parse(
            &mut BufReader::new(f),
            usize::try_from(len).unwrap_or(0),
            path,
        )
    }

    /// [`ModelFile::read`] from `r` (about `len` bytes; errors name `path`).
    fn parse(r: &mut impl BufRead, len: usize, path: &Path) -> Result<ModelFile, ModelFileError> {
        Self::parse_with(r, len, path, true)
    }

    /// [`ModelFile::parse`], the current writer's elements read as records (`rows`) or, with
    /// `records` false, by the columns every layout is read by (the reference `rows` is tested
    /// against).
    fn parse_with(
        r: &mut impl BufRead,
        len: usize,
        path: &Path,
        records: bool,
    ) -> Result<ModelFile, ModelFileError> {
        let io = |source| ModelFileError::Io {
            path: path.to_path_buf(),
            source,
        };
        let fmt = |message: String| ModelFileError::Format {
            path: path.to_path_buf(),
            message,
        };
        let mut line = String::new();
        let mut elements: Vec<(String, usize, Vec<Prop>)> = Vec::new();
        let (mut terms, mut segments, mut colour, mut magic) = (None, None, None, false);
        let mut baseline = None;
        let mut fitted_with = None;
        let mut fitted_frames: Option<Vec<usize>> = None;
        // Files before version 4 have no `comment frame`: their rule.
        let mut frame = FrameRule::ReferenceAxis;
        let mut first = true;
        loop {
            line.clear();
            if r.read_line(&mut line).map_err(io)? == 0 || line.len() > 1024 {
                return Err(fmt("truncated or malformed PLY header".into()));
            }
            let words: Vec<&str> = line.split_whitespace().collect();
            if first {
                if words != ["ply"] {
                    return Err(fmt("not a PLY file".into()));
                }
                first = false;
                continue;
            }
            match words.as_slice() {
                ["format", "binary_little_endian", "1.0"] => {}
                ["format", ..] => return Err(fmt("only binary_little_endian PLY is read".into())),
                ["comment", m] if *m == MODEL_FORMAT || OLD_FORMATS.contains(m) => magic = true,
                ["comment", "terms", n] => terms = n.parse().ok(),
                ["comment", "segments", n] => segments = n.parse().ok(),
                ["comment", "colour", "shared"] => colour = Some(ColourMode::Shared),
                ["comment", "colour", "per-channel"] => colour = Some(ColourMode::PerChannel),
                ["comment", "frame", name] => {
                    frame = FrameRule::from_name(name)
                        .ok_or_else(|| fmt(format!("unknown tangent-frame rule {name:?}")))?
                }
                ["comment", "baseline", rest @ ..] => {
                    baseline = Some(
                        BaselineParams::parse(rest, colour)
                            .ok_or_else(|| fmt(format!("bad baseline line {:?}", line.trim())))?,
                    )
                }
                ["comment", "fitted_frames", "-"] => {
                    fitted_frames.get_or_insert_with(Vec::new);
                }
                ["comment", "fitted_frames", list] => {
                    let more = crate::dataset::parse_frame_list(list).map_err(|e| {
                        fmt(format!("bad fitted_frames line {:?}: {e}", line.trim()))
                    })?;
                    let all = fitted_frames.get_or_insert_with(Vec::new);
                    if all.len() + more.len() > crate::dataset::MAX_FRAME_RANGE {
                        return Err(fmt("more fitted frames than any scan holds".into()));
                    }
                    all.extend(more);
                    all.sort_unstable();
                    all.dedup();
                }
                ["comment", "fitted", rest @ ..] => {
                    fitted_with = Some(
                        FitRecord::parse(rest)
                            .ok_or_else(|| fmt(format!("bad fitted line {:?}", line.trim())))?,
                    )
                }
                ["comment", ..] | ["obj_info", ..] => {}
                ["element", name, n] => {
                    let n: usize = n
                        .parse()
                        .map_err(|_| fmt(format!("bad count in {line:?}")))?;
                    elements.push((name.to_string(), n, Vec::new()));
                }
                ["property", "list", ct, vt, name] => {
                    let p = Prop {
                        name: name.to_string(),
                        count: Some(ty(ct).ok_or_else(|| fmt(format!("type {ct}")))?),
                        ty: ty(vt).ok_or_else(|| fmt(format!("type {vt}")))?,
                    };
                    elements
                        .last_mut()
                        .ok_or_else(|| fmt("property before element".into()))?
                        .2
                        .push(p);
                }
                ["property", t, name] => {
                    let p = Prop {
                        name: name.to_string(),
                        count: None,
                        ty: ty(t).ok_or_else(|| fmt(format!("type {t}")))?,
                    };
                    elements
                        .last_mut()
                        .ok_or_else(|| fmt("property before element".into()))?
                        .2
                        .push(p);
                }
                ["end_header"] => break,
                _ => return Err(fmt(format!("unexpected header line {:?}", line.trim()))),
            }
        }
        if !magic {
            return Err(fmt(format!(
                "no `comment {MODEL_FORMAT}`: not a subsurf model"
            )));
        }
        let shape = ModelShape {
            terms: terms.ok_or_else(|| fmt("no terms comment".into()))?,
            segments: segments.ok_or_else(|| fmt("no segments comment".into()))?,
            colour: colour.ok_or_else(|| fmt("no colour comment".into()))?,
        };
        // The body in one allocation (a prolonged model is about 100 MB: grown by doubling, its
        // copies were a third of a read).
        let mut body = Vec::with_capacity(len);
        r.read_to_end(&mut body).map_err(io)?;
        let mut cur = Cursor { b: &body, at: 0 };
        let mut m = ModelFile {
            shape,
            positions: Vec::new(),
            normals: Vec::new(),
            triangles: Vec::new(),
            vertices: Vec::new(),
            baseline: None,
            frame,
            face_alpha: None,
            fitted_with,
            fitted_frames,
        };
        let (mut levels, mut detail) = (Vec::new(), Vec::new());
        let mut face_alpha_seen = false;
        // Version 6: the vertices' parameter counts and the values of element `param`; the rows
        // of element `face_alpha_point`.
        let (mut param_counts, mut param_values, mut points) = (Vec::new(), Vec::new(), Vec::new());
        if let Some(b) = baseline {
            b.model(shape.colour)
                .map_err(|e| fmt(format!("baseline: {e}")))?;
            m.baseline = Some(b);
        }
        // A face lattice is per triangle: the faces must be triangles (not polygons).
        let triangles_only = elements.iter().any(|e| e.0 == "face_alpha");
        for (name, count, props) in &elements {
            if count.saturating_mul(props.len()) > body.len() {
                return Err(fmt(format!(
                    "element {name} claims more data than the file holds"
                )));
            }
            // The elements the current writer writes are read as fixed records (`rows`); any
            // other layout (older versions, other tools' property orders) by the columns below.
            let into = rows::Into {
                m: &mut m,
                param_counts: &mut param_counts,
                param_values: &mut param_values,
                triangles_only,
            };
            if records
                && rows::read(name, *count, props, &mut cur, into)
                    .map_err(|e| fmt(e.message(name)))?
            {
                continue;
            }
            // Why columns and reused rows: a prolonged model of 650,000 vertices has millions of
            // rows; fresh vectors per row and a search by name per value were most of a read.
            let at = COLS.map(|(_, k)| props.iter().position(|p| p.name == k));
            let mut vals: Vec<Vec<f64>> = vec![Vec::new(); props.len()];
            // The count is bounded by the body's length (above).
            match name.as_str() {
                "vertex" => {
                    m.positions.reserve(*count);
                    m.normals.reserve(*count);
                    m.vertices.reserve(*count);
                    param_counts.reserve(*count);
                }
                "face" => m.triangles.reserve(*count),
                "param" => param_values.reserve(*count),
                _ => {}
            }
            for _ in 0..*count {
                for (p, v) in props.iter().zip(vals.iter_mut()) {
                    v.clear();
                    match p.count {
                        None => v.push(cur.read(p.ty).ok_or_else(|| fmt("truncated data".into()))?),
                        Some(ct) => {
                            let n = cur.read(ct).ok_or_else(|| fmt("truncated data".into()))?;
                            if !(0.0..=1e6).contains(&n) {
                                return Err(fmt("bad list length".into()));
                            }
                            for _ in 0..n as usize {
                                v.push(cur.read(p.ty).ok_or_else(|| fmt("truncated data".into()))?);
                            }
                        }
                    }
                }
                let get = |c: Col| at[c as usize].map(|j| &vals[j]);
                let one = |c: Col| -> Result<f64, ModelFileError> {
                    get(c)
                        .and_then(|v| v.first().copied())
                        .ok_or_else(|| fmt(format!("{name} has no property {}", c.name())))
                };
                match name.as_str() {
                    "vertex" => {
                        m.positions.push([one(Col::X)?, one(Col::Y)?, one(Col::Z)?]);
                        m.normals
                            .push([one(Col::Nx)?, one(Col::Ny)?, one(Col::Nz)?]);
                        let s = one(Col::Status)? as u8;
                        let status = VertexStatus::from_byte(s)
                            .ok_or_else(|| fmt(format!("unknown vertex status {s}")))?;
                        // Versions 1–5: a list in the vertex; version 6: a count here, the
                        // values in element `param`.
                        let params = match (get(Col::Params), get(Col::ParamCount)) {
                            (Some(p), _) => p.clone(),
                            (None, Some(n)) => {
                                param_counts.push(n.first().copied().unwrap_or(0.0) as usize);
                                Vec::new()
                            }
                            (None, None) => return Err(fmt("vertex has no params".into())),
                        };
                        let terms = match get(Col::Terms) {
                            Some(v) => v.first().copied().unwrap_or(0.0) as u8,
                            None => shape.terms as u8,
                        };
                        // Before version 3 every vertex has the header's m.
                        let segments = match get(Col::Segments) {
                            Some(v) => v.first().copied().unwrap_or(0.0) as u8,
                            None if status == VertexStatus::NoModel => 0,
                            None => shape.segments.min(u8::MAX as usize) as u8,
                        };
                        m.vertices.push(VertexModel {
                            alpha: [
                                one(Col::AlphaR)? as f32,
                                one(Col::AlphaG)? as f32,
                                one(Col::AlphaB)? as f32,
                            ],
                            status,
                            log_e: log_e_read(one(Col::LogE)? as f32),
                            terms,
                            segments,
                            params,
                            // Older files have no sampled range: unknown.
                            r_range: match (get(Col::RMin), get(Col::RMax)) {
                                (Some(a), Some(b)) => [
                                    a.first().copied().unwrap_or(0.0) as f32,
                                    b.first().copied().unwrap_or(0.0) as f32,
                                ],
                                _ => NO_RANGE,
                            },
                        });
                    }
                    "param" => param_values.push(one(Col::Value)?),
                    "face_alpha_point" => {
                        points.push([
                            one(Col::DetailR)? as f32,
                            one(Col::DetailG)? as f32,
                            one(Col::DetailB)? as f32,
                        ]);
                    }
                    "face_alpha" => {
                        face_alpha_seen = true;
                        let level = one(Col::Level)?;
                        if !(1.0..=crate::lattice::MAX_LEVEL as f64).contains(&level) {
                            return Err(fmt(format!("face_alpha level {level} out of range")));
                        }
                        let level = level as u8;
                        levels.push(level);
                        // Version 5: the detail as lists here; version 6: rows of element
                        // `face_alpha_point`, split by the levels below.
                        if get(Col::DetailR).is_some() {
                            let want = crate::lattice::point_count(level);
                            let ch = |c: Col| -> Result<&Vec<f64>, ModelFileError> {
                                get(c).filter(|v| v.len() == want).ok_or_else(|| {
                                    fmt(format!("face_alpha {}: want {want} values", c.name()))
                                })
                            };
                            let (dr, dg, db) =
                                (ch(Col::DetailR)?, ch(Col::DetailG)?, ch(Col::DetailB)?);
                            for p in 0..want {
                                detail.push([dr[p] as f32, dg[p] as f32, db[p] as f32]);
                            }
                        }
                    }
                    "face" => {
                        let idx = get(Col::VertexIndices)
                            .ok_or_else(|| fmt("face has no vertex_indices".into()))?;
                        // face_alpha is per triangle: a polygon would become several.
                        if idx.len() != 3 && triangles_only {
                            return Err(fmt("face_alpha needs a triangle mesh".into()));
                        }
                        if idx.iter().any(|&i| !(0.0..=u32::MAX as f64).contains(&i)) {
                            return Err(fmt("face: a vertex index out of range".into()));
                        }
                        // Triangulate polygons as a fan.
                        for k in 1..idx.len().saturating_sub(1) {
                            m.triangles
                                .push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
                        }
                    }
                    _ => {}
                }
            }
        }
        if !param_counts.is_empty() || !param_values.is_empty() {
            if param_counts.len() != m.vertices.len()
                || param_counts.iter().sum::<usize>() != param_values.len()
            {
                return Err(fmt(format!(
                    "the vertices' param_count add up to {}, element param has {} values",
                    param_counts.iter().sum::<usize>(),
                    param_values.len()
                )));
            }
            // Each vertex's slice (the counts add up, checked above), copied in parallel: a
            // prolonged model has 650,000 of them.
            let mut start = Vec::with_capacity(param_counts.len());
            let mut at = 0;
            for &n in &param_counts {
                start.push(at);
                at += n;
            }
            m.vertices
                .par_iter_mut()
                .zip(start.par_iter().zip(&param_counts))
                .with_min_len(4096)
                .for_each(|(v, (&a, &n))| v.params = param_values[a..a + n].to_vec());
        }
        if !points.is_empty() {
            let want: usize = levels.iter().map(|&k| crate::lattice::point_count(k)).sum();
            if !detail.is_empty() || points.len() != want {
                return Err(fmt(format!(
                    "face_alpha: the levels want {want} lattice points, element \
                     face_alpha_point has {}",
                    points.len()
                )));
            }
            detail = points;
        }
        if face_alpha_seen {
            m.face_alpha = Some(
                crate::lattice::FaceAlpha::new(levels, detail)
                    .map_err(|e| fmt(format!("face_alpha: {e}")))?,
            );
        }
        m.check().map_err(|e| fmt(e.to_string()))?;
        Ok(m)
    }
}

/// Bytes of a vertex record and a face record in the current version ([`Layout::Rows`]).
const VERTEX_RECORD: usize = 6 * 8 + 3 * 4 + 1 + 4 + 1 + 1 + 2 + 2 * 4;
const FACE_RECORD: usize = 1 + 3 * 4;

/// Where the encoder puts a record's bytes: the file's buffer, or a record's slot.
trait Sink {
    fn put(&mut self, bytes: &[u8]);
}

impl Sink for Vec<u8> {
    fn put(&mut self, bytes: &[u8]) {
        self.extend_from_slice(bytes);
    }
}

/// Bytes written into a slot of known size from its start (a record of [`Layout::Rows`]).
struct SliceSink<'a>(&'a mut [u8], usize);

impl Sink for SliceSink<'_> {
    fn put(&mut self, bytes: &[u8]) {
        // The slot is the record's size (the constants above, tested by the round trips).
        self.0[self.1..self.1 + bytes.len()].copy_from_slice(bytes);
        self.1 += bytes.len();
    }
}

/// Whether the file at `path` holds exactly `bytes`, read in blocks (a prolonged model is
/// 100 MB: read whole, it was one more buffer of that size to allocate and fault in).
fn same_bytes(path: &Path, bytes: &[u8]) -> std::io::Result<bool> {
    use std::io::Read;
    let mut f = std::fs::File::open(path)?;
    if f.metadata()?.len() != bytes.len() as u64 {
        return Ok(false);
    }
    let mut block = vec![0u8; 1 << 20];
    let mut at = 0;
    loop {
        let n = f.read(&mut block)?;
        if n == 0 {
            return Ok(at == bytes.len());
        }
        if bytes.get(at..at + n) != Some(&block[..n]) {
            return Ok(false);
        }
        at += n;
    }
}

/// How variable-length data is laid out in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Layout {
    /// Version 6: every element's rows have one size; parameters in element `param`, lattice
    /// detail in element `face_alpha_point`.
    Rows,
    /// Version 5: parameters as a list in the vertex element, detail as lists in `face_alpha`.
    #[cfg_attr(not(test), allow(dead_code))]
    Lists,
}

struct Prop {
    name: String,
    count: Option<Ty>,
    ty: Ty,
}

/// The properties the reader knows. Each element's columns are looked up by name once
/// (`COLS`), and rows are read by column.
#[derive(Clone, Copy)]
enum Col {
    X,
    Y,
    Z,
    Nx,
    Ny,
    Nz,
    Status,
    Params,
    ParamCount,
    Terms,
    Segments,
    AlphaR,
    AlphaG,
    AlphaB,
    LogE,
    RMin,
    RMax,
    Value,
    DetailR,
    DetailG,
    DetailB,
    Level,
    VertexIndices,
}

/// Each [`Col`] with its PLY property name, in the enum's order.
const COLS: [(Col, &str); 23] = [
    (Col::X, "x"),
    (Col::Y, "y"),
    (Col::Z, "z"),
    (Col::Nx, "nx"),
    (Col::Ny, "ny"),
    (Col::Nz, "nz"),
    (Col::Status, "status"),
    (Col::Params, "params"),
    (Col::ParamCount, "param_count"),
    (Col::Terms, "terms"),
    (Col::Segments, "segments"),
    (Col::AlphaR, "alpha_r"),
    (Col::AlphaG, "alpha_g"),
    (Col::AlphaB, "alpha_b"),
    (Col::LogE, "log_e"),
    (Col::RMin, "r_min"),
    (Col::RMax, "r_max"),
    (Col::Value, "value"),
    (Col::DetailR, "detail_r"),
    (Col::DetailG, "detail_g"),
    (Col::DetailB, "detail_b"),
    (Col::Level, "level"),
    (Col::VertexIndices, "vertex_indices"),
];

impl Col {
    fn name(self) -> &'static str {
        COLS[self as usize].1
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Ty {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

fn ty(s: &str) -> Option<Ty> {
    Some(match s {
        "char" | "int8" => Ty::I8,
        "uchar" | "uint8" => Ty::U8,
        "short" | "int16" => Ty::I16,
        "ushort" | "uint16" => Ty::U16,
        "int" | "int32" => Ty::I32,
        "uint" | "uint32" => Ty::U32,
        "float" | "float32" => Ty::F32,
        "double" | "float64" => Ty::F64,
        _ => return None,
    })
}

struct Cursor<'a> {
    b: &'a [u8],
    at: usize,
}

impl Cursor<'_> {
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let s = self.b.get(self.at..self.at + N)?;
        self.at += N;
        s.try_into().ok()
    }
    fn read(&mut self, t: Ty) -> Option<f64> {
        Some(match t {
            Ty::I8 => i8::from_le_bytes(self.take()?) as f64,
            Ty::U8 => u8::from_le_bytes(self.take()?) as f64,
            Ty::I16 => i16::from_le_bytes(self.take()?) as f64,
            Ty::U16 => u16::from_le_bytes(self.take()?) as f64,
            Ty::I32 => i32::from_le_bytes(self.take()?) as f64,
            Ty::U32 => u32::from_le_bytes(self.take()?) as f64,
            Ty::F32 => f32::from_le_bytes(self.take()?) as f64,
            Ty::F64 => f64::from_le_bytes(self.take()?),
        })
    }
}

/// The current writer's elements read as fixed records: [`ModelFile::parse`]'s columns, without
/// a lookup and a conversion through f64 per value. A prolonged model of 650,000 vertices is
/// 100 MB and was read at 160 MB/s by the columns alone: every fit writes and reads
/// back its model, and `evaluate` and `render` read it. The same values as the columns read
/// (test `the_record_reader_reads_as_the_column_reader`).
mod rows {
    use super::{
        Cursor, ModelFile, Prop, Ty, VERTEX_RECORD, VertexModel, VertexStatus, log_e_read,
    };

    /// Why a record could not be read.
    pub(super) enum RowError {
        Truncated,
        Status(u8),
        Index,
        Polygon,
    }

    impl RowError {
        pub(super) fn message(&self, element: &str) -> String {
            match self {
                RowError::Truncated => "truncated data".into(),
                RowError::Status(s) => format!("unknown vertex status {s}"),
                RowError::Index => format!("{element}: a vertex index out of range"),
                RowError::Polygon => "face_alpha needs a triangle mesh".into(),
            }
        }
    }

    /// The vertex record of the current version: names and types in order.
    const VERTEX: [(&str, Ty); 16] = [
        ("x", Ty::F64),
        ("y", Ty::F64),
        ("z", Ty::F64),
        ("nx", Ty::F64),
        ("ny", Ty::F64),
        ("nz", Ty::F64),
        ("alpha_r", Ty::F32),
        ("alpha_g", Ty::F32),
        ("alpha_b", Ty::F32),
        ("status", Ty::U8),
        ("log_e", Ty::F32),
        ("terms", Ty::U8),
        ("segments", Ty::U8),
        ("param_count", Ty::U16),
        ("r_min", Ty::F32),
        ("r_max", Ty::F32),
    ];

    fn is(props: &[Prop], want: &[(&str, Ty)]) -> bool {
        props.len() == want.len()
            && props
                .iter()
                .zip(want)
                .all(|(p, (n, t))| p.count.is_none() && p.name == *n && p.ty == *t)
    }

    fn f64_at(r: &[u8], at: usize) -> f64 {
        f64::from_le_bytes(r[at..at + 8].try_into().unwrap_or_default())
    }

    fn f32_at(r: &[u8], at: usize) -> f32 {
        f32::from_le_bytes(r[at..at + 4].try_into().unwrap_or_default())
    }

    /// Where the records go: the model, and the vectors of parameter counts and values the
    /// columns fill too; whether faces must be triangles (the file has a face lattice).
    pub(super) struct Into<'a> {
        pub m: &'a mut ModelFile,
        pub param_counts: &'a mut Vec<usize>,
        pub param_values: &'a mut Vec<f64>,
        pub triangles_only: bool,
    }

    /// Reads `count` records of element `name` if its properties are the current writer's;
    /// `Ok(false)` and nothing read otherwise.
    pub(super) fn read(
        name: &str,
        count: usize,
        props: &[Prop],
        cur: &mut Cursor,
        into: Into,
    ) -> Result<bool, RowError> {
        let Into {
            m,
            param_counts,
            param_values,
            triangles_only,
        } = into;
        match name {
            "vertex" if is(props, &VERTEX) => {
                let body = take(cur, count, VERTEX_RECORD)?;
                m.positions.reserve(count);
                m.normals.reserve(count);
                m.vertices.reserve(count);
                param_counts.reserve(count);
                for r in body.chunks_exact(VERTEX_RECORD) {
                    m.positions
                        .push([f64_at(r, 0), f64_at(r, 8), f64_at(r, 16)]);
                    m.normals
                        .push([f64_at(r, 24), f64_at(r, 32), f64_at(r, 40)]);
                    let status = VertexStatus::from_byte(r[60]).ok_or(RowError::Status(r[60]))?;
                    param_counts.push(u16::from_le_bytes([r[67], r[68]]) as usize);
                    m.vertices.push(VertexModel {
                        alpha: [f32_at(r, 48), f32_at(r, 52), f32_at(r, 56)],
                        status,
                        log_e: log_e_read(f32_at(r, 61)),
                        terms: r[65],
                        segments: r[66],
                        params: Vec::new(),
                        r_range: [f32_at(r, 69), f32_at(r, 73)],
                    });
                }
                Ok(true)
            }
            "param" if is(props, &[("value", Ty::F64)]) => {
                let body = take(cur, count, 8)?;
                param_values.extend(body.chunks_exact(8).map(|r| f64_at(r, 0)));
                Ok(true)
            }
            "face"
                if props.len() == 1
                    && props[0].name == "vertex_indices"
                    && props[0].count == Some(Ty::U8)
                    && props[0].ty == Ty::I32 =>
            {
                m.triangles.reserve(count);
                let mut idx = Vec::new();
                for _ in 0..count {
                    let n = usize::from(u8::from_le_bytes(cur.take().ok_or(RowError::Truncated)?));
                    if n != 3 && triangles_only {
                        return Err(RowError::Polygon);
                    }
                    idx.clear();
                    for _ in 0..n {
                        let i = i32::from_le_bytes(cur.take().ok_or(RowError::Truncated)?);
                        idx.push(u32::try_from(i).map_err(|_| RowError::Index)?);
                    }
                    // Polygons as a fan, as the columns read them.
                    for k in 1..n.saturating_sub(1) {
                        m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                    }
                }
                Ok(true)
            }
            _ => Ok(false),
        }
    }

    /// The next `count` records of `size` bytes.
    fn take<'a>(cur: &mut Cursor<'a>, count: usize, size: usize) -> Result<&'a [u8], RowError> {
        let end = count
            .checked_mul(size)
            .and_then(|n| n.checked_add(cur.at))
            .filter(|&e| e <= cur.b.len())
            .ok_or(RowError::Truncated)?;
        let body = &cur.b[cur.at..end];
        cur.at = end;
        Ok(body)
    }
}

/// Parameters of a colour model in the file's order (`docs/model-format.md`), its term count n
/// and segment count m. Segments must share one term count.
pub fn params_of(
    model: &crate::model::ColourModel,
) -> Result<(Vec<f64>, usize, usize), ModelFileError> {
    use crate::model::{Anisotropic, ColourModel};
    fn push(
        out: &mut Vec<f64>,
        a: &Anisotropic,
        n: &mut Option<usize>,
    ) -> Result<(), ModelFileError> {
        for seg in &a.segments {
            if n.is_some_and(|n| n != seg.n()) {
                return Err(ModelFileError::Invalid(
                    "segments and channels of a vertex must share one term count".into(),
                ));
            }
            *n = Some(seg.n());
            for t in &seg.terms {
                out.push(t.c);
                out.push(t.d);
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    let mut n = None;
    let m = match model {
        ColourModel::Shared { falloff, s_g, s_b } => {
            out.push(*s_g);
            out.push(*s_b);
            push(&mut out, falloff, &mut n)?;
            falloff.m()
        }
        ColourModel::PerChannel { channels } => {
            for ch in channels {
                if ch.m() != channels[0].m() {
                    return Err(ModelFileError::Invalid(
                        "channels differ in segments".into(),
                    ));
                }
                push(&mut out, ch, &mut n)?;
            }
            channels[0].m()
        }
    };
    Ok((out, n.unwrap_or(0), m))
}

/// The colour model of a vertex's parameters (validated: c > 0, d < 0, finite, scales > 0). The
/// vertex's m (1..=`shape.segments`) follows from the number of parameters and `terms`.
pub fn model_of(
    shape: &ModelShape,
    terms: usize,
    params: &[f64],
) -> Result<crate::model::ColourModel, crate::model::ModelError> {
    use crate::model::{Anisotropic, ColourModel, ExpSum, ModelError, Term};
    let segments = (1..=shape.segments).find(|&m| shape.param_count_m(terms, m) == params.len());
    let (Some(segments), true) = (segments, terms > 0) else {
        return Err(ModelError::TermCount {
            got: terms,
            max: crate::model::MAX_TERMS,
        });
    };
    let aniso = |p: &[f64]| -> Result<Anisotropic, ModelError> {
        let segments = p
            .chunks_exact(2 * terms)
            .map(|s| {
                ExpSum::new(
                    s.chunks_exact(2)
                        .map(|t| Term { c: t[0], d: t[1] })
                        .collect(),
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        let a = Anisotropic { segments };
        a.validate()?;
        Ok(a)
    };
    let m = match shape.colour {
        ColourMode::Shared => ColourModel::Shared {
            falloff: aniso(&params[2..])?,
            s_g: params[0],
            s_b: params[1],
        },
        ColourMode::PerChannel => {
            let k = 2 * terms * segments;
            ColourModel::PerChannel {
                channels: [
                    aniso(&params[..k])?,
                    aniso(&params[k..2 * k])?,
                    aniso(&params[2 * k..])?,
                ],
            }
        }
    };
    m.validate()?;
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The offset of the first byte after `end_header\n`.
    fn header_end(bytes: &[u8]) -> usize {
        bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .expect("a PLY header")
            + 11
    }

    fn sample() -> ModelFile {
        let shape = ModelShape {
            terms: 3,
            segments: 1,
            colour: ColourMode::Shared,
        };
        let v = |status, terms: u8| VertexModel {
            alpha: [1.0, 0.9, 1.1],
            status,
            log_e: if status == VertexStatus::Fitted {
                0.02
            } else {
                f32::NAN
            },
            terms,
            segments: if status == VertexStatus::NoModel {
                0
            } else {
                1
            },
            params: if status == VertexStatus::NoModel {
                vec![]
            } else {
                (0..shape.param_count(terms as usize))
                    .map(|k| k as f64 * 0.5 - 1.0)
                    .collect()
            },
            r_range: [0.7, 12.5],
        };
        ModelFile {
            shape,
            positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            normals: vec![[0.0, 0.0, 1.0]; 3],
            triangles: vec![[0, 1, 2]],
            vertices: vec![
                v(VertexStatus::Fitted, 3),
                v(VertexStatus::Interpolated, 2),
                v(VertexStatus::NoModel, 0),
            ],
            baseline: None,
            frame: FrameRule::MinimalRotation,
            face_alpha: None,
            fitted_with: None,
            fitted_frames: None,
        }
    }

    /// The rules a model was fitted with round-trip through `comment fitted`; a file without
    /// the line (every file before it) reads as none, and a reader skips keys it does not know.
    #[test]
    fn the_fitted_frames_round_trip_over_several_lines_and_are_optional() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("m.ply");
        let mut m = sample();
        m.write(&p).unwrap();
        assert_eq!(ModelFile::read(&p).unwrap().fitted_frames, None);
        // Every third frame of 3,000: a thousand holes, several header lines.
        let frames: Vec<usize> = (0..3000).filter(|f| f % 3 != 1).collect();
        m.fitted_frames = Some(frames.clone());
        m.write(&p).unwrap();
        let text = std::fs::read(&p).unwrap();
        let header = String::from_utf8_lossy(&text[..header_end(&text)]).to_string();
        assert!(
            header.matches("comment fitted_frames").count() > 3,
            "{header}"
        );
        assert!(header.lines().all(|l| l.len() <= 1024));
        assert_eq!(ModelFile::read(&p).unwrap().fitted_frames, Some(frames));
        m.fitted_frames = Some(vec![]);
        m.write(&p).unwrap();
        assert_eq!(ModelFile::read(&p).unwrap().fitted_frames, Some(vec![]));
        m.fitted_frames = Some(vec![0, 1, 2, 3, 7, 9, 10]);
        m.write(&p).unwrap();
        let text = std::fs::read(&p).unwrap();
        let header = String::from_utf8_lossy(&text[..header_end(&text)]).to_string();
        assert!(
            header.contains("comment fitted_frames 0-3,7,9-10\n"),
            "{header}"
        );
        // A range no scan holds is refused, not allocated.
        let bad = header.replace("0-3,7,9-10", "0-99999999999");
        let mut bytes = bad.into_bytes();
        bytes.extend_from_slice(&text[header_end(&text)..]);
        std::fs::write(&p, bytes).unwrap();
        assert!(ModelFile::read(&p).is_err());
    }

    #[test]
    fn the_fit_record_round_trips_and_is_optional() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let mut m = sample();
        m.write(&p).unwrap();
        assert_eq!(ModelFile::read(&p).unwrap().fitted_with, None);
        let rec = FitRecord {
            noise_floor: 2.5e-5,
            exclusion_radius_mm: 0.75,
            cos_min: 0.5,
            coverage: true,
            laser_tolerance_mm: 2.0,
            spot_cos_min: 0.1,
        };
        m.fitted_with = Some(rec);
        m.write(&p).unwrap();
        assert_eq!(ModelFile::read(&p).unwrap().fitted_with, Some(rec));
        let words = ["future_key=3", "noise_floor=1", "exclusion_radius_mm=0.5"];
        let mut more: Vec<&str> = words.to_vec();
        more.extend([
            "cos_min=0.5",
            "coverage=0",
            "laser_tolerance_mm=2",
            "spot_cos_min=0.2",
        ]);
        let r = FitRecord::parse(&more).unwrap();
        assert_eq!(
            (r.noise_floor, r.coverage, r.spot_cos_min),
            (1.0, false, 0.2)
        );
        assert_eq!(FitRecord::parse(&words), None);
    }

    /// A face lattice of `level` on the sample's one triangle, with detail at every non-corner
    /// point.
    fn lattice(level: u8) -> crate::lattice::FaceAlpha {
        use crate::lattice::{is_corner, points};
        let d = points(level)
            .map(|(n, i, j)| {
                if is_corner(level, i, j) {
                    [0.0; 3]
                } else {
                    let x = n as f32 * 0.01;
                    [x, -x, 0.5 * x]
                }
            })
            .collect();
        crate::lattice::FaceAlpha::new(vec![level], d).unwrap()
    }

    /// alpha finer than the mesh (format 5): the finest lattice round-trips exactly, alpha at a
    /// corner is the vertex's and between lattice points it carries the detail; a version 4
    /// file (no element) reads with alpha at the vertices only; a damaged lattice is refused.
    #[test]
    fn face_alpha_round_trips_and_version_4_files_still_read() {
        let mut m = sample();
        m.face_alpha = Some(lattice(crate::lattice::MAX_LEVEL));
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("fa.ply");
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.face_alpha, m.face_alpha);
        assert_eq!(back.to_bytes().unwrap(), m.to_bytes().unwrap());
        assert_eq!(
            back.alpha_at(0, [1.0, 0.0, 0.0]),
            [1.0, 0.9f32 as f64, 1.1f32 as f64]
        );
        let k = crate::lattice::MAX_LEVEL;
        let mid = crate::lattice::point_bary(k, 3, 2);
        let d =
            back.face_alpha.as_ref().unwrap().face_detail(0)[crate::lattice::point_index(k, 3, 2)];
        let a = back.alpha_at(0, mid);
        assert!((a[0] - (d[0] as f64).exp()).abs() < 1e-6, "{a:?} {d:?}");
        assert!((a[1] - 0.9f32 as f64 * (d[1] as f64).exp()).abs() < 1e-6);

        // Version 5 (the detail as lists inside `face_alpha`) reads to the same lattice.
        let p5 = dir.path().join("v5.ply");
        std::fs::write(&p5, m.encode(Layout::Lists).unwrap()).unwrap();
        let back5 = ModelFile::read(&p5).unwrap();
        assert_eq!(back5.face_alpha, m.face_alpha);
        assert_eq!(back5.to_bytes().unwrap(), m.to_bytes().unwrap());

        // Version 4: version 5's bytes without the element and with the old magic.
        let mut v4 = sample();
        v4.face_alpha = None;
        let mut old = v4.encode(Layout::Lists).unwrap();
        let at = old
            .windows(15)
            .position(|w| w == b"subsurf-model/5")
            .unwrap();
        old[at + 14] = b'4';
        let p4 = dir.path().join("v4.ply");
        std::fs::write(&p4, &old).unwrap();
        let back4 = ModelFile::read(&p4).unwrap();
        assert_eq!(back4.face_alpha, None);
        assert_eq!(
            back4.alpha_at(0, [0.2, 0.3, 0.5]),
            v4.alpha_at(0, [0.2, 0.3, 0.5])
        );

        // A lattice for another mesh is refused before anything is written.
        let mut wrong = sample();
        wrong.face_alpha = Some(crate::lattice::FaceAlpha::flat(2));
        assert!(wrong.write(&dir.path().join("wrong.ply")).is_err());
        assert!(!dir.path().join("wrong.ply").exists());

        // A damaged level byte (0) is refused with a clear error.
        let mut bytes = std::fs::read(&p).unwrap();
        let header_end = header_end(&bytes);
        let face_alpha_at = bytes.len() - (1 + 3 * 4 * crate::lattice::point_count(k));
        assert!(face_alpha_at > header_end);
        assert_eq!(bytes[face_alpha_at], k);
        bytes[face_alpha_at] = 0;
        let bad = dir.path().join("bad.ply");
        std::fs::write(&bad, &bytes).unwrap();
        let e = ModelFile::read(&bad).unwrap_err().to_string();
        assert!(e.contains("face_alpha"), "{e}");
    }

    /// The largest model the CLI allows (per-channel colour, n = MAX_TERMS, m = MAX_SEGMENTS)
    /// writes, reads back and compares equal (version 1 wrapped its 8-bit count here).
    #[test]
    fn the_largest_model_the_cli_allows_round_trips() {
        let shape = ModelShape {
            terms: crate::model::MAX_TERMS,
            segments: crate::pipeline::MAX_SEGMENTS,
            colour: ColourMode::PerChannel,
        };
        let count = shape.param_count(shape.terms);
        assert!(count > 255, "{count}");
        let mut m = sample();
        m.shape = shape;
        for v in &mut m.vertices {
            if v.status != VertexStatus::NoModel {
                v.terms = shape.terms as u8;
                v.segments = shape.segments as u8;
                v.params = (0..count).map(|k| (k as f64 + 1.0) * 0.25).collect();
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("big.ply");
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.vertices[0].params, m.vertices[0].params);
        assert_eq!(back.to_bytes().unwrap(), m.to_bytes().unwrap());
        // Every number in the file is finite: the interpolated vertex's log E reads back as NaN
        // ("none") from the written -1.
        assert!(back.vertices[1].log_e.is_nan());
        let bytes = std::fs::read(&p).unwrap();
        let header_end = header_end(&bytes);
        let vertex_bytes = &bytes[header_end..];
        let log_e_at = 6 * 8 + 3 * 4 + 1;
        let le = f32::from_le_bytes(vertex_bytes[log_e_at..log_e_at + 4].try_into().unwrap());
        assert_eq!(le, 0.02);
        // Nothing but the model is left in the folder (the read-back used a temporary file).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// Version 3: each vertex has its own m (at most the header's), written, read back and
    /// turned into the model it describes; a vertex whose count disagrees with its m is refused.
    #[test]
    fn per_vertex_segments_round_trip() {
        let mut m = sample();
        m.shape.segments = 4;
        let (a, b) = m.vertices[..2].split_at_mut(1);
        let (fitted, interp) = (&mut a[0], &mut b[0]);
        fitted.segments = 4;
        fitted.params = (0..m.shape.param_count_m(3, 4))
            .map(|k| {
                if k < 2 {
                    1.0
                } else if k % 2 == 0 {
                    0.5
                } else {
                    -0.5 - k as f64
                }
            })
            .collect();
        interp.segments = 1;
        interp.params = vec![1.0, 1.0, 0.3, -0.2, 0.7, -1.0];
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.to_bytes().unwrap(), m.to_bytes().unwrap());
        for v in &back.vertices[..2] {
            let model = model_of(&back.shape, v.terms as usize, &v.params).unwrap();
            let (_, n, segs) = params_of(&model).unwrap();
            assert_eq!((n, segs), (v.terms as usize, v.segments as usize));
        }
        let mut bad = m.clone();
        bad.vertices[1].segments = 2;
        assert!(bad.check().is_err());
        bad.vertices[1].segments = 8;
        bad.vertices[1].params = vec![1.0; bad.shape.param_count_m(2, 8)];
        assert!(bad.check().is_err(), "more segments than the header's");
    }

    /// Version 6: every element's rows have one size (the only list is the face's
    /// `vertex_indices`, three for every triangle), so readers of fixed-size records (trimesh,
    /// Open3D) take the file; the parameters are in element `param` in vertex order, and a count
    /// that disagrees with the values is refused.
    #[test]
    fn version_6_rows_have_one_size_and_version_5_files_still_read() {
        let mut m = sample();
        m.face_alpha = Some(lattice(3));
        let bytes = m.to_bytes().unwrap();
        let end = header_end(&bytes);
        let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
        let lists: Vec<&str> = header
            .lines()
            .filter(|l| l.starts_with("property list"))
            .collect();
        assert_eq!(
            lists,
            ["property list uchar int vertex_indices"],
            "{header}"
        );
        let total: usize = m.vertices.iter().map(|v| v.params.len()).sum();
        assert!(header.contains(&format!("element param {total}\nproperty double value\n")));
        // The body is exactly the rows the header describes.
        let vertex_row = 6 * 8 + 3 * 4 + 1 + 4 + 1 + 1 + 2 + 2 * 4;
        let face_row = 1 + 3 * 4;
        let points = crate::lattice::point_count(3);
        assert_eq!(
            bytes.len() - end,
            3 * vertex_row + face_row + 8 * total + 1 + 12 * points
        );
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        for (a, b) in back.vertices.iter().zip(&m.vertices) {
            assert_eq!(a.params, b.params);
        }
        assert_eq!(back.face_alpha, m.face_alpha);
        // Version 5's layout (lists inside the vertex element) reads to the same model.
        std::fs::write(&p, m.encode(Layout::Lists).unwrap()).unwrap();
        let v5 = ModelFile::read(&p).unwrap();
        assert_eq!(v5.to_bytes().unwrap(), bytes);
        // A vertex count that does not match the values: refused, not shifted.
        let mut bad = bytes.clone();
        let count_at = end + 6 * 8 + 3 * 4 + 1 + 4 + 1 + 1;
        bad[count_at] += 1;
        std::fs::write(&p, &bad).unwrap();
        let e = ModelFile::read(&p).unwrap_err().to_string();
        assert!(e.contains("param"), "{e}");
    }

    /// Files of version 1 (`uchar` counts) still read.
    #[test]
    fn version_1_files_still_read() {
        let m = sample();
        let mut out = Vec::new();
        out.extend_from_slice(
            b"ply\nformat binary_little_endian 1.0\ncomment subsurf-model/1\ncomment terms 3\n\
              comment segments 1\ncomment colour shared\nelement vertex 3\n\
              property double x\nproperty double y\nproperty double z\n\
              property double nx\nproperty double ny\nproperty double nz\n\
              property float alpha_r\nproperty float alpha_g\nproperty float alpha_b\n\
              property uchar status\nproperty float log_e\nproperty uchar terms\n\
              property list uchar double params\n\
              property float r_min\nproperty float r_max\nelement face 1\n\
              property list uchar int vertex_indices\nend_header\n",
        );
        for (i, v) in m.vertices.iter().enumerate() {
            for x in m.positions[i].iter().chain(&m.normals[i]) {
                out.extend_from_slice(&x.to_le_bytes());
            }
            for a in v.alpha {
                out.extend_from_slice(&a.to_le_bytes());
            }
            out.push(v.status as u8);
            out.extend_from_slice(&v.log_e.to_le_bytes());
            out.push(v.terms);
            out.push(v.params.len() as u8);
            for x in &v.params {
                out.extend_from_slice(&x.to_le_bytes());
            }
            for r in v.r_range {
                out.extend_from_slice(&r.to_le_bytes());
            }
        }
        out.push(3);
        for i in [0i32, 1, 2] {
            out.extend_from_slice(&i.to_le_bytes());
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v1.ply");
        std::fs::write(&p, &out).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.vertices.len(), 3);
        for (a, b) in back.vertices.iter().zip(&m.vertices) {
            assert_eq!(a.params, b.params);
            assert_eq!(a.status, b.status);
        }
        assert_eq!(back.frame, FrameRule::ReferenceAxis);
    }

    /// Version 4 records the frame rule; a version-3 file (no `comment frame`) reads with the
    /// rule it was fitted in, so its segments point where they did: at a normal on the old
    /// rule's seam side its frame is the old one, not the new.
    #[test]
    fn the_frame_rule_round_trips_and_version_3_files_keep_theirs() {
        use crate::model::TangentFrame;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let m = sample();
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.frame, FrameRule::MinimalRotation);
        let bytes = std::fs::read(&p).unwrap();
        let end = header_end(&bytes);
        let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
        assert!(header.contains(&format!("comment {MODEL_FORMAT}\n")));
        assert!(header.contains("comment frame minimal-rotation\n"));
        // Version 3: version 5's layout without the frame comment.
        let bytes = m.encode(Layout::Lists).unwrap();
        let end = header_end(&bytes);
        let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
        let old_header = header
            .replace("comment subsurf-model/5\n", "comment subsurf-model/3\n")
            .replace("comment frame minimal-rotation\n", "");
        let mut old = old_header.into_bytes();
        old.extend_from_slice(&bytes[end..]);
        std::fs::write(&p, &old).unwrap();
        let v3 = ModelFile::read(&p).unwrap();
        assert_eq!(v3.frame, FrameRule::ReferenceAxis);
        for (a, b) in v3.vertices.iter().zip(&back.vertices) {
            assert_eq!(
                (&a.params, a.status, a.r_range),
                (&b.params, b.status, b.r_range)
            );
        }
        let n = [0.95, 0.1, 0.3];
        assert_eq!(
            v3.frame_at(n).unwrap(),
            TangentFrame::with_rule(FrameRule::ReferenceAxis, n).unwrap()
        );
        assert_eq!(
            back.frame_at(n).unwrap(),
            TangentFrame::from_normal(n).unwrap()
        );
        assert_ne!(v3.frame_at(n), back.frame_at(n));
        // An unknown rule is refused, not guessed.
        let bad = String::from_utf8(bytes[..end].to_vec())
            .unwrap()
            .replace("minimal-rotation", "sideways");
        let mut b = bad.into_bytes();
        b.extend_from_slice(&bytes[end..]);
        std::fs::write(&p, &b).unwrap();
        assert!(ModelFile::read(&p).is_err());
    }

    #[test]
    fn the_baseline_round_trips_in_the_header() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let mut m = sample();
        m.baseline = Some(BaselineParams {
            terms: 2,
            params: vec![0.9, 0.8, 0.123456789012345, -0.1, 1.0 / 3.0, -2.5],
            r_range: [0.5, 21.25],
        });
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.baseline, m.baseline);
        // Files without one read as before.
        m.baseline = None;
        m.write(&p).unwrap();
        assert_eq!(ModelFile::read(&p).unwrap().baseline, None);
    }

    #[test]
    fn the_reader_columns_name_their_properties_in_order() {
        for (i, (c, name)) in COLS.iter().enumerate() {
            assert_eq!(*c as usize, i, "{name}");
            assert_eq!(c.name(), *name);
        }
    }

    #[test]
    fn round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let m = sample();
        m.write(&p).unwrap();
        let back = ModelFile::read(&p).unwrap();
        assert_eq!(back.positions, m.positions);
        assert_eq!(back.triangles, m.triangles);
        for (a, b) in back.vertices.iter().zip(&m.vertices) {
            assert_eq!(a.params, b.params);
            assert_eq!(a.status, b.status);
            assert_eq!(a.terms, b.terms);
            assert_eq!(a.r_range, b.r_range);
        }
    }

    #[test]
    fn files_without_a_sampled_range_read_as_unknown() {
        // A file written before `r_min`/`r_max` existed: the same layout without them.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let m = sample();
        let bytes = m.encode(Layout::Lists).unwrap();
        let end = header_end(&bytes);
        let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
        let old_header = header.replace("property float r_min\nproperty float r_max\n", "");
        let mut old = old_header.into_bytes();
        let mut at = end;
        for v in &m.vertices {
            let len = 6 * 8 + 3 * 4 + 1 + 4 + 1 + 1 + 2 + 8 * v.params.len();
            old.extend_from_slice(&bytes[at..at + len]);
            at += len + 8;
        }
        old.extend_from_slice(&bytes[at..]);
        std::fs::write(&p, &old).unwrap();
        let back = ModelFile::read(&p).unwrap();
        for (a, b) in back.vertices.iter().zip(&m.vertices) {
            assert_eq!(a.params, b.params);
            assert_eq!(a.r_range, NO_RANGE);
        }
    }

    /// The read-back compares the file block by block: equal bytes over several blocks, one
    /// changed byte in the last block, a shorter and a longer file.
    #[test]
    fn the_read_back_finds_any_difference() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b");
        let bytes: Vec<u8> = (0..(5 << 19) + 7).map(|i| (i * 31 % 251) as u8).collect();
        std::fs::write(&p, &bytes).unwrap();
        assert!(same_bytes(&p, &bytes).unwrap());
        let mut other = bytes.clone();
        *other.last_mut().unwrap() ^= 1;
        assert!(!same_bytes(&p, &other).unwrap());
        assert!(!same_bytes(&p, &bytes[..bytes.len() - 1]).unwrap());
        other = bytes.clone();
        other.push(0);
        assert!(!same_bytes(&p, &other).unwrap());
    }

    #[test]
    fn the_record_reader_reads_as_the_column_reader() {
        let read = |bytes: &[u8], records| {
            ModelFile::parse_with(&mut &bytes[..], bytes.len(), Path::new("m.ply"), records)
        };
        let mut with_lattice = sample();
        with_lattice.face_alpha = Some(lattice(3));
        for m in [sample(), with_lattice] {
            let bytes = m.to_bytes().unwrap();
            let (records, columns) = (read(&bytes, true).unwrap(), read(&bytes, false).unwrap());
            assert_eq!(records.to_bytes().unwrap(), bytes);
            assert_eq!(columns.to_bytes().unwrap(), bytes);
            assert_eq!(records.vertices.len(), 3);
            assert!(records.vertices[1].log_e.is_nan() && records.vertices[0].log_e == 0.02);
            // Damaged records are refused by both: a status no version writes, a negative
            // vertex index, a cut inside the vertices, faces and parameters.
            let start = header_end(&bytes);
            let mut bad_status = bytes.clone();
            bad_status[start + 60] = 7;
            let mut bad_index = bytes.clone();
            let face = start + 3 * 77;
            assert_eq!(bad_index[face], 3, "a face record");
            bad_index[face + 1..face + 5].copy_from_slice(&(-1i32).to_le_bytes());
            for (what, b) in [("status", &bad_status), ("index", &bad_index)] {
                let (r, c) = (read(b, true), read(b, false));
                assert!(r.is_err() && c.is_err(), "{what}: {r:?} / {c:?}");
            }
            for cut in [start + 100, face + 3, face + 14, bytes.len() - 1] {
                assert!(read(&bytes[..cut], true).is_err(), "cut {cut}");
                assert!(read(&bytes[..cut], false).is_err(), "cut {cut}");
            }
        }
    }

    #[test]
    fn non_finite_parameters_are_refused_and_damaged_files_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let mut m = sample();
        m.vertices[0].params[1] = f64::NAN;
        assert!(matches!(m.write(&p), Err(ModelFileError::Invalid(_))));
        let m = sample();
        m.write(&p).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        for cut in [0, 10, 200, bytes.len() - 3] {
            std::fs::write(&p, &bytes[..cut]).unwrap();
            assert!(ModelFile::read(&p).is_err(), "cut {cut}");
        }
    }
}
