//! The A/B storage against a RAM NOR flash that can lose power at any byte operation.

use super::*;
use embedded_storage::nor_flash::{
    check_erase, check_read, check_write, ErrorType, NorFlashErrorKind, ReadNorFlash,
};
use proptest::prelude::*;

/// Budget steps that erasing one erase unit is split into: a cut can land after any of them.
const ERASE_STEPS: usize = 8;

/// What a power cut during an erase leaves in the unit being erased.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum EraseCut {
    /// The steps done erased the unit's first part; the rest is untouched.
    HeadFirst,
    /// The steps done erased the unit's last part; the rest (the header) is untouched.
    TailFirst,
    /// The whole unit holds random bytes.
    Garbage,
}

/// What a power cut during a write leaves in the byte being programmed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ByteCut {
    /// Unchanged (the cut came just before it).
    Untouched,
    /// Some of its bits cleared: `old & (new | random)`.
    Partial,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum MockError {
    PowerCut,
    NotAligned,
    OutOfBounds,
}

impl NorFlashError for MockError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            MockError::PowerCut => NorFlashErrorKind::Other,
            MockError::NotAligned => NorFlashErrorKind::NotAligned,
            MockError::OutOfBounds => NorFlashErrorKind::OutOfBounds,
        }
    }
}

impl From<NorFlashErrorKind> for MockError {
    fn from(k: NorFlashErrorKind) -> Self {
        match k {
            NorFlashErrorKind::NotAligned => MockError::NotAligned,
            _ => MockError::OutOfBounds,
        }
    }
}

/// SplitMix64: seeded bytes for garbage and partial writes.
#[derive(Clone)]
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn byte(&mut self) -> u8 {
        self.next() as u8
    }
    fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.byte()).collect()
    }
}

/// NOR flash in RAM: erase sets 0xFF, a write clears bits (`old & new`), a word may be written
/// once per erase, reads and writes must be aligned. With a budget, the power fails on the
/// byte operation (a byte programmed, an erase step) after the budget: that operation is left
/// half done and every later one fails.
#[derive(Clone)]
struct Mock<const ERASE: usize, const WRITE: usize, const READ: usize> {
    mem: Vec<u8>,
    /// Words written since their last erase in this power-up; after a (re)boot every word
    /// counts as written, so storage must erase before it writes.
    programmed: Vec<bool>,
    budget: Option<usize>,
    ops: usize,
    off: bool,
    erase_cut: EraseCut,
    byte_cut: ByteCut,
    rng: Rng,
}

impl<const ERASE: usize, const WRITE: usize, const READ: usize> Mock<ERASE, WRITE, READ> {
    fn blank(capacity: usize) -> Self {
        Self::with(vec![0xFF; capacity])
    }

    fn with(mem: Vec<u8>) -> Self {
        Mock {
            programmed: vec![true; mem.len() / WRITE],
            mem,
            budget: None,
            ops: 0,
            off: false,
            erase_cut: EraseCut::HeadFirst,
            byte_cut: ByteCut::Untouched,
            rng: Rng(1),
        }
    }

    /// Power back on: same content, no budget.
    fn reboot(&self) -> Self {
        Self::with(self.mem.clone())
    }

    /// Armed to cut the power at byte operation `n` (0: the first).
    fn cut_at(&self, n: usize, erase_cut: EraseCut, byte_cut: ByteCut) -> Self {
        let mut m = self.reboot();
        m.budget = Some(n);
        m.erase_cut = erase_cut;
        m.byte_cut = byte_cut;
        m.rng = Rng(0x5EED ^ (n as u64) << 8 ^ erase_cut as u64 ^ (byte_cut as u64) << 4);
        m
    }

    /// One byte operation: false when the power fails on it.
    fn spend(&mut self) -> bool {
        match &mut self.budget {
            Some(0) => {
                self.off = true;
                false
            }
            Some(b) => {
                *b -= 1;
                self.ops += 1;
                true
            }
            None => {
                self.ops += 1;
                true
            }
        }
    }
}

impl<const ERASE: usize, const WRITE: usize, const READ: usize> ErrorType
    for Mock<ERASE, WRITE, READ>
{
    type Error = MockError;
}

