//! Build-time conversions from SI parameters (`f64`) to the fixed-point coefficient formats.
//! Every function names the configuration field it is checking in its error. Never called per
//! tick.

use crate::ConfigField;
use fixed::types::{I16F16, I1F31};

use super::fixmath::pow2;
use crate::ConfigError;

/// Largest magnitude, in micrometres, of any band value, height or amplitude the models accept.
///
/// Keeping values within +-2^14 um (+-16.4 mm) guarantees that differences of two values fit an
/// `i32` in Q16.16, which every interpolation relies on, and leaves headroom for sums.
pub const MAX_ABS_UM: f64 = 16_000.0;

/// A finite number or [`ConfigError::NotFinite`].
pub(crate) fn finite(v: f64, field: ConfigField) -> Result<f64, ConfigError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(ConfigError::NotFinite(field))
    }
}

/// `v_um` in Q16.16 micrometres, checked against `[min_um, MAX_ABS_UM]`.
pub(crate) fn um_q16(v_um: f64, min_um: f64, field: ConfigField) -> Result<I16F16, ConfigError> {
    let v = finite(v_um, field)?;
    if v < min_um || v.abs() > MAX_ABS_UM {
        return Err(ConfigError::OutOfRange(field));
    }
    I16F16::checked_from_num(v).ok_or(ConfigError::OutOfRange(field))
}

/// A slope in mm of error per mm of travel as Q1.31 micrometres per encoder count.
///
/// Range +-1 um/count (for the paper's rig: |slope| < 1.87 mm/mm); quantisation step 2^-31
/// um/count, i.e. at most 0.002 um of error over 2^24 counts.
pub(crate) fn slope_q31(
    v_mm_per_mm: f64,
    counts_per_mm: f64,
    field: ConfigField,
) -> Result<I1F31, ConfigError> {
    let v = finite(v_mm_per_mm, field)?;
    let um_per_count = v * 1000.0 / counts_per_mm;
    I1F31::checked_from_num(um_per_count).ok_or(ConfigError::OutOfRange(field))
}

/// `e^x` for `x <= 0` without `std` (build-time diagnostics only): `x = k ln 2 + r`, `|r| <= ln 2`,
/// 2^k by exponent bits, `e^r` by a 24-term Taylor series (relative error below 1e-12).
pub(crate) fn exp_nonpos(x: f64) -> f64 {
    if x.is_nan() {
        return f64::NAN;
    }
    if x > 0.0 {
        return f64::INFINITY;
    }
    if x < -700.0 {
        return 0.0;
    }
    let kf = x / core::f64::consts::LN_2; // in [-1010, 0]
    let k = kf as i32; // truncates towards zero: k in [kf, kf + 1)
    let r = x - k as f64 * core::f64::consts::LN_2; // in (-ln 2, 0]
    let mut term = 1.0;
    let mut sum = 1.0;
    let mut n = 1;
    while n < 24 {
        term *= r / n as f64;
        sum += term;
        n += 1;
    }
    sum * pow2(k)
}

/// `sqrt(v)` for finite `v >= 0` without `std` (build time only): a start within a factor of
/// 2 from the exponent, then Newton's steps (quadratic: 6 reach the last bit).
pub(crate) fn sqrt_nonneg(v: f64) -> f64 {
    if v == 0.0 {
        return 0.0;
    }
    if v.is_nan() || v < 0.0 || v.is_infinite() {
        return f64::NAN;
    }
    // Half the biased exponent: within a factor of 2 of the root.
    let mut y = f64::from_bits((v.to_bits() >> 1) + (1023u64 << 51));
    for _ in 0..8 {
        y = 0.5 * (y + v / y);
    }
    y
}

