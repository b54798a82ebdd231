//! How much of Model 4's residual one more state would explain: replays the plant alongside each
//! recording (same scenario, same seed, the recorded currents), reads its true mesh offset
//! `P - b` tick by tick, and adds it to Model 4's least-squares fit as one more term. A
//! measurement for the README ("Why this structure"), not part of the product: the drive never
//! sees the plant's state.
//!
//! `cargo run --profile ci -p hil-sim --example oracle [plant-name-part]` prints, for Model 4's
//! terms alone, with the true offset and with the span tension too: the fit on the calibration
//! data and the RMS of e on fig18, zigzag, accelerations and one generated workload of every
//! class (seed 11), all held out of the calibration.
//!
//! As a model rather than the truth: `ORACLE_REPLAY_SEED=N` replays with the seed moved by N
//! (the plant's run-to-run draws of friction, bristles and pitch differ), `ORACLE_REPLAY_PLANT=
//! NAME` with another built-in plant's parameters. Either replay is driven open loop by the
//! recorded currents, so it also prints how far its motor drifts from the recorded encoder.
//! `ORACLE_REPLAY_SCALE=field*factor,...` scales the replay's parameters (`mass`, `preload`,
//! `rigidity`, `tooth`, `mu`, `sigma0`, `guide`, `gap`): how much a model's parameters may be
//! off. `ORACLE_REPLAY_TIE=kp,kd` ties the replay's motor to the recorded encoder by a
//! correction current `kp e + kd de/dt` (e the encoder less the replay's motor, um and um/tick;
//! A per um): an observer, not an open-loop model.
#![allow(clippy::print_stdout)]

use estimator_core::model::ModelParams;
use estimator_core::reference::Reference;
use estimator_core::rig::Rig;
use hil_sim::calibrate::model4_row;
use hil_sim::eval;
use hil_sim::run::Trace;
use hil_sim::scenario::Scenario;
use hil_sim::tables::NormalEquations;
use hil_sim::{Plant, PlantParams};

/// One recording with the plant's state beside it.
struct Run {
    name: String,
    /// Model 4's terms (the observer's offset included), one row per tick.
    terms: Vec<Vec<f64>>,
    dx_um: Vec<f64>,
    offset_um: Vec<f64>,
    span_n: Vec<f64>,
    /// The replay's motor less the recorded encoder, um (0 when replayed as recorded).
    drift_um: Vec<f64>,
}

fn replay(t: &Trace, s: &Scenario, plant: &PlantParams, params: &ModelParams, rig: &Rig) -> Run {
    let shift: u64 = std::env::var("ORACLE_REPLAY_SEED")
        .ok()
        .map_or(0, |v| v.parse().expect("ORACLE_REPLAY_SEED: an integer"));
    let mut model = match std::env::var("ORACLE_REPLAY_PLANT") {
        Ok(n) => hil_sim::generalise::plant_named(Some(&n))
            .expect("built-in plants")
            .expect("ORACLE_REPLAY_PLANT: a built-in plant's name"),
        Err(_) => plant.clone(),
    };
    for item in std::env::var("ORACLE_REPLAY_SCALE")
        .unwrap_or_default()
        .split(',')
    {
        let Some((field, factor)) = item.split_once('*') else {
            continue;
        };
        let f: f64 = factor.parse().expect("ORACLE_REPLAY_SCALE: field*factor");
        match field {
            "mass" => model.carriage.mass_kg *= f,
            "preload" => model.belt.preload_n *= f,
            "rigidity" => model.belt.axial_rigidity_n *= f,
            "tooth" => model.belt.tooth_stiffness_n_per_m *= f,
            "mu" => {
                model.friction.mu_kinetic *= f;
                model.friction.mu_static *= f;
            }
            "sigma0" => model.friction.sigma0_per_m *= f,
            "guide" => model.carriage.coulomb_n *= f,
            "gap" => model.belt.tooth_half_gap_m *= f,
            _ => panic!("ORACLE_REPLAY_SCALE: no field {field:?}"),
        }
    }
    let mut p = Plant::new(&model, s.start_mm, t.seed.wrapping_add(shift)).expect("plant");
    let tie: (f64, f64) = std::env::var("ORACLE_REPLAY_TIE")
        .ok()
        .map_or((0.0, 0.0), |v| {
            let (a, b) = v.split_once(',').expect("ORACLE_REPLAY_TIE: kp,kd");
            (a.parse().expect("kp"), b.parse().expect("kd"))
        });
    let cpm = rig.counts_per_mm();
    let x0 = t.records[0].motor_counts.0;
    let p0 = p.motor_counts();
    let mut m = Reference::new(params, rig, t.records[0].motor_counts.0).expect("reference");
    let mut run = Run {
        name: t.scenario.clone(),
        terms: Vec::new(),
        dx_um: Vec::new(),
        offset_um: Vec::new(),
        span_n: Vec::new(),
        drift_um: Vec::new(),
    };
    for (k, r) in t.records.iter().enumerate() {
        let b = p.belt();
        run.offset_um.push(b.mesh_offset_m * 1e6);
        run.span_n.push(b.span2_n - b.span1_n);
        let recorded = f64::from(r.motor_counts.0.wrapping_sub(x0));
        run.drift_um
            .push(((p.motor_counts() - p0) as f64 - recorded) / cpm * 1000.0);
        let current = r.out.current_a.to_num::<f64>();
        let (_, f) = m.model4_step(r.motor_counts.0, current);
        let mut row = model4_row(&f, cpm).to_vec();
        row.push(f.slip_um);
        run.terms.push(row);
        run.dx_um.push(t.dx_um(k));
        let err_um = -run.drift_um[k];
        let prev_um = if k > 0 { -run.drift_um[k - 1] } else { err_um };
        p.step(
            current + tie.0 * err_um + tie.1 * (err_um - prev_um),
            1.0 / 2000.0,
        );
    }
    run
}

