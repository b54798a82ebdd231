//! Carriage placement on the simulated rig: carriage-space moves to rest, approached from both
//! sides, at several speeds; the arrival error is read on the linear scale.

use estimator_core::model::ModelKind;
use hil_sim::placement::{arrival_errors_in_process, Move};
use hil_sim::plant::PlantParams;

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

#[test]
fn models_place_the_carriage_where_the_motor_alone_does_not() {
    let plant = PlantParams::paper_rig();
    let cal = crate::paper_calibration();
    // Long and short strokes, both directions, over the travel.
    let moves: Vec<Move> = vec![
        (200.0, 60.0, 1500.0),
        (120.0, 60.0, 1500.0),
        (260.0, 80.0, 2000.0),
        (90.0, 80.0, 2000.0),
        (180.0, 80.0, 2000.0),
        (150.0, 40.0, 1500.0),
        (152.0, 20.0, 500.0),
        (100.0, 100.0, 3000.0),
        (97.0, 20.0, 500.0),
        (40.0, 50.0, 1000.0),
    ];
    let mut report = Vec::new();
    for model in ModelKind::ALL {
        let e = arrival_errors_in_process(&plant, &cal.params, model, 30.0, &moves, 7).unwrap();
        let max = e.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        eprintln!(
            "{:<7} arrival RMS {:6.1} um, max {:6.1} um: {:?}",
            model.as_str(),
            rms(&e),
            max,
            e.iter().map(|x| x.round()).collect::<Vec<_>>()
        );
        report.push((model, rms(&e)));
    }
    let of = |kinds: &[ModelKind]| {
        report
            .iter()
            .filter(|r| kinds.contains(&r.0))
            .map(|r| r.1)
            .fold(f64::MAX, f64::min)
    };
    let none = of(&[ModelKind::None]);
    let best = of(&ModelKind::PAPER_MODELS);
    let baseline = of(&[ModelKind::Backlash, ModelKind::BidirTable]);
    assert!(none > 100.0, "none: {none}");
    assert!(
        best <= none / 5.0,
        "best model {best} um against none {none} um"
    );
    // The anchors' ways, on the same plant and the same moves, place the carriage worse.
    assert!(
        best < baseline && baseline < none,
        "best model {best} um, best baseline {baseline} um, none {none} um"
    );
}
