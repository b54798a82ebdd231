//! Where a calibration image waits between its transfer and its installation, and how it is
//! read from there: the drive keeps no RAM copy of it (3.4 KiB of static RAM), it writes the
//! image to a flash sector as the chunks arrive and reads it back in small windows to check,
//! install, read back over the link and save it.
//!
//! - [`Source`]: bytes read by offset (a slice, a flash region, the staged image).
//! - [`Stream`]: the little-endian fields of a [`Source`], front to back ([`Fields`]), through a
//!   64-byte window on the stack.
//! - [`Staging`]: the area a transfer writes (erase, write in order, read); [`FlashStaging`] on
//!   any byte-writable NOR flash (the board's sector 9, QEMU's `--staging` file), a
//!   [`BlobBuffer`] on hosts and in tests.
//!
//! Nothing here panics: a read outside the bytes or a flash failure is an error.

use belt_link::bytes::{Fields, Short};
use embedded_storage::nor_flash::NorFlash;

use crate::image;

/// Bytes read by offset.
pub trait Source {
    /// How many bytes there are.
    fn len(&self) -> usize;
    /// Copies `buf.len()` bytes from `offset`.
    fn read_at(&mut self, offset: usize, buf: &mut [u8]) -> Result<(), StagingError>;
    /// True when there are no bytes.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Source for &[u8] {
    fn len(&self) -> usize {
        <[u8]>::len(self)
    }

    fn read_at(&mut self, offset: usize, buf: &mut [u8]) -> Result<(), StagingError> {
        let end = offset
            .checked_add(buf.len())
            .ok_or(StagingError::OutOfBounds)?;
        let bytes = self.get(offset..end).ok_or(StagingError::OutOfBounds)?;
        buf.copy_from_slice(bytes);
        Ok(())
    }
}

/// Why the staging area failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StagingError {
    /// This build has no staging area (QEMU started without `--staging`).
    Missing,
    /// Outside the area.
    OutOfBounds,
    /// The flash refused an erase, a write or a read.
    Flash,
}

impl StagingError {
    /// A short name for logs.
    pub fn name(self) -> &'static str {
        match self {
            StagingError::Missing => "no staging area on this build",
            StagingError::OutOfBounds => "outside the staging area",
            StagingError::Flash => "staging flash failed",
        }
    }
}

impl core::fmt::Display for StagingError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// Window of a [`Stream`]: one flash read per 64 bytes.
const WINDOW: usize = 64;

/// Little-endian fields of a [`Source`], front to back. A read past the end is [`Short`]; a
/// failed read of the source is [`Short`] too and sets [`Stream::failed`].
pub struct Stream<'s> {
    src: &'s mut dyn Source,
    /// Offset of the next field.
    at: usize,
    /// The window holds the source's bytes `win_at..win_at + win_len`.
    win: [u8; WINDOW],
    win_at: usize,
    win_len: usize,
    failed: bool,
}

impl<'s> Stream<'s> {
    /// A stream at `at` in `src`.
    pub fn new(src: &'s mut dyn Source, at: usize) -> Self {
        Stream {
            src,
            at,
            win: [0; WINDOW],
            win_at: 0,
            win_len: 0,
            failed: false,
        }
    }

    /// The source could not be read (as opposed to ending early).
    pub fn failed(&self) -> bool {
        self.failed
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.src.len().saturating_sub(self.at)
    }

    /// Skips `n` bytes.
    pub fn skip(&mut self, n: usize) -> Result<(), Short> {
        if n > self.remaining() {
            return Err(Short);
        }
        self.at += n;
        Ok(())
    }
}

