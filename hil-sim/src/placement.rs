//! Carriage placement: moves commanded in carriage space (`Command::MoveTo`), judged by
//! the linear scale once the carriage has settled.
//!
//! The drive turns each carriage target into a motor target with the active model's inverse
//! along the planned path; the motor still runs a plain trapezoid, so its velocity and
//! acceleration stay within the move's limits and never step.

use crate::error::{Context, Error};
use estimator_core::drive::{Command, Drive};
use estimator_core::model::{ModelKind, ModelParams};
use estimator_core::rig::Rig;

use crate::controller::{Controller, InProcess};
use crate::drive_setup::drive_config;
use crate::plant::{Plant, PlantParams};
use crate::run::{home_and_enable, keepalive_ticks, sample};

/// One move to rest: carriage target (mm), speed (mm/s), acceleration (mm/s^2).
pub type Move = (f64, f64, f64);

/// Rest after arrival before the scale is read, seconds.
pub const SETTLE_S: f64 = 0.3;

/// Arrival error of every move, micrometres: scale reading at rest minus the carriage target.
pub fn arrival_errors(
    controller: &mut dyn Controller,
    plant_params: &PlantParams,
    rig: &Rig,
    model: ModelKind,
    start_mm: f64,
    moves: &[Move],
    seed: u64,
) -> Result<Vec<f64>, Error> {
    let dt = 1.0 / 2000.0;
    let keepalive = keepalive_ticks(dt);
    let mut plant = Plant::new(plant_params, start_mm, seed)?;
    home_and_enable(controller, &plant, rig)?;
    controller.command(Command::SelectModel(model))?;
    let mut tick: u64 = 0;
    let mut errors = Vec::with_capacity(moves.len());
    for (k, &(to_mm, v, a)) in moves.iter().enumerate() {
        controller
            .command(Command::MoveTo {
                target_um: (to_mm * 1000.0).round() as i32,
                velocity_um_s: (v * 1000.0).round() as u32,
                accel_um_s2: (a * 1000.0).round() as u32,
            })
            .context(|| format!("move {k}"))?;
        let mut rest_ticks = 0u64;
        let settle = (SETTLE_S / dt) as u64;
        loop {
            if tick.is_multiple_of(keepalive) {
                controller.keepalive()?;
            }
            let out = controller.step(sample(&plant))?;
            if !out.telemetry.faults.is_clear() {
                return Err(Error::Fault(out.telemetry.faults).context(format!("move {k}")));
            }
            plant.step(out.current_a.to_num::<f64>(), dt);
            tick += 1;
            rest_ticks = if out.telemetry.moving {
                0
            } else {
                rest_ticks + 1
            };
            if rest_ticks >= settle {
                break;
            }
            if tick > 10_000_000 {
                return Err(Error::NeverAtRest.context(format!("move {k}")));
            }
        }
        let scale_mm = plant.scale_counts() as f64 / plant.scale_counts_per_mm();
        errors.push((scale_mm - to_mm) * 1000.0);
    }
    Ok(errors)
}

/// [`arrival_errors`] with the core in this process, `params` loaded.
pub fn arrival_errors_in_process(
    plant: &PlantParams,
    params: &ModelParams,
    model: ModelKind,
    start_mm: f64,
    moves: &[Move],
    seed: u64,
) -> Result<Vec<f64>, Error> {
    let cfg = drive_config(params, model, plant.rig());
    let drive = Drive::new(&cfg).context(|| "drive configuration".into())?;
    arrival_errors(
        &mut InProcess(drive),
        plant,
        &cfg.settings.rig,
        model,
        start_mm,
        moves,
        seed,
    )
}

