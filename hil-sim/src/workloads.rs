//! Workloads of machine builders, generated from a seed within the drive's limits: the classes
//! on which the estimators are judged beyond the paper's scenarios, and the default calibration
//! plan that spans the drive's configured range.
//!
//! Each class is a family, not a file: a seed draws one member (strokes, speeds, accelerations,
//! dwells, places on the travel), so a model tuned to one member is found out by the next.

use crate::plant::rng::Rng;
use crate::scenario::{Move, Scenario};

/// The drive's range a workload must respect (mm, mm/s, mm/s²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Lowest target, mm.
    pub travel_min_mm: f64,
    /// Highest target, mm.
    pub travel_max_mm: f64,
    /// Highest cruise speed, mm/s.
    pub max_velocity_mm_s: f64,
    /// Highest acceleration, mm/s².
    pub max_accel_mm_s2: f64,
}

impl Limits {
    /// The limits of a drive configuration.
    pub fn of(cfg: &estimator_core::drive::DriveConfig) -> Limits {
        let cfg = &cfg.settings;
        Limits {
            travel_min_mm: cfg.travel_min_mm,
            travel_max_mm: cfg.travel_max_mm,
            max_velocity_mm_s: cfg.max_velocity_mm_s,
            max_accel_mm_s2: cfg.max_accel_mm_s2,
        }
    }

    fn span_mm(&self) -> f64 {
        self.travel_max_mm - self.travel_min_mm
    }
}

/// The workload classes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Class {
    /// Printer raster: 2-10 mm strokes back and forth stepping along, 3000 mm/s².
    PrinterRaster,
    /// Pick and place: long moves between random stations, 200 mm/s, 4000 mm/s², dwells.
    PickAndPlace,
    /// Slow feeds: 2-8 mm/s over 3-30 mm, gentle accelerations.
    SlowFeed,
    /// Work within the first and last tenth of the travel.
    TravelEnds,
    /// Every move with its own limits, 200-5000 mm/s², 5-250 mm/s.
    MixedLimits,
    /// Short and medium strokes at the highest acceleration, some retargeted mid-move.
    HighAccelReversals,
}

impl Class {
    /// Every class, in report order.
    pub const ALL: [Class; 6] = [
        Class::PrinterRaster,
        Class::PickAndPlace,
        Class::SlowFeed,
        Class::TravelEnds,
        Class::MixedLimits,
        Class::HighAccelReversals,
    ];

    /// Name in reports and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Class::PrinterRaster => "printer-raster",
            Class::PickAndPlace => "pick-and-place",
            Class::SlowFeed => "slow-feed",
            Class::TravelEnds => "travel-ends",
            Class::MixedLimits => "mixed-limits",
            Class::HighAccelReversals => "high-accel-reversals",
        }
    }

    /// The class of a name.
    pub fn parse(name: &str) -> Option<Class> {
        Class::ALL.into_iter().find(|c| c.name() == name)
    }
}

/// Log-uniform draw in `[lo, hi]`.
fn log_uniform(r: &mut Rng, lo: f64, hi: f64) -> f64 {
    (lo.ln() + r.uniform() * (hi.ln() - lo.ln())).exp()
}

fn between(r: &mut Rng, lo: f64, hi: f64) -> f64 {
    lo + r.uniform() * (hi - lo)
}

/// `v` at least `floor` and at most `max`; a limit below the floor (a drive capped to slow
/// moves) wins over it. Never panics, unlike `clamp`, whatever the limit.
fn held(v: f64, floor: f64, max: f64) -> f64 {
    v.max(floor.min(max)).min(max)
}

/// Builds moves, keeping targets inside the travel and values on the drive's integer grid.
struct Builder {
    lim: Limits,
    x: f64,
    moves: Vec<Move>,
}

impl Builder {
    fn new(lim: Limits, start_mm: f64) -> Builder {
        Builder {
            lim,
            x: start_mm,
            moves: Vec::new(),
        }
    }

