//! Lossless JPEG (ITU-T T.81, process 14: SOF3, Huffman-coded prediction differences), the
//! compression of most raw DNGs (DNG compression 7). Written here for the same reason as the DNG
//! reader ([`super::camera_file`]): the Rust JPEG decoders of the image-rs family (`zune-jpeg`,
//! which the `tiff` crate uses) do not decode SOF3, and the raw decoder that does (`rawler`) is
//! LGPL. Only what DNG writers emit is read: one frame, one scan holding every component, 2 to 16
//! bits, predictors 1 to 7, point transform, restart intervals.

/// Why a stream could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LjpegError(pub String);

fn err<T>(m: impl Into<String>) -> Result<T, LjpegError> {
    Err(LjpegError(m.into()))
}

/// A decoded stream: `width × height` samples of `components` interleaved components, in
/// raster order (DNG lays a tile's photosites out in exactly that order, whatever split of the
/// tile into lines and components the writer chose).
#[derive(Debug)]
pub struct Decoded {
    /// Samples per line per component (the frame's X).
    pub width: usize,
    /// Lines (the frame's Y).
    pub height: usize,
    /// Interleaved components (the frame's Nf).
    pub components: usize,
    /// `height × width × components` values.
    pub samples: Vec<u16>,
}

/// A Huffman table as canonical codes: per code length, the first code and the index of its
/// first value.
#[derive(Clone, Default)]
struct Huffman {
    /// For length l (1..=16): (first code, number of codes, offset into `values`).
    lengths: [(u32, u32, usize); 17],
    values: Vec<u8>,
}

impl Huffman {
    fn new(counts: &[u8; 16], values: Vec<u8>) -> Result<Huffman, LjpegError> {
        let mut h = Huffman {
            values,
            ..Huffman::default()
        };
        let (mut code, mut offset) = (0u32, 0usize);
        for l in 1..=16 {
            let n = counts[l - 1] as u32;
            h.lengths[l] = (code, n, offset);
            code = (code + n) << 1;
            offset += n as usize;
            if code > (2u32 << l) {
                return err("Huffman table over-subscribed");
            }
        }
        if offset > h.values.len() {
            return err("Huffman table has fewer values than codes");
        }
        Ok(h)
    }
}

/// Reads the entropy-coded segment bit by bit (0xFF 0x00 is a data 0xFF; any other marker ends
/// the segment and reads as zero bits).
struct Bits<'a> {
    b: &'a [u8],
    at: usize,
    acc: u64,
    n: u32,
    marker: bool,
}

impl Bits<'_> {
    fn fill(&mut self) {
        while self.n <= 56 {
            let byte = if self.marker || self.at >= self.b.len() {
                0
            } else if self.b[self.at] == 0xff {
                match self.b.get(self.at + 1) {
                    Some(0x00) => {
                        self.at += 2;
                        0xff
                    }
                    _ => {
                        self.marker = true;
                        0
                    }
                }
            } else {
                self.at += 1;
                self.b[self.at - 1]
            };
            self.acc |= (byte as u64) << (56 - self.n);
            self.n += 8;
        }
    }

    fn bits(&mut self, k: u32) -> u32 {
        if k == 0 {
            return 0;
        }
        self.fill();
        let v = (self.acc >> (64 - k)) as u32;
        self.acc <<= k;
        self.n -= k;
        v
    }

    fn decode(&mut self, h: &Huffman) -> Result<u8, LjpegError> {
        self.fill();
        let mut code = 0u32;
        for l in 1..=16 {
            code = code << 1 | (self.acc >> 63) as u32;
            self.acc <<= 1;
            self.n -= 1;
            let (first, count, offset) = h.lengths[l];
            if code.wrapping_sub(first) < count {
                let k = offset + (code - first) as usize;
                return h
                    .values
                    .get(k)
                    .copied()
                    .ok_or_else(|| LjpegError("Huffman value missing".into()));
            }
        }
        err("bad Huffman code")
    }

    /// Skips to after the next restart marker.
    fn restart(&mut self) -> Result<(), LjpegError> {
        self.acc = 0;
        self.n = 0;
        self.marker = false;
        while self.at + 1 < self.b.len() {
            if self.b[self.at] == 0xff && (0xd0..=0xd7).contains(&self.b[self.at + 1]) {
                self.at += 2;
                return Ok(());
            }
            self.at += 1;
        }
        err("restart marker missing")
    }
}

