//! Model 4: the project's own estimator, a belt-slip observer ([`super::slip`]) and a few play
//! operators (a Prandtl-Ishlinskii hysteresis) plus what the paper's models leave out, all
//! linear in its weights so that calibration fits every part jointly by least squares.
//!
//! ```text
//! y = w_g g                                               belt in the tooth gap (observer state)
//!   + offset + slope (x - x_ref)                          band centre, extrapolates along its slope
//!   + sum_k band_k hat_k(x)                               band shape inside the calibrated span
//!   + sum_j (w_j + [forward] v_j) P_rj[x]                 the fast part: gear backlash, unloading
//!   + s_p sin(2 pi x / p) + c_p cos(..)                   tooth-passing harmonic (belt pitch p)
//!   + s_r sin(2 pi x / (n p)) + c_r cos(..)               pulley run-out (one pulley turn)
//!     (each pair evaluated as one amplitude and phase, `r sin(2 pi x / p + phi)`)
//!   + k_i i + k_l i_lp                                    belt force: the current, and its low pass
//! ```
//! `g` is the observer's mesh offset: where the belt sits in the pulley's tooth gap, moved by
//! pre-sliding and creep under the load the current and the direction of motion put on it. The
//! observer's own parameters (load, limit, half gap, creep rate) are fitted by calibration
//! around the least-squares fit of the weights. Where calibration identified the belt observer
//! ([`BeltTerm`], [`super::belt`]: the carriage on its spans, the bristles, the capstan, a step
//! every few ticks), its offset is `g` instead and the slip observer is not run; the placement's
//! prediction at rest then predicts its rest rather than stepping it (`predict_rest`).
//!
//! `P_r[x]` is the play operator of half-width `r`: its state `p` follows `x` only when `x` is
//! more than `r` away (`p = clamp(p, x - r, x + r)`), and the feature is `x - p` in `[-r, r]`.
//! Three plays (10-60 um) carry what turns at once at a reversal and is not the belt on the
//! pulley: the gear's backlash and the unloading of gear, spans and teeth. The forward-only
//! weights let the two directions differ (the paper's `a != b`). The hats are interior knots
//! only, so outside the knots the band continues along the fitted slope instead of being held
//! flat.
//!
//! Why this and not the sum before it (Model 2's estimate and ten plays up to 40 mm): measured
//! on the simulated rig (`hil-sim generalise`, README), the plays modelled the creep as a
//! function of the distance since each turning point, where the real creep depends on the load
//! on the way; the observer carries it as a state. With the plant's true mesh offset in place
//! of the observer, the same fit leaves 2.4 um on Fig. 18: the rest is the observer's error.
//!
//! `i_lp` is the current through a one-pole low pass of [`CURRENT_LP_TICKS`] ticks (16 ms at the
//! 2 kHz rate), restarted at the current when Model 4 starts. It carries the belt force the
//! carriage felt over the last stroke (acceleration and friction through the belt's elastic
//! lag), which the instantaneous current does not.
//!
//! # Fixed point
//! Every term lands in one `i64` accumulator in Q24 micrometres:
//! - play weights Q24 um per count (|w| < 128 um/count) times the feature in counts;
//! - slope Q31 um per count times `x - x_ref` (saturated to `i32`), shifted by 7;
//! - the observer's weight Q16 times `g` I16F16, shifted by 8 (the belt observer's on a tick:
//!   `w_q16 15625 / 4` times its offset in Q36 m, shifted by 20);
//! - the offset I16F16 um shifted to Q31, summed with the slope's product before its shift;
//! - hat and current weights I16F16 (um, um per A) times the hat in Q16 and the currents in
//!   I16F16, each harmonic's amplitude in Q17 um times one sine in Q15: both hats summed and
//!   shifted by 8, both harmonics and both currents (Q32, the currents' products below 2^61
//!   with weights within `MAX_ABS_UM`) summed and shifted by 8;
//! - the low pass `l += (i - l) >> 5` on the I16F16 current bits (arithmetic shift: floor);
//! - the output `acc >> 8` as I16F16, saturated to +-2^14 um ([`OUT_BITS`]).
//!
//! Phases are `u32` turns: `(x - x_ref) * rate + phase` wrapping, `rate = round(2^32 /
//! period_counts)`, `phase` the harmonic's (`atan2(c, s)`, Q32 turns; its amplitude
//! `hypot(s, c)`): one table read a harmonic instead of two (21 instructions a tick fewer);
//! the sine is a 256-step table with linear interpolation (error < 1e-4 of the amplitude).
//! The hat position is `(x - start) * recip >> 16` with `recip = round(2^32 / step_counts)`.
//! The [`crate::reference`] model evaluates the same definitions in `f64`.

use crate::ConfigField;
use fixed::types::I16F16;

use super::belt::{BeltCoeffs, BeltParams, BeltState};
use super::convert::{finite, MAX_ABS_UM};
use super::fixmath::{exp2_neg_q30, sat_i32, Scale};
use super::slip::{SlipCoeffs, SlipParams};
use super::{Direction, ModelState};
use crate::ConfigError;

/// Play operators (half-widths).
pub const N_OPS: usize = 3;
/// Interior knots of the band shape.
pub const N_KNOTS: usize = 8;
/// The current's low pass: time constant in ticks, a power of two (a shift on the drive).
pub const CURRENT_LP_TICKS: u32 = 1 << CURRENT_LP_SHIFT;
const CURRENT_LP_SHIFT: u32 = 5;