    fn to(&mut self, to_mm: f64, v: f64, a: f64, dwell_ms: u32, retarget_after_ms: Option<u32>) {
        let to_mm = to_mm
            .max(self.lim.travel_min_mm)
            .min(self.lim.travel_max_mm);
        let round3 = |v: f64| (v * 1000.0).round() / 1000.0;
        self.moves.push(Move {
            to_mm: round3(to_mm),
            velocity_mm_s: round3(held(v, 0.5, self.lim.max_velocity_mm_s)),
            accel_mm_s2: round3(held(a, 10.0, self.lim.max_accel_mm_s2)),
            dwell_ms,
            retarget_after_ms,
        });
        self.x = to_mm;
    }

    fn finish(mut self, name: String, start_mm: f64) -> Scenario {
        // Nothing follows the last move: it runs to its end.
        if let Some(last) = self.moves.last_mut() {
            if last.retarget_after_ms.take().is_some() {
                last.dwell_ms = last.dwell_ms.max(100);
            }
        }
        Scenario {
            name: name.clone(),
            start_mm: (start_mm * 1000.0).round() / 1000.0,
            moves: self.moves,
            source: format!("workload {name}"),
        }
    }
}

/// One member of `class` for `seed`, about `duration_s` of simulated motion.
pub fn generate(class: Class, seed: u64, lim: &Limits, duration_s: f64) -> Scenario {
    let mut r = Rng::new(seed, 0x3017_0000 + class as u64);
    let span = lim.span_mm();
    let lo = lim.travel_min_mm;
    let start = match class {
        Class::TravelEnds => lo + 0.05 * span,
        _ => lo + between(&mut r, 0.2, 0.8) * span,
    };
    let mut b = Builder::new(*lim, start);
    let mut t = 0.0;
    while t < duration_s {
        let x0 = b.x;
        match class {
            Class::PrinterRaster => {
                // A line of strokes, then a step along and a new line elsewhere.
                let stroke = between(&mut r, 2.0, 10.0);
                let v = between(&mut r, 80.0, 200.0);
                let a = 3000.0;
                let lines = 4 + (r.next_u64() % 8) as usize;
                let step = between(&mut r, 0.1, 0.6);
                let mut base = b.x;
                for k in 0..lines {
                    let far = base + stroke;
                    b.to(far, v, a, 0, None);
                    base += step;
                    b.to(base, v, a, if k + 1 == lines { 50 } else { 0 }, None);
                    t += 2.0 * (stroke / v + 2.0 * v / a);
                }
                if r.uniform() < 0.3 {
                    let next = lo + between(&mut r, 0.1, 0.85) * span;
                    b.to(next, 200.0, a, 100, None);
                    t += (next - base).abs() / 200.0 + 0.2;
                }
            }
            Class::PickAndPlace => {
                let next = lo + between(&mut r, 0.03, 0.97) * span;
                let dwell = 50 + (r.next_u64() % 250) as u32;
                b.to(next, 200.0, 4000.0, dwell, None);
                t += (next - x0).abs() / 200.0 + 0.1 + dwell as f64 / 1000.0;
            }
            Class::SlowFeed => {
                let d = between(&mut r, 3.0, 30.0) * if r.uniform() < 0.5 { -1.0 } else { 1.0 };
                let mut next = x0 + d;
                if next < lo + 0.05 * span || next > lo + 0.95 * span {
                    next = x0 - d;
                }
                let v = between(&mut r, 2.0, 8.0);
                let a = log_uniform(&mut r, 100.0, 1000.0);
                let dwell = (r.next_u64() % 300) as u32;
                b.to(next, v, a, dwell, None);
                t += d.abs() / v + dwell as f64 / 1000.0;
            }
            Class::TravelEnds => {
                // Work near one end, then cross to the other now and then.
                let near_low = x0 < lo + 0.5 * span;
                let (zlo, zhi) = if near_low {
                    (lo, lo + 0.1 * span)
                } else {
                    (lo + 0.9 * span, lo + span)
                };
                let next = if r.uniform() < 0.15 {
                    if near_low {
                        lo + between(&mut r, 0.9, 1.0) * span
                    } else {
                        lo + between(&mut r, 0.0, 0.1) * span
                    }
                } else {
                    between(&mut r, zlo, zhi)
                };
                let v = log_uniform(&mut r, 10.0, 150.0);
                let a = log_uniform(&mut r, 300.0, 3000.0);
                let dwell = (r.next_u64() % 200) as u32;
                b.to(next, v, a, dwell, None);
                t += (next - x0).abs() / v + 2.0 * v / a + dwell as f64 / 1000.0;
            }
            Class::MixedLimits => {
                let d = log_uniform(&mut r, 0.5, 0.6 * span);
                let mut next = if r.uniform() < 0.5 { x0 - d } else { x0 + d };
                if next < lo || next > lo + span {
                    next = 2.0 * x0 - next;
                }
                let v = log_uniform(&mut r, 5.0, lim.max_velocity_mm_s);
                let a = log_uniform(&mut r, 200.0, lim.max_accel_mm_s2);
                let dwell = (r.next_u64() % 200) as u32;
                b.to(next, v, a, dwell, None);
                t += (next - x0).abs() / v + 2.0 * v / a + dwell as f64 / 1000.0;
            }
            Class::HighAccelReversals => {
                let d = log_uniform(&mut r, 1.0, 40.0);
                let mut next = if r.uniform() < 0.5 { x0 - d } else { x0 + d };
                if next < lo + 0.02 * span || next > lo + 0.98 * span {
                    next = 2.0 * x0 - next;
                }
                let v = log_uniform(&mut r, 50.0, lim.max_velocity_mm_s);
                let a = lim.max_accel_mm_s2;
                let retarget = if r.uniform() < 0.3 {
                    Some(20 + (r.next_u64() % 120) as u32)
                } else {
                    None
                };
                let dwell = if retarget.is_some() {
                    0
                } else {
                    (r.next_u64() % 100) as u32
                };
                b.to(next, v, a, dwell, retarget);
                t += (next - x0).abs() / v + 2.0 * v / a + dwell as f64 / 1000.0;
            }
        }
    }
    b.finish(format!("{}-{seed}", class.name()), start)
}

