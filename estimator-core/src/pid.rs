//! Position loop: PID on the motor encoder position with velocity and acceleration
//! feed-forward, giving a motor current command.
//!
//! Per tick, with `e = setpoint - measured` (counts):
//! ```text
//! current = kp e + I + D + kff_vel v_setpoint + kff_acc a_setpoint,  clamped to ±max_current
//! I      += ki e                      (only when that does not push a saturated output further)
//! D       = -kd lowpass(measured - measured_previous)
//! ```
//! - The derivative acts on the measurement, not on the error: a step of the setpoint (a new
//!   target, `reset`, a jump of the profile) then moves only the P term and never kicks the
//!   output. The D term is plain damping, `-kd × velocity`; in a move the velocity feed-forward
//!   is what pays for it, so `kff_vel` should be about `kd` plus the viscous friction.
//! - The measured velocity is low-pass filtered (first order, backward Euler
//!   `alpha = wT / (1 + wT)`, no `exp` needed in `core`): the encoder's one-count steps would
//!   otherwise reach the current as `kd` amperes of noise.
//! - Anti-windup by clamping (conditional integration): the integrator is frozen while the output
//!   is saturated and the error would push it further, and it never exceeds ±max_current.
//!   Chosen over back-calculation because it needs no extra tracking gain to tune, costs two
//!   compares, and leaves the integrator exactly where it was when saturation began, so recovery
//!   does not depend on how long the saturation lasted.
//! - `ki` multiplies the error before integration, so the integrator holds amperes and a gain
//!   change never steps the output.
//!
//! # Fixed-point formats
//! The datapath is 32-bit: each term is one `i32 x i32 -> i64` multiply (SMULL) shifted back to
//! an `i32` of I16F16 amperes, and the terms are summed with saturating adds (QADD). The ranges
//! are chosen so that no product needs saturating:
//! - following error I24F8 counts, saturated at ±2^22 counts (±2.2 m) for reporting and at
//!   ±32768 counts (±17.5 mm) inside P and I, where 8 A is reached at 0.8 mm anyway;
//! - measured velocity I16F16 counts/tick, saturated at ±2047 counts/tick (2.2 m/s at 2 kHz,
//!   beyond the motor at any rate >= 500 Hz); the setpoint's velocity (I16F16 after a shift) and
//!   acceleration (I8F24) need no saturation: a [`Setpoint`] is always within ±2048 counts/tick
//!   and ±64 counts/tick²;
//! - gains per count and per tick: `kp` I8F24 A/count (< 1), `ki` I1F31 A/(count·tick)
//!   (< 2^-8), `kd` and `kff_vel` I16F16 A/(count/tick) (< 16), `kff_acc` I16F16
//!   A/(count/tick²) (< 512); `build` names the field that does not fit;
//! - integrator I8F24 amperes, output I16F16 amperes, both within ±max_current (<= 127 A).

use crate::ConfigField;
use fixed::types::{I16F16, I1F31, I24F8, I8F24};

#[cfg(test)]
use crate::rig::Rig;
use crate::trajectory::Setpoint;
use crate::{BuildContext, ConfigError};

/// Gains and limits in SI units, converted by [`Config::build`]. All gains are `>= 0`; a zero
/// gain switches its term off.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Config {
    /// Proportional gain, amperes per millimetre of following error.
    pub kp_a_per_mm: f64,
    /// Integral gain, amperes per millimetre-second of following error.
    pub ki_a_per_mm_s: f64,
    /// Derivative gain on the measured velocity, amperes per mm/s.
    pub kd_a_s_per_mm: f64,
    /// Corner of the first-order low-pass on the measured velocity; `(0, rate_hz / 2]`.
    pub derivative_cutoff_hz: f64,
    /// Velocity feed-forward, amperes per mm/s of setpoint velocity.
    pub kff_vel_a_s_per_mm: f64,
    /// Acceleration feed-forward, amperes per mm/s² of setpoint acceleration.
    pub kff_acc_a_s2_per_mm: f64,
    /// Output limit, amperes (symmetric).
    pub max_current_a: f64,
}