/// One tick of the current's low pass on I16F16 bits (the reference runs this too: the filter
/// is part of the feature's definition).
#[inline(always)]
pub fn current_lowpass(lp_bits: i32, current_bits: i32) -> i32 {
    lowpass_bits(lp_bits, current_bits, CURRENT_LP_SHIFT)
}

/// A one-pole low pass of `1 / 2^shift` per tick on raw bits, modulo 2^32 (arithmetic shift:
/// floor). Model 4's current term and its slip observer both run it.
#[inline(always)]
pub fn lowpass_bits(lp_bits: i32, input_bits: i32, shift: u32) -> i32 {
    lp_bits.wrapping_add(input_bits.wrapping_sub(lp_bits) >> shift)
}

/// Model 4's parameters in SI-ish units (mm, um); all zero predicts 0 everywhere.
#[derive(Clone, Debug, PartialEq)]
pub struct Model4Params {
    /// Half-widths of the play operators, mm, each in `(0, 500]`, strictly increasing (at least
    /// one encoder count apart).
    pub widths_mm: [f64; N_OPS],
    /// Weight of each play, um of error per mm of operator output.
    pub play_um_per_mm: [f64; N_OPS],
    /// Extra weight of each play while the registered direction is forward.
    pub play_forward_um_per_mm: [f64; N_OPS],
    /// Where the slope is measured from, mm.
    pub x_ref_mm: f64,
    /// Error at `x_ref`, um.
    pub offset_um: f64,
    /// Slope of the band centre, um per mm of travel.
    pub slope_um_per_mm: f64,
    /// First interior knot, mm.
    pub knot_start_mm: f64,
    /// Knot spacing, mm (> 0).
    pub knot_step_mm: f64,
    /// Band shape at each knot, um.
    pub knot_um: [f64; N_KNOTS],
    /// Belt pitch, mm (the tooth-passing period along the travel).
    pub pitch_mm: f64,
    /// Harmonic at the belt pitch: sine and cosine amplitudes, um.
    pub pitch_um: [f64; 2],
    /// One pulley turn, mm.
    pub turn_mm: f64,
    /// Harmonic at one pulley turn: sine and cosine amplitudes, um.
    pub turn_um: [f64; 2],
    /// Error per ampere of motor current (the belt's stretch under its force), um/A.
    pub current_um_per_a: f64,
    /// Error per ampere of the low-passed current, um/A.
    pub current_lp_um_per_a: f64,
    /// The belt-slip observer and the weight of its mesh offset.
    pub slip: SlipParams,
    /// The reduced plant observer ([`super::belt`]) whose mesh offset, weighted, takes the slip
    /// observer's place (the slip observer is then not run); `None`: the slip observer.
    pub belt: Option<BeltTerm>,
}

/// Model 4's belt observer term: identified physics, the step it was built for, and the weight
/// of its mesh offset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BeltTerm {
    /// The observer's physics (identified by calibration).
    pub physics: BeltParams,
    /// The control tick the physics were identified at, s (the drive's `1 / rate_hz`).
    pub tick_s: f64,
    /// Ticks per observer step, 1 to [`super::belt::MAX_STEP_TICKS`].
    pub step_ticks: u32,
    /// Error per unit of mesh offset (um per um), within +-8.
    pub weight: f64,
    /// Where the offset settles at rest after travel in reverse (`[0]`) and forward (`[1]`),
    /// um: the placement's prediction ([`crate::model::estimate`]), measured by calibration on
    /// the observer's own offsets.
    pub rest_um: [f64; 2],
    /// Travel that halves the offset's way to its rest value, mm (> 0): the fast part (the
    /// belt crossing the tooth gap) and the slow one (its creep).
    pub half_travel_mm: [f64; 2],
    /// The fast part's share of the way, 0 to 1.
    pub fast_share: f64,
}

/// [`BeltTerm`] built: the observer's coefficients and the offset's weight, Q16.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BeltTermCoeffs {
    pub(crate) c: BeltCoeffs,
    pub(crate) weight_q16: i32,
    /// [`BeltTerm::rest_um`], I16F16 um.
    pub(crate) rest_bits: [i32; 2],
    /// Counts to the exponent of `2^-t` (Q32.32) of the offset's approach to rest, fast and
    /// slow part.
    pub(crate) approach: [Scale; 2],
    /// The fast part's share, Q30.
    pub(crate) fast_q30: i32,
    /// The control rate the observer was built for (`1 / tick_s`), whole hertz: a drive at
    /// another rate refuses it ([`crate::blob::BlobError::RateMismatch`]).
    pub(crate) rate_hz: u32,
}

impl BeltTermCoeffs {
    /// The control rate this observer was built for, whole hertz.
    pub fn rate_hz(&self) -> u32 {
        self.rate_hz
    }
}

