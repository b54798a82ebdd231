//! The region of motion a calibration covers, and the moves of a run that leave it.
//!
//! Every model is fitted on the same recordings, so the region is one: the travel the moves
//! span and the (peak speed, acceleration) pairs they reach. Outside it every model
//! extrapolates: Model 3's tables are held flat, Model 4's gross-slip threshold is a guess where
//! no move loaded the belt that hard. A run is checked move by move against it, so that a user
//! learns which of their motions the calibration never made.

use std::collections::BTreeMap;
use std::fmt;

use crate::scenario::Scenario;

/// Half-octave band of a positive quantity: band `k` holds `[2^(k/2), 2^((k+1)/2))`.
pub fn band(x: f64) -> i32 {
    (2.0 * x.max(1e-9).log2()).floor() as i32
}

/// Lower edge of half-octave band `k`.
pub fn band_floor(k: i32) -> f64 {
    2f64.powf(k as f64 / 2.0)
}

/// A move judged inside when some calibration move is within this many half-octave bands in
/// both speed and acceleration (two bands: a factor of 2 to 2.8, as the values fall in their
/// bands; a move flagged outside has no calibration move within a factor of two).
pub const NEAR_BANDS: i32 = 2;

/// Positions may lie this far beyond the calibrated travel, mm.
pub const TRAVEL_SLACK_MM: f64 = 0.5;

/// One move as the coverage sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MoveExtent {
    /// Lowest and highest position the move passes, mm.
    pub span_mm: [f64; 2],
    /// The highest speed it reaches, mm/s (its cruise speed, or less on a short or cut move).
    pub peak_mm_s: f64,
    /// Its acceleration, mm/s².
    pub accel_mm_s2: f64,
}

/// Distance covered and speed `t_s` into a symmetric trapezoid of length `d`, top speed `vp`
/// and acceleration `a`.
fn trapezoid_at(d: f64, vp: f64, a: f64, t_s: f64) -> (f64, f64) {
    let ta = vp / a;
    let da = vp * vp / (2.0 * a);
    let tc = ((d - 2.0 * da) / vp).max(0.0);
    if t_s <= ta {
        (0.5 * a * t_s * t_s, a * t_s)
    } else if t_s <= ta + tc {
        (da + vp * (t_s - ta), vp)
    } else if t_s <= 2.0 * ta + tc {
        let tau = t_s - ta - tc;
        (da + vp * tc + vp * tau - 0.5 * a * tau * tau, vp - a * tau)
    } else {
        (d, 0.0)
    }
}

/// The moves of `scenario` that travel, with where each starts (the previous target, or where
/// a retargeted move had reached when the next one was commanded). A move that follows a cut
/// starts at the speed of the cut: it reaches at least that speed, and where it cannot stop
/// short of its target or turns back it brakes past where it was (the drive's replanning).
pub fn extents(scenario: &Scenario) -> Vec<(usize, MoveExtent)> {
    // Targets as the drive takes them, on its micrometre grid.
    let um = |x: f64| (x * 1000.0).round() / 1000.0;
    let mut out = Vec::new();
    let mut x = um(scenario.start_mm);
    // Speed and direction at a cut, carried into the next move.
    let mut carry: Option<(f64, f64)> = None;
    for (i, m) in scenario.moves.iter().enumerate() {
        let to = um(m.to_mm);
        let d = (to - x).abs();
        let (v, a) = (m.velocity_mm_s, m.accel_mm_s2);
        let moving = carry.is_some_and(|(v0, _)| v0 > 0.0);
        if !((d > 0.0 || moving) && v > 0.0 && a > 0.0) {
            x = to;
            carry = None;
            continue;
        }
        let vp = v.min((a * d).sqrt());
        let (peak, end, next) = match m.retarget_after_ms {
            Some(ms) if d > 0.0 => {
                let t = ms as f64 / 1000.0;
                let dir = (to - x).signum();
                let (s, v_cut) = trapezoid_at(d, vp, a, t);
                (vp.min(a * t), x + dir * s.min(d), Some((v_cut, dir)))
            }
            _ => (vp, to, None),
        };
        let (mut lo, mut hi) = (x.min(end), x.max(end));
        let mut peak = peak;
        if let Some((v0, dir0)) = carry {
            let braked = x + dir0 * v0 * v0 / (2.0 * a);
            lo = lo.min(braked);
            hi = hi.max(braked);
            peak = peak.max(v0);
        }
        out.push((
            i,
            MoveExtent {
                span_mm: [lo, hi],
                peak_mm_s: peak,
                accel_mm_s2: a,
            },
        ));
        x = end;
        carry = next;
    }
    out
}

