//! Model 2 (eq. 17): the band of Model 1 with an exponential transition
//! `u = y_d - A (1 - e^{a (x - x_d)})` forward and `u = y_d + B (1 - e^{-b (x - x_d)})` reverse
//! (`a, b < 0`: both decay with the distance travelled since the turning point).
//!
//! The fixed-point exponential is `2^-t` with `t = |a| log2(e) d` (see
//! [`exp2_neg_q30`](super::fixmath::exp2_neg_q30)): `d` is the distance in counts, the rate a
//! [`Scale`] built once, so a tick costs one 32x32->64 multiply, one 64-bit shift and the `2^-t`
//! kernel (four more multiplies and a 64-entry table).
//!
//! Where the curve meets the band edge the output follows the edge (eq. 17's conditions,
//! `y = max(u, m x - h)` forward): with Table 2 the asymptotes `y_d - A` and `y_d + B` stop short of
//! the far edge (`A, B < h - h_g = 0.23 mm`), but the edges slope with `m`, so they still meet the
//! curve after about 151 mm (forward) and 132 mm (reverse) of travel from a full-band reversal. The
//! switch is continuous (the curve crosses the edge, it does not jump to it). When the edge can
//! never reach the curve (`m <= 0` and the asymptote short of the edge), the output settles on the
//! asymptote inside the band: [`Model2Coeffs::closing`] reports `None` so the firmware can warn.

use crate::ConfigField;
use fixed::types::I16F16;

use super::convert::{exp_nonpos, finite, um_q16};
use super::fixmath::{exp2_neg_q30, Scale, ONE_Q30};
use super::linear::{travel_since_turn, LinearBand};
use super::{Closing, Direction, ModelState};
use crate::ConfigError;

/// Model 2 parameters in the paper's units (Table 2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Model2Params {
    /// Slope `m` of the band along travel (mm of error per mm of travel).
    pub m_mm_per_mm: f64,
    /// Band offset `c` (mm), as in [`super::Model1Params::offset_mm`].
    pub offset_mm: f64,
    /// Band height `h` (mm), `>= 0`.
    pub h_mm: f64,
    /// Fast jump `h_g` (mm) at a reversal, `>= 0`.
    pub h_g_mm: f64,
    /// Rate `a` of the forward transition (1/mm), `<= 0`.
    pub rate_a_per_mm: f64,
    /// Rate `b` of the reverse transition (1/mm), `<= 0`.
    pub rate_b_per_mm: f64,
    /// Amplitude `A` of the forward transition (mm), `>= 0`.
    pub amplitude_a_mm: f64,
    /// Amplitude `B` of the reverse transition (mm), `>= 0`.
    pub amplitude_b_mm: f64,
}

impl Model2Params {
    /// Table 2, Model 2.
    pub const PAPER: Model2Params = Model2Params {
        m_mm_per_mm: 0.0010594,
        offset_mm: 0.0,
        h_mm: 0.34,
        h_g_mm: 0.11,
        rate_a_per_mm: -0.05,
        rate_b_per_mm: -0.03,
        amplitude_a_mm: 0.07,
        amplitude_b_mm: 0.09,
    };

    /// Converts to fixed-point coefficients for a rig with `counts_per_mm` encoder counts per mm.
    pub fn build(&self, counts_per_mm: f64) -> Result<Model2Coeffs, ConfigError> {
        let band = LinearBand::build(
            self.m_mm_per_mm,
            self.offset_mm,
            self.h_mm,
            counts_per_mm,
            [
                ConfigField::Model2MMmPerMm,
                ConfigField::Model2OffsetMm,
                ConfigField::Model2HMm,
            ],
        )?;
        let h_g_um = um_q16(self.h_g_mm * 1000.0, 0.0, ConfigField::Model2HGMm)?;
        let amp_a_um = um_q16(
            self.amplitude_a_mm * 1000.0,
            0.0,
            ConfigField::Model2AmplitudeAMm,
        )?;
        let amp_b_um = um_q16(
            self.amplitude_b_mm * 1000.0,
            0.0,
            ConfigField::Model2AmplitudeBMm,
        )?;
        let rate_a = rate(
            self.rate_a_per_mm,
            counts_per_mm,
            ConfigField::Model2RateAPerMm,
        )?;
        let rate_b = rate(
            self.rate_b_per_mm,
            counts_per_mm,
            ConfigField::Model2RateBPerMm,
        )?;
        Ok(Model2Coeffs {
            band,
            h_g_um,
            amp_a_um,
            amp_b_um,
            rate_a,
            rate_b,
            #[cfg(feature = "std")]
            closing: self.closing(),
        })
    }

