//! `hil-sim`'s integration tests as one binary: its tests share the machine's two cores (as
//! separate binaries they ran one after another, most of them one test on one core), and the
//! paper rig's default calibration is recorded and fitted once for all of them
//! ([`paper_calibration`]). The processor-in-the-loop tests stay in `tests/pil.rs` (they need
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

use std::sync::OnceLock;

use hil_sim::calibrate::Calibration;
use hil_sim::{eval, PlantParams};

/// The paper rig calibrated by its default plan (`eval::calibrate_plant`), made once.
pub fn paper_calibration() -> &'static Calibration {
    static CAL: OnceLock<Calibration> = OnceLock::new();
    CAL.get_or_init(|| {
        eval::calibrate_plant(&PlantParams::paper_rig(), &mut |_, _| {})
            .expect("the paper rig calibrates")
    })
}
