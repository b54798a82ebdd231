//! The reduced plant observer of the belt in fixed point: the port of `hil_sim::belt_observer`
//! (the `f64` original, measured there against the slip observer) for the drive's tick. Model 4
//! takes its mesh offset in the slip observer's place where calibration identified it
//! ([`super::operator::BeltTerm`]).
//!
//! One step per tick, from the motor counts and the drive's current:
//! 1. an alpha-beta-gamma tracking filter on the counts, its model acceleration the current's;
//! 2. the belt's force balance at the pulley (gear and spans as one dead-zone spring, teeth,
//!    the capstan friction of eq. 10 to second order in `alpha mu`, span damping) solved for
//!    the slip by two Newton steps from the last slip;
//! 3. the bristles (eq. 11 with the renewal term) relaxed exactly over the tick;
//! 4. the carriage (mass, guide Coulomb friction with its profile along the travel) by
//!    symplectic Euler.
//!
//! A step may span several ticks ([`BeltParams::build_every`], [`BeltState::tick`]); between
//! steps the offset is carried by the last step's slip per count ([`BeltState::offset_um_bits`]).
//!
//! # Fixed point
//! Lengths are metres in Q36: `i32` for the state (mesh offset, bristles, the carriage and the
//! tracking filter relative to the counts: +-31 mm at 1.5e-11 m), `i64` only for the carriage's
//! position along the travel, which sets the spans' lengths (Q16 metres). Velocities and slips
//! are Q36 metres per tick, accelerations Q36 metres per tick². Forces are Q16 newtons,
//! friction coefficients Q30, the bristles' relaxation per tick `lambda T` Q24 in a `u64`
//! (its exponential is 0 in Q30 from 64 on, but its inverse sets the bristles' steady state).
//! Build-time factors have up to 31 significant bits and a shift of at most 31 (`Gain`): one
//! `SMULL` and a 64-bit shift the M4 does in four instructions. The step's divisions (the
//! chain's stiffness, two Newton steps, the relaxation rate and its `(1 - e^-x) / x`) are
//! 32-bit `UDIV`s on 16-bit normalised divisors
//! ([`recip`]): 2^-15 relative, well inside what the physics is known to. The exponentials are
//! third-order polynomials below 1/64 and [`exp2_neg_q30`] above. Every operation saturates,
//! and no clamp or index can panic whatever the coefficients hold: any counts, current and
//! state give a defined state. The products stay within 64 bits for the coefficients
//! [`BeltParams::build_every`] makes and the calibration image's checks accept (a preload
//! times wrap beyond 28 kN or a `1 / L` not the belt's could overflow the capstan's slope).
//!
//! Against the `f64` observer on the same inputs: within 0.3 um (hil-sim's
//! `the_fixed_point_port_follows_the_f64_observer`); bit-identical on the Cortex-M4
//! (`tests/core_vectors.rs`); about 1,210 instructions a step in parts, 234 a tick at a step
//! every 6 ticks (README).

use super::convert::finite;
use super::fixmath::{exp2_neg_q30, sat_i32, Scale, ONE_Q30};
use crate::{ConfigError, ConfigField};

/// The observer's parameters, SI units, belt travel for the gear's (see `hil-sim`'s
/// `BeltPhysics`, which identifies them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BeltParams {
    /// Carriage mass, kg.
    pub mass_kg: f64,
    /// Guide Coulomb friction, N.
    pub guide_n: f64,
    /// Belt preload F-bar, N.
    pub preload_n: f64,
    /// Axial rigidity AE, N.
    pub axial_rigidity_n: f64,
    /// Belt free length L, m.
    pub length_m: f64,
    /// Span from pulley to carriage at x = 0, m.
    pub span_offset_m: f64,
    /// Wrap angle, rad.
    pub wrap_rad: f64,
    /// LuGre bristle stiffness, 1/m.
    pub sigma0_per_m: f64,
    /// Bristle damping, s/m.
    pub sigma1_s_per_m: f64,
    /// Viscous friction, s/m.
    pub sigma2_s_per_m: f64,
    /// Static friction coefficient.
    pub mu_static: f64,
    /// Kinetic friction coefficient.
    pub mu_kinetic: f64,
    /// Stribeck velocity, m/s.
    pub stribeck_m_per_s: f64,
    /// Renewal of the contact per metre of pulley travel, 1/m.
    pub kappa_per_m: f64,
    /// Half the tooth gap, m.
    pub half_gap_m: f64,
    /// Teeth stiffness, N/m.
    pub tooth_n_per_m: f64,
    /// Gear half backlash as belt travel, m.
    pub gear_half_m: f64,
    /// Gear stiffness as belt stiffness, N/m.
    pub gear_n_per_m: f64,
    /// Span damping, N s/m.
    pub span_damping_n_s_per_m: f64,
    /// Acceleration of the whole drive per ampere, belt m/s² per A.
    pub accel_per_a: f64,
    /// Belt metres per motor count.
    pub m_per_count: f64,
    /// The tracking filter's discount per tick (critically damped alpha-beta-gamma, gains
    /// from `t = discount^ticks` for a step of `ticks`): its bandwidth against the counts'
    /// quantisation, chosen by calibration per machine ([`TRACK_DISCOUNTS`]).
    pub track_discount: f64,
    /// The guide's friction along the travel less its mean (N at evenly spaced carriage
    /// positions, the first `guide_bins` of `guide_delta_n`), linear between, held flat beyond.
    pub guide_delta_n: [f64; MAX_GUIDE_BINS],
    /// See [`BeltParams::guide_delta_n`]; 0: a flat guide.
    pub guide_bins: usize,
    /// Carriage position of the first point and the points' spacing, m.
    pub guide_start_m: f64,
    /// See [`BeltParams::guide_start_m`].
    pub guide_step_m: f64,
}

/// Most points of the guide's friction profile.
pub const MAX_GUIDE_BINS: usize = 64;

/// Q36 metres: `2^36` per metre.
const M_Q36: f64 = (1u64 << 36) as f64;
/// One in Q28 (`alpha mu` and the capstan's factors).
const ONE_Q28: i64 = 1 << 28;
/// Cap of `lambda T`, Q24 (2^22: beyond the slip any tick can have with the physics `build`
/// accepts, and every product below stays in 64 bits).
const MAX_LAMBDA_Q24: u64 = 1 << 46;
/// `lambda T` from which `e^-lambda T` is 0 in Q30 (64, Q24).
const LAMBDA_ZERO_DECAY_Q24: u64 = 64 << 24;
/// log2(e) in Q30.
const LOG2_E_Q30: u64 = 1_549_082_005;
/// The tracking filter's discounts calibration tries ([`BeltParams::track_discount`]), the
/// first the default: measured on the five built-in plants, the coarser counts of a 500-line
/// encoder fit better at 0.97 (4.4 against 5.2 um), the paper rig's at 0.95 (4.5 against 5.7).
pub const TRACK_DISCOUNTS: [f64; 2] = [0.95, 0.97];
/// The discounts [`BeltParams::build_every`] accepts (within them every step of 1 to
/// [`MAX_STEP_TICKS`] ticks keeps the gains below 1, as the image requires).
pub const TRACK_DISCOUNT_RANGE: core::ops::RangeInclusive<f64> = 0.93..=0.999;
/// Most ticks in one step ([`BeltParams::build_every`]).
pub const MAX_STEP_TICKS: u32 = 16;
/// Newton steps per step.
pub const NEWTON_STEPS: u8 = 2;
/// The parts of a step: [`BeltState::begin`] (the tracking filter), then for
/// [`BeltState::advance`] the geometry, the Newton steps, the bristles and the carriage.
pub const STEP_PARTS: u8 = 4 + NEWTON_STEPS;
const PART_GEOMETRY: u8 = 1;
/// The bristles' part, which first commits the last Newton step's slip: the offset moves
/// here. (In the last Newton step's part, the heaviest, it made that tick 25 instructions
/// heavier; the state after the step is the same either way.)
pub const PART_COMMIT: u8 = PART_GEOMETRY + NEWTON_STEPS + 1;
const PART_BRISTLES: u8 = PART_COMMIT;
const PART_CARRIAGE: u8 = PART_BRISTLES + 1;
const _: () = assert!(PART_CARRIAGE + 1 == STEP_PARTS);

