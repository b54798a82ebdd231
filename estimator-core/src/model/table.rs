//! Model 3 (eq. 18): lookup tables.
//!
//! Our parametrisation of the paper's `Λ_f, Λ_r, Λ_ft, Λ_rt`:
//! - **Band tables** `Λ_f(x)` (lower, forward) and `Λ_r(x)` (upper, reverse): error values in um on
//!   an evenly spaced axis along travel (mm in the parameters, as the calibration's bins are; to
//!   [`UNIFORM_TOLERANCE_MM`], the blob's rounding of the axis to whole um); linear interpolation,
//!   clamped to the end values outside the axis.
//! - **Transition tables** `G_f(d, g0)`, `G_r(d, g0)`: the remaining gap (um, `>= 0`) between the
//!   error and the new direction's band edge, as a function of the travel since the reversal
//!   `d = |x - x_d|` and of the initial gap `g0 = max(0, y_d - Λ_f(x_d))` forward
//!   (`max(0, Λ_r(x_d) - y_d)` reverse), where `y_d` is the error at the turning point. Both axes
//!   are uniform and start at 0 (steps `d_step_mm`, `g0_step_um`), so a tick finds its cell by a
//!   multiply and a shift. The fast jump `h_g` is not applied: the table holds it (its `d = 0`
//!   row). Forward `y = Λ_f(x) + G_f(d, g0)`, reverse `y = Λ_r(x) - G_r(d, g0)`, bilinear in the
//!   cell; beyond the last `d` the last row is held (no jump), beyond the last `g0` the last
//!   column.
//!
//! `g0` is clamped at 0 rather than taken as `|y_d - Λ(x_d)|`: the two agree whenever the turning
//! point lies inside the band, and a turning point outside it then starts on the edge instead of
//! mirrored to the far side of it.
//!
//! Storage: band values `I16F16` um (256 B per direction at 64 points) with the axis as its
//! start (counts) and points per count (Q0.32); gaps `U11F5` um (0..2047.97 um in steps of
//! 1/32 um, far finer than the 0.5 um linear scale), 768 B per direction at 16 x 24. The whole of
//! [`Model3Coeffs`] is 2112 bytes (496 fewer than with an explicit axis of `i32` counts).
//!
//! The sizes were chosen by measurement (`hil-sim calibrate` and `evaluate` on the simulated
//! rig): 64-point bands with 16 x 24 transitions fit the calibration data better (14.7 um RMS)
//! than 128 points with 32 x 24 (15.2 um) or 64 with 32 x 12 (15.2 um), with the same error on
//! held-out scenarios, at half the RAM. 896 points in all; the paper used 650.
//!
//! Per tick: the band segment and the fraction within it are one multiply (the position on the
//! even axis, like the transition table's cells: no search, no division, no cache), the cell of
//! the transition table one more; `g0`'s cell is found once per reversal (on the first Model 3
//! tick after it) and cached in the state.

use crate::ConfigField;
use core::num::NonZeroU32;
use fixed::types::{I16F16, U11F5};

use super::convert::{finite, um_q16, MAX_ABS_UM};
use super::fixmath::{lerp_diff_q32, lerp_q32, round_i32};
use super::linear::Model1Params;
#[cfg(feature = "std")]
use super::Closing;
use super::{Direction, ModelState};
use crate::ConfigError;

/// Most points of one band table (`Λ_f` or `Λ_r`).
pub const MAX_BAND_POINTS: usize = 64;
/// Most rows (travel since the reversal, `d`) of one transition table.
pub const MAX_TRANSITION_D: usize = 16;
/// Most columns (initial gap, `g0`) of one transition table.
pub const MAX_TRANSITION_G0: usize = 24;

/// One band table in SI-ish units: `len` points `(x_mm[i], y_um[i])`; entries past `len` are
/// ignored.
#[derive(Clone, Debug, PartialEq)]
pub struct BandParams {
    /// Number of points used, `2..=MAX_BAND_POINTS`.
    pub len: usize,
    /// Positions along travel (mm), strictly increasing (also after rounding to counts).
    pub x_mm: [f64; MAX_BAND_POINTS],
    /// Error at each position (um), within +-[`MAX_ABS_UM`].
    pub y_um: [f64; MAX_BAND_POINTS],
}

impl BandParams {
    /// A table with no points (invalid until filled).
    pub const EMPTY: BandParams = BandParams {
        len: 0,
        x_mm: [0.0; MAX_BAND_POINTS],
        y_um: [0.0; MAX_BAND_POINTS],
    };

    /// A table from `(x_mm, y_um)` points; `None` if there are more than [`MAX_BAND_POINTS`].
    pub fn from_points(points: &[(f64, f64)]) -> Option<BandParams> {
        if points.len() > MAX_BAND_POINTS {
            return None;
        }
        let mut b = BandParams::EMPTY;
        b.len = points.len();
        for (i, &(x, y)) in points.iter().enumerate() {
            b.x_mm[i] = x;
            b.y_um[i] = y;
        }
        Some(b)
    }
}

/// One transition table: `gap_um[i][j] = G(i * d_step_mm, j * g0_step_um)`.
#[derive(Clone, Debug, PartialEq)]
pub struct TransitionParams {
    /// Rows used (`d` axis), `2..=MAX_TRANSITION_D`.
    pub n_d: usize,
    /// Columns used (`g0` axis), `2..=MAX_TRANSITION_G0`.
    pub n_g0: usize,
    /// Spacing of the `d` axis (mm of travel since the reversal), at least two encoder counts.
    pub d_step_mm: f64,
    /// Spacing of the `g0` axis (um of initial gap), at least 2^-15 um.
    pub g0_step_um: f64,
    /// Remaining gap to the band edge (um), `0..=U11F5::MAX` (2047.97 um).
    pub gap_um: [[f64; MAX_TRANSITION_G0]; MAX_TRANSITION_D],
}

