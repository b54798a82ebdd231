//! The generalisation table: every estimator on every scenario preset and on generated workloads
//! of every class (`workloads`), on the paper rig and plant variants, each plant calibrated by
//! its own default plan. The workloads' seed is not the calibration plan's: what is measured is
//! held out. Each row also has its floor: the non-repeatable part of `x_LS - x_PE`, the RMS of
//! the tick-by-tick difference between two noise seeds of the same run, divided by sqrt 2.

use crate::error::{Context, Error};
use estimator_core::model::{ModelKind, ModelParams};

use crate::params::PlantParams;
use crate::run::Trace;
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

/// The built-in plant whose name contains `part` (`paper` or none: the paper rig), for the
/// examples' command lines; `None` if no plant's name does.
pub fn plant_named(part: Option<&str>) -> Result<Option<PlantParams>, Error> {
    Ok(match part {
        None | Some("paper") => Some(PlantParams::paper_rig()),
        Some(part) => plants()?.into_iter().find(|p| p.source.contains(part)),
    })
}

/// A machine drawn at random around the paper rig (`hil-sim generalise --drawn N`): a machine
/// no model was designed against. Log-uniform over ranges a builder meets:
/// - carriage 0.8-6 kg, guide friction 4-20 N;
/// - tooth half gap 60-220 um, belt preload 20-70 N, belt rigidity 1e5-4e5 N;
/// - belt-on-pulley friction 0.25-0.45 kinetic, static 0.05-0.15 above it;
/// - gearbox 8:1 to 30:1;
/// - uniform over 15, 20, 24 and 30 pulley teeth, 2, 3, 5 and 5.08 mm pitch, and 500, 1000 and
///   2000 encoder lines.
///
/// Only machines the drive's default tuning can move are kept. At the default limits'
/// acceleration the carriage, the reflected rotor and twice the guide's friction need at most
/// half of the loop's current limit; a draw beyond is drawn again. Without this rule, one of
/// the first three draws (a 2 mm pitch on a 20.8:1 gearbox: 226 kg reflected) saturates the
/// current at 5000 mm/s² and the drive stops with `current_saturation`, as it must. Where the
/// simulation needs a shorter step for a draw's stiffer contact, it gets one.
pub fn drawn_plant(seed: u64) -> PlantParams {
    let mut r = crate::plant::rng::Rng::new(seed, 0x4d41_4348);
    let settings = estimator_core::settings::Settings::PAPER;
    loop {
        let mut log_uniform = |lo: f64, hi: f64| (lo.ln() + r.uniform() * (hi / lo).ln()).exp();
        let mut p = PlantParams::paper_rig();
        p.carriage.mass_kg = log_uniform(0.8, 6.0);
        p.carriage.coulomb_n = log_uniform(4.0, 20.0);
        p.belt.tooth_half_gap_m = log_uniform(0.6e-4, 2.2e-4);
        p.belt.preload_n = log_uniform(20.0, 70.0);
        p.belt.axial_rigidity_n = log_uniform(1.0e5, 4.0e5);
        p.friction.mu_kinetic = log_uniform(0.25, 0.45);
        p.friction.mu_static = p.friction.mu_kinetic + log_uniform(0.05, 0.15);
        p.gearbox.ratio = (log_uniform(8.0, 30.0) * 100.0).round() / 100.0;
        let mut pick = |n: usize| ((r.uniform() * n as f64) as usize).min(n - 1);
        p.pulley.teeth = [15, 20, 24, 30][pick(4)];
        p.belt.pitch_m = [2.0e-3, 3.0e-3, 5.0e-3, 5.08e-3][pick(4)];
        p.encoder.lines = [500, 1000, 2000][pick(3)];
        let radius_m = p.pulley.teeth as f64 * p.belt.pitch_m / std::f64::consts::TAU;
        let newton_per_a = p.motor.torque_constant_nm_per_a * p.gearbox.ratio / radius_m;
        let mass_kg = p.carriage.mass_kg
            + (p.motor.rotor_inertia_kg_m2 * p.gearbox.ratio.powi(2)
                + p.gearbox.output_inertia_kg_m2)
                / radius_m.powi(2);
        let need_a =
            (mass_kg * settings.max_accel_mm_s2 * 1e-3 + 2.0 * p.carriage.coulomb_n) / newton_per_a;
        if need_a > 0.5 * settings.pid.max_current_a {
            continue;
        }
        // A stiff contact on a light pulley needs a shorter integration step (the simulation's,
        // not the machine's): halved up to four times, else drawn again.
        for _ in 0..5 {
            if p.validate().is_ok() {
                p.source = format!("machine drawn at random, seed {seed}");
                return p;
            }
            p.integration.max_substep_s /= 2.0;
        }
    }
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
    /// Moves that travel, and those outside the region the calibration covered
    /// (`crate::coverage`).
    pub moves: usize,
    /// See `moves`.
    pub moves_outside: usize,
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

    /// The RMS of `estimator` on this row, um.
    pub fn rms(&self, estimator: &str) -> Option<f64> {
        self.rms_um
            .iter()
            .find(|(k, _)| *k == estimator)
            .map(|x| x.1)
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

impl PlantTable {
    /// Root of the mean square of `estimator` over the workloads generated with
    /// `workload_seed` (named `*-{seed}`; each weighs the same), um; `None` without any.
    pub fn held_out_rms(&self, estimator: &str, workload_seed: u64) -> Option<f64> {
        let suffix = format!("-{workload_seed}");
        let v: Vec<f64> = self
            .rows
            .iter()
            .filter(|r| r.workload.ends_with(&suffix))
            .filter_map(|r| r.rms(estimator))
            .collect();
        (!v.is_empty()).then(|| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt())
    }
}

/// The held-out set of the Model 4 probes (`examples/oracle.rs`, `examples/observer_variants.rs`):
/// fig18, zigzag and accelerations, then one generated member of every class for `seed`, each
/// recorded on `plant` with no model (noise seed 1), beside its scenario.
pub fn probe_set(plant: &PlantParams, seed: u64) -> Result<Vec<(Scenario, Trace)>, Error> {
    let lim = Limits::of(&drive_setup::drive_limits(plant.rig()));
    let mut out = Vec::new();
    for name in ["fig18", "zigzag", "accelerations"] {
        out.push(Scenario::load(name)?);
    }
    out.extend(Class::ALL.map(|c| workloads::generate(c, seed, &lim, WORKLOAD_S)));
    out.into_iter()
        .map(|s| {
            let t = eval::run_in_process(
                &s,
                plant,
                &ModelParams::PAPER,
                ModelKind::None,
                1,
                &mut |_| {},
            )
            .context(|| format!("probe workload {}", s.name))?;
            Ok((s, t))
        })
        .collect()
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

/// The floor of a workload: the RMS of the non-repeatable part of `x_LS - x_PE`, from two runs
/// of it with different seeds (their difference has twice its variance).
pub fn floor_um(a: &Trace, b: &Trace) -> f64 {
    let n = a.records.len().min(b.records.len());
    ((0..n)
        .map(|i| (a.dx_um(i) - b.dx_um(i)).powi(2))
        .sum::<f64>()
        / n.max(1) as f64
        / 2.0)
        .sqrt()
}

/// Calibrates `plant` (default plan drawn with `plan_seed`) and measures every estimator and
/// the floor on `scenarios` (those the plant's drive limits refuse are left out).
pub fn measure(
    plant: &PlantParams,
    scenarios: &[Scenario],
    plan_seed: u64,
    observer: eval::Observer,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<PlantTable, Error> {
    let cal = eval::calibrate_plant_for(plant, plan_seed, &[], observer, progress)?;
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
        let floor_um = floor_um(&a, &b);
        let est = eval::estimates(&a, &coeffs);
        let rms_um = eval::table3(&a, &est)
            .into_iter()
            .map(|(k, st)| (k, st.rms_um))
            .collect();
        let check = cal.coverage.as_ref().map(|c| c.check(s));
        rows.push(Row {
            workload: s.name.clone(),
            floor_um,
            rms_um,
            moves: check.as_ref().map_or(0, |c| c.moves()),
            moves_outside: check.as_ref().map_or(0, |c| c.moves_outside()),
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

/// [`measure`] of every `(plant, scenarios)` pair, on every core at once: each plant's
/// calibration and runs are its own (their own seeds), so the tables, in the pairs' order, and
/// the first error in that order are what one core would give. Progress names the plant; a
/// stage's fraction is shown only as the stage begins (two plants' stages interleave).
pub fn measure_all(
    jobs: &[(PlantParams, Vec<Scenario>)],
    plan_seed: u64,
    observer: eval::Observer,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Vec<PlantTable>, Error> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::{mpsc, Mutex};
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(jobs.len());
    if workers <= 1 {
        return jobs
            .iter()
            .map(|(p, w)| {
                let name = p.name().to_string();
                measure(p, w, plan_seed, observer, &mut |s, f| {
                    progress(&format!("{name}: {s}"), f)
                })
            })
            .collect();
    }
    let next = AtomicUsize::new(0);
    let done: Vec<Mutex<Option<Result<PlantTable, Error>>>> =
        jobs.iter().map(|_| Mutex::new(None)).collect();
    let (tx, rx) = mpsc::channel::<String>();
    std::thread::scope(|scope| {
        for _ in 0..workers {
            let tx = tx.clone();
            let (next, done) = (&next, &done);
            scope.spawn(move || loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                let Some((plant, scenarios)) = jobs.get(k) else {
                    break;
                };
                let name = plant.name().to_string();
                let mut stage = String::new();
                let r = measure(plant, scenarios, plan_seed, observer, &mut |s, _| {
                    if s != stage {
                        stage = s.to_string();
                        // The receiver outlives every worker; a failed send loses progress only.
                        let _ = tx.send(format!("{name}: {s}"));
                    }
                });
                let failed = r.is_err();
                if let Ok(mut slot) = done[k].lock() {
                    *slot = Some(r);
                }
                if failed {
                    // Later plants are not needed; earlier ones finish (an error of theirs
                    // comes first).
                    next.store(jobs.len(), Ordering::Relaxed);
                }
            });
        }
        drop(tx);
        for stage in rx {
            progress(&stage, 0.0);
        }
    });
    let mut tables = Vec::with_capacity(jobs.len());
    for (slot, (plant, _)) in done.into_iter().zip(jobs) {
        match slot.into_inner().ok().flatten() {
            Some(r) => tables.push(r?),
            // Not run: only after a plant before it failed, whose error came first.
            None => return Err(Error::NotMeasured(plant.name().to_string())),
        }
    }
    Ok(tables)
}

/// `path` with the plan seed before its extension (`gen.png`, 7 -> `gen-plan7.png`): one
/// picture per draw of `hil-sim generalise --plot`.
pub fn seeded_path(path: &std::path::Path, plan_seed: u64) -> std::path::PathBuf {
    let stem = path.file_stem().map_or_else(
        || "generalisation".into(),
        |s| s.to_string_lossy().into_owned(),
    );
    let name = match path.extension() {
        Some(ext) => format!("{stem}-plan{plan_seed}.{}", ext.to_string_lossy()),
        None => format!("{stem}-plan{plan_seed}"),
    };
    path.with_file_name(name)
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
            "\n**{}**\n\n| workload | outside | floor |{head}\n|---|---:|---:|{rule}\n",
            t.plant
        );
        out += "| (calibration fit) | | |";
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
            let m4 = r.rms("model4");
            near += m4.is_some_and(|v| v <= 4.0 * r.floor_um) as usize;
            out += &format!(
                "| {} | {}/{} | {:.1} |",
                r.workload, r.moves_outside, r.moves, r.floor_um
            );
            for e in eval::ESTIMATORS {
                match r.rms(e) {
                    Some(v) if *e == best => out += &format!(" **{v:.1}** |"),
                    Some(v) => out += &format!(" {v:.1} |"),
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

/// Model 4 over several draws of the calibration plan (`hil-sim generalise --plan-seed A,B,...`):
/// per draw, the rows where it is best and, per plant, its mean square over the generated
/// workloads (those named `*-{workload_seed}`) and its fig18; the means over the draws beside the
/// best other estimator's; then every row Model 4 loses, with the number of draws it loses it in.
/// `draws` holds each plan seed with its tables, every draw the same plants and rows.
pub fn draws_markdown(draws: &[(u64, Vec<PlantTable>)], workload_seed: u64) -> String {
    let Some((_, first)) = draws.first() else {
        return String::new();
    };
    let others = || {
        eval::ESTIMATORS
            .iter()
            .filter(|e| !matches!(**e, "none" | "model4"))
    };
    let cell = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
    let n = draws.len() as f64;
    let mut out = format!(
        "\n**Model 4 over {} draws of the calibration plan** (workload seed {workload_seed}): \
         its mean square over the generated workloads / fig18, um\n\n| plan seed | best rows |",
        draws.len()
    );
    for t in first {
        out += &format!(" {} |", t.plant);
    }
    out += &format!("\n|---:|---:|{}\n", "---:|".repeat(first.len()));
    let mut sums = vec![(0.0, 0.0, 0.0); first.len()];
    let mut best_total = 0usize;
    // Draws in which Model 4 loses each row, by plant and row (every draw has the same ones).
    let mut lost: Vec<Vec<usize>> = first.iter().map(|t| vec![0; t.rows.len()]).collect();
    for (seed, tables) in draws {
        let best = tables
            .iter()
            .flat_map(|t| &t.rows)
            .filter(|r| r.best() == "model4")
            .count();
        best_total += best;
        out += &format!("| {seed} | {best} |");
        for (k, t) in tables.iter().enumerate() {
            let gen = t.held_out_rms("model4", workload_seed);
            let fig = t
                .rows
                .iter()
                .find(|r| r.workload == "fig18")
                .and_then(|r| r.rms("model4"));
            let other = others()
                .filter_map(|e| t.held_out_rms(e, workload_seed))
                .fold(f64::INFINITY, f64::min);
            if let Some(s) = sums.get_mut(k) {
                s.0 += gen.unwrap_or(f64::NAN);
                s.1 += fig.unwrap_or(f64::NAN);
                s.2 += other;
            }
            out += &format!(" {} / {} |", cell(gen), cell(fig));
            for (count, r) in lost.get_mut(k).into_iter().flatten().zip(&t.rows) {
                *count += usize::from(r.best() != "model4");
            }
        }
        out += "\n";
    }
    out += &format!("| mean | {:.1} |", best_total as f64 / n);
    for s in &sums {
        out += &format!(" {:.1} / {:.1} |", s.0 / n, s.1 / n);
    }
    out += "\n| best other, mean | |";
    for s in &sums {
        out += &format!(" {:.1} |", s.2 / n);
    }
    out += "\n\nRows Model 4 loses, in how many draws:\n\n| plant | workload | draws |\n|---|---|---:|\n";
    for (t, counts) in first.iter().zip(&lost) {
        for (r, k) in t.rows.iter().zip(counts).filter(|(_, k)| **k > 0) {
            out += &format!(
                "| {} | {} | {k} of {} |\n",
                t.plant,
                r.workload,
                draws.len()
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(workload: &str, m1: f64, m4: f64) -> Row {
        Row {
            workload: workload.into(),
            floor_um: 1.0,
            rms_um: vec![("none", 100.0), ("model1", m1), ("model4", m4)],
            moves: 10,
            moves_outside: 0,
        }
    }

    /// The summary's means, the best other estimator and the lost rows, on two hand-made draws.
    #[test]
    fn draws_summary_counts_and_averages() {
        let table = |m4_fig: f64, m4_gen: f64| PlantTable {
            plant: "rig".into(),
            fit_rms_um: Vec::new(),
            rows: vec![
                row("fig18", 20.0, m4_fig),
                row("raster-11", 30.0, m4_gen),
                row("feed-11", 40.0, 0.0),
                row("feed-12", 1.0, 1.0e6),
            ],
        };
        // Draw 1: Model 4 loses fig18 and feed-12 (best on 2 rows); generated
        // sqrt((6^2 + 0) / 2). Draw 2: it wins fig18 and loses the raster and feed-12.
        let md = draws_markdown(
            &[(5, vec![table(25.0, 6.0)]), (6, vec![table(10.0, 32.0)])],
            11,
        );
        let gen1 = (36.0f64 / 2.0).sqrt();
        let gen2 = (32.0f64 * 32.0 / 2.0).sqrt();
        assert!(
            md.contains(&format!("| 5 | 2 | {gen1:.1} / 25.0 |")),
            "{md}"
        );
        assert!(
            md.contains(&format!("| 6 | 2 | {gen2:.1} / 10.0 |")),
            "{md}"
        );
        let m1 = ((900.0f64 + 1600.0) / 2.0).sqrt();
        assert!(
            md.contains(&format!(
                "| mean | 2.0 | {:.1} / 17.5 |",
                (gen1 + gen2) / 2.0
            )),
            "{md}"
        );
        assert!(
            md.contains(&format!("| best other, mean | | {m1:.1} |")),
            "{md}"
        );
        // feed-12 is not generated at seed 11 but is a row Model 4 loses in both draws.
        assert!(md.contains("| rig | fig18 | 1 of 2 |"), "{md}");
        assert!(md.contains("| rig | raster-11 | 1 of 2 |"), "{md}");
        assert!(md.contains("| rig | feed-12 | 2 of 2 |"), "{md}");
        assert!(!md.contains("| rig | feed-11 |"), "{md}");
        // In the tables' order.
        let at = |w: &str| md.find(&format!("| rig | {w} |")).unwrap();
        assert!(
            at("fig18") < at("raster-11") && at("raster-11") < at("feed-12"),
            "{md}"
        );
    }

    /// A draw is a valid plant, the same for the same seed, and within the drive's current at
    /// the default acceleration by the rule of [`drawn_plant`].
    #[test]
    fn drawn_machines_are_valid_repeatable_and_movable() {
        let settings = estimator_core::settings::Settings::PAPER;
        let mut rigs = Vec::new();
        for seed in 1..=50 {
            let p = drawn_plant(seed);
            p.validate().unwrap();
            assert_eq!(p, drawn_plant(seed));
            let r = p.pulley.teeth as f64 * p.belt.pitch_m / std::f64::consts::TAU;
            let reflected = p.motor.rotor_inertia_kg_m2 * p.gearbox.ratio.powi(2) / (r * r);
            let n_per_a = p.motor.torque_constant_nm_per_a * p.gearbox.ratio / r;
            assert!(
                (p.carriage.mass_kg + reflected) * settings.max_accel_mm_s2 * 1e-3 / n_per_a
                    < 0.5 * settings.pid.max_current_a,
                "seed {seed}"
            );
            rigs.push(format!("{:?}", p.rig()));
        }
        rigs.sort();
        rigs.dedup();
        assert!(rigs.len() > 40, "{} geometries in 50 draws", rigs.len());
    }
}
