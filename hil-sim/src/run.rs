//! Closed-loop scenario runs: plant <-> controller, one record per control tick.

use estimator_core::drive::{Command, Faults, Output, Sample};
use estimator_core::rig::Rig;
use estimator_core::units::MotorCounts;

use crate::controller::{ControlError, Controller};
use crate::plant::{Plant, PlantParams};
use crate::scenario::Scenario;

/// One control tick as recorded for calibration, evaluation and plots.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Record {
    /// Simulated time, seconds.
    pub t_s: f64,
    /// Motor position x_PE as the drive unwrapped it.
    pub motor_counts: MotorCounts,
    /// Carriage position x_LS from the linear scale (0.5 um counts, as read), millimetres.
    pub x_ls_mm: f64,
    /// Trajectory set-point.
    pub setpoint_counts: MotorCounts,
    /// Commanded direction (sign of the set-point's motion, held at rest): +1 or -1.
    pub cmd_dir: i8,
    /// The drive's output (current and telemetry).
    pub out: Output,
}

/// A finished run.
#[derive(Clone, Debug)]
pub struct Trace {
    /// Scenario name.
    pub scenario: String,
    /// Noise seed of the plant.
    pub seed: u64,
    /// Counts per millimetre used to turn x_PE into millimetres.
    pub counts_per_mm: f64,
    /// One record per tick.
    pub records: Vec<Record>,
    /// Index of the record on whose tick each move was commanded.
    pub move_starts: Vec<usize>,
}

impl Trace {
    /// x_PE in millimetres at record `i`.
    pub fn x_pe_mm(&self, i: usize) -> f64 {
        self.records[i].motor_counts.to_mm(self.counts_per_mm)
    }
    /// Delta x = x_LS - x_PE in micrometres at record `i` (the paper's eq. 13).
    pub fn dx_um(&self, i: usize) -> f64 {
        (self.records[i].x_ls_mm - self.x_pe_mm(i)) * 1000.0
    }
}

/// Settings of one run.
#[derive(Clone, Debug)]
pub struct RunConfig {
    /// Control rate, Hz (the drive's own rate).
    pub rate_hz: f64,
    /// Plant noise seed.
    pub seed: u64,
    /// Rest after the last move before the run ends, seconds.
    pub settle_s: f64,
    /// Command the scenario's targets as carriage positions (`MoveTo`: the drive places
    /// the carriage with its active model) instead of motor positions (`MoveMotorTo`).
    pub carriage_space: bool,
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            rate_hz: 2000.0,
            seed: 1,
            settle_s: 0.2,
            carriage_space: false,
        }
    }
}

/// Why a run stopped early.
#[derive(Debug)]
pub enum RunError {
    /// The controller failed or refused a command.
    Control(ControlError),
    /// The drive latched a fault.
    Fault {
        /// The latched faults.
        faults: Faults,
        /// Simulated time of the fault, seconds.
        t_s: f64,
        /// The move under way (counted from 1; 0 before the first) and the number of moves.
        move_n: usize,
        /// See `move_n`.
        moves: usize,
    },
    /// The scenario did not finish within its time budget.
    Timeout {
        /// Simulated time, seconds.
        t_s: f64,
        /// The move under way (counted from 1) and the number of moves.
        move_n: usize,
        /// See `move_n`.
        moves: usize,
    },
    /// The scenario does not fit the drive or the plant (checked before the run).
    Scenario(crate::scenario::ScenarioError),
    /// The plant refused its parameters or the start position.
    Plant(Box<crate::error::Error>),
    /// The core refused the drive configuration (the field is named).
    Drive(estimator_core::ConfigError),
}

impl std::fmt::Display for RunError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RunError::Control(e) => write!(f, "{e}"),
            RunError::Fault {
                faults,
                t_s,
                move_n,
                moves,
            } => {
                write!(f, "drive fault {faults} at t = {t_s:.4} s")?;
                if *move_n == 0 {
                    write!(f, ", before the first move")
                } else {
                    write!(f, ", in move {move_n} of {moves}")
                }
            }
            RunError::Timeout { t_s, move_n, moves } => write!(
                f,
                "move {move_n} of {moves} still under way after {t_s:.1} s of simulated time, \
                 twice the scenario's estimated duration and more: the drive does not arrive \
                 (a target it cannot reach, or a speed too low for it to settle)"
            ),
            RunError::Scenario(e) => write!(f, "{e}"),
            RunError::Plant(e) => write!(f, "{e}"),
            RunError::Drive(e) => write!(f, "drive configuration: {e}"),
        }
    }
}

