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

/// The default calibration identifies Model 4's belt observer on the paper rig and keeps it
/// (it fits the recordings better than the slip observer: 4.4 against 9.5 um measured); the
/// calibration directory carries it exactly, and an edit of its physics in the TOML is refused
/// naming the field. On fig18, held out, Model 4 is below every other estimator.
#[test]
fn the_belt_observer_is_calibrated_kept_and_carried() {
    let plant = PlantParams::paper_rig();
    let cal = crate::paper_calibration();
    let belt = cal.params.model4.belt.expect("the belt observer kept");
    assert_eq!(belt.step_ticks, hil_sim::calibrate::BELT_STEP_TICKS);
    assert!(belt.weight.abs() > 0.1, "weight {}", belt.weight);
    // Rest after travel: reverse below forward (the belt leans on the other flanks).
    assert!(belt.rest_um[0] < belt.rest_um[1], "{:?}", belt.rest_um);
    let fit = |k: ModelKind| cal.fit_rms_um.iter().find(|(m, _)| *m == k).unwrap().1;
    assert!(
        fit(ModelKind::Operator) < 0.5 * fit(ModelKind::Table),
        "Model 4 fits {} um",
        fit(ModelKind::Operator)
    );
    let dir = std::env::temp_dir().join(format!("belt-drive-belt-{}", std::process::id()));
    hil_sim::calfile::save(&dir, cal, &plant.rig()).unwrap();
    let back = hil_sim::calfile::load(&dir, &plant.rig()).unwrap();
    assert_eq!(back.params, cal.params);
    let toml = dir.join("calibration.toml");
    let text = std::fs::read_to_string(&toml).unwrap();
    let line = text
        .lines()
        .find(|l| l.starts_with("preload_n = "))
        .expect("the belt's preload in the TOML")
        .to_string();
    std::fs::write(&toml, text.replace(&line, "preload_n = 1.0")).unwrap();
    let e = hil_sim::calfile::load(&dir, &plant.rig()).map(|_| ());
    let _ = std::fs::remove_dir_all(&dir);
    let e = e.expect_err("an edited belt physics loaded").to_string();
    assert!(e.contains("model4.belt.preload_n"), "{e}");
    let t = evaluate(cal, &plant, "fig18", 7);
    let m4 = rms(&t, "model4");
    for (name, s) in &t {
        if !matches!(*name, "model4" | "none") {
            assert!(m4 < s.rms_um, "fig18: {name} {} <= model4 {m4}", s.rms_um);
        }
    }
}
