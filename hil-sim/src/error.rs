//! The error of hil-sim's operations (calibrate, evaluate, place, inject faults, report, run the
//! firmware): each variant says what failed, typed, and [`Error::In`] the plant, scenario, move
//! or file it failed in. `Display` is the one-line message the command line prints.

use std::path::PathBuf;

use estimator_core::blob::BlobError;
use estimator_core::fault::Faults;
use estimator_core::rig::Rig;
use estimator_core::ConfigError;

use crate::calfile::CalFileError;
use crate::calibrate::CalibrationError;
use crate::controller::ControlError;
use crate::params::ParamsError;
use crate::pil::PilError;
use crate::run::RunError;
use crate::scenario::ScenarioError;

/// What a hil-sim operation failed on.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file or device the system refused.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file, directory or device.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// A scenario file or preset.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// A plant file or variant.
    #[error(transparent)]
    Params(#[from] ParamsError),
    /// The calibration could not be fitted.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// A calibration directory or file.
    #[error(transparent)]
    CalFile(#[from] CalFileError),
    /// The core refused a configuration or model parameters (the field is named).
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The core refused a calibration image.
    #[error(transparent)]
    Image(#[from] BlobError),
    /// A closed-loop run stopped early.
    #[error("{0}")]
    Run(RunError),
    /// A controller call failed.
    #[error("{0}")]
    Control(ControlError),
    /// A PIL call failed.
    #[error(transparent)]
    Pil(#[from] PilError),
    /// A run's start lies outside the plant's travel.
    #[error(
        "start at {start_mm} mm is outside the plant's travel {min_mm}..={max_mm} mm \
         (carriage.travel_min_m, carriage.travel_max_m of {plant})"
    )]
    StartOutsideTravel {
        /// The requested start, mm.
        start_mm: f64,
        /// The travel, mm.
        min_mm: f64,
        /// The travel, mm.
        max_mm: f64,
        /// The plant's name.
        plant: String,
    },
    /// The drive latched a fault.
    #[error("fault {0}")]
    Fault(Faults),
    /// The carriage did not come to rest within the move's time.
    #[error("never came to rest")]
    NeverAtRest,
    /// A fault latched before the injection it was to detect.
    #[error("fault {faults} before the injection (tick {tick})")]
    FaultBeforeInjection {
        /// The latched faults.
        faults: Faults,
        /// The tick it latched on.
        tick: u32,
    },
    /// A fault injection ended before the drive ticked again.
    #[error("no tick after detection")]
    NoTickAfterDetection,
    /// The QEMU firmware, sent no configuration, runs the paper rig; the plant has another
    /// geometry.
    #[error(
        "PIL: the QEMU firmware is configured for the paper rig ({paper}); {plant} has {has}: \
         send it a configuration (PilOptions::settings) or run it in-process (without --pil)"
    )]
    PilGeometry {
        /// The firmware's geometry.
        paper: Rig,
        /// The plant's name.
        plant: String,
        /// The plant's geometry.
        has: Rig,
    },
    /// A plant of the generalisation table that was never measured (one before it failed; not
    /// reached in practice: that failure is returned first).
    #[error("{0}: not measured")]
    NotMeasured(String),
    /// QEMU ended with a status other than success.
    #[error("PIL: QEMU exited with status {0}")]
    QemuExit(i32),
    /// A result is not a number (NaN or infinite), so there is nothing to report.
    #[error("{scenario}: {field} is not a number: nothing to report")]
    NotANumber {
        /// The scenario.
        scenario: String,
        /// The JSON path of the value.
        field: String,
    },
    /// A font file that plotters cannot use.
    #[error("{0}: not a usable TrueType font")]
    BadFont(String),
    /// A picture that could not be drawn or written: `{file}: figure not drawn: {why}`.
    #[error("{0}: figure not drawn: {1}")]
    Figure(String, String),
    /// No font for plot text.
    #[error("no font found (tried {0}); install fonts-dejavu-core")]
    NoFont(String),
    /// A firmware file that is not a 32-bit ELF.
    #[error("{}: not a 32-bit ELF", .0.display())]
    NotElf32(PathBuf),
    /// A firmware file that ends inside its headers.
    #[error("{}: truncated ELF", .0.display())]
    TruncatedElf(PathBuf),
    /// No firmware to run under QEMU.
    #[error("{}: no firmware ELF; build it with `cargo fw-qemu`", .0.display())]
    NoFirmware(PathBuf),
    /// A command-line value out of its rule: `{flag} {value}: {rule}`.
    #[error("{flag} {value}: {rule}")]
    Argument {
        /// The option, e.g. `--speed`.
        flag: &'static str,
        /// The value given.
        value: String,
        /// What it must be.
        rule: String,
    },
    /// The fault campaign found a class undetected, a false trip, or PIL differing from the host.
    #[error(
        "fault campaign failed: classes {failed:?}, {trips} false trips{}",
        if *pil_differs { ", PIL differs from the host" } else { "" }
    )]
    CampaignFailed {
        /// The classes that did not pass.
        failed: Vec<&'static str>,
        /// Faults raised on the presets with no injection.
        trips: usize,
        /// A class ended differently under QEMU than in-process.
        pil_differs: bool,
    },
    /// A JSON file that does not parse.
    #[error("{}: {source}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// What the parser said.
        source: serde_json::Error,
    },
    /// The firmware costs more than the checked-in figures (`figure: measured > limit`, or a
    /// figure missing on one side).
    #[error(
        "{}: the firmware costs more than the checked-in figures ({}); if that is intended, \
         update the file with the figures of the JSON line below",
        path.display(),
        over.join(", ")
    )]
    OverBudget {
        /// The checked-in figures.
        path: PathBuf,
        /// Each figure above its limit.
        over: Vec<String>,
    },
    /// The operating system refused to watch for a signal.
    #[error("signal handler: {0}")]
    Signal(std::io::Error),
    /// No pseudo-terminal for the virtual drive's link.
    #[error("pseudo-terminal: {0}")]
    Pty(std::io::Error),
    /// The error of an operation on a named thing: `{context}: {error}`.
    #[error("{context}: {error}")]
    In {
        /// What was being worked on (a plant, a scenario, a move, a step).
        context: String,
        /// What went wrong there.
        error: Box<Error>,
    },
}