impl<const ERASE: usize, const WRITE: usize, const READ: usize> ReadNorFlash
    for Mock<ERASE, WRITE, READ>
{
    const READ_SIZE: usize = READ;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), MockError> {
        check_read(self, offset, bytes.len())?;
        if self.off {
            return Err(MockError::PowerCut);
        }
        let at = offset as usize;
        bytes.copy_from_slice(&self.mem[at..at + bytes.len()]);
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.mem.len()
    }
}

impl<const ERASE: usize, const WRITE: usize, const READ: usize> NorFlash
    for Mock<ERASE, WRITE, READ>
{
    const WRITE_SIZE: usize = WRITE;
    const ERASE_SIZE: usize = ERASE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), MockError> {
        check_erase(self, from, to)?;
        if self.off {
            return Err(MockError::PowerCut);
        }
        for unit in (from as usize..to as usize).step_by(ERASE) {
            for done in 0..ERASE_STEPS {
                if !self.spend() {
                    let part = ERASE * done / ERASE_STEPS;
                    let range = unit..unit + ERASE;
                    match self.erase_cut {
                        EraseCut::HeadFirst => self.mem[unit..unit + part].fill(0xFF),
                        EraseCut::TailFirst => self.mem[range.end - part..range.end].fill(0xFF),
                        EraseCut::Garbage => {
                            let junk = self.rng.bytes(ERASE);
                            self.mem[range].copy_from_slice(&junk);
                        }
                    }
                    return Err(MockError::PowerCut);
                }
            }
            self.mem[unit..unit + ERASE].fill(0xFF);
            self.programmed[unit / WRITE..(unit + ERASE) / WRITE].fill(false);
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), MockError> {
        check_write(self, offset, bytes.len())?;
        if self.off {
            return Err(MockError::PowerCut);
        }
        for (i, &new) in bytes.iter().enumerate() {
            let at = offset as usize + i;
            if at.is_multiple_of(WRITE) {
                assert!(
                    !self.programmed[at / WRITE],
                    "word at {at:#x} written twice without an erase"
                );
                self.programmed[at / WRITE] = true;
            }
            if !self.spend() {
                if self.byte_cut == ByteCut::Partial {
                    self.mem[at] &= new | self.rng.byte();
                }
                return Err(MockError::PowerCut);
            }
            self.mem[at] &= new;
        }
        Ok(())
    }
}

/// Two 4 KiB slots of four 1 KiB erase units, byte writes (the STM32F4's write size).
type Small = Mock<1024, 1, 1>;
const SMALL: usize = 8 * 1024;

/// A record as the test wrote it.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Rec {
    seq: u32,
    settings: Vec<u8>,
    blob: Vec<u8>,
}

/// Distinct contents for each `tag`.
fn contents(tag: u64, settings_len: usize, blob_len: usize) -> (Vec<u8>, Vec<u8>) {
    let mut rng = Rng(tag.wrapping_mul(0x1234_5678_9ABC));
    (rng.bytes(settings_len), rng.bytes(blob_len))
}

/// Everything `load` returns, copied out.
fn load_rec<F: NorFlash>(flash: &mut F) -> Option<Rec> {
    let mut settings = vec![0u8; 16 * 1024];
    let mut blob = vec![0u8; 16 * 1024];
    let r = load(flash, &mut settings, &mut blob).expect("load")?;
    assert_eq!(inspect(flash).ok().and_then(|s| newest(&s)), Some(r));
    Some(Rec {
        seq: r.seq,
        settings: settings[..r.settings_len].to_vec(),
        blob: blob[..r.blob_len].to_vec(),
    })
}

fn save_rec<F: NorFlash>(flash: &mut F, settings: &[u8], blob: &[u8]) -> Rec {
    let info = save(flash, settings, blob).expect("save");
    Rec {
        seq: info.seq,
        settings: settings.to_vec(),
        blob: blob.to_vec(),
    }
}

/// A record with a chosen sequence number in a chosen slot.
fn put<F: NorFlash>(flash: &mut F, slot: Slot, seq: u32, settings: &[u8], blob: &[u8]) -> Rec {
    let g = Geometry::of::<F, F::Error>(flash).expect("geometry");
    write_record(flash, &g, slot, seq, settings, &mut { blob }).expect("write_record");
    Rec {
        seq,
        settings: settings.to_vec(),
        blob: blob.to_vec(),
    }
}

