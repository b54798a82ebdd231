//! What machine builders use today (see shared/ANCHORS.md), as compensators of the drive beside
//! the paper's models, so that all of them run on the same plant through the same code:
//! - constant backlash, the LinuxCNC `BACKLASH` / Marlin `M425` way: one offset and one backlash
//!   per axis, `offset -+ backlash/2` by direction of travel;
//! - a bidirectional table, the LinuxCNC `COMP_FILE` way: up to [`MAX_BIDIR_ROWS`] evenly spaced
//!   rows of (forward error, reverse error), linear interpolation, held flat outside the rows,
//!   nothing between the two curves.
//!
//! The direction is the reversal detector's (the same dead band as the models'), which equals the
//! commanded direction along a planned path. Neither keeps any state of its own.

use crate::ConfigField;
use fixed::types::{I13F3, I16F16};

use super::convert::{finite, um_q16};
use super::fixmath::{lerp_q32, round_i32, round_u64, Recip};
use super::{Direction, ModelState};
use crate::ConfigError;

/// Rows of the largest bidirectional table (LinuxCNC's `COMP_FILE` limit).
pub const MAX_BIDIR_ROWS: usize = 256;

/// Constant backlash in micrometres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BacklashParams {
    /// Mean of the two directions' errors, um.
    pub offset_um: f64,
    /// Reverse minus forward error, um (what `M425` or LinuxCNC's `BACKLASH` is set to).
    pub backlash_um: f64,
}

impl BacklashParams {
    /// From Table 2's Model 1 band at the encoder's zero: forward rides `-h`, reverse `0`.
    pub const PAPER: BacklashParams = BacklashParams {
        offset_um: -170.0,
        backlash_um: 340.0,
    };

    /// Checks and converts to fixed point.
    pub fn build(&self) -> Result<BacklashCoeffs, ConfigError> {
        let offset = um_q16(
            self.offset_um,
            -super::MAX_ABS_UM,
            ConfigField::BacklashOffsetUm,
        )?;
        let backlash = um_q16(
            self.backlash_um,
            -super::MAX_ABS_UM,
            ConfigField::BacklashBacklashUm,
        )?;
        Ok(BacklashCoeffs {
            forward_um: offset - backlash / 2,
            reverse_um: offset + (backlash - backlash / 2),
        })
    }
}

/// Constant backlash in fixed point: the estimate per direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BacklashCoeffs {
    pub(crate) forward_um: I16F16,
    pub(crate) reverse_um: I16F16,
}

impl BacklashCoeffs {
    /// The estimate travelling in `dir`, um.
    #[inline]
    pub fn at(&self, dir: Direction) -> I16F16 {
        match dir {
            Direction::Forward => self.forward_um,
            Direction::Reverse => self.reverse_um,
        }
    }
}

/// Where a bidirectional table's values come from: `f64` parameters or a blob in place.
pub trait BidirSource {
    /// `(rows, x0_mm, step_mm)`: the first row's motor position and the spacing.
    fn shape(&self) -> (usize, f64, f64);
    /// Row `i` of direction `dir` (0 forward, 1 reverse), um.
    fn value_um(&self, dir: usize, i: usize) -> f64;
}

/// A bidirectional table in micrometres of error over mm of motor travel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BidirParams {
    /// Motor position of row 0, mm.
    pub x0_mm: f64,
    /// Row spacing, mm (> 0).
    pub step_mm: f64,
    /// Rows in use, `2..=MAX_BIDIR_ROWS`.
    pub rows: usize,
    /// Error travelling forward, per row, um.
    pub forward_um: [f64; MAX_BIDIR_ROWS],
    /// Error travelling in reverse, per row, um.
    pub reverse_um: [f64; MAX_BIDIR_ROWS],
}

impl BidirParams {
    /// Two rows of zeros over 0-1 mm: a start to fill in.
    pub const ZERO: BidirParams = BidirParams {
        x0_mm: 0.0,
        step_mm: 1.0,
        rows: 2,
        forward_um: [0.0; MAX_BIDIR_ROWS],
        reverse_um: [0.0; MAX_BIDIR_ROWS],
    };

    /// Table 2's Model 1 band edges over `+-travel_mm`, two rows.
    pub const fn from_model1(m: &super::Model1Params, travel_mm: f64) -> BidirParams {
        let mut forward_um = [0.0; MAX_BIDIR_ROWS];
        let mut reverse_um = [0.0; MAX_BIDIR_ROWS];
        let x = [-travel_mm, travel_mm];
        let mut i = 0;
        while i < 2 {
            let upper = m.m_mm_per_mm * x[i] + m.offset_mm;
            reverse_um[i] = upper * 1000.0;
            forward_um[i] = (upper - m.h_mm) * 1000.0;
            i += 1;
        }
        BidirParams {
            x0_mm: -travel_mm,
            step_mm: 2.0 * travel_mm,
            rows: 2,
            forward_um,
            reverse_um,
        }
    }
}