/// [`BeltState::tick`]'s schedule: for a step every `n` ticks ([`schedule`]), how many of the
/// step's parts have run by the end of each tick from the one that begins it. Balanced by
/// their cost measured on the Cortex-M4 (README, before the commit moved into the bristles'
/// part): `begin` 241 instructions, the geometry 160 (with the bristles' relaxation), the Newton
/// steps 259 and 274, the bristles 162, the carriage 138 at most. From 6 ticks a step on (the
/// last row) [`BeltState::tick`] runs one part a tick without the table.
const SCHEDULE: [[u8; 6]; 6] = [
    [6, 6, 6, 6, 6, 6],
    [3, 6, 6, 6, 6, 6],
    [2, 4, 6, 6, 6, 6],
    [2, 3, 4, 6, 6, 6],
    [1, 2, 3, 4, 6, 6],
    [1, 2, 3, 4, 5, 6],
];
const _: () = assert!(STEP_PARTS == 6);

/// Ticks from the one that begins a step to the one whose end shows its offset, for a step
/// every `ticks` ticks ([`BeltState::tick`]).
pub fn commit_latency_ticks(ticks: u32) -> u32 {
    schedule(ticks)
        .iter()
        .position(|&done| done > PART_COMMIT)
        .unwrap_or(0) as u32
}

/// [`SCHEDULE`]'s row for a step every `ticks` ticks (beyond 6, one part a tick).
fn schedule(ticks: u32) -> &'static [u8; 6] {
    &SCHEDULE[(ticks.clamp(1, 6) - 1) as usize]
}

/// Limits a machine's physics must keep for the formats above.
const MAX_LENGTH_M: f64 = 100.0;
const MAX_SMALL_M: f64 = 0.01;

/// The observer's build-time constants.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BeltCoeffs {
    pub(crate) m_per_count: Gain,
    pub(crate) accel: Gain,
    pub(crate) sigma0: Gain,
    pub(crate) sigma1_t: Gain,
    pub(crate) m1_t: Gain,
    pub(crate) inv_stribeck: Gain,
    pub(crate) kappa: Gain,
    pub(crate) damping_t: Gain,
    pub(crate) tt_per_m: Gain,
    pub(crate) tooth: Gain,
    pub(crate) span_per_ae_l: Gain,
    pub(crate) inv_length: Gain,
    pub(crate) mu_kinetic_q30: i32,
    pub(crate) dmu_q30: i32,
    /// `sigma0` and `sigma1 / T` as friction coefficient (Q30) per slip (Q36 m), times 2^8:
    /// the bristles' growth over the step in the balance ([`BeltState::advance`]).
    pub(crate) sigma0_q8: i32,
    pub(crate) sigma1_t_q8: i32,
    pub(crate) wrap_q28: i32,
    pub(crate) preload_q16: i32,
    pub(crate) preload_wrap_q16: i32,
    pub(crate) tooth_n_per_m: u32,
    pub(crate) damping_t_n_per_m: u32,
    pub(crate) gear_compliance_q56: u64,
    pub(crate) guide_q16: i32,
    pub(crate) guide_delta_q16: [i32; MAX_GUIDE_BINS],
    pub(crate) guide_bins: u32,
    pub(crate) guide_start_q16: i32,
    /// Q16 m to Q16 points.
    pub(crate) guide_per_step: Gain,
    pub(crate) half_gap_q36: i32,
    pub(crate) gear_half_q36: i32,
    pub(crate) length_q16: i32,
    pub(crate) span_offset_q16: i32,
    pub(crate) max_slip_q36: i32,
    pub(crate) jump_q36: i32,
    /// The tracking filter's gains in Q32 for one step: position `1 - t^3`, velocity
    /// `1.5 (1 - t)^2 (1 + t)`, acceleration `2 * 0.5 (1 - t)^3`. (In Q31 `i32`s, one `SMULL`
    /// each, the step measured 14 instructions more.)
    pub(crate) track_q32: [i64; 3],
    /// Ticks per step ([`BeltState::tick`]), 1 to [`MAX_STEP_TICKS`].
    pub(crate) every: u8,
}

impl BeltParams {
    /// The paper rig's physics (hil-sim's preset as `BeltPhysics::of` derives them, rounded): the on-target vectors' machine.
    pub const PAPER: BeltParams = BeltParams {
        mass_kg: 2.5,
        guide_n: 10.0,
        preload_n: 40.0,
        axial_rigidity_n: 2.0e5,
        length_m: 0.94,
        span_offset_m: 0.12,
        wrap_rad: core::f64::consts::PI,
        sigma0_per_m: 1360.0,
        sigma1_s_per_m: 5.0,
        sigma2_s_per_m: 0.05,
        mu_static: 0.45,
        mu_kinetic: 0.35,
        stribeck_m_per_s: 1e-3,
        kappa_per_m: 39.4,
        half_gap_m: 1.4e-4,
        tooth_n_per_m: 4e6,
        gear_half_m: 6.06e-6,
        gear_n_per_m: 3.82e6,
        span_damping_n_s_per_m: 15.0,
        accel_per_a: 4.9,
        m_per_count: 5.35e-7,
        track_discount: 0.95,
        guide_delta_n: [0.0; MAX_GUIDE_BINS],
        guide_bins: 0,
        guide_start_m: 0.0,
        guide_step_m: 0.01,
    };

    /// Checks every field and converts for a tick of `tick_s` seconds; errors name the field.
    pub fn build(&self, tick_s: f64) -> Result<BeltCoeffs, ConfigError> {
        self.build_every(tick_s, 1)
    }

