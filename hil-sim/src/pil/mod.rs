//! Processor-in-the-loop: the real firmware under QEMU, paced by the simulated plant.
//!
//! [`PilController`] implements [`Controller`]: each `step` sends the plant's raw counters as a
//! [`Request::Sample`] over the link, the firmware's `control` task runs `Drive::control` and
//! answers with the current and telemetry, and only then does the simulator integrate the plant
//! for one tick.
//!
//! The link ([`Transport`]) is either the firmware's USART2 on a Unix socket (byte by byte
//! through QEMU's USART model, as a real serial line) or, by default, the PIL pipe: two FIFOs
//! that the QEMU firmware reads and writes through semihosting, one call per frame. Same
//! frames, same decoder, same tasks; the pipe is about ten times faster. The firmware has no other notion of time in this mode, so
//! a run gives the same numbers on a fast or a slow host; `-icount shift=0` makes QEMU itself
//! deterministic and turns TIM2 into the instruction counter reported with every answer.
//!
//! [`qemu`] starts and supervises QEMU and decodes the firmware's defmt log.

pub mod bench;
pub mod fuzz;
pub mod qemu;
pub mod virtual_drive;

use std::fs::File;
use std::io::{self, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use belt_link::{
    encode, kind, Command, CommandError, LinkError, Message, Receiver, Reply, Request, WireStatus,
    MAX_FRAME,
};
use estimator_core::drive::{Output, Sample};
use estimator_core::endpoint::output_of;
use estimator_core::settings::{self, Settings};

use crate::controller::{ControlError, Controller};
use qemu::{LogSink, Qemu, QemuError, QemuOptions};

/// Why a PIL call failed. Request kinds are the link's (`belt_link::kind`).
#[derive(Debug, thiserror::Error)]
pub enum PilError {
    /// The drive refused the command; nothing changed.
    #[error("command refused: {0}")]
    Refused(CommandError),
    /// The temporary directory's path cannot go on QEMU's command line.
    #[error(
        "the temporary directory {} has a space: the PIL pipe cannot be named on QEMU's \
         command line (set TMPDIR)",
        .0.display()
    )]
    TempDirSpace(PathBuf),
    /// The pipes' paths would not fit the firmware's command-line buffers.
    #[error(
        "the temporary directory {} is too long for the PIL pipe's paths on QEMU's \
         semihosting command line ({len} of at most {max} bytes): set TMPDIR to a shorter path",
        dir.display()
    )]
    TempDirTooLong {
        /// The temporary directory.
        dir: PathBuf,
        /// Length of the longer pipe path, bytes.
        len: usize,
        /// What the firmware takes.
        max: usize,
    },
    /// Setting up the link (pipes, socket) failed.
    #[error("{doing} {}: {source}", path.display())]
    Setup {
        /// What was being done.
        doing: &'static str,
        /// The file, pipe or socket.
        path: PathBuf,
        /// What the system said.
        source: io::Error,
    },
    /// Reading or writing the link failed.
    #[error("PIL link: {0}")]
    Link(io::Error),
    /// QEMU could not be started, or ended badly.
    #[error(transparent)]
    Qemu(#[from] QemuError),
    /// QEMU closed the link while a reply was awaited.
    #[error("QEMU closed the link while waiting for a reply of kind {kind:#04x}")]
    Closed {
        /// The kind of reply awaited (the request's).
        kind: u8,
    },
    /// QEMU exited while a reply was awaited.
    #[error("QEMU exited while waiting for a reply of kind {kind:#04x}")]
    Exited {
        /// The kind of reply awaited (the request's).
        kind: u8,
    },
    /// No reply within the reply time-out.
    #[error("no reply of kind {kind:#04x} within {:.1} s", waited.as_secs_f64())]
    NoReply {
        /// The kind of reply awaited (the request's).
        kind: u8,
        /// How long this side waited.
        waited: Duration,
    },
    /// A reply of another type than the request asks for.
    #[error("unexpected reply to request kind {kind:#04x}: {reply:?}")]
    UnexpectedReply {
        /// The request's kind.
        kind: u8,
        /// What came.
        reply: Box<Reply>,
    },
    /// The drive refused with a code this side does not know.
    #[error("request kind {kind:#04x} refused with unknown code {detail}")]
    UnknownRefusal {
        /// The request's kind.
        kind: u8,
        /// The refusal code.
        detail: u8,
    },
    /// The drive refused a configuration value or the configuration as a whole.
    #[error("configuration refused by the drive: {field}")]
    ConfigRefused {
        /// The field the drive named.
        field: &'static str,
    },
    /// The drive rejected a request at the link level.
    #[error("request kind {kind:#04x} rejected: {reason:?} (detail {detail})")]
    Rejected {
        /// The request's kind.
        kind: u8,
        /// The link's reason.
        reason: LinkError,
        /// Reason-specific detail.
        detail: u8,
    },
    /// Setting one configuration field failed.
    #[error("{field} = {value}: {source}")]
    ConfigSet {
        /// The field's name.
        field: &'static str,
        /// The value sent.
        value: f64,
        /// Why it failed.
        source: Box<PilError>,
    },
    /// This side's core refused a configuration (the field is named).
    #[error("configuration refused: {0}")]
    Config(#[from] estimator_core::ConfigError),
    /// This side's core refused a calibration image, or it could not be built.
    #[error("calibration image: {0}")]
    Image(#[from] estimator_core::blob::BlobError),
    /// The bench's plant, or its footprint reading (the ELF).
    #[error("{0}")]
    Sim(Box<crate::error::Error>),
    /// A bench command that the core and the firmware did not both accept.
    #[error("command {command:?} not accepted by both: core {core:?}, firmware {firmware:?}")]
    NotAccepted {
        /// The command.
        command: Command,
        /// The core's answer.
        core: Result<(), CommandError>,
        /// The firmware's answer.
        firmware: Result<(), CommandError>,
    },
    /// The drive latched a fault during a bench run.
    #[error("drive fault {0}")]
    Fault(estimator_core::fault::Faults),
}

/// How to start a PIL session.
#[derive(Clone, Debug)]
pub struct PilOptions {
    /// The QEMU firmware ELF (`cargo fw-qemu`).
    pub elf: PathBuf,
    /// QEMU icount shift (0: one instruction per ns, exact instruction counts).
    pub icount_shift: u8,
    /// Wall-clock limit of the whole session.
    pub timeout: Duration,
    /// Wall-clock limit for one reply.
    pub reply_timeout: Duration,
    /// Where the firmware's defmt log goes.
    pub log: LogSink,
    /// Lowest defmt level shown.
    pub min_level: &'static str,
    /// How the link travels.
    pub transport: Transport,
    /// The configuration sent to the firmware after boot (it boots unconfigured without
    /// storage); `None`: send none (the drive keeps what it booted with).
    pub settings: Option<Settings>,
    /// The drive's storage file (`None`: the firmware has no storage).
    pub storage: Option<PathBuf>,
}

/// How the PIL link travels between this process and the firmware under QEMU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transport {
    /// Two FIFOs through semihosting: whole frames per call (the fast default).
    Pipe,
    /// USART2 on a Unix socket: one emulated byte at a time, as on a serial line.
    Usart,
}

/// The link's byte stream on this side.
enum LinkIo {
    Usart(UnixStream),
    Pipe {
        to_fw: File,
        from_fw: File,
        /// The directory holding both FIFOs, removed on drop.
        dir: PathBuf,
    },
}

impl LinkIo {
    fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        match self {
            LinkIo::Usart(s) => s.write_all(bytes),
            LinkIo::Pipe { to_fw, .. } => to_fw.write_all(bytes),
        }
    }

    /// Reads what is there, waiting at most `wait`; `WouldBlock` when nothing came.
    fn read(&mut self, buf: &mut [u8], wait: Duration) -> io::Result<usize> {
        match self {
            LinkIo::Usart(s) => {
                s.set_read_timeout(Some(wait))?;
                s.read(buf)
            }
            LinkIo::Pipe { from_fw, .. } => {
                use rustix::event::{poll, PollFd, PollFlags, Timespec};
                let t = Timespec {
                    tv_sec: wait.as_secs() as i64,
                    tv_nsec: wait.subsec_nanos() as i64,
                };
                let mut fds = [PollFd::new(&*from_fw, PollFlags::IN)];
                match poll(&mut fds, Some(&t)) {
                    Ok(0) | Err(rustix::io::Errno::INTR) => {
                        return Err(io::ErrorKind::WouldBlock.into())
                    }
                    Ok(_) => {}
                    Err(e) => return Err(e.into()),
                }
                from_fw.read(buf)
            }
        }
    }
}