/// How well a compensator places the carriage over a scenario run in carriage space.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Positioning {
    /// RMS of (scale at rest - carriage target) over the moves that end at rest, um.
    pub arrival_rms_um: f64,
    /// Largest |arrival error|, um.
    pub arrival_max_um: f64,
    /// RMS of (scale - planned carriage set-point) while moving, um.
    pub tracking_rms_um: f64,
    /// Length of the run, seconds.
    pub cycle_time_s: f64,
    /// Motor set-point's peak speed over the move's limit (10-tick windows), worst move.
    pub peak_velocity_ratio: f64,
    /// Motor set-point's peak acceleration over the move's limit (two 10-tick windows), worst move.
    pub peak_accel_ratio: f64,
    /// Moves that end at rest (the arrival statistics' sample).
    pub moves_at_rest: usize,
}

/// The set-point's speed and acceleration are measured over windows long enough that its
/// whole-count rounding (up to one count at each end) stays within 1 % of the move's limits:
/// at least this many ticks, and at least 100 counts of travel or 200 counts of second
/// difference at the limit.
const RATIO_WINDOW_MIN: usize = 10;

/// Arrival error of every move of `scenario` that ends at rest in `trace`: (move index, scale at
/// rest minus the carriage target, um), read on the last tick before the next command.
pub fn arrivals(
    scenario: &crate::scenario::Scenario,
    trace: &crate::run::Trace,
) -> Vec<(usize, f64)> {
    let recs = &trace.records;
    let n = recs.len();
    let mut out = Vec::new();
    for (k, m) in scenario.moves.iter().enumerate() {
        if m.retarget_after_ms.is_some() {
            continue;
        }
        let end = trace.move_starts.get(k + 1).copied().unwrap_or(n);
        if end == 0 || end > n {
            continue;
        }
        let r = &recs[end - 1];
        if !r.out.telemetry.moving {
            out.push((k, (r.x_ls_mm - m.to_mm) * 1000.0));
        }
    }
    out
}

/// One compensator's placement over a scenario: the figures and the arrival of every move.
#[derive(Clone, Debug)]
pub struct Placement {
    /// Compensator name (`ModelKind::as_str`).
    pub name: &'static str,
    /// The figures of `hil-sim evaluate --json`'s `"positioning"`.
    pub positioning: Positioning,
    /// (move index, arrival error um) of the moves that end at rest.
    pub arrivals: Vec<(usize, f64)>,
}

/// Runs `scenario` in carriage space once per compensator of the drive (`ModelKind::ALL`)
/// through `run` (the core in this process, or the firmware under QEMU) and measures each run.
pub fn compare(
    scenario: &crate::scenario::Scenario,
    params: &ModelParams,
    rig: &Rig,
    run: &mut dyn FnMut(ModelKind) -> Result<crate::run::Trace, Error>,
) -> Result<Vec<Placement>, Error> {
    let coeffs = params.build(rig).context(|| "drive configuration".into())?;
    let mut out = Vec::new();
    for model in ModelKind::ALL {
        let t = run(model)?;
        out.push(Placement {
            name: model.as_str(),
            positioning: positioning(scenario, &t, &coeffs, model),
            arrivals: arrivals(scenario, &t),
        });
    }
    Ok(out)
}

/// [`compare`] with the core in this process.
pub fn compare_in_process(
    scenario: &crate::scenario::Scenario,
    plant: &PlantParams,
    params: &ModelParams,
    seed: u64,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Vec<Placement>, Error> {
    compare(scenario, params, &plant.rig(), &mut |model| {
        let label = format!("placement {model}");
        run_carriage_space(scenario, plant, params, model, seed, &mut |f| {
            progress(&label, f)
        })
    })
}

/// The best of `names` by arrival RMS.
pub fn best<'a>(placements: &'a [Placement], names: &[&str]) -> Option<&'a Placement> {
    placements
        .iter()
        .filter(|p| names.contains(&p.name))
        .min_by(|a, b| {
            a.positioning
                .arrival_rms_um
                .total_cmp(&b.positioning.arrival_rms_um)
        })
}

