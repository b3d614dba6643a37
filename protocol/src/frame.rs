//! Framing: `COBS(postcard(message) ‖ CRC-32/ISO-HDLC little-endian) ‖ 0x00`.
//!
//! The encoder writes one whole frame into a caller-provided buffer; the [`FrameDecoder`] takes
//! arbitrary byte chunks (as a UART or USB delivers them) and yields whole messages. Nothing here
//! allocates or does I/O.

use core::marker::PhantomData;

use serde::{Serialize, de::DeserializeOwned};

use crate::message::{Event, Reply, Request};

/// Largest frame on the wire in bytes, including the trailing `0x00` delimiter. A receive buffer of
/// this size always holds a whole frame; longer runs between delimiters are dropped as oversize.
pub const MAX_FRAME: usize = 256;

/// Largest postcard-encoded message (before CRC and COBS). Chosen so that message + 4 CRC bytes,
/// COBS-encoded, plus the delimiter never exceed [`MAX_FRAME`].
pub const MAX_MESSAGE: usize = 248;

/// Bytes of CRC appended to every message.
pub const CRC_LEN: usize = 4;

const _: () = assert!(cobs::max_encoding_length(MAX_MESSAGE + CRC_LEN) < MAX_FRAME);

/// CRC-32/ISO-HDLC (the zlib/Ethernet CRC) over the postcard bytes.
const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// Why a message could not be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum EncodeError {
    /// The postcard encoding is longer than [`MAX_MESSAGE`].
    MessageTooLarge,
    /// The output buffer is shorter than the frame (use [`MAX_FRAME`] bytes).
    BufferTooSmall,
}

impl core::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::MessageTooLarge => write!(f, "message longer than {MAX_MESSAGE} bytes"),
            Self::BufferTooSmall => write!(f, "output buffer too small for the frame"),
        }
    }
}

impl core::error::Error for EncodeError {}

/// Why one received frame was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum DropReason {
    /// More than [`MAX_FRAME`] bytes before a delimiter.
    Oversize,
    /// Not valid COBS, or shorter than one byte plus the CRC.
    Corrupt,
    /// CRC mismatch.
    Crc,
    /// CRC fine but not a valid message of the expected type (e.g. other protocol version).
    Malformed,
}

/// Counters of everything the decoder saw. Counters saturate instead of wrapping.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DecoderStats {
    /// Messages yielded.
    pub frames: u32,
    /// Frames dropped as oversize.
    pub oversize: u32,
    /// Frames dropped as invalid COBS or too short.
    pub corrupt: u32,
    /// Frames dropped for a CRC mismatch.
    pub crc: u32,
    /// Frames dropped because the payload did not parse.
    pub malformed: u32,
}

impl DecoderStats {
    /// All dropped frames.
    pub fn dropped(&self) -> u32 {
        self.oversize
            .saturating_add(self.corrupt)
            .saturating_add(self.crc)
            .saturating_add(self.malformed)
    }

    fn count(&mut self, reason: DropReason) {
        let c = match reason {
            DropReason::Oversize => &mut self.oversize,
            DropReason::Corrupt => &mut self.corrupt,
            DropReason::Crc => &mut self.crc,
            DropReason::Malformed => &mut self.malformed,
        };
        *c = c.saturating_add(1);
    }
}

/// Encodes any message as one frame (delimiter included) into `out`; returns the frame length.
///
/// Prefer the typed [`encode_request`], [`encode_reply`] and [`encode_event`]: the receiver must
/// decode the same type that was encoded.
pub fn encode_frame<T: Serialize + ?Sized>(msg: &T, out: &mut [u8]) -> Result<usize, EncodeError> {
    let mut raw = [0u8; MAX_MESSAGE + CRC_LEN];
    let (body, _) = raw.split_at_mut(MAX_MESSAGE);
    let len = postcard::to_slice(msg, body)
        .map_err(|_| EncodeError::MessageTooLarge)?
        .len();
    let crc = CRC.checksum(raw.get(..len).ok_or(EncodeError::MessageTooLarge)?);
    let tail = raw
        .get_mut(len..len + CRC_LEN)
        .ok_or(EncodeError::MessageTooLarge)?;
    tail.copy_from_slice(&crc.to_le_bytes());
    let raw = raw
        .get(..len + CRC_LEN)
        .ok_or(EncodeError::MessageTooLarge)?;
    // Checking the worst case up front keeps `cobs` away from its short-buffer edge cases.
    if out.len() <= cobs::max_encoding_length(raw.len()) {
        return Err(EncodeError::BufferTooSmall);
    }
    let n = cobs::try_encode(raw, out).map_err(|_| EncodeError::BufferTooSmall)?;
    *out.get_mut(n).ok_or(EncodeError::BufferTooSmall)? = 0;
    Ok(n + 1)
}

/// Encodes a host → rig request.
pub fn encode_request(req: &Request, out: &mut [u8]) -> Result<usize, EncodeError> {
    encode_frame(req, out)
}

