//! The QEMU storage backend on the Cortex-M4: a host file through semihosting behaves as NOR
//! flash, and `estimator_core::storage` saves and loads on it across a reopen. The power-cut
//! tests of the storage itself run on the host (`estimator-core`, `storage::tests`). Run with
//! `cargo test-target` (QEMU build only).
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
use belt_drive::hardware::qemu_storage::{FileFlash, CAPACITY};
#[cfg(target_os = "none")]
use core::ffi::CStr;

/// In cargo's scratch directory for integration tests (an absolute host path).
#[cfg(target_os = "none")]
const PATH: &str = concat!(env!("CARGO_TARGET_TMPDIR"), "/qemu-storage-test.bin\0");

#[cfg(target_os = "none")]
fn path() -> &'static CStr {
    let Ok(p) = CStr::from_bytes_with_nul(PATH.as_bytes()) else {
        defmt::panic!("bad path")
    };
    p
}

/// The staging file of the staging test.
#[cfg(target_os = "none")]
const STAGING: &str = concat!(env!("CARGO_TARGET_TMPDIR"), "/qemu-staging-test.bin\0");

/// A new, empty file (created by `open`).
#[cfg(target_os = "none")]
fn fresh() -> FileFlash {
    let _ = semihosting::sys::arm_compat::sys_remove(path());
    let Some(f) = FileFlash::open(path(), CAPACITY) else {
        defmt::panic!("cannot create {=str}", PATH)
    };
    f
}

#[cfg(target_os = "none")]
#[defmt_test::tests]
mod tests {
    use super::{fresh, path, STAGING};
    use belt_drive::hardware::qemu_storage::{FileFlash, FileFlashError, CAPACITY, SECTOR_BYTES};
    use embedded_storage::nor_flash::{NorFlash, ReadNorFlash};
    use estimator_core::storage::{self, Slot, SlotState};
    use semihosting::sys::arm_compat::sys_remove;

    /// What a panic, a HardFault or a stray interrupt leaves in `.uninit` RAM reads back once,
    /// by kind; the path keeps its last bytes.
    #[test]
    fn the_post_mortem_record_reads_back_once() {
        use belt_drive::postmortem::{self, Ended, FILE_BYTES};
        let long = "estimator-core/src/a/path/longer/than/the/record/keeps/drive.rs";
        postmortem::record_panic(long, 1234);
        let ended = postmortem::take();
        defmt::assert!(matches!(ended, Some(Ended::Panic { line: 1234, .. })));
        let ended = ended.unwrap();
        let file = ended.file();
        defmt::assert_eq!(file.len(), FILE_BYTES);
        defmt::assert!(long.as_bytes().ends_with(file));
        defmt::assert!(postmortem::take().is_none(), "read twice");

        postmortem::record_panic("lib.rs", 7);
        defmt::assert_eq!(postmortem::take().unwrap().file(), b"lib.rs");
        postmortem::record_hardfault(0x0800_1235);
        defmt::assert_eq!(
            postmortem::take(),
            Some(Ended::HardFault { pc: 0x0800_1235 })
        );
        postmortem::record_interrupt(-3);
        defmt::assert_eq!(
            postmortem::take(),
            Some(Ended::UnexpectedInterrupt { irqn: 0xFFFD })
        );
        defmt::assert!(postmortem::take().is_none());
    }

    #[test]
    fn a_new_file_reads_erased_and_programs_like_nor() {
        let mut f = fresh();
        defmt::assert_eq!(f.capacity(), CAPACITY);
        let mut b = [0u8; 8];
        f.read(CAPACITY as u32 - 8, &mut b).unwrap();
        defmt::assert_eq!(b, [0xFF; 8]);
        // Past the end of the (empty) file: extended with 0xFF, not 0x00.
        f.write(1000, &[0x0F, 0xF0]).unwrap();
        f.read(996, &mut b).unwrap();
        defmt::assert_eq!(b, [0xFF, 0xFF, 0xFF, 0xFF, 0x0F, 0xF0, 0xFF, 0xFF]);
        f.read(0, &mut b).unwrap();
        defmt::assert_eq!(b, [0xFF; 8]);
        // Programming only clears bits.
        f.write(1000, &[0xF3, 0x3F]).unwrap();
        f.read(1000, &mut b[..2]).unwrap();
        defmt::assert_eq!(b[..2], [0x03, 0x30]);
        // An erase sets the sector back to 0xFF and leaves the other alone.
        f.write(SECTOR_BYTES as u32, &[0x00]).unwrap();
        f.erase(0, SECTOR_BYTES as u32).unwrap();
        f.read(1000, &mut b[..2]).unwrap();
        defmt::assert_eq!(b[..2], [0xFF, 0xFF]);
        f.read(SECTOR_BYTES as u32, &mut b[..1]).unwrap();
        defmt::assert_eq!(b[0], 0x00);
        // Outside or misaligned: refused.
        defmt::assert_eq!(
            f.write(CAPACITY as u32, &[0]),
            Err(FileFlashError::OutOfBounds)
        );
        defmt::assert_eq!(f.erase(0, 100), Err(FileFlashError::NotAligned));
    }

