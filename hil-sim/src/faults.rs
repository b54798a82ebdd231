//! Fault-injection campaign: each class of failure injected into the simulated plant, its
//! sensors or the link, with the drive's reaction measured (`hil-sim faults`).
//!
//! A class passes when the drive latches the fault it is meant to raise, the current commanded
//! on the tick after detection is zero with the amplifier disabled, and the fault stays latched
//! (zero current, `Enable` refused) until it is cleared. Every scenario preset is also run with
//! no injection: any fault there is a false trip.

use crate::error::{Context, Error};
use estimator_core::drive::{Command, CommandError, Drive, Faults, Output, Sample};
use estimator_core::model::{ModelKind, ModelParams};
use estimator_core::rig::Rig;

use crate::controller::{ControlError, Controller, InProcess};
use crate::drive_setup::drive_config;
use crate::plant::{Plant, PlantParams};
use crate::run::{home_and_enable, keepalive_ticks, RunError};
use crate::scenario::{Scenario, PRESETS};

/// What goes wrong.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Injection {
    /// One encoder channel cut: the x4 count only dithers by one while the motor turns.
    EncoderLineCut,
    /// The encoder counter freezes (dead encoder supply, connector off).
    EncoderStuck,
    /// One sample off by a burst of counts (EMI on the encoder cable).
    CountGlitch,
    /// Motor wires swapped: the current pushes the other way.
    MotorWiresReversed,
    /// An obstacle 2 mm ahead of the carriage.
    CarriageJammed,
    /// A heavy load asked for the drive's full acceleration (5000 mm/s^2): the 8 A limit falls
    /// short. The rotor reflects about 65 kg through the gearbox, so it takes an 80 kg carriage.
    AmplifierSaturated,
    /// The amplifier's input stuck at full current at cruise: the motor overspeeds.
    AmplifierStuck,
    /// The host stops talking.
    LinkSilence,
    /// The control tick runs late once (the plant advances two ticks on one step).
    LateTick,
}

impl Injection {
    /// Every class, in report order.
    pub const ALL: [Injection; 9] = [
        Injection::EncoderLineCut,
        Injection::EncoderStuck,
        Injection::CountGlitch,
        Injection::MotorWiresReversed,
        Injection::CarriageJammed,
        Injection::AmplifierSaturated,
        Injection::AmplifierStuck,
        Injection::LinkSilence,
        Injection::LateTick,
    ];

    /// Its name in the JSON.
    pub fn name(self) -> &'static str {
        match self {
            Injection::EncoderLineCut => "encoder_line_cut",
            Injection::EncoderStuck => "encoder_stuck",
            Injection::CountGlitch => "count_glitch",
            Injection::MotorWiresReversed => "motor_wires_reversed",
            Injection::CarriageJammed => "carriage_jammed",
            Injection::AmplifierSaturated => "amplifier_saturated",
            Injection::AmplifierStuck => "amplifier_stuck_overspeed",
            Injection::LinkSilence => "link_silence",
            Injection::LateTick => "late_tick",
        }
    }

    /// The fault the drive must raise (any of these bits).
    ///
    /// A jammed carriage stops, but the belt still stretches by millimetres under the rising
    /// current, so the motor keeps moving until the current reaches its limit: "effort without
    /// response" shows as the limit held, or as the following error, whichever comes first.
    pub fn expected(self) -> u16 {
        match self {
            Injection::EncoderLineCut | Injection::EncoderStuck => Faults::STALL,
            Injection::CarriageJammed => {
                Faults::STALL | Faults::CURRENT_SATURATION | Faults::FOLLOWING_ERROR
            }
            Injection::CountGlitch => Faults::ENCODER_JUMP,
            Injection::MotorWiresReversed => Faults::RUNAWAY,
            Injection::AmplifierSaturated => Faults::CURRENT_SATURATION,
            Injection::AmplifierStuck => Faults::OVERSPEED,
            Injection::LinkSilence => Faults::LINK_TIMEOUT,
            Injection::LateTick => Faults::DEADLINE_MISSED,
        }
    }

    /// Whether the firmware under QEMU can run it: the plant paces the ticks (none can be
    /// late). A silent host can: the samples do not feed the link watchdog.
    pub fn applies_to_pil(self) -> bool {
        !matches!(self, Injection::LateTick)
    }

    /// The move that is running when the fault strikes: (target mm, mm/s, mm/s^2).
    fn motion(self) -> (f64, f64, f64) {
        match self {
            Injection::AmplifierSaturated => (250.0, 250.0, 5000.0),
            Injection::AmplifierStuck => (280.0, 250.0, 2000.0),
            Injection::CarriageJammed => (200.0, 20.0, 500.0),
            _ => (200.0, 60.0, 1500.0),
        }
    }

    /// Ticks after the move starts at which the fault strikes.
    fn at_tick(self) -> u32 {
        match self {
            // From the start: a wiring error or a load is there before the first move.
            Injection::MotorWiresReversed | Injection::AmplifierSaturated => 0,
            // At cruise (250 mm/s is reached after 125 ms at 2000 mm/s^2).
            Injection::AmplifierStuck => 400,
            _ => 300,
        }
    }

    /// The plant this class runs on.
    fn plant(self, base: &PlantParams) -> PlantParams {
        let mut p = base.clone();
        if self == Injection::AmplifierSaturated {
            p.carriage.mass_kg = 80.0;
        }
        p
    }
}

