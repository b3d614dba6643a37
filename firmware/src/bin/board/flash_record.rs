//! The rig profile's home on the board: a log of versioned, CRC-checked, numbered records in two
//! small flash sectors used in turn. Free of registers; `firmware/tests/board_model.rs` runs it on
//! in-memory sectors.
//!
//! Record layout (little-endian, padded with 0xFF to [`RECORD_ALIGN`] bytes):
//!
//! ```text
//! magic "SSRP" (u32) | format version (u16) | payload length (u16) | sequence (u32) | payload | CRC-32 (u32)
//! ```
//!
//! The CRC (CRC-32/ISO-HDLC, as the link's frames) covers everything before it. Writes append after
//! the newest record (erased flash reads 0xFF, and NOR flash can only clear bits, so appending
//! never touches an older record). Reading takes the valid record with the highest sequence number
//! in either sector: a write cut by a power loss leaves at worst a bad record after the good one,
//! which is then ignored. When the sector in use is full (or holds something unreadable), the
//! *other* sector is erased and the record goes there: the newest good record is never in the
//! sector being erased, so a reset during the erase loses nothing.
//!
//! Blocking: the core asks for a save only while the rig is idle with the lasers off. A save that
//! appends programs one record (≤ [`MAX_RECORD`] / 4 words at ≤ 100 µs each: ≤ 7.4 ms); about one
//! save in [`RECORDS_PER_SECTOR`] also erases a 16 KiB sector first, at most
//! [`SECTOR_ERASE_MAX_MS`]. The CPU runs from the same flash bank, so every interrupt waits that
//! long; the independent watchdog is stretched to [`ERASE_WATCHDOG_MS`] around the erase
//! ([`erase_watchdog`]) so it cannot reset the chip mid-erase, as it did with the 128 KiB sector
//! (up to 2 s) and a 500 ms watchdog.

use subsurf_protocol::{RigProfile, SaveError};

/// Record magic, "SSRP" read as little-endian u32.
pub const RECORD_MAGIC: u32 = u32::from_le_bytes(*b"SSRP");
/// Format version of the record this firmware writes and reads (2: the sequence number; 3: the
/// payload starts with the profile's layout key, [`encode_profile`]).
pub const RECORD_VERSION: u16 = 3;
/// Records start at multiples of this (covers the flash's write granularity).
pub const RECORD_ALIGN: usize = 32;
/// Header bytes before the payload.
pub const HEADER_LEN: usize = 12;
/// Largest payload.
pub const MAX_PAYLOAD: usize = 256;
/// Largest record (header + payload + CRC, padded).
pub const MAX_RECORD: usize = (HEADER_LEN + MAX_PAYLOAD + 4).div_ceil(RECORD_ALIGN) * RECORD_ALIGN;
/// The profile's sectors: sectors 1 and 2 of the STM32F446, 16 KiB each.
pub const SECTOR_LEN: usize = 16 * 1024;
/// Records of the largest size a sector holds between two erases.
pub const RECORDS_PER_SECTOR: usize = SECTOR_LEN / MAX_RECORD;

/// Longest erase of one 16 KiB sector at ×32 parallelism (`store.rs` erases with PSIZE = ×32
/// itself: embassy-stm32 0.6 left it at ×8, up to 800 ms), ms: STM32F446xC/E datasheet, "Flash
/// memory programming" characteristics, t_ERASE16KB max (typ 250 ms). A 128 KiB sector takes up
/// to 2 s there.
pub const SECTOR_ERASE_MAX_MS: u32 = 500;
/// Longest programming of one 32-bit word, µs (same table, t_prog max).
pub const WORD_PROGRAM_MAX_US: u32 = 100;
/// The watchdog's timeout at its fastest during an erase, ms: above the longest erase plus the
/// record's programming, with room to spare.
pub const ERASE_WATCHDOG_MS: u32 = 1_000;
/// The watchdog counts the LSI oscillator, which may run this fast (datasheet: 17–47 kHz,
/// 32 kHz typical): a timeout computed at 32 kHz comes this much sooner.
pub const LSI_MAX_HZ: u32 = 47_000;

