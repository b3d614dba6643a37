//! The object's triangle mesh: OBJ in (the common subset read on every core, `dataset::obj`;
//! the rest through `tobj`), degenerate and duplicate faces reported and
//! dropped, area-weighted vertex normals, OBJ out.
use super::obj::{CommonObj, common_obj};
use foldhash::fast::FixedState;
use rayon::slice::ParallelSliceMut;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Why a mesh could not be used.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MeshError {
    /// The OBJ parser failed.
    #[error("{path}: cannot load OBJ: {source}")]
    Obj {
        /// The file.
        path: PathBuf,
        /// The parser's error.
        source: tobj::LoadError,
    },
    /// The mesh has no usable triangle or a non-finite coordinate.
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Writing the OBJ failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// What loading found and left out, so nothing is dropped silently.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct MeshReport {
    /// Faces with zero area or a repeated vertex (dropped).
    pub degenerate_faces: usize,
    /// Faces with the same three vertices as an earlier face (dropped).
    pub duplicate_faces: usize,
    /// Vertices that belong to no usable face (they get no normal and are never visible).
    pub isolated_vertices: usize,
}

/// A triangle mesh in the object frame (mm), with unit vertex normals.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f64; 3]>,
    /// Triangles (counter-clockwise seen from outside), indices into `positions`.
    pub triangles: Vec<[u32; 3]>,
    /// Area-weighted unit vertex normals; zero for isolated vertices.
    pub normals: Vec<[f64; 3]>,
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

impl Mesh {
    /// Builds a mesh from positions and triangles: drops degenerate and duplicate faces (counted in
    /// the report) and computes normals.
    pub fn new(positions: Vec<[f64; 3]>, triangles: Vec<[u32; 3]>) -> (Mesh, MeshReport) {
        let mut report = MeshReport::default();
        let n = positions.len();
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let diag = norm(sub(hi, lo));
        // Area below this counts as zero: relative to the mesh's size, far below any real triangle.
        let min_area2 = (diag * diag * 1e-14).max(f64::MIN_POSITIVE);
        let mut good = Vec::with_capacity(triangles.len());
        for t in triangles {
            let [a, b, c] = t.map(|i| i as usize);
            if a >= n || b >= n || c >= n || a == b || b == c || a == c {
                report.degenerate_faces += 1;
                continue;
            }
            let cr = cross(
                sub(positions[b], positions[a]),
                sub(positions[c], positions[a]),
            );
            if norm(cr).is_nan() || norm(cr) <= min_area2 {
                report.degenerate_faces += 1;
                continue;
            }
            good.push(t);
        }
        // A face is a duplicate of an earlier one with the same corners in any order: the
        // first is kept. Found by sorting (corners, position) rather than a hash set, whose
        // inserts miss the cache on a scanner's million faces.
        let mut by_corners: Vec<([u32; 3], u32)> = good
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let mut key = *t;
                key.sort_unstable();
                (key, i as u32)
            })
            .collect();
        by_corners.par_sort_unstable();
        let mut duplicate = vec![false; good.len()];
        for w in by_corners.windows(2) {
            if w[0].0 == w[1].0 {
                duplicate[w[1].1 as usize] = true;
                report.duplicate_faces += 1;
            }
        }
        let kept: Vec<[u32; 3]> = good
            .into_iter()
            .zip(&duplicate)
            .filter_map(|(t, &d)| (!d).then_some(t))
            .collect();
        let mut normals = vec![[0.0; 3]; n];
        for t in &kept {
            let [a, b, c] = t.map(|i| i as usize);
            // Unnormalised cross product = area-weighted face normal.
            let cr = cross(
                sub(positions[b], positions[a]),
                sub(positions[c], positions[a]),
            );
            for v in [a, b, c] {
                for k in 0..3 {
                    normals[v][k] += cr[k];
                }
            }
        }
        for nv in &mut normals {
            let l = norm(*nv);
            if l > 0.0 && l.is_finite() {
                *nv = nv.map(|x| x / l);
            } else {
                *nv = [0.0; 3];
                report.isolated_vertices += 1;
            }
        }
        (
            Mesh {
                positions,
                triangles: kept,
                normals,
            },
            report,
        )
    }

    /// The surface area (mm²): the sum of its triangles' ([`triangle_area`]).
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|&t| triangle_area(&self.positions, t))
            .sum()
    }

    /// The bounding box (min, max corner; infinite and reversed for no vertices).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// Length of the bounding box diagonal (mm): the scale for geometric tolerances.
    pub fn diagonal(&self) -> f64 {
        let (lo, hi) = self.bounds();
        norm(sub(hi, lo))
    }
}