    /// [`BeltParams::build`] for one step every `ticks` ticks (1 to [`MAX_STEP_TICKS`]): the
    /// caller steps with the ticks' mean current and holds the estimate between steps.
    pub fn build_every(&self, tick_s: f64, ticks: u32) -> Result<BeltCoeffs, ConfigError> {
        use ConfigField as F;
        if !(1..=MAX_STEP_TICKS).contains(&ticks) {
            return Err(ConfigError::OutOfRange(F::Model4BeltStepTicks));
        }
        let tick_s = positive_tick(tick_s)? * f64::from(ticks);
        let discount = finite(self.track_discount, F::Model4BeltTrackDiscount)?;
        if !TRACK_DISCOUNT_RANGE.contains(&discount) {
            return Err(ConfigError::OutOfRange(F::Model4BeltTrackDiscount));
        }
        let theta = (0..ticks).fold(1.0, |t, _| t * discount);
        let d = 1.0 - theta;
        // In [0, 1) for t in (0, 1): adding a half and truncating rounds (no `round` in
        // `core`).
        let q32 = |g: f64| (g * (1u64 << 32) as f64 + 0.5) as i64;
        let track_q32 = [
            q32(1.0 - theta * theta * theta),
            q32(1.5 * d * d * (1.0 + theta)),
            q32(d * d * d),
        ];
        let in_range = |v: f64, lo: f64, hi: f64, f: F| -> Result<f64, ConfigError> {
            let v = finite(v, f)?;
            if !(lo..=hi).contains(&v) {
                return Err(ConfigError::OutOfRange(f));
            }
            Ok(v)
        };
        let positive = |v: f64, hi: f64, f: F| -> Result<f64, ConfigError> {
            let v = in_range(v, 0.0, hi, f)?;
            if v == 0.0 {
                return Err(ConfigError::OutOfRange(f));
            }
            Ok(v)
        };
        let t = positive(tick_s, MAX_STEP_TICKS as f64, F::DriveRateHz)?;
        let mass = positive(self.mass_kg, 1e4, F::Model4BeltMassKg)?;
        let guide = in_range(self.guide_n, 0.0, 1e4, F::Model4BeltGuideN)?;
        let preload = positive(self.preload_n, 4e3, F::Model4BeltPreloadN)?;
        let ae = positive(self.axial_rigidity_n, 1e9, F::Model4BeltAxialRigidityN)?;
        let length = in_range(self.length_m, 3e-3, MAX_LENGTH_M, F::Model4BeltLengthM)?;
        let offset = in_range(self.span_offset_m, 0.0, length, F::Model4BeltSpanOffsetM)?;
        let wrap = positive(self.wrap_rad, 7.0, F::Model4BeltWrapRad)?;
        // Below 100 /m the bristles' deflection leaves the Q36 `i32` (+-31 mm).
        let sigma0 = in_range(self.sigma0_per_m, 100.0, 1e8, F::Model4BeltSigma0PerM)?;
        let sigma1 = in_range(self.sigma1_s_per_m, 0.0, 1e4, F::Model4BeltSigma1SPerM)?;
        let sigma2 = in_range(self.sigma2_s_per_m, 0.0, 1e4, F::Model4BeltSigma2SPerM)?;
        let mu_k = positive(self.mu_kinetic, 1.0, F::Model4BeltMuKinetic)?;
        let mu_s = in_range(self.mu_static, mu_k, 1.0, F::Model4BeltMuStatic)?;
        let stribeck = positive(self.stribeck_m_per_s, 10.0, F::Model4BeltStribeckMPerS)?;
        let kappa = in_range(self.kappa_per_m, 0.0, 1e6, F::Model4BeltKappaPerM)?;
        let half_gap = positive(self.half_gap_m, MAX_SMALL_M, F::Model4BeltHalfGapM)?;
        let tooth = positive(self.tooth_n_per_m, 1e9, F::Model4BeltToothNPerM)?;
        let gear_half = in_range(self.gear_half_m, 0.0, MAX_SMALL_M, F::Model4BeltGearHalfM)?;
        let gear = positive(self.gear_n_per_m, 1e9, F::Model4BeltGearNPerM)?;
        let damping = in_range(
            self.span_damping_n_s_per_m,
            0.0,
            1e5,
            F::Model4BeltSpanDampingNSPerM,
        )?;
        let accel = in_range(self.accel_per_a, 0.0, 1e5, F::Model4BeltAccelPerA)?;
        // A count beyond 0.1 mm is a jump to the tracking filter (1 mm).
        let mpc = positive(self.m_per_count, 1e-4, F::Model4BeltMPerCount)?;
        if self.guide_bins > MAX_GUIDE_BINS {
            return Err(ConfigError::TableSize(F::Model4BeltGuideProfileN));
        }
        let mut guide_delta_q16 = [0i32; MAX_GUIDE_BINS];
        for (q16, &n) in guide_delta_q16
            .iter_mut()
            .zip(&self.guide_delta_n[..self.guide_bins])
        {
            let n = in_range(n, -1e4, 1e4, F::Model4BeltGuideProfileN)?;
            *q16 = q(n, 16.0, F::Model4BeltGuideProfileN)?;
        }
        let guide_start = in_range(
            self.guide_start_m,
            -MAX_LENGTH_M,
            MAX_LENGTH_M,
            F::Model4BeltGuideProfileStartM,
        )?;
        let guide_step = in_range(
            self.guide_step_m,
            1e-3,
            MAX_LENGTH_M,
            F::Model4BeltGuideProfileStepM,
        )?;
        let scale = Gain::new;
        let q30_per_q36 = 1.0 / 64.0;
        Ok(BeltCoeffs {
            m_per_count: scale(mpc * M_Q36, F::Model4BeltMPerCount)?,
            // Current in I16F16 amperes.
            accel: scale(accel * t * t * M_Q36 / 65536.0, F::Model4BeltAccelPerA)?,
            sigma0: scale(sigma0 * q30_per_q36, F::Model4BeltSigma0PerM)?,
            sigma1_t: scale(sigma1 / t * q30_per_q36, F::Model4BeltSigma1SPerM)?,
            m1_t: scale(
                (sigma1 + sigma2) / t * q30_per_q36,
                F::Model4BeltSigma2SPerM,
            )?,
            inv_stribeck: scale(
                1.0 / (stribeck * t) * 65536.0 / M_Q36,
                F::Model4BeltStribeckMPerS,
            )?,
            kappa: scale(kappa * (1u64 << 24) as f64 / M_Q36, F::Model4BeltKappaPerM)?,
            damping_t: scale(
                damping / t * 65536.0 / M_Q36,
                F::Model4BeltSpanDampingNSPerM,
            )?,
            tt_per_m: scale(t * t / mass * M_Q36 / 65536.0, F::Model4BeltMassKg)?,
            tooth: scale(tooth * 65536.0 / M_Q36, F::Model4BeltToothNPerM)?,
            // l1 l2 in Q18 m² to the compliance in Q56 m/N (AE L above 256 N m).
            span_per_ae_l: scale(
                (1u64 << 38) as f64 / (ae * length),
                F::Model4BeltAxialRigidityN,
            )?,
            // l1 in Q16 m to l1 / L in Q30.
            inv_length: scale((1u64 << 14) as f64 / length, F::Model4BeltLengthM)?,
            mu_kinetic_q30: q_positive(mu_k, 30.0, F::Model4BeltMuKinetic)?,
            sigma0_q8: q(sigma0 * q30_per_q36, 8.0, F::Model4BeltSigma0PerM)?,
            sigma1_t_q8: q(sigma1 / t * q30_per_q36, 8.0, F::Model4BeltSigma1SPerM)?,
            dmu_q30: q(mu_s - mu_k, 30.0, F::Model4BeltMuStatic)?,
            wrap_q28: q_positive(wrap, 28.0, F::Model4BeltWrapRad)?,
            preload_q16: q_positive(preload, 16.0, F::Model4BeltPreloadN)?,
            preload_wrap_q16: q_positive(preload * wrap, 16.0, F::Model4BeltPreloadN)?,
            tooth_n_per_m: tooth as u32,
            damping_t_n_per_m: (damping / t).min(u32::MAX as f64) as u32,
            gear_compliance_q56: ((1u64 << 56) as f64 / gear) as u64,
            guide_q16: q(guide, 16.0, F::Model4BeltGuideN)?,
            guide_delta_q16,
            guide_bins: self.guide_bins as u32,
            guide_start_q16: q(guide_start, 16.0, F::Model4BeltGuideProfileStartM)?,
            guide_per_step: scale(1.0 / guide_step, F::Model4BeltGuideProfileStepM)?,
            half_gap_q36: q_positive(half_gap, 36.0, F::Model4BeltHalfGapM)?,
            gear_half_q36: q(gear_half, 36.0, F::Model4BeltGearHalfM)?,
            length_q16: q(length, 16.0, F::Model4BeltLengthM)?,
            span_offset_q16: q(offset, 16.0, F::Model4BeltSpanOffsetM)?,
            max_slip_q36: q((10.0 * t).min(MAX_SMALL_M / 2.0), 36.0, F::DriveRateHz)?,
            jump_q36: (1e-3 * M_Q36) as i32,
            track_q32,
            every: ticks as u8,
        })
    }
}

/// The drive's tick, checked before it is multiplied by the ticks of a step.
fn positive_tick(tick_s: f64) -> Result<f64, ConfigError> {
    if !tick_s.is_finite() {
        return Err(ConfigError::NotFinite(ConfigField::DriveRateHz));
    }
    if tick_s <= 0.0 || tick_s > 1.0 {
        return Err(ConfigError::OutOfRange(ConfigField::DriveRateHz));
    }
    Ok(tick_s)
}

/// [`q`] of a value that must stay above 0 in its format (the image refuses a 0 there).
fn q_positive(v: f64, bits: f64, f: ConfigField) -> Result<i32, ConfigError> {
    match q(v, bits, f)? {
        0 => Err(ConfigError::OutOfRange(f)),
        v => Ok(v),
    }
}

/// `v * 2^bits` rounded, if it fits an `i32`.
fn q(v: f64, bits: f64, f: ConfigField) -> Result<i32, ConfigError> {
    let scaled = v * super::fixmath::pow2(bits as i32);
    super::fixmath::round_i32(scaled).ok_or(ConfigError::OutOfRange(f))
}

