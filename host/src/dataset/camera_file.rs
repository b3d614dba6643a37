//! Camera files as cameras write them: linear 16-bit TIFF and PNG, and raw DNG. Every one is
//! decoded to the linear float [`Image`] with the black level removed and the white level at 1:
//! `value = (DN − black) / (white − black)`, so a pixel the sensor clipped reads ≥ 1 whatever the
//! camera's bit depth, and the dataset's saturation for camera files is 1 ([`CLIPPED`]).
//!
//! What is refused, and why: JPEG and 8-bit files are gamma-encoded (a tone curve and white
//! balance already applied) and have 256 levels, too few for a fall-off spanning decades; a PNG
//! that declares sRGB or a gamma other than 1 says it is not linear. Raw files in vendor formats
//! (CR2, CR3, NEF, ARW, RAF, ORF, RW2, …) are refused with the way to DNG.
//!
//! Why DNG is read here and not through a raw-decoding crate: the maintained Rust raw decoder,
//! `rawler` (dnglab), is LGPL-2.1, and this workspace is MIT OR Apache-2.0; the `tiff` crate
//! cannot open a DNG (its decoder refuses the colour-filter-array photometric interpretation,
//! 32803, already when it opens the first directory). A DNG is a TIFF with a few tags of its own
//! (Adobe's DNG specification 1.6); reading its directories and samples (uncompressed, or lossless
//! JPEG: [`super::ljpeg`]) is the small part written here ([`Tiff`]). Vendor formats are converted to DNG by `dnglab convert` (rawler's
//! own command-line tool, so the LGPL code stays a separate program) or Adobe DNG Converter.
use super::image::{Image, ImageError};

/// A camera-file pixel at or above this (after black and white level) is clipped: the white
/// level maps to 1.
pub const CLIPPED: f64 = 1.0;

/// Black and white level of a camera file in its digital numbers (DN): the value of no light and
/// the value at which the sensor clips. `scan.json` gives them for TIFF and PNG frames
/// (`black_level`, `white_level`; per dataset, a frame may override); raw files carry their own.
/// Absent: black 0, white the largest value of the file's bit depth (65535 for 16 bits).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Levels {
    /// DN of no light.
    #[serde(
        rename = "black_level",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub black: Option<f64>,
    /// DN at which the sensor clips.
    #[serde(
        rename = "white_level",
        default,
        skip_serializing_if = "Option::is_none"
    )]
    pub white: Option<f64>,
}

impl Levels {
    /// Each level of `self`, or `fallback`'s where `self` has none (a frame's over the dataset's).
    pub fn or(self, fallback: Levels) -> Levels {
        Levels {
            black: self.black.or(fallback.black),
            white: self.white.or(fallback.white),
        }
    }

    /// `Err` with the reason when a given level is not finite, negative, or white ≤ black.
    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [("black_level", self.black), ("white_level", self.white)] {
            if let Some(v) = v
                && !(v.is_finite() && v >= 0.0)
            {
                return Err(format!("{name} {v} must be finite and >= 0"));
            }
        }
        if let (Some(b), Some(w)) = (self.black, self.white)
            && w <= b
        {
            return Err(format!("white_level {w} must be above black_level {b}"));
        }
        Ok(())
    }

    /// (black, white) for a file whose largest value is `max`.
    fn resolve(&self, max: f64) -> Result<(f64, f64), ImageError> {
        let black = self.black.unwrap_or(0.0);
        let white = self.white.unwrap_or(max);
        if !(white > black && white <= max && black >= 0.0) {
            return Err(ImageError::Format(format!(
                "black level {black} and white level {white} do not fit the file's values \
                 0..={max} (white must be above black)"
            )));
        }
        Ok((black, white))
    }
}

/// What the first bytes of a file say it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileKind {
    /// OpenEXR.
    Exr,
    /// Portable float map.
    Pfm,
    /// TIFF, DNG, or a TIFF-based vendor raw file (told apart when decoded).
    Tiff,
    /// PNG.
    Png,
    /// JPEG: refused.
    Jpeg,
    /// A vendor raw format that is not TIFF-based (CR3, RAF, ORF, RW2): refused.
    VendorRaw(&'static str),
    /// Anything else.
    Unknown,
}

impl FileKind {
    /// The kind of a file from its first 16 bytes (fewer if the file is shorter).
    pub fn sniff(head: &[u8]) -> FileKind {
        let starts = |m: &[u8]| head.starts_with(m);
        if starts(&[0x76, 0x2f, 0x31, 0x01]) {
            FileKind::Exr
        } else if (starts(b"PF") || starts(b"Pf"))
            && head.get(2).is_some_and(u8::is_ascii_whitespace)
        {
            FileKind::Pfm
        } else if starts(b"\x89PNG\r\n\x1a\n") {
            FileKind::Png
        } else if starts(&[0xff, 0xd8, 0xff]) {
            FileKind::Jpeg
        } else if starts(b"IIRO") || starts(b"IIRS") || starts(b"MMOR") {
            FileKind::VendorRaw("Olympus ORF")
        } else if starts(b"IIU\0") {
            FileKind::VendorRaw("Panasonic RW2")
        } else if starts(b"II*\0") || starts(b"MM\0*") {
            FileKind::Tiff
        } else if starts(b"FUJIFILMCCD-RAW") {
            FileKind::VendorRaw("Fujifilm RAF")
        } else if head.get(4..12) == Some(b"ftypcrx ") {
            FileKind::VendorRaw("Canon CR3")
        } else {
            FileKind::Unknown
        }
    }

    /// Whether frames of this kind are camera files, decoded with the white level at
    /// [`CLIPPED`].
    pub fn is_camera_file(self) -> bool {
        matches!(
            self,
            FileKind::Tiff | FileKind::Png | FileKind::VendorRaw(_) | FileKind::Jpeg
        )
    }
}