impl TransitionParams {
    /// A table with no cells (invalid until filled).
    pub const EMPTY: TransitionParams = TransitionParams {
        n_d: 0,
        n_g0: 0,
        d_step_mm: 0.0,
        g0_step_um: 0.0,
        gap_um: [[0.0; MAX_TRANSITION_G0]; MAX_TRANSITION_D],
    };
}

/// Model 3 parameters: band and transition tables per direction.
#[derive(Clone, Debug, PartialEq)]
pub struct Model3Params {
    /// `Λ_f`: the lower band edge followed moving forward.
    pub forward_band: BandParams,
    /// `Λ_r`: the upper band edge followed moving in reverse.
    pub reverse_band: BandParams,
    /// `G_f`: transition after a reversal to forward.
    pub forward_transition: TransitionParams,
    /// `G_r`: transition after a reversal to reverse.
    pub reverse_transition: TransitionParams,
}

/// Points of the band tables [`Model3Params::from_model1`] makes.
pub const FROM_MODEL1_BAND_POINTS: usize = 9;

impl Model3Params {
    /// Tables sampled from Model 1, for use before a calibration exists: straight band tables
    /// `m x - h` and `m x` (um) over `[-travel_mm, travel_mm]`, and full 16 x 24 transition tables
    /// of Model 1's gap `clamp(g0 - h_g - (a + m) d, 0, h)` (reverse: `b`), with `g0` from 0 to `h`
    /// and `d` from 0 to just past the closing distance (at least 1 mm; 200 mm if the transition
    /// never closes). Reproduces Model 1 up to the bilinear interpolation across the kink where the
    /// transition meets the edge (a few um with Table 2; measured in the tests).
    pub const fn from_model1(p: &Model1Params, travel_mm: f64) -> Model3Params {
        let m = p.m_mm_per_mm;
        let h_um = p.h_mm * 1000.0;
        let mut forward_band = BandParams::EMPTY;
        let mut reverse_band = BandParams::EMPTY;
        forward_band.len = FROM_MODEL1_BAND_POINTS;
        reverse_band.len = FROM_MODEL1_BAND_POINTS;
        let mut i = 0;
        while i < FROM_MODEL1_BAND_POINTS {
            let x = -travel_mm + 2.0 * travel_mm * i as f64 / (FROM_MODEL1_BAND_POINTS - 1) as f64;
            forward_band.x_mm[i] = x;
            reverse_band.x_mm[i] = x;
            forward_band.y_um[i] = (m * x + p.offset_mm - p.h_mm) * 1000.0;
            reverse_band.y_um[i] = (m * x + p.offset_mm) * 1000.0;
            i += 1;
        }
        Model3Params {
            forward_band,
            reverse_band,
            forward_transition: model1_transition(p, p.slope_a_mm_per_mm, h_um),
            reverse_transition: model1_transition(p, p.slope_b_mm_per_mm, h_um),
        }
    }
}

const fn model1_transition(p: &Model1Params, slope: f64, h_um: f64) -> TransitionParams {
    let closing_slope = slope + p.m_mm_per_mm; // mm of gap closed per mm of travel
    let gap_mm = p.h_mm - p.h_g_mm;
    let mut span_mm = if closing_slope > 0.0 && gap_mm > 0.0 {
        gap_mm / closing_slope
    } else {
        200.0
    };
    // At least 1 mm, so that a row spans encoder counts on any plausible rig.
    if span_mm < 1.0 {
        span_mm = 1.0;
    }
    let mut t = TransitionParams::EMPTY;
    t.n_d = MAX_TRANSITION_D;
    t.n_g0 = MAX_TRANSITION_G0;
    // The last row lies one step past the closing distance, so it is all zeros.
    t.d_step_mm = span_mm / (MAX_TRANSITION_D - 2) as f64;
    // Up to the band height, but at least 1 um (a degenerate band).
    t.g0_step_um = if h_um > 1.0 { h_um } else { 1.0 } / (MAX_TRANSITION_G0 - 1) as f64;
    let mut i = 0;
    while i < MAX_TRANSITION_D {
        let d_mm = i as f64 * t.d_step_mm;
        let mut j = 0;
        while j < MAX_TRANSITION_G0 {
            let g0 = j as f64 * t.g0_step_um;
            let mut g = g0 - p.h_g_mm * 1000.0 - closing_slope * d_mm * 1000.0;
            if g < 0.0 {
                g = 0.0;
            }
            if g > h_um {
                g = h_um;
            }
            t.gap_um[i][j] = g;
            j += 1;
        }
        i += 1;
    }
    t
}

/// A band table in fixed point: values in Q16.16 um on an even axis in encoder counts.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BandCoeffs {
    pub(crate) len: u8,
    /// The first point, counts.
    pub(crate) x0_counts: i32,
    /// Points per count of travel in Q0.32: `(x - x0) * points_q32` is the position on the axis in
    /// Q32.32, one `UMULL` (steps of at least two counts keep it below 2^31). The step is
    /// honoured to `1 / points_q32` relative; the reference uses the same quantised value.
    pub(crate) points_q32: u32,
    pub(crate) y_um: [I16F16; MAX_BAND_POINTS],
}

/// How far a band table's axis point may lie from the even axis through its first and last
/// points, mm: the blob carries the axis in whole um, so a calibration's evenly spaced bins come
/// back within 1 um of it.
pub const UNIFORM_TOLERANCE_MM: f64 = 0.0015;

/// A transition table in fixed point.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TransitionCoeffs {
    pub(crate) n_d: u8,
    pub(crate) n_g0: u8,
    /// Rows per count of travel in Q0.32: `d * rows_q32` is the row position in Q32.32, one
    /// `UMULL` whose high word is the row and low word the fraction. Steps of at least two counts
    /// keep it below 2^31; the step is honoured to `1 / rows_q32` relative (the reference uses
    /// the same quantised value).
    pub(crate) rows_q32: u32,
    /// Columns per Q16.16 unit of initial gap, in Q0.32 (steps of at least two units).
    pub(crate) cols_q32: u32,
    pub(crate) gap_um: [[U11F5; MAX_TRANSITION_G0]; MAX_TRANSITION_D],
}

