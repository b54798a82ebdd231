//! The generalisation table: every estimator on every scenario preset and on generated workloads
//! of every class (`workloads`), on the paper rig and plant variants, each plant calibrated by
//! its own default plan. The workloads' seed is not the calibration plan's: what is measured is
//! held out. Each row also has its floor: the non-repeatable part of `x_LS - x_PE`, the RMS of
//! the tick-by-tick difference between two noise seeds of the same run, divided by sqrt 2.

use crate::error::{Context, Error};
use estimator_core::model::{ModelKind, ModelParams};

use crate::params::PlantParams;
use crate::scenario::{Scenario, PRESETS};
use crate::workloads::{self, Class, Limits};
use crate::{drive_setup, eval};

/// The plant variants (each a change of the paper rig argued in its file's comments).
pub const VARIANTS: [(&str, &str); 4] = [
    (
        "tight-belt",
        include_str!("../presets/variants/tight-belt.toml"),
    ),
    (
        "worn-belt",
        include_str!("../presets/variants/worn-belt.toml"),
    ),
    (
        "heavy-carriage",
        include_str!("../presets/variants/heavy-carriage.toml"),
    ),
    (
        "other-geometry",
        include_str!("../presets/variants/other-geometry.toml"),
    ),
];

/// The paper rig and the variants, named.
pub fn plants() -> Result<Vec<PlantParams>, Error> {
    let mut out = vec![PlantParams::paper_rig()];
    for (name, text) in VARIANTS {
        let mut p = PlantParams::from_toml_str(text).context(|| format!("variant {name}"))?;
        p.source = format!("variant {name}");
        out.push(p);
    }
    Ok(out)
}

/// Seed of the generated workloads in the README's table (the calibration plan's is another).
pub const TABLE_SEED: u64 = 11;
/// Length of each generated workload, s.
pub const WORKLOAD_S: f64 = 20.0;

/// One workload on one plant.
#[derive(Clone, Debug)]
pub struct Row {
    /// Scenario name.
    pub workload: String,
    /// Non-repeatable part of `x_LS - x_PE`, um RMS.
    pub floor_um: f64,
    /// RMS of `e = x_LS - x_PE - y` of each estimator, in `eval::ESTIMATORS` order, um.
    pub rms_um: Vec<(&'static str, f64)>,
}

impl Row {
    /// The estimator (not `none`) with the lowest RMS.
    pub fn best(&self) -> &'static str {
        self.rms_um
            .iter()
            .filter(|(k, _)| *k != "none")
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map_or("none", |(k, _)| k)
    }
}

/// One plant's table.
#[derive(Clone, Debug)]
pub struct PlantTable {
    /// The plant's name.
    pub plant: String,
    /// Each model's RMS on its own calibration data, um.
    pub fit_rms_um: Vec<(&'static str, f64)>,
    /// Scenario presets first, then the generated workloads.
    pub rows: Vec<Row>,
}

/// The workloads of the table: every preset and one generated member of every class.
pub fn workloads(plant: &PlantParams, seed: u64) -> Result<Vec<Scenario>, Error> {
    let lim = Limits::of(&drive_setup::drive_limits(plant.rig()));
    let mut out: Vec<Scenario> = PRESETS
        .iter()
        .map(|(n, _)| Scenario::load(n))
        .collect::<Result<_, crate::scenario::ScenarioError>>()?;
    out.extend(
        Class::ALL
            .into_iter()
            .map(|c| workloads::generate(c, seed, &lim, WORKLOAD_S)),
    );
    Ok(out)
}

/// Calibrates `plant` and measures every estimator and the floor on `scenarios` (those the
/// plant's drive limits refuse are left out).
pub fn measure(
    plant: &PlantParams,
    scenarios: &[Scenario],
    progress: &mut dyn FnMut(&str, f64),
) -> Result<PlantTable, Error> {
    let cal = eval::calibrate_plant(plant, progress)?;
    let coeffs = cal.params.build(&plant.rig())?;
    let limits = drive_setup::drive_limits(plant.rig());
    let mut rows = Vec::new();
    for (k, s) in scenarios.iter().enumerate() {
        if s.check_against(&limits, plant).is_err() {
            continue;
        }
        progress(
            &format!("workload {}", s.name),
            k as f64 / scenarios.len() as f64,
        );
        let run = |seed| {
            eval::run_in_process(
                s,
                plant,
                &ModelParams::PAPER,
                ModelKind::None,
                seed,
                &mut |_| {},
            )
            .context(|| s.name.clone())
        };
        let (a, b) = (run(1)?, run(2)?);
        let n = a.records.len().min(b.records.len());
        let floor_um = ((0..n)
            .map(|i| (a.dx_um(i) - b.dx_um(i)).powi(2))
            .sum::<f64>()
            / n.max(1) as f64
            / 2.0)
            .sqrt();
        let est = eval::estimates(&a, &coeffs);
        let rms_um = eval::table3(&a, &est)
            .into_iter()
            .map(|(k, st)| (k, st.rms_um))
            .collect();
        rows.push(Row {
            workload: s.name.clone(),
            floor_um,
            rms_um,
        });
    }
    let fit_rms_um = cal
        .fit_rms_um
        .iter()
        .map(|(k, v)| (k.as_str(), *v))
        .collect();
    Ok(PlantTable {
        plant: plant.name().to_string(),
        fit_rms_um,
        rows,
    })
}

/// The tables as Markdown, the best estimator of each row in bold, with a count of the rows
/// where Model 4 is best and where it is within 4x of the floor.
pub fn markdown(tables: &[PlantTable]) -> String {
    let mut out = String::new();
    let head: String = eval::ESTIMATORS.iter().map(|e| format!(" {e} |")).collect();
    let rule = "---:|".repeat(eval::ESTIMATORS.len());
    let (mut rows, mut best4, mut near) = (0, 0, 0);
    for t in tables {
        out += &format!(
            "\n**{}**\n\n| workload | floor |{head}\n|---|---:|{rule}\n",
            t.plant
        );
        out += "| (calibration fit) | |";
        for e in eval::ESTIMATORS {
            match t.fit_rms_um.iter().find(|(k, _)| k == e) {
                Some((_, v)) => out += &format!(" {v:.1} |"),
                None => out += " |",
            }
        }
        out += "\n";
        for r in &t.rows {
            let best = r.best();
            rows += 1;
            best4 += (best == "model4") as usize;
            let m4 = r.rms_um.iter().find(|(k, _)| *k == "model4").map(|x| x.1);
            near += m4.is_some_and(|v| v <= 4.0 * r.floor_um) as usize;
            out += &format!("| {} | {:.1} |", r.workload, r.floor_um);
            for e in eval::ESTIMATORS {
                match r.rms_um.iter().find(|(k, _)| k == e) {
                    Some((k, v)) if *k == best => out += &format!(" **{v:.1}** |"),
                    Some((_, v)) => out += &format!(" {v:.1} |"),
                    None => out += " |",
                }
            }
            out += "\n";
        }
    }
    out += &format!(
        "\nModel 4 best on {best4} of {rows} rows; within 4x of the floor on {near} of {rows}.\n"
    );
    out
}