impl Drop for LinkIo {
    fn drop(&mut self) {
        if let LinkIo::Pipe { dir, .. } = self {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// Makes a FIFO at `path`.
fn mkfifo(path: &Path) -> io::Result<()> {
    use rustix::fs::{mkfifoat, Mode, CWD};
    Ok(mkfifoat(CWD, path, Mode::RUSR | Mode::WUSR)?)
}

/// Opens a FIFO read-write: never blocks on the other end, whichever opens first.
fn open_fifo(path: &Path) -> io::Result<File> {
    std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
}

impl PilOptions {
    /// Defaults: icount shift 0, 10 minutes overall, 10 s per reply, log to stderr from `info`.
    pub fn new(elf: impl Into<PathBuf>) -> Self {
        PilOptions {
            elf: elf.into(),
            icount_shift: 0,
            timeout: Duration::from_secs(600),
            reply_timeout: Duration::from_secs(10),
            log: LogSink::Stderr,
            min_level: "info",
            transport: Transport::Pipe,
            settings: Some(Settings::PAPER),
            storage: None,
        }
    }

    /// The configuration sent after boot with the geometry `rig` (the drive-train of the plant
    /// in the loop); nothing changes when no configuration is sent.
    pub fn with_rig(mut self, rig: estimator_core::rig::Rig) -> Self {
        if let Some(s) = &mut self.settings {
            s.rig = rig;
        }
        self
    }

    /// The firmware ELF `cargo fw-qemu` builds, under `target_dir` (default `target`).
    pub fn default_elf(target_dir: Option<&str>) -> PathBuf {
        let dir = target_dir
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("CARGO_TARGET_DIR").map(PathBuf::from))
            .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../target")));
        dir.join("thumbv7em-none-eabihf/release/belt-drive")
    }
}

/// Instruction counts of `Drive::control` over a session (QEMU's TIM2 counter).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StepCounts {
    /// Ticks measured.
    pub ticks: u64,
    /// Fewest instructions in one step.
    pub min: u32,
    /// Most instructions in one step.
    pub max: u32,
    /// Sum over all steps.
    pub total: u64,
}

impl StepCounts {
    fn add(&mut self, n: u32) {
        if self.ticks == 0 {
            self.min = n;
            self.max = n;
        }
        self.min = self.min.min(n);
        self.max = self.max.max(n);
        self.total += n as u64;
        self.ticks += 1;
    }
    /// Mean instructions per step.
    pub fn mean(&self) -> f64 {
        if self.ticks == 0 {
            0.0
        } else {
            self.total as f64 / self.ticks as f64
        }
    }
}

/// The firmware under QEMU as a [`Controller`].
pub struct PilController {
    qemu: Qemu,
    link: LinkIo,
    rx: Receiver,
    seq: u8,
    reply_timeout: Duration,
    /// `Drive::control` instruction counts, all ticks so far.
    pub counts: StepCounts,
    /// Frames the firmware sent that this side could not decode.
    pub bad_replies: u32,
}

static LINK_SERIAL: AtomicU32 = AtomicU32::new(0);

/// The longest pipe path the firmware takes: it reads its command line into 768 bytes and each
/// pipe path into 128 (`src/hardware/qemu.rs`).
const MAX_PIPE_PATH: usize = 110;

impl PilController {
    /// Starts QEMU on the firmware and connects to its link.
    pub fn start(opts: &PilOptions) -> Result<PilController, PilError> {
        let name = format!(
            "belt-drive-pil-{}-{}",
            std::process::id(),
            LINK_SERIAL.fetch_add(1, Ordering::Relaxed)
        );
        let mut q = QemuOptions::new(&opts.elf);
        q.icount_shift = Some(opts.icount_shift);
        q.timeout = opts.timeout;
        q.log = opts.log.clone();
        q.min_level = opts.min_level;
        q.storage = opts.storage.clone();
        let link = match opts.transport {
            Transport::Pipe => {
                let dir = pipe_dir(&std::env::temp_dir(), &name)?;
                let _ = std::fs::remove_dir_all(&dir);
                std::fs::create_dir(&dir).map_err(|source| PilError::Setup {
                    doing: "creating the PIL pipe directory",
                    path: dir.clone(),
                    source,
                })?;
                let (input, output) = (dir.join("to-firmware"), dir.join("from-firmware"));
                let fifos = mkfifo(&input)
                    .and_then(|_| mkfifo(&output))
                    .and_then(|_| Ok((open_fifo(&input)?, open_fifo(&output)?)));
                let (to_fw, from_fw) = match fifos {
                    Ok(f) => f,
                    Err(source) => {
                        let _ = std::fs::remove_dir_all(&dir);
                        return Err(PilError::Setup {
                            doing: "making the PIL pipes in",
                            path: dir,
                            source,
                        });
                    }
                };
                q.pipe = Some((input, output));
                let link = LinkIo::Pipe {
                    to_fw,
                    from_fw,
                    dir,
                };
                let qemu = Qemu::spawn(&q)?;
                (qemu, link)
            }
            Transport::Usart => {
                let socket = std::env::temp_dir().join(format!("{name}.sock"));
                let _ = std::fs::remove_file(&socket);
                q.usart2_socket = Some(socket.clone());
                let mut qemu = Qemu::spawn(&q)?;
                // QEMU creates the socket and waits (wait=on) for us before the CPU starts.
                let deadline = Instant::now() + Duration::from_secs(20).min(opts.timeout);
                let link = loop {
                    match UnixStream::connect(&socket) {
                        Ok(s) => break s,
                        Err(source) if Instant::now() >= deadline || !qemu.is_running() => {
                            return Err(PilError::Setup {
                                doing: "connecting to QEMU's USART2 socket",
                                path: socket,
                                source,
                            });
                        }
                        Err(_) => std::thread::sleep(Duration::from_millis(10)),
                    }
                };
                let _ = std::fs::remove_file(&socket);
                (qemu, LinkIo::Usart(link))
            }
        };
        let (qemu, link) = link;
        let mut pil = PilController {
            qemu,
            link,
            rx: Receiver::new(),
            seq: 0,
            reply_timeout: opts.reply_timeout,
            counts: StepCounts::default(),
            bad_replies: 0,
        };
        // QEMU drops bytes that arrive before the firmware enables its USART: wait for the
        // firmware's boot announcement (an unsolicited status, sequence 0) before sending.
        pil.wait_for(
            |r| matches!(r, Reply::Status(_)),
            0,
            kind::STATUS,
            Duration::from_secs(20),
        )?;
        if let Some(s) = &opts.settings {
            pil.configure(s)?;
        }
        Ok(pil)
    }

