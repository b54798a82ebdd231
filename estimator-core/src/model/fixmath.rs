//! Integer primitives of the per-tick path: scaling by a build-time constant, a 64/32 fraction,
//! interpolation and `2^-t`. Every function is total: it returns a defined value for every input
//! (no panics, no unchecked overflow), and the bounds it relies on are stated next to the code and
//! checked by the tests at the end of this file.
//!
//! Cortex-M4 cost model used here: `UMULL`/`SMULL` (32x32->64) are single-cycle, `UDIV` is 2..12
//! cycles, 64-bit shifts by a variable amount are a handful of instructions. No 64x64 multiply and
//! no 64-bit division appear below.

use crate::ConfigError;
use crate::ConfigField;

/// Multiplication by a positive constant known at build time: `v * mant / 2^shift`.
///
/// The mantissa is normalised into `[2^31, 2^32)` whenever the shift allows, so every factor
/// carries 32 significant bits (relative error <= 2^-32) whatever its magnitude. Factors below
/// 2^-32 lose precision gracefully (they only ever scale distances whose product is negligible).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Scale {
    pub(crate) mant: u32,
    /// `0..=63`, enforced by [`Scale::from_f64`].
    pub(crate) shift: u8,
}

/// Largest shift a [`Scale`] uses; a smaller factor is rounded towards zero.
pub(crate) const MAX_SHIFT: i32 = 63;

impl Scale {
    /// The zero factor.
    pub const ZERO: Scale = Scale { mant: 0, shift: 0 };

    /// The scale closest to `factor` (>= 0, < 2^32). `field` names the configuration value that
    /// produced it for the error.
    pub fn from_f64(factor: f64, field: ConfigField) -> Result<Scale, ConfigError> {
        if !factor.is_finite() {
            return Err(ConfigError::NotFinite(field));
        }
        if factor < 0.0 {
            return Err(ConfigError::OutOfRange(field));
        }
        // Exponent of the leading bit; subnormals and zero give zero.
        let biased = ((factor.to_bits() >> 52) & 0x7ff) as i32;
        if biased == 0 {
            return Ok(Scale::ZERO);
        }
        let exponent = biased - 1023;
        let mut shift = 31 - exponent;
        if shift < 0 {
            return Err(ConfigError::OutOfRange(field));
        }
        if shift > MAX_SHIFT {
            shift = MAX_SHIFT;
        }
        let mut mant = round_u64(factor * pow2(shift)).ok_or(ConfigError::OutOfRange(field))?;
        if mant >= 1 << 32 {
            // Rounding carried into bit 32: one bit less of shift.
            shift -= 1;
            if shift < 0 {
                return Err(ConfigError::OutOfRange(field));
            }
            mant = round_u64(factor * pow2(shift)).ok_or(ConfigError::OutOfRange(field))?;
            if mant >= 1 << 32 {
                return Err(ConfigError::OutOfRange(field));
            }
        }
        Ok(Scale {
            mant: mant as u32,
            shift: shift as u8,
        })
    }

    /// The exact factor this scale multiplies by (host side and diagnostics; not per tick).
    pub fn factor(&self) -> f64 {
        self.mant as f64 / pow2(self.shift as i32)
    }

    /// `floor(v * factor)`. `v * mant < 2^64` always, and the shift is at most 63.
    #[inline]
    pub fn apply(&self, v: u32) -> u64 {
        ((v as u64) * (self.mant as u64)).wrapping_shr(self.shift as u32)
    }
}

/// `2^e` for `|e| <= 1000`, exactly, without `std`.
pub(crate) fn pow2(e: i32) -> f64 {
    let e = e.clamp(-1022, 1023);
    f64::from_bits(((e + 1023) as u64) << 52)
}

/// Round to the nearest integer (ties to even) if the result fits a `u64`.
pub(crate) fn round_u64(v: f64) -> Option<u64> {
    fixed::types::U64F0::checked_from_num(v).map(|f| f.to_bits())
}

/// Round to the nearest integer (ties to even) if the result fits an `i32`.
pub(crate) fn round_i32(v: f64) -> Option<i32> {
    fixed::types::I32F0::checked_from_num(v).map(|f| f.to_bits())
}

