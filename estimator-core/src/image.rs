//! The calibration image: every model's fixed-point coefficients as the drive uses them,
//! versioned and checksummed. The host builds them (`f64`, from a calibration blob's parameters,
//! see [`crate::blob`]) and the drive only reads and checks them, in integers: no floating point
//! on the microcontroller's calibration path. A blob stays the file a calibration writes
//! (`calibration.bin`, parameters for people and tools); [`from_blob`] turns it into the image a
//! drive loads over the link, stores, and boots from.
//!
//! Layout (little-endian), version 8 (version 7 held each harmonic as its sine and cosine
//! amplitudes; version 6 did not record the belt observer's control rate;
//! version 5 had no belt observer; version 4 weighted Model 2 in Model 4 and had ten plays and no
//! slip observer; earlier versions weighted Model 1 and had no low-passed current):
//! ```text
//! 0   magic "BDCI"
//! 4   version u16 (= 8)          6  reserved u16 (= 0)
//! 8   payload length u32        12  CRC-32 (IEEE) of bytes 0..12 followed by the payload
//! 16  payload:
//!     geometry        as in the blob (must match the drive's exactly)
//!     deadband        u32 counts
//!     model1          m I1F31 um/count, offset, h, h_g I16F16 um, slopes a, b I1F31  6 x i32
//!     model2          m, offset, h, h_g, A, B (as Model 1), then per rate: mantissa u32,
//!                     shift u16, 0 u16                                    6 x i32, 2 x 8
//!     model3 bands    forward, reverse: n u16, 0 u16, first point counts i32, points per
//!                     count Q0.32 u32, n x y I16F16 um
//!     model3 trans.   forward, reverse: n_d u16, n_g0 u16, rows per count Q0.32 u32,
//!                     columns per Q16.16 um Q0.32 u32, n_d x n_g0 gaps U11F5 u16
//!     backlash        forward, reverse I16F16 um                          2 x i32
//!     bidir table     rows u16, 0 u16, x0 counts i32, step counts u32,
//!                     rows x (forward, reverse) I13F3 um i16
//!     model4          widths counts, weights reverse, weights forward Q24 um/count
//!                     3 x N_OPS x i32; x_ref counts, offset I16F16, slope Q31 um/count, hat
//!                     start counts, hat reciprocal u32, knots N_KNOTS x I16F16, pitch rate u32,
//!                     amplitude I16F16 (not negative), phase Q32 turns u32, turn rate u32,
//!                     amplitude, phase, um/A, low-passed um/A I16F16,
//!                     slip observer: load reverse, forward, per A reverse, forward I16F16 um,
//!                     kappa per count Q32 u32, um per count I16F16 u32, limit, half gap I16F16
//!                     um, weight Q16,
//!                     belt observer: present u32 (0: none, the rest absent), control rate
//!                     u32 Hz (must be the drive's), weight Q16,
//!                     rest reverse, forward I16F16 um, fast and slow approach per count (as
//!                     Model 2's rates), fast share Q30,
//!                     13 factors (mantissa i32, shift u32), 7 friction and force words i32,
//!                     tooth and damping stiffness u32, gear compliance Q56 u64, guide
//!                     friction Q16, guide points u32, guide start Q16 m, 6 lengths i32,
//!                     guide points x Q16 N, tracking gains 3 x Q32 u64, ticks a step u32
//!     closing         Models 1, 2, 3: forward, reverse I16F16 mm, -1 = never   6 x i32
//!                     (host diagnostics: the drive skips them)
//! ```
//! What the per-tick code derives (reciprocals, spans, total weights) is derived again here, in
//! integers, rather than trusted. Every field is checked against the range its builder
//! guarantees (the per-tick code has no panic path on any value in the release build, and these
//! ranges keep its products within their formats); a refusal names the parameter it came from,
//! as the builders do. What stays with the host builder is the one check
//! that needs the parameters' `f64` interpolation: Model 3's reverse band at or above its forward
//! band (a violation misplaces the estimate, never the drive).

use crate::ConfigField;
use fixed::types::{I13F3, I16F16, I1F31, U11F5};

use crate::blob::{check_header_from, BlobError};
use crate::model::belt::{BeltCoeffs, Gain, GAIN_MAX_SHIFT, MAX_GUIDE_BINS, MAX_STEP_TICKS};
use crate::model::fixmath::{Recip, Scale, MAX_SHIFT};
use crate::model::operator::{Harmonic, FORWARD, N_KNOTS, N_OPS, REVERSE};
use crate::model::slip::{self, SlipCoeffs};
use crate::model::BeltTermCoeffs;
use crate::model::LinearBand;
use crate::model::{
    BacklashCoeffs, BandCoeffs, BidirCoeffs, Model1Coeffs, Model2Coeffs, Model3Coeffs,
    Model4Coeffs, ModelCoeffs, TransitionCoeffs, MAX_ABS_UM, MAX_BAND_POINTS, MAX_BIDIR_ROWS,
    MAX_TRANSITION_D, MAX_TRANSITION_G0,
};
use crate::rig::Rig;
use crate::staging::{Source, Stream};
use crate::ConfigError;
use belt_link::bytes::Fields;