impl BidirSource for BidirParams {
    fn shape(&self) -> (usize, f64, f64) {
        (self.rows, self.x0_mm, self.step_mm)
    }
    fn value_um(&self, dir: usize, i: usize) -> f64 {
        let t = if dir == 0 {
            &self.forward_um
        } else {
            &self.reverse_um
        };
        t.get(i).copied().unwrap_or(f64::NAN)
    }
}

/// A bidirectional table in fixed point.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BidirCoeffs {
    pub(crate) x0_counts: i32,
    pub(crate) step_counts: u32,
    /// `(rows - 1) * step_counts`: positions beyond are held at the last row.
    pub(crate) span_counts: u32,
    pub(crate) step_recip: Recip,
    /// Rows in use, `2..=MAX_BIDIR_ROWS`.
    pub(crate) rows: u16,
    /// Per direction (forward, reverse), um in I13F3 (+-4096 um to 1/8 um): half the RAM of
    /// I16F16, which the drive's coefficients and the link's calibration buffer both hold
    /// (2 KiB of static RAM together), for at most 1/16 um of rounding.
    pub(crate) values: [[I13F3; MAX_BIDIR_ROWS]; 2],
}

impl BidirCoeffs {
    /// Checks a table for a rig of `counts_per_mm`; the error names the field.
    pub fn build(src: &impl BidirSource, counts_per_mm: f64) -> Result<BidirCoeffs, ConfigError> {
        let (rows, x0_mm, step_mm) = src.shape();
        if !(2..=MAX_BIDIR_ROWS).contains(&rows) {
            return Err(ConfigError::OutOfRange(ConfigField::BidirTableRows));
        }
        let x0 = finite(x0_mm, ConfigField::BidirTableX0Mm)? * counts_per_mm;
        let step = finite(step_mm, ConfigField::BidirTableStepMm)? * counts_per_mm;
        if !(x0 >= i32::MIN as f64 && x0 <= i32::MAX as f64) {
            return Err(ConfigError::OutOfRange(ConfigField::BidirTableX0Mm));
        }
        let span = step * (rows - 1) as f64;
        if !(step >= 1.0 && span <= u32::MAX as f64 && x0 + span <= i32::MAX as f64) {
            return Err(ConfigError::OutOfRange(ConfigField::BidirTableStepMm));
        }
        let step_counts = round_u64(step)
            .filter(|&s| s <= u32::MAX as u64)
            .ok_or(ConfigError::OutOfRange(ConfigField::BidirTableStepMm))?
            as u32;
        let x0_counts =
            round_i32(x0).ok_or(ConfigError::OutOfRange(ConfigField::BidirTableX0Mm))?;
        let mut values = [[I13F3::ZERO; MAX_BIDIR_ROWS]; 2];
        for (dir, name) in [
            ConfigField::BidirTableForwardUm,
            ConfigField::BidirTableReverseUm,
        ]
        .into_iter()
        .enumerate()
        {
            for (i, v) in values[dir].iter_mut().enumerate().take(rows) {
                *v = bidir_um(src.value_um(dir, i), name)?;
            }
        }
        Ok(BidirCoeffs {
            x0_counts,
            step_counts,
            span_counts: step_counts.saturating_mul(rows as u32 - 1),
            step_recip: Recip::new(step_counts),
            rows: rows as u16,
            values,
        })
    }

    /// Rows in use.
    pub fn rows(&self) -> usize {
        self.rows as usize
    }

    /// Motor position of row 0 and the spacing, counts.
    pub fn grid_counts(&self) -> (i32, u32) {
        (self.x0_counts, self.step_counts)
    }

    /// Row `i` of `dir`, um.
    pub fn value_um(&self, dir: Direction, i: usize) -> Option<I16F16> {
        let d = match dir {
            Direction::Forward => 0,
            Direction::Reverse => 1,
        };
        self.values[d]
            .get(i)
            .filter(|_| i < self.rows())
            .map(|v| I16F16::from(*v))
    }

    /// The table of `dir` at `x_counts`, interpolated, held flat outside. Integer-only: one
    /// `UDIV` for the row, one multiply for the fraction.
    #[inline]
    pub fn at(&self, dir: Direction, x_counts: i32) -> I16F16 {
        let t = match dir {
            Direction::Forward => &self.values[0],
            Direction::Reverse => &self.values[1],
        };
        let d = (x_counts as i64 - self.x0_counts as i64).clamp(0, self.span_counts as i64) as u32;
        // `step_counts >= 1` by construction; `checked_div` keeps the panic path out anyway.
        let last = (self.rows as u32).saturating_sub(2);
        let i = d.checked_div(self.step_counts).unwrap_or(0).min(last);
        let w = d - i * self.step_counts;
        let frac = if w >= self.step_counts {
            u32::MAX
        } else {
            self.step_recip.frac(w)
        };
        let i = i as usize % MAX_BIDIR_ROWS;
        // I13F3 to I16F16 bits: exact.
        let a = (t[i].to_bits() as i32) << 13;
        let b = (t[(i + 1) % MAX_BIDIR_ROWS].to_bits() as i32) << 13;
        I16F16::from_bits(lerp_q32(a, b, frac))
    }
}