/// Borrowing twin of [`crate::RigMessage`]: serde encodes `&T` exactly like `T`, so this produces
/// the same bytes without cloning the reply or event.
#[derive(Serialize)]
enum RigMessageRef<'a> {
    Reply(&'a Reply),
    Event(&'a Event),
}

/// Encodes a reply as a [`crate::RigMessage::Reply`] frame.
pub fn encode_reply(reply: &Reply, out: &mut [u8]) -> Result<usize, EncodeError> {
    encode_frame(&RigMessageRef::Reply(reply), out)
}

/// Encodes an event as a [`crate::RigMessage::Event`] frame.
pub fn encode_event(event: &Event, out: &mut [u8]) -> Result<usize, EncodeError> {
    encode_frame(&RigMessageRef::Event(event), out)
}

/// Decodes one frame's bytes (COBS-encoded, without the delimiter) in place.
pub fn decode_frame<T: DeserializeOwned>(encoded: &mut [u8]) -> Result<T, DropReason> {
    let n = cobs::decode_in_place(encoded).map_err(|_| DropReason::Corrupt)?;
    let raw = encoded.get(..n).ok_or(DropReason::Corrupt)?;
    let body_len = n
        .checked_sub(CRC_LEN)
        .filter(|&l| l > 0)
        .ok_or(DropReason::Corrupt)?;
    let (body, crc) = raw.split_at(body_len);
    let mut expected = [0u8; CRC_LEN];
    expected.copy_from_slice(crc);
    if CRC.checksum(body) != u32::from_le_bytes(expected) {
        return Err(DropReason::Crc);
    }
    match postcard::take_from_bytes::<T>(body) {
        Ok((msg, [])) => Ok(msg),
        _ => Err(DropReason::Malformed),
    }
}

/// Streaming frame decoder: feed it whatever bytes arrived, get whole messages out.
///
/// Corrupt, oversize and unparseable frames are dropped and counted in [`FrameDecoder::stats`];
/// the decoder resynchronises at the next `0x00`. Empty frames (two delimiters in a row) are
/// ignored and not counted: a sender may write a lone `0x00` at any time to flush the receiver.
#[derive(Debug, Clone)]
pub struct FrameDecoder {
    buf: [u8; MAX_FRAME],
    len: usize,
    /// Inside an oversize frame: skip until the next delimiter.
    discarding: bool,
    stats: DecoderStats,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buf: [0; MAX_FRAME],
            len: 0,
            discarding: false,
            stats: DecoderStats {
                frames: 0,
                oversize: 0,
                corrupt: 0,
                crc: 0,
                malformed: 0,
            },
        }
    }

    /// What the decoder has yielded and dropped so far.
    pub fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// Forgets a partially received frame (not counted as a drop), e.g. after reopening a port.
    pub fn reset(&mut self) {
        self.len = 0;
        self.discarding = false;
    }

    /// Consumes `input` up to and including the end of the first good frame and returns its
    /// message together with the unconsumed rest; returns `(None, &[])` when `input` ran out first
    /// (a partial frame stays buffered for the next call).
    pub fn feed<'a, T: DeserializeOwned>(&mut self, mut input: &'a [u8]) -> (Option<T>, &'a [u8]) {
        while !input.is_empty() {
            let (chunk, rest, ends) = match input.iter().position(|&b| b == 0) {
                Some(i) => (
                    input.get(..i).unwrap_or(&[]),
                    input.get(i + 1..).unwrap_or(&[]),
                    true,
                ),
                None => (input, &[][..], false),
            };
            input = rest;
            if !self.discarding {
                let end = self.len + chunk.len();
                // The delimiter is not stored, so at most MAX_FRAME - 1 encoded bytes fit.
                match self.buf.get_mut(self.len..end).filter(|_| end < MAX_FRAME) {
                    Some(dst) => {
                        dst.copy_from_slice(chunk);
                        self.len = end;
                    }
                    None => self.discarding = true,
                }
            }
            if !ends {
                break;
            }
            if self.discarding {
                self.stats.count(DropReason::Oversize);
                self.reset();
                continue;
            }
            if self.len == 0 {
                continue;
            }
            let result = match self.buf.get_mut(..self.len) {
                Some(frame) => decode_frame::<T>(frame),
                None => Err(DropReason::Oversize),
            };
            self.len = 0;
            match result {
                Ok(msg) => {
                    self.stats.frames = self.stats.frames.saturating_add(1);
                    return (Some(msg), input);
                }
                Err(reason) => self.stats.count(reason),
            }
        }
        (None, &[])
    }

    /// Iterates over every message completed by `input`.
    pub fn decode<'d, 'a, T: DeserializeOwned>(&'d mut self, input: &'a [u8]) -> Frames<'d, 'a, T> {
        Frames {
            decoder: self,
            input,
            _msg: PhantomData,
        }
    }
}

/// Iterator returned by [`FrameDecoder::decode`].
#[derive(Debug)]
pub struct Frames<'d, 'a, T> {
    decoder: &'d mut FrameDecoder,
    input: &'a [u8],
    _msg: PhantomData<fn() -> T>,
}

impl<T: DeserializeOwned> Iterator for Frames<'_, '_, T> {
    type Item = T;

    fn next(&mut self) -> Option<T> {
        if self.input.is_empty() {
            return None;
        }
        let (msg, rest) = self.decoder.feed(self.input);
        self.input = rest;
        msg
    }
}
