//! The command line: arguments (clap) and what each command does.

use std::path::{Path, PathBuf};
use std::time::Duration;

use belt_link::{Command, ModelKind};
use clap::{Args, Parser, Subcommand};
use serde_json::json;

use crate::error::ToolError;
use crate::link::{Link, LinkOptions};
use crate::ops::{self, Arrival, MoveLimits};
use crate::{calibrate, config, port, record, status, validate};
use estimator_core::settings;
use hil_sim::progress::Progress;

/// beltctl: set up, move, record and calibrate a belt-drive controller over its serial link.
#[derive(Parser, Debug)]
#[command(name = "beltctl", version, about, long_about = None)]
pub struct Cli {
    /// How to reach the drive.
    #[command(flatten)]
    pub link: LinkArgs,
    /// Print JSON instead of tables (status, move, config get/save, record, calibrate).
    #[arg(long, global = true)]
    pub json: bool,
    /// What to do.
    #[command(subcommand)]
    pub cmd: Cmd,
}

/// How to reach the drive.
#[derive(Args, Debug, Clone)]
pub struct LinkArgs {
    /// The drive's serial port, e.g. /dev/ttyUSB0 (required).
    #[arg(long, global = true, value_name = "PATH")]
    pub port: Option<String>,
    /// Baud rate (8N1).
    #[arg(long, global = true, default_value_t = port::DEFAULT_BAUD)]
    pub baud: u32,
    /// Time allowed for each reply, ms. The drive hears nothing while the tool waits: above
    /// the default, a wait longer than 0.8 of the drive's link watchdog
    /// (faults.link_timeout_s, 0.5 s by default) is refused.
    #[arg(long, global = true, default_value_t = DEFAULT_TIMEOUT_MS, value_name = "MS",
          value_parser = clap::value_parser!(u64).range(1..=600_000))]
    pub timeout_ms: u64,
    /// Tries per request (a request is sent again after a timeout or when it reached the
    /// drive damaged).
    #[arg(long, global = true, default_value_t = 3, value_name = "N",
          value_parser = clap::value_parser!(u32).range(1..=100))]
    pub retries: u32,
}