/// First four bytes of every image.
pub const MAGIC: [u8; 4] = *b"BDCI";
/// The version this code writes and reads.
pub const VERSION: u16 = 8;
const HEADER: usize = 16;
const RIG_BYTES: usize = 24;
const BAND_BYTES: usize = 12 + 4 * MAX_BAND_POINTS;
const TRANSITION_BYTES: usize = 12 + 2 * MAX_TRANSITION_D * MAX_TRANSITION_G0;
const BIDIR_BYTES: usize = 12 + 4 * MAX_BIDIR_ROWS;
const MODEL4_BYTES: usize = 4 * (3 * N_OPS + 5 + N_KNOTS + 8 + 9) + BELT_BYTES;
/// Model 4's belt observer: presence, control rate and weight, the rest prediction, 13 factors,
/// 20 words, the guide profile, the tracking gains and the step.
const BELT_BYTES: usize = 12 + 8 + 20 + 13 * 8 + 4 * 20 + 4 * MAX_GUIDE_BINS + 3 * 8 + 4;
/// Largest image: every table full.
pub const MAX_BYTES: usize = HEADER
    + RIG_BYTES
    + 4
    + 4 * 6
    + (4 * 6 + 2 * 8)
    + 2 * BAND_BYTES
    + 2 * TRANSITION_BYTES
    + 8
    + BIDIR_BYTES
    + MODEL4_BYTES
    + 4 * 6;

/// Micrometres in Q16.16 within `[min_um, MAX_ABS_UM]`, as the builders accept them. Not
/// inlined: one copy for the image's many such fields (flash; loading is never per tick).
#[inline(never)]
fn um(r: &mut Stream, min_um: i32, field: ConfigField) -> Result<I16F16, BlobError> {
    let bits = r.i32()?;
    let max = (MAX_ABS_UM as i32) << 16;
    if bits < min_um.saturating_mul(1 << 16) || bits > max {
        return Err(out_of_range(field));
    }
    Ok(I16F16::from_bits(bits))
}

fn out_of_range(field: ConfigField) -> BlobError {
    BlobError::Invalid(ConfigError::OutOfRange(field))
}

/// The lower bound of values that may be negative (`[-MAX_ABS_UM, MAX_ABS_UM]`).
const ANY: i32 = -(MAX_ABS_UM as i32);

/// A band line: any Q1.31 slope, the offset within the range, a height of zero or more.
fn read_band(r: &mut Stream, [c, h]: [ConfigField; 2]) -> Result<LinearBand, BlobError> {
    Ok(LinearBand {
        m_um_per_count: I1F31::from_bits(r.i32()?),
        offset_um: um(r, ANY, c)?,
        h_um: um(r, 0, h)?,
    })
}

fn read_model1(r: &mut Stream) -> Result<Model1Coeffs, BlobError> {
    let band = read_band(r, [ConfigField::Model1OffsetMm, ConfigField::Model1HMm])?;
    let h_g_um = um(r, 0, ConfigField::Model1HGMm)?;
    let mut slope = |field| -> Result<I1F31, BlobError> {
        let s = r.i32()?;
        if s < 0 {
            return Err(out_of_range(field));
        }
        Ok(I1F31::from_bits(s))
    };
    Ok(Model1Coeffs {
        band,
        h_g_um,
        slope_a_um_per_count: slope(ConfigField::Model1SlopeAMmPerMm)?,
        slope_b_um_per_count: slope(ConfigField::Model1SlopeBMmPerMm)?,
        #[cfg(feature = "std")]
        closing: Default::default(),
    })
}

fn read_scale(r: &mut Stream, field: ConfigField) -> Result<Scale, BlobError> {
    let mant = r.u32()?;
    let shift = r.u16()?;
    r.u16()?;
    if shift as i32 > MAX_SHIFT {
        return Err(out_of_range(field));
    }
    Ok(Scale {
        mant,
        shift: shift as u8,
    })
}

fn read_model2(r: &mut Stream) -> Result<Model2Coeffs, BlobError> {
    let band = read_band(r, [ConfigField::Model2OffsetMm, ConfigField::Model2HMm])?;
    Ok(Model2Coeffs {
        band,
        h_g_um: um(r, 0, ConfigField::Model2HGMm)?,
        amp_a_um: um(r, 0, ConfigField::Model2AmplitudeAMm)?,
        amp_b_um: um(r, 0, ConfigField::Model2AmplitudeBMm)?,
        rate_a: read_scale(r, ConfigField::Model2RateAPerMm)?,
        rate_b: read_scale(r, ConfigField::Model2RateBPerMm)?,
        #[cfg(feature = "std")]
        closing: Default::default(),
    })
}

// The tables are read in place, into the caller's coefficients (`None`: checked only): a table
// built by value and moved would put kilobytes on the stack for each copy.

fn read_band_table(
    r: &mut Stream,
    mut out: Option<&mut BandCoeffs>,
    [len_f, x_f, y_f]: [ConfigField; 3],
) -> Result<(), BlobError> {
    let n = r.u16()? as usize;
    r.u16()?;
    if !(2..=MAX_BAND_POINTS).contains(&n) {
        return Err(BlobError::Invalid(ConfigError::TableSize(len_f)));
    }
    let x0_counts = r.i32()?;
    // Steps of two counts or more (as the builder makes them); any start is safe (the tick
    // clamps its distance from it in `i64`).
    let points_q32 = r.u32()?;
    if !(1..=1 << 31).contains(&points_q32) {
        return Err(out_of_range(x_f));
    }
    for i in 0..MAX_BAND_POINTS {
        let y = if i < n {
            um(r, ANY, y_f)?
        } else {
            I16F16::ZERO
        };
        if let Some(b) = out.as_deref_mut() {
            b.y_um[i] = y;
        }
    }
    if let Some(b) = out {
        b.len = n as u8;
        b.x0_counts = x0_counts;
        b.points_q32 = points_q32;
    }
    Ok(())
}

