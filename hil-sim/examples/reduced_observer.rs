//! The reduced plant observer (`hil_sim::belt_observer`) measured as Model 4's slip state, before
//! any fixed-point port (README, "A reduced plant observer"). Not part of the product.
//!
//! `cargo run --profile ci -p hil-sim --example reduced_observer [plant | drawn:N]` calibrates
//! the drive as `hil-sim calibrate` does, replays every recording on the plant for its true mesh
//! offset and prints, on the nine held-out runs of the Model 4 probes (seed 11):
//! - how far the observer's offset is from the true one (RMS, with the true offset's RMS);
//! - Model 4 fitted by least squares on the calibration recordings with, as its slip state,
//!   the slip observer as built, the plant's true offset, or the reduced observer's offset;
//!   then the RMS of e on each held-out run and the root mean square over the six generated
//!   ones.
//!
//! The observer's physics are the plant's own unless told otherwise:
//! - `RO_START_PLANT=name`: the belt's, friction's and carriage's from that built-in plant
//!   (the drive's defaults for a machine it does not know), geometry and motor the plant's;
//! - `RO_SCALE=param*factor,...`: scaled (`mass`, `guide`, `preload`, `gap`, `sigma0`, `mu`,
//!   `kappa`, `rigidity`);
//! - `RO_FIT=param,...`: those fitted on the calibration recordings by
//!   `belt_observer::identify` (`RO_EVALS` a round, 400; `RO_ROUNDS` more, 2;
//!   `RO_MASS_STARTS=0.5,1,2,4`: one start per carriage mass factor).
//!
//! `RO_GUIDE=1` gives the observer the guide's friction along the travel as
//! `belt_observer::guide_profile` measures it on the calibration recordings (before any fit).
//! `RO_SEED=N` takes the held-out workloads of seed N (11). `RO_CAPSTAN_TAYLOR=1` gives the
//! observer the capstan's second-order polynomial.
//! `RO_DRIVE_PORT=1` runs the drive's fixed-point port (`estimator_core::model::belt`:
//! Taylor capstan, guide profile in 64 points) in place of the `f64` observer.
//! `RO_DECIMATE=N` steps the observer once per N ticks (the port as the drive runs it, its step
//! spread over the ticks that follow: `BeltState::tick`; the `f64` observer the same way), its
//! offset carried by the counts between steps.
//! Each row also counts the runs where it is below the best of the other estimators (Models
//! 1-3 and the baselines, as `hil-sim generalise` measures them) and within 4x of the floor.
//! `RO_DROP=plays,current` leaves those of Model 4's terms out of the fits (not of the
//! identification). `RO_RAW_ENCODER=1` feeds the counts without the tracking filter.
#![allow(clippy::print_stdout)]

use estimator_core::model::ModelParams;
use estimator_core::reference::Reference;
use estimator_core::rig::Rig;
use hil_sim::belt_observer::{self, BeltPhysics, FitRun, Param, TICK_S};
use hil_sim::calibrate::model4_row;
use hil_sim::run::Trace;
use hil_sim::scenario::Scenario;
use hil_sim::tables::NormalEquations;
use hil_sim::{Plant, PlantParams};

/// One recording with the plant's truth beside it.
struct Run {
    name: String,
    /// Model 4's terms but its slip state, the observer's inputs and the measured error.
    fit: FitRun,
    /// The slip observer's offset as built, the plant's true one, the reduced observer's
    /// offset and its predicted carriage less motor, um.
    slip: [Vec<f64>; 4],
}

fn replay(t: &Trace, s: &Scenario, plant: &PlantParams, params: &ModelParams, rig: &Rig) -> Run {
    let mut p = Plant::new(plant, s.start_mm, t.seed).expect("plant");
    let cpm = rig.counts_per_mm();
    let x0 = t.records[0].motor_counts.0;
    let c0 = p.motor_counts();
    let mut m = Reference::new(params, rig, x0).expect("reference");
    let mut run = Run {
        name: t.scenario.clone(),
        fit: FitRun {
            inputs: Vec::new(),
            terms: Vec::new(),
            dx_um: Vec::new(),
        },
        slip: [Vec::new(), Vec::new(), Vec::new(), Vec::new()],
    };
    for (k, r) in t.records.iter().enumerate() {
        let current = r.out.current_a.to_num::<f64>();
        run.fit
            .inputs
            .push((c0 + i64::from(r.motor_counts.0.wrapping_sub(x0)), current));
        let (_, f) = m.model4_step(r.motor_counts.0, current);
        run.fit.terms.push(model4_row(&f, cpm).to_vec());
        run.fit.dx_um.push(t.dx_um(k));
        run.slip[0].push(f.slip_um);
        run.slip[1].push(p.belt().mesh_offset_m * 1e6);
        p.step(current, TICK_S);
    }
    run
}

