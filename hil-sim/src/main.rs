//! `hil-sim`: the belt-drive simulator's command line.
// Output only through `stdout` (`out!`, `outln!`, `errln!`): the std macros panic on a closed pipe.
#![deny(clippy::print_stdout, clippy::print_stderr)]

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use estimator_core::model::ModelKind;
use hil_sim::calibrate::Calibration;
use hil_sim::error::{Context, Error};
use hil_sim::pil::PilOptions;
use hil_sim::plant::PlantParams;
use hil_sim::progress::Progress;
use hil_sim::scenario::Scenario;
use hil_sim::{calfile, drive_setup, eval, generalise, report};

#[derive(Parser)]
#[command(
    name = "hil-sim",
    version,
    about = "Simulated timing-belt drive: run, calibrate and evaluate the belt-drive controller"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(clap::Args, Clone)]
struct Common {
    /// Plant parameters (TOML); default: the built-in `paper-rig` preset.
    #[arg(long)]
    plant: Option<PathBuf>,
    /// Noise seed of the evaluated run (calibration runs use their own seeds).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// A calibration directory written by `hil-sim calibrate`; default: calibrate now.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Processor in the loop: the firmware runs under QEMU and closes the loop over its USART.
    #[arg(long)]
    pil: bool,
    /// Firmware ELF for --pil (default: target/thumbv7em-none-eabihf/release/belt-drive).
    #[arg(long)]
    elf: Option<PathBuf>,
    /// Lowest level of the firmware's defmt log shown with --pil (trace, debug, info, warn, error).
    #[arg(long, default_value = "info")]
    log_level: String,
}

impl Common {
    /// Runs `scenario` in-process, or under QEMU with --pil.
    fn run(
        &self,
        scenario: &Scenario,
        plant: &PlantParams,
        params: &estimator_core::model::ModelParams,
        model: ModelKind,
        progress: &mut Progress,
    ) -> Result<hil_sim::run::Trace, Error> {
        self.run_as(scenario, plant, params, model, false, progress)
    }

    /// The scenario in carriage space once per compensator, in-process or under QEMU.
    fn placement(
        &self,
        scenario: &Scenario,
        plant: &PlantParams,
        params: &estimator_core::model::ModelParams,
        progress: &mut Progress,
    ) -> Result<Vec<hil_sim::placement::Placement>, Error> {
        hil_sim::placement::compare(scenario, params, &plant.rig(), &mut |model| {
            self.run_as(scenario, plant, params, model, true, progress)
        })
    }

    /// [`Common::run`], the targets as motor or (`carriage_space`) carriage positions.
    fn run_as(
        &self,
        scenario: &Scenario,
        plant: &PlantParams,
        params: &estimator_core::model::ModelParams,
        model: ModelKind,
        carriage_space: bool,
        progress: &mut Progress,
    ) -> Result<hil_sim::run::Trace, Error> {
        let label = format!(
            "{} {}{}",
            if self.pil { "PIL" } else { "run" },
            scenario.name,
            if carriage_space {
                format!(" placing with {model}")
            } else {
                String::new()
            }
        );
        let mut p = |f| progress.stage(&label, f);
        let rc = hil_sim::run::RunConfig {
            seed: self.seed,
            carriage_space,
            ..hil_sim::run::RunConfig::default()
        };
        if self.pil {
            let elf = self
                .elf
                .clone()
                .unwrap_or_else(|| PilOptions::default_elf(None));
            if !elf.exists() {
                return Err(Error::NoFirmware(elf));
            }
            let mut opts = PilOptions::new(elf);
            opts.min_level = hil_sim::pil::qemu::LEVELS
                .iter()
                .find(|l| **l == self.log_level)
                .ok_or_else(|| Error::Argument {
                    flag: "--log-level",
                    value: self.log_level.clone(),
                    rule: "use trace, debug, info, warn or error".into(),
                })?;
            eval::run_pil(scenario, plant, params, model, &rc, &opts, &mut p)
        } else if carriage_space {
            hil_sim::placement::run_carriage_space(
                scenario, plant, params, model, self.seed, &mut p,
            )
        } else {
            eval::run_in_process(scenario, plant, params, model, self.seed, &mut p)
                .context(|| scenario.source().to_string())
        }
    }
}

