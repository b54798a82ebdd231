//! The board's flash beyond the firmware: sectors 10 and 11 (0x080C_0000..0x0810_0000, two
//! 128 KiB sectors) are the configuration storage, the A and B slots of
//! `estimator_core::storage`; sector 9 (0x080A_0000) is the calibration staging area
//! (`estimator_core::staging`), where a transferred image is written as it arrives instead of
//! in RAM. `memory.x` ends the firmware image before sector 9.
//!
//! The F405 has one flash bank: while a sector erases or a byte programs, every instruction
//! fetch and vector fetch from flash waits, interrupts included. The HAL erases with 8-bit
//! parallelism: a 128 KiB sector takes 2 s typical, 4 s at most (DS8626, x8), far beyond the
//! watchdog's 7-19 ms. So a save runs with the motor off, inside [`with_long_watchdog`].

use embedded_storage::nor_flash::{
    check_erase, check_read, check_write, ErrorType, NorFlash, NorFlashError, NorFlashErrorKind,
    ReadNorFlash,
};
use stm32f4xx_hal::flash::{Error as HalError, FlashExt};
use stm32f4xx_hal::pac;

use super::{IWDG_KEY_FEED, IWDG_KEY_UNLOCK, IWDG_PRESCALER, IWDG_RELOAD};

/// Address of sector 10, slot A.
pub const START: u32 = 0x080C_0000;
/// Address of sector 9, the staging area.
pub const STAGING_START: u32 = 0x080A_0000;
/// One slot: a 128 KiB sector.
pub const SECTOR_BYTES: usize = 128 * 1024;
/// Sectors 10 and 11.
pub const CAPACITY: usize = 2 * SECTOR_BYTES;

/// Why a board flash operation failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum BoardFlashError {
    /// Outside the window (or the chip has less than 1 MiB of flash).
    OutOfBounds,
    /// An erase not on sector boundaries.
    NotAligned,
    /// FLASH_SR.PGSERR: programming sequence error.
    ProgrammingSequence,
    /// FLASH_SR.PGPERR: programming parallelism error.
    ProgrammingParallelism,
    /// FLASH_SR.PGAERR: programming alignment error.
    ProgrammingAlignment,
    /// FLASH_SR.WRPERR: the sector is write-protected (option bytes).
    WriteProtection,
    /// FLASH_SR.OPERR: operation error.
    Operation,
}

impl NorFlashError for BoardFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            BoardFlashError::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            BoardFlashError::NotAligned | BoardFlashError::ProgrammingAlignment => {
                NorFlashErrorKind::NotAligned
            }
            _ => NorFlashErrorKind::Other,
        }
    }
}

impl From<NorFlashErrorKind> for BoardFlashError {
    fn from(kind: NorFlashErrorKind) -> Self {
        match kind {
            NorFlashErrorKind::NotAligned => BoardFlashError::NotAligned,
            _ => BoardFlashError::OutOfBounds,
        }
    }
}

impl From<HalError> for BoardFlashError {
    fn from(e: HalError) -> Self {
        match e {
            HalError::ProgrammingSequence => BoardFlashError::ProgrammingSequence,
            HalError::ProgrammingParallelism => BoardFlashError::ProgrammingParallelism,
            HalError::ProgrammingAlignment => BoardFlashError::ProgrammingAlignment,
            HalError::WriteProtection => BoardFlashError::WriteProtection,
            HalError::Operation => BoardFlashError::Operation,
        }
    }
}

/// A window of whole 128 KiB sectors as one NOR flash (offsets from its start; anything
/// outside is refused): byte writes, 128 KiB erases, through stm32f4xx-hal's `UnlockedFlash`,
/// unlocked for each operation and locked again after it.
pub struct BoardFlash {
    flash: pac::FLASH,
    /// The window's offset from the start of flash (what the HAL's `NorFlash` takes).
    start_offset: u32,
    capacity: usize,
}

