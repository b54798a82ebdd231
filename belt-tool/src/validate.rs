//! `beltctl validate`: the user's own moves placed once per compensator, each arrival read on the
//! linear scale, so that the machine's own workload decides which compensator the drive runs.
//!
//! The calibration's fit says how well each model follows its own recordings; the drive's job
//! is the carriage at rest on its target, on this machine's moves. Those can rank the models
//! differently (README, "Commissioning a machine", step 6), so commissioning measures
//! the arrivals themselves while the scale is still fitted.

use std::time::Duration;

use belt_link::{status_flags, Command, CommandError, LinkError, ModelKind};
use estimator_core::settings::Settings;
use hil_sim::progress::Progress;
use hil_sim::scenario::Scenario;

use crate::calibrate::{SEAT_LIMITS, SEAT_MM};
use crate::error::ToolError;
use crate::link::Link;
use crate::ops::{self, Arrival, MoveLimits};

/// Options of `beltctl validate`.
#[derive(Clone, Debug)]
pub struct Options {
    /// The scenario file's path (for messages) and its moves, in the drive's coordinates.
    pub scenario: (String, Scenario),
    /// Compensators to compare, in order (no repeats).
    pub models: Vec<ModelKind>,
    /// Select the best compensator afterwards (otherwise the one active before is restored).
    pub select: bool,
    /// Least rest after arrival before the scale is read (a move's `dwell_ms` if longer).
    pub settle: Duration,
}

/// One compensator's arrivals.
#[derive(Clone, Debug, PartialEq)]
pub struct Placed {
    /// The compensator.
    pub model: ModelKind,
    /// Scale minus target at rest, um, for each move that ends at rest.
    pub errors_um: Vec<f64>,
}

impl Placed {
    /// RMS of the arrival errors, um.
    pub fn rms_um(&self) -> f64 {
        ops::rms_and_max_um(&self.errors_um).0
    }

    /// Largest arrival error, um.
    pub fn max_um(&self) -> f64 {
        ops::rms_and_max_um(&self.errors_um).1
    }
}

/// What a validation measured.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// The scenario's name.
    pub scenario: String,
    /// Each compensator's arrivals, in the order run.
    pub placed: Vec<Placed>,
    /// The compensator with the lowest arrival RMS (the first of equals).
    pub best: ModelKind,
    /// The compensator active afterwards.
    pub active: ModelKind,
}

/// The scenario against the drive, before anything moves: every move must end inside the
/// travel, within the drive's speed and acceleration, and at least one must end at rest.
/// Refused by file, move and field; nothing is clipped, because a slower move is another
/// workload than the one being validated.
pub fn check(settings: &Settings, path: &str, s: &Scenario) -> Result<(), ToolError> {
    let refuse = |reason: String| {
        Err(ToolError::File {
            path: path.to_string(),
            reason,
        })
    };
    // The last move always ends at rest (nothing follows to retarget it).
    if s.moves.is_empty() {
        return refuse("no moves to validate on".into());
    }
    ops::within_travel(path, s, (settings.travel_min_mm, settings.travel_max_mm))?;
    for (i, m) in s.moves.iter().enumerate() {
        let n = i + 1;
        if m.velocity_mm_s > settings.max_velocity_mm_s {
            return refuse(format!(
                "move {n}: velocity_mm_s = {} is above the drive's limit {} mm/s \
                 (limits.max_velocity_mm_s)",
                m.velocity_mm_s, settings.max_velocity_mm_s
            ));
        }
        if m.accel_mm_s2 > settings.max_accel_mm_s2 {
            return refuse(format!(
                "move {n}: accel_mm_s2 = {} is above the drive's limit {} mm/s^2 \
                 (limits.max_accel_mm_s2)",
                m.accel_mm_s2, settings.max_accel_mm_s2
            ));
        }
    }
    Ok(())
}

/// Places the carriage on the scenario's moves once per compensator. Each pass starts the same
/// way: a raw motor stroke forward onto the scenario's start (as the calibration's recordings
/// start), so that every compensator meets the belt in the same state. Any failure stops the
/// drive and selects the compensator active before.
pub fn run(
    link: &mut Link,
    settings: &Settings,
    opts: &Options,
    progress: &mut Progress,
) -> Result<Outcome, ToolError> {
    let (path, s) = &opts.scenario;
    check(settings, path, s)?;
    let before = link.status()?;
    ops::require_ready(&before, "validation")?;
    if before.flags & status_flags::CALIBRATED == 0 {
        if let Some(m) = opts.models.iter().find(|&&m| m != ModelKind::None) {
            return Err(ToolError::Drive(format!(
                "validating {m} needs a calibration on the drive: upload one first (`beltctl \
                 calibrate`)"
            )));
        }
    }
    let mut placed = Vec::with_capacity(opts.models.len());
    let result = (|| {
        for &model in &opts.models {
            placed.push(pass(link, settings, opts, model, progress)?);
        }
        Ok(())
    })();
    let restore = |link: &mut Link| {
        let _ = link.command(Command::Stop);
        let _ = link.command(Command::SelectModel(before.model));
    };
    if let Err(e) = result {
        restore(link);
        return Err(e);
    }
    // `min_by` keeps the first of equals.
    let best = placed
        .iter()
        .min_by(|a, b| a.rms_um().total_cmp(&b.rms_um()))
        .map_or(before.model, |p| p.model);
    let active = if opts.select { best } else { before.model };
    if let Err(e) = link.command(Command::SelectModel(active)) {
        restore(link);
        return Err(refused_model(e, active));
    }
    Ok(Outcome {
        scenario: s.name.clone(),
        placed,
        best,
        active,
    })
}

