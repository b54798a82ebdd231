//! Where Model 4 loses, move by move (README, "Machines drawn at random" and "How much Model
//! 4's figures depend on the calibration draw"): a preset on a plant, Model 3's and Model 4's
//! RMS move by move, then the ticks around Model 4's worst error with the observer's offset `g`
//! beside the plant's true mesh offset `P - b`, and the fitted observer.
//!
//! `cargo run --profile ci -p hil-sim --example drawn_machine -- [PLANT] [PRESET] [PLAN-SEED]`:
//! PLANT is N for `generalise::drawn_plant(N)` (default 3) or a part of a built-in plant's name
//! (`paper`, `tight`, ...); PRESET defaults to `accelerations` and may be a generated workload of
//! the generalisation table (`pick-and-place-11`); PLAN-SEED defaults to the default plan's.
#![allow(clippy::print_stdout)]
use estimator_core::model::{ModelKind, ModelParams};
use hil_sim::eval;
fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let plant = match arg(1) {
        None => hil_sim::generalise::drawn_plant(3),
        Some(a) => match a.parse::<u64>() {
            Ok(n) => hil_sim::generalise::drawn_plant(n),
            Err(_) => hil_sim::generalise::plant_named(Some(&a))
                .expect("built-in plants")
                .expect("a built-in plant of that name"),
        },
    };
    let preset = arg(2).unwrap_or_else(|| "accelerations".into());
    let plan_seed = arg(3).map_or(eval::CALIBRATION_PLAN_SEED, |s| {
        s.parse().expect("a plan seed (an integer)")
    });
    let cal = eval::calibrate_plant_with(&plant, plan_seed, &[], &mut |_, _| {}).unwrap();
    let coeffs = cal.params.build(&plant.rig()).unwrap();
    // A preset, or a workload of the generalisation table by name (`pick-and-place-11`).
    let s = hil_sim::scenario::Scenario::load(&preset).unwrap_or_else(|_| {
        let seed = preset.rsplit('-').next().and_then(|n| n.parse().ok());
        hil_sim::generalise::workloads(&plant, seed.expect("a preset or a generated workload"))
            .unwrap()
            .into_iter()
            .find(|w| w.name == preset)
            .expect("a preset or a generated workload")
    });
    let t = eval::run_in_process(
        &s,
        &plant,
        &ModelParams::PAPER,
        ModelKind::None,
        1,
        &mut |_| {},
    )
    .unwrap();
    let est = eval::estimates(&t, &coeffs);
    let get = |n: &str| est.iter().find(|e| e.0 == n).unwrap().1.clone();
    let (y3, y4) = (get("model3"), get("model4"));
    let mut rf = estimator_core::reference::Reference::new(
        &cal.params,
        &plant.rig(),
        t.records[0].motor_counts.0,
    )
    .unwrap();
    let mut pl = hil_sim::Plant::new(&plant, s.start_mm, t.seed).unwrap();
    let n = t.records.len();
    for (k, m) in s.moves.iter().enumerate() {
        let a = t.move_starts[k];
        let b = t.move_starts.get(k + 1).copied().unwrap_or(n);
        let (mut s3, mut s4) = (0.0, 0.0);
        for i in a..b {
            let dx = t.dx_um(i);
            s3 += (dx - y3[i]).powi(2);
            s4 += (dx - y4[i]).powi(2);
        }
        println!(
            "move {k} to {} v {} a {}: rms m3 {:.1} m4 {:.1}",
            m.to_mm,
            m.velocity_mm_s,
            m.accel_mm_s2,
            (s3 / (b - a) as f64).sqrt(),
            (s4 / (b - a) as f64).sqrt()
        );
    }
    let mut gs = Vec::new();
    for r in &t.records {
        let (_, f) = rf.model4_step(r.motor_counts.0, r.out.current_a.to_num::<f64>());
        let bb = pl.belt();
        gs.push((f.slip_um, bb.mesh_offset_m * 1e6, f.current_lp_a));
        pl.step(r.out.current_a.to_num::<f64>(), 1.0 / 2000.0);
    }
    let worst = (0..n)
        .max_by(|&i, &j| {
            (t.dx_um(i) - y4[i])
                .abs()
                .total_cmp(&(t.dx_um(j) - y4[j]).abs())
        })
        .unwrap();
    for i in (worst.saturating_sub(200)..(worst + 200).min(n)).step_by(20) {
        println!(
            "  t {:.3} x {:.3} dx {:6.1} e3 {:6.1} e4 {:6.1} cur {:+.2} g {:6.1} P-b {:6.1}",
            t.records[i].t_s,
            t.x_pe_mm(i),
            t.dx_um(i),
            t.dx_um(i) - y3[i],
            t.dx_um(i) - y4[i],
            t.records[i].out.current_a.to_num::<f64>(),
            gs[i].0,
            gs[i].1
        );
    }
    println!("{:?}", cal.params.model4.slip);
}