/// A bidirectional table's value, um, as I13F3 (rounded to 1/8 um): within +-4095 um, which
/// holds the paper's Table 2 bands over +-2.5 m of travel; the error names the field.
pub(crate) fn bidir_um(v_um: f64, field: ConfigField) -> Result<I13F3, ConfigError> {
    let v = finite(v_um, field)?;
    if v.abs() > BIDIR_MAX_ABS_UM {
        return Err(ConfigError::OutOfRange(field));
    }
    I13F3::checked_from_num(v).ok_or(ConfigError::OutOfRange(field))
}

/// The largest bidirectional table value, um (I13F3's range, with rounding room).
pub const BIDIR_MAX_ABS_UM: f64 = 4095.0;

/// Backlash for the current direction.
#[inline]
pub(crate) fn eval_backlash(c: &BacklashCoeffs, state: &ModelState) -> I16F16 {
    c.at(state.dir)
}

/// Bidirectional table for the current direction at `x_counts`.
#[inline]
pub(crate) fn eval_bidir(c: &BidirCoeffs, state: &ModelState, x_counts: i32) -> I16F16 {
    c.at(state.dir, x_counts)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table(rows: usize) -> BidirParams {
        let mut p = BidirParams::ZERO;
        p.rows = rows;
        p.x0_mm = -10.0;
        p.step_mm = 1.0;
        for i in 0..rows {
            p.forward_um[i] = -100.0 - i as f64;
            p.reverse_um[i] = 50.0 + 2.0 * i as f64;
        }
        p
    }

    #[test]
    fn interpolates_and_holds_outside() {
        let cpm = 1000.0;
        let c = BidirCoeffs::build(&table(5), cpm).unwrap();
        let at = |d, x_mm: f64| c.at(d, (x_mm * cpm) as i32).to_num::<f64>();
        assert!((at(Direction::Forward, -10.0) + 100.0).abs() < 1e-3);
        assert!((at(Direction::Forward, -9.5) + 100.5).abs() < 1e-3);
        assert!((at(Direction::Reverse, -7.25) - 55.5).abs() < 1e-3);
        assert!((at(Direction::Reverse, -6.0) - 58.0).abs() < 1e-3);
        assert!((at(Direction::Reverse, 500.0) - 58.0).abs() < 1e-3);
        assert!((at(Direction::Forward, -500.0) + 100.0).abs() < 1e-3);
        // Total over the whole input range.
        for x in [i32::MIN, -1, 0, 1, i32::MAX] {
            let _ = c.at(Direction::Forward, x);
        }
    }

    #[test]
    fn refuses_bad_tables_by_field() {
        let cpm = 1000.0;
        let mut p = table(1);
        assert_eq!(
            BidirCoeffs::build(&p, cpm),
            Err(ConfigError::OutOfRange(ConfigField::BidirTableRows))
        );
        p = table(4);
        p.step_mm = 0.0;
        assert_eq!(
            BidirCoeffs::build(&p, cpm),
            Err(ConfigError::OutOfRange(ConfigField::BidirTableStepMm))
        );
        p = table(4);
        p.reverse_um[3] = f64::NAN;
        assert_eq!(
            BidirCoeffs::build(&p, cpm),
            Err(ConfigError::NotFinite(ConfigField::BidirTableReverseUm))
        );
        p = table(4);
        p.x0_mm = 1e12;
        assert_eq!(
            BidirCoeffs::build(&p, cpm),
            Err(ConfigError::OutOfRange(ConfigField::BidirTableX0Mm))
        );
        // The values' format (I13F3) ends at +-4095 um; within it, they round to 1/8 um.
        p = table(4);
        p.forward_um[2] = 4095.5;
        assert_eq!(
            BidirCoeffs::build(&p, cpm),
            Err(ConfigError::OutOfRange(ConfigField::BidirTableForwardUm))
        );
        p.forward_um[2] = -4095.0;
        p.reverse_um[1] = 12.3;
        let c = BidirCoeffs::build(&p, cpm).unwrap();
        assert_eq!(
            c.value_um(Direction::Forward, 2),
            Some(I16F16::from_num(-4095))
        );
        assert_eq!(
            c.value_um(Direction::Reverse, 1),
            Some(I16F16::from_num(12.25))
        );
        let b = BacklashParams {
            offset_um: 0.0,
            backlash_um: f64::INFINITY,
        };
        assert_eq!(
            b.build(),
            Err(ConfigError::NotFinite(ConfigField::BacklashBacklashUm))
        );
    }

    #[test]
    fn backlash_is_offset_minus_and_plus_half() {
        let c = BacklashParams::PAPER.build().unwrap();
        assert_eq!(c.at(Direction::Forward).to_num::<f64>(), -340.0);
        assert_eq!(c.at(Direction::Reverse).to_num::<f64>(), 0.0);
    }
}
