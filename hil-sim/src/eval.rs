//! Table 3: calibrate on the calibration scenarios (their own noise seeds), run a scenario, and
//! report max, min and RMS of e = x_LS - x_PE - y (eq. 19) for every model and both baselines.

use estimator_core::drive::Drive;
use estimator_core::model::{self, ModelCoeffs, ModelKind, ModelParams, ModelState};
use estimator_core::rig::Rig;

use crate::calibrate::{calibrate_with, Calibration};
use crate::controller::{Controller, InProcess};
use crate::drive_setup::{drive_config, drive_limits};
use crate::error::{Context, Error};
use crate::plant::PlantParams;
use crate::run::{run, RunConfig, RunError, Trace};
use crate::scenario::Scenario;
use crate::stats::ErrorStats;

/// Scenarios the calibration records (Figs. 9-15 experiments); never the test scenarios.
pub const CALIBRATION_SCENARIOS: &[&str] = &["repeatability", "reversals", "velocities"];
/// Seed of the default calibration plan's moves.
pub const CALIBRATION_PLAN_SEED: u64 = 0xCA1;
/// Length of the default calibration plan, simulated seconds.
pub const CALIBRATION_PLAN_S: f64 = 60.0;
/// Noise seeds of calibration runs start here; evaluation runs use their own seed.
pub const CALIBRATION_SEED_BASE: u64 = 1_000;

/// Names of the estimators in report order.
pub const ESTIMATORS: &[&str] = &[
    "none",
    "model1",
    "model2",
    "model3",
    "backlash",
    "bidir_table",
    "model4",
];

/// A firmware under QEMU that is sent no configuration (`PilOptions::settings` is `None`) runs
/// with the paper rig's: a plant of another geometry cannot run with it in the loop. With a
/// configuration sent, [`run_pil`] configures the drive for the plant's geometry instead.
pub fn check_pil_geometry(plant: &PlantParams) -> Result<(), Error> {
    let (paper, has) = (Rig::PAPER, plant.rig());
    if paper == has {
        return Ok(());
    }
    Err(Error::PilGeometry {
        paper,
        plant: plant.name().to_string(),
        has,
    })
}

/// Runs `scenario` with the core in-process.
pub fn run_in_process(
    scenario: &Scenario,
    plant: &PlantParams,
    params: &ModelParams,
    model: ModelKind,
    seed: u64,
    progress: &mut dyn FnMut(f64),
) -> Result<Trace, RunError> {
    let cfg = drive_config(params, model, plant.rig());
    let drive = Drive::new(&cfg).map_err(RunError::Drive)?;
    let mut c = InProcess(drive);
    run_with(scenario, plant, &cfg.settings.rig, &mut c, seed, progress)
}

/// Runs `scenario` through any controller (in-process or PIL).
pub fn run_with(
    scenario: &Scenario,
    plant: &PlantParams,
    rig: &Rig,
    controller: &mut dyn Controller,
    seed: u64,
    progress: &mut dyn FnMut(f64),
) -> Result<Trace, RunError> {
    let rc = RunConfig {
        seed,
        ..RunConfig::default()
    };
    run(scenario, plant, rig, controller, &rc, progress)
}

/// What a calibration records, in order: the paper's calibration scenarios, the default plan
/// drawn with `plan_seed` ([`CALIBRATION_PLAN_SEED`] unless a study asks for another draw), and
/// the user's own scenarios, every one checked against the plant and the drive's limits before
/// anything is recorded (a scenario they do not fit fails at once, by name).
pub fn calibration_scenarios(
    plant: &PlantParams,
    plan_seed: u64,
    user: &[Scenario],
) -> Result<Vec<Scenario>, Error> {
    let limits = drive_limits(plant.rig());
    let mut scenarios = CALIBRATION_SCENARIOS
        .iter()
        .map(|name| Scenario::load(name))
        .collect::<Result<Vec<_>, _>>()?;
    for s in &scenarios {
        s.check_against(&limits, plant)
            .context(|| "calibration scenario".into())?;
    }
    // The default plan across the drive's configured range (see `workloads::calibration_plan`).
    let lim = crate::workloads::Limits::of(&limits);
    let plan = crate::workloads::calibration_plan(&lim, plan_seed, CALIBRATION_PLAN_S);
    plan.check_against(&limits, plant)
        .context(|| "calibration plan".into())?;
    scenarios.push(plan);
    for s in user {
        s.check_against(&limits, plant)
            .context(|| "calibration scenario".into())?;
        scenarios.push(s.clone());
    }
    Ok(scenarios)
}

