//! CRC-32/ISO-HDLC (the zlib / Ethernet CRC): the link's frame check and the calibration blob's.

/// CRC-32/ISO-HDLC, nibble-table form: 64 bytes of table, two lookups per byte.
const CRC_NIBBLES: [u32; 16] = {
    let mut t = [0u32; 16];
    let mut i = 0;
    while i < 16 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 4 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
};

/// A running CRC-32/ISO-HDLC (the zlib CRC), for data that arrives in pieces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crc32(u32);

impl Default for Crc32 {
    fn default() -> Self {
        Self::new()
    }
}

impl Crc32 {
    /// A fresh CRC.
    pub const fn new() -> Self {
        Crc32(0xFFFF_FFFF)
    }
    /// Feeds `data`.
    // Not inlined: one copy instead of one per caller (~400 B of the drive's flash).
    #[inline(never)]
    pub fn update(&mut self, data: &[u8]) {
        let mut c = self.0;
        for &b in data {
            c ^= b as u32;
            c = (c >> 4) ^ CRC_NIBBLES[(c & 0xf) as usize];
            c = (c >> 4) ^ CRC_NIBBLES[(c & 0xf) as usize];
        }
        self.0 = c;
    }
    /// The CRC of everything fed so far.
    pub fn finish(&self) -> u32 {
        !self.0
    }
}

/// CRC-32/ISO-HDLC of `data`.
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = Crc32::new();
    c.update(data);
    c.finish()
}
