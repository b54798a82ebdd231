//! The position loop against a small simulated plant, and property tests on extreme inputs.

use estimator_core::encoder;
use estimator_core::fixed::types::{I16F16, I40F24};
use estimator_core::pid::{Coeffs, Config, Output, State};
use estimator_core::rig::Rig;
use estimator_core::trajectory::{self, Setpoint, Trajectory};
use estimator_core::BuildContext;
use proptest::prelude::*;

/// The carriage as a double integrator with friction, integrated in f64 at 10 sub-steps per tick:
/// ≈33 kg effective mass, 35 N/A at the belt (the figures behind `Config::PAPER_RIG`), 5 N of
/// Coulomb and 20 N·s/m of viscous friction. The encoder reads the floor of the motor position.
struct Plant {
    x_mm: f64,
    v_mm_s: f64,
    counts_per_mm: f64,
    rate_hz: f64,
}

impl Plant {
    const MASS_KG: f64 = 33.0;
    const NEWTON_PER_A: f64 = 35.4;
    const COULOMB_N: f64 = 5.0;
    const VISCOUS_N_S_PER_M: f64 = 20.0;

    fn new(rate_hz: f64) -> Self {
        Self {
            x_mm: 0.0,
            v_mm_s: 0.0,
            counts_per_mm: Rig::PAPER.counts_per_mm(),
            rate_hz,
        }
    }

    fn counts(&self) -> i32 {
        (self.x_mm * self.counts_per_mm).floor() as i32
    }

    fn step(&mut self, current_a: I16F16) {
        let dt = 1.0 / self.rate_hz / 10.0;
        let drive_n = current_a.to_num::<f64>() * Self::NEWTON_PER_A;
        for _ in 0..10 {
            let v_m_s = self.v_mm_s / 1000.0;
            let mut friction_n = Self::VISCOUS_N_S_PER_M * v_m_s;
            if v_m_s.abs() > 1e-6 {
                friction_n += Self::COULOMB_N * v_m_s.signum();
            } else if drive_n.abs() <= Self::COULOMB_N {
                // Stuck: static friction holds.
                self.v_mm_s = 0.0;
                continue;
            } else {
                friction_n += Self::COULOMB_N * drive_n.signum();
            }
            let a_mm_s2 = (drive_n - friction_n) / Self::MASS_KG * 1000.0;
            self.v_mm_s += a_mm_s2 * dt;
            self.x_mm += self.v_mm_s * dt;
        }
    }
}

fn paper_pid() -> Coeffs {
    Config::PAPER_RIG.build(&BuildContext::PAPER).unwrap()
}

#[test]
fn step_response_settles_without_large_overshoot() {
    let c = paper_pid();
    let mut s = State::new();
    let mut plant = Plant::new(2000.0);
    // A 0.1 mm step (187 counts) straight into the loop: P alone asks for 1 A.
    let target = 187;
    let sp = Setpoint::at_rest(target);
    let mut peak = i32::MIN;
    let mut near_at = None;
    for tick in 0..4000 {
        let o = c.update(&mut s, &sp, plant.counts());
        plant.step(o.current_a);
        peak = peak.max(plant.counts());
        if near_at.is_none() && (plant.counts() - target).abs() <= 12 {
            near_at = Some(tick);
        }
    }
    // A 17 Hz loop with damping ≈0.6 gets within 12 counts (6 um) in tens of ms...
    let near_at = near_at.expect("gets near the target");
    assert!(near_at < 100, "near after {near_at} ticks");
    let overshoot = (peak - target) as f64 / target as f64;
    assert!(overshoot < 0.35, "overshoot {overshoot}");
    // ...and the integrator then works the rest off against the plant's static friction.
    assert!(
        (plant.counts() - target).abs() <= 1,
        "{}",
        plant.counts() - target
    );
}

