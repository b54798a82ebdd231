//! Quadrature counter unwrapping: a free-running hardware counter (16- or 32-bit) into a position
//! in motor encoder counts.
//!
//! The position is an `i32` of counts, not an `i64`:
//! - it is the crate's unit for motor position (the PID and the error models take `i32` counts), so
//!   nothing downstream has to narrow it;
//! - ±2^31 counts is ±1150 m of belt at [`Rig::PAPER`] (1867.89 counts/mm): a thousand times the
//!   ±1 m a stage can travel, so a 16-bit counter may wrap 32768 times each way before it matters;
//! - on the Cortex-M4 it is one register, one add, and the error of the position loop stays a
//!   32x32->64 multiply.
//!
//! Leaving the `i32` range would take 70 minutes of free spinning in one direction at 250 mm/s;
//! it is reported as [`Error::Overflow`] instead of wrapping, because a silent 2^32-count jump in
//! the position would be far worse than a fault.
//!
//! The 32-bit variant (TIM2/TIM5 on the STM32F405) unwraps the same way; its position is the
//! counter itself, re-based and checked for plausibility.
//!
//! Follows idsp's unwrapper: the step is the counter difference taken modulo the counter's range
//! (`wrapping_sub`, then reinterpreted as signed), so wraps in either direction cost nothing.

use crate::ConfigField;
use core::marker::PhantomData;

use crate::{BuildContext, ConfigError};

mod sealed {
    pub trait Sealed {}
    impl Sealed for u16 {}
    impl Sealed for u32 {}
}

/// A raw hardware counter register: `u16` (e.g. TIM3/TIM4) or `u32` (TIM2/TIM5).
pub trait Counter: Copy + core::fmt::Debug + sealed::Sealed {
    /// The counter reset value, used before the first sample.
    const ZERO: Self;
    /// The largest step the counter can tell apart from a step the other way round:
    /// half its range minus one. A step of exactly half the range is ambiguous and always rejected.
    const MAX_DELTA_COUNTS: u32;
    /// Signed steps from `earlier` to `self`, modulo the counter's range (two's complement).
    fn delta_counts(self, earlier: Self) -> i32;
}

impl Counter for u16 {
    const ZERO: Self = 0;
    const MAX_DELTA_COUNTS: u32 = i16::MAX as u32;
    #[inline(always)]
    fn delta_counts(self, earlier: Self) -> i32 {
        // Bit pattern of the modular difference, read as signed: 0x0000 - 0xffff = +1.
        self.wrapping_sub(earlier) as i16 as i32
    }
}

impl Counter for u32 {
    const ZERO: Self = 0;
    const MAX_DELTA_COUNTS: u32 = i32::MAX as u32;
    #[inline(always)]
    fn delta_counts(self, earlier: Self) -> i32 {
        self.wrapping_sub(earlier) as i32
    }
}

/// Plausibility limit of the unwrapper, in SI units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Config {
    /// Fastest believable carriage speed. Any faster step between two samples is a fault
    /// (missed sample, counter glitch, encoder cable). Choose it well above the fastest move but
    /// well below half the counter range per tick.
    pub max_speed_mm_s: f64,
}

impl Config {
    /// For the paper's rig at 2 kHz: 1000 mm/s is about twice the carriage speed at the 150 W
    /// motor's no-load speed (≈540 mm/s through 23.7:1 and a 20-tooth XL pulley), i.e. 934 counts
    /// per tick, far below the 32767 a 16-bit counter can resolve.
    pub const PAPER_RIG: Config = Config {
        max_speed_mm_s: 1000.0,
    };

    /// Converts the limit into counts per sample of `ctx` (rounded up, so the configured speed
    /// itself is accepted) for counter type `C`.
    pub fn build<C: Counter>(&self, ctx: &BuildContext) -> Result<Coeffs<C>, ConfigError> {
        if !self.max_speed_mm_s.is_finite() {
            return Err(ConfigError::NotFinite(ConfigField::EncoderMaxSpeedMmS));
        }
        let per_tick = self.max_speed_mm_s * ctx.rig().counts_per_mm() / ctx.rate_hz();
        if !(per_tick > 0.0 && per_tick <= C::MAX_DELTA_COUNTS as f64) {
            return Err(ConfigError::OutOfRange(ConfigField::EncoderMaxSpeedMmS));
        }
        // Round up without `f64::ceil` (not in `core`): the cast truncates a positive value.
        let whole = per_tick as u32;
        let max_delta_counts = if (whole as f64) < per_tick {
            whole + 1
        } else {
            whole
        };
        Coeffs::from_max_delta_counts(max_delta_counts)
            .map_err(|_| ConfigError::OutOfRange(ConfigField::EncoderMaxSpeedMmS))
    }
}

