//! Running a firmware ELF under `qemu-system-arm -M netduinoplus2`.
//!
//! - defmt frames arrive on QEMU's stdout (semihosting); a thread decodes them with the ELF's own
//!   table and location info and writes them to the chosen [`LogSink`], filtered by level.
//! - The exit status is the firmware's semihosting exit code.
//! - Every wait has a wall-clock deadline; dropping a [`Qemu`] kills the process, so nothing can
//!   outlive the run or hang CI.

use std::fs::File;
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Where decoded defmt lines go.
#[derive(Clone, Debug)]
pub enum LogSink {
    /// This process's stderr.
    Stderr,
    /// This process's stdout.
    Stdout,
    /// A file (created or truncated).
    File(PathBuf),
    /// Nowhere (still decoded and kept in [`Qemu::log_lines`]).
    Discard,
}

/// defmt levels, lowest first.
pub const LEVELS: [&str; 5] = ["trace", "debug", "info", "warn", "error"];

/// How to run QEMU.
#[derive(Clone, Debug)]
pub struct QemuOptions {
    /// Firmware ELF (with its `.defmt` table and debug info).
    pub elf: PathBuf,
    /// `-icount shift=N,align=off,sleep=off`: repeatable runs; 0 makes TIM2 count instructions.
    pub icount_shift: Option<u8>,
    /// Put USART2 on this Unix socket (QEMU is the server and waits for the connection).
    pub usart2_socket: Option<PathBuf>,
    /// The link over two FIFOs (host to firmware, firmware to host) through semihosting
    /// instead of USART2: passed as `--pipe IN OUT` on the semihosting command line.
    pub pipe: Option<(PathBuf, PathBuf)>,
    /// The drive's persistent storage: a host file standing in for the flash sectors
    /// (`--storage FILE` on the semihosting command line).
    pub storage: Option<PathBuf>,
    /// The drive's calibration staging area: a host file standing in for flash sector 9
    /// (`--staging FILE`). `None`: [`Qemu::spawn`] makes a temporary one and removes it after.
    pub staging: Option<PathBuf>,
    /// Wall-clock limit for the whole run.
    pub timeout: Duration,
    /// Where the decoded log goes.
    pub log: LogSink,
    /// Lowest level shown (frames without a level are always shown).
    pub min_level: &'static str,
    /// Keep at most this many decoded lines in memory (for tests and benchmarks).
    pub keep_lines: usize,
}

impl QemuOptions {
    /// Defaults: no icount, no link, 60 s, log to stderr from `info`.
    pub fn new(elf: impl Into<PathBuf>) -> Self {
        QemuOptions {
            elf: elf.into(),
            icount_shift: None,
            usart2_socket: None,
            pipe: None,
            storage: None,
            staging: None,
            timeout: Duration::from_secs(60),
            log: LogSink::Stderr,
            min_level: "info",
            keep_lines: 10_000,
        }
    }
}