/// What to use instead of a refused file.
const USE_INSTEAD: &str = "use the camera's raw files (DNG; convert CR2/NEF/ARW/… with \
     `dnglab convert` or Adobe DNG Converter), a linear 16-bit TIFF or PNG, or float OpenEXR/PFM \
     (docs/scan-format.md)";

fn non_linear(what: &str) -> ImageError {
    ImageError::NonLinear(format!(
        "{what}: its values are not proportional to the light, and subsurf fits light; \
         {USE_INSTEAD}"
    ))
}

/// Decodes a camera file (TIFF, DNG, PNG) with `levels` (used by TIFF and PNG; raw files carry
/// their own). Other kinds are errors that say what to use instead.
pub fn decode(bytes: &[u8], levels: Levels) -> Result<Image, ImageError> {
    levels.check().map_err(ImageError::Format)?;
    match FileKind::sniff(bytes) {
        FileKind::Png => decode_png(bytes, levels),
        FileKind::Tiff => {
            let t = Tiff::parse(bytes)?;
            match t.kind()? {
                TiffKind::Dng => decode_dng(&t),
                TiffKind::VendorRaw(make) => Err(ImageError::Unsupported(format!(
                    "a camera raw file in its maker's own format ({make}): subsurf reads raw \
                     files as DNG; convert it with `dnglab convert --compression none` or \
                     Adobe DNG Converter"
                ))),
                TiffKind::Plain => decode_tiff(bytes, levels),
            }
        }
        FileKind::Jpeg => Err(non_linear(
            "a JPEG is an 8-bit, gamma-encoded, lossily compressed picture with the camera's \
             tone curve and white balance applied",
        )),
        FileKind::VendorRaw(name) => Err(ImageError::Unsupported(format!(
            "a {name} raw file: subsurf reads raw files as DNG; convert it with `dnglab convert \
             --compression none` or Adobe DNG Converter"
        ))),
        FileKind::Exr | FileKind::Pfm | FileKind::Unknown => {
            Err(ImageError::Decode("not a TIFF, PNG or DNG file".into()))
        }
    }
}

fn eight_bit() -> ImageError {
    non_linear(
        "an 8-bit image: 8-bit camera output is gamma-encoded (sRGB), and 256 levels cannot \
         hold a fall-off that spans decades",
    )
}

/// `(DN − black) / (white − black)`.
fn normalised(dn: f64, black: f64, white: f64) -> f32 {
    ((dn - black) / (white - black)) as f32
}

/// Keeps R, G, B (or the one grey channel) of `samples` interleaved `per_pixel` to a pixel.
fn linear_image(
    width: usize,
    height: usize,
    per_pixel: usize,
    colour: bool,
    samples: &[u16],
    max: f64,
    levels: Levels,
) -> Result<Image, ImageError> {
    let (black, white) = levels.resolve(max)?;
    let channels = if colour { 3 } else { 1 };
    if samples.len() < width * height * per_pixel {
        return Err(ImageError::Format(
            "fewer samples than the image size".into(),
        ));
    }
    let mut data = Vec::with_capacity(width * height * channels);
    for px in samples.chunks_exact(per_pixel).take(width * height) {
        for &v in &px[..channels] {
            data.push(normalised(v as f64, black, white));
        }
    }
    let img = Image {
        width,
        height,
        channels,
        data,
    };
    img.check()?;
    Ok(img)
}

fn decode_png(bytes: &[u8], levels: Levels) -> Result<Image, ImageError> {
    let bad = |e: png::DecodingError| ImageError::Decode(format!("PNG: {e}"));
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .map_err(bad)?;
    let info = reader.info();
    if info.bit_depth != png::BitDepth::Sixteen {
        return Err(eight_bit());
    }
    if info.srgb.is_some() {
        return Err(non_linear(
            "a PNG that declares itself sRGB (its sRGB chunk)",
        ));
    }
    if let Some(g) = info.gama_chunk
        && (g.into_value() - 1.0).abs() > 0.01
    {
        return Err(non_linear(&format!(
            "a PNG that declares gamma {} (its gAMA chunk; linear is 1)",
            g.into_value()
        )));
    }
    let (per_pixel, colour) = match info.color_type {
        png::ColorType::Grayscale => (1, false),
        png::ColorType::GrayscaleAlpha => (2, false),
        png::ColorType::Rgb => (3, true),
        png::ColorType::Rgba => (4, true),
        png::ColorType::Indexed => return Err(eight_bit()),
    };
    let (w, h) = (info.width as usize, info.height as usize);
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| ImageError::Decode("PNG too large".into()))?;
    let mut buf = vec![0u8; size];
    reader.next_frame(&mut buf).map_err(bad)?;
    // PNG stores 16-bit samples big-endian.
    let samples: Vec<u16> = buf
        .chunks_exact(2)
        .map(|b| u16::from_be_bytes([b[0], b[1]]))
        .collect();
    linear_image(w, h, per_pixel, colour, &samples, 65535.0, levels)
}

fn decode_tiff(bytes: &[u8], levels: Levels) -> Result<Image, ImageError> {
    use tiff::ColorType;
    use tiff::decoder::{Decoder, DecodingResult};
    let bad = |e: tiff::TiffError| ImageError::Decode(format!("TIFF: {e}"));
    let mut d = Decoder::new(std::io::Cursor::new(bytes)).map_err(bad)?;
    let (w, h) = d.dimensions().map_err(bad)?;
    let (per_pixel, colour, bits) = match d.colortype().map_err(bad)? {
        ColorType::Gray(b) => (1, false, b),
        ColorType::GrayA(b) => (2, false, b),
        ColorType::RGB(b) => (3, true, b),
        ColorType::RGBA(b) => (4, true, b),
        other => {
            return Err(ImageError::Decode(format!(
                "TIFF colour type {other:?}: subsurf reads grey or RGB"
            )));
        }
    };
    match d.read_image().map_err(bad)? {
        DecodingResult::U16(v) => linear_image(
            w as usize,
            h as usize,
            per_pixel,
            colour,
            &v,
            ((1u32 << bits.min(16)) - 1) as f64,
            levels,
        ),
        DecodingResult::U8(_) => Err(eight_bit()),
        DecodingResult::F16(_) | DecodingResult::F32(_) | DecodingResult::F64(_) => {
            Err(ImageError::Unsupported(
                "a floating-point TIFF: write float frames as OpenEXR or PFM; TIFF frames are \
                 a camera's integer values with black and white level"
                    .into(),
            ))
        }
        _ => Err(ImageError::Unsupported(
            "TIFF with 32- or 64-bit integer samples: subsurf reads 16-bit TIFF".into(),
        )),
    }
}

