//! Fall-off curves as CSV text: the input format of `subsurf fit-curve`.
//!
//! A header `r,value` (one channel) or `r,r_value,g_value,b_value` (RGB), with a leading `id`
//! column in batch files, where every id is one curve (rows of an id need not be contiguous);
//! `#` starts a comment; blank lines are skipped. Values are kept as written, NaN and negative
//! ones included: cleaning them is the fit's job ([`crate::fit::clean`]), which counts what it
//! drops.
//!
//! Lives in the host library rather than in `subsurf-model` because it is a file format, and the
//! model crate's contract is to know no files. [`parse`] reads a `&str`; [`read`] streams from
//! any reader through a ~1 MiB buffer (`fit-curve` reads its file that way, so a large batch is
//! never held twice); callers keep the context of where the text came from.
//!
//! Hand-written rather than with the `csv` crate: the format is four fixed numeric columns, and
//! `fit-curve --batch` parses millions of rows on the path the issue's throughput target is
//! measured on (BENCHMARKS.md). One pass over the bytes of a block of lines, with no per-row
//! allocation and no per-row search for the newline. On x86-64 the rows of a curve are read by
//! a vector reader (`simd`: SSE4.1, AVX2's encoding where the CPU has it, chosen at run time):
//! a row's two separators from one 32-byte compare, each field's digits converted by a shuffle
//! and three multiply-adds. Elsewhere, and for the rows it declines, plain decimals by
//! `short_decimal` (a word-at-a-time reader, ~1/3 fewer instructions a row than `fast-float2`).
//! Both end in Clinger's exact fast path; every other number shape is read by `fast-float2`,
//! to the same bits, so the result never depends on the reader or the machine.

use std::collections::{HashMap, HashSet};

pub mod fitting;

/// One curve of a file: its id (batch files) and its samples per channel.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// The id column's value (batch files only).
    pub id: Option<String>,
    /// Distances r = |x_o − x_i|, one per row.
    pub r: Vec<f64>,
    /// Samples per channel (1 or 3 channels), each as long as `r`.
    pub channels: Vec<Vec<f64>>,
}

impl Curve {
    /// Appends one row of `N` numbers: r, then one value per channel (`N` − 1 channels).
    #[inline(always)]
    fn push_values<const N: usize>(&mut self, row: &[f64; N]) {
        self.r.push(row[0]);
        for (dst, v) in self.channels.iter_mut().zip(&row[1..]) {
            dst.push(*v);
        }
    }

    /// Appends one row: `row[0]` is r, the rest one value per channel.
    #[inline]
    fn push_row(&mut self, row: &[f64]) {
        self.r.push(row[0]);
        for (dst, v) in self.channels.iter_mut().zip(&row[1..]) {
            dst.push(*v);
        }
    }
}

/// Why a curve file cannot be read. Every error about a row names its 1-based line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum CurvesError {
    /// A header that is not one of the two formats.
    #[error(
        "line {line}: expected header `{prefix}r,value` or `{prefix}r,r_value,g_value,b_value`, got `{got}`"
    )]
    Header {
        /// 1-based line number.
        line: usize,
        /// `id,` in batch files, empty otherwise.
        prefix: &'static str,
        /// The line as found.
        got: String,
    },
    /// A row with the wrong number of columns.
    #[error("line {line}: expected {expected} columns, got {got}")]
    Columns {
        /// 1-based line number.
        line: usize,
        /// Columns the header announced.
        expected: usize,
        /// Columns found.
        got: usize,
    },
    /// A field that is not a number.
    #[error("line {line}: column {column} is not a number: `{field}`")]
    NotANumber {
        /// 1-based line number.
        line: usize,
        /// 1-based column.
        column: usize,
        /// The field as found.
        field: String,
    },
    /// A line that is not UTF-8 text.
    #[error("line {line}: not UTF-8 text")]
    NotText {
        /// 1-based line number.
        line: usize,
    },
    /// No header line at all.
    #[error("no header line found (expected `r,value` or `r,r_value,g_value,b_value`)")]
    NoHeader,
}

/// Most columns a row can have (`id,r,r_value,g_value,b_value`).
const MAX_COLUMNS: usize = 5;

/// Parses a curve file's text. `batch`: the first column is an id and each id is a curve;
/// otherwise the whole file is one curve (id `None`).
pub fn parse(text: &str, batch: bool) -> Result<Vec<Curve>, CurvesError> {
    let mut p = Parser::new(batch);
    let bytes = text.as_bytes();
    // Complete lines in one block, then the last line (no newline after it) on its own.
    let complete = memchr::memrchr(b'\n', bytes).map_or(0, |at| at + 1);
    let lines = p.block(0, &bytes[..complete])?;
    if complete < bytes.len() {
        p.line(lines + 1, &bytes[complete..])?;
    }
    p.finish()
}

/// Why a curve file could not be read: the reader failed, or its text is not a curve file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReadError {
    /// The reader failed (after `line` complete lines).
    #[error("reading after line {line}: {source}")]
    Io {
        /// Complete lines read before the failure.
        line: usize,
        /// The reader's error.
        source: std::io::Error,
    },
    /// The text is not a curve file.
    #[error(transparent)]
    Curves(#[from] CurvesError),
}

/// Bytes read at a time by [`read`].
const CHUNK: usize = 1 << 20;

/// Parses a curve file from a reader as it streams in (a buffer of ~1 MiB, never the whole
/// file): the same format and errors as [`parse`]. The data can be large (`fit-curve --batch`
/// on millions of rows), so only the parsed numbers are held.
pub fn read(reader: impl std::io::Read, batch: bool) -> Result<Vec<Curve>, ReadError> {
    let mut p = Parser::new(batch);
    stream(reader, &mut p, |_| Ok(false))?;
    Ok(p.finish()?)
}

/// How [`read_groups`] ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Grouped {
    /// Every curve was handed out once, complete, in the order of the file.
    Complete,
    /// An id came back after its curve had been handed out (the rows of an id are not
    /// contiguous): the groups handed out so far are not the file's curves, and the caller
    /// should read the file again with [`read`]. Reading stopped there.
    Interleaved,
}

/// [`read`] for batch files whose curves come one after the other (each id's rows together,
/// as `fit-curve --batch` files usually are): complete curves are handed to `each` as soon as
/// the next curve has begun, a block of input (~1 MiB) at a time, instead of all at the end.
/// Memory then holds a block's curves rather than the whole file's, and a curve's numbers are
/// still in cache when `each` fits them (at the scipy comparison's size that saves the ~8 % of
/// the command's time that the page faults and cache misses of 64 MB of parsed numbers cost,
/// BENCHMARKS.md). Files where an id's rows are apart are detected ([`Grouped::Interleaved`]).
pub fn read_groups(
    reader: impl std::io::Read,
    batch: bool,
    mut each: impl FnMut(Vec<Curve>),
) -> Result<Grouped, ReadError> {
    let mut p = Parser::new(batch);
    p.handed_out = Some(HashSet::new());
    let interleaved = stream(reader, &mut p, |p| {
        if p.interleaved {
            return Ok(true);
        }
        // Every curve but the last is complete: a later row of its id would be interleaved.
        let last = p.curves.pop();
        let done = std::mem::take(&mut p.curves);
        p.index.clear();
        if let Some(handed) = &mut p.handed_out {
            handed.extend(done.iter().filter_map(|c| c.id.clone()));
        }
        if let Some(c) = last {
            if let Some(id) = &c.id {
                p.index.insert(id.clone(), 0);
            }
            p.last = Some(0);
            p.curves.push(c);
        }
        if !done.is_empty() {
            each(done);
        }
        Ok(false)
    })?;
    if interleaved || p.interleaved {
        return Ok(Grouped::Interleaved);
    }
    let rest = p.finish()?;
    if !rest.is_empty() {
        each(rest);
    }
    Ok(Grouped::Complete)
}

/// The reading loop of [`read`] and [`read_groups`]: feeds the parser block by block and calls
/// `after_block` after each block of complete lines; `Ok(true)` from it stops reading (and is
/// returned).
fn stream(
    mut reader: impl std::io::Read,
    p: &mut Parser,
    mut after_block: impl FnMut(&mut Parser) -> Result<bool, CurvesError>,
) -> Result<bool, ReadError> {
    let mut buf: Vec<u8> = vec![0; CHUNK];
    // buf[..filled] holds unprocessed bytes: the tail of an incomplete line, then fresh data.
    let (mut filled, mut line_no) = (0usize, 0usize);
    loop {
        if filled == buf.len() {
            // One line longer than the buffer: grow it.
            buf.resize(buf.len() * 2, 0);
        }
        let got = match reader.read(&mut buf[filled..]) {
            Ok(k) => k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(source) => {
                return Err(ReadError::Io {
                    line: line_no,
                    source,
                });
            }
        };
        let scanned = filled;
        filled += got;
        if got == 0 {
            // End of input: the last line needs no newline.
            if filled > 0 {
                p.line(line_no + 1, &buf[..filled])?;
            }
            return Ok(false);
        }
        // Complete lines in buf[..filled]; only the fresh bytes can hold new newlines.
        let start = match memchr::memrchr(b'\n', &buf[scanned..filled]) {
            Some(at) => scanned + at + 1,
            None => 0,
        };
        line_no += p.block(line_no, &buf[..start])?;
        buf.copy_within(start..filled, 0);
        filled -= start;
        if start > 0 && after_block(p)? {
            return Ok(true);
        }
    }
}