/// Why a QEMU run failed.
#[derive(Debug, thiserror::Error)]
pub enum QemuError {
    /// Starting QEMU failed.
    #[error("qemu: {0}")]
    Io(#[from] io::Error),
    /// The firmware ELF could not be read.
    #[error("firmware ELF {path}: {source}")]
    ElfRead {
        /// The ELF named.
        path: PathBuf,
        /// Why it could not be read.
        source: io::Error,
    },
    /// The ELF's defmt table cannot be parsed (the decoder's reason).
    #[error("firmware ELF {path}: defmt table: {reason}")]
    ElfTable {
        /// The ELF named.
        path: PathBuf,
        /// The decoder's reason.
        reason: String,
    },
    /// The ELF has no defmt table (not a defmt firmware).
    #[error("firmware ELF {0}: no .defmt table (not a belt-drive firmware?)")]
    NoDefmtTable(PathBuf),
    /// The run exceeded its deadline; QEMU was killed.
    #[error("qemu: no exit after {:.1} s, killed", .0.as_secs_f64())]
    Timeout(Duration),
    /// QEMU ended without an exit code (killed by a signal).
    #[error("qemu: killed by a signal")]
    Signal,
}

/// A running QEMU.
pub struct Qemu {
    child: Child,
    started: Instant,
    timeout: Duration,
    log_thread: Option<JoinHandle<()>>,
    lines: Arc<Mutex<Vec<String>>>,
    status: Option<i32>,
    /// The temporary staging file made for this run (removed on drop).
    staging_tmp: Option<PathBuf>,
}

static STAGING_SERIAL: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

/// The QEMU command line for `opts` (exposed for logs and tests).
pub fn command_line(opts: &QemuOptions) -> Vec<String> {
    let mut args: Vec<String> = ["-M", "netduinoplus2", "-nographic", "-monitor", "none"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    args.push("-semihosting-config".into());
    let mut semihosting = String::from("enable=on,target=native");
    // QEMU's option syntax doubles a comma inside a value.
    let arg = |p: &PathBuf| p.display().to_string().replace(',', ",,");
    if opts.pipe.is_some() || opts.storage.is_some() || opts.staging.is_some() {
        semihosting += ",arg=belt-drive";
    }
    if let Some((input, output)) = &opts.pipe {
        semihosting += &format!(",arg=--pipe,arg={},arg={}", arg(input), arg(output));
    }
    if let Some(path) = &opts.storage {
        semihosting += &format!(",arg=--storage,arg={}", arg(path));
    }
    if let Some(path) = &opts.staging {
        semihosting += &format!(",arg=--staging,arg={}", arg(path));
    }
    args.push(semihosting);
    args.push("-kernel".into());
    args.push(opts.elf.display().to_string());
    if let Some(shift) = opts.icount_shift {
        args.push("-icount".into());
        args.push(format!("shift={shift},align=off,sleep=off"));
    }
    // Developer hook, e.g. a per-instruction trace for a tick profile (tools/tick-profile.sh):
    // `BELT_QEMU_ARGS="-singlestep -d exec,nochain -D /tmp/trace.log"`.
    if let Ok(extra) = std::env::var("BELT_QEMU_ARGS") {
        args.extend(extra.split_whitespace().map(str::to_string));
    }
    // The n-th -serial is the n-th USART: USART1 unused, USART2 the link.
    args.push("-serial".into());
    args.push("null".into());
    if let Some(path) = &opts.usart2_socket {
        args.push("-serial".into());
        args.push("chardev:link".into());
        args.push("-chardev".into());
        args.push(format!(
            "socket,id=link,path={},server=on,wait=on",
            path.display()
        ));
    }
    args
}

impl Qemu {
    /// Starts QEMU on `opts.elf` and the log decoder thread.
    pub fn spawn(opts: &QemuOptions) -> Result<Qemu, QemuError> {
        let elf = crate::input::read_file(&opts.elf).map_err(|source| QemuError::ElfRead {
            path: opts.elf.clone(),
            source,
        })?;
        // The decoder's error type is its own (anyhow); its message is kept as the reason.
        let table = defmt_decoder::Table::parse(&elf)
            .map_err(|e| QemuError::ElfTable {
                path: opts.elf.clone(),
                reason: e.to_string(),
            })?
            .ok_or_else(|| QemuError::NoDefmtTable(opts.elf.clone()))?;
        let locations = table.get_locations(&elf).unwrap_or_default();

        // Every run gets a staging area (calibration transfers need one): a fresh file when
        // the caller names none. The firmware splits its command line at spaces.
        let mut opts = opts.clone();
        let mut staging_tmp = None;
        if opts.staging.is_none() {
            let path = std::env::temp_dir().join(format!(
                "belt-drive-staging-{}-{}.bin",
                std::process::id(),
                STAGING_SERIAL.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
            ));
            if !path.to_string_lossy().contains(char::is_whitespace) {
                let _ = std::fs::remove_file(&path);
                opts.staging = Some(path.clone());
                staging_tmp = Some(path);
            }
        }
        let opts = &opts;
        let mut child = Command::new("qemu-system-arm")
            .args(command_line(opts))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?;
        // QEMU's own messages pass through, except its note that it waits for the socket.
        if let Some(err) = child.stderr.take() {
            std::thread::Builder::new()
                .name("qemu-stderr".into())
                .spawn(move || {
                    use std::io::BufRead;
                    for line in io::BufReader::new(err).lines().map_while(Result::ok) {
                        if !line.contains("QEMU waiting for connection") {
                            crate::errln!("{line}");
                        }
                    }
                })?;
        }
        let stdout = child
            .stdout
            .take()
            .ok_or_else(|| io::Error::other("no stdout"))?;

        let sink: Box<dyn Write + Send> = match &opts.log {
            LogSink::Stderr => Box::new(io::stderr()),
            // Through the tools' standard output: a closed pipe or a full disk is noted.
            LogSink::Stdout => Box::new(crate::stdout::Sink),
            LogSink::File(p) => Box::new(File::create(p)?),
            LogSink::Discard => Box::new(io::sink()),
        };
        let lines = Arc::new(Mutex::new(Vec::new()));
        let min = LEVELS
            .iter()
            .position(|l| *l == opts.min_level)
            .unwrap_or(0);
        let keep = opts.keep_lines;
        let lines2 = Arc::clone(&lines);
        let log_thread = std::thread::Builder::new()
            .name("defmt".into())
            .spawn(move || decode_log(stdout, table, locations, sink, min, keep, lines2))?;

        Ok(Qemu {
            child,
            started: Instant::now(),
            timeout: opts.timeout,
            log_thread: Some(log_thread),
            lines,
            status: None,
            staging_tmp,
        })
    }

    /// Time left before the deadline.
    pub fn remaining(&self) -> Duration {
        self.timeout.saturating_sub(self.started.elapsed())
    }

    /// True while QEMU runs.
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// Waits for QEMU to exit (until the deadline) and returns its exit status. The log thread is
    /// joined, so every line has been written when this returns.
    pub fn wait(&mut self) -> Result<i32, QemuError> {
        if let Some(code) = self.status {
            return Ok(code);
        }
        let status: ExitStatus = loop {
            if let Some(s) = self.child.try_wait()? {
                break s;
            }
            if self.started.elapsed() >= self.timeout {
                self.kill();
                return Err(QemuError::Timeout(self.timeout));
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        if let Some(t) = self.log_thread.take() {
            let _ = t.join();
        }
        let code = status.code().ok_or(QemuError::Signal)?;
        self.status = Some(code);
        Ok(code)
    }

    /// [`Qemu::wait`], but gives up early when `stop` says so (checked every 5 ms): then QEMU is
    /// killed and `Ok(None)` returned.
    pub fn wait_unless(&mut self, stop: impl Fn() -> bool) -> Result<Option<i32>, QemuError> {
        while self.status.is_none() && self.is_running() && self.remaining() > Duration::ZERO {
            if stop() {
                self.kill();
                return Ok(None);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        self.wait().map(Some)
    }

    /// Kills QEMU (idempotent).
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(t) = self.log_thread.take() {
            let _ = t.join();
        }
    }

    /// The decoded log lines so far (level filter applied), oldest first.
    pub fn log_lines(&self) -> Vec<String> {
        self.lines.lock().map(|l| l.clone()).unwrap_or_default()
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        if self.status.is_none() {
            self.kill();
        }
        if let Some(path) = self.staging_tmp.take() {
            let _ = std::fs::remove_file(path);
        }
    }
}

fn decode_log(
    mut stdout: impl Read,
    table: defmt_decoder::Table,
    locations: defmt_decoder::Locations,
    mut sink: Box<dyn Write + Send>,
    min_level: usize,
    keep: usize,
    lines: Arc<Mutex<Vec<String>>>,
) {
    let mut decoder = table.new_stream_decoder();
    let mut buf = [0u8; 4096];
    loop {
        let n = match stdout.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        decoder.received(&buf[..n]);
        loop {
            match decoder.decode() {
                Ok(frame) => {
                    let level = frame.level().map(|l| l.as_str());
                    if let Some(l) = level {
                        if LEVELS.iter().position(|x| *x == l).unwrap_or(0) < min_level {
                            continue;
                        }
                    }
                    let loc = locations
                        .get(&frame.index())
                        .map(|l| format!(" ({}:{})", short_path(&l.file), l.line))
                        .unwrap_or_default();
                    let line = format!("{}{loc}", frame.display(false));
                    let _ = writeln!(sink, "{line}");
                    if let Ok(mut v) = lines.lock() {
                        if v.len() < keep {
                            v.push(line);
                        }
                    }
                }
                Err(defmt_decoder::DecodeError::UnexpectedEof) => break,
                Err(defmt_decoder::DecodeError::Malformed) => {
                    let _ = writeln!(sink, "(defmt: malformed frame, log may be incomplete)");
                    if table.encoding().can_recover() {
                        continue;
                    }
                    break;
                }
            }
        }
    }
    let _ = sink.flush();
}

fn short_path(p: &Path) -> String {
    let parts: Vec<_> = p.components().rev().take(2).collect();
    let mut out = PathBuf::new();
    for c in parts.into_iter().rev() {
        out.push(c);
    }
    out.display().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A firmware path that is missing, or a file that is no defmt firmware, is refused before
    /// QEMU starts, naming the file.
    #[test]
    fn a_bad_firmware_file_is_named() {
        let dir = std::env::temp_dir().join(format!("belt-qemu-elf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let missing = dir.join("missing.elf");
        let e = Qemu::spawn(&QemuOptions::new(&missing)).err().unwrap();
        assert!(
            matches!(&e, QemuError::ElfRead { path, .. } if *path == missing),
            "{e}"
        );
        assert!(e.to_string().contains("missing.elf"), "{e}");

        let text = dir.join("not-an-elf.elf");
        std::fs::write(&text, b"not an ELF at all").unwrap();
        let e = Qemu::spawn(&QemuOptions::new(&text)).err().unwrap();
        assert!(
            matches!(&e, QemuError::ElfTable { path, .. } | QemuError::NoDefmtTable(path) if *path == text),
            "{e}"
        );
        assert!(e.to_string().contains("not-an-elf.elf"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
