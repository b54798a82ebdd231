//! The calibration blob: every model's parameters in fixed point, versioned and checksummed, as
//! `hil-sim calibrate` writes it (`calibration.bin`). The drive loads the image built from it
//! on the host ([`crate::image::from_blob`]): the coefficients, with no `f64` on the drive.
//!
//! Layout (little-endian), version 7 (version 6 had no tracking discount for the belt observer,
//! always 0.95; version 5 had no belt observer; version 4 weighted Model
//! 2 in Model 4 and had ten plays and no slip observer; version 3 weighted Model 1, not Model 2, and had no low-passed current;
//! version 2 recorded only counts/mm and had no Model 4; version 1 had no baselines):
//! ```text
//! 0   magic "BDCB"
//! 4   version u16 (= 7)          6  reserved u16 (= 0)
//! 8   payload length u32        12  CRC-32 (IEEE) of bytes 0..12 followed by the payload
//! 16  payload:
//!     geometry        encoder lines u32, pulley teeth u32, gear ratio f64, belt pitch mm f64:
//!                     the rig it was calibrated on (must match the drive's exactly)
//!     deadband        u32 counts
//!     model1          m, offset, h, h_g, a, b                         6 x i32
//!     model2          m, offset, h, h_g, rate a, rate b, A, B          8 x i32
//!     model3 bands    forward, reverse: n u16, 0 u16, n x (x um i32, y um I16F16)
//!     model3 trans.   forward, reverse: n_d u16, n_g0 u16, d step um I16F16, g0 step um I16F16,
//!                     n_d x n_g0 gaps U11F5 u16
//!     backlash        offset, backlash                                2 x i32 I16F16 um
//!     bidir table     rows u16, 0 u16, x0 um i32, step um I24F8, rows x (forward, reverse)
//!                     I16F16 um
//!     model4          widths um I24F8, plays and forward plays um/mm I16F16   3 x N_OPS x i32
//!                     x_ref um i32, offset um, slope um/mm I16F16
//!                     knot start um i32, knot step um I24F8, knots N_KNOTS x um I16F16
//!                     pitch um I20F12, sin, cos um I16F16, turn um I24F8, sin, cos um,
//!                     um/A I16F16, low-passed um/A I16F16,
//!                     slip observer: load um reverse, forward I16F16, um/A reverse, forward
//!                     I16F16, creep per mm I8F24, limit um, half gap um, weight I16F16,
//!                     belt observer: present u32 (0: none, the rest absent), tick s f64,
//!                     ticks a step u32, weight I16F16, rest reverse, forward um I16F16,
//!                     half travels fast, slow mm f64, fast share I8F24, 22 physics f64
//!                     (SI, `BeltParams`' order), guide points u32, guide start m, step m f64, points x N f64
//! ```
//! Slopes are I16F16 um per mm, errors I16F16 um, Model 2 rates I8F24 per mm. Decoding checks
//! every length and count before reading and never panics; a blob that fails any check is
//! refused with the reason and changes nothing.

use crate::model::belt::{BeltParams, MAX_GUIDE_BINS};
use crate::model::operator::{N_KNOTS, N_OPS};
use crate::model::BeltTerm;
use crate::model::{
    BacklashParams, BandParams, BidirParams, BidirSource, Model1Params, Model2Params, Model3Params,
    Model3Source, Model4Params, ModelParams, TransitionParams, MAX_BAND_POINTS, MAX_BIDIR_ROWS,
    MAX_TRANSITION_D, MAX_TRANSITION_G0,
};
use crate::rig::Rig;
use crate::staging::Source;
use crate::ConfigError;
use crate::ConfigField;
use belt_link::bytes::{Fields, Reader, Short, Writer};
use belt_link::Crc32;

