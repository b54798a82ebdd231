//! Host-side belt-drive simulator.
//!
//! * [`params`]: the plant's physical constants (SI, serde, TOML presets; `paper-rig` embedded).
//! * [`plant`]: the simulated rig of the paper's section 2, stepped once per control tick.
#![forbid(unsafe_code)]
// Output only through `stdout` (`out!`, `outln!`, `errln!`): the std macros panic on a closed pipe.
#![deny(clippy::print_stdout, clippy::print_stderr)]
#![warn(missing_docs)]

pub mod baseline;
pub mod belt_observer;
pub mod calfile;
pub mod calibrate;
pub mod controller;
pub mod coverage;
pub mod drive_setup;
pub mod error;
pub mod eval;
pub mod faults;
pub mod fit;
pub mod generalise;
pub mod input;
pub mod params;
pub mod pil;
pub mod placement;
pub mod plant;
pub mod plot;
pub mod progress;
pub mod report;
pub mod run;
pub mod scenario;
pub mod stats;
pub mod stdout;
pub mod tables;
pub mod workloads;

pub use params::{ParamsError, PlantParams};
pub use plant::{BeltForces, Plant};
