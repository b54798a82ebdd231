//! A fake drive on a pseudo-terminal: the binary opens the pty's slave as its serial port, a
//! thread answers on the master with belt-link frames (or garbage, or silence).

#![allow(dead_code)]

use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::OwnedFd;
use std::process::{Command, Output, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use belt_link::{
    encode, kind, status_flags, LinkError, Message, MotorCounts, Receiver, RecordSample, Reply,
    Request, ScaleCounts, WireStatus, MAX_FRAME, RECORD_BATCH,
};
use estimator_core::settings::Settings;
use rustix::event::{poll, PollFd, PollFlags, Timespec};
use rustix::fs::{Mode, OFlags};
use rustix::pty::{grantpt, openpt, ptsname, unlockpt, OpenptFlags};
use rustix::termios::{tcgetattr, tcsetattr, OptionalActions};

/// A pseudo-terminal pair: the master for the fake drive, the slave's path for the binary.
pub struct Pty {
    pub master: File,
    pub path: String,
    /// Held open so that the master keeps working after the binary closes its end, and raw
    /// from the start.
    _slave: OwnedFd,
}

pub fn pty() -> Pty {
    let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).expect("openpt");
    grantpt(&master).expect("grantpt");
    unlockpt(&master).expect("unlockpt");
    let path = ptsname(&master, Vec::new())
        .expect("ptsname")
        .into_string()
        .expect("utf-8 pty path");
    let slave = rustix::fs::open(
        path.as_str(),
        OFlags::RDWR | OFlags::NOCTTY | OFlags::CLOEXEC,
        Mode::empty(),
    )
    .expect("open pty slave");
    let mut t = tcgetattr(&slave).expect("tcgetattr");
    t.make_raw();
    tcsetattr(&slave, OptionalActions::Now, &t).expect("tcsetattr");
    Pty {
        master: File::from(master),
        path,
        _slave: slave,
    }
}

pub fn frame(seq: u8, reply: &Reply) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(seq, reply, &mut buf);
    buf[..n].to_vec()
}

/// How the fake misbehaves.
#[derive(Clone, Copy, Debug, Default)]
pub struct Faults {
    /// Answer every request with random bytes.
    pub garbage: bool,
    /// Never answer.
    pub silent: bool,
    /// Answer the first request with a CRC-error reply (as the drive answers a damaged frame).
    pub first_crc_error: bool,
    /// Skip this records frame (a loss on the way).
    pub drop_records_seq: Option<u32>,
    /// Refuse to record.
    pub refuse_record: bool,
    /// Acknowledge a recording and stream nothing.
    pub mute_records: bool,
}

/// A small drive: enough state for status, config, moves and recording.
pub struct FakeDrive {
    pub faults: Faults,
    pub requests: Vec<Request>,
    /// When each request arrived.
    pub arrivals: Vec<std::time::Instant>,
    pub tick: u32,
    pub enabled: bool,
    pub homed: bool,
    pub motor_um: i32,
    pub target_um: i32,
    /// Status polls a move stays "moving".
    pub moving_polls: u32,
    /// The carriage arrives this far off its target, scale counts.
    pub arrival_offset_counts: i32,
    /// The compensator selected.
    pub model: belt_link::ModelKind,
    /// More arrival offset with each compensator (by wire number), scale counts.
    pub model_offset_counts: [i32; 7],
    /// Holds a calibration (status flag; otherwise selecting a model is refused).
    pub calibrated: bool,
    /// The scale reads this whatever the carriage does (not fitted).
    pub scale_stuck_counts: Option<i32>,
    pub recording_every: u16,
    pub records_seq: u32,
    /// What `ConfigGet` answers (active and staged alike).
    pub settings: Settings,
    rng: u64,
}