impl Config {
    /// Defaults for the paper's rig: a 150 W brushed DC motor (24 V, Kt ≈ 30 mN·m/A, rotor
    /// ≈ 140 g·cm²) through 23.7:1 on a 20-tooth XL pulley (16.2 mm pitch radius) driving a 2 kg
    /// carriage. The belt sees ≈35 N/A (with 80 % gearbox efficiency) and an effective mass of
    /// ≈33 kg (the rotor reflects ≈31 kg through N²/r²): about 1.09 m/s² per ampere.
    ///
    /// - `kp` 10 A/mm and `kd` 0.12 A·s/mm: a 17 Hz closed loop with damping ≈0.6, well below the
    ///   belt's first resonance (tens of Hz) and 1/100 of the 2 kHz rate; 0.8 mm of error
    ///   saturates the 8 A.
    /// - `ki` 100 A/(mm·s): integral corner at ≈1.6 Hz, a decade below the loop, to remove the
    ///   friction offset.
    /// - derivative filter at 300 Hz: ≈3° of lag at the loop frequency; the one-count quantisation
    ///   of the velocity (0.13 A through `kd`) is halved.
    /// - `kff_vel` = `kd`, cancelling the damping of the D term at constant speed (friction is
    ///   left to the integrator); `kff_acc` 0.92 mA·s²/mm = effective mass / force per ampere.
    /// - 8 A: about 1.4 x the motor's continuous current; the gearbox, not the motor, limits peaks.
    pub const PAPER_RIG: Config = Config {
        kp_a_per_mm: 10.0,
        ki_a_per_mm_s: 100.0,
        kd_a_s_per_mm: 0.12,
        derivative_cutoff_hz: 300.0,
        kff_vel_a_s_per_mm: 0.12,
        kff_acc_a_s2_per_mm: 0.00092,
        max_current_a: 8.0,
    };

    /// Converts the SI gains into per-tick, per-count fixed-point coefficients for `ctx`.
    pub fn build(&self, ctx: &BuildContext) -> Result<Coeffs, ConfigError> {
        let rate = ctx.rate_hz();
        let counts_per_mm = ctx.rig().counts_per_mm();
        let kp_a_per_count = gain::<I8F24>(
            self.kp_a_per_mm,
            1.0 / counts_per_mm,
            1.0,
            ConfigField::PidKpAPerMm,
        )?;
        let ki_a_per_count_tick = gain::<I1F31>(
            self.ki_a_per_mm_s,
            1.0 / (counts_per_mm * rate),
            1.0 / 256.0,
            ConfigField::PidKiAPerMmS,
        )?;
        let kd_a_tick_per_count = gain::<I16F16>(
            self.kd_a_s_per_mm,
            rate / counts_per_mm,
            16.0,
            ConfigField::PidKdASPerMm,
        )?;
        let kff_vel_a_tick_per_count = gain::<I16F16>(
            self.kff_vel_a_s_per_mm,
            rate / counts_per_mm,
            16.0,
            ConfigField::PidKffVelASPerMm,
        )?;
        let kff_acc_a_tick2_per_count = gain::<I16F16>(
            self.kff_acc_a_s2_per_mm,
            rate * rate / counts_per_mm,
            512.0,
            ConfigField::PidKffAccAS2PerMm,
        )?;
        let cutoff = self.derivative_cutoff_hz;
        if !cutoff.is_finite() {
            return Err(ConfigError::NotFinite(ConfigField::PidDerivativeCutoffHz));
        }
        if !(cutoff > 0.0 && cutoff <= rate / 2.0) {
            return Err(ConfigError::OutOfRange(ConfigField::PidDerivativeCutoffHz));
        }
        let wt = 2.0 * core::f64::consts::PI * cutoff / rate;
        let derivative_alpha = I1F31::checked_from_num(wt / (1.0 + wt))
            .filter(|a| *a > 0)
            .ok_or(ConfigError::OutOfRange(ConfigField::PidDerivativeCutoffHz))?;
        let max = self.max_current_a;
        if !max.is_finite() {
            return Err(ConfigError::NotFinite(ConfigField::PidMaxCurrentA));
        }
        let max_current_a = I16F16::checked_from_num(max)
            .filter(|m| *m > 0 && *m <= MAX_CURRENT_A)
            .ok_or(ConfigError::OutOfRange(ConfigField::PidMaxCurrentA))?;
        Ok(Coeffs {
            kp_a_per_count,
            ki_a_per_count_tick,
            kd_a_tick_per_count,
            derivative_alpha,
            kff_vel_a_tick_per_count,
            kff_acc_a_tick2_per_count,
            max_current_a,
        })
    }
}

