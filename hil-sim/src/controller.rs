//! What drives the simulated plant each tick: the core in-process, or the firmware under QEMU.
//!
//! Scenario runs are written once against this trait, so the in-process run and the
//! processor-in-the-loop run execute the very same scenario code and can be compared tick by tick.

use estimator_core::drive::{Command, CommandError, Drive, Output, Sample};

use crate::pil::PilError;

/// Why a controller call failed.
#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    /// The drive refused the command; nothing changed.
    #[error("command refused: {0}")]
    Refused(CommandError),
    /// The link to the firmware failed (QEMU exited, timed out, or sent garbage).
    #[error("link to the firmware failed: {0}")]
    Pil(PilError),
    /// The controller cannot do this (e.g. inject late ticks where the plant paces the
    /// firmware).
    #[error("{0}")]
    Unsupported(&'static str),
}

/// A drive controller the simulator can close the loop through.
pub trait Controller {
    /// Sends a command (applied before the next tick).
    fn command(&mut self, cmd: Command) -> Result<(), ControlError>;
    /// Runs one control tick on `sample`.
    fn step(&mut self, sample: Sample) -> Result<Output, ControlError>;
    /// What a host does periodically to show it is alive (feeds the drive's link watchdog;
    /// the samples do not).
    fn keepalive(&mut self) -> Result<(), ControlError>;
    /// Reports `n` control ticks that ran late (fault injection); only where the runner owns
    /// the tick timing.
    fn missed_ticks(&mut self, _n: u32) -> Result<(), ControlError> {
        Err(ControlError::Unsupported(
            "late ticks cannot be injected here: the plant paces the firmware",
        ))
    }
}

/// The core running in this process: the reference for every PIL comparison.
pub struct InProcess(pub Drive);

impl Controller for InProcess {
    fn command(&mut self, cmd: Command) -> Result<(), ControlError> {
        self.0.command(cmd).map_err(ControlError::Refused)
    }
    fn step(&mut self, sample: Sample) -> Result<Output, ControlError> {
        Ok(self.0.step(sample))
    }
    fn keepalive(&mut self) -> Result<(), ControlError> {
        self.0.link_alive();
        Ok(())
    }
    fn missed_ticks(&mut self, n: u32) -> Result<(), ControlError> {
        self.0.missed_ticks(n);
        Ok(())
    }
}
