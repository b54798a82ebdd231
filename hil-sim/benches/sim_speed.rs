//! `cargo bench -p hil-sim --bench sim_speed`: in-process simulation speed (simulated seconds per
//! wall-clock second, one core) of the closed loop plant + drive on the Fig. 18 and reversals
//! scenarios.

use std::time::Instant;

use estimator_core::model::{ModelKind, ModelParams};
use hil_sim::eval::run_in_process;
use hil_sim::plant::PlantParams;
use hil_sim::scenario::Scenario;

fn main() {
    let plant = PlantParams::paper_rig();
    for name in ["fig18", "reversals"] {
        let s = Scenario::load(name).expect("preset");
        let start = Instant::now();
        let t = run_in_process(
            &s,
            &plant,
            &ModelParams::PAPER,
            ModelKind::Table,
            1,
            &mut |_| {},
        )
        .expect("run");
        let wall = start.elapsed().as_secs_f64();
        let sim = t.records.last().map_or(0.0, |r| r.t_s);
        println!(
            "{name:<10} {sim:7.1} s simulated in {wall:6.3} s wall: {:7.0}x real time ({} ticks)",
            sim / wall,
            t.records.len()
        );
    }
}
