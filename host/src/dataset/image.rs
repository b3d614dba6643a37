//! The one image type ([`Image`], linear float) and its one encoder and decoder: OpenEXR
//! through the `exr` crate (half or float, RGB or one channel), PFM, and camera files (16-bit
//! TIFF and PNG, DNG: [`super::camera_file`]). Frames of a dataset, images a camera delivers to
//! `subsurf scan`, HDR merges, predictions and renders all use these.
use std::io::{BufRead, BufReader, Read, Seek};
use std::path::{Path, PathBuf};

use super::camera_file::{self, FileKind, Levels};

/// Why an image could not be read or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageError {
    /// The file could not be opened, read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The OpenEXR decoder rejected the file (truncated, corrupt, unsupported).
    #[error("{path}: not a readable OpenEXR image: {message}")]
    Exr {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// The file decoded but its content does not fit the contract, or an image's size, channel
    /// count and data disagree.
    #[error("{0}")]
    Format(String),
    /// In-memory bytes that no decoder reads (see [`Image::decode`]).
    #[error("not a readable image: {0}")]
    Decode(String),
    /// A file whose values are not linear in light (JPEG, 8-bit, declared sRGB): refused, with
    /// what to use instead.
    #[error("refused: {0}")]
    NonLinear(String),
    /// A readable kind of file in a variant subsurf does not read (a vendor raw format, a
    /// compression, a colour filter array), with what to do instead.
    #[error("not read: {0}")]
    Unsupported(String),
}

/// A linear float image, row-major, channels interleaved (1 or 3).
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// 1 (one laser colour) or 3 (r, g, b).
    pub channels: usize,
    /// `height * width * channels` values; pixel `(i, j)` channel `c` at `(j * width + i) * channels + c`.
    pub data: Vec<f32>,
}

impl Image {
    /// A black image.
    pub fn new(width: usize, height: usize, channels: usize) -> Image {
        Image {
            width,
            height,
            channels,
            data: vec![0.0; width * height * channels],
        }
    }

    /// `Ok` when the size, channel count (1 or 3) and data length agree.
    pub fn check(&self) -> Result<(), ImageError> {
        if !(self.channels == 1 || self.channels == 3)
            || self.width == 0
            || self.height == 0
            || self.data.len() != self.width * self.height * self.channels
        {
            return Err(ImageError::Format(format!(
                "image shape {}x{}x{} with {} samples",
                self.width,
                self.height,
                self.channels,
                self.data.len()
            )));
        }
        Ok(())
    }

    /// Decodes an image held in memory, as a camera delivers it: OpenEXR (R, G, B or one
    /// channel kept as one), PFM, or a camera file ([`camera_file`]: 16-bit TIFF or PNG with
    /// black 0 and white 65535, DNG with its own levels), told apart by their first bytes.
    /// JPEG and 8-bit files are refused ([`ImageError::NonLinear`]).
    pub fn decode(bytes: &[u8]) -> Result<Image, ImageError> {
        Image::decode_with(bytes, Levels::default())
    }

    /// [`Image::decode`] with the black and white level of a TIFF or PNG camera file (raw files
    /// carry their own; float images have none).
    pub fn decode_with(bytes: &[u8], levels: Levels) -> Result<Image, ImageError> {
        match FileKind::sniff(bytes) {
            FileKind::Exr => decode_exr(std::io::Cursor::new(bytes), "image")
                .map(|(img, _)| img)
                .map_err(|e| ImageError::Decode(e.to_string())),
            FileKind::Pfm => decode_pfm(&mut std::io::Cursor::new(bytes), "image"),
            _ => camera_file::decode(bytes, levels),
        }
    }