impl BeltTerm {
    /// Checks every field (errors name it) and builds the observer for `counts_per_mm`.
    pub fn build(&self, counts_per_mm: f64) -> Result<BeltTermCoeffs, ConfigError> {
        let c = self.physics.build_every(self.tick_s, self.step_ticks)?;
        // A rate the drive takes, in whole hertz.
        let rate = crate::BuildContext::check_rate_hz(1.0 / self.tick_s)?;
        if (rate - rnd(rate)).abs() >= 1e-6 * rate {
            return Err(ConfigError::OutOfRange(ConfigField::DriveRateHz));
        }
        let w = finite(self.weight, ConfigField::Model4BeltWeight)?;
        if w.abs() > 8.0 {
            return Err(ConfigError::OutOfRange(ConfigField::Model4BeltWeight));
        }
        let rest = [
            um(self.rest_um[0], ConfigField::Model4BeltRestUm)?,
            um(self.rest_um[1], ConfigField::Model4BeltRestUm)?,
        ];
        let mut approach = [Scale::ZERO; 2];
        for (a, &half) in approach.iter_mut().zip(&self.half_travel_mm) {
            let half = finite(half, ConfigField::Model4BeltHalfTravelMm)?;
            // More than a count (the factor stays below 2^32), at most 10 m.
            if !(half * counts_per_mm > 1.0 && half <= 10_000.0) {
                return Err(ConfigError::OutOfRange(ConfigField::Model4BeltHalfTravelMm));
            }
            *a = Scale::from_f64(
                (1u64 << 32) as f64 / (half * counts_per_mm),
                ConfigField::Model4BeltHalfTravelMm,
            )?;
        }
        let share = finite(self.fast_share, ConfigField::Model4BeltFastShare)?;
        if !(0.0..=1.0).contains(&share) {
            return Err(ConfigError::OutOfRange(ConfigField::Model4BeltFastShare));
        }
        Ok(BeltTermCoeffs {
            c,
            weight_q16: rnd(w * 65536.0) as i32,
            rest_bits: rest.map(I16F16::to_bits),
            approach,
            fast_q30: rnd(share * (1u64 << 30) as f64) as i32,
            rate_hz: rnd(rate) as u32,
        })
    }
}

impl Model4Params {
    /// Half-widths used by calibration: 10 to 60 um (the fast part of a reversal).
    pub const WIDTHS_MM: [f64; N_OPS] = [0.01, 0.025, 0.06];

    /// No correction (uncalibrated): every weight zero, geometry of `rig`'s belt.
    pub const fn zero(pitch_mm: f64, turn_mm: f64) -> Model4Params {
        Model4Params {
            widths_mm: Model4Params::WIDTHS_MM,
            play_um_per_mm: [0.0; N_OPS],
            play_forward_um_per_mm: [0.0; N_OPS],
            x_ref_mm: 0.0,
            offset_um: 0.0,
            slope_um_per_mm: 0.0,
            knot_start_mm: 0.0,
            knot_step_mm: 1.0,
            knot_um: [0.0; N_KNOTS],
            pitch_mm,
            pitch_um: [0.0; 2],
            turn_mm,
            turn_um: [0.0; 2],
            current_um_per_a: 0.0,
            current_lp_um_per_a: 0.0,
            slip: SlipParams::ZERO,
            belt: None,
        }
    }

    /// Checks every field and converts for `counts_per_mm`; errors name the field.
    pub fn build(&self, counts_per_mm: f64) -> Result<Model4Coeffs, ConfigError> {
        let counts = |mm: f64, field: ConfigField| -> Result<f64, ConfigError> {
            Ok(finite(mm, field)? * counts_per_mm)
        };
        let mut widths = [0i32; N_OPS];
        // Per direction (`FORWARD`, `REVERSE`): the forward weight is summed here, not per tick.
        let mut weight = [[0i32; N_OPS]; 2];
        for j in 0..N_OPS {
            let w = rnd(counts(self.widths_mm[j], ConfigField::Model4WidthsMm)?);
            if !(1.0..=(1 << 24) as f64).contains(&w) {
                return Err(ConfigError::OutOfRange(ConfigField::Model4WidthsMm));
            }
            widths[j] = w as i32;
            let reverse = finite(self.play_um_per_mm[j], ConfigField::Model4PlayUmPerMm)?;
            let extra = finite(
                self.play_forward_um_per_mm[j],
                ConfigField::Model4PlayForwardUmPerMm,
            )?;
            weight[REVERSE][j] =
                q24_per_count(reverse, counts_per_mm, ConfigField::Model4PlayUmPerMm)?;
            weight[FORWARD][j] = q24_per_count(
                reverse + extra,
                counts_per_mm,
                ConfigField::Model4PlayForwardUmPerMm,
            )?;
        }
        let x_ref = rnd(counts(self.x_ref_mm, ConfigField::Model4XRefMm)?);
        if x_ref.abs() > i32::MAX as f64 / 2.0 {
            return Err(ConfigError::OutOfRange(ConfigField::Model4XRefMm));
        }
        let slope = finite(self.slope_um_per_mm, ConfigField::Model4SlopeUmPerMm)? / counts_per_mm;
        let slope_q31 = rnd(slope * (1u64 << 31) as f64);
        if slope_q31.abs() >= (1u64 << 31) as f64 {
            return Err(ConfigError::OutOfRange(ConfigField::Model4SlopeUmPerMm));
        }
        let step = rnd(counts(self.knot_step_mm, ConfigField::Model4KnotStepMm)?);
        if !(1.0..=(1 << 24) as f64).contains(&step) {
            return Err(ConfigError::OutOfRange(ConfigField::Model4KnotStepMm));
        }
        // Support of the hats: one step before the first knot to one after the last.
        let hat_start = rnd(counts(self.knot_start_mm, ConfigField::Model4KnotStartMm)?) - step;
        if hat_start.abs() > (1 << 30) as f64 {
            return Err(ConfigError::OutOfRange(ConfigField::Model4KnotStartMm));
        }
        let mut knots = [I16F16::ZERO; N_KNOTS];
        for (k, v) in knots.iter_mut().zip(&self.knot_um) {
            *k = um(*v, ConfigField::Model4KnotUm)?;
        }
        let rate = |period_mm: f64, field| -> Result<u32, ConfigError> {
            let p = counts(period_mm, field)?;
            if !(16.0..=(1u64 << 31) as f64).contains(&p) {
                return Err(ConfigError::OutOfRange(field));
            }
            Ok(rnd((1u64 << 32) as f64 / p) as u32)
        };
        // Narrowest first: the tick relies on the order (the plays that move are a prefix, see
        // [`Plays`]), and two plays of one width would be one play.
        if widths.windows(2).any(|w| w[1] <= w[0]) {
            return Err(ConfigError::NotMonotonic(ConfigField::Model4WidthsMm));
        }
        Ok(Model4Coeffs {
            widths_counts: widths,
            weight_q24: weight,
            x_ref_counts: x_ref as i32,
            offset_q31: (um(self.offset_um, ConfigField::Model4OffsetUm)?.to_bits() as i64) << 15,
            slope_q31: slope_q31 as i32,
            hat_start_counts: hat_start as i32,
            hat_recip_q32: rnd((1u64 << 32) as f64 / step).min(u32::MAX as f64) as u32,
            knot_um: knots,
            pitch_rate: rate(self.pitch_mm, ConfigField::Model4PitchMm)?,
            pitch: Harmonic::build(self.pitch_um, ConfigField::Model4PitchUm)?,
            turn_rate: rate(self.turn_mm, ConfigField::Model4TurnMm)?,
            turn: Harmonic::build(self.turn_um, ConfigField::Model4TurnUm)?,
            current_um_per_a: um(self.current_um_per_a, ConfigField::Model4CurrentUmPerA)?,
            current_lp_um_per_a: um(self.current_lp_um_per_a, ConfigField::Model4CurrentLpUmPerA)?,
            slip: self.slip.build(counts_per_mm)?,
            belt: match &self.belt {
                Some(b) => Some(b.build(counts_per_mm)?),
                None => None,
            },
        })
    }
}