impl std::error::Error for RunError {}

impl From<ControlError> for RunError {
    fn from(e: ControlError) -> Self {
        RunError::Control(e)
    }
}

/// How often the simulated host polls its drive, seconds: a fifth of the drive's default link
/// timeout (0.5 s), as `beltctl` does.
pub const KEEPALIVE_S: f64 = 0.1;

/// Ticks between two keep-alives of the simulated host at a tick of `dt_s` seconds (200 at
/// 2 kHz); at least one. In time, not ticks: at 250 Hz, 200 ticks would be 0.8 s of silence.
pub fn keepalive_ticks(dt_s: f64) -> u64 {
    let n = (KEEPALIVE_S / dt_s).round();
    // NaN (a NaN tick) compares false, as does anything below one.
    if n >= 1.0 {
        n.min(u32::MAX as f64) as u64
    } else {
        1
    }
}

/// Rough upper bound of a scenario's duration, for the time-out: twice the estimate, 5 s, a few
/// ticks a move (a move of no length still takes them), and the first move's way from where
/// homing leaves the drive (up to the transmission error, well under 1 mm, off `start_mm`).
fn budget_s(s: &Scenario) -> f64 {
    let first = s.moves.first().map_or(0.0, |m| 1.0 / m.velocity_mm_s);
    2.0 * s.duration_estimate_s() + 5.0 + 0.005 * s.moves.len() as f64 + 2.0 * first
}

/// Records reserved up front (about 10 s at 2 kHz); longer runs grow the buffer as they go.
const RECORDS_RESERVED: usize = 20_000;

/// What the board samples: the plant's two raw counters.
pub fn sample(p: &Plant) -> Sample {
    Sample {
        motor_counter: p.motor_counter(),
        scale_counter: p.scale_counter(),
    }
}

/// Homing as on a machine, then `Enable`: one tick at rest so the drive has seen the counters,
/// then both encoders get positions tied to the stage, not to where this run happens to start,
/// so calibrations carry over between runs.
pub fn home_and_enable(
    controller: &mut dyn Controller,
    plant: &Plant,
    rig: &Rig,
) -> Result<(), ControlError> {
    let motor_um = (plant.motor_counts() as f64 / rig.counts_per_mm() * 1000.0).round() as i32;
    let scale_um =
        (plant.scale_counts() as f64 / plant.scale_counts_per_mm() * 1000.0).round() as i32;
    controller.step(sample(plant))?;
    controller.command(Command::Home {
        position_um: motor_um,
        scale_um,
    })?;
    controller.command(Command::Enable)
}