#[derive(Subcommand)]
enum Cmd {
    /// Run a scenario and print Table 3 (max, min, RMS of e = x_LS - x_PE - y) for every model.
    Evaluate {
        /// Scenario file, or a preset name.
        #[arg(long)]
        scenario: String,
        #[command(flatten)]
        common: Common,
        /// Print one JSON object instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Record the calibration scenarios and fit Models 1-3 and the baselines.
    Calibrate {
        /// Plant parameters (TOML); default: `paper-rig`.
        #[arg(long)]
        plant: Option<PathBuf>,
        /// Output directory for calibration.bin and calibration.toml.
        #[arg(long, default_value = "out/calibration")]
        out: PathBuf,
        /// Seed of the default calibration plan's moves: another seed draws another plan from
        /// the same ranges (how much the fit depends on the draw).
        #[arg(long, default_value_t = eval::CALIBRATION_PLAN_SEED)]
        plan_seed: u64,
        /// A scenario of your machine's own motions (file or preset name), recorded and fitted
        /// besides the default set; give it once per scenario.
        #[arg(long = "scenario", value_name = "FILE")]
        scenarios: Vec<String>,
        /// Model 4's observer of the belt in the tooth gap: `belt` identifies the belt observer
        /// from the plant file's geometry and motor (about 10 s more) and keeps it where it
        /// fits the recordings better than the slip observer; `slip` fits the slip observer only.
        #[arg(long, default_value = "belt", value_parser = ["belt", "slip"])]
        observer: String,
    },
    /// Run a scenario and write every tick as CSV.
    Run {
        /// Scenario file, or a preset name.
        #[arg(long)]
        scenario: String,
        #[command(flatten)]
        common: Common,
        /// Compensator the drive uses for its estimate: none, model1, model2, model3, backlash,
        /// bidir_table, model4.
        #[arg(long, default_value = "model3")]
        model: String,
        /// CSV output file ("-" for standard output).
        #[arg(long, default_value = "-")]
        out: String,
    },
    /// Fault-injection campaign: inject each fault class into the simulated plant, sensors or
    /// link and check that the drive detects it, stops the current and latches; then run every
    /// scenario preset without injection and count false trips. Exits non-zero on any miss.
    Faults {
        /// Plant parameters (TOML); default: `paper-rig`.
        #[arg(long)]
        plant: Option<PathBuf>,
        /// Noise seed of the runs.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Also run the classes that apply with the firmware under QEMU and require the same
        /// result.
        #[arg(long)]
        pil: bool,
        /// Firmware ELF for --pil (default: target/thumbv7em-none-eabihf/release/belt-drive).
        #[arg(long)]
        elf: Option<PathBuf>,
        /// Print one JSON object instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// The generalisation table: every estimator and the floor on every scenario preset and a
    /// generated workload of every class, on the paper rig and the built-in plant variants,
    /// each calibrated by its own default plan (Markdown on stdout).
    Generalise {
        /// More plant files to include.
        #[arg(long)]
        plant: Vec<PathBuf>,
        /// Seed of the generated workloads.
        #[arg(long, default_value_t = generalise::TABLE_SEED)]
        seed: u64,
        /// Leave out the built-in variants (tight belt, worn belt, heavy carriage, other
        /// geometry).
        #[arg(long)]
        no_variants: bool,
        /// Also N machines drawn at random around the paper rig (seeds 1 to N; see
        /// `generalise::drawn_plant`).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=100))]
        drawn: u64,
        /// Seed of every plant's default calibration plan (as `calibrate --plan-seed`). Several
        /// (`3233,7,8`): every draw is measured and a summary of Model 4 over the draws is
        /// printed instead of the tables.
        #[arg(long, value_delimiter = ',', default_values_t = [eval::CALIBRATION_PLAN_SEED])]
        plan_seed: Vec<u64>,
        /// Also draw the tables as a PNG picture to this file (with several plan seeds, one
        /// picture per draw: the seed is added to the file's name).
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Model 4's observer, as `calibrate --observer`.
        #[arg(long, default_value = "belt", value_parser = ["belt", "slip"])]
        observer: String,
    },
    /// Calibrate, run the scenario, and write report.md with PNG figures (Figs. 11, 18-24).
    Report {
        /// Scenario file, or a preset name.
        #[arg(long, default_value = "fig18")]
        scenario: String,
        #[command(flatten)]
        common: Common,
        /// Output directory.
        #[arg(long, default_value = "out/report")]
        out: PathBuf,
    },
    /// A virtual drive: the firmware under QEMU on the simulated plant, its link on a
    /// pseudo-terminal that a host tool opens like a USB-serial adapter. Runs until Ctrl-C,
    /// SIGTERM, or a host's Shutdown request.
    VirtualDrive {
        /// Plant parameters (TOML); default: the built-in `paper-rig` preset.
        #[arg(long)]
        plant: Option<PathBuf>,
        /// The drive's storage (a file standing in for the flash sectors; created if missing).
        #[arg(long)]
        storage: PathBuf,
        /// Make this symbolic link to the terminal (e.g. /tmp/belt-drive).
        #[arg(long)]
        link: Option<PathBuf>,
        /// Carriage position at power-on, mm (the drive must home to learn it).
        #[arg(long, default_value_t = 150.0)]
        start_mm: f64,
        /// Plant noise seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Plant time per wall time (1 = real time, 0 = as fast as QEMU runs; else 0.01 to 1000).
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// Firmware ELF (default: target/thumbv7em-none-eabihf/release/belt-drive).
        #[arg(long)]
        elf: Option<PathBuf>,
        /// Write the firmware's defmt log here (default: stderr).
        #[arg(long)]
        log: Option<PathBuf>,
    },
}

/// A file the run will write (`flag`'s value): a regular file it may write (and, with
/// `regular_only`, read: the drive's storage), or a new one in a directory that exists; without
/// `regular_only` also a device or a FIFO (`--log /dev/null`). Checked before anything starts,
/// so that a drive does not run without its storage or its log.
fn output_file(flag: &'static str, path: &Path, regular_only: bool) -> Result<(), Error> {
    let refuse = |rule: String| Error::Argument {
        flag,
        value: path.display().to_string(),
        rule,
    };
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => std::fs::OpenOptions::new()
            .read(regular_only)
            .write(true)
            .open(path)
            .map(drop)
            .map_err(|e| refuse(format!("cannot be opened: {e}"))),
        Ok(m) if m.is_dir() => Err(refuse("is a directory".into())),
        Ok(_) if !regular_only => Ok(()),
        Ok(_) => Err(refuse("is not a regular file (a device or a FIFO)".into())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let parent = path.parent().filter(|p| !p.as_os_str().is_empty());
            match parent {
                Some(dir) if !dir.is_dir() => Err(refuse(format!(
                    "its directory {} does not exist",
                    dir.display()
                ))),
                _ => Ok(()),
            }
        }
        Err(e) => Err(refuse(e.to_string())),
    }
}

/// A directory the command writes its files into (made, with its parents, when it writes):
/// a path that is a file fails before minutes of simulation, not after. Nothing is made here,
/// so that a refused run leaves nothing behind.
fn output_dir(flag: &'static str, path: &Path) -> Result<(), Error> {
    if path.exists() && !path.is_dir() {
        return Err(Error::Argument {
            flag,
            value: path.display().to_string(),
            rule: "is not a directory".into(),
        });
    }
    // Made and tried now: a directory that cannot be written fails before the run, not after.
    calfile::check_writable(path).map_err(|e| Error::Argument {
        flag,
        value: path.display().to_string(),
        rule: format!("cannot be written ({e})"),
    })
}

/// The plant file (or the built-in paper rig), for a virtual drive: its host configures the
/// drive, so any valid plant will do.
fn any_plant(path: &Option<PathBuf>) -> Result<PlantParams, Error> {
    match path {
        None => Ok(PlantParams::paper_rig()),
        Some(p) => Ok(PlantParams::load(p)?),
    }
}

/// [`any_plant`] for the in-process commands, whose drive is the paper rig's tuning with the
/// plant's geometry: a geometry it refuses is named by the plant file, not later by a run.
fn plant_params(path: &Option<PathBuf>) -> Result<PlantParams, Error> {
    let p = any_plant(path)?;
    p.check_default_drive()?;
    Ok(p)
}

fn calibration(
    common: &Common,
    plant: &PlantParams,
    progress: &mut Progress,
) -> Result<Calibration, Error> {
    match &common.calibration {
        Some(dir) => {
            hil_sim::errln!("model parameters: {}", dir.display());
            Ok(calfile::load(dir, &plant.rig())?)
        }
        None => {
            hil_sim::errln!(
                "model parameters: calibrating on {} now (give --calibration DIR to reuse one)",
                plant.name()
            );
            eval::calibrate_plant(plant, &mut |stage, f| progress.stage(stage, f))
        }
    }
}

/// Plant, calibration and the scenario's run with Model 3 active: what `evaluate` and `report`
/// share.
struct Session {
    scenario: Scenario,
    plant: PlantParams,
    cal: Calibration,
    trace: hil_sim::run::Trace,
    progress: Progress,
}

/// The scenario and the plant, checked against each other and the drive's limits before
/// anything runs.
fn scenario_and_plant(
    scenario: &str,
    plant: &Option<PathBuf>,
) -> Result<(Scenario, PlantParams), Error> {
    let scenario = Scenario::load(scenario)?;
    let plant = plant_params(plant)?;
    scenario.check_against(&drive_setup::drive_limits(plant.rig()), &plant)?;
    Ok((scenario, plant))
}

/// Says which moves of `scenario` leave the region the calibration covers (every model
/// extrapolates there), or that the calibration file does not record it.
fn warn_outside(scenario: &Scenario, cal: &Calibration) {
    if let Some(line) = hil_sim::coverage::advice(cal.coverage.as_ref(), scenario) {
        hil_sim::errln!("{line}");
    }
}

/// `check` sees the scenario before anything runs (a report checks the files it will write).
fn session(
    scenario: &str,
    common: &Common,
    check: &dyn Fn(&Scenario) -> Result<(), Error>,
) -> Result<Session, Error> {
    let (scenario, plant) = scenario_and_plant(scenario, &common.plant)?;
    check(&scenario)?;
    let mut progress = Progress::new();
    let cal = calibration(common, &plant, &mut progress)?;
    warn_outside(&scenario, &cal);
    let trace = common.run(
        &scenario,
        &plant,
        &cal.params,
        ModelKind::Table,
        &mut progress,
    )?;
    Ok(Session {
        scenario,
        plant,
        cal,
        trace,
        progress,
    })
}

fn evaluate(scenario: &str, common: &Common, json: bool) -> Result<(), Error> {
    let Session {
        scenario,
        plant,
        cal,
        trace,
        mut progress,
    } = session(scenario, common, &|_| Ok(()))?;
    let coeffs = cal.params.build(&plant.rig())?;
    let est = eval::estimates(&trace, &coeffs);
    let table = eval::table3(&trace, &est);
    // Placement: the scenario again in carriage space, once per compensator the drive has.
    let placed: Vec<_> = common
        .placement(&scenario, &plant, &cal.params, &mut progress)?
        .into_iter()
        .map(|p| (p.name, p.positioning))
        .collect();
    progress.finish();
    if json {
        hil_sim::outln!(
            "{}",
            eval::to_json(&trace.scenario, trace.records.len(), &table, &placed)?
        );
    } else {
        hil_sim::out!(
            "{}",
            report::table_markdown(
                &trace.scenario,
                trace.records.len(),
                &table,
                eval::paper_setting(&scenario, &plant)
            )
        );
        hil_sim::out!("\n{}", report::placement_markdown(&placed));
    }
    Ok(())
}

fn run_csv(scenario: &str, common: &Common, model: &str, out: &str) -> Result<(), Error> {
    let kind: ModelKind = model.parse().map_err(|e| Error::Argument {
        flag: "--model",
        value: model.to_string(),
        rule: format!("{e}"),
    })?;
    if out != "-" {
        output_file("--out", Path::new(out), false)?;
    }
    let (scenario, plant) = scenario_and_plant(scenario, &common.plant)?;
    let mut progress = Progress::new();
    // As documented for every command: the given calibration, or one made now on this plant.
    let cal = calibration(common, &plant, &mut progress)?;
    warn_outside(&scenario, &cal);
    let params = cal.params;
    let trace = common.run(&scenario, &plant, &params, kind, &mut progress)?;
    progress.finish();
    let mut w: Box<dyn std::io::Write> = if out == "-" {
        Box::new(hil_sim::stdout::Sink)
    } else {
        Box::new(std::io::BufWriter::new(
            std::fs::File::create(out).map_err(|e| Error::io(out, e))?,
        ))
    };
    report::write_csv(&mut w, &trace).map_err(|e| Error::io(out, e))
}

fn faults_campaign(
    plant: &Option<PathBuf>,
    seed: u64,
    pil: bool,
    elf: &Option<PathBuf>,
    json: bool,
) -> Result<(), Error> {
    use hil_sim::faults::{self, Injection};
    let plant = plant_params(plant)?;
    let mut progress = Progress::new();
    let mut results = Vec::new();
    for (k, inj) in Injection::ALL.iter().enumerate() {
        progress.stage("fault injection", k as f64 / Injection::ALL.len() as f64);
        results.push(faults::run_class_in_process(*inj, &plant, seed)?);
    }
    let mut pil_same = Vec::new();
    if pil {
        let elf = elf.clone().unwrap_or_else(|| PilOptions::default_elf(None));
        if !elf.exists() {
            return Err(Error::NoFirmware(elf));
        }
        let applicable: Vec<_> = results
            .iter()
            .filter(|r| r.injection.applies_to_pil())
            .collect();
        for (k, host) in applicable.iter().enumerate() {
            progress.stage(
                "fault injection, firmware under QEMU",
                k as f64 / applicable.len() as f64,
            );
            // Configured over the link for the plant's geometry.
            let mut opts = PilOptions::new(&elf).with_rig(plant.rig());
            opts.min_level = "warn";
            let mut c = hil_sim::pil::PilController::start(&opts).context(|| "PIL".into())?;
            let r = faults::run_class(host.injection, &plant, &plant.rig(), &mut c, seed)
                .context(|| format!("PIL {}", host.injection.name()))?;
            let status = c.shutdown(0).context(|| "PIL".into())?;
            if status != 0 {
                return Err(Error::QemuExit(status));
            }
            pil_same.push((host.injection, Some(r == **host)));
            if r != **host {
                hil_sim::errln!(
                    "PIL {} differs: host {:?}, firmware {:?}",
                    host.injection.name(),
                    host,
                    r
                );
            }
        }
    }
    let (checked, trips, what) = faults::false_trips(&plant, &mut |s, f| progress.stage(s, f))?;
    progress.finish();
    for w in &what {
        hil_sim::errln!("false trip: {w}");
    }
    if json {
        hil_sim::outln!("{}", faults::to_json(&results, &pil_same, trips, checked));
    } else {
        hil_sim::outln!("| class | expected (any) | raised | detected | latency (ticks) | current after (A) | latched | PIL |");
        hil_sim::outln!("|---|---|---|---|---:|---:|---|---|");
        for r in &results {
            let p = pil_same.iter().find(|(i, _)| *i == r.injection);
            hil_sim::outln!(
                "| {} | {} | {} | {} | {} | {} | {} | {} |",
                r.injection.name(),
                estimator_core::drive::Faults(r.injection.expected()),
                r.faults,
                r.detected,
                r.latency_ticks,
                r.current_after_a,
                r.latched,
                match (r.injection.applies_to_pil(), p) {
                    (false, _) => "n/a",
                    (true, Some((_, Some(true)))) => "same",
                    (true, Some(_)) => "differs",
                    (true, None) => "not run",
                }
            );
        }
        hil_sim::outln!(
            "
false trips: {trips} on {checked} scenario presets"
        );
    }
    let failed: Vec<_> = results
        .iter()
        .filter(|r| !r.passed())
        .map(|r| r.injection.name())
        .collect();
    let differs = pil_same.iter().any(|(_, s)| *s != Some(true));
    if !failed.is_empty() || trips != 0 || differs {
        return Err(Error::CampaignFailed {
            failed,
            trips,
            pil_differs: differs,
        });
    }
    Ok(())
}

/// `--observer`'s observer (clap has checked the name).
fn observer(name: &str) -> eval::Observer {
    match name {
        "slip" => eval::Observer::Slip,
        _ => eval::Observer::Belt,
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Evaluate {
            scenario,
            common,
            json,
        } => evaluate(&scenario, &common, json),
        Cmd::Calibrate {
            plant,
            out,
            plan_seed,
            scenarios,
            observer: obs,
        } => (|| {
            output_dir("--out", &out)?;
            let plant = plant_params(&plant)?;
            let user = scenarios
                .iter()
                .map(|s| Scenario::load(s))
                .collect::<Result<Vec<_>, _>>()?;
            let mut progress = Progress::new();
            let cal = eval::calibrate_plant_for(
                &plant,
                plan_seed,
                &user,
                observer(&obs),
                &mut |s, f| progress.stage(s, f),
            )?;
            progress.finish();
            calfile::save(&out, &cal, &plant.rig())?;
            if let Some(c) = &cal.coverage {
                hil_sim::errln!("{}", c.markdown());
                let lim = hil_sim::workloads::Limits::of(&drive_setup::drive_limits(plant.rig()));
                for w in c.short_of(lim.max_velocity_mm_s, lim.max_accel_mm_s2) {
                    hil_sim::errln!("warning: {w}");
                }
            }
            hil_sim::errln!(
                "reversal dead band: {} counts",
                cal.params.reversal_deadband_counts
            );
            // A transition that never meets the far band edge leaves the estimate inside the
            // band after long strokes: worth knowing before the tables go to a machine.
            for (name, c) in [
                ("model1", cal.params.model1.closing()),
                ("model2", cal.params.model2.closing()),
            ] {
                for (dir, d) in [("forward", c.forward_mm), ("reverse", c.reverse_mm)] {
                    match d {
                        Some(mm) => hil_sim::errln!("{name} {dir} transition closes after {mm} mm"),
                        None => hil_sim::errln!(
                            "warning: {name}'s {dir} transition never meets the far band edge \
                             within {} mm: its estimate stays inside the band after long strokes",
                            estimator_core::model::Closing::LIMIT_MM
                        ),
                    }
                }
            }
            for (k, rms) in cal.fit_rms_um {
                hil_sim::errln!(
                    "fit {:<7} RMS {:6.2} um on {} calibration samples",
                    k.as_str(),
                    rms,
                    cal.samples
                );
            }
            hil_sim::errln!(
                "wrote {} and {}",
                out.join("calibration.bin").display(),
                out.join("calibration.toml").display()
            );
            Ok(())
        })(),
        Cmd::Run {
            scenario,
            common,
            model,
            out,
        } => run_csv(&scenario, &common, &model, &out),
        Cmd::Faults {
            plant,
            seed,
            pil,
            elf,
            json,
        } => faults_campaign(&plant, seed, pil, &elf, json),
        Cmd::VirtualDrive {
            plant,
            storage,
            link,
            start_mm,
            seed,
            speed,
            elf,
            log,
        } => (|| {
            let plant = any_plant(&plant)?;
            let elf = elf.unwrap_or_else(|| PilOptions::default_elf(None));
            if !elf.exists() {
                return Err(Error::NoFirmware(elf));
            }
            // Below 1 % of real time the drive's timeouts would take hours of wall time.
            if !(speed == 0.0 || (0.01..=1000.0).contains(&speed)) {
                return Err(Error::Argument {
                    flag: "--speed",
                    value: speed.to_string(),
                    rule: "must be 0 (as fast as QEMU runs) or 0.01 to 1000".into(),
                });
            }
            output_file("--storage", &storage, true)?;
            if let Some(path) = &log {
                output_file("--log", path, false)?;
            }
            let mut pil = PilOptions::new(elf);
            pil.storage = Some(storage.clone());
            // Runs for as long as the host needs it.
            pil.timeout = std::time::Duration::from_secs(24 * 3600);
            if let Some(path) = log {
                pil.log = hil_sim::pil::qemu::LogSink::File(path);
            }
            let opts = hil_sim::pil::virtual_drive::VirtualDriveOptions {
                pil,
                plant,
                start_mm,
                seed,
                link,
                speed,
            };
            hil_sim::errln!(
                "virtual drive: plant {}, storage {}",
                opts.plant.name(),
                storage.display()
            );
            let end = hil_sim::pil::virtual_drive::run(&opts, &mut |tty| {
                // stdout: the port, for scripts.
                hil_sim::outln!("{}", tty.display());
                hil_sim::errln!("virtual drive: link on {}", tty.display());
            })?;
            hil_sim::errln!(
                "virtual drive: stopped after {} ticks{}",
                end.ticks,
                end.exit_code
                    .map(|c| format!(", firmware exit {c}"))
                    .unwrap_or_default()
            );
            Ok(())
        })(),
        Cmd::Generalise {
            plant,
            seed,
            no_variants,
            drawn,
            plan_seed,
            plot,
            observer: obs,
        } => (|| {
            // A picture that cannot be written is refused before minutes of measuring.
            if let Some(path) = &plot {
                let png = path
                    .extension()
                    .is_some_and(|e| e.eq_ignore_ascii_case("png"));
                if !png {
                    return Err(Error::Argument {
                        flag: "--plot",
                        value: path.display().to_string(),
                        rule: "must be a .png file".into(),
                    });
                }
                output_file("--plot", path, true)?;
            }
            let mut plants = if no_variants {
                vec![PlantParams::paper_rig()]
            } else {
                generalise::plants()?
            };
            for p in &plant {
                let p = PlantParams::load(p)?;
                p.check_default_drive()?;
                plants.push(p);
            }
            plants.extend((1..=drawn).map(generalise::drawn_plant));
            let mut progress = Progress::new();
            let mut draws = Vec::new();
            let mut jobs = Vec::new();
            for p in plants {
                let w = generalise::workloads(&p, seed)?;
                jobs.push((p, w));
            }
            for &plan in &plan_seed {
                let tables = generalise::measure_all(&jobs, plan, observer(&obs), &mut |s, f| {
                    progress.stage(&format!("plan {plan}: {s}"), f)
                })?;
                draws.push((plan, tables));
            }
            progress.finish();
            match draws.as_slice() {
                [(_, tables)] => hil_sim::out!("{}", generalise::markdown(tables)),
                _ => hil_sim::out!("{}", generalise::draws_markdown(&draws, seed)),
            }
            if let Some(path) = &plot {
                for (plan, tables) in &draws {
                    let file = match draws.len() {
                        1 => path.clone(),
                        _ => generalise::seeded_path(path, *plan),
                    };
                    hil_sim::plot::generalisation(&file, tables)
                        .map_err(|e| Error::Figure(file.display().to_string(), e.to_string()))?;
                }
            }
            Ok(())
        })(),
        Cmd::Report {
            scenario,
            common,
            out,
        } => (|| {
            output_dir("--out", &out)?;
            // The files the report writes whatever happens: one that exists and cannot be
            // written (a directory of that name) fails now, not after the run. `--out` itself
            // is made only when the report writes.
            let targets = |s: &Scenario| {
                for file in report::required_files(&s.name) {
                    let path = out.join(file);
                    if std::fs::symlink_metadata(&path).is_ok() {
                        output_file("--out", &path, false)?;
                    }
                }
                Ok(())
            };
            let Session {
                scenario,
                plant,
                cal,
                trace,
                mut progress,
            } = session(&scenario, &common, &targets)?;
            let how = if common.pil {
                "firmware under QEMU (PIL)"
            } else {
                "core in-process"
            };
            let placed = common.placement(&scenario, &plant, &cal.params, &mut progress)?;
            let setting = report::Setting {
                scenario: &scenario,
                plant: &plant,
                how,
            };
            report::write(
                Path::new(&out),
                &setting,
                &trace,
                &cal,
                &placed,
                &mut progress,
            )?;
            progress.finish();
            hil_sim::errln!("wrote {}", out.join("report.md").display());
            Ok(())
        })(),
    };
    hil_sim::stdout::exit_code(match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // A missing scenario's error lists the presets itself; other files are no preset.
            hil_sim::errln!("hil-sim: {e}");
            ExitCode::FAILURE
        }
    })
}
