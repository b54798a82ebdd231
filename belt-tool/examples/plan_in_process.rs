//! `beltctl calibrate`'s plan for a drive, recorded in-process on the simulated stage and fitted:
//! what the on-drive fit should give when the recording path adds nothing. A measurement for the
//! README ("Proven against a virtual drive"), not part of the product.
//!
//! `cargo run --profile ci -p belt-tool --example plan_in_process -- CONFIG.toml PLANT.toml`
//! (the drive's configuration as `beltctl config load` takes it, and a `hil-sim` plant file)
//! prints each model's RMS on its own calibration data, um.
#![allow(clippy::print_stdout)]

use estimator_core::model::{ModelKind, ModelParams};
use estimator_core::settings::Settings;
use hil_sim::{eval, PlantParams};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, config, plant] = args.as_slice() else {
        return Err("usage: plan_in_process CONFIG.toml PLANT.toml".into());
    };
    let mut settings = Settings::PAPER;
    let text = std::fs::read_to_string(config)?;
    for (field, value) in belt_tool::config::parse_file(std::path::Path::new(config), &text)? {
        settings
            .set(field.key(), value)
            .map_err(|e| format!("{config}: {}: {e}", field.name()))?;
    }
    let plant = PlantParams::from_toml_str(&std::fs::read_to_string(plant)?)?;
    let plan = belt_tool::calibrate::plan(
        &settings,
        None,
        None,
        hil_sim::eval::CALIBRATION_PLAN_SEED,
        &[],
    )?;
    let traces = plan
        .scenarios
        .iter()
        .enumerate()
        .map(|(k, s)| {
            eval::run_in_process(
                s,
                &plant,
                &ModelParams::PAPER,
                ModelKind::None,
                1000 + k as u64,
                &mut |_| {},
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let cal = hil_sim::calibrate::calibrate(&traces, &plant.rig(), &mut |_, _| {})?;
    for (kind, rms) in cal.fit_rms_um {
        println!("{:8} {rms:5.1} um", kind.as_str());
    }
    Ok(())
}
