//! Experiment (README, "Machines drawn at random"): Model 4 fitted on the motor current minus the
//! reflected rotor's share, `J ratio / (r kt)` amperes per m/s² times the set-point's acceleration
//! (the plant's true inertia; the acceleration from the set-point's whole counts, a second
//! difference over +-W ticks: not causal, an upper bound). The drive cannot run this as it is.
//!
//! `cargo run --profile ci -p hil-sim --example rotor -- [MACHINE] [W]`: MACHINE 0 is the paper
//! rig, N the N-th machine drawn at random (`generalise::drawn_plant`); W defaults to 10. Prints
//! Model 4's calibration fit and RMS per held-out workload for no, half and the whole share.
#![allow(clippy::print_stdout)]
use estimator_core::fixed::types::I16F16;
use hil_sim::run::Trace;
use hil_sim::{eval, PlantParams};

fn shifted(t: &Trace, k_a_per_m_s2: f64, w: usize) -> Trace {
    let mut u = t.clone();
    let n = t.records.len();
    let s = |i: usize| t.records[i].setpoint_counts.0 as f64;
    for i in 0..n {
        let a = if i >= w && i + w < n {
            (s(i + w) - 2.0 * s(i) + s(i - w)) / (w * w) as f64 * 2000.0 * 2000.0
                / t.counts_per_mm
                / 1000.0
        } else {
            0.0
        };
        let c = t.records[i].out.current_a.to_num::<f64>() - k_a_per_m_s2 * a;
        u.records[i].out.current_a = I16F16::from_num(c);
    }
    u
}

fn main() {
    let which: u64 = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let w: usize = std::env::args()
        .nth(2)
        .and_then(|s| s.parse().ok())
        .unwrap_or(10);
    let plant = if which == 0 {
        PlantParams::paper_rig()
    } else {
        hil_sim::generalise::drawn_plant(which)
    };
    let r = plant.pulley.teeth as f64 * plant.belt.pitch_m / std::f64::consts::TAU;
    let k = plant.motor.rotor_inertia_kg_m2 * plant.gearbox.ratio
        / (r * plant.motor.torque_constant_nm_per_a);
    println!("{} k = {k:.3} A per m/s^2", plant.name());
    let cal_traces =
        eval::record_calibration(&plant, eval::CALIBRATION_PLAN_SEED, &[], &mut |_, _| {}).unwrap();
    let held_traces: Vec<Trace> = hil_sim::generalise::probe_set(&plant, 11)
        .unwrap()
        .into_iter()
        .map(|(_, t)| t)
        .collect();
    for kk in [0.0, 0.5 * k, k] {
        let cal = hil_sim::calibrate::calibrate(
            &cal_traces
                .iter()
                .map(|t| shifted(t, kk, w))
                .collect::<Vec<_>>(),
            &plant.rig(),
            &mut |_, _| {},
        )
        .unwrap();
        let coeffs = cal.params.build(&plant.rig()).unwrap();
        let mut line = format!("k {kk:.3}: fit {:.1} |", cal.fit_rms_um[3].1);
        let mut ms = 0.0;
        let mut m = 0;
        for t in &held_traces {
            let t2 = shifted(t, kk, w);
            let est = eval::estimates(&t2, &coeffs);
            let tab = eval::table3(&t2, &est);
            let v = tab.iter().find(|e| e.0 == "model4").unwrap().1.rms_um;
            line += &format!(" {} {v:.1}", t.scenario);
            if t.scenario.ends_with("-11") {
                ms += v * v;
                m += 1;
            }
        }
        println!("{line} | held-out ms {:.1}", (ms / m as f64).sqrt());
    }
}