/// What a calibration's moves covered.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Coverage {
    /// Lowest and highest position the moves passed, mm.
    pub travel_mm: [f64; 2],
    /// Moves per (speed band, acceleration band), half-octave bands (see [`band`]).
    pub cells: BTreeMap<(i32, i32), u32>,
}

/// Why a move of a run is outside the calibration's region.
#[derive(Clone, Debug, PartialEq)]
pub enum Outside {
    /// No calibration move within a factor of two in both speed and acceleration.
    SpeedAccel {
        /// Index of the move in its scenario.
        index: usize,
        /// Its peak speed, mm/s.
        peak_mm_s: f64,
        /// Its acceleration, mm/s².
        accel_mm_s2: f64,
    },
    /// It passes positions the calibration never reached.
    Travel {
        /// Index of the move in its scenario.
        index: usize,
        /// Its lowest and highest position, mm.
        span_mm: [f64; 2],
    },
}

impl fmt::Display for Outside {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Outside::SpeedAccel {
                index,
                peak_mm_s,
                accel_mm_s2,
            } => write!(
                f,
                "move {}: {} mm/s at {} mm/s²",
                index + 1,
                fmt_value(*peak_mm_s),
                fmt_value(*accel_mm_s2)
            ),
            Outside::Travel { index, span_mm } => write!(
                f,
                "move {}: {:.1}-{:.1} mm",
                index + 1,
                span_mm[0],
                span_mm[1]
            ),
        }
    }
}

/// A run's moves checked against a coverage.
#[derive(Clone, Debug, PartialEq)]
pub struct Check {
    /// The scenario's name.
    pub scenario: String,
    /// Its moves that travel, as [`extents`] gives them.
    pub extents: Vec<(usize, MoveExtent)>,
    /// Moves outside in speed and acceleration, and moves outside the travel.
    pub outside: Vec<Outside>,
    /// The calibrated travel, mm.
    pub travel_mm: [f64; 2],
}

impl Check {
    /// Moves that travel.
    pub fn moves(&self) -> usize {
        self.extents.len()
    }

    /// Moves outside in speed and acceleration.
    pub fn speed_accel(&self) -> usize {
        self.outside
            .iter()
            .filter(|o| matches!(o, Outside::SpeedAccel { .. }))
            .count()
    }

    /// Moves outside the calibrated travel.
    pub fn travel(&self) -> usize {
        self.outside
            .iter()
            .filter(|o| matches!(o, Outside::Travel { .. }))
            .count()
    }

    /// Moves outside in any way (each counted once).
    pub fn moves_outside(&self) -> usize {
        let mut idx: Vec<usize> = self
            .outside
            .iter()
            .map(|o| match o {
                Outside::SpeedAccel { index, .. } | Outside::Travel { index, .. } => *index,
            })
            .collect();
        idx.dedup();
        idx.len()
    }

