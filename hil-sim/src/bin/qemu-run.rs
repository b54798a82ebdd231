//! Cargo runner for `thumbv7em-none-eabihf`: runs a firmware ELF under QEMU (netduinoplus2) with
//! semihosting, prints its defmt log decoded with the ELF's own table, and exits with the
//! firmware's semihosting exit status (124 on timeout, 2 on a runner error, 141 when the reader
//! of the log went away first: QEMU is stopped then, and the firmware's verdict is unknown, as
//! for a writer the shell saw ended by SIGPIPE).
//!
//! ```text
//! qemu-run [--timeout SECS] [--icount SHIFT] [--log-level LEVEL] [--log-file PATH] ELF [ignored...]
//! qemu-run --bench [--check FILE] [--log-level LEVEL] [ELF]
//!                                                  PIL runs per model: instructions per tick,
//!                                                 host/firmware equality, stack, flash, RAM
//! qemu-run --pil-fuzz N [--log-level LEVEL] [ELF] N bad frames through USART2 in PIL mode
//!                                                 (the emulated serial line, byte by byte)
//! qemu-run --footprint [--check FILE] ELF          flash and static RAM only, no QEMU (the
//!                                                 real board's image, tools/board-target.json)
//! ```
//! `.cargo/qemu-runner.sh` calls it for `cargo test-target` / `cargo run-qemu`; ELF defaults to
//! the `cargo fw-qemu` output for `--bench` and `--pil-fuzz`.
// Output only through `stdout` (`out!`, `outln!`, `errln!`): the std macros panic on a closed pipe.
#![deny(clippy::print_stdout, clippy::print_stderr)]

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::Parser;
use hil_sim::pil::qemu::{LogSink, Qemu, QemuError, QemuOptions, LEVELS};
use hil_sim::pil::{bench, PilOptions, Transport};

/// The command line.
#[derive(Parser)]
#[command(
    name = "qemu-run",
    about = "Runs a belt-drive firmware ELF under QEMU (netduinoplus2) with its defmt log decoded; \
             or benchmarks it (--bench) or fuzzes its link (--pil-fuzz)"
)]
struct Args {
    /// Wall-clock limit of a plain run, seconds (exit 124 when reached).
    #[arg(long, default_value_t = 120.0)]
    timeout: f64,
    /// QEMU `-icount` shift of a plain run (0 counts instructions exactly), or `off`.
    #[arg(long, default_value = "4")]
    icount: String,
    /// Lowest defmt level shown (default: trace for a run, warn for --bench and --pil-fuzz).
    #[arg(long, value_parser = LEVELS)]
    log_level: Option<String>,
    /// Write the decoded log to this file instead of standard output.
    #[arg(long)]
    log_file: Option<PathBuf>,
    /// PIL runs per compensator: instructions per tick, host/firmware equality, stack, flash,
    /// static RAM; the last line is one JSON object.
    #[arg(long)]
    bench: bool,
    /// Flash and static RAM of the ELF from its section headers only (no QEMU run; any build,
    /// e.g. the real board's); the last line is one JSON object.
    #[arg(long, conflicts_with_all = ["bench", "pil_fuzz"], requires = "elf")]
    footprint: bool,
    /// With --bench or --footprint: fail when a figure exceeds this checked-in JSON file.
    #[arg(long)]
    check: Option<PathBuf>,
    /// With --bench: run only this model (e.g. for a tick profile, tools/tick-profile.sh).
    #[arg(long, requires = "bench", conflicts_with = "check")]
    model: Option<estimator_core::model::ModelKind>,
    /// N bad frames through USART2 in PIL mode (the emulated serial line, byte by byte).
    #[arg(long, value_name = "N", conflicts_with = "bench")]
    pil_fuzz: Option<u32>,
    /// The firmware ELF (default for --bench and --pil-fuzz: the `cargo fw-qemu` output).
    elf: Option<PathBuf>,
    /// Cargo appends the test binary's own arguments (filters, --nocapture): defmt-test runs
    /// every test, so they are ignored.
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, hide = true)]
    ignored: Vec<String>,
}

fn main() -> ExitCode {
    hil_sim::stdout::exit_code(run())
}