/// A TIFF file's structure: byte order and directories (IFDs), read by hand for DNG (see the
/// module's doc for why).
pub(crate) struct Tiff<'a> {
    b: &'a [u8],
    little: bool,
    /// Every directory: IFD0's chain and their SubIFDs, depth first.
    ifds: Vec<Ifd>,
}

/// One directory: its entries by tag.
struct Ifd {
    entries: Vec<Entry>,
}

#[derive(Clone, Copy)]
struct Entry {
    tag: u16,
    ty: u16,
    count: usize,
    /// Where the value is: in the entry itself when it fits 4 bytes, else at the offset there.
    at: usize,
}

/// What a TIFF file holds.
enum TiffKind {
    Dng,
    VendorRaw(String),
    Plain,
}

mod tag {
    pub const NEW_SUBFILE_TYPE: u16 = 254;
    pub const WIDTH: u16 = 256;
    pub const HEIGHT: u16 = 257;
    pub const BITS_PER_SAMPLE: u16 = 258;
    pub const COMPRESSION: u16 = 259;
    pub const PHOTOMETRIC: u16 = 262;
    pub const MAKE: u16 = 271;
    pub const STRIP_OFFSETS: u16 = 273;
    pub const SAMPLES_PER_PIXEL: u16 = 277;
    pub const ROWS_PER_STRIP: u16 = 278;
    pub const STRIP_BYTE_COUNTS: u16 = 279;
    pub const PLANAR_CONFIGURATION: u16 = 284;
    pub const TILE_WIDTH: u16 = 322;
    pub const TILE_LENGTH: u16 = 323;
    pub const TILE_OFFSETS: u16 = 324;
    pub const TILE_BYTE_COUNTS: u16 = 325;
    pub const SUB_IFDS: u16 = 330;
    pub const SAMPLE_FORMAT: u16 = 339;
    pub const CFA_REPEAT_PATTERN_DIM: u16 = 33421;
    pub const CFA_PATTERN: u16 = 33422;
    pub const DNG_VERSION: u16 = 50706;
    pub const CFA_PLANE_COLOR: u16 = 50710;
    pub const CFA_LAYOUT: u16 = 50711;
    pub const LINEARIZATION_TABLE: u16 = 50712;
    pub const BLACK_LEVEL_REPEAT_DIM: u16 = 50713;
    pub const BLACK_LEVEL: u16 = 50714;
    pub const BLACK_LEVEL_DELTA_H: u16 = 50715;
    pub const BLACK_LEVEL_DELTA_V: u16 = 50716;
    pub const WHITE_LEVEL: u16 = 50717;
    pub const ACTIVE_AREA: u16 = 50829;
}

/// Photometric interpretation of a raw colour-filter-array image (DNG).
const CFA: u16 = 32803;
/// Photometric interpretation of a demosaiced linear raw image (DNG).
const LINEAR_RAW: u16 = 34892;
/// At most this many directories are followed (a loop or a damaged file stops there).
const MAX_IFDS: usize = 64;

fn damaged(m: &str) -> ImageError {
    ImageError::Decode(format!("TIFF/DNG: {m}"))
}

impl<'a> Tiff<'a> {
    /// Reads the header and every directory (IFD0's chain and SubIFDs); damaged offsets are
    /// errors, never panics.
    pub(crate) fn parse(b: &'a [u8]) -> Result<Tiff<'a>, ImageError> {
        let little = match b.get(..2) {
            Some(b"II") => true,
            Some(b"MM") => false,
            _ => return Err(damaged("no TIFF byte-order mark")),
        };
        let mut t = Tiff {
            b,
            little,
            ifds: Vec::new(),
        };
        if t.u16_at(2)? != 42 {
            return Err(damaged("not a classic TIFF (BigTIFF is not read)"));
        }
        let mut todo = vec![t.u32_at(4)? as usize];
        let mut seen = std::collections::BTreeSet::new();
        while let Some(off) = todo.pop() {
            if off == 0 || !seen.insert(off) {
                continue;
            }
            if seen.len() > MAX_IFDS {
                return Err(damaged("too many directories"));
            }
            let n = t.u16_at(off)? as usize;
            let mut entries = Vec::with_capacity(n);
            for k in 0..n {
                let e = off + 2 + 12 * k;
                let (tag, ty) = (t.u16_at(e)?, t.u16_at(e + 2)?);
                let count = t.u32_at(e + 4)? as usize;
                let size = type_size(ty).saturating_mul(count);
                let at = if size <= 4 {
                    e + 8
                } else {
                    t.u32_at(e + 8)? as usize
                };
                if type_size(ty) > 0 && at.checked_add(size).is_none_or(|end| end > b.len()) {
                    return Err(damaged(&format!("tag {tag} points outside the file")));
                }
                entries.push(Entry { tag, ty, count, at });
            }
            let next = t.u32_at(off + 2 + 12 * n)? as usize;
            let ifd = Ifd { entries };
            let subs = ifd
                .get(tag::SUB_IFDS)
                .map(|e| t.values(e))
                .transpose()?
                .unwrap_or_default();
            t.ifds.push(ifd);
            todo.push(next);
            todo.extend(subs.iter().rev().map(|&s| s as usize));
        }
        Ok(t)
    }

    fn bytes(&self, at: usize, n: usize) -> Result<&'a [u8], ImageError> {
        at.checked_add(n)
            .and_then(|end| self.b.get(at..end))
            .ok_or_else(|| damaged("offset outside the file"))
    }

