//! The drive's persistent record (configuration and calibration) on the board's storage: the
//! STM32F405's sectors 10-11 on the board, a host file through semihosting under QEMU (which
//! does not model the flash controller). The record format, the A/B slots and the power-cut
//! safety are `estimator_core::storage`'s, tested on the host.

use estimator_core::staging::{Source, Staging};
use estimator_core::storage::{self, RecordInfo, StorageError};

use crate::hardware::{self, StorageFlash};

/// `detail` codes of a failed save beyond the storage's own ([`StorageError::code`], 1-7) and the
/// endpoint's (0x40..).
pub mod detail {
    /// The settings record did not encode (cannot happen: the buffer is sized for it).
    pub const ENCODE: u8 = 0x30;
}

/// A short name for a save failure's detail code, for the log. Not inlined: one copy of the
/// table (flash).
#[inline(never)]
pub fn detail_name(code: u8) -> defmt::Str {
    use estimator_core::endpoint::storage_detail as e;
    match code {
        1 => defmt::intern!("flash error"),
        2 => defmt::intern!("flash geometry not supported"),
        3 => defmt::intern!("record larger than a slot"),
        4 | 5 => defmt::intern!("buffer too small"),
        6 => defmt::intern!("the record read back differs"),
        7 => defmt::intern!("the record changed while read"),
        8 => defmt::intern!("the calibration staging area failed"),
        detail::ENCODE => defmt::intern!("settings did not encode"),
        e::NO_STORAGE => {
            defmt::intern!("no storage on this build (QEMU: start with --storage FILE)")
        }
        e::CALIBRATION_BYTES_GONE => {
            defmt::intern!(
                "the calibration's bytes were overwritten by a later transfer: upload it again"
            )
        }
        e::ENABLED => defmt::intern!("the drive is enabled: disable it first"),
        _ => defmt::intern!("unknown"),
    }
}

/// What the boot found in storage.
#[derive(Clone, Copy, Debug)]
pub enum Boot {
    /// This build has no storage (QEMU without `--storage`).
    NoStorage,
    /// Neither slot holds a valid record.
    Nothing,
    /// The storage could not be read, or its newest record does not fit the buffers.
    Failed(u8),
    /// The newest valid record (its settings copied; its blob left in place until
    /// [`Persist::stage_blob`]).
    Loaded(RecordInfo),
}

/// Logs what the boot found.
pub fn log_boot(b: &Boot) {
    match *b {
        Boot::NoStorage => defmt::warn!("storage: none on this build"),
        Boot::Nothing => defmt::warn!("storage: no valid record"),
        Boot::Failed(code) => defmt::error!("storage: unreadable: {=istr}", detail_name(code)),
        Boot::Loaded(r) => defmt::info!(
            "storage: record {=u32} in slot {=str}, crc {=u32:#010x}, {=usize} B settings, {=usize} B calibration",
            r.seq,
            r.slot.name(),
            r.crc32,
            r.settings_len,
            r.blob_len
        ),
    }
}

/// The board's storage, if it has one.
pub struct Persist {
    flash: Option<StorageFlash>,
}

impl Persist {
    /// Opens the storage (board: always; QEMU: when `--storage FILE` is given).
    pub fn open() -> Persist {
        Persist {
            flash: hardware::open_storage(),
        }
    }

    /// Loads the newest valid record's settings into `settings_buf`.
    pub fn load(&mut self, settings_buf: &mut [u8]) -> Boot {
        let Some(flash) = &mut self.flash else {
            return Boot::NoStorage;
        };
        match storage::load_settings(flash, settings_buf) {
            Ok(Some(r)) => Boot::Loaded(r),
            Ok(None) => Boot::Nothing,
            Err(e) => Boot::Failed(e.code()),
        }
    }

    /// Puts record `r`'s calibration into `staging` (erasing it only when it holds other
    /// bytes, with the watchdog lengthened); the storage detail code on failure.
    pub fn stage_blob(
        &mut self,
        r: &RecordInfo,
        staging: &mut impl Staging,
    ) -> Result<storage::Staged, u8> {
        let Some(flash) = &mut self.flash else {
            return Err(estimator_core::endpoint::storage_detail::NO_STORAGE);
        };
        storage::stage_blob(flash, r, staging).map_err(|e| e.code())
    }

    /// Saves a new record (the drive is disabled: the erase stalls the CPU for up to 2 s on the
    /// board, with the watchdog lengthened meanwhile). Returns its sequence number and CRC, or
    /// the detail code of the failure.
    pub fn save(&mut self, settings: &[u8], blob: &mut dyn Source) -> Result<(u32, u32), u8> {
        let Some(flash) = &mut self.flash else {
            return Err(estimator_core::endpoint::storage_detail::NO_STORAGE);
        };
        let r = hardware::during_save(|| storage::save_from(flash, settings, blob))
            .map_err(|e: StorageError<_>| e.code())?;
        Ok((r.seq, r.crc32))
    }
}
