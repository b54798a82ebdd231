//! Model 4 on workloads that calibration never sees.

use hil_sim::eval;
use hil_sim::generalise::{self, PlantTable};

/// Neither the calibration plan's seed nor the README table's.
const HELD_OUT_SEED: u64 = 101;

/// The RMS over the set's workloads (each weighs the same) of `estimator`, um.
fn held_out(t: &PlantTable, estimator: &str) -> f64 {
    t.held_out_rms(estimator, HELD_OUT_SEED)
        .expect("every held-out workload measured")
}

/// Every plant (the paper rig and the four variants), each calibrated by its default plan, runs
/// one generated workload of every class (printer raster, pick-and-place, slow feed, travel ends,
/// mixed limits, high-acceleration reversals) at a held-out seed. Over that set, on every plant,
/// Model 4 has the lowest RMS error of every estimator (the paper's models and the baselines).
/// Measured at this seed (`hil-sim generalise --seed 101`, Model 4 with the belt observer the
/// default calibration gives it), Model 4 against the next best: paper rig 18.0 / 47.1 (Model 3),
/// tight belt 16.0 / 34.0 (Model 2), worn belt 19.2 / 67.7 (Model 3), heavy carriage 38.8 /
/// 112.9 (Model 3), other geometry 23.0 / 46.1 (Model 1) um (with the slip observer: 28.1, 24.4,
/// 48.7, 60.4 and 28.7).
#[test]
fn model4_is_best_over_held_out_workloads() {
    assert_model4_best_held_out(generalise::plants().unwrap());
}

/// On every plant, calibrated by its default plan, over one generated workload of every class at
/// [`HELD_OUT_SEED`]: Model 4's mean square is below every other estimator's. Prints the figures.
fn assert_model4_best_held_out(plants: impl IntoIterator<Item = hil_sim::PlantParams>) {
    let mut report = String::new();
    let mut failed = Vec::new();
    let jobs: Vec<_> = plants
        .into_iter()
        .map(|plant| {
            let generated: Vec<_> = generalise::workloads(&plant, HELD_OUT_SEED)
                .unwrap()
                .into_iter()
                .filter(|s| s.name.ends_with(&format!("-{HELD_OUT_SEED}")))
                .collect();
            assert_eq!(generated.len(), 6, "{}", plant.name());
            (plant, generated)
        })
        .collect();
    let tables = generalise::measure_all(
        &jobs,
        eval::CALIBRATION_PLAN_SEED,
        eval::Observer::default(),
        &mut |_, _| {},
    );
    for (t, (plant, _)) in tables.unwrap().iter().zip(&jobs) {
        assert_eq!(t.rows.len(), 6, "{}: a workload was refused", plant.name());
        let m4 = held_out(t, "model4");
        report += &format!("{} {:?}: model4 {m4:.1} um", t.plant, plant.rig());
        for e in hil_sim::eval::ESTIMATORS {
            if *e == "model4" {
                continue;
            }
            let other = held_out(t, e);
            report += &format!(", {e} {other:.1}");
            if other <= m4 {
                failed.push(format!("{}: {e} {other:.1} <= model4 {m4:.1}", t.plant));
            }
        }
        report += "\n";
    }
    println!("{report}");
    assert!(failed.is_empty(), "{failed:?}\n{report}");
}

/// Every generated workload and calibration plan is a scenario the drive accepts on every
/// plant (the variants and twenty machines drawn at random): inside the travel and the limits,
/// on the integer grid, no retarget on the last move.
#[test]
fn generated_workloads_are_valid_on_every_plant() {
    use hil_sim::workloads::{calibration_plan, generate, Class, Limits};
    let drawn = (1..=20).map(generalise::drawn_plant);
    for plant in generalise::plants().unwrap().into_iter().chain(drawn) {
        let limits = hil_sim::drive_setup::drive_limits(plant.rig());
        let lim = Limits::of(&limits);
        for seed in 0..150 {
            for class in Class::ALL {
                let s = generate(class, seed, &lim, generalise::WORKLOAD_S);
                if let Err(e) = s.check_against(&limits, &plant) {
                    panic!("{}: {}: {e}", plant.name(), s.name);
                }
            }
            let plan = calibration_plan(&lim, seed, 60.0);
            if let Err(e) = plan.check_against(&limits, &plant) {
                panic!("{}: calibration plan seed {seed}: {e}", plant.name());
            }
        }
    }
}

/// Model 4's lead over the held-out workloads on three machines drawn at random
/// (`generalise::drawn_plant`: not the built-in variants, not designed against), each calibrated
/// by its default plan. Measured (`hil-sim generalise --no-variants --drawn 3 --seed 101`), Model
/// 4 against the next best: 49.5 / 96.7, 39.7 / 47.3 and 15.8 / 20.3 um (Model 3 each time; with
/// the slip observer 71.5, 33.9 and 15.8: on the third the calibration keeps the slip observer).
/// With the gap crossed at once in gross slip the third was 23.0 against 20.3.
#[test]
fn model4_is_best_on_machines_drawn_at_random() {
    assert_model4_best_held_out((1..=3).map(generalise::drawn_plant));
}
