//! `hil-sim`'s integration tests as one binary: its tests share the machine's two cores (as
//! separate binaries they ran one after another, most of them one test on one core), and the
//! paper rig's default calibration is recorded and fitted once for all of them
//! (`common::paper_calibration`). The processor-in-the-loop tests stay in `tests/pil.rs` (they need
//! the firmware and run in their own CI step).

mod bad_inputs;
mod coverage;
mod evaluation;
mod fidelity;
mod generalisation;
mod geometry;
mod homing;
mod placement;
mod retarget;

#[path = "../common/mod.rs"]
mod common;

pub use common::paper_calibration;