fn read_transition(
    r: &mut Stream,
    mut out: Option<&mut TransitionCoeffs>,
    [nd_f, ng_f, d_f, g_f]: [ConfigField; 4],
) -> Result<(), BlobError> {
    let (n_d, n_g0) = (r.u16()? as usize, r.u16()? as usize);
    if !(2..=MAX_TRANSITION_D).contains(&n_d) {
        return Err(BlobError::Invalid(ConfigError::TableSize(nd_f)));
    }
    if !(2..=MAX_TRANSITION_G0).contains(&n_g0) {
        return Err(BlobError::Invalid(ConfigError::TableSize(ng_f)));
    }
    // Steps of at least two units: at most 2^31 rows (columns) per unit, and at least one.
    let inv = |v: u32, field| {
        if (1..=1 << 31).contains(&v) {
            Ok(v)
        } else {
            Err(out_of_range(field))
        }
    };
    let rows_q32 = inv(r.u32()?, d_f)?;
    let cols_q32 = inv(r.u32()?, g_f)?;
    for i in 0..MAX_TRANSITION_D {
        for j in 0..MAX_TRANSITION_G0 {
            let g = if i < n_d && j < n_g0 {
                U11F5::from_bits(r.u16()?)
            } else {
                U11F5::ZERO
            };
            if let Some(t) = out.as_deref_mut() {
                t.gap_um[i][j] = g;
            }
        }
    }
    if let Some(t) = out {
        t.n_d = n_d as u8;
        t.n_g0 = n_g0 as u8;
        t.rows_q32 = rows_q32;
        t.cols_q32 = cols_q32;
    }
    Ok(())
}

fn read_model3(r: &mut Stream, mut m: Option<&mut Model3Coeffs>) -> Result<(), BlobError> {
    read_band_table(
        r,
        m.as_deref_mut().map(|m| &mut m.forward_band),
        [
            ConfigField::Model3ForwardBandLen,
            ConfigField::Model3ForwardBandXMm,
            ConfigField::Model3ForwardBandYUm,
        ],
    )?;
    read_band_table(
        r,
        m.as_deref_mut().map(|m| &mut m.reverse_band),
        [
            ConfigField::Model3ReverseBandLen,
            ConfigField::Model3ReverseBandXMm,
            ConfigField::Model3ReverseBandYUm,
        ],
    )?;
    read_transition(
        r,
        m.as_deref_mut().map(|m| &mut m.forward_transition),
        [
            ConfigField::Model3ForwardTransitionND,
            ConfigField::Model3ForwardTransitionNG0,
            ConfigField::Model3ForwardTransitionDStepMm,
            ConfigField::Model3ForwardTransitionG0StepUm,
        ],
    )?;
    read_transition(
        r,
        m.map(|m| &mut m.reverse_transition),
        [
            ConfigField::Model3ReverseTransitionND,
            ConfigField::Model3ReverseTransitionNG0,
            ConfigField::Model3ReverseTransitionDStepMm,
            ConfigField::Model3ReverseTransitionG0StepUm,
        ],
    )
}

fn read_bidir(r: &mut Stream, mut out: Option<&mut BidirCoeffs>) -> Result<(), BlobError> {
    let rows = r.u16()? as usize;
    r.u16()?;
    if !(2..=MAX_BIDIR_ROWS).contains(&rows) {
        return Err(out_of_range(ConfigField::BidirTableRows));
    }
    let x0_counts = r.i32()?;
    let step_counts = r.u32()?;
    // A step of one count at least; the span as the builder derives it (saturating: the tick
    // clamps positions to it in `i64`, any value is safe).
    if step_counts == 0 {
        return Err(out_of_range(ConfigField::BidirTableStepMm));
    }
    let span = step_counts.saturating_mul(rows as u32 - 1);
    for i in 0..MAX_BIDIR_ROWS {
        // Any I13F3 is a value the table can hold (+-4096 um).
        let (f, v) = if i < rows {
            (
                I13F3::from_bits(r.u16()? as i16),
                I13F3::from_bits(r.u16()? as i16),
            )
        } else {
            (I13F3::ZERO, I13F3::ZERO)
        };
        if let Some(b) = out.as_deref_mut() {
            b.values[0][i] = f;
            b.values[1][i] = v;
        }
    }
    if let Some(b) = out {
        b.x0_counts = x0_counts;
        b.step_counts = step_counts;
        b.span_counts = span;
        b.step_recip = Recip::new(step_counts);
        b.rows = rows as u16;
    }
    Ok(())
}

