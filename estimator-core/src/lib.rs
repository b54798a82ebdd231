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

pub mod rig;

pub mod encoder;
pub mod pid;
pub mod trajectory;

pub mod model;

pub mod blob;
pub mod drive;
pub mod fault;

pub mod endpoint;

#[cfg(feature = "vectors")]
pub mod vectors;

#[cfg(feature = "std")]
pub mod reference;

pub use fixed;

/// A configuration value that `build` refused, naming the field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConfigError {
    /// The field is NaN or infinite.
    NotFinite(&'static str),
    /// The field is outside the range the fixed-point formats can carry.
    OutOfRange(&'static str),
    /// A table axis is not strictly increasing.
    NotMonotonic(&'static str),
    /// A table has more points than the firmware reserves, or too few to interpolate.
    TableSize(&'static str),
}

impl ConfigError {
    /// The offending field, e.g. `"model1.h_mm"`.
    pub fn field(&self) -> &'static str {
        match *self {
            ConfigError::NotFinite(f)
            | ConfigError::OutOfRange(f)
            | ConfigError::NotMonotonic(f)
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
            ConfigError::TableSize(x) => write!(f, "{x}: table size out of bounds"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for ConfigError {}
