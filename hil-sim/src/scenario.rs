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

use serde::Deserialize;

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
        let s: Scenario = toml::from_str(text).map_err(|e| format!("scenario: {e}"))?;
        s.validate()?;
        Ok(s)
    }

    /// Loads a file path, or a shipped preset by name (`fig18`, `reversals`, ...).
    pub fn load(path_or_preset: &str) -> Result<Scenario, String> {
        if let Some((_, text)) = PRESETS.iter().find(|(n, _)| *n == path_or_preset) {
            return Scenario::from_toml_str(text);
        }
        let text = std::fs::read_to_string(path_or_preset).map_err(|e| {
            format!(
                "scenario {path_or_preset}: {e} (presets: {})",
                preset_names()
            )
        })?;
        Scenario::from_toml_str(&text).map_err(|e| format!("{path_or_preset}: {e}"))
    }

    /// Checks ranges: finite numbers, positive speeds, travel within 0..=2000 mm.
    pub fn validate(&self) -> Result<(), String> {
        let travel = |v: f64| v.is_finite() && (0.0..=2000.0).contains(&v);
        if !travel(self.start_mm) {
            return Err(format!(
                "start_mm = {} is outside 0..=2000 mm",
                self.start_mm
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
                    m.to_mm
                ));
            }
            if !(m.velocity_mm_s.is_finite() && m.velocity_mm_s > 0.0 && m.velocity_mm_s <= 1000.0)
            {
                return Err(format!(
                    "move {n}: velocity_mm_s = {} must be in (0, 1000]",
                    m.velocity_mm_s
                ));
            }
            if !(m.accel_mm_s2.is_finite() && m.accel_mm_s2 > 0.0 && m.accel_mm_s2 <= 50_000.0) {
                return Err(format!(
                    "move {n}: accel_mm_s2 = {} must be in (0, 50000]",
                    m.accel_mm_s2
                ));
            }
            if m.retarget_after_ms == Some(0) {
                return Err(format!("move {n}: retarget_after_ms must be > 0"));
            }
        }
        Ok(())
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