/// Round half away from zero (`core` has no `f64::round`); saturates beyond `i64`.
fn rnd(v: f64) -> f64 {
    if v >= 0.0 {
        (v + 0.5) as i64 as f64
    } else {
        (v - 0.5) as i64 as f64
    }
}

fn um(v: f64, field: ConfigField) -> Result<I16F16, ConfigError> {
    let v = finite(v, field)?;
    if v.abs() > MAX_ABS_UM {
        return Err(ConfigError::OutOfRange(field));
    }
    Ok(I16F16::from_num(v))
}

fn q24_per_count(
    v_um_per_mm: f64,
    counts_per_mm: f64,
    field: ConfigField,
) -> Result<i32, ConfigError> {
    let q = rnd(finite(v_um_per_mm, field)? / counts_per_mm * (1u64 << 24) as f64);
    if q.abs() >= (1u64 << 31) as f64 {
        return Err(ConfigError::OutOfRange(field));
    }
    Ok(q as i32)
}

/// A harmonic `amp sin(phase of x + phase)`: the fit's sine and cosine amplitudes `(s, c)` as
/// `amp = hypot(s, c)`, `phase = atan2(c, s)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Harmonic {
    /// um in Q17 (an I16F16 value within `[0, MAX_ABS_UM]` shifted by 1: times the Q15 sine,
    /// Q32 like the currents' products, under their shift).
    pub(crate) amp_q17: i32,
    /// Q32 turns.
    pub(crate) phase_q32: u32,
}

impl Harmonic {
    pub(crate) const ZERO: Harmonic = Harmonic {
        amp_q17: 0,
        phase_q32: 0,
    };

    /// From the sine and cosine amplitudes in um; errors name `field`.
    fn build(w_um: [f64; 2], field: ConfigField) -> Result<Harmonic, ConfigError> {
        // Each within the bound (as when they were stored apart), then their amplitude too.
        let [s, c] = w_um;
        um(s, field)?;
        um(c, field)?;
        let (amp, turns) = super::convert::polar(s, c);
        let amp_q17 = um(amp, field)?.to_bits() << 1;
        if amp_q17 == 0 {
            return Ok(Harmonic::ZERO);
        }
        // `turns` in [0, 1): wraps at 1 to 0.
        let phase_q32 = rnd(turns * (1u64 << 32) as f64) as u64 as u32;
        Ok(Harmonic { amp_q17, phase_q32 })
    }

    /// The sine and cosine amplitudes it stands for, um (the reference's).
    #[cfg(feature = "std")]
    pub(crate) fn sin_cos_um(&self) -> [f64; 2] {
        let a = self.amp_q17 as f64 / (1u64 << 17) as f64;
        let t = self.phase_q32 as f64 / (1u64 << 32) as f64 * core::f64::consts::TAU;
        [a * t.cos(), a * t.sin()]
    }
}

/// [`Model4Coeffs`]'s play weights' rows, by [`Direction`]'s discriminant: the tick indexes
/// them with the registered direction as it is (3 instructions a tick fewer than by a flag).
pub(crate) const FORWARD: usize = Direction::Forward as usize;
pub(crate) const REVERSE: usize = Direction::Reverse as usize;
const _: () = assert!(FORWARD != REVERSE && FORWARD < 2 && REVERSE < 2);