/// One compensator's pass over the scenario.
fn pass(
    link: &mut Link,
    settings: &Settings,
    opts: &Options,
    model: ModelKind,
    progress: &mut Progress,
) -> Result<Placed, ToolError> {
    let s = &opts.scenario.1;
    let label = format!("validate {model}");
    progress.stage(&label, 0.0);
    link.command(Command::SelectModel(model))
        .map_err(|e| refused_model(e, model))?;
    let mut rest = seat_at(link, settings, s.start_mm)?;
    let mut errors_um = Vec::with_capacity(s.moves.len());
    for (i, m) in s.moves.iter().enumerate() {
        progress.stage(&label, i as f64 / s.moves.len() as f64);
        let limits = MoveLimits {
            velocity_mm_s: m.velocity_mm_s,
            accel_mm_s2: m.accel_mm_s2,
        };
        let cmd = ops::move_command(ops::target_um(m.to_mm)?, &limits, false)?;
        // A retargeted move is cut by the next one: it has no arrival.
        let retarget = m.retarget_after_ms.filter(|_| i + 1 < s.moves.len());
        if let Some(ms) = retarget {
            link.command(cmd)?;
            ops::dwell(link, Duration::from_millis(ms as u64))?;
        } else {
            // The time budget from where the carriage is (a cut move left it short).
            let here_mm = link.status()?.carriage_estimate_um as f64 / 1000.0;
            ops::move_and_wait(link, cmd, m.to_mm - here_mm, &limits, |_| Ok(()))?;
            ops::dwell(
                link,
                opts.settle.max(Duration::from_millis(m.dwell_ms as u64)),
            )?;
            let now = at_rest(
                link,
                &format!("{label}: move {}", i + 1),
                m.to_mm,
                Some(rest),
            )?;
            errors_um.push(now.error_um());
            rest = now;
        }
    }
    progress.stage(&label, 1.0);
    Ok(Placed { model, errors_um })
}

/// The forward stroke onto `start_mm` every pass begins with, raw motor moves: the
/// calibration's seating stroke from up to [`SEAT_MM`] below (none when the start is the
/// travel's lower end), then rest. Returns the arrival at the start.
fn seat_at(link: &mut Link, settings: &Settings, start_mm: f64) -> Result<Arrival, ToolError> {
    let limits = MoveLimits {
        velocity_mm_s: SEAT_LIMITS.velocity_mm_s.min(settings.max_velocity_mm_s),
        accel_mm_s2: SEAT_LIMITS.accel_mm_s2.min(settings.max_accel_mm_s2),
    };
    let below_mm = start_mm - SEAT_MM.min(start_mm - settings.travel_min_mm).max(0.0);
    let mut rest = None;
    for to in [below_mm, start_mm] {
        let here_mm = link.status()?.carriage_estimate_um as f64 / 1000.0;
        let cmd = ops::move_command(ops::target_um(to)?, &limits, true)?;
        ops::move_and_wait(link, cmd, to - here_mm, &limits, |_| Ok(()))?;
        ops::dwell(link, Duration::from_millis(300))?;
        let what = format!("seating stroke to {to} mm");
        rest = Some(at_rest(link, &what, to, rest)?);
    }
    rest.ok_or_else(|| ToolError::Drive("seating stroke: no status".into()))
}

/// The status at rest on `target_mm`, refused if the drive latched a fault or if the scale did
/// not follow the move from `from` (the last rest): a missing, stuck or reversed scale would
/// rank the compensators by noise.
fn at_rest(
    link: &mut Link,
    what: &str,
    target_mm: f64,
    from: Option<Arrival>,
) -> Result<Arrival, ToolError> {
    let st = link.status()?;
    ops::no_faults(&st, what)?;
    let now = Arrival::of(target_mm, &st, None);
    if let Some(from) = from {
        let (moved, read) = (now.target_mm - from.target_mm, now.scale_mm - from.scale_mm);
        // 1 mm or more commanded: the scale must show it within a fifth and 0.5 mm.
        if moved.abs() >= 1.0 && (read - moved).abs() > 0.2 * moved.abs() + 0.5 {
            return Err(ToolError::Drive(format!(
                "{what}: the linear scale moved {read:.3} mm for {moved:.3} mm commanded: \
                 validation needs the linear scale fitted and connected (polarity.scale_inverted)"
            )));
        }
    }
    Ok(now)
}

/// A selection refused for want of a calibration, said so with what to do.
fn refused_model(e: ToolError, model: ModelKind) -> ToolError {
    match e {
        ToolError::Refused { reason, detail, .. }
            if reason == LinkError::Refused && detail == CommandError::NotCalibrated.code() =>
        {
            ToolError::Drive(format!(
                "the drive refused to select {model}: not calibrated; upload a calibration first \
                 (`beltctl calibrate`)"
            ))
        }
        other => other,
    }
}

/// The compensators named in `list` (comma-separated), in order, each once.
pub fn parse_models(list: &str) -> Result<Vec<ModelKind>, ToolError> {
    let mut out = Vec::new();
    for name in list.split(',').map(str::trim) {
        let m: ModelKind = name
            .parse()
            .map_err(|e| ToolError::Usage(format!("--models {list}: {name:?}: {e}")))?;
        if out.contains(&m) {
            return Err(ToolError::Usage(format!(
                "--models {list}: {m} is named twice"
            )));
        }
        out.push(m);
    }
    Ok(out)
}
