//! Scenarios: sequences of moves in TOML, run closed loop by the drive's own trajectory and PID.
//!
//! ```toml
//! name = "example"
//! start_mm = 20.0
//! [[move]]
//! to_mm = 300.0
//! velocity_mm_s = 80.0
//! accel_mm_s2 = 800.0
//! dwell_ms = 200          # optional, default 0: rest after arrival
//! retarget_after_ms = 150 # optional: start the next move this long after this one starts
//! ```

use estimator_core::drive::DriveConfig;
use serde::Deserialize;

use crate::plant::PlantParams;

/// Longest scenario a run accepts, simulated seconds (its duration estimated from the moves):
/// a run records every tick, about 0.25 GB per simulated hour at 2 kHz.
pub const MAX_DURATION_S: f64 = 3600.0;

/// One commanded move.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Move {
    /// Target, millimetres of nominal travel.
    pub to_mm: f64,
    /// Cruise speed, mm/s.
    pub velocity_mm_s: f64,
    /// Acceleration and deceleration, mm/s^2.
    pub accel_mm_s2: f64,
    /// Rest after arrival, milliseconds.
    #[serde(default)]
    pub dwell_ms: u32,
    /// If set, the next move is commanded this long after this one starts, arrived or not.
    #[serde(default)]
    pub retarget_after_ms: Option<u32>,
}

impl Move {
    /// The move in the drive's integer units: target um, um/s, um/s^2, rounded (the scenario's
    /// ranges keep them in range): what a run sends and what the check checks.
    pub fn drive_units(&self) -> (i32, u32, u32) {
        (
            (self.to_mm * 1000.0).round() as i32,
            (self.velocity_mm_s * 1000.0).round() as u32,
            (self.accel_mm_s2 * 1000.0).round() as u32,
        )
    }
}

/// A named sequence of moves from a start position.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Name shown in reports.
    pub name: String,
    /// Where the carriage rests (nominal mm) before the first move.
    pub start_mm: f64,
    /// The moves, in order.
    #[serde(rename = "move")]
    pub moves: Vec<Move>,
    /// Where it came from (a file path or `preset NAME`), for error messages.
    #[serde(skip)]
    pub source: String,
}

/// The shipped presets, by name, mirroring the paper's experiments.
pub const PRESETS: &[(&str, &str)] = &[
    (
        "repeatability",
        include_str!("../scenarios/repeatability.toml"),
    ),
    ("velocities", include_str!("../scenarios/velocities.toml")),
    (
        "accelerations",
        include_str!("../scenarios/accelerations.toml"),
    ),
    ("reversals", include_str!("../scenarios/reversals.toml")),
    ("fig18", include_str!("../scenarios/fig18.toml")),
    ("zigzag", include_str!("../scenarios/zigzag.toml")),
];

impl Scenario {
    /// Parses and validates a scenario; errors name the move and field.
    pub fn from_toml_str(text: &str) -> Result<Scenario, String> {
        let s: Scenario = crate::input::from_toml(text)?;
        s.validate()?;
        Ok(s)
    }

    /// Loads a file path, or a shipped preset by name (`fig18`, `reversals`, ...).
    pub fn load(path_or_preset: &str) -> Result<Scenario, String> {
        if let Some((name, text)) = PRESETS.iter().find(|(n, _)| *n == path_or_preset) {
            let mut s = Scenario::from_toml_str(text).map_err(|e| format!("preset {name}: {e}"))?;
            s.source = format!("preset {name}");
            return Ok(s);
        }
        let text = std::fs::read_to_string(path_or_preset).map_err(|e| {
            format!(
                "scenario {path_or_preset}: {e} (presets: {})",
                preset_names()
            )
        })?;
        let mut s = Scenario::from_toml_str(&text).map_err(|e| format!("{path_or_preset}: {e}"))?;
        s.source = path_or_preset.to_string();
        Ok(s)
    }