    /// The warning for people, when any move leaves the region: counts and the first examples
    /// of each kind.
    pub fn warning(&self) -> Option<String> {
        if self.outside.is_empty() {
            return None;
        }
        let examples = |speed: bool| {
            let all: Vec<String> = self
                .outside
                .iter()
                .filter(|o| matches!(o, Outside::SpeedAccel { .. }) == speed)
                .map(|o| o.to_string())
                .collect();
            let mut s = all.iter().take(3).cloned().collect::<Vec<_>>().join("; ");
            if all.len() > 3 {
                s += &format!("; and {} more", all.len() - 3);
            }
            s
        };
        let mut parts = Vec::new();
        if self.speed_accel() > 0 {
            parts.push(format!(
                "{} of {} moves with no calibration move within a factor of two in both peak \
                 speed and acceleration ({})",
                self.speed_accel(),
                self.moves(),
                examples(true)
            ));
        }
        if self.travel() > 0 {
            parts.push(format!(
                "{} of {} moves outside the calibrated travel {:.1}-{:.1} mm ({})",
                self.travel(),
                self.moves(),
                self.travel_mm[0],
                self.travel_mm[1],
                examples(false)
            ));
        }
        Some(format!(
            "{} leaves the calibrated region: {}. Every model extrapolates there: add such moves \
             to the calibration (`--scenario`).",
            self.scenario,
            parts.join("; ")
        ))
    }
}