/// Model 4's fixed-point coefficients (see the module docs for the formats).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Model4Coeffs {
    pub(crate) widths_counts: [i32; N_OPS],
    /// Play weights while moving forward ([`FORWARD`]) and in reverse ([`REVERSE`]), um per
    /// count Q24.
    pub(crate) weight_q24: [[i32; N_OPS]; 2],
    pub(crate) x_ref_counts: i32,
    /// The offset, um in Q31 (I16F16 bits shifted by 15: it starts the slope's sum).
    pub(crate) offset_q31: i64,
    pub(crate) slope_q31: i32,
    pub(crate) hat_start_counts: i32,
    pub(crate) hat_recip_q32: u32,
    pub(crate) knot_um: [I16F16; N_KNOTS],
    pub(crate) pitch_rate: u32,
    /// The belt pitch's harmonic.
    pub(crate) pitch: Harmonic,
    pub(crate) turn_rate: u32,
    /// The pulley turn's harmonic.
    pub(crate) turn: Harmonic,
    pub(crate) current_um_per_a: I16F16,
    pub(crate) current_lp_um_per_a: I16F16,
    /// The belt-slip observer.
    pub(crate) slip: SlipCoeffs,
    /// The belt observer in the slip observer's place.
    pub(crate) belt: Option<BeltTermCoeffs>,
}

impl Model4Coeffs {
    /// The belt observer's term, where the calibration has one.
    pub fn belt(&self) -> Option<&BeltTermCoeffs> {
        self.belt.as_ref()
    }
}

/// Sine of `i / 256` of a turn in Q15, `i = 0..=256`, for interpolation.
const SINE_Q15: [i16; 257] = sine_table();

const fn sine_table() -> [i16; 257] {
    let mut t = [0i16; 257];
    let mut i = 0;
    while i < 257 {
        // Reduce to [-pi/2, pi/2] by symmetry, then a Taylor series (|error| < 1e-12).
        let turn = i as f64 / 256.0;
        let (a, sign) = if turn <= 0.25 {
            (turn, 1.0)
        } else if turn <= 0.75 {
            (0.5 - turn, 1.0)
        } else {
            (turn - 1.0, 1.0)
        };
        let x = a * 2.0 * core::f64::consts::PI;
        let mut term = x;
        let mut sum = x;
        let mut k = 1;
        while k < 15 {
            term = -term * x * x / ((2 * k) as f64 * (2 * k + 1) as f64);
            sum += term;
            k += 1;
        }
        let v = sign * sum * 32767.0;
        t[i] = if v >= 0.0 {
            (v + 0.5) as i16
        } else {
            (v - 0.5) as i16
        };
        i += 1;
    }
    t
}

/// `sin(2 pi phase / 2^32)` in Q15 by linear interpolation in [`SINE_Q15`].
#[inline(always)]
fn sine_q15(phase: u32) -> i32 {
    let i = (phase >> 24) as usize;
    let frac = ((phase >> 8) & 0xffff) as i32;
    let a = SINE_Q15[i] as i32;
    let b = SINE_Q15[(i + 1) & 0x1ff] as i32;
    a + (((b - a) * frac) >> 16)
}

/// `h` at phase `ph`, Q32 um (`|.| < 2^46`: the two harmonics and the two currents are summed
/// before their one shift).
#[inline(always)]
fn harmonic(ph: u32, h: &Harmonic) -> i64 {
    h.amp_q17 as i64 * sine_q15(ph.wrapping_add(h.phase_q32)) as i64
}

/// Phase in turns (Q32) of `x` along a period with `rate` turns per count.
#[inline(always)]
fn phase(x: i32, x_ref: i32, rate: u32) -> u32 {
    // The low 32 bits of `(x - x_ref) * rate` depend only on the operands' low 32 bits.
    (x.wrapping_sub(x_ref) as u32).wrapping_mul(rate)
}

/// The two hats that can be non-zero at `x`: `(index of the left knot + 1, weight of the right
/// knot in Q16)`; the left knot's weight is `1 - t`. Index 0 or `N_KNOTS` means one of the two
/// is outside the knots; `None`: outside the support.
#[inline(always)]
fn hat(x: i32, start: i32, recip_q32: u32) -> Option<(usize, i32)> {
    if x < start {
        return None;
    }
    // 0 <= x - start < 2^32 (x in i32, |start| <= 2^30 + 2^24): exact in a `u32`; times
    // recip < 2^32 it fits a u64 for any coefficients `build` accepts (a step of 1 count has
    // recip = u32::MAX). Knots from the start of the support in Q32: the segment is the high
    // word, the weight the low word's top half (32-bit compares, no 64-bit shift).
    let p = (x.wrapping_sub(start) as u32) as u64 * recip_q32 as u64;
    let seg = (p >> 32) as u32;
    if seg > N_KNOTS as u32 {
        return None;
    }
    Some((seg as usize, (p as u32 >> 16) as i32))
}

/// Model 4's plays: each tick every play is clamped, `p = clamp(p, x - w, x + w)`, and enters
/// as `(x - p) weight`. With three plays the direct form costs the same per tick as running
/// sums over the group of plays that move together, and it has no dearer ticks at reversals
/// (the running sums cost 250 instructions more on the tick that wrote the group out).
///
/// `x -+ w` saturate at the ends of `i32`, so `p` stays within `w` of `x` and `x - p` is exact
/// in `i32` (`|x - p| <= w <= 2^24`): the term is `N_OPS` products of two `i32`, Q24 um.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Plays {
    /// States, counts.
    p: [i32; N_OPS],
    /// The state follows `x`; otherwise it restarts at the next tick.
    pub(crate) valid: bool,
}