    /// A picture for geometry only (chessboard detection in `subsurf calib`), where linearity
    /// does not matter: whatever [`Image::decode`] reads, else any 8-bit PNG as values in
    /// `[0, 1]`.
    pub fn decode_picture(bytes: &[u8]) -> Result<Image, ImageError> {
        match Image::decode(bytes) {
            Err(ImageError::NonLinear(why)) => {
                let img = image::load_from_memory(bytes)
                    .map_err(|e| ImageError::Decode(format!("{e} ({why})")))?;
                let rgb = img.to_rgb32f();
                Ok(Image {
                    width: rgb.width() as usize,
                    height: rgb.height() as usize,
                    channels: 3,
                    data: rgb.into_raw(),
                })
            }
            other => other,
        }
    }

    /// The value of pixel column `i`, row `j`, channel `c`.
    pub fn get(&self, i: usize, j: usize, c: usize) -> f32 {
        self.data[(j * self.width + i) * self.channels + c]
    }

    /// Bilinear interpolation at pixel coordinates `(u, v)` (pixel centres at integers), for
    /// colour channel `c` (0..3; a one-channel image answers its only channel). Returns the value
    /// and the largest raw pixel with a non-zero weight, so callers can reject clipped
    /// neighbourhoods.
    /// `None` outside the image.
    pub fn bilinear(&self, u: f64, v: f64, c: usize) -> Option<(f64, f64)> {
        let c = c.min(2);
        self.bilinear_channels(u, v, &[c]).map(|read| read[c])
    }

    /// [`Image::bilinear`] of each channel of `chans` at once: one neighbourhood, each pixel's
    /// channels read together (the extraction reads every visible lattice point of every frame:
    /// at 1024 px, ~450 million reads of the built-in sphere's scan). Each channel's sums are
    /// the ones it takes alone, in the same order, so the same bits; entries not in `chans` are
    /// `(0.0, -inf)`.
    pub fn bilinear_channels(&self, u: f64, v: f64, chans: &[usize]) -> Option<[(f64, f64); 3]> {
        let taps = bilinear_taps(self.width, self.height, u, v)?;
        let mut out = [(0.0, f64::NEG_INFINITY); 3];
        // Pixels with zero weight take no part: neither their value (a NaN there must not poison
        // an exact hit on a pixel centre) nor their clipping.
        for (i, j, wk) in taps {
            if wk > 0.0 {
                let px = (j * self.width + i) * self.channels;
                for &c in chans {
                    let c = c.min(2);
                    let pk = self.data[px + if self.channels == 1 { 0 } else { c }] as f64;
                    let (val, max) = &mut out[c];
                    *val += wk * pk;
                    *max = max.max(pk);
                }
            }
        }
        Some(out)
    }
}

/// The four pixel centres `(column, row, weight)` a bilinear read at `(u, v)` of a
/// `width × height` image weights ([`Image::bilinear`]; weights sum to 1, some may be 0), or
/// `None` outside the image. The one definition of the neighbourhood, shared with the coverage
/// check of samples ([`crate::geometry::Scene::covers`]), which must test exactly the pixels
/// the value is made of.
pub fn bilinear_taps(
    width: usize,
    height: usize,
    u: f64,
    v: f64,
) -> Option<[(usize, usize, f64); 4]> {
    if width == 0
        || height == 0
        || !(u >= -0.5 && v >= -0.5 && u < width as f64 - 0.5 && v < height as f64 - 0.5)
    {
        return None;
    }
    let u = u.clamp(0.0, (width - 1) as f64);
    let v = v.clamp(0.0, (height - 1) as f64);
    // u, v >= 0 here: truncation is their floor, without a libm call per read.
    let i0 = (u as usize).min(width.saturating_sub(2));
    let j0 = (v as usize).min(height.saturating_sub(2));
    let i1 = (i0 + 1).min(width - 1);
    let j1 = (j0 + 1).min(height - 1);
    let (fu, fv) = (u - i0 as f64, v - j0 as f64);
    Some([
        (i0, j0, (1.0 - fu) * (1.0 - fv)),
        (i1, j0, fu * (1.0 - fv)),
        (i0, j1, (1.0 - fu) * fv),
        (i1, j1, fu * fv),
    ])
}

