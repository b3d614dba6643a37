//! The `alignment` record of `scan.json` (an extension of this project, `docs/scan-format.md`):
//! how `subsurf align` placed the user's mesh in the object frame, and how well the scan's own
//! laser spots agree with it. Written here, beside the other `scan.json` types, so there is one
//! type set for the file and one place that rewrites it.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{
    Dataset, DatasetError, Mesh, confined_path, load_obj, obj_bytes, writer::write_atomic,
};

/// A rotational symmetry of the aligned mesh that the scan cannot (and need not) resolve: every
/// pose it allows puts the same surface in the same place.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Symmetry {
    /// The surface is unchanged by rotations about the turntable axis (`+z` through the origin):
    /// by every angle (`fold` absent: a body of revolution, such as a torus lying on the
    /// platter) or by multiples of 360°/`fold`.
    TurntableAxis {
        /// `n` for an `n`-fold symmetry; absent for a continuous one.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        fold: Option<u32>,
    },
    /// Another motion leaves the surface unchanged (a sphere's rotations about its centre).
    Other {
        /// Which motion, in words.
        motion: String,
    },
    /// A finite set of rotations that is not only turns about the turntable axis leaves the
    /// surface unchanged: `poses` of them, the identity included (4 for an ellipsoid with three
    /// distinct axes: the identity and a half turn about each axis), each putting the same
    /// surface in the same place. Reported so a user is not told "2-fold" of an object the scan
    /// cannot tell apart in four poses.
    Rotations {
        /// How many poses put the same surface in the same place, the identity included.
        poses: u32,
        /// The rotations other than the identity (object frame).
        turns: Vec<Turn>,
    },
}

/// One rotation of a [`Symmetry::Rotations`]: `degrees` about the line along `axis` through
/// `through` (object frame, mm).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Turn {
    /// The angle, degrees (0..=180).
    pub degrees: f64,
    /// The unit axis.
    pub axis: [f64; 3],
    /// A point on the axis, mm.
    pub through: [f64; 3],
}

impl std::fmt::Display for Symmetry {
    /// The symmetry in words, for `subsurf align`'s report.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Symmetry::TurntableAxis { fold: None } => write!(
                f,
                "the surface is a body of revolution about the turntable axis; the scan cannot \
                 fix the angle about it, and every angle puts the same surface in the same place"
            ),
            Symmetry::TurntableAxis { fold: Some(k) } => write!(
                f,
                "{k}-fold about the turntable axis; the {k} poses put the same surface in the \
                 same place"
            ),
            Symmetry::Other { motion } => write!(
                f,
                "{motion} leaves the surface unchanged; the scan cannot fix it, and need not"
            ),
            Symmetry::Rotations { poses, turns } => {
                write!(
                    f,
                    "{poses} poses put the same surface in the same place (the scan cannot tell \
                     them apart, and need not): the found one"
                )?;
                for t in turns {
                    let [a, b, c] = t.axis;
                    let [x, y, z] = t.through;
                    write!(
                        f,
                        "; {:.0}° about ({a:.2}, {b:.2}, {c:.2}) through ({x:.2}, {y:.2}, {z:.2}) mm",
                        t.degrees
                    )?;
                }
                Ok(())
            }
        }
    }
}

/// What `subsurf align` found: the similarity transform from the source mesh's own frame to the
/// object frame, `p_object = scale · rotation · p_source + translation` (mm), and the residuals of
/// the laser spots it was estimated from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Alignment {
    /// The mesh as the user gave it (its own frame and units), relative to the dataset
    /// directory; `mesh` is the aligned copy written beside it.
    pub source_mesh: String,
    /// Uniform scale (1000 for a mesh in metres).
    pub scale: f64,
    /// Rotation, row-major 3 × 3, proper (determinant +1).
    pub rotation: [[f64; 3]; 3],
    /// Translation, mm.
    pub translation: [f64; 3],
    /// Frames whose laser spot gave a triangulated surface point (camera ray × laser ray).
    pub spots: usize,
    /// Of those, the points the pose was fitted to (the rest are outliers).
    pub inliers: usize,
    /// `inliers / spots`.
    pub inlier_share: f64,
    /// RMS distance of the inlier points from the aligned surface, mm.
    pub rms_mm: f64,
    /// The same RMS in pixels: each point's distance divided by the pixel footprint at it.
    pub rms_px: f64,
    /// The pose's standard error carried to the aligned mesh: RMS over its vertices of the
    /// displacement one standard deviation of the fitted transform gives, mm (directions of a
    /// symmetry left out).
    pub pose_sigma_mm: f64,
    /// How far inside the surface, along the laser ray, the camera saw the spots' centres, mm
    /// (estimated with the pose: a translucent object's spot glows from below its surface).
    #[serde(default)]
    pub spot_depth_mm: f64,
    /// A symmetry of the surface the scan cannot resolve, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub symmetry: Option<Symmetry>,
}