/// The flash states a save can start from, and the record `load` returns from each.
fn histories<const E: usize, const W: usize, const R: usize>(
    capacity: usize,
    settings_len: usize,
    blob_len: usize,
) -> Vec<(&'static str, Mock<E, W, R>, Option<Rec>)> {
    let half = capacity / 2;
    let (s1, b1) = contents(1, settings_len, blob_len);
    // Shorter, so that the older record's bytes differ in length too.
    let (s2, b2) = contents(2, settings_len / 2, blob_len / 3);
    let mut out = Vec::new();

    out.push(("blank", Mock::blank(capacity), None));

    let mut f = Mock::blank(capacity);
    let r1 = save_rec(&mut f, &s1, &b1);
    out.push(("A valid, B blank", f.reboot(), Some(r1.clone())));

    let r2 = save_rec(&mut f, &s2, &b2);
    out.push(("A older, B newest", f.reboot(), Some(r2)));

    let mut g = Mock::blank(capacity);
    save_rec(&mut g, &s1, &b1);
    let junk = Rng(7).bytes(half);
    g.mem[half..].copy_from_slice(&junk);
    out.push(("A valid, B garbage", g.reboot(), Some(r1)));

    let mut g = Mock::blank(capacity);
    g.mem = Rng(8).bytes(capacity);
    out.push(("both garbage", g.reboot(), None));

    // Sequence numbers about to wrap: the new record gets seq 0.
    let mut g = Mock::blank(capacity);
    put(&mut g, Slot::A, u32::MAX - 1, &s1, &b1);
    let r = put(&mut g, Slot::B, u32::MAX, &s2, &b2);
    out.push(("A seq MAX-1, B seq MAX", g.reboot(), Some(r)));
    out
}

/// Cuts the power at every byte operation of one save (every `stride`-th payload byte, but every
/// erase step and every header byte), for each starting state and cut kind; after each, reboots
/// and checks that `load` returns exactly the previous record or exactly the new one, then that
/// a further save works and loads. Returns (cut positions, cases run).
fn power_cut_sweep<const E: usize, const W: usize, const R: usize>(
    capacity: usize,
    settings_len: usize,
    blob_len: usize,
    stride: usize,
) -> (usize, usize) {
    let (s_new, b_new) = contents(100, settings_len, blob_len);
    let (s_more, b_more) = contents(200, settings_len / 3, blob_len / 2);
    let erase_ops = capacity / 2 / E * ERASE_STEPS;
    let header_ops = HEADER_BYTES.div_ceil(W) * W;
    let (mut positions, mut cases) = (0, 0);
    for (name, start, previous) in histories::<E, W, R>(capacity, settings_len, blob_len) {
        let mut probe = start.reboot();
        save(&mut probe, &s_new, &b_new).expect("uncut save");
        let total = probe.ops;
        let expected_new = Rec {
            seq: previous.as_ref().map_or(1, |p| p.seq.wrapping_add(1)),
            settings: s_new.clone(),
            blob: b_new.clone(),
        };
        let cuts = (0..=total)
            .filter(|&n| n < erase_ops || n % stride == 0 || n + header_ops >= total)
            .collect::<Vec<_>>();
        positions += cuts.len();
        for n in cuts {
            let modes: &[(EraseCut, ByteCut)] = if n < erase_ops {
                &[
                    (EraseCut::HeadFirst, ByteCut::Untouched),
                    (EraseCut::TailFirst, ByteCut::Untouched),
                    (EraseCut::Garbage, ByteCut::Untouched),
                ]
            } else {
                &[
                    (EraseCut::HeadFirst, ByteCut::Untouched),
                    (EraseCut::HeadFirst, ByteCut::Partial),
                ]
            };
            for &(erase_cut, byte_cut) in modes {
                cases += 1;
                let case = format!("{name}: cut at op {n} of {total}, {erase_cut:?}/{byte_cut:?}");
                let mut f = start.cut_at(n, erase_cut, byte_cut);
                let saved = save(&mut f, &s_new, &b_new);
                if n < total {
                    assert_eq!(
                        saved,
                        Err(StorageError::Flash(MockError::PowerCut)),
                        "{case}"
                    );
                } else {
                    assert_eq!(saved.map(|r| r.seq), Ok(expected_new.seq), "{case}");
                }

                let mut f = f.reboot();
                let got = load_rec(&mut f);
                let ok = got == previous || got.as_ref() == Some(&expected_new);
                assert!(ok, "{case}: loaded {got:?}");
                if n >= total {
                    assert_eq!(got.as_ref(), Some(&expected_new), "{case}");
                }

                let more = save_rec(&mut f, &s_more, &b_more);
                assert_eq!(
                    more.seq,
                    got.as_ref().map_or(1, |g| g.seq.wrapping_add(1)),
                    "{case}"
                );
                assert_eq!(load_rec(&mut f.reboot()), Some(more), "{case}");
            }
        }
    }
    (positions, cases)
}

