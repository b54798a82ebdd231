//! The configuration storage and the calibration staging area under QEMU: host files standing
//! in for flash sectors 10-11 and sector 9, read and written through semihosting (QEMU does not
//! model the flash controller).
//!
//! `--storage PATH` and `--staging PATH` on QEMU's semihosting command line name the files. [`FileFlash`] behaves as
//! the board's NOR flash, so `estimator_core::storage` runs on it unchanged: two 128 KiB erase
//! units (256 KiB), an erase writes 0xFF, a write ANDs with what is there (read-modify-write:
//! bits only clear, as in flash). A file shorter than 256 KiB (new or empty) reads as 0xFF past
//! its end and is extended with 0xFF when something is written there; an existing file is never
//! truncated.

use core::ffi::CStr;
use core::mem::MaybeUninit;

use embedded_storage::nor_flash::{
    check_erase, check_read, check_write, ErrorType, NorFlash, NorFlashError, NorFlashErrorKind,
    ReadNorFlash,
};
use semihosting::fd::{AsFd, OwnedFd};
use semihosting::io::ErrorKind;
use semihosting::sys::arm_compat::{
    sys_flen, sys_get_cmdline_uninit, sys_open, sys_seek, OpenMode,
};

/// One slot: a 128 KiB sector, as on the board.
pub const SECTOR_BYTES: usize = 128 * 1024;
/// Two slots.
pub const CAPACITY: usize = 2 * SECTOR_BYTES;
/// Bytes moved per semihosting call in erases and read-modify-writes (on the stack).
const CHUNK: usize = 256;

/// Why a file-flash operation failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum FileFlashError {
    /// Outside the 256 KiB.
    OutOfBounds,
    /// Not aligned (never, with byte reads and writes and whole-sector erases).
    NotAligned,
    /// A semihosting call failed (the host file).
    Io,
}

impl NorFlashError for FileFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            FileFlashError::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            FileFlashError::NotAligned => NorFlashErrorKind::NotAligned,
            FileFlashError::Io => NorFlashErrorKind::Other,
        }
    }
}

impl From<NorFlashErrorKind> for FileFlashError {
    fn from(kind: NorFlashErrorKind) -> Self {
        match kind {
            NorFlashErrorKind::NotAligned => FileFlashError::NotAligned,
            _ => FileFlashError::OutOfBounds,
        }
    }
}

/// 256 KiB of NOR flash in a host file.
pub struct FileFlash {
    fd: OwnedFd,
    /// The file's length: bytes at and past it read as 0xFF.
    len: usize,
    /// The flash it stands for: bytes.
    capacity: usize,
}

impl FileFlash {
    /// Opens `path` read-write, creating it (empty: all 0xFF) if it does not exist. QEMU's
    /// semihosting open modes: "r+b" (O_RDWR) keeps an existing file; "w+b" creates but also
    /// truncates, so it is used only when the file is not there; "a+b" would force every write
    /// to the end.
    pub fn open(path: &CStr, capacity: usize) -> Option<FileFlash> {
        let fd = match sys_open(path, OpenMode::RDWR_BINARY) {
            Ok(fd) => fd,
            Err(e) if e.kind() == ErrorKind::NotFound => {
                sys_open(path, OpenMode::RDWR_TRUNC_BINARY).ok()?
            }
            Err(_) => return None,
        };
        let len = sys_flen(fd.as_fd()).ok()?;
        Some(FileFlash { fd, len, capacity })
    }

    /// Moves the file position to `at`, at most the file's length.
    fn seek(&mut self, at: usize) -> Result<(), FileFlashError> {
        debug_assert!(at <= self.len);
        // SAFETY: `at` is within the file's extent (seeking past it is what the semihosting
        // specification leaves undefined).
        unsafe { sys_seek(self.fd.as_fd(), at.min(self.len)) }.map_err(|_| FileFlashError::Io)
    }

    /// Fills `buf` from `at`: the file's bytes, 0xFF past its end.
    fn read_at(&mut self, at: usize, buf: &mut [u8]) -> Result<(), FileFlashError> {
        let in_file = self.len.saturating_sub(at).min(buf.len());
        let (head, tail) = buf.split_at_mut(in_file);
        tail.fill(0xFF);
        if head.is_empty() {
            return Ok(());
        }
        self.seek(at)?;
        let mut done = 0;
        while done < head.len() {
            match semihosting::sys::read(self.fd.as_fd(), &mut head[done..]) {
                Ok(0) => break,
                Ok(n) => done += n.min(head.len() - done),
                Err(_) => return Err(FileFlashError::Io),
            }
        }
        // The file shrank under us: what is missing reads as erased.
        if let Some(missing) = head.get_mut(done..) {
            missing.fill(0xFF);
        }
        Ok(())
    }

