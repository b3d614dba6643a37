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

use crate::flash_record::{self, RECORD_ALIGN, SECTOR_LEN};

/// Offsets of the two profile sectors from the start of flash.
pub const SECTOR_OFFSETS: [u32; 2] = [0x4000, 0x8000];
/// Their sector numbers (FLASH_CR.SNB).
const SECTOR_NUMBERS: [u8; 2] = [1, 2];
const FLASH_BASE: usize = 0x0800_0000;

const _: () = assert!(RECORD_ALIGN.is_multiple_of(WRITE_SIZE));
// The stretched watchdog outlasts the worst save (the datasheet's longest erase and programming).
const _: () = assert!(flash_record::worst_case_blocking_ms() < flash_record::ERASE_WATCHDOG_MS);
// Erases stay rare: a sector takes this many of the largest records.
const _: () = assert!(flash_record::RECORDS_PER_SECTOR >= 50);

/// Why the profile could not be stored (reported to the host as `RigError::ProfileNotSaved`).
pub use subsurf_protocol::SaveError as StoreError;

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

    /// The newest stored payload, copied into `out` (`None`: nothing valid stored).
    pub fn load<'b>(&self, out: &'b mut [u8]) -> Option<&'b [u8]> {
        flash_record::load(self, out)
    }
}

/// Profile sector `i` (0 or 1) through the memory map.
fn mapped_sector(i: usize) -> &'static [u8] {
    let offset = SECTOR_OFFSETS.get(i).copied().unwrap_or(SECTOR_OFFSETS[0]);
    // SAFETY: sectors 1 and 2 are always-mapped, always-readable flash on the STM32F446RE;
    // nothing else writes them (the linker keeps code out), and only `Store`'s erase and
    // program change them, which take the store mutably, so no slice is read across a write
    // (a stale one only ever reads bytes that were flash's).
    unsafe { core::slice::from_raw_parts((FLASH_BASE + offset as usize) as *const u8, SECTOR_LEN) }
}

/// The stored profile straight from the memory map, without the flash driver or a log line:
/// `main` reads it before the clocks are even set up (EN's polarity).
pub fn stored_profile_quiet() -> Option<subsurf_protocol::RigProfile> {
    let mut buf = [0u8; flash_record::MAX_PAYLOAD];
    let payload = flash_record::latest_payload([mapped_sector(0), mapped_sector(1)])?;
    let out = buf.get_mut(..payload.len())?;
    out.copy_from_slice(payload);
    flash_record::decode_profile(out)
}

impl flash_record::SectorFlash for Store {
    fn sector(&self, i: usize) -> &[u8] {
        mapped_sector(i)
    }

    fn erase(&mut self, i: usize) -> Result<(), StoreError> {
        let snb = SECTOR_NUMBERS.get(i).copied().ok_or(StoreError::Erase)?;
        defmt::info!("profile sector {} full or unreadable: erasing", i + 1);
        with_erase_watchdog(|| erase_sector_x32(snb))
    }

    fn program(&mut self, i: usize, at: usize, bytes: &[u8]) -> Result<(), StoreError> {
        let sector = SECTOR_OFFSETS.get(i).copied().ok_or(StoreError::Program)?;
        let offset = sector + u32::try_from(at).map_err(|_| StoreError::Program)?;
        // embassy-stm32's write turns the data cache off around programming and resets it
        // before turning it back on.
        self.flash
            .blocking_write(offset, bytes)
            .map_err(|_| StoreError::Program)
    }

    fn reset_data_cache(&mut self) {
        reset_data_cache();
    }
}

/// Reset the flash's data cache (RM0390 §3.4.2: DCRST only while DCEN is off) and turn it on
/// (`main` turned it on at boot; the erase turned it off).
fn reset_data_cache() {
    let f = pac::FLASH;
    f.acr().modify(|w| w.set_dcen(false));
    f.acr().modify(|w| w.set_dcrst(true));
    f.acr().modify(|w| w.set_dcrst(false));
    f.acr().modify(|w| w.set_dcen(true));
}

/// Erase sector `snb` at ×32 parallelism, interrupts masked, through the registers (RM0390
/// §3.5.2, "Sector Erase"; FLASH_CR.PSIZE = 0b10).
///
/// Not embassy-stm32's `blocking_erase`: version 0.6 sets only SER and SNB for an erase, and its
/// last programming write clears the whole control register, so its erases ran at PSIZE = ×8,
/// whose worst case for a 16 KiB sector is 800 ms, not the 500 ms of ×32 (STM32F446xC/E
/// datasheet, "Flash memory programming", t_ERASE16KB: ×8 typ 400 / max 800 ms, ×16 300 / 600,
/// ×32 250 / 500). ×32 needs VDD of 2.7–3.6 V, which the Nucleo's 3.3 V regulator gives and the
/// 168 MHz clock needs anyway (brown-out: `subsurf flash` checks BOR). Masking interrupts costs
/// nothing here: the CPU fetches from the bank being erased and stalls until the erase ends, every
/// handler with it (all of them run from flash).
fn erase_sector_x32(snb: u8) -> Result<(), StoreError> {
    use pac::flash::vals::Psize;
    let f = pac::FLASH;
    let sr = cortex_m::interrupt::free(|_| {
        // The data cache off while the sector changes under it (`reset_data_cache` afterwards,
        // through the caller, drops what it held and turns it back on).
        f.acr().modify(|w| w.set_dcen(false));
        if f.cr().read().lock() {
            f.keyr().write_value(0x4567_0123);
            f.keyr().write_value(0xCDEF_89AB);
        }
        // Clear the sticky error flags (write 1 to clear) left by an earlier operation.
        f.sr().modify(|_| {});
        f.cr().write(|w| {
            w.set_psize(Psize::PSIZE32);
            w.set_ser(true);
            w.set_snb(snb);
        });
        f.cr().modify(|w| w.set_strt(true));
        while f.sr().read().bsy() {}
        let sr = f.sr().read();
        f.cr().write(|w| w.set_lock(true));
        sr
    });
    if sr.pgserr() || sr.pgperr() || sr.pgaerr() || sr.wrperr() || sr.operr() {
        Err(StoreError::Erase)
    } else {
        Ok(())
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