impl FakeDrive {
    pub fn new(faults: Faults) -> FakeDrive {
        FakeDrive {
            faults,
            requests: Vec::new(),
            arrivals: Vec::new(),
            tick: 1000,
            enabled: true,
            homed: true,
            motor_um: 0,
            target_um: 0,
            moving_polls: 0,
            arrival_offset_counts: 7,
            model: belt_link::ModelKind::Table,
            model_offset_counts: [0; 7],
            calibrated: true,
            scale_stuck_counts: None,
            recording_every: 0,
            records_seq: 0,
            settings: Settings::PAPER,
            rng: 0x9e37_79b9_7f4a_7c15,
        }
    }

    fn random(&mut self) -> u8 {
        // xorshift64: the same garbage every run.
        self.rng ^= self.rng << 13;
        self.rng ^= self.rng >> 7;
        self.rng ^= self.rng << 17;
        self.rng as u8
    }

    fn status(&self) -> WireStatus {
        let rig = Settings::PAPER.rig;
        let mut flags = status_flags::CONFIGURED;
        if self.enabled {
            flags |= status_flags::ENABLED | status_flags::AMPLIFIER_ENABLED;
        }
        if self.homed {
            flags |= status_flags::HOMED;
        }
        if self.calibrated {
            flags |= status_flags::CALIBRATED;
        }
        if self.moving_polls > 0 {
            flags |= status_flags::MOVING;
        }
        let at = if self.moving_polls > 0 {
            self.motor_um
        } else {
            self.target_um
        };
        WireStatus {
            tick: self.tick,
            motor_counts: MotorCounts((at as f64 * rig.counts_per_mm() / 1000.0).round() as i32),
            flags,
            model: self.model,
            scale_counts: ScaleCounts(self.scale_stuck_counts.unwrap_or(
                at * 2 + self.arrival_offset_counts + self.model_offset_counts[self.model as usize],
            )),
            carriage_target_um: self.target_um,
            carriage_estimate_um: at,
            record_crc: 0x1234_abcd,
            ..WireStatus::default()
        }
    }

    /// The bytes answering one request.
    pub fn answer(&mut self, seq: u8, req: Request) -> Vec<u8> {
        self.requests.push(req);
        self.arrivals.push(std::time::Instant::now());
        if self.faults.silent {
            return Vec::new();
        }
        if self.faults.garbage {
            let n = 40 + (self.random() as usize % 80);
            return (0..n).map(|_| self.random()).collect();
        }
        if self.faults.first_crc_error && self.requests.len() == 1 {
            return frame(
                0,
                &Reply::Error {
                    of: kind::UNKNOWN,
                    reason: LinkError::Crc,
                    detail: 0,
                },
            );
        }
        let k = req.kind();
        let ack = Reply::Ack { of: k };
        let reply = match req {
            Request::Status => {
                let s = self.status();
                self.moving_polls = self.moving_polls.saturating_sub(1);
                Reply::Status(s)
            }
            Request::ConfigGet { key } => match self.settings.get(key) {
                Some(v) => Reply::ConfigValue {
                    key,
                    active_bits: v.to_bits(),
                    staged_bits: v.to_bits(),
                },
                None => Reply::Error {
                    of: k,
                    reason: LinkError::Config,
                    detail: key,
                },
            },
            Request::Command(belt_link::Command::MoveTo { target_um, .. })
            | Request::Command(belt_link::Command::MoveMotorTo { target_um, .. }) => {
                self.motor_um = (self.motor_um + target_um) / 2;
                self.target_um = target_um;
                self.moving_polls = 2;
                ack
            }
            Request::Command(belt_link::Command::SelectModel(m)) => {
                if self.calibrated || m == belt_link::ModelKind::None {
                    self.model = m;
                    ack
                } else {
                    Reply::Error {
                        of: k,
                        reason: LinkError::Refused,
                        detail: belt_link::CommandError::NotCalibrated.code(),
                    }
                }
            }
            Request::Record { every_n_ticks } if self.faults.refuse_record => Reply::Error {
                of: k,
                reason: LinkError::Refused,
                detail: every_n_ticks as u8,
            },
            Request::Record { every_n_ticks } => {
                self.recording_every = every_n_ticks;
                self.records_seq = 0;
                ack
            }
            _ => ack,
        };
        frame(seq, &reply)
    }