/// The commands.
#[derive(Subcommand, Debug)]
pub enum Cmd {
    /// Show the drive's state: flags, faults, model, positions, stored record, reset cause.
    Status,
    /// Enable the current output.
    Enable,
    /// Zero the current at once and stay so.
    Disable,
    /// Decelerate to rest.
    Stop,
    /// Clear latched faults (the drive stays disabled until `enable`).
    ClearFaults,
    /// Select the compensator: none, model1, model2, model3, backlash, bidir_table, model4.
    Model {
        /// The compensator's name.
        name: String,
    },
    /// Run the drive's homing routine and wait until it ends.
    Home {
        /// Give up (and stop the drive) after this long, s.
        #[arg(long, default_value_t = 60.0)]
        timeout_s: f64,
    },
    /// Move to each target in turn and report where the carriage arrived.
    #[command(allow_negative_numbers = true)]
    Move {
        /// Targets, mm of carriage travel.
        #[arg(required = true, value_name = "MM")]
        targets: Vec<f64>,
        /// Cruise speed, mm/s.
        #[arg(long, default_value_t = 50.0, value_name = "MM_S")]
        velocity: f64,
        /// Acceleration and deceleration, mm/s^2.
        #[arg(long, default_value_t = 500.0, value_name = "MM_S2")]
        accel: f64,
        /// Raw motor moves (no compensation) instead of carriage moves.
        #[arg(long)]
        motor: bool,
        /// Rest after arrival before reading the position, ms.
        #[arg(long, default_value_t = 200, value_name = "MS",
              value_parser = clap::value_parser!(u64).range(0..=3_600_000))]
        settle_ms: u64,
        /// The calibration directory (`beltctl calibrate --out`): warn about moves outside the
        /// region its moves covered, where every model extrapolates.
        #[arg(long, value_name = "DIR")]
        calibration: Option<PathBuf>,
    },
    /// Read, change, save, load and dump the drive's configuration.
    #[command(subcommand)]
    Config(ConfigCmd),
    /// Record the drive's samples into a CSV file.
    Record {
        /// How long, s.
        #[arg(long)]
        seconds: f64,
        /// One sample every N control ticks.
        #[arg(long, default_value_t = 1, value_name = "N",
              value_parser = clap::value_parser!(u16).range(1..))]
        every: u16,
        /// The CSV file.
        #[arg(long, value_name = "FILE.csv")]
        out: PathBuf,
    },
    /// Calibrate on the drive: run hil-sim's calibration moves while recording, fit Models 1-4
    /// and the baselines, write the calibration files, upload, verify and select the model.
    Calibrate {
        /// Directory for calibration.bin, calibration.toml and the plots.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Cap on the moves' speed, mm/s (they never exceed the drive's limit either).
        #[arg(long, value_name = "MM_S", value_parser = cap_value)]
        velocity: Option<f64>,
        /// Cap on the moves' acceleration, mm/s^2.
        #[arg(long, value_name = "MM_S2", value_parser = cap_value)]
        accel: Option<f64>,
        /// Seed of the default calibration plan's moves (another seed draws another plan from
        /// the same ranges: calibrating twice shows how stable the fit is on this machine).
        #[arg(long, value_name = "N", default_value_t = hil_sim::eval::CALIBRATION_PLAN_SEED)]
        plan_seed: u64,
        /// A scenario of your machine's own motions (TOML file, in the drive's coordinates),
        /// recorded and fitted besides the default set; give it once per file.
        #[arg(long = "scenario", value_name = "FILE")]
        scenarios: Vec<PathBuf>,
        /// Model selected after the upload.
        #[arg(long, default_value = "model3")]
        model: String,
        /// Save configuration and calibration on the drive afterwards (disables the drive:
        /// it saves only while disabled).
        #[arg(long)]
        save: bool,
        /// This machine's geometry and motor as a plant file (`hil-sim`'s format: encoder,
        /// gearbox, pulley, belt lengths, motor): Model 4's belt observer is identified from
        /// them (the belt's, friction's and carriage's physics start from the paper rig's) and
        /// kept where it fits better than the slip observer. Without it: the slip observer.
        #[arg(long, value_name = "FILE")]
        machine: Option<PathBuf>,
    },
    /// Place the carriage on a scenario's moves once per compensator and compare the arrivals
    /// on the linear scale (commissioning, with the scale fitted); `--select` keeps the best.
    Validate {
        /// The moves (TOML scenario file, in the drive's coordinates): your machine's own.
        #[arg(long, value_name = "FILE")]
        scenario: PathBuf,
        /// Compensators to compare, comma-separated.
        #[arg(
            long,
            value_name = "LIST",
            default_value = "none,model1,model2,model3,backlash,bidir_table,model4"
        )]
        models: String,
        /// Select the compensator with the lowest arrival RMS afterwards (otherwise the one
        /// active before is selected again). To keep it after a restart, set
        /// drive.initial_model and save (`beltctl config set`, `config save`).
        #[arg(long)]
        select: bool,
        /// Least rest after arrival before reading the scale, ms (a move's dwell_ms if longer).
        #[arg(long, default_value_t = 200, value_name = "MS",
              value_parser = clap::value_parser!(u64).range(0..=3_600_000))]
        settle_ms: u64,
        /// The calibration directory (`beltctl calibrate --out`): warn about moves outside the
        /// region its moves covered, where every model extrapolates.
        #[arg(long, value_name = "DIR")]
        calibration: Option<PathBuf>,
    },
}

/// `beltctl config ...`
#[derive(Subcommand, Debug)]
pub enum ConfigCmd {
    /// Show fields (all when none is named): active value, staged value if different, unit.
    Get {
        /// Field names, e.g. rig.gear_ratio.
        names: Vec<String>,
    },
    /// Stage NAME=VALUE for each, then apply them together (the drive must be disabled).
    Set {
        /// Assignments, e.g. rig.gear_ratio=19.2 drive.travel_max_mm=450.
        #[arg(required = true, value_name = "NAME=VALUE")]
        values: Vec<String>,
    },
    /// Store configuration and calibration in the drive's persistent storage.
    Save,
    /// Stage and apply every value of a TOML file of `"name" = value`.
    Load {
        /// The file.
        file: PathBuf,
    },
    /// Print the active configuration as a file `config load` reads back.
    Dump,
}