impl BoardFlash {
    /// Takes the flash interface (after the clocks have set its wait states) for the window of
    /// `capacity` bytes at address `start`.
    pub fn new(flash: pac::FLASH, start: u32, capacity: usize) -> Self {
        BoardFlash {
            flash,
            start_offset: start - 0x0800_0000,
            capacity,
        }
    }

    /// Gives the flash interface back.
    pub fn free(self) -> pac::FLASH {
        self.flash
    }

    /// Clears error flags left by an earlier operation: the HAL reads them after each
    /// operation but never clears them, so one error would fail every later operation.
    fn clear_errors(&mut self) {
        self.flash.sr().write(|w| {
            w.eop()
                .clear()
                .operr()
                .clear()
                .wrperr()
                .clear()
                .pgaerr()
                .clear()
                .pgperr()
                .clear()
                .pgserr()
                .clear()
        });
    }

    /// Drops what the ART data cache holds of the flash just changed, so that reading back
    /// (the storage verifies every save) sees the flash, not stale lines (as ST's HAL does after
    /// an erase). The cache may only be reset while disabled.
    fn flush_data_cache(&mut self) {
        let acr = self.flash.acr();
        if acr.read().dcen().bit_is_set() {
            acr.modify(|_, w| w.dcen().clear_bit());
            acr.modify(|_, w| w.dcrst().set_bit());
            acr.modify(|_, w| w.dcrst().clear_bit());
            acr.modify(|_, w| w.dcen().set_bit());
        }
    }
}

impl ErrorType for BoardFlash {
    type Error = BoardFlashError;
}

impl ReadNorFlash for BoardFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), BoardFlashError> {
        check_read(self, offset, bytes.len())?;
        let from = (self.start_offset + offset) as usize;
        let stored = FlashExt::read(&self.flash)
            .get(from..from + bytes.len())
            .ok_or(BoardFlashError::OutOfBounds)?;
        bytes.copy_from_slice(stored);
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.capacity
    }
}

impl NorFlash for BoardFlash {
    const WRITE_SIZE: usize = 1;
    const ERASE_SIZE: usize = SECTOR_BYTES;

    /// Erases whole sectors (1-2 s each, up to 4 s: the CPU stalls meanwhile).
    fn erase(&mut self, from: u32, to: u32) -> Result<(), BoardFlashError> {
        check_erase(self, from, to)?;
        // The HAL erases the sector holding `from` before it looks at `to`.
        if from == to {
            return Ok(());
        }
        self.clear_errors();
        let erased = NorFlash::erase(
            &mut self.flash.unlocked(),
            self.start_offset + from,
            self.start_offset + to,
        );
        self.flush_data_cache();
        Ok(erased?)
    }

    /// Programs bytes (about 16 us each; the CPU stalls meanwhile).
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), BoardFlashError> {
        check_write(self, offset, bytes.len())?;
        if bytes.is_empty() {
            return Ok(());
        }
        self.clear_errors();
        let written = NorFlash::write(
            &mut self.flash.unlocked(),
            self.start_offset + offset,
            bytes,
        );
        self.flush_data_cache();
        Ok(written?)
    }
}

/// The board's storage, always present. Takes the flash interface without the peripheral
/// singleton: `init` hands `cx.device` to `hardware::init`, which only borrows FLASH while the
/// clocks set its wait states and caches (before any task runs); after that this is FLASH's only
/// user. Call it once.
pub fn open_storage() -> Option<BoardFlash> {
    // SAFETY: see above; the clocks' one-time ACR set-up never overlaps a flash operation.
    Some(BoardFlash::new(
        unsafe { pac::FLASH::steal() },
        START,
        CAPACITY,
    ))
}