/// First four bytes of every blob.
pub const MAGIC: [u8; 4] = *b"BDCB";
/// The version this code writes and reads.
pub const VERSION: u16 = 7;
const HEADER: usize = 16;
const BAND_BYTES: usize = 4 + 8 * MAX_BAND_POINTS;
const TRANSITION_BYTES: usize = 12 + 2 * MAX_TRANSITION_D * MAX_TRANSITION_G0;
const BIDIR_BYTES: usize = 12 + 8 * MAX_BIDIR_ROWS;
/// Largest size of Model 4's section (the last): 3 words per play, 5 for the band line and the
/// knot grid, the knots, 8 for the two harmonics, the current and its low pass, 8 for the slip
/// observer, and the belt observer with a full guide profile.
pub const MODEL4_BYTES: usize = 4 * (3 * N_OPS + 5 + N_KNOTS + 8 + 8) + BELT_BYTES;
/// Size of Model 4's section without a belt observer (its presence word only).
pub const MODEL4_NO_BELT_BYTES: usize = 4 * (3 * N_OPS + 5 + N_KNOTS + 8 + 8) + 4;
/// Model 4's belt observer: presence, tick, step and weight, 22 physics and the guide
/// profile's count, start, step and points.
const BELT_BYTES: usize = 4 + 8 + 4 + 4 + 8 + 16 + 4 + 8 * 22 + 4 + 16 + 8 * MAX_GUIDE_BINS;
const RIG_BYTES: usize = 24;
/// Largest blob: header, rig and dead band, Models 1 and 2, two full bands, two full tables,
/// backlash and a full bidirectional table.
pub const MAX_BYTES: usize = HEADER
    + RIG_BYTES
    + 4
    + 4 * 6
    + 4 * 8
    + 2 * BAND_BYTES
    + 2 * TRANSITION_BYTES
    + 8
    + BIDIR_BYTES
    + MODEL4_BYTES;

/// Why a blob was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlobError {
    /// Shorter than its header, or than its header says.
    Truncated,
    /// Longer than `MAX_BYTES` or than its header says.
    TooLong,
    /// Not a calibration blob.
    BadMagic,
    /// Written by another version of the format.
    UnsupportedVersion(u16),
    /// The CRC does not match: corrupted in transit or storage.
    BadChecksum,
    /// Calibrated on a rig with another counts-per-mm.
    RigMismatch,
    /// Its belt observer was built for another control rate than the drive's.
    RateMismatch,
    /// A table count is out of bounds.
    BadCount(ConfigField),
    /// A value failed the models' own checks.
    Invalid(ConfigError),
    /// The drive is moving: calibrations load at rest.
    Busy,
    /// The output buffer is too small (encoding only).
    BufferTooSmall,
    /// A value does not fit the blob's fixed-point format (encoding only).
    Unrepresentable(ConfigField),
    /// The stored bytes could not be read (the staging flash failed).
    Unreadable,
}

impl core::fmt::Display for BlobError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            BlobError::Truncated => f.write_str("calibration blob truncated"),
            BlobError::TooLong => f.write_str("calibration blob longer than its header says"),
            BlobError::BadMagic => f.write_str("not a calibration blob (bad magic)"),
            BlobError::UnsupportedVersion(v) => {
                write!(f, "calibration blob version {v} is not supported")
            }
            BlobError::BadChecksum => f.write_str("calibration blob checksum mismatch"),
            BlobError::RigMismatch => {
                f.write_str("calibration blob is for another rig (counts per mm differ)")
            }
            BlobError::RateMismatch => f.write_str(
                "calibration blob's belt observer is for another control rate (drive.rate_hz)",
            ),
            BlobError::BadCount(x) => write!(f, "calibration blob: {x} out of bounds"),
            BlobError::Invalid(e) => write!(f, "calibration blob: {e}"),
            BlobError::Busy => f.write_str("calibration refused: the drive is moving"),
            BlobError::BufferTooSmall => f.write_str("output buffer too small for the blob"),
            BlobError::Unrepresentable(x) => write!(f, "{x} does not fit the blob format"),
            BlobError::Unreadable => f.write_str("the staged calibration could not be read"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for BlobError {}

/// The blob's CRC-32 over `chunks` in order: the link's CRC (`belt_link::Crc32`, IEEE, as
/// zlib), one implementation for both.
pub fn crc32(chunks: &[&[u8]]) -> u32 {
    let mut c = Crc32::new();
    for chunk in chunks {
        c.update(chunk);
    }
    c.finish()
}

pub(crate) fn write_rig(w: &mut Writer, rig: &Rig) {
    w.u32(rig.encoder_lines);
    w.u32(rig.pulley_teeth);
    w.u64(rig.gear_ratio.to_bits());
    w.u64(rig.belt_pitch_mm.to_bits());
}

pub(crate) fn read_rig(r: &mut impl Fields) -> Result<Rig, BlobError> {
    Ok(Rig {
        encoder_lines: r.u32()?,
        pulley_teeth: r.u32()?,
        gear_ratio: f64::from_bits(r.u64()?),
        belt_pitch_mm: f64::from_bits(r.u64()?),
    })
}

/// The geometry a blob was calibrated for, read after its header and checksum are checked
/// (to say which rig a refused blob belongs to).
pub fn calibrated_rig(blob: &[u8]) -> Result<Rig, BlobError> {
    check_header(blob)?;
    read_rig(&mut Reader::new(&blob[HEADER..]))
}

impl From<Short> for BlobError {
    fn from(_: Short) -> Self {
        BlobError::Truncated
    }
}

/// The blob's fixed-point fields on the shared reader and writer.
trait ReadFixed {
    /// An `i32` read as a value with `frac` fraction bits.
    fn fixed(&mut self, frac: u32) -> Result<f64, BlobError>;
}

impl ReadFixed for Reader<'_> {
    fn fixed(&mut self, frac: u32) -> Result<f64, BlobError> {
        Ok(self.i32()? as f64 / (1u64 << frac) as f64)
    }
}

