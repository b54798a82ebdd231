//! Table 3 on the simulated rig: calibrate on the calibration scenarios only, then evaluate on
//! scenarios the calibration never saw. The paper's ordering must hold on every one of them.

use estimator_core::model::ModelKind;
use estimator_core::rig::Rig;
use hil_sim::calibrate::Calibration;
use hil_sim::eval;
use hil_sim::plant::PlantParams;
use hil_sim::scenario::Scenario;
use hil_sim::stats::ErrorStats;

fn rms(table: &[(&'static str, ErrorStats)], name: &str) -> f64 {
    table
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, s)| s.rms_um)
        .unwrap()
}

fn evaluate(
    cal: &Calibration,
    plant: &PlantParams,
    name: &str,
    seed: u64,
) -> Vec<(&'static str, ErrorStats)> {
    let s = Scenario::load(name).unwrap();
    let trace =
        eval::run_in_process(&s, plant, &cal.params, ModelKind::Table, seed, &mut |_| {}).unwrap();
    let coeffs = cal.params.build(&Rig::PAPER).unwrap();
    let est = eval::estimates(&trace, &coeffs);
    // The drive's own per-tick estimate is the replayed fixed-point Model 3, bit for bit.
    let m3 = &est.iter().find(|(n, _)| *n == "model3").unwrap().1;
    for (r, y) in trace.records.iter().zip(m3) {
        assert_eq!(r.out.telemetry.est_error_um.to_num::<f64>(), *y);
    }
    eval::table3(&trace, &est)
}

#[test]
fn table3_ordering_holds_on_unseen_scenarios() {
    let plant = PlantParams::paper_rig();
    let cal = crate::paper_calibration();
    for name in ["fig18", "zigzag", "accelerations"] {
        assert!(!eval::CALIBRATION_SCENARIOS.contains(&name));
        let t = evaluate(cal, &plant, name, 7);
        let r = |n| rms(&t, n);
        eprintln!(
            "{name}: none {:.1} model1 {:.1} model2 {:.1} model3 {:.1} backlash {:.1} bidir_table {:.1}",
            r("none"),
            r("model1"),
            r("model2"),
            r("model3"),
            r("backlash"),
            r("bidir_table")
        );
        // Model 3 best; Models 1 and 2 close; today's compensations behind the paper's models;
        // no model worst.
        assert!(
            r("model3") <= r("model1") && r("model3") <= r("model2"),
            "{name}: model 3 not best"
        );
        assert!(
            (r("model1") - r("model2")).abs() <= 0.2 * r("model1").max(r("model2")),
            "{name}: models 1 and 2 not close"
        );
        for base in ["backlash", "bidir_table"] {
            assert!(
                r(base) > r("model1").max(r("model2")),
                "{name}: {base} beats a paper model"
            );
            assert!(r(base) < r("none"), "{name}: {base} worse than nothing");
        }
    }
}
