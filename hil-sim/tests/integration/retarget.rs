//! Scenarios that retarget a running move with new limits (a feed override, blended G-code) run
//! to the end on the simulated rig, with the set-point continuous in position and velocity.

use estimator_core::model::{ModelKind, ModelParams};
use hil_sim::eval;
use hil_sim::plant::PlantParams;
use hil_sim::scenario::Scenario;

const SCENARIO: &str = r#"
name = "feed-overrides"
start_mm = 40.0

# Slower in mid-move, same direction.
[[move]]
to_mm = 160.0
velocity_mm_s = 120.0
accel_mm_s2 = 2000.0
retarget_after_ms = 400

[[move]]
to_mm = 200.0
velocity_mm_s = 30.0
accel_mm_s2 = 600.0
retarget_after_ms = 700

# Faster and reversing, in mid-move.
[[move]]
to_mm = 90.0
velocity_mm_s = 200.0
accel_mm_s2 = 4000.0
retarget_after_ms = 300

# Gentler limits while braking.
[[move]]
to_mm = 60.0
velocity_mm_s = 15.0
accel_mm_s2 = 200.0
dwell_ms = 100
"#;

#[test]
fn retargets_with_new_limits_run_and_stay_continuous() {
    let s = Scenario::from_toml_str(SCENARIO).unwrap();
    let trace = eval::run_in_process(
        &s,
        &PlantParams::paper_rig(),
        &ModelParams::PAPER,
        ModelKind::Table,
        1,
        &mut |_| {},
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let sp: Vec<i64> = trace
        .records
        .iter()
        .map(|r| r.setpoint_counts.0 as i64)
        .collect();
    let cpm = trace.counts_per_mm;
    assert!(trace.records.len() > 4000, "{} ticks", trace.records.len());
    // 200 mm/s at 2 kHz is 187 counts per tick; 4000 mm/s^2 is 1.9 counts/tick^2, plus at most
    // 2 counts of whole-count rounding.
    let max_step = sp.windows(2).map(|w| (w[1] - w[0]).abs()).max().unwrap();
    let max_dv = sp
        .windows(3)
        .map(|w| ((w[2] - w[1]) - (w[1] - w[0])).abs())
        .max()
        .unwrap();
    assert!(max_step as f64 <= 200.0 * cpm / 2000.0 + 1.0, "{max_step}");
    assert!(max_dv <= 4, "velocity stepped by {max_dv} counts/tick");
    assert_eq!(*sp.last().unwrap(), (60.0 * cpm).round() as i64);
    let x = trace.records.last().unwrap().motor_counts.to_mm(cpm);
    assert!((x - 60.0).abs() < 0.01, "ended at {x} mm");
}

/// Back-and-forth moves of a few micrometres at the drive's highest acceleration (a fine
/// adjustment, a dither) run without a fault: each reversal's acceleration feed-forward (4.6 A
/// for a tick on the paper rig) with the motor inside the stall detector's 20 um dead band once
/// tripped `stall` (in move 15 of 20 at 1 um).
#[test]
fn micrometre_dithers_at_full_acceleration_do_not_trip_the_stall_detector() {
    for step_mm in [0.001, 0.005, 0.01, 0.05] {
        let mut text = String::from("name = \"dither\"\nstart_mm = 150.0\n");
        for k in 0..20 {
            let to = if k % 2 == 0 { 150.0 + step_mm } else { 150.0 };
            text +=
                &format!("[[move]]\nto_mm = {to}\nvelocity_mm_s = 250.0\naccel_mm_s2 = 5000.0\n");
        }
        let s = Scenario::from_toml_str(&text).unwrap();
        for model in [ModelKind::None, ModelKind::Table] {
            eval::run_in_process(
                &s,
                &PlantParams::paper_rig(),
                &ModelParams::PAPER,
                model,
                1,
                &mut |_| {},
            )
            .unwrap_or_else(|e| panic!("{step_mm} mm, {model:?}: {e}"));
        }
    }
}