trait WriteFixed {
    /// `v * 2^frac` rounded to an i32, or `Unrepresentable(field)`.
    fn fixed(&mut self, v: f64, frac: u32, field: ConfigField) -> Result<(), BlobError>;
}

impl WriteFixed for Writer<'_> {
    fn fixed(&mut self, v: f64, frac: u32, field: ConfigField) -> Result<(), BlobError> {
        let q = v * (1u64 << frac) as f64;
        let q = if q >= 0.0 { q + 0.5 } else { q - 0.5 };
        if !(q.is_finite() && q >= i32::MIN as f64 && q <= i32::MAX as f64) {
            return Err(BlobError::Unrepresentable(field));
        }
        self.i32(q as i32);
        Ok(())
    }
}

const Q16: u32 = 16;
const Q24: u32 = 24;

/// Writes `params` for `rig` into `buf`; returns the blob's length. The parameters are quantised
/// to the blob's formats: load the decoded blob on the host too, so host and firmware agree.
pub fn encode(params: &ModelParams, rig: &Rig, buf: &mut [u8]) -> Result<usize, BlobError> {
    params.build(rig).map_err(BlobError::Invalid)?;
    let mut w = Writer::at(&mut *buf, HEADER);
    write_rig(&mut w, rig);
    w.u32(params.reversal_deadband_counts);
    let m1 = &params.model1;
    w.fixed(m1.m_mm_per_mm * 1000.0, Q16, ConfigField::Model1MMmPerMm)?;
    w.fixed(m1.offset_mm * 1000.0, Q16, ConfigField::Model1OffsetMm)?;
    w.fixed(m1.h_mm * 1000.0, Q16, ConfigField::Model1HMm)?;
    w.fixed(m1.h_g_mm * 1000.0, Q16, ConfigField::Model1HGMm)?;
    w.fixed(
        m1.slope_a_mm_per_mm * 1000.0,
        Q16,
        ConfigField::Model1SlopeAMmPerMm,
    )?;
    w.fixed(
        m1.slope_b_mm_per_mm * 1000.0,
        Q16,
        ConfigField::Model1SlopeBMmPerMm,
    )?;
    let m2 = &params.model2;
    w.fixed(m2.m_mm_per_mm * 1000.0, Q16, ConfigField::Model2MMmPerMm)?;
    w.fixed(m2.offset_mm * 1000.0, Q16, ConfigField::Model2OffsetMm)?;
    w.fixed(m2.h_mm * 1000.0, Q16, ConfigField::Model2HMm)?;
    w.fixed(m2.h_g_mm * 1000.0, Q16, ConfigField::Model2HGMm)?;
    w.fixed(m2.rate_a_per_mm, Q24, ConfigField::Model2RateAPerMm)?;
    w.fixed(m2.rate_b_per_mm, Q24, ConfigField::Model2RateBPerMm)?;
    w.fixed(
        m2.amplitude_a_mm * 1000.0,
        Q16,
        ConfigField::Model2AmplitudeAMm,
    )?;
    w.fixed(
        m2.amplitude_b_mm * 1000.0,
        Q16,
        ConfigField::Model2AmplitudeBMm,
    )?;
    let m3 = &params.model3;
    for (band, name) in [
        (&m3.forward_band, ConfigField::Model3ForwardBand),
        (&m3.reverse_band, ConfigField::Model3ReverseBand),
    ] {
        let n = band.len.min(MAX_BAND_POINTS);
        w.u16(n as u16);
        w.u16(0);
        for i in 0..n {
            w.fixed(band.x_mm[i] * 1000.0, 0, name)?;
            w.fixed(band.y_um[i], Q16, name)?;
        }
    }
    for (t, name) in [
        (&m3.forward_transition, ConfigField::Model3ForwardTransition),
        (&m3.reverse_transition, ConfigField::Model3ReverseTransition),
    ] {
        let (nd, ng) = (t.n_d.min(MAX_TRANSITION_D), t.n_g0.min(MAX_TRANSITION_G0));
        w.u16(nd as u16);
        w.u16(ng as u16);
        w.fixed(t.d_step_mm * 1000.0, Q16, name)?;
        w.fixed(t.g0_step_um, Q16, name)?;
        for row in t.gap_um.iter().take(nd) {
            for &g in row.iter().take(ng) {
                let q = g * 32.0 + 0.5;
                if !(q >= 0.0 && q <= u16::MAX as f64) {
                    return Err(BlobError::Unrepresentable(name));
                }
                w.u16(q as u16);
            }
        }
    }
    w.fixed(
        params.backlash.offset_um,
        Q16,
        ConfigField::BacklashOffsetUm,
    )?;
    w.fixed(
        params.backlash.backlash_um,
        Q16,
        ConfigField::BacklashBacklashUm,
    )?;
    let t = &params.bidir_table;
    let rows = t.rows.min(MAX_BIDIR_ROWS);
    w.u16(rows as u16);
    w.u16(0);
    w.fixed(t.x0_mm * 1000.0, 0, ConfigField::BidirTableX0Mm)?;
    w.fixed(t.step_mm * 1000.0, 8, ConfigField::BidirTableStepMm)?;
    for i in 0..rows {
        w.fixed(t.forward_um[i], Q16, ConfigField::BidirTableForwardUm)?;
        w.fixed(t.reverse_um[i], Q16, ConfigField::BidirTableReverseUm)?;
    }
    write_model4(&mut w, &params.model4)?;
    let len = w.finish().map_err(|_| BlobError::BufferTooSmall)?;
    seal(buf, len, MAGIC, VERSION);
    Ok(len)
}

