//! The plant's geometry flows into the drive and the calibration: a rig with another pulley and
//! another encoder calibrates and is estimated in micrometres like the paper's, and a calibration
//! made for one geometry is refused on another, naming both.

use estimator_core::model::ModelKind;
use hil_sim::eval;
use hil_sim::plant::PlantParams;
use hil_sim::scenario::Scenario;

/// The paper rig with a 15-tooth pulley and a 500-line encoder (3.7 times coarser counts).
fn other_rig() -> PlantParams {
    let mut p = PlantParams::paper_rig();
    p.pulley.teeth = 15;
    p.encoder.lines = 500;
    p.validate().expect("a valid plant");
    p
}

#[test]
fn another_geometry_calibrates_and_estimates_in_micrometres() {
    let plant = other_rig();
    assert_ne!(plant.rig(), PlantParams::paper_rig().rig());
    let cal = eval::calibrate_plant(&plant, &mut |_, _| {}).unwrap();
    let s = Scenario::load("zigzag").unwrap();
    let trace =
        eval::run_in_process(&s, &plant, &cal.params, ModelKind::Table, 1, &mut |_| {}).unwrap();
    let coeffs = cal.params.build(&plant.rig()).unwrap();
    let table = eval::table3(&trace, &eval::estimates(&trace, &coeffs));
    let rms = |n: &str| table.iter().find(|(k, _)| *k == n).unwrap().1.rms_um;
    eprintln!(
        "15 teeth, 500 lines, zigzag: none {:.1}, model1 {:.1}, model3 {:.1} um RMS",
        rms("none"),
        rms("model1"),
        rms("model3")
    );
    // The belt's error is the same physics in the same units: about 0.15 mm uncompensated, and
    // the models remove most of it (paper rig: none 151, Model 3 19 um).
    assert!((100.0..250.0).contains(&rms("none")), "{}", rms("none"));
    assert!(rms("model3") < rms("none") / 4.0, "{}", rms("model3"));
    assert!(rms("model1") < rms("none") / 3.0, "{}", rms("model1"));
}

#[test]
fn a_calibration_for_another_geometry_is_refused_naming_both() {
    let dir = std::env::temp_dir().join(format!("belt-drive-geometry-{}", std::process::id()));
    let paper = PlantParams::paper_rig();
    let cal = crate::paper_calibration();
    hil_sim::calfile::save(&dir, cal, &paper.rig()).unwrap();
    let e = match hil_sim::calfile::load(&dir, &other_rig().rig()) {
        Err(e) => e,
        Ok(_) => panic!("a paper-rig calibration loaded on another geometry"),
    };
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        matches!(&e, hil_sim::calfile::CalFileError::OtherGeometry { made_for, plant, .. }
            if *made_for == paper.rig() && *plant == other_rig().rig()),
        "{e:?}"
    );
    let e = e.to_string();
    assert!(e.contains("calibration.bin"), "{e}");
    assert!(e.contains("1867.9 counts/mm"), "{e}");
    assert!(
        e.contains("15-tooth pulley") && e.contains("500 encoder lines"),
        "{e}"
    );
    // The firmware under QEMU is configured for the paper rig: refused before QEMU starts.
    let e = eval::check_pil_geometry(&other_rig()).unwrap_err();
    assert!(
        matches!(&e, hil_sim::error::Error::PilGeometry { paper, has, .. }
            if *paper == estimator_core::rig::Rig::PAPER && *has == other_rig().rig()),
        "{e:?}"
    );
    let e = e.to_string();
    assert!(e.contains("paper rig") && e.contains("15-tooth"), "{e}");
    assert!(eval::check_pil_geometry(&paper).is_ok());
}