    fn u16_at(&self, at: usize) -> Result<u16, ImageError> {
        let s: [u8; 2] = self.bytes(at, 2)?.try_into().expect("2 bytes");
        Ok(if self.little {
            u16::from_le_bytes(s)
        } else {
            u16::from_be_bytes(s)
        })
    }

    fn u32_at(&self, at: usize) -> Result<u32, ImageError> {
        let s: [u8; 4] = self.bytes(at, 4)?.try_into().expect("4 bytes");
        Ok(if self.little {
            u32::from_le_bytes(s)
        } else {
            u32::from_be_bytes(s)
        })
    }

    /// An entry's values as numbers (integers, rationals, floats; ASCII and unknown types give
    /// their bytes).
    fn values(&self, e: &Entry) -> Result<Vec<f64>, ImageError> {
        let size = type_size(e.ty).max(1);
        if e.count > self.b.len() / size + 1 {
            return Err(damaged(&format!("tag {} claims too many values", e.tag)));
        }
        (0..e.count)
            .map(|k| {
                let at = e.at + k * size;
                Ok(match e.ty {
                    3 => self.u16_at(at)? as f64,
                    8 => self.u16_at(at)? as i16 as f64,
                    4 | 13 => self.u32_at(at)? as f64,
                    9 => self.u32_at(at)? as i32 as f64,
                    5 => {
                        let (n, d) = (self.u32_at(at)?, self.u32_at(at + 4)?);
                        n as f64 / d as f64
                    }
                    10 => {
                        let (n, d) = (self.u32_at(at)? as i32, self.u32_at(at + 4)? as i32);
                        n as f64 / d as f64
                    }
                    11 => f32::from_bits(self.u32_at(at)?) as f64,
                    12 => {
                        let (a, b) = (self.u32_at(at)? as u64, self.u32_at(at + 4)? as u64);
                        f64::from_bits(if self.little {
                            a | b << 32
                        } else {
                            a << 32 | b
                        })
                    }
                    6 => self.bytes(at, 1)?[0] as i8 as f64,
                    _ => self.bytes(at, 1)?[0] as f64,
                })
            })
            .collect()
    }

    fn kind(&self) -> Result<TiffKind, ImageError> {
        let ifd0 = self.ifds.first().ok_or_else(|| damaged("no directory"))?;
        if ifd0.get(tag::DNG_VERSION).is_some() {
            return Ok(TiffKind::Dng);
        }
        // Vendor raw files are TIFF-based too: a reduced-resolution preview first, the raw
        // data in a SubIFD or a maker note (NEF, ARW, PEF, CR2 with its "CR" mark, ...).
        let make = ifd0
            .get(tag::MAKE)
            .map(|e| self.bytes(e.at, e.count.min(64)))
            .transpose()?
            .map(|s| {
                String::from_utf8_lossy(s)
                    .trim_end_matches('\0')
                    .trim()
                    .to_owned()
            });
        let preview = self.num(ifd0, tag::NEW_SUBFILE_TYPE)? == Some(1.0);
        let cr2 = self.b.get(8..10) == Some(b"CR");
        if cr2 || (make.is_some() && (preview || ifd0.get(tag::SUB_IFDS).is_some())) {
            return Ok(TiffKind::VendorRaw(
                make.unwrap_or_else(|| "Canon CR2".into()),
            ));
        }
        Ok(TiffKind::Plain)
    }

    fn num(&self, ifd: &Ifd, tag: u16) -> Result<Option<f64>, ImageError> {
        Ok(match ifd.get(tag) {
            Some(e) => self.values(e)?.first().copied(),
            None => None,
        })
    }

    fn nums(&self, ifd: &Ifd, tag: u16) -> Result<Option<Vec<f64>>, ImageError> {
        ifd.get(tag).map(|e| self.values(e)).transpose()
    }
}

impl Ifd {
    fn get(&self, tag: u16) -> Option<&Entry> {
        self.entries.iter().find(|e| e.tag == tag)
    }
}

/// Bytes per value of a TIFF field type (0 for unknown types).
fn type_size(ty: u16) -> usize {
    match ty {
        1 | 2 | 6 | 7 => 1,
        3 | 8 => 2,
        4 | 9 | 11 | 13 => 4,
        5 | 10 | 12 => 8,
        _ => 0,
    }
}