/// Reads a frame image: OpenEXR, PFM, or a camera file (16-bit TIFF or PNG with black 0 and
/// white 65535, DNG with its own levels), told apart by their first bytes.
pub fn read_image(path: &Path) -> Result<Image, ImageError> {
    read_image_with(path, Levels::default())
}

/// [`read_image`] with the black and white level of a TIFF or PNG camera file (from
/// `scan.json`; raw files carry their own).
pub fn read_image_with(path: &Path, levels: Levels) -> Result<Image, ImageError> {
    let io = |source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut head = [0u8; 16];
    let n = {
        let mut f = std::fs::File::open(path).map_err(io)?;
        let mut n = 0;
        while n < head.len() {
            match f.read(&mut head[n..]).map_err(io)? {
                0 => break,
                k => n += k,
            }
        }
        n
    };
    match FileKind::sniff(&head[..n]) {
        FileKind::Exr => read_exr(path),
        FileKind::Pfm => read_pfm(path),
        // Files too short to tell keep the old rule: `.pfm` by extension, else EXR.
        FileKind::Unknown
            if path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("pfm")) =>
        {
            read_pfm(path)
        }
        FileKind::Unknown => read_exr(path),
        _ => {
            let bytes = std::fs::read(path).map_err(io)?;
            camera_file::decode(&bytes, levels)
                .map_err(|e| ImageError::Format(format!("{}: {e}", path.display())))
        }
    }
}

fn read_exr(path: &Path) -> Result<Image, ImageError> {
    read_exr_with_alpha(path).map(|(img, _)| img)
}

/// Reads an OpenEXR image as [`read_image`] does, and its alpha channel `A` when it has one (a
/// renderer's coverage: another program's render with a transparent background).
pub fn read_exr_with_alpha(path: &Path) -> Result<(Image, Option<Vec<f32>>), ImageError> {
    let file = std::fs::File::open(path).map_err(|source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    decode_exr(BufReader::new(file), &path.display().to_string()).map_err(|e| match e {
        ExrError::Codec(message) => ImageError::Exr {
            path: path.to_path_buf(),
            message,
        },
        ExrError::Content(m) => ImageError::Format(m),
    })
}

/// Why [`decode_exr`] failed: the decoder, or the content.
enum ExrError {
    Codec(String),
    Content(String),
}

impl std::fmt::Display for ExrError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ExrError::Codec(m) => write!(f, "not a readable OpenEXR image: {m}"),
            ExrError::Content(m) => f.write_str(m),
        }
    }
}

/// An OpenEXR image's first valid layer: R, G, B if present, else Y, else its only channel; and
/// its `A` channel if it has one. `name` (the file, or "image") goes into the content errors.
fn decode_exr(
    source: impl Read + Seek + Send,
    name: &str,
) -> Result<(Image, Option<Vec<f32>>), ExrError> {
    use exr::prelude::*;
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(source)
        .map_err(|e| ExrError::Codec(e.to_string()))?;
    let layer = &img.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let chans = &layer.channel_data.list;
    let find = |name: &str| {
        chans.iter().position(|c| {
            let n = c.name.to_string();
            n == name || n.ends_with(&format!(".{name}"))
        })
    };
    let picked: Vec<usize> = match (find("R"), find("G"), find("B")) {
        (Some(r), Some(g), Some(b)) => vec![r, g, b],
        _ => {
            if let Some(y) = find("Y") {
                vec![y]
            } else if chans.len() == 1 {
                vec![0]
            } else {
                return Err(ExrError::Content(format!(
                    "{name}: channels {:?} are neither R,G,B nor one channel",
                    chans.iter().map(|c| c.name.to_string()).collect::<Vec<_>>()
                )));
            }
        }
    };
    let n = picked.len();
    let mut data = vec![0.0f32; w * h * n];
    for (k, &ci) in picked.iter().enumerate() {
        let samples = &chans[ci].sample_data;
        if samples.len() != w * h {
            return Err(ExrError::Content(format!(
                "{name}: channel holds {} samples, expected {}",
                samples.len(),
                w * h
            )));
        }
        for (p, v) in samples.values_as_f32().enumerate() {
            data[p * n + k] = v;
        }
    }
    let alpha = find("A")
        .map(|a| chans[a].sample_data.values_as_f32().collect::<Vec<f32>>())
        .filter(|a| a.len() == w * h);
    Ok((
        self::Image {
            width: w,
            height: h,
            channels: n,
            data,
        },
        alpha,
    ))
}