/// One class's outcome.
#[derive(Clone, Debug, PartialEq)]
pub struct ClassResult {
    /// The injection.
    pub injection: Injection,
    /// The expected fault was latched.
    pub detected: bool,
    /// Ticks from the injection to the first tick that reports a fault (-1 if none).
    pub latency_ticks: i64,
    /// The current commanded on the tick after detection, amperes.
    pub current_after_a: f64,
    /// The amplifier enable on the tick after detection.
    pub amplifier_enabled_after: bool,
    /// Still faulted, at zero current with the amplifier off, 0.5 s later, and `Enable`
    /// refused until `ClearFaults`.
    pub latched: bool,
    /// Every fault latched at detection.
    pub faults: Faults,
}

impl ClassResult {
    /// All four goals met.
    pub fn passed(&self) -> bool {
        self.detected
            && self.current_after_a == 0.0
            && !self.amplifier_enabled_after
            && self.latched
    }
}

/// Ticks a class may take to be detected before it counts as missed (2 s).
const DETECT_LIMIT_TICKS: u32 = 4000;
/// Ticks after detection over which the latch is checked (0.5 s).
const LATCH_TICKS: u32 = 1000;
/// Where the carriage starts, mm.
const START_MM: f64 = 100.0;
/// Counts a glitch adds to one sample.
const GLITCH_COUNTS: u16 = 12_000;

/// What the sensors report, with the injection applied.
struct Sensors {
    injection: Injection,
    /// Motor counter when the fault struck.
    frozen: Option<(u16, i64)>,
}

impl Sensors {
    fn sample(&mut self, plant: &Plant, active: bool, first: bool) -> Sample {
        let real = plant.motor_counter();
        let truth = plant.motor_counts();
        let motor_counter = if !active {
            real
        } else {
            match self.injection {
                Injection::EncoderStuck | Injection::EncoderLineCut => {
                    let (c0, t0) = *self.frozen.get_or_insert((real, truth));
                    if self.injection == Injection::EncoderStuck {
                        c0
                    } else {
                        // One channel dead: the other's edges count up and down in turn.
                        c0.wrapping_add(((truth - t0).div_euclid(2).rem_euclid(2)) as u16)
                    }
                }
                Injection::CountGlitch if first => real.wrapping_add(GLITCH_COUNTS),
                _ => real,
            }
        };
        Sample {
            motor_counter,
            scale_counter: plant.scale_counter(),
        }
    }
}

