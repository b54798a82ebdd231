//! Cargo runner for `thumbv7em-none-eabihf`: runs a firmware ELF under QEMU (netduinoplus2) with
//! semihosting, prints its defmt log decoded with the ELF's own table, and exits with the
//! firmware's semihosting exit status (124 on timeout, 2 on a runner error).
//!
//! ```text
//! qemu-run [--timeout SECS] [--icount SHIFT] [--log-level LEVEL] [--log-file PATH] ELF [ignored...]
//! ```
//! `.cargo/qemu-runner.sh` calls it for `cargo test-target` / `cargo run-qemu`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use hil_sim::pil::qemu::{LogSink, Qemu, QemuError, QemuOptions, LEVELS};

fn usage() -> ExitCode {
    eprintln!(
        "usage: qemu-run [--timeout SECS] [--icount SHIFT] [--log-level trace|debug|info|warn|error] \
         [--log-file PATH] ELF [ignored...]"
    );
    ExitCode::from(2)
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let mut timeout = Duration::from_secs(120);
    let mut icount = Some(4u8);
    let mut level: &'static str = "trace";
    let mut log = LogSink::Stdout;
    let mut elf: Option<PathBuf> = None;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--timeout" => match args.next().and_then(|v| v.parse::<f64>().ok()) {
                Some(s) if s > 0.0 => timeout = Duration::from_secs_f64(s),
                _ => return usage(),
            },
            "--icount" => match args.next().as_deref() {
                Some("off") => icount = None,
                Some(v) => match v.parse() {
                    Ok(s) => icount = Some(s),
                    Err(_) => return usage(),
                },
                None => return usage(),
            },
            "--log-level" => match args.next().and_then(|v| LEVELS.iter().find(|l| **l == v)) {
                Some(l) => level = l,
                None => return usage(),
            },
            "--log-file" => match args.next() {
                Some(p) => log = LogSink::File(p.into()),
                None => return usage(),
            },
            "-h" | "--help" => {
                usage();
                return ExitCode::SUCCESS;
            }
            _ if elf.is_none() => elf = Some(a.into()),
            // Cargo appends the test binary's own arguments (filters, --nocapture): defmt-test
            // runs every test, so they are ignored.
            _ => {}
        }
    }
    let Some(elf) = elf else { return usage() };

    let mut opts = QemuOptions::new(elf);
    opts.timeout = timeout;
    opts.icount_shift = icount;
    opts.log = log;
    opts.min_level = level;
    opts.keep_lines = 0;
    let result = Qemu::spawn(&opts).and_then(|mut q| q.wait());
    match result {
        Ok(code) => {
            if code != 0 {
                eprintln!("qemu-run: firmware exited with status {code}");
            }
            ExitCode::from(code.clamp(0, 255) as u8)
        }
        Err(e @ QemuError::Timeout(_)) => {
            eprintln!("qemu-run: {e}");
            ExitCode::from(124)
        }
        Err(e) => {
            eprintln!("qemu-run: {e}");
            ExitCode::from(2)
        }
    }
}