impl Default for Config {
    fn default() -> Self {
        Self::PAPER_RIG
    }
}

/// Output limit: the integrator (I8F24) must hold it.
const MAX_CURRENT_A: I16F16 = I16F16::lit("127");
/// Following error reported: a 23-bit signed number of counts (±2^22), so I24F8 never wraps.
const ERROR_BITS: u32 = 23;
/// Error inside P and I: 24-bit signed LSBs of I24F8 (±32768 counts).
const ERROR_PI_BITS: u32 = 24;
/// Measured velocity: a 12-bit signed number of counts/tick (-2048 ..= 2047).
const VELOCITY_BITS: u32 = 12;

/// `value * scale` in format `F`, `0 <= value * scale < max` (also after rounding); a non-zero
/// value must not round to zero (that would silently switch the term off).
fn gain<F: fixed::traits::Fixed>(
    value: f64,
    scale: f64,
    max: f64,
    field: ConfigField,
) -> Result<F, ConfigError> {
    if !value.is_finite() {
        return Err(ConfigError::NotFinite(field));
    }
    let x = value * scale;
    if !(x >= 0.0 && x < max) {
        return Err(ConfigError::OutOfRange(field));
    }
    match F::checked_from_num(x) {
        // Rounding to nearest may reach `max` itself; the bounds are strict.
        Some(g) if g.to_num::<f64>() < max && (g != F::ZERO || value == 0.0) => Ok(g),
        _ => Err(ConfigError::OutOfRange(field)),
    }
}

/// Fixed-point gains, per count and per tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Coeffs {
    kp_a_per_count: I8F24,
    ki_a_per_count_tick: I1F31,
    kd_a_tick_per_count: I16F16,
    derivative_alpha: I1F31,
    kff_vel_a_tick_per_count: I16F16,
    kff_acc_a_tick2_per_count: I16F16,
    max_current_a: I16F16,
}

impl Default for Coeffs {
    fn default() -> Self {
        match Config::PAPER_RIG.build(&BuildContext::PAPER) {
            Ok(c) => c,
            // Unreachable (the defaults are tested); a loop that outputs nothing, not a panic.
            Err(_) => Self {
                kp_a_per_count: I8F24::ZERO,
                ki_a_per_count_tick: I1F31::ZERO,
                kd_a_tick_per_count: I16F16::ZERO,
                derivative_alpha: I1F31::MAX,
                kff_vel_a_tick_per_count: I16F16::ZERO,
                kff_acc_a_tick2_per_count: I16F16::ZERO,
                max_current_a: I16F16::ZERO,
            },
        }
    }
}

/// Loop state: integrator, filtered velocity and the previous measurement.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct State {
    integrator_a: I8F24,
    velocity_counts_per_tick: I16F16,
    last_position_counts: i32,
    primed: bool,
}

impl State {
    /// Cleared: no integral, no velocity; the first measurement after this has no derivative.
    pub const fn new() -> Self {
        Self {
            integrator_a: I8F24::ZERO,
            velocity_counts_per_tick: I16F16::ZERO,
            last_position_counts: 0,
            primed: false,
        }
    }

    /// Clears everything, e.g. before re-enabling the drive (pair with
    /// `Trajectory::reset(measured)` so the first error is zero).
    pub fn reset(&mut self) {
        *self = Self::new();
    }

    /// The integral term.
    pub fn integrator_a(&self) -> I8F24 {
        self.integrator_a
    }

    /// The low-pass filtered measured velocity used by the D term.
    pub fn velocity_counts_per_tick(&self) -> I16F16 {
        self.velocity_counts_per_tick
    }
}

/// One tick's command.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Output {
    /// Motor current command, within ±max_current.
    pub current_a: I16F16,
    /// `setpoint - measured`, saturated at ±2^22 counts: for following-error fault detection.
    pub following_error_counts: I24F8,
    /// The unclamped command exceeded ±max_current.
    pub saturated: bool,
    /// The acceleration feed-forward's share of the command (unclamped): the current the
    /// setpoint's acceleration asks for, which the stall detector does not count as effort.
    pub accel_feedforward_a: I16F16,
}

/// Saturates to `±limit` (`limit >= 0`); `max`/`min` rather than `clamp`, which has a panic
/// path for `min > max`.
#[inline(always)]
fn sat(x: i32, limit: i32) -> i32 {
    x.max(limit.wrapping_neg()).min(limit)
}