/// Writes the header of a blob or image whose payload is `buf[16..len]` (`len >= 16`).
pub(crate) fn seal(buf: &mut [u8], len: usize, magic: [u8; 4], version: u16) {
    let mut head = [0u8; 12];
    let mut w = Writer::new(&mut head);
    w.put(&magic);
    w.u16(version);
    w.u16(0); // reserved
    w.u32((len - HEADER) as u32);
    // Twelve bytes of fields into twelve: cannot fall short.
    let _ = w.finish();
    let crc = crc32(&[&head, &buf[HEADER..len]]);
    let mut w = Writer::new(&mut buf[..HEADER]);
    w.put(&head);
    w.u32(crc);
    let _ = w.finish();
}

/// A checked blob: Models 1 and 2 read out, Model 3's tables left in place in the bytes.
struct Parsed<'a> {
    deadband: u32,
    model1: Model1Params,
    model2: Model2Params,
    model3: BlobModel3<'a>,
    backlash: BacklashParams,
    bidir: BlobBidir<'a>,
    model4: Model4Params,
}

/// The bidirectional table read straight from a checked blob.
struct BlobBidir<'a> {
    rows: usize,
    x0_mm: f64,
    step_mm: f64,
    /// Rows of (forward, reverse), 8 bytes each.
    values: &'a [u8],
}

impl BidirSource for BlobBidir<'_> {
    fn shape(&self) -> (usize, f64, f64) {
        (self.rows, self.x0_mm, self.step_mm)
    }
    fn value_um(&self, dir: usize, i: usize) -> f64 {
        if i >= self.rows {
            return f64::NAN;
        }
        le_i32(self.values, 8 * i + 4 * (dir & 1)) as f64 / 65536.0
    }
}