/// Positioning figures of `trace`, a run of `scenario` in carriage space with `model` active;
/// the planned carriage set-point is the motor set-point plus the same fixed-point model replayed
/// along it.
pub fn positioning(
    scenario: &crate::scenario::Scenario,
    trace: &crate::run::Trace,
    coeffs: &estimator_core::model::ModelCoeffs,
    model: ModelKind,
) -> Positioning {
    use estimator_core::model::{estimate, ModelState};
    let cpm = trace.counts_per_mm;
    let recs = &trace.records;
    let n = recs.len();
    let arrivals: Vec<f64> = arrivals(scenario, trace).into_iter().map(|a| a.1).collect();
    // Tracking while moving.
    let mut state = ModelState::new(recs.first().map_or(0, |r| r.setpoint_counts.0));
    let (mut sq, mut count) = (0.0, 0usize);
    for r in recs {
        let y = estimate(coeffs, model, &mut state, r.setpoint_counts.0).to_num::<f64>();
        if r.out.telemetry.moving {
            let planned_mm = r.setpoint_counts.to_mm(cpm) + y / 1000.0;
            let e = (r.x_ls_mm - planned_mm) * 1000.0;
            sq += e * e;
            count += 1;
        }
    }
    // Limits of each move, against its stretch of set-points.
    let dt = if n >= 2 {
        recs[1].t_s - recs[0].t_s
    } else {
        1.0 / 2000.0
    };
    let (mut v_ratio, mut a_ratio) = (0.0f64, 0.0f64);
    for (k, m) in scenario.moves.iter().enumerate() {
        let Some(&start) = trace.move_starts.get(k) else {
            break;
        };
        let end = trace.move_starts.get(k + 1).copied().unwrap_or(n);
        let v_lim = m.velocity_mm_s * cpm * dt; // counts per tick
        let a_lim = m.accel_mm_s2 * cpm * dt * dt; // counts per tick^2
        let wv = RATIO_WINDOW_MIN.max((100.0 / v_lim).ceil() as usize);
        let wa = RATIO_WINDOW_MIN.max((200.0 / a_lim).sqrt().ceil() as usize);
        let s = |j: usize| recs[j].setpoint_counts.0 as f64;
        for i in (start + wv)..end {
            v_ratio = v_ratio.max((s(i) - s(i - wv)).abs() / wv as f64 / v_lim);
        }
        for i in (start + 2 * wa)..end {
            let a = (s(i) - 2.0 * s(i - wa) + s(i - 2 * wa)).abs() / (wa * wa) as f64;
            a_ratio = a_ratio.max(a / a_lim);
        }
    }
    let rms = |v: &[f64]| {
        if v.is_empty() {
            0.0
        } else {
            (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
        }
    };
    Positioning {
        arrival_rms_um: rms(&arrivals),
        arrival_max_um: arrivals.iter().fold(0.0f64, |m, x| m.max(x.abs())),
        tracking_rms_um: if count == 0 {
            0.0
        } else {
            (sq / count as f64).sqrt()
        },
        cycle_time_s: n as f64 * dt,
        peak_velocity_ratio: v_ratio,
        peak_accel_ratio: a_ratio,
        moves_at_rest: arrivals.len(),
    }
}

/// Runs `scenario` in carriage space with the core in this process and `model` active.
pub fn run_carriage_space(
    scenario: &crate::scenario::Scenario,
    plant: &PlantParams,
    params: &ModelParams,
    model: ModelKind,
    seed: u64,
    progress: &mut dyn FnMut(f64),
) -> Result<crate::run::Trace, Error> {
    let cfg = drive_config(params, model, plant.rig());
    let drive = Drive::new(&cfg).context(|| "drive configuration".into())?;
    let rc = crate::run::RunConfig {
        seed,
        carriage_space: true,
        ..crate::run::RunConfig::default()
    };
    crate::run::run(
        scenario,
        plant,
        &cfg.settings.rig,
        &mut InProcess(drive),
        &rc,
        progress,
    )
    .context(|| scenario.source().to_string())
}