/// Model 3 in fixed point; build with [`Model3Params::build`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Model3Coeffs {
    pub(crate) forward_band: BandCoeffs,
    pub(crate) reverse_band: BandCoeffs,
    pub(crate) forward_transition: TransitionCoeffs,
    pub(crate) reverse_transition: TransitionCoeffs,
    #[cfg(feature = "std")]
    pub(crate) closing: Closing,
}

struct BandFields {
    len: ConfigField,
    x: ConfigField,
    y: ConfigField,
}

struct TransitionFields {
    n_d: ConfigField,
    n_g0: ConfigField,
    d_step: ConfigField,
    g0_step: ConfigField,
    gap: ConfigField,
}

const _: () = assert!(MAX_BAND_POINTS.is_power_of_two() && MAX_TRANSITION_D.is_power_of_two());

const FWD_BAND: BandFields = BandFields {
    len: ConfigField::Model3ForwardBandLen,
    x: ConfigField::Model3ForwardBandXMm,
    y: ConfigField::Model3ForwardBandYUm,
};
const REV_BAND: BandFields = BandFields {
    len: ConfigField::Model3ReverseBandLen,
    x: ConfigField::Model3ReverseBandXMm,
    y: ConfigField::Model3ReverseBandYUm,
};
const FWD_TRANSITION: TransitionFields = TransitionFields {
    n_d: ConfigField::Model3ForwardTransitionND,
    n_g0: ConfigField::Model3ForwardTransitionNG0,
    d_step: ConfigField::Model3ForwardTransitionDStepMm,
    g0_step: ConfigField::Model3ForwardTransitionG0StepUm,
    gap: ConfigField::Model3ForwardTransitionGapUm,
};
const REV_TRANSITION: TransitionFields = TransitionFields {
    n_d: ConfigField::Model3ReverseTransitionND,
    n_g0: ConfigField::Model3ReverseTransitionNG0,
    d_step: ConfigField::Model3ReverseTransitionDStepMm,
    g0_step: ConfigField::Model3ReverseTransitionG0StepUm,
    gap: ConfigField::Model3ReverseTransitionGapUm,
};

/// Where Model 3's table values come from when the coefficients are built: the `f64` arrays of
/// [`Model3Params`] on the host, or a calibration blob read in place on the target, so that the
/// firmware never holds the 16 KiB of `f64` tables. `dir` is 0 forward, 1 reverse.
pub trait Model3Source {
    /// Points of band table `dir`.
    fn band_len(&self, dir: usize) -> usize;
    /// Point `i` of band table `dir`: `(x_mm, y_um)`.
    fn band_point(&self, dir: usize, i: usize) -> (f64, f64);
    /// Shape of transition table `dir`: `(n_d, n_g0, d_step_mm, g0_step_um)`.
    fn transition_shape(&self, dir: usize) -> (usize, usize, f64, f64);
    /// Cell `(i, j)` of transition table `dir`, um.
    fn gap_um(&self, dir: usize, i: usize, j: usize) -> f64;
}

impl Model3Source for Model3Params {
    fn band_len(&self, dir: usize) -> usize {
        self.band(dir).len
    }
    fn band_point(&self, dir: usize, i: usize) -> (f64, f64) {
        let b = self.band(dir);
        (b.x_mm[i % MAX_BAND_POINTS], b.y_um[i % MAX_BAND_POINTS])
    }
    fn transition_shape(&self, dir: usize) -> (usize, usize, f64, f64) {
        let t = self.transition(dir);
        (t.n_d, t.n_g0, t.d_step_mm, t.g0_step_um)
    }
    fn gap_um(&self, dir: usize, i: usize, j: usize) -> f64 {
        self.transition(dir).gap_um[i % MAX_TRANSITION_D][j % MAX_TRANSITION_G0]
    }
}

impl Model3Params {
    fn band(&self, dir: usize) -> &BandParams {
        if dir == 0 {
            &self.forward_band
        } else {
            &self.reverse_band
        }
    }

    fn transition(&self, dir: usize) -> &TransitionParams {
        if dir == 0 {
            &self.forward_transition
        } else {
            &self.reverse_transition
        }
    }

    /// Checks and quantises the tables for a rig with `counts_per_mm` counts per mm
    /// (see [`build_model3`]).
    pub fn build(&self, counts_per_mm: f64) -> Result<Model3Coeffs, ConfigError> {
        build_model3(self, counts_per_mm)
    }
}

/// Checks and quantises Model 3's tables from `src` for a rig with `counts_per_mm` counts per mm.
///
/// Errors name the table and field: NaN/inf (`NotFinite`), a point count outside its limits
/// (`TableSize`), an axis not strictly increasing after rounding to counts (`NotMonotonic`),
/// a value outside its format, a negative gap, or a reverse band below the forward band
/// (`OutOfRange`, on `model3.reverse_band.y_um`).
pub fn build_model3(
    src: &impl Model3Source,
    counts_per_mm: f64,
) -> Result<Model3Coeffs, ConfigError> {
    let forward_band = build_band(src, 0, counts_per_mm, &FWD_BAND)?;
    let reverse_band = build_band(src, 1, counts_per_mm, &REV_BAND)?;
    check_band_order(src)?;
    let forward_transition = build_transition(src, 0, counts_per_mm, &FWD_TRANSITION)?;
    let reverse_transition = build_transition(src, 1, counts_per_mm, &REV_TRANSITION)?;
    // Reported by the host (hil-sim); the firmware has no use for them.
    #[cfg(feature = "std")]
    let closing = Closing::from_mm(
        forward_transition.closing_mm(counts_per_mm),
        reverse_transition.closing_mm(counts_per_mm),
    );
    Ok(Model3Coeffs {
        forward_band,
        reverse_band,
        forward_transition,
        reverse_transition,
        #[cfg(feature = "std")]
        closing,
    })
}