/// `floor(num * 2^32 / den)`: the fraction `num / den` in Q0.32, for `num < den`.
///
/// Returns `u32::MAX` when `num >= den` (including `den == 0`) so callers never divide by zero.
/// This is a two-digit long division in base 2^16 (Knuth's algorithm D specialised to a two-digit
/// divisor), built from the Cortex-M4's 32/32 `UDIV`: two divisions and at most two corrections
/// per digit instead of a software 64/64 division. With a two-digit divisor the correction test
/// compares the full partial remainder, so no add-back step is needed.
#[inline]
pub fn frac_q32(num: u32, den: u32) -> u32 {
    if num >= den {
        return u32::MAX;
    }
    // Normalise so that the divisor's top bit is set; `num < den` so no bit of `num` is lost.
    let s = den.leading_zeros();
    let d = den << s;
    let n = num << s;
    // In [2^15, 2^16): the top bit of `d` is set. Or-ing it in again changes nothing but lets the
    // compiler see that the divisions below cannot divide by zero (no panic path on target).
    let dh = (d >> 16) | 0x8000;
    let dl = d & 0xffff;

    // Quotient digit of (n * 2^16) / d, where the next dividend digit is zero.
    #[inline(always)]
    fn digit(n: u32, dh: u32, dl: u32) -> u32 {
        let mut q = n / dh;
        let mut r = n - q * dh; // n % dh, no overflow
        let mut k = 0;
        // The estimate from the high divisor digit exceeds the true digit by at most 2.
        while k < 2 {
            // `q <= 0xffff` is checked first, so `q * dl < 2^32`; `r < 2^16` so `r << 16` fits.
            if q > 0xffff || q * dl > (r << 16) {
                q -= 1; // q >= 1 here: either q > 0xffff or q * dl > 0
                r += dh; // r < 2^17
                if r > 0xffff {
                    break;
                }
            } else {
                break;
            }
            k += 1;
        }
        q
    }

    let q1 = digit(n, dh, dl);
    // Partial remainder n * 2^16 - q1 * d lies in [0, d): compute it modulo 2^32.
    let rem = (n << 16).wrapping_sub(q1.wrapping_mul(d));
    let q0 = digit(rem, dh, dl);
    (q1 << 16) | (q0 & 0xffff)
}

/// Linear interpolation `a + (b - a) * t` with `t` in Q0.32 (`[0, 1)`), rounded to nearest.
///
/// Contract: `|a|, |b| < 2^30` (every table value the models interpolate is within +-16000 um, i.e.
/// below 2^30 in Q16.16). Then `b - a` fits an `i32`, the product of one `SMULL` fits an `i64`,
/// the result is within one unit of the exact value and lies between `a` and `b`. Outside the
/// contract the arithmetic wraps (a wrong value, never a panic).
#[inline]
pub fn lerp_q32(a: i32, b: i32, t: u32) -> i32 {
    lerp_diff_q32(a, b.wrapping_sub(a), t)
}

/// [`lerp_q32`] from `a` and `diff = b - a` (wrapping): for a caller that keeps the difference.
#[inline(always)]
pub fn lerp_diff_q32(a: i32, diff: i32, t: u32) -> i32 {
    let step = (diff as i64 * (t >> 1) as i64 + (1 << 30)) >> 31;
    a.wrapping_add(step as i32)
}

/// `1 / len` prepared for repeated fractions `dx / len` without a division:
/// `frac(dx) = ((dx << z) * r) >> 31` with `z` the leading zeros of `len` and
/// `r = floor(2^63 / (len << z))` (32 significant bits); one `UMULL` and constant shifts per use.
/// At most 3 units of Q0.32 below the exact fraction.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Recip {
    r: u32,
    z: u8,
}

impl Recip {
    /// The reciprocal of nothing (`frac` is 0).
    pub const ZERO: Recip = Recip { r: 0, z: 0 };

    /// The reciprocal of `len` (`len >= 1`; 0 gives [`Recip::ZERO`]). Two `UDIV`s.
    #[inline]
    pub fn new(len: u32) -> Recip {
        if len == 0 {
            return Recip::ZERO;
        }
        let z = len.leading_zeros(); // 0..=31
        let l = len << z; // in [2^31, 2^32)
                          // floor(2^31 * 2^32 / l); l == 2^31 would be 2^32: saturates to 2^32 - 1.
        Recip {
            r: frac_q32(1 << 31, l),
            z: z as u8,
        }
    }

    /// `dx / len` in Q0.32 for `dx < len` (then `(dx << z) < 2^32` and the product is below
    /// 2^63); saturates at `u32::MAX` for other `dx`.
    #[inline]
    pub fn frac(&self, dx: u32) -> u32 {
        let x = dx.wrapping_shl(self.z as u32);
        let q = ((x as u64) * (self.r as u64)) >> 31;
        if dx.leading_zeros() < self.z as u32 || q > u32::MAX as u64 {
            u32::MAX
        } else {
            q as u32
        }
    }
}