/// A positive build-time factor `mant 2^-shift`, `mant` below `2^31` (an `i32` for one
/// `SMULL`) and `shift` in `1..=31`, so that it is applied with one 64-bit shift the M4 does in
/// four 32-bit instructions (a shift by a variable amount that may reach 32 costs about ten, and
/// a step applies some twenty factors). Factors from 2^-1 up carry 31 significant bits; smaller
/// ones `31 + log2 factor` (the smallest physics `build` accepts keep 20 or more), and below
/// 2^-32 a factor multiplies to 0.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Gain {
    pub(crate) mant: i32,
    pub(crate) shift: u8,
}

/// [`Gain`]'s largest shift.
pub(crate) const GAIN_MAX_SHIFT: u8 = 31;

impl Gain {
    fn new(v: f64, f: ConfigField) -> Result<Gain, ConfigError> {
        let s = Scale::from_f64(v, f)?;
        if s.mant < 2 {
            // 0 (or below 2^-62): multiplies to 0.
            return Ok(Gain { mant: 0, shift: 1 });
        }
        if s.shift < 2 {
            return Err(ConfigError::OutOfRange(f));
        }
        // 31 significant bits, then as many as a shift of at most 31 keeps (rounded).
        let (mant, shift) = ((s.mant >> 1) as u64, s.shift - 1);
        if shift <= GAIN_MAX_SHIFT {
            return Ok(Gain {
                mant: mant as i32,
                shift,
            });
        }
        let drop = u32::from(shift - GAIN_MAX_SHIFT).min(40);
        let mant = (mant + (1 << (drop - 1))) >> drop;
        Ok(Gain {
            // At most 2^30 after rounding: fits.
            mant: mant as i32,
            shift: GAIN_MAX_SHIFT,
        })
    }
}

/// `p >> sh` for `sh` in `1..=63` from 32-bit shifts (`sh = 0` counts as 1).
#[inline(always)]
fn shr64(p: u64, sh: u32) -> u64 {
    let (hi, lo) = ((p >> 32) as u32, p as u32);
    if sh >= 32 {
        (hi >> (sh - 32).min(31)) as u64
    } else {
        let sh = sh.max(1);
        ((hi >> sh) as u64) << 32 | ((lo >> sh) | (hi << (32 - sh))) as u64
    }
}

/// `floor(v * g)`: one `SMULL` and a 64-bit shift by less than 32.
#[inline(always)]
fn mul(g: Gain, v: i32) -> i64 {
    // `Gain` keeps the shift in 1..=31; the mask tells the compiler so.
    (v as i64 * g.mant as i64) >> (g.shift & 31)
}

/// [`mul`] saturated to `i32`.
#[inline(always)]
fn mul32(g: Gain, v: i32) -> i32 {
    sat_i32(mul(g, v))
}

/// `1 / d ~ m 2^-e` with `m` in `(2^16, 2^17)`: one 32-bit `UDIV` on the top 16 bits of `d`
/// (relative error below 2^-15). `d = 0` counts as 1.
#[inline]
pub fn recip(d: u64) -> (u32, u32) {
    let n = 63 - (d | 1).leading_zeros();
    let top = if n > 15 {
        shr64(d, n - 15) as u32
    } else {
        (d as u32) << (15 - n)
    };
    // `top` is in [2^15, 2^16); or-ing the bit in lets the compiler drop the zero check.
    (u32::MAX / (top | 0x8000), n + 17)
}

/// [`recip`] of a 32-bit `d` (one `CLZ`).
#[inline(always)]
fn recip32(d: u32) -> (u32, u32) {
    let n = 31 - (d | 1).leading_zeros();
    let top = if n > 15 { d >> (n - 15) } else { d << (15 - n) };
    (u32::MAX / (top | 0x8000), n + 17)
}

/// `num 2^s / d` for `(m, e) = recip(d)`, truncated towards 0, saturated to `i32`.
#[inline]
fn div(num: i32, (m, e): (u32, u32), s: u32) -> i32 {
    let a = num.unsigned_abs() as u64 * m as u64; // < 2^48
    let r = if e > s {
        shr64(a, e - s).min(i32::MAX as u64)
    } else if e == s {
        a.min(i32::MAX as u64)
    } else if s - e >= 31 || a >> (31 - (s - e)) != 0 {
        i32::MAX as u64
    } else {
        a << (s - e)
    } as i32;
    if num < 0 {
        -r
    } else {
        r
    }
}

/// Q36 metres to I16F16 micrometres (`1e6 / 2^20 = 15625 / 2^14` exactly), rounded.
#[inline(always)]
fn to_um_bits(q36: i32) -> i32 {
    sat_i32((q36 as i64 * 15625 + (1 << 13)) >> 14)
}

#[inline(always)]
fn dead_zone(d: i32, h: i32) -> i32 {
    if d > h {
        d - h
    } else if d < -h {
        d + h
    } else {
        0
    }
}

/// The observer's state (a few words; `Copy` for the drive's double buffering). The tracking
/// filter and the carriage are kept relative to the counts (`i32`): only the spans' lengths
/// need the absolute position.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BeltState {
    /// The counts of the last step.
    counts: i32,
    /// Tracking filter: position less the counts' (Q36 m), velocity (per tick), disturbance
    /// acceleration (per tick²).
    track: [i32; 3],
    /// Carriage less the tracked motor position, Q36 m, and its velocity, Q36 m per tick.
    d: i32,
    v: i32,
    /// Mesh offset and bristle deflection, Q36 m.
    o: i32,
    z: i32,
    /// The last slip, Q36 m per tick, and its part of the bristles' relaxation, Q24.
    du: i32,
    slide: u64,
    /// A step begun and not yet ended.
    pending: Pending,
    /// The latest counts ([`BeltState::tick`] or [`BeltState::begin`]), to which
    /// [`BeltState::offset_um_bits`] carries the committed step's slip.
    now_counts: i32,
    /// The committed step's counts at its begin, its slip per count (Q36 m) and the most
    /// counts it is carried over either way (twice the step's: the carried slip is at most
    /// twice the step's).
    ahead_counts: i32,
    ahead_per_count: i32,
    ahead_most_counts: i32,
    /// [`BeltState::tick`]: ticks since the last step began and their current's sum (I16F16
    /// amperes).
    ticks: u32,
    current_sum: i32,
}

/// What a step's parts pass on ([`BeltState::advance`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Pending {
    /// The next part; 0: none (the step has ended).
    next: u8,
    /// The tracked motor's travel over the step less the carriage's velocity at its start
    /// (per step), Q36 m: the spans' stretch rate with no slip (the Newton steps and the
    /// carriage take it with the slip).
    ds_less_v: i32,
    /// The counts' travel over the step; 0 after a jump.
    dcounts: i32,
    /// The carriage along the travel, Q16 m.
    x16: i32,
    /// The chain's stiffness (N/m) and `l1 / L - 1/2` (Q30) there.
    k_chain: u32,
    ratio: i32,
    /// The bristles' relaxation over the step at the rate it begins with, Q24; then, from the
    /// geometry part on, its decay `e^-l` and `(1 - e^-l) / l`, Q30.
    lambda: u64,
    decay: i32,
    phi: i32,
    /// The bristles' friction coefficient with no slip, Q30: at the step's start from `begin`,
    /// at its end from the geometry part on; and its growth per slip there (Q30 per Q36 m,
    /// times 2^8) beside the damping's.
    m0: i32,
    kz_q8: i32,
    /// Motor less carriage, Q36 m.
    rel: i32,
    /// The slip being solved for, Q36 m per tick.
    du: i32,
}

impl Pending {
    const NONE: Pending = Pending {
        next: 0,
        ds_less_v: 0,
        dcounts: 0,
        x16: 0,
        k_chain: 0,
        ratio: 0,
        lambda: 0,
        decay: 0,
        phi: 0,
        m0: 0,
        kz_q8: 0,
        rel: 0,
        du: 0,
    };
}