fn build_band(
    src: &impl Model3Source,
    dir: usize,
    counts_per_mm: f64,
    f: &BandFields,
) -> Result<BandCoeffs, ConfigError> {
    let len = src.band_len(dir);
    if !(2..=MAX_BAND_POINTS).contains(&len) {
        return Err(ConfigError::TableSize(f.len));
    }
    // The even axis through the first and last points: every point must lie on it.
    let (first_mm, last_mm) = (src.band_point(dir, 0).0, src.band_point(dir, len - 1).0);
    let step_mm = (last_mm - first_mm) / (len - 1) as f64;
    let mut c = BandCoeffs {
        len: len as u8,
        x0_counts: 0,
        points_q32: 0,
        y_um: [I16F16::ZERO; MAX_BAND_POINTS],
    };
    let mut prev_counts = 0;
    for (i, y) in c.y_um.iter_mut().enumerate().take(len) {
        let (x_mm, v_um) = src.band_point(dir, i);
        let x =
            round_i32(finite(x_mm, f.x)? * counts_per_mm).ok_or(ConfigError::OutOfRange(f.x))?;
        if i == 0 {
            c.x0_counts = x;
        } else if x <= prev_counts {
            return Err(ConfigError::NotMonotonic(f.x));
        }
        prev_counts = x;
        if (x_mm - (first_mm + i as f64 * step_mm)).abs() > UNIFORM_TOLERANCE_MM {
            return Err(ConfigError::NotUniform(f.x));
        }
        *y = um_q16(v_um, -MAX_ABS_UM, f.y)?;
    }
    c.points_q32 = per_step_q32(step_mm * counts_per_mm, f.x)?;
    Ok(c)
}

/// Cells per unit of an even axis in Q0.32 for a step of `step` units: a position times it is
/// the cell in Q32.32 (one `UMULL`). Steps of at least two units keep it below 2^31; a step
/// beyond 2^33 units cannot be resolved. `step` is finite (the callers check it first).
fn per_step_q32(step: f64, field: ConfigField) -> Result<u32, ConfigError> {
    if step < 2.0 {
        return Err(ConfigError::OutOfRange(field));
    }
    match round_i32(4_294_967_296.0 / step) {
        Some(v) if v >= 1 => Ok(v as u32),
        _ => Err(ConfigError::OutOfRange(field)),
    }
}

/// Linear interpolation of band `dir` of `src` in `f64`, clamped outside the axis.
fn source_value_at(src: &impl Model3Source, dir: usize, x_mm: f64) -> f64 {
    let mut prev: Option<(f64, f64)> = None;
    for i in 0..src.band_len(dir).min(MAX_BAND_POINTS) {
        let (x1, y1) = src.band_point(dir, i);
        match prev {
            None if x_mm <= x1 => return y1,
            Some((x0, y0)) if x_mm < x1 => {
                return y0 + (x_mm - x0) / (x1 - x0) * (y1 - y0);
            }
            _ => prev = Some((x1, y1)),
        }
    }
    prev.map_or(0.0, |(_, y)| y)
}

/// `Λ_r >= Λ_f` everywhere; both are piecewise linear, so checking every knot of both suffices.
fn check_band_order(src: &impl Model3Source) -> Result<(), ConfigError> {
    for dir in 0..2 {
        for i in 0..src.band_len(dir).min(MAX_BAND_POINTS) {
            let x = src.band_point(dir, i).0;
            if source_value_at(src, 1, x) < source_value_at(src, 0, x) {
                return Err(ConfigError::OutOfRange(REV_BAND.y));
            }
        }
    }
    Ok(())
}

fn build_transition(
    src: &impl Model3Source,
    dir: usize,
    counts_per_mm: f64,
    f: &TransitionFields,
) -> Result<TransitionCoeffs, ConfigError> {
    let (n_d, n_g0, d_step_mm, g0_step_um) = src.transition_shape(dir);
    if !(2..=MAX_TRANSITION_D).contains(&n_d) {
        return Err(ConfigError::TableSize(f.n_d));
    }
    if !(2..=MAX_TRANSITION_G0).contains(&n_g0) {
        return Err(ConfigError::TableSize(f.n_g0));
    }
    // In counts and in Q16.16 units (see `per_step_q32`).
    let rows_q32 = per_step_q32(finite(d_step_mm, f.d_step)? * counts_per_mm, f.d_step)?;
    if finite(g0_step_um, f.g0_step)? > MAX_ABS_UM {
        return Err(ConfigError::OutOfRange(f.g0_step));
    }
    let cols_q32 = per_step_q32(g0_step_um * 65536.0, f.g0_step)?;
    let mut c = TransitionCoeffs {
        n_d: n_d as u8,
        n_g0: n_g0 as u8,
        rows_q32,
        cols_q32,
        gap_um: [[U11F5::ZERO; MAX_TRANSITION_G0]; MAX_TRANSITION_D],
    };
    for i in 0..n_d {
        for j in 0..n_g0 {
            let g = finite(src.gap_um(dir, i, j), f.gap)?;
            c.gap_um[i][j] = U11F5::checked_from_num(g).ok_or(ConfigError::OutOfRange(f.gap))?;
        }
    }
    Ok(c)
}

