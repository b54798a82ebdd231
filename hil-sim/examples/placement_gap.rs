//! Where a compensator's placement error comes from (README, "Carriage placement"): runs a preset
//! in carriage space and splits each move's arrival error, exactly, into three parts:
//! - **prediction**: the model's estimate at rest minus what the move's plan predicted
//!   (the carriage target minus the motor target the drive planned);
//! - **estimate**: the true error at rest minus the model's estimate there;
//! - **motor**: the motor at rest minus its set-point (the loop's overshoot, the same for every
//!   model).
//!
//! Then the same preset in motor space: the model's RMS while moving, in the first 50 ms at rest
//! and after, which says whether a model's lead over the run holds where placement reads it.
//!
//! `cargo run --profile ci -p hil-sim --example placement_gap -- [PRESET] [MODEL]` (fig18,
//! model4 by default; the paper rig, calibrated as `hil-sim calibrate` does).
#![allow(clippy::print_stdout)]
use estimator_core::model::{ModelKind, ModelParams};
use hil_sim::{eval, placement, scenario::Scenario, PlantParams};

fn main() {
    let preset = std::env::args().nth(1).unwrap_or_else(|| "fig18".into());
    let name = std::env::args().nth(2).unwrap_or_else(|| "model4".into());
    let Some(model) = ModelKind::ALL.into_iter().find(|m| m.as_str() == name) else {
        eprintln!(
            "placement_gap: unknown model {name:?} (none, model1..model4, backlash, bidir_table)"
        );
        std::process::exit(2);
    };
    let scenario = match Scenario::load(&preset) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("placement_gap: {e}");
            std::process::exit(2);
        }
    };
    let plant = PlantParams::paper_rig();
    let cal = eval::calibrate_plant(&plant, &mut |_, _| {}).expect("calibration of the paper rig");
    let t = placement::run_carriage_space(&scenario, &plant, &cal.params, model, 1, &mut |_| {})
        .expect("carriage-space run");
    let cpm = t.counts_per_mm;
    let um = |counts: i32| counts as f64 / cpm * 1000.0;
    println!("{preset}, {name}, carriage space: arrival = prediction + estimate + motor (um)");
    println!("move  target mm   arrival  prediction  estimate   motor");
    let mut sums = [0.0f64; 4];
    let mut moves = 0.0;
    // The moves that end at rest, read as the placement figures read them.
    for (k, arrival) in placement::arrivals(&scenario, &t) {
        let m = &scenario.moves[k];
        let i = t.move_starts.get(k + 1).copied().unwrap_or(t.records.len()) - 1;
        let r = &t.records[i];
        let predicted = m.to_mm * 1000.0 - um(r.setpoint_counts.0);
        let estimated = r.out.telemetry.est_error_um.to_num::<f64>();
        let parts = [
            arrival,
            estimated - predicted,
            t.dx_um(i) - estimated,
            um(r.motor_counts.0 - r.setpoint_counts.0),
        ];
        println!(
            "{k:4} {:10.3} {:9.1} {:11.1} {:9.1} {:7.1}",
            m.to_mm, parts[0], parts[1], parts[2], parts[3]
        );
        for (s, p) in sums.iter_mut().zip(parts) {
            *s += p * p;
        }
        moves += 1.0;
    }
    let [a, p, e, o] = sums.map(|s| (s / moves).sqrt());
    println!("RMS  {:19.1} {p:11.1} {e:9.1} {o:7.1}  ({moves} moves)", a);

    // Motor space: the estimate's RMS by phase.
    let coeffs = cal.params.build(&plant.rig()).expect("calibration builds");
    let t = eval::run_in_process(
        &scenario,
        &plant,
        &ModelParams::PAPER,
        ModelKind::None,
        1,
        &mut |_| {},
    )
    .expect("motor-space run");
    let est = eval::estimates(&t, &coeffs);
    let (_, y) = est
        .iter()
        .find(|e| e.0 == name)
        .expect("an estimate for every compensator");
    // Moving, the first 100 ticks (50 ms) at rest, and after.
    let mut phase = [(0.0f64, 0usize); 3];
    let mut at_rest = 0usize;
    for (i, r) in t.records.iter().enumerate() {
        at_rest = if r.out.telemetry.moving {
            0
        } else {
            at_rest + 1
        };
        let p = match at_rest {
            0 => 0,
            1..=100 => 1,
            _ => 2,
        };
        phase[p].0 += (t.dx_um(i) - y[i]).powi(2);
        phase[p].1 += 1;
    }
    let rms = |(s, n): (f64, usize)| if n == 0 { 0.0 } else { (s / n as f64).sqrt() };
    println!(
        "motor space, RMS of e - y: moving {:.1} um ({} ticks), first 50 ms at rest {:.1} ({}), at rest after {:.1} ({})",
        rms(phase[0]),
        phase[0].1,
        rms(phase[1]),
        phase[1].1,
        rms(phase[2]),
        phase[2].1
    );
}
