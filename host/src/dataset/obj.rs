//! The OBJ subset that meshes as scanners, trimesh, Blender and our own writer produce, parsed on
//! every core.
//!
//! Written by hand, not left to `tobj`, because `tobj` reads line by line on one thread and
//! hashes every face corner: on a 655,362-vertex scanner mesh (53 MB) that was about 0.8 s of a
//! 6 s fit, the largest part of it nothing else could overlap. This reader only
//! accepts what it can read exactly as tobj does; for anything else ([`common_obj`] returns
//! `None`) the caller reads the file with tobj, whose reading stays the reference
//! (`dataset::mesh`'s tests compare the two).
//!
//! The subset: `v` lines of exactly three numbers; `vt`, `vn` lines whose first two or three
//! words are numbers; `f` lines whose corners are `v`, `v/vt`, `v//vn` or `v/vt/vn` integers
//! that refer back to lines already read (1-based, or negative, relative to the lines so far);
//! faces of one or two corners (points and lines, which are not loaded); comments, `o`, `g`,
//! `s`, `mtllib`, a named `usemtl` and any word tobj ignores. Not in it: a `v` line with a
//! weight or a colour, `l` lines (tobj reads a three-corner line as a triangle), an index that
//! points forward or outside the file, a face without corners, text that is not UTF-8.
use rayon::prelude::*;

/// An OBJ in the subset: `v` lines in file order, their f32 bits (the key tobj's reading welds
/// by), and the triangles by `v`-line index, in file order, polygons as fans.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CommonObj {
    /// The `v` lines' positions, read as f64.
    pub positions: Vec<[f64; 3]>,
    /// The same numbers read as f32, as bits.
    pub keys: Vec<[u32; 3]>,
    /// Triangles by 0-based `v`-line index.
    pub triangles: Vec<[u32; 3]>,
}

/// Text per chunk parsed on one thread: large enough that the per-chunk bookkeeping is nothing,
/// small enough that two cores share a 50 MB file evenly.
pub(crate) const CHUNK_BYTES: usize = 1 << 20;

/// What one chunk of lines holds. Indices are resolved after every chunk is read, when the
/// number of `v`, `vt` and `vn` lines before each chunk is known.
#[derive(Default)]
struct Chunk {
    positions: Vec<[f64; 3]>,
    keys: Vec<[u32; 3]>,
    /// Triangle corners as written (1-based, or negative), and how many `v` lines of this chunk
    /// come before the face.
    corners: Vec<[i64; 3]>,
    v_before: Vec<u32>,
    /// Faces with texture or normal indices: the chunk's `vt` and `vn` lines before the face and
    /// the largest index the face uses of each (0: none).
    refs: Vec<[u32; 4]>,
    texcoords: u32,
    normals: u32,
}

/// Reads `text` if it is in the subset (module doc); `None` if any line is not.
pub(crate) fn common_obj(text: &str) -> Option<CommonObj> {
    let bytes = text.as_bytes();
    let mut bounds = vec![0];
    while let Some(&last) = bounds.last() {
        let target = last + CHUNK_BYTES;
        if target >= bytes.len() {
            break;
        }
        // The chunk ends after the first newline at or past its target size.
        let end = bytes[target..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |k| target + k + 1);
        bounds.push(end);
    }
    bounds.push(bytes.len());
    bounds.dedup();
    let chunks: Vec<Chunk> = bounds
        .par_windows(2)
        .map(|w| parse_chunk(&text[w[0]..w[1]]))
        .collect::<Option<_>>()?;

    let n: usize = chunks.iter().map(|c| c.positions.len()).sum();
    let faces: usize = chunks.iter().map(|c| c.corners.len()).sum();
    let mut out = CommonObj {
        positions: Vec::with_capacity(n),
        keys: Vec::with_capacity(n),
        triangles: Vec::with_capacity(faces),
    };
    let (mut v0, mut vt0, mut vn0) = (0u64, 0u64, 0u64);
    for c in &chunks {
        for r in &c.refs {
            // A texture or normal index must point to a line already read (tobj checks it
            // against the lines read when the object ends, never fewer).
            if u64::from(r[1]) > vt0 + u64::from(r[0]) || u64::from(r[3]) > vn0 + u64::from(r[2]) {
                return None;
            }
        }
        for (t, &before) in c.corners.iter().zip(&c.v_before) {
            let before = v0 + u64::from(before);
            let mut tri = [0u32; 3];
            for (k, &x) in t.iter().enumerate() {
                let i = if x > 0 {
                    x as u64 - 1
                } else {
                    // x < 0 (0 is refused while parsing): relative to the v lines so far.
                    before.checked_sub(x.unsigned_abs())?
                };
                if i >= before {
                    return None;
                }
                tri[k] = u32::try_from(i).ok()?;
            }
            out.triangles.push(tri);
        }
        out.positions.extend_from_slice(&c.positions);
        out.keys.extend_from_slice(&c.keys);
        v0 += c.positions.len() as u64;
        vt0 += u64::from(c.texcoords);
        vn0 += u64::from(c.normals);
    }
    Some(out)
}