/// Decodes one lossless JPEG stream.
pub fn decode(b: &[u8]) -> Result<Decoded, LjpegError> {
    if b.get(..2) != Some(&[0xff, 0xd8]) {
        return err("no JPEG start-of-image marker");
    }
    let u16_at = |at: usize| -> Result<usize, LjpegError> {
        b.get(at..at + 2)
            .map(|s| u16::from_be_bytes([s[0], s[1]]) as usize)
            .ok_or_else(|| LjpegError("truncated".into()))
    };
    let mut tables: [Option<Huffman>; 4] = Default::default();
    // (precision, lines, samples per line, component ids)
    let mut frame: Option<(u32, usize, usize, Vec<u8>)> = None;
    let mut restart_interval = 0usize;
    let mut at = 2;
    loop {
        while b.get(at) == Some(&0xff) && b.get(at + 1) == Some(&0xff) {
            at += 1;
        }
        let (Some(&0xff), Some(&marker)) = (b.get(at), b.get(at + 1)) else {
            return err("marker expected");
        };
        let len = u16_at(at + 2)?;
        let seg = b
            .get(at + 4..at + 2 + len)
            .ok_or_else(|| LjpegError("truncated segment".into()))?;
        if len < 2 {
            return err("bad segment length");
        }
        match marker {
            0xc3 => {
                if seg.len() < 6 {
                    return err("short SOF3");
                }
                let nf = seg[5] as usize;
                if !(1..=4).contains(&nf) || seg.len() < 6 + 3 * nf {
                    return err("bad component count");
                }
                let ids = (0..nf).map(|c| seg[6 + 3 * c]).collect();
                if (0..nf).any(|c| seg[7 + 3 * c] != 0x11) {
                    return err("subsampled components are not read");
                }
                frame = Some((
                    seg[0] as u32,
                    u16::from_be_bytes([seg[1], seg[2]]) as usize,
                    u16::from_be_bytes([seg[3], seg[4]]) as usize,
                    ids,
                ));
            }
            0xc0..=0xc2 | 0xc5..=0xc7 | 0xc9..=0xcb | 0xcd..=0xcf => {
                return err("not a lossless (SOF3) JPEG");
            }
            0xc4 => {
                let mut p = 0;
                while p < seg.len() {
                    let th = (seg[p] & 0x0f) as usize;
                    let counts: [u8; 16] = seg
                        .get(p + 1..p + 17)
                        .and_then(|s| s.try_into().ok())
                        .ok_or_else(|| LjpegError("short DHT".into()))?;
                    let n: usize = counts.iter().map(|&c| c as usize).sum();
                    let values = seg
                        .get(p + 17..p + 17 + n)
                        .ok_or_else(|| LjpegError("short DHT".into()))?
                        .to_vec();
                    if th > 3 {
                        return err("bad Huffman table id");
                    }
                    tables[th] = Some(Huffman::new(&counts, values)?);
                    p += 17 + n;
                }
            }
            0xdd => restart_interval = u16_at(at + 4)?,
            0xda => {
                let Some((precision, height, width, ids)) = frame.take() else {
                    return err("scan before frame header");
                };
                let ns = *seg.first().ok_or_else(|| LjpegError("short SOS".into()))? as usize;
                if ns != ids.len() || seg.len() < 1 + 2 * ns + 3 {
                    return err("the scan must hold every component (one scan)");
                }
                let mut comp_tables = Vec::with_capacity(ns);
                for c in 0..ns {
                    let id = seg[1 + 2 * c];
                    if ids.get(c) != Some(&id) {
                        return err("scan components out of frame order");
                    }
                    let t = (seg[2 + 2 * c] >> 4) as usize;
                    comp_tables.push(
                        tables
                            .get(t)
                            .cloned()
                            .flatten()
                            .ok_or_else(|| LjpegError(format!("Huffman table {t} missing")))?,
                    );
                }
                let predictor = seg[1 + 2 * ns];
                let pt = (seg[3 + 2 * ns] & 0x0f) as u32;
                if !(2..=16).contains(&precision)
                    || pt >= precision
                    || !(1..=7).contains(&predictor)
                {
                    return err("bad precision, point transform or predictor");
                }
                let data = &b[at + 2 + len..];
                // Every sample takes at least one bit (its Huffman code).
                if width == 0 || height == 0 || width * height * ns > 8 * data.len() + 64 {
                    return err("bad image size");
                }
                let samples = scan(
                    data,
                    &comp_tables,
                    width,
                    height,
                    precision,
                    pt,
                    predictor,
                    restart_interval,
                )?;
                return Ok(Decoded {
                    width,
                    height,
                    components: ns,
                    samples,
                });
            }
            0xd9 => return err("end of image before a scan"),
            _ => {}
        }
        at += 2 + len;
    }
}