    /// Where the scenario came from, for messages.
    pub fn source(&self) -> &str {
        if self.source.is_empty() {
            "scenario"
        } else {
            &self.source
        }
    }

    /// Estimated duration, seconds: each move at its cruise speed plus its ramps, its dwell.
    /// An upper bound of a run's length up to a factor of two (the run's time-out).
    pub fn duration_estimate_s(&self) -> f64 {
        let mut x = self.start_mm;
        let mut t = 0.0;
        for m in &self.moves {
            let d = (m.to_mm - x).abs();
            t += d / m.velocity_mm_s
                + 2.0 * m.velocity_mm_s / m.accel_mm_s2
                + m.dwell_ms as f64 / 1000.0;
            x = m.to_mm;
        }
        t
    }

    /// Checks the scenario against the drive's limits (the checks `Drive::command` makes, in
    /// the units it receives) and the plant's travel, before anything runs. Errors name the
    /// scenario, the move (counted from 1) and the field.
    pub fn check_against(&self, drive: &DriveConfig, plant: &PlantParams) -> Result<(), String> {
        let src = self.source();
        let plant_mm = (
            plant.carriage.travel_min_m * 1e3,
            plant.carriage.travel_max_m * 1e3,
        );
        let in_plant = |v: f64| (plant_mm.0..=plant_mm.1).contains(&v);
        let plant_name = plant.name();
        if !in_plant(self.start_mm) {
            return Err(format!(
                "{src}: start_mm = {} mm is outside the plant's travel {}..={} mm \
                 (carriage.travel_min_m, carriage.travel_max_m of {plant_name})",
                show(self.start_mm),
                plant_mm.0,
                plant_mm.1
            ));
        }
        // The drive's own range checks, on the integers the run will send.
        let checker = estimator_core::drive::Drive::new(drive)
            .map_err(|e| format!("drive configuration: {e}"))?;
        for (i, m) in self.moves.iter().enumerate() {
            let n = i + 1;
            let (target_um, velocity_um_s, accel_um_s2) = m.drive_units();
            use estimator_core::drive::CommandError as E;
            match checker.check_move(target_um, velocity_um_s, accel_um_s2) {
                Ok(()) => {}
                Err(E::TargetOutOfTravel) => {
                    return Err(format!(
                        "{src}: move {n}: to_mm = {} mm is outside the drive's travel {}..={} mm",
                        show(m.to_mm),
                        drive.travel_min_mm,
                        drive.travel_max_mm
                    ))
                }
                Err(E::VelocityOutOfRange) => {
                    return Err(format!(
                        "{src}: move {n}: velocity_mm_s = {} must be in 0.001..={} mm/s (the \
                         drive's limit; it takes whole um/s)",
                        show(m.velocity_mm_s),
                        drive.max_velocity_mm_s
                    ))
                }
                Err(_) => {
                    return Err(format!(
                        "{src}: move {n}: accel_mm_s2 = {} must be in 0.001..={} mm/s^2 (the \
                         drive's limit; it takes whole um/s^2)",
                        show(m.accel_mm_s2),
                        drive.max_accel_mm_s2
                    ))
                }
            }
            if !in_plant(m.to_mm) {
                return Err(format!(
                    "{src}: move {n}: to_mm = {} mm is outside the plant's travel {}..={} mm \
                     (carriage.travel_min_m, carriage.travel_max_m of {plant_name})",
                    show(m.to_mm),
                    plant_mm.0,
                    plant_mm.1
                ));
            }
        }
        Ok(())
    }