/// Model 3's tables read straight from a checked blob.
struct BlobModel3<'a> {
    /// Per direction: the points, 8 bytes each.
    bands: [&'a [u8]; 2],
    /// Per direction: `(n_d, n_g0, d_step_mm, g0_step_um)` and the cells, 2 bytes each.
    shapes: [(usize, usize, f64, f64); 2],
    gaps: [&'a [u8]; 2],
}

fn le_i32(b: &[u8], at: usize) -> i32 {
    match b.get(at..at + 4) {
        Some(s) => i32::from_le_bytes([s[0], s[1], s[2], s[3]]),
        None => 0,
    }
}

impl Model3Source for BlobModel3<'_> {
    fn band_len(&self, dir: usize) -> usize {
        self.bands[dir & 1].len() / 8
    }
    fn band_point(&self, dir: usize, i: usize) -> (f64, f64) {
        let b = self.bands[dir & 1];
        (
            le_i32(b, 8 * i) as f64 / 1000.0,
            le_i32(b, 8 * i + 4) as f64 / 65536.0,
        )
    }
    fn transition_shape(&self, dir: usize) -> (usize, usize, f64, f64) {
        self.shapes[dir & 1]
    }
    fn gap_um(&self, dir: usize, i: usize, j: usize) -> f64 {
        let n_g0 = self.shapes[dir & 1].1;
        let at = 2 * (i * n_g0 + j);
        match self.gaps[dir & 1].get(at..at + 2) {
            Some(s) => u16::from_le_bytes([s[0], s[1]]) as f64 / 32.0,
            None => f64::NAN,
        }
    }
}

/// Checks the header, the lengths and the checksum.
fn check_header(blob: &[u8]) -> Result<(), BlobError> {
    check_header_of(blob, MAGIC, VERSION, MAX_BYTES)
}

/// Checks the header of a blob or image (`magic`, `version`, at most `max` bytes), the lengths
/// and the checksum.
pub(crate) fn check_header_of(
    blob: &[u8],
    magic: [u8; 4],
    version: u16,
    max: usize,
) -> Result<(), BlobError> {
    check_header_from(&mut { blob }, magic, version, max)
}

/// [`check_header_of`] for bytes read from `src` in small pieces (the drive's staging flash);
/// a source that cannot be read is [`BlobError::Unreadable`].
pub(crate) fn check_header_from(
    src: &mut dyn Source,
    magic: [u8; 4],
    version: u16,
    max: usize,
) -> Result<(), BlobError> {
    let len = src.len();
    if len < HEADER {
        return Err(BlobError::Truncated);
    }
    if len > max {
        return Err(BlobError::TooLong);
    }
    let mut head = [0u8; HEADER];
    src.read_at(0, &mut head)
        .map_err(|_| BlobError::Unreadable)?;
    let mut r = Reader::new(&head);
    if r.take::<4>()? != magic {
        return Err(BlobError::BadMagic);
    }
    let found = r.u16()?;
    r.u16()?;
    let payload_len = r.u32()? as usize;
    let crc = r.u32()?;
    if found != version {
        return Err(BlobError::UnsupportedVersion(found));
    }
    let total = HEADER.saturating_add(payload_len);
    if len < total {
        return Err(BlobError::Truncated);
    }
    if len > total {
        return Err(BlobError::TooLong);
    }
    let mut sum = Crc32::new();
    sum.update(&head[..12]);
    crate::staging::crc32_from(src, HEADER, &mut sum).map_err(|_| BlobError::Unreadable)?;
    if sum.finish() != crc {
        return Err(BlobError::BadChecksum);
    }
    Ok(())
}