impl BandCoeffs {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.len as usize
    }

    /// Always false for built coefficients (at least two points).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The quantised points: counts on the even axis (as `f64`, the step need not be whole
    /// counts) and Q16.16 um.
    pub fn points(&self) -> impl Iterator<Item = (f64, I16F16)> + '_ {
        let step = self.step_counts();
        self.y_um
            .iter()
            .copied()
            .take(self.len())
            .enumerate()
            .map(move |(i, y)| (self.x0_counts as f64 + i as f64 * step, y))
    }

    /// The axis step in counts, as the tick uses it (`2^32 / points_q32`).
    pub fn step_counts(&self) -> f64 {
        4_294_967_296.0 / self.points_q32.max(1) as f64
    }

    // MAX_BAND_POINTS is a power of two: masking an index proves it in bounds to the compiler
    // (no panic path, no bounds-check branch); every index used is below `len` anyway.
    #[inline]
    fn y(&self, i: u8) -> i32 {
        self.y_um[i as usize & (MAX_BAND_POINTS - 1)].to_bits()
    }

    /// `Λ(x)` as Q16.16 um bits: the cell on the even axis by one multiply, held at the end
    /// values outside it. Total on any coefficients (an empty table gives 0). The definition
    /// [`BandCoeffs::eval_cached`] is tested against; the drive calls only that.
    #[cfg(test)]
    pub(crate) fn eval(&self, x: i32) -> i32 {
        let cell = Cell::locate(self.position_q32(x), self.len);
        lerp_q32(self.y(cell.lo), self.y(cell.hi), cell.t)
    }

    /// The position of `x` on the axis in Q32.32 (held at 0 before the first point). `x - x0`
    /// of two `i32` lies in `[0, 2^32)` once `x >= x0`; times a Q0.32 below 2^31, below 2^63.
    #[inline(always)]
    pub(crate) fn position_q32(&self, x: i32) -> u64 {
        let d = if x < self.x0_counts {
            0
        } else {
            x.wrapping_sub(self.x0_counts) as u32
        };
        d as u64 * self.points_q32 as u64
    }

    /// [`BandCoeffs::eval`] with the cell's ends kept in `cache`: bit-identical, and a tick
    /// that stays in the cell (nearly all) reloads nothing.
    #[inline(always)]
    pub(crate) fn eval_cached(&self, x: i32, cache: &mut SegmentCache) -> i32 {
        let pos = self.position_q32(x);
        // `len >= 2` once built: one SUBS instead of five. An empty table (`ModelCoeffs::ZERO`)
        // wraps to 255, but its `points_q32` is 0, so `i` is 0 as with the saturated 0.
        let last = self.len.wrapping_sub(1) as u32;
        let i = ((pos >> 32) as u32).min(last);
        if i != cache.index {
            // Past the last point both ends are the last value: the hold of `Cell::locate`.
            let lo = self.y(i as u8);
            let hi = self.y(if i < last { i as u8 + 1 } else { i as u8 });
            *cache = SegmentCache::new(i, lo, hi);
        }
        cache.at(pos as u32)
    }
}

/// One segment of a piecewise-linear table in use: its index and its ends (Q16.16 um bits), so
/// that the next tick in the same segment is one multiply. Invalid: an index no table has.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct SegmentCache {
    index: u32,
    lo: i32,
    /// `hi - lo`, wrapping (as [`lerp_q32`] computes it).
    diff: i32,
}

impl SegmentCache {
    /// Nothing cached: the next use loads its segment.
    pub(crate) const EMPTY: SegmentCache = SegmentCache {
        index: u32::MAX,
        lo: 0,
        diff: 0,
    };

    /// Empties the cache: only the index says whether it holds a segment, so the ends stay.
    #[inline(always)]
    pub(crate) fn invalidate(&mut self) {
        self.index = Self::EMPTY.index;
    }

    #[inline(always)]
    fn new(index: u32, lo: i32, hi: i32) -> SegmentCache {
        SegmentCache {
            index,
            lo,
            diff: hi.wrapping_sub(lo),
        }
    }

    /// [`lerp_q32`] between the segment's ends at `t` (Q0.32), bit for bit.
    #[inline(always)]
    fn at(&self, t: u32) -> i32 {
        lerp_diff_q32(self.lo, self.diff, t)
    }
}

/// A cell coordinate along one uniform axis: lower index, upper index, fraction in Q0.32.
/// Past the end of the axis both indices are the last one and the fraction is 0 (hold).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Cell {
    pub lo: u8,
    pub hi: u8,
    pub t: u32,
}

impl Cell {
    #[inline]
    fn locate(pos_q32: u64, n: u8) -> Cell {
        let last = n.saturating_sub(1) as u64;
        let i = pos_q32 >> 32;
        if i >= last {
            Cell {
                lo: last as u8,
                hi: last as u8,
                t: 0,
            }
        } else {
            Cell {
                lo: i as u8,
                hi: i as u8 + 1,
                t: pos_q32 as u32,
            }
        }
    }
}

impl TransitionCoeffs {
    /// Rows (`d` axis).
    pub fn n_d(&self) -> usize {
        self.n_d as usize
    }

    /// Columns (`g0` axis).
    pub fn n_g0(&self) -> usize {
        self.n_g0 as usize
    }

    /// The quantised gap at row `i`, column `j`.
    pub fn gap_um(&self, i: usize, j: usize) -> Option<U11F5> {
        if i >= self.n_d() || j >= self.n_g0() {
            return None;
        }
        self.gap_um.get(i).and_then(|row| row.get(j)).copied()
    }

    /// Rows per count of travel as used per tick (the quantised inverse of the row spacing).
    pub fn rows_per_count(&self) -> f64 {
        self.rows_q32 as f64 / 4_294_967_296.0
    }

    /// Columns per um of initial gap as used per tick (the quantised inverse of the spacing).
    pub fn columns_per_um(&self) -> f64 {
        self.cols_q32 as f64 * 65536.0 / 4_294_967_296.0
    }

    /// Travel after which every row is zero (all transitions have closed), in mm; `None` if the
    /// last row holds a non-zero gap.
    #[cfg(feature = "std")]
    fn closing_mm(&self, counts_per_mm: f64) -> Option<f64> {
        let mut first_zero = self.n_d();
        while first_zero > 0 {
            let row = first_zero - 1;
            let all_zero = (0..self.n_g0()).all(|j| self.gap_um(row, j) == Some(U11F5::ZERO));
            if !all_zero {
                break;
            }
            first_zero = row;
        }
        if first_zero == self.n_d() {
            None
        } else {
            Some(first_zero as f64 / self.rows_per_count() / counts_per_mm)
        }
    }

    /// Column cell of the initial gap `g0` (Q16.16 um bits, `>= 0`).
    #[inline]
    pub(crate) fn g0_cell(&self, g0_bits: i32) -> Cell {
        Cell::locate(g0_bits.max(0) as u64 * self.cols_q32 as u64, self.n_g0)
    }