    /// Sends every configuration field and applies them (the drive must be disabled).
    pub fn configure(&mut self, s: &Settings) -> Result<(), PilError> {
        for f in &settings::FIELDS {
            let value = s.get(f.key()).unwrap_or_default();
            self.expect_ack(&Request::ConfigSet {
                key: f.key(),
                value_bits: value.to_bits(),
            })
            .map_err(|e| PilError::ConfigSet {
                field: f.name(),
                value,
                source: Box::new(e),
            })?;
        }
        // The drive converts no units: the image is built here, from the very same values.
        let image = s.parts_image()?;
        for req in estimator_core::endpoint::config_parts_requests(&image) {
            self.expect_ack(&req)?;
        }
        self.expect_ack(&Request::ConfigApply)
    }

    /// Reads replies until one with sequence `seq` satisfies `want`, or the time is up.
    fn wait_for(
        &mut self,
        want: impl Fn(&Reply) -> bool,
        seq: u8,
        kind: u8,
        limit: Duration,
    ) -> Result<Reply, PilError> {
        self.wait_passing(want, seq, kind, limit, &mut |_| {})
    }

    /// [`PilController::wait_for`]; every other valid frame goes to `other`.
    fn wait_passing(
        &mut self,
        want: impl Fn(&Reply) -> bool,
        seq: u8,
        kind: u8,
        limit: Duration,
        other: &mut dyn FnMut(belt_link::Frame<Reply>),
    ) -> Result<Reply, PilError> {
        let deadline = Instant::now() + limit;
        let mut buf = [0u8; 256];
        loop {
            let n = match self.link.read(&mut buf, Duration::from_millis(50)) {
                Ok(0) => return Err(PilError::Closed { kind }),
                Ok(n) => n,
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) =>
                {
                    if Instant::now() >= deadline {
                        return Err(PilError::NoReply {
                            kind,
                            waited: limit,
                        });
                    }
                    if !self.qemu.is_running() {
                        return Err(PilError::Exited { kind });
                    }
                    continue;
                }
                Err(e) => return Err(PilError::Link(e)),
            };
            let mut found = None;
            for &b in &buf[..n] {
                match self.rx.push::<Reply>(b) {
                    Some(Ok(f)) if f.seq == seq && want(&f.msg) => found = Some(f.msg),
                    Some(Ok(f)) => other(f),
                    None => {}
                    Some(Err(_)) => self.bad_replies += 1,
                }
            }
            if let Some(r) = found {
                return Ok(r);
            }
        }
    }

