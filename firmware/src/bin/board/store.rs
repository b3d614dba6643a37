//! The rig profile in flash: the record log of `flash_record.rs` in the chip's last sector
//! (sector 7, 128 KiB at 0x0806_0000), read through the memory map and written with
//! embassy-stm32's blocking flash driver. The firmware image stays far below it (the size budget
//! is 128 KiB from 0x0800_0000).
use embassy_stm32::Peri;
use embassy_stm32::flash::{Blocking, Flash, WRITE_SIZE};
use embassy_stm32::peripherals as p;

use crate::flash_record::{self, MAX_RECORD, RECORD_ALIGN};

/// Offset of the profile sector from the start of flash.
pub const SECTOR_OFFSET: u32 = 0x6_0000;
/// Its length.
pub const SECTOR_LEN: usize = 128 * 1024;
/// Its address in the memory map.
const SECTOR_ADDR: usize = 0x0800_0000 + SECTOR_OFFSET as usize;

const _: () = assert!(RECORD_ALIGN.is_multiple_of(WRITE_SIZE));

/// Why the profile could not be stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum StoreError {
    /// Payload too large for a record.
    TooLarge,
    /// The flash controller reported an error.
    Flash,
}

/// The profile store.
pub struct Store {
    flash: Flash<'static, Blocking>,
}

impl Store {
    /// Take the flash controller.
    pub fn new(flash: Peri<'static, p::FLASH>) -> Self {
        Self {
            flash: Flash::new_blocking(flash),
        }
    }

    fn sector(&self) -> &'static [u8] {
        // SAFETY: sector 7 is always-mapped, always-readable flash on the STM32F446RE; nothing
        // else writes it, and `save` borrows `self` mutably, so no reference outlives a write.
        unsafe { core::slice::from_raw_parts(SECTOR_ADDR as *const u8, SECTOR_LEN) }
    }

    /// The newest stored payload, copied into `out` (`None`: nothing valid stored).
    pub fn load<'b>(&self, out: &'b mut [u8]) -> Option<&'b [u8]> {
        let payload = flash_record::latest_payload(self.sector())?;
        let out = out.get_mut(..payload.len())?;
        out.copy_from_slice(payload);
        Some(out)
    }

    /// Append `payload` as the newest record (erasing the sector first when it is full).
    pub fn save(&mut self, payload: &[u8]) -> Result<(), StoreError> {
        let mut record = [0u8; MAX_RECORD];
        let n = flash_record::encode(payload, &mut record).map_err(|_| StoreError::TooLarge)?;
        let record = record.get(..n).ok_or(StoreError::TooLarge)?;
        let scan = flash_record::scan(self.sector());
        let at = match flash_record::place(&scan, n, SECTOR_LEN) {
            Ok(at) => at,
            Err(()) => {
                defmt::info!("profile sector full or unreadable: erasing");
                self.flash
                    .blocking_erase(SECTOR_OFFSET, SECTOR_OFFSET + SECTOR_LEN as u32)
                    .map_err(|_| StoreError::Flash)?;
                0
            }
        };
        let offset = SECTOR_OFFSET + u32::try_from(at).map_err(|_| StoreError::Flash)?;
        self.flash
            .blocking_write(offset, record)
            .map_err(|_| StoreError::Flash)
    }
}
