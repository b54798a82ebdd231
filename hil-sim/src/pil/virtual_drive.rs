//! The virtual drive: the firmware under QEMU closing the loop on the simulated plant, with the
//! drive's link on a pseudo-terminal, so that a host tool connects to it exactly as to a board on
//! a USB-serial adapter (only the port's name differs).
//!
//! This process sits on the wire between the firmware and the terminal: it feeds the firmware a
//! PIL sample per control tick (the plant's counters), applies the answered current to the
//! plant, passes every other frame from the firmware to the terminal and every frame from the
//! terminal to the firmware, whole, between two ticks. Plant time is paced to the wall clock
//! (`speed` 1.0) so the drive's timeouts mean what they mean on a machine.

use crate::error::Error;
use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use belt_link::{kind, Receiver, Reply, Request, MAX_ENCODED};
use estimator_core::{settings, BuildContext};

use super::{PilController, PilError, PilOptions};
use crate::plant::{Plant, PlantParams};
use crate::run::sample;

/// How to run a virtual drive.
#[derive(Clone, Debug)]
pub struct VirtualDriveOptions {
    /// QEMU, the firmware and its storage file (`pil.storage`).
    pub pil: PilOptions,
    /// The simulated machine.
    pub plant: PlantParams,
    /// Where the carriage stands at power-on, mm (the drive does not know: it must home).
    pub start_mm: f64,
    /// Plant noise seed.
    pub seed: u64,
    /// A symbolic link made to the terminal's device (e.g. `/tmp/belt-drive`), for scripts.
    pub link: Option<PathBuf>,
    /// Plant time per wall time: 1.0 = real time; 0 = as fast as the emulator goes.
    pub speed: f64,
}

/// The pseudo-terminal: the master end here, the slave's name for the host tool.
struct Pty {
    master: File,
    /// Held open so that the master never reads end-of-file while no host is connected.
    _slave: OwnedFd,
    name: PathBuf,
}

fn open_pty() -> io::Result<Pty> {
    use rustix::fs::{fcntl_setfl, Mode, OFlags};
    use rustix::pty::{grantpt, openpt, ptsname, unlockpt, OpenptFlags};
    use rustix::termios::{tcgetattr, tcsetattr, OptionalActions};
    let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY)?;
    grantpt(&master)?;
    unlockpt(&master)?;
    let name = ptsname(&master, Vec::new())?;
    let name = PathBuf::from(name.to_string_lossy().into_owned());
    let slave = rustix::fs::open(&name, OFlags::RDWR | OFlags::NOCTTY, Mode::empty())?;
    // Raw bytes both ways: no echo, no line discipline, no CR/LF translation.
    let mut t = tcgetattr(&slave)?;
    t.make_raw();
    tcsetattr(&slave, OptionalActions::Now, &t)?;
    fcntl_setfl(&master, OFlags::NONBLOCK)?;
    Ok(Pty {
        master: File::from(master),
        _slave: slave,
        name,
    })
}

/// Frames from the terminal, cut at their delimiters.
struct HostFrames {
    pending: Vec<u8>,
}

impl HostFrames {
    /// Takes bytes; returns the complete frames (delimiter included). Junk longer than any
    /// frame is passed on as it is (the firmware rejects and counts it, as on a wire).
    fn push(&mut self, bytes: &[u8], out: &mut Vec<Vec<u8>>) {
        for &b in bytes {
            self.pending.push(b);
            if b == 0 || self.pending.len() > MAX_ENCODED + 1 {
                out.push(std::mem::take(&mut self.pending));
            }
        }
    }
}

/// What a finished virtual drive reports.
#[derive(Clone, Copy, Debug)]
pub struct VirtualDriveEnd {
    /// Control ticks run.
    pub ticks: u64,
    /// QEMU's exit status (a host's `Shutdown`), or `None` when stopped by a signal.
    pub exit_code: Option<i32>,
}

