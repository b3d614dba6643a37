//! The rig profile in flash: the record log of `flash_record.rs` in sectors 1 and 2 (16 KiB each
//! at 0x0800_4000 and 0x0800_8000; `firmware/board/memory.x` keeps the code out of them), read
//! through the memory map and written with embassy-stm32's blocking flash driver.
//!
//! An erase stalls the CPU (it runs from the same flash bank) for up to
//! [`flash_record::SECTOR_ERASE_MAX_MS`], every interrupt included; the independent watchdog is
//! stretched around it ([`flash_record::erase_watchdog`]) and put back afterwards, so it cannot
//! reset the chip mid-erase. The core asks for a save only while the rig is idle with the lasers
//! off, and the e-stop's EXTI line latches its edge, so a press during the erase is acted on
//! right after it.
use embassy_stm32::Peri;
use embassy_stm32::flash::{Blocking, Flash, WRITE_SIZE};
use embassy_stm32::pac;
use embassy_stm32::peripherals as p;

use crate::flash_record::{self, MAX_RECORD, RECORD_ALIGN, SECTOR_LEN};

/// Offsets of the two profile sectors from the start of flash.
pub const SECTOR_OFFSETS: [u32; 2] = [0x4000, 0x8000];
const FLASH_BASE: usize = 0x0800_0000;

const _: () = assert!(RECORD_ALIGN.is_multiple_of(WRITE_SIZE));
// The stretched watchdog outlasts the worst save (the datasheet's longest erase and programming).
const _: () = assert!(flash_record::worst_case_blocking_ms() < flash_record::ERASE_WATCHDOG_MS);
// Erases stay rare: a sector takes this many of the largest records.
const _: () = assert!(flash_record::RECORDS_PER_SECTOR >= 50);

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

    fn sector(&self, i: usize) -> &'static [u8] {
        let offset = SECTOR_OFFSETS.get(i).copied().unwrap_or(SECTOR_OFFSETS[0]);
        // SAFETY: sectors 1 and 2 are always-mapped, always-readable flash on the STM32F446RE;
        // nothing else writes them (the linker keeps code out), and `save` borrows `self`
        // mutably, so no reference outlives a write.
        unsafe {
            core::slice::from_raw_parts((FLASH_BASE + offset as usize) as *const u8, SECTOR_LEN)
        }
    }

    /// The newest stored payload, copied into `out` (`None`: nothing valid stored).
    pub fn load<'b>(&self, out: &'b mut [u8]) -> Option<&'b [u8]> {
        let payload = flash_record::latest_payload([self.sector(0), self.sector(1)])?;
        let out = out.get_mut(..payload.len())?;
        out.copy_from_slice(payload);
        Some(out)
    }

    /// Store `payload` as the newest record (erasing the other sector first when the one in use
    /// is full).
    pub fn save(&mut self, payload: &[u8]) -> Result<(), StoreError> {
        let scans = [
            flash_record::scan(self.sector(0)),
            flash_record::scan(self.sector(1)),
        ];
        let mut record = [0u8; MAX_RECORD];
        let len = flash_record::record_len(payload.len());
        let place = flash_record::place(&scans, len, SECTOR_LEN);
        let n = flash_record::encode(payload, place.seq, &mut record)
            .map_err(|_| StoreError::TooLarge)?;
        let record = record.get(..n).ok_or(StoreError::TooLarge)?;
        let sector = SECTOR_OFFSETS
            .get(place.sector)
            .copied()
            .ok_or(StoreError::Flash)?;
        if place.erase {
            defmt::info!(
                "profile sector {} full or unreadable: erasing",
                place.sector + 1
            );
            let erased = with_erase_watchdog(|| {
                self.flash
                    .blocking_erase(sector, sector + SECTOR_LEN as u32)
                    .map_err(|_| StoreError::Flash)
            });
            erased?;
        }
        let offset = sector + u32::try_from(place.at).map_err(|_| StoreError::Flash)?;
        self.flash
            .blocking_write(offset, record)
            .map_err(|_| StoreError::Flash)
    }
}

/// Run `f` (an erase) with the independent watchdog stretched to
/// [`flash_record::ERASE_WATCHDOG_MS`], then put its prescaler and reload back and pet it. The
/// watchdog task shares the executor with this task, so nothing else touches it meanwhile.
fn with_erase_watchdog<T>(f: impl FnOnce() -> T) -> T {
    let iwdg = pac::IWDG;
    let Some((pr, rlr)) = flash_record::erase_watchdog() else {
        return f();
    };
    let (old_pr, old_rlr) = (iwdg.pr().read(), iwdg.rlr().read());
    // Pet, unlock PR/RLR, write, wait for the LSI domain to take them, pet again (loads RLR).
    iwdg.kr().write(|w| w.set_key(pac::iwdg::vals::Key::RESET));
    iwdg.kr().write(|w| w.set_key(pac::iwdg::vals::Key::ENABLE));
    iwdg.pr()
        .write(|w| w.set_pr(pac::iwdg::vals::Pr::from_bits(pr)));
    iwdg.rlr().write(|w| w.set_rl(rlr));
    wait_watchdog_update();
    iwdg.kr().write(|w| w.set_key(pac::iwdg::vals::Key::RESET));
    let out = f();
    iwdg.kr().write(|w| w.set_key(pac::iwdg::vals::Key::ENABLE));
    iwdg.pr().write_value(old_pr);
    iwdg.rlr().write_value(old_rlr);
    wait_watchdog_update();
    iwdg.kr().write(|w| w.set_key(pac::iwdg::vals::Key::RESET));
    out
}

/// Wait until the watchdog has taken new PR/RLR values (a few LSI cycles, ~200 µs), bounded.
fn wait_watchdog_update() {
    for _ in 0..200_000 {
        let sr = pac::IWDG.sr().read();
        if !sr.pvu() && !sr.rvu() {
            return;
        }
    }
}