/// Saturates to a `BITS`-bit signed range, `-2^(BITS-1) ..= 2^(BITS-1) - 1`: one SSAT.
#[inline(always)]
fn ssat<const BITS: u32>(x: i32) -> i32 {
    x.max(-(1 << (BITS - 1))).min((1 << (BITS - 1)) - 1)
}

/// `(a * b) >> shift`, a 32x32->64 multiply (it cannot wrap); the caller guarantees the result
/// fits.
#[inline(always)]
fn mul_shr(a: i32, b: i32, shift: u32) -> i32 {
    ((a as i64).wrapping_mul(b as i64) >> shift) as i32
}

impl Coeffs {
    /// The gains as raw bits, in the order [`Coeffs::from_bits`] reads them: for the
    /// configuration image the host builds (`drive::Parts::encode`).
    pub(crate) fn to_bits(self) -> [i32; 7] {
        [
            self.kp_a_per_count.to_bits(),
            self.ki_a_per_count_tick.to_bits(),
            self.kd_a_tick_per_count.to_bits(),
            self.derivative_alpha.to_bits(),
            self.kff_vel_a_tick_per_count.to_bits(),
            self.kff_acc_a_tick2_per_count.to_bits(),
            self.max_current_a.to_bits(),
        ]
    }

    /// Gains from raw bits, checked in integers against the bounds [`Config::build`] keeps
    /// (which [`Coeffs::update`] relies on to never overflow); a refusal names the SI field.
    pub(crate) fn from_bits(b: [i32; 7]) -> Result<Coeffs, ConfigError> {
        // `0 <= bits < 2^max_log2` (the strict upper bounds of `gain`).
        let gain = |bits: i32, max_log2: u32, field| {
            if (0..1 << max_log2).contains(&bits) {
                Ok(bits)
            } else {
                Err(ConfigError::OutOfRange(field))
            }
        };
        let [kp, ki, kd, alpha, kff_vel, kff_acc, max] = b;
        if alpha <= 0 {
            return Err(ConfigError::OutOfRange(ConfigField::PidDerivativeCutoffHz));
        }
        if !(max > 0 && max <= MAX_CURRENT_A.to_bits()) {
            return Err(ConfigError::OutOfRange(ConfigField::PidMaxCurrentA));
        }
        Ok(Coeffs {
            kp_a_per_count: I8F24::from_bits(gain(kp, 24, ConfigField::PidKpAPerMm)?),
            ki_a_per_count_tick: I1F31::from_bits(gain(ki, 23, ConfigField::PidKiAPerMmS)?),
            kd_a_tick_per_count: I16F16::from_bits(gain(kd, 20, ConfigField::PidKdASPerMm)?),
            derivative_alpha: I1F31::from_bits(alpha),
            kff_vel_a_tick_per_count: I16F16::from_bits(gain(
                kff_vel,
                20,
                ConfigField::PidKffVelASPerMm,
            )?),
            kff_acc_a_tick2_per_count: I16F16::from_bits(gain(
                kff_acc,
                25,
                ConfigField::PidKffAccAS2PerMm,
            )?),
            max_current_a: I16F16::from_bits(max),
        })
    }

    /// The output limit.
    pub fn max_current_a(&self) -> I16F16 {
        self.max_current_a
    }

    /// Proportional gain, A per count.
    pub fn kp_a_per_count(&self) -> I8F24 {
        self.kp_a_per_count
    }

    /// Integral gain, A per count per tick.
    pub fn ki_a_per_count_tick(&self) -> I1F31 {
        self.ki_a_per_count_tick
    }

    /// Derivative gain, A per count/tick.
    pub fn kd_a_tick_per_count(&self) -> I16F16 {
        self.kd_a_tick_per_count
    }

    /// Derivative low-pass coefficient (`y += alpha (x - y)`).
    pub fn derivative_alpha(&self) -> I1F31 {
        self.derivative_alpha
    }

    /// Velocity feed-forward, A per count/tick.
    pub fn kff_vel_a_tick_per_count(&self) -> I16F16 {
        self.kff_vel_a_tick_per_count
    }

    /// Acceleration feed-forward, A per count/tick².
    pub fn kff_acc_a_tick2_per_count(&self) -> I16F16 {
        self.kff_acc_a_tick2_per_count
    }