impl BeltState {
    /// Nothing observed: a value to hold until [`BeltState::new`] starts the observer.
    pub const ZERO: BeltState = BeltState {
        counts: 0,
        track: [0; 3],
        d: 0,
        v: 0,
        o: 0,
        z: 0,
        du: 0,
        slide: 0,
        pending: Pending::NONE,
        now_counts: 0,
        ahead_counts: 0,
        ahead_per_count: 0,
        ahead_most_counts: 0,
        ticks: 0,
        current_sum: 0,
    };

    /// At rest at motor position `counts`, on the forward flanks and unloaded.
    pub fn new(c: &BeltCoeffs, counts: i32) -> BeltState {
        BeltState {
            counts,
            track: [0; 3],
            d: -c.half_gap_q36.saturating_add(c.gear_half_q36),
            v: 0,
            o: c.half_gap_q36,
            z: 0,
            du: 0,
            slide: 0,
            pending: Pending::default(),
            now_counts: counts,
            ahead_counts: counts,
            ahead_per_count: 0,
            ahead_most_counts: 0,
            ticks: 0,
            current_sum: 0,
        }
    }

    /// [`BeltState::new`] on the flanks that motion in the registered direction leans on
    /// (reverse: the mirror image, gear and teeth on their other flanks), for an observer
    /// started after a move.
    pub fn start(c: &BeltCoeffs, counts: i32, forward: bool) -> BeltState {
        let mut s = BeltState::new(c, counts);
        if !forward {
            s.d = c.half_gap_q36.saturating_add(c.gear_half_q36);
            s.o = c.half_gap_q36.saturating_neg();
        }
        s
    }

    /// One tick of the drive: a step begins every [`BeltParams::build_every`] ticks, on this
    /// tick's counts and the mean current of the ticks since the last, and its parts run over
    /// the ticks that follow ([`SCHEDULE`]); the offset moves [`commit_latency_ticks`] after
    /// the step begins. The same inputs give the same state as [`BeltState::step`] on each
    /// step's counts and mean current.
    pub fn tick(&mut self, c: &BeltCoeffs, counts: i32, current_bits: i32) {
        // `build_every` and the image keep `every` in 1..=16; a 0 would begin a step every
        // tick (and divide by 1).
        let every = u32::from(c.every);
        self.now_counts = counts;
        self.ticks += 1;
        // Saturates only beyond 2^31 / 16 bits (2,048 A) a tick; `SDIV`, not a 64-bit call.
        self.current_sum = self.current_sum.saturating_add(current_bits);
        // From 6 ticks a step on (the schedule's last row, without the table): `begin` alone
        // on its tick, then one part a tick.
        let one_a_tick = every >= STEP_PARTS as u32;
        let since = if self.ticks >= every {
            let mean = self.current_sum / every.max(1) as i32;
            self.begin(c, counts, mean);
            (self.ticks, self.current_sum) = (0, 0);
            if one_a_tick {
                return;
            }
            0
        } else {
            self.ticks
        };
        if one_a_tick {
            if self.pending.next != 0 {
                self.advance(c);
            }
            return;
        }
        let want = schedule(every)[(since as usize).min(STEP_PARTS as usize - 1)];
        while self.parts_done() < want {
            self.advance(c);
        }
    }

    /// No step is part-way (the error is the last step's, not a part of one).
    pub fn step_ended(&self) -> bool {
        self.pending.next == 0
    }

    /// Parts of the last step that have run (all of them once it has ended).
    fn parts_done(&self) -> u8 {
        match self.pending.next {
            0 => STEP_PARTS,
            n => n,
        }
    }

    /// Mesh offset in I16F16 micrometres at the latest counts: the committed step's offset,
    /// carried forward by its slip per count over the counts since that step began (a step
    /// every few ticks holds its offset for as long, and its inputs are older still), at most
    /// twice that slip either way. Measured on the paper rig, a step every 4 ticks, identified
    /// (README): fig18 5.2 -> 3.6 um, generated mean square 11.5 -> 10.3 um. At a step every
    /// tick nothing is carried.
    #[inline(always)]
    pub fn offset_um_bits(&self) -> i32 {
        to_um_bits(self.offset_q36())
    }

    /// [`BeltState::offset_um_bits`] in Q36 metres, not rounded to micrometres.
    #[inline(always)]
    pub fn offset_q36(&self) -> i32 {
        let most = self.ahead_most_counts;
        // `min` then `max`, not `clamp`: no panic path (`most` is at least 0).
        let since = self
            .now_counts
            .wrapping_sub(self.ahead_counts)
            .min(most)
            .max(most.wrapping_neg());
        let ahead = sat_i32(self.ahead_per_count as i64 * since as i64);
        self.o.saturating_add(ahead)
    }

    /// The latest counts the observer was given.
    pub fn now_counts(&self) -> i32 {
        self.now_counts
    }

    /// The committed step's mesh offset, not carried forward ([`BeltState::offset_um_bits`]),
    /// I16F16 micrometres.
    pub fn step_offset_um_bits(&self) -> i32 {
        to_um_bits(self.o)
    }

    /// Carriage less the motor's belt position (the tracked one), I16F16 micrometres.
    pub fn error_um_bits(&self) -> i32 {
        to_um_bits(self.d)
    }

    /// The chain's stiffness at carriage position `x16` (Q16 m), N/m, and `l1 / L - 1/2` in
    /// Q30.
    #[inline(always)]
    fn geometry(c: &BeltCoeffs, x16: i32) -> (u32, i32) {
        const MM_Q16: i32 = 66; // 1 mm, rounded up
        let l1 = c
            .span_offset_q16
            .saturating_add(x16)
            .min(c.length_q16 - MM_Q16)
            .max(MM_Q16);
        let l2 = (c.length_q16 - l1).max(MM_Q16);
        // l1 l2 < 2^46 in Q32 m²; Q18 fits a u32.
        let p = ((l1 as u64 * l2 as u64) >> 14) as u32;
        // A `Gain` (non-negative mantissa, shift within 31) on an unsigned length product.
        let compliance = ((p as u64 * c.span_per_ae_l.mant as u64) >> (c.span_per_ae_l.shift & 31))
            .saturating_add(c.gear_compliance_q56);
        // 2^56 / compliance, N/m.
        let (m, e) = recip(compliance);
        let k = if e >= 56 {
            m >> (e - 56).min(31)
        } else if e + 15 <= 56 {
            u32::MAX
        } else {
            m << (56 - e)
        };
        let ratio = mul32(c.inv_length, l1) - (1 << 29);
        (k, ratio)
    }

    /// The guide's friction less its mean at carriage position `x16` (Q16 m), N Q16.
    #[inline(always)]
    fn guide_profile(c: &BeltCoeffs, x16: i32) -> i32 {
        // Held within the table whatever the coefficients hold: no panic path.
        let n = (c.guide_bins as usize).min(MAX_GUIDE_BINS);
        let d = &c.guide_delta_q16;
        if n < 2 {
            return if n == 1 { d[0] } else { 0 };
        }
        // Q16 points from the first, held within the table.
        let pos = mul(c.guide_per_step, x16.saturating_sub(c.guide_start_q16))
            .min(((n - 1) as i64) << 16)
            .max(0) as u32;
        let k = ((pos >> 16) as usize).min(n - 2);
        let t = (pos - ((k as u32) << 16)) as i64;
        let (a, b) = (d[k] as i64, d[k + 1] as i64);
        (a + (((b - a) * t) >> 16)) as i32
    }