fn run() -> ExitCode {
    let args = match Args::try_parse() {
        Ok(a) => a,
        Err(e) => {
            let _ = e.print();
            return ExitCode::from(if e.use_stderr() { 2 } else { 0 });
        }
    };
    // A year is far beyond any run and far inside `Duration`.
    if !(args.timeout > 0.0 && args.timeout <= 3.2e7) {
        hil_sim::errln!(
            "qemu-run: --timeout {}: must be more than 0 and at most 3.2e7 seconds (a year)",
            args.timeout
        );
        return ExitCode::from(2);
    }
    let icount = match args.icount.as_str() {
        "off" => None,
        v => match v.parse::<u8>() {
            Ok(s) => Some(s),
            Err(_) => {
                hil_sim::errln!("qemu-run: --icount {v}: use a shift of 0-255 or `off`");
                return ExitCode::from(2);
            }
        },
    };
    let level_of = |default: &'static str| -> &'static str {
        args.log_level
            .as_deref()
            .and_then(|l| LEVELS.iter().find(|x| **x == l).copied())
            .unwrap_or(default)
    };
    let log = match &args.log_file {
        Some(p) => LogSink::File(p.clone()),
        None => LogSink::Stdout,
    };
    if args.check.is_some() && !(args.bench || args.footprint) {
        hil_sim::errln!("qemu-run: --check needs --bench or --footprint");
        return ExitCode::from(2);
    }
    // clap requires the ELF with --footprint.
    if let (true, Some(elf)) = (args.footprint, &args.elf) {
        return run_footprint(elf, args.check.as_deref());
    }
    if args.bench || args.pil_fuzz.is_some() {
        let elf = args
            .elf
            .clone()
            .unwrap_or_else(|| PilOptions::default_elf(None));
        let mut opts = PilOptions::new(elf);
        opts.min_level = level_of("warn");
        opts.log = log;
        return match args.pil_fuzz {
            // The fuzz goes through the emulated USART2, the board's byte-by-byte path.
            Some(n) => run_fuzz(
                &PilOptions {
                    transport: Transport::Usart,
                    ..opts
                },
                n,
            ),
            None => run_bench(&opts, args.check.as_deref(), args.model),
        };
    }
    let Some(elf) = args.elf else {
        hil_sim::errln!("qemu-run: no firmware ELF given (see --help)");
        return ExitCode::from(2);
    };

    let mut opts = QemuOptions::new(elf);
    opts.timeout = Duration::from_secs_f64(args.timeout);
    opts.icount_shift = icount;
    opts.log = log;
    opts.min_level = level_of("trace");
    opts.keep_lines = 0;
    let to_stdout = args.log_file.is_none();
    let result = Qemu::spawn(&opts)
        .and_then(|mut q| q.wait_unless(|| to_stdout && hil_sim::stdout::reader_gone()));
    match result {
        // `qemu-run ELF | head`: the reader took what it wanted; quiet, but no success either.
        Ok(None) => ExitCode::from(141),
        Ok(Some(code)) => {
            if code != 0 {
                hil_sim::errln!("qemu-run: firmware exited with status {code}");
            }
            ExitCode::from(code.clamp(0, 255) as u8)
        }
        Err(e @ QemuError::Timeout(_)) => {
            hil_sim::errln!("qemu-run: {e}");
            ExitCode::from(124)
        }
        Err(e) => {
            hil_sim::errln!("qemu-run: {e}");
            ExitCode::from(2)
        }
    }
}