impl Coverage {
    /// The region the moves of `scenarios` cover.
    pub fn of<'a>(scenarios: impl IntoIterator<Item = &'a Scenario>) -> Coverage {
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let mut cells = BTreeMap::new();
        for s in scenarios {
            lo = lo.min(s.start_mm);
            hi = hi.max(s.start_mm);
            for (_, e) in extents(s) {
                lo = lo.min(e.span_mm[0]);
                hi = hi.max(e.span_mm[1]);
                *cells
                    .entry((band(e.peak_mm_s), band(e.accel_mm_s2)))
                    .or_insert(0) += 1;
            }
        }
        if lo > hi {
            (lo, hi) = (0.0, 0.0);
        }
        Coverage {
            travel_mm: [lo, hi],
            cells,
        }
    }

    /// True when a calibration move lies within [`NEAR_BANDS`] of cell `(sb, ab)`.
    fn near(&self, sb: i32, ab: i32) -> bool {
        self.cells
            .keys()
            .any(|&(s, a)| (s - sb).abs() <= NEAR_BANDS && (a - ab).abs() <= NEAR_BANDS)
    }

    /// The highest speed band and acceleration band any move reached.
    fn top_bands(&self) -> Option<(i32, i32)> {
        let s = self.cells.keys().map(|c| c.0).max()?;
        let a = self.cells.keys().map(|c| c.1).max()?;
        Some((s, a))
    }

    /// The highest peak speed (mm/s) and acceleration (mm/s²) the moves reached, to within
    /// their half-octave band (the band's upper edge); `None` without moves.
    pub fn reach(&self) -> Option<(f64, f64)> {
        let (s, a) = self.top_bands()?;
        Some((band_floor(s + 1), band_floor(a + 1)))
    }

    /// What a drive allowed `max_velocity_mm_s` and `max_accel_mm_s2` may do beyond this
    /// region: a sentence per limit that no calibration move comes within a factor of two of.
    pub fn short_of(&self, max_velocity_mm_s: f64, max_accel_mm_s2: f64) -> Vec<String> {
        let (Some((top_s, top_a)), Some((v, a))) = (self.top_bands(), self.reach()) else {
            return vec!["no calibration move travels".into()];
        };
        let mut out = Vec::new();
        if band(max_velocity_mm_s) > top_s + NEAR_BANDS {
            out.push(format!(
                "the calibration's moves reach {} mm/s at most and the drive allows {}: faster \
                 moves are outside the calibrated region",
                fmt_value(v),
                fmt_value(max_velocity_mm_s)
            ));
        }
        if band(max_accel_mm_s2) > top_a + NEAR_BANDS {
            out.push(format!(
                "the calibration's moves reach {} mm/s² at most and the drive allows {}: \
                 moves that accelerate harder are outside the calibrated region",
                fmt_value(a),
                fmt_value(max_accel_mm_s2)
            ));
        }
        out
    }

    /// The moves of `scenario` outside this region.
    pub fn check(&self, scenario: &Scenario) -> Check {
        let ext = extents(scenario);
        let mut outside = Vec::new();
        for &(index, e) in &ext {
            if !self.near(band(e.peak_mm_s), band(e.accel_mm_s2)) {
                outside.push(Outside::SpeedAccel {
                    index,
                    peak_mm_s: e.peak_mm_s,
                    accel_mm_s2: e.accel_mm_s2,
                });
            }
            if e.span_mm[0] < self.travel_mm[0] - TRAVEL_SLACK_MM
                || e.span_mm[1] > self.travel_mm[1] + TRAVEL_SLACK_MM
            {
                outside.push(Outside::Travel {
                    index,
                    span_mm: e.span_mm,
                });
            }
        }
        Check {
            scenario: scenario.name.clone(),
            extents: ext,
            outside,
            travel_mm: self.travel_mm,
        }
    }

    /// A table for people: moves per octave of acceleration (rows) and of peak speed (columns).
    pub fn markdown(&self) -> String {
        let oct = |k: i32| k.div_euclid(2);
        // u64: four half-octave cells of a stored file's u32 counts add without overflow.
        let mut grid: BTreeMap<(i32, i32), u64> = BTreeMap::new();
        for (&(s, a), &n) in &self.cells {
            *grid.entry((oct(a), oct(s))).or_insert(0) += u64::from(n);
        }
        let (Some(s_lo), Some(s_hi)) = (
            grid.keys().map(|k| k.1).min(),
            grid.keys().map(|k| k.1).max(),
        ) else {
            return "no calibration moves\n".into();
        };
        let mut out = format!(
            "Calibrated travel {:.1}-{:.1} mm. Moves per band of acceleration (rows, mm/s²) and \
             peak speed (columns, mm/s):\n\n| mm/s² \\ mm/s |",
            self.travel_mm[0], self.travel_mm[1]
        );
        for s in s_lo..=s_hi {
            out += &format!(" {}-{} |", fmt_edge(2 * s), fmt_edge(2 * s + 2));
        }
        out += "\n|---|";
        out += &"---:|".repeat((s_hi - s_lo + 1) as usize);
        out += "\n";
        let rows: Vec<i32> = grid.keys().map(|k| k.0).collect();
        let (a_lo, a_hi) = (rows[0], rows[rows.len() - 1]);
        for a in a_lo..=a_hi {
            out += &format!("| {}-{} |", fmt_edge(2 * a), fmt_edge(2 * a + 2));
            for s in s_lo..=s_hi {
                match grid.get(&(a, s)) {
                    Some(n) => out += &format!(" {n} |"),
                    None => out += " |",
                }
            }
            out += "\n";
        }
        out
    }

    /// The region as `calibration.toml` holds it.
    pub fn to_toml(&self) -> toml::Table {
        let mut t = toml::Table::new();
        t.insert(
            "travel_mm".into(),
            toml::Value::Array(
                self.travel_mm
                    .iter()
                    .map(|x| toml::Value::Float((x * 1e3).round() / 1e3))
                    .collect(),
            ),
        );
        t.insert(
            "half_octave_cells".into(),
            toml::Value::Array(
                self.cells
                    .iter()
                    .map(|(&(s, a), &n)| {
                        toml::Value::Array(vec![
                            toml::Value::Integer(s.into()),
                            toml::Value::Integer(a.into()),
                            toml::Value::Integer(n.into()),
                        ])
                    })
                    .collect(),
            ),
        );
        t
    }

    /// Reads [`Coverage::to_toml`]'s table; the error names the field.
    pub fn from_toml(t: &toml::Table) -> Result<Coverage, String> {
        if let Some(k) = t
            .keys()
            .find(|k| !["travel_mm", "half_octave_cells"].contains(&k.as_str()))
        {
            return Err(format!("coverage.{k}: not a coverage field"));
        }
        let travel = match t.get("travel_mm") {
            Some(toml::Value::Array(a)) if a.len() == 2 => {
                let x: Vec<f64> = a
                    .iter()
                    .filter_map(|v| match v {
                        toml::Value::Float(f) => Some(*f),
                        toml::Value::Integer(i) => Some(*i as f64),
                        _ => None,
                    })
                    .filter(|f| f.is_finite())
                    .collect();
                if x.len() != 2 || x[0] > x[1] {
                    return Err("coverage.travel_mm: two finite numbers, lowest first".into());
                }
                [x[0], x[1]]
            }
            _ => return Err("coverage.travel_mm: two finite numbers, lowest first".into()),
        };
        let mut cells = BTreeMap::new();
        let Some(toml::Value::Array(rows)) = t.get("half_octave_cells") else {
            return Err("coverage.half_octave_cells: missing or not a list".into());
        };
        for (i, r) in rows.iter().enumerate() {
            let bad = || {
                format!(
                    "coverage.half_octave_cells[{i}]: [speed band, acceleration band, moves] as \
                     integers (bands within +-64, moves >= 1)"
                )
            };
            let toml::Value::Array(r) = r else {
                return Err(bad());
            };
            let n: Vec<i64> = r
                .iter()
                .filter_map(|v| match v {
                    toml::Value::Integer(i) => Some(*i),
                    _ => None,
                })
                .collect();
            let band_ok = |b: i64| (-64..=64).contains(&b);
            if n.len() != 3 || r.len() != 3 || !band_ok(n[0]) || !band_ok(n[1]) || n[2] < 1 {
                return Err(bad());
            }
            let moves = u32::try_from(n[2]).map_err(|_| bad())?;
            if cells.insert((n[0] as i32, n[1] as i32), moves).is_some() {
                return Err(format!(
                    "coverage.half_octave_cells[{i}]: cell [{}, {}] is listed twice",
                    n[0], n[1]
                ));
            }
        }
        Ok(Coverage {
            travel_mm: travel,
            cells,
        })
    }
}