fn read_model4(r: &mut Stream, rate_hz: Option<u32>) -> Result<Model4Coeffs, BlobError> {
    let mut widths_counts = [0i32; N_OPS];
    let mut narrower = 0;
    for w in widths_counts.iter_mut() {
        *w = r.i32()?;
        // Narrowest first, one count at least, at most 2^24 (see `Model4Params::build`).
        if !(1..=1 << 24).contains(w) {
            return Err(out_of_range(ConfigField::Model4WidthsMm));
        }
        if *w <= narrower {
            return Err(BlobError::Invalid(ConfigError::NotMonotonic(
                ConfigField::Model4WidthsMm,
            )));
        }
        narrower = *w;
    }
    // Reverse, then forward; the rows of `weight_q24` go by direction.
    let mut rows = [[0i32; N_OPS]; 2];
    for set in rows.iter_mut() {
        for w in set.iter_mut() {
            *w = r.i32()?;
        }
    }
    let mut weight_q24 = [[0i32; N_OPS]; 2];
    (weight_q24[REVERSE], weight_q24[FORWARD]) = (rows[0], rows[1]);
    let x_ref_counts = r.i32()?;
    if x_ref_counts.unsigned_abs() > i32::MAX as u32 / 2 {
        return Err(out_of_range(ConfigField::Model4XRefMm));
    }
    let offset_q31 = (um(r, ANY, ConfigField::Model4OffsetUm)?.to_bits() as i64) << 15;
    let slope_q31 = r.i32()?;
    if slope_q31 == i32::MIN {
        return Err(out_of_range(ConfigField::Model4SlopeUmPerMm));
    }
    let hat_start_counts = r.i32()?;
    if hat_start_counts.unsigned_abs() > 1 << 30 {
        return Err(out_of_range(ConfigField::Model4KnotStartMm));
    }
    // A step of 1..=2^24 counts.
    let hat_recip_q32 = r.u32()?;
    if hat_recip_q32 < 1 << 8 {
        return Err(out_of_range(ConfigField::Model4KnotStepMm));
    }
    let mut knot_um = [I16F16::ZERO; N_KNOTS];
    for k in knot_um.iter_mut() {
        *k = um(r, ANY, ConfigField::Model4KnotUm)?;
    }
    // Periods of 16 counts to 2^31 counts.
    let rate = |r: &mut Stream, field| -> Result<u32, BlobError> {
        let v = r.u32()?;
        if (2..=1 << 28).contains(&v) {
            Ok(v)
        } else {
            Err(out_of_range(field))
        }
    };
    // Amplitude (not negative) and phase (any turn).
    let harmonic = |r: &mut Stream, field| -> Result<Harmonic, BlobError> {
        Ok(Harmonic {
            amp_q17: um(r, 0, field)?.to_bits() << 1,
            phase_q32: r.u32()?,
        })
    };
    let pitch_rate = rate(r, ConfigField::Model4PitchMm)?;
    let pitch = harmonic(r, ConfigField::Model4PitchUm)?;
    let turn_rate = rate(r, ConfigField::Model4TurnMm)?;
    let turn = harmonic(r, ConfigField::Model4TurnUm)?;
    let current_um_per_a = um(r, ANY, ConfigField::Model4CurrentUmPerA)?;
    let current_lp_um_per_a = um(r, ANY, ConfigField::Model4CurrentLpUmPerA)?;
    let slip = read_slip(r)?;
    let belt = read_belt(r, rate_hz)?;
    Ok(Model4Coeffs {
        widths_counts,
        weight_q24,
        x_ref_counts,
        offset_q31,
        slope_q31,
        hat_start_counts,
        hat_recip_q32,
        knot_um,
        pitch_rate,
        pitch,
        turn_rate,
        turn,
        current_um_per_a,
        current_lp_um_per_a,
        slip,
        belt,
    })
}

/// The belt observer's factors in the image's order, each named by the field it comes from.
const BELT_GAINS: [ConfigField; 13] = {
    use ConfigField as F;
    [
        F::Model4BeltMPerCount,
        F::Model4BeltAccelPerA,
        F::Model4BeltSigma0PerM,
        F::Model4BeltSigma1SPerM,
        F::Model4BeltSigma2SPerM,
        F::Model4BeltStribeckMPerS,
        F::Model4BeltKappaPerM,
        F::Model4BeltSpanDampingNSPerM,
        F::Model4BeltMassKg,
        F::Model4BeltToothNPerM,
        F::Model4BeltAxialRigidityN,
        F::Model4BeltLengthM,
        F::Model4BeltGuideProfileStepM,
    ]
};

/// Its friction and force words with the ranges the builder makes: the kinetic coefficient
/// and the static one's excess (Q30, at most 1), `sigma0` and `sigma1 / T` as coefficient per
/// slip (Q8), the wrap (Q28 rad, up to 7), the preload and preload times wrap (Q16 N).
const BELT_WORDS: [(i32, i32, ConfigField); 7] = {
    use ConfigField as F;
    [
        (1, 1 << 30, F::Model4BeltMuKinetic),
        (0, 1 << 30, F::Model4BeltMuStatic),
        (0, i32::MAX, F::Model4BeltSigma0PerM),
        (0, i32::MAX, F::Model4BeltSigma1SPerM),
        (1, 7 << 28, F::Model4BeltWrapRad),
        (1, 4000 << 16, F::Model4BeltPreloadN),
        // At most 4 kN times 7 rad: the capstan's slope stays within 64 bits in the balance.
        (1, 28_000 << 16, F::Model4BeltPreloadN),
    ]
};

/// 10 mm in Q36 m, rounded up.
const BELT_SMALL_Q36: i32 = 687_194_768;