fn run_bench(
    opts: &PilOptions,
    check: Option<&std::path::Path>,
    only: Option<estimator_core::model::ModelKind>,
) -> ExitCode {
    hil_sim::outln!(
        "belt-drive PIL bench: {} under QEMU netduinoplus2, -icount shift={}",
        opts.elf.display(),
        opts.icount_shift
    );
    hil_sim::outln!(
        "Drive::control instructions per control tick (TIM2 instruction counter), each tick"
    );
    hil_sim::outln!("compared with the same core run in-process on the host:\n");
    hil_sim::outln!(
        "{:<12} {:>7} {:>6} {:>8} {:>6}  {:<12} {:>11}",
        "model",
        "ticks",
        "min",
        "mean",
        "max",
        "host = fw",
        "stack peak"
    );
    let mut ok = true;
    let mut peak = 0;
    let mut instructions = serde_json::Map::new();
    for model in estimator_core::model::ModelKind::ALL {
        if only.is_some_and(|m| m != model) {
            continue;
        }
        if hil_sim::stdout::closed() {
            // Nobody reads the table any more: stop, and fail (the figures are incomplete).
            ok = false;
            break;
        }
        match bench::run_model(opts, model) {
            Ok(r) => {
                let same = match r.first_mismatch {
                    None => "identical".to_string(),
                    Some(t) => {
                        ok = false;
                        format!("DIFF @ {t}")
                    }
                };
                if r.exit_status != 0 {
                    ok = false;
                }
                peak = peak.max(r.stack_peak_bytes);
                instructions.insert(
                    model.as_str().to_string(),
                    serde_json::json!({
                        "mean": (r.counts.mean() * 10.0).round() / 10.0,
                        "max": r.counts.max,
                    }),
                );
                hil_sim::outln!(
                    "{:<12} {:>7} {:>6} {:>8.1} {:>6}  {:<12} {:>7} B",
                    format!("{} ({})", model.as_str(), model as u8),
                    r.ticks,
                    r.counts.min,
                    r.counts.mean(),
                    r.counts.max,
                    same,
                    r.stack_peak_bytes
                );
            }
            Err(e) => {
                ok = false;
                hil_sim::outln!("{:<12} failed: {e}", model.as_str());
            }
        }
    }
    // A footprint that cannot be measured fails the bench but still ends in the JSON line
    // (null sizes), so that a script reads the instruction counts it did get.
    let footprint = match bench::footprint(&opts.elf) {
        Ok(f) => {
            hil_sim::outln!(
                "\nflash {} B ({:.1} KiB), static RAM {} B ({:.1} KiB), peak stack {} B",
                f.flash_bytes,
                f.flash_bytes as f64 / 1024.0,
                f.static_ram_bytes,
                f.static_ram_bytes as f64 / 1024.0,
                peak
            );
            Some(f)
        }
        Err(e) => {
            hil_sim::outln!("footprint: {e}");
            ok = false;
            None
        }
    };
    hil_sim::outln!(
        "goals (issue 12): <= 48 KiB flash, <= 8 KiB static RAM, <= 16 KiB stack, \
         <= 400 mean / 500 max instructions per tick"
    );
    let measured = serde_json::json!({
        "flash_bytes": footprint.as_ref().map(|f| f.flash_bytes),
        "static_ram_bytes": footprint.as_ref().map(|f| f.static_ram_bytes),
        "peak_stack_bytes": peak,
        "instructions": instructions,
    });
    report(&measured, check, ok)
}

/// `--footprint`: flash and static RAM of `elf`, held against `check` when given.
fn run_footprint(elf: &std::path::Path, check: Option<&std::path::Path>) -> ExitCode {
    let f = match bench::footprint(elf) {
        Ok(f) => f,
        Err(e) => {
            hil_sim::errln!("qemu-run: {e}");
            return ExitCode::FAILURE;
        }
    };
    let measured = serde_json::json!({
        "flash_bytes": f.flash_bytes,
        "static_ram_bytes": f.static_ram_bytes,
    });
    report(&measured, check, true)
}

/// Holds `measured` against `check` when given (notes and the refusal printed), then prints it
/// as the last line, one JSON object for scripts; fails if `ok` is false or the check refuses.
fn report(measured: &serde_json::Value, check: Option<&std::path::Path>, mut ok: bool) -> ExitCode {
    if let Some(path) = check {
        match check_against(measured, path) {
            Ok(notes) => notes.iter().for_each(|n| hil_sim::outln!("{n}")),
            Err(e) => {
                hil_sim::outln!("{e}");
                ok = false;
            }
        }
    }
    hil_sim::outln!("{measured}");
    if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}

