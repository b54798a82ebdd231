//! The fault catalogue: every detector just under its threshold (no trip) and just over (trip at
//! the expected tick), the amplifier-enable rule, homing, polarity, the link watchdog and late
//! ticks.

use estimator_core::drive::{Command, CommandError, Drive, DriveConfig, Faults, Polarity, Sample};
use estimator_core::fault::{self, Inputs, State, WINDOW};
use estimator_core::fixed::types::I16F16;
use estimator_core::rig::Rig;
use estimator_core::settings::Settings;
use estimator_core::units::MotorCounts;

const RATE_HZ: f64 = 2000.0;
const VMAX_MM_S: f64 = 250.0;

fn cpm() -> f64 {
    Rig::PAPER.counts_per_mm()
}

fn coeffs(cfg: fault::Config) -> fault::Coeffs {
    cfg.build(
        &estimator_core::BuildContext::new(Rig::PAPER, RATE_HZ).unwrap(),
        VMAX_MM_S,
    )
    .unwrap()
}

/// Every timed detector off: each test switches on the one it checks.
fn quiet() -> fault::Config {
    fault::Config {
        stall_time_s: 0.0,
        runaway_time_s: 0.0,
        overspeed_time_s: 0.0,
        saturation_time_s: 0.0,
        link_timeout_s: 0.0,
        ..fault::Config::PAPER_RIG
    }
}

fn amps(a: f64) -> I16F16 {
    I16F16::from_num(a)
}

/// Feeds `positions` with a fixed current; returns the 1-based tick of the first trip.
fn first_trip(
    c: &fault::Coeffs,
    positions: &[i32],
    current: I16F16,
    saturated: bool,
) -> Option<usize> {
    let mut s = State::new();
    for (k, &x) in positions.iter().enumerate() {
        let raised = fault::check(
            c,
            &mut s,
            Inputs {
                position_counts: x,
                prev_current_a: current,
                prev_accel_ff_a: I16F16::ZERO,
                prev_saturated: saturated,
            },
        );
        if raised != 0 {
            return Some(k + 1);
        }
    }
    None
}

/// The window detectors look every other tick: a trip within one tick of `n`, either side.
#[track_caller]
fn within_a_tick(trip: Option<usize>, n: usize) {
    let t = trip.unwrap_or_else(|| panic!("no trip, expected tick {n}"));
    assert!(t.abs_diff(n) <= 1, "tripped on tick {t}, expected {n} +- 1");
}

/// Positions moving at `counts_per_tick` (fractional), for `n` ticks.
fn ramp(counts_per_tick: f64, n: usize) -> Vec<i32> {
    (0..n)
        .map(|k| (k as f64 * counts_per_tick).floor() as i32)
        .collect()
}

#[test]
fn stall_trips_at_the_configured_time_and_not_below_its_current() {
    let c = coeffs(fault::Config {
        stall_time_s: 0.05,
        stall_current_a: 2.0,
        ..quiet()
    });
    let n = 100; // 0.05 s at 2 kHz
    let still = vec![1234; 400];
    within_a_tick(first_trip(&c, &still, amps(2.0), false), n);
    // The condition beginning on the other parity of tick: a step on tick 2 restarts the
    // timer, which runs from tick 3 (at full rate the trip would come on tick n + 2).
    let later: Vec<i32> = [0].into_iter().chain(still.iter().copied()).collect();
    within_a_tick(first_trip(&c, &later, amps(2.0), false), n + 2);
    let under = I16F16::from_bits(amps(2.0).to_bits() - 1);
    assert_eq!(first_trip(&c, &still, under, false), None);
    within_a_tick(first_trip(&c, &still, -amps(2.5), false), n);
    // Motion just inside the dead band (20 um = 37 counts) is no motion; just outside, each
    // window restarts the timer.
    let band = (0.02 * cpm()) as i32;
    let creeping: Vec<i32> = (0..400)
        .map(|k| if k % 2 == 0 { 0 } else { band })
        .collect();
    within_a_tick(first_trip(&c, &creeping, amps(3.0), false), n);
    let moving = ramp((band + 1) as f64 / 50.0, 400);
    assert_eq!(first_trip(&c, &moving, amps(3.0), false), None);
}

