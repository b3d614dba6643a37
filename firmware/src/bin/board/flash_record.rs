//! The rig profile's home on the board: a log of versioned, CRC-checked records in one flash
//! sector. Free of registers; `firmware/tests/board_model.rs` runs it on an in-memory sector.
//!
//! Record layout (little-endian, padded with 0xFF to [`RECORD_ALIGN`] bytes):
//!
//! ```text
//! magic "SSRP" (u32) | format version (u16) | payload length (u16) | payload | CRC-32 (u32)
//! ```
//!
//! The CRC (CRC-32/ISO-HDLC, as the link's frames) covers magic, version, length and payload.
//! Writes append after the newest record (erased flash reads 0xFF, and NOR flash can only clear
//! bits, so appending never touches an older record); the sector is erased only when it is full or
//! holds something unreadable. Reading takes the *last* record whose CRC checks: a write cut by a
//! power loss leaves at worst a bad record after the good one, which is then ignored. Whole-sector
//! erases are rare (a 128 KiB sector takes ~1000 profile writes between erases), which keeps the
//! flash far inside its 10 000-cycle endurance.

/// Record magic, "SSRP" read as little-endian u32.
pub const RECORD_MAGIC: u32 = u32::from_le_bytes(*b"SSRP");
/// Format version of the payload this firmware writes and reads.
pub const RECORD_VERSION: u16 = 1;
/// Records start at multiples of this (covers the flash's write granularity).
pub const RECORD_ALIGN: usize = 32;
/// Header bytes before the payload.
pub const HEADER_LEN: usize = 8;
/// Largest payload.
pub const MAX_PAYLOAD: usize = 256;
/// Largest record (header + payload + CRC, padded).
pub const MAX_RECORD: usize = (HEADER_LEN + MAX_PAYLOAD + 4).div_ceil(RECORD_ALIGN) * RECORD_ALIGN;

const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// Why a record could not be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RecordError {
    /// Payload longer than [`MAX_PAYLOAD`].
    TooLarge,
    /// Output buffer shorter than the record.
    BufferTooSmall,
}

/// Length of the record for a payload of `len` bytes, padded.
pub const fn record_len(len: usize) -> usize {
    (HEADER_LEN + len + 4).div_ceil(RECORD_ALIGN) * RECORD_ALIGN
}

/// Write one record for `payload` into `out`; returns its (padded) length.
pub fn encode(payload: &[u8], out: &mut [u8]) -> Result<usize, RecordError> {
    if payload.len() > MAX_PAYLOAD {
        return Err(RecordError::TooLarge);
    }
    let total = record_len(payload.len());
    let out = out.get_mut(..total).ok_or(RecordError::BufferTooSmall)?;
    out.fill(0xff);
    let len = u16::try_from(payload.len()).map_err(|_| RecordError::TooLarge)?;
    let body = HEADER_LEN + payload.len();
    let (head, rest) = out.split_at_mut(HEADER_LEN);
    head[..4].copy_from_slice(&RECORD_MAGIC.to_le_bytes());
    head[4..6].copy_from_slice(&RECORD_VERSION.to_le_bytes());
    head[6..8].copy_from_slice(&len.to_le_bytes());
    rest[..payload.len()].copy_from_slice(payload);
    let mut digest = CRC.digest();
    digest.update(head);
    digest.update(payload);
    let crc = digest.finalize();
    out[body..body + 4].copy_from_slice(&crc.to_le_bytes());
    Ok(total)
}

/// What a sector holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Scan {
    /// Offset and payload length of the newest valid record of this format version.
    pub latest: Option<(usize, usize)>,
    /// Where the next record goes; `None` when the sector must be erased first (something
    /// unreadable where free space should start).
    pub free: Option<usize>,
}

fn read_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let b = bytes.get(at..at + 4)?;
    Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

fn read_u16(bytes: &[u8], at: usize) -> Option<u16> {
    let b = bytes.get(at..at + 2)?;
    Some(u16::from_le_bytes([b[0], b[1]]))
}

/// Walk the records of a sector image.
pub fn scan(sector: &[u8]) -> Scan {
    let mut latest = None;
    let mut at = 0usize;
    // Bounded by the sector: every pass advances by at least RECORD_ALIGN.
    while at < sector.len() {
        let Some(magic) = read_u32(sector, at) else {
            return Scan { latest, free: None };
        };
        if magic == u32::MAX {
            // Erased: free space starts here if the rest of this record slot is erased too.
            let clean = sector[at..].iter().take(MAX_RECORD).all(|&b| b == 0xff);
            return Scan {
                latest,
                free: clean.then_some(at),
            };
        }
        let (Some(version), Some(len)) = (read_u16(sector, at + 4), read_u16(sector, at + 6))
        else {
            return Scan { latest, free: None };
        };
        let len = usize::from(len);
        if magic != RECORD_MAGIC || len > MAX_PAYLOAD || at + record_len(len) > sector.len() {
            // Not ours or torn mid-header: nothing after it can be trusted as free space.
            return Scan { latest, free: None };
        }
        let body = at + HEADER_LEN + len;
        let stored = read_u32(sector, body);
        let computed = CRC.checksum(&sector[at..body]);
        if stored == Some(computed) && version == RECORD_VERSION {
            latest = Some((at, len));
        }
        at += record_len(len);
    }
    Scan { latest, free: None }
}

/// The payload of the newest valid record, if any.
pub fn latest_payload(sector: &[u8]) -> Option<&[u8]> {
    let (at, len) = scan(sector).latest?;
    sector.get(at + HEADER_LEN..at + HEADER_LEN + len)
}

/// Where to put a record of `len` bytes (padded): `Ok(offset)` to append, `Err(())` to erase the
/// sector and write at 0.
#[allow(clippy::result_unit_err)]
pub fn place(scan: &Scan, len: usize, sector_len: usize) -> Result<usize, ()> {
    match scan.free {
        Some(at) if at + len <= sector_len => Ok(at),
        _ => Err(()),
    }
}