    /// Writes `data` at `at`, first extending the file with 0xFF up to `at` (a host file
    /// extended by a seek past its end would read 0x00 there, not erased flash).
    fn write_at(&mut self, at: usize, data: &[u8]) -> Result<(), FileFlashError> {
        while self.len < at {
            let n = (at - self.len).min(CHUNK);
            let len = self.len;
            self.write_all(len, &[0xFF; CHUNK][..n])?;
        }
        self.write_all(at, data)
    }

    fn write_all(&mut self, at: usize, data: &[u8]) -> Result<(), FileFlashError> {
        self.seek(at)?;
        let mut done = 0;
        while done < data.len() {
            match semihosting::sys::write(self.fd.as_fd(), &data[done..]) {
                Ok(n) if n > 0 => done += n.min(data.len() - done),
                _ => return Err(FileFlashError::Io),
            }
        }
        self.len = self.len.max(at + data.len());
        Ok(())
    }
}

impl ErrorType for FileFlash {
    type Error = FileFlashError;
}

impl ReadNorFlash for FileFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), FileFlashError> {
        check_read(self, offset, bytes.len())?;
        self.read_at(offset as usize, bytes)
    }

    fn capacity(&self) -> usize {
        self.capacity
    }
}

impl NorFlash for FileFlash {
    const WRITE_SIZE: usize = 1;
    const ERASE_SIZE: usize = SECTOR_BYTES;

    /// 0xFF over the range; the part past the file's end already reads so.
    fn erase(&mut self, from: u32, to: u32) -> Result<(), FileFlashError> {
        check_erase(self, from, to)?;
        let end = (to as usize).min(self.len);
        let mut at = from as usize;
        while at < end {
            let n = (end - at).min(CHUNK);
            self.write_all(at, &[0xFF; CHUNK][..n])?;
            at += n;
        }
        Ok(())
    }

    /// Programs as flash does: each stored byte becomes `old & new`.
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), FileFlashError> {
        check_write(self, offset, bytes.len())?;
        let mut buf = [0u8; CHUNK];
        for (i, new) in bytes.chunks(CHUNK).enumerate() {
            let at = offset as usize + i * CHUNK;
            let old = &mut buf[..new.len()];
            self.read_at(at, old)?;
            for (o, n) in old.iter_mut().zip(new) {
                *o &= n;
            }
            self.write_at(at, old)?;
        }
        Ok(())
    }
}

/// Runs `f` (a save): nothing to arrange under QEMU, which models no watchdog and no flash
/// stall.
pub fn during_save<R>(f: impl FnOnce() -> R) -> R {
    f()
}

/// The storage file named by `--storage PATH` on QEMU's semihosting command line, opened (and
/// created if missing). `None` without `--storage`; also `None`, with an error logged, when the
/// path is missing, too long or cannot be opened.
pub fn open_storage() -> Option<FileFlash> {
    open_named(b"--storage", CAPACITY, "no persistent storage")
}

/// The calibration staging file named by `--staging PATH` (one 128 KiB sector, as sector 9 on
/// the board). `None` without it: calibration transfers are then refused by name.
pub fn open_staging() -> Option<FileFlash> {
    open_named(b"--staging", SECTOR_BYTES, "no calibration staging")
}

/// The file after `flag` on the semihosting command line, as a flash of `capacity` bytes.
fn open_named(flag: &[u8], capacity: usize, without: &str) -> Option<FileFlash> {
    // The whole command line (`belt-drive --pipe IN OUT --storage PATH --staging PATH`): QEMU
    // refuses to return a line longer than the buffer.
    let mut line = [MaybeUninit::<u8>::uninit(); 768];
    let line = sys_get_cmdline_uninit(&mut line).ok()?;
    let mut words = line.split(|&b| b == b' ').filter(|w| !w.is_empty());
    words.find(|w| *w == flag)?;
    let opened = words.next().and_then(|path| {
        let mut z = [0u8; 256];
        z.get_mut(..path.len())?.copy_from_slice(path);
        CStr::from_bytes_until_nul(&z)
            .ok()
            .and_then(|p| FileFlash::open(p, capacity))
    });
    if opened.is_none() {
        defmt::error!(
            "{=[u8]:a}: no path, a path of 256 bytes or more, or a file that cannot be opened or created: {=str}",
            flag,
            without
        );
    }
    opened
}
