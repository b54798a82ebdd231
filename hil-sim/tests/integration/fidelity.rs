//! Fidelity of the `paper-rig` plant against the paper's section 4 (and Fig. 4 of section 2).
//!
//! The plant is driven the way the paper drove the rig: a trapezoidal velocity profile on the
//! motor, tracked closely by a position loop, while `dx = x_LS - x_PE` is logged against `x_PE`.
//! The loop here is a test-only f64 harness (trapezoid + PID on the motor angle); the firmware's
//! own trajectory and PID live in `estimator-core` and are not used here, so these tests judge
//! the plant alone.
//!
//! Every test prints its figures: `cargo test -p hil-sim --release --test integration fidelity -- --nocapture`.
//! Speed is a benchmark, not a test: `cargo bench -p hil-sim --bench sim_speed`.

use hil_sim::PlantParams;

/// Control tick of the harness (the firmware's 2 kHz).
const TICK_S: f64 = 5e-4;
/// Belt pitch: the period of the tooth-passing harmonic in carriage travel.
const PITCH_MM: f64 = 5.08;
/// Belt travel per pulley revolution: the period of the eccentricity term (eq. 12).
const PULLEY_REV_MM: f64 = 101.6;

mod harness {
    //! Test-only closed loop: trapezoidal profile + PID on the motor angle, current out.
    use super::TICK_S;
    use hil_sim::{Plant, PlantParams};

    /// Trapezoidal point-to-point profile in nominal millimetres.
    #[derive(Clone, Debug)]
    pub struct Profile {
        pub pos: f64,
        pub vel: f64,
        pub acc: f64,
    }

    impl Profile {
        /// Advances one tick toward `target`; returns true once there and at rest.
        pub fn advance(&mut self, target: f64, v_max: f64, a_max: f64) -> bool {
            let d = target - self.pos;
            let dv = a_max * TICK_S;
            if d.abs() < 0.5 * dv * TICK_S && self.vel.abs() <= dv {
                self.acc = -self.vel / TICK_S;
                self.pos = target;
                self.vel = 0.0;
                return true;
            }
            // Fastest speed from which we can still stop at the target.
            let v_stop = (2.0 * a_max * (d.abs() - 0.5 * self.vel.abs() * TICK_S).max(0.0)).sqrt();
            let v_des = d.signum() * v_max.min(v_stop);
            let v_new = self.vel + (v_des - self.vel).clamp(-dv, dv);
            self.acc = (v_new - self.vel) / TICK_S;
            self.pos += 0.5 * (self.vel + v_new) * TICK_S;
            self.vel = v_new;
            false
        }
    }

    /// One logged control tick.
    #[derive(Clone, Copy, Debug)]
    pub struct Sample {
        /// Index of the move this tick belongs to.
        pub seg: usize,
        /// x_PE, as read from the motor encoder.
        pub pe_mm: f64,
        /// x_LS, as read from the scale.
        pub ls_mm: f64,
        /// dx without quantisation and noise.
        pub dx_true_mm: f64,
    }

    impl Sample {
        /// The paper's `dx = x_LS - x_PE`.
        pub fn dx_mm(&self) -> f64 {
            self.ls_mm - self.pe_mm
        }
    }

    /// Go to `target_mm` with speed `v_mm_s` and acceleration `a_mm_s2`, then dwell 0.2 s.
    #[derive(Clone, Copy, Debug)]
    pub struct Move {
        pub target_mm: f64,
        pub v_mm_s: f64,
        pub a_mm_s2: f64,
    }

    pub fn mv(target_mm: f64, v_mm_s: f64, a_mm_s2: f64) -> Move {
        Move {
            target_mm,
            v_mm_s,
            a_mm_s2,
        }
    }

    /// Plant plus PID on the motor angle (30 Hz bandwidth), with acceleration feedforward.
    #[derive(Clone, Debug)]
    pub struct Drive {
        pub plant: Plant,
        rad_per_mm: f64,
        rad_per_count: f64,
        kp: f64,
        ki: f64,
        kd: f64,
        j_over_kt: f64,
        integral: f64,
        theta_prev: f64,
        omega_f: f64,
        pub profile: Profile,
    }