/// The parsing state shared by [`parse`] and [`read`]: the header's channel count once seen, the
/// curves so far, and where each id went.
struct Parser {
    batch: bool,
    channels: Option<usize>,
    curves: Vec<Curve>,
    index: HashMap<String, usize>,
    /// Rows of one id usually come together: the last curve written, to skip the map lookup.
    last: Option<usize>,
    /// [`read_groups`]: the ids of the curves handed out already, and whether one came back.
    handed_out: Option<HashSet<String>>,
    interleaved: bool,
    /// The last curve's id followed by `,` as the low bytes of a little-endian word, the mask
    /// of those bytes and their count, when they fit in one word (ids of up to 7 bytes): a row
    /// of that curve is then recognised by one load and one compare. Outside batch files the
    /// key is empty (mask 0) and matches every row.
    key: Option<(u64, u64, usize)>,
    /// Which row readers [`Parser::block`] may use: the best the CPU has, except in tests,
    /// which compare them. (Only x86-64 has a reader to choose.)
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    readers: Readers,
}

/// The row readers [`Parser::block`] may choose from (tests pick one to compare them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(not(test), allow(dead_code))]
enum Readers {
    /// The best the CPU has: AVX2, SSE4.1 or the portable reader.
    Best,
    /// SSE4.1 at most (what x86-64 CPUs without AVX2 run).
    Sse41,
    /// The portable reader only.
    Portable,
}

impl Parser {
    fn new(batch: bool) -> Self {
        Self {
            batch,
            channels: None,
            curves: Vec::new(),
            index: HashMap::new(),
            last: None,
            key: None,
            handed_out: None,
            interleaved: false,
            readers: Readers::Best,
        }
    }

    fn finish(self) -> Result<Vec<Curve>, CurvesError> {
        if self.channels.is_none() {
            return Err(CurvesError::NoHeader);
        }
        Ok(self.curves)
    }

    /// Every line of `text`, which holds complete lines only (each ends in `\n`), the first one
    /// numbered `line_no + 1`; returns how many there were. Data rows in the usual form (no
    /// blanks, no comment) are read in one pass over their bytes, which also finds the end of
    /// the line: a row of the last curve by one compare of its id ([`Parser::key`]), its numbers
    /// by [`fast_values`]. Everything else goes through [`Parser::line`].
    fn block(&mut self, line_no: usize, text: &[u8]) -> Result<usize, CurvesError> {
        let (mut at, mut count) = (0, 0);
        // Up to the header, by the general path.
        while at < text.len() && self.channels.is_none() {
            count += 1;
            let end = memchr::memchr(b'\n', &text[at..]).map_or(text.len(), |k| at + k);
            self.line(line_no + count, &text[at..end])?;
            at = end + 1;
        }
        match self.channels {
            Some(1) => self.rows_on_cpu::<2>(line_no, text, at, count),
            Some(_) => self.rows_on_cpu::<4>(line_no, text, at, count),
            None => Ok(count),
        }
    }

    /// [`Parser::rows`] with the best number reader this CPU has: on x86-64 the vector reader
    /// ([`simd::Sse`]), compiled for AVX2 (VEX encoding, BMI's bit scans) where the CPU has it,
    /// else for SSE4.1; elsewhere, or without SSE4.1, the portable one. Both read the same
    /// numbers to the same bits (the tests hold them to it), so the output never depends on
    /// the machine. Detection is one cached load per block.
    fn rows_on_cpu<const N: usize>(
        &mut self,
        line_no: usize,
        text: &[u8],
        at: usize,
        count: usize,
    ) -> Result<usize, CurvesError> {
        #[cfg(target_arch = "x86_64")]
        if self.readers != Readers::Portable {
            if let Some(v3) = pulp::x86::V3::try_new().filter(|_| self.readers == Readers::Best) {
                return v3.vectorize(simd::Rows::<N> {
                    parser: self,
                    line_no,
                    text,
                    at,
                    count,
                    reader: simd::Sse(*v3),
                });
            }
            if let Some(v2) = pulp::x86::V2::try_new() {
                return v2.vectorize(simd::Rows::<N> {
                    parser: self,
                    line_no,
                    text,
                    at,
                    count,
                    reader: simd::Sse(v2),
                });
            }
        }
        self.rows::<N, _>(line_no, text, at, count, Portable)
    }

    /// [`Parser::block`] after the header, for rows of `N` numbers (r and the channels): one
    /// loop per row width, so a row's numbers stay in registers from the parse to the curve's
    /// vectors (with the width a run-time value they went through an array on the stack, whose
    /// two 8-byte stores then a 16-byte load stalled store forwarding on every row).
    /// Inlined into [`Parser::rows_on_cpu`]'s callers so that it is compiled once per reader
    /// and instruction set.
    #[inline(always)]
    fn rows<const N: usize, R: Reader>(
        &mut self,
        line_no: usize,
        text: &[u8],
        mut at: usize,
        mut count: usize,
        reader: R,
    ) -> Result<usize, CurvesError> {
        let ch = N - 1;
        while at < text.len() {
            // The rows of the last curve, in a loop of their own: its key and vectors stay in
            // registers.
            if let Some(k) = self.last
                && let Some((key, mask, len)) = self.key
                && let Some(c) = self.curves.get_mut(k)
            {
                if N == 2 {
                    // One channel, the common case: the two numbers as scalars.
                    if let Some(dst) = c.channels.first_mut() {
                        loop {
                            // As many rows as the reader's row loop takes (none for the
                            // portable one), then one row by the reader alone: a row that loop
                            // declined, or the last ones of the block.
                            let (rows, next) =
                                reader.pairs(text, at, (key, mask, len), (&mut c.r, &mut *dst));
                            count += rows;
                            at = next;
                            if word(text, at) & mask == key
                                && let Some((r, v, next)) = fast_pair(text, at + len, reader)
                            {
                                c.r.push(r);
                                dst.push(v);
                                count += 1;
                                at = next;
                            } else {
                                break;
                            }
                        }
                    }
                } else {
                    while word(text, at) & mask == key
                        && let Some((values, next)) = fast_values::<N, R>(text, at + len, reader)
                    {
                        c.push_values(&values);
                        count += 1;
                        at = next;
                    }
                }
                if at >= text.len() {
                    break;
                }
            }
            count += 1;
            if let Some((id, from)) = fast_id(text, at, self.batch)
                && let Some((values, next)) = fast_values::<N, R>(text, from, reader)
            {
                let k = self.curve_for(line_no + count, id, ch)?;
                self.curves[k].push_values(&values);
                at = next;
                continue;
            }
            let end = memchr::memchr(b'\n', &text[at..]).map_or(text.len(), |k| at + k);
            self.line(line_no + count, &text[at..end])?;
            at = end + 1;
        }
        Ok(count)
    }

    /// One line (without its `\n`; a `\r` before it is whitespace), 1-based number `line_no`,
    /// by the general path: the header, comments, blank lines, unusual spacing and errors.
    fn line(&mut self, line_no: usize, raw: &[u8]) -> Result<(), CurvesError> {
        let Some(ch) = self.channels else {
            return self.header_line(line_no, raw);
        };
        let expected = ch + 1 + usize::from(self.batch);
        match slow_row(line_no, raw, self.batch, expected)? {
            Some((id, values)) => self.push(line_no, id, &values, ch),
            None => Ok(()),
        }
    }

    /// Appends a data row to its id's curve.
    #[inline]
    fn push(
        &mut self,
        line_no: usize,
        id: &[u8],
        values: &[f64; MAX_COLUMNS],
        ch: usize,
    ) -> Result<(), CurvesError> {
        let first = usize::from(self.batch);
        let at = self.curve_for(line_no, id, ch)?;
        self.curves[at].push_row(&values[first..=first + ch]);
        Ok(())
    }