/// Saturating `i64 -> i32`.
#[inline]
pub fn sat_i32(v: i64) -> i32 {
    // In range exactly when the high word is the low word's sign: one compare on the M4.
    let low = v as i32;
    if low as i64 == v {
        low
    } else if v < 0 {
        i32::MIN
    } else {
        i32::MAX
    }
}

/// `x * slope` with `slope` in Q1.31 micrometres per count, returned in Q16.16 micrometres
/// (rounded to nearest, saturated). `|x * slope| <= 2^62`, so the rounding add cannot overflow.
#[inline]
pub fn mul_q31_to_q16(x: i32, slope_q31: i32) -> i32 {
    let p = x as i64 * slope_q31 as i64;
    sat_i32((p + (1 << 14)) >> 15)
}

/// `2^(-i/64)` in Q1.31 for `i = 0..64`, correctly rounded (checked against `f64` in the tests).
const EXP2_NEG_Q31: [u32; 64] = [
    2147483648, 2124350982, 2101467502, 2078830522, 2056437387, 2034285470, 2012372174, 1990694927,
    1969251188, 1948038440, 1927054196, 1906295993, 1885761398, 1865448001, 1845353420, 1825475297,
    1805811301, 1786359126, 1767116489, 1748081133, 1729250827, 1710623359, 1692196547, 1673968228,
    1655936265, 1638098541, 1620452965, 1602997467, 1585730000, 1568648537, 1551751076, 1535035634,
    1518500250, 1502142985, 1485961921, 1469955159, 1454120821, 1438457051, 1422962010, 1407633882,
    1392470869, 1377471191, 1362633090, 1347954824, 1333434672, 1319070932, 1304861917, 1290805962,
    1276901417, 1263146652, 1249540052, 1236080024, 1222764986, 1209593378, 1196563654, 1183674286,
    1170923762, 1158310587, 1145833280, 1133490379, 1121280436, 1109202018, 1097253708, 1085434106,
];

/// Taylor coefficients of `2^-r = 1 - c1 r + c2 r^2 - c3 r^3` in Q0.32:
/// `c1 = ln 2`, `c2 = ln^2 2 / 2`, `c3 = ln^3 2 / 6`.
const C1_Q32: u64 = 2_977_044_472;
const C2_Q32: u64 = 1_031_764_991;
const C3_Q32: u64 = 238_388_332;

/// One in Q2.30, the format of [`exp2_neg_q30`]'s result.
pub const ONE_Q30: u32 = 1 << 30;