/// Its lengths: half the tooth gap and the gear's half backlash (Q36 m, up to 10 mm), the belt
/// (Q16 m, 3 mm to 100 m), the span from the pulley at 0 (within the belt), the largest slip a
/// step and the tracking filter's jump (Q36 m).
const BELT_LENGTHS: [(i32, i32, ConfigField); 6] = {
    use ConfigField as F;
    [
        (1, BELT_SMALL_Q36, F::Model4BeltHalfGapM),
        (0, BELT_SMALL_Q36, F::Model4BeltGearHalfM),
        (196, 100 << 16, F::Model4BeltLengthM),
        (0, 100 << 16, F::Model4BeltSpanOffsetM),
        (0, BELT_SMALL_Q36, F::DriveRateHz),
        (1, BELT_SMALL_Q36, F::Model4BeltMPerCount),
    ]
};

/// A factor: a non-negative mantissa, a shift of 1 to 31. Inlined into its one loop (flash).
#[inline(always)]
fn read_gain(r: &mut Stream, f: ConfigField) -> Result<Gain, BlobError> {
    let mant = r.i32()?;
    let shift = r.u32()?;
    if mant < 0 || !(1..=u32::from(GAIN_MAX_SHIFT)).contains(&shift) {
        return Err(out_of_range(f));
    }
    Ok(Gain {
        mant,
        shift: shift as u8,
    })
}

/// Model 4's belt observer, if the image has one: each field within what
/// [`crate::model::belt::BeltParams::build_every`] makes: these keep the step the physics it
/// was built from, and its products within their formats.
fn read_belt(r: &mut Stream, rate_hz: Option<u32>) -> Result<Option<BeltTermCoeffs>, BlobError> {
    use ConfigField as F;
    match r.u32()? {
        0 => return Ok(None),
        1 => {}
        _ => return Err(out_of_range(F::Model4BeltStepTicks)),
    }
    // Built for one control rate: every factor per tick is that rate's.
    let made_for_hz = r.u32()?;
    if !crate::RATE_HZ.contains(&made_for_hz) {
        return Err(out_of_range(F::DriveRateHz));
    }
    if rate_hz.is_some_and(|hz| hz != made_for_hz) {
        return Err(BlobError::RateMismatch);
    }
    let weight_q16 = i32_in(r, -(8 << 16), 8 << 16, F::Model4BeltWeight)?;
    let rest_bits = [
        um(r, ANY, F::Model4BeltRestUm)?.to_bits(),
        um(r, ANY, F::Model4BeltRestUm)?.to_bits(),
    ];
    let approach = [
        read_scale(r, F::Model4BeltHalfTravelMm)?,
        read_scale(r, F::Model4BeltHalfTravelMm)?,
    ];
    let fast_q30 = i32_in(r, 0, 1 << 30, F::Model4BeltFastShare)?;
    let mut g = [Gain { mant: 0, shift: 1 }; BELT_GAINS.len()];
    for (g, &f) in g.iter_mut().zip(&BELT_GAINS) {
        *g = read_gain(r, f)?;
    }
    let mut w = [0i32; BELT_WORDS.len()];
    for (w, &(lo, hi, f)) in w.iter_mut().zip(&BELT_WORDS) {
        *w = i32_in(r, lo, hi, f)?;
    }
    // The static coefficient's excess over the kinetic one keeps their sum within 1 (and a
    // unit of rounding).
    if w[1] > (1 << 30) - w[0] + 1 {
        return Err(out_of_range(F::Model4BeltMuStatic));
    }
    let tooth_n_per_m = r.u32()?;
    let damping_t_n_per_m = r.u32()?;
    let gear_compliance_q56 = r.u64()?;
    let guide_q16 = i32_in(r, 0, 10_000 << 16, F::Model4BeltGuideN)?;
    let guide_bins = r.u32()?;
    if guide_bins as usize > MAX_GUIDE_BINS {
        return Err(BlobError::Invalid(ConfigError::TableSize(
            F::Model4BeltGuideProfileN,
        )));
    }
    let guide_start_q16 = r.i32()?;
    let mut l = [0i32; BELT_LENGTHS.len()];
    for (l, &(lo, hi, f)) in l.iter_mut().zip(&BELT_LENGTHS) {
        *l = i32_in(r, lo, hi, f)?;
    }
    // The span from the pulley within the belt.
    if l[3] > l[2] {
        return Err(out_of_range(F::Model4BeltSpanOffsetM));
    }
    // `1 / L` is the belt's own (L / L = 1 in Q30 within 0.4 %): the spans' ratio stays within
    // its range in the balance whatever the carriage's position.
    let one_q30 = (l[2] as i64 * g[11].mant as i64) >> g[11].shift;
    if (one_q30 - (1 << 30)).abs() > 1 << 22 {
        return Err(out_of_range(F::Model4BeltLengthM));
    }
    let mut guide_delta_q16 = [0i32; MAX_GUIDE_BINS];
    for d in guide_delta_q16.iter_mut().take(guide_bins as usize) {
        *d = i32_in(r, -(10_000 << 16), 10_000 << 16, F::Model4BeltGuideProfileN)?;
    }
    let mut track_q32 = [0i64; 3];
    for t in track_q32.iter_mut() {
        let v = r.u64()?;
        if v > 1 << 32 {
            return Err(out_of_range(F::Model4BeltStepTicks));
        }
        *t = v as i64;
    }
    let every = r.u32()?;
    if !(1..=MAX_STEP_TICKS).contains(&every) {
        return Err(out_of_range(F::Model4BeltStepTicks));
    }
    Ok(Some(BeltTermCoeffs {
        c: BeltCoeffs {
            m_per_count: g[0],
            accel: g[1],
            sigma0: g[2],
            sigma1_t: g[3],
            m1_t: g[4],
            inv_stribeck: g[5],
            kappa: g[6],
            damping_t: g[7],
            tt_per_m: g[8],
            tooth: g[9],
            span_per_ae_l: g[10],
            inv_length: g[11],
            guide_per_step: g[12],
            mu_kinetic_q30: w[0],
            dmu_q30: w[1],
            sigma0_q8: w[2],
            sigma1_t_q8: w[3],
            wrap_q28: w[4],
            preload_q16: w[5],
            preload_wrap_q16: w[6],
            tooth_n_per_m,
            damping_t_n_per_m,
            gear_compliance_q56,
            guide_q16,
            guide_delta_q16,
            guide_bins,
            guide_start_q16,
            half_gap_q36: l[0],
            gear_half_q36: l[1],
            length_q16: l[2],
            span_offset_q16: l[3],
            max_slip_q36: l[4],
            jump_q36: l[5],
            track_q32,
            every: every as u8,
        },
        weight_q16,
        rest_bits,
        approach,
        fast_q30,
        rate_hz: made_for_hz,
    }))
}