fn parse<'a>(blob: &'a [u8], rig: &Rig) -> Result<Parsed<'a>, BlobError> {
    check_header(blob)?;
    let mut r = Reader::new(&blob[HEADER..]);
    if read_rig(&mut r)? != *rig {
        return Err(BlobError::RigMismatch);
    }
    let deadband = r.u32()?;
    let um = |v: f64| v / 1000.0;
    let model1 = Model1Params {
        m_mm_per_mm: um(r.fixed(Q16)?),
        offset_mm: um(r.fixed(Q16)?),
        h_mm: um(r.fixed(Q16)?),
        h_g_mm: um(r.fixed(Q16)?),
        slope_a_mm_per_mm: um(r.fixed(Q16)?),
        slope_b_mm_per_mm: um(r.fixed(Q16)?),
    };
    let model2 = Model2Params {
        m_mm_per_mm: um(r.fixed(Q16)?),
        offset_mm: um(r.fixed(Q16)?),
        h_mm: um(r.fixed(Q16)?),
        h_g_mm: um(r.fixed(Q16)?),
        rate_a_per_mm: r.fixed(Q24)?,
        rate_b_per_mm: r.fixed(Q24)?,
        amplitude_a_mm: um(r.fixed(Q16)?),
        amplitude_b_mm: um(r.fixed(Q16)?),
    };
    let mut bands: [&[u8]; 2] = [&[], &[]];
    for (dir, name) in [
        ConfigField::Model3ForwardBand,
        ConfigField::Model3ReverseBand,
    ]
    .into_iter()
    .enumerate()
    {
        let n = r.u16()? as usize;
        r.u16()?;
        if n > MAX_BAND_POINTS {
            return Err(BlobError::BadCount(name));
        }
        bands[dir] = r.slice(8 * n)?;
    }
    let mut shapes = [(0, 0, 0.0, 0.0); 2];
    let mut gaps: [&[u8]; 2] = [&[], &[]];
    for (dir, name) in [
        ConfigField::Model3ForwardTransition,
        ConfigField::Model3ReverseTransition,
    ]
    .into_iter()
    .enumerate()
    {
        let (nd, ng) = (r.u16()? as usize, r.u16()? as usize);
        if nd > MAX_TRANSITION_D || ng > MAX_TRANSITION_G0 {
            return Err(BlobError::BadCount(name));
        }
        let d_step_mm = r.fixed(Q16)? / 1000.0;
        let g0_step_um = r.fixed(Q16)?;
        shapes[dir] = (nd, ng, d_step_mm, g0_step_um);
        gaps[dir] = r.slice(2 * nd * ng)?;
    }
    let backlash = BacklashParams {
        offset_um: r.fixed(Q16)?,
        backlash_um: r.fixed(Q16)?,
    };
    let rows = r.u16()? as usize;
    r.u16()?;
    if !(2..=MAX_BIDIR_ROWS).contains(&rows) {
        return Err(BlobError::BadCount(ConfigField::BidirTableRows));
    }
    let x0_mm = r.fixed(0)? / 1000.0;
    let step_mm = r.fixed(8)? / 1000.0;
    let bidir = BlobBidir {
        rows,
        x0_mm,
        step_mm,
        values: r.slice(8 * rows)?,
    };
    let model4 = read_model4(&mut r)?;
    if r.remaining() != 0 {
        return Err(BlobError::TooLong);
    }
    Ok(Parsed {
        deadband,
        model1,
        model2,
        model3: BlobModel3 {
            bands,
            shapes,
            gaps,
        },
        backlash,
        bidir,
        model4,
    })
}

/// Checks and decodes a blob for a drive on `rig` into `f64` parameters (host tools).
pub fn decode(blob: &[u8], rig: &Rig) -> Result<ModelParams, BlobError> {
    let p = parse(blob, rig)?;
    let mut model3 = Model3Params {
        forward_band: BandParams::EMPTY,
        reverse_band: BandParams::EMPTY,
        forward_transition: TransitionParams::EMPTY,
        reverse_transition: TransitionParams::EMPTY,
    };
    for dir in 0..2 {
        let band = if dir == 0 {
            &mut model3.forward_band
        } else {
            &mut model3.reverse_band
        };
        band.len = p.model3.band_len(dir);
        for i in 0..band.len {
            (band.x_mm[i], band.y_um[i]) = p.model3.band_point(dir, i);
        }
        let t = if dir == 0 {
            &mut model3.forward_transition
        } else {
            &mut model3.reverse_transition
        };
        (t.n_d, t.n_g0, t.d_step_mm, t.g0_step_um) = p.model3.transition_shape(dir);
        for i in 0..t.n_d {
            for j in 0..t.n_g0 {
                t.gap_um[i][j] = p.model3.gap_um(dir, i, j);
            }
        }
    }
    let mut bidir_table = BidirParams::ZERO;
    (bidir_table.rows, bidir_table.x0_mm, bidir_table.step_mm) = p.bidir.shape();
    for i in 0..bidir_table.rows {
        bidir_table.forward_um[i] = p.bidir.value_um(0, i);
        bidir_table.reverse_um[i] = p.bidir.value_um(1, i);
    }
    let params = ModelParams {
        model1: p.model1,
        model2: p.model2,
        model3,
        model4: p.model4,
        backlash: p.backlash,
        bidir_table,
        reversal_deadband_counts: p.deadband,
    };
    params.build(rig).map_err(BlobError::Invalid)?;
    Ok(params)
}