/// The raw image of a DNG, decoded to linear RGB: a colour-filter-array image binned to half
/// size (each 2×2 Bayer cell one pixel: its red, the mean of its two greens, its blue; no white
/// balance, no demosaicing, so no value is invented), a linear raw image at full size. Black
/// level (with its repeat pattern and per-row and per-column deltas), linearisation table and
/// white level are the file's (DNG 1.6, chapter 5: the "linearization" and "black level"
/// steps); the active area is kept. Pixels as stored (the Orientation tag is not applied: the
/// camera calibration is made in the same images).
fn decode_dng(t: &Tiff) -> Result<Image, ImageError> {
    let unsupported = |m: String| Err(ImageError::Unsupported(format!("DNG: {m}")));
    // The main raw image: full resolution (NewSubfileType 0), CFA or linear raw; the largest if
    // several.
    let mut best: Option<(&Ifd, u64)> = None;
    for ifd in &t.ifds {
        let photometric = t.num(ifd, tag::PHOTOMETRIC)?;
        let main = t.num(ifd, tag::NEW_SUBFILE_TYPE)?.unwrap_or(0.0) == 0.0;
        if main && matches!(photometric, Some(p) if p == CFA as f64 || p == LINEAR_RAW as f64) {
            let size =
                t.num(ifd, tag::WIDTH)?.unwrap_or(0.0) * t.num(ifd, tag::HEIGHT)?.unwrap_or(0.0);
            if best.is_none_or(|(_, s)| size as u64 > s) {
                best = Some((ifd, size as u64));
            }
        }
    }
    let Some((ifd, _)) = best else {
        return Err(damaged(
            "no raw image (colour filter array or linear raw) in the DNG",
        ));
    };
    let req = |tag: u16, name: &str| -> Result<f64, ImageError> {
        t.num(ifd, tag)?
            .ok_or_else(|| damaged(&format!("raw image has no {name}")))
    };
    let width = req(tag::WIDTH, "ImageWidth")? as usize;
    let height = req(tag::HEIGHT, "ImageLength")? as usize;
    let spp = t.num(ifd, tag::SAMPLES_PER_PIXEL)?.unwrap_or(1.0) as usize;
    let bits = req(tag::BITS_PER_SAMPLE, "BitsPerSample")? as usize;
    let cfa = t.num(ifd, tag::PHOTOMETRIC)? == Some(CFA as f64);
    // Every sample takes at least one bit of the file, compressed or not: a size the file
    // cannot hold is damage, not an allocation to attempt.
    if width == 0
        || height == 0
        || width > 1 << 16
        || height > 1 << 16
        || width * height * spp.max(1) > 8 * t.b.len()
    {
        return Err(damaged(&format!("raw image size {width}x{height}")));
    }
    if !(1..=16).contains(&bits) {
        return unsupported(format!("{bits}-bit samples (1 to 16 bits are read)"));
    }
    if t.num(ifd, tag::SAMPLE_FORMAT)?.is_some_and(|f| f != 1.0) {
        return unsupported("floating-point raw data".into());
    }
    // A colour filter array has one sample per photosite; linear raw one (grey) or three.
    if !(spp == 1 || (!cfa && spp == 3)) {
        return unsupported(format!("{spp} samples per pixel"));
    }
    if spp > 1
        && t.num(ifd, tag::PLANAR_CONFIGURATION)?
            .is_some_and(|p| p != 1.0)
    {
        return unsupported("planar sample layout".into());
    }
    let lossless_jpeg = match t.num(ifd, tag::COMPRESSION)?.unwrap_or(1.0) as u32 {
        1 => false,
        7 => true,
        c => {
            return unsupported(format!(
                "compression {c} (uncompressed and lossless JPEG are read); save the DNG \
                 uncompressed (`dnglab convert --compression none`)"
            ));
        }
    };
    let samples = read_samples(t, ifd, width, height, spp, bits, lossless_jpeg)?;

    // Linearisation table, black level pattern + deltas, white level (DNG 1.6, ch. 5).
    let table = t.nums(ifd, tag::LINEARIZATION_TABLE)?;
    let max = ((1u32 << bits) - 1) as f64;
    let dims = t
        .nums(ifd, tag::BLACK_LEVEL_REPEAT_DIM)?
        .unwrap_or(vec![1.0, 1.0]);
    let (br, bc) = match dims.as_slice() {
        [r, c] if *r >= 1.0 && *c >= 1.0 && *r <= 16.0 && *c <= 16.0 => (*r as usize, *c as usize),
        _ => return Err(damaged("bad BlackLevelRepeatDim")),
    };
    let black = t
        .nums(ifd, tag::BLACK_LEVEL)?
        .filter(|b| !b.is_empty())
        .unwrap_or(vec![0.0]);
    let black_at = |r: usize, c: usize, s: usize| -> f64 {
        if black.len() == br * bc * spp {
            black[((r % br) * bc + c % bc) * spp + s]
        } else {
            // One value for every position and sample (a common simplification).
            black[0]
        }
    };
    let delta_h = t.nums(ifd, tag::BLACK_LEVEL_DELTA_H)?;
    let delta_v = t.nums(ifd, tag::BLACK_LEVEL_DELTA_V)?;
    let white = t.nums(ifd, tag::WHITE_LEVEL)?.unwrap_or(vec![max]);
    let white_of = |s: usize| white.get(s).or(white.first()).copied().unwrap_or(max);
    let highest_black = black.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lowest_white = (0..spp).map(white_of).fold(f64::INFINITY, f64::min);
    if !(highest_black.is_finite() && lowest_white.is_finite() && lowest_white > highest_black) {
        return Err(damaged(&format!(
            "white level {lowest_white} not above black level {highest_black}"
        )));
    }
    let area = t.nums(ifd, tag::ACTIVE_AREA)?;
    let (top, left, bottom, right) = match area.as_deref() {
        None => (0, 0, height, width),
        Some([a, b, c, d]) => (*a as usize, *b as usize, *c as usize, *d as usize),
        Some(_) => return Err(damaged("bad ActiveArea")),
    };
    if !(top < bottom && left < right && bottom <= height && right <= width) {
        return Err(damaged("ActiveArea outside the image"));
    }
    // Sample at active-area row r, column c, sample s: (value, clipped), black subtracted and
    // scaled by the white level.
    let level = |r: usize, c: usize, s: usize| -> (f32, bool) {
        let raw = samples[((top + r) * width + left + c) * spp + s];
        let lin = match &table {
            Some(tb) if !tb.is_empty() => tb[(raw as usize).min(tb.len() - 1)],
            _ => raw as f64,
        };
        let b = black_at(r, c, s)
            + delta_h
                .as_ref()
                .and_then(|d| d.get(c))
                .copied()
                .unwrap_or(0.0)
            + delta_v
                .as_ref()
                .and_then(|d| d.get(r))
                .copied()
                .unwrap_or(0.0);
        let w = white_of(s);
        (normalised(lin, b, w), lin >= w)
    };
    let (aw, ah) = (right - left, bottom - top);
    if !cfa {
        let mut data = Vec::with_capacity(aw * ah * spp);
        for r in 0..ah {
            for c in 0..aw {
                for s in 0..spp {
                    data.push(level(r, c, s).0);
                }
            }
        }
        let img = Image {
            width: aw,
            height: ah,
            channels: spp,
            data,
        };
        img.check()?;
        return Ok(img);
    }
    // Bayer cell: the colour (0 = R, 1 = G, 2 = B) of each of its four positions.
    if t.nums(ifd, tag::CFA_LAYOUT)?
        .is_some_and(|l| l.first() != Some(&1.0))
    {
        return unsupported("a colour filter array that is not a rectangular grid".into());
    }
    let dim = t.nums(ifd, tag::CFA_REPEAT_PATTERN_DIM)?;
    let pattern = t.nums(ifd, tag::CFA_PATTERN)?;
    let planes = t
        .nums(ifd, tag::CFA_PLANE_COLOR)?
        .unwrap_or(vec![0.0, 1.0, 2.0]);
    let (Some([2.0, 2.0]), Some(pattern)) = (dim.as_deref(), pattern) else {
        return unsupported(
            "only 2x2 Bayer colour filter arrays are read (not X-Trans or other patterns)".into(),
        );
    };
    let colours: Vec<usize> = pattern
        .iter()
        .map(|&p| {
            planes
                .get(p as usize)
                .map(|&c| c as usize)
                .filter(|&c| c <= 2)
                .ok_or_else(|| damaged("CFAPattern names a colour that is not R, G or B"))
        })
        .collect::<Result<_, _>>()?;
    let mut count = [0; 3];
    for &c in &colours {
        count[c] += 1;
    }
    if colours.len() != 4 || count != [1, 2, 1] {
        return unsupported(format!("CFA pattern {colours:?} is not a Bayer pattern"));
    }
    let (w2, h2) = (aw / 2, ah / 2);
    if w2 == 0 || h2 == 0 {
        return Err(damaged("active area smaller than one Bayer cell"));
    }
    let mut data = Vec::with_capacity(w2 * h2 * 3);
    for j in 0..h2 {
        for i in 0..w2 {
            let mut sum = [0f32; 3];
            let mut top_value = [f32::NEG_INFINITY; 3];
            let mut clipped = [false; 3];
            for (k, &colour) in colours.iter().enumerate() {
                let (v, clip) = level(2 * j + k / 2, 2 * i + k % 2, 0);
                sum[colour] += v;
                top_value[colour] = top_value[colour].max(v);
                clipped[colour] |= clip;
            }
            for c in 0..3 {
                // A channel with a clipped photosite is clipped: it reads its largest value
                // (>= 1), not a mean that could fall below the white level.
                data.push(if clipped[c] {
                    top_value[c].max(CLIPPED as f32)
                } else {
                    sum[c] / count[c] as f32
                });
            }
        }
    }
    let img = Image {
        width: w2,
        height: h2,
        channels: 3,
        data,
    };
    img.check()?;
    Ok(img)
}