const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// The record payload for a rig profile, in `out`: [`RigProfile::LAYOUT`] (u32, little-endian),
/// then the profile's postcard bytes. `None` if `out` is too small.
///
/// The key makes a record name the layout it was written with: the record's format version
/// does not change when `RigProfile` gains, loses or retypes a field, and postcard has no field
/// names, so without it a new firmware would decode an old record's bytes into the wrong fields
/// (a polarity among them) and could still pass `validate()`.
pub fn encode_profile<'b>(profile: &RigProfile, out: &'b mut [u8]) -> Option<&'b [u8]> {
    let (key, rest) = out.split_at_mut_checked(4)?;
    key.copy_from_slice(&RigProfile::LAYOUT.to_le_bytes());
    let n = postcard::to_slice(profile, rest).ok()?.len();
    out.get(..4 + n)
}

/// The rig profile in a record payload: only under this firmware's layout key, only when the
/// bytes are exactly one profile (postcard's `from_bytes` would ignore trailing bytes) and only a
/// valid one. Anything else is "no profile stored".
pub fn decode_profile(payload: &[u8]) -> Option<RigProfile> {
    let (key, rest) = payload.split_at_checked(4)?;
    if key != RigProfile::LAYOUT.to_le_bytes() {
        return None;
    }
    let (profile, tail) = postcard::take_from_bytes::<RigProfile>(rest).ok()?;
    (tail.is_empty() && profile.validate().is_ok()).then_some(profile)
}

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

/// Write record number `seq` for `payload` into `out`; returns its (padded) length.
pub fn encode(payload: &[u8], seq: u32, out: &mut [u8]) -> Result<usize, RecordError> {
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
    head[8..12].copy_from_slice(&seq.to_le_bytes());
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
    /// Offset, payload length and sequence number of the newest valid record of this format.
    pub latest: Option<(usize, usize, u32)>,
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
    let mut latest: Option<(usize, usize, u32)> = None;
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
        let (Some(version), Some(len), Some(seq)) = (
            read_u16(sector, at + 4),
            read_u16(sector, at + 6),
            read_u32(sector, at + 8),
        ) else {
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
        if stored == Some(computed)
            && version == RECORD_VERSION
            && latest.is_none_or(|(_, _, s)| seq > s)
        {
            latest = Some((at, len, seq));
        }
        at += record_len(len);
    }
    Scan { latest, free: None }
}

/// The sector (0 or 1) and record holding the newest valid record of the two, if any.
pub fn newest(scans: &[Scan; 2]) -> Option<(usize, (usize, usize, u32))> {
    let a = scans[0].latest.map(|r| (0, r));
    let b = scans[1].latest.map(|r| (1, r));
    match (a, b) {
        (Some(a), Some(b)) => Some(if b.1.2 > a.1.2 { b } else { a }),
        (a, b) => a.or(b),
    }
}

/// The payload of the newest valid record in either sector, if any.
pub fn latest_payload(sectors: [&[u8]; 2]) -> Option<&[u8]> {
    let scans = [scan(sectors[0]), scan(sectors[1])];
    let (sector, (at, len, _)) = newest(&scans)?;
    sectors
        .get(sector)?
        .get(at + HEADER_LEN..at + HEADER_LEN + len)
}

/// Where the next record of `len` bytes (padded) goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Placement {
    /// Sector 0 or 1.
    pub sector: usize,
    /// Erase that sector first.
    pub erase: bool,
    /// Offset in the sector.
    pub at: usize,
    /// The record's sequence number.
    pub seq: u32,
}

/// Append to the sector holding the newest record while it has room; otherwise erase the other
/// sector (never the one with the newest good record) and start it.
pub fn place(scans: &[Scan; 2], len: usize, sector_len: usize) -> Placement {
    let (current, seq) = match newest(scans) {
        Some((sector, (_, _, seq))) => (sector, seq.wrapping_add(1)),
        None => (0, 1),
    };
    match scans.get(current).and_then(|s| s.free) {
        Some(at) if at + len <= sector_len => Placement {
            sector: current,
            erase: false,
            at,
            seq,
        },
        _ => Placement {
            sector: if newest(scans).is_some() {
                1 - current
            } else {
                current
            },
            erase: true,
            at: 0,
            seq,
        },
    }
}