    fn header_line(&mut self, line_no: usize, raw: &[u8]) -> Result<(), CurvesError> {
        let text = String::from_utf8_lossy(raw);
        let line = strip_comment(&text);
        if line.is_empty() {
            return Ok(());
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        self.channels = Some(
            header(&fields, self.batch).ok_or_else(|| CurvesError::Header {
                line: line_no,
                prefix: if self.batch { "id," } else { "" },
                got: line.to_string(),
            })?,
        );
        Ok(())
    }

    /// Index of the curve of `id` (a new one for an id not seen yet).
    fn curve_for(&mut self, line_no: usize, id: &[u8], ch: usize) -> Result<usize, CurvesError> {
        if let Some(k) = self.last
            && self.curves[k]
                .id
                .as_deref()
                .map_or(b"" as &[u8], str::as_bytes)
                == id
        {
            return Ok(k);
        }
        let key = std::str::from_utf8(id).map_err(|_| CurvesError::NotText { line: line_no })?;
        let k = match self.index.get(key) {
            Some(&k) => k,
            None => {
                if self.handed_out.as_ref().is_some_and(|h| h.contains(key)) {
                    self.interleaved = true;
                }
                // Curves of a batch are usually alike: room for as many rows as the last one
                // had saves the vectors' regrowth (a measurable part of parsing large files).
                let rows = self.last.map_or(0, |k| self.curves[k].r.len());
                self.curves.push(Curve {
                    id: self.batch.then(|| key.to_string()),
                    r: Vec::with_capacity(rows),
                    channels: (0..ch).map(|_| Vec::with_capacity(rows)).collect(),
                });
                self.index.insert(key.to_string(), self.curves.len() - 1);
                self.curves.len() - 1
            }
        };
        self.last = Some(k);
        // The key of [`Parser::block`]'s one-compare path: the id and its comma in one word
        // (outside batch files there is no id and every row is this curve's).
        let key_len = if self.batch { id.len() + 1 } else { 0 };
        self.key = (key_len <= 8).then(|| {
            let mut bytes = [0u8; 8];
            bytes[..id.len()].copy_from_slice(id);
            if self.batch {
                bytes[id.len()] = b',';
            }
            let mask = u64::MAX.checked_shr(64 - 8 * key_len as u32).unwrap_or(0);
            (u64::from_le_bytes(bytes) & mask, mask, key_len)
        });
        Ok(k)
    }
}

/// The line up to a `#`, trimmed.
fn strip_comment(line: &str) -> &str {
    match line.find('#') {
        Some(at) => &line[..at],
        None => line,
    }
    .trim()
}

/// A data row: the id's bytes (empty outside batch files) and the values by column.
type Row<'a> = (&'a [u8], [f64; MAX_COLUMNS]);

/// The id of a batch row in the usual form at `text[at..]` (no blanks, no `#`, followed by a
/// comma) and where its first number starts; outside batch files an empty id at `at`.
#[inline]
fn fast_id(text: &[u8], at: usize, batch: bool) -> Option<(&[u8], usize)> {
    if !batch {
        return Some((&[], at));
    }
    let mut i = at;
    while i < text.len() && !matches!(text[i], b',' | b'\n' | b'#' | b' ' | b'\t' | b'\r') {
        i += 1;
    }
    (i > at && text.get(i) == Some(&b',')).then(|| (&text[at..i], i + 1))
}

/// `N` numbers at `text[at..]` separated by commas, with no blanks, ended by `\n` or `\r\n`:
/// the values and where the next line starts. `None` for anything else, which the general path
/// ([`slow_row`]) then reads or rejects.
#[inline(always)]
fn fast_values<const N: usize, R: Reader>(
    text: &[u8],
    at: usize,
    reader: R,
) -> Option<([f64; N], usize)> {
    let mut values = [0.0f64; N];
    let mut i = at;
    for (col, v) in values.iter_mut().enumerate() {
        let (x, used) = reader.number(text.get(i..)?)?;
        *v = x;
        i += used;
        if col + 1 < N {
            if text.get(i) != Some(&b',') {
                return None;
            }
            i += 1;
        }
    }
    match text.get(i..) {
        Some([b'\n', ..]) => Some((values, i + 1)),
        Some([b'\r', b'\n', ..]) => Some((values, i + 2)),
        _ => None,
    }
}

/// [`fast_values`] for two numbers, returned as scalars.
#[inline(always)]
fn fast_pair(text: &[u8], at: usize, reader: impl Reader) -> Option<(f64, f64, usize)> {
    let (x, used) = reader.number(text.get(at..)?)?;
    let i = at + used;
    if text.get(i) != Some(&b',') {
        return None;
    }
    let (y, used) = reader.number(text.get(i + 1..)?)?;
    let j = i + 1 + used;
    match text.get(j..) {
        Some([b'\n', ..]) => Some((x, y, j + 1)),
        Some([b'\r', b'\n', ..]) => Some((x, y, j + 2)),
        _ => None,
    }
}

/// The general reading of a data row: comments, blank lines (`Ok(None)`), Unicode spacing, and
/// the errors naming the line.
fn slow_row(
    line_no: usize,
    raw: &[u8],
    batch: bool,
    expected: usize,
) -> Result<Option<Row<'_>>, CurvesError> {
    let text = std::str::from_utf8(raw).map_err(|_| CurvesError::NotText { line: line_no })?;
    let line = strip_comment(text);
    if line.is_empty() {
        return Ok(None);
    }
    let mut fields = [""; MAX_COLUMNS];
    let mut count = 0;
    for f in line.split(',') {
        if count < MAX_COLUMNS {
            fields[count] = f.trim();
        }
        count += 1;
    }
    if count != expected {
        return Err(CurvesError::Columns {
            line: line_no,
            expected,
            got: count,
        });
    }
    let first = usize::from(batch);
    let mut values = [0.0f64; MAX_COLUMNS];
    for col in first..expected {
        values[col] = parse_f64(fields[col]).ok_or_else(|| CurvesError::NotANumber {
            line: line_no,
            column: col + 1,
            field: fields[col].to_string(),
        })?;
    }
    Ok(Some((
        if batch { fields[0].as_bytes() } else { &[] },
        values,
    )))
}

/// A whole field as f64 (correctly rounded, by the `fast-float2` crate), `None` if it is not
/// one number.
fn parse_f64(s: &str) -> Option<f64> {
    fast_float2::parse(s).ok()
}

/// How the row loop ([`Parser::rows`]) reads a number at the start of `b`: the value and the
/// bytes it takes, always [`number_prefix`]'s answer (the same bits, the same length).
trait Reader: Copy {
    fn number(self, b: &[u8]) -> Option<(f64, usize)>;

    /// Rows of one curve of one value (`id,r,value` with the id and comma given as `key`, a
    /// masked little-endian word and its length, as [`Parser::key`]) from `text[at..]`, pushed
    /// to `dst`: how many and where the next line starts. Only rows read exactly as
    /// [`fast_pair`] reads them; it may stop anywhere before (the portable reader takes none:
    /// the row loop then goes row by row).
    #[inline(always)]
    fn pairs(
        self,
        _text: &[u8],
        at: usize,
        _key: (u64, u64, usize),
        _dst: (&mut Vec<f64>, &mut Vec<f64>),
    ) -> (usize, usize) {
        (0, at)
    }
}

/// The portable reader: [`number_prefix`] itself.
#[derive(Clone, Copy)]
struct Portable;

impl Reader for Portable {
    #[inline(always)]
    fn number(self, b: &[u8]) -> Option<(f64, usize)> {
        number_prefix(b)
    }
}

/// The number at the start of `b` and the bytes it takes, correctly rounded: the usual CSV
/// shapes by [`short_decimal`], everything else (and whatever it declines) by `fast-float2`,
/// whose longest-valid-prefix reading this keeps.
#[inline]
pub(crate) fn number_prefix(b: &[u8]) -> Option<(f64, usize)> {
    if let Some(x) = short_decimal(b) {
        return Some(x);
    }
    fast_float2::parse_partial::<f64, _>(b).ok()
}

/// `0x01` in every byte of a word.
const ONES: u64 = 0x0101_0101_0101_0101;

/// Exact powers of ten as f64 (10^22 is the largest exact one): Clinger's fast path.
const POW10_F64: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// The run of decimal digits at the start of the word `w` (little-endian, the first byte
/// lowest): its length (0 to 8) and its value. [`short_decimal`] reads exponents with it: a
/// fixed handful of operations instead of a loop with a data-dependent branch per digit (the
/// length from the first non-digit byte, the value by [`eight_digits`] on the digits shifted
/// to the word's high end, zeros before them).
#[inline(always)]
fn digit_run(w: u64) -> (usize, u64) {
    let t = w ^ (0x30 * ONES);
    // A byte is a digit iff t < 10: then t + 0x76 < 0x80, and no carry leaves a digit byte, so
    // the lowest flagged byte is the first non-digit (bytes after it may be flagged or not).
    let flags = (t.wrapping_add(0x76 * ONES) | t) & (0x80 * ONES);
    let len = (flags.trailing_zeros() / 8) as usize;
    // The digits to the high end (len = 0: shift by 64, masked to 0 below).
    let v = t.wrapping_shl(64 - 8 * len as u32) & 0u64.wrapping_sub(u64::from(len != 0));
    let v = eight_digits(v);
    (len, v)
}

/// Powers of ten as integers, to append a run of up to eight digits to a mantissa.
const POW10_U64: [u64; 9] = [
    1,
    10,
    100,
    1_000,
    10_000,
    100_000,
    1_000_000,
    10_000_000,
    100_000_000,
];

/// The value of eight decimal digits, one per byte of `v` (0 to 9 each, the first digit in the
/// lowest byte): three multiplies instead of a chain of eight.
#[inline(always)]
fn eight_digits(v: u64) -> u64 {
    let v = v.wrapping_mul(10).wrapping_add(v >> 8);
    ((v & 0x0000_00ff_0000_00ff).wrapping_mul(100 + (1_000_000 << 32))
        + ((v >> 16) & 0x0000_00ff_0000_00ff).wrapping_mul(1 + (10_000 << 32)))
        >> 32
}

