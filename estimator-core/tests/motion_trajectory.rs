//! Property tests of the trapezoidal profile: limits every tick, exact arrival, retargets.

use estimator_core::fixed::types::I40F24;
use estimator_core::rig::Rig;
use estimator_core::trajectory::{Coeffs, Config, Setpoint, Trajectory};
use estimator_core::BuildContext;
use proptest::prelude::*;

const ONE: f64 = (1u64 << 24) as f64;

/// Limits in LSBs of the counts grid.
#[derive(Clone, Copy, Debug)]
struct Limits {
    v: i64,
    a: i64,
    d: i64,
}

impl Limits {
    fn of(c: &Coeffs) -> Self {
        Self {
            v: c.velocity_counts_per_tick().to_bits(),
            a: c.acceleration_counts_per_tick2().to_bits(),
            d: c.deceleration_counts_per_tick2().to_bits(),
        }
    }
}

/// Checks one tick against the previous one.
fn check(l: Limits, prev: &Setpoint, s: &Setpoint) -> Result<(), TestCaseError> {
    let (v0, v1) = (
        prev.velocity_counts_per_tick().to_bits(),
        s.velocity_counts_per_tick().to_bits(),
    );
    prop_assert!(v1.abs() <= l.v, "velocity {} above the limit {}", v1, l.v);
    prop_assert_eq!(
        s.position_counts().to_bits() - prev.position_counts().to_bits(),
        v1
    );
    prop_assert_eq!(s.acceleration_counts_per_tick2().to_bits(), v1 - v0);
    prop_assert!(v0.signum() * v1.signum() >= 0, "reversal without rest");
    if v1.abs() > v0.abs() {
        prop_assert!(
            v1.abs() - v0.abs() <= l.a,
            "acceleration {} > {}",
            v1.abs() - v0.abs(),
            l.a
        );
    } else {
        prop_assert!(
            v0.abs() - v1.abs() <= l.d,
            "deceleration {} > {}",
            v0.abs() - v1.abs(),
            l.d
        );
    }
    if s.is_done() {
        prop_assert_eq!(v1, 0);
    }
    Ok(())
}

/// A generous bound on the ticks to reach `target` from the current state.
fn tick_bound(t: &Trajectory, l: Limits, target: i32) -> u64 {
    let (v, a, d) = (l.v as f64 / ONE, l.a as f64 / ONE, l.d as f64 / ONE);
    let speed = t.velocity_counts_per_tick().to_num::<f64>().abs();
    let brake = speed * speed / (2.0 * d) + speed;
    let dist = (target as f64 - t.position_counts().to_num::<f64>()).abs() + 2.0 * brake;
    let k = 1.0 / a + 1.0 / d;
    let time = speed / d + dist / v + v * k + (2.0 * dist * k).sqrt();
    (time * 1.5 + 20.0) as u64
}

/// Runs to rest on the target (at least one tick), checking every tick; returns the ticks taken.
fn run_to_rest(t: &mut Trajectory, l: Limits, prev: &mut Setpoint) -> Result<u64, TestCaseError> {
    let target = t.target_counts();
    let bound = tick_bound(t, l, target.to_num());
    let mut ticks = 0;
    loop {
        let s = t.tick();
        check(l, prev, &s)?;
        *prev = s;
        ticks += 1;
        if s.is_done() {
            break;
        }
        prop_assert!(ticks <= bound, "not at rest after {} ticks", ticks);
    }
    prop_assert_eq!(prev.position_counts(), target);
    prop_assert_eq!(prev.velocity_counts_per_tick(), 0);
    prop_assert!(t.is_done());
    Ok(ticks)
}