#[test]
fn the_acceleration_feed_forward_is_not_stall_effort() {
    // A dither of a few um at 5000 mm/s²: 4.6 A of feed-forward each tick, alternating, and
    // the motor within the dead band. Only the current beyond the feed-forward counts.
    let c = coeffs(fault::Config {
        stall_time_s: 0.015,
        stall_current_a: 2.0,
        ..quiet()
    });
    let run = |beyond_a: f64| {
        let mut s = State::new();
        (0..400).find(|&k| {
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            fault::check(
                &c,
                &mut s,
                Inputs {
                    position_counts: 1234 + (k % 2) as i32,
                    prev_current_a: amps(sign * (4.6 + beyond_a)),
                    prev_accel_ff_a: amps(sign * 4.6),
                    prev_saturated: false,
                },
            ) != 0
        })
    };
    assert_eq!(run(0.0), None);
    assert_eq!(run(1.9), None);
    // Effort beyond it still trips, at the configured time.
    within_a_tick(run(2.0).map(|k| k + 1), 30);
}

#[test]
fn saturation_trips_after_its_time_net_of_unsaturated_ticks() {
    let c = coeffs(fault::Config {
        saturation_time_s: 0.03,
        ..quiet()
    });
    let n = 60;
    let xs = ramp(10.0, 400);
    assert_eq!(first_trip(&c, &xs, amps(8.0), true), Some(n));
    assert_eq!(first_trip(&c, &xs[..n - 1], amps(8.0), true), None);
    // Alternating saturated / not: never accumulates.
    let mut s = State::new();
    for (k, &x) in xs.iter().enumerate() {
        let r = fault::check(
            &c,
            &mut s,
            Inputs {
                position_counts: x,
                prev_current_a: amps(8.0),
                prev_accel_ff_a: I16F16::ZERO,
                prev_saturated: k % 2 == 0,
            },
        );
        assert_eq!(r, 0);
    }
}

#[test]
fn overspeed_trips_just_over_the_margin_and_not_just_under() {
    let c = coeffs(fault::Config {
        overspeed_time_s: 0.002, // 4 ticks
        overspeed_ratio: 1.2,
        ..quiet()
    });
    let limit_per_tick = 1.2 * VMAX_MM_S * cpm() / RATE_HZ;
    // The window measures WINDOW ticks: the first verdict comes on tick WINDOW + 1.
    let over = ramp(limit_per_tick * 1.01, 200);
    within_a_tick(first_trip(&c, &over, amps(0.5), false), WINDOW + 4);
    // Beginning on the other parity of tick: one tick at rest first.
    let later: Vec<i32> = [0].into_iter().chain(over.iter().copied()).collect();
    within_a_tick(first_trip(&c, &later, amps(0.5), false), WINDOW + 5);
    let under = ramp(limit_per_tick * 0.99, 200);
    assert_eq!(first_trip(&c, &under, amps(0.5), false), None);
    let backwards: Vec<i32> = over.iter().map(|x| -x).collect();
    within_a_tick(first_trip(&c, &backwards, amps(0.5), false), WINDOW + 4);
}