/// The drive's control rate, asked over the link (`drive.rate_hz`).
fn control_rate(pil: &mut PilController) -> Result<f64, PilError> {
    let key = settings::field_named("drive.rate_hz").map_or(4, |f| f.key());
    match pil.call(&Request::ConfigGet { key })? {
        // The plant steps by its inverse: the core's own check of the rate, by name.
        Reply::ConfigValue { active_bits, .. } => {
            Ok(BuildContext::check_rate_hz(f64::from_bits(active_bits))?)
        }
        other => Err(PilError::UnexpectedReply {
            kind: belt_link::kind::CONFIG_GET,
            reply: Box::new(other),
        }),
    }
}

/// Runs the virtual drive until SIGINT/SIGTERM or until the firmware ends (a host's
/// `Shutdown`). `ready(terminal)` is called once the link is up.
pub fn run(
    opts: &VirtualDriveOptions,
    ready: &mut dyn FnMut(&Path),
) -> Result<VirtualDriveEnd, Error> {
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(sig, Arc::clone(&stop)).map_err(Error::Signal)?;
    }
    let mut plant = Plant::new(&opts.plant, opts.start_mm, opts.seed)?;
    let mut pil_opts = opts.pil.clone();
    // The drive boots from its storage, or unconfigured: the host configures it.
    pil_opts.settings = None;
    let mut pil = PilController::start(&pil_opts)?;
    let mut rate_hz = control_rate(&mut pil)?;

    let mut pty = open_pty().map_err(Error::Pty)?;
    if let Some(link) = &opts.link {
        let _ = std::fs::remove_file(link);
        std::os::unix::fs::symlink(&pty.name, link).map_err(|e| Error::io(link, e))?;
    }
    ready(&pty.name);

    let mut frames = HostFrames {
        pending: Vec::new(),
    };
    // Acks to a configuration the host applied: the plant must then tick at the new rate.
    let mut watch = Receiver::new();
    let mut rate_changed = false;
    let mut pace = Pace::new(Instant::now());
    let mut plant_s = 0.0;
    let mut ticks = 0u64;
    let mut buf = [0u8; 1024];
    let mut to_host: Vec<u8> = Vec::new();
    let result = 'ticks: loop {
        if stop.load(Ordering::Relaxed) {
            break Ok(());
        }
        // Host -> drive: whole frames between ticks.
        let mut complete = Vec::new();
        loop {
            match pty.master.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => frames.push(&buf[..n], &mut complete),
                // EIO: no host has the terminal open.
                Err(_) => break,
            }
        }
        for f in &complete {
            if let Err(e) = pil.send_raw(f) {
                break 'ticks Err(Some(e));
            }
        }
        // One control tick.
        let out = pil.step_forwarding(sample(&plant), &mut |frame| {
            for &b in frame {
                if let Some(Ok(f)) = watch.push::<Reply>(b) {
                    if matches!(f.msg, Reply::Ack { of } if of == kind::CONFIG_APPLY) {
                        rate_changed = true;
                    }
                }
            }
            to_host.extend_from_slice(frame);
        });
        let out = match out {
            Ok(o) => o,
            Err(e) => {
                if !pil.is_running() {
                    break Err(None);
                }
                break Err(Some(e));
            }
        };
        let dt = 1.0 / rate_hz;
        plant.step(out.current_a.to_num::<f64>(), dt);
        plant_s += dt;
        ticks += 1;
        // Drive -> host: what the terminal takes; a full terminal buffer (no host reading)
        // drops the rest, as a serial line into an unplugged adapter would.
        if !to_host.is_empty() {
            match pty.master.write(&to_host) {
                Ok(n) => {
                    to_host.drain(..n);
                }
                Err(_) => to_host.clear(),
            }
            if to_host.len() > 64 * 1024 {
                to_host.clear();
            }
        }
        if rate_changed {
            rate_changed = false;
            match control_rate(&mut pil) {
                Ok(r) => rate_hz = r,
                Err(e) => break Err(Some(e)),
            }
        }
        // Pace plant time to the wall clock.
        if opts.speed > 0.0 && ticks.is_multiple_of(20) {
            if let Some(d) = pace.wait(plant_s, opts.speed, Instant::now()) {
                std::thread::sleep(d);
            }
        }
    };
    match result {
        Ok(()) => Ok(VirtualDriveEnd {
            ticks,
            exit_code: None,
        }),
        Err(None) => {
            let code = pil.wait()?;
            Ok(VirtualDriveEnd {
                ticks,
                exit_code: Some(code),
            })
        }
        Err(Some(e)) => Err(e.into()),
    }
}