/// `a sin(t) + b cos(t)` as `r sin(t + phase)`: `(r, phase)` with `phase` in turns, in
/// `[0, 1)`; `(0, 0)` for `a = b = 0`. Build time only, without `std`.
pub(crate) fn polar(a: f64, b: f64) -> (f64, f64) {
    let r = sqrt_nonneg(a * a + b * b);
    if r == 0.0 {
        return (0.0, 0.0);
    }
    // atan2(b, a): reduced to t = min/max in [0, 1], halved twice by
    // atan t = 2 atan(t / (1 + sqrt(1 + t^2))), then its series (|t| < 0.2: 24 terms).
    let (ax, bx) = (a.abs(), b.abs());
    let t = if ax >= bx { bx / ax } else { ax / bx };
    let mut u = t;
    for _ in 0..2 {
        u /= 1.0 + sqrt_nonneg(1.0 + u * u);
    }
    let (mut term, mut sum, u2) = (u, 0.0, u * u);
    for k in 0..24 {
        sum += term / (2 * k + 1) as f64;
        term *= -u2;
    }
    let quarter = core::f64::consts::FRAC_PI_2;
    let first = 4.0 * sum;
    let mut angle = if ax >= bx { first } else { quarter - first };
    if a < 0.0 {
        angle = 2.0 * quarter - angle;
    }
    if b < 0.0 {
        angle = -angle;
    }
    let turns = angle / core::f64::consts::TAU;
    (r, if turns < 0.0 { turns + 1.0 } else { turns })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polar_matches_std() {
        assert_eq!(polar(0.0, 0.0), (0.0, 0.0));
        for i in 0..2000 {
            let t = i as f64 * 0.0137 - 13.0;
            for r in [1e-6, 0.3, 11.0, 16_000.0] {
                let (a, b) = (r * t.cos(), r * t.sin());
                let (rr, ph) = polar(a, b);
                assert!((rr - r).abs() <= 1e-12 * r, "{a} {b}: {rr}");
                assert!((0.0..1.0).contains(&ph), "{ph}");
                let x = 0.7f64;
                let want = a * x.sin() + b * x.cos();
                let got = rr * (x + ph * core::f64::consts::TAU).sin();
                assert!((want - got).abs() <= 1e-11 * r, "{a} {b}: {want} vs {got}");
            }
        }
        for v in [0.0, 1e-300, 2.0, 1e300] {
            assert!((sqrt_nonneg(v) - v.sqrt()).abs() <= 1e-15 * v.sqrt());
        }
    }

    #[test]
    fn exp_nonpos_matches_std() {
        for i in 0..1890 {
            let x = -(i as f64) * 0.37;
            let e = exp_nonpos(x);
            let r = x.exp();
            assert!((e - r).abs() <= 1e-12 * r.max(1e-300), "{x}: {e} vs {r}");
        }
        assert_eq!(exp_nonpos(-1e9), 0.0);
        assert_eq!(exp_nonpos(0.0), 1.0);
    }

    #[test]
    fn conversions_name_fields() {
        assert_eq!(
            um_q16(f64::NAN, 0.0, ConfigField::Model1HMm),
            Err(ConfigError::NotFinite(ConfigField::Model1HMm))
        );
        assert_eq!(
            um_q16(-1.0, 0.0, ConfigField::Model1HMm),
            Err(ConfigError::OutOfRange(ConfigField::Model1HMm))
        );
        assert_eq!(
            um_q16(16_001.0, 0.0, ConfigField::Model1HMm),
            Err(ConfigError::OutOfRange(ConfigField::Model1HMm))
        );
        assert_eq!(
            um_q16(1.5, 0.0, ConfigField::Model1HMm).unwrap(),
            I16F16::from_num(1.5)
        );
        assert_eq!(
            slope_q31(2.0, 1867.89, ConfigField::Model1SlopeAMmPerMm),
            Err(ConfigError::OutOfRange(ConfigField::Model1SlopeAMmPerMm))
        );
        assert!(slope_q31(0.0010594, 1867.89, ConfigField::Model1SlopeAMmPerMm).is_ok());
    }
}