/// A value for people: integers from 10 up, one decimal down to 0.1, three below.
pub(crate) fn fmt_value(x: f64) -> String {
    if x >= 10.0 {
        format!("{x:.0}")
    } else if x >= 0.1 {
        format!("{x:.1}")
    } else {
        format!("{x:.3}")
    }
}

/// A band edge for people.
fn fmt_edge(k: i32) -> String {
    fmt_value(band_floor(k))
}

/// What a tool says about `scenario` against a calibration's region: a warning naming the moves
/// that leave it (every model extrapolates there), a note when the calibration records no
/// region (an older file), nothing when every move stays inside.
pub fn advice(coverage: Option<&Coverage>, scenario: &Scenario) -> Option<String> {
    match coverage {
        Some(c) => c.check(scenario).warning().map(|w| format!("warning: {w}")),
        None => Some(format!(
            "note: the calibration records no coverage (an older file): whether {} stays \
             within the calibrated motions is not checked",
            scenario.name
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Move;

    fn mv(to_mm: f64, v: f64, a: f64, retarget: Option<u32>) -> Move {
        Move {
            to_mm,
            velocity_mm_s: v,
            accel_mm_s2: a,
            dwell_ms: 0,
            retarget_after_ms: retarget,
        }
    }

    fn scenario(start_mm: f64, moves: Vec<Move>) -> Scenario {
        Scenario {
            name: "test".into(),
            start_mm,
            moves,
            source: "test".into(),
        }
    }

    #[test]
    fn bands_are_half_octaves() {
        assert_eq!(band(1.0), 0);
        assert_eq!(band(1.41), 0);
        assert_eq!(band(1.42), 1);
        assert_eq!(band(2.0), 2);
        assert_eq!(band(0.5), -2);
        for k in -10..30 {
            assert_eq!(band(band_floor(k) * 1.0001), k);
        }
    }

    #[test]
    fn short_and_cut_moves_peak_below_their_cruise_speed() {
        let s = scenario(
            100.0,
            vec![
                // Long: reaches 100 mm/s.
                mv(200.0, 100.0, 1000.0, None),
                // 1 mm at 1000 mm/s²: a triangle, peak sqrt(a d) = 31.6 mm/s.
                mv(199.0, 100.0, 1000.0, None),
                // Cut after 50 ms: 50 mm/s reached, 1.25 mm travelled.
                mv(100.0, 100.0, 1000.0, Some(50)),
                mv(150.0, 10.0, 1000.0, None),
            ],
        );
        let e = extents(&s);
        assert_eq!(e.len(), 4);
        assert!((e[0].1.peak_mm_s - 100.0).abs() < 1e-9);
        assert!((e[1].1.peak_mm_s - 1000f64.sqrt()).abs() < 1e-9);
        assert!((e[2].1.peak_mm_s - 50.0).abs() < 1e-9);
        assert!((e[2].1.span_mm[0] - 197.75).abs() < 1e-9, "{:?}", e[2]);
        // It starts at the cut's 50 mm/s and brakes within its stroke.
        assert_eq!(e[3].1.span_mm, [150.0, 197.75]);
        assert_eq!(e[3].1.peak_mm_s, 50.0);
    }

    #[test]
    fn a_move_that_turns_back_after_a_cut_brakes_past_the_cut() {
        let s = scenario(
            100.0,
            vec![
                // Cut after 200 ms at 100 mm/s, 15 mm up.
                mv(200.0, 100.0, 1000.0, Some(200)),
                // Back down at 500 mm/s²: 10 mm to stop first.
                mv(110.0, 20.0, 500.0, None),
                // Nothing to travel and nothing carried: not a move.
                mv(110.0000001, 20.0, 500.0, None),
            ],
        );
        let e = extents(&s);
        assert_eq!(e.len(), 2, "{e:?}");
        assert_eq!(e[0].1.span_mm, [100.0, 115.0]);
        assert_eq!(e[1].1.span_mm, [110.0, 125.0]);
        assert_eq!(e[1].1.peak_mm_s, 100.0);
    }

    #[test]
    fn a_run_inside_passes_and_one_outside_is_named() {
        let cal = scenario(
            10.0,
            vec![
                mv(200.0, 100.0, 1000.0, None),
                mv(20.0, 50.0, 500.0, None),
                mv(250.0, 200.0, 2000.0, None),
            ],
        );
        let c = Coverage::of([&cal]);
        assert_eq!(c.travel_mm, [10.0, 250.0]);
        // Within a factor of two of a calibration move, inside the travel.
        let near = scenario(30.0, vec![mv(180.0, 150.0, 1500.0, None)]);
        let k = c.check(&near);
        assert!(k.outside.is_empty(), "{k:?}");
        assert_eq!(k.warning(), None);
        // Four times the fastest acceleration, and beyond the travel.
        let far = scenario(
            100.0,
            vec![
                mv(200.0, 200.0, 8000.0, None),
                mv(280.0, 100.0, 1000.0, None),
                // Both ways at once: counted once among the moves.
                mv(290.0, 2.0, 1000.0, None),
            ],
        );
        let k = c.check(&far);
        assert_eq!(k.moves(), 3);
        assert_eq!(k.speed_accel(), 2);
        assert_eq!(k.travel(), 2);
        assert_eq!(k.outside.len(), 4);
        assert_eq!(k.moves_outside(), 3);
        let w = k.warning().unwrap();
        assert!(
            w.contains("(move 1: 200 mm/s at 8000 mm/s²; move 3: 2.0 mm/s at 1000 mm/s²)"),
            "{w}"
        );
        assert!(
            w.contains(
                "2 of 3 moves outside the calibrated travel 10.0-250.0 mm (move 2: 200.0-280.0 mm; \
                 move 3: 280.0-290.0 mm)"
            ),
            "{w}"
        );
    }

    #[test]
    fn limits_beyond_the_calibration_are_named() {
        let cal = scenario(10.0, vec![mv(200.0, 100.0, 1000.0, None)]);
        let c = Coverage::of([&cal]);
        // Band edges: 90.5-128 mm/s, 724-1024 mm/s².
        assert_eq!(
            c.reach().map(|(v, a)| (v.round(), a.round())),
            Some((128.0, 1024.0))
        );
        assert!(c.short_of(250.0, 2000.0).is_empty());
        let w = c.short_of(500.0, 5000.0);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(
            w[0].contains("reach 128 mm/s at most and the drive allows 500"),
            "{w:?}"
        );
        assert!(
            w[1].contains("reach 1024 mm/s² at most and the drive allows 5000"),
            "{w:?}"
        );
        assert_eq!(Coverage::default().short_of(1.0, 1.0).len(), 1);
    }

    #[test]
    fn the_toml_form_reads_back_and_bad_fields_are_named() {
        let cal = scenario(
            10.0,
            vec![mv(200.0, 100.0, 1000.0, None), mv(20.0, 2.0, 300.0, None)],
        );
        let c = Coverage::of([&cal]);
        assert_eq!(Coverage::from_toml(&c.to_toml()), Ok(c.clone()));
        let mut t = c.to_toml();
        t.insert("travel_mm".into(), toml::Value::Float(1.0));
        assert!(Coverage::from_toml(&t)
            .unwrap_err()
            .contains("coverage.travel_mm"));
        let mut t = c.to_toml();
        t.insert(
            "half_octave_cells".into(),
            toml::Value::Array(vec![toml::Value::Array(vec![
                toml::Value::Integer(1),
                toml::Value::Integer(2),
                toml::Value::Integer(0),
            ])]),
        );
        let e = Coverage::from_toml(&t).unwrap_err();
        assert!(e.contains("coverage.half_octave_cells[0]"), "{e}");
        let cell = |s: i64| toml::Value::Array([s, 2, 1].map(toml::Value::Integer).to_vec());
        for (cells, field) in [
            (vec![cell(i64::MIN)], "half_octave_cells[0]"),
            (vec![cell(65)], "half_octave_cells[0]"),
            (
                vec![cell(1), cell(1)],
                "half_octave_cells[1]: cell [1, 2] is listed twice",
            ),
        ] {
            let mut t = c.to_toml();
            t.insert("half_octave_cells".into(), toml::Value::Array(cells));
            let e = Coverage::from_toml(&t).unwrap_err();
            assert!(e.contains(field), "{e}");
        }
        // The largest counts a file can hold, in two cells of one octave: the table adds them.
        let mut t = c.to_toml();
        let full = |s: i64| {
            toml::Value::Array(
                [s, 0, i64::from(u32::MAX)]
                    .map(toml::Value::Integer)
                    .to_vec(),
            )
        };
        t.insert(
            "half_octave_cells".into(),
            toml::Value::Array(vec![full(0), full(1)]),
        );
        let md = Coverage::from_toml(&t)
            .expect("counts within u32")
            .markdown();
        assert!(md.contains(" 8589934590 |"), "{md}");
        let mut t = c.to_toml();
        t.insert("extra".into(), toml::Value::Integer(1));
        assert_eq!(
            Coverage::from_toml(&t).unwrap_err(),
            "coverage.extra: not a coverage field"
        );
    }

    #[test]
    fn the_table_counts_every_move() {
        let cal = scenario(
            10.0,
            vec![
                mv(200.0, 100.0, 1000.0, None),
                mv(20.0, 100.0, 1000.0, None),
                mv(21.0, 2.0, 300.0, None),
            ],
        );
        let md = Coverage::of([&cal]).markdown();
        assert!(md.contains("10.0-200.0 mm"), "{md}");
        let total: u32 = md
            .lines()
            .filter(|l| l.starts_with("| ") && !l.starts_with("| mm/s²"))
            .flat_map(|l| {
                l.split('|')
                    .skip(2)
                    .filter_map(|c| c.trim().parse::<u32>().ok())
            })
            .sum();
        assert_eq!(total, 3, "{md}");
    }
}
