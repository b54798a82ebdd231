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

use crate::input::show;
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

/// Why a scenario was refused: the file, the place in the TOML, or the move (counted from 1)
/// and the field out of its range, its own or the drive's and the plant's.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// The file could not be read (and it is no preset's name).
    #[error("scenario {path}: {source} (presets: {})", preset_names())]
    Io {
        /// What was given.
        path: String,
        /// What the system said.
        source: std::io::Error,
    },
    /// Not a scenario in TOML (a syntax error, a missing or unknown key), with line and column.
    #[error("{0}")]
    Toml(crate::input::TomlError),
    /// A field out of its range: the scenario's own, the drive's or the plant's.
    #[error("{}{field} = {value} {rule}", at_move(*move_n))]
    Field {
        /// The move, counted from 1 (`None`: the scenario's `start_mm`).
        move_n: Option<usize>,
        /// The field, e.g. `velocity_mm_s`.
        field: &'static str,
        /// Its value as written.
        value: String,
        /// The rule it breaks, with the limit and whose it is.
        rule: String,
    },
    /// No moves.
    #[error("a scenario needs at least one [[move]]")]
    NoMoves,
    /// A retarget that cannot work (the field is `retarget_after_ms`).
    #[error("move {move_n}: {reason}")]
    Retarget {
        /// The move, counted from 1.
        move_n: usize,
        /// Why.
        reason: &'static str,
    },
    /// The run would be longer than a run may be.
    #[error(
        "the moves and dwells take about {seconds:.3e} s of simulated time; a run is limited to \
         {MAX_DURATION_S:.0} s; the longest is move {longest_move} ({longest_s:.3e} s, mostly its \
         {mostly})"
    )]
    TooLong {
        /// The estimate, seconds.
        seconds: f64,
        /// The longest move, counted from 1.
        longest_move: usize,
        /// Its estimate, seconds.
        longest_s: f64,
        /// The field that makes it long.
        mostly: &'static str,
    },
    /// The drive configuration the scenario is checked against was refused.
    #[error("drive configuration: {0}")]
    Drive(estimator_core::ConfigError),
    /// One of the above, in a file or preset.
    #[error("{file}: {error}")]
    InFile {
        /// The file, or `preset NAME`.
        file: String,
        /// What is wrong in it.
        error: Box<ScenarioError>,
    },
}

fn at_move(n: Option<usize>) -> String {
    n.map_or(String::new(), |n| format!("move {n}: "))
}

impl ScenarioError {
    /// This error in the file or preset `source`.
    pub fn in_file(self, source: &str) -> ScenarioError {
        ScenarioError::InFile {
            file: source.to_string(),
            error: Box::new(self),
        }
    }

    /// The innermost error (what is wrong, without where).
    pub fn cause(&self) -> &ScenarioError {
        match self {
            ScenarioError::InFile { error, .. } => error.cause(),
            e => e,
        }
    }
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
    pub fn from_toml_str(text: &str) -> Result<Scenario, ScenarioError> {
        let s: Scenario = crate::input::from_toml(text).map_err(ScenarioError::Toml)?;
        s.validate()?;
        Ok(s)
    }

