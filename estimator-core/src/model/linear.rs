//! Model 1 (eq. 14): a hysteresis band `[m x - h, m x]` and a straight transition of slope `a`
//! (forward) or `b` (reverse) from the turning point to the new direction's band edge.

use crate::ConfigField;
use fixed::types::{I16F16, I1F31};

use super::convert::{slope_q31, um_q16};
use super::fixmath::{mul_q31_to_q16, sat_i32};
use super::{Closing, Direction, ModelState};
use crate::ConfigError;

/// Model 1 parameters in the paper's units (Table 2): positions in mm along the primary
/// encoder's travel, errors in mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Model1Params {
    /// Slope `m` of the band along travel (mm of error per mm of travel). Any sign.
    pub m_mm_per_mm: f64,
    /// Offset `c` of the band (mm): the edges are `m x + c - h` and `m x + c`. Zero in Table 2,
    /// whose encoder and scale zeros coincide; a calibration fits it.
    pub offset_mm: f64,
    /// Band height `h` (mm), `>= 0`: forward motion rides the lower edge `m x - h`, reverse the
    /// upper edge `m x`.
    pub h_mm: f64,
    /// Fast jump `h_g` (mm), `>= 0`, applied at a reversal (eq. 16).
    pub h_g_mm: f64,
    /// Transition slope `a` after a reversal to forward (mm of error per mm of travel), `>= 0`.
    pub slope_a_mm_per_mm: f64,
    /// Transition slope `b` after a reversal to reverse (mm of error per mm of travel), `>= 0`.
    pub slope_b_mm_per_mm: f64,
}

impl Model1Params {
    /// Table 2, Model 1.
    pub const PAPER: Model1Params = Model1Params {
        m_mm_per_mm: 0.0010594,
        offset_mm: 0.0,
        h_mm: 0.34,
        h_g_mm: 0.11,
        slope_a_mm_per_mm: 0.0012,
        slope_b_mm_per_mm: 0.0012,
    };

    /// Converts to fixed-point coefficients for a rig with `counts_per_mm` encoder counts per mm.
    pub fn build(&self, counts_per_mm: f64) -> Result<Model1Coeffs, ConfigError> {
        let band = LinearBand::build(
            self.m_mm_per_mm,
            self.offset_mm,
            self.h_mm,
            counts_per_mm,
            [
                ConfigField::Model1MMmPerMm,
                ConfigField::Model1OffsetMm,
                ConfigField::Model1HMm,
            ],
        )?;
        let h_g_um = um_q16(self.h_g_mm * 1000.0, 0.0, ConfigField::Model1HGMm)?;
        let a = nonneg_slope(
            self.slope_a_mm_per_mm,
            counts_per_mm,
            ConfigField::Model1SlopeAMmPerMm,
        )?;
        let b = nonneg_slope(
            self.slope_b_mm_per_mm,
            counts_per_mm,
            ConfigField::Model1SlopeBMmPerMm,
        )?;
        Ok(Model1Coeffs {
            band,
            h_g_um,
            slope_a_um_per_count: a,
            slope_b_um_per_count: b,
            #[cfg(feature = "std")]
            closing: self.closing(),
        })
    }

    /// Travel from a turning point on one band edge until the transition meets the other edge:
    /// `(h - h_g) / (a + m)` forward and `(h - h_g) / (b + m)` reverse; `None` when the slopes
    /// never close the gap (`a + m <= 0`).
    pub fn closing(&self) -> Closing {
        let gap = self.h_mm - self.h_g_mm;
        let dist = |slope: f64| {
            if gap <= 0.0 {
                Some(0.0)
            } else if slope + self.m_mm_per_mm > 0.0 {
                Some(gap / (slope + self.m_mm_per_mm))
            } else {
                None
            }
        };
        Closing::from_mm(dist(self.slope_a_mm_per_mm), dist(self.slope_b_mm_per_mm))
    }
}

fn nonneg_slope(v: f64, counts_per_mm: f64, field: ConfigField) -> Result<I1F31, ConfigError> {
    let s = slope_q31(v, counts_per_mm, field)?;
    if v < 0.0 {
        return Err(ConfigError::OutOfRange(field));
    }
    Ok(s)
}

/// The straight band of Models 1 and 2: lower edge `m x - h`, upper edge `m x`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinearBand {
    /// `m` in Q1.31 micrometres per count.
    pub m_um_per_count: I1F31,
    /// `c` in micrometres.
    pub offset_um: I16F16,
    /// `h` in micrometres, `>= 0`.
    pub h_um: I16F16,
}

impl LinearBand {
    pub(crate) fn build(
        m_mm_per_mm: f64,
        offset_mm: f64,
        h_mm: f64,
        counts_per_mm: f64,
        [m_field, c_field, h_field]: [ConfigField; 3],
    ) -> Result<LinearBand, ConfigError> {
        Ok(LinearBand {
            m_um_per_count: slope_q31(m_mm_per_mm, counts_per_mm, m_field)?,
            offset_um: um_q16(offset_mm * 1000.0, -super::MAX_ABS_UM, c_field)?,
            h_um: um_q16(h_mm * 1000.0, 0.0, h_field)?,
        })
    }

    /// `(lower, upper)` edges at `x` as Q16.16 micrometre bits; `lower <= upper` always
    /// (`h >= 0`, saturating).
    #[inline]
    pub(crate) fn edges(&self, x_counts: i32) -> (i32, i32) {
        let upper = mul_q31_to_q16(x_counts, self.m_um_per_count.to_bits())
            .saturating_add(self.offset_um.to_bits());
        (upper.saturating_sub(self.h_um.to_bits()), upper)
    }
}

/// Model 1 in fixed point; build with [`Model1Params::build`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Model1Coeffs {
    pub(crate) band: LinearBand,
    pub(crate) h_g_um: I16F16,
    pub(crate) slope_a_um_per_count: I1F31,
    pub(crate) slope_b_um_per_count: I1F31,
    #[cfg(feature = "std")]
    pub(crate) closing: Closing,
}

impl Model1Coeffs {
    #[cfg(feature = "std")]
    /// Closing distances computed at build time (see [`Model1Params::closing`]).
    pub fn closing(&self) -> Closing {
        self.closing
    }
}

/// `x - x_d` in counts, saturated to `i32` (a jump across the whole `i32` range does not wrap).
#[inline]
pub(crate) fn travel_since_turn(x_counts: i32, x_d_counts: i32) -> i32 {
    sat_i32(x_counts as i64 - x_d_counts as i64)
}

/// One step of eq. 14, bounded on both sides by the band (see the module docs of `model`).
#[inline]
pub(crate) fn eval(c: &Model1Coeffs, s: &ModelState, x_counts: i32) -> I16F16 {
    eval_at(c, s.dir, s.transition, s.x_d_counts, s.y_d_um, x_counts)
}

/// [`eval`] from an explicit transition state.
#[inline(always)]
pub(crate) fn eval_at(
    c: &Model1Coeffs,
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
        // u = y_d -/+ h_g - slope * (x - x_d)   (eqs. 14, 16)
        let (start, slope) = match dir {
            Direction::Forward => (
                y_d.saturating_sub(c.h_g_um.to_bits()),
                c.slope_a_um_per_count,
            ),
            Direction::Reverse => (
                y_d.saturating_add(c.h_g_um.to_bits()),
                c.slope_b_um_per_count,
            ),
        };
        let u = start.saturating_sub(mul_q31_to_q16(dx, slope.to_bits()));
        u.max(lower).min(upper)
    };
    I16F16::from_bits(y)
}