    /// The slip's part of the bristles' relaxation over the tick `sigma0 |du| / g(u)`, Q24.
    #[inline]
    fn slide(c: &BeltCoeffs, du: i32) -> u64 {
        // (u / v_s)² in Q32, capped at 49 (e^-49 is 0 in Q30).
        let r = mul32(c.inv_stribeck, du).unsigned_abs().min(7 << 16) as u64;
        let s = r * r;
        let e = if s < 1 << 26 {
            // Below 1/64: e^-s to third order (error below 3 units of Q30), no table.
            let s = (s >> 2) as i32; // Q30, < 2^24
            let s2 = ((s as i64 * s as i64) >> 30) as i32;
            let s3 = ((s2 as i64 * s as i64) >> 30) as i32;
            ONE_Q30 as i32 - s + s2 / 2 - s3 / 6
        } else {
            exp2_neg_q30(((s >> 8) * LOG2_E_Q30) >> 22) as i32
        };
        let g = c.mu_kinetic_q30 + ((c.dmu_q30 as i64 * e as i64) >> 30) as i32;
        // sigma0 |du| in Q30 (up to 2^46, 65536), over g in Q30, to Q24.
        let num = (mul(c.sigma0, du).unsigned_abs()).min(1 << 46);
        let (m, e) = recip32(g.max(1074) as u32);
        shr64(num * m as u64, e - 24).min(MAX_LAMBDA_Q24)
    }

    /// One step to motor position `counts` (unwrapped) with the drive's current in I16F16
    /// amperes: [`BeltState::begin`] and every part of [`BeltState::advance`] at once.
    pub fn step(&mut self, c: &BeltCoeffs, counts: i32, current_bits: i32) {
        self.begin(c, counts, current_bits);
        while !self.advance(c) {}
    }

    /// Starts a step (finishing one still pending first) and runs its first part, the
    /// tracking filter: the inputs are taken here, so a step spread over ticks by
    /// [`BeltState::advance`] ends in the same state as [`BeltState::step`]. Until it ends, the
    /// offset is the last step's (it moves at part [`PART_COMMIT`]) and the error is partial.
    pub fn begin(&mut self, c: &BeltCoeffs, counts: i32, current_bits: i32) {
        if self.pending.next != 0 {
            while !self.advance(c) {}
        }
        // Tracking filter, per-tick units, relative to the counts: the prediction less this
        // tick's counts is the last position less the travel of the counts since.
        let mut dcounts = counts.wrapping_sub(self.counts);
        let travel = mul(c.m_per_count, dcounts);
        self.counts = counts;
        self.now_counts = counts;
        let [e0, v0, a0] = self.track;
        let a = a0.saturating_add(mul32(c.accel, current_bits));
        let pred = e0 as i64 + v0 as i64 + (a >> 1) as i64 - travel;
        let ds;
        if pred.unsigned_abs() >= c.jump_q36 as u64 {
            // A jump (restart, wild count): the filter restarts there and the carriage moves
            // with it; the pulley did not travel under the belt.
            self.track = [0; 3];
            ds = 0;
            dcounts = 0;
        } else {
            let r = -(pred as i32);
            let gain = |g: i64| ((g * r as i64 + (1 << 31)) >> 32) as i32;
            let e = pred as i32 + gain(c.track_q32[0]);
            self.track = [
                e,
                v0.saturating_add(a).saturating_add(gain(c.track_q32[1])),
                a0.saturating_add(gain(c.track_q32[2])),
            ];
            // The tracked motor's travel this tick.
            ds = sat_i32(travel).saturating_add(e - e0);
            // The carriage relative to the tracked motor.
            self.d = self.d.saturating_sub(ds);
        }
        let x = mul(c.m_per_count, counts) + self.track[0] as i64 + self.d as i64;
        let renew = mul(c.kappa, ds.saturating_abs()) as u64;
        // The relaxation rate of the last slip and this step's renewal: the bristles relax at
        // it over the whole step (the balance and the bristles' update agree on it).
        let lambda = (self.slide + renew).min(MAX_LAMBDA_Q24);
        // m0 = sigma0 z - sigma1 lambda z (Q30); lambda z in Q36 within 64 bits.
        let lz = sat_i32(if lambda < 1 << 30 {
            (lambda as i64 * self.z as i64) >> 24
        } else {
            ((lambda >> 16) as i64 * self.z as i64) >> 8
        });
        self.pending = Pending {
            next: PART_GEOMETRY,
            ds_less_v: ds.saturating_sub(self.v),
            dcounts,
            x16: sat_i32(x >> 20),
            k_chain: 0,
            ratio: 0,
            lambda,
            decay: 0,
            phi: 0,
            kz_q8: 0,
            m0: sat_i32(mul(c.sigma0, self.z) - mul(c.sigma1_t, lz)),
            // Motor less carriage.
            rel: self.d.saturating_neg(),
            du: self.du,
        };
    }

    /// Runs the pending step's next part; `true` once none is left (the step has ended). The
    /// parts after [`BeltState::begin`]: the geometry, each Newton step, the bristles (which
    /// first commit the slip: [`PART_COMMIT`]), the carriage: [`STEP_PARTS`] in all.
    pub fn advance(&mut self, c: &BeltCoeffs) -> bool {
        let p = &mut self.pending;
        match p.next {
            0 => return true,
            PART_GEOMETRY => {
                (p.k_chain, p.ratio) = Self::geometry(c, p.x16);
                // The bristles at the step's end, linear in the slip: `z e + du phi`. So the
                // balance's friction is `m0 e + (sigma0 phi - sigma1 / T (1 - e)) du` beside
                // the damping's (`sigma1 lambda phi = (1 - e) / T` keeps it bounded at any
                // rate). A step of several ticks needs it: with `z` held at its start, a step
                // every 6th tick left the plant's offset 45 um RMS away on fig18, 5.5 with it
                // (`f64`, the plant's physics; README).
                (p.decay, p.phi) = Self::relax(p.lambda);
                p.m0 = ((p.m0 as i64 * p.decay as i64) >> 30) as i32;
                let grow = (c.sigma0_q8 as i64 * p.phi as i64) >> 30;
                let damp = (c.sigma1_t_q8 as i64 * (ONE_Q30 as i64 - p.decay as i64)) >> 30;
                p.kz_q8 = sat_i32(grow - damp);
            }
            PART_BRISTLES => {
                // The commit (`PART_COMMIT`).
                self.du = p.du;
                self.o = self.o.saturating_add(p.du);
                // Slip per count, carried forward by `offset_um_bits` until the next commit
                // (`self.counts` is still this step's: the next begins later). Truncated to a
                // Q36 unit per count: over the counts a step holds, well under 0.1 um.
                let dc = p.dcounts;
                self.ahead_per_count = if dc == 0 { 0 } else { p.du.wrapping_div(dc) };
                self.ahead_counts = self.counts;
                // Twice |dc|, at most 2^31 - 2 (`dcounts` is a difference of `i32`s).
                self.ahead_most_counts = (dc.unsigned_abs().min((1 << 30) - 1) << 1) as i32;
                // z e^-l + du (1 - e^-l) / l, at the rate the step began with; the slip's part
                // of the next step's rate from this one's slip.
                self.slide = Self::slide(c, p.du);
                self.z = sat_i32(
                    ((self.z as i64 * p.decay as i64) >> 30) + ((p.du as i64 * p.phi as i64) >> 30),
                );
            }
            PART_CARRIAGE => {
                p.next = 0;
                let p = *p;
                self.carriage(c, p.k_chain as i64, p.rel, p.ds_less_v, p.du, p.x16);
                return true;
            }
            _ => {
                // A Newton step (on the offset not yet committed: `self.o` is the last step's).
                p.du = Self::newton(c, p, self.o);
            }
        }
        p.next += 1;
        false
    }