/// A plain decimal at the start of `b`: `-`? digits? (`.` digits?)? with at least one digit, at
/// most 7 before the point and at most 15 bytes after the sign, then optionally (`e`|`E`)
/// (`+`|`-`)? and 1–4 digits, whose decimal exponent q (the written one minus the fraction's
/// digits) is within ±22. Then the
/// mantissa M < 10^15 < 2^53 and 10^|q| are exact doubles, and one correctly rounded multiply
/// or divide gives the correctly rounded value (Clinger's fast path, the value `fast-float2`
/// returns for it too). `None` for anything else (the caller falls back to `fast-float2`),
/// including text too near the end of `b` for the word reads.
///
/// Why: the `%.10g` numbers of a `fit-curve --batch` file (BENCHMARKS.md) are all of this
/// shape; `fast-float2` spends ~185 instructions on each (callgrind). Here the mantissa is read
/// as one 16-byte window (two words) without a loop: the bytes that are not digits flagged all
/// at once, the point and the end found from the flags, the point cut out by shifts, and the
/// digits converted eight at a time.
#[inline(always)]
fn short_decimal(b: &[u8]) -> Option<(f64, usize)> {
    // Sign, the 16-byte window, an exponent of up to 7 bytes.
    if b.len() < 32 {
        return None;
    }
    let neg = b[0] == b'-';
    let s = usize::from(neg);
    // The window as two words of digit values (bytes 0–9 where there are digits).
    let t0 = word(b, s) ^ (0x30 * ONES);
    let t1 = word(b, s + 8) ^ (0x30 * ONES);
    // Bit 7 of every byte that is not a digit (a digit byte is < 10 here; the low seven bits
    // plus 0x76 cannot carry into the next byte).
    let nondigit = |t: u64| (((t & (0x7f * ONES)) + 0x76 * ONES) | t) & (0x80 * ONES);
    let (f0, f1) = (nondigit(t0), nondigit(t1));
    // The first non-digit, at p: in the first word (at most 7 integer digits).
    if f0 == 0 {
        return None;
    }
    let first = f0 & f0.wrapping_neg();
    let p = (f0.trailing_zeros() / 8) as usize;
    let dot = b[s + p] == b'.';
    // The end of the mantissa, at e: the first non-digit that is not that point.
    let rest = if dot { f0 ^ first } else { f0 };
    let e = if rest != 0 {
        (rest.trailing_zeros() / 8) as usize
    } else {
        8 + (f1.trailing_zeros() / 8) as usize
    };
    if e >= 16 {
        return None;
    }
    let digits = e - usize::from(dot);
    if digits == 0 {
        return None;
    }
    // The digits together in bytes [0, digits) of (j0, j1): the bytes after the point moved
    // down over it (`below` masks the bytes before it, from its flag bit).
    let below = (first - 1) >> 7;
    let (j0, j1) = if dot {
        ((t0 & below) | ((t0 >> 8 | t1 << 56) & !below), t1 >> 8)
    } else {
        (t0, t1)
    };
    // Eight digits at a time, right-aligned in a word (zeros before them).
    let mant = if digits <= 8 {
        eight_digits(j0 << (8 * (8 - digits)))
    } else {
        eight_digits(j0) * POW10_U64[digits - 8] + eight_digits(j1 << (8 * (16 - digits)))
    };
    // Fraction digits (none without a point: then e = p).
    let q = -((e - p - usize::from(dot)) as i64);
    exponent_and_value(b, mant, q, s + e, neg)
}

/// The end of a plain decimal read by [`short_decimal`] or the vector reader: an optional
/// exponent at `b[end..]` (`e`|`E`, sign, 1–4 digits) added to the fraction's exponent `q`, then
/// Clinger's fast path for the mantissa `mant` (< 10^15) when |q| ≤ 22; `None` otherwise (the
/// caller falls back to `fast-float2`). Returns the value and the end of the number.
#[inline(always)]
fn exponent_and_value(
    b: &[u8],
    mant: u64,
    mut q: i64,
    mut end: usize,
    neg: bool,
) -> Option<(f64, usize)> {
    if b[end] | 0x20 == b'e' {
        let mut j = end + 1;
        let eneg = b[j] == b'-';
        j += usize::from(eneg || b[j] == b'+');
        let (ne, ev) = digit_run(word(b, j));
        if ne == 0 || ne > 4 {
            return None;
        }
        q += if eneg { -(ev as i64) } else { ev as i64 };
        end = j + ne;
    }
    let v = clinger(mant, q)?;
    Some((if neg { -v } else { v }, end))
}

/// mant · 10^q correctly rounded for mant < 10^15 (< 2^53) and |q| ≤ 22, where both are exact
/// doubles and one multiply or divide rounds once (Clinger's fast path, the value `fast-float2`
/// returns too); `None` for |q| > 22.
#[inline(always)]
fn clinger(mant: u64, q: i64) -> Option<f64> {
    if !(-22..=22).contains(&q) {
        return None;
    }
    // mant < 10^15: the signed conversion is one instruction, the unsigned one a sequence.
    let m = mant as i64 as f64;
    Some(if q >= 0 {
        m * POW10_F64[q as usize]
    } else {
        m / POW10_F64[(-q) as usize]
    })
}

/// The eight bytes at `b[i..]` as a little-endian word; bytes past the end read as 0.
#[inline(always)]
fn word(b: &[u8], i: usize) -> u64 {
    match b.get(i..i + 8) {
        Some(w) => u64::from_le_bytes(w.try_into().unwrap_or_default()),
        None => {
            let mut w = [0u8; 8];
            let tail = b.get(i..).unwrap_or_default();
            w[..tail.len()].copy_from_slice(tail);
            u64::from_le_bytes(w)
        }
    }
}

/// The vector number reader of x86-64 (SSE4.1, and AVX2's encoding where the CPU has it), by
/// the `pulp` crate's safe intrinsics, which the workspace's `unsafe_code = "deny"` requires.
///
/// Why by hand: reading the numbers was a third of `fit-curve --batch`'s time, and scalar
/// readers had run out of levers (BENCHMARKS.md, the scipy comparison's second pass:
/// word-at-a-time readers stay bound by their chains of shifts and multiplies, and each row's
/// start waited on the previous row's numbers being scanned). Here:
/// - the row loop ([`pairs`]) finds a row's comma and newline from one compare of the 32
///   bytes after its id, so the next row starts after one load and one scan while the
///   numbers' conversion overlaps the following rows;
/// - a field whose ends are known ([`field`]) is one 16-byte load: the digit and point bytes
///   flagged by two compares and read out as bit masks, its shape (length, point position)
///   one entry of a compile-time table ([`SHAPES`]) holding the digit mask to expect, the
///   shuffle that squeezes the point out and right-aligns the digits, and the power of ten;
///   the (up to 15) digits converted together by three multiply-adds and a pack;
/// - a number at the start of a text ([`decimal`], for the rows the loop declines) by the
///   same masks, its end found from them.
///
/// Every path ends in the exact fast path of [`short_decimal`] (Clinger: M < 10^15 < 2^53 and
/// |q| ≤ 22, one correctly rounded multiply or divide), so the bits are those `fast-float2`
/// gives; every other shape goes to [`number_prefix`]. No FMA anywhere: the results must
/// be the portable reader's bit for bit.
#[cfg(target_arch = "x86_64")]
mod simd {
    use super::{CurvesError, POW10_F64, Parser, Reader, number_prefix};
    use core::arch::x86_64::__m128i;
    use pulp::x86::V2;

    /// The vector reader: [`decimal`], else [`number_prefix`]. Holds the token that proves
    /// the CPU has SSE4.1.
    #[derive(Clone, Copy)]
    pub(super) struct Sse(pub(super) V2);

    impl Reader for Sse {
        #[inline(always)]
        fn number(self, b: &[u8]) -> Option<(f64, usize)> {
            match decimal(self.0, b) {
                Some(x) => Some(x),
                None => number_prefix(b),
            }
        }

        #[inline(always)]
        fn pairs(
            self,
            text: &[u8],
            at: usize,
            key: (u64, u64, usize),
            dst: (&mut Vec<f64>, &mut Vec<f64>),
        ) -> (usize, usize) {
            pairs(self.0, text, at, key, dst)
        }
    }

    /// What a plain decimal field of `len` bytes (after the sign) with its point at `p` (`p` >=
    /// `len`: no point) needs: the shuffle that squeezes the point out and right-aligns the
    /// digits, the digit mask its bytes must show, and the power of ten to divide by.
    #[derive(Clone, Copy)]
    struct Shape {
        shuffle: [u8; 16],
        /// `u32::MAX` where the shape is not a number [`field`] reads this way (no digit, or
        /// more than 15): no digit mask of a field of at most 16 bytes is that.
        digits: u32,
        divisor: f64,
    }

    /// [`Shape`]s by (`len`, `p`), `len` and `p` <= 16, built at compile time.
    static SHAPES: [[Shape; 17]; 17] = shapes();

    const fn shapes() -> [[Shape; 17]; 17] {
        let none = Shape {
            shuffle: [0x80; 16],
            digits: u32::MAX,
            divisor: 1.0,
        };
        let mut table = [[none; 17]; 17];
        let mut len = 0;
        while len <= 16 {
            // A point at or past the end (the next field's, or none: `p` = 16) is no point.
            let mut p = 0;
            while p <= 16 {
                let dot = p < len;
                let n = len - dot as usize;
                if n >= 1 && n <= 15 {
                    let mut shuffle = [0x80u8; 16];
                    let mut t = 0;
                    while t < n {
                        let from = if dot && t >= p { t + 1 } else { t };
                        shuffle[16 - n + t] = from as u8;
                        t += 1;
                    }
                    let all = (1u32 << len) - 1;
                    let frac = if dot { len - p - 1 } else { 0 };
                    table[len][p] = Shape {
                        shuffle,
                        digits: if dot { all & !(1u32 << p) } else { all },
                        divisor: POW10_F64[frac],
                    };
                }
                p += 1;
            }
            len += 1;
        }
        table
    }