/// The raw image's samples (`height × width × spp`, row-major), from strips or tiles of
/// `bits`-bit samples: uncompressed (16 and 8 bits in the file's byte order; other depths packed
/// most significant bit first, each row starting on a byte, as TIFF 6.0 says), or each chunk one
/// lossless JPEG stream ([`super::ljpeg`]) whose samples in raster order are the chunk's.
fn read_samples(
    t: &Tiff,
    ifd: &Ifd,
    width: usize,
    height: usize,
    spp: usize,
    bits: usize,
    lossless_jpeg: bool,
) -> Result<Vec<u16>, ImageError> {
    let mut out = vec![0u16; width * height * spp];
    // Chunks: (offset, first row, first column, rows, columns), and their byte counts.
    let mut chunks = Vec::new();
    let counts = t
        .nums(ifd, tag::TILE_BYTE_COUNTS)?
        .or(t.nums(ifd, tag::STRIP_BYTE_COUNTS)?)
        .unwrap_or_default();
    if let Some(offsets) = t.nums(ifd, tag::TILE_OFFSETS)? {
        let tw = t.num(ifd, tag::TILE_WIDTH)?.unwrap_or(0.0) as usize;
        let th = t.num(ifd, tag::TILE_LENGTH)?.unwrap_or(0.0) as usize;
        if tw == 0 || th == 0 || tw > 1 << 16 || th > 1 << 16 {
            return Err(damaged("tiles without a sensible size"));
        }
        let across = width.div_ceil(tw);
        if offsets.len() < across * height.div_ceil(th) {
            return Err(damaged("fewer tiles than the image needs"));
        }
        for (k, &o) in offsets
            .iter()
            .enumerate()
            .take(across * height.div_ceil(th))
        {
            chunks.push((o as usize, (k / across) * th, (k % across) * tw, th, tw));
        }
    } else {
        let offsets = t
            .nums(ifd, tag::STRIP_OFFSETS)?
            .ok_or_else(|| damaged("raw image has neither strips nor tiles"))?;
        let rows =
            (t.num(ifd, tag::ROWS_PER_STRIP)?.unwrap_or(height as f64) as usize).clamp(1, height);
        if offsets.len() < height.div_ceil(rows) {
            return Err(damaged("fewer strips than the image needs"));
        }
        for (k, &o) in offsets.iter().enumerate().take(height.div_ceil(rows)) {
            chunks.push((o as usize, k * rows, 0, rows, width));
        }
    }
    let row_bytes = |cols: usize| (cols * spp * bits).div_ceil(8);
    if lossless_jpeg {
        for (k, (offset, r0, c0, rows, cols)) in chunks.into_iter().enumerate() {
            let len = *counts
                .get(k)
                .ok_or_else(|| damaged("a compressed chunk without its byte count"))?;
            let d = super::ljpeg::decode(t.bytes(offset, len as usize)?)
                .map_err(|e| damaged(&format!("lossless JPEG: {}", e.0)))?;
            let per_row = cols * spp;
            if d.width * d.components * d.height < per_row * rows.min(height - r0.min(height)) {
                return Err(damaged(
                    "lossless JPEG chunk smaller than its tile or strip",
                ));
            }
            for (i, &v) in d.samples.iter().enumerate() {
                let (r, rest) = (i / per_row, i % per_row);
                let (y, x) = (r0 + r, c0 + rest / spp);
                if y >= height {
                    break;
                }
                if x < width {
                    out[(y * width + x) * spp + rest % spp] = v;
                }
            }
        }
        return Ok(out);
    }
    for (offset, r0, c0, rows, cols) in chunks {
        let need = rows.min(height - r0.min(height)) * row_bytes(cols);
        // The last strip may be short; tiles are always whole.
        let data = t.bytes(offset, need)?;
        for r in 0..rows {
            let y = r0 + r;
            if y >= height {
                break;
            }
            let row = &data[r * row_bytes(cols)..(r + 1) * row_bytes(cols)];
            for c in 0..cols {
                let x = c0 + c;
                if x >= width {
                    break;
                }
                for s in 0..spp {
                    let k = c * spp + s;
                    let v = match bits {
                        16 => {
                            let p = [row[2 * k], row[2 * k + 1]];
                            if t.little {
                                u16::from_le_bytes(p)
                            } else {
                                u16::from_be_bytes(p)
                            }
                        }
                        8 => row[k] as u16,
                        _ => packed(row, k, bits),
                    };
                    out[(y * width + x) * spp + s] = v;
                }
            }
        }
    }
    Ok(out)
}

