//! Power-loss-safe storage of the drive's configuration and calibration on NOR flash: two
//! equal slots (A, B) with a sequence number, written alternately, header last.
//!
//! One flash device (any blocking [`NorFlash`]) holds the two slots: A at offset 0, B at
//! `capacity / 2`; each slot is a whole number of erase units (on the board one 128 KiB sector
//! each, sectors 10 and 11). A slot holds one record, header then payload (little-endian):
//! ```text
//! 0   magic "BDST"
//! 4   schema u16 (= 1)            6   reserved u16 (= 0, covered by the CRC)
//! 8   seq u32                     12  settings length u32
//! 16  blob length u32             20  CRC-32 (IEEE) of bytes 0..20, then settings, then blob
//! 24  payload: settings, then blob (at 24 rounded up to the flash's WRITE_SIZE: 24 on the
//!     STM32F4 and on the QEMU file)
//! ```
//! [`save`] never touches the slot holding the newest valid record: it erases the other slot,
//! writes the payload, then the header, so that until the header's last byte lands the new slot
//! reads as empty or corrupt and [`load`] still returns the previous record. A cut during the
//! erase leaves a slot that fails its magic, lengths or CRC (or is an older intact record, whose
//! sequence number loses). [`load`] takes the valid record with the newest sequence number
//! (serial-number arithmetic, so the 32-bit counter may wrap).
//!
//! Reads and writes go through a 64-byte buffer on the stack, aligned to the flash's
//! `READ_SIZE` / `WRITE_SIZE` (padding written as 0xFF); the CRC is computed while streaming.
//! Nothing here panics, whatever the flash holds.

use belt_link::bytes::{Fields, Reader, Writer};
use belt_link::Crc32;
use embedded_storage::nor_flash::{NorFlash, NorFlashError};

use crate::staging::{Source, Staging, StagingError};

/// First four bytes of every record.
pub const MAGIC: [u8; 4] = *b"BDST";
/// The record layout this code writes and reads.
pub const SCHEMA_VERSION: u16 = 1;
/// Header size; the payload starts at this offset rounded up to the flash's `WRITE_SIZE`.
pub const HEADER_BYTES: usize = 24;
/// The header bytes covered by the CRC (everything before the CRC itself).
const CRC_COVERS: usize = 20;
/// Stack buffer for streaming reads and staged writes: `READ_SIZE` and `WRITE_SIZE` must divide
/// it (the geometry check refuses other flashes).
const CHUNK: usize = 64;

/// One of the two slots.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Slot {
    /// The first half of the flash.
    A,
    /// The second half of the flash.
    B,
}

impl Slot {
    /// Both slots, in address order.
    pub const BOTH: [Slot; 2] = [Slot::A, Slot::B];

    /// The slot a save writes after a record in `self`.
    pub fn other(self) -> Slot {
        match self {
            Slot::A => Slot::B,
            Slot::B => Slot::A,
        }
    }

    /// 0 for A, 1 for B (the index into [`inspect`]'s answer).
    pub fn index(self) -> usize {
        self as usize
    }

    /// `"A"` or `"B"`.
    pub fn name(self) -> &'static str {
        match self {
            Slot::A => "A",
            Slot::B => "B",
        }
    }
}

impl core::fmt::Display for Slot {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// A valid record: where it is and what it holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RecordInfo {
    /// The slot holding it.
    pub slot: Slot,
    /// Sequence number: one more (wrapping) than the record it replaced, 1 on a blank flash.
    pub seq: u32,
    /// Bytes of settings.
    pub settings_len: usize,
    /// Bytes of calibration blob (0: none).
    pub blob_len: usize,
    /// The header's CRC-32 (of header bytes 0..20, settings and blob).
    pub crc32: u32,
}

/// Why a slot holds no valid record although it is not blank.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Corruption {
    /// The first four bytes are not [`MAGIC`].
    BadMagic,
    /// Written with another record layout (the schema found).
    Schema(u16),
    /// The lengths do not fit in the slot.
    BadLength,
    /// The CRC does not match: a save cut short, or the flash decayed.
    BadCrc,
}

