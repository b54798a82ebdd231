//! `hil-sim report`: Table 3 in Markdown, the per-tick CSV, and the paper's figures as PNG.

use crate::error::{Context, Error};
use std::io::Write;
use std::path::Path;

use estimator_core::model::{ModelKind, ModelParams};

use crate::calibrate::Calibration;
use crate::eval;
use crate::plant::PlantParams;
use crate::plot;
use crate::progress::Progress;
use crate::run::Trace;
use crate::scenario::Scenario;
use crate::stats::ErrorStats;

/// The paper's Table 3 (um): (name, max, min, rms).
pub const PAPER_TABLE3: &[(&str, f64, f64, f64)] = &[
    ("model1", 131.0, -148.0, 38.0),
    ("model2", 120.0, -130.0, 34.0),
    ("model3", 99.0, -79.0, 26.0),
    ("none", 365.0, -93.0, 195.0),
];

/// Table 3 as Markdown, with the paper's figures beside ours.
/// `paper`: the paper's own setting (its Fig. 18 scenario on its rig, see
/// [`eval::paper_setting`]): only then are Table 3's published figures shown beside ours.
pub fn table_markdown(
    scenario: &str,
    samples: usize,
    table: &[(&'static str, ErrorStats)],
    paper: bool,
) -> String {
    let mut s =
        format!("Scenario `{scenario}`, {samples} samples; e = x_LS - x_PE - y in um (eq. 19)\n\n");
    if !paper {
        s += "| estimator | max | min | RMS |\n|---|---:|---:|---:|\n";
        for (name, st) in table {
            s += &format!(
                "| {name} | {:.1} | {:.1} | {:.1} |\n",
                st.max_um, st.min_um, st.rms_um
            );
        }
        s +=
            "\n(The paper's Table 3 applies to its Fig. 18 scenario on its rig only: not shown.)\n";
        return s;
    }
    s += "| estimator | max | min | RMS | paper max | paper min | paper RMS |\n|---|---:|---:|---:|---:|---:|---:|\n";
    for (name, st) in table {
        let paper = PAPER_TABLE3.iter().find(|p| p.0 == *name);
        let p = |f: fn(&(&str, f64, f64, f64)) -> f64| {
            paper.map_or("-".to_string(), |q| format!("{:.0}", f(q)))
        };
        s += &format!(
            "| {name} | {:.1} | {:.1} | {:.1} | {} | {} | {} |\n",
            st.max_um,
            st.min_um,
            st.rms_um,
            p(|q| q.1),
            p(|q| q.2),
            p(|q| q.3)
        );
    }
    s
}

/// The positioning table: one row per compensator, the keys of `evaluate --json`.
pub fn placement_markdown(placed: &[(&'static str, crate::placement::Positioning)]) -> String {
    let mut s = String::from(
        "Carriage placement: the scenario again with every move in carriage space (`MoveTo`), \
         one run per compensator; arrival = scale at rest minus the carriage target; tracking = \
         scale minus the planned carriage set-point while moving; ratios = the motor set-point's \
         peak velocity and acceleration over the move's limits.\n\n\
         | compensator | arrival RMS (um) | arrival max (um) | tracking RMS (um) | cycle (s) | peak v / limit | peak a / limit | moves at rest |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for (n, p) in placed {
        s += &format!(
            "| {n} | {:.1} | {:.1} | {:.1} | {:.3} | {:.3} | {:.3} | {} |\n",
            p.arrival_rms_um,
            p.arrival_max_um,
            p.tracking_rms_um,
            p.cycle_time_s,
            p.peak_velocity_ratio,
            p.peak_accel_ratio,
            p.moves_at_rest
        );
    }
    s
}

/// Every tick of `trace` as CSV.
pub fn write_csv(w: &mut dyn Write, trace: &Trace) -> std::io::Result<()> {
    writeln!(
        w,
        "t_s,motor_counts,x_pe_mm,x_ls_mm,dx_um,setpoint_counts,following_error_counts,current_a,est_error_um,model,faults"
    )?;
    for (i, r) in trace.records.iter().enumerate() {
        let t = &r.out.telemetry;
        writeln!(
            w,
            "{:.4},{},{:.6},{:.6},{:.3},{},{},{:.5},{:.4},{},{}",
            r.t_s,
            r.motor_counts,
            trace.x_pe_mm(i),
            r.x_ls_mm,
            trace.dx_um(i),
            t.setpoint_counts.0,
            t.following_error_counts.0,
            r.out.current_a.to_num::<f64>(),
            t.est_error_um.to_num::<f64>(),
            t.model.as_str(),
            t.faults
        )?;
    }
    Ok(())
}

/// Repetitions of the repeatability scenario overlaid in Fig. 11.
pub const FIG11_RUNS: u64 = 12;

/// What a report is about.
pub struct Setting<'a> {
    /// The scenario run.
    pub scenario: &'a Scenario,
    /// The plant it ran on.
    pub plant: &'a PlantParams,
    /// How the loop was closed (in-process or the firmware under QEMU), for the text.
    pub how: &'a str,
}

/// The files [`write`] must write (a figure that cannot be drawn is named in the report
/// instead): the report and the trace of `scenario`.
pub fn required_files(scenario: &str) -> [String; 2] {
    ["report.md".to_string(), format!("{scenario}.csv")]
}

/// Runs the scenario, writes report.md, the figures and the CSV into `dir`.
/// `placed`: the scenario in carriage space per compensator ([`crate::placement::compare`]).
pub fn write(
    dir: &Path,
    setting: &Setting,
    trace: &Trace,
    cal: &Calibration,
    placed: &[crate::placement::Placement],
    progress: &mut Progress,
) -> Result<(), Error> {
    let Setting { plant, how, .. } = *setting;
    let paper = eval::paper_setting(setting.scenario, plant);
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let coeffs = cal.params.build(&plant.rig())?;
    let est = eval::estimates(trace, &coeffs);
    let table = eval::table3(trace, &est);

    // Fig. 11 from the second of two cycles: a fresh plant starts on the forward band edge, so
    // the first cycle lacks the reverse-to-forward transition; the second shows the whole loop.
    let rep = Scenario::load("repeatability")?;
    let cycle = rep.moves.len();
    let twice = Scenario {
        moves: [rep.moves.clone(), rep.moves.clone()].concat(),
        ..rep.clone()
    };
    let mut overlay = Vec::new();
    for k in 0..FIG11_RUNS {
        let label = format!("Fig. 11 run {}/{}", k + 1, FIG11_RUNS);
        let mut t = eval::run_in_process(
            &twice,
            plant,
            &ModelParams::PAPER,
            ModelKind::None,
            2_000 + k,
            &mut |f| progress.stage(&label, f),
        )
        .context(|| "repeatability".into())?;
        let from = t.move_starts.get(cycle).copied().unwrap_or(0);
        t.records.drain(..from);
        t.move_starts = t.move_starts[cycle..].iter().map(|s| s - from).collect();
        overlay.push(t);
    }

    progress.stage("figures", 0.0);
    let mut figures = Vec::new();
    let mut failures = Vec::new();
    let mut fig = |file: &str, caption: String, r: Result<(), Box<dyn std::error::Error>>| match r {
        Ok(()) => figures.push((file.to_string(), caption)),
        Err(e) => failures.push(format!("{file}: {e}")),
    };
    fig(
        "fig11_hysteresis.png",
        format!(
            "Fig. 11: x_LS - x_PE against x_PE, {FIG11_RUNS} runs of `repeatability` overlaid \
             (each run's second cycle: the whole loop, both reversals)"
        ),
        plot::hysteresis(
            &dir.join("fig11_hysteresis.png"),
            "Position error, repeated runs (Fig. 11)",
            &overlay,
        ),
    );
    // The paper's figure numbers only for the paper's own scenario.
    let fig18 = eval::is_paper_fig18(setting.scenario);
    let paper_fig = |n: &str| {
        if fig18 {
            format!(" (the paper's {n})")
        } else {
            String::new()
        }
    };
    fig(
        "scenario.png",
        format!(
            "The `{}` scenario: motor position against time{}",
            trace.scenario,
            paper_fig("Fig. 18")
        ),
        plot::scenario(
            &dir.join("scenario.png"),
            &format!("Scenario {}", trace.scenario),
            trace,
        ),
    );
    let ys: Vec<&[f64]> = est.iter().map(|(_, y)| y.as_slice()).collect();
    let scales = plot::estimate_scales(trace, &ys);
    for (name, y) in &est {
        let file = format!("estimate_{name}.png");
        fig(
            &file,
            format!(
                "`{name}` estimate and its error along `{}`{}; every estimator's figure has the \
                 same scales",
                trace.scenario,
                paper_fig("Figs. 19-24")
            ),
            plot::estimate(
                &dir.join(&file),
                &format!("{name} along {}: estimate and error", trace.scenario),
                trace,
                y,
                scales,
            ),
        );
    }
    let shown: Vec<_> = [
        crate::placement::best(placed, &["none"]),
        crate::placement::best(placed, &["backlash", "bidir_table"]),
        crate::placement::best(placed, &["model1", "model2", "model3"]),
    ]
    .into_iter()
    .flatten()
    .map(|p| (p.name, p.arrivals.clone()))
    .collect();
    fig(
        "placement_arrivals.png",
        format!(
            "Carriage placement along `{}`: arrival error of every move that ends at rest, for no \
             compensation, the best baseline and the best model",
            trace.scenario
        ),
        plot::arrivals(
            &dir.join("placement_arrivals.png"),
            &format!("Arrival error per move, {}", trace.scenario),
            &shown,
        ),
    );
    // The scenario's moves against what the calibration covered, where it records that.
    let region = cal
        .coverage
        .as_ref()
        .map(|c| (c, c.check(setting.scenario)));
    if let Some((c, check)) = &region {
        fig(
            "coverage.png",
            format!(
                "The moves of `{}` (peak speed, acceleration) over the calibration's moves: {} of \
                 {} outside in speed and acceleration",
                trace.scenario,
                check.speed_accel(),
                check.moves()
            ),
            plot::coverage(
                &dir.join("coverage.png"),
                &format!("Calibrated region and the moves of {}", trace.scenario),
                c,
                check,
            ),
        );
    }
    progress.stage("figures", 1.0);

    let spread = repeatability_spread_um(&overlay);
    let mut md = format!(
        "# belt-drive: estimation of the carriage position along `{}`\n\n",
        trace.scenario
    );
    md += &format!("Closed loop: {how}; noise seed {}.\n\n", trace.seed);
    md += &table_markdown(&trace.scenario, trace.records.len(), &table, paper);
    md += "\nCalibration fit on its own data (RMS, um): ";
    md += &cal
        .fit_rms_um
        .iter()
        .map(|(k, v)| format!("{} {:.1}", k.as_str(), v))
        .collect::<Vec<_>>()
        .join(", ");
    md += &format!(
        ".\n\nRun-to-run repeatability of Delta x over {FIG11_RUNS} runs (RMS of the deviation from the mean, binned by \
         position and direction): {spread:.1} um. This is the floor under every model's error.\n\n"
    );
    match &region {
        Some((c, check)) => {
            md += &format!(
                "**The calibrated region** (every model is fitted on the same moves). {}\n{}\n\n",
                c.markdown(),
                check.warning().unwrap_or_else(|| format!(
                    "Every move of `{}` lies within the calibrated region.",
                    trace.scenario
                ))
            );
        }
        None => md += "The calibration records no region (an older file): not checked.\n\n",
    }
    let rows: Vec<_> = placed.iter().map(|p| (p.name, p.positioning)).collect();
    md += &placement_markdown(&rows);
    md += "\n";
    for (file, caption) in &figures {
        md += &format!("![{caption}]({file})\n\n*{caption}*\n\n");
    }
    if !failures.is_empty() {
        md += "Figures not drawn:\n\n";
        for f in &failures {
            md += &format!("- {f}\n");
        }
    }
    // Generalisation: the paper rig and the variants, each calibrated by its own plan, on every
    // preset and a generated workload of every class (held out of calibration).
    let mut jobs = Vec::new();
    for p in crate::generalise::plants()? {
        let w = crate::generalise::workloads(&p, crate::generalise::TABLE_SEED)?;
        jobs.push((p, w));
    }
    let tables = crate::generalise::measure_all(
        &jobs,
        crate::eval::CALIBRATION_PLAN_SEED,
        crate::eval::Observer::default(),
        &mut |s, f| progress.stage(&format!("generalisation: {s}"), f),
    )?;
    md += "\n## Generalisation (every estimator, held-out workloads, five plants)\n\n";
    md += "RMS of e in um; floor: RMS of the tick-by-tick difference of x_LS - x_PE between two \
           noise seeds, / sqrt 2. Each plant is calibrated by its own default plan; generated \
           workloads use seed 11 (`hil-sim generalise`).\n";
    md += &crate::generalise::markdown(&tables);
    let picture = dir.join("generalisation.png");
    match crate::plot::generalisation(&picture, &tables) {
        Ok(()) => {
            md += "\n![Generalisation: Model 4 against the best other estimator and the floor, \
                   per plant and workload](generalisation.png)\n\n*Generalisation: RMS of e per \
                   workload on a log scale; Model 4 green where best, red where not; the grey \
                   band runs from the floor to 4x the floor.*\n";
        }
        Err(e) => {
            md += &format!("\nFigure not drawn: generalisation.png: {e}\n");
            crate::errln!("hil-sim: figure not drawn: generalisation.png: {e}");
        }
    }
    let [md_name, csv_name] = required_files(&trace.scenario);
    let csv = dir.join(csv_name);
    let mut w =
        std::io::BufWriter::new(std::fs::File::create(&csv).map_err(|e| Error::io(&csv, e))?);
    write_csv(&mut w, trace).map_err(|e| Error::io(&csv, e))?;
    let md_path = dir.join(md_name);
    std::fs::write(&md_path, md).map_err(|e| Error::io(&md_path, e))?;
    for f in &failures {
        crate::errln!("hil-sim: figure not drawn: {f}");
    }
    Ok(())
}

/// RMS deviation of Delta x from the mean over runs, in 1 mm bins per direction.
pub fn repeatability_spread_um(runs: &[Trace]) -> f64 {
    use std::collections::HashMap;
    let mut bins: HashMap<(i64, i8, usize), (f64, usize)> = HashMap::new();
    for (k, t) in runs.iter().enumerate() {
        for (i, r) in t.records.iter().enumerate() {
            let e = bins
                .entry(((t.x_pe_mm(i)).floor() as i64, r.cmd_dir, k))
                .or_insert((0.0, 0));
            e.0 += t.dx_um(i);
            e.1 += 1;
        }
    }
    let mut per_bin: HashMap<(i64, i8), Vec<f64>> = HashMap::new();
    for ((x, d, _), (s, n)) in bins {
        per_bin.entry((x, d)).or_default().push(s / n as f64);
    }
    let (mut ss, mut n) = (0.0, 0usize);
    for v in per_bin.values().filter(|v| v.len() == runs.len()) {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        ss += v.iter().map(|x| (x - mean).powi(2)).sum::<f64>();
        n += v.len();
    }
    if n == 0 {
        f64::NAN
    } else {
        (ss / n as f64).sqrt()
    }
}