/// One chunk of whole lines; `None` if a line is outside the subset.
fn parse_chunk(text: &str) -> Option<Chunk> {
    let mut c = Chunk::default();
    for line in text.split('\n') {
        let mut words = line.split_whitespace();
        match words.next() {
            None => {}
            Some("v") => {
                let (mut p, mut key) = ([0.0; 3], [0u32; 3]);
                for k in 0..3 {
                    let w = words.next()?;
                    p[k] = w.parse::<f64>().ok()?;
                    key[k] = w.parse::<f32>().ok()?.to_bits();
                }
                if words.next().is_some() {
                    return None;
                }
                c.positions.push(p);
                c.keys.push(key);
            }
            Some("vt") => {
                numbers(words, 2)?;
                c.texcoords = c.texcoords.checked_add(1)?;
            }
            Some("vn") => {
                numbers(words, 3)?;
                c.normals = c.normals.checked_add(1)?;
            }
            Some("f") => face(words, &mut c)?,
            Some("l") => return None,
            // tobj refuses a usemtl without a name.
            Some("usemtl") if line.split_once(' ').unwrap_or_default().1.trim().is_empty() => {
                return None;
            }
            // Comments, o, g, s, mtllib and any other word: tobj reads no geometry from them.
            Some(_) => {}
        }
    }
    Some(c)
}

/// The first `n` words are f32 numbers (tobj's check; the rest of the line is not read).
fn numbers<'a>(mut words: impl Iterator<Item = &'a str>, n: usize) -> Option<()> {
    for _ in 0..n {
        words.next()?.parse::<f32>().ok()?;
    }
    Some(())
}

/// An `f` line: its corners' position indices as written, fanned from the first corner.
fn face<'a>(words: impl Iterator<Item = &'a str>, c: &mut Chunk) -> Option<()> {
    let v_before = u32::try_from(c.positions.len()).ok()?;
    let mut first = None;
    let mut previous = None;
    let mut corners = 0usize;
    let (mut max_vt, mut max_vn) = (0u32, 0u32);
    for w in words {
        let mut v = None;
        for (k, part) in w.split('/').enumerate() {
            if part.is_empty() {
                continue;
            }
            let x: i64 = part.parse().ok()?;
            match k {
                0 if x != 0 => v = Some(x),
                // Texture and normal indices: only positive ones, checked once all are read.
                1 if x > 0 => max_vt = max_vt.max(u32::try_from(x).ok()?),
                2 if x > 0 => max_vn = max_vn.max(u32::try_from(x).ok()?),
                _ => return None,
            }
        }
        let v = v?;
        corners += 1;
        match (first, previous) {
            (None, _) => first = Some(v),
            (Some(_), None) => previous = Some(v),
            (Some(a), Some(b)) => {
                c.corners.push([a, b, v]);
                c.v_before.push(v_before);
                previous = Some(v);
            }
        }
    }
    match corners {
        0 => None,
        // A point or a line: not loaded (nor are its indices checked by tobj).
        1 | 2 => Some(()),
        _ => {
            if max_vt > 0 || max_vn > 0 {
                c.refs.push([c.texcoords, max_vt, c.normals, max_vn]);
            }
            Some(())
        }
    }
}