    /// One control tick: the setpoint of this tick and the position measured at its start.
    /// Total on every input: saturates, never overflows, bounded time. Always inlined: the
    /// control tick is its one caller on the drive (16 instructions per tick fewer, measured).
    #[inline(always)]
    pub fn update(&self, state: &mut State, setpoint: &Setpoint, measured_counts: i32) -> Output {
        // Following error: whole counts (the setpoint's floor; within `i32` by the `Setpoint`
        // invariant) saturating, then the setpoint's top 8 fractional bits.
        let setpoint_counts = setpoint.position_floor_counts();
        let setpoint_frac_f8 = setpoint.position_frac_q8();
        let error_counts = ssat::<ERROR_BITS>(setpoint_counts.saturating_sub(measured_counts));
        let error_f8 = (error_counts << 8) | setpoint_frac_f8;
        let error_pi_f8 = ssat::<ERROR_PI_BITS>(error_f8);

        // Measured velocity (counts/tick, I16F16), low-passed. No history yet: no derivative.
        let last = if state.primed {
            state.last_position_counts
        } else {
            measured_counts
        };
        let step_f16 = ssat::<VELOCITY_BITS>(measured_counts.saturating_sub(last)) << 16;
        let mut velocity_f16 = state.velocity_counts_per_tick.to_bits();
        // Both within ±2^27 (no wrap); alpha < 1 and rounding to nearest keep the filter between
        // them. Plain arithmetic in this function cannot overflow; the few `wrapping_*` keep debug
        // and release builds the same panic-free code.
        let towards = (step_f16.wrapping_sub(velocity_f16) as i64)
            .wrapping_mul(self.derivative_alpha.to_bits() as i64);
        velocity_f16 = velocity_f16.wrapping_add((towards.wrapping_add(1 << 30) >> 31) as i32);

        // Terms in I16F16 amperes, each below 2^31 by the bounds in `build` and `Setpoint`.
        let p = mul_shr(error_pi_f8, self.kp_a_per_count.to_bits(), 16);
        let d = mul_shr(velocity_f16, self.kd_a_tick_per_count.to_bits(), 16).wrapping_neg();
        let v_ff = mul_shr(
            setpoint.velocity_q16(),
            self.kff_vel_a_tick_per_count.to_bits(),
            16,
        );
        let a_ff = mul_shr(
            setpoint.acceleration_q24(),
            self.kff_acc_a_tick2_per_count.to_bits(),
            24,
        );
        let others = p
            .saturating_add(d)
            .saturating_add(v_ff)
            .saturating_add(a_ff);

        // Integrator in I8F24 (F8 x F31 >> 15). Conditional integration: frozen while the output
        // is saturated in the direction the error would push it.
        let limit_f16 = self.max_current_a.to_bits();
        let limit_f24 = limit_f16 << 8;
        let mut integrator_f24 = state.integrator_a.to_bits();
        let increment_f24 = mul_shr(error_pi_f8, self.ki_a_per_count_tick.to_bits(), 15);
        let before = others.saturating_add(integrator_f24 >> 8);
        let winding = if increment_f24 > 0 {
            before >= limit_f16
        } else {
            before <= limit_f16.wrapping_neg()
        };
        if !winding {
            integrator_f24 = sat(integrator_f24.saturating_add(increment_f24), limit_f24);
        }
        let total = others.saturating_add(integrator_f24 >> 8);

        state.integrator_a = I8F24::from_bits(integrator_f24);
        state.velocity_counts_per_tick = I16F16::from_bits(velocity_f16);
        state.last_position_counts = measured_counts;
        state.primed = true;
        let current_f16 = sat(total, limit_f16);
        Output {
            current_a: I16F16::from_bits(current_f16),
            following_error_counts: I24F8::from_bits(error_f8),
            // Outside `±limit` exactly when the clamp changed it.
            saturated: current_f16 != total,
            accel_feedforward_a: I16F16::from_bits(a_ff),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fixed::types::I40F24;

    fn at(position_counts: f64) -> Setpoint {
        Setpoint::new(
            I40F24::from_num(position_counts),
            I40F24::ZERO,
            I40F24::ZERO,
        )
    }

    fn only(kp: f64, ki: f64, kd: f64) -> Coeffs {
        Config {
            kp_a_per_mm: kp,
            ki_a_per_mm_s: ki,
            kd_a_s_per_mm: kd,
            kff_vel_a_s_per_mm: 0.0,
            kff_acc_a_s2_per_mm: 0.0,
            ..Config::PAPER_RIG
        }
        .build(&BuildContext::PAPER)
        .unwrap()
    }

    fn amps(o: Output) -> f64 {
        o.current_a.to_num()
    }

    #[test]
    fn defaults_build_and_convert() {
        let c = Config::PAPER_RIG.build(&BuildContext::PAPER).unwrap();
        assert_eq!(c, Coeffs::default());
        let cpm = Rig::PAPER.counts_per_mm();
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-4 * y.abs();
        assert!(close(c.kp_a_per_count().to_num(), 10.0 / cpm));
        assert!(close(
            c.ki_a_per_count_tick().to_num(),
            100.0 / cpm / 2000.0
        ));
        assert!(close(c.kd_a_tick_per_count().to_num(), 0.12 * 2000.0 / cpm));
        assert!(close(
            c.kff_acc_a_tick2_per_count().to_num(),
            0.00092 * 4e6 / cpm
        ));
        assert_eq!(c.max_current_a(), 8);
        let wt = 2.0 * core::f64::consts::PI * 300.0 / 2000.0;
        assert!(close(c.derivative_alpha().to_num(), wt / (1.0 + wt)));
    }

    #[test]
    fn config_errors_name_the_field() {
        let ok = Config::PAPER_RIG;
        let field = |c: Config| c.build(&BuildContext::PAPER).unwrap_err().field();
        assert_eq!(
            field(Config {
                kp_a_per_mm: f64::NAN,
                ..ok
            }),
            ConfigField::PidKpAPerMm
        );
        assert_eq!(
            field(Config {
                kp_a_per_mm: -1.0,
                ..ok
            }),
            ConfigField::PidKpAPerMm
        );
        assert_eq!(
            field(Config {
                kp_a_per_mm: 2000.0,
                ..ok
            }),
            ConfigField::PidKpAPerMm
        );
        assert_eq!(
            field(Config {
                ki_a_per_mm_s: 1e-9,
                ..ok
            }),
            ConfigField::PidKiAPerMmS
        );
        assert_eq!(
            field(Config {
                ki_a_per_mm_s: 1e12,
                ..ok
            }),
            ConfigField::PidKiAPerMmS
        );
        assert_eq!(
            field(Config {
                kd_a_s_per_mm: f64::INFINITY,
                ..ok
            }),
            ConfigField::PidKdASPerMm
        );
        assert_eq!(
            field(Config {
                kd_a_s_per_mm: 1e5,
                ..ok
            }),
            ConfigField::PidKdASPerMm
        );
        assert_eq!(
            field(Config {
                kff_vel_a_s_per_mm: -0.1,
                ..ok
            }),
            ConfigField::PidKffVelASPerMm
        );
        assert_eq!(
            field(Config {
                kff_acc_a_s2_per_mm: 1e3,
                ..ok
            }),
            ConfigField::PidKffAccAS2PerMm
        );
        assert_eq!(
            field(Config {
                derivative_cutoff_hz: 0.0,
                ..ok
            }),
            ConfigField::PidDerivativeCutoffHz
        );
        assert_eq!(
            field(Config {
                derivative_cutoff_hz: 1001.0,
                ..ok
            }),
            ConfigField::PidDerivativeCutoffHz
        );
        assert_eq!(
            field(Config {
                derivative_cutoff_hz: f64::NAN,
                ..ok
            }),
            ConfigField::PidDerivativeCutoffHz
        );
        assert_eq!(
            field(Config {
                max_current_a: 0.0,
                ..ok
            }),
            ConfigField::PidMaxCurrentA
        );
        assert_eq!(
            field(Config {
                max_current_a: 128.0,
                ..ok
            }),
            ConfigField::PidMaxCurrentA
        );
        // Zero switches a term off.
        assert!(Config {
            ki_a_per_mm_s: 0.0,
            kd_a_s_per_mm: 0.0,
            ..ok
        }
        .build(&BuildContext::PAPER)
        .is_ok());
    }

    #[test]
    fn proportional_term_and_following_error() {
        let c = only(10.0, 0.0, 0.0);
        let mut s = State::new();
        let o = c.update(&mut s, &at(1100.25), 1000);
        assert_eq!(o.following_error_counts, I24F8::from_num(100.25));
        let expected = 10.0 / Rig::PAPER.counts_per_mm() * 100.25;
        assert!((amps(o) - expected).abs() < 1e-4, "{}", amps(o));
        let o = c.update(&mut s, &at(900.0), 1000);
        assert!((amps(o) + 10.0 / Rig::PAPER.counts_per_mm() * 100.0).abs() < 1e-4);
        assert!(!o.saturated);
    }

    #[test]
    fn saturates_symmetrically() {
        let c = only(10.0, 0.0, 0.0);
        let mut s = State::new();
        let o = c.update(&mut s, &at(1e6), 0);
        assert_eq!(o.current_a, 8);
        assert!(o.saturated);
        let o = c.update(&mut s, &at(-1e6), 0);
        assert_eq!(o.current_a, -8);
        assert!(o.saturated);
    }

    #[test]
    fn no_derivative_kick_on_setpoint_step() {
        let pd = only(10.0, 0.0, 0.5);
        let p = only(10.0, 0.0, 0.0);
        let (mut s_pd, mut s_p) = (State::new(), State::new());
        for _ in 0..10 {
            pd.update(&mut s_pd, &at(0.0), 0);
            p.update(&mut s_p, &at(0.0), 0);
        }
        // Step the setpoint by 500 counts, carriage still.
        let o_pd = pd.update(&mut s_pd, &at(500.0), 0);
        let o_p = p.update(&mut s_p, &at(500.0), 0);
        assert_eq!(o_pd.current_a, o_p.current_a);
        // A moving carriage is damped: the D term opposes the motion.
        let o_pd = pd.update(&mut s_pd, &at(500.0), 10);
        let o_p = p.update(&mut s_p, &at(500.0), 10);
        assert!(o_pd.current_a < o_p.current_a);
    }

    #[test]
    fn first_sample_after_reset_has_no_derivative() {
        let c = only(0.0, 0.0, 0.5);
        let mut s = State::new();
        assert_eq!(c.update(&mut s, &at(123_456.0), 123_456).current_a, 0);
        c.update(&mut s, &at(0.0), 123_500);
        assert!(s.velocity_counts_per_tick() > 0);
        s.reset();
        assert_eq!(s, State::new());
        assert_eq!(c.update(&mut s, &at(-5.0), -5).current_a, 0);
    }

    #[test]
    fn derivative_filter_converges_to_the_measured_velocity() {
        let c = only(0.0, 0.0, 0.1);
        let mut s = State::new();
        for k in 0..200 {
            c.update(&mut s, &at(0.0), 7 * k);
        }
        // Rounding stops the filter within 1/(2 alpha) LSB of its input.
        let lsb = I16F16::DELTA;
        assert!((s.velocity_counts_per_tick() - I16F16::from_num(7)).abs() <= lsb);
        for _ in 0..200 {
            c.update(&mut s, &at(0.0), 0);
        }
        assert!(s.velocity_counts_per_tick().abs() <= lsb);
    }

    #[test]
    fn integrator_stops_winding_when_saturated_and_recovers() {
        let c = only(1.0, 1000.0, 0.0);
        let mut s = State::new();
        // A large error held for 2 s: P alone gives 5.35 A, the integrator takes the rest.
        for _ in 0..4000 {
            let o = c.update(&mut s, &at(10_000.0), 0);
            assert!(o.current_a <= 8);
        }
        let wound = s.integrator_a();
        assert!(wound <= 8, "{wound}");
        assert!(wound > 2, "{wound}");
        // Once the error reverses the output leaves saturation at once: the integrator only holds
        // what was needed to reach the limit, not two seconds' worth.
        let o = c.update(&mut s, &at(-10_000.0), 0);
        assert!(o.current_a < 0, "{}", o.current_a);
        assert!(s.integrator_a() <= wound);
        // The integrator itself never leaves ±max.
        let c = only(0.0, 1000.0, 0.0);
        let mut s = State::new();
        for _ in 0..100_000 {
            c.update(&mut s, &at(1e6), 0);
        }
        assert_eq!(s.integrator_a(), 8);
    }

    #[test]
    fn feed_forward_scales_with_setpoint_velocity_and_acceleration() {
        let c = Config {
            kp_a_per_mm: 0.0,
            ki_a_per_mm_s: 0.0,
            kd_a_s_per_mm: 0.0,
            ..Config::PAPER_RIG
        }
        .build(&BuildContext::PAPER)
        .unwrap();
        let mut s = State::new();
        let cpm = Rig::PAPER.counts_per_mm();
        // 50 mm/s and 1000 mm/s² at 2 kHz.
        let sp = Setpoint::new(
            I40F24::ZERO,
            I40F24::from_num(50.0 * cpm / 2000.0),
            I40F24::from_num(1000.0 * cpm / 4e6),
        );
        let expected = 0.12 * 50.0 + 0.00092 * 1000.0;
        let got = amps(c.update(&mut s, &sp, 0));
        assert!((got - expected).abs() < 1e-3, "{got} vs {expected}");
    }

    #[test]
    fn gains_at_their_bounds_keep_the_sign() {
        let cpm = Rig::PAPER.counts_per_mm();
        let rate = 2000.0;
        let zero = Config {
            kp_a_per_mm: 0.0,
            ki_a_per_mm_s: 0.0,
            kd_a_s_per_mm: 0.0,
            kff_vel_a_s_per_mm: 0.0,
            kff_acc_a_s2_per_mm: 0.0,
            max_current_a: 127.0,
            derivative_cutoff_hz: 1000.0,
        };
        // A few LSBs below each bound.
        let top = |x: f64| x * (1.0 - 1e-5);
        let build = |c: Config| c.build(&BuildContext::PAPER).unwrap();
        let big = I40F24::from_num(2_000_000_000);
        let v_max = I40F24::from_num(2048);
        let a_max = I40F24::from_num(63.999);

        let p = build(Config {
            kp_a_per_mm: top(cpm),
            ..zero
        });
        let o = p.update(
            &mut State::new(),
            &Setpoint::new(big, I40F24::ZERO, I40F24::ZERO),
            -5,
        );
        assert_eq!(o.current_a, 127);
        let o = p.update(
            &mut State::new(),
            &Setpoint::new(-big, I40F24::ZERO, I40F24::ZERO),
            5,
        );
        assert_eq!(o.current_a, -127);

        let d = build(Config {
            kd_a_s_per_mm: top(16.0 * cpm / rate),
            ..zero
        });
        let mut s = State::new();
        let at0 = Setpoint::at_rest(0);
        let mut o = d.update(&mut s, &at0, 0);
        for k in 1..20 {
            o = d.update(&mut s, &at0, -5000 * k);
        }
        // Measured falling at the velocity limit: the damping pushes up, at full scale.
        assert_eq!(o.current_a, 127);

        let v = build(Config {
            kff_vel_a_s_per_mm: top(16.0 * cpm / rate),
            ..zero
        });
        let o = v.update(
            &mut State::new(),
            &Setpoint::new(I40F24::ZERO, v_max, I40F24::ZERO),
            0,
        );
        assert_eq!(o.current_a, 127);
        let o = v.update(
            &mut State::new(),
            &Setpoint::new(I40F24::ZERO, -v_max, I40F24::ZERO),
            0,
        );
        assert_eq!(o.current_a, -127);

        let a = build(Config {
            kff_acc_a_s2_per_mm: top(512.0 * cpm / (rate * rate)),
            ..zero
        });
        let o = a.update(
            &mut State::new(),
            &Setpoint::new(I40F24::ZERO, I40F24::ZERO, a_max),
            0,
        );
        assert_eq!(o.current_a, 127);
        let o = a.update(
            &mut State::new(),
            &Setpoint::new(I40F24::ZERO, I40F24::ZERO, -a_max),
            0,
        );
        assert_eq!(o.current_a, -127);

        // Exactly at a bound (after rounding) is refused.
        let at_bound = Config {
            kd_a_s_per_mm: 16.0 * cpm / rate,
            ..zero
        };
        assert_eq!(
            at_bound.build(&BuildContext::PAPER).unwrap_err().field(),
            ConfigField::PidKdASPerMm
        );
    }

    #[test]
    fn extreme_inputs_saturate() {
        let c = Coeffs::default();
        let mut s = State::new();
        let extremes = [i64::MIN, i64::MAX, 0, -1, 1 << 55];
        for &p in &extremes {
            for &v in &extremes {
                for &a in &extremes {
                    for m in [i32::MIN, i32::MAX, 0] {
                        let sp = Setpoint::new(
                            I40F24::from_bits(p),
                            I40F24::from_bits(v),
                            I40F24::from_bits(a),
                        );
                        let o = c.update(&mut s, &sp, m);
                        assert!(o.current_a.abs() <= 8);
                        assert!(s.integrator_a().abs() <= 8);
                    }
                }
            }
        }
    }
}