    /// The number that is exactly `text[start..end]` (a field whose ends the row's scan found).
    /// Plain decimals (`-`? digits with at most one point, 1 to 15 digits, 16 bytes at most
    /// after the sign: every field `%.10g` writes without an exponent) by one table entry
    /// ([`SHAPES`]): the shape is the field's length and its point's position, so one compare
    /// of the digit mask checks it, one shuffle aligns its digits and the fraction's power of
    /// ten is a division by an exact double (q <= 0: Clinger's fast path, always a division,
    /// by 1 for integers). Anything else by [`field_general`].
    #[inline(always)]
    pub(super) fn field(simd: V2, text: &[u8; 128], start: usize, end: usize) -> Option<f64> {
        if *text.get(start)? == b'-' {
            // Rare in these files, so on a branch of its own: the magnitude (with no second
            // sign), negated (exactly: a sign flip, −0 for 0).
            if matches!(text.get(start + 1), Some(b'-' | b'+')) {
                return None;
            }
            return magnitude(simd, text, start + 1, end).map(|v| -v);
        }
        magnitude(simd, text, start, end)
    }

    /// [`field`] without a sign: `text[start]` is not `-`.
    #[inline(always)]
    fn magnitude(simd: V2, text: &[u8; 128], start: usize, end: usize) -> Option<f64> {
        let len = end.checked_sub(start)?;
        if len > 16 {
            return None;
        }
        let window: [u8; 16] = text.get(start..start + 16)?.try_into().ok()?;
        let x: __m128i = pulp::cast(window);
        let (sse2, ssse3) = (simd.sse2, simd.ssse3);
        let d = sse2._mm_sub_epi8(x, sse2._mm_set1_epi8(b'0' as i8));
        let is_digit = sse2._mm_cmpeq_epi8(sse2._mm_min_epu8(d, sse2._mm_set1_epi8(9)), d);
        let is_dot = sse2._mm_cmpeq_epi8(x, sse2._mm_set1_epi8(b'.' as i8));
        let digit = sse2._mm_movemask_epi8(is_digit) as u32;
        let dots = sse2._mm_movemask_epi8(is_dot) as u32;
        let p = (dots | 1 << 16).trailing_zeros() as usize;
        let shape = &SHAPES[len][p];
        if digit & ((1u32 << len) - 1) != shape.digits {
            return field_general(simd, text, start, end);
        }
        let digits_right = ssse3._mm_shuffle_epi8(d, pulp::cast(shape.shuffle));
        let mant = mantissa_of(simd, digits_right);
        Some(mant as i64 as f64 / shape.divisor)
    }

    /// [`field`] for every shape: the number that is exactly `text[start..end]`, in
    /// the shapes of [`decimal`] with at most 3 exponent digits and 16 bytes after the sign;
    /// `None` for anything else. Knowing the end beforehand, no scan for it is needed: the
    /// digit, point and exponent-letter bytes are three masks, and the shape is checked
    /// against them with a few bit operations.
    #[inline(always)]
    fn field_general(simd: V2, text: &[u8; 128], start: usize, end: usize) -> Option<f64> {
        let neg = *text.get(start)? == b'-';
        let a = start + usize::from(neg);
        let len = end.checked_sub(a)? as u32;
        if len > 16 {
            return None;
        }
        let window: [u8; 16] = text.get(a..a + 16)?.try_into().ok()?;
        let x: __m128i = pulp::cast(window);
        let sse2 = simd.sse2;
        let d = sse2._mm_sub_epi8(x, sse2._mm_set1_epi8(b'0' as i8));
        let is_digit = sse2._mm_cmpeq_epi8(sse2._mm_min_epu8(d, sse2._mm_set1_epi8(9)), d);
        let is_dot = sse2._mm_cmpeq_epi8(x, sse2._mm_set1_epi8(b'.' as i8));
        let is_e = sse2._mm_cmpeq_epi8(
            sse2._mm_or_si128(x, sse2._mm_set1_epi8(0x20)),
            sse2._mm_set1_epi8(b'e' as i8),
        );
        let digit = sse2._mm_movemask_epi8(is_digit) as u32;
        let dots = sse2._mm_movemask_epi8(is_dot) as u32;
        let es = sse2._mm_movemask_epi8(is_e) as u32;
        // The mantissa is bytes [0, k): up to the exponent letter or the end.
        let k = (es | 1 << len).trailing_zeros();
        let mantissa = (1u32 << k) - 1;
        let point = dots & mantissa;
        let dot = point != 0;
        // At most one point, every other byte of the mantissa a digit, 1 to 15 digits.
        if point & point.wrapping_sub(1) != 0 || digit & mantissa != mantissa ^ point {
            return None;
        }
        let digits = k - u32::from(dot);
        if digits == 0 || digits > 15 {
            return None;
        }
        let p = if dot { point.trailing_zeros() } else { 16 };
        let digits_right = right_aligned(simd, d, digits, p);
        let mant = mantissa_of(simd, digits_right);
        let mut q = if dot { p as i32 + 1 - k as i32 } else { 0 };
        if k < len {
            // (`e`|`E`) (`+`|`-`)? and 1 to 3 digits up to the end.
            let sign = *text.get(a + k as usize + 1)?;
            let eneg = sign == b'-';
            let from = k + 1 + u32::from(eneg || sign == b'+');
            let run = (1u32 << len) - (1u32 << from.min(len));
            if from >= len || len - from > 3 || digit & run != run {
                return None;
            }
            let mut ev = 0i32;
            for &c in text.get(a + from as usize..a + len as usize)? {
                ev = ev * 10 + i32::from(c - b'0');
            }
            q += if eneg { -ev } else { ev };
        }
        let v = super::clinger(mant, i64::from(q))?;
        Some(if neg { -v } else { v })
    }

    /// The separators (commas and newlines) and the commas among the 16 bytes at `row[at..]`,
    /// as bit masks.
    #[inline(always)]
    fn seps16(simd: V2, row: &[u8; 128], at: usize) -> Option<(u32, u32)> {
        let sse2 = simd.sse2;
        let window: [u8; 16] = row.get(at..at + 16)?.try_into().ok()?;
        let x: __m128i = pulp::cast(window);
        let comma = sse2._mm_cmpeq_epi8(x, sse2._mm_set1_epi8(b',' as i8));
        let newline = sse2._mm_cmpeq_epi8(x, sse2._mm_set1_epi8(b'\n' as i8));
        let seps = sse2._mm_movemask_epi8(sse2._mm_or_si128(comma, newline)) as u32;
        Some((seps, sse2._mm_movemask_epi8(comma) as u32))
    }

    /// [`Reader::pairs`] for the vector reader: the rows of one curve while each is its id
    /// (`key`), then exactly two fields, each one number of [`field`]'s shapes (else of
    /// [`field_general`]'s), ended by a comma and a newline. The 32 bytes after the id are
    /// scanned for separators at once, so a row's start depends on the previous row through
    /// one load and one scan (the numbers' conversion overlaps the next rows), and every read
    /// is inside a 128-byte window of the row (rows that start in the last 128 bytes of `text`
    /// are left to the caller). Stops at the first row that is not so.
    #[inline(always)]
    pub(super) fn pairs(
        simd: V2,
        text: &[u8],
        mut at: usize,
        (key, mask, len): (u64, u64, usize),
        (r, v): (&mut Vec<f64>, &mut Vec<f64>),
    ) -> (usize, usize) {
        let Some(limit) = text.len().checked_sub(128) else {
            return (0, at);
        };
        let (mut rows, mut held) = (0, 0);
        let (mut xs, mut ys) = ([0.0f64; BATCH], [0.0f64; BATCH]);
        while at < limit {
            let Some(row) = text
                .get(at..at + 128)
                .and_then(|t| <&[u8; 128]>::try_from(t).ok())
            else {
                break;
            };
            let head: [u8; 8] = row[..8].try_into().unwrap_or_default();
            // (The key is at most one word: the bound lets the compiler drop bounds checks.)
            if u64::from_le_bytes(head) & mask != key || len > 8 {
                break;
            }
            // Both separators of the row from one mask of the 32 bytes after the id.
            let (Some((seps_lo, commas_lo)), Some((seps_hi, commas_hi))) =
                (seps16(simd, row, len), seps16(simd, row, len + 16))
            else {
                break;
            };
            let seps = seps_lo | seps_hi << 16;
            let commas = commas_lo | commas_hi << 16;
            let rest = seps & seps.wrapping_sub(1);
            // The first separator a comma, the second a newline (not a comma).
            if rest == 0
                || commas & seps & seps.wrapping_neg() == 0
                || commas & rest & rest.wrapping_neg() != 0
            {
                break;
            }
            let s1 = len + seps.trailing_zeros() as usize;
            let s2 = len + rest.trailing_zeros() as usize;
            let Some(x) = field(simd, row, len, s1) else {
                break;
            };
            let Some(y) = field(simd, row, s1 + 1, s2) else {
                break;
            };
            xs[held % BATCH] = x;
            ys[held % BATCH] = y;
            held += 1;
            if held == BATCH {
                r.extend_from_slice(&xs);
                v.extend_from_slice(&ys);
                held = 0;
            }
            rows += 1;
            at += s2 + 1;
        }
        r.extend_from_slice(&xs[..held]);
        v.extend_from_slice(&ys[..held]);
        (rows, at)
    }

