//! Property tests of the counter unwrapper against an `i64` ground truth.

use estimator_core::encoder::{Coeffs, Error, State};
use proptest::prelude::*;

proptest! {
    /// Any walk whose steps stay within the limit is tracked exactly, across any number of wraps
    /// of a 16-bit counter, as long as the position stays in `i32`.
    #[test]
    fn walk_16_bit_matches_truth(
        max in 1u32..=32767,
        raw0 in any::<u16>(),
        start in -1_000_000_000i32..1_000_000_000,
        steps in prop::collection::vec(any::<i32>(), 1..2000),
    ) {
        let c = Coeffs::<u16>::from_max_delta_counts(max).unwrap();
        let mut s = State::new(start);
        let mut raw = raw0;
        prop_assert_eq!(c.update(&mut s, raw), Ok(start));
        let mut truth = start as i64;
        for step in steps {
            // Fold the step into [-max, max].
            let step = step.rem_euclid(2 * max as i32 + 1) - max as i32;
            raw = raw.wrapping_add(step as u16);
            truth += step as i64;
            prop_assert_eq!(c.update(&mut s, raw), Ok(truth as i32));
        }
    }

    /// Steps beyond the limit are refused and leave the state as it was; the walk then goes on.
    #[test]
    fn glitches_are_refused_16_bit(
        max in 1u32..=30000,
        raw0 in any::<u16>(),
        walk in prop::collection::vec((any::<i16>(), any::<bool>()), 1..500),
    ) {
        let c = Coeffs::<u16>::from_max_delta_counts(max).unwrap();
        let mut s = State::new(0);
        let mut raw = raw0;
        c.update(&mut s, raw).unwrap();
        let mut truth = 0i64;
        for (step, glitch) in walk {
            let step = step as i32;
            if glitch {
                let bad = raw.wrapping_add(step as u16);
                let delta = bad.wrapping_sub(raw) as i16 as i32;
                let before = s;
                let got = c.update(&mut s, bad);
                if delta.unsigned_abs() > max {
                    prop_assert_eq!(got, Err(Error::Jump { delta_counts: delta }));
                    prop_assert_eq!(s, before);
                } else {
                    raw = bad;
                    truth += delta as i64;
                    prop_assert_eq!(got, Ok(truth as i32));
                }
            } else {
                let step = step.rem_euclid(2 * max as i32 + 1) - max as i32;
                raw = raw.wrapping_add(step as u16);
                truth += step as i64;
                prop_assert_eq!(c.update(&mut s, raw), Ok(truth as i32));
            }
        }
    }

    /// The 32-bit counter: any sequence of raw values, including ones leaving `i32`, gives either
    /// the exact position or a refusal with the state untouched.
    #[test]
    fn walk_32_bit_total(
        max in 1u32..=i32::MAX as u32,
        start in any::<i32>(),
        raws in prop::collection::vec(any::<u32>(), 1..300),
    ) {
        let c = Coeffs::<u32>::from_max_delta_counts(max).unwrap();
        let mut s = State::new(start);
        let mut last: Option<u32> = None;
        let mut truth = start as i64;
        for raw in raws {
            let before = s;
            let got = c.update(&mut s, raw);
            match last {
                None => {
                    prop_assert_eq!(got, Ok(start));
                    last = Some(raw);
                }
                Some(prev) => {
                    let delta = raw.wrapping_sub(prev) as i32;
                    let next = truth + delta as i64;
                    if delta.unsigned_abs() > max {
                        prop_assert_eq!(got, Err(Error::Jump { delta_counts: delta }));
                        prop_assert_eq!(s, before);
                    } else if next > i32::MAX as i64 || next < i32::MIN as i64 {
                        prop_assert_eq!(got, Err(Error::Overflow));
                        prop_assert_eq!(s, before);
                    } else {
                        prop_assert_eq!(got, Ok(next as i32));
                        truth = next;
                        last = Some(raw);
                    }
                }
            }
        }
    }
}