#[test]
fn storage_survives_a_power_cut_at_every_byte_of_a_save() {
    // 40 B settings + 100 B blob: 32 erase steps + 164 bytes per save.
    let (positions, cases) = power_cut_sweep::<1024, 1, 1>(SMALL, 40, 100, 1);
    assert!(
        positions > 6 * 196 && cases > 6 * 400,
        "{positions} {cases}"
    );
    println!("byte writes: {positions} cut positions, {cases} cases");
}

#[test]
fn storage_survives_power_cuts_with_aligned_words() {
    // 4-byte words (e.g. an STM32L4-style flash), and 16-byte writes / 8-byte reads with one
    // 4 KiB erase unit per slot (the payload starts at 32).
    let (p4, c4) = power_cut_sweep::<1024, 4, 4>(SMALL, 40, 100, 1);
    let (p16, c16) = power_cut_sweep::<4096, 16, 8>(SMALL, 41, 99, 1);
    println!(
        "4-byte words: {p4} positions, {c4} cases; 16-byte words: {p16} positions, {c16} cases"
    );
}

#[test]
fn storage_survives_power_cuts_with_a_realistic_blob() {
    // 300 B settings + a 5 kB blob, two 8 KiB slots of two 4 KiB units: every erase step and
    // header byte, every 37th payload byte.
    let (positions, cases) = power_cut_sweep::<4096, 1, 1>(16 * 1024, 300, 5000, 37);
    println!("5 kB blob: {positions} cut positions, {cases} cases");
}

/// Two records: A seq 1 (`older`), B seq 2 (`newer`).
fn two_records() -> (Small, Rec, Rec) {
    let mut f = Small::blank(SMALL);
    let (s1, b1) = contents(1, 40, 100);
    let (s2, b2) = contents(2, 30, 90);
    let older = save_rec(&mut f, &s1, &b1);
    let newer = save_rec(&mut f, &s2, &b2);
    (f.reboot(), older, newer)
}

#[test]
fn storage_a_flipped_byte_in_the_newest_record_loads_the_older_one() {
    let (f, older, newer) = two_records();
    let b = SMALL / 2;
    let record_end = b + HEADER_BYTES + 30 + 90;
    for at in b..record_end {
        for flip in [0x01, 0x80, 0xFF] {
            let mut g = f.reboot();
            g.mem[at] ^= flip;
            assert_eq!(
                load_rec(&mut g).as_ref(),
                Some(&older),
                "byte {at:#x} ^ {flip:#x}"
            );
            let states = inspect(&mut g).unwrap();
            assert!(matches!(states[1], SlotState::Corrupt(_)), "{}", states[1]);
        }
    }
    // Beyond the record, or in the older record: the newest still loads.
    for at in [record_end, SMALL - 1, 0, HEADER_BYTES + 5] {
        let mut g = f.reboot();
        g.mem[at] ^= 0x01;
        assert_eq!(load_rec(&mut g).as_ref(), Some(&newer), "byte {at:#x}");
    }
}

#[test]
fn storage_both_records_corrupt_load_nothing_and_save_starts_over() {
    let (mut f, _, _) = two_records();
    f.mem[30] ^= 0x10;
    f.mem[SMALL / 2 + 9] ^= 0x10;
    let states = inspect(&mut f).unwrap();
    assert_eq!(
        states,
        [
            SlotState::Corrupt(Corruption::BadCrc),
            SlotState::Corrupt(Corruption::BadCrc)
        ]
    );
    assert_eq!(load_rec(&mut f), None);
    let r = save_rec(&mut f, b"fresh", b"");
    assert_eq!(r.seq, 1);
    assert_eq!(load_rec(&mut f), Some(r));
}