impl Corruption {
    /// A short name for logs.
    pub fn name(self) -> &'static str {
        match self {
            Corruption::BadMagic => "bad magic",
            Corruption::Schema(_) => "unknown schema",
            Corruption::BadLength => "bad lengths",
            Corruption::BadCrc => "bad CRC",
        }
    }
}

impl core::fmt::Display for Corruption {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Corruption::Schema(v) => write!(f, "unknown schema {v} (want {SCHEMA_VERSION})"),
            other => f.write_str(other.name()),
        }
    }
}

/// What a slot holds, as [`inspect`] finds it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SlotState {
    /// The header is all 0xFF: never written, erased, or a save cut before its header.
    Empty,
    /// A record that passes every check.
    Valid(RecordInfo),
    /// Something that is not a valid record.
    Corrupt(Corruption),
}

impl SlotState {
    /// The record, if valid.
    pub fn record(&self) -> Option<RecordInfo> {
        match *self {
            SlotState::Valid(r) => Some(r),
            _ => None,
        }
    }

    /// A short name for logs: `"empty"`, `"valid"` or the corruption's name.
    pub fn name(&self) -> &'static str {
        match self {
            SlotState::Empty => "empty",
            SlotState::Valid(_) => "valid",
            SlotState::Corrupt(c) => c.name(),
        }
    }
}

impl core::fmt::Display for SlotState {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            SlotState::Empty => f.write_str("empty"),
            SlotState::Valid(r) => write!(
                f,
                "valid seq {} crc {:#010x} ({} B settings, {} B blob)",
                r.seq, r.crc32, r.settings_len, r.blob_len
            ),
            SlotState::Corrupt(c) => write!(f, "corrupt ({c})"),
        }
    }
}

/// Why a save or load failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StorageError<E> {
    /// The flash driver failed (read, erase or write).
    Flash(E),
    /// The flash is not two equal slots of whole erase units, or its read or write size does
    /// not divide 64 bytes.
    Geometry,
    /// The payload does not fit in a slot; nothing was written.
    TooLarge {
        /// Settings and blob bytes.
        needed: usize,
        /// Payload bytes a slot holds.
        room: usize,
    },
    /// The newest record's settings do not fit the caller's buffer (nothing older is loaded
    /// instead: that would silently roll the configuration back).
    SettingsBufferTooSmall {
        /// Bytes of settings in the record.
        needed: usize,
        /// The buffer's length.
        have: usize,
    },
    /// The newest record's blob does not fit the caller's buffer.
    BlobBufferTooSmall {
        /// Bytes of blob in the record.
        needed: usize,
        /// The buffer's length.
        have: usize,
    },
    /// After a save, the record read back is not the one written.
    Verify,
    /// The record read differently when copied than when checked (unstable flash).
    Changed,
    /// The staging area failed (reading the blob to save, or staging a stored one).
    Staging(StagingError),
}

impl<E> StorageError<E> {
    /// A one-byte code for the link's error detail: 1 flash, 2 geometry, 3 too large,
    /// 4 settings buffer, 5 blob buffer, 6 verify, 7 changed, 8 staging.
    pub fn code(&self) -> u8 {
        match self {
            StorageError::Flash(_) => 1,
            StorageError::Geometry => 2,
            StorageError::TooLarge { .. } => 3,
            StorageError::SettingsBufferTooSmall { .. } => 4,
            StorageError::BlobBufferTooSmall { .. } => 5,
            StorageError::Verify => 6,
            StorageError::Changed => 7,
            StorageError::Staging(_) => 8,
        }
    }
}