#[test]
fn runaway_trips_on_motion_against_the_current_but_not_on_braking() {
    let c = coeffs(fault::Config {
        runaway_time_s: 0.015, // 30 ticks
        runaway_current_a: 1.5,
        runaway_speed_mm_s: 5.0,
        ..quiet()
    });
    let n = 30;
    // Accelerating backwards while the current pushes forwards (wires reversed).
    let accel: Vec<i32> = (0..300).map(|k: i32| -(k * k) / 4 - 20 * k).collect();
    // Until the window fills, speed counts from the first sample: 41 counts on tick 3 is
    // over the threshold (37 counts per window), and the 30th such tick trips.
    within_a_tick(first_trip(&c, &accel, amps(1.5), false), 3 + n - 1);
    let later: Vec<i32> = [0].into_iter().chain(accel.iter().copied()).collect();
    within_a_tick(first_trip(&c, &later, amps(1.5), false), 3 + n);
    let under = I16F16::from_bits(amps(1.5).to_bits() - 1);
    assert_eq!(first_trip(&c, &accel, under, false), None);
    // Same motion with the current along it: a normal acceleration.
    assert_eq!(first_trip(&c, &accel, -amps(3.0), false), None);
    // Braking: forward motion slowing under a backward current.
    let braking: Vec<i32> = (0..300).map(|k| 600 * k - k * k).collect();
    assert_eq!(first_trip(&c, &braking[..290], -amps(3.0), false), None);
    // Constant speed against the current, just above and just below the speed threshold.
    let v = 5.0 * cpm() / RATE_HZ;
    let over = ramp(-v * 1.05, 300);
    within_a_tick(first_trip(&c, &over, amps(2.0), false), WINDOW + n);
    let slow = ramp(-v * 0.95, 300);
    assert_eq!(first_trip(&c, &slow, amps(2.0), false), None);
}

#[test]
fn following_error_limit_grows_with_speed() {
    let c = coeffs(fault::Config {
        following_error_at_rest_mm: 1.0,
        following_error_at_max_velocity_mm: 3.0,
        ..quiet()
    });
    let rest = c.following_error_limit_counts(0);
    assert_eq!(rest, (1.0 * cpm()) as u32);
    // The set-point velocity in Q16.16 counts per tick.
    let vmax = (VMAX_MM_S * cpm() / RATE_HZ * 65536.0) as i32;
    let at_max = c.following_error_limit_counts(vmax);
    // The speed is taken to 1/16 count per tick: within 2 counts of the exact line.
    assert!(at_max.abs_diff((3.0 * cpm()) as u32) <= 2, "{at_max}");
    let half = c.following_error_limit_counts(-vmax / 2);
    assert!(half.abs_diff((2.0 * cpm()) as u32) <= 2, "{half}");
    assert!(c.following_error_limit_counts(i32::MAX) > at_max);
    assert!(c.following_error_limit_counts(i32::MIN) > at_max);
}

// ---- drive level ----------------------------------------------------------------------------

mod common;
use common::{homed_with, mv, Mass};

#[test]
fn amplifier_enable_follows_enabled_and_no_fault() {
    let (mut d, mut m) = homed_with(&DriveConfig::paper_rig(), 50.0);
    let tick = |d: &mut Drive, m: &mut Mass| {
        let o = d.step(m.sample());
        m.step(o.current_a.to_num(), 1.0 / RATE_HZ);
        o.telemetry.amplifier_enabled
    };
    assert!(!tick(&mut d, &mut m), "disabled at start");
    d.command(Command::Enable).unwrap();
    assert!(tick(&mut d, &mut m), "enabled");
    d.command(Command::Disable).unwrap();
    assert!(!tick(&mut d, &mut m), "disabled");
    d.command(Command::Enable).unwrap();
    assert!(tick(&mut d, &mut m));
    d.raise_fault(Faults::CLOCK_FAILURE);
    assert!(!tick(&mut d, &mut m), "faulted");
    d.command(Command::ClearFaults).unwrap();
    assert!(!tick(&mut d, &mut m), "cleared but not re-enabled");
    d.command(Command::Enable).unwrap();
    assert!(tick(&mut d, &mut m), "re-enabled");
}