    /// Row `i` of the table interpolated at the column cell `col`, Q16.16 um bits. Both
    /// indices are masked or capped into the array (no panic path, no branch): a cell from
    /// [`TransitionCoeffs::g0_cell`] is always inside the table, and at the last column its
    /// fraction is 0, so the value beside it (capped) does not count.
    #[inline(always)]
    fn row_at(&self, i: u8, col: Cell) -> i32 {
        let row = &self.gap_um[i as usize & (MAX_TRANSITION_D - 1)];
        let j = col.lo as usize;
        // U11F5 -> Q16.16: < 2^27, no overflow.
        let a = (row[j.min(MAX_TRANSITION_G0 - 1)].to_bits() as i32) << 11;
        let b = (row[(j + 1).min(MAX_TRANSITION_G0 - 1)].to_bits() as i32) << 11;
        lerp_q32(a, b, col.t)
    }

    /// `G(d, g0)` in Q16.16 um bits for `d_counts` of travel and the column cell `col` of `g0`.
    ///
    /// `g0` is fixed during a transition, so the two rows around `d`, interpolated at `g0`, are
    /// kept in `rows` (empty whenever `g0` changes) and recomputed only when `d` enters another
    /// row pair: a typical tick is one multiply (the row position) and one interpolation.
    #[inline(always)]
    pub(crate) fn eval(&self, d_counts: u32, col: Cell, rows: &mut SegmentCache) -> i32 {
        let pos = d_counts as u64 * self.rows_q32 as u64;
        // As for the bands: an empty table wraps to 255, but its `rows_q32` is 0, so `r` is 0.
        let last = self.n_d.wrapping_sub(1) as u32;
        let r = ((pos >> 32) as u32).min(last);
        if r != rows.index {
            // Past the last row both rows are the last: the hold of `Cell::locate`.
            let (lo, hi) = (r as u8, if r < last { r as u8 + 1 } else { r as u8 });
            *rows = SegmentCache::new(r, self.row_at(lo, col), self.row_at(hi, col));
        }
        rows.at(pos as u32)
    }
}

impl Model3Coeffs {
    /// The band table followed in direction `dir` (`Λ_f` forward, `Λ_r` reverse).
    pub fn band(&self, dir: Direction) -> &BandCoeffs {
        match dir {
            Direction::Forward => &self.forward_band,
            Direction::Reverse => &self.reverse_band,
        }
    }

    /// The transition table used after a reversal into direction `dir`.
    pub fn transition(&self, dir: Direction) -> &TransitionCoeffs {
        match dir {
            Direction::Forward => &self.forward_transition,
            Direction::Reverse => &self.reverse_transition,
        }
    }

    /// Travel after which the tables' transitions have closed, per direction (host only).
    #[cfg(feature = "std")]
    pub fn closing(&self) -> Closing {
        self.closing
    }
}

/// The first Model 3 tick of a transition: the column cell of `g0` (`g0 = max(0, y_d -
/// Λ_f(x_d))` forward, `max(0, Λ_r(x_d) - y_d)` reverse), then the gap at `d_counts` of travel
/// through a fresh row pair. Once per reversal, on the first Model 3 tick after it (a reversal
/// under another model costs nothing here; switching to Model 3 mid-transition gives the same
/// cell as computing it at the reversal). Out of line and cold: the tick that needs it is the
/// reversal's, and the common tick keeps its registers.
#[cold]
#[inline(never)]
fn start_transition(c: &Model3Coeffs, s: &mut ModelState, d_counts: u32) -> i32 {
    let dir = s.dir;
    // Through the band's cache: the tick is at x near x_d, mostly in this segment.
    let edge = c.band(dir).eval_cached(s.x_d_counts, &mut s.band);
    let y_d = s.y_d_um.to_bits();
    // Saturating where the difference leaves `i32`; `g0_cell` takes a negative `g0` as 0.
    let g0 = match dir {
        Direction::Forward => y_d.saturating_sub(edge),
        Direction::Reverse => edge.saturating_sub(y_d),
    };
    let t = c.transition(dir);
    s.g0_cell = t.g0_cell(g0);
    s.needs_g0 = false;
    s.rows.invalidate();
    t.eval(d_counts, s.g0_cell, &mut s.rows)
}

/// Model 3's estimate as one straight line over the stretch of travel where neither the band
/// segment nor the transition's row pair (nor the hold before the turning point) changes: there
/// both terms of eq. 18 are linear in `x`, so their sum is too. A tick on the line is one
/// multiply (about 15 instructions instead of two table lookups and interpolations, about 60);
/// a tick off it interpolates as before. The next line is drawn in two halves on the following
/// ticks that reload no table segment: the band's stretch (about 60 instructions), then the
/// transition's and the line (about 85), so that no tick pays a reload and a whole new line
/// together, nor a reversal and a line (the reversal's first tick only interpolates).
///
/// Within one line `y = y_ref + slope (x - x_ref)` rounds once where the interpolations round
/// twice: the two agree within a few 2^-16 um (a property test holds them to 4 LSB).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Piece {
    /// Valid for `x - lo` in `[0, span)` (as `u32`): `span = 0` holds nothing.
    lo: i32,
    pub(crate) span: u32,
    /// Where the line was drawn, and the estimate there (Q16.16 um bits).
    x_ref: i32,
    y_ref: i32,
    /// Q16.16 um bits per count, times 2^32 (while half drawn: the band's).
    slope: i64,
    /// Half drawn: the band segment's (or hold's) stretch `[half_lo, half_hi]`.
    half: bool,
    half_lo: i32,
    half_hi: i32,
}

impl Piece {
    pub(crate) const NONE: Piece = Piece {
        lo: 0,
        span: 0,
        x_ref: 0,
        y_ref: 0,
        slope: 0,
        half: false,
        half_lo: 0,
        half_hi: 0,
    };

    /// Holds nothing: the next ticks interpolate and draw anew.
    #[inline(always)]
    pub(crate) fn invalidate(&mut self) {
        self.span = 0;
        self.half = false;
    }

