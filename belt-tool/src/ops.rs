//! What the commands do on the drive: moves that wait for arrival, homing, waiting on status.

use std::time::{Duration, Instant};

use belt_link::{status_flags, Command, WireStatus};
use hil_sim::input::show;
use hil_sim::scenario::Scenario;
use hil_sim::stats::ErrorStats;

use crate::error::ToolError;
use crate::link::Link;
use crate::status::{fault_names, scale_um};

/// How often a waiting command polls the status (it also feeds the drive's link watchdog).
pub const POLL: Duration = Duration::from_millis(50);

/// The longest the host stays silent while the drive may be enabled: a fifth of the drive's
/// default link timeout (0.5 s), so that a host stalled by its scheduler, or a virtual drive
/// run faster than real time, still keeps the watchdog fed.
pub const KEEPALIVE: Duration = Duration::from_millis(100);

/// Polls the status every [`POLL`] until `done` holds, a fault latches, or `timeout` passes
/// (then the drive is told to stop). The first poll comes after one period, so that a command
/// just sent has reached the drive's state.
pub fn wait_for(
    link: &mut Link,
    what: &str,
    timeout: Duration,
    done: impl Fn(&WireStatus) -> bool,
    mut tick: impl FnMut(&mut Link) -> Result<(), ToolError>,
) -> Result<WireStatus, ToolError> {
    let start = Instant::now();
    let boots = link.stats().boots;
    loop {
        // Between polls the link listens (records keep arriving).
        link.pump(POLL)?;
        tick(link)?;
        let s = link.status()?;
        if link.stats().boots != boots {
            return Err(ToolError::Drive(format!(
                "{what}: the drive restarted (it sent its boot status)"
            )));
        }
        no_faults(&s, what)?;
        if done(&s) {
            return Ok(s);
        }
        if start.elapsed() > timeout {
            let _ = link.command(Command::Stop);
            return Err(ToolError::Drive(format!(
                "{what}: not done after {:.1} s; told the drive to stop",
                timeout.as_secs_f64()
            )));
        }
    }
}

/// RMS and largest magnitude of arrival errors, um (0 for none).
pub fn rms_and_max_um(errors_um: &[f64]) -> (f64, f64) {
    ErrorStats::of(errors_um.iter().copied()).map_or((0.0, 0.0), |s| {
        (s.rms_um, s.max_um.abs().max(s.min_um.abs()))
    })
}

/// Fails, naming them, if the drive has latched faults.
pub fn no_faults(s: &WireStatus, what: &str) -> Result<(), ToolError> {
    if s.faults.is_clear() {
        return Ok(());
    }
    Err(ToolError::Drive(format!(
        "{what}: the drive latched faults: {} (`beltctl clear-faults`, then `beltctl enable`)",
        fault_names(s.faults).join(", ")
    )))
}

/// A user's scenario (file `path`) must start and end every move inside the drive's travel
/// `d0..=d1` mm; refused by file, move and field.
pub fn within_travel(path: &str, s: &Scenario, (d0, d1): (f64, f64)) -> Result<(), ToolError> {
    let refuse = |reason: String| {
        Err(ToolError::File {
            path: path.to_string(),
            reason,
        })
    };
    let inside = |x: f64| (d0..=d1).contains(&x);
    if !inside(s.start_mm) {
        return refuse(format!(
            "start_mm = {} is outside the drive's travel {d0}..{d1} mm",
            s.start_mm
        ));
    }
    match s.moves.iter().position(|m| !inside(m.to_mm)) {
        Some(i) => refuse(format!(
            "move {}: to_mm = {} is outside the drive's travel {d0}..{d1} mm",
            i + 1,
            s.moves[i].to_mm
        )),
        None => Ok(()),
    }
}

/// Rests for `d`, polling the status every [`KEEPALIVE`] (the drive's link watchdog).
pub fn dwell(link: &mut Link, d: Duration) -> Result<(), ToolError> {
    let end = crate::link::later(d);
    loop {
        let left = end.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Ok(());
        }
        link.pump(left.min(KEEPALIVE))?;
        link.status()?;
    }
}

/// Limits of one move, SI.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MoveLimits {
    /// Cruise speed, mm/s.
    pub velocity_mm_s: f64,
    /// Acceleration, mm/s².
    pub accel_mm_s2: f64,
}

impl MoveLimits {
    /// The drive's integer units, checked: whole um/s and um/s², at least 1.
    pub fn drive_units(&self) -> Result<(u32, u32), ToolError> {
        let unit = |v: f64, name: &str, unit: &str| {
            let x = (v * 1000.0).round();
            if !(x.is_finite() && x >= 1.0 && x <= u32::MAX as f64) {
                return Err(ToolError::Usage(format!(
                    "{name} {}: must be from 0.001 to {} {unit}",
                    show(v),
                    u32::MAX as f64 / 1000.0
                )));
            }
            Ok(x as u32)
        };
        Ok((
            unit(self.velocity_mm_s, "--velocity", "mm/s")?,
            unit(self.accel_mm_s2, "--accel", "mm/s^2")?,
        ))
    }