/// Holds `measured` against the checked-in figures at `path` (same keys): any flash, static RAM,
/// peak stack or per-tick mean or maximum above them is an error that names the figure, so that
/// every change of cost shows in a reviewed change of the file. Figures below them are notes. Only the
/// keys `measured` has are held (`--footprint` measures no stack).
fn check_against(
    measured: &serde_json::Value,
    path: &std::path::Path,
) -> Result<Vec<String>, hil_sim::error::Error> {
    use hil_sim::error::Error;
    let text = hil_sim::input::read_text(path).map_err(|e| Error::io(path, e))?;
    let want: serde_json::Value = serde_json::from_str(&text).map_err(|source| Error::Json {
        path: path.to_path_buf(),
        source,
    })?;
    let mut keys: Vec<String> = ["flash_bytes", "static_ram_bytes", "peak_stack_bytes"]
        .iter()
        .filter(|k| measured.get(**k).is_some())
        .map(|k| format!("/{k}"))
        .collect();
    if let Some(models) = measured["instructions"].as_object() {
        // The mean too: under `-icount` it is as exact as the max (one decimal in the JSON).
        for m in models.keys() {
            keys.push(format!("/instructions/{m}/max"));
            keys.push(format!("/instructions/{m}/mean"));
        }
    }
    let (mut over, mut notes) = (Vec::new(), Vec::new());
    for k in keys {
        let got = measured.pointer(&k).and_then(|v| v.as_f64());
        let limit = want.pointer(&k).and_then(|v| v.as_f64());
        match (got, limit) {
            (Some(g), Some(l)) if g > l => over.push(format!("{k}: {g} > {l}")),
            (Some(g), Some(l)) if g < l => notes.push(format!(
                "{}: {k} is now {g}, below {l}: lower it in the file",
                path.display()
            )),
            (Some(_), Some(_)) => {}
            (_, None) => over.push(format!("{k}: missing from {}", path.display())),
            (None, _) => over.push(format!("{k}: not measured")),
        }
    }
    if over.is_empty() {
        Ok(notes)
    } else {
        Err(Error::OverBudget {
            path: path.to_path_buf(),
            over,
        })
    }
}

fn run_fuzz(opts: &PilOptions, n: u32) -> ExitCode {
    match hil_sim::pil::fuzz::run(opts, n) {
        Ok(r) => {
            hil_sim::outln!(
                "PIL fuzz: {} bad frames sent over USART2, {} counted by the firmware, {} accepted; \
                 {} ticks, drive unmoved: {}; QEMU exit {}",
                n, r.frames_bad, r.frames_ok_extra, r.ticks, r.unmoved, r.exit_status
            );
            if r.frames_bad == n && r.frames_ok_extra == 0 && r.unmoved && r.exit_status == 0 {
                hil_sim::outln!("1 passed, 0 failed");
                ExitCode::SUCCESS
            } else {
                hil_sim::outln!("0 passed, 1 failed");
                ExitCode::FAILURE
            }
        }
        Err(e) => {
            hil_sim::errln!("qemu-run: PIL fuzz: {e}");
            hil_sim::outln!("0 passed, 1 failed");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::check_against;

    /// The checked-in figures hold the mean as well as the maximum: a mean above its figure is
    /// refused by name, one below is a note to lower the file.
    #[test]
    fn the_mean_is_held_like_the_max() {
        let path = std::env::temp_dir().join(format!("bench-target-{}.json", std::process::id()));
        std::fs::write(
            &path,
            r#"{"flash_bytes": 100, "instructions": {"model3": {"mean": 390.8, "max": 635}}}"#,
        )
        .unwrap();
        let at = |mean: f64, max: u64| {
            let measured = serde_json::json!({
                "flash_bytes": 100,
                "instructions": {"model3": {"mean": mean, "max": max}},
            });
            check_against(&measured, &path)
        };
        assert_eq!(at(390.8, 635).unwrap(), Vec::<String>::new());
        let over = at(390.9, 635).unwrap_err().to_string();
        assert!(
            over.contains("/instructions/model3/mean: 390.9 > 390.8"),
            "{over}"
        );
        let over = at(390.8, 636).unwrap_err().to_string();
        assert!(
            over.contains("/instructions/model3/max: 636 > 635"),
            "{over}"
        );
        let notes = at(389.0, 635).unwrap();
        assert!(
            notes[0].contains("/instructions/model3/mean is now 389"),
            "{notes:?}"
        );
        let _ = std::fs::remove_file(&path);
    }
}