    /// One Newton step of the belt's force balance at the pulley from slip `p.du`.
    #[inline(always)]
    fn newton(c: &BeltCoeffs, p: &Pending, o: i32) -> i32 {
        let (k_chain, ratio, rel, ds_less_v, m0, kz_q8) =
            (p.k_chain, p.ratio, p.rel, p.ds_less_v, p.m0, p.kz_q8 as i64);
        let k_chain64 = k_chain as i64;
        let du = p.du;
        let o = o.saturating_add(du);
        let q = dead_zone(rel.saturating_sub(o), c.gear_half_q36);
        let f_chain = (k_chain64 * q as i64) >> 20;
        let k_c = if q == 0 { 0 } else { k_chain };
        let teeth = dead_zone(o, c.half_gap_q36);
        let f_teeth = mul(c.tooth, teeth);
        let k_t = if teeth == 0 { 0 } else { c.tooth_n_per_m };
        let mu = m0
            .saturating_add(sat_i32(mul(c.m1_t, du) + ((kz_q8 * du as i64) >> 8)))
            .clamp(-(ONE_Q30 as i32), ONE_Q30 as i32);
        let a = ((c.wrap_q28 as i64 * mu as i64) >> 30) as i32; // Q28
        let ac = ((a as i64 * ratio as i64) >> 30) as i32; // Q28
        let f_f = (c.preload_q16 as i64 * (a as i64 + ((a as i64 * ac as i64) >> 28))) >> 28;
        // N Q16 per unit of mu.
        let slope_f = sat_i32((c.preload_wrap_q16 as i64 * (ONE_Q28 + 2 * ac as i64)) >> 28);
        let rel_v = ds_less_v.saturating_sub(du);
        let damping = mul(c.damping_t, rel_v);
        let residual = sat_i32(f_chain + damping - f_teeth - f_f);
        // N/m; the capstan's through mu's slope in du (Q30 per Q36, Q16 -> Q10 N/m).
        let friction = (mul(c.m1_t, slope_f) + ((kz_q8 * slope_f as i64) >> 8)).max(0);
        let slope = k_c as u64 + k_t as u64 + (friction as u64 >> 10) + c.damping_t_n_per_m as u64;
        if slope == 0 {
            return du;
        }
        // N Q16 / (N/m) = m Q16; Q36 wanted.
        let step = div(residual, recip32(slope.min(u32::MAX as u64) as u32), 20);
        // `min` then `max`, not `clamp`: no panic path whatever the coefficients hold.
        du.saturating_add(step)
            .min(c.max_slip_q36)
            .max(c.max_slip_q36.saturating_neg())
    }

    /// The bristles' relaxation over the step at rate `lambda` (Q24): `e^-l` and
    /// `(1 - e^-l) / l`, Q30.
    #[inline(always)]
    fn relax(lambda: u64) -> (i32, i32) {
        let (decay, phi) = if lambda < 1 << 18 {
            // Below 1/64: e^-l and (1 - e^-l) / l to third order (error below 3 units of
            // Q30), no table and no division.
            let l = (lambda << 6) as i32; // Q30, < 2^24
            let l2 = ((l as i64 * l as i64) >> 30) as i32;
            let l3 = ((l2 as i64 * l as i64) >> 30) as i32;
            (
                ONE_Q30 as i32 - l + l2 / 2 - l3 / 6,
                ONE_Q30 as i32 - l / 2 + l2 / 6 - l3 / 24,
            )
        } else {
            let decay = if lambda >= LAMBDA_ZERO_DECAY_Q24 {
                0
            } else {
                exp2_neg_q30((lambda * LOG2_E_Q30) >> 22) as i32 // Q30
            };
            (decay, div(ONE_Q30 as i32 - decay, recip(lambda), 24)) // Q30
        };
        (decay, phi)
    }