/// The reduced observer's offset and predicted error over a run, um.
fn observe(run: &Run, physics: &BeltPhysics) -> (Vec<f64>, Vec<f64>) {
    if physics.drive_port {
        return belt_observer::port_estimates(&run.fit, physics);
    }
    let mut o = belt_observer::BeltObserver::new(physics.clone(), run.fit.inputs[0].0);
    o.set_tracking(std::env::var("RO_RAW_ENCODER").is_err());
    run.fit
        .inputs
        .iter()
        .map(|&(c, i)| {
            let e = o.step(c, i);
            (e.offset_um, e.error_um)
        })
        .unzip()
}

/// Whether column `j` of Model 4's terms stays (`RO_DROP=plays,current` drops those).
fn kept(j: usize) -> bool {
    use estimator_core::model::operator::N_OPS;
    use hil_sim::calibrate::NB;
    static KEPT: std::sync::OnceLock<Vec<bool>> = std::sync::OnceLock::new();
    KEPT.get_or_init(|| {
        let drop = env_list("RO_DROP");
        let has = |n: &str| drop.iter().any(|d| d == n);
        (0..NB)
            .map(|j| !((has("plays") && j < 2 * N_OPS) || (has("current") && j >= NB - 2)))
            .collect()
    })
    .get(j)
    .copied()
    .unwrap_or(true)
}

fn row(run: &Run, slip: usize, k: usize) -> Vec<f64> {
    let mut v: Vec<f64> = run.fit.terms[k]
        .iter()
        .enumerate()
        .filter(|(j, _)| kept(*j))
        .map(|(_, t)| *t)
        .collect();
    // 4: both of the reduced observer's.
    if slip == 4 {
        v.extend([run.slip[2][k], run.slip[3][k]]);
    } else {
        v.push(run.slip[slip][k]);
    }
    v
}

/// Model 4's weights with slip state `slip`, fitted on `runs`.
fn fit(runs: &[Run], slip: usize) -> (Vec<f64>, f64) {
    let mut ne = NormalEquations::new(row(&runs[0], slip, 0).len());
    let mut n = 0;
    for r in runs {
        for (k, &y) in r.fit.dx_um.iter().enumerate() {
            ne.add(&row(r, slip, k), y);
            n += 1;
        }
    }
    let (w, sse) = ne.solve(1e-6).expect("fit");
    (w, (sse.max(0.0) / n as f64).sqrt())
}

fn rms(run: &Run, slip: usize, w: &[f64]) -> f64 {
    let s: f64 = (0..run.fit.dx_um.len())
        .map(|k| {
            let y: f64 = row(run, slip, k).iter().zip(w).map(|(a, b)| a * b).sum();
            (run.fit.dx_um[k] - y).powi(2)
        })
        .sum();
    (s / run.fit.dx_um.len() as f64).sqrt()
}

fn env_list(name: &str) -> Vec<String> {
    std::env::var(name)
        .unwrap_or_default()
        .split(',')
        .filter(|s| !s.is_empty())
        .map(str::to_string)
        .collect()
}

fn env_num(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .map_or(default, |v| v.parse().expect("a count"))
}

fn param(name: &str) -> Param {
    Param::named(name).unwrap_or_else(|| panic!("no parameter {name:?}"))
}