/// The default calibration plan: moves drawn across the drive's whole configured range, log-
/// uniform in stroke (0.1 mm to the whole travel), speed (2 mm/s to the maximum) and acceleration
/// (200 mm/s² to the maximum), with dwells and a share of retargeted moves (reversals in mid-
/// motion), over the whole travel. It is what `hil-sim calibrate` records besides the paper's
/// scenarios and any the user adds.
pub fn calibration_plan(lim: &Limits, seed: u64, duration_s: f64) -> Scenario {
    let mut r = Rng::new(seed, 0xCA11_B7A7);
    let span = lim.span_mm();
    let lo = lim.travel_min_mm;
    let start = lo + 0.5 * span;
    let mut b = Builder::new(*lim, start);
    let mut t = 0.0;
    let mut k = 0u64;
    let mut retargeted = false;
    while t < duration_s {
        let x0 = b.x;
        // Every eighth move crosses to an end of the travel, so both ends are always covered.
        let next = if k % 8 == 7 {
            if x0 < lo + 0.5 * span {
                lo + between(&mut r, 0.97, 1.0) * span
            } else {
                lo + between(&mut r, 0.0, 0.03) * span
            }
        } else {
            let d = log_uniform(&mut r, 0.1, span);
            let n = if r.uniform() < 0.5 { x0 - d } else { x0 + d };
            if n < lo || n > lo + span {
                2.0 * x0 - n
            } else {
                n
            }
        };
        let v = log_uniform(&mut r, 2.0, lim.max_velocity_mm_s);
        let a = log_uniform(&mut r, 200.0, lim.max_accel_mm_s2);
        // Slow moves over long strokes would take the whole plan: cap their duration. After a
        // retarget the carriage may be anywhere on the travel.
        let reach = if retargeted { span } else { (next - x0).abs() };
        let v = v.max(reach / 4.0);
        let retarget = if r.uniform() < 0.15 {
            Some(30 + (r.next_u64() % 300) as u32)
        } else {
            None
        };
        let dwell = if retarget.is_some() {
            0
        } else {
            (r.next_u64() % 300) as u32
        };
        retargeted = retarget.is_some();
        b.to(next, v, a, dwell, retarget);
        t += (next - x0).abs() / v.min(lim.max_velocity_mm_s) + 2.0 * v / a + dwell as f64 / 1000.0;
        k += 1;
    }
    b.finish(format!("calibration-plan-{seed}"), start)
}