/// SI limits for the paper's rig at the usual control rates.
fn si_coeffs() -> impl Strategy<Value = Coeffs> {
    (
        -0.5f64..2.7,
        1.0f64..4.0,
        1.0f64..4.0,
        prop::sample::select(vec![500.0, 1000.0, 2000.0, 5000.0, 10_000.0, 20_000.0]),
    )
        .prop_filter_map("representable", |(v, a, d, rate_hz)| {
            Config {
                velocity_mm_s: 10f64.powf(v),
                acceleration_mm_s2: 10f64.powf(a),
                deceleration_mm_s2: 10f64.powf(d),
            }
            .build(&BuildContext::new(Rig::PAPER, rate_hz).ok()?)
            .ok()
        })
}

/// Raw limits over the whole representable range, including lopsided acceleration/deceleration.
fn raw_coeffs() -> impl Strategy<Value = Coeffs> {
    (-3.0f64..4.2, 0.0f64..4.0, 0.0f64..4.0).prop_filter_map("representable", |(v, a, d)| {
        let v = 10f64.powf(v);
        Coeffs::new(
            I40F24::from_num(v),
            I40F24::from_num((v / 10f64.powf(a)).min(63.0)),
            I40F24::from_num((v / 10f64.powf(d)).min(63.0)),
        )
        .ok()
    })
}

/// A start and a few retargets, at distances the profile covers in a bounded number of ticks.
fn scenario(c: Coeffs) -> impl Strategy<Value = (Coeffs, i32, Vec<(i32, u32)>)> {
    let v = c.velocity_counts_per_tick().to_num::<f64>();
    let span = (v * 5000.0).clamp(10.0, 1e9) as i32;
    (
        Just(c),
        -1_000_000_000i32..1_000_000_000,
        prop::collection::vec((-span..=span, 0u32..3000), 1..6),
    )
}

/// Time of the continuous optimum for a rest-to-rest move.
fn optimum_ticks(l: Limits, dist: f64) -> f64 {
    let (v, a, d) = (l.v as f64 / ONE, l.a as f64 / ONE, l.d as f64 / ONE);
    let k = 0.5 * (1.0 / a + 1.0 / d);
    if dist >= v * v * k {
        dist / v + v * k
    } else {
        (4.0 * dist * k).sqrt()
    }
}