    impl Drive {
        pub fn new(params: &PlantParams, start_mm: f64, seed: u64) -> Drive {
            let plant = Plant::new(params, start_mm, seed).unwrap();
            let rad_per_count = core::f64::consts::TAU / (4.0 * params.encoder.lines as f64);
            let rad_per_mm = plant.counts_per_mm() * rad_per_count;
            // Inertia at the motor: rotor + pulley + carriage and belt through the drive.
            let r = params.nominal_radius_m() / params.gearbox.ratio;
            let j = params.motor.rotor_inertia_kg_m2
                + params.gearbox.output_inertia_kg_m2 / params.gearbox.ratio.powi(2)
                + (params.carriage.mass_kg + params.belt.lumped_mass_kg) * r * r;
            let kt = params.motor.torque_constant_nm_per_a;
            let w = core::f64::consts::TAU * 30.0;
            let theta0 = plant.motor_counts() as f64 * rad_per_count;
            Drive {
                plant,
                rad_per_mm,
                rad_per_count,
                kp: j * w * w / kt,
                ki: j * w * w * w / 10.0 / kt,
                kd: 1.6 * j * w / kt,
                j_over_kt: j / kt,
                integral: 0.0,
                theta_prev: theta0,
                omega_f: 0.0,
                profile: Profile {
                    pos: theta0 / rad_per_mm,
                    vel: 0.0,
                    acc: 0.0,
                },
            }
        }

        /// One control tick: sample the encoder, control, step the plant.
        pub fn tick(&mut self) {
            let theta = self.plant.motor_counts() as f64 * self.rad_per_count;
            // Velocity from counts, low-passed (1 ms) against quantisation noise.
            let omega_raw = (theta - self.theta_prev) / TICK_S;
            self.theta_prev = theta;
            self.omega_f += (omega_raw - self.omega_f) * (TICK_S / (1e-3 + TICK_S));
            let e = self.profile.pos * self.rad_per_mm - theta;
            let ev = self.profile.vel * self.rad_per_mm - self.omega_f;
            self.integral += e * TICK_S;
            let i = self.j_over_kt * self.profile.acc * self.rad_per_mm
                + self.kp * e
                + self.ki * self.integral
                + self.kd * ev;
            self.plant.step(i, TICK_S);
        }

        pub fn sample(&self, seg: usize) -> Sample {
            Sample {
                seg,
                pe_mm: self.plant.motor_mm(),
                ls_mm: self.plant.scale_mm(),
                dx_true_mm: self.plant.scale_true_mm() - self.plant.motor_true_mm(),
            }
        }

        /// Runs the moves in turn, logging every tick; segment numbers start at `seg0`.
        pub fn run_from(&mut self, seg0: usize, moves: &[Move]) -> Vec<Sample> {
            let mut log = Vec::new();
            for (k, m) in moves.iter().enumerate() {
                while !self.profile.advance(m.target_mm, m.v_mm_s, m.a_mm_s2) {
                    self.tick();
                    log.push(self.sample(seg0 + k));
                }
                for _ in 0..400 {
                    self.profile.acc = 0.0;
                    self.tick();
                    log.push(self.sample(seg0 + k));
                }
            }
            log
        }

        pub fn run(&mut self, moves: &[Move]) -> Vec<Sample> {
            self.run_from(0, moves)
        }
    }
}

mod analysis {
    //! Least squares on dx(x_PE) and the measures the tests assert on.
    use super::harness::Sample;
    use super::{PITCH_MM, PULLEY_REV_MM};