/// `2^-t` in Q2.30 for `t >= 0` given in Q32.32 (`t_q32 = t * 2^32`).
///
/// `t = n + i/64 + r` with `r < 1/64`: `2^-t = 2^-n * T[i] * 2^-r`, where `T` is a 64-entry table
/// and `2^-r` a cubic Taylor polynomial (truncation error `(r ln 2)^4 / 24 < 5.8e-10`). Total error
/// below 2e-9 absolute (about 2 units of Q2.30; measured in the tests), monotone
/// non-increasing in `t`, and exactly `2^30` at `t = 0`. For `n >= 31` the result is 0 (true value
/// below half a unit).
#[inline]
pub fn exp2_neg_q30(t_q32: u64) -> u32 {
    let n = t_q32 >> 32;
    if n >= 31 {
        return 0;
    }
    let frac = t_q32 as u32;
    let i = (frac >> 26) as usize; // 0..64
    let r = (frac & 0x03ff_ffff) as u64; // Q0.32, < 2^26
                                         // Horner; every product is < 2^26 * 2^32 and every difference stays positive.
    let w3 = (r * C3_Q32) >> 32;
    let w2 = C2_Q32 - w3;
    let w1 = C1_Q32 - ((r * w2) >> 32);
    let q = (r * w1) >> 32; // r ln2 (1 - ...) < 0.0109 * 2^32
    let p_q31 = ((1u64 << 32) - q + 1) >> 1; // 2^-r in Q1.31, <= 2^31
    let table = match EXP2_NEG_Q31.get(i) {
        Some(v) => *v as u64,
        None => 0, // unreachable: i < 64
    };
    let prod = table * p_q31; // Q2.62, <= 2^62
                              // Rounded `prod >> (32 + n)` in 32-bit arithmetic: with `h = prod >> 31` (<= 2^31) the
                              // dropped low 31 bits never carry into the result, so it is `(h + 2^n) >> (n + 1)`, below
                              // 2^32 for n <= 30 (a 64-bit variable shift costs the M4 about ten instructions more).
    let h = (prod >> 31) as u32;
    let n = n as u32;
    (h + (1 << n)) >> (n + 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn exp_table_is_correctly_rounded() {
        for (i, &v) in EXP2_NEG_Q31.iter().enumerate() {
            let exact = (-(i as f64) / 64.0).exp2() * 2f64.powi(31);
            assert!(
                (v as f64 - exact).abs() <= 0.5 + 1e-6,
                "i={i}: {v} vs {exact}"
            );
        }
    }

    #[test]
    fn sat_i32_saturates_exactly_like_clamp() {
        let (min, max) = (i32::MIN as i64, i32::MAX as i64);
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut vs = vec![
            0,
            1,
            -1,
            min,
            max,
            min - 1,
            max + 1,
            i64::MIN,
            i64::MAX,
            1 << 32,
        ];
        for _ in 0..100_000 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            // Every magnitude, from a few bits to all 64.
            vs.push((seed as i64) >> (seed % 64));
        }
        for v in vs {
            assert_eq!(sat_i32(v), v.clamp(min, max) as i32, "{v}");
        }
    }

    /// The final rounding shift in 32-bit arithmetic equals the 64-bit one it replaced, for every
    /// product the function can form (`<= 2^62`) and every `n` it shifts by: the low 31 bits,
    /// each bit above, and random products.
    #[test]
    fn rounding_shift_in_32_bits_is_exact() {
        let wide = |prod: u64, n: u32| ((prod + (1u64 << (31 + n))) >> (32 + n)) as u32;
        let narrow = |prod: u64, n: u32| ((prod >> 31) as u32 + (1 << n)) >> (n + 1);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        for n in 0..=30 {
            let check = |prod: u64| assert_eq!(narrow(prod, n), wide(prod, n), "{prod} {n}");
            for b in 0..=62 {
                let p = 1u64 << b;
                check(p);
                check(p - 1);
                check(p | ((1 << 31) - 1));
            }
            for _ in 0..20_000 {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                check(seed >> 2);
            }
        }
    }

    fn exp_err(t_q32: u64) -> f64 {
        let got = exp2_neg_q30(t_q32) as f64 / 2f64.powi(30);
        let t = t_q32 as f64 / 2f64.powi(32);
        (got - (-t).exp2()).abs()
    }

    #[test]
    fn exp2_edges_and_error_bound() {
        assert_eq!(exp2_neg_q30(0), ONE_Q30);
        assert_eq!(exp2_neg_q30(u64::MAX), 0);
        assert_eq!(exp2_neg_q30(31 << 32), 0);
        assert_eq!(exp2_neg_q30(1 << 32), ONE_Q30 / 2);
        let mut worst = 0f64;
        let mut prev = u32::MAX;
        // Dense sweep over [0, 4) plus every table knot and its neighbours.
        let mut t = 0u64;
        while t < 4 << 32 {
            let e = exp2_neg_q30(t);
            assert!(e <= prev, "not monotone at {t}");
            prev = e;
            worst = worst.max(exp_err(t));
            t += 1 << 20;
        }
        for k in 0..(64 * 32u64) {
            for dt in [0u64, 1, (1 << 26) - 1] {
                worst = worst.max(exp_err((k << 26) + dt));
            }
        }
        assert!(worst < 2e-9, "exp2 error {worst:e}");
    }

    #[test]
    fn frac_edge_cases() {
        assert_eq!(frac_q32(0, 1), 0);
        assert_eq!(frac_q32(1, 2), 1 << 31);
        assert_eq!(frac_q32(1, 0), u32::MAX);
        assert_eq!(frac_q32(0, 0), u32::MAX);
        assert_eq!(frac_q32(5, 5), u32::MAX);
        assert_eq!(frac_q32(u32::MAX - 1, u32::MAX), u32::MAX - 1);
        assert_eq!(frac_q32(0x7fff, 0x8000), 0xfffe_0000);
        assert_eq!(frac_q32(0x8000_0000, 0x8000_0001), 0xffff_fffe);
        for (n, d) in [
            (1u32, 3u32),
            (2, 3),
            (0xffff, 0x1_0000),
            (0x1_0000, 0x1_0001),
            (12345, 0xffff_ffff),
            (0x7fff_ffff, 0x8000_0000),
            (1, 0x8000_0000),
            (0xffff_0000, 0xffff_0001),
        ] {
            assert_eq!(
                frac_q32(n, d) as u64,
                ((n as u64) << 32) / d as u64,
                "{n}/{d}"
            );
        }
    }

    proptest! {
        #[test]
        fn frac_matches_u64_division(d in 1u32.., n in any::<u32>()) {
            let n = n % d;
            prop_assert_eq!(frac_q32(n, d) as u64, ((n as u64) << 32) / d as u64);
        }

        #[test]
        fn frac_small_divisors(d in 1u32..70000, n in any::<u32>()) {
            let n = n % d;
            prop_assert_eq!(frac_q32(n, d) as u64, ((n as u64) << 32) / d as u64);
        }

        #[test]
        fn lerp_bounds(a in -(1i32 << 30) + 1..1 << 30, b in -(1i32 << 30) + 1..1 << 30, t in any::<u32>()) {
            let v = lerp_q32(a, b, t);
            prop_assert!(v >= a.min(b) && v <= a.max(b));
            let exact = a as f64 + (b as f64 - a as f64) * t as f64 / 2f64.powi(32);
            prop_assert!((v as f64 - exact).abs() <= 1.0);
        }

        #[test]
        fn lerp_never_panics(a in any::<i32>(), b in any::<i32>(), t in any::<u32>()) {
            let _ = lerp_q32(a, b, t);
        }

        #[test]
        fn recip_fraction(len in 1u32.., dx in any::<u32>()) {
            let dx = dx % len;
            let exact = ((dx as u64) << 32) as f64 / len as f64;
            let got = Recip::new(len).frac(dx) as f64;
            prop_assert!(got <= exact + 1e-6 && got >= exact - 3.0, "{} vs {}", got, exact);
        }

        #[test]
        fn recip_small_lengths(len in 1u32..5000, dx in any::<u32>()) {
            let dx = dx % len;
            let exact = ((dx as u64) << 32) as f64 / len as f64;
            let got = Recip::new(len).frac(dx) as f64;
            prop_assert!(got <= exact + 1e-6 && got >= exact - 3.0);
        }

        #[test]
        fn exp2_random(t in 0u64..(40u64 << 32)) {
            prop_assert!(exp_err(t) < 2e-9);
        }

        #[test]
        fn scale_precision(f in 1e-9f64..4.0e9) {
            let s = Scale::from_f64(f, ConfigField::Model1HMm).unwrap();
            prop_assert!(((s.factor() - f) / f).abs() <= 2f64.powi(-32));
            prop_assert!(s.apply(u32::MAX) as f64 <= u32::MAX as f64 * f * (1.0 + 1e-9));
        }
    }

    #[test]
    fn recip_edges() {
        assert_eq!(Recip::new(0).frac(5), 0);
        assert_eq!(Recip::new(1).frac(0), 0);
        assert!((1u32 << 31) - Recip::new(2).frac(1) <= 3);
        assert!((u32::MAX - 1) - Recip::new(u32::MAX).frac(u32::MAX - 1) <= 3);
        assert!((1u32 << 31) - Recip::new(1 << 31).frac(1 << 30) <= 1);
        assert_eq!(Recip::new(3).frac(7), u32::MAX);
    }

    #[test]
    fn scale_limits() {
        assert_eq!(
            Scale::from_f64(0.0, ConfigField::Model1HMm),
            Ok(Scale::ZERO)
        );
        assert_eq!(
            Scale::from_f64(-1.0, ConfigField::Model1HMm),
            Err(ConfigError::OutOfRange(ConfigField::Model1HMm))
        );
        assert_eq!(
            Scale::from_f64(f64::NAN, ConfigField::Model1HMm),
            Err(ConfigError::NotFinite(ConfigField::Model1HMm))
        );
        assert_eq!(
            Scale::from_f64(5e9, ConfigField::Model1HMm),
            Err(ConfigError::OutOfRange(ConfigField::Model1HMm))
        );
        // Just below 2^32 rounds up to 2^32: does not fit.
        assert!(Scale::from_f64(4294967295.9, ConfigField::Model1HMm).is_err());
        let s = Scale::from_f64(1e-30, ConfigField::Model1HMm).unwrap();
        assert_eq!(s.apply(u32::MAX), 0);
        let one = Scale::from_f64(1.0, ConfigField::Model1HMm).unwrap();
        assert_eq!(one.apply(u32::MAX), u32::MAX as u64);
        let half = Scale::from_f64(0.5, ConfigField::Model1HMm).unwrap();
        assert_eq!(half.apply(7), 3);
    }
}