impl<E: NorFlashError> core::fmt::Display for StorageError<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            StorageError::Flash(e) => write!(f, "flash error: {} ({e:?})", e.kind()),
            StorageError::Geometry => f.write_str(
                "flash geometry not supported: need two equal slots of whole erase units and \
                 read/write sizes dividing 64 bytes",
            ),
            StorageError::TooLarge { needed, room } => write!(
                f,
                "record too large: {needed} bytes of settings and blob, a slot holds {room}"
            ),
            StorageError::SettingsBufferTooSmall { needed, have } => write!(
                f,
                "stored settings are {needed} bytes, the buffer holds {have}"
            ),
            StorageError::BlobBufferTooSmall { needed, have } => write!(
                f,
                "stored calibration blob is {needed} bytes, the buffer holds {have}"
            ),
            StorageError::Verify => {
                f.write_str("the record read back differs from the one written")
            }
            StorageError::Changed => f.write_str("the record changed while it was being read"),
            StorageError::Staging(e) => write!(f, "staging area: {e}"),
        }
    }
}

#[cfg(feature = "std")]
impl<E: NorFlashError> std::error::Error for StorageError<E> {}

/// True when sequence number `a` is newer than `b` (RFC 1982 serial-number arithmetic: `a` is
/// ahead by less than half the counter). Two numbers exactly half the counter apart are
/// neither; saves only ever produce neighbours.
pub fn is_newer(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) > 0
}

/// The record [`load`] would return from these slot states: the valid one with the newer
/// sequence number (A when neither is newer).
pub fn newest(states: &[SlotState; 2]) -> Option<RecordInfo> {
    match (states[0].record(), states[1].record()) {
        (Some(a), Some(b)) => Some(if is_newer(b.seq, a.seq) { b } else { a }),
        (a, b) => a.or(b),
    }
}

/// Checks both slots (header fields, lengths, CRC over the whole record), for a status report.
pub fn inspect<F: NorFlash>(flash: &mut F) -> Result<[SlotState; 2], StorageError<F::Error>> {
    let g = Geometry::of(flash)?;
    scan(flash, &g).map_err(StorageError::Flash)
}

/// Saves `settings` and `blob` as a new record in the slot that does not hold the newest valid
/// record, with the next sequence number; the previous record stays intact until the new one is
/// complete. Refuses (writing nothing) a payload larger than a slot. The record is read back and
/// checked before `Ok`.
pub fn save<F: NorFlash>(
    flash: &mut F,
    settings: &[u8],
    blob: &[u8],
) -> Result<RecordInfo, StorageError<F::Error>> {
    save_from(flash, settings, &mut { blob })
}

/// [`save`] with the blob read from `blob` (the drive's staging flash) in small pieces.
pub fn save_from<F: NorFlash>(
    flash: &mut F,
    settings: &[u8],
    blob: &mut dyn Source,
) -> Result<RecordInfo, StorageError<F::Error>> {
    let g = Geometry::of(flash)?;
    let room = g.room();
    let needed = settings.len().saturating_add(blob.len());
    if needed > room {
        return Err(StorageError::TooLarge { needed, room });
    }
    let states = scan(flash, &g).map_err(StorageError::Flash)?;
    let (slot, seq) = match newest(&states) {
        Some(r) => (r.slot.other(), r.seq.wrapping_add(1)),
        None => (Slot::A, 1),
    };
    write_record(flash, &g, slot, seq, settings, blob)
}

/// Loads the newest valid record into the buffers (settings into `settings_buf[..settings_len]`,
/// blob into `blob_buf[..blob_len]`); `Ok(None)` when neither slot holds a valid record.
pub fn load<F: NorFlash>(
    flash: &mut F,
    settings_buf: &mut [u8],
    blob_buf: &mut [u8],
) -> Result<Option<RecordInfo>, StorageError<F::Error>> {
    load_with(flash, settings_buf, Some(blob_buf))
}

/// [`load`] without copying the blob (its bytes still pass the CRC): the drive stages it with
/// [`stage_blob`] instead.
pub fn load_settings<F: NorFlash>(
    flash: &mut F,
    settings_buf: &mut [u8],
) -> Result<Option<RecordInfo>, StorageError<F::Error>> {
    load_with(flash, settings_buf, None)
}