    /// Rows read at a time into arrays before they are appended to the curve's vectors: the
    /// vectors' lengths then stay out of the row loop.
    const BATCH: usize = 16;

    /// [`Parser::rows`] with the vector reader, as the job `pulp` compiles for the CPU's
    /// instruction set: a type with an `#[inline(always)]` call rather than a closure, whose
    /// body (compiled apart, without the target features) would call every intrinsic as a
    /// function.
    pub(super) struct Rows<'a, const N: usize> {
        pub(super) parser: &'a mut Parser,
        pub(super) line_no: usize,
        pub(super) text: &'a [u8],
        pub(super) at: usize,
        pub(super) count: usize,
        pub(super) reader: Sse,
    }

    impl<const N: usize> pulp::NullaryFnOnce for Rows<'_, N> {
        type Output = Result<usize, CurvesError>;

        #[inline(always)]
        fn call(self) -> Self::Output {
            self.parser
                .rows::<N, Sse>(self.line_no, self.text, self.at, self.count, self.reader)
        }
    }

    /// Byte j holds j − 16 (as i8): added to the digit count, the index of the digit that goes
    /// to byte j when the digits are right-aligned (negative, so zero, before the first).
    const FROM_END: [i8; 16] = [
        -16, -15, -14, -13, -12, -11, -10, -9, -8, -7, -6, -5, -4, -3, -2, -1,
    ];

    /// The digit values `d` (bytes 0–9) moved to the right end of the register with the point
    /// squeezed out: byte j takes digit t = j − 16 + `digits`, which sits at byte t, or t + 1 at
    /// and after the point at byte `p` (no point: `p` = 16, never reached); t < 0 gives 0. One
    /// `pshufb` whose control is computed, for shapes the table of [`SHAPES`] does not hold.
    #[inline(always)]
    fn right_aligned(simd: V2, d: __m128i, digits: u32, p: u32) -> __m128i {
        let (sse2, ssse3) = (simd.sse2, simd.ssse3);
        let t = sse2._mm_add_epi8(pulp::cast(FROM_END), sse2._mm_set1_epi8(digits as i8));
        let after = sse2._mm_cmpgt_epi8(t, sse2._mm_set1_epi8(p as i8 - 1));
        ssse3._mm_shuffle_epi8(d, sse2._mm_sub_epi8(t, after))
    }

    /// The integer of 16 right-aligned digit values (at most 15 non-zero: < 10^15): pairs,
    /// fours, then eights of digits by multiply-adds, the first eight in lane 0, the last in
    /// lane 1.
    #[inline(always)]
    fn mantissa_of(simd: V2, digits_right: __m128i) -> u64 {
        let (sse2, ssse3, sse4_1) = (simd.sse2, simd.ssse3, simd.sse4_1);
        let pairs = ssse3._mm_maddubs_epi16(
            digits_right,
            pulp::cast([10u8, 1, 10, 1, 10, 1, 10, 1, 10, 1, 10, 1, 10, 1, 10, 1]),
        );
        let fours = sse2._mm_madd_epi16(pairs, pulp::cast([100i16, 1, 100, 1, 100, 1, 100, 1]));
        let fours = sse4_1._mm_packus_epi32(fours, fours);
        let eights = sse2._mm_madd_epi16(
            fours,
            pulp::cast([10_000i16, 1, 10_000, 1, 10_000, 1, 10_000, 1]),
        );
        let [high, low, _, _]: [u32; 4] = pulp::cast(eights);
        u64::from(high) * 100_000_000 + u64::from(low)
    }

    /// A plain decimal at the start of `b`: `-`? digits? (`.` digits?)? with 1 to 15 digits,
    /// 15 bytes at most after the sign, then optionally (`e`|`E`) (`+`|`-`)? and 1–4 digits,
    /// the decimal exponent q (the written one minus the fraction's digits) within ±22: the
    /// value and the bytes it takes. `None` for anything else, and when `b` has fewer than 32
    /// bytes (the loads need 16 after the sign and a word at the exponent).
    #[inline(always)]
    pub(super) fn decimal(simd: V2, b: &[u8]) -> Option<(f64, usize)> {
        if b.len() < 32 {
            return None;
        }
        let neg = b[0] == b'-';
        let s = usize::from(neg);
        let window: [u8; 16] = b.get(s..s + 16)?.try_into().ok()?;
        let x: __m128i = pulp::cast(window);
        let sse2 = simd.sse2;
        // Digit values (bytes 0–9 where there are digits) and the masks of digits and points.
        let d = sse2._mm_sub_epi8(x, sse2._mm_set1_epi8(b'0' as i8));
        let is_digit = sse2._mm_cmpeq_epi8(sse2._mm_min_epu8(d, sse2._mm_set1_epi8(9)), d);
        let is_dot = sse2._mm_cmpeq_epi8(x, sse2._mm_set1_epi8(b'.' as i8));
        // Non-digits, with every bit from 16 up set: the scans below end at 16 at the latest.
        let nondigit = !(sse2._mm_movemask_epi8(is_digit) as u32);
        let dots = sse2._mm_movemask_epi8(is_dot) as u32;
        // The first non-digit, at p; if it is a point, the end is the next one.
        let first = nondigit & nondigit.wrapping_neg();
        let dot = dots & first != 0;
        let p = nondigit.trailing_zeros();
        let e = if dot { nondigit ^ first } else { nondigit }.trailing_zeros();
        let digits = e - u32::from(dot);
        if e >= 16 || digits == 0 {
            return None;
        }
        let digits_right = right_aligned(simd, d, digits, if dot { p } else { 16 });
        let mant = mantissa_of(simd, digits_right);
        // Fraction digits (none without a point).
        let q = -(if dot { e - p - 1 } else { 0 } as i64);
        super::exponent_and_value(b, mant, q, s + e as usize, neg)
    }
}

