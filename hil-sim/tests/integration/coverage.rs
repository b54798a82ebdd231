//! The user's own calibration scenarios, and the warning when a run leaves what the
//! calibration covered (issue 9, item 2).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use hil_sim::coverage::Coverage;
use hil_sim::eval;
use hil_sim::scenario::Scenario;
use hil_sim::PlantParams;

/// Slow feeds at 0.6 mm/s: a seventh of the slowest peak speed of the default set (4 mm/s).
const CREEP: &str = "name = \"creep\"
start_mm = 120.0
[[move]]
to_mm = 122.0
velocity_mm_s = 0.6
accel_mm_s2 = 200.0
dwell_ms = 100
[[move]]
to_mm = 120.5
velocity_mm_s = 0.6
accel_mm_s2 = 200.0
";

fn scratch(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("coverage-{name}"));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.to_str().unwrap().to_string()
}

fn hil_sim(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .expect("spawn hil-sim");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into(),
    )
}

#[test]
fn a_user_scenario_is_recorded_fitted_and_widens_the_region() {
    let dir = scratch("library");
    let plant = PlantParams::paper_rig();
    let creep = Scenario::load(&write(&dir, "creep.toml", CREEP)).unwrap();
    let seed = eval::CALIBRATION_PLAN_SEED;

    // Without it, the default set leaves the slow feed outside, by name.
    let default = eval::calibration_scenarios(&plant, seed, &[]).unwrap();
    let check = Coverage::of(&default).check(&creep);
    assert_eq!(check.moves(), 2);
    assert_eq!(check.speed_accel(), 2, "{check:?}");
    let w = check.warning().unwrap();
    assert!(w.starts_with("creep leaves the calibrated region"), "{w}");
    assert!(
        w.contains("(move 1: 0.6 mm/s at 200 mm/s²; move 2: 0.6 mm/s at 200 mm/s²)"),
        "{w}"
    );

    // With it: recorded after the default set, fitted, and inside the region.
    let with = eval::calibration_scenarios(&plant, seed, std::slice::from_ref(&creep)).unwrap();
    assert_eq!(with.len(), default.len() + 1);
    assert_eq!(with.last().unwrap().moves, creep.moves);
    let recorded: usize = eval::record_calibration(&plant, seed, &[], &mut |_, _| {})
        .unwrap()
        .iter()
        .map(|t| t.records.len())
        .sum();
    let cal =
        eval::calibrate_plant_with(&plant, seed, std::slice::from_ref(&creep), &mut |_, _| {})
            .unwrap();
    // About 6 s at 2 kHz beside the default set's samples.
    assert!(
        cal.samples > recorded + 10_000,
        "{} vs {recorded}",
        cal.samples
    );
    let coverage = cal
        .coverage
        .expect("a calibration from scenarios records its region");
    assert_eq!(coverage.check(&creep).warning(), None);
    let moves = |c: &Coverage| c.cells.values().sum::<u32>();
    assert_eq!(moves(&coverage), moves(&Coverage::of(&default)) + 2);
}

#[test]
fn a_user_scenario_the_drive_refuses_is_named_before_anything_runs() {
    let dir = scratch("refused");
    let far = write(
        &dir,
        "beyond_travel.toml",
        &CREEP.replace("to_mm = 122.0", "to_mm = 1200.0"),
    );
    let out = dir.join("cal");
    let (code, err) = hil_sim(&[
        "calibrate",
        "--scenario",
        &far,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(1), "{err}");
    let last = err.lines().last().unwrap_or("");
    assert!(
        last.contains("beyond_travel.toml") && last.contains("move 1"),
        "{err}"
    );
    assert!(!err.contains("record"), "refused before recording: {err}");
    assert!(!out.exists(), "nothing written");
    let (code, err) = hil_sim(&["calibrate", "--scenario", "/nonexistent/mine.toml"]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.lines().last().unwrap_or("").contains("mine.toml"),
        "{err}"
    );
}

#[test]
fn calibrate_writes_the_region_and_evaluate_warns_outside_it() {
    let dir = scratch("cli");
    let cal = dir.join("cal");
    let (code, err) = hil_sim(&["calibrate", "--out", cal.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{err}");
    // The table of what the moves covered, and the same in calibration.toml.
    assert!(err.contains("Calibrated travel 0.0-300.0 mm"), "{err}");
    let text = std::fs::read_to_string(cal.join("calibration.toml")).unwrap();
    assert!(
        text.contains("[coverage]") && text.contains("half_octave_cells"),
        "{text}"
    );

    let evaluate = |scenario: &str| {
        hil_sim(&[
            "evaluate",
            "--scenario",
            scenario,
            "--calibration",
            cal.to_str().unwrap(),
            "--json",
        ])
    };
    let creep = write(&dir, "creep.toml", CREEP);
    let (code, err) = evaluate(&creep);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains("warning: creep leaves the calibrated region: 2 of 2 moves"),
        "{err}"
    );
    // A preset inside the region: no warning.
    let (code, err) = evaluate("zigzag");
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("warning"), "{err}");

    // A file made before the region was recorded: loaded, with a note that nothing is checked.
    let start = text.find("\n[coverage]\n").unwrap() + 1;
    let end = start + text[start..].find("\n[").unwrap() + 1;
    let old = format!("{}{}", &text[..start], &text[end..]);
    assert!(!old.contains("half_octave_cells"), "{old}");
    std::fs::write(cal.join("calibration.toml"), &old).unwrap();
    let (code, err) = evaluate(&creep);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains("note: the calibration records no coverage") && !err.contains("warning"),
        "{err}"
    );

    // A damaged region is refused by field, naming the file.
    let bad = text.replace("half_octave_cells = [[", "half_octave_cells = [[\"x\", ");
    assert_ne!(bad, text);
    std::fs::write(cal.join("calibration.toml"), bad).unwrap();
    let (code, err) = evaluate("zigzag");
    assert_eq!(code, Some(1), "{err}");
    let last = err.lines().last().unwrap_or("");
    assert!(
        last.contains("calibration.toml") && last.contains("coverage.half_octave_cells[0]"),
        "{err}"
    );
}

/// The report's picture of the region: drawn where a font is installed, a named error where not.
#[test]
fn the_region_is_drawn_with_the_run_over_it() {
    let dir = scratch("plot");
    let plant = PlantParams::paper_rig();
    let default = eval::calibration_scenarios(&plant, eval::CALIBRATION_PLAN_SEED, &[]).unwrap();
    let region = Coverage::of(&default);
    let creep = Scenario::load(&write(&dir, "creep.toml", CREEP)).unwrap();
    let check = region.check(&creep);
    let png = dir.join("coverage.png");
    match hil_sim::plot::coverage(&png, "region", &region, &check) {
        Ok(()) => {
            let bytes = std::fs::read(&png).unwrap();
            assert!(
                bytes.starts_with(b"\x89PNG") && bytes.len() > 10_000,
                "{}",
                bytes.len()
            );
        }
        Err(e) => {
            let e = e.to_string();
            assert!(hil_sim::plot::init_fonts().is_err(), "drawing failed: {e}");
        }
    }
}