/// The samples of one scan (T.81 H.1.2: prediction, then difference).
#[allow(clippy::too_many_arguments)]
fn scan(
    data: &[u8],
    tables: &[Huffman],
    width: usize,
    height: usize,
    precision: u32,
    pt: u32,
    predictor: u8,
    restart_interval: usize,
) -> Result<Vec<u16>, LjpegError> {
    let nc = tables.len();
    let mut out = vec![0u16; width * height * nc];
    let mut bits = Bits {
        b: data,
        at: 0,
        acc: 0,
        n: 0,
        marker: false,
    };
    let mask = if precision == 16 {
        0xffff
    } else {
        (1i32 << precision) - 1
    };
    let initial = 1i32 << (precision - pt - 1);
    let row_len = width * nc;
    // Restart intervals count MCUs (one sample of every component); after a restart the
    // prediction starts over as at the image's first sample and line (T.81 H.1.2.1).
    let mut since_restart = 0usize;
    let mut first_line_of_interval = true;
    let mut reset = true;
    for y in 0..height {
        for x in 0..width {
            if restart_interval > 0 && since_restart == restart_interval {
                bits.restart()?;
                since_restart = 0;
                first_line_of_interval = true;
                reset = true;
            }
            for c in 0..nc {
                let k = y * row_len + x * nc + c;
                let ssss = bits.decode(&tables[c])? as u32;
                let diff: i32 = match ssss {
                    0 => 0,
                    16 => 32768,
                    1..=15 => {
                        let v = bits.bits(ssss) as i32;
                        if v < 1 << (ssss - 1) {
                            v - (1 << ssss) + 1
                        } else {
                            v
                        }
                    }
                    _ => return err("bad difference size"),
                };
                let at = |dy: usize, dx: usize| out[(y - dy) * row_len + (x - dx) * nc + c] as i32;
                let pred = if reset {
                    initial
                } else if first_line_of_interval {
                    at(0, 1)
                } else if x == 0 {
                    at(1, 0)
                } else {
                    let (ra, rb, rc) = (at(0, 1), at(1, 0), at(1, 1));
                    match predictor {
                        1 => ra,
                        2 => rb,
                        3 => rc,
                        4 => ra + rb - rc,
                        5 => ra + ((rb - rc) >> 1),
                        6 => rb + ((ra - rc) >> 1),
                        _ => (ra + rb) >> 1,
                    }
                };
                out[k] = ((pred + diff) & mask) as u16;
            }
            reset = false;
            since_restart += 1;
        }
        first_line_of_interval = false;
    }
    if pt > 0 {
        for v in &mut out {
            *v <<= pt;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A lossless JPEG of `samples` (`width × height`, one component, predictor 1), with a
    /// Huffman table coding every difference size 0..=16 in 5 bits: the encoder the decoder is
    /// checked against, by the standard's rules (T.81 H.1.2, F.1.2.1, K.3).
    fn encode(width: usize, height: usize, samples: &[u16], precision: u8) -> Vec<u8> {
        let mut out = vec![0xff, 0xd8];
        // DHT: 17 codes of length 5 (values 0..=16).
        out.extend([0xff, 0xc4, 0, 2 + 17 + 17, 0x00]);
        let mut counts = [0u8; 16];
        counts[4] = 17;
        out.extend(counts);
        out.extend(0u8..=16);
        out.extend([0xff, 0xc3, 0, 11, precision]);
        out.extend((height as u16).to_be_bytes());
        out.extend((width as u16).to_be_bytes());
        out.extend([1, 1, 0x11, 0]);
        out.extend([0xff, 0xda, 0, 8, 1, 1, 0x00, 1, 0, 0]);
        let (mut acc, mut n) = (0u64, 0u32);
        let mut bytes = Vec::new();
        let mut put = |v: u64, k: u32, acc: &mut u64, n: &mut u32| {
            *acc = *acc << k | v;
            *n += k;
            while *n >= 8 {
                let b = (*acc >> (*n - 8)) as u8;
                bytes.push(b);
                if b == 0xff {
                    bytes.push(0);
                }
                *n -= 8;
            }
        };
        for y in 0..height {
            for x in 0..width {
                let v = samples[y * width + x] as i32;
                let pred = if y == 0 && x == 0 {
                    1 << (precision - 1)
                } else if x == 0 {
                    samples[(y - 1) * width] as i32
                } else {
                    samples[y * width + x - 1] as i32
                };
                let d = (v - pred).rem_euclid(65536);
                let d = if d >= 32768 { d - 65536 } else { d };
                let ssss = if d == 0 {
                    0
                } else {
                    32 - d.unsigned_abs().leading_zeros()
                };
                put(ssss as u64, 5, &mut acc, &mut n);
                if ssss > 0 && ssss < 16 {
                    let extra = if d < 0 { d - 1 } else { d } as u64 & ((1 << ssss) - 1);
                    put(extra, ssss, &mut acc, &mut n);
                }
            }
        }
        if n > 0 {
            put((1 << (8 - n)) - 1, 8 - n, &mut acc, &mut n);
        }
        out.extend(bytes);
        out.extend([0xff, 0xd9]);
        out
    }

    #[test]
    fn decodes_what_the_standard_encodes() {
        let (w, h) = (7, 5);
        let samples: Vec<u16> = (0..w * h)
            .map(|k| ((k * 7919) % 4096) as u16 ^ if k % 3 == 0 { 0xfff } else { 0 })
            .collect();
        let bytes = encode(w, h, &samples, 12);
        let d = decode(&bytes).unwrap();
        assert_eq!((d.width, d.height, d.components), (w, h, 1));
        assert_eq!(d.samples, samples);
        let big: Vec<u16> = (0..w * h).map(|k| (k as u16).wrapping_mul(40503)).collect();
        assert_eq!(decode(&encode(w, h, &big, 16)).unwrap().samples, big);
    }

    #[test]
    fn damaged_streams_are_errors_not_panics() {
        let samples: Vec<u16> = (0..64).map(|k| (k * 97 % 1024) as u16).collect();
        let good = encode(8, 8, &samples, 10);
        for cut in 0..good.len() {
            let _ = decode(&good[..cut]);
        }
        for k in 0..good.len() {
            let mut b = good.clone();
            b[k] ^= 0x5a;
            let _ = decode(&b);
        }
        assert!(decode(b"\xff\xd8\xff\xc0\0\x02").is_err());
    }
}