/// Model 4's section (the last one).
fn write_model4(w: &mut Writer<'_>, m4: &Model4Params) -> Result<(), BlobError> {
    for v in m4.widths_mm {
        w.fixed(v * 1000.0, 8, ConfigField::Model4WidthsMm)?;
    }
    for v in m4.play_um_per_mm {
        w.fixed(v, Q16, ConfigField::Model4PlayUmPerMm)?;
    }
    for v in m4.play_forward_um_per_mm {
        w.fixed(v, Q16, ConfigField::Model4PlayForwardUmPerMm)?;
    }
    w.fixed(m4.x_ref_mm * 1000.0, 0, ConfigField::Model4XRefMm)?;
    w.fixed(m4.offset_um, Q16, ConfigField::Model4OffsetUm)?;
    w.fixed(m4.slope_um_per_mm, Q16, ConfigField::Model4SlopeUmPerMm)?;
    w.fixed(m4.knot_start_mm * 1000.0, 0, ConfigField::Model4KnotStartMm)?;
    w.fixed(m4.knot_step_mm * 1000.0, 8, ConfigField::Model4KnotStepMm)?;
    for v in m4.knot_um {
        w.fixed(v, Q16, ConfigField::Model4KnotUm)?;
    }
    w.fixed(m4.pitch_mm * 1000.0, 12, ConfigField::Model4PitchMm)?;
    w.fixed(m4.pitch_um[0], Q16, ConfigField::Model4PitchUm)?;
    w.fixed(m4.pitch_um[1], Q16, ConfigField::Model4PitchUm)?;
    w.fixed(m4.turn_mm * 1000.0, 8, ConfigField::Model4TurnMm)?;
    w.fixed(m4.turn_um[0], Q16, ConfigField::Model4TurnUm)?;
    w.fixed(m4.turn_um[1], Q16, ConfigField::Model4TurnUm)?;
    w.fixed(m4.current_um_per_a, Q16, ConfigField::Model4CurrentUmPerA)?;
    w.fixed(
        m4.current_lp_um_per_a,
        Q16,
        ConfigField::Model4CurrentLpUmPerA,
    )?;
    let sl = &m4.slip;
    for v in sl.load_um {
        w.fixed(v, Q16, ConfigField::Model4SlipLoadUm)?;
    }
    for v in sl.um_per_a {
        w.fixed(v, Q16, ConfigField::Model4SlipUmPerA)?;
    }
    w.fixed(sl.creep_per_mm, 24, ConfigField::Model4SlipCreepPerMm)?;
    w.fixed(sl.limit_um, Q16, ConfigField::Model4SlipLimitUm)?;
    w.fixed(sl.half_gap_um, Q16, ConfigField::Model4SlipHalfGapUm)?;
    w.fixed(sl.weight, Q16, ConfigField::Model4SlipWeight)?;
    write_belt(w, m4.belt.as_ref())
}

/// [`BeltParams`]'s 22 scalars, in the blob's order.
fn belt_scalars(p: &mut BeltParams) -> [&mut f64; 22] {
    [
        &mut p.mass_kg,
        &mut p.guide_n,
        &mut p.preload_n,
        &mut p.axial_rigidity_n,
        &mut p.length_m,
        &mut p.span_offset_m,
        &mut p.wrap_rad,
        &mut p.sigma0_per_m,
        &mut p.sigma1_s_per_m,
        &mut p.sigma2_s_per_m,
        &mut p.mu_static,
        &mut p.mu_kinetic,
        &mut p.stribeck_m_per_s,
        &mut p.kappa_per_m,
        &mut p.half_gap_m,
        &mut p.tooth_n_per_m,
        &mut p.gear_half_m,
        &mut p.gear_n_per_m,
        &mut p.span_damping_n_s_per_m,
        &mut p.accel_per_a,
        &mut p.m_per_count,
        &mut p.track_discount,
    ]
}

/// Model 4's belt observer: a presence word, then its physics as `f64` (the identification's
/// values exactly; the image's builder checks them) and its weight in Q16.
fn write_belt(w: &mut Writer<'_>, belt: Option<&BeltTerm>) -> Result<(), BlobError> {
    let Some(b) = belt else {
        w.u32(0);
        return Ok(());
    };
    if b.physics.guide_bins > MAX_GUIDE_BINS {
        return Err(BlobError::Invalid(ConfigError::TableSize(
            ConfigField::Model4BeltGuideProfileN,
        )));
    }
    w.u32(1);
    w.u64(b.tick_s.to_bits());
    w.u32(b.step_ticks);
    w.fixed(b.weight, Q16, ConfigField::Model4BeltWeight)?;
    w.fixed(b.rest_um[0], Q16, ConfigField::Model4BeltRestUm)?;
    w.fixed(b.rest_um[1], Q16, ConfigField::Model4BeltRestUm)?;
    w.u64(b.half_travel_mm[0].to_bits());
    w.u64(b.half_travel_mm[1].to_bits());
    w.fixed(b.fast_share, Q24, ConfigField::Model4BeltFastShare)?;
    let mut p = b.physics;
    for v in belt_scalars(&mut p) {
        w.u64(v.to_bits());
    }
    w.u32(p.guide_bins as u32);
    w.u64(p.guide_start_m.to_bits());
    w.u64(p.guide_step_m.to_bits());
    for v in &p.guide_delta_n[..p.guide_bins] {
        w.u64(v.to_bits());
    }
    Ok(())
}