    /// The line through `(x, y)` with the slope in hand, over `[lo, hi]` (`lo <= x <= hi`).
    #[inline(always)]
    fn set(&mut self, lo: i32, hi: i32, x: i32, y: i32) {
        self.lo = lo;
        // The whole `i32` range loses its one last count.
        self.span = (hi.wrapping_sub(lo) as u32).saturating_add(1);
        self.x_ref = x;
        self.y_ref = y;
        self.half = false;
    }

    /// The line at `x`, if `x` lies on it.
    #[inline(always)]
    fn at(&self, x: i32) -> Option<i32> {
        if (x.wrapping_sub(self.lo) as u32) >= self.span {
            return None;
        }
        // Within the tables' contract (values below 2^30) |slope (x - x_ref)| < 2^63: the line
        // spans at most one band segment and one row (`pq |x - x_ref| < 2^32`), and where it
        // has a slope at most 2^30 counts either way (`cell_room`: `x - x_ref` does not wrap);
        // on the holds the slope is 0.
        let rel = x.wrapping_sub(self.x_ref) as i64;
        let step = self.slope.wrapping_mul(rel).wrapping_add(1 << 31) >> 32;
        Some(self.y_ref.wrapping_add(step as i32))
    }
}

/// The counts `x` can move back and forward and stay in the cell of an even axis at fraction
/// `t` (Q0.32) with `per_count` (Q0.32 of a cell per count): `t / per_count` back, `(2^32 - 1 -
/// t) / per_count` forward, two hardware divisions. Dividing by at least 4 holds each below
/// 2^30, so that a line with a slope never spans enough for `x - x_ref` to wrap (only cells of
/// more than 2^30 counts see less than their whole room).
#[inline(always)]
fn cell_room(t: u32, per_count: u32) -> (u32, u32) {
    let q = NonZeroU32::new(per_count.max(4)).unwrap_or(NonZeroU32::MIN);
    (t / q, !t / q)
}

/// `x - m` and `x + m` held within the `i32` range.
#[inline(always)]
fn back_by(x: i32, m: u32) -> i32 {
    x.wrapping_sub(m.min(x.wrapping_sub(i32::MIN) as u32) as i32)
}
#[inline(always)]
fn on_by(x: i32, m: u32) -> i32 {
    x.wrapping_add(m.min(i32::MAX.wrapping_sub(x) as u32) as i32)
}

/// The first half of a new [`Piece`]: the band segment's stretch around `x` (in the cache),
/// and its slope. Without a transition that is the line, drawn through `(x, y)`.
#[inline(never)]
fn draw_band(c: &Model3Coeffs, s: &mut ModelState, x: i32, y: i32) {
    let b = c.band(s.dir);
    // Held at the first value before the axis, linear within a segment, held from the last
    // point on (where the cached difference is 0).
    let (lo, hi, slope) = if x < b.x0_counts {
        // The cache holds segment 0 at its start.
        (i32::MIN, b.x0_counts.wrapping_sub(1), 0)
    } else {
        let (to_start, to_end) = cell_room(b.position_q32(x) as u32, b.points_q32);
        let hi = if s.band.index < b.len.wrapping_sub(1) as u32 {
            on_by(x, to_end)
        } else {
            i32::MAX
        };
        (
            back_by(x, to_start),
            hi,
            s.band.diff as i64 * b.points_q32 as i64,
        )
    };
    let p = &mut s.piece;
    p.slope = slope;
    if s.transition {
        // The old line goes with its slope: a tick back on it would read the band's.
        p.span = 0;
        (p.half, p.half_lo, p.half_hi) = (true, lo, hi);
    } else {
        p.set(lo, hi, x, y);
    }
}

/// The second half: the transition's stretch around `x` (its row pair in the cache, or the
/// hold before the turning point) within the band's, and the line through `(x, y)`.
#[inline(never)]
fn draw_rows(c: &Model3Coeffs, s: &mut ModelState, x: i32, y: i32) {
    let dir = s.dir;
    let t_c = c.transition(dir);
    let forward = dir == Direction::Forward;
    let (from, to) = if forward {
        (s.x_d_counts, x)
    } else {
        (x, s.x_d_counts)
    };
    let (mut lo, mut hi) = (s.piece.half_lo, s.piece.half_hi);
    if to <= from {
        // Held at d = 0 up to the turning point.
        if forward {
            hi = hi.min(s.x_d_counts);
        } else {
            lo = lo.max(s.x_d_counts);
        }
    } else {
        // Travel `d` from the turning point along `dir`: `x` moves with `d` forward, against
        // it in reverse. Row 0 reaches back to d = 0 (`to_start = d` there), where the hold
        // begins; the last row is held on.
        let d = to.wrapping_sub(from) as u32;
        let (to_start, to_end) = cell_room(d.wrapping_mul(t_c.rows_q32), t_c.rows_q32);
        let to_end = if s.rows.index < t_c.n_d.wrapping_sub(1) as u32 {
            to_end
        } else {
            u32::MAX
        };
        let (b_r, f_r) = if forward {
            (to_start, to_end)
        } else {
            (to_end, to_start)
        };
        lo = lo.max(back_by(x, b_r));
        hi = hi.min(on_by(x, f_r));
        // The gap adds its slope per count either way (eq. 18 subtracts it in reverse, where
        // `d` falls as `x` rises).
        s.piece.slope = s
            .piece
            .slope
            .wrapping_add(s.rows.diff as i64 * t_c.rows_q32 as i64);
    }
    s.piece.set(lo, hi, x, y);
}

/// One step of eq. 18 in our parametrisation: on the current [`Piece`], or by interpolation.
#[inline]
pub(crate) fn eval(c: &Model3Coeffs, s: &mut ModelState, x_counts: i32) -> I16F16 {
    if s.needs_g0 {
        // The first tick of a transition (after a reversal, no line): interpolate only.
        return interpolate(c, s, x_counts);
    }
    if let Some(y) = s.piece.at(x_counts) {
        return I16F16::from_bits(y);
    }
    let (band_at, rows_at) = (s.band.index, s.rows.index);
    let y = interpolate(c, s, x_counts);
    // Nothing reloaded: the caches hold this stretch.
    if s.band.index == band_at && s.rows.index == rows_at {
        let p = &s.piece;
        if p.half && x_counts >= p.half_lo && x_counts <= p.half_hi {
            draw_rows(c, s, x_counts, y.to_bits());
        } else {
            draw_band(c, s, x_counts, y.to_bits());
        }
    }
    y
}