    #[test]
    fn records_survive_a_reopen() {
        let mut f = fresh();
        let mut settings = [0u8; 256];
        let mut blob = [0u8; 5000];
        defmt::assert!(matches!(
            storage::load(&mut f, &mut settings, &mut blob),
            Ok(None)
        ));
        let mut written = [0u8; 5000];
        for (i, b) in written.iter_mut().enumerate() {
            *b = (i * 7 + 3) as u8;
        }
        let first = storage::save(&mut f, &written[..200], &written).unwrap();
        defmt::assert!(first.slot == Slot::A && first.seq == 1);
        let second = storage::save(&mut f, b"second", &written[..100]).unwrap();
        defmt::assert!(second.slot == Slot::B && second.seq == 2);
        drop(f);

        // Reopened: nothing truncated, both records there, the newest loads.
        let Some(mut f) = FileFlash::open(path(), CAPACITY) else {
            defmt::panic!("cannot reopen")
        };
        let states = storage::inspect(&mut f).unwrap();
        defmt::assert!(states == [SlotState::Valid(first), SlotState::Valid(second)]);
        let r = storage::load(&mut f, &mut settings, &mut blob)
            .unwrap()
            .unwrap();
        defmt::assert!(r == second);
        defmt::assert_eq!(&settings[..6], b"second");
        defmt::assert_eq!(blob[..100], written[..100]);

        // A third save replaces the older record (slot A) and keeps B.
        let third = storage::save(&mut f, b"third", &[]).unwrap();
        defmt::assert!(third.slot == Slot::A && third.seq == 3);
        let states = storage::inspect(&mut f).unwrap();
        defmt::assert!(states == [SlotState::Valid(third), SlotState::Valid(second)]);
        let _ = sys_remove(path());
    }

    /// The staging area on a QEMU file (sector 9's stand-in): a transferred image written as
    /// it arrives, read back, saved from there, and staged again from the record after a
    /// reboot found another image there.
    #[test]
    fn staging_on_a_file_saves_and_restages_a_calibration() {
        use core::ffi::CStr;
        use estimator_core::staging::{FlashStaging, Staged, Staging};
        let Ok(sp) = CStr::from_bytes_with_nul(STAGING.as_bytes()) else {
            defmt::panic!("bad path")
        };
        let _ = sys_remove(sp);
        let mut st = FlashStaging::new(FileFlash::open(sp, SECTOR_BYTES));
        defmt::assert!(st.is_present());
        let mut image = [0u8; 1500];
        for (i, b) in image.iter_mut().enumerate() {
            *b = (i * 13 + 5) as u8;
        }
        st.erase().unwrap();
        for (i, piece) in image.chunks(60).enumerate() {
            st.write(i * 60, piece).unwrap();
        }
        let mut f = fresh();
        let saved = storage::save_from(&mut f, b"settings", &mut Staged::new(&mut st, image.len()))
            .unwrap();
        // Another transfer overwrites the staging area; the record's image comes back.
        st.erase().unwrap();
        st.write(0, &[0u8; 64]).unwrap();
        let r = storage::load_settings(&mut f, &mut [0u8; 64])
            .unwrap()
            .unwrap();
        defmt::assert!(r == saved);
        defmt::assert!(storage::stage_blob(&mut f, &r, &mut st) == Ok(storage::Staged::Copied));
        defmt::assert!(storage::stage_blob(&mut f, &r, &mut st) == Ok(storage::Staged::Already));
        let mut back = [0u8; 1500];
        st.read(0, &mut back).unwrap();
        defmt::assert_eq!(back, image);
        let _ = sys_remove(sp);
        let _ = sys_remove(path());
    }
}