/// Runs `scenario` through `controller` on a fresh plant. `progress` is called with the fraction
/// of the scenario done (moves commanded), for progress bars.
pub fn run(
    scenario: &Scenario,
    plant_params: &PlantParams,
    rig: &Rig,
    controller: &mut dyn Controller,
    cfg: &RunConfig,
    progress: &mut dyn FnMut(f64),
) -> Result<Trace, RunError> {
    // The limits hil-sim's drive runs with, in-process and in the firmware (the paper rig's).
    scenario
        .validate()
        .map_err(|e| e.in_file(scenario.source()))
        .and_then(|_| scenario.check_against(&crate::drive_setup::drive_limits(*rig), plant_params))
        .map_err(RunError::Scenario)?;
    let dt = 1.0 / cfg.rate_hz;
    let keepalive = keepalive_ticks(dt);
    let mut plant = Plant::new(plant_params, scenario.start_mm, cfg.seed)
        .map_err(|e| RunError::Plant(Box::new(e)))?;
    home_and_enable(controller, &plant, rig)?;

    let budget = budget_s(scenario);
    let expected = budget * cfg.rate_hz * 0.6;
    let mut records = Vec::with_capacity(if expected < RECORDS_RESERVED as f64 {
        expected as usize
    } else {
        RECORDS_RESERVED
    });
    let mut move_starts = Vec::with_capacity(scenario.moves.len());
    let mut next = 0usize; // next move to command
    let mut next_at: Option<f64> = Some(0.0); // time it is due, None = when the drive is at rest
    let mut rest_since: Option<f64> = None;
    let mut last_sp = i32::MIN;
    let mut cmd_dir: i8 = 1;
    let mut t = 0.0;
    let mut tick: u64 = 0;
    loop {
        // Commands due this tick go in before the step.
        let due = match next_at {
            Some(at) => t >= at - 0.5 * dt,
            None => rest_since.is_some_and(|since| t >= since - 0.5 * dt),
        };
        if due && next < scenario.moves.len() {
            let m = &scenario.moves[next];
            let (target_um, velocity_um_s, accel_um_s2) = m.drive_units();
            controller.command(Command::move_to(
                cfg.carriage_space,
                target_um,
                velocity_um_s,
                accel_um_s2,
            ))?;
            move_starts.push(records.len());
            next_at = m.retarget_after_ms.map(|ms| t + ms as f64 / 1000.0);
            rest_since = None;
            next += 1;
            progress(next as f64 / scenario.moves.len() as f64);
        } else if due && next == scenario.moves.len() {
            break;
        }

        // A host polls its drive: the link watchdog stays fed (every 100 ms).
        if tick.is_multiple_of(keepalive) {
            controller.keepalive()?;
        }
        let out = controller.step(sample(&plant))?;
        let tel = out.telemetry;
        if !tel.faults.is_clear() {
            return Err(RunError::Fault {
                faults: tel.faults,
                t_s: t,
                move_n: next,
                moves: scenario.moves.len(),
            });
        }
        if last_sp != i32::MIN && tel.setpoint_counts.0 != last_sp {
            cmd_dir = if tel.setpoint_counts.0 > last_sp {
                1
            } else {
                -1
            };
        }
        last_sp = tel.setpoint_counts.0;
        records.push(Record {
            t_s: t,
            motor_counts: tel.motor_counts,
            x_ls_mm: plant.scale_counts() as f64 / plant.scale_counts_per_mm(),
            setpoint_counts: tel.setpoint_counts,
            cmd_dir,
            out,
        });
        plant.step(out.current_a.to_num::<f64>(), dt);
        tick += 1;
        t = tick as f64 * dt;

        // Arrival of a move without retarget: rest for its dwell (or the final settle).
        if next_at.is_none() && rest_since.is_none() && !tel.moving {
            let dwell = scenario.moves[next - 1].dwell_ms as f64 / 1000.0;
            let extra = if next == scenario.moves.len() {
                dwell + cfg.settle_s
            } else {
                dwell
            };
            rest_since = Some(t + extra);
        }
        if t > budget {
            return Err(RunError::Timeout {
                t_s: t,
                move_n: next.max(1),
                moves: scenario.moves.len(),
            });
        }
    }
    Ok(Trace {
        scenario: scenario.name.clone(),
        seed: cfg.seed,
        counts_per_mm: rig.counts_per_mm(),
        records,
        move_starts,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_simulated_host_polls_every_100_ms_at_any_control_rate() {
        assert_eq!(keepalive_ticks(1.0 / 2000.0), 200);
        // Every rate the drive takes (100 Hz to 100 kHz): a poll at least every 100 ms plus
        // half a tick, far inside the 0.5 s link timeout.
        for rate_hz in [100.0, 250.0, 333.0, 1000.0, 7777.0, 100_000.0] {
            let dt = 1.0 / rate_hz;
            let silence_s = keepalive_ticks(dt) as f64 * dt;
            assert!(
                silence_s <= KEEPALIVE_S + dt / 2.0,
                "{rate_hz} Hz: {silence_s} s"
            );
            assert!(
                silence_s >= KEEPALIVE_S - dt / 2.0,
                "{rate_hz} Hz: {silence_s} s"
            );
        }
        for dt in [1.0, f64::INFINITY, f64::NAN, 0.0, -1.0] {
            assert!(keepalive_ticks(dt) >= 1, "{dt}");
        }
    }
}