#[test]
fn storage_slot_states_name_what_is_wrong() {
    let mut f = Small::blank(SMALL);
    assert_eq!(
        inspect(&mut f).unwrap(),
        [SlotState::Empty, SlotState::Empty]
    );
    let info = save(&mut f, b"settings", b"blob").unwrap();
    assert_eq!((info.slot, info.seq), (Slot::A, 1));
    let states = inspect(&mut f).unwrap();
    assert_eq!(states, [SlotState::Valid(info), SlotState::Empty]);
    assert_eq!(
        states[0].to_string(),
        format!(
            "valid seq 1 crc {:#010x} (8 B settings, 4 B blob)",
            info.crc32
        )
    );
    assert_eq!(states[1].to_string(), "empty");

    let cases: [(usize, u8, Corruption); 4] = [
        (0, b'X', Corruption::BadMagic),
        (4, 2, Corruption::Schema(2)),
        (14, 0x10, Corruption::BadLength),
        (26, b'S' ^ 1, Corruption::BadCrc),
    ];
    for (at, value, want) in cases {
        let mut g = f.reboot();
        g.mem[at] = value;
        assert_eq!(inspect(&mut g).unwrap()[0], SlotState::Corrupt(want));
        assert_eq!(load_rec(&mut g), None);
    }
    assert_eq!(
        SlotState::Corrupt(Corruption::Schema(2)).to_string(),
        "corrupt (unknown schema 2 (want 1))"
    );
    assert_eq!(SlotState::Corrupt(Corruption::BadCrc).name(), "bad CRC");
}

#[test]
fn storage_header_layout_is_as_documented() {
    let mut f = Small::blank(SMALL);
    let info = save(&mut f, b"abc", b"de").unwrap();
    let h = &f.mem[..HEADER_BYTES];
    assert_eq!(&h[0..4], b"BDST");
    assert_eq!(h[4..6], 1u16.to_le_bytes());
    assert_eq!(h[6..8], [0, 0]);
    assert_eq!(h[8..12], 1u32.to_le_bytes());
    assert_eq!(h[12..16], 3u32.to_le_bytes());
    assert_eq!(h[16..20], 2u32.to_le_bytes());
    assert_eq!(h[20..24], info.crc32.to_le_bytes());
    assert_eq!(&f.mem[24..29], b"abcde");
    assert_eq!(f.mem[29], 0xFF);
    // The CRC is the link's CRC-32 (zlib) of header bytes 0..20 and the payload.
    let mut all = h[..20].to_vec();
    all.extend_from_slice(b"abcde");
    assert_eq!(info.crc32, belt_link::crc32(&all));
}

#[test]
fn storage_sequence_numbers_wrap() {
    let table: [(u32, u32, Slot); 8] = [
        (u32::MAX, 0, Slot::B),
        (0, u32::MAX, Slot::A),
        (0x7FFF_FFFF, 0x8000_0000, Slot::B),
        (0x8000_0000, 0x7FFF_FFFF, Slot::A),
        (5, 4, Slot::A),
        (4, 5, Slot::B),
        (7, 7, Slot::A),
        // Half the counter apart: neither is newer, A wins.
        (0, 0x8000_0000, Slot::A),
    ];
    for (seq_a, seq_b, want) in table {
        let mut f = Small::blank(SMALL);
        let a = put(&mut f, Slot::A, seq_a, b"a-settings", b"a-blob");
        let b = put(&mut f, Slot::B, seq_b, b"b", b"");
        let got = load_rec(&mut f).unwrap();
        assert_eq!(got, if want == Slot::A { a } else { b }, "{seq_a} {seq_b}");
        // The next save replaces the other slot, one further on.
        let next = save(&mut f, b"next", b"n").unwrap();
        assert_eq!(next.slot, want.other(), "{seq_a} {seq_b}");
        assert_eq!(next.seq, got.seq.wrapping_add(1));
        assert_eq!(load_rec(&mut f).unwrap().seq, next.seq);
    }
    assert!(is_newer(0, u32::MAX) && !is_newer(u32::MAX, 0));
    assert!(is_newer(1, 0) && !is_newer(0, 0));
    assert!(is_newer(0x7FFF_FFFF, 0) && !is_newer(0x8000_0000, 0) && !is_newer(0, 0x8000_0000));
}

