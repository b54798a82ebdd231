//! Little-endian fields front to back: the one reader and writer of the link's payloads and the
//! calibration blob. Nothing here panics; a read past the end is [`Short`], a write past the end
//! is remembered and reported by [`Writer::finish`].

/// Not enough bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Short;

/// Reads fields from a byte slice.
#[derive(Clone, Debug)]
pub struct Reader<'a> {
    buf: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `buf`.
    pub const fn new(buf: &'a [u8]) -> Self {
        Reader { buf, at: 0 }
    }
    /// The next `n` bytes.
    pub fn slice(&mut self, n: usize) -> Result<&'a [u8], Short> {
        let end = self.at.checked_add(n).ok_or(Short)?;
        let s = self.buf.get(self.at..end).ok_or(Short)?;
        self.at = end;
        Ok(s)
    }
    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.buf.len().saturating_sub(self.at)
    }
}

impl Fields for Reader<'_> {
    fn fill(&mut self, out: &mut [u8]) -> Result<(), Short> {
        out.copy_from_slice(self.slice(out.len())?);
        Ok(())
    }
}

/// Little-endian fields read front to back from anything that can fill a buffer with its next
/// bytes: a [`Reader`] over a slice, or a windowed reader over flash.
pub trait Fields {
    /// Fills `out` with the next `out.len()` bytes, or fails with [`Short`].
    fn fill(&mut self, out: &mut [u8]) -> Result<(), Short>;
    /// The next `N` bytes as an array.
    fn take<const N: usize>(&mut self) -> Result<[u8; N], Short> {
        let mut a = [0u8; N];
        self.fill(&mut a)?;
        Ok(a)
    }
    /// An unsigned byte.
    fn u8(&mut self) -> Result<u8, Short> {
        Ok(self.take::<1>()?[0])
    }
    /// A little-endian `u16`.
    fn u16(&mut self) -> Result<u16, Short> {
        Ok(u16::from_le_bytes(self.take()?))
    }
    /// A little-endian `u32`.
    fn u32(&mut self) -> Result<u32, Short> {
        Ok(u32::from_le_bytes(self.take()?))
    }
    /// A little-endian `i32`.
    fn i32(&mut self) -> Result<i32, Short> {
        Ok(i32::from_le_bytes(self.take()?))
    }
    /// A little-endian `u64`.
    fn u64(&mut self) -> Result<u64, Short> {
        Ok(u64::from_le_bytes(self.take()?))
    }
}

/// Writes fields into a byte slice.
#[derive(Debug)]
pub struct Writer<'a> {
    buf: &'a mut [u8],
    at: usize,
    short: bool,
}

impl<'a> Writer<'a> {
    /// A writer at the start of `buf`.
    pub fn new(buf: &'a mut [u8]) -> Self {
        Writer {
            buf,
            at: 0,
            short: false,
        }
    }
    /// A writer at `at` in `buf` (after a header written later).
    pub fn at(buf: &'a mut [u8], at: usize) -> Self {
        Writer {
            buf,
            at,
            short: false,
        }
    }
    /// Appends `bytes`, or remembers that they did not fit.
    pub fn put(&mut self, bytes: &[u8]) {
        match self
            .at
            .checked_add(bytes.len())
            .and_then(|end| self.buf.get_mut(self.at..end))
        {
            Some(dst) => {
                dst.copy_from_slice(bytes);
                self.at += bytes.len();
            }
            None => self.short = true,
        }
    }
    /// An unsigned byte.
    pub fn u8(&mut self, v: u8) {
        self.put(&[v]);
    }
    /// A little-endian `u16`.
    pub fn u16(&mut self, v: u16) {
        self.put(&v.to_le_bytes());
    }
    /// A little-endian `u32`.
    pub fn u32(&mut self, v: u32) {
        self.put(&v.to_le_bytes());
    }
    /// A little-endian `i32`.
    pub fn i32(&mut self, v: i32) {
        self.put(&v.to_le_bytes());
    }
    /// A little-endian `u64`.
    pub fn u64(&mut self, v: u64) {
        self.put(&v.to_le_bytes());
    }
    /// Bytes written so far (from the start of the buffer).
    pub fn len(&self) -> usize {
        self.at
    }
    /// True when nothing was written.
    pub fn is_empty(&self) -> bool {
        self.at == 0
    }
    /// The length written, or [`Short`] if anything did not fit.
    pub fn finish(self) -> Result<usize, Short> {
        if self.short {
            Err(Short)
        } else {
            Ok(self.at)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_and_writes_round_trip_and_stop_at_the_end() {
        let mut buf = [0u8; 11];
        let mut w = Writer::new(&mut buf);
        w.u8(7);
        w.u16(0xBEEF);
        w.u32(0xDEAD_BEEF);
        w.i32(-5);
        assert_eq!(w.finish(), Ok(11));
        let mut r = Reader::new(&buf);
        assert_eq!(
            (r.u8(), r.u16(), r.u32(), r.i32()),
            (Ok(7), Ok(0xBEEF), Ok(0xDEAD_BEEF), Ok(-5))
        );
        assert_eq!(r.u8(), Err(Short));
        assert_eq!(r.remaining(), 0);

        let mut small = [0u8; 3];
        let mut w = Writer::new(&mut small);
        w.u16(1);
        w.u16(2);
        assert_eq!(
            w.len(),
            2,
            "a field that does not fit is not written in part"
        );
        assert_eq!(w.finish(), Err(Short));
        let mut r = Reader::new(&[1, 2, 3]);
        assert_eq!(r.slice(usize::MAX), Err(Short));
        assert_eq!(r.slice(3), Ok(&[1u8, 2, 3][..]));
    }
}