    /// Travel from a turning point on one band edge until the exponential meets the other edge:
    /// the root of `m d = (h - h_g) - A (1 - e^{a d})` (forward; `B`, `b` reverse), found by
    /// bisection. `None` when there is no root within [`Closing::LIMIT_MM`], or when `m < 0` (the
    /// edge would meet the curve and then fall away from it again).
    pub fn closing(&self) -> Closing {
        let gap = self.h_mm - self.h_g_mm;
        let m = self.m_mm_per_mm;
        let dist = |amp: f64, rate: f64| -> Option<f64> {
            if !(gap.is_finite() && m.is_finite() && amp.is_finite() && rate.is_finite()) {
                return None;
            }
            if gap <= 0.0 {
                return Some(0.0);
            }
            if m < 0.0 {
                return None;
            }
            // f(d) = m d - gap + A (1 - e^{rate d}); f(0) < 0, increasing for m >= 0, A >= 0.
            let f = |d: f64| m * d - gap + amp * (1.0 - exp_nonpos(rate * d));
            let mut hi = Closing::LIMIT_MM;
            if f(hi) < 0.0 {
                return None;
            }
            let mut lo = 0.0;
            let mut k = 0;
            while k < 100 {
                let mid = 0.5 * (lo + hi);
                if f(mid) < 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
                k += 1;
            }
            Some(hi)
        };
        Closing::from_mm(
            dist(self.amplitude_a_mm, self.rate_a_per_mm),
            dist(self.amplitude_b_mm, self.rate_b_per_mm),
        )
    }
}

/// `|rate| log2(e) / counts_per_mm`, scaled so that `Scale::apply(d_counts)` is the exponent `t`
/// of `2^-t` in Q32.32.
fn rate(rate_per_mm: f64, counts_per_mm: f64, field: ConfigField) -> Result<Scale, ConfigError> {
    let r = finite(rate_per_mm, field)?;
    if r > 0.0 {
        return Err(ConfigError::OutOfRange(field));
    }
    let per_count = -r * core::f64::consts::LOG2_E / counts_per_mm;
    // t must stay below 2^32 per count (|rate| < 1294 /mm on the paper's rig).
    Scale::from_f64(per_count * 4_294_967_296.0, field)
}

/// Model 2 in fixed point; build with [`Model2Params::build`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Model2Coeffs {
    pub(crate) band: LinearBand,
    pub(crate) h_g_um: I16F16,
    pub(crate) amp_a_um: I16F16,
    pub(crate) amp_b_um: I16F16,
    /// Exponent of the forward transition per count, `t_q32 = rate_a.apply(d)`.
    pub(crate) rate_a: Scale,
    pub(crate) rate_b: Scale,
    #[cfg(feature = "std")]
    pub(crate) closing: Closing,
}

impl Model2Coeffs {
    /// Closing distances computed at build time (host only); `None` means the transition never
    /// reaches that band edge with these parameters (`hil-sim calibrate` warns).
    #[cfg(feature = "std")]
    pub fn closing(&self) -> Closing {
        self.closing
    }
}

/// `A (1 - 2^-t)` in Q16.16 micrometre bits: `|A| < 2^31`, `1 - 2^-t` in `[0, 2^30]` (Q2.30).
#[inline]
fn rise(amp_um: I16F16, rate: &Scale, d_counts: u32) -> i32 {
    let one_minus = ONE_Q30.saturating_sub(exp2_neg_q30(rate.apply(d_counts))) as i64;
    ((amp_um.to_bits() as i64 * one_minus + (1 << 29)) >> 30) as i32
}

/// One step of eq. 17, bounded on both sides by the band.
#[inline]
pub(crate) fn eval(c: &Model2Coeffs, s: &ModelState, x_counts: i32) -> I16F16 {
    eval_at(c, s.dir, s.transition, s.x_d_counts, s.y_d_um, x_counts)
}

/// [`eval`] from an explicit transition state (Model 4 runs Model 2 on its own turning-point
/// output, not on the active model's).
#[inline(always)]
pub(crate) fn eval_at(
    c: &Model2Coeffs,
    dir: Direction,
    transition: bool,
    x_d_counts: i32,
    y_d_um: I16F16,
    x_counts: i32,
) -> I16F16 {
    let (lower, upper) = c.band.edges(x_counts);
    let y = if !transition {
        match dir {
            Direction::Forward => lower,
            Direction::Reverse => upper,
        }
    } else {
        let dx = travel_since_turn(x_counts, x_d_counts);
        let y_d = y_d_um.to_bits();
        let u = match dir {
            // Distance travelled forward since the turn; 0 if the dead band let x fall behind.
            Direction::Forward => {
                let d = dx.max(0) as u32;
                y_d.saturating_sub(c.h_g_um.to_bits())
                    .saturating_sub(rise(c.amp_a_um, &c.rate_a, d))
            }
            Direction::Reverse => {
                let d = dx.saturating_neg().max(0) as u32;
                y_d.saturating_add(c.h_g_um.to_bits())
                    .saturating_add(rise(c.amp_b_um, &c.rate_b, d))
            }
        };
        u.max(lower).min(upper)
    };
    I16F16::from_bits(y)
}