    /// Least squares by the normal equations (Gauss-Jordan with partial pivoting).
    pub fn lstsq(rows: &[Vec<f64>], y: &[f64]) -> Vec<f64> {
        let n = rows[0].len();
        let mut a = vec![vec![0.0; n + 1]; n];
        for (r, &yi) in rows.iter().zip(y) {
            for i in 0..n {
                for j in 0..n {
                    a[i][j] += r[i] * r[j];
                }
                a[i][n] += r[i] * yi;
            }
        }
        for c in 0..n {
            let p = (c..n)
                .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
                .unwrap();
            a.swap(c, p);
            let piv = a[c][c];
            a[c].iter_mut().for_each(|x| *x /= piv);
            let pivot = a[c].clone();
            for (i, row) in a.iter_mut().enumerate() {
                if i != c {
                    let f = row[c];
                    row.iter_mut().zip(&pivot).for_each(|(x, p)| *x -= f * p);
                }
            }
        }
        a.iter().map(|r| r[n]).collect()
    }

    fn basis(x: f64) -> Vec<f64> {
        let kt = core::f64::consts::TAU / PITCH_MM;
        let kp = core::f64::consts::TAU / PULLEY_REV_MM;
        vec![
            1.0,
            x,
            (kt * x).sin(),
            (kt * x).cos(),
            (kp * x).sin(),
            (kp * x).cos(),
        ]
    }

    /// A band edge: dx = c0 + m x + tooth-passing harmonic + once-per-pulley-turn term, fitted
    /// over a stretch of one pass.
    #[derive(Clone, Debug)]
    pub struct Edge {
        c: Vec<f64>,
        pub rms_residual_mm: f64,
    }

    impl Edge {
        pub fn fit(samples: &[Sample], lo_mm: f64, hi_mm: f64) -> Edge {
            let pts: Vec<&Sample> = samples
                .iter()
                .filter(|s| (lo_mm..=hi_mm).contains(&s.pe_mm))
                .collect();
            assert!(pts.len() > 100, "too few samples on [{lo_mm}, {hi_mm}]");
            let rows: Vec<Vec<f64>> = pts.iter().map(|s| basis(s.pe_mm)).collect();
            let y: Vec<f64> = pts.iter().map(|s| s.dx_mm()).collect();
            let mut e = Edge {
                c: lstsq(&rows, &y),
                rms_residual_mm: 0.0,
            };
            let ss: f64 = pts
                .iter()
                .map(|s| (s.dx_mm() - e.at(s.pe_mm)).powi(2))
                .sum();
            e.rms_residual_mm = (ss / pts.len() as f64).sqrt();
            e
        }

        pub fn at(&self, x_mm: f64) -> f64 {
            basis(x_mm).iter().zip(&self.c).map(|(b, c)| b * c).sum()
        }

        /// The straight part: dx at x = 0 and slope.
        pub fn line(&self) -> (f64, f64) {
            (self.c[0], self.c[1])
        }

        /// Amplitude of the tooth-passing harmonic.
        pub fn harmonic_mm(&self) -> f64 {
            self.c[2].hypot(self.c[3])
        }
    }

    /// The transition after a reversal.
    #[derive(Clone, Copy, Debug)]
    pub struct Transition {
        /// dx change over the first 0.5 mm of motor travel.
        pub jump_mm: f64,
        /// Motor travel until 90 % of that jump.
        pub jump_travel_mm: f64,
        /// dx change between 0.5 mm and 5 mm of motor travel, relative to the band edges.
        pub early_creep_mm: f64,
        /// Motor travel until half of what remains after the jump is crossed.
        pub half_mm: f64,
        /// Motor travel until dx is within 10 % of the band from the far edge.
        pub closing_mm: f64,
    }

