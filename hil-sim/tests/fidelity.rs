//! Fidelity of the `paper-rig` plant against the paper's section 4 (and Fig. 4 of section 2).
//!
//! The plant is driven the way the paper drove the rig: a trapezoidal velocity profile on the
//! motor, tracked closely by a position loop, while `dx = x_LS - x_PE` is logged against `x_PE`.
//! The loop here is a test-only f64 harness (trapezoid + PID on the motor angle); the firmware's
//! own trajectory and PID live in `estimator-core`.
//!
//! Figures are printed; run `cargo test -p hil-sim --release --test fidelity -- --nocapture`.

use hil_sim::{Plant, PlantParams};

/// Control tick of the harness (the firmware's 2 kHz).
const TICK_S: f64 = 5e-4;
/// Tooth pitch of the belt: the period of the form-error harmonic in carriage travel.
const PITCH_MM: f64 = 5.08;

mod harness {
    //! Test-only closed loop: trapezoidal profile + PID on the motor angle, current out.
    use super::TICK_S;
    use hil_sim::{Plant, PlantParams};

    /// Trapezoidal point-to-point profile in nominal millimetres.
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
        pub t_s: f64,
        /// Index of the move this tick belongs to.
        pub seg: usize,
        /// Reference (nominal motor) position.
        pub ref_mm: f64,
        /// x_PE.
        pub pe_mm: f64,
        /// x_LS.
        pub ls_mm: f64,
        /// True carriage position.
        pub x_mm: f64,
        /// dx without quantisation and noise.
        pub dx_true_mm: f64,
    }

    impl Sample {
        pub fn dx_mm(&self) -> f64 {
            self.ls_mm - self.pe_mm
        }
    }

    /// A move: go to `target_mm` with speed `v_mm_s` and acceleration `a_mm_s2`, then dwell.
    #[derive(Clone, Copy, Debug)]
    pub struct Move {
        pub target_mm: f64,
        pub v_mm_s: f64,
        pub a_mm_s2: f64,
        pub dwell_s: f64,
    }

    pub fn mv(target_mm: f64, v_mm_s: f64, a_mm_s2: f64) -> Move {
        Move { target_mm, v_mm_s, a_mm_s2, dwell_s: 0.2 }
    }

    /// Plant plus PID on the motor angle, with acceleration feedforward.
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
            let plant = Plant::new(params, start_mm, seed);
            let rad_per_count = core::f64::consts::TAU / (4.0 * params.encoder.lines as f64);
            let rad_per_mm = plant.counts_per_mm() * rad_per_count;
            // Inertia at the motor: rotor + pulley + carriage and belt through the drive.
            let r = params.nominal_radius_m() / params.gearbox.ratio;
            let j = params.motor.rotor_inertia_kg_m2
                + params.gearbox.output_inertia_kg_m2 / params.gearbox.ratio.powi(2)
                + (params.carriage.mass_kg + params.belt.lumped_mass_kg) * r * r;
            let kt = params.motor.torque_constant_nm_per_a;
            // 30 Hz position loop, damping 0.8, integral a decade lower.
            let w = core::f64::consts::TAU * 30.0;
            let theta0 = plant.motor_counts() as f64 * rad_per_count;
            let pos0 = theta0 / rad_per_mm;
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
                profile: Profile { pos: pos0, vel: 0.0, acc: 0.0 },
            }
        }

        /// One control tick: sample, control, step the plant.
        pub fn tick(&mut self) {
            let theta = self.plant.motor_counts() as f64 * self.rad_per_count;
            // Velocity from counts, low-passed (tau = 1 ms) against quantisation noise.
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
                t_s: self.plant.time_s(),
                seg,
                ref_mm: self.profile.pos,
                pe_mm: self.plant.motor_mm(),
                ls_mm: self.plant.scale_mm(),
                x_mm: self.plant.carriage_mm(),
                dx_true_mm: self.plant.scale_true_mm() - self.plant.motor_true_mm(),
            }
        }

        /// Runs the moves in turn, logging every tick.
        pub fn run(&mut self, moves: &[Move]) -> Vec<Sample> {
            let mut log = Vec::new();
            for (seg, m) in moves.iter().enumerate() {
                while !self.profile.advance(m.target_mm, m.v_mm_s, m.a_mm_s2) {
                    self.tick();
                    log.push(self.sample(seg));
                }
                let n = (m.dwell_s / TICK_S).round() as usize;
                for _ in 0..n {
                    self.profile.acc = 0.0;
                    self.tick();
                    log.push(self.sample(seg));
                }
            }
            log
        }
    }
}

mod analysis {
    //! Least squares on dx(x_PE) and the measures of the fidelity tests.
    use super::harness::Sample;
    use super::PITCH_MM;