fn read_belt(r: &mut Reader<'_>) -> Result<Option<BeltTerm>, BlobError> {
    match r.u32()? {
        0 => return Ok(None),
        1 => {}
        _ => {
            return Err(BlobError::Invalid(ConfigError::OutOfRange(
                ConfigField::Model4BeltStepTicks,
            )))
        }
    }
    let f64_ = |r: &mut Reader<'_>| -> Result<f64, BlobError> { Ok(f64::from_bits(r.u64()?)) };
    let tick_s = f64_(r)?;
    let step_ticks = r.u32()?;
    let weight = r.fixed(Q16)?;
    let rest_um = [r.fixed(Q16)?, r.fixed(Q16)?];
    let half_travel_mm = [f64_(r)?, f64_(r)?];
    let fast_share = r.fixed(Q24)?;
    let mut physics = BeltParams::PAPER;
    for v in belt_scalars(&mut physics) {
        *v = f64_(r)?;
    }
    let bins = r.u32()? as usize;
    if bins > MAX_GUIDE_BINS {
        return Err(BlobError::Invalid(ConfigError::TableSize(
            ConfigField::Model4BeltGuideProfileN,
        )));
    }
    physics.guide_bins = bins;
    physics.guide_start_m = f64_(r)?;
    physics.guide_step_m = f64_(r)?;
    for v in physics.guide_delta_n[..bins].iter_mut() {
        *v = f64_(r)?;
    }
    Ok(Some(BeltTerm {
        physics,
        tick_s,
        step_ticks,
        weight,
        rest_um,
        half_travel_mm,
        fast_share,
    }))
}

fn read_model4(r: &mut Reader<'_>) -> Result<Model4Params, BlobError> {
    let mut model4 = Model4Params::zero(0.0, 0.0);
    for v in model4.widths_mm.iter_mut() {
        *v = r.fixed(8)? / 1000.0;
    }
    for v in model4.play_um_per_mm.iter_mut() {
        *v = r.fixed(Q16)?;
    }
    for v in model4.play_forward_um_per_mm.iter_mut() {
        *v = r.fixed(Q16)?;
    }
    model4.x_ref_mm = r.fixed(0)? / 1000.0;
    model4.offset_um = r.fixed(Q16)?;
    model4.slope_um_per_mm = r.fixed(Q16)?;
    model4.knot_start_mm = r.fixed(0)? / 1000.0;
    model4.knot_step_mm = r.fixed(8)? / 1000.0;
    for v in model4.knot_um.iter_mut() {
        *v = r.fixed(Q16)?;
    }
    model4.pitch_mm = r.fixed(12)? / 1000.0;
    model4.pitch_um = [r.fixed(Q16)?, r.fixed(Q16)?];
    model4.turn_mm = r.fixed(8)? / 1000.0;
    model4.turn_um = [r.fixed(Q16)?, r.fixed(Q16)?];
    model4.current_um_per_a = r.fixed(Q16)?;
    model4.current_lp_um_per_a = r.fixed(Q16)?;
    let sl = &mut model4.slip;
    sl.load_um = [r.fixed(Q16)?, r.fixed(Q16)?];
    sl.um_per_a = [r.fixed(Q16)?, r.fixed(Q16)?];
    sl.creep_per_mm = r.fixed(24)?;
    sl.limit_um = r.fixed(Q16)?;
    sl.half_gap_um = r.fixed(Q16)?;
    sl.weight = r.fixed(Q16)?;
    model4.belt = read_belt(r)?;
    Ok(model4)
}

/// Model 4's parameters as a blob holds them (its formats' rounding), for a calibration that
/// must compute its features from the geometry the drive will use.
pub fn quantise_model4(m4: &Model4Params) -> Result<Model4Params, BlobError> {
    let mut buf = [0u8; MODEL4_BYTES];
    let mut w = Writer::new(&mut buf);
    write_model4(&mut w, m4)?;
    w.finish().map_err(|_| BlobError::BufferTooSmall)?;
    read_model4(&mut Reader::new(&buf))
}