/// An `i32` in `lo..=hi`, or a refusal naming `field`.
fn i32_in(r: &mut Stream, lo: i32, hi: i32, field: ConfigField) -> Result<i32, BlobError> {
    let v = r.i32()?;
    if (lo..=hi).contains(&v) {
        Ok(v)
    } else {
        Err(out_of_range(field))
    }
}

/// The slip observer, each field within what [`crate::model::slip::SlipParams::build`] makes.
fn read_slip(r: &mut Stream) -> Result<SlipCoeffs, BlobError> {
    use ConfigField::{
        Model4SlipHalfGapUm, Model4SlipLimitUm, Model4SlipLoadUm, Model4SlipUmPerA,
        Model4SlipWeight,
    };
    let max = (slip::MAX_SLIP_UM as i32) << 16;
    // The reverse load acts backward, the forward one forward.
    let load_bits = [
        i32_in(r, -max, 0, Model4SlipLoadUm)?,
        i32_in(r, 0, max, Model4SlipLoadUm)?,
    ];
    let per_a_bits = [
        i32_in(r, -max, max, Model4SlipUmPerA)?,
        i32_in(r, -max, max, Model4SlipUmPerA)?,
    ];
    let kappa_q32 = r.u32()?;
    if kappa_q32 as u64 > slip::MAX_KAPPA_Q32 {
        return Err(out_of_range(ConfigField::Model4SlipCreepPerMm));
    }
    // Any travel per count: the step saturates the pre-slide limit.
    let um_per_count_bits = r.u32()?;
    let limit_bits = i32_in(r, 1 << 16, max, Model4SlipLimitUm)?;
    let half_gap_bits = i32_in(r, 1 << 16, max, Model4SlipHalfGapUm)?;
    let weight_q16 = i32_in(r, -(8 << 16), 8 << 16, Model4SlipWeight)?;
    Ok(SlipCoeffs {
        load_bits,
        per_a_bits,
        kappa_q32,
        um_per_count_bits,
        limit_bits,
        cap_bits: SlipCoeffs::cap_bits_of(limit_bits),
        half_gap_bits,
        weight_q16,
    })
}

/// Closing distances as the image carries them: I16F16 mm, -1 for never.
#[cfg(feature = "std")]
fn read_closing(r: &mut Stream) -> Result<crate::model::Closing, BlobError> {
    let mut one = || -> Result<Option<I16F16>, BlobError> {
        let bits = r.i32()?;
        Ok((bits >= 0).then_some(I16F16::from_bits(bits)))
    };
    Ok(crate::model::Closing {
        forward_mm: one()?,
        reverse_mm: one()?,
    })
}

/// Checks an image for a drive on `rig` and, if `out` is given, reads its coefficients into it.
fn read_image(
    src: &mut dyn Source,
    rig: &Rig,
    rate_hz: Option<u32>,
    out: Option<&mut ModelCoeffs>,
) -> Result<(), BlobError> {
    check_header_from(src, MAGIC, VERSION, MAX_BYTES)?;
    let mut r = Stream::new(src, HEADER);
    let result = read_fields(&mut r, rig, rate_hz, out);
    // A source that failed to read is not a short image.
    match result {
        Err(BlobError::Truncated) if r.failed() => Err(BlobError::Unreadable),
        other => other,
    }
}

fn read_fields(
    r: &mut Stream,
    rig: &Rig,
    rate_hz: Option<u32>,
    mut out: Option<&mut ModelCoeffs>,
) -> Result<(), BlobError> {
    let r = &mut *r;
    // Bit for bit: the geometry must be the drive's exactly, and no float compare is needed.
    let made_for = crate::blob::read_rig(r)?;
    if !made_for.same_bits(rig) {
        return Err(BlobError::RigMismatch);
    }
    let deadband_counts = r.u32()?;
    let model1 = read_model1(r)?;
    let model2 = read_model2(r)?;
    read_model3(r, out.as_deref_mut().map(|c| &mut c.model3))?;
    // Offset -+ half the backlash: each up to 1.5 MAX_ABS_UM, any I16F16 serves the tick.
    let backlash = BacklashCoeffs {
        forward_um: I16F16::from_bits(r.i32()?),
        reverse_um: I16F16::from_bits(r.i32()?),
    };
    read_bidir(r, out.as_deref_mut().map(|c| &mut c.bidir))?;
    let model4 = read_model4(r, rate_hz)?;
    #[cfg(feature = "std")]
    let closing = [read_closing(r)?, read_closing(r)?, read_closing(r)?];
    #[cfg(not(feature = "std"))]
    r.skip(4 * 6)?;
    if r.remaining() != 0 {
        return Err(BlobError::TooLong);
    }
    if let Some(c) = out {
        c.deadband_counts = deadband_counts;
        c.model1 = model1;
        c.model2 = model2;
        c.backlash = backlash;
        c.model4 = model4;
        #[cfg(feature = "std")]
        {
            c.model1.closing = closing[0];
            c.model2.closing = closing[1];
            c.model3.closing = closing[2];
        }
    }
    Ok(())
}