/// The area of face `f` of the vertices `p` (mm²); 0 for a face with an index out of range.
pub fn triangle_area(p: &[[f64; 3]], f: [u32; 3]) -> f64 {
    let (Some(a), Some(b), Some(c)) = (
        p.get(f[0] as usize),
        p.get(f[1] as usize),
        p.get(f[2] as usize),
    ) else {
        return 0.0;
    };
    0.5 * norm(cross(sub(*b, *a), sub(*c, *a)))
}

/// Loads an OBJ (all objects merged, polygons triangulated as fans from their first corner).
/// Vertex i is the file's i-th `v` line; faces refer to the first `v` line of their corner's
/// position (in f32, as tobj reads it), so split seams are welded.
pub fn load_obj(path: &Path) -> Result<(Mesh, MeshReport), MeshError> {
    let fast = std::fs::read_to_string(path)
        .ok()
        .and_then(|text| common_obj(&text));
    let (positions, triangles) = match fast {
        Some(CommonObj {
            positions,
            keys,
            triangles,
        }) => (positions, weld(&keys, triangles)),
        None => load_obj_tobj(path)?,
    };
    let invalid = |message: String| MeshError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    if positions.iter().flatten().any(|x| !x.is_finite()) {
        return Err(invalid("a vertex coordinate is not finite".into()));
    }
    let (mesh, report) = Mesh::new(positions, triangles);
    if mesh.triangles.is_empty() {
        return Err(invalid(format!(
            "no usable triangle ({} degenerate, {} duplicate)",
            report.degenerate_faces, report.duplicate_faces
        )));
    }
    Ok((mesh, report))
}

/// Faces of `v`-line indices mapped to the first `v` line with the same f32 position.
fn weld(keys: &[[u32; 3]], mut triangles: Vec<[u32; 3]>) -> Vec<[u32; 3]> {
    let mut first = CornerIndex::with_capacity_and_hasher(keys.len(), FixedState::default());
    let mut canonical = Vec::with_capacity(keys.len());
    let mut welded = false;
    for (i, k) in keys.iter().enumerate() {
        let c = *first.entry(*k).or_insert(i as u32);
        welded |= c as usize != i;
        canonical.push(c);
    }
    if welded {
        for t in &mut triangles {
            for c in t.iter_mut() {
                *c = canonical[*c as usize];
            }
        }
    }
    triangles
}

/// The positions in file order and the triangles as tobj reads them (its reading is the
/// reference [`common_obj`] is tested against, and what reads any file outside its subset).
fn load_obj_tobj(path: &Path) -> Result<Read, MeshError> {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // tobj reads the faces while the v lines are read here: two passes over the file, one on
    // each core.
    let (faces, vertices) = rayon::join(|| tobj::load_obj(path, &opts), || v_lines(path));
    let (models, _materials) = faces.map_err(|source| MeshError::Obj {
        path: path.to_path_buf(),
        source,
    })?;
    let (positions, index_of) = vertices?;
    let invalid = |message: String| MeshError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let mut triangles = Vec::new();
    for m in &models {
        let lookup = |i: u32| -> Result<u32, MeshError> {
            let k = 3 * i as usize;
            let p = m
                .mesh
                .positions
                .get(k..k + 3)
                .ok_or_else(|| invalid("face index out of range".into()))?;
            index_of
                .get(&[p[0].to_bits(), p[1].to_bits(), p[2].to_bits()])
                .copied()
                .ok_or_else(|| invalid("face vertex not among the v lines".into()))
        };
        for t in m.mesh.indices.chunks_exact(3) {
            triangles.push([lookup(t[0])?, lookup(t[1])?, lookup(t[2])?]);
        }
    }
    Ok((positions, triangles))
}