fn retargets((c, start, moves): (Coeffs, i32, Vec<(i32, u32)>)) -> Result<(), TestCaseError> {
    let l = Limits::of(&c);
    let mut t = Trajectory::new(c, start);
    let mut prev = t.tick();
    prop_assert!(prev.is_done());
    let mut target = start;
    // The profile never passes a target, so it stays between the start and the targets.
    let (mut lowest, mut highest) = (start, start);
    let within = |s: &Setpoint, lowest: i32, highest: i32| {
        s.position_counts() >= lowest && s.position_counts() <= highest
    };
    for (offset, hold) in moves {
        target = start.saturating_add(offset);
        (lowest, highest) = (lowest.min(target), highest.max(target));
        t.set_target(target);
        for _ in 0..hold {
            let s = t.tick();
            check(l, &prev, &s)?;
            prop_assert!(within(&s, lowest, highest), "left the targets' span");
            prev = s;
        }
    }
    run_to_rest(&mut t, l, &mut prev)?;
    prop_assert_eq!(t.position_counts(), I40F24::from_num(target));
    // Stays at rest.
    for _ in 0..3 {
        let s = t.tick();
        check(l, &prev, &s)?;
        prop_assert!(s.is_done());
        prev = s;
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn retargets_si(s in si_coeffs().prop_flat_map(scenario)) {
        retargets(s)?;
    }

    #[test]
    fn retargets_raw(s in raw_coeffs().prop_flat_map(scenario)) {
        retargets(s)?;
    }

    /// From rest to rest: within a few ticks of the continuous optimum, and the speed never rises
    /// again once it has started to fall (no bump before arrival).
    #[test]
    fn rest_to_rest_is_near_optimal(
        c in prop_oneof![si_coeffs(), raw_coeffs()],
        fraction in 0.0f64..1.0,
        start in any::<i32>(),
        backwards in any::<bool>(),
    ) {
        let l = Limits::of(&c);
        let v = l.v as f64 / ONE;
        // Up to ~5000 ticks of cruise; at least a count.
        let dist = (1.0 + fraction * fraction * v * 5000.0).min(2e9) as i64;
        let target = if backwards { start as i64 - dist } else { start as i64 + dist };
        let target = target.clamp(i32::MIN as i64, i32::MAX as i64) as i32;
        let dist = (target as i64 - start as i64).abs() as f64;
        let mut t = Trajectory::new(c, start);
        let mut prev = Setpoint::at_rest(start);
        t.set_target(target);
        let mut ticks = 0u64;
        let mut falling = false;
        loop {
            let s = t.tick();
            check(l, &prev, &s)?;
            let (v0, v1) = (
                prev.velocity_counts_per_tick().to_bits().abs(),
                s.velocity_counts_per_tick().to_bits().abs(),
            );
            falling |= v1 < v0;
            prop_assert!(!(falling && v1 > v0), "speed rose again at tick {}", ticks);
            prev = s;
            ticks += 1;
            if s.is_done() {
                break;
            }
            prop_assert!(ticks < 1_000_000);
        }
        prop_assert_eq!(t.position_counts(), I40F24::from_num(target));
        let optimum = optimum_ticks(l, dist);
        // `ticks` counts the final tick at rest; discrete steps cost about one more, and with
        // decelerations of a few LSBs the last ticks' rounding a few more.
        prop_assert!(
            ticks as f64 <= optimum * 1.001 + 4.0,
            "{} ticks, optimum {:.1}",
            ticks,
            optimum
        );
    }

    /// `stop` at any moment: decelerates at the limit all the way to rest.
    #[test]
    fn stop_anywhere(
        c in si_coeffs(),
        dist in -2_000_000i32..2_000_000,
        at in 0u32..20_000,
    ) {
        let l = Limits::of(&c);
        let mut t = Trajectory::new(c, 0);
        let mut prev = t.tick();
        t.set_target(dist);
        for _ in 0..at {
            let s = t.tick();
            check(l, &prev, &s)?;
            prev = s;
        }
        let speed = prev.velocity_counts_per_tick().to_bits().abs();
        t.stop();
        let ticks = run_to_rest(&mut t, l, &mut prev)?;
        // Full deceleration all the way: ceil(speed / d) ticks, plus the tick reporting rest.
        let full_braking_ticks = (speed + l.d - 1) / l.d;
        prop_assert!(ticks as i64 <= full_braking_ticks + 1, "{} ticks from speed {}", ticks, speed);
    }
}

/// The paper's Fig. 18 scenario: the carriage changes direction abruptly at several places along
/// its 300 mm travel, each new target given mid-move.
#[test]
fn fig18_like_abrupt_reversals() {
    let rig = Rig::PAPER;
    let c = Config {
        velocity_mm_s: 50.0,
        acceleration_mm_s2: 500.0,
        deceleration_mm_s2: 500.0,
    }
    .build(&BuildContext::PAPER)
    .unwrap();
    let l = Limits::of(&c);
    let mm = |x: f64| (x * rig.counts_per_mm()).round() as i32;
    let mut t = Trajectory::new(c, 0);
    let mut prev = t.tick();
    let mut reversals = 0;
    let mut direction = 0;
    for (target_mm, hold_s) in [
        (300.0, 2.0),
        (20.0, 1.0),
        (250.0, 1.5),
        (10.0, 0.5),
        (290.0, 0.05),
        (0.0, 10.0),
    ] {
        t.set_target(mm(target_mm));
        for _ in 0..(hold_s * 2000.0) as u32 {
            let s = t.tick();
            check(l, &prev, &s).unwrap();
            let v = s.velocity_counts_per_tick().to_bits().signum();
            if v != 0 {
                reversals += (v == -direction) as u32;
                direction = v;
            }
            prev = s;
        }
    }
    run_to_rest(&mut t, l, &mut prev).unwrap();
    assert_eq!(t.position_counts(), 0);
    // To 20, to 250, to 10; the 290 target is dropped before the carriage has stopped.
    assert_eq!(reversals, 3);
}