    /// `pass`: samples of one move, from its reversal on; `far`: the edge being approached.
    pub fn transition(pass: &[Sample], far: &Edge, band_mm: f64) -> Transition {
        let x0 = pass[0].pe_mm;
        let dx0 = pass[0].dx_mm();
        let dir = (far.at(x0) - dx0).signum();
        let travel = |s: &Sample| (s.pe_mm - x0).abs();
        let at = |d: f64| {
            pass.iter()
                .find(|s| travel(s) >= d)
                .expect("pass long enough")
        };
        let jump = (at(0.5).dx_mm() - dx0) * dir;
        let jump_travel = travel(
            pass.iter()
                .find(|s| (s.dx_mm() - dx0) * dir >= 0.9 * jump)
                .unwrap(),
        );
        let gap = |s: &Sample| (far.at(s.pe_mm) - s.dx_mm()) * dir;
        let gap0 = gap(at(0.5));
        let first = |limit: f64| {
            pass.iter()
                .find(|s| travel(s) > 0.5 && gap(s) <= limit)
                .map_or(f64::NAN, travel)
        };
        Transition {
            jump_mm: jump,
            jump_travel_mm: jump_travel,
            early_creep_mm: gap0 - gap(at(5.0)),
            half_mm: first(0.5 * gap0),
            closing_mm: first(0.1 * band_mm),
        }
    }

    /// Mean dx in 1 mm bins of x_PE over [lo, hi).
    pub fn binned(samples: &[Sample], lo_mm: f64, hi_mm: f64) -> Vec<f64> {
        let n = (hi_mm - lo_mm).round() as usize;
        let mut sum = vec![0.0; n];
        let mut cnt = vec![0usize; n];
        for s in samples {
            let i = (s.pe_mm - lo_mm).floor();
            if i >= 0.0 && (i as usize) < n {
                sum[i as usize] += s.dx_mm();
                cnt[i as usize] += 1;
            }
        }
        sum.iter()
            .zip(&cnt)
            .map(|(s, &c)| if c > 0 { s / c as f64 } else { f64::NAN })
            .collect()
    }

    pub fn rms(v: impl Iterator<Item = f64>) -> f64 {
        let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
        (s / n as f64).sqrt()
    }
}

use analysis::{binned, rms, transition, Edge, Transition};
use harness::{mv, Drive, Move, Sample};

fn paper() -> PlantParams {
    PlantParams::paper_rig()
}

fn seg(log: &[Sample], i: usize) -> Vec<Sample> {
    log.iter().copied().filter(|s| s.seg == i).collect()
}

/// Forward 0 -> 420 mm, back to 0, forward to 200 mm: both band edges over 10..300 mm (each
/// after at least 120 mm in its direction) and one transition in each direction.
fn cycle(v: f64, a: f64) -> Vec<Move> {
    vec![mv(420.0, v, a), mv(0.0, v, a), mv(200.0, v, a)]
}

/// The section-4 figures of one `cycle` run.
struct Figures {
    /// Forward motion (x increasing): the lower edge.
    lower: Edge,
    /// Reverse motion: the upper edge.
    upper: Edge,
    /// Mean distance between the edges over 10..300 mm.
    band_mm: f64,
    /// Forward -> reverse at 420 mm.
    to_reverse: Transition,
    /// Reverse -> forward at 0 mm.
    to_forward: Transition,
}

impl Figures {
    fn of(log: &[Sample]) -> Figures {
        let lower = Edge::fit(&seg(log, 0), 10.0, 300.0);
        let upper = Edge::fit(&seg(log, 1), 10.0, 300.0);
        let band_mm = (10..300)
            .map(|x| upper.at(x as f64) - lower.at(x as f64))
            .sum::<f64>()
            / 290.0;
        Figures {
            to_reverse: transition(&seg(log, 1), &upper, band_mm),
            to_forward: transition(&seg(log, 2), &lower, band_mm),
            lower,
            upper,
            band_mm,
        }
    }

    fn run(params: &PlantParams, v: f64, a: f64, seed: u64) -> (Figures, Vec<Sample>) {
        let mut d = Drive::new(params, 0.0, seed);
        let log = d.run(&cycle(v, a));
        (Figures::of(&log), log)
    }