#[test]
fn tracks_a_trapezoid_with_feed_forward() {
    let rig = Rig::PAPER;
    let c = paper_pid();
    let mut s = State::new();
    let mut plant = Plant::new(2000.0);
    let ctx = BuildContext::PAPER;
    let enc_c: encoder::Coeffs<u16> = encoder::Config::PAPER_RIG.build(&ctx).unwrap();
    let mut enc = encoder::State::new(0);
    let traj_c = trajectory::Config::PAPER_RIG.build(&ctx).unwrap();
    let mut traj = Trajectory::new(traj_c, 0);
    // 100 mm and back to 20 mm, reversing mid-way; the 16-bit counter wraps three times.
    let target_a = (100.0 * rig.counts_per_mm()) as i32;
    let target_b = (20.0 * rig.counts_per_mm()) as i32;
    traj.set_target(target_a);
    let mut worst_counts = 0f64;
    let mut worst_current = I16F16::ZERO;
    for tick in 0..6000 {
        if tick == 1000 {
            traj.set_target(target_b);
        }
        let raw = plant.counts() as u16;
        let measured = enc_c
            .update(&mut enc, raw)
            .expect("plausible encoder steps");
        assert_eq!(measured, plant.counts());
        let sp = traj.tick();
        let o = c.update(&mut s, &sp, measured);
        assert!(!o.saturated, "saturated at tick {tick}");
        worst_counts = worst_counts.max(o.following_error_counts.to_num::<f64>().abs());
        worst_current = worst_current.max(o.current_a.abs());
        plant.step(o.current_a);
    }
    assert!(traj.is_done());
    // Feed-forward carries the motion: the loop only sees friction and quantisation.
    let worst_mm = worst_counts / rig.counts_per_mm();
    assert!(worst_mm < 0.05, "following error {worst_mm} mm");
    assert!(worst_current > 1 && worst_current < 8, "{worst_current}");
    assert!(
        (plant.counts() - target_b).abs() <= 2,
        "{}",
        plant.counts() - target_b
    );
}

#[test]
fn same_inputs_same_outputs_bit_for_bit() {
    // A Fig. 18-like sequence of reversals through trajectory and PID, with a synthetic integer
    // "plant" (the setpoint lagging and jittering): every output is hashed. Integer arithmetic
    // only, so the hash is the same on the host and on the Cortex-M4; it changes only if the
    // per-tick arithmetic changes (then update it deliberately).
    fn run() -> (u64, Output) {
        let c = paper_pid();
        let mut s = State::new();
        let mut traj = Trajectory::new(
            trajectory::Config::PAPER_RIG
                .build(&BuildContext::PAPER)
                .unwrap(),
            0,
        );
        let mut hash = 0xcbf2_9ce4_8422_2325u64;
        let mut eat = |x: u64| {
            for b in x.to_le_bytes() {
                hash = (hash ^ b as u64).wrapping_mul(0x0100_0000_01b3);
            }
        };
        let mut last = None;
        let mut measured = 0i32;
        for tick in 0..20_000u32 {
            match tick {
                0 => traj.set_target(400_000),
                3000 => traj.set_target(50_000),
                5000 => traj.set_target(300_000),
                5400 => traj.set_target(-20_000),
                9000 => traj.stop(),
                12_000 => traj.set_target(7),
                _ => {}
            }
            let sp = traj.tick();
            let o = c.update(&mut s, &sp, measured);
            eat(sp.position_counts().to_bits() as u64);
            eat(sp.velocity_counts_per_tick().to_bits() as u64);
            eat(o.current_a.to_bits() as u64);
            eat(o.following_error_counts.to_bits() as u64);
            eat(s.integrator_a().to_bits() as u64);
            measured = sp.position_counts().to_num::<i32>() - 40 + ((tick * 7919) % 61) as i32;
            last = Some(o);
        }
        (hash, last.unwrap())
    }
    let (a, out_a) = run();
    let (b, out_b) = run();
    assert_eq!(a, b);
    assert_eq!(out_a, out_b);
    assert_eq!(a, GOLDEN, "per-tick arithmetic changed: {a:#018x}");
}

/// Hash of `same_inputs_same_outputs_bit_for_bit`.
const GOLDEN: u64 = 0x6b55_4c8e_d219_8272;