fn load_with<F: NorFlash>(
    flash: &mut F,
    settings_buf: &mut [u8],
    blob_buf: Option<&mut [u8]>,
) -> Result<Option<RecordInfo>, StorageError<F::Error>> {
    let g = Geometry::of(flash)?;
    let states = scan(flash, &g).map_err(StorageError::Flash)?;
    let Some(r) = newest(&states) else {
        return Ok(None);
    };
    let blob_have = blob_buf.as_ref().map_or(0, |b| b.len());
    let blob_out = match blob_buf {
        Some(buf) => buf.get_mut(..r.blob_len).map(Some),
        None => Some(None),
    };
    let (Some(settings_out), Some(blob_out)) = (settings_buf.get_mut(..r.settings_len), blob_out)
    else {
        return Err(if r.settings_len > settings_buf.len() {
            StorageError::SettingsBufferTooSmall {
                needed: r.settings_len,
                have: settings_buf.len(),
            }
        } else {
            StorageError::BlobBufferTooSmall {
                needed: r.blob_len,
                have: blob_have,
            }
        });
    };
    // The CRC again, over exactly the bytes handed out.
    let base = g.base(r.slot);
    let mut head = [0u8; HEADER_BYTES];
    read_exact(flash, base, &mut head).map_err(StorageError::Flash)?;
    let mut crc = Crc32::new();
    crc.update(&head[..CRC_COVERS]);
    let at = base + g.payload_at;
    read_exact(flash, at, settings_out).map_err(StorageError::Flash)?;
    crc.update(settings_out);
    let blob_at = at + r.settings_len as u32;
    match blob_out {
        Some(out) => {
            read_exact(flash, blob_at, out).map_err(StorageError::Flash)?;
            crc.update(out);
        }
        None => crc_over(flash, blob_at, r.blob_len, &mut crc).map_err(StorageError::Flash)?,
    }
    let same_header = Header::parse(&head).is_some_and(|h| {
        h.seq == r.seq
            && h.settings_len as usize == r.settings_len
            && h.blob_len as usize == r.blob_len
            && h.crc32 == r.crc32
    });
    if !same_header || crc.finish() != r.crc32 {
        return Err(StorageError::Changed);
    }
    Ok(Some(r))
}

/// Erases `slot`, writes the payload, then the header; reads the record back. Saves call it
/// with the slot and sequence number [`save`] chose; tests call it directly to build a flash.
fn write_record<F: NorFlash>(
    flash: &mut F,
    g: &Geometry,
    slot: Slot,
    seq: u32,
    settings: &[u8],
    blob: &mut dyn Source,
) -> Result<RecordInfo, StorageError<F::Error>> {
    let needed = settings.len().saturating_add(blob.len());
    if needed > g.room() {
        return Err(StorageError::TooLarge {
            needed,
            room: g.room(),
        });
    }
    // Both lengths fit in the slot, whose size fits in a u32.
    let mut head = Header {
        seq,
        settings_len: settings.len() as u32,
        blob_len: blob.len() as u32,
        crc32: 0,
    }
    .encode();
    let mut crc = Crc32::new();
    crc.update(&head[..CRC_COVERS]);
    crc.update(settings);
    crate::staging::crc32_from(blob, 0, &mut crc).map_err(StorageError::Staging)?;
    let crc32 = crc.finish();
    head[CRC_COVERS..].copy_from_slice(&crc32.to_le_bytes());

    let base = g.base(slot);
    let flash_err = StorageError::Flash;
    flash.erase(base, base + g.slot_len).map_err(flash_err)?;
    let mut payload = Program::new(flash, base + g.payload_at);
    payload.push(settings).map_err(flash_err)?;
    // The blob again, piece by piece: a source that changed since its CRC fails the read-back.
    let mut piece = [0u8; CHUNK];
    let mut at = 0;
    while at < blob.len() {
        let n = (blob.len() - at).min(CHUNK);
        blob.read_at(at, &mut piece[..n])
            .map_err(StorageError::Staging)?;
        payload.push(&piece[..n]).map_err(flash_err)?;
        at += n;
    }
    payload.finish().map_err(flash_err)?;
    // The header last: the record exists only once this lands.
    let mut header = Program::new(flash, base);
    header.push(&head).map_err(flash_err)?;
    header.finish().map_err(flash_err)?;

    let info = RecordInfo {
        slot,
        seq,
        settings_len: settings.len(),
        blob_len: blob.len(),
        crc32,
    };
    match check_slot(flash, g, slot).map_err(flash_err)? {
        SlotState::Valid(r) if r == info => Ok(info),
        _ => Err(StorageError::Verify),
    }
}