    /// The carriage on the chain's force, Coulomb friction implicit.
    #[inline(always)]
    fn carriage(
        &mut self,
        c: &BeltCoeffs,
        k_chain64: i64,
        rel: i32,
        ds_less_v: i32,
        du: i32,
        x16: i32,
    ) {
        let q = dead_zone(rel.saturating_sub(self.o), c.gear_half_q36);
        let rel_v = ds_less_v.saturating_sub(du);
        let f = sat_i32(((k_chain64 * q as i64) >> 20) + mul(c.damping_t, rel_v));
        let v = self.v.saturating_add(mul32(c.tt_per_m, f));
        let guide = c
            .guide_q16
            .saturating_add(Self::guide_profile(c, x16))
            .max(0);
        let dv = mul32(c.tt_per_m, guide);
        self.v = if v > dv {
            v - dv
        } else if v < -dv {
            v + dv
        } else {
            0
        };
        self.d = self.d.saturating_add(self.v);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn tracking_gains_are_the_f64_observer_s() {
        // The gains of one tick, as first written; then a step of n ticks discounts 0.95^n.
        let one = BeltParams::PAPER.build(5e-4).unwrap().track_q32;
        assert_eq!(one, [612_569_711, 31_406_948, 536_871]);
        for n in [1u32, 2, 3, 7, MAX_STEP_TICKS] {
            let t = 0.95f64.powi(n as i32);
            let d = 1.0 - t;
            let g = [1.0 - t * t * t, 1.5 * d * d * (1.0 + t), d * d * d];
            let c = BeltParams::PAPER.build_every(5e-4, n).unwrap();
            for (q, g) in c.track_q32.iter().zip(g) {
                assert!((*q as f64 / 2f64.powi(32) - g).abs() < 1e-9, "{n}: {q} {g}");
            }
        }
        for n in [0, MAX_STEP_TICKS + 1] {
            assert_eq!(
                BeltParams::PAPER.build_every(5e-4, n),
                Err(ConfigError::OutOfRange(ConfigField::Model4BeltStepTicks))
            );
        }
        // Every discount of the range keeps the gains below 1 at the longest step, which the
        // image requires; beyond it, and not a number, refused by name.
        for d in [
            *TRACK_DISCOUNT_RANGE.start(),
            0.97,
            *TRACK_DISCOUNT_RANGE.end(),
        ] {
            let p = BeltParams {
                track_discount: d,
                ..BeltParams::PAPER
            };
            let c = p.build_every(5e-4, MAX_STEP_TICKS).unwrap();
            assert!(
                c.track_q32.iter().all(|&g| (0..=1 << 32).contains(&g)),
                "{d}"
            );
        }
        for d in [0.9, 1.0, f64::NAN] {
            let p = BeltParams {
                track_discount: d,
                ..BeltParams::PAPER
            };
            let field = ConfigField::Model4BeltTrackDiscount;
            assert!(
                p.build(5e-4) == Err(ConfigError::OutOfRange(field))
                    || p.build(5e-4) == Err(ConfigError::NotFinite(field)),
                "{d}"
            );
        }
        assert!((LOG2_E_Q30 as f64 / 2f64.powi(30) - core::f64::consts::LOG2_E).abs() < 1e-9);
    }

    #[test]
    fn reciprocal_within_2_pow_minus_15() {
        for d in [
            1u64,
            2,
            3,
            1000,
            65_535,
            65_536,
            1 << 40,
            u64::MAX,
            987_654_321_987,
        ] {
            let (m, e) = recip(d);
            let approx = m as f64 / 2f64.powi(e as i32);
            assert!((approx * d as f64 - 1.0).abs() < 2f64.powi(-15), "{d}");
            if let Ok(d32) = u32::try_from(d) {
                assert_eq!(recip32(d32), (m, e), "{d}");
            }
        }
    }

    #[test]
    fn bad_physics_is_refused_by_name() {
        let mut p = BeltParams::PAPER;
        p.mu_static = 0.1; // below kinetic
        assert_eq!(
            p.build(5e-4),
            Err(ConfigError::OutOfRange(ConfigField::Model4BeltMuStatic))
        );
        let mut p = BeltParams::PAPER;
        p.half_gap_m = f64::NAN;
        assert_eq!(
            p.build(5e-4),
            Err(ConfigError::NotFinite(ConfigField::Model4BeltHalfGapM))
        );
        let mut p = BeltParams::PAPER;
        p.mass_kg = 0.0;
        assert_eq!(
            p.build(5e-4),
            Err(ConfigError::OutOfRange(ConfigField::Model4BeltMassKg))
        );
    }

    #[test]
    fn a_reversal_moves_the_belt_across_the_gap() {
        let c = BeltParams::PAPER.build(5e-4).unwrap();
        let mut s = BeltState::new(&c, 0);
        let h_um = 140.0;
        let um = |s: &BeltState| s.offset_um_bits() as f64 / 65536.0;
        assert!((um(&s) - h_um).abs() < 0.01);
        // 50 mm/s forward for 0.2 s, then back: a 0.535 um count.
        let mut counts = 0i32;
        let amps = |a: f64| (a * 65536.0) as i32;
        for _ in 0..400 {
            counts += 47;
            s.step(&c, counts, amps(0.15));
        }
        let forward = um(&s);
        for _ in 0..2000 {
            counts -= 47;
            s.step(&c, counts, amps(-0.15));
        }
        let back = um(&s);
        assert!(forward > 100.0, "{forward}");
        assert!(back < forward - 100.0, "{forward} -> {back}");
    }

    proptest! {
        /// Any counts (small steps through the Newton path, wild ones through the jump), any
        /// current, and physics and step lengths drawn across the accepted ranges (those
        /// `build_every` accepts) give a defined state; in a debug build any overflow would panic here.
        #[test]
        fn any_input_gives_a_defined_state(
            start in any::<i32>(),
            steps in proptest::collection::vec((any::<i16>(), any::<bool>(), any::<i32>()), 1..300),
            (mass, sigma0, gap, preload, tooth) in (1e-3f64..1e4, 100.0f64..1e8, 1e-6f64..0.01, 0.1f64..4e3, 1e2f64..1e9),
            (kappa, wrap, ae, length) in (0.0f64..1e6, 0.1f64..7.0, 1.0f64..1e9, 3e-3f64..100.0),
            (sigma1, sigma2, damping, accel, mpc) in (0.0f64..1e4, 0.0f64..1e4, 0.0f64..1e5, 0.0f64..1e5, 1e-8f64..1e-4),
            (guide, bins, rate_hz, every) in (0.0f64..1e3, 0usize..=MAX_GUIDE_BINS, 500.0f64..20_000.0, 1u32..=MAX_STEP_TICKS),
        ) {
            let mut p = BeltParams {
                mass_kg: mass, sigma0_per_m: sigma0, half_gap_m: gap, preload_n: preload,
                tooth_n_per_m: tooth, kappa_per_m: kappa, wrap_rad: wrap,
                axial_rigidity_n: ae, length_m: length, span_offset_m: 0.1 * length,
                sigma1_s_per_m: sigma1, sigma2_s_per_m: sigma2,
                span_damping_n_s_per_m: damping, accel_per_a: accel, m_per_count: mpc,
                guide_n: guide, guide_bins: bins,
                ..BeltParams::PAPER
            };
            for (k, d) in p.guide_delta_n.iter_mut().enumerate() {
                *d = (k as f64 * 0.7).sin() * guide;
            }
            // Physics the formats cannot carry are refused by name; the rest run.
            let Ok(c) = p.build_every(1.0 / rate_hz, every) else { return Ok(()) };
            let mut s = BeltState::new(&c, start);
            let mut counts = start;
            for (delta, wild, amps) in steps {
                counts = if wild { amps } else { counts.wrapping_add(i32::from(delta)) };
                if wild {
                    s.step(&c, counts, amps);
                } else {
                    s.tick(&c, counts, amps);
                }
                let _ = (s.offset_um_bits(), s.error_um_bits());
            }
        }
    }

    /// A step spread over ticks ends where [`BeltState::step`] does on the step's counts and
    /// mean current; its offset moves [`commit_latency_ticks`] after the step begins, and no
    /// earlier.
    #[test]
    fn ticks_spread_the_step_and_end_where_it_does() {
        for every in 1..=MAX_STEP_TICKS {
            let c = BeltParams::PAPER.build_every(5e-4, every).unwrap();
            let latency = commit_latency_ticks(every);
            assert!(latency < every.max(1), "{every}: {latency}");
            let (mut ticked, mut whole) = (BeltState::new(&c, 0), BeltState::new(&c, 0));
            let (mut before, mut sum) = (whole, 0i64);
            let mut since_begin = None;
            let mut counts = 0i32;
            let mut moved = false;
            for t in 0..3000i32 {
                // Out and back at up to 47 counts a tick with the current of the motion.
                let v = ((t % 1200) - 600).signum() * (47 - ((t % 600) - 300).abs() / 8).max(0);
                counts += v;
                let bits = v * 2000 + (t % 7) * 300;
                sum += i64::from(bits);
                ticked.tick(&c, counts, bits);
                if (t + 1) % every as i32 == 0 {
                    before = whole;
                    whole.step(&c, counts, (sum / i64::from(every)) as i32);
                    sum = 0;
                    since_begin = Some(0);
                } else if let Some(k) = since_begin.as_mut() {
                    *k += 1;
                }
                let Some(k) = since_begin else {
                    continue;
                };
                let want = if k >= latency { &whole } else { &before };
                assert_eq!(
                    ticked.step_offset_um_bits(),
                    want.step_offset_um_bits(),
                    "{every} tick {t}"
                );
                moved |= before.step_offset_um_bits() != whole.step_offset_um_bits();
                if k + 1 == every {
                    assert_eq!(ticked.error_um_bits(), whole.error_um_bits(), "{every} {t}");
                    assert_eq!(
                        (ticked.o, ticked.z, ticked.d, ticked.v),
                        (whole.o, whole.z, whole.d, whole.v)
                    );
                }
            }
            assert!(moved, "{every}: the offset never moved");
        }
    }

    /// The carried slip's bound stays a count of at least 0 whatever the step's counts (a
    /// difference of `i32`s, up to 2^31 either way).
    #[test]
    fn the_carried_bound_is_never_negative() {
        let c = BeltParams::PAPER.build_every(5e-4, 6).unwrap();
        for dc in [i32::MIN, i32::MIN + 1, -(1 << 30), 1 << 30, i32::MAX] {
            let mut s = BeltState::new(&c, 0);
            s.begin(&c, 0, 0);
            s.pending.dcounts = dc;
            while !s.advance(&c) {}
            assert!(s.ahead_most_counts >= 0, "{dc}: {}", s.ahead_most_counts);
            s.now_counts = s.ahead_counts.wrapping_add(dc);
            let ahead = i64::from(s.offset_q36()) - i64::from(s.o);
            assert!(ahead.abs() <= 2 * i64::from(s.du).abs(), "{dc}: {ahead}");
        }
    }

    /// Between commits the offset is carried by the committed step's slip per count, at most
    /// twice that slip, and nothing at a standstill or at a step every tick. (What it gains is
    /// measured against the plant, in hil-sim.)
    #[test]
    fn the_offset_is_carried_by_the_counts_between_steps() {
        for every in [1u32, 4, 6] {
            let c = BeltParams::PAPER.build_every(5e-4, every).unwrap();
            let mut s = BeltState::new(&c, 0);
            let mut counts = 0i32;
            let mut carried = 0;
            for t in 0..2400i32 {
                // 40 counts a tick out, then back, then still.
                let v = if t < 800 {
                    40
                } else if t < 1600 {
                    -40
                } else {
                    0
                };
                counts += v;
                s.tick(&c, counts, v.signum() * 9830);
                let ahead = i64::from(s.offset_um_bits()) - i64::from(s.step_offset_um_bits());
                // Twice the step's slip, and the rounding of the two conversions.
                let cap = 2 * i64::from(to_um_bits(s.du).unsigned_abs() as i32) + 2;
                assert!(ahead.abs() <= cap, "{every} tick {t}: {ahead} > {cap}");
                if every == 1 || t >= 1600 + 2 * every as i32 {
                    assert_eq!(ahead, 0, "{every} tick {t}");
                }
                carried += usize::from(ahead != 0);
            }
            assert_eq!(
                carried > 0,
                every > 1,
                "{every}: carried on {carried} ticks"
            );
        }
    }

    /// Zero damping, renewal, viscous friction and acceleration per ampere are physics, not
    /// errors; realistic soft, short belts are carried.
    #[test]
    fn zeros_and_soft_short_belts_build() {
        let mut p = BeltParams::PAPER;
        p.sigma1_s_per_m = 0.0;
        p.sigma2_s_per_m = 0.0;
        p.kappa_per_m = 0.0;
        p.span_damping_n_s_per_m = 0.0;
        p.accel_per_a = 0.0;
        p.guide_n = 0.0;
        assert!(p.build(5e-4).is_ok());
        let mut p = BeltParams::PAPER;
        p.axial_rigidity_n = 1e4;
        p.length_m = 0.2;
        p.span_offset_m = 0.05;
        assert!(p.build(5e-4).is_ok());
    }
}