    /// Solves the normal equations of a small least-squares problem (Gauss-Jordan).
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
            let p = (c..n).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs())).unwrap();
            a.swap(c, p);
            let piv = a[c][c];
            for j in c..=n {
                a[c][j] /= piv;
            }
            for i in 0..n {
                if i != c {
                    let f = a[i][c];
                    for j in c..=n {
                        a[i][j] -= f * a[c][j];
                    }
                }
            }
        }
        a.iter().map(|r| r[n]).collect()
    }

    /// A band edge: dx ~ c0 + m x + tooth-passing harmonic, fitted over a stretch of one pass.
    #[derive(Clone, Copy, Debug)]
    pub struct Edge {
        pub offset_mm: f64,
        pub slope: f64,
        pub harmonic_mm: f64,
        sin: f64,
        cos: f64,
        pub rms_residual_mm: f64,
    }

    impl Edge {
        pub fn fit(samples: &[Sample], lo_mm: f64, hi_mm: f64) -> Edge {
            let k = core::f64::consts::TAU / PITCH_MM;
            let pts: Vec<&Sample> = samples.iter().filter(|s| (lo_mm..=hi_mm).contains(&s.pe_mm)).collect();
            assert!(pts.len() > 100, "too few samples on [{lo_mm}, {hi_mm}]");
            let rows: Vec<Vec<f64>> =
                pts.iter().map(|s| vec![1.0, s.pe_mm, (k * s.pe_mm).sin(), (k * s.pe_mm).cos()]).collect();
            let y: Vec<f64> = pts.iter().map(|s| s.dx_mm()).collect();
            let c = lstsq(&rows, &y);
            let mut e = Edge {
                offset_mm: c[0],
                slope: c[1],
                harmonic_mm: c[2].hypot(c[3]),
                sin: c[2],
                cos: c[3],
                rms_residual_mm: 0.0,
            };
            let ss: f64 = pts.iter().map(|s| (s.dx_mm() - e.at(s.pe_mm)).powi(2)).sum();
            e.rms_residual_mm = (ss / pts.len() as f64).sqrt();
            e
        }

        pub fn at(&self, x_mm: f64) -> f64 {
            let k = core::f64::consts::TAU / PITCH_MM;
            self.offset_mm + self.slope * x_mm + self.sin * (k * x_mm).sin() + self.cos * (k * x_mm).cos()
        }
    }

    /// The transition after the reversal that starts `pass`: fast jump, its length, slow part.
    #[derive(Clone, Copy, Debug)]
    pub struct Transition {
        /// dx change over the first 0.5 mm of motor travel.
        pub jump_mm: f64,
        /// Motor travel until 90 % of that jump.
        pub jump_travel_mm: f64,
        /// Motor travel until dx is within 10 % of the band of the far edge.
        pub length_mm: f64,
        /// Motor travel until half of what remains after the jump is done.
        pub half_mm: f64,
    }

    /// `pass`: samples of one move, starting at the reversal. `far`: the edge being approached;
    /// `band_mm`: its distance from the near edge.
    pub fn transition(pass: &[Sample], far: &Edge, band_mm: f64) -> Transition {
        let x0 = pass[0].pe_mm;
        let dx0 = pass[0].dx_mm();
        let dir = (far.at(x0) - dx0).signum();
        let travel = |s: &Sample| (s.pe_mm - x0).abs();
        let at = |d: f64| pass.iter().find(|s| travel(s) >= d).expect("pass long enough");
        let jump = (at(0.5).dx_mm() - dx0) * dir;
        let jump_travel = travel(pass.iter().find(|s| (s.dx_mm() - dx0) * dir >= 0.9 * jump).unwrap());
        let gap = |s: &Sample| (far.at(s.pe_mm) - s.dx_mm()) * dir;
        let gap0 = gap(at(0.5));
        let half = pass.iter().find(|s| travel(s) > 0.5 && gap(s) <= 0.5 * gap0).map_or(f64::NAN, travel);
        let length = pass.iter().find(|s| travel(s) > 0.5 && gap(s) <= 0.1 * band_mm).map_or(f64::NAN, travel);
        Transition { jump_mm: jump, jump_travel_mm: jump_travel, length_mm: length, half_mm: half }
    }

    /// Mean of dx in 1 mm bins of x_PE over [lo, hi) (NaN where a bin is empty).
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
        sum.iter().zip(&cnt).map(|(s, &c)| if c > 0 { s / c as f64 } else { f64::NAN }).collect()
    }
}

use analysis::{binned, transition, Edge, Transition};
use harness::{mv, Drive, Move, Sample};

fn seg(log: &[Sample], i: usize) -> Vec<Sample> {
    log.iter().copied().filter(|s| s.seg == i).collect()
}

/// Forward 0 -> 420 mm, back to 0, forward to 200 mm: both edges over 0..300 mm and a
/// transition in each direction.
fn cycle(v: f64, a: f64) -> Vec<Move> {
    vec![mv(420.0, v, a), mv(0.0, v, a), mv(200.0, v, a)]
}