/// The independent watchdog's prescaler register value (divider 4 · 2^pr) and reload for a
/// timeout of at least `min_ms` even when the LSI runs at [`LSI_MAX_HZ`]. `None` if the watchdog
/// cannot wait that long (at most 4095 · 256 LSI cycles).
pub fn watchdog_setting(min_ms: u32) -> Option<(u8, u16)> {
    (0u8..=6).find_map(|pr| {
        let divider = 4u64 << pr;
        let ticks = (u64::from(min_ms) * u64::from(LSI_MAX_HZ)).div_ceil(1_000 * divider);
        u16::try_from(ticks)
            .ok()
            .filter(|&t| t <= 0x0fff)
            .map(|t| (pr, t.max(1)))
    })
}

/// The watchdog setting used around an erase: [`ERASE_WATCHDOG_MS`] at the fastest LSI.
pub fn erase_watchdog() -> Option<(u8, u16)> {
    watchdog_setting(ERASE_WATCHDOG_MS)
}

/// The longest a save blocks everything, ms: one sector erase and one record's programming.
pub const fn worst_case_blocking_ms() -> u32 {
    SECTOR_ERASE_MAX_MS + ((MAX_RECORD / 4) as u32 * WORD_PROGRAM_MAX_US).div_ceil(1_000)
}

/// The two profile sectors as a save touches them: the board's flash controller (`store.rs`) or
/// an in-memory model in the host tests, which run this module's save and read-back as shipped.
pub trait SectorFlash {
    /// Sector `i`'s bytes as a read sees them (on the board through the flash's data cache).
    fn sector(&self, i: usize) -> &[u8];
    /// Erase sector `i`.
    fn erase(&mut self, i: usize) -> Result<(), SaveError>;
    /// Program `bytes` at offset `at` of sector `i`.
    fn program(&mut self, i: usize, at: usize, bytes: &[u8]) -> Result<(), SaveError>;
    /// Drop what the flash's data cache holds: after an erase it may still hold the erased
    /// bytes, and a read-back would verify them instead of the flash.
    fn reset_data_cache(&mut self);
}

/// The newest stored payload (`None`: nothing valid stored).
pub fn load<'b>(flash: &impl SectorFlash, out: &'b mut [u8]) -> Option<&'b [u8]> {
    let payload = latest_payload([flash.sector(0), flash.sector(1)])?;
    let out = out.get_mut(..payload.len())?;
    out.copy_from_slice(payload);
    Some(out)
}

/// The stored rig profile, if a valid one of this firmware's layout is.
pub fn load_profile(flash: &impl SectorFlash) -> Option<RigProfile> {
    let mut buf = [0u8; MAX_PAYLOAD];
    load(flash, &mut buf).and_then(decode_profile)
}

/// Store `payload` as the newest record, erasing the other sector first when the one in use is
/// full (and then resetting the data cache); where it went.
pub fn save(flash: &mut impl SectorFlash, payload: &[u8]) -> Result<Placement, SaveError> {
    let scans = [scan(flash.sector(0)), scan(flash.sector(1))];
    let mut record = [0u8; MAX_RECORD];
    let len = record_len(payload.len());
    let place = place(&scans, len, SECTOR_LEN);
    let n = encode(payload, place.seq, &mut record).map_err(|_| SaveError::Encode)?;
    let record = record.get(..n).ok_or(SaveError::Encode)?;
    if place.erase {
        let erased = flash.erase(place.sector);
        flash.reset_data_cache();
        erased?;
    }
    flash.program(place.sector, place.at, record)?;
    Ok(place)
}

/// Save `profile` and read it back the way a boot does: `Ok` only when flash now returns this
/// profile, `Err(SaveError::Verify)` when it returns anything else (a stuck bit, a write that
/// did not take, stale cached data). A profile flash already holds is not written again (no
/// wear, no erase stall).
pub fn store_profile(flash: &mut impl SectorFlash, profile: &RigProfile) -> Result<(), SaveError> {
    if load_profile(flash).as_ref() == Some(profile) {
        return Ok(());
    }
    let mut buf = [0u8; MAX_PAYLOAD];
    let bytes = encode_profile(profile, &mut buf).ok_or(SaveError::Encode)?;
    save(flash, bytes)?;
    if load_profile(flash).as_ref() == Some(profile) {
        Ok(())
    } else {
        Err(SaveError::Verify)
    }
}