/// Checks an image for a drive on `rig` at control rate `rate_hz` without keeping anything.
/// Integer-only: lengths and the checksum first, then every field against its range; a
/// refusal names the field. The geometry must be the drive's ([`BlobError::RigMismatch`]),
/// and a belt observer must be built for the drive's rate ([`BlobError::RateMismatch`]).
pub fn check(image: &[u8], rig: &Rig, rate_hz: u32) -> Result<(), BlobError> {
    read_image(&mut { image }, rig, Some(rate_hz), None)
}

/// [`check`] an image read from `src` (the drive's staging flash) in small windows.
pub fn check_from(src: &mut dyn Source, rig: &Rig, rate_hz: u32) -> Result<(), BlobError> {
    read_image(src, rig, Some(rate_hz), None)
}

/// Reads an image's coefficients into `out`, checking it as [`check`] does. On a refusal `out`
/// holds part of the image: read into a staging copy, or [`check`] first (the drive does, and
/// then reads straight into its own coefficients without a 5 KiB copy).
pub fn decode_into(
    image: &[u8],
    rig: &Rig,
    rate_hz: u32,
    out: &mut ModelCoeffs,
) -> Result<(), BlobError> {
    read_image(&mut { image }, rig, Some(rate_hz), Some(out))
}

/// [`decode_into`] from an image read from `src` in small windows.
pub fn decode_from(
    src: &mut dyn Source,
    rig: &Rig,
    rate_hz: u32,
    out: &mut ModelCoeffs,
) -> Result<(), BlobError> {
    read_image(src, rig, Some(rate_hz), Some(out))
}

/// An image's coefficients for `rig` at whatever control rate its belt observer was built for
/// (host tools reading an image: no drive's rate to hold it to; see
/// [`BeltTermCoeffs::rate_hz`]); otherwise checked as [`check`] does. The refusal changes
/// nothing.
pub fn decode(image: &[u8], rig: &Rig) -> Result<ModelCoeffs, BlobError> {
    let mut c = ModelCoeffs::ZERO;
    read_image(&mut { image }, rig, None, Some(&mut c))?;
    Ok(c)
}

#[cfg(feature = "std")]
mod write {
    use super::*;
    use belt_link::bytes::Writer;

    fn band(w: &mut Writer, b: &LinearBand) {
        w.i32(b.m_um_per_count.to_bits());
        w.i32(b.offset_um.to_bits());
        w.i32(b.h_um.to_bits());
    }

    fn scale(w: &mut Writer, s: &Scale) {
        w.u32(s.mant);
        w.u16(s.shift as u16);
        w.u16(0);
    }

    fn closing(w: &mut Writer, c: &crate::model::Closing) {
        for d in [c.forward_mm, c.reverse_mm] {
            w.i32(d.map_or(-1, |d| d.to_bits()));
        }
    }

    fn model3(w: &mut Writer, m: &Model3Coeffs) {
        for b in [&m.forward_band, &m.reverse_band] {
            w.u16(b.len as u16);
            w.u16(0);
            w.i32(b.x0_counts);
            w.u32(b.points_q32);
            for y in b.y_um.iter().take(b.len as usize) {
                w.i32(y.to_bits());
            }
        }
        for t in [&m.forward_transition, &m.reverse_transition] {
            w.u16(t.n_d as u16);
            w.u16(t.n_g0 as u16);
            w.u32(t.rows_q32);
            w.u32(t.cols_q32);
            for row in t.gap_um.iter().take(t.n_d as usize) {
                for g in row.iter().take(t.n_g0 as usize) {
                    w.u16(g.to_bits());
                }
            }
        }
    }

    fn model4(w: &mut Writer, m: &Model4Coeffs) {
        for v in m
            .widths_counts
            .iter()
            .chain(&m.weight_q24[REVERSE])
            .chain(&m.weight_q24[FORWARD])
        {
            w.i32(*v);
        }
        w.i32(m.x_ref_counts);
        w.i32((m.offset_q31 >> 15) as i32);
        w.i32(m.slope_q31);
        w.i32(m.hat_start_counts);
        w.u32(m.hat_recip_q32);
        for k in m.knot_um {
            w.i32(k.to_bits());
        }
        w.u32(m.pitch_rate);
        w.i32(m.pitch.amp_q17 >> 1);
        w.u32(m.pitch.phase_q32);
        w.u32(m.turn_rate);
        w.i32(m.turn.amp_q17 >> 1);
        w.u32(m.turn.phase_q32);
        w.i32(m.current_um_per_a.to_bits());
        w.i32(m.current_lp_um_per_a.to_bits());
        let sl = &m.slip;
        for v in sl.load_bits.iter().chain(&sl.per_a_bits) {
            w.i32(*v);
        }
        w.u32(sl.kappa_q32);
        w.u32(sl.um_per_count_bits);
        w.i32(sl.limit_bits);
        w.i32(sl.half_gap_bits);
        w.i32(sl.weight_q16);
        belt(w, m.belt.as_ref());
    }

