//! Deterministic per-tick core of the belt-drive controller.
//!
//! Everything that runs every control tick lives here, identical on the host (`hil-sim`) and on
//! the STM32F405 firmware: integer and fixed-point arithmetic only, no allocation, bounded time.
//! Configuration is given in SI units (`f64`) and turned once, off the hot path, into fixed-point
//! coefficients (`build`), following quartiq idsp's configuration / coefficients / state split.
//!
//! Units live in names (`_counts`, `_um`, `_mm`, `_mm_s`) and fixed-point formats in types
//! (`I16F16` micrometres, `i32` encoder counts).
#![cfg_attr(not(feature = "std"), no_std)]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod field;
pub mod rig;
pub mod units;

pub mod encoder;
pub mod pid;
pub mod trajectory;

pub mod model;

pub mod blob;
pub mod drive;
pub mod fault;
pub mod image;
pub mod settings;

pub mod endpoint;

pub mod staging;
pub mod storage;

#[cfg(feature = "vectors")]
pub mod vectors;

#[cfg(feature = "std")]
pub mod reference;

pub use field::ConfigField;
pub use fixed;

/// The control rates the drive takes, whole hertz (`drive.rate_hz`): the configuration's
/// check, its image's and the calibration image's belt observer's.
pub const RATE_HZ: core::ops::RangeInclusive<u32> = 100..=100_000;

/// What every per-tick configuration is built for: the drive train's geometry and the control
/// rate, given once (as quartiq idsp passes the sample period to its builders) rather than a
/// `rate_hz` in each sub-configuration. Only [`BuildContext::new`] makes one, so a builder can
/// rely on a valid rig and rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildContext {
    rig: rig::Rig,
    rate_hz: f64,
}

impl BuildContext {
    /// The paper's rig at 2 kHz.
    pub const PAPER: BuildContext = BuildContext {
        rig: rig::Rig::PAPER,
        rate_hz: 2000.0,
    };

    /// Checks the geometry and the rate ([`BuildContext::check_rate_hz`]).
    pub fn new(rig: rig::Rig, rate_hz: f64) -> Result<BuildContext, ConfigError> {
        rig.validate()?;
        Ok(BuildContext {
            rig,
            rate_hz: Self::check_rate_hz(rate_hz)?,
        })
    }

    /// A control rate the drive takes ([`RATE_HZ`]), named `drive.rate_hz`.
    pub fn check_rate_hz(rate_hz: f64) -> Result<f64, ConfigError> {
        if !rate_hz.is_finite() {
            return Err(ConfigError::NotFinite(ConfigField::DriveRateHz));
        }
        if !(*RATE_HZ.start() as f64..=*RATE_HZ.end() as f64).contains(&rate_hz) {
            return Err(ConfigError::OutOfRange(ConfigField::DriveRateHz));
        }
        Ok(rate_hz)
    }

    /// The drive train's geometry.
    pub fn rig(&self) -> &rig::Rig {
        &self.rig
    }

    /// Control ticks per second.
    pub fn rate_hz(&self) -> f64 {
        self.rate_hz
    }
}

/// A configuration value that `build` refused, naming the field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConfigError {
    /// The field is NaN or infinite.
    NotFinite(ConfigField),
    /// The field is outside the range the fixed-point formats can carry.
    OutOfRange(ConfigField),
    /// A table axis is not strictly increasing.
    NotMonotonic(ConfigField),
    /// A table axis that must be evenly spaced is not.
    NotUniform(ConfigField),
    /// A table has more points than the firmware reserves, or too few to interpolate.
    TableSize(ConfigField),
}

impl ConfigError {
    /// The offending field, e.g. `model1.h_mm`.
    pub fn field(&self) -> ConfigField {
        match *self {
            ConfigError::NotFinite(f)
            | ConfigError::OutOfRange(f)
            | ConfigError::NotMonotonic(f)
            | ConfigError::NotUniform(f)
            | ConfigError::TableSize(f) => f,
        }
    }
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            ConfigError::NotFinite(x) => write!(f, "{x}: not a finite number"),
            ConfigError::OutOfRange(x) => write!(f, "{x}: out of range"),
            ConfigError::NotMonotonic(x) => write!(f, "{x}: axis is not strictly increasing"),
            ConfigError::NotUniform(x) => write!(f, "{x}: axis is not evenly spaced"),
            ConfigError::TableSize(x) => write!(f, "{x}: table size out of bounds"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for ConfigError {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_build_context_refuses_a_bad_rate_or_rig_by_name() {
        let paper = rig::Rig::PAPER;
        assert_eq!(BuildContext::new(paper, 2000.0), Ok(BuildContext::PAPER));
        for rate in [f64::NAN, f64::INFINITY, 0.0, 50.0, 200_000.0] {
            let e = BuildContext::new(paper, rate).unwrap_err();
            assert_eq!(e.field(), ConfigField::DriveRateHz, "{rate}");
        }
        let mut broken = paper;
        broken.gear_ratio = f64::NAN;
        assert_eq!(
            BuildContext::new(broken, 2000.0).unwrap_err().field(),
            ConfigField::RigGearRatio
        );
        let mut broken = paper;
        broken.pulley_teeth = 0;
        assert_eq!(
            BuildContext::new(broken, 2000.0).unwrap_err().field(),
            ConfigField::RigPulleyTeeth
        );
    }
}