/// Eq. 18 by interpolating the band table and the transition table.
#[inline(always)]
fn interpolate(c: &Model3Coeffs, s: &mut ModelState, x_counts: i32) -> I16F16 {
    let dir = s.dir;
    let edge = c.band(dir).eval_cached(x_counts, &mut s.band);
    if !s.transition {
        return I16F16::from_bits(edge);
    }
    // Travel since the turning point along `dir`, held at 0 before it: the difference of two
    // `i32` lies in [0, 2^32) on the far side.
    let (from, to) = match dir {
        Direction::Forward => (s.x_d_counts, x_counts),
        Direction::Reverse => (x_counts, s.x_d_counts),
    };
    let d = if to <= from {
        0
    } else {
        to.wrapping_sub(from) as u32
    };
    let gap = if s.needs_g0 {
        start_transition(c, s, d)
    } else {
        c.transition(dir).eval(d, s.g0_cell, &mut s.rows)
    };
    I16F16::from_bits(match dir {
        Direction::Forward => edge.saturating_add(gap),
        Direction::Reverse => edge.saturating_sub(gap),
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Band tables of 2 to 64 points from `x0` with `points_q32` from `min_points_q32`
    /// (segments of at most `2^32 / min_points_q32` counts), values within the contract.
    pub(crate) fn band_in(
        x0: impl Strategy<Value = i32>,
        min_points_q32: u32,
    ) -> impl Strategy<Value = BandCoeffs> {
        (
            2u8..=MAX_BAND_POINTS as u8,
            x0,
            min_points_q32..(1u32 << 31),
            prop::collection::vec(-(1i32 << 29)..(1i32 << 29), MAX_BAND_POINTS),
        )
            .prop_map(|(len, x0_counts, points_q32, y)| {
                let mut b = BandCoeffs {
                    len,
                    x0_counts,
                    points_q32,
                    y_um: [I16F16::ZERO; MAX_BAND_POINTS],
                };
                for (dst, v) in b.y_um.iter_mut().zip(y) {
                    *dst = I16F16::from_bits(v);
                }
                b
            })
    }

    fn band() -> impl Strategy<Value = BandCoeffs> {
        band_in(any::<i32>(), 1 << 12)
    }

    /// Transition tables of any shape and gaps, rows from `min_rows_q32` per count.
    pub(crate) fn transition_in(min_rows_q32: u32) -> impl Strategy<Value = TransitionCoeffs> {
        (
            2u8..=MAX_TRANSITION_D as u8,
            2u8..=MAX_TRANSITION_G0 as u8,
            min_rows_q32..(1u32 << 31),
            (1u32 << 12)..(1u32 << 31),
            prop::collection::vec(any::<u16>(), MAX_TRANSITION_D * MAX_TRANSITION_G0),
        )
            .prop_map(|(n_d, n_g0, rows_q32, cols_q32, gaps)| {
                let mut t = TransitionCoeffs {
                    n_d,
                    n_g0,
                    rows_q32,
                    cols_q32,
                    gap_um: [[U11F5::ZERO; MAX_TRANSITION_G0]; MAX_TRANSITION_D],
                };
                for (k, g) in gaps.into_iter().enumerate() {
                    t.gap_um[k / MAX_TRANSITION_G0][k % MAX_TRANSITION_G0] = U11F5::from_bits(g);
                }
                t
            })
    }

    /// One move of a walk: a small step either way (most ticks stay in a segment) or a jump.
    #[derive(Clone, Copy, Debug)]
    enum Move {
        By(i32),
        To(i32),
    }

    fn walk() -> impl Strategy<Value = Vec<Move>> {
        prop::collection::vec(
            prop_oneof![
                4 => (-3000i32..3000).prop_map(Move::By),
                1 => any::<i32>().prop_map(Move::To),
            ],
            1..400,
        )
    }

    proptest! {
        /// The cached band segment gives what a fresh lookup gives, bit for bit, wherever the
        /// positions go (before the first point, across segments, past the last).
        #[test]
        fn cached_band_is_the_lookup(b in band(), start in any::<i32>(), steps in walk()) {
            let mut cache = SegmentCache::EMPTY;
            let mut x = start;
            for m in steps {
                x = match m {
                    Move::By(s) => x.saturating_add(s),
                    Move::To(to) => to,
                };
                prop_assert_eq!(b.eval_cached(x, &mut cache), b.eval(x), "x = {}", x);
            }
        }

        /// The cached row pair gives the interpolation of the four table values around
        /// `(d, g0)`, bit for bit, for any travel sequence and initial gap.
        #[test]
        fn cached_rows_are_the_lookup(
            t in transition_in(1 << 12),
            g0_bits in any::<i32>(),
            steps in walk(),
        ) {
            let col = t.g0_cell(g0_bits);
            let g = |i: u8, j: u8| (t.gap_um[i as usize][j as usize].to_bits() as i32) << 11;
            let mut rows = SegmentCache::EMPTY;
            let mut d = 0u32;
            for m in steps {
                d = match m {
                    Move::By(s) => d.saturating_add_signed(s),
                    Move::To(to) => to as u32,
                };
                let row = Cell::locate(d as u64 * t.rows_q32 as u64, t.n_d);
                let near = lerp_q32(g(row.lo, col.lo), g(row.lo, col.hi), col.t);
                let far = lerp_q32(g(row.hi, col.lo), g(row.hi, col.hi), col.t);
                prop_assert_eq!(t.eval(d, col, &mut rows), lerp_q32(near, far, row.t), "d = {}", d);
            }
        }
    }
}