    /// Checks ranges: finite numbers, positive speeds, travel within 0..=2000 mm.
    pub fn validate(&self) -> Result<(), String> {
        let travel = |v: f64| v.is_finite() && (0.0..=2000.0).contains(&v);
        if !travel(self.start_mm) {
            return Err(format!(
                "start_mm = {} is outside 0..=2000 mm",
                show(self.start_mm)
            ));
        }
        if self.moves.is_empty() {
            return Err("a scenario needs at least one [[move]]".into());
        }
        for (i, m) in self.moves.iter().enumerate() {
            let n = i + 1;
            if !travel(m.to_mm) {
                return Err(format!(
                    "move {n}: to_mm = {} is outside 0..=2000 mm",
                    show(m.to_mm)
                ));
            }
            // The drive takes whole um/s and um/s^2: 0.001 is the least it can be asked for.
            if !(m.velocity_mm_s.is_finite() && (0.001..=1000.0).contains(&m.velocity_mm_s)) {
                return Err(format!(
                    "move {n}: velocity_mm_s = {} must be in 0.001..=1000",
                    show(m.velocity_mm_s)
                ));
            }
            if !(m.accel_mm_s2.is_finite() && (0.001..=50_000.0).contains(&m.accel_mm_s2)) {
                return Err(format!(
                    "move {n}: accel_mm_s2 = {} must be in 0.001..=50000",
                    show(m.accel_mm_s2)
                ));
            }
            if m.retarget_after_ms == Some(0) {
                return Err(format!("move {n}: retarget_after_ms must be > 0"));
            }
            if m.retarget_after_ms.is_some() && n == self.moves.len() {
                return Err(format!(
                    "move {n}: retarget_after_ms on the last move: there is no next move to \
                     start (the run would end mid-move); remove it"
                ));
            }
        }
        let t = self.duration_estimate_s();
        if t > MAX_DURATION_S {
            // Name the move that takes longest, and what makes it long.
            let mut x = self.start_mm;
            let mut worst = (0usize, 0.0f64, "");
            for (i, m) in self.moves.iter().enumerate() {
                let parts = [
                    ((m.to_mm - x).abs() / m.velocity_mm_s, "velocity_mm_s"),
                    (2.0 * m.velocity_mm_s / m.accel_mm_s2, "accel_mm_s2"),
                    (m.dwell_ms as f64 / 1000.0, "dwell_ms"),
                ];
                let (ti, field) = parts
                    .iter()
                    .fold((0.0, ""), |a, &(t, f)| if t > a.0 { (t, f) } else { a });
                let total: f64 = parts.iter().map(|p| p.0).sum();
                if total > worst.1 {
                    worst = (i + 1, total, if ti > 0.0 { field } else { "" });
                }
                x = m.to_mm;
            }
            return Err(format!(
                "the moves and dwells take about {t:.3e} s of simulated time; a run is limited to \
                 {MAX_DURATION_S:.0} s; the longest is move {} ({:.3e} s, mostly its {})",
                worst.0, worst.1, worst.2
            ));
        }
        Ok(())
    }
}

/// A number as a person reads it: plain, or in scientific notation when very large or small.
fn show(v: f64) -> String {
    if v == 0.0 || (1e-4..1e9).contains(&v.abs()) || !v.is_finite() {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Comma-separated preset names, for error messages and `--help`.
pub fn preset_names() -> String {
    PRESETS
        .iter()
        .map(|(n, _)| *n)
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_parse_and_validate() {
        for (name, text) in PRESETS {
            let s = Scenario::from_toml_str(text).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(&s.name, name);
        }
    }

    #[test]
    fn errors_name_the_move_and_field() {
        let bad = "name='x'\nstart_mm=10\n[[move]]\nto_mm=20\nvelocity_mm_s=-1\naccel_mm_s2=100\n";
        let e = Scenario::from_toml_str(bad).unwrap_err();
        assert!(e.contains("move 1") && e.contains("velocity_mm_s"), "{e}");
        let unknown = "name='x'\nstart_mm=10\n[[move]]\nto_mm=20\nvelocity_mm_s=1\naccel_mm_s2=100\nspeed=3\n";
        assert!(Scenario::from_toml_str(unknown)
            .unwrap_err()
            .contains("speed"));
        assert!(Scenario::load("no-such-file.toml")
            .unwrap_err()
            .contains("fig18"));
    }
}