/// True when `staging` holds the `len` bytes at `blob_at` (false also when they do not fit it).
fn same_blob<F: NorFlash, S: Staging + ?Sized>(
    flash: &mut F,
    blob_at: u32,
    len: usize,
    staging: &mut S,
) -> Result<bool, StorageError<F::Error>> {
    let (mut stored, mut staged) = ([0u8; CHUNK], [0u8; CHUNK]);
    let mut at = 0;
    while at < len {
        let n = (len - at).min(CHUNK);
        read_exact(flash, blob_at + at as u32, &mut stored[..n]).map_err(StorageError::Flash)?;
        match staging.read(at, &mut staged[..n]) {
            Ok(()) if stored[..n] == staged[..n] => at += n,
            Ok(()) | Err(StagingError::OutOfBounds) => return Ok(false),
            Err(e) => return Err(StorageError::Staging(e)),
        }
    }
    Ok(true)
}

/// Whether [`stage_blob`] found the record's blob already staged or copied it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Staged {
    /// The staging area already held these bytes (no erase).
    Already,
    /// The staging area was erased and the blob copied and read back.
    Copied,
}

/// Makes `staging` hold the blob of record `r` (from [`load_settings`]) at offset 0, erasing
/// and copying only when it holds other bytes. The record must still pass its CRC while it is
/// read ([`StorageError::Changed`] otherwise), and the copy must read back equal
/// ([`StorageError::Verify`]).
pub fn stage_blob<F: NorFlash, S: Staging + ?Sized>(
    flash: &mut F,
    r: &RecordInfo,
    staging: &mut S,
) -> Result<Staged, StorageError<F::Error>> {
    let g = Geometry::of(flash)?;
    let base = g.base(r.slot);
    let blob_at = base + g.payload_at + r.settings_len as u32;
    // The record as a whole first: what is staged must be what the CRC vouches for.
    match check_slot(flash, &g, r.slot).map_err(StorageError::Flash)? {
        SlotState::Valid(now) if now == *r => {}
        _ => return Err(StorageError::Changed),
    }
    if same_blob(flash, blob_at, r.blob_len, staging)? {
        return Ok(Staged::Already);
    }
    staging.erase().map_err(StorageError::Staging)?;
    let mut piece = [0u8; CHUNK];
    let mut at = 0;
    while at < r.blob_len {
        let n = (r.blob_len - at).min(CHUNK);
        read_exact(flash, blob_at + at as u32, &mut piece[..n]).map_err(StorageError::Flash)?;
        staging
            .write(at, &piece[..n])
            .map_err(StorageError::Staging)?;
        at += n;
    }
    if !same_blob(flash, blob_at, r.blob_len, staging)? {
        return Err(StorageError::Verify);
    }
    Ok(Staged::Copied)
}

/// Where the slots and the payload are on this flash.
struct Geometry {
    slot_len: u32,
    payload_at: u32,
}

impl Geometry {
    /// Two equal halves of whole erase units, read and write sizes dividing [`CHUNK`] and the
    /// slot, offsets within `u32`.
    fn of<F: NorFlash, E>(flash: &F) -> Result<Geometry, StorageError<E>> {
        let (erase, write, read) = (F::ERASE_SIZE, F::WRITE_SIZE, F::READ_SIZE);
        let capacity = flash.capacity();
        let slot = capacity / 2;
        let divides = |unit: usize, n: usize| unit != 0 && n.is_multiple_of(unit);
        let payload_at = HEADER_BYTES.div_ceil(write.max(1)) * write.max(1);
        let ok = u32::try_from(capacity).is_ok()
            && slot > 0
            && capacity == 2 * slot
            && divides(erase, slot)
            && divides(write, CHUNK)
            && divides(read, CHUNK)
            && divides(write, slot)
            && divides(read, slot)
            && payload_at <= slot;
        if !ok {
            return Err(StorageError::Geometry);
        }
        Ok(Geometry {
            slot_len: slot as u32,
            payload_at: payload_at as u32,
        })
    }