fn read_pfm(path: &Path) -> Result<Image, ImageError> {
    let file = std::fs::File::open(path).map_err(|source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    decode_pfm(&mut BufReader::new(file), &path.display().to_string())
}

/// A PFM from `r`; `name` (the file, or "image") goes into the errors.
fn decode_pfm(r: &mut impl BufRead, name: &str) -> Result<Image, ImageError> {
    let io = |e: std::io::Error| ImageError::Format(format!("{name}: not a PFM image: {e}"));
    let bad = |m: &str| ImageError::Format(format!("{name}: not a PFM image: {m}"));
    let mut tokens = Vec::new();
    // Header: three whitespace-separated tokens (type, "w h", scale), each line ended by one newline.
    let mut line = String::new();
    while tokens.len() < 4 {
        line.clear();
        let n = r.read_line(&mut line).map_err(io)?;
        if n == 0 || line.len() > 256 {
            return Err(bad("truncated header"));
        }
        tokens.extend(line.split_whitespace().map(str::to_owned));
    }
    let channels = match tokens[0].as_str() {
        "PF" => 3,
        "Pf" => 1,
        _ => return Err(bad("magic is not PF or Pf")),
    };
    let w: usize = tokens[1].parse().map_err(|_| bad("bad width"))?;
    let h: usize = tokens[2].parse().map_err(|_| bad("bad height"))?;
    let scale: f64 = tokens[3].parse().map_err(|_| bad("bad scale"))?;
    if w == 0 || h == 0 || w > 1 << 16 || h > 1 << 16 || scale == 0.0 || !scale.is_finite() {
        return Err(bad("bad size or scale"));
    }
    let little = scale < 0.0;
    let mut bytes = vec![0u8; w * h * channels * 4];
    r.read_exact(&mut bytes)
        .map_err(|_| bad("truncated pixel data"))?;
    let mut data = vec![0.0f32; w * h * channels];
    let row = w * channels;
    for j in 0..h {
        // PFM stores rows bottom to top.
        let src = (h - 1 - j) * row;
        for k in 0..row {
            let b: [u8; 4] = bytes[(src + k) * 4..(src + k) * 4 + 4]
                .try_into()
                .map_err(|_| bad("internal size"))?;
            data[j * row + k] = if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            };
        }
    }
    Ok(Image {
        width: w,
        height: h,
        channels,
        data,
    })
}