#[test]
fn storage_refuses_a_payload_larger_than_a_slot_and_writes_nothing() {
    let (mut f, _, newer) = two_records();
    let room = SMALL / 2 - HEADER_BYTES;
    let before = f.mem.clone();
    let big = vec![0x42u8; room - 10];
    assert_eq!(
        save(&mut f, &[1; 11], &big),
        Err(StorageError::TooLarge {
            needed: room + 1,
            room
        })
    );
    assert_eq!(f.mem, before);
    assert_eq!(f.ops, 0, "no erase, no write");
    assert_eq!(load_rec(&mut f), Some(newer));
    // Exactly full fits.
    let full = save_rec(&mut f, &[1; 10], &big);
    assert_eq!(load_rec(&mut f), Some(full));
}

#[test]
fn storage_load_refuses_small_buffers_rather_than_an_older_record() {
    let (mut f, _, _) = two_records();
    let mut settings = [0u8; 30];
    let mut blob = [0u8; 90];
    assert_eq!(
        load(&mut f, &mut settings[..29], &mut blob),
        Err(StorageError::SettingsBufferTooSmall {
            needed: 30,
            have: 29
        })
    );
    assert_eq!(
        load(&mut f, &mut settings, &mut blob[..89]),
        Err(StorageError::BlobBufferTooSmall {
            needed: 90,
            have: 89
        })
    );
    let r = load(&mut f, &mut settings, &mut blob).unwrap().unwrap();
    assert_eq!(
        (r.slot, r.seq, r.settings_len, r.blob_len),
        (Slot::B, 2, 30, 90)
    );
    assert_eq!(settings.to_vec(), contents(2, 30, 90).0);
}

#[test]
fn storage_empty_payloads_round_trip() {
    let mut f = Small::blank(SMALL);
    let r = save_rec(&mut f, &[], &[]);
    assert_eq!(load_rec(&mut f), Some(r));
    let r = save_rec(&mut f, b"only settings", &[]);
    assert_eq!(load_rec(&mut f), Some(r));
}

#[test]
fn storage_refuses_flash_geometries_it_cannot_split() {
    let mut odd = Small::blank(3 * 1024);
    assert_eq!(inspect(&mut odd), Err(StorageError::Geometry));
    let mut none = Small::blank(0);
    assert_eq!(save(&mut none, b"x", b""), Err(StorageError::Geometry));
    let mut wide = Mock::<1024, 128, 1>::blank(SMALL);
    assert_eq!(
        load(&mut wide, &mut [], &mut []),
        Err(StorageError::Geometry)
    );
    let mut half_unit = Mock::<2048, 1, 1>::blank(2048);
    assert_eq!(inspect(&mut half_unit), Err(StorageError::Geometry));
}

#[test]
fn storage_errors_have_distinct_codes_and_say_what_went_wrong() {
    type E = StorageError<MockError>;
    let all: [E; 8] = [
        StorageError::Flash(MockError::PowerCut),
        StorageError::Geometry,
        StorageError::TooLarge {
            needed: 9000,
            room: 4072,
        },
        StorageError::SettingsBufferTooSmall {
            needed: 300,
            have: 256,
        },
        StorageError::BlobBufferTooSmall {
            needed: 6000,
            have: 5000,
        },
        StorageError::Verify,
        StorageError::Changed,
        StorageError::Staging(StagingError::Flash),
    ];
    let codes: Vec<u8> = all.iter().map(|e| e.code()).collect();
    assert_eq!(codes, [1, 2, 3, 4, 5, 6, 7, 8]);
    assert_eq!(all[7].to_string(), "staging area: staging flash failed");
    assert!(all[0].to_string().starts_with("flash error"));
    assert_eq!(
        all[2].to_string(),
        "record too large: 9000 bytes of settings and blob, a slot holds 4072"
    );
    assert_eq!(
        all[4].to_string(),
        "stored calibration blob is 6000 bytes, the buffer holds 5000"
    );
}

/// A flash that stops working: load and save report it rather than guessing.
#[test]
fn storage_reports_flash_errors() {
    let (f, _, _) = two_records();
    let mut dead = f.cut_at(0, EraseCut::HeadFirst, ByteCut::Untouched);
    dead.off = true;
    assert_eq!(
        load(&mut dead, &mut [0; 64], &mut [0; 128]),
        Err(StorageError::Flash(MockError::PowerCut))
    );
    let before = dead.mem.clone();
    assert_eq!(
        save(&mut dead, b"x", b"y"),
        Err(StorageError::Flash(MockError::PowerCut))
    );
    assert_eq!(dead.mem, before);
}