/// Sample `k` of a row of `bits`-bit values packed most significant bit first.
fn packed(row: &[u8], k: usize, bits: usize) -> u16 {
    let mut v = 0u32;
    for b in k * bits..(k + 1) * bits {
        let bit = (row[b / 8] >> (7 - b % 8)) & 1;
        v = v << 1 | bit as u32;
    }
    v as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_are_told_apart_by_their_first_bytes() {
        assert_eq!(FileKind::sniff(&[0x76, 0x2f, 0x31, 0x01, 2]), FileKind::Exr);
        assert_eq!(FileKind::sniff(b"PF\n4 4\n-1\n"), FileKind::Pfm);
        assert_eq!(FileKind::sniff(b"II*\0\x08\0\0\0"), FileKind::Tiff);
        assert_eq!(FileKind::sniff(b"MM\0*\0\0\0\x08"), FileKind::Tiff);
        assert_eq!(FileKind::sniff(&[0xff, 0xd8, 0xff, 0xe0]), FileKind::Jpeg);
        assert_eq!(
            FileKind::sniff(b"\0\0\0\x18ftypcrx \0\0\0\x01"),
            FileKind::VendorRaw("Canon CR3")
        );
        assert_eq!(FileKind::sniff(b"hello"), FileKind::Unknown);
        assert_eq!(FileKind::sniff(b""), FileKind::Unknown);
        assert!(FileKind::Tiff.is_camera_file() && !FileKind::Exr.is_camera_file());
    }

    fn png16(w: u32, h: u32, colour: png::ColorType, samples: &[u16], srgb: bool) -> Vec<u8> {
        let mut out = Vec::new();
        let mut e = png::Encoder::new(&mut out, w, h);
        e.set_color(colour);
        e.set_depth(png::BitDepth::Sixteen);
        if srgb {
            e.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        }
        let mut wr = e.write_header().unwrap();
        let bytes: Vec<u8> = samples.iter().flat_map(|v| v.to_be_bytes()).collect();
        wr.write_image_data(&bytes).unwrap();
        wr.finish().unwrap();
        out
    }

    #[test]
    fn sixteen_bit_png_is_linear_with_its_levels_and_srgb_png_is_refused() {
        let px = [1024u16, 2048, 64000, 5120, 1024, 1024];
        let bytes = png16(2, 1, png::ColorType::Rgb, &px, false);
        let levels = Levels {
            black: Some(1024.0),
            white: Some(9216.0),
        };
        let img = decode(&bytes, levels).unwrap();
        assert_eq!((img.width, img.height, img.channels), (2, 1, 3));
        assert_eq!(img.data[0], 0.0);
        assert_eq!(img.data[1], 0.125);
        assert!(img.data[2] > 1.0, "clipped reads above the white level");
        assert_eq!(img.data[3], 0.5);
        // Defaults: black 0, white 65535.
        let img = decode(&bytes, Levels::default()).unwrap();
        assert_eq!(img.data[0], (1024.0 / 65535.0) as f32);
        // One grey channel stays one channel.
        let grey = png16(2, 1, png::ColorType::Grayscale, &[0, 65535], false);
        assert_eq!(decode(&grey, Levels::default()).unwrap().data, [0.0, 1.0]);
        // Declared sRGB: refused, saying why.
        let e = decode(
            &png16(2, 1, png::ColorType::Rgb, &px, true),
            Levels::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("sRGB") && e.contains("16-bit TIFF"), "{e}");
        // Levels that do not fit are errors.
        let bad = Levels {
            black: Some(10.0),
            white: Some(5.0),
        };
        assert!(decode(&bytes, bad).is_err());
        let too_high = Levels {
            black: None,
            white: Some(70000.0),
        };
        assert!(decode(&bytes, too_high).is_err());
    }

    #[test]
    fn jpeg_and_eight_bit_files_are_refused_with_what_to_use_instead() {
        let e = decode(&[0xff, 0xd8, 0xff, 0xe0, 0, 0], Levels::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("JPEG") && e.contains("DNG"), "{e}");
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 1, 1);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().unwrap();
        wr.write_image_data(&[1, 2, 3]).unwrap();
        wr.finish().unwrap();
        let e = decode(&out, Levels::default()).unwrap_err().to_string();
        assert!(e.contains("8-bit") && e.contains("raw"), "{e}");
        let e = decode(b"\0\0\0\x18ftypcrx \0\0\0\x01", Levels::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("CR3") && e.contains("dnglab"), "{e}");
    }

    /// A minimal little-endian DNG: one IFD, a 4x4 RGGB CFA of 16-bit samples, black 64, white
    /// 1023, with a tag per `extra` entry.
    fn tiny_dng(samples: &[u16; 16], extra: &[(u16, u16, Vec<u32>)]) -> Vec<u8> {
        let mut tags: Vec<(u16, u16, Vec<u32>)> = vec![
            (tag::NEW_SUBFILE_TYPE, 4, vec![0]),
            (tag::WIDTH, 4, vec![4]),
            (tag::HEIGHT, 4, vec![4]),
            (tag::BITS_PER_SAMPLE, 3, vec![16]),
            (tag::COMPRESSION, 3, vec![1]),
            (tag::PHOTOMETRIC, 3, vec![CFA as u32]),
            (tag::STRIP_OFFSETS, 4, vec![0]),
            (tag::SAMPLES_PER_PIXEL, 3, vec![1]),
            (tag::ROWS_PER_STRIP, 4, vec![4]),
            (tag::STRIP_BYTE_COUNTS, 4, vec![32]),
            (tag::CFA_REPEAT_PATTERN_DIM, 3, vec![2, 2]),
            (tag::CFA_PATTERN, 1, vec![0, 1, 1, 2]),
            (tag::DNG_VERSION, 1, vec![1, 4, 0, 0]),
            (tag::BLACK_LEVEL, 4, vec![64]),
            (tag::WHITE_LEVEL, 4, vec![1023]),
        ];
        tags.retain(|t| !extra.iter().any(|e| e.0 == t.0));
        tags.extend(extra.iter().cloned());
        tags.sort_by_key(|t| t.0);
        let ifd_at = 8usize;
        let ifd_len = 2 + 12 * tags.len() + 4;
        let mut heap = Vec::new();
        let data_at = ifd_at + ifd_len;
        let mut out = b"II*\0".to_vec();
        out.extend_from_slice(&(ifd_at as u32).to_le_bytes());
        out.extend_from_slice(&(tags.len() as u16).to_le_bytes());
        let pixels_at = data_at;
        heap.extend(samples.iter().flat_map(|v| v.to_le_bytes()));
        for (tag, ty, vals) in &tags {
            let vals = if *tag == tag::STRIP_OFFSETS {
                vec![pixels_at as u32]
            } else {
                vals.clone()
            };
            out.extend_from_slice(&tag.to_le_bytes());
            out.extend_from_slice(&ty.to_le_bytes());
            out.extend_from_slice(&(vals.len() as u32).to_le_bytes());
            let bytes: Vec<u8> = vals
                .iter()
                .flat_map(|&v| match ty {
                    1 => vec![v as u8],
                    3 => (v as u16).to_le_bytes().to_vec(),
                    _ => v.to_le_bytes().to_vec(),
                })
                .collect();
            if bytes.len() <= 4 {
                let mut b = bytes.clone();
                b.resize(4, 0);
                out.extend_from_slice(&b);
            } else {
                out.extend_from_slice(&((data_at + heap.len()) as u32).to_le_bytes());
                heap.extend_from_slice(&bytes);
            }
        }
        out.extend_from_slice(&0u32.to_le_bytes());
        out.extend_from_slice(&heap);
        out
    }

    #[test]
    fn a_dng_bayer_image_is_binned_to_half_size_with_its_own_levels() {
        // Cells: R G / G B. Top-left cell: R 64+480, greens 64+500 and 64+300, B 1023
        // (clipped); the next cell's R 64+96.
        let mut s = [64u16; 16];
        s[0] = 64 + 480;
        s[1] = 64 + 500;
        s[4] = 64 + 300;
        s[5] = 1023;
        s[2] = 64 + 96;
        let img = decode(&tiny_dng(&s, &[]), Levels::default()).unwrap();
        assert_eq!((img.width, img.height, img.channels), (2, 2, 3));
        assert!((img.data[0] - 480.0 / 959.0).abs() < 1e-6, "R");
        assert!(
            (img.data[1] - 400.0 / 959.0).abs() < 1e-6,
            "G: the mean of its two greens"
        );
        assert!(img.data[2] >= 1.0, "B clipped");
        assert!((img.data[3] - 96.0 / 959.0).abs() < 1e-6, "next cell's R");
        assert_eq!(img.data[11], 0.0);
        // A clipped green among two: the channel is clipped, not averaged below white.
        let mut s2 = [64u16; 16];
        s2[1] = 1023;
        let img = decode(&tiny_dng(&s2, &[]), Levels::default()).unwrap();
        assert!(img.data[1] >= 1.0);
        // GRBG: the pattern moves the colours.
        let img = decode(
            &tiny_dng(&s, &[(tag::CFA_PATTERN, 1, vec![1, 0, 2, 1])]),
            Levels::default(),
        )
        .unwrap();
        assert!(
            (img.data[0] - 500.0 / 959.0).abs() < 1e-6,
            "R is the second photosite"
        );
        // The levels in scan.json do not apply to raw files: the file's are used.
        let other = Levels {
            black: Some(0.0),
            white: Some(100.0),
        };
        assert_eq!(
            decode(&tiny_dng(&s, &[]), other).unwrap(),
            decode(&tiny_dng(&s, &[]), Levels::default()).unwrap()
        );
    }

    #[test]
    fn damaged_and_unsupported_dngs_are_errors_not_panics() {
        let good = tiny_dng(&[100; 16], &[]);
        for cut in [0, 4, 8, 20, 60, good.len() / 2, good.len() - 1] {
            assert!(
                decode(&good[..cut], Levels::default()).is_err(),
                "cut {cut}"
            );
        }
        let e = decode(
            &tiny_dng(&[100; 16], &[(tag::COMPRESSION, 3, vec![8])]),
            Levels::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("uncompressed"), "{e}");
        let e = decode(
            &tiny_dng(&[100; 16], &[(tag::CFA_REPEAT_PATTERN_DIM, 3, vec![6, 6])]),
            Levels::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("Bayer"), "{e}");
        // Every byte flipped in turn: an error or an image, never a panic.
        for k in 0..good.len() {
            let mut b = good.clone();
            b[k] ^= 0xa5;
            let _ = decode(&b, Levels::default());
        }
    }

    #[test]
    fn packed_samples_unpack_most_significant_bit_first() {
        // Two 12-bit values 0xABC, 0x123 in three bytes.
        let row = [0xAB, 0xC1, 0x23];
        assert_eq!(packed(&row, 0, 12), 0xABC);
        assert_eq!(packed(&row, 1, 12), 0x123);
    }
}