    fn send(&mut self, seq: u8, req: &Request) -> Result<(), PilError> {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(seq, req, &mut buf);
        self.link.write_all(&buf[..n]).map_err(PilError::Link)
    }

    /// Writes raw bytes to the firmware's link (fuzzing).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), PilError> {
        self.link.write_all(bytes).map_err(PilError::Link)
    }

    /// Sends `req` and waits for its reply (same sequence number and request kind); streamed
    /// telemetry and replies to other frames are skipped.
    pub fn call(&mut self, req: &Request) -> Result<Reply, PilError> {
        // Sequence 0 is never used here: the fuzzer sends its frames with 0, so error replies
        // to them cannot be mistaken for replies to our requests.
        self.seq = self.seq.checked_add(1).unwrap_or(1);
        let seq = self.seq;
        self.send(seq, req)?;
        let k = req.kind();
        self.wait_for(|r| answers(r, k), seq, k, self.reply_timeout)
    }

    /// The firmware's status (tick, faults, link counters, stack high-water mark).
    pub fn status(&mut self) -> Result<WireStatus, PilError> {
        match self.call(&Request::Status)? {
            Reply::Status(s) => Ok(s),
            other => Err(PilError::UnexpectedReply {
                kind: kind::STATUS,
                reply: Box::new(other),
            }),
        }
    }

    /// Sends a calibration blob (begin, chunks, commit).
    pub fn load_calibration(&mut self, blob: &[u8]) -> Result<(), PilError> {
        for req in estimator_core::endpoint::calibration_requests(blob) {
            self.expect_ack(&req)?;
        }
        Ok(())
    }

    fn expect_ack(&mut self, req: &Request) -> Result<(), PilError> {
        let kind = req.kind();
        match self.call(req)? {
            Reply::Ack { .. } => Ok(()),
            Reply::Error {
                reason: LinkError::Refused,
                detail,
                ..
            } => match CommandError::from_code(detail) {
                Some(e) => Err(PilError::Refused(e)),
                None => Err(PilError::UnknownRefusal { kind, detail }),
            },
            Reply::Error {
                reason: LinkError::Config,
                detail,
                ..
            } => Err(PilError::ConfigRefused {
                field: settings::field(detail).map_or("unknown field", |f| f.name()),
            }),
            Reply::Error { reason, detail, .. } => Err(PilError::Rejected {
                kind,
                reason,
                detail,
            }),
            other => Err(PilError::UnexpectedReply {
                kind,
                reply: Box::new(other),
            }),
        }
    }

    /// Ends the firmware (semihosting exit with `code`) and returns QEMU's exit status.
    pub fn shutdown(mut self, code: u8) -> Result<i32, PilError> {
        // The firmware exits right after queueing the ack; it may or may not get out.
        self.send(0, &Request::Shutdown { code })?;
        Ok(self.qemu.wait()?)
    }

    /// Sends a drive command; `Ok` once the firmware acknowledged it.
    pub fn send_command(&mut self, cmd: Command) -> Result<(), PilError> {
        self.expect_ack(&Request::Command(cmd))
    }

    /// Runs one control tick in the firmware on `sample`.
    pub fn step_sample(&mut self, sample: Sample) -> Result<Output, PilError> {
        let req = Request::Sample {
            motor_counter: sample.motor_counter,
            scale_counter: sample.scale_counter,
        };
        let reply = self.call(&req)?;
        let (out, instructions) = output_of(&reply).ok_or(PilError::UnexpectedReply {
            kind: kind::SAMPLE,
            reply: Box::new(reply),
        })?;
        self.counts.add(instructions);
        Ok(out)
    }

    /// [`PilController::step_sample`] for a drive whose link also serves another host (the
    /// virtual drive): every frame from the firmware other than this tick's answer is handed
    /// to `forward` whole, re-encoded exactly as it came (the encoding is canonical).
    pub fn step_forwarding(
        &mut self,
        sample: Sample,
        forward: &mut dyn FnMut(&[u8]),
    ) -> Result<Output, PilError> {
        self.seq = self.seq.checked_add(1).unwrap_or(1);
        let seq = self.seq;
        self.send(
            seq,
            &Request::Sample {
                motor_counter: sample.motor_counter,
                scale_counter: sample.scale_counter,
            },
        )?;
        let reply = self.wait_passing(
            |r| matches!(r, Reply::Answer { .. }),
            seq,
            kind::SAMPLE,
            self.reply_timeout,
            &mut |f| {
                let mut out = [0u8; MAX_FRAME];
                let len = encode(f.seq, &f.msg, &mut out);
                forward(&out[..len]);
            },
        )?;
        let (out, instructions) = output_of(&reply).ok_or(PilError::UnexpectedReply {
            kind: kind::SAMPLE,
            reply: Box::new(reply),
        })?;
        self.counts.add(instructions);
        Ok(out)
    }

    /// True while QEMU runs.
    pub fn is_running(&mut self) -> bool {
        self.qemu.is_running()
    }

    /// Waits for QEMU to end (after a host's `Shutdown`) and returns its exit status.
    pub fn wait(mut self) -> Result<i32, PilError> {
        Ok(self.qemu.wait()?)
    }

    /// The decoded defmt lines kept so far.
    pub fn log_lines(&self) -> Vec<String> {
        self.qemu.log_lines()
    }
}