impl Alignment {
    /// Checks the numbers (finite, positive scale, a rotation matrix) and the source path.
    pub fn validate(&self) -> Result<(), DatasetError> {
        let bad = |m: &str| Err(DatasetError::Invalid(format!("alignment: {m}")));
        confined_path(Path::new("."), &self.source_mesh)?;
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return bad("scale must be finite and positive");
        }
        let r = &self.rotation;
        if !r
            .iter()
            .flatten()
            .chain(&self.translation)
            .chain([&self.spot_depth_mm])
            .all(|x| x.is_finite())
        {
            return bad("rotation and translation must be finite");
        }
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
                if (d - f64::from(u8::from(i == j))).abs() > 1e-6 {
                    return bad("rotation is not orthonormal");
                }
            }
        }
        let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
            - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
        if det < 0.0 {
            return bad("rotation is a reflection");
        }
        for (k, v) in [
            ("inlier_share", self.inlier_share),
            ("rms_mm", self.rms_mm),
            ("rms_px", self.rms_px),
            ("pose_sigma_mm", self.pose_sigma_mm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(&format!("{k} must be finite and >= 0"));
            }
        }
        Ok(())
    }

    /// `p` of the source mesh in the object frame.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        std::array::from_fn(|i| {
            self.scale * (r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2]) + self.translation[i]
        })
    }
}

/// The file name of the aligned copy of `source` (relative): `dir/name.obj` →
/// `dir/name.aligned.obj`.
pub fn aligned_name(source: &str) -> String {
    let (dir, file) = match source.rfind('/') {
        Some(k) => (&source[..=k], &source[k + 1..]),
        None => ("", source),
    };
    let stem = file.strip_suffix(".obj").unwrap_or(file);
    format!("{dir}{stem}.aligned.obj")
}

impl Dataset {
    /// The mesh as the user gave it: the recorded `alignment.source_mesh` once the dataset has
    /// been aligned (so aligning again starts from the same file), else `mesh` itself.
    pub fn source_mesh(&self) -> Result<(String, Mesh), DatasetError> {
        match &self.spec.alignment {
            None => Ok((self.spec.mesh.clone(), self.mesh.clone())),
            Some(a) => {
                let p = confined_path(&self.dir, &a.source_mesh)?;
                if !p.is_file() {
                    return Err(DatasetError::Missing(p));
                }
                Ok((a.source_mesh.clone(), load_obj(&p)?.0))
            }
        }
    }

