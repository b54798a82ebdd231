//! The drive configuration every simulation runs: the paper rig's limits, gains and thresholds
//! with the plant's geometry. A leaf module: the runner, the evaluation, placement and the fault
//! scenarios all build their drive here without importing one another.

use estimator_core::drive::{DriveConfig, Models};
use estimator_core::model::{ModelKind, ModelParams};
use estimator_core::rig::Rig;
use estimator_core::settings::Settings;

/// The paper rig's limits, gains and thresholds (all in millimetres and seconds) with the
/// plant's geometry (`rig`: encoder lines, gearbox, pulley, pitch).
pub fn drive_limits(rig: Rig) -> DriveConfig<'static> {
    DriveConfig {
        settings: Settings {
            rig,
            ..Settings::PAPER
        },
        ..DriveConfig::paper_rig()
    }
}

/// [`drive_limits`] with `params` loaded and `model` active.
pub fn drive_config(params: &ModelParams, model: ModelKind, rig: Rig) -> DriveConfig<'_> {
    Settings {
        rig,
        initial_model: model,
        ..Settings::PAPER
    }
    .drive_config(Models::Params(params))
}