    /// What the drive sends on its own every few milliseconds: a records frame while recording.
    pub fn stream(&mut self) -> Vec<u8> {
        if self.recording_every == 0 || self.faults.mute_records {
            return Vec::new();
        }
        let every = self.recording_every;
        let seq = self.records_seq;
        let first_tick = self.tick;
        let mut samples = [RecordSample::default(); RECORD_BATCH];
        for (i, s) in samples.iter_mut().enumerate() {
            *s = RecordSample {
                motor_counts: MotorCounts((first_tick + i as u32) as i32),
                scale_counts: ScaleCounts(2 * (first_tick + i as u32) as i32),
                setpoint_counts: MotorCounts(7),
                current_ma: -120,
            };
        }
        self.records_seq += 1;
        self.tick += every as u32 * RECORD_BATCH as u32;
        if self.faults.drop_records_seq == Some(seq) {
            return Vec::new();
        }
        frame(
            0,
            &Reply::Records {
                seq,
                first_tick,
                every,
                count: RECORD_BATCH as u8,
                samples,
            },
        )
    }
}

/// The fake drive answering on `master` until dropped.
pub struct Serving {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    pub drive: Arc<Mutex<FakeDrive>>,
}

impl Drop for Serving {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

pub fn serve(mut master: File, drive: FakeDrive) -> Serving {
    let stop = Arc::new(AtomicBool::new(false));
    let drive = Arc::new(Mutex::new(drive));
    let (s, d) = (stop.clone(), drive.clone());
    let thread = std::thread::spawn(move || {
        let mut rx = Receiver::new();
        let mut buf = [0u8; 1024];
        let mut last_stream = Instant::now();
        while !s.load(Ordering::Relaxed) {
            let ready = {
                let mut fds = [PollFd::new(&master, PollFlags::IN)];
                let t = Timespec {
                    tv_sec: 0,
                    tv_nsec: 5_000_000,
                };
                poll(&mut fds, Some(&t)).unwrap_or(0) > 0
                    && fds[0].revents().contains(PollFlags::IN)
            };
            let mut out = Vec::new();
            if ready {
                // EIO when no slave is open; the test holds one, so this is a real error.
                let n = match master.read(&mut buf) {
                    Ok(n) => n,
                    Err(_) => break,
                };
                let mut d = d.lock().unwrap();
                for &b in &buf[..n] {
                    if let Some(Ok(f)) = rx.push::<Request>(b) {
                        out.extend(d.answer(f.seq, f.msg));
                    }
                }
            }
            if last_stream.elapsed() >= Duration::from_millis(4) {
                last_stream = Instant::now();
                out.extend(d.lock().unwrap().stream());
            }
            if !out.is_empty() && master.write_all(&out).is_err() {
                break;
            }
        }
    });
    Serving {
        stop,
        thread: Some(thread),
        drive,
    }
}

/// Runs beltctl with `args`; kills it after `limit` (a hang is a failure, not a stuck test).
pub fn beltctl(args: &[&str], limit: Duration) -> (Output, Duration) {
    beltctl_into(args, limit, Stdio::piped(), Stdio::piped())
}

/// [`beltctl`] with its standard output and error where the caller says (the `Output` holds
/// only what went into pipes of its own).
pub fn beltctl_into(
    args: &[&str],
    limit: Duration,
    stdout: Stdio,
    stderr: Stdio,
) -> (Output, Duration) {
    let start = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_beltctl"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(stdout)
        .stderr(stderr)
        .spawn()
        .expect("run beltctl");
    loop {
        if child.try_wait().expect("wait").is_some() {
            break;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let out = child.wait_with_output().expect("output");
            panic!(
                "beltctl {args:?} still running after {limit:?}; stderr: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let took = start.elapsed();
    (child.wait_with_output().expect("output"), took)
}

pub fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}