fn model_kind(name: &str, flag: &str) -> Result<ModelKind, ToolError> {
    name.parse()
        .map_err(|e| ToolError::Usage(format!("{flag}{name}: {e}")))
}

fn connect(a: &LinkArgs) -> Result<Link, ToolError> {
    let path = a.port.as_deref().ok_or_else(|| {
        ToolError::Usage("no port given: use --port PATH (e.g. --port /dev/ttyUSB0)".into())
    })?;
    let mut link = port::connect(
        path,
        a.baud,
        LinkOptions {
            timeout: Duration::from_millis(a.timeout_ms),
            tries: a.retries,
        },
    )?;
    if a.timeout_ms > DEFAULT_TIMEOUT_MS {
        check_timeout(&mut link, a.timeout_ms)?;
    }
    Ok(link)
}

/// The default `--timeout-ms`: within [`WATCHDOG_SHARE`] of the drive's default link watchdog
/// (0.5 s), so only a longer one is checked against the drive's own (one request more).
const DEFAULT_TIMEOUT_MS: u64 = 300;

/// The share of the drive's link watchdog a reply may take: the drive hears nothing while the
/// tool waits, and the request that follows a lost reply must reach it with time to spare.
const WATCHDOG_SHARE: f64 = 0.8;

/// The longest reply wait a link watchdog of `watchdog_s` survives, when `timeout_ms` is
/// longer; `None` when it is within it or the watchdog is off (0).
fn longest_wait_ms(watchdog_s: f64, timeout_ms: u64) -> Option<f64> {
    let most_ms = (watchdog_s * 1000.0 * WATCHDOG_SHARE).floor();
    (watchdog_s > 0.0 && timeout_ms as f64 > most_ms).then_some(most_ms)
}

