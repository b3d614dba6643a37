//! Fall-off curves as CSV text: the input format of `subsurf fit-curve`.
//!
//! A header `r,value` (one channel) or `r,r_value,g_value,b_value` (RGB), with a leading `id`
//! column in batch files, where every id is one curve (rows of an id need not be contiguous);
//! `#` starts a comment; blank lines are skipped. Values are kept as written, NaN and negative
//! ones included: cleaning them is the fit's job ([`crate::fit::clean`]), which counts what it
//! drops.
//!
//! Lives in the host library rather than in `subsurf-model` because it is a file format, and the
//! model crate's contract is to know no files. It parses a `&str` (no I/O), so callers read the
//! file and keep the context of where it came from.
//!
//! Hand-written rather than with the `csv` crate: the format is four fixed numeric columns, and
//! `fit-curve --batch` parses millions of rows on the path the issue's throughput target is
//! measured on (BENCHMARKS.md); one pass over each line with no per-row allocation keeps parsing a
//! small part of that budget.

use std::collections::HashMap;

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
    /// No header line at all.
    #[error("no header line found (expected `r,value` or `r,r_value,g_value,b_value`)")]
    NoHeader,
}

/// Most columns a row can have (`id,r,r_value,g_value,b_value`).
const MAX_COLUMNS: usize = 5;

/// Parses a curve file's text. `batch`: the first column is an id and each id is a curve;
/// otherwise the whole file is one curve (id `None`).
pub fn parse(text: &str, batch: bool) -> Result<Vec<Curve>, CurvesError> {
    let prefix = if batch { "id," } else { "" };
    let mut channels: Option<usize> = None;
    let mut curves: Vec<Curve> = Vec::new();
    let mut index: HashMap<String, usize> = HashMap::new();
    // Rows of one id usually come together: remember the last one and skip the map lookup.
    let mut last: Option<usize> = None;
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = match raw.find('#') {
            Some(at) => &raw[..at],
            None => raw,
        }
        .trim();
        if line.is_empty() {
            continue;
        }
        let mut fields = [""; MAX_COLUMNS];
        let mut count = 0;
        for f in line.split(',') {
            if count < MAX_COLUMNS {
                fields[count] = f.trim();
            }
            count += 1;
        }
        let Some(ch) = channels else {
            channels = Some(
                header(&fields[..count.min(MAX_COLUMNS)], batch).ok_or_else(|| {
                    CurvesError::Header {
                        line: line_no,
                        prefix,
                        got: line.to_string(),
                    }
                })?,
            );
            continue;
        };
        let first = usize::from(batch);
        let expected = ch + 1 + first;
        if count != expected {
            return Err(CurvesError::Columns {
                line: line_no,
                expected,
                got: count,
            });
        }
        let mut values = [0.0f64; MAX_COLUMNS];
        for col in first..expected {
            values[col] = parse_f64(fields[col]).ok_or_else(|| CurvesError::NotANumber {
                line: line_no,
                column: col + 1,
                field: fields[col].to_string(),
            })?;
        }
        let id = if batch { Some(fields[0]) } else { None };
        let at = match last {
            Some(k) if curves[k].id.as_deref() == id => k,
            _ => {
                let key = id.unwrap_or("");
                let k = match index.get(key) {
                    Some(&k) => k,
                    None => {
                        curves.push(Curve {
                            id: id.map(str::to_string),
                            r: Vec::new(),
                            channels: vec![Vec::new(); ch],
                        });
                        index.insert(key.to_string(), curves.len() - 1);
                        curves.len() - 1
                    }
                };
                last = Some(k);
                k
            }
        };
        let c = &mut curves[at];
        c.r.push(values[first]);
        for (dst, v) in c.channels.iter_mut().zip(&values[first + 1..expected]) {
            dst.push(*v);
        }
    }
    if channels.is_none() {
        return Err(CurvesError::NoHeader);
    }
    Ok(curves)
}

/// Exact powers of ten representable in f64 (10^22 is the largest).
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// A decimal number as f64, correctly rounded (identical to `str::parse::<f64>`). The common
/// case of CSV data, at most 19 significant digits with a mantissa up to 2^53 and a power of ten
/// within ±22, takes Clinger's fast path: mantissa and power of ten are both exact in f64, so one
/// multiplication or division rounds correctly. Everything else (NaN, inf, long or extreme
/// numbers) goes to the standard library. Hand-written because the general parser's per-call
/// validation and dispatch are a measurable part of `fit-curve --batch` on millions of rows.
fn parse_f64(s: &str) -> Option<f64> {
    let b = s.as_bytes();
    let mut i = 0;
    let neg = match b.first() {
        Some(b'-') => {
            i = 1;
            true
        }
        Some(b'+') => {
            i = 1;
            false
        }
        _ => false,
    };
    let (mut mantissa, mut digits, mut exp10, mut any) = (0u64, 0u32, 0i32, false);
    while i < b.len() && b[i].is_ascii_digit() {
        let d = u64::from(b[i] - b'0');
        if digits > 0 || d != 0 {
            digits += 1;
            mantissa = mantissa.wrapping_mul(10).wrapping_add(d);
        }
        any = true;
        i += 1;
    }
    if i < b.len() && b[i] == b'.' {
        i += 1;
        while i < b.len() && b[i].is_ascii_digit() {
            let d = u64::from(b[i] - b'0');
            if digits > 0 || d != 0 {
                digits += 1;
                mantissa = mantissa.wrapping_mul(10).wrapping_add(d);
            }
            exp10 -= 1;
            any = true;
            i += 1;
        }
    }
    if any && i < b.len() && (b[i] == b'e' || b[i] == b'E') {
        i += 1;
        let eneg = match b.get(i) {
            Some(b'-') => {
                i += 1;
                true
            }
            Some(b'+') => {
                i += 1;
                false
            }
            _ => false,
        };
        let (mut e, mut edigits) = (0i32, 0);
        while i < b.len() && b[i].is_ascii_digit() && edigits < 6 {
            e = e * 10 + i32::from(b[i] - b'0');
            edigits += 1;
            i += 1;
        }
        if edigits == 0 {
            return s.parse().ok();
        }
        exp10 += if eneg { -e } else { e };
    }
    if !any || i != b.len() || digits > 19 || mantissa > (1u64 << 53) || exp10.abs() > 22 {
        return s.parse().ok();
    }
    let m = mantissa as f64;
    let v = if exp10 >= 0 {
        m * POW10[exp10 as usize]
    } else {
        m / POW10[(-exp10) as usize]
    };
    Some(if neg { -v } else { v })
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
        }
        for c in &cases {
            let (a, b) = (parse_f64(c), c.parse::<f64>().ok());
            assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits), "{c}");
        }
        for bad in [
            "", "-", ".", "e5", "1e", "1.2.3", "1e5x", "abc", "--1", "1 2",
        ] {
            assert_eq!(parse_f64(bad), None, "{bad}");
        }
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
        // Header words in any case.
        assert_eq!(
            parse("ID,R,Value\n7,1,2\n", true).unwrap()[0].id.as_deref(),
            Some("7")
        );
    }
}