    fn print(&self, label: &str) {
        println!(
            "{label}: band {:.1} um; slope lower {:.6} upper {:.6}; harmonic {:.1} / {:.1} um; edge rms {:.1} / {:.1} um",
            self.band_mm * 1e3,
            self.lower.line().1,
            self.upper.line().1,
            self.lower.harmonic_mm() * 1e3,
            self.upper.harmonic_mm() * 1e3,
            self.lower.rms_residual_mm * 1e3,
            self.upper.rms_residual_mm * 1e3,
        );
        for (d, t) in [
            ("fwd->rev", &self.to_reverse),
            ("rev->fwd", &self.to_forward),
        ] {
            println!(
                "  {d}: jump {:.1} um within {:.3} mm; then {:.1} um by 5 mm; half-way {:.1} mm; closed (10 % of band) {:.1} mm",
                t.jump_mm * 1e3,
                t.jump_travel_mm,
                t.early_creep_mm * 1e3,
                t.half_mm,
                t.closing_mm
            );
        }
    }
}

fn within(what: &str, value: f64, lo: f64, hi: f64) {
    assert!(
        (lo..=hi).contains(&value),
        "{what} = {value} outside [{lo}, {hi}]"
    );
}

/// Section 4: band ~0.3 mm (Table 2: h = 0.34), forward on the lower edge, slope ~0.00106
/// (Table 2: m = 0.0010594), a 10 um harmonic at the tooth-passing period.
#[test]
fn band_slope_and_tooth_harmonic() {
    let (f, _) = Figures::run(&paper(), 20.0, 200.0, 1);
    f.print("v 20 mm/s, a 200 mm/s^2");
    within("band (mm)", f.band_mm, 0.28, 0.36);
    // Forward motion lies on the lower edge (the carriage lags), at every position.
    for x in (10..300).step_by(10) {
        let (lo, up) = (f.lower.at(x as f64), f.upper.at(x as f64));
        within("band at x (mm)", up - lo, 0.26, 0.38);
    }
    let (m_lo, m_up) = (f.lower.line().1, f.upper.line().1);
    within("lower-edge slope", m_lo, 0.0009, 0.0012);
    within("upper-edge slope", m_up, 0.0009, 0.0012);
    within("mean slope", 0.5 * (m_lo + m_up), 0.00100, 0.00112);
    within(
        "lower-edge harmonic (mm)",
        f.lower.harmonic_mm(),
        0.008,
        0.012,
    );
    within(
        "upper-edge harmonic (mm)",
        f.upper.harmonic_mm(),
        0.008,
        0.012,
    );
    // What the fit leaves: Abbe terms, guide-friction ripple, span stiffness, noise, counts.
    within(
        "lower-edge residual (mm)",
        f.lower.rms_residual_mm,
        0.0003,
        0.004,
    );
    within(
        "upper-edge residual (mm)",
        f.upper.rms_residual_mm,
        0.0003,
        0.004,
    );
}

/// Section 4: after a reversal a fast transition of ~0.12 mm (Table 2: h_g = 0.11) within the
/// first ~0.1-0.2 mm of motor travel, then a slow one over tens of millimetres (Table 2's slopes
/// and decay lengths suggest 20-100 mm).
#[test]
fn reversal_fast_jump_then_slow_creep() {
    let (f, _) = Figures::run(&paper(), 20.0, 200.0, 1);
    f.print("v 20 mm/s, a 200 mm/s^2");
    for t in [&f.to_reverse, &f.to_forward] {
        within("fast jump (mm)", t.jump_mm, 0.09, 0.15);
        within("motor travel of the jump (mm)", t.jump_travel_mm, 0.05, 0.2);
        // Right after the jump the transition is slow: well under 1 um per mm.
        within("dx change 0.5..5 mm (mm)", t.early_creep_mm, 0.0, 0.03);
        within("half-way (mm of travel)", t.half_mm, 10.0, 50.0);
        within("closing distance (mm of travel)", t.closing_mm, 25.0, 100.0);
        // The jump plus the slow part spans the band.
        assert!(t.jump_mm < 0.6 * f.band_mm);
    }
}