#[test]
fn storage_garbage_flash_never_panics() {
    let mut rng = Rng(0xBAD);
    for i in 0..500 {
        let mut mem = rng.bytes(SMALL);
        // Half the time, valid-looking headers over the garbage.
        if i % 2 == 0 {
            for base in [0, SMALL / 2] {
                mem[base..base + 4].copy_from_slice(&MAGIC);
                mem[base + 4..base + 6].copy_from_slice(&SCHEMA_VERSION.to_le_bytes());
                if i % 4 == 0 {
                    let len = (rng.next() % 5000) as u32;
                    mem[base + 12..base + 16].copy_from_slice(&len.to_le_bytes());
                }
            }
        }
        let mut f = Small::with(mem);
        let states = inspect(&mut f).unwrap();
        assert_eq!(
            load_rec(&mut f).map(|r| r.seq),
            newest(&states).map(|r| r.seq)
        );
        let r = save_rec(&mut f, b"after garbage", b"");
        assert_eq!(load_rec(&mut f.reboot()), Some(r));
    }
}

proptest! {
    /// Any header fields over any payload: whatever `inspect` calls valid really is (its CRC
    /// matches), lengths never run past the slot, and nothing panics.
    #[test]
    fn storage_arbitrary_headers_are_checked_not_trusted(
        magic_ok in any::<bool>(),
        schema in prop_oneof![Just(SCHEMA_VERSION), any::<u16>()],
        reserved in any::<u16>(),
        seq in any::<u32>(),
        settings_len in prop_oneof![0u32..200, any::<u32>()],
        blob_len in prop_oneof![0u32..200, any::<u32>()],
        crc_ok in any::<bool>(),
        crc in any::<u32>(),
        seed in any::<u64>(),
    ) {
        let mut mem = Rng(seed).bytes(SMALL);
        let mut head = [0u8; HEADER_BYTES];
        head[0..4].copy_from_slice(if magic_ok { &MAGIC } else { b"BDSX" });
        head[4..6].copy_from_slice(&schema.to_le_bytes());
        head[6..8].copy_from_slice(&reserved.to_le_bytes());
        head[8..12].copy_from_slice(&seq.to_le_bytes());
        head[12..16].copy_from_slice(&settings_len.to_le_bytes());
        head[16..20].copy_from_slice(&blob_len.to_le_bytes());
        let total = settings_len as u64 + blob_len as u64;
        let fits = total <= (SMALL / 2 - HEADER_BYTES) as u64;
        let crc = if crc_ok && fits {
            let end = HEADER_BYTES + total as usize;
            let mut c = Crc32::new();
            c.update(&head[..20]);
            c.update(&mem[HEADER_BYTES..end]);
            c.finish()
        } else {
            crc
        };
        head[20..24].copy_from_slice(&crc.to_le_bytes());
        mem[..HEADER_BYTES].copy_from_slice(&head);
        let mut f = Small::with(mem);
        let states = inspect(&mut f).unwrap();
        let valid = magic_ok && schema == SCHEMA_VERSION && fits && crc_ok;
        if valid {
            prop_assert_eq!(states[0].record().map(|r| (r.seq, r.crc32)), Some((seq, crc)));
            let got = load_rec(&mut f).unwrap();
            prop_assert_eq!(got.settings.len(), settings_len as usize);
            prop_assert_eq!(got.blob.len(), blob_len as usize);
        } else if states[0].record().is_some() {
            // Only by a chance CRC match on random bytes (2^-32).
            let r = states[0].record().unwrap();
            prop_assert_eq!(r.crc32, crc);
        }
        let _ = load_rec(&mut f);
    }
}

// The staging area on flash, and a stored blob staged at boot.

use crate::staging::{FlashStaging, Staged as StagedBytes};

/// A staging sector: byte writes, one erase unit holding the largest image.
type StagingFlash = Mock<4096, 1, 1>;

fn staging_flash() -> FlashStaging<StagingFlash> {
    FlashStaging::new(Some(StagingFlash::blank(4096)))
}