    /// Loads a file path, or a shipped preset by name (`fig18`, `reversals`, ...).
    pub fn load(path_or_preset: &str) -> Result<Scenario, ScenarioError> {
        if let Some((name, text)) = PRESETS.iter().find(|(n, _)| *n == path_or_preset) {
            let source = format!("preset {name}");
            let mut s = Scenario::from_toml_str(text).map_err(|e| e.in_file(&source))?;
            s.source = source;
            return Ok(s);
        }
        let text = crate::input::read_text(path_or_preset).map_err(|source| ScenarioError::Io {
            path: path_or_preset.to_string(),
            source,
        })?;
        let mut s = Scenario::from_toml_str(&text).map_err(|e| e.in_file(path_or_preset))?;
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

    /// Estimated duration, seconds: each move at its cruise speed plus its ramps, its dwell;
    /// a move that is retargeted lasts until the next one starts if that is later. An upper
    /// bound of a run's length up to a factor of two (the run's time-out).
    pub fn duration_estimate_s(&self) -> f64 {
        self.move_times_s().map(|(t, _)| t).sum()
    }

    /// Each move's share of [`Scenario::duration_estimate_s`], with the field that makes most
    /// of it (`""` for a move that takes no time).
    fn move_times_s(&self) -> impl Iterator<Item = (f64, &'static str)> + '_ {
        let froms = core::iter::once(self.start_mm).chain(self.moves.iter().map(|m| m.to_mm));
        self.moves.iter().zip(froms).map(|(m, x)| {
            let parts = [
                ((m.to_mm - x).abs() / m.velocity_mm_s, "velocity_mm_s"),
                (2.0 * m.velocity_mm_s / m.accel_mm_s2, "accel_mm_s2"),
                (m.dwell_ms as f64 / 1000.0, "dwell_ms"),
            ];
            let full: f64 = parts.iter().map(|p| p.0).sum();
            let (most, field) = parts
                .iter()
                .fold((0.0, ""), |a, &(t, f)| if t > a.0 { (t, f) } else { a });
            match m.retarget_after_ms.map(|ms| ms as f64 / 1000.0) {
                Some(wait) if wait > full => (wait, "retarget_after_ms"),
                _ => (full, if most > 0.0 { field } else { "" }),
            }
        })
    }

    /// Checks the scenario against the drive's limits (the checks `Drive::command` makes, in
    /// the units it receives) and the plant's travel, before anything runs. Errors name the
    /// scenario, the move (counted from 1) and the field.
    pub fn check_against(
        &self,
        drive: &DriveConfig,
        plant: &PlantParams,
    ) -> Result<(), ScenarioError> {
        self.check_limits(drive, plant)
            .map_err(|e| e.in_file(self.source()))
    }

    fn check_limits(&self, drive: &DriveConfig, plant: &PlantParams) -> Result<(), ScenarioError> {
        let plant_mm = (
            plant.carriage.travel_min_m * 1e3,
            plant.carriage.travel_max_m * 1e3,
        );
        let in_plant = |v: f64| (plant_mm.0..=plant_mm.1).contains(&v);
        let plant_name = plant.name();
        let outside_plant = |move_n, v| ScenarioError::Field {
            move_n,
            field: if move_n.is_some() {
                "to_mm"
            } else {
                "start_mm"
            },
            value: show(v),
            rule: format!(
                "mm is outside the plant's travel {}..={} mm (carriage.travel_min_m, \
                 carriage.travel_max_m of {plant_name})",
                plant_mm.0, plant_mm.1
            ),
        };
        if !in_plant(self.start_mm) {
            return Err(outside_plant(None, self.start_mm));
        }
        // The drive trips its travel limit at once where it starts beyond its travel's margin.
        let st = &drive.settings;
        let (d0, d1) = (
            st.travel_min_mm - st.travel_margin_mm,
            st.travel_max_mm + st.travel_margin_mm,
        );
        if !(d0..=d1).contains(&self.start_mm) {
            return Err(ScenarioError::Field {
                move_n: None,
                field: "start_mm",
                value: show(self.start_mm),
                rule: format!(
                    "mm is beyond the drive's travel and its margin, {d0}..={d1} mm (the drive \
                     would stop at once on its travel limit)"
                ),
            });
        }
        // The drive's own range checks, on the integers the run will send.
        let checker = estimator_core::drive::Drive::new(drive).map_err(ScenarioError::Drive)?;
        for (i, m) in self.moves.iter().enumerate() {
            let n = i + 1;
            let (target_um, velocity_um_s, accel_um_s2) = m.drive_units();
            use estimator_core::drive::CommandError as E;
            let field = |field, v: f64, rule| ScenarioError::Field {
                move_n: Some(n),
                field,
                value: show(v),
                rule,
            };
            match checker.check_move(target_um, velocity_um_s, accel_um_s2) {
                Ok(()) => {}
                Err(E::TargetOutOfTravel) => {
                    return Err(field(
                        "to_mm",
                        m.to_mm,
                        format!(
                            "mm is outside the drive's travel {}..={} mm",
                            drive.settings.travel_min_mm, drive.settings.travel_max_mm
                        ),
                    ))
                }
                Err(E::VelocityOutOfRange) => {
                    return Err(field(
                        "velocity_mm_s",
                        m.velocity_mm_s,
                        format!(
                            "must be in 0.001..={} mm/s (the drive's limit; it takes whole um/s)",
                            drive.settings.max_velocity_mm_s
                        ),
                    ))
                }
                Err(_) => {
                    return Err(field(
                        "accel_mm_s2",
                        m.accel_mm_s2,
                        format!(
                            "must be in 0.001..={} mm/s^2 (the drive's limit; it takes whole \
                             um/s^2)",
                            drive.settings.max_accel_mm_s2
                        ),
                    ))
                }
            }
            if !in_plant(m.to_mm) {
                return Err(outside_plant(Some(n), m.to_mm));
            }
        }
        Ok(())
    }

    /// Checks ranges: finite numbers, positive speeds, travel within 0..=2000 mm.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let travel = |v: f64| v.is_finite() && (0.0..=2000.0).contains(&v);
        let field = |move_n, field, v: f64, rule: &str| ScenarioError::Field {
            move_n,
            field,
            value: show(v),
            rule: rule.to_string(),
        };
        // The name goes into messages, tables and file names (`report` writes `NAME.csv`):
        // printable, one line, no path separator.
        if self.name.is_empty()
            || self.name.len() > 200
            || self
                .name
                .chars()
                .any(|c| c.is_control() || c == '/' || c == '\\')
        {
            return Err(ScenarioError::Field {
                move_n: None,
                field: "name",
                value: format!("{:?}", self.name.chars().take(40).collect::<String>()),
                rule: "must be 1 to 200 bytes without control characters or path separators \
                       (it names files)"
                    .into(),
            });
        }
        if !travel(self.start_mm) {
            return Err(field(
                None,
                "start_mm",
                self.start_mm,
                "is outside 0..=2000 mm",
            ));
        }
        if self.moves.is_empty() {
            return Err(ScenarioError::NoMoves);
        }
        for (i, m) in self.moves.iter().enumerate() {
            let n = Some(i + 1);
            if !travel(m.to_mm) {
                return Err(field(n, "to_mm", m.to_mm, "is outside 0..=2000 mm"));
            }
            // The drive takes whole um/s and um/s^2: 0.001 is the least it can be asked for.
            if !(m.velocity_mm_s.is_finite() && (0.001..=1000.0).contains(&m.velocity_mm_s)) {
                return Err(field(
                    n,
                    "velocity_mm_s",
                    m.velocity_mm_s,
                    "must be in 0.001..=1000",
                ));
            }
            if !(m.accel_mm_s2.is_finite() && (0.001..=50_000.0).contains(&m.accel_mm_s2)) {
                return Err(field(
                    n,
                    "accel_mm_s2",
                    m.accel_mm_s2,
                    "must be in 0.001..=50000",
                ));
            }
            if m.retarget_after_ms == Some(0) {
                return Err(ScenarioError::Retarget {
                    move_n: i + 1,
                    reason: "retarget_after_ms must be > 0",
                });
            }
            if m.retarget_after_ms.is_some() && i + 1 == self.moves.len() {
                return Err(ScenarioError::Retarget {
                    move_n: i + 1,
                    reason: "retarget_after_ms on the last move: there is no next move to \
                             start (the run would end mid-move); remove it",
                });
            }
        }
        let t = self.duration_estimate_s();
        if t > MAX_DURATION_S {
            // Name the move that takes longest, and what makes it long.
            let worst =
                self.move_times_s()
                    .enumerate()
                    .fold((0usize, 0.0f64, ""), |w, (i, (t, field))| {
                        if t > w.1 {
                            (i + 1, t, field)
                        } else {
                            w
                        }
                    });
            return Err(ScenarioError::TooLong {
                seconds: t,
                longest_move: worst.0,
                longest_s: worst.1,
                mostly: worst.2,
            });
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
        assert!(
            matches!(
                e,
                ScenarioError::Field {
                    move_n: Some(1),
                    field: "velocity_mm_s",
                    ..
                }
            ),
            "{e:?}"
        );
        let text = e.to_string();
        assert!(
            text.starts_with("move 1: velocity_mm_s = -1 must be in"),
            "{text}"
        );
        let unknown = "name='x'\nstart_mm=10\n[[move]]\nto_mm=20\nvelocity_mm_s=1\naccel_mm_s2=100\nspeed=3\n";
        let e = Scenario::from_toml_str(unknown).unwrap_err();
        assert!(
            matches!(&e, ScenarioError::Toml(t) if t.message.contains("speed")),
            "{e:?}"
        );
        let e = Scenario::load("no-such-file.toml").unwrap_err();
        assert!(matches!(e, ScenarioError::Io { .. }), "{e:?}");
        assert!(e.to_string().contains("fig18"), "{e}");
        for name in [
            "''",
            "\"a\\u001b[31mred\"",
            "\"two\\nlines\"",
            "'../../outside'",
            "'a\\b'",
        ] {
            let bad = format!(
                "name={name}\nstart_mm=10\n[[move]]\nto_mm=20\nvelocity_mm_s=1\naccel_mm_s2=100\n"
            );
            let e = Scenario::from_toml_str(&bad).unwrap_err().to_string();
            assert!(
                e.starts_with("name = ") && e.contains("control characters"),
                "{e}"
            );
            assert!(!e.contains('\u{1b}') && !e.contains('\n'), "{e}");
        }
        let empty = "name='x'\nstart_mm=10\nmove=[]\n";
        assert!(matches!(
            Scenario::from_toml_str(empty).unwrap_err(),
            ScenarioError::NoMoves
        ));
        let last = "name='x'\nstart_mm=10\n[[move]]\nto_mm=20\nvelocity_mm_s=1\naccel_mm_s2=100\nretarget_after_ms=5\n";
        assert!(matches!(
            Scenario::from_toml_str(last).unwrap_err(),
            ScenarioError::Retarget { move_n: 1, .. }
        ));
    }

    #[test]
    fn limits_of_the_drive_and_the_plant_name_the_scenario_move_and_field() {
        let plant = PlantParams::paper_rig();
        let drive = crate::drive_setup::drive_limits(plant.rig());
        let mut s = Scenario::load("fig18").unwrap();
        s.moves[2].velocity_mm_s = drive.settings.max_velocity_mm_s * 2.0;
        let e = s.check_against(&drive, &plant).unwrap_err();
        assert!(
            matches!(
                e.cause(),
                ScenarioError::Field {
                    move_n: Some(3),
                    field: "velocity_mm_s",
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(
            e.to_string()
                .starts_with("preset fig18: move 3: velocity_mm_s = "),
            "{e}"
        );
        let mut s = Scenario::load("fig18").unwrap();
        s.start_mm = plant.carriage.travel_max_m * 1e3 + 1.0;
        let e = s.check_against(&drive, &plant).unwrap_err();
        assert!(
            matches!(
                e.cause(),
                ScenarioError::Field {
                    move_n: None,
                    field: "start_mm",
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(e.to_string().contains("outside the plant's travel"), "{e}");
    }
}