impl Plays {
    pub(crate) const NEW: Plays = Plays {
        p: [0; N_OPS],
        valid: false,
    };

    /// Every play dragged to the side that moving `dir` puts it.
    fn start(&mut self, c: &Model4Coeffs, dir: Direction, x: i32) {
        for (p, &w) in self.p.iter_mut().zip(&c.widths_counts) {
            *p = match dir {
                Direction::Forward => x.saturating_sub(w),
                Direction::Reverse => x.saturating_add(w),
            };
        }
        self.valid = true;
    }

    /// Moves the plays with `x` and returns `sum (x - p_i) weight_i` with weight set `k`
    /// ([`FORWARD`] or [`REVERSE`]), Q24 um.
    #[inline(always)]
    fn step(&mut self, c: &Model4Coeffs, k: usize, x: i32) -> i64 {
        let weight = &c.weight_q24[k];
        // Unrolled by hand (`opt-level = "s"` keeps the loop): 15 instructions a tick less.
        let mut play = |j: usize| {
            let w = c.widths_counts[j];
            // max/min, not clamp: clamp asserts the order of bounds that come from coefficients.
            let p = self.p[j].max(x.saturating_sub(w)).min(x.saturating_add(w));
            self.p[j] = p;
            x.wrapping_sub(p) as i64 * weight[j] as i64
        };
        const _: () = assert!(N_OPS == 3);
        play(0) + play(1) + play(2)
    }
}

/// The mesh offset's weighted term, Q24 um: the belt observer's where the calibration has one,
/// else the slip observer's. Each is started (on the registered direction's flanks) when the
/// plays are, and steps every tick after; while predicting ([`crate::model::estimate`]) the
/// belt observer does not step, its rest is predicted.
#[inline(always)]
fn mesh_offset_term(
    c: &Model4Coeffs,
    state: &mut ModelState,
    starting: bool,
    predict: bool,
    forward: bool,
    x: i32,
    current_bits: i32,
) -> i64 {
    if let Some(b) = &c.belt {
        if starting {
            state.belt = BeltState::start(&b.c, x, forward);
            state.belt_rest.valid = false;
        }
        if predict {
            return (b.weight_q16 as i64 * predict_rest(b, state, x) as i64) >> 8;
        }
        if !starting {
            state.belt.tick(&b.c, x, current_bits);
        }
        // `belt_rest` stays invalid: only a prediction's copy ever sets it.
        // The weight times the offset in Q36 m, to Q24 um, without rounding the offset to
        // I16F16 um first: `w_q16 1e6 2^-36 2^24 = (w_q16 15625 / 4) 2^-20`, the factor in an
        // `i32` for |w| <= 8 (2 instructions a tick fewer than through micrometres; stored
        // with the coefficients instead, 8 more, by register allocation).
        let per_q36 = ((b.weight_q16 as i64 * 15625) >> 2) as i32;
        return (per_q36 as i64 * state.belt.offset_q36() as i64) >> 20;
    }
    if starting {
        state.slip.start(&c.slip, forward, x, current_bits);
    } else {
        state.slip.step(&c.slip, forward, x, current_bits);
    }
    state.slip.term(&c.slip)
}

/// Where the belt observer's offset will rest after travel to `x` (the placement's prediction,
/// [`crate::model::estimate`]): from the offset now, or the last prediction's, it approaches
/// the rest value of the direction of travel in two parts, each halving its way every
/// [`BeltTerm::half_travel_mm`]. I16F16 um; the observer itself does not move.
#[inline(never)]
fn predict_rest(b: &BeltTermCoeffs, state: &mut ModelState, x: i32) -> i32 {
    let r = &mut state.belt_rest;
    let (from, o) = if r.valid {
        (r.counts, r.offset_bits)
    } else {
        (state.belt.now_counts(), state.belt.offset_um_bits())
    };
    let d = x as i64 - from as i64;
    let o = if d == 0 {
        o
    } else {
        let rest = b.rest_bits[(d > 0) as usize];
        let travel = d.unsigned_abs().min(u32::MAX as u64) as u32;
        // The share of the way still to go, Q30: `a 2^(-L / H_fast) + (1 - a) 2^(-L / H_slow)`.
        let [fast, slow] = b.approach.map(|a| away_q30(a, travel));
        let k = slow + (((fast - slow) * b.fast_q30 as i64) >> 30);
        let gap = o as i64 - rest as i64;
        (rest as i64 + ((gap * k) >> 30)) as i32
    };
    *r = BeltRest {
        valid: true,
        counts: x,
        offset_bits: o,
    };
    o
}

/// `2^(-travel a)` in Q30 (one copy of the exponential for both parts: flash).
#[inline(never)]
fn away_q30(a: Scale, travel: u32) -> i64 {
    exp2_neg_q30(a.apply(travel)) as i64
}

/// The placement's predicted rest of the belt observer's offset, on a copy of the model state
/// ([`predict_rest`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct BeltRest {
    pub(crate) valid: bool,
    pub(crate) counts: i32,
    pub(crate) offset_bits: i32,
}

impl BeltRest {
    pub(crate) const NONE: BeltRest = BeltRest {
        valid: false,
        counts: 0,
        offset_bits: 0,
    };
}