#[test]
fn staging_on_flash_erases_writes_in_order_and_reads_back() {
    let mut st = staging_flash();
    assert!(st.is_present());
    st.erase().unwrap();
    st.write(0, b"abc").unwrap();
    st.write(3, b"def").unwrap();
    let mut six = [0u8; 6];
    st.read(0, &mut six).unwrap();
    assert_eq!(&six, b"abcdef");
    // Past the largest image: refused, not a panic.
    assert_eq!(
        st.write(crate::image::MAX_BYTES, b"x"),
        Err(StagingError::OutOfBounds)
    );
    // A second transfer erases first (the mock refuses a write twice without one).
    st.erase().unwrap();
    st.write(0, b"xyz").unwrap();
    st.read(0, &mut six[..3]).unwrap();
    assert_eq!(&six[..3], b"xyz");
}

#[test]
fn staging_refuses_missing_small_or_word_written_flash_by_name() {
    let mut none = FlashStaging::<StagingFlash>::new(None);
    assert!(!none.is_present());
    assert_eq!(none.erase(), Err(StagingError::Missing));
    assert_eq!(none.write(0, b"x"), Err(StagingError::Missing));
    assert_eq!(none.read(0, &mut [0]), Err(StagingError::Missing));
    // Smaller than the largest image.
    let small = FlashStaging::new(Some(Mock::<1024, 1, 1>::blank(2048)));
    assert!(!small.is_present());
    // Word writes: a chunk of odd length could not be programmed in place.
    let words = FlashStaging::new(Some(Mock::<4096, 4, 4>::blank(4096)));
    assert!(!words.is_present());
    // A dead flash fails by name.
    let mut dead = StagingFlash::blank(4096);
    dead.off = true;
    let mut dead = FlashStaging::new(Some(dead));
    assert_eq!(dead.erase(), Err(StagingError::Flash));
}

#[test]
fn a_blob_saved_from_staging_is_the_staged_bytes() {
    let (settings, blob) = contents(3, 100, 900);
    let mut st = staging_flash();
    st.erase().unwrap();
    st.write(0, &blob).unwrap();
    let mut f = Small::blank(SMALL);
    let r = save_from(
        &mut f,
        &settings,
        &mut StagedBytes::new(&mut st, blob.len()),
    )
    .unwrap();
    assert_eq!(r.blob_len, 900);
    assert_eq!(
        load_rec(&mut f),
        Some(Rec {
            seq: 1,
            settings,
            blob
        })
    );
}

#[test]
fn a_stored_blob_is_staged_once_and_then_found_in_place() {
    let (settings, blob) = contents(4, 120, 1500);
    let mut f = Small::blank(SMALL);
    save(&mut f, &settings, &blob).unwrap();
    let mut buf = [0u8; 256];
    let r = load_settings(&mut f, &mut buf).unwrap().unwrap();
    assert_eq!(&buf[..r.settings_len], &settings[..]);
    let mut st = staging_flash();
    // Blank staging: copied (an erase), and the bytes are the blob's.
    assert_eq!(stage_blob(&mut f, &r, &mut st), Ok(Staged::Copied));
    let staged = crate::staging::read_all(&mut StagedBytes::new(&mut st, r.blob_len)).unwrap();
    assert_eq!(staged, blob);
    // Already there: no erase (the mock would refuse the rewrite anyway).
    assert_eq!(stage_blob(&mut f, &r, &mut st), Ok(Staged::Already));
    // Another image staged since (an unsaved transfer): copied back.
    st.erase().unwrap();
    st.write(0, &[0u8; 10]).unwrap();
    assert_eq!(stage_blob(&mut f, &r, &mut st), Ok(Staged::Copied));
}

#[test]
fn staging_a_changed_record_or_into_a_dead_area_is_refused() {
    let (settings, blob) = contents(5, 50, 700);
    let mut f = Small::blank(SMALL);
    save(&mut f, &settings, &blob).unwrap();
    let r = load_settings(&mut f, &mut [0u8; 64]).unwrap().unwrap();
    // A flipped blob byte after the load: the record no longer passes its CRC.
    let mut flipped = f.reboot();
    let at = HEADER_BYTES + 50 + 3;
    flipped.mem[at] ^= 0x10;
    assert_eq!(
        stage_blob(&mut flipped, &r, &mut staging_flash()),
        Err(StorageError::Changed)
    );
    let mut none = FlashStaging::<StagingFlash>::new(None);
    assert_eq!(
        stage_blob(&mut f, &r, &mut none),
        Err(StorageError::Staging(StagingError::Missing))
    );
}
