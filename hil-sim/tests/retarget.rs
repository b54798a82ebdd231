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