impl Default for Config {
    fn default() -> Self {
        Self::PAPER_RIG
    }
}

/// The unwrapper's fixed coefficient: the largest accepted step per sample, for counter type `C`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Coeffs<C> {
    max_delta_counts: u32,
    counter: PhantomData<C>,
}

/// Why a sample was refused. The state is left exactly as it was before the sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Error {
    /// The counter moved more than the configured maximum since the last accepted sample
    /// (`delta_counts` is the step as seen modulo the counter range).
    Jump {
        /// The refused step, in counts.
        delta_counts: i32,
    },
    /// The position would leave the `i32` range.
    Overflow,
}

impl core::fmt::Display for Error {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Error::Jump { delta_counts } => {
                write!(f, "encoder: implausible step of {delta_counts} counts")
            }
            Error::Overflow => write!(f, "encoder: position out of the i32 range"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for Error {}

impl<C: Counter> Coeffs<C> {
    /// Coefficients from a step limit in counts per sample: 1 ..= [`Counter::MAX_DELTA_COUNTS`].
    pub const fn from_max_delta_counts(max_delta_counts: u32) -> Result<Self, ConfigError> {
        if max_delta_counts == 0 || max_delta_counts > C::MAX_DELTA_COUNTS {
            return Err(ConfigError::OutOfRange(ConfigField::EncoderMaxDeltaCounts));
        }
        Ok(Self {
            max_delta_counts,
            counter: PhantomData,
        })
    }

    /// The largest accepted step per sample, in counts (inclusive).
    pub const fn max_delta_counts(&self) -> u32 {
        self.max_delta_counts
    }

    /// Takes one raw counter sample and returns the unwrapped position in counts.
    ///
    /// The first sample after [`State::new`] or [`State::reset`] only records the counter and
    /// returns the position given there. After that, a step with `|delta| > max_delta_counts`
    /// is refused with [`Error::Jump`] and a position outside `i32` with [`Error::Overflow`]; in
    /// both cases `state` is untouched, so a single glitched read is simply skipped (the next good
    /// sample is measured against the last accepted one) while a real loss of count keeps failing
    /// until the caller re-homes with [`State::reset`].
    #[inline]
    pub fn update(&self, state: &mut State<C>, raw: C) -> Result<i32, Error> {
        if !state.primed {
            state.last_raw = raw;
            state.primed = true;
            return Ok(state.position_counts);
        }
        let delta_counts = raw.delta_counts(state.last_raw);
        if outside(delta_counts, self.max_delta_counts) {
            return Err(Error::Jump { delta_counts });
        }
        let Some(position_counts) = state.position_counts.checked_add(delta_counts) else {
            return Err(Error::Overflow);
        };
        state.last_raw = raw;
        state.position_counts = position_counts;
        Ok(position_counts)
    }
}

/// `|delta| > max` as one add and one compare: `delta + max` lies in `[0, 2 max]` exactly when
/// `|delta| <= max`. For `max <= i32::MAX` neither `2 max` nor the sum of an in-range `delta`
/// wraps, and an out-of-range one lands above `2 max` (below zero it wraps past `2^31 + max`).
#[inline(always)]
fn outside(delta: i32, max: u32) -> bool {
    (delta as u32).wrapping_add(max) > max << 1
}

impl Default for Coeffs<u16> {
    fn default() -> Self {
        // 934 counts per tick: Config::PAPER_RIG on Rig::PAPER.
        Self {
            max_delta_counts: 934,
            counter: PhantomData,
        }
    }
}

impl Default for Coeffs<u32> {
    fn default() -> Self {
        Self {
            max_delta_counts: 934,
            counter: PhantomData,
        }
    }
}

/// The unwrapper's state: the last accepted counter value and the position it stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct State<C> {
    last_raw: C,
    position_counts: i32,
    primed: bool,
}

impl<C: Counter> State<C> {
    /// A state whose first sample, whatever the counter reads, is taken as `position_counts`.
    pub const fn new(position_counts: i32) -> Self {
        Self {
            last_raw: C::ZERO,
            position_counts,
            primed: false,
        }
    }

    /// Re-homes: the next sample is taken as `position_counts` and never refused.
    pub fn reset(&mut self, position_counts: i32) {
        *self = Self::new(position_counts);
    }

    /// The last accepted position, in counts.
    pub const fn position_counts(&self) -> i32 {
        self.position_counts
    }

    /// Whether a first sample has been taken since construction or the last reset.
    pub const fn is_primed(&self) -> bool {
        self.primed
    }