/// Model 4's output range, I16F16 bits: +-2^14 um, the range whose differences fit Q16.16
/// ([`MAX_ABS_UM`] is the parameters' bound, within it). A power of two: the clamp is one
/// `SSAT` (7 instructions a tick fewer than the clamp to +-`MAX_ABS_UM`).
pub(crate) const OUT_BITS: (i32, i32) = (-(1 << 30), (1 << 30) - 1);

/// One tick of Model 4: moves the plays and the observer with `x` and sums every term. Out of
/// line: inlined into the dispatch it made every other model's tick dearer (measured).
#[inline(never)]
pub(crate) fn eval(c: &Model4Coeffs, state: &mut ModelState, x: i32, current_a: I16F16) -> I16F16 {
    let predict = state.predicting;
    let forward = state.dir == Direction::Forward;
    let current_bits = current_a.to_bits();
    let starting = !state.plays.valid;
    if starting {
        state.plays.start(c, state.dir, x);
        state.current_lp_bits = current_bits;
    } else {
        state.current_lp_bits = current_lowpass(state.current_lp_bits, current_bits);
    }
    let mut acc = mesh_offset_term(c, state, starting, predict, forward, x, current_bits);
    // `x - x_ref` saturated to `i32`; the offset in the same sum (Q31: exact under the shift).
    let dx = x.saturating_sub(c.x_ref_counts);
    acc += (c.offset_q31 + dx as i64 * c.slope_q31 as i64) >> 7;
    acc += state.plays.step(c, state.dir as usize, x);
    if let Some((seg, t)) = hat(x, c.hat_start_counts, c.hat_recip_q32) {
        // Both hats under one shift (each product below 2^47).
        let mut hats = 0i64;
        if seg >= 1 {
            hats += (c.knot_um[seg - 1].to_bits() as i64) * (65536 - t) as i64;
        }
        if seg < N_KNOTS {
            hats += (c.knot_um[seg].to_bits() as i64) * t as i64;
        }
        acc += hats >> 8;
    }
    // Both harmonics and both currents under one shift, all Q32 (the currents' products below
    // 2^61: weights within MAX_ABS_UM).
    acc += (harmonic(phase(x, c.x_ref_counts, c.pitch_rate), &c.pitch)
        + harmonic(phase(x, c.x_ref_counts, c.turn_rate), &c.turn)
        + c.current_um_per_a.to_bits() as i64 * current_bits as i64
        + c.current_lp_um_per_a.to_bits() as i64 * state.current_lp_bits as i64)
        >> 8;
    // Saturated to `i32` first, then to the output's range: one `SSAT`.
    I16F16::from_bits(sat_i32(acc >> 8).clamp(OUT_BITS.0, OUT_BITS.1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The plain definition: every play clamped every tick, `sum (x - p) weight` in `i64`.
    fn naive(plays: &mut [i32; N_OPS], c: &Model4Coeffs, k: usize, x: i32) -> i64 {
        let mut acc = 0i64;
        for ((p, &w), &weight) in plays.iter_mut().zip(&c.widths_counts).zip(&c.weight_q24[k]) {
            *p = (*p).clamp(x - w, x + w);
            acc += (x - *p) as i64 * weight as i64;
        }
        acc
    }

    fn coeffs(widths_mm: [f64; N_OPS], weights: [(f64, f64); N_OPS]) -> Model4Coeffs {
        let mut m = Model4Params::zero(5.08, 5.08 * 28.0);
        m.widths_mm = widths_mm;
        for (j, (r, f)) in weights.into_iter().enumerate() {
            m.play_um_per_mm[j] = r;
            m.play_forward_um_per_mm[j] = f;
        }
        m.build(1868.0).expect("plays build")
    }

    /// The placement's prediction with the belt observer: from the offset now it approaches
    /// the rest of the direction of travel by `a 2^(-L / H1) + (1 - a) 2^(-L / H2)` (within
    /// 0.05 um of that in `f64`), a second prediction continues from the first, and the
    /// observer itself never moves.
    #[test]
    fn the_belt_prediction_approaches_the_rest_of_its_direction() {
        use crate::model::{estimate, estimate_with_current, ModelKind, ModelParams, ModelState};
        use crate::rig::Rig;
        let rig = Rig::PAPER;
        let cpm = rig.counts_per_mm();
        let (rest, half_mm, share) = ([-120.0, 135.0], [0.4, 8.0], 0.7);
        let mut p = ModelParams::PAPER;
        p.model4.belt = Some(BeltTerm {
            physics: BeltParams {
                m_per_count: 1e-3 / cpm,
                ..BeltParams::PAPER
            },
            tick_s: 1.0 / 2000.0,
            step_ticks: 6,
            weight: 1.0,
            rest_um: rest,
            half_travel_mm: half_mm,
            fast_share: share,
        });
        let c = p.build(&rig).unwrap();
        let mut s = ModelState::new(0);
        // Out and part of the way back, with a current that loads the belt.
        for k in 0..4000i32 {
            let x = if k < 3000 {
                k * 4
            } else {
                12_000 - (k - 3000) * 3
            };
            let a = I16F16::from_num(if k < 3000 { 1.5 } else { -1.0 });
            estimate_with_current(&c, ModelKind::Operator, &mut s, x, a);
        }
        let here = s.belt.now_counts();
        let o_now = s.belt.offset_um_bits() as f64 / 65536.0;
        let predict = |o: f64, from: i32, to: i32| {
            let r = rest[(to > from) as usize];
            let l_mm = (to - from).abs() as f64 / cpm;
            let k =
                share * (-l_mm / half_mm[0]).exp2() + (1.0 - share) * (-l_mm / half_mm[1]).exp2();
            r + (o - r) * k
        };
        let offset_after = |state: &ModelState| state.belt_rest.offset_bits as f64 / 65536.0;
        for target in [here, here + 1, here - 1_000, 20_000, -400_000, 2_000_000] {
            let mut copy = s.clone();
            estimate(&c, ModelKind::Operator, &mut copy, target);
            assert_eq!(copy.belt, s.belt, "the observer moved");
            let want = predict(o_now, here, target);
            let got = offset_after(&copy);
            assert!(
                (got - want).abs() <= 0.05,
                "to {target}: {got} against {want}"
            );
            // Through a stopping point, then back.
            estimate(&c, ModelKind::Operator, &mut copy, target - 5_000);
            let want = predict(want, target, target - 5_000);
            let got = offset_after(&copy);
            assert!(
                (got - want).abs() <= 0.05,
                "back from {target}: {got} against {want}"
            );
        }
        // Far enough, the offset rests at its direction's value.
        let mut copy = s.clone();
        estimate(
            &c,
            ModelKind::Operator,
            &mut copy,
            here + (400.0 * cpm) as i32,
        );
        assert!((offset_after(&copy) - rest[1]).abs() <= 0.05);
    }

    #[test]
    fn widths_must_increase() {
        let mut m = Model4Params::zero(5.08, 5.08 * 28.0);
        assert!(m.build(1868.0).is_ok());
        m.widths_mm.swap(1, 2);
        assert_eq!(
            m.build(1868.0),
            Err(ConfigError::NotMonotonic(ConfigField::Model4WidthsMm))
        );
        // Distinct in mm but one count on the drive: one play, refused as well.
        let mut m = Model4Params::zero(5.08, 5.08 * 28.0);
        m.widths_mm[1] = m.widths_mm[0] + 0.1 / 1868.0;
        assert_eq!(
            m.build(1868.0),
            Err(ConfigError::NotMonotonic(ConfigField::Model4WidthsMm))
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 512, failure_persistence: None, ..ProptestConfig::default() })]

        /// The plays give exactly the plain sum in `i64`, on either weight set, for any
        /// increasing widths, from either starting side, on walks with reversals of every
        /// size, standstills and jitter.
        #[test]
        fn the_plays_equal_the_plain_sum(
            first in 0.0006f64..0.5,
            ratios in prop::array::uniform3(1.0f64..2.5),
            weights in prop::array::uniform3((-60_000.0f64..60_000.0, -60_000.0f64..60_000.0)),
            x0 in -(1i32 << 24)..(1 << 24),
            forward in any::<bool>(),
            steps in prop::collection::vec((-20_000i32..=20_000, 0u32..4, 0usize..300), 1..40),
        ) {
            // Increasing by at least 1.9 counts (0.001 mm) each.
            let mut widths = [first; N_OPS];
            for j in 1..N_OPS {
                widths[j] = widths[j - 1] * ratios[j] + 0.001;
            }
            let c = coeffs(widths, weights);
            let dir = if forward { Direction::Forward } else { Direction::Reverse };
            let mut fast = Plays::NEW;
            fast.start(&c, dir, x0);
            let mut plain = [0i32; N_OPS];
            for (p, &w) in plain.iter_mut().zip(&c.widths_counts) {
                *p = if forward { x0 - w } else { x0 + w };
            }
            let mut x = x0;
            for (k, &(step, shape, n)) in steps.iter().enumerate() {
                for i in 0..n {
                    // A ramp, a standstill, or jitter of a count around it.
                    x += match shape {
                        0 | 1 => step.signum() * (step.abs() / n as i32).max(1),
                        2 => 0,
                        _ => if i % 2 == 0 { 1 } else { -1 },
                    };
                    // Both weight sets from the same state; the walk goes on with the reverse set.
                    for set in 0..2 {
                        let want = naive(&mut plain.clone(), &c, set, x);
                        prop_assert_eq!(fast.clone().step(&c, set, x), want, "walk {} tick {} x {}", k, i, x);
                    }
                    prop_assert_eq!(fast.step(&c, 0, x), naive(&mut plain, &c, 0, x));
                }
            }
        }

        /// At the ends of `i32` the plays stay within their width of `x`: the term stays
        /// within `sum |w weight|` whatever `x` does.
        #[test]
        fn the_plays_stay_bounded_at_the_ends_of_the_range(
            weights in prop::array::uniform3((-60_000.0f64..60_000.0, -60_000.0f64..60_000.0)),
            walk in prop::collection::vec(prop_oneof![
                Just(i32::MIN), Just(i32::MAX), any::<i32>(), (i32::MAX - 50_000)..=i32::MAX,
            ], 1..50),
        ) {
            let c = coeffs([0.01, 0.025, 0.06], weights);
            let bound: [i64; 2] = core::array::from_fn(|k| {
                c.widths_counts.iter().zip(&c.weight_q24[k]).map(|(&w, &v)| (w as i64 * v as i64).abs()).sum()
            });
            let mut plays = Plays::NEW;
            plays.start(&c, Direction::Forward, walk[0]);
            for (i, &x) in walk.iter().enumerate() {
                let term = plays.step(&c, i % 2, x);
                prop_assert!(term.abs() <= bound[i % 2]);
            }
        }
    }
}