/// Records [`calibration_scenarios`] with the Table 2 presets loaded (the models do not
/// influence the motion: the loop closes on the motor encoder).
pub fn record_calibration(
    plant: &PlantParams,
    plan_seed: u64,
    user: &[Scenario],
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Vec<Trace>, Error> {
    record(
        plant,
        &calibration_scenarios(plant, plan_seed, user)?,
        progress,
    )
}

/// Records calibration runs of `scenarios`, each with its own noise seed.
fn record(
    plant: &PlantParams,
    scenarios: &[Scenario],
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Vec<Trace>, Error> {
    let mut traces = Vec::new();
    for (k, s) in scenarios.iter().enumerate() {
        let label = format!("record {}", s.name);
        let t = run_in_process(
            s,
            plant,
            &ModelParams::PAPER,
            ModelKind::None,
            CALIBRATION_SEED_BASE + k as u64,
            &mut |f| progress(&label, f),
        )
        // Where the scenario came from: a user's file, `preset NAME` or `workload NAME`.
        .context(|| s.source().to_string())?;
        traces.push(t);
    }
    Ok(traces)
}

/// True when `scenario` and `plant` are the paper's own setting (the Fig. 18 preset's moves on
/// the built-in paper rig), where Table 3's published figures can be set beside ours.
pub fn paper_setting(scenario: &Scenario, plant: &PlantParams) -> bool {
    let same_plant = PlantParams {
        source: String::new(),
        ..plant.clone()
    } == PlantParams::paper_rig();
    same_plant && is_paper_fig18(scenario)
}

/// True when `scenario` has the moves of the paper's Fig. 18 (the `fig18` preset), whatever its
/// name or file.
pub fn is_paper_fig18(scenario: &Scenario) -> bool {
    Scenario::load("fig18")
        .is_ok_and(|f| f.start_mm == scenario.start_mm && f.moves == scenario.moves)
}

/// Records the calibration scenarios and the default plan, and calibrates.
pub fn calibrate_plant(
    plant: &PlantParams,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Calibration, Error> {
    calibrate_plant_with(plant, CALIBRATION_PLAN_SEED, &[], progress)
}

/// [`calibrate_plant`] with the default plan drawn with `plan_seed` and the user's scenarios
/// recorded besides; the calibration records the region their moves cover.
pub fn calibrate_plant_with(
    plant: &PlantParams,
    plan_seed: u64,
    user: &[Scenario],
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Calibration, Error> {
    calibrate_plant_for(plant, plan_seed, user, Observer::default(), progress)
}

/// Which observer of the belt's place in the tooth gap Model 4's calibration fits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Observer {
    /// The slip observer (`estimator_core::model::slip`) only: six parameters, about 10 s.
    Slip,
    /// Also the belt observer (`estimator_core::model::belt`), identified from the plant file's
    /// geometry and motor with the paper rig's physics as the start (about 10 s more on this
    /// machine); kept where it fits the recordings better than the slip observer.
    #[default]
    Belt,
}

/// [`calibrate_plant_with`] fitting Model 4 with `observer`.
pub fn calibrate_plant_for(
    plant: &PlantParams,
    plan_seed: u64,
    user: &[Scenario],
    observer: Observer,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Calibration, Error> {
    let scenarios = calibration_scenarios(plant, plan_seed, user)?;
    let traces = record(plant, &scenarios, progress)?;
    let start = (observer == Observer::Belt)
        .then(|| crate::belt_observer::BeltPhysics::identification_start(plant));
    let mut cal = calibrate_with(&traces, &plant.rig(), start.as_ref(), progress)?;
    cal.coverage = Some(crate::coverage::Coverage::of(&scenarios));
    Ok(cal)
}

/// Every estimator's y along `trace`, um, in `ESTIMATORS` order: every compensator of the drive
/// (the paper's models and the baselines) replayed through the fixed-point code the firmware
/// runs, from the recorded motor counts.
pub fn estimates(trace: &Trace, coeffs: &ModelCoeffs) -> Vec<(&'static str, Vec<f64>)> {
    let x0 = trace.records.first().map_or(0, |r| r.motor_counts.0);
    ModelKind::ALL
        .iter()
        .map(|&kind| {
            let mut st = ModelState::new(x0);
            let y = trace
                .records
                .iter()
                .map(|r| {
                    // The current as commanded (the simulations wire it with normal polarity).
                    model::estimate_with_current(
                        coeffs,
                        kind,
                        &mut st,
                        r.motor_counts.0,
                        r.out.current_a,
                    )
                    .to_num::<f64>()
                })
                .collect();
            (kind.as_str(), y)
        })
        .collect()
}

/// Table 3 for one trace.
pub fn table3(
    trace: &Trace,
    estimates: &[(&'static str, Vec<f64>)],
) -> Vec<(&'static str, ErrorStats)> {
    estimates
        .iter()
        .filter_map(|(name, y)| {
            ErrorStats::of((0..trace.records.len()).map(|i| trace.dx_um(i) - y[i]))
                .map(|s| (*name, s))
        })
        .collect()
}

/// The JSON object of `hil-sim evaluate --json`: Table 3 (`models`) and carriage placement
/// (`positioning`), each keyed by estimator name.
pub fn to_json(
    scenario: &str,
    samples: usize,
    table: &[(&'static str, ErrorStats)],
    positioning: &[(&'static str, crate::placement::Positioning)],
) -> Result<String, Error> {
    fn by_name<T: serde::Serialize>(
        rows: &[(&'static str, T)],
    ) -> serde_json::Map<String, serde_json::Value> {
        rows.iter()
            .map(|(n, v)| {
                (
                    n.to_string(),
                    serde_json::to_value(v).unwrap_or(serde_json::Value::Null),
                )
            })
            .collect()
    }
    let v = serde_json::json!({
        "scenario": scenario,
        "samples": samples,
        "models": by_name(table),
        "positioning": by_name(positioning),
    });
    // serde_json writes NaN and infinities as null: a result that is not a number is an error.
    match first_null("", &v) {
        Some(at) => Err(Error::NotANumber {
            scenario: scenario.to_string(),
            field: at.trim_start_matches('.').to_string(),
        }),
        None => Ok(v.to_string()),
    }
}

/// The path of the first null in `v`, if any.
fn first_null(path: &str, v: &serde_json::Value) -> Option<String> {
    match v {
        serde_json::Value::Null => Some(path.to_string()),
        serde_json::Value::Object(m) => m
            .iter()
            .find_map(|(k, v)| first_null(&format!("{path}.{k}"), v)),
        serde_json::Value::Array(a) => a
            .iter()
            .enumerate()
            .find_map(|(i, v)| first_null(&format!("{path}[{i}]"), v)),
        _ => None,
    }
}

/// Runs `scenario` with the firmware under QEMU in the loop: the drive is configured over the
/// link for the plant's geometry (the paper rig's limits, as in-process), the calibration goes
/// over the link as the image, the model is selected by command, then the very same scenario
/// code as [`run_in_process`] drives it. Ends QEMU and checks its exit status.
pub fn run_pil(
    scenario: &Scenario,
    plant: &PlantParams,
    params: &ModelParams,
    model: ModelKind,
    rc: &RunConfig,
    opts: &crate::pil::PilOptions,
    progress: &mut dyn FnMut(f64),
) -> Result<Trace, Error> {
    let rig = plant.rig();
    let opts = opts.clone().with_rig(rig);
    if opts.settings.is_none() {
        check_pil_geometry(plant)?;
    }
    let image = estimator_core::image::of_params(params, &rig)?;
    let mut c = crate::pil::PilController::start(&opts).context(|| "PIL".into())?;
    c.load_calibration(&image)
        .context(|| "PIL: loading the calibration".into())?;
    c.send_command(estimator_core::drive::Command::SelectModel(model))
        .context(|| format!("PIL: selecting {model}"))?;
    let trace = run(scenario, plant, &rig, &mut c, rc, progress)
        .context(|| format!("PIL: {}", scenario.source()))?;
    let status = c.shutdown(0).context(|| "PIL".into())?;
    if status != 0 {
        return Err(Error::QemuExit(status));
    }
    Ok(trace)
}