/// A PFM's bytes (little-endian, rows bottom to top as the format requires).
pub fn encode_pfm(img: &Image) -> Result<Vec<u8>, ImageError> {
    img.check()?;
    let mut out = Vec::with_capacity(img.data.len() * 4 + 32);
    let magic = if img.channels == 3 { "PF" } else { "Pf" };
    out.extend_from_slice(format!("{magic}\n{} {}\n-1.0\n", img.width, img.height).as_bytes());
    let row = img.width * img.channels;
    for j in (0..img.height).rev() {
        for v in &img.data[j * row..(j + 1) * row] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}

/// Writes a PFM ([`encode_pfm`]).
pub fn write_pfm(path: &Path, img: &Image) -> Result<(), ImageError> {
    let bytes = encode_pfm(img)?;
    std::fs::write(path, bytes).map_err(|source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// A float32 OpenEXR's bytes: channels R, G, B for a three-channel image, Y for one channel.
/// The one EXR encoder (scan frames, simulated frames, predictions, renders). Written in one
/// thread with a fixed encoding, so equal images always give equal bytes (a resumed scan is
/// byte-identical to an uninterrupted one).
pub fn encode_exr(img: &Image) -> Result<Vec<u8>, ImageError> {
    use exr::prelude::*;
    img.check()?;
    let exr_err = |e: exr::error::Error| ImageError::Format(format!("cannot encode EXR: {e}"));
    let (w, c) = (img.width, img.channels);
    let size = (img.width, img.height);
    let mut out = std::io::Cursor::new(Vec::new());
    match c {
        3 => {
            let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
                let k = (p.y() * w + p.x()) * 3;
                (img.data[k], img.data[k + 1], img.data[k + 2])
            });
            exr::image::Image::from_channels(size, channels)
                .write()
                .non_parallel()
                .to_buffered(&mut out)
                .map_err(exr_err)?;
        }
        1 => {
            let channels = SpecificChannels::build()
                .with_channel("Y")
                .with_pixel_fn(|p: Vec2<usize>| (img.data[p.y() * w + p.x()],));
            exr::image::Image::from_channels(size, channels)
                .write()
                .non_parallel()
                .to_buffered(&mut out)
                .map_err(exr_err)?;
        }
        _ => {
            return Err(ImageError::Format(format!(
                "EXR writer takes 1 or 3 channels, image has {c}"
            )));
        }
    }
    Ok(out.into_inner())
}

/// Writes a float32 OpenEXR ([`encode_exr`]).
pub fn write_exr(path: &Path, img: &Image) -> Result<(), ImageError> {
    let bytes = encode_exr(img)?;
    std::fs::write(path, bytes).map_err(|source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// One channel's bilinear read pixel by pixel, as `Image::bilinear` read it before it went
    /// through `bilinear_channels`: the reference the channels read together are held to.
    fn bilinear_one(img: &Image, u: f64, v: f64, c: usize) -> Option<(f64, f64)> {
        let taps = bilinear_taps(img.width, img.height, u, v)?;
        let c = if img.channels == 1 { 0 } else { c };
        let (mut val, mut max) = (0.0, f64::NEG_INFINITY);
        for (i, j, wk) in taps {
            if wk > 0.0 {
                let pk = img.get(i, j, c) as f64;
                val += wk * pk;
                max = max.max(pk);
            }
        }
        Some((val, max))
    }

    proptest! {
        /// `bilinear_channels` (and `bilinear`, which reads one channel through it) is each
        /// channel read alone, to the bit: NaNs, infinities and clipped pixels in the
        /// neighbourhood, reads on and off pixel centres, edges, outside.
        #[test]
        fn all_channels_at_once_read_each_channel_to_the_bit(
            w in 1usize..6,
            h in 1usize..6,
            three in proptest::bool::ANY,
            pixels in proptest::collection::vec(
                proptest::prop_oneof![
                    8 => -1.0f32..100.0,
                    1 => proptest::sample::select(vec![f32::NAN, f32::INFINITY, 0.0, 20.0]),
                ],
                75,
            ),
            u in proptest::prop_oneof![-1.0f64..6.0, (-1i32..7).prop_map(f64::from)],
            v in proptest::prop_oneof![-1.0f64..6.0, (-1i32..7).prop_map(f64::from)],
            chans in proptest::sample::select(vec![vec![0usize, 1, 2], vec![0], vec![1], vec![2]]),
        ) {
            let channels = if three { 3 } else { 1 };
            let mut img = Image::new(w, h, channels);
            let n = img.data.len();
            img.data.copy_from_slice(&pixels[..n]);
            let all = img.bilinear_channels(u, v, &chans);
            let bits = |x: Option<(f64, f64)>| x.map(|(a, b)| (a.to_bits(), b.to_bits()));
            for &c in &chans {
                let one = bilinear_one(&img, u, v, c);
                prop_assert_eq!(bits(one), bits(all.map(|a| a[c])));
                prop_assert_eq!(bits(one), bits(img.bilinear(u, v, c)));
            }
        }
    }

    fn ramp(w: usize, h: usize, c: usize) -> Image {
        let mut img = Image::new(w, h, c);
        for (k, v) in img.data.iter_mut().enumerate() {
            *v = k as f32 * 0.25 + 1e-3;
        }
        img
    }

    #[test]
    fn exr_and_pfm_round_trip_one_and_three_channels() {
        let dir = tempfile::tempdir().unwrap();
        for c in [1, 3] {
            let img = ramp(7, 5, c);
            for name in ["a.exr", "a.pfm"] {
                let p = dir.path().join(name);
                if name.ends_with("exr") {
                    write_exr(&p, &img).unwrap();
                } else {
                    write_pfm(&p, &img).unwrap();
                }
                assert_eq!(read_image(&p).unwrap(), img, "{name} {c}");
            }
        }
    }

    #[test]
    fn encoding_is_deterministic_and_decode_reads_it_back() {
        for c in [1, 3] {
            let img = ramp(9, 4, c);
            let a = encode_exr(&img).unwrap();
            assert_eq!(a, encode_exr(&img).unwrap());
            assert_eq!(Image::decode(&a).unwrap(), img, "{c} channels");
        }
        // Anything else goes to the `image` crate, as linear RGB.
        let mut png = Vec::new();
        image::DynamicImage::ImageRgb16(image::ImageBuffer::from_pixel(
            3,
            2,
            image::Rgb([0u16, 32768, 65535]),
        ))
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
        let back = Image::decode(&png).unwrap();
        assert_eq!((back.width, back.height, back.channels), (3, 2, 3));
        assert_eq!(back.data[2], 1.0);
    }

    #[test]
    fn bad_shapes_and_bytes_are_errors_not_panics() {
        let mut img = ramp(4, 4, 3);
        img.data.pop();
        assert!(encode_exr(&img).is_err());
        assert!(encode_pfm(&img).is_err());
        assert!(encode_exr(&Image::new(2, 2, 2)).is_err());
        let good = encode_exr(&ramp(4, 4, 3)).unwrap();
        for cut in [0, 3, 4, 20, good.len() / 2, good.len() - 1] {
            assert!(Image::decode(&good[..cut]).is_err(), "cut at {cut}");
        }
        assert!(Image::decode(b"not an image").is_err());
    }

    #[test]
    fn truncated_files_are_errors_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let img = ramp(16, 16, 3);
        for name in ["t.exr", "t.pfm"] {
            let p = dir.path().join(name);
            if name.ends_with("exr") {
                write_exr(&p, &img).unwrap();
            } else {
                write_pfm(&p, &img).unwrap();
            }
            let bytes = std::fs::read(&p).unwrap();
            for cut in [0, 3, 20, bytes.len() / 2, bytes.len() - 1] {
                std::fs::write(&p, &bytes[..cut]).unwrap();
                assert!(read_image(&p).is_err(), "{name} cut at {cut}");
            }
        }
    }

    #[test]
    fn bilinear_is_exact_at_centres_and_linear_between() {
        let img = ramp(4, 3, 1);
        assert_eq!(
            img.bilinear(2.0, 1.0, 0).unwrap().0,
            img.get(2, 1, 0) as f64
        );
        let mid = img.bilinear(1.5, 1.0, 0).unwrap().0;
        let want = 0.5 * (img.get(1, 1, 0) + img.get(2, 1, 0)) as f64;
        assert!((mid - want).abs() < 1e-6);
        assert!(img.bilinear(-0.6, 0.0, 0).is_none());
        assert!(img.bilinear(3.6, 0.0, 0).is_none());
    }
}