/// After a link watchdog was applied that this run's `--timeout-ms` would not survive (a lost
/// reply would stop an enabled drive): the longest wait to use with this drive from now on.
fn short_watchdog_warning(
    applied: &[(&'static settings::Field, f64)],
    timeout_ms: u64,
) -> Option<String> {
    let key = estimator_core::ConfigField::FaultsLinkTimeoutS;
    applied.iter().find_map(|&(field, watchdog_s)| {
        let most_ms = longest_wait_ms(watchdog_s, timeout_ms)?;
        (field.field == key).then(|| {
            format!(
                "beltctl: {} = {watchdog_s} s: the drive's link watchdog stops an enabled drive \
                 when one reply is lost within a --timeout-ms of {timeout_ms}; use --timeout-ms \
                 {most_ms} or less with this drive",
                key.name()
            )
        })
    })
}

/// The drive's active control rate (`drive.rate_hz`), before a change: `None` from a drive that
/// does not answer with it (nothing to compare against).
fn active_rate_hz(link: &mut Link) -> Option<f64> {
    let field = config::lookup(estimator_core::ConfigField::DriveRateHz.name()).ok()?;
    config::get(link, field).ok().map(|v| v.active)
}

/// The note for values that changed the control rate: the drive's tick timer is set at boot,
/// so it installs the new rate but refuses to enable until it restarts with it saved.
fn rate_change_warning(
    before_hz: Option<f64>,
    applied: &[(&'static settings::Field, f64)],
) -> Option<String> {
    let key = estimator_core::ConfigField::DriveRateHz;
    let (_, hz) = applied.iter().rev().find(|(f, _)| f.field == key)?;
    let before = before_hz?;
    (*hz != before).then(|| {
        format!(
            "beltctl: {} = {hz} Hz (was {before} Hz): the drive's tick keeps the rate it booted              with, so the drive refuses to enable until it restarts with this configuration:              `beltctl config save`, then restart the drive",
            key.name()
        )
    })
}

/// Refuses a `--timeout-ms` that would let one lost reply trip an enabled drive's link
/// watchdog (`faults.link_timeout_s`): the motor would stop with `link_timeout` mid-move.
fn check_timeout(link: &mut Link, timeout_ms: u64) -> Result<(), ToolError> {
    let field = config::lookup(estimator_core::ConfigField::FaultsLinkTimeoutS.name())
        .map_err(|e| ToolError::Usage(e.to_string()))?;
    let watchdog_s = match config::get(link, field) {
        Ok(v) => v.active,
        // A drive that does not answer with its configuration: nothing to check against.
        Err(ToolError::Refused { .. } | ToolError::Drive(_)) => return Ok(()),
        Err(e) => return Err(e),
    };
    if let Some(most_ms) = longest_wait_ms(watchdog_s, timeout_ms) {
        return Err(ToolError::Usage(format!(
            "--timeout-ms {timeout_ms}: the drive's link watchdog (faults.link_timeout_s) is \
             {watchdog_s} s, and the drive hears nothing while the tool waits for a reply: one \
             lost reply would stop an enabled drive; use at most {most_ms} ms or raise \
             faults.link_timeout_s"
        )));
    }
    Ok(())
}

fn print_json(v: &serde_json::Value) {
    hil_sim::outln!("{v}");
}

/// Runs the command line.
pub fn run(cli: Cli) -> Result<(), ToolError> {
    // Arguments first: a mistyped argument should not need a drive.
    if let Cmd::Model { name } = &cli.cmd {
        model_kind(name, "model ")?;
    }
    if let Cmd::Calibrate { model, .. } = &cli.cmd {
        model_kind(model, "--model ")?;
    }
    let set_values = match &cli.cmd {
        Cmd::Config(ConfigCmd::Set { values }) => values
            .iter()
            .map(|a| config::parse_assignment(a).map_err(|e| ToolError::Usage(e.to_string())))
            .collect::<Result<Vec<_>, _>>()?,
        _ => Vec::new(),
    };
    let get_fields = match &cli.cmd {
        Cmd::Config(ConfigCmd::Get { names }) => names
            .iter()
            .map(|n| config::lookup(n).map_err(|e| ToolError::Usage(e.to_string())))
            .collect::<Result<Vec<_>, _>>()?,
        _ => Vec::new(),
    };
    // The validation's moves and compensators, checked before any port is opened.
    let validation = match &cli.cmd {
        Cmd::Validate {
            scenario,
            models,
            select,
            settle_ms,
            ..
        } => {
            let path = scenario.display().to_string();
            let s = hil_sim::scenario::Scenario::load(&path)
                .map_err(|e| ToolError::Usage(format!("--scenario {e}")))?;
            Some(validate::Options {
                scenario: (path, s),
                models: validate::parse_models(models)?,
                select: *select,
                settle: Duration::from_millis(*settle_ms),
            })
        }
        _ => None,
    };
    let load = match &cli.cmd {
        Cmd::Config(ConfigCmd::Load { file }) => {
            let text =
                hil_sim::input::read_text(file).map_err(|e| ToolError::file(file.display(), e))?;
            config::parse_file(file, &text)?
        }
        _ => Vec::new(),
    };

    let mut link = connect(&cli.link)?;
    let link = &mut link;
    let json = cli.json;
    let timeout_ms = cli.link.timeout_ms;
    match cli.cmd {
        Cmd::Status => {
            let s = link.status()?;
            let rig = match config::rig(link) {
                Ok(r) => Some(r),
                // A drive that answers status but not the configuration: show what we have.
                Err(ToolError::Refused { .. } | ToolError::Drive(_)) => None,
                Err(e) => return Err(e),
            };
            if json {
                print_json(&status::to_json(&s, rig.as_ref()));
            } else {
                hil_sim::out!("{}", status::to_table(link.name(), &s, rig.as_ref()));
            }
        }
        Cmd::Enable => simple(link, Command::Enable, "enabled")?,
        Cmd::Disable => simple(link, Command::Disable, "disabled")?,
        Cmd::Stop => simple(link, Command::Stop, "stopping")?,
        Cmd::ClearFaults => simple(link, Command::ClearFaults, "faults cleared")?,
        Cmd::Model { name } => {
            let m = model_kind(&name, "model ")?;
            simple(
                link,
                Command::SelectModel(m),
                &format!("model {m} selected"),
            )?
        }
        Cmd::Home { timeout_s } => {
            if !(timeout_s.is_finite() && timeout_s > 0.0) {
                return Err(ToolError::Usage(format!(
                    "--timeout-s {timeout_s}: must be > 0"
                )));
            }
            let s = ops::home(link, Duration::from_secs_f64(timeout_s.min(86_400.0)))?;
            if json {
                print_json(&status::to_json(&s, None));
            } else {
                hil_sim::outln!(
                    "homed: carriage at {:.3} mm, scale {:.1} um",
                    s.carriage_estimate_um as f64 / 1000.0,
                    status::scale_um(&s)
                );
            }
        }
        Cmd::Move {
            targets,
            velocity,
            accel,
            motor,
            settle_ms,
            calibration,
        } => {
            let limits = MoveLimits {
                velocity_mm_s: velocity,
                accel_mm_s2: accel,
            };
            let calibration = calibration.as_deref();
            moves(link, &targets, &limits, motor, settle_ms, calibration, json)?
        }
        Cmd::Config(c) => match c {
            ConfigCmd::Get { .. } => {
                let values = if get_fields.is_empty() {
                    config::get_all(link)?
                } else {
                    get_fields
                        .iter()
                        .map(|f| config::get(link, f))
                        .collect::<Result<Vec<_>, _>>()?
                };
                if json {
                    let obj: serde_json::Map<_, _> = values
                        .iter()
                        .map(|v| {
                            (
                                v.field.name().to_string(),
                                json!({"active": v.active, "staged": v.staged_change(),
                                       "unit": v.field.unit}),
                            )
                        })
                        .collect();
                    print_json(&serde_json::Value::Object(obj));
                } else {
                    for v in &values {
                        let staged = v.staged_change().map_or(String::new(), |s| {
                            format!("  (staged: {})", config::format_value(v.field, s))
                        });
                        hil_sim::outln!(
                            "{:<42} {:>14}  {}{staged}",
                            v.field.name(),
                            config::format_value(v.field, v.active),
                            v.field.unit
                        );
                    }
                }
            }
            ConfigCmd::Set { .. } => {
                let rate_before = active_rate_hz(link);
                config::set_and_apply(link, &set_values, "config set")?;
                hil_sim::outln!("applied {}", values(set_values.len()));
                if let Some(w) = short_watchdog_warning(&set_values, timeout_ms) {
                    hil_sim::errln!("{w}");
                }
                if let Some(w) = rate_change_warning(rate_before, &set_values) {
                    hil_sim::errln!("{w}");
                }
            }
            ConfigCmd::Load { file } => {
                let rate_before = active_rate_hz(link);
                config::set_and_apply(link, &load, &file.display().to_string())?;
                hil_sim::outln!("applied {} from {}", values(load.len()), file.display());
                if let Some(w) = short_watchdog_warning(&load, timeout_ms) {
                    hil_sim::errln!("{w}");
                }
                if let Some(w) = rate_change_warning(rate_before, &load) {
                    hil_sim::errln!("{w}");
                }
            }
            ConfigCmd::Save => {
                config::require_disabled(link, "saving")?;
                let (seq, crc) = calibrate::save(link)?;
                if json {
                    print_json(&json!({"seq": seq, "crc": format!("{crc:08x}")}));
                } else {
                    hil_sim::outln!("saved: record {seq}, crc {crc:08x}");
                }
            }
            ConfigCmd::Dump => {
                let values = config::get_all(link)?;
                hil_sim::out!("{}", config::dump(link.name(), &values));
            }
        },
        Cmd::Record {
            seconds,
            every,
            out,
        } => {
            let (written, stats) = record::record(link, seconds, every, &out)?;
            if json {
                print_json(&json!({
                    "samples": written, "file": out.display().to_string(),
                    "frames": stats.frames, "lost_frames": stats.lost_frames,
                    "missing_samples": stats.missing_samples,
                }));
            } else {
                hil_sim::outln!("wrote {written} samples to {}", out.display());
            }
            stats.check().map_err(|e| {
                ToolError::Drive(format!("{e} ({} holds what arrived)", out.display()))
            })?;
        }
        Cmd::Calibrate {
            out,
            velocity,
            accel,
            plan_seed,
            scenarios,
            model,
            save,
            machine,
        } => {
            // The error names the file and the field.
            let machine = machine
                .map(|p| {
                    hil_sim::PlantParams::load(&p)
                        .map(|m| (p.clone(), m))
                        .map_err(|e| ToolError::Usage(format!("--machine {e}")))
                })
                .transpose()?;
            let scenarios = scenarios
                .iter()
                .map(|p| {
                    let path = p.display().to_string();
                    // The error names the file, the move and the field.
                    hil_sim::scenario::Scenario::load(&path)
                        .map(|s| (path, s))
                        .map_err(|e| ToolError::Usage(format!("--scenario {e}")))
                })
                .collect::<Result<Vec<_>, _>>()?;
            let opts = calibrate::Options {
                out,
                velocity_cap: velocity,
                accel_cap: accel,
                plan_seed,
                scenarios,
                model: model_kind(&model, "--model ")?,
                save,
                machine,
            };
            let mut progress = Progress::named("beltctl");
            let o = calibrate::run(link, &opts, &mut progress)?;
            progress.finish();
            for w in &o.plot_warnings {
                hil_sim::errln!("beltctl: warning: plot not drawn: {w}");
            }
            let rms: serde_json::Map<_, _> = o
                .calibration
                .fit_rms_um
                .iter()
                .map(|(k, v)| (k.as_str().to_string(), json!(v)))
                .collect();
            if !json {
                hil_sim::outln!("| model | fit RMS (um) |\n|---|---:|");
                for (k, v) in &o.calibration.fit_rms_um {
                    hil_sim::outln!("| {} | {v:.2} |", k.as_str());
                }
                hil_sim::outln!(
                    "\n{} samples; blob {} bytes, crc {:08x}, uploaded and verified; {} selected{}",
                    o.calibration.samples,
                    o.blob_len,
                    o.blob_crc,
                    opts.model,
                    o.saved_crc
                        .map_or(String::new(), |c| format!("; saved, crc {c:08x}"))
                );
                for f in &o.files {
                    hil_sim::outln!("wrote {}", f.display());
                }
            } else {
                print_json(&json!({
                    "fit_rms_um": rms,
                    "samples": o.calibration.samples,
                    "blob_crc": format!("{:08x}", o.blob_crc),
                    "saved_crc": o.saved_crc.map(|c| format!("{c:08x}")),
                }));
            }
        }
        Cmd::Validate { calibration, .. } => {
            let Some(opts) = validation else {
                return Err(ToolError::Usage("validate: no options".into()));
            };
            if let Some(dir) = &calibration {
                warn_outside(link, dir, &opts.scenario.1)?;
            }
            let settings = config::settings(link)?;
            let mut progress = Progress::named("beltctl");
            let o = validate::run(link, &settings, &opts, &mut progress)?;
            progress.finish();
            print_validation(&o, json);
        }
    }
    Ok(())
}

/// Warns, on stderr, about the moves of `s` that leave the region the calibration in `dir`
/// covered (every model extrapolates there). The files must be readable and made for the
/// drive's geometry; a calibration without a region gets a note.
fn warn_outside(
    link: &mut Link,
    dir: &Path,
    s: &hil_sim::scenario::Scenario,
) -> Result<(), ToolError> {
    let rig = config::rig(link)?;
    let cal = hil_sim::calfile::load(dir, &rig)
        .map_err(|e| ToolError::Usage(format!("--calibration {}: {e}", dir.display())))?;
    if let Some(line) = hil_sim::coverage::advice(cal.coverage.as_ref(), s) {
        hil_sim::errln!("beltctl: {line}");
    }
    Ok(())
}

/// The validation's table (or one JSON object): arrival RMS and max per compensator.
fn print_validation(o: &validate::Outcome, json: bool) {
    if json {
        let per = |f: fn(&validate::Placed) -> f64| -> serde_json::Map<String, serde_json::Value> {
            o.placed
                .iter()
                .map(|p| (p.model.as_str().to_string(), json!(f(p))))
                .collect()
        };
        print_json(&json!({
            "scenario": o.scenario,
            "arrivals": o.placed.first().map_or(0, |p| p.errors_um.len()),
            "arrival_rms_um": per(validate::Placed::rms_um),
            "arrival_max_um": per(validate::Placed::max_um),
            "best": o.best.as_str(),
            "active": o.active.as_str(),
            // What `config set drive.initial_model=N` takes to keep it after a restart.
            "initial_model": o.active as u8,
        }));
        return;
    }
    hil_sim::outln!(
        "{}: {} arrivals per compensator, |scale - target| in um\n\n| compensator | RMS | max |\n|---|---:|---:|",
        o.scenario,
        o.placed.first().map_or(0, |p| p.errors_um.len())
    );
    for p in &o.placed {
        let mark = if p.model == o.best { " (best)" } else { "" };
        hil_sim::outln!(
            "| {}{mark} | {:.1} | {:.1} |",
            p.model,
            p.rms_um(),
            p.max_um()
        );
    }
    hil_sim::outln!(
        "\n{} selected{}",
        o.active,
        if o.active == o.best {
            format!(
                "; to keep it after a restart: `beltctl disable`, `beltctl config set \
                 drive.initial_model={}`, `beltctl config save` (then home again)",
                o.active as u8
            )
        } else {
            format!(" again (the best, {}, with --select)", o.best)
        }
    );
}

fn values(n: usize) -> String {
    format!("{n} value{}", if n == 1 { "" } else { "s" })
}

fn simple(link: &mut Link, cmd: Command, done: &str) -> Result<(), ToolError> {
    link.command(cmd)?;
    hil_sim::outln!("{done}");
    Ok(())
}

fn moves(
    link: &mut Link,
    targets: &[f64],
    limits: &MoveLimits,
    motor: bool,
    settle_ms: u64,
    calibration: Option<&Path>,
    json: bool,
) -> Result<(), ToolError> {
    // Arguments checked before anything moves.
    let cmds = targets
        .iter()
        .map(|&mm| ops::move_command(ops::target_um(mm)?, limits, motor).map(|c| (mm, c)))
        .collect::<Result<Vec<_>, _>>()?;
    let start = link.status()?;
    ops::require_ready(&start, "moving")?;
    match calibration {
        Some(_) if motor => hil_sim::errln!(
            "beltctl: note: --calibration is not checked with --motor (raw motor moves: no model \
             places them)"
        ),
        Some(dir) => {
            // The moves as a scenario from where the carriage stands, for the region's check.
            let moves = targets
                .iter()
                .map(|&to_mm| hil_sim::scenario::Move {
                    to_mm,
                    velocity_mm_s: limits.velocity_mm_s,
                    accel_mm_s2: limits.accel_mm_s2,
                    dwell_ms: 0,
                    retarget_after_ms: None,
                })
                .collect();
            let s = hil_sim::scenario::Scenario {
                name: "beltctl move".into(),
                start_mm: start.carriage_estimate_um as f64 / 1000.0,
                moves,
                source: String::new(),
            };
            warn_outside(link, dir, &s)?;
        }
        None => {}
    }
    let counts_per_mm = config::rig(link).ok().map(|r| r.counts_per_mm());
    let mut here = start.carriage_estimate_um as f64 / 1000.0;
    let mut errors = Vec::with_capacity(targets.len());
    for (mm, cmd) in cmds {
        ops::move_and_wait(link, cmd, mm - here, limits, |_| Ok(()))?;
        // Polled: a rest of 0.5 s or more would trip the drive's link watchdog.
        ops::dwell(link, Duration::from_millis(settle_ms))?;
        let s = link.status()?;
        let a = Arrival::of(mm, &s, counts_per_mm);
        errors.push(a.error_um());
        here = a.estimate_mm;
        if json {
            print_json(&json!({
                "target_mm": a.target_mm,
                "estimate_mm": a.estimate_mm,
                "motor_mm": a.motor_mm,
                "scale_mm": a.scale_mm,
                "scale_minus_target_um": a.error_um(),
            }));
        } else {
            hil_sim::outln!(
                "target {:>10.3} mm   estimate {:>10.3} mm   scale {:>10.4} mm   scale - target \
                 {:>8.1} um",
                a.target_mm,
                a.estimate_mm,
                a.scale_mm,
                a.error_um()
            );
        }
    }
    let (rms, max) = ops::rms_and_max_um(&errors);
    if json {
        print_json(&json!({"count": errors.len(), "rms_um": rms, "max_um": max}));
    } else if errors.len() > 1 {
        hil_sim::outln!(
            "{} moves: |scale - target| RMS {rms:.1} um, max {max:.1} um",
            errors.len()
        );
    }
    Ok(())
}

/// A calibration cap: a number of at least 0.001 (the drive's unit), refused before the port
/// is opened (NaN would otherwise leave the moves uncapped, 0 ask for moves that never end).
fn cap_value(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.001 => Ok(v),
        Ok(_) => Err("must be a number of at least 0.001".into()),
        Err(e) => Err(e.to_string()),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn calibration_caps_are_numbers_of_at_least_the_drive_s_unit() {
        for ok in ["0.001", "10", " 250.5 ", "1e6"] {
            assert!(super::cap_value(ok).is_ok(), "{ok}");
        }
        for bad in ["nan", "NaN", "inf", "-inf", "0", "-1", "0.0009", "", "ten"] {
            assert!(super::cap_value(bad).is_err(), "{bad}");
        }
    }

    /// A link watchdog applied below what this run's wait survives is warned about, with the
    /// longest wait to use; one that leaves room, one switched off (0) and other fields are not.
    #[test]
    fn a_link_watchdog_shorter_than_the_reply_wait_is_warned_about() {
        let f = |name| crate::config::lookup(name).unwrap();
        let watchdog = f("faults.link_timeout_s");
        let w = super::short_watchdog_warning(&[(f("pid.kp_a_per_mm"), 0.1), (watchdog, 0.2)], 300)
            .expect("a warning");
        for says in [
            "faults.link_timeout_s = 0.2 s",
            "--timeout-ms of 300",
            "160 or less",
        ] {
            assert!(w.contains(says), "lacks `{says}`: {w}");
        }
        assert!(super::short_watchdog_warning(&[(watchdog, 0.2)], 160).is_none());
        assert!(super::short_watchdog_warning(&[(watchdog, 0.5)], 300).is_none());
        assert!(super::short_watchdog_warning(&[(watchdog, 0.0)], 300).is_none());
        assert!(super::short_watchdog_warning(&[(f("pid.kp_a_per_mm"), 0.2)], 300).is_none());
    }

    /// A configuration of another control rate is applied but not run until the drive restarts:
    /// `config set` / `load` say so with what to do, and the drive's refusal to enable says why.
    /// The same rate, other fields and a drive that did not answer with its rate give no note.
    #[test]
    fn a_changed_control_rate_is_noted_with_the_restart_it_needs() {
        use belt_link::{Command, Request};
        let f = |name| crate::config::lookup(name).unwrap();
        let rate = f("drive.rate_hz");
        let mut link = crate::testing::endpoint_drive(|_| false);
        let before = super::active_rate_hz(&mut link);
        assert_eq!(before, Some(2000.0));
        crate::config::set_and_apply(&mut link, &[(rate, 4000.0)], "config set").unwrap();
        let w = super::rate_change_warning(before, &[(rate, 4000.0)]).expect("a note");
        for says in [
            "drive.rate_hz = 4000 Hz (was 2000 Hz)",
            "beltctl config save",
            "restart",
        ] {
            assert!(w.contains(says), "lacks `{says}`: {w}");
        }
        let e = link
            .acked(&Request::Command(Command::Enable))
            .unwrap_err()
            .to_string();
        assert!(e.contains("the control rate changed"), "{e}");
        assert!(super::rate_change_warning(before, &[(rate, 2000.0)]).is_none());
        assert!(super::rate_change_warning(before, &[(f("pid.kp_a_per_mm"), 2.0)]).is_none());
        assert!(super::rate_change_warning(None, &[(rate, 4000.0)]).is_none());
    }
}