#[test]
fn moves_are_refused_until_homed() {
    let mut d = Drive::new(&DriveConfig::paper_rig()).unwrap();
    let m = Mass::new(10.0);
    let o = d.step(m.sample());
    assert!(!o.telemetry.homed);
    d.command(Command::Enable).unwrap();
    assert_eq!(d.command(mv(20.0)), Err(CommandError::NotHomed));
    d.command(Command::Home {
        position_um: 10_000,
        scale_um: 0,
    })
    .unwrap();
    assert!(d.is_homed());
    assert!(d.step(m.sample()).telemetry.homed);
    d.command(mv(20.0)).unwrap();
}

#[test]
fn encoder_jump_loses_the_home() {
    let (mut d, m) = homed_with(&DriveConfig::paper_rig(), 50.0);
    d.command(Command::Enable).unwrap();
    d.step(m.sample());
    let s = m.sample();
    let o = d.step(Sample {
        motor_counter: s.motor_counter.wrapping_add(20_000),
        ..s
    });
    assert!(o.telemetry.faults.has(Faults::ENCODER_JUMP));
    assert!(!o.telemetry.homed);
    d.command(Command::ClearFaults).unwrap();
    d.command(Command::Enable).unwrap();
    assert_eq!(d.command(mv(60.0)), Err(CommandError::NotHomed));
}

#[test]
fn link_watchdog_trips_after_its_timeout_and_not_before() {
    let (mut d, mut m) = homed_with(&DriveConfig::paper_rig(), 50.0);
    d.command(Command::Enable).unwrap();
    let n = d.monitor().link_timeout_ticks();
    assert_eq!(n, 1000);
    for _ in 0..n - 1 {
        let o = d.step(m.sample());
        assert!(o.telemetry.faults.is_clear());
        m.step(o.current_a.to_num(), 1.0 / RATE_HZ);
    }
    d.link_alive();
    for _ in 0..n - 1 {
        let o = d.step(m.sample());
        assert!(o.telemetry.faults.is_clear());
        m.step(o.current_a.to_num(), 1.0 / RATE_HZ);
    }
    let o = d.step(m.sample());
    assert_eq!(o.telemetry.faults, Faults(Faults::LINK_TIMEOUT));
    assert_eq!(o.current_a.to_bits(), 0);
    assert!(!o.telemetry.amplifier_enabled);
}

#[test]
fn a_late_tick_latches_deadline_missed_only_while_enabled() {
    let (mut d, m) = homed_with(&DriveConfig::paper_rig(), 50.0);
    d.missed_ticks(3);
    assert!(d.step(m.sample()).telemetry.faults.is_clear());
    assert_eq!(d.missed_tick_count(), 3);
    d.command(Command::Enable).unwrap();
    d.missed_ticks(0);
    assert!(d.step(m.sample()).telemetry.faults.is_clear());
    d.missed_ticks(1);
    let o = d.step(m.sample());
    assert_eq!(o.telemetry.faults, Faults(Faults::DEADLINE_MISSED));
    assert_eq!(o.current_a.to_bits(), 0);
    assert_eq!(d.missed_tick_count(), 4);
}

#[test]
fn a_scale_glitch_is_counted_not_a_motor_fault() {
    let (mut d, m) = homed_with(&DriveConfig::paper_rig(), 50.0);
    d.command(Command::Enable).unwrap();
    d.step(m.sample());
    let o = d.step(Sample {
        scale_counter: 30_000,
        ..m.sample()
    });
    assert!(o.telemetry.faults.is_clear());
    assert_eq!(d.scale_glitch_count(), 1);
}