/// The slow transition is creep, and it comes from bristle renewal: with eq. 11 alone
/// (`renewal_factor = 0`) the belt stays wherever the fast transient left it in the tooth gap.
#[test]
fn creep_needs_bristle_renewal() {
    let (f, _) = Figures::run(&paper(), 20.0, 200.0, 1);
    let mut p = paper();
    p.friction.renewal_factor = 0.0;
    let mut d = Drive::new(&p, 0.0, 1);
    let log = d.run(&cycle(20.0, 200.0));
    let rev = seg(&log, 1);
    // Reversed at 420 mm: after 150 mm of reverse travel dx is still far from the upper edge.
    let s = rev.iter().find(|s| s.pe_mm <= 270.0).unwrap();
    let gap = f.upper.at(s.pe_mm) - s.dx_mm();
    println!(
        "eq. 11 alone: 150 mm after the reversal dx is {:.1} um below the upper edge",
        gap * 1e3
    );
    within(
        "gap left without renewal (fraction of band)",
        gap / f.band_mm,
        0.3,
        0.8,
    );
    let t = transition(&rev, &f.upper, f.band_mm);
    within("jump without renewal (mm)", t.jump_mm, 0.09, 0.15);
}

/// Section 4, Figs. 11-12: twelve repeated runs overlay. The spread is the non-repeatable floor
/// under every model's error: a few micrometres.
#[test]
fn twelve_runs_overlay() {
    let runs: Vec<Vec<Sample>> = (0..12)
        .map(|seed| {
            let mut d = Drive::new(&paper(), 0.0, 100 + seed);
            d.run(&cycle(20.0, 200.0))
        })
        .collect();
    // (pass, from, to): edges first, then the two transitions.
    let stretches = [
        (0, 10.0, 300.0),
        (1, 10.0, 300.0),
        (1, 320.0, 420.0),
        (2, 1.0, 100.0),
    ];
    let mut spread = Vec::new();
    let mut sd = Vec::new();
    for &(pass, lo, hi) in &stretches {
        let curves: Vec<Vec<f64>> = runs.iter().map(|r| binned(&seg(r, pass), lo, hi)).collect();
        let (mut sp, mut s) = (Vec::new(), Vec::new());
        for b in 0..curves[0].len() {
            let v: Vec<f64> = curves.iter().map(|c| c[b]).collect();
            let mean = v.iter().sum::<f64>() / 12.0;
            sp.push(
                v.iter().fold(f64::MIN, |a, &x| a.max(x))
                    - v.iter().fold(f64::MAX, |a, &x| a.min(x)),
            );
            s.push((v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 11.0).sqrt());
        }
        spread.push(sp);
        sd.push(s);
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let max = |v: &[f64]| v.iter().fold(0.0f64, |a, &x| a.max(x));
    let edge_spread = 0.5 * (mean(&spread[0]) + mean(&spread[1]));
    let edge_sd = 0.5 * (mean(&sd[0]) + mean(&sd[1]));
    let edge_max = max(&spread[0]).max(max(&spread[1]));
    let tr_spread = 0.5 * (mean(&spread[2]) + mean(&spread[3]));
    let tr_sd = 0.5 * (mean(&sd[2]) + mean(&sd[3]));
    let tr_max = max(&spread[2]).max(max(&spread[3]));
    println!(
        "12 runs, 1 mm bins: edges spread mean {:.1} um (max {:.1}), sd {:.2} um; transitions spread mean {:.1} um (max {:.1}), sd {:.2} um",
        edge_spread * 1e3,
        edge_max * 1e3,
        edge_sd * 1e3,
        tr_spread * 1e3,
        tr_max * 1e3,
        tr_sd * 1e3
    );
    within("edge spread (mm)", edge_spread, 0.0005, 0.006);
    within("edge max spread (mm)", edge_max, 0.001, 0.012);
    within("transition spread (mm)", tr_spread, 0.001, 0.02);
    within("transition max spread (mm)", tr_max, 0.002, 0.04);
}

/// Fig. 13: steady velocity has only a minor influence on dx.
#[test]
fn velocity_has_minor_influence() {
    let p = paper();
    let results: Vec<(f64, Figures, Vec<Sample>)> = [5.0, 10.0, 20.0, 40.0, 80.0]
        .iter()
        .map(|&v| {
            let (f, log) = Figures::run(&p, v, 200.0, 1);
            f.print(&format!("v {v} mm/s"));
            (v, f, log)
        })
        .collect();
    let reference = &results[2];
    let ref_lower = binned(&seg(&reference.2, 0), 10.0, 300.0);
    let ref_upper = binned(&seg(&reference.2, 1), 10.0, 300.0);
    for (v, f, log) in &results {
        let d_lower = rms(binned(&seg(log, 0), 10.0, 300.0)
            .iter()
            .zip(&ref_lower)
            .map(|(a, b)| a - b));
        let d_upper = rms(binned(&seg(log, 1), 10.0, 300.0)
            .iter()
            .zip(&ref_upper)
            .map(|(a, b)| a - b));
        println!(
            "v {v}: edges differ from v 20 by {:.2} / {:.2} um rms",
            d_lower * 1e3,
            d_upper * 1e3
        );
        within("edge difference (mm rms)", d_lower.max(d_upper), 0.0, 0.004);
        within(
            "band / band at 20 mm/s",
            f.band_mm / reference.1.band_mm,
            0.97,
            1.03,
        );
        for (t, r) in [
            (&f.to_reverse, &reference.1.to_reverse),
            (&f.to_forward, &reference.1.to_forward),
        ] {
            within(
                "jump - jump at 20 mm/s (mm)",
                t.jump_mm - r.jump_mm,
                -0.03,
                0.03,
            );
            within(
                "closing / closing at 20 mm/s",
                t.closing_mm / r.closing_mm,
                0.75,
                1.25,
            );
            within(
                "half-way / half-way at 20 mm/s",
                t.half_mm / r.half_mm,
                0.7,
                1.3,
            );
        }
    }
}

/// Fig. 14: acceleration (inertial forces) has no considerable effect on the closing distances.
#[test]
fn acceleration_has_minor_influence() {
    let p = paper();
    let (reference, _) = Figures::run(&p, 20.0, 200.0, 1);
    for a in [50.0, 500.0, 1000.0] {
        let (f, _) = Figures::run(&p, 20.0, a, 1);
        f.print(&format!("a {a} mm/s^2"));
        for (t, r) in [
            (&f.to_reverse, &reference.to_reverse),
            (&f.to_forward, &reference.to_forward),
        ] {
            within(
                "jump - jump at 200 mm/s^2 (mm)",
                t.jump_mm - r.jump_mm,
                -0.03,
                0.05,
            );
            within(
                "closing / closing at 200 mm/s^2",
                t.closing_mm / r.closing_mm,
                0.75,
                1.25,
            );
        }
    }
}

/// Fig. 15: reversals at intermediate points stay inside the band and close on its edges.
#[test]
fn intermediate_reversals_stay_in_the_band() {
    let p = paper();
    let (f, _) = Figures::run(&p, 20.0, 200.0, 1);
    // On the lower edge at 200 mm: back by r mm, then forward to 290 mm.
    let mut base = Drive::new(&p, 0.0, 1);
    base.run(&[mv(200.0, 20.0, 200.0)]);
    for r in [0.5, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0] {
        let mut d = base.clone();
        let log = d.run(&[mv(200.0 - r, 20.0, 200.0), mv(290.0, 20.0, 200.0)]);
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for s in &log {
            let (e_lo, e_up) = (f.lower.at(s.pe_mm), f.upper.at(s.pe_mm));
            lo = lo.min(s.dx_mm() - e_lo);
            hi = hi.max(s.dx_mm() - e_up);
        }
        let back = seg(&log, 1);
        let t = transition(&back, &f.lower, f.band_mm);
        let end = back.iter().find(|s| s.pe_mm >= 285.0).unwrap();
        let at_end = end.dx_mm() - f.lower.at(end.pe_mm);
        println!(
            "back {r:4} mm: excursion below lower edge {:.1} um, above upper edge {:.1} um; return jump {:.1} um, closing {:.1} mm; at 285 mm {:.1} um off the lower edge",
            -lo * 1e3,
            hi * 1e3,
            t.jump_mm * 1e3,
            t.closing_mm,
            at_end * 1e3
        );
        // The band is an envelope; only the tooth re-engaging after a short reversal overshoots
        // it a little (impact on the flank).
        within("excursion below the lower edge (mm)", -lo, -1.0, 0.02);
        within("excursion above the upper edge (mm)", hi, -1.0, 0.02);
        within(
            "distance from the lower edge at 285 mm (mm)",
            at_end.abs(),
            0.0,
            0.005,
        );
    }
}

/// Fig. 4: pulley-belt friction damps the response; without it (the paper's undamped model) the
/// teeth are the only coupling, the carriage waits for the far flank, is hit by it and rings.
#[test]
fn fig4_belt_friction_damps_the_response() {
    let mut out = Vec::new();
    for friction in [true, false] {
        let mut p = paper();
        p.friction.enabled = friction;
        let mut d = Drive::new(&p, 100.0, 1);
        d.run(&[mv(102.0, 20.0, 200.0)]);
        // Reverse at 20 mm/s; log motor (nominal) and carriage.
        let mut trace = Vec::new();
        for _ in 0..1600 {
            d.profile.advance(90.0, 20.0, 200.0);
            d.tick();
            trace.push((
                d.plant.motor_true_mm(),
                d.plant.carriage_velocity_mm_s(),
                d.profile.vel,
            ));
        }
        let start = trace.iter().position(|o| o.1.abs() > 0.5).unwrap();
        let lost_mm = trace[0].0 - trace[start].0;
        let err = |a: usize, b: usize| rms(trace[start + a..start + b].iter().map(|o| o.1 - o.2));
        let peak = trace[start..start + 400]
            .iter()
            .map(|o| (o.1 - o.2).abs())
            .fold(0.0, f64::max);
        let (e1, e2) = (err(0, 400), err(400, 800));
        println!(
            "belt friction {friction}: carriage moves after {lost_mm:.3} mm of motor travel; |v - v_ref| peak {peak:.2} mm/s, rms {e1:.2} mm/s (first 0.2 s), {e2:.2} mm/s (next 0.2 s)"
        );
        out.push((lost_mm, peak, e1, e2));
    }
    let (damped, undamped) = (out[0], out[1]);
    // Without friction nothing drives the carriage across the tooth gap (~2 h = 0.28 mm).
    within("lost motion, undamped (mm)", undamped.0, 0.25, 0.35);
    within("lost motion, damped (mm)", damped.0, 0.0, 0.15);
    assert!(
        undamped.1 > 1.5 * damped.1,
        "peak velocity error {:?} vs {:?}",
        undamped,
        damped
    );
    assert!(
        undamped.2 > 3.0 * damped.2,
        "rms velocity error {:?} vs {:?}",
        undamped,
        damped
    );
    assert!(
        undamped.3 > 1.5 * damped.3,
        "later rms velocity error {:?} vs {:?}",
        undamped,
        damped
    );
}

/// The default 20 us substep against 5 us: the same dx to well under a scale count.
#[test]
fn substep_convergence() {
    let moves = [
        mv(60.0, 20.0, 200.0),
        mv(0.0, 20.0, 200.0),
        mv(30.0, 80.0, 1000.0),
    ];
    let run = |h: f64| {
        let mut p = paper();
        p.integration.max_substep_s = h;
        let mut d = Drive::new(&p, 0.0, 1);
        d.run(&moves)
    };
    let fine = run(5e-6);
    let default = run(paper().integration.max_substep_s);
    assert_eq!(fine.len(), default.len());
    let max = fine
        .iter()
        .zip(&default)
        .map(|(a, b)| (a.dx_true_mm - b.dx_true_mm).abs())
        .fold(0.0, f64::max);
    let rms_d = rms(fine
        .iter()
        .zip(&default)
        .map(|(a, b)| a.dx_true_mm - b.dx_true_mm));
    println!(
        "20 us vs 5 us substeps: dx differs by {:.3} um max, {:.3} um rms",
        max * 1e3,
        rms_d * 1e3
    );
    within("max dx difference (mm)", max, 0.0, 0.001);
}