/// Channels a header announces, or `None` if it is not a known header.
fn header(fields: &[&str], batch: bool) -> Option<usize> {
    let rest = if batch {
        match fields.split_first() {
            Some((id, rest)) if id.eq_ignore_ascii_case("id") => rest,
            _ => return None,
        }
    } else {
        fields
    };
    let is = |f: &str, name: &str| f.eq_ignore_ascii_case(name);
    match rest {
        [r, v] if is(r, "r") && is(v, "value") => Some(1),
        [r, a, b, c] if is(r, "r") && is(a, "r_value") && is(b, "g_value") && is(c, "b_value") => {
            Some(3)
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::Strategy;
    use proptest::prop_oneof;

    #[test]
    fn errors_name_the_line() {
        let e = parse("# c\nr,value\n1,2\n3\n", false)
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 4"), "{e}");
        let e = parse("r,value\n1,abc\n", false).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("abc"), "{e}");
        let e = parse("x,y\n", false).unwrap_err().to_string();
        assert!(e.contains("line 1"), "{e}");
        let e = parse("r,value\n", true).unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("id"), "{e}");
        assert_eq!(
            parse("# only comments\n", false),
            Err(CurvesError::NoHeader)
        );
        // Too many columns, even past the widest format.
        let e = parse("r,value\n1,2,3,4,5,6,7\n", false).unwrap_err();
        assert!(
            matches!(
                e,
                CurvesError::Columns {
                    line: 2,
                    got: 7,
                    ..
                }
            ),
            "{e}"
        );
    }

    #[test]
    fn number_parsing_is_the_standard_librarys() {
        let mut cases: Vec<String> = [
            "0",
            "-0",
            "1",
            "+1",
            "0.5",
            ".5",
            "5.",
            "1e3",
            "1E-3",
            "-2.5e+10",
            "123456789012345678",
            "1234567890123456789",
            "12345678901234567890",
            "9007199254740993",
            "0.1",
            "0.3",
            "1e22",
            "1e23",
            "1e-22",
            "1e-23",
            "2.2250738585072014e-308",
            "4.9e-324",
            "1.7976931348623157e308",
            "1e400",
            "NaN",
            "inf",
            "-inf",
            "00012.5000",
            "3.141592653589793238462643383279",
            "12.09039342",
            "0.6002071621",
            "5.096327544e-05",
            "1.e5",
            "-.5e-3",
            "5e+0000007",
            "5e00000007",
            "0.00000000000000000000001",
            "123456789.5",
            "1234567.123456789012345",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let mut seed = 7u64;
        for _ in 0..20_000 {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let v = f64::from_bits(seed >> 2) * if seed & 1 == 0 { 1.0 } else { -1.0 };
            if v.is_finite() {
                cases.push(format!("{v:e}"));
                cases.push(format!("{v:.9e}"));
                cases.push(format!("{}", (seed >> 40) as f64 / 1e7));
            }
            // Digits split every way around the point (0 to 17 after it, 1 to 9 before it),
            // with and without exponents.
            let x = (seed >> 11) as f64 / (1u64 << 53) as f64 * 10f64.powi((seed % 9) as i32);
            let k = (seed >> 5) as usize % 18;
            cases.push(format!("{x:.k$}"));
            cases.push(format!("-{x:.k$}e-{}", seed % 30));
            cases.push(format!("{x:.k$}E+{}", seed % 25));
        }
        for c in &cases {
            let want = c.parse::<f64>().ok().map(f64::to_bits);
            assert_eq!(parse_f64(c).map(f64::to_bits), want, "{c}");
            // The row parser's prefix reading, as a whole field and followed by a comma.
            let whole = number_prefix(c.as_bytes()).filter(|p| p.1 == c.len());
            assert_eq!(whole.map(|p| p.0.to_bits()), want, "{c}");
            let then = format!("{c},7");
            let prefix = number_prefix(then.as_bytes()).filter(|p| p.1 == c.len());
            assert_eq!(prefix.map(|p| p.0.to_bits()), want, "{c},");
            // Inside a block, with room for [`short_decimal`]'s word reads.
            let row = format!("{c},7\n{PAD}");
            let prefix = number_prefix(row.as_bytes()).filter(|p| p.1 == c.len());
            assert_eq!(prefix.map(|p| p.0.to_bits()), want, "{c}, in a block");
        }
        for bad in [
            "", "-", ".", "e5", "1e", "1.2.3", "1e5x", "abc", "--1", "1 2", "-.", "1e-", "+-1",
        ] {
            assert_eq!(parse_f64(bad), None, "{bad}");
            assert!(
                number_prefix(bad.as_bytes()).is_none_or(|p| p.1 < bad.len()),
                "{bad}"
            );
        }
    }

    /// What follows a number inside a block: more rows, enough for the word reads.
    const PAD: &str = "0,12.09039342,5.096327544e-05\n0,1,2\n";

    /// Text around a number in every shape the CSV reader may meet: short and long digit runs,
    /// points anywhere, exponents of any length, signs, and what may follow.
    fn decimal_text() -> impl Strategy<Value = String> {
        let number = prop_oneof![
            "[-+]?[0-9]{0,20}(\\.[0-9]{0,20})?([eE][-+]?[0-9]{0,6})?",
            "-?[0-9]{1,4}\\.[0-9]{1,12}([eE][-+][0-9]{2})?",
            "-?[0-9]{0,3}\\.?[0-9]{0,3}([eE][-+]?[0-9]{1,3})?",
            "-?(0|00|[1-9][0-9]{0,15})(\\.[0-9]{0,16})?(e-?[0-9]{1,2})?",
            "-?[0-9.eE+-]{0,10}|inf|-inf|NaN|nan|infinity",
        ];
        let tail = "[,\\n\\r.eE+0-9x -]{0,3}";
        (number, tail, 0usize..3).prop_map(|(n, t, pads)| format!("{n}{t}{}", PAD.repeat(pads)))
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(20_000))]
        /// The row parser's number reading is `fast-float2`'s longest-prefix reading, bit for
        /// bit and byte for byte, and on whole fields the standard library's; where
        /// [`short_decimal`] answers at all, it answers the same.
        #[test]
        fn number_prefix_is_fast_float_and_std(text in decimal_text()) {
            let b = text.as_bytes();
            let want = fast_float2::parse_partial::<f64, _>(b).ok().map(|(v, k)| (v.to_bits(), k));
            let got = number_prefix(b).map(|(v, k)| (v.to_bits(), k));
            proptest::prop_assert_eq!(got, want, "{:?}", text);
            if let Some((v, k)) = short_decimal(b) {
                proptest::prop_assert_eq!(Some((v.to_bits(), k)), want, "{:?}", text);
            }
            if let Some((_, k)) = want
                && matches!(b.get(k), None | Some(b',' | b'\n'))
            {
                let field = &text[..k];
                let std = field.parse::<f64>().ok().map(f64::to_bits);
                proptest::prop_assert_eq!(got.map(|g| g.0), std, "{:?}", field);
            }
        }
    }

    /// [`short_decimal`] reads the shapes `%.10g` writes (so the comparison above is not
    /// vacuous) and declines what it cannot read exactly.
    #[test]
    fn short_decimal_takes_the_usual_shapes() {
        for (text, v, k) in [
            ("12.09039342", 12.09039342, 11),
            ("5.096327544e-05", 5.096327544e-05, 15),
            ("0.6002071621", 0.6002071621, 12),
            ("-3", -3.0, 2),
            ("5.", 5.0, 2),
            (".5", 0.5, 2),
            ("-0", -0.0, 2),
            ("1.5E+3", 1500.0, 6),
            ("1.2.3", 1.2, 3),
            ("9999999.9999999", 9_999_999.999_999_9, 15),
            ("1234567", 1_234_567.0, 7),
        ] {
            let row = format!("{text},{PAD}");
            let got = short_decimal(row.as_bytes());
            assert_eq!(
                got.map(|(x, n)| (x.to_bits(), n)),
                Some((f64::to_bits(v), k)),
                "{text}"
            );
        }
        for text in [
            "",
            "-",
            ".",
            "+1",
            "inf",
            "NaN",
            "1e",
            "1e+",
            "1e400",
            "1e-23",
            "1e23",
            "1234567890123456",
            "0.000000000000001",
            "12345678",
            "12345678.5",
            "1e12345",
        ] {
            let row = format!("{text},{PAD}");
            assert_eq!(short_decimal(row.as_bytes()), None, "{text}");
        }
        // Too near the end of the text for the word reads: the crate's reading.
        assert_eq!(short_decimal(b"1.5,2\n"), None);
        assert_eq!(number_prefix(b"1.5,2\n"), Some((1.5, 3)));
    }

    /// The vector readers' two ways of reading a number, each where it answers at all,
    /// against the portable [`number_prefix`] (itself held to `fast-float2` above): a number
    /// at the start of a text ([`simd::decimal`], what the vector reader's `number` uses) and
    /// a field whose end is known ([`simd::field`], what its row loop uses).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_numbers_are_number_prefix() {
        let Some(v2) = pulp::x86::V2::try_new() else {
            return;
        };
        let mut runner = proptest::test_runner::TestRunner::new(
            proptest::test_runner::Config::with_cases(20_000),
        );
        runner
            .run(&decimal_text(), |text| {
                let b = text.as_bytes();
                let want = number_prefix(b).map(|(v, k)| (v.to_bits(), k));
                if let Some((v, k)) = simd::decimal(v2, b) {
                    proptest::prop_assert_eq!(Some((v.to_bits(), k)), want, "{:?}", text);
                }
                proptest::prop_assert_eq!(
                    simd::Sse(v2).number(b).map(|(v, k)| (v.to_bits(), k)),
                    want,
                    "{:?}",
                    text
                );
                // The text up to its first separator as a field of a row, whose reading is
                // the portable reader's when the whole field is one number.
                let field = text.split([',', '\n']).next().unwrap_or_default();
                if field.len() <= 60 {
                    let mut row = [b'0'; 128];
                    row[..2].copy_from_slice(b"7,");
                    row[2..2 + field.len()].copy_from_slice(field.as_bytes());
                    row[2 + field.len()] = b'\n';
                    let whole = number_prefix(&row[2..])
                        .filter(|p| p.1 == field.len())
                        .map(|p| p.0.to_bits());
                    if let Some(v) = simd::field(v2, &row, 2, 2 + field.len()) {
                        proptest::prop_assert_eq!(Some(v.to_bits()), whole, "{:?}", field);
                    }
                }
                Ok(())
            })
            .unwrap();
    }

    /// The vector readers read the usual shapes themselves (so the comparisons above and
    /// below are not vacuous): on this machine (every x86-64 test machine has SSE4.1) the
    /// number and field readers answer for `%.10g`'s shapes, and the row loop takes every
    /// row of a block but those in its last 128 bytes.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_reader_takes_the_usual_shapes() {
        let v2 = pulp::x86::V2::try_new().expect("an x86-64 machine with SSE4.1");
        for (text, v) in [
            ("12.09039342", 12.09039342f64),
            ("5.096327544e-05", 5.096327544e-05),
            ("0.6002071621", 0.6002071621),
            ("0.0005610659461", 0.0005610659461),
            ("139.2325188", 139.2325188),
            ("-3", -3.0),
            ("5.", 5.0),
            (".5", 0.5),
            ("-0", -0.0),
            ("1.5E+3", 1500.0),
            ("123456789012345", 123_456_789_012_345.0),
        ] {
            let padded = format!("{text},{PAD}{PAD}");
            assert_eq!(
                simd::decimal(v2, padded.as_bytes()).map(|(x, k)| (x.to_bits(), k)),
                Some((v.to_bits(), text.len())),
                "{text}"
            );
            let mut row = [b'0'; 128];
            row[..2].copy_from_slice(b"0,");
            row[2..2 + text.len()].copy_from_slice(text.as_bytes());
            row[2 + text.len()] = b'\n';
            assert_eq!(
                simd::field(v2, &row, 2, 2 + text.len()).map(f64::to_bits),
                Some(v.to_bits()),
                "{text}"
            );
        }
        let row = "17,12.09039342,5.096327544e-05\n";
        let text = row.repeat(100);
        let key = (u64::from_le_bytes(*b"17,\0\0\0\0\0"), 0xff_ffff, 3);
        let (mut r, mut v) = (Vec::new(), Vec::new());
        let (rows, at) = simd::pairs(v2, text.as_bytes(), 0, key, (&mut r, &mut v));
        let expected = (text.len() - 128).div_ceil(row.len());
        assert_eq!((rows, at), (expected, expected * row.len()));
        assert_eq!(r, vec![12.09039342; rows]);
        assert_eq!(v, vec![5.096327544e-05; rows]);
    }

    /// [`read`] with the given row readers, the text handed out `step` bytes at a time.
    fn read_with(
        text: &[u8],
        batch: bool,
        readers: Readers,
        step: usize,
    ) -> Result<Vec<Curve>, String> {
        let mut p = Parser::new(batch);
        p.readers = readers;
        stream(Trickle(text, step), &mut p, |_| Ok(false)).map_err(|e| e.to_string())?;
        p.finish().map_err(|e| e.to_string())
    }

    /// A curve file of rows in the shapes the readers meet: the usual `%.10g` numbers mostly,
    /// any decimal, odd values and text sometimes, ids that repeat (rows of a curve together)
    /// or not, and now and then a CRLF, a comment, a blank line, spaces or a wrong column count.
    fn curve_file() -> impl Strategy<Value = (bool, String)> {
        let number = prop_oneof![
            8 => "-?[0-9]{1,4}\\.[0-9]{1,12}(e-0[1-9])?",
            2 => "[-+]?[0-9]{0,17}(\\.[0-9]{0,17})?([eE][-+]?[0-9]{0,4})?",
            1 => "inf|NaN|-0|0|1e400|1e-400|x|-|\\.|1\\.2\\.3",
        ];
        let end = prop_oneof![
            20 => proptest::strategy::Just("\n"),
            1 => proptest::strategy::Just("\r\n"),
            1 => proptest::strategy::Just(" # c\n"),
            1 => proptest::strategy::Just("\n\n"),
            1 => proptest::strategy::Just(",5\n"),
        ];
        let id = prop_oneof![6 => "[0-2]", 1 => "[a-z]{1,9}", 1 => " 1"];
        let row = (id, number.clone(), number, end);
        (proptest::bool::ANY, proptest::collection::vec(row, 0..300)).prop_map(|(batch, rows)| {
            let mut text = String::from(if batch { "id,r,value\n" } else { "r,value\n" });
            for (id, r, v, end) in rows {
                if batch {
                    text += &format!("{id},");
                }
                text += &format!("{r},{v}{end}");
            }
            (batch, text)
        })
    }

    /// Every number of the curves as its bits (NaN compared as bits too).
    type Bits = Vec<(Option<String>, Vec<u64>, Vec<Vec<u64>>)>;

    fn bits(curves: &[Curve]) -> Bits {
        let b = |x: &Vec<f64>| x.iter().map(|v| v.to_bits()).collect();
        curves
            .iter()
            .map(|c| (c.id.clone(), b(&c.r), c.channels.iter().map(b).collect()))
            .collect()
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2_000))]
        /// Whole files read by the vector readers (AVX2 where the machine has it, SSE4.1) are
        /// the portable reader's: the same curves bit for bit, or the same error, whether
        /// the text arrives at once or in pieces.
        #[test]
        fn vector_rows_are_portable_rows((batch, text) in curve_file()) {
            for step in [usize::MAX, 97] {
                let want = read_with(text.as_bytes(), batch, Readers::Portable, step);
                for readers in [Readers::Best, Readers::Sse41] {
                    let got = read_with(text.as_bytes(), batch, readers, step);
                    match (&got, &want) {
                        (Ok(g), Ok(w)) => proptest::prop_assert_eq!(bits(g), bits(w)),
                        _ => proptest::prop_assert_eq!(&got, &want),
                    }
                }
            }
        }
    }

    /// A reader that hands out a few bytes at a time, so lines straddle every read.
    struct Trickle<'a>(&'a [u8], usize);
    impl std::io::Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let k = self.1.min(buf.len()).min(self.0.len());
            buf[..k].copy_from_slice(&self.0[..k]);
            self.0 = &self.0[k..];
            Ok(k)
        }
    }

    #[test]
    fn streaming_read_is_parse() {
        let text = "# c\r\nid,r,value\r\na,0,1 # x\r\n\r\nb, 1e-3 ,2.5\na,1,NaN\nb,+2,-0\nb,3,4";
        for step in [1, 3, 7, 1000] {
            let streamed = read(Trickle(text.as_bytes(), step), true).unwrap();
            assert_eq!(streamed.len(), 2);
            assert_eq!(streamed[1].r, vec![1e-3, 2.0, 3.0]);
            assert_eq!(streamed[1].channels[0], vec![2.5, -0.0, 4.0]);
            let parsed = parse(text, true).unwrap();
            assert_eq!(format!("{streamed:?}"), format!("{parsed:?}"), "{step}");
        }
        // A line longer than the read buffer.
        let long = format!("r,value\n{}1,2\n3,4\n", " ".repeat(3 * CHUNK));
        let c = read(long.as_bytes(), false).unwrap();
        assert_eq!(c[0].r, vec![1.0, 3.0]);
        // Errors name the line, wherever the reads split.
        for step in [1, 5, 1000] {
            let bad = "id,r,value\na,0,1\na,1,x2\n";
            let e = read(Trickle(bad.as_bytes(), step), true)
                .unwrap_err()
                .to_string();
            assert!(e.contains("line 3") && e.contains("x2"), "{e}");
            let e = read(Trickle(b"id,r,value\n\xff,0,1\n", step), true)
                .unwrap_err()
                .to_string();
            assert!(e.contains("line 2") && e.contains("UTF-8"), "{e}");
        }
    }

    /// `read_groups` hands out the curves of `read`, complete and in order, whatever the block
    /// boundaries, and says when an id comes back after its curve was handed out.
    #[test]
    fn grouped_reading_is_read_or_says_interleaved() {
        let mut text = String::from("# c\nid,r,value\n");
        for id in ["a", "b", "long-identifier", "c"] {
            for k in 0..50 {
                text += &format!("{id},{k},{}\n", k + 1);
            }
        }
        text += "d,0,1"; // no newline at the end
        let whole = read(text.as_bytes(), true).unwrap();
        for step in [1, 7, 64, 100_000] {
            let mut got: Vec<Curve> = Vec::new();
            let mut calls = 0;
            let end = read_groups(Trickle(text.as_bytes(), step), true, |g| {
                calls += 1;
                got.extend(g);
            })
            .unwrap();
            assert_eq!(end, Grouped::Complete);
            assert_eq!(got, whole, "{step}");
            assert!(step > 1000 || calls > 1, "{step}: {calls}");
        }
        // Single-curve files are one group at the end.
        let single = "r,value\n0,1\n1,2\n";
        let mut got = Vec::new();
        let end = read_groups(Trickle(single.as_bytes(), 3), false, |g| got.extend(g)).unwrap();
        assert_eq!(
            (end, got),
            (Grouped::Complete, read(single.as_bytes(), false).unwrap())
        );
        // An id whose rows are apart, noticed once its first curve has been handed out.
        let apart = format!("{text}\na,99,1\n");
        let end = read_groups(Trickle(apart.as_bytes(), 5), true, |_| {}).unwrap();
        assert_eq!(end, Grouped::Interleaved);
        // Errors name the line as `read` does.
        let e = read_groups(Trickle(b"id,r,value\na,0,1\nb,1,x\n", 4), true, |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 3"), "{e}");
    }

    #[test]
    fn groups_batch_ids_and_keeps_nan() {
        let c = parse("id,r,value # header\na,0,1\nb,0,2\na,1,NaN\n", true).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c[0].id.as_deref(), Some("a"));
        assert_eq!(c[0].r, vec![0.0, 1.0]);
        assert!(c[0].channels[0][1].is_nan());
        assert_eq!(c[1].channels[0], vec![2.0]);
        let rgb = parse("r,r_value,g_value,b_value\n0,1,2,3\n\n1, 4 ,5,6\n", false).unwrap();
        assert_eq!(rgb.len(), 1);
        assert_eq!(rgb[0].id, None);
        assert_eq!(
            rgb[0].channels,
            vec![vec![1.0, 4.0], vec![2.0, 5.0], vec![3.0, 6.0]]
        );
        // Ids longer than one word, ids that are prefixes of others, rows of an id apart.
        let c = parse(
            "id,r,value\nlong-identifier,0,1\nlong-identifier,1,2\n1,0,3\n12,0,4\n1,1,5\nlong-identifier,2,6\n",
            true,
        )
        .unwrap();
        let ids: Vec<_> = c.iter().map(|c| c.id.as_deref().unwrap()).collect();
        assert_eq!(ids, ["long-identifier", "1", "12"]);
        assert_eq!(c[0].channels[0], vec![1.0, 2.0, 6.0]);
        assert_eq!(c[1].channels[0], vec![3.0, 5.0]);
        assert_eq!(c[2].channels[0], vec![4.0]);
        // Header words in any case.
        assert_eq!(
            parse("ID,R,Value\n7,1,2\n", true).unwrap()[0].id.as_deref(),
            Some("7")
        );
    }
}