impl Fields for Stream<'_> {
    /// Fills `out` (at most [`WINDOW`] bytes) with the next bytes: one body for every field
    /// size (the image reader calls it a few hundred times; flash, not speed, is what counts).
    #[inline(never)]
    fn fill(&mut self, out: &mut [u8]) -> Result<(), Short> {
        let n = out.len();
        if n > WINDOW || n > self.remaining() {
            return Err(Short);
        }
        let inside = self.at >= self.win_at && self.at + n <= self.win_at + self.win_len;
        if !inside {
            let len = self.remaining().min(WINDOW);
            if self.src.read_at(self.at, &mut self.win[..len]).is_err() {
                self.failed = true;
                self.win_len = 0;
                return Err(Short);
            }
            self.win_at = self.at;
            self.win_len = len;
        }
        let from = self.at - self.win_at;
        let Some(bytes) = self.win.get(from..from + n) else {
            return Err(Short);
        };
        out.copy_from_slice(bytes);
        self.at += n;
        Ok(())
    }
}

/// CRC-32 of `src[from..]`, read in 64-byte pieces.
pub fn crc32_from(
    src: &mut dyn Source,
    from: usize,
    crc: &mut belt_link::Crc32,
) -> Result<(), StagingError> {
    let mut buf = [0u8; WINDOW];
    let mut at = from;
    while at < src.len() {
        let n = (src.len() - at).min(WINDOW);
        src.read_at(at, &mut buf[..n])?;
        crc.update(&buf[..n]);
        at += n;
    }
    Ok(())
}

/// Every byte of `src` (hosts and tests).
#[cfg(feature = "std")]
pub fn read_all(src: &mut dyn Source) -> Result<Vec<u8>, StagingError> {
    let mut out = vec![0u8; src.len()];
    src.read_at(0, &mut out)?;
    Ok(out)
}

/// The area a calibration transfer writes: erased once, written in order, read any number of
/// times. Holds at least [`image::MAX_BYTES`].
pub trait Staging {
    /// Makes the area ready for a new image (on flash: erases it, stalling a single-bank MCU
    /// for up to 2 s; the drive refuses a transfer while enabled).
    fn erase(&mut self) -> Result<(), StagingError>;
    /// Writes `data` at `offset` (each byte at most once after an erase).
    fn write(&mut self, offset: usize, data: &[u8]) -> Result<(), StagingError>;
    /// Reads `buf.len()` bytes from `offset`.
    fn read(&mut self, offset: usize, buf: &mut [u8]) -> Result<(), StagingError>;
}

/// A RAM buffer of the largest image: the staging area of hosts and tests.
pub type BlobBuffer = [u8; image::MAX_BYTES];

impl Staging for BlobBuffer {
    fn erase(&mut self) -> Result<(), StagingError> {
        self.fill(0xFF);
        Ok(())
    }

    fn write(&mut self, offset: usize, data: &[u8]) -> Result<(), StagingError> {
        let end = offset
            .checked_add(data.len())
            .ok_or(StagingError::OutOfBounds)?;
        self.get_mut(offset..end)
            .ok_or(StagingError::OutOfBounds)?
            .copy_from_slice(data);
        Ok(())
    }

    fn read(&mut self, offset: usize, buf: &mut [u8]) -> Result<(), StagingError> {
        (&self[..]).read_at(offset, buf)
    }
}

/// A staging area on NOR flash written and read by the byte (`WRITE_SIZE` and `READ_SIZE` 1,
/// as the STM32F4's and QEMU's file flash): the image at offset 0, the erase covering
/// [`image::MAX_BYTES`]. `None` (no flash, or one too small or not byte-writable) refuses
/// every operation with [`StagingError::Missing`].
pub struct FlashStaging<F>(Option<F>);

impl<F: NorFlash> FlashStaging<F> {
    /// Staging on `flash`, if it is one this can use.
    pub fn new(flash: Option<F>) -> Self {
        let usable = F::WRITE_SIZE == 1
            && F::READ_SIZE == 1
            && flash
                .as_ref()
                .is_some_and(|f| f.capacity() >= image::MAX_BYTES);
        FlashStaging(flash.filter(|_| usable))
    }

    /// True when there is a usable flash.
    pub fn is_present(&self) -> bool {
        self.0.is_some()
    }

    fn flash(&mut self) -> Result<&mut F, StagingError> {
        self.0.as_mut().ok_or(StagingError::Missing)
    }
}