/// How far plant time may fall behind the wall clock (times `speed`) before the pacing lets
/// it go.
const MAX_LAG: Duration = Duration::from_millis(20);

/// Paces plant time to the wall clock, never ahead of it and never sprinting to catch up: a
/// virtual drive that fell behind (its machine busy) and then ran its ticks back to back would
/// pass the drive's time faster than the host's, so that a host keeping the drive's link
/// watchdog fed in wall time could miss it (one cause of a commissioning run's `link_timeout`
/// under extra load, not the only one: README). Behind by more than [`MAX_LAG`], the pace
/// starts again from where the plant is.
struct Pace {
    origin: Instant,
    plant_at_origin_s: f64,
}

impl Pace {
    fn new(now: Instant) -> Pace {
        Pace {
            origin: now,
            plant_at_origin_s: 0.0,
        }
    }

    /// How long to sleep at plant time `plant_s` (`speed` > 0: plant time per wall time).
    fn wait(&mut self, plant_s: f64, speed: f64, now: Instant) -> Option<Duration> {
        // `speed` is at least 0.01 (main.rs), so this stays far inside `Duration`.
        let due = Duration::try_from_secs_f64((plant_s - self.plant_at_origin_s) / speed)
            .unwrap_or(Duration::ZERO);
        let elapsed = now.saturating_duration_since(self.origin);
        if due > elapsed {
            Some(due - elapsed)
        } else {
            if elapsed - due > MAX_LAG {
                (self.origin, self.plant_at_origin_s) = (now, plant_s);
            }
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Plant time keeps to the wall clock, and after a stall it does not run ahead to catch
    /// up: the next 0.1 s of plant time at twice real time still takes 50 ms.
    #[test]
    fn the_pace_sleeps_to_the_clock_and_never_sprints_after_a_stall() {
        let t0 = Instant::now();
        let mut p = Pace::new(t0);
        let ms = Duration::from_millis;
        assert_eq!(p.wait(0.1, 2.0, t0), Some(ms(50)));
        assert_eq!(p.wait(0.1, 2.0, t0 + ms(60)), None); // 10 ms behind: kept
        assert_eq!(p.wait(0.2, 2.0, t0 + ms(60)), Some(ms(40)));
        // A stall of a second: let go, then paced from there.
        assert_eq!(p.wait(0.3, 2.0, t0 + ms(1100)), None);
        assert_eq!(p.wait(0.4, 2.0, t0 + ms(1100)), Some(ms(50)));
    }

    #[test]
    fn host_frames_are_cut_at_delimiters_and_junk_is_bounded() {
        let mut h = HostFrames {
            pending: Vec::new(),
        };
        let mut out = Vec::new();
        h.push(&[1, 2, 0, 3], &mut out);
        assert_eq!(out, vec![vec![1, 2, 0]]);
        h.push(&[4, 0], &mut out);
        assert_eq!(out[1], vec![3, 4, 0]);
        let junk = vec![7u8; 3 * MAX_ENCODED];
        let mut out = Vec::new();
        h.push(&junk, &mut out);
        assert!(out.iter().all(|f| f.len() <= MAX_ENCODED + 2));
    }
}