impl Error {
    /// This error as having happened in `context`.
    pub fn context(self, context: impl Into<String>) -> Error {
        Error::In {
            context: context.into(),
            error: Box::new(self),
        }
    }

    /// A file-system error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Error {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    /// The innermost error, past every [`Error::In`].
    pub fn root(&self) -> &Error {
        match self {
            Error::In { error, .. } => error.root(),
            e => e,
        }
    }
}

impl From<RunError> for Error {
    fn from(e: RunError) -> Error {
        Error::Run(e)
    }
}

impl From<ControlError> for Error {
    fn from(e: ControlError) -> Error {
        Error::Control(e)
    }
}

/// Adds a context to a `Result`'s error.
pub trait Context<T> {
    /// The error, if any, as having happened in `context()`.
    fn context(self, context: impl FnOnce() -> String) -> Result<T, Error>;
}

impl<T, E: Into<Error>> Context<T> for Result<T, E> {
    fn context(self, context: impl FnOnce() -> String) -> Result<T, Error> {
        self.map_err(|e| e.into().context(context()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn context_prefixes_the_message_and_keeps_the_cause() {
        let e: Result<(), Error> = Err(Error::NeverAtRest);
        let e = e.context(|| "move 3".into()).unwrap_err();
        assert_eq!(e.to_string(), "move 3: never came to rest");
        assert!(matches!(e.root(), Error::NeverAtRest));
        let e = e.context("placement model1");
        assert_eq!(
            e.to_string(),
            "placement model1: move 3: never came to rest"
        );
        assert!(matches!(e.root(), Error::NeverAtRest));
    }
}