/// Rows of `run` with `extra` terms appended.
fn rows(run: &Run, extra: usize) -> Vec<Vec<f64>> {
    (0..run.terms.len())
        .map(|k| {
            let mut v = run.terms[k].clone();
            let more = [run.offset_um[k], run.span_n[k]];
            v.extend_from_slice(&more[..extra]);
            v
        })
        .collect()
}

fn fit(runs: &[Run], extra: usize) -> Vec<f64> {
    let mut ne = NormalEquations::new(runs[0].terms[0].len() + extra);
    for r in runs {
        for (row, &y) in rows(r, extra).iter().zip(&r.dx_um) {
            ne.add(row, y);
        }
    }
    ne.solve(1e-6).expect("fit").0
}

fn rms(run: &Run, extra: usize, w: &[f64]) -> f64 {
    let rows = rows(run, extra);
    let s: f64 = rows
        .iter()
        .zip(&run.dx_um)
        .map(|(r, y)| (y - r.iter().zip(w).map(|(a, b)| a * b).sum::<f64>()).powi(2))
        .sum();
    (s / rows.len() as f64).sqrt()
}

fn main() {
    let which = std::env::args().nth(1);
    let plant = hil_sim::generalise::plant_named(which.as_deref())
        .expect("built-in plants")
        .expect("a built-in plant of that name");
    let rig = plant.rig();
    let cal_scenarios = eval::calibration_scenarios(&plant, eval::CALIBRATION_PLAN_SEED, &[])
        .expect("calibration scenarios");
    let traces = eval::record_calibration(&plant, eval::CALIBRATION_PLAN_SEED, &[], &mut |_, _| {})
        .expect("recordings");
    let cal = hil_sim::calibrate::calibrate(&traces, &rig, &mut |_, _| {}).expect("calibration");
    let cal_runs: Vec<Run> = traces
        .iter()
        .zip(&cal_scenarios)
        .map(|(t, s)| replay(t, s, &plant, &cal.params, &rig))
        .collect();
    let runs: Vec<Run> = hil_sim::generalise::probe_set(&plant, 11)
        .expect("held-out runs")
        .iter()
        .map(|(s, t)| replay(t, s, &plant, &cal.params, &rig))
        .collect();
    for (extra, name) in [
        (0, "Model 4's terms"),
        (1, "+ true offset"),
        (2, "+ span tension"),
    ] {
        let w = fit(&cal_runs, extra);
        let n: usize = cal_runs.iter().map(|r| r.dx_um.len()).sum();
        let fit_rms = (cal_runs
            .iter()
            .map(|r| rms(r, extra, &w).powi(2) * r.dx_um.len() as f64)
            .sum::<f64>()
            / n as f64)
            .sqrt();
        print!("{name:16} fit {fit_rms:5.1} |");
        let mut ms = 0.0;
        for r in &runs {
            let e = rms(r, extra, &w);
            ms += e * e;
            print!(" {} {e:.1}", r.name);
        }
        println!(" | mean square {:.1} um", (ms / runs.len() as f64).sqrt());
    }
    print!("replay's motor drift from the encoder, RMS um:");
    for r in &runs {
        let d = (r.drift_um.iter().map(|d| d * d).sum::<f64>() / r.drift_um.len() as f64).sqrt();
        print!(" {} {d:.0}", r.name);
    }
    println!();
}