    /// Upper bound of a move's time over `distance_mm`, with room for settling and polling.
    pub fn budget(&self, distance_mm: f64) -> Duration {
        let t =
            distance_mm.abs() / self.velocity_mm_s + 2.0 * self.velocity_mm_s / self.accel_mm_s2;
        Duration::from_secs_f64((2.0 * t + 5.0).min(3600.0))
    }
}

/// A target in the drive's micrometres.
pub fn target_um(mm: f64) -> Result<i32, ToolError> {
    let um = (mm * 1000.0).round();
    if !(um.is_finite() && um.abs() <= i32::MAX as f64) {
        return Err(ToolError::Usage(format!(
            "target {} mm is out of range",
            show(mm)
        )));
    }
    Ok(um as i32)
}

/// The move command: the carriage placed with the active model (`MoveTo`), or the raw motor
/// (`MoveMotorTo`, `motor`).
pub fn move_command(
    target_um: i32,
    limits: &MoveLimits,
    motor: bool,
) -> Result<Command, ToolError> {
    let (velocity_um_s, accel_um_s2) = limits.drive_units()?;
    Ok(Command::move_to(
        !motor,
        target_um,
        velocity_um_s,
        accel_um_s2,
    ))
}

/// Sends a move and waits until the drive is at rest again; returns that status.
pub fn move_and_wait(
    link: &mut Link,
    cmd: Command,
    distance_mm: f64,
    limits: &MoveLimits,
    tick: impl FnMut(&mut Link) -> Result<(), ToolError>,
) -> Result<WireStatus, ToolError> {
    let what = crate::link::describe(&belt_link::Request::Command(cmd));
    link.command(cmd)?;
    wait_for(
        link,
        &what,
        limits.budget(distance_mm),
        |s| s.flags & status_flags::MOVING == 0,
        tick,
    )
}

/// One arrival: where the carriage was sent and where it is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Arrival {
    /// Target, mm.
    pub target_mm: f64,
    /// The drive's estimate of the carriage position, mm.
    pub estimate_mm: f64,
    /// The motor's position, mm of nominal travel, where the geometry is known.
    pub motor_mm: Option<f64>,
    /// The linear scale, mm.
    pub scale_mm: f64,
}

impl Arrival {
    /// From the status after settling.
    pub fn of(target_mm: f64, s: &WireStatus, counts_per_mm: Option<f64>) -> Arrival {
        Arrival {
            target_mm,
            estimate_mm: s.carriage_estimate_um as f64 / 1000.0,
            motor_mm: counts_per_mm.map(|c| s.motor_counts.to_mm(c)),
            scale_mm: scale_um(s) / 1000.0,
        }
    }

    /// Scale minus target, um.
    pub fn error_um(&self) -> f64 {
        (self.scale_mm - self.target_mm) * 1000.0
    }
}

/// Runs the drive's homing routine and waits for it and its back-off to end; Ok when the drive
/// is homed.
pub fn home(link: &mut Link, timeout: Duration) -> Result<WireStatus, ToolError> {
    link.command(Command::Homing)?;
    let s = wait_for(
        link,
        "homing",
        timeout,
        // The routine ends at the stop; the back-off from it is an ordinary move.
        |s| s.flags & (status_flags::HOMING | status_flags::MOVING) == 0,
        |_| Ok(()),
    )?;
    if s.flags & status_flags::HOMED == 0 {
        return Err(ToolError::Drive(format!(
            "homing ended without homing the drive (faults: {})",
            s.faults
        )));
    }
    Ok(s)
}

/// Fails unless the drive is enabled, homed and free of faults: what moves need.
pub fn require_ready(s: &WireStatus, what: &str) -> Result<(), ToolError> {
    let mut missing = Vec::new();
    if !s.faults.is_clear() {
        missing.push(format!(
            "its faults cleared ({}: `beltctl clear-faults`)",
            fault_names(s.faults).join(", ")
        ));
    }
    if s.flags & status_flags::ENABLED == 0 {
        missing.push("enabled (`beltctl enable`)".into());
    }
    if s.flags & status_flags::HOMED == 0 {
        missing.push("homed (`beltctl home`)".into());
    }
    if missing.is_empty() {
        Ok(())
    } else {
        Err(ToolError::Drive(format!(
            "{what} needs the drive {}",
            missing.join(" and ")
        )))
    }
}