    fn base(&self, slot: Slot) -> u32 {
        slot.index() as u32 * self.slot_len
    }

    /// Payload bytes a slot holds.
    fn room(&self) -> usize {
        (self.slot_len - self.payload_at) as usize
    }
}

/// The header's fields (magic, schema and reserved are implied).
struct Header {
    seq: u32,
    settings_len: u32,
    blob_len: u32,
    crc32: u32,
}

impl Header {
    fn encode(&self) -> [u8; HEADER_BYTES] {
        let mut h = [0u8; HEADER_BYTES];
        let mut w = Writer::new(&mut h);
        w.put(&MAGIC);
        w.u16(SCHEMA_VERSION);
        w.u16(0); // reserved
        w.u32(self.seq);
        w.u32(self.settings_len);
        w.u32(self.blob_len);
        w.u32(self.crc32);
        // Exactly HEADER_BYTES fields: cannot fall short (the round-trip tests read them back).
        let _ = w.finish();
        h
    }

    /// The fields of a header with the right magic and schema.
    fn parse(h: &[u8; HEADER_BYTES]) -> Option<Header> {
        let mut r = Reader::new(h);
        if r.take::<4>().ok()? != MAGIC || r.u16().ok()? != SCHEMA_VERSION {
            return None;
        }
        r.u16().ok()?;
        Some(Header {
            seq: r.u32().ok()?,
            settings_len: r.u32().ok()?,
            blob_len: r.u32().ok()?,
            crc32: r.u32().ok()?,
        })
    }
}

fn schema(h: &[u8; HEADER_BYTES]) -> u16 {
    let mut r = Reader::new(&h[4..]);
    r.u16().unwrap_or(0)
}

fn scan<F: NorFlash>(flash: &mut F, g: &Geometry) -> Result<[SlotState; 2], F::Error> {
    Ok([
        check_slot(flash, g, Slot::A)?,
        check_slot(flash, g, Slot::B)?,
    ])
}

/// Checks one slot's header and lengths, then streams the payload through the CRC.
fn check_slot<F: NorFlash>(flash: &mut F, g: &Geometry, slot: Slot) -> Result<SlotState, F::Error> {
    let base = g.base(slot);
    let mut head = [0u8; HEADER_BYTES];
    read_exact(flash, base, &mut head)?;
    if head.iter().all(|&b| b == 0xFF) {
        return Ok(SlotState::Empty);
    }
    if head[0..4] != MAGIC {
        return Ok(SlotState::Corrupt(Corruption::BadMagic));
    }
    let Some(h) = Header::parse(&head) else {
        return Ok(SlotState::Corrupt(Corruption::Schema(schema(&head))));
    };
    // u64: two u32 lengths cannot overflow it.
    let total = h.settings_len as u64 + h.blob_len as u64;
    if total > g.room() as u64 {
        return Ok(SlotState::Corrupt(Corruption::BadLength));
    }
    let mut crc = Crc32::new();
    crc.update(&head[..CRC_COVERS]);
    crc_over(flash, base + g.payload_at, total as usize, &mut crc)?;
    if crc.finish() != h.crc32 {
        return Ok(SlotState::Corrupt(Corruption::BadCrc));
    }
    Ok(SlotState::Valid(RecordInfo {
        slot,
        seq: h.seq,
        settings_len: h.settings_len as usize,
        blob_len: h.blob_len as usize,
        crc32: h.crc32,
    }))
}