struct Figures {
    lower: Edge,
    upper: Edge,
    band_mm: f64,
    to_reverse: Transition,
    to_forward: Transition,
}

fn figures(log: &[Sample]) -> Figures {
    let fwd = seg(log, 0);
    let rev = seg(log, 1);
    let fwd2 = seg(log, 2);
    let lower = Edge::fit(&fwd, 10.0, 300.0);
    let upper = Edge::fit(&rev, 10.0, 300.0);
    let band_mm = upper.offset_mm - lower.offset_mm + (upper.slope - lower.slope) * 155.0;
    Figures {
        lower,
        upper,
        band_mm,
        to_reverse: transition(&rev, &upper, band_mm),
        to_forward: transition(&fwd2, &lower, band_mm),
    }
}

fn print(label: &str, f: &Figures) {
    println!(
        "{label}: band {:.1} um, slopes {:.5} / {:.5}, harmonic {:.1} / {:.1} um, edge rms {:.1} / {:.1} um",
        f.band_mm * 1e3,
        f.lower.slope,
        f.upper.slope,
        f.lower.harmonic_mm * 1e3,
        f.upper.harmonic_mm * 1e3,
        f.lower.rms_residual_mm * 1e3,
        f.upper.rms_residual_mm * 1e3,
    );
    for (d, t) in [("fwd->rev", &f.to_reverse), ("rev->fwd", &f.to_forward)] {
        println!(
            "  {d}: jump {:.1} um within {:.3} mm, half-way {:.1} mm, 90 % {:.1} mm",
            t.jump_mm * 1e3,
            t.jump_travel_mm,
            t.half_mm,
            t.length_mm
        );
    }
}

#[test]
fn explore() {
    let p = match std::env::var("PLANT_PRESET") {
        Ok(f) => PlantParams::from_toml_str(&std::fs::read_to_string(f).unwrap()).unwrap(),
        Err(_) => PlantParams::paper_rig(),
    };
    for (v, a) in [(5.0, 200.0), (20.0, 200.0), (80.0, 200.0), (20.0, 50.0), (40.0, 1000.0)] {
        let t0 = std::time::Instant::now();
        let mut d = Drive::new(&p, 0.0, 1);
        let log = d.run(&cycle(v, a));
        let wall = t0.elapsed().as_secs_f64();
        println!("simulated {:.1} s in {:.2} s: {:.0}x", d.plant.time_s(), wall, d.plant.time_s() / wall);
        let f = figures(&log);
        print(&format!("v={v} a={a}"), &f);
    }
}

#[test]
fn substeps() {
    let mut base = None;
    for h in [5e-6, 1e-5, 2e-5, 2.5e-5] {
        let mut p = PlantParams::paper_rig();
        p.integration.max_substep_s = h;
        let t0 = std::time::Instant::now();
        let mut d = Drive::new(&p, 0.0, 1);
        let log = d.run(&[mv(60.0, 20.0, 200.0), mv(0.0, 20.0, 200.0), mv(30.0, 80.0, 1000.0)]);
        let wall = t0.elapsed().as_secs_f64();
        let dx: Vec<f64> = log.iter().map(|s| s.dx_true_mm).collect();
        let b = base.get_or_insert(dx.clone());
        let n = b.len().min(dx.len());
        let err = (0..n).map(|i| (dx[i] - b[i]).abs()).fold(0.0, f64::max);
        println!("h {h:e}: {:.0}x, max |ddx| vs 5 us {:.3} um, n {} / {}", d.plant.time_s() / wall, err * 1e3, dx.len(), b.len());
    }
}

#[test]
fn trace() {
    let p = PlantParams::paper_rig();
    let mut d = Drive::new(&p, 0.0, 1);
    d.run(&[mv(150.0, 20.0, 200.0)]);
    let x0 = d.plant.motor_mm();
    let dx0 = d.plant.delta_x_mm();
    let marks = [0.0, 0.02, 0.05, 0.08, 0.1, 0.13, 0.16, 0.2, 0.3, 0.4, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 80.0, 100.0, 140.0];
    let mut k = 0;
    while !d.profile.advance(0.0, 20.0, 200.0) {
        d.tick();
        let tr = x0 - d.plant.motor_mm();
        if k < marks.len() && tr >= marks[k] {
            let b = d.plant.belt();
            println!(
                "{:7.3} dx {:7.1} um  x {:8.4} mesh {:7.1} um z {:6.1} um mu {:.4} Ft {:6.2} Ff {:6.2} F2-F1 {:6.2} u {:.3} mm/s",
                tr,
                (d.plant.delta_x_mm() - dx0) * 1e3,
                d.plant.carriage_mm(),
                b.mesh_offset_m * 1e6,
                b.bristle_m * 1e6,
                b.mu,
                b.tooth_n,
                b.friction_n,
                b.span2_n - b.span1_n,
                b.slip_m_per_s * 1e3
            );
            k += 1;
        }
    }
}