fn any_config() -> impl Strategy<Value = Coeffs> {
    (
        (
            0.0f64..1.0,
            0.0f64..1.0,
            0.0f64..1.0,
            0.0f64..1.0,
            0.0f64..1.0,
        ),
        (0.0f64..1.0, 0.1f64..127.0),
        prop::sample::select(vec![500.0, 2000.0, 20_000.0]),
    )
        .prop_filter_map(
            "representable",
            |((kp, ki, kd, kv, ka), (fc, max_current_a), rate_hz)| {
                let cpm = Rig::PAPER.counts_per_mm();
                // Each gain anywhere up to its bound (log-spread), zero included.
                let spread = |x: f64, top: f64| {
                    if x < 0.05 {
                        0.0
                    } else {
                        top * 10f64.powf(-6.0 * x)
                    }
                };
                Config {
                    kp_a_per_mm: spread(kp, 0.99 * cpm),
                    ki_a_per_mm_s: spread(ki, 0.99 * cpm * rate_hz / 256.0),
                    kd_a_s_per_mm: spread(kd, 15.9 * cpm / rate_hz),
                    derivative_cutoff_hz: (rate_hz / 2.0) * 10f64.powf(-3.0 * fc),
                    kff_vel_a_s_per_mm: spread(kv, 15.9 * cpm / rate_hz),
                    kff_acc_a_s2_per_mm: spread(ka, 511.0 * cpm / (rate_hz * rate_hz)),
                    max_current_a,
                }
                .build(&BuildContext::new(Rig::PAPER, rate_hz).ok()?)
                .ok()
            },
        )
}

fn any_setpoint() -> impl Strategy<Value = Setpoint> {
    let bits = prop_oneof![
        Just(i64::MIN),
        Just(i64::MAX),
        Just(0i64),
        any::<i64>(),
        (i32::MIN as i64..=i32::MAX as i64).prop_map(|c| c << 24),
    ];
    (bits.clone(), bits.clone(), bits).prop_map(|(p, v, a)| {
        Setpoint::new(
            I40F24::from_bits(p),
            I40F24::from_bits(v),
            I40F24::from_bits(a),
        )
    })
}

fn any_position() -> impl Strategy<Value = i32> {
    prop_oneof![Just(i32::MIN), Just(i32::MAX), Just(0), any::<i32>()]
}

proptest! {
    /// Whatever the gains and inputs: no panic or overflow (debug builds check), the current and
    /// the integrator stay within ±max, and the same inputs give the same outputs.
    #[test]
    fn total_and_bounded(
        c in any_config(),
        inputs in prop::collection::vec((any_setpoint(), any_position()), 1..200),
    ) {
        let max = c.max_current_a();
        let mut s = State::new();
        let mut twin = State::new();
        for (sp, m) in &inputs {
            let o = c.update(&mut s, sp, *m);
            prop_assert!(o.current_a.abs() <= max);
            if o.saturated {
                prop_assert_eq!(o.current_a.abs(), max);
            }
            prop_assert!(s.integrator_a().abs() <= max);
            prop_assert_eq!(o, c.update(&mut twin, sp, *m));
        }
    }

    /// The reported following error is `setpoint - measured`, to 1/256 count, saturated.
    #[test]
    fn following_error_is_exact_or_saturated(sp in any_setpoint(), m in any_position()) {
        let o = paper_pid().update(&mut State::new(), &sp, m);
        // Exact, in LSBs of I40F24: the error is its floor to 1/256 count, or saturated.
        let exact = sp.position_counts().to_bits() as i128 - ((m as i128) << 24);
        let got = (o.following_error_counts.to_bits() as i128) << 16;
        let limit = 1i128 << (22 + 24);
        if exact >= -limit && exact < limit {
            prop_assert!(exact - got >= 0 && exact - got < 1 << 16, "{} vs {}", got, exact);
        } else {
            prop_assert_eq!(got.signum(), exact.signum());
            prop_assert!(got.abs() >= limit - (1 << 24));
        }
    }
}