    /// The last accepted raw counter value (meaningless before the first sample).
    pub const fn last_raw(&self) -> C {
        self.last_raw
    }
}

impl<C: Counter> Default for State<C> {
    fn default() -> Self {
        Self::new(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn outside_is_the_absolute_value_compare(delta: i32, max in 0..=(i32::MAX as u32)) {
            prop_assert_eq!(outside(delta, max), delta.unsigned_abs() > max);
        }
    }

    #[test]
    fn outside_at_the_edges() {
        for max in [0, 1, 934, i16::MAX as u32, i32::MAX as u32] {
            for delta in [0, 1, -1, i32::MAX, i32::MIN, i32::MIN + 1] {
                assert_eq!(
                    outside(delta, max),
                    delta.unsigned_abs() > max,
                    "{delta} {max}"
                );
            }
            let m = max as i64;
            for delta in [m, m + 1, -m, -m - 1] {
                if let Ok(d) = i32::try_from(delta) {
                    assert_eq!(outside(d, max), d.unsigned_abs() > max, "{d} {max}");
                }
            }
        }
    }

    fn coeffs16(max: u32) -> Coeffs<u16> {
        Coeffs::from_max_delta_counts(max).unwrap()
    }

    fn primed16(raw: u16, position_counts: i32) -> State<u16> {
        let mut s = State::new(position_counts);
        coeffs16(1).update(&mut s, raw).unwrap();
        s
    }

    #[test]
    fn first_sample_initialises_at_any_raw_value() {
        let c = coeffs16(1);
        for (raw, start) in [
            (0u16, 0i32),
            (0xffff, 0),
            (0x8000, -5),
            (0x7fff, i32::MAX),
            (1234, i32::MIN),
        ] {
            let mut s = State::new(start);
            assert!(!s.is_primed());
            assert_eq!(c.update(&mut s, raw), Ok(start), "raw {raw:#06x}");
            assert!(s.is_primed());
            assert_eq!(s.last_raw(), raw);
            // The next identical sample is a zero step.
            assert_eq!(c.update(&mut s, raw), Ok(start));
        }
    }

    #[test]
    fn table_16_bit_steps() {
        // (previous raw, new raw, max step, expected result relative to position 1000)
        let jump = |delta_counts| Err(Error::Jump { delta_counts });
        #[allow(clippy::type_complexity)]
        let table: &[(u16, u16, u32, Result<i32, Error>)] = &[
            (0x0000, 0x0000, 1, Ok(1000)),
            (0x7fff, 0x8000, 1, Ok(1001)),
            (0x8000, 0x7fff, 1, Ok(999)),
            (0xffff, 0x0000, 1, Ok(1001)),
            (0x0000, 0xffff, 1, Ok(999)),
            (0xfff0, 0x0010, 32, Ok(1032)),
            (0x0010, 0xfff0, 32, Ok(968)),
            // Exactly at the limit is accepted, one more is refused, in both directions.
            (0xfff0, 0x0010, 31, jump(32)),
            (0x0010, 0xfff0, 31, jump(-32)),
            (0x0000, 0x7fff, 32767, Ok(1000 + 32767)),
            (0x7fff, 0x0000, 32767, Ok(1000 - 32767)),
            (0x8000, 0xffff, 32767, Ok(1000 + 32767)),
            (0xffff, 0x8000, 32767, Ok(1000 - 32767)),
            // Half the range is ambiguous: refused whatever the limit.
            (0x0000, 0x8000, 32767, jump(-32768)),
            (0x8000, 0x0000, 32767, jump(-32768)),
            (0x7fff, 0xffff, 32767, jump(-32768)),
            (0x1234, 0x9234, 32767, jump(-32768)),
            (0x0000, 0x7fff, 32766, jump(32767)),
            (0x7fff, 0x0000, 32766, jump(-32767)),
        ];
        for &(prev, raw, max, expected) in table {
            let mut s = primed16(prev, 1000);
            let before = s;
            let got = coeffs16(max).update(&mut s, raw);
            assert_eq!(got, expected, "{prev:#06x} -> {raw:#06x}, max {max}");
            match got {
                Ok(p) => {
                    assert_eq!(s.position_counts(), p);
                    assert_eq!(s.last_raw(), raw);
                }
                Err(_) => assert_eq!(s, before, "a refused sample must leave the state"),
            }
        }
    }

    #[test]
    fn table_32_bit_steps() {
        let c = Coeffs::<u32>::from_max_delta_counts(i32::MAX as u32).unwrap();
        let table: &[(u32, u32, Result<i32, Error>)] = &[
            (0xffff_ffff, 0, Ok(1)),
            (0, 0xffff_ffff, Ok(-1)),
            (0x7fff_ffff, 0x8000_0000, Ok(1)),
            (0x8000_0000, 0x7fff_ffff, Ok(-1)),
            (0, 0x7fff_ffff, Ok(i32::MAX)),
            (0, 0x8000_0001, Ok(-i32::MAX)),
            (
                0,
                0x8000_0000,
                Err(Error::Jump {
                    delta_counts: i32::MIN,
                }),
            ),
        ];
        for &(prev, raw, expected) in table {
            let mut s = State::<u32>::new(0);
            c.update(&mut s, prev).unwrap();
            assert_eq!(c.update(&mut s, raw), expected, "{prev:#x} -> {raw:#x}");
        }
    }

    #[test]
    fn many_wraps_each_way() {
        let c = coeffs16(1000);
        let mut s = State::new(0);
        let mut raw = 0x7ff0u16;
        c.update(&mut s, raw).unwrap();
        // 200 forward wraps in steps of 997 counts, then 400 back, then 200 forward.
        let mut truth: i64 = 0;
        for (steps, step) in [(13_147i64, 997i64), (26_294, -997), (13_147, 997)] {
            for _ in 0..steps {
                raw = raw.wrapping_add(step as u16);
                truth += step;
                assert_eq!(c.update(&mut s, raw), Ok(truth as i32));
            }
        }
        assert_eq!(truth, 0);
        assert_eq!(s.position_counts(), 0);
        assert_eq!(raw, 0x7ff0);
    }

    #[test]
    fn overflow_is_refused_not_wrapped() {
        let c = coeffs16(32767);
        let mut s = State::new(i32::MAX - 1);
        c.update(&mut s, 0).unwrap();
        assert_eq!(c.update(&mut s, 1), Ok(i32::MAX));
        assert_eq!(c.update(&mut s, 2), Err(Error::Overflow));
        assert_eq!(s.position_counts(), i32::MAX);
        assert_eq!(s.last_raw(), 1);
        // Going back is fine.
        assert_eq!(c.update(&mut s, 0), Ok(i32::MAX - 1));

        let mut s = State::new(i32::MIN);
        c.update(&mut s, 0x8000).unwrap();
        assert_eq!(c.update(&mut s, 0x7fff), Err(Error::Overflow));
        assert_eq!(c.update(&mut s, 0x8001), Ok(i32::MIN + 1));
    }

    #[test]
    fn glitch_is_skipped_and_reset_rehomes() {
        let c = coeffs16(10);
        let mut s = State::new(0);
        c.update(&mut s, 100).unwrap();
        assert_eq!(c.update(&mut s, 105), Ok(5));
        assert_eq!(
            c.update(&mut s, 40_000),
            Err(Error::Jump {
                delta_counts: 40_000 - 105 - 65_536
            })
        );
        assert_eq!(c.update(&mut s, 110), Ok(10));
        s.reset(-7);
        assert!(!s.is_primed());
        assert_eq!(c.update(&mut s, 40_000), Ok(-7));
        assert_eq!(c.update(&mut s, 39_990), Ok(-17));
    }

    #[test]
    fn build_from_si() {
        let rig = BuildContext::PAPER;
        let c: Coeffs<u16> = Config::PAPER_RIG.build(&rig).unwrap();
        // 1000 mm/s * 1867.89 counts/mm / 2000 Hz = 933.9 -> 934
        assert_eq!(c.max_delta_counts(), 934);
        assert_eq!(c, Coeffs::<u16>::default());
        assert_eq!(
            Config::PAPER_RIG.build::<u32>(&rig).unwrap(),
            Coeffs::<u32>::default()
        );

        let bad = |max_speed_mm_s| Config { max_speed_mm_s };
        let field = |cfg: Config| cfg.build::<u16>(&rig).unwrap_err().field();
        assert_eq!(field(bad(f64::NAN)), ConfigField::EncoderMaxSpeedMmS);
        assert_eq!(field(bad(0.0)), ConfigField::EncoderMaxSpeedMmS);
        assert_eq!(field(bad(-1.0)), ConfigField::EncoderMaxSpeedMmS);
        // 40 m/s at 2 kHz is 37358 counts per tick: more than a 16-bit counter can tell.
        assert_eq!(field(bad(40_000.0)), ConfigField::EncoderMaxSpeedMmS);
        assert!(bad(40_000.0).build::<u32>(&rig).is_ok());
        // The same speed at 20 kHz is 3736 counts per sample: within 16 bits.
        let fast = BuildContext::new(crate::rig::Rig::PAPER, 20_000.0).unwrap();
        assert!(bad(40_000.0).build::<u16>(&fast).is_ok());
        assert!(Coeffs::<u16>::from_max_delta_counts(0).is_err());
        assert!(Coeffs::<u16>::from_max_delta_counts(32768).is_err());
        assert!(Coeffs::<u32>::from_max_delta_counts(1 << 31).is_err());
    }
}