/// Runs one class through `controller` on a fresh plant.
pub fn run_class(
    injection: Injection,
    base: &PlantParams,
    rig: &Rig,
    controller: &mut dyn Controller,
    seed: u64,
) -> Result<ClassResult, Error> {
    let dt = 1.0 / 2000.0;
    let keepalive = keepalive_ticks(dt);
    let params = injection.plant(base);
    let mut plant = Plant::new(&params, START_MM, seed)?;
    let mut sensors = Sensors {
        injection,
        frozen: None,
    };
    home_and_enable(controller, &plant, rig)?;
    let (to_mm, v, a) = injection.motion();
    controller.command(Command::MoveMotorTo {
        target_um: (to_mm * 1000.0) as i32,
        velocity_um_s: (v * 1000.0) as u32,
        accel_um_s2: (a * 1000.0) as u32,
    })?;

    let strike = injection.at_tick();
    let mut detected_at: Option<(u32, Faults)> = None;
    let mut after: Option<Output> = None;
    let mut latched = true;
    let mut tick: u32 = 0;
    let mut late_done = false;
    loop {
        let active = tick >= strike;
        if !(active && injection == Injection::LinkSilence)
            && (tick as u64).is_multiple_of(keepalive)
        {
            controller.keepalive()?;
        }
        if active && injection == Injection::CarriageJammed && tick == strike {
            let x = plant.carriage_mm();
            plant.set_end_stops_mm(-10.0, x + 2.0);
        }
        let sample = sensors.sample(&plant, active, tick == strike);
        let out = controller.step(sample)?;
        let tel = out.telemetry;

        // The board's enable line cuts the power stage whatever the DAC says.
        let mut i_a = if tel.amplifier_enabled {
            out.current_a.to_num::<f64>()
        } else {
            0.0
        };
        if active && tel.amplifier_enabled {
            match injection {
                Injection::MotorWiresReversed => i_a = -i_a,
                Injection::AmplifierStuck => i_a = plant.current_limit_a(),
                _ => {}
            }
        }
        if active && injection == Injection::LateTick && !late_done {
            // The tick ran late: the plant moved on for two ticks under the old current, and the
            // board reports the miss.
            late_done = true;
            plant.step(i_a, dt);
            controller.missed_ticks(1)?;
        }
        plant.step(i_a, dt);

        match detected_at {
            None if !tel.faults.is_clear() => {
                if !active {
                    return Err(Error::FaultBeforeInjection {
                        faults: tel.faults,
                        tick,
                    }
                    .context(injection.name()));
                }
                detected_at = Some((tick, tel.faults));
            }
            None => {}
            Some((at, _)) => {
                if tick == at + 1 {
                    after = Some(out);
                }
                if tel.faults.is_clear() || out.current_a.to_bits() != 0 || tel.amplifier_enabled {
                    latched = false;
                }
                if tick >= at + LATCH_TICKS {
                    break;
                }
            }
        }
        tick += 1;
        if detected_at.is_none() && tick > strike + DETECT_LIMIT_TICKS {
            break;
        }
    }
    let Some((at, faults)) = detected_at else {
        return Ok(ClassResult {
            injection,
            detected: false,
            latency_ticks: -1,
            current_after_a: f64::NAN,
            amplifier_enabled_after: true,
            latched: false,
            faults: Faults::NONE,
        });
    };
    // Still latched: `Enable` must be refused until the host clears the fault.
    match controller.command(Command::Enable) {
        Err(ControlError::Refused(CommandError::NotEnabled)) => {}
        Ok(()) => latched = false,
        Err(e) => {
            return Err(Error::Control(e)
                .context("enable after the fault")
                .context(injection.name()))
        }
    }
    let after = after.ok_or(Error::NoTickAfterDetection)?;
    Ok(ClassResult {
        injection,
        detected: faults.0 & injection.expected() != 0,
        latency_ticks: at as i64 - strike as i64,
        current_after_a: after.current_a.to_num::<f64>(),
        amplifier_enabled_after: after.telemetry.amplifier_enabled,
        latched,
        faults,
    })
}

/// Runs one class with the core in this process.
pub fn run_class_in_process(
    injection: Injection,
    plant: &PlantParams,
    seed: u64,
) -> Result<ClassResult, Error> {
    let cfg = drive_config(&ModelParams::PAPER, ModelKind::None, plant.rig());
    let drive = Drive::new(&cfg).context(|| "drive configuration".into())?;
    run_class(
        injection,
        plant,
        &cfg.settings.rig,
        &mut InProcess(drive),
        seed,
    )
}

/// Runs every scenario preset with no injection; returns (scenarios run, faults raised, what
/// tripped).
pub fn false_trips(
    plant: &PlantParams,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<(usize, usize, Vec<String>), Error> {
    let mut checked = 0;
    let mut trips = Vec::new();
    for (name, _) in PRESETS {
        let s = Scenario::load(name)?;
        let label = format!("no injection: {name}");
        match crate::eval::run_in_process(
            &s,
            plant,
            &ModelParams::PAPER,
            ModelKind::None,
            1,
            &mut |f| progress(&label, f),
        ) {
            Ok(_) => {}
            Err(RunError::Fault { faults, t_s, .. }) => {
                trips.push(format!("{name}: {faults} at t = {t_s:.4} s"))
            }
            Err(e) => return Err(Error::Run(e).context(*name)),
        }
        checked += 1;
    }
    Ok((checked, trips.len(), trips))
}

/// The campaign's JSON object (one line).
pub fn to_json(
    results: &[ClassResult],
    pil: &[(Injection, Option<bool>)],
    false_trips: usize,
    scenarios_checked: usize,
) -> serde_json::Value {
    let classes: Vec<serde_json::Value> = results
        .iter()
        .map(|r| {
            let pil_same = pil
                .iter()
                .find(|(i, _)| *i == r.injection)
                .and_then(|(_, same)| *same);
            serde_json::json!({
                "name": r.injection.name(),
                "detected": r.detected,
                "latency_ticks": r.latency_ticks,
                "current_after_a": if r.current_after_a.is_finite() {
                    serde_json::json!(r.current_after_a)
                } else {
                    serde_json::Value::Null
                },
                "latched": r.latched,
                "expected_faults": Faults(r.injection.expected()).names().collect::<Vec<_>>(),
                "faults": r.faults.names().collect::<Vec<_>>(),
                "amplifier_enabled_after": r.amplifier_enabled_after,
                "pil": match (r.injection.applies_to_pil(), pil_same) {
                    (false, _) => "not_applicable",
                    (true, None) => "not_run",
                    (true, Some(true)) => "same",
                    (true, Some(false)) => "differs",
                },
            })
        })
        .collect();
    serde_json::json!({
        "classes": classes,
        "false_trips": false_trips,
        "scenarios_checked": scenarios_checked,
    })
}
