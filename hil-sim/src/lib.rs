//! Host-side belt-drive simulator.
//!
//! * [`params`]: the plant's physical constants (SI, serde, TOML presets; `paper-rig` embedded).
//! * [`plant`]: the simulated rig of the paper's section 2, stepped once per control tick.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod params;
pub mod plant;
pub mod pil;

pub use params::PlantParams;
pub use plant::{BeltForces, Plant};