    /// In [`read_belt`]'s order.
    fn belt(w: &mut Writer, b: Option<&BeltTermCoeffs>) {
        let Some(b) = b else {
            w.u32(0);
            return;
        };
        w.u32(1);
        w.u32(b.rate_hz);
        w.i32(b.weight_q16);
        w.i32(b.rest_bits[0]);
        w.i32(b.rest_bits[1]);
        scale(w, &b.approach[0]);
        scale(w, &b.approach[1]);
        w.i32(b.fast_q30);
        let c = &b.c;
        for g in [
            c.m_per_count,
            c.accel,
            c.sigma0,
            c.sigma1_t,
            c.m1_t,
            c.inv_stribeck,
            c.kappa,
            c.damping_t,
            c.tt_per_m,
            c.tooth,
            c.span_per_ae_l,
            c.inv_length,
            c.guide_per_step,
        ] {
            w.i32(g.mant);
            w.u32(u32::from(g.shift));
        }
        for v in [
            c.mu_kinetic_q30,
            c.dmu_q30,
            c.sigma0_q8,
            c.sigma1_t_q8,
            c.wrap_q28,
            c.preload_q16,
            c.preload_wrap_q16,
        ] {
            w.i32(v);
        }
        w.u32(c.tooth_n_per_m);
        w.u32(c.damping_t_n_per_m);
        w.u64(c.gear_compliance_q56);
        w.i32(c.guide_q16);
        w.u32(c.guide_bins);
        w.i32(c.guide_start_q16);
        for v in [
            c.half_gap_q36,
            c.gear_half_q36,
            c.length_q16,
            c.span_offset_q16,
            c.max_slip_q36,
            c.jump_q36,
        ] {
            w.i32(v);
        }
        for d in c.guide_delta_q16.iter().take(c.guide_bins as usize) {
            w.i32(*d);
        }
        for t in c.track_q32 {
            w.u64(t as u64);
        }
        w.u32(u32::from(c.every));
    }

    /// Writes coefficients built for `rig` into `buf`; returns the image's length.
    pub fn encode(c: &ModelCoeffs, rig: &Rig, buf: &mut [u8]) -> Result<usize, BlobError> {
        let mut w = Writer::at(&mut *buf, HEADER);
        crate::blob::write_rig(&mut w, rig);
        w.u32(c.deadband_counts);
        let m1 = &c.model1;
        band(&mut w, &m1.band);
        w.i32(m1.h_g_um.to_bits());
        w.i32(m1.slope_a_um_per_count.to_bits());
        w.i32(m1.slope_b_um_per_count.to_bits());
        let m2 = &c.model2;
        band(&mut w, &m2.band);
        for v in [m2.h_g_um, m2.amp_a_um, m2.amp_b_um] {
            w.i32(v.to_bits());
        }
        scale(&mut w, &m2.rate_a);
        scale(&mut w, &m2.rate_b);
        model3(&mut w, &c.model3);
        w.i32(c.backlash.forward_um.to_bits());
        w.i32(c.backlash.reverse_um.to_bits());
        let b = &c.bidir;
        w.u16(b.rows);
        w.u16(0);
        w.i32(b.x0_counts);
        w.u32(b.step_counts);
        for i in 0..(b.rows as usize).min(MAX_BIDIR_ROWS) {
            w.u16(b.values[0][i].to_bits() as u16);
            w.u16(b.values[1][i].to_bits() as u16);
        }
        model4(&mut w, &c.model4);
        closing(&mut w, &c.model1.closing);
        closing(&mut w, &c.model2.closing);
        closing(&mut w, &c.model3.closing);
        let len = w.finish().map_err(|_| BlobError::BufferTooSmall)?;
        crate::blob::seal(buf, len, MAGIC, VERSION);
        Ok(len)
    }
}

#[cfg(feature = "std")]
pub use write::encode;

/// The image a drive loads for `params` on `rig` (host tools): the parameters quantised to a
/// calibration blob's formats first, as a calibration file holds them, then built. The same
/// as [`from_blob`] of their blob.
#[cfg(feature = "std")]
pub fn of_params(params: &crate::model::ModelParams, rig: &Rig) -> Result<Vec<u8>, BlobError> {
    let mut blob = vec![0u8; crate::blob::MAX_BYTES];
    let n = crate::blob::encode(params, rig, &mut blob)?;
    from_blob(&blob[..n])
}

/// The image a drive loads for a calibration blob: its parameters (checked as the blob's own
/// decoder checks them) built for the geometry the blob records.
#[cfg(feature = "std")]
pub fn from_blob(blob: &[u8]) -> Result<Vec<u8>, BlobError> {
    let rig = crate::blob::calibrated_rig(blob)?;
    let c = crate::blob::decode(blob, &rig)?
        .build(&rig)
        .map_err(BlobError::Invalid)?;
    let mut buf = vec![0u8; MAX_BYTES];
    let n = encode(&c, &rig, &mut buf)?;
    buf.truncate(n);
    Ok(buf)
}