/// The directory for the PIL pipes, `name` in `tmp`, if its paths fit QEMU's command line.
fn pipe_dir(tmp: &Path, name: &str) -> Result<PathBuf, PilError> {
    let dir = tmp.join(name);
    // The firmware splits its command line at spaces.
    if dir.to_string_lossy().contains(char::is_whitespace) {
        return Err(PilError::TempDirSpace(tmp.to_path_buf()));
    }
    let len = dir.join("from-firmware").as_os_str().len();
    if len > MAX_PIPE_PATH {
        return Err(PilError::TempDirTooLong {
            dir: tmp.to_path_buf(),
            len,
            max: MAX_PIPE_PATH,
        });
    }
    Ok(dir)
}

/// True when `reply` is an answer to a request of kind `k`.
fn answers(reply: &Reply, k: u8) -> bool {
    match reply {
        Reply::Ack { of } | Reply::Error { of, .. } => *of == k,
        Reply::Status(_) => k == kind::STATUS,
        Reply::Answer { .. } => k == kind::SAMPLE,
        Reply::ConfigValue { .. } => k == kind::CONFIG_GET,
        Reply::Saved { .. } => k == kind::SAVE,
        Reply::CalData { .. } => k == kind::CAL_READ,
        Reply::Telemetry(_) | Reply::Records { .. } => false,
    }
}