    /// Writes `aligned` (the source mesh moved by `alignment`, same vertices in the same order)
    /// beside the source mesh through the one OBJ writer, then points `scan.json`'s `mesh` at it
    /// and records `alignment`. Only those two keys change: every other key of the file, ours or
    /// another program's, is kept (object keys come out sorted). Both files are replaced
    /// atomically, the mesh first, so an interrupted run leaves a consistent dataset. Returns
    /// the aligned mesh's path.
    pub fn record_alignment(
        &self,
        aligned: &Mesh,
        alignment: &Alignment,
    ) -> Result<PathBuf, DatasetError> {
        alignment.validate()?;
        let rel = aligned_name(&alignment.source_mesh);
        let mesh_path = confined_path(&self.dir, &rel)?;
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |e: super::WriteError| DatasetError::Io {
                path,
                source: std::io::Error::other(e.to_string()),
            }
        };
        write_atomic(&mesh_path, &obj_bytes(aligned)).map_err(io(&mesh_path))?;
        let text = std::fs::read_to_string(&self.manifest).map_err(|source| DatasetError::Io {
            path: self.manifest.clone(),
            source,
        })?;
        let json = |source| DatasetError::Json {
            path: self.manifest.clone(),
            source,
        };
        let mut doc: serde_json::Value = serde_json::from_str(&text).map_err(json)?;
        let obj = doc
            .as_object_mut()
            .ok_or_else(|| DatasetError::Invalid("scan.json is not a JSON object".into()))?;
        obj.insert("mesh".into(), serde_json::Value::String(rel));
        obj.insert(
            "alignment".into(),
            serde_json::to_value(alignment).map_err(json)?,
        );
        // The result must read back as a valid manifest before it replaces the old one.
        let spec: super::ScanSpec = serde_json::from_value(doc.clone()).map_err(json)?;
        spec.validate()?;
        let out = serde_json::to_string_pretty(&doc).map_err(json)? + "\n";
        write_atomic(&self.manifest, out.as_bytes()).map_err(io(&self.manifest))?;
        Ok(mesh_path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aligned_names_sit_beside_the_source() {
        assert_eq!(aligned_name("object.obj"), "object.aligned.obj");
        assert_eq!(aligned_name("m/scan.obj"), "m/scan.aligned.obj");
        assert_eq!(aligned_name("m/scan"), "m/scan.aligned.obj");
    }

    fn record() -> Alignment {
        let (s, c) = 30f64.to_radians().sin_cos();
        Alignment {
            source_mesh: "object.obj".into(),
            scale: 1000.0,
            rotation: [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
            translation: [1.0, 2.0, 3.0],
            spots: 40,
            inliers: 38,
            inlier_share: 0.95,
            rms_mm: 0.05,
            rms_px: 0.1,
            pose_sigma_mm: 0.01,
            spot_depth_mm: 0.1,
            symmetry: Some(Symmetry::TurntableAxis { fold: None }),
        }
    }

    #[test]
    fn bad_records_are_refused() {
        assert!(record().validate().is_ok());
        let mut a = record();
        a.rotation[0][0] = -a.rotation[0][0];
        assert!(a.validate().is_err());
        // A reflection (det -1) of an orthonormal matrix.
        let mut refl = record();
        refl.rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        assert!(refl.validate().is_err());
        let mut a = record();
        a.scale = f64::NAN;
        assert!(a.validate().is_err());
        let mut a = record();
        a.source_mesh = "../x.obj".into();
        assert!(a.validate().is_err());
    }

    #[test]
    fn recording_keeps_other_keys_and_reads_back() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::create_dir_all(dir.join("frames")).unwrap();
        std::fs::write(
            dir.join("object.obj"),
            "v 0 0 0\nv 0.001 0 0\nv 0 0.001 0\nf 1 2 3\n",
        )
        .unwrap();
        let img = super::super::Image::new(4, 4, 3);
        super::super::write_pfm(&dir.join("frames/0.pfm"), &img).unwrap();
        std::fs::write(
            dir.join("scan.json"),
            r#"{"format": "subsurf-scan/1", "units": "mm", "mesh": "object.obj",
              "other_program": {"kept": [1, 2]},
              "cameras": [{"width": 4, "height": 4, "fx": 10.0, "fy": 10.0, "cx": 1.5, "cy": 1.5,
                "camera_from_world": [[1,0,0,0],[0,1,0,0],[0,0,1,50],[0,0,0,1]]}],
              "frames": [{"image": "frames/0.pfm", "turntable_deg": 0.0, "vendor": 7}]}"#,
        )
        .unwrap();
        let ds = Dataset::open(dir).unwrap();
        let rec = record();
        let (_, src) = ds.source_mesh().unwrap();
        let moved = Mesh::new(
            src.positions.iter().map(|p| rec.apply(*p)).collect(),
            src.triangles.clone(),
        )
        .0;
        let path = ds.record_alignment(&moved, &rec).unwrap();
        assert_eq!(path, dir.join("object.aligned.obj"));
        let back = Dataset::open(dir).unwrap();
        assert_eq!(back.spec.mesh, "object.aligned.obj");
        assert_eq!(back.spec.alignment.as_ref(), Some(&rec));
        assert_eq!(back.mesh.positions, moved.positions);
        // Aligning again starts from the file the user gave.
        let (name, again) = back.source_mesh().unwrap();
        assert_eq!(name, "object.obj");
        assert_eq!(again.positions, src.positions);
        let text = std::fs::read_to_string(dir.join("scan.json")).unwrap();
        assert!(
            text.contains("other_program") && text.contains("\"vendor\": 7"),
            "{text}"
        );
    }
}