#[test]
fn reversed_motor_wires_trip_runaway_and_polarity_setting_fixes_them() {
    // Wires reversed: a runaway (or, at worst, the following error) stops it.
    let (mut d, mut m) = homed_with(&DriveConfig::paper_rig(), 100.0);
    m.sign = -1.0;
    d.command(Command::Enable).unwrap();
    d.command(mv(150.0)).unwrap();
    let mut trip = None;
    for k in 0..4000 {
        let o = d.step(m.sample());
        m.step(o.current_a.to_num(), 1.0 / RATE_HZ);
        if !o.telemetry.faults.is_clear() {
            trip = Some((k, o.telemetry.faults));
            break;
        }
    }
    let (k, f) = trip.expect("reversed wires must trip");
    assert!(f.has(Faults::RUNAWAY), "{f} after {k} ticks");
    // The same reversed wiring with `current_inverted`: the move completes.
    let cfg = DriveConfig {
        settings: Settings {
            polarity: Polarity {
                current_inverted: true,
                ..Polarity::NORMAL
            },
            ..Settings::PAPER
        },
        ..DriveConfig::paper_rig()
    };
    let (mut d, mut m) = homed_with(&cfg, 100.0);
    m.sign = -1.0;
    d.command(Command::Enable).unwrap();
    d.command(mv(150.0)).unwrap();
    for _ in 0..4000 {
        d.link_alive();
        let o = d.step(m.sample());
        assert!(o.telemetry.faults.is_clear(), "{}", o.telemetry.faults);
        m.step(o.current_a.to_num(), 1.0 / RATE_HZ);
    }
    let t = d.telemetry();
    assert!(!t.moving);
    assert!((t.motor_counts.0 - (150.0 * cpm()) as i32).abs() <= 3);
}

#[test]
fn inverted_encoder_counts_the_other_way() {
    let cfg = DriveConfig {
        settings: Settings {
            polarity: Polarity {
                motor_encoder_inverted: true,
                ..Polarity::NORMAL
            },
            ..Settings::PAPER
        },
        ..DriveConfig::paper_rig()
    };
    let mut d = Drive::new(&cfg).unwrap();
    d.step(Sample::default());
    d.command(Command::Home {
        position_um: 50_000,
        scale_um: 0,
    })
    .unwrap();
    d.step(Sample::default());
    let o = d.step(Sample {
        motor_counter: 100,
        scale_counter: 0,
    });
    assert_eq!(
        o.telemetry.motor_counts,
        MotorCounts((50.0 * cpm()).round() as i32 - 100)
    );
}

#[test]
fn a_jammed_axis_trips_stall() {
    // The counter freezes (jam or encoder lost) while the drive pushes.
    let (mut d, mut m) = homed_with(&DriveConfig::paper_rig(), 50.0);
    d.command(Command::Enable).unwrap();
    d.command(Command::MoveMotorTo {
        target_um: 52_000,
        velocity_um_s: 5_000,
        accel_um_s2: 100_000,
    })
    .unwrap();
    for _ in 0..100 {
        let o = d.step(m.sample());
        m.step(o.current_a.to_num(), 1.0 / RATE_HZ);
    }
    let frozen = m.sample();
    let mut trip = None;
    for k in 0..4000 {
        let o = d.step(frozen);
        if !o.telemetry.faults.is_clear() {
            trip = Some((k, o));
            break;
        }
    }
    let (k, o) = trip.expect("a frozen counter under effort must trip");
    assert!(
        o.telemetry.faults.has(Faults::STALL),
        "{}",
        o.telemetry.faults
    );
    assert_eq!(o.current_a.to_bits(), 0);
    assert!(k < 400, "{k} ticks");
}

#[test]
fn a_hold_primes_the_window_as_the_first_tick_would() {
    // The drive primes the detectors when it holds (enable, homing, a cleared fault) rather
    // than on the first tick after: the same state from there on.
    let c = coeffs(quiet());
    for x in [-5000, 0, 1234] {
        let input = Inputs {
            position_counts: x,
            prev_current_a: amps(0.5),
            prev_accel_ff_a: I16F16::ZERO,
            prev_saturated: false,
        };
        let (mut fresh, mut held) = (State::new(), State::new());
        held.restart_at(x);
        for _ in 0..20 {
            assert_eq!(
                fault::check(&c, &mut fresh, input),
                fault::check(&c, &mut held, input)
            );
        }
        assert_eq!(fresh, held);
    }
}