impl From<PilError> for ControlError {
    fn from(e: PilError) -> Self {
        match e {
            PilError::Refused(r) => ControlError::Refused(r),
            other => ControlError::Pil(other),
        }
    }
}

impl Controller for PilController {
    fn command(&mut self, cmd: Command) -> Result<(), ControlError> {
        Ok(self.send_command(cmd)?)
    }

    fn step(&mut self, sample: Sample) -> Result<Output, ControlError> {
        Ok(self.step_sample(sample)?)
    }
    /// A status request: the firmware's samples do not feed its link watchdog, a host's
    /// frames do.
    fn keepalive(&mut self) -> Result<(), ControlError> {
        self.status()?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pipe_paths_that_do_not_fit_the_command_line_are_named() {
        let ok = pipe_dir(Path::new("/tmp"), "belt-drive-pil-1-0").expect("short path");
        assert_eq!(ok, Path::new("/tmp/belt-drive-pil-1-0"));
        let spaced = pipe_dir(Path::new("/tmp/my dir"), "p").unwrap_err();
        assert!(matches!(&spaced, PilError::TempDirSpace(d) if d == Path::new("/tmp/my dir")));
        assert!(
            spaced.to_string().contains("/tmp/my dir has a space"),
            "{spaced}"
        );
        let deep = format!("/{}", "d".repeat(100));
        let long = pipe_dir(Path::new(&deep), "belt-drive-pil-1-0").unwrap_err();
        match &long {
            PilError::TempDirTooLong { dir, len, max } => {
                assert_eq!(dir, Path::new(&deep));
                assert_eq!((*len, *max), (deep.len() + 33, MAX_PIPE_PATH));
            }
            other => panic!("{other:?}"),
        }
        assert!(long.to_string().contains("set TMPDIR"), "{long}");
    }

    #[test]
    fn a_refusal_stays_a_refusal_for_the_scenario_runner() {
        let e = ControlError::from(PilError::Refused(CommandError::NotEnabled));
        assert!(matches!(e, ControlError::Refused(CommandError::NotEnabled)));
        let e = ControlError::from(PilError::NoReply {
            kind: kind::SAMPLE,
            waited: Duration::from_millis(1500),
        });
        assert!(matches!(&e, ControlError::Pil(PilError::NoReply { .. })));
        assert_eq!(
            e.to_string(),
            format!(
                "link to the firmware failed: no reply of kind {:#04x} within 1.5 s",
                kind::SAMPLE
            )
        );
    }
}