/// The calibration staging area, sector 9, always present: its erase runs with the watchdog
/// lengthened ([`LongErase`]). A second handle on FLASH: the link task owns both and uses
/// one at a time, so their operations never interleave.
pub fn open_staging() -> Option<LongErase<BoardFlash>> {
    // SAFETY: as `open_storage`; the link task is the only user of either handle.
    let flash = unsafe { pac::FLASH::steal() };
    Some(LongErase(BoardFlash::new(
        flash,
        STAGING_START,
        SECTOR_BYTES,
    )))
}

/// A flash whose erases and writes run inside [`with_long_watchdog`]: the CPU stalls for the
/// whole erase (the drive is disabled: a transfer is refused otherwise).
pub struct LongErase<F>(pub F);

impl<F: ErrorType> ErrorType for LongErase<F> {
    type Error = F::Error;
}

impl<F: ReadNorFlash> ReadNorFlash for LongErase<F> {
    const READ_SIZE: usize = F::READ_SIZE;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), F::Error> {
        self.0.read(offset, bytes)
    }

    fn capacity(&self) -> usize {
        self.0.capacity()
    }
}

impl<F: NorFlash> NorFlash for LongErase<F> {
    const WRITE_SIZE: usize = F::WRITE_SIZE;
    const ERASE_SIZE: usize = F::ERASE_SIZE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), F::Error> {
        with_long_watchdog(|| self.0.erase(from, to))
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), F::Error> {
        self.0.write(offset, bytes)
    }
}

/// The long timeout: LSI / 256 (PR = 6) and 4095 counts, 33 s at the nominal 32 kHz, 22-62 s
/// over the LSI's 17-47 kHz: room for erasing both sectors (8 s at most) and programming.
const IWDG_PRESCALER_LONG: u8 = 6;
const IWDG_RELOAD_LONG: u16 = 4095;
/// Polls of IWDG_SR: an update crosses into the LSI domain in up to 5 LSI cycles (~300 us at
/// 17 kHz); this bound is milliseconds.
const IWDG_UPDATE_POLLS: u32 = 100_000;

/// Runs `f` (a flash save) with the independent watchdog's timeout raised to 22-62 s, then
/// puts the normal 7-19 ms back; the watchdog is fed before and after. A board that hangs
/// inside `f` still resets, only later.
///
/// Usable before `ControlIo::start` too: the watchdog is then not running, its update flags
/// never clear (no LSI) and the bounded waits simply expire; `start` sets its own values.
pub fn with_long_watchdog<R>(f: impl FnOnce() -> R) -> R {
    set_watchdog(IWDG_PRESCALER_LONG, IWDG_RELOAD_LONG);
    let r = f();
    set_watchdog(IWDG_PRESCALER, IWDG_RELOAD);
    r
}

/// Feeds, waits for any update in flight (RM0090: PR and RLR may be written only while
/// SR.PVU / SR.RVU are clear), writes PR and RLR, waits until the new values are in force,
/// then feeds so the count restarts from the new reload value.
fn set_watchdog(prescaler: u8, reload: u16) {
    // SAFETY: `ControlIo` owns the IWDG but only ever writes the feed key; the unlock and the
    // two writes below run in a critical section, because a feed between them would protect
    // PR and RLR again and the writes would be lost.
    let iwdg = unsafe { &*pac::IWDG::ptr() };
    let feed = || {
        iwdg.kr().write(|w| unsafe { w.key().bits(IWDG_KEY_FEED) });
    };
    let settled = || {
        for _ in 0..IWDG_UPDATE_POLLS {
            let sr = iwdg.sr().read();
            if sr.pvu().bit_is_clear() && sr.rvu().bit_is_clear() {
                return;
            }
        }
    };
    feed();
    settled();
    cortex_m::interrupt::free(|_| {
        iwdg.kr()
            .write(|w| unsafe { w.key().bits(IWDG_KEY_UNLOCK) });
        iwdg.pr().write(|w| unsafe { w.pr().bits(prescaler) });
        iwdg.rlr().write(|w| unsafe { w.rl().bits(reload) });
    });
    settled();
    feed();
}