/// Offsets within a staging area that fits in `u32` (an image is at most [`image::MAX_BYTES`]).
fn offset_u32(offset: usize, len: usize) -> Result<u32, StagingError> {
    match offset.checked_add(len) {
        Some(end) if end <= image::MAX_BYTES => Ok(offset as u32),
        _ => Err(StagingError::OutOfBounds),
    }
}

impl<F: NorFlash> Staging for FlashStaging<F> {
    fn erase(&mut self) -> Result<(), StagingError> {
        let flash = self.flash()?;
        let unit = F::ERASE_SIZE.max(1);
        let to = image::MAX_BYTES.div_ceil(unit) * unit;
        let to = u32::try_from(to).map_err(|_| StagingError::OutOfBounds)?;
        flash.erase(0, to).map_err(|_| StagingError::Flash)
    }

    fn write(&mut self, offset: usize, data: &[u8]) -> Result<(), StagingError> {
        let at = offset_u32(offset, data.len())?;
        self.flash()?
            .write(at, data)
            .map_err(|_| StagingError::Flash)
    }

    fn read(&mut self, offset: usize, buf: &mut [u8]) -> Result<(), StagingError> {
        let at = offset_u32(offset, buf.len())?;
        self.flash()?.read(at, buf).map_err(|_| StagingError::Flash)
    }
}

/// The first `len` bytes of a staging area, as a [`Source`].
pub struct Staged<'a, S: ?Sized> {
    staging: &'a mut S,
    len: usize,
}

impl<'a, S: Staging + ?Sized> Staged<'a, S> {
    /// The first `len` bytes of `staging` (at most [`image::MAX_BYTES`]).
    pub fn new(staging: &'a mut S, len: usize) -> Self {
        Staged {
            staging,
            len: len.min(image::MAX_BYTES),
        }
    }
}

impl<S: Staging + ?Sized> Source for Staged<'_, S> {
    fn len(&self) -> usize {
        self.len
    }

    fn read_at(&mut self, offset: usize, buf: &mut [u8]) -> Result<(), StagingError> {
        match offset.checked_add(buf.len()) {
            Some(end) if end <= self.len => self.staging.read(offset, buf),
            _ => Err(StagingError::OutOfBounds),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stream_reads_across_windows_and_stops_at_the_end() {
        let bytes: [u8; 150] = core::array::from_fn(|i| i as u8);
        let mut src: &[u8] = &bytes;
        let mut s = Stream::new(&mut src, 2);
        // 62 bytes to the first window's end, then a field across it.
        s.skip(60).unwrap();
        assert_eq!(s.u32().unwrap(), u32::from_le_bytes([62, 63, 64, 65]));
        assert_eq!(s.remaining(), 150 - 66);
        s.skip(150 - 66 - 2).unwrap();
        assert_eq!(s.u16().unwrap(), u16::from_le_bytes([148, 149]));
        assert_eq!(s.u16(), Err(Short));
        assert!(!s.failed());
    }

    struct Broken;
    impl Source for Broken {
        fn len(&self) -> usize {
            100
        }
        fn read_at(&mut self, _: usize, _: &mut [u8]) -> Result<(), StagingError> {
            Err(StagingError::Flash)
        }
    }

    #[test]
    fn a_failed_read_is_short_and_flagged() {
        let mut src = Broken;
        let mut s = Stream::new(&mut src, 0);
        assert_eq!(s.u32(), Err(Short));
        assert!(s.failed());
    }

    #[test]
    fn staged_bytes_stay_within_their_length() {
        let mut buf: BlobBuffer = [0; image::MAX_BYTES];
        buf.erase().unwrap();
        buf.write(10, &[1, 2, 3]).unwrap();
        assert_eq!(
            buf.write(image::MAX_BYTES - 1, &[1, 2]),
            Err(StagingError::OutOfBounds)
        );
        let mut staged = Staged::new(&mut buf, 12);
        let mut two = [0u8; 2];
        staged.read_at(10, &mut two).unwrap();
        assert_eq!(two, [1, 2]);
        assert_eq!(staged.read_at(11, &mut two), Err(StagingError::OutOfBounds));
    }
}