fn main() {
    let which = std::env::args().nth(1);
    let plant = match which.as_deref().and_then(|w| w.strip_prefix("drawn:")) {
        Some(n) => hil_sim::generalise::drawn_plant(n.parse().expect("drawn:N")),
        None => hil_sim::generalise::plant_named(which.as_deref())
            .expect("built-in plants")
            .expect("a built-in plant of that name"),
    };
    let defaults = match std::env::var("RO_START_PLANT") {
        Ok(n) => hil_sim::generalise::plant_named(Some(&n))
            .expect("built-in plants")
            .expect("RO_START_PLANT: a built-in plant"),
        Err(_) => plant.clone(),
    };
    let mut physics = BeltPhysics::of(&plant, &defaults);
    for item in env_list("RO_SCALE") {
        let (name, f) = item.split_once('*').expect("RO_SCALE: param*factor");
        physics.scale(param(name), f.parse().expect("RO_SCALE: a factor"));
    }

    let rig = plant.rig();
    let plan = hil_sim::eval::CALIBRATION_PLAN_SEED;
    let scenarios =
        hil_sim::eval::calibration_scenarios(&plant, plan, &[]).expect("calibration scenarios");
    let traces =
        hil_sim::eval::record_calibration(&plant, plan, &[], &mut |_, _| {}).expect("recordings");
    let cal = hil_sim::calibrate::calibrate(&traces, &rig, &mut |_, _| {}).expect("calibration");
    let mut cal_runs: Vec<Run> = traces
        .iter()
        .zip(&scenarios)
        .map(|(t, s)| replay(t, s, &plant, &cal.params, &rig))
        .collect();
    let seed = env_num("RO_SEED", 11) as u64;
    let suffix = format!("-{seed}");
    let probes = hil_sim::generalise::probe_set(&plant, seed).expect("held-out runs");
    let mut runs: Vec<Run> = probes
        .iter()
        .map(|(s, t)| replay(t, s, &plant, &cal.params, &rig))
        .collect();

    physics.capstan_taylor = std::env::var("RO_CAPSTAN_TAYLOR").is_ok();
    // The drive's fixed-point port has the Taylor capstan.
    physics.drive_port = std::env::var("RO_DRIVE_PORT").is_ok();
    physics.capstan_taylor |= physics.drive_port;
    physics.decimation = env_num("RO_DECIMATE", 1).max(1) as u32;
    if std::env::var("RO_GUIDE").is_ok() {
        let fit_runs: Vec<FitRun> = cal_runs.iter().map(|r| r.fit.clone()).collect();
        physics.guide_profile = belt_observer::guide_profile(&fit_runs, &physics);
    }
    let fields: Vec<Param> = env_list("RO_FIT").iter().map(|n| param(n)).collect();
    if !fields.is_empty() {
        let starts: Vec<BeltPhysics> = match env_list("RO_MASS_STARTS") {
            // Each start keeps the guide profile measured above.
            v if v.is_empty() => vec![physics.clone()],
            v => v
                .iter()
                .map(|f| {
                    let mut p = physics.clone();
                    p.scale(Param::Mass, f.parse().expect("RO_MASS_STARTS: factors"));
                    p
                })
                .collect(),
        };
        let fit_runs: Vec<FitRun> = cal_runs.iter().map(|r| r.fit.clone()).collect();
        let found = belt_observer::identify(
            &fit_runs,
            &starts,
            &fields,
            env_num("RO_EVALS", 400),
            env_num("RO_ROUNDS", 2),
        )
        .expect("a start");
        print!(
            "identified: fit {:.2} -> {:.2} um; on the plant's own physics:",
            found.start_rms_um, found.fit_rms_um
        );
        let own = BeltPhysics::of(&plant, &plant);
        for &(p, name) in &Param::ALL {
            print!(" {name} {:.2}", found.physics.value(p) / own.value(p));
        }
        println!();
        physics = found.physics;
    }
    for r in cal_runs.iter_mut().chain(runs.iter_mut()) {
        (r.slip[2], r.slip[3]) = observe(r, &physics);
    }

    print!("observer less true offset, RMS um (the true offset's RMS):");
    let rms_of = |v: &mut dyn Iterator<Item = f64>| {
        let (s, n) = v.fold((0.0, 0usize), |(s, n), d| (s + d * d, n + 1));
        (s / n.max(1) as f64).sqrt()
    };
    for r in &runs {
        let d = rms_of(&mut r.slip[1].iter().zip(&r.slip[2]).map(|(a, b)| b - a));
        let t = rms_of(&mut r.slip[1].iter().copied());
        print!(" {} {d:.1} ({t:.0})", r.name);
    }
    println!();
    // The other estimators on the same runs, as `hil-sim generalise` measures them: the best of
    // Models 1-3 and the baselines, and the floor (the run again with another seed).
    let coeffs = cal.params.build(&rig).expect("calibration builds");
    let others: Vec<(f64, f64)> = probes
        .iter()
        .map(|(s, t)| {
            let est = hil_sim::eval::estimates(t, &coeffs);
            let best = hil_sim::eval::table3(t, &est)
                .into_iter()
                .filter(|(k, _)| !matches!(*k, "none" | "model4"))
                .map(|(_, st)| st.rms_um)
                .fold(f64::INFINITY, f64::min);
            let b = hil_sim::eval::run_in_process(
                s,
                &plant,
                &ModelParams::PAPER,
                estimator_core::model::ModelKind::None,
                2,
                &mut |_| {},
            )
            .expect("second run");
            (best, hil_sim::generalise::floor_um(t, &b))
        })
        .collect();
    print!("best of the other estimators (floor), um:");
    for (r, (best, floor)) in runs.iter().zip(&others) {
        print!(" {} {best:.1} ({floor:.1})", r.name);
    }
    println!();
    for (slip, name) in [
        (0, "slip as built"),
        (1, "true offset"),
        (2, "reduced observer"),
        (3, "its error"),
        (4, "both"),
    ] {
        let (w, fit_rms) = fit(&cal_runs, slip);
        print!("{name:16} fit {fit_rms:5.2} |");
        let (mut generated, mut best, mut near) = (0.0, 0, 0);
        for (r, (other, floor)) in runs.iter().zip(&others) {
            let e = rms(r, slip, &w);
            if r.name.ends_with(&suffix) {
                generated += e * e;
            }
            best += (e < *other) as usize;
            near += (e <= 4.0 * floor) as usize;
            print!(" {} {e:.1}", r.name);
        }
        println!(
            " | generated mean square {:.1} um (weight {:.3}) | best on {best} of {n}, within 4x of the floor on {near}",
            (generated / 6.0).sqrt(),
            w.last().copied().unwrap_or(0.0),
            n = runs.len()
        );
    }
}
