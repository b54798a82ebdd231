//! What `hil-sim`'s test binaries share (`tests/pil.rs` and `tests/integration/`).

use std::sync::OnceLock;

use hil_sim::calibrate::Calibration;
use hil_sim::{eval, PlantParams};

/// The paper rig calibrated by its default plan (`eval::calibrate_plant`), made once per test
/// binary for the tests that share it.
pub fn paper_calibration() -> &'static Calibration {
    static CAL: OnceLock<Calibration> = OnceLock::new();
    CAL.get_or_init(|| {
        eval::calibrate_plant(&PlantParams::paper_rig(), &mut |_, _| {})
            .expect("the paper rig calibrates")
    })
}