/// Reads `len` bytes from `start` in `READ_SIZE`-aligned chunks of at most [`CHUNK`] bytes,
/// handing `each` the requested part of every chunk. The caller keeps `start + len` within a
/// slot (whose end is `READ_SIZE`-aligned), so the aligned reads stay within it too.
fn stream<F: NorFlash>(
    flash: &mut F,
    start: u32,
    len: usize,
    mut each: impl FnMut(&[u8]),
) -> Result<(), F::Error> {
    let align = F::READ_SIZE.max(1) as u32;
    let end = start + len as u32;
    let aligned_end = end.div_ceil(align) * align;
    let mut at = start - start % align;
    let mut buf = [0u8; CHUNK];
    while at < end {
        let n = (aligned_end - at).min(CHUNK as u32);
        flash.read(at, &mut buf[..n as usize])?;
        let lo = start.saturating_sub(at) as usize;
        let hi = (end.min(at + n) - at) as usize;
        // `get`, not indexing: `lo <= hi` holds, and no slice panic (with its `core::fmt`,
        // ~1 KB of flash) is linked for it.
        if let Some(bytes) = buf.get(lo..hi) {
            each(bytes);
        }
        at += n;
    }
    Ok(())
}

/// Feeds `len` bytes from `start` to `crc` (see [`stream`]).
fn crc_over<F: NorFlash>(
    flash: &mut F,
    start: u32,
    len: usize,
    crc: &mut Crc32,
) -> Result<(), F::Error> {
    stream(flash, start, len, |bytes| crc.update(bytes))
}

/// Fills `out` from `start` (see [`stream`]). Not inlined: one copy per flash (flash size).
#[inline(never)]
fn read_exact<F: NorFlash>(flash: &mut F, start: u32, out: &mut [u8]) -> Result<(), F::Error> {
    let mut filled = 0;
    stream(flash, start, out.len(), |bytes| {
        if let Some(dst) = out.get_mut(filled..filled + bytes.len()) {
            dst.copy_from_slice(bytes);
        }
        filled += bytes.len();
    })
}

/// Bytes staged for programming in `WRITE_SIZE`-aligned chunks, the tail padded with 0xFF.
struct Program<'f, F> {
    flash: &'f mut F,
    at: u32,
    buf: [u8; CHUNK],
    fill: usize,
}

impl<'f, F: NorFlash> Program<'f, F> {
    /// Programming starts at `at`, which is `WRITE_SIZE`-aligned.
    fn new(flash: &'f mut F, at: u32) -> Self {
        Program {
            flash,
            at,
            buf: [0xFF; CHUNK],
            fill: 0,
        }
    }

    fn push(&mut self, mut bytes: &[u8]) -> Result<(), F::Error> {
        while !bytes.is_empty() {
            let n = (CHUNK - self.fill).min(bytes.len());
            let (head, rest) = bytes.split_at(n);
            // `fill + n <= CHUNK`; `get_mut` keeps the slice panic (and `core::fmt`) out.
            if let Some(dst) = self.buf.get_mut(self.fill..self.fill + n) {
                dst.copy_from_slice(head);
            }
            self.fill += n;
            bytes = rest;
            if self.fill == CHUNK {
                self.flush()?;
            }
        }
        Ok(())
    }

    /// Writes what is staged, padded to `WRITE_SIZE` (`CHUNK` is a multiple of it).
    fn flush(&mut self) -> Result<(), F::Error> {
        let align = F::WRITE_SIZE.max(1);
        let n = self.fill.div_ceil(align) * align;
        // `n <= CHUNK`: `CHUNK` is a multiple of `WRITE_SIZE`.
        if let Some(pad) = self.buf.get_mut(self.fill..n) {
            pad.fill(0xFF);
        }
        if let Some(staged) = self.buf.get(..n).filter(|s| !s.is_empty()) {
            self.flash.write(self.at, staged)?;
        }
        self.at += n as u32;
        self.fill = 0;
        Ok(())
    }

    fn finish(mut self) -> Result<(), F::Error> {
        self.flush()
    }
}

#[cfg(test)]
mod tests;