/// Positions in file order and triangles by their index.
type Read = (Vec<[f64; 3]>, Vec<[u32; 3]>);

/// A position's index by its f32 coordinates' bits. foldhash, not std's SipHash: a scanner's
/// mesh has millions of corners to look up, and the keys are our own file's numbers, so there is
/// no adversary to hash against.
type CornerIndex = HashMap<[u32; 3], u32, FixedState>;

/// The OBJ's `v` lines in file order (as f64), and each position's index by the f32 values
/// tobj parses (the first of equal positions).
fn v_lines(path: &Path) -> Result<(Vec<[f64; 3]>, CornerIndex), MeshError> {
    // tobj orders vertices by first use in a face (and splits them by normal/texture index).
    // Vertex i of every per-vertex file of this project is the i-th `v` line of the OBJ, so the
    // positions are read in file order here (as f64) and tobj's faces are mapped back to them by
    // the exact f32 values tobj parsed. Duplicate positions map to their first occurrence.
    let invalid = |message: String| MeshError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let text = std::fs::read_to_string(path).map_err(|source| MeshError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut positions = Vec::new();
    let mut index_of = CornerIndex::default();
    for line in text.lines() {
        let mut w = line.split_whitespace();
        if w.next() != Some("v") {
            continue;
        }
        let (mut p64, mut key) = ([0.0; 3], [0u32; 3]);
        for k in 0..3 {
            let parsed = w.next().map(|t| (t.parse::<f64>(), t.parse::<f32>()));
            let Some((Ok(a), Ok(b))) = parsed else {
                return Err(invalid(format!("bad vertex line {line:?}")));
            };
            p64[k] = a;
            key[k] = b.to_bits();
        }
        index_of.entry(key).or_insert(positions.len() as u32);
        positions.push(p64);
    }
    Ok((positions, index_of))
}

/// The OBJ text of `mesh`, the one OBJ writer (scan, simulate, the demo): positions in Rust's
/// shortest round-trip form (read back bit for bit), 1-based faces; deterministic, so equal
/// meshes give equal bytes.
pub fn obj_bytes(mesh: &Mesh) -> Vec<u8> {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(mesh.positions.len() * 40 + mesh.triangles.len() * 24);
    s.push_str("# subsurf mesh, object frame, mm\n");
    for p in &mesh.positions {
        let _ = writeln!(s, "v {} {} {}", p[0], p[1], p[2]);
    }
    for t in &mesh.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s.into_bytes()
}

/// Writes the mesh as OBJ ([`obj_bytes`]).
pub fn write_obj(path: &Path, mesh: &Mesh) -> Result<(), MeshError> {
    std::fs::write(path, obj_bytes(mesh)).map_err(|source| MeshError::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn degenerate_and_duplicate_faces_are_reported_and_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.obj");
        std::fs::write(
            &p,
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nv 5 5 5\nf 1 2 3\nf 2 3 1\nf 1 2 4\nf 1 1 3\n",
        )
        .unwrap();
        let (m, r) = load_obj(&p).unwrap();
        assert_eq!(m.triangles.len(), 1);
        assert_eq!(r.duplicate_faces, 1);
        assert_eq!(r.degenerate_faces, 2);
        // (2,0,0) is used only by a degenerate face, (5,5,5) by none.
        assert_eq!(r.isolated_vertices, 2);
        assert_eq!(m.positions.len(), 5);
        assert_eq!(m.normals[0], [0.0, 0.0, 1.0]);
    }

    #[test]
    fn of_duplicate_faces_the_first_is_kept_in_file_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.obj");
        std::fs::write(
            &p,
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n\
             f 2 3 1\nf 4 3 2\nf 1 2 3\nf 3 4 2\nf 2 4 3\n",
        )
        .unwrap();
        let (m, r) = load_obj(&p).unwrap();
        assert_eq!(r.duplicate_faces, 3);
        assert_eq!(m.triangles, vec![[1, 2, 0], [3, 2, 1]]);
    }

    #[test]
    fn only_degenerate_faces_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.obj");
        std::fs::write(&p, "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n").unwrap();
        assert!(matches!(load_obj(&p), Err(MeshError::Invalid { .. })));
        std::fs::write(&p, "v 0 0 0\nf 1 2 9\n").unwrap();
        assert!(load_obj(&p).is_err());
    }

    #[test]
    fn vertex_order_is_the_files_even_when_faces_use_them_out_of_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.obj");
        std::fs::write(
            &p,
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvn 0 0 1\nf 4//1 2//1 3//1\nf 2//1 1//1 3//1\n",
        )
        .unwrap();
        let (m, r) = load_obj(&p).unwrap();
        assert_eq!(m.positions[3], [1.0, 1.0, 0.0]);
        assert_eq!(m.triangles, vec![[3, 1, 2], [1, 0, 2]]);
        assert_eq!(r, MeshReport::default());
    }

    type Loaded = Result<(Mesh, MeshReport), String>;

    /// tobj's reading (the reference) of `text`, and whether the common-subset reader took it.
    fn both_readings(dir: &Path, text: &str) -> (Loaded, Loaded, bool) {
        let p = dir.join("m.obj");
        std::fs::write(&p, text).unwrap();
        let reference =
            load_obj_tobj(&p)
                .map_err(|e| e.to_string())
                .and_then(|(positions, triangles)| {
                    let (m, r) = Mesh::new(positions, triangles);
                    if m.triangles.is_empty() {
                        Err("no usable triangle".into())
                    } else {
                        Ok((m, r))
                    }
                });
        let loaded = load_obj(&p).map_err(|e| e.to_string());
        (reference, loaded, common_obj(text).is_some())
    }

    /// The same mesh and report, or an error from both.
    fn same<T: PartialEq + std::fmt::Debug>(
        a: &Result<T, String>,
        b: &Result<T, String>,
        text: &str,
    ) {
        match (a, b) {
            (Ok(a), Ok(b)) => assert_eq!(a, b, "{text:?}"),
            (Err(_), Err(_)) => {}
            _ => panic!("{text:?}: {a:?} against tobj's {b:?}"),
        }
    }

    /// The common subset is read as tobj reads it (welding, fans, relative indices, groups,
    /// texture and normal indices), and every file outside it is left to tobj: the loaded mesh
    /// is tobj's in every case.
    #[test]
    fn the_parallel_reader_reads_as_tobj_does_and_leaves_the_rest_to_it() {
        let dir = tempfile::tempdir().unwrap();
        let square = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n";
        let common = [
            format!("{square}f 1 2 3\nf 1 3 4\n"),
            format!("# c\n{square}f 1 2 3 4\n"),
            format!("{square}v 0.5 1.5 0\nf 1 2 3 5 4\n"),
            format!("{square}f -4 -3 -2\nf -4 -2 -1\n"),
            format!(
                "mtllib m.mtl\no a\n{square}vt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\ng b\ns 1\nusemtl x\nf 1/1/1 2/2/1 3/3/1\nf 1//1 3//1 4//1\n"
            ),
            format!("{square}vt 0 0\nf 1/1 2/1 3/1\np 1\nf 1\nf 2 3\nf 9 9\nvp 1 2\n"),
            // Split seams: v lines 5 and 6 repeat 1 and 3 (equal in f32) and are welded to them.
            format!("{square}v 0 0 0\nv 1.00000000001 1 0\nf 1 2 6\nf 5 3 4\n"),
            format!("{square}f 1 2 3\r\nf 1 3 4\r\n"),
            format!("{square}f +1 2/ 3//\nf 1/// 3 4\n"),
            // Degenerate and duplicate faces: Mesh::new's report.
            format!("{square}f 1 2 3\nf 2 3 1\nf 1 1 2\nf 1 3 4\n"),
            // Only a point and a line: no usable triangle either way.
            format!("{square}f 1\nf 1 2\n"),
        ];
        for text in &common {
            let (reference, loaded, fast) = both_readings(dir.path(), text);
            assert!(fast, "outside the subset: {text:?}");
            assert_eq!(reference.is_ok(), !text.ends_with("f 1 2\n"), "{text:?}");
            same(&loaded, &reference, text);
        }
        let welded = both_readings(dir.path(), &common[6]).1.unwrap().0;
        assert_eq!(welded.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let outside = [
            "v 0 0 0 2\nv 1 0 0 2\nv 0 1 0 2\nf 1 2 3\n".to_string(),
            "v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1 2 3\n".to_string(),
            format!("{square}l 1 2 3\n"),
            format!("f 1 2 3\n{square}"),
            format!("{square}f 1 2 5\n"),
            format!("{square}f 0 1 2\n"),
            format!("{square}f -5 1 2\n"),
            format!("{square}f 1/1 2/1 3/1\n"),
            format!("{square}f 1/1/1/1 2 3\n"),
            format!("{square}f /1 2 3\n"),
            format!("{square}f\n"),
            format!("{square}f 1 2 x\n"),
            format!("{square}usemtl\nf 1 2 3\n"),
            format!("{square}vt 0\nf 1 2 3\n"),
            "v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_string(),
            "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_string(),
        ];
        for text in &outside[..outside.len() - 1] {
            let (reference, loaded, fast) = both_readings(dir.path(), text);
            assert!(!fast, "read by the subset: {text:?}");
            same(&loaded, &reference, text);
        }
        // NaN is a number to both readers; the loader refuses it after either.
        let (_, loaded, fast) = both_readings(dir.path(), outside.last().unwrap());
        assert!(fast && loaded.unwrap_err().contains("not finite"));
    }

    /// Files of other tools and sizes: the shared datasets' meshes (written by the outside
    /// renderer) and a generated mesh large enough to be read in several chunks.
    #[test]
    fn the_parallel_reader_reads_whole_meshes_as_tobj_does() {
        let dir = tempfile::tempdir().unwrap();
        let here = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
        let mut texts: Vec<String> = ["sample-slab", "sample-torus", "sample-pebble"]
            .iter()
            .filter_map(|name| {
                here.ancestors()
                    .map(|a| a.join("shared/data").join(name).join("object.obj"))
                    .find(|p| p.is_file())
            })
            .map(|p| std::fs::read_to_string(p).unwrap())
            .collect();
        // A 200 × 200 grid of quads with normals, written with relative indices: about 3 MB.
        let n = 200;
        let mut s = String::new();
        for j in 0..n {
            for i in 0..n {
                s += &format!(
                    "v {} {} {}\nvn 0 0 1\n",
                    i as f64 * 0.1,
                    j as f64 * 0.1,
                    ((i * j) % 7) as f64 * 1e-3
                );
            }
        }
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = j * n + i + 1;
                s += &format!(
                    "f {}//{a} {}//{a} {}//{a} {}//{a}\n",
                    a,
                    a + 1,
                    a + n + 1,
                    a + n
                );
            }
        }
        s += &format!("f -1 -2 -{}\n", n + 1);
        assert!(s.len() > 2 * super::super::obj::CHUNK_BYTES);
        texts.push(s);
        for text in &texts {
            let (reference, loaded, fast) = both_readings(dir.path(), text);
            assert!(fast);
            let (reference, loaded) = (reference.unwrap(), loaded.unwrap());
            assert!(reference.0.triangles.len() > 1000);
            assert_eq!(loaded, reference);
        }
    }

    #[test]
    fn write_then_load_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.obj");
        let (m, _) = Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.5],
                [1.0, 1.0 / 3.0, 0.1 + 0.2],
            ],
            vec![[0, 1, 2], [1, 3, 2]],
        );
        write_obj(&p, &m).unwrap();
        let (back, r) = load_obj(&p).unwrap();
        assert_eq!(r, MeshReport::default());
        assert_eq!(back.triangles, m.triangles);
        // Positions come back bit for bit (the writer loses no digits).
        assert_eq!(back.positions, m.positions);
        for (a, b) in back.positions.iter().zip(&m.positions) {
            assert!(norm(sub(*a, *b)) < 1e-6);
        }
    }
}
