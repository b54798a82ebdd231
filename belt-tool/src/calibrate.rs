//! `beltctl calibrate`: the calibration of `hil-sim calibrate` on a real drive.
//!
//! The same scenarios (`hil_sim::eval::CALIBRATION_SCENARIOS`, fitted to the drive's travel and
//! limits, and `hil-sim`'s default calibration plan drawn across the drive's own range), run as
//! raw motor moves while the drive records every tick; the recordings become
//! `hil_sim::run::Trace`s and are fitted by `hil_sim::calibrate::calibrate`, written by
//! `hil_sim::calfile`, plotted by `hil_sim::plot`; the blob goes to the drive and is read back.

use std::path::{Path, PathBuf};
use std::time::Duration;

use belt_link::{crc32, Command, ModelKind, Reply, Request, CHUNK_MAX};
use estimator_core::drive::{Faults, Output, Polarity, Telemetry, SCALE_COUNTS_PER_UM};
use estimator_core::endpoint::calibration_requests;
use estimator_core::fixed::types::I16F16;
use estimator_core::model::ModelParams;
use estimator_core::rig::Rig;
use estimator_core::settings::Settings;
use estimator_core::units::MotorCounts;
use hil_sim::calibrate::Calibration;
use hil_sim::run::{Record, Trace};
use hil_sim::scenario::{Move, Scenario};

use crate::error::ToolError;
use crate::link::{Link, TickSample};
use crate::ops::{self, MoveLimits};
use hil_sim::progress::Progress;

/// Rest after the last move of a scenario before its recording stops (as `hil-sim` runs end).
const SETTLE: Duration = Duration::from_millis(200);

/// Forward stroke that seats the belt before each recording, mm. The fit starts every recording
/// as after a long forward move, on the forward flanks (the models' start state, and how
/// `hil-sim`'s plant starts); after a stroke the other way the belt creeps across the tooth gap
/// for tens of mm (section 2: the paper rig is within 10 % of the band after about 50 mm,
/// Model 3's transitions close within about 100 mm). Without it the first 50-80 mm of each
/// recording were up to 170 um off every model, and the on-drive fit was 28.4 / 27.0 / 27.5 /
/// 21.4 um (Models 1-4) against 20.3 / 18.6 / 19.9 / 9.6 um in-process on the same plan.
pub(crate) const SEAT_MM: f64 = 100.0;

/// Limits of the seating stroke and of the way from it to a scenario's start: moderate, so that
/// braking swings the belt back little (mm/s, mm/s²; lowered to the drive's limits and caps).
pub(crate) const SEAT_LIMITS: MoveLimits = MoveLimits {
    velocity_mm_s: 50.0,
    accel_mm_s2: 1000.0,
};

/// How a recording starts: the drive's travel and the limits of the moves to the start.
#[derive(Clone, Copy, Debug)]
struct Approach {
    travel_mm: (f64, f64),
    limits: MoveLimits,
}

impl Approach {
    /// The unrecorded moves from `here_mm` before a recording of a scenario that starts at
    /// `start_mm`, and where the recording begins. The last move is a forward stroke of
    /// [`SEAT_MM`] (or the whole travel, if shorter) onto the beginning: the scenario's start,
    /// or that stroke's length above the travel's lower end, and the recording then begins with
    /// the way down to the start.
    fn path(&self, here_mm: f64, start_mm: f64) -> (Vec<f64>, f64) {
        let (lo, hi) = self.travel_mm;
        let seat = SEAT_MM.min(hi - lo);
        let begin = start_mm.max(lo + seat).min(hi);
        let below = (begin - seat).max(lo);
        // Already far enough below (1 um of tolerance): the way up is the seating stroke.
        if here_mm > below + 1e-3 {
            (vec![below, begin], begin)
        } else {
            (vec![begin], begin)
        }
    }
}

/// The travel the calibration scenarios were written for: the paper rig's.
fn scenario_travel_mm() -> (f64, f64) {
    (Settings::PAPER.travel_min_mm, Settings::PAPER.travel_max_mm)
}

/// What the calibration scenarios became on this drive.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The scenarios, positions and limits fitted to the drive.
    pub scenarios: Vec<Scenario>,
    /// Positions were scaled by this factor (1 when the drive's travel holds the scenarios).
    pub position_scale: f64,
    /// Moves whose velocity or acceleration was lowered to the drive's (or `--velocity`,
    /// `--accel`) limits.
    pub clipped_moves: usize,
}

/// `hil-sim`'s calibration scenarios fitted to the drive: positions mapped from the paper's
/// travel onto the drive's (scaled down only where the drive's is shorter), speeds and
/// accelerations clipped to the drive's limits and to the caps given; then `hil-sim`'s default
/// calibration plan drawn across the drive's own range with `plan_seed`; then the user's own
/// scenarios (`user`: each file's path beside it), in the drive's coordinates as written: a
/// target outside the travel is refused by file and move, speeds and accelerations are held
/// to the drive's limits and the caps like the others'.
pub fn plan(
    settings: &Settings,
    velocity_cap: Option<f64>,
    accel_cap: Option<f64>,
    plan_seed: u64,
    user: &[(String, Scenario)],
) -> Result<Plan, ToolError> {
    let (p0, p1) = scenario_travel_mm();
    let (d0, d1) = (settings.travel_min_mm, settings.travel_max_mm);
    // NaN-proof: only a real, non-empty travel passes.
    if d1.partial_cmp(&d0) != Some(std::cmp::Ordering::Greater) {
        return Err(ToolError::Drive(format!(
            "the drive's travel {d0}..{d1} mm is empty (drive.travel_min_mm, drive.travel_max_mm)"
        )));
    }
    let scale = ((d1 - d0) / (p1 - p0)).min(1.0);
    let map = |x: f64| (d0 + (x - p0) * scale).clamp(d0, d1);
    let vmax = velocity_cap.map_or(settings.max_velocity_mm_s, |c| {
        c.min(settings.max_velocity_mm_s)
    });
    let amax = accel_cap.map_or(settings.max_accel_mm_s2, |c| {
        c.min(settings.max_accel_mm_s2)
    });
    let mut clipped = 0;
    // A move to `to_mm` held to the limits and caps, counted when that slows it.
    let mut held = |m: &Move, to_mm: f64| {
        let (v, a) = (m.velocity_mm_s.min(vmax), m.accel_mm_s2.min(amax));
        if v < m.velocity_mm_s || a < m.accel_mm_s2 {
            clipped += 1;
        }
        Move {
            to_mm,
            velocity_mm_s: v,
            accel_mm_s2: a,
            ..m.clone()
        }
    };
    let mut scenarios = Vec::new();
    for name in hil_sim::eval::CALIBRATION_SCENARIOS {
        let s = Scenario::load(name).map_err(|e| ToolError::Drive(e.to_string()))?;
        let moves = s.moves.iter().map(|m| held(m, map(m.to_mm))).collect();
        scenarios.push(Scenario {
            start_mm: map(s.start_mm),
            moves,
            ..s
        });
    }
    // The default plan of `hil-sim calibrate` across the drive's own range (travel, speed and
    // acceleration up to the caps): short and long strokes, slow feeds to the fastest moves,
    // reversals in mid-motion, both travel ends. Without it the fit saw only the paper's three
    // scenarios, at their speeds.
    let lim = hil_sim::workloads::Limits {
        travel_min_mm: d0,
        travel_max_mm: d1,
        max_velocity_mm_s: vmax,
        max_accel_mm_s2: amax,
    };
    scenarios.push(hil_sim::workloads::calibration_plan(
        &lim,
        plan_seed,
        hil_sim::eval::CALIBRATION_PLAN_S,
    ));
    for (path, s) in user {
        ops::within_travel(path, s, (d0, d1))?;
        let moves = s.moves.iter().map(|m| held(m, m.to_mm)).collect();
        scenarios.push(Scenario { moves, ..s.clone() });
    }
    Ok(Plan {
        scenarios,
        position_scale: scale,
        clipped_moves: clipped,
    })
}

/// A recording as a `hil-sim` trace: time from the recording's first tick, the scale in
/// millimetres, the commanded direction held at rest, the current in the drive's own frame
/// (positive pushes towards positive travel), which is what Model 4's current term sees: the
/// drive records its amplifier command, which `polarity` maps back to the drive's frame.
pub fn to_trace(
    name: &str,
    samples: &[TickSample],
    rate_hz: f64,
    rig: &Rig,
    move_ticks: &[u32],
    polarity: &Polarity,
) -> Trace {
    let t0 = samples.first().map_or(0, |s| s.tick);
    let mut cmd_dir: i8 = 1;
    let mut last_sp: Option<MotorCounts> = None;
    let records = samples
        .iter()
        .map(|s| {
            let r = &s.sample;
            let moving = last_sp.is_some_and(|sp| sp != r.setpoint_counts);
            if let Some(sp) = last_sp {
                if r.setpoint_counts != sp {
                    cmd_dir = if r.setpoint_counts > sp { 1 } else { -1 };
                }
            }
            last_sp = Some(r.setpoint_counts);
            let command_a = I16F16::saturating_from_num(r.current_ma as f64 / 1000.0);
            let current_a = polarity.current_frame(command_a);
            Record {
                t_s: s.tick.wrapping_sub(t0) as f64 / rate_hz,
                motor_counts: r.motor_counts,
                x_ls_mm: r.scale_counts.0 as f64 / (SCALE_COUNTS_PER_UM as f64 * 1000.0),
                setpoint_counts: r.setpoint_counts,
                cmd_dir,
                out: Output {
                    current_a,
                    telemetry: Telemetry {
                        tick: s.tick,
                        motor_counts: r.motor_counts,
                        scale_counts: r.scale_counts,
                        setpoint_counts: r.setpoint_counts,
                        following_error_counts: MotorCounts(
                            r.setpoint_counts.0.wrapping_sub(r.motor_counts.0),
                        ),
                        current_a,
                        faults: Faults::NONE,
                        moving,
                        amplifier_enabled: true,
                        homed: true,
                        ..Telemetry::default()
                    },
                },
            }
        })
        .collect();
    let move_starts = move_ticks
        .iter()
        .map(|&t| samples.partition_point(|s| s.tick.wrapping_sub(t0) < t.wrapping_sub(t0)))
        .collect();
    Trace {
        scenario: name.to_string(),
        seed: 0,
        counts_per_mm: rig.counts_per_mm(),
        records,
        move_starts,
    }
}

/// Fails unless the scale followed the motor over the recording: calibration needs it fitted,
/// connected and counting the right way.
pub fn check_scale(trace: &Trace) -> Result<(), ToolError> {
    let r = &trace.records;
    let (Some(lo), Some(hi)) = (
        (0..r.len()).min_by_key(|&i| r[i].motor_counts),
        (0..r.len()).max_by_key(|&i| r[i].motor_counts),
    ) else {
        return Err(ToolError::Drive("the recording is empty".into()));
    };
    let motor_mm = trace.x_pe_mm(hi) - trace.x_pe_mm(lo);
    let scale_mm = r[hi].x_ls_mm - r[lo].x_ls_mm;
    if motor_mm < 1.0 {
        return Err(ToolError::Drive(format!(
            "the motor moved only {motor_mm:.3} mm during {}: calibration needs the moves",
            trace.scenario
        )));
    }
    let ratio = scale_mm / motor_mm;
    if ratio < -0.5 {
        return Err(ToolError::Drive(format!(
            "the linear scale counts backwards (motor +{motor_mm:.1} mm, scale {scale_mm:.1} \
             mm): set polarity.scale_inverted"
        )));
    }
    if !(0.5..=2.0).contains(&ratio) {
        return Err(ToolError::Drive(format!(
            "the linear scale does not follow the motor (motor {motor_mm:.1} mm, scale \
             {scale_mm:.3} mm): calibration needs the linear scale fitted and connected"
        )));
    }
    Ok(())
}

/// Runs one scenario's moves as raw motor moves while recording every tick; returns the
/// recording and the ticks at which each move was commanded.
fn run_scenario(
    link: &mut Link,
    s: &Scenario,
    approach: &Approach,
    progress: &mut Progress,
) -> Result<(Vec<TickSample>, Vec<u32>), ToolError> {
    let label = format!("record {}", s.name);
    // Unrecorded: a forward stroke of SEAT_MM onto where the recording starts, then rest, as a
    // hil-sim run starts at rest on the forward flanks.
    let go = |link: &mut Link, from_mm: f64, to_mm: f64| -> Result<(), ToolError> {
        let cmd = ops::move_command(ops::target_um(to_mm)?, &approach.limits, true)?;
        ops::move_and_wait(link, cmd, to_mm - from_mm, &approach.limits, |_| Ok(()))?;
        Ok(())
    };
    let mut here = link.status()?.carriage_estimate_um as f64 / 1000.0;
    let (path, begin) = approach.path(here, s.start_mm);
    for to in path {
        go(link, here, to)?;
        here = to;
    }
    ops::dwell(link, Duration::from_millis(300))?;

    link.start_recording(1)?;
    let mut samples = Vec::new();
    let mut move_ticks = Vec::with_capacity(s.moves.len());
    let result = (|| {
        if begin != s.start_mm {
            // Recorded: the way down to the start is part of the data the fit sees.
            go(link, begin, s.start_mm)?;
            ops::dwell(link, Duration::from_millis(300))?;
        }
        for (i, m) in s.moves.iter().enumerate() {
            progress.stage(&label, i as f64 / s.moves.len() as f64);
            let limits = MoveLimits {
                velocity_mm_s: m.velocity_mm_s,
                accel_mm_s2: m.accel_mm_s2,
            };
            let now = link.status()?;
            move_ticks.push(now.tick);
            let cmd = ops::move_command(ops::target_um(m.to_mm)?, &limits, true)?;
            match m.retarget_after_ms {
                Some(ms) => {
                    link.command(cmd)?;
                    // Polled: a wait of 0.5 s or more would trip the drive's link watchdog.
                    ops::dwell(link, Duration::from_millis(ms as u64))?;
                }
                None => {
                    // The time budget from where the drive is (a cut move left it short).
                    let here_mm = now.carriage_estimate_um as f64 / 1000.0;
                    ops::move_and_wait(link, cmd, m.to_mm - here_mm, &limits, |_| Ok(()))?;
                    ops::dwell(link, Duration::from_millis(m.dwell_ms as u64))?;
                }
            }
            samples.extend(link.take_samples());
        }
        ops::dwell(link, SETTLE)
    })();
    progress.stage(&label, 1.0);
    let stopped = link.stop_recording();
    result?;
    let (rest, stats) = stopped?;
    samples.extend(rest);
    stats.check()?;
    Ok((samples, move_ticks))
}

/// Uploads a calibration blob: begin, chunks, commit. A transfer broken by the link (a lost
/// reply makes the drive see a chunk twice) starts over, up to the link's tries.
pub fn upload(link: &mut Link, blob: &[u8]) -> Result<(), ToolError> {
    use estimator_core::endpoint::cal_error;
    let tries = link.options().tries;
    let mut last = None;
    for _ in 0..tries {
        match upload_once(link, blob) {
            Ok(()) => return Ok(()),
            Err(
                e @ ToolError::Refused {
                    reason: belt_link::LinkError::Calibration,
                    detail,
                    ..
                },
            ) if detail & cal_error::REJECTED == 0
                && detail != cal_error::TOO_LONG
                && detail != cal_error::ENABLED =>
            {
                last = Some(e)
            }
            Err(e @ (ToolError::Timeout { .. } | ToolError::Damaged { .. })) => last = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(last.unwrap_or_else(|| ToolError::Drive("calibration upload failed".into())))
}

fn upload_once(link: &mut Link, blob: &[u8]) -> Result<(), ToolError> {
    for req in calibration_requests(blob) {
        link.acked(&req)?;
    }
    Ok(())
}

/// Reads the installed calibration blob back (`CalRead`); `expected_len` is what was uploaded.
pub fn read_back(link: &mut Link, expected_len: usize) -> Result<Vec<u8>, ToolError> {
    let mut out = Vec::with_capacity(expected_len);
    while out.len() < expected_len {
        let req = Request::CalRead {
            offset: out.len() as u32,
        };
        match link.call(&req)? {
            Reply::CalData {
                total_len,
                len,
                data,
                ..
            } => {
                if total_len as usize != expected_len {
                    return Err(ToolError::Drive(format!(
                        "the drive holds a calibration of {total_len} bytes, not the \
                         {expected_len} uploaded"
                    )));
                }
                if len == 0 {
                    return Err(link.unexpected(
                        &req,
                        &Reply::CalData {
                            offset: out.len() as u32,
                            total_len,
                            len,
                            data,
                        },
                    ));
                }
                let n = (len as usize).min(CHUNK_MAX).min(expected_len - out.len());
                out.extend_from_slice(&data[..n]);
            }
            other => return Err(link.unexpected(&req, &other)),
        }
    }
    Ok(out)
}

/// Options of `beltctl calibrate`.
#[derive(Clone, Debug)]
pub struct Options {
    /// Directory for the calibration files and plots.
    pub out: PathBuf,
    /// Cap on the moves' speed, mm/s.
    pub velocity_cap: Option<f64>,
    /// Cap on the moves' acceleration, mm/s².
    pub accel_cap: Option<f64>,
    /// Seed of the default calibration plan (`hil_sim::eval::CALIBRATION_PLAN_SEED` unless
    /// the user draws another).
    pub plan_seed: u64,
    /// The user's own scenarios, each with its file, recorded after the default set.
    pub scenarios: Vec<(String, Scenario)>,
    /// Model to select after the upload.
    pub model: ModelKind,
    /// Save configuration and calibration in the drive's storage afterwards.
    pub save: bool,
    /// The machine's geometry and motor (a plant file and its path) for Model 4's belt
    /// observer; none: the slip observer only.
    pub machine: Option<(PathBuf, hil_sim::PlantParams)>,
}

/// What a calibration produced.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// The fit.
    pub calibration: Calibration,
    /// CRC-32 of the uploaded blob.
    pub blob_crc: u32,
    /// Its length, bytes.
    pub blob_len: usize,
    /// The stored record's CRC, with `--save`.
    pub saved_crc: Option<u32>,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Plot files that could not be drawn, and why (no font, ...).
    pub plot_warnings: Vec<String>,
    /// The plan that ran.
    pub plan: Plan,
}

/// The whole calibration on the drive behind `link`.
pub fn run(link: &mut Link, opts: &Options, progress: &mut Progress) -> Result<Outcome, ToolError> {
    // Before any move: a calibration takes minutes of them.
    hil_sim::calfile::check_writable(&opts.out).map_err(|e| {
        ToolError::Usage(format!(
            "--out {}: cannot be written ({e})",
            opts.out.display()
        ))
    })?;
    let status = link.status()?;
    ops::require_ready(&status, "calibration")?;
    let settings = crate::config::settings(link)?;
    let rig = settings.rig;
    // Before any move: the machine file must describe this drive's geometry.
    let belt_start = match &opts.machine {
        Some((path, m)) if !m.rig().same_bits(&rig) => {
            return Err(ToolError::Usage(format!(
                "--machine {}: its geometry {:?} is not the drive's {:?}",
                path.display(),
                m.rig(),
                rig
            )))
        }
        // The identification steps the observer at hil-sim's 2 kHz tick.
        Some((path, _)) if settings.rate_hz != 1.0 / hil_sim::belt_observer::TICK_S => {
            return Err(ToolError::Usage(format!(
                "--machine {}: Model 4's belt observer is identified at {} Hz, this drive runs at \
                 {} Hz (drive.rate_hz); calibrate without --machine for the slip observer",
                path.display(),
                1.0 / hil_sim::belt_observer::TICK_S,
                settings.rate_hz
            )))
        }
        Some((_, m)) => Some(hil_sim::belt_observer::BeltPhysics::identification_start(m)),
        None => None,
    };
    let plan = plan(
        &settings,
        opts.velocity_cap,
        opts.accel_cap,
        opts.plan_seed,
        &opts.scenarios,
    )?;
    if plan.position_scale < 1.0 {
        progress.println(&format!(
            "beltctl: the drive's travel is shorter than the scenarios': positions scaled by {:.3}",
            plan.position_scale
        ));
    }
    if plan.clipped_moves > 0 {
        progress.println(&format!(
            "beltctl: {} moves slowed to the drive's limits or the caps given",
            plan.clipped_moves
        ));
    }

    let cap = |limit: f64, cap: Option<f64>| cap.map_or(limit, |c| c.min(limit));
    let approach = Approach {
        travel_mm: (settings.travel_min_mm, settings.travel_max_mm),
        limits: MoveLimits {
            velocity_mm_s: SEAT_LIMITS
                .velocity_mm_s
                .min(cap(settings.max_velocity_mm_s, opts.velocity_cap)),
            accel_mm_s2: SEAT_LIMITS
                .accel_mm_s2
                .min(cap(settings.max_accel_mm_s2, opts.accel_cap)),
        },
    };
    let mut traces = Vec::new();
    for s in &plan.scenarios {
        let (samples, move_ticks) = match run_scenario(link, s, &approach, progress) {
            Ok(r) => r,
            Err(e) => {
                let _ = link.command(Command::Stop);
                return Err(e);
            }
        };
        let t = to_trace(
            &s.name,
            &samples,
            settings.rate_hz,
            &rig,
            &move_ticks,
            &settings.polarity,
        );
        check_scale(&t)?;
        traces.push(t);
    }

    // The fit takes seconds to minutes on the host, silent on the link: the drive rests
    // disabled meanwhile (still homed), not enabled until its link watchdog trips. The upload
    // needs it disabled too: the drive stages the image in flash, whose erase stalls its CPU.
    link.command(Command::Disable)?;
    progress.println(
        "beltctl: disabled the drive for the fit and the upload (the drive stages the calibration \
         in flash); enable it to move again",
    );
    let mut cal =
        hil_sim::calibrate::calibrate_with(&traces, &rig, belt_start.as_ref(), &mut |s, f| {
            progress.stage(s, f)
        })?;
    // What the moves covered: calibration.toml keeps it, `hil-sim` warns by it.
    let coverage = hil_sim::coverage::Coverage::of(&plan.scenarios);
    progress.println(&coverage.markdown());
    // Caps below the drive's limits leave its fastest moves uncalibrated: say so now.
    for w in coverage.short_of(settings.max_velocity_mm_s, settings.max_accel_mm_s2) {
        progress.println(&format!("beltctl: warning: {w}"));
    }
    cal.coverage = Some(coverage);

    hil_sim::calfile::save(&opts.out, &cal, &rig)?;
    let mut files = vec![
        opts.out.join("calibration.bin"),
        opts.out.join("calibration.toml"),
    ];
    let mut plot_warnings = Vec::new();
    plots(
        &opts.out,
        &traces,
        &cal.params,
        &rig,
        &mut files,
        &mut plot_warnings,
    );

    // The drive loads the coefficients, built here: no floating point on its side.
    let image = estimator_core::image::of_params(&cal.params, &rig)
        .map_err(|e| ToolError::Drive(format!("calibration image: {e}")))?;
    let blob = &image[..];
    progress.stage("upload calibration", 0.0);
    upload(link, blob)?;
    progress.stage("verify calibration", 0.5);
    let back = read_back(link, blob.len())?;
    if let Some(i) = (0..blob.len()).find(|&i| back[i] != blob[i]) {
        return Err(ToolError::Drive(format!(
            "calibration read-back differs from the upload at byte {i} of {}",
            blob.len()
        )));
    }
    progress.finish();
    link.command(Command::SelectModel(opts.model))?;
    let saved_crc = if opts.save {
        // Disabled since the fit: the drive saves only while disabled.
        Some(save(link)?.1)
    } else {
        None
    };
    Ok(Outcome {
        calibration: cal,
        blob_crc: crc32(blob),
        blob_len: blob.len(),
        saved_crc,
        files,
        plot_warnings,
        plan,
    })
}

/// `Request::Save`: the stored record's sequence number and CRC.
pub fn save(link: &mut Link) -> Result<(u32, u32), ToolError> {
    match link.call(&Request::Save)? {
        Reply::Saved { seq, crc32 } => Ok((seq, crc32)),
        other => Err(link.unexpected(&Request::Save, &other)),
    }
}

/// The figures: Delta x against x_PE over every recording (Fig. 11), and Models 1 and 3 along
/// the reversals recording (Figs. 19-24 style). A figure that cannot be drawn is a warning.
fn plots(
    dir: &Path,
    traces: &[Trace],
    params: &ModelParams,
    rig: &Rig,
    files: &mut Vec<PathBuf>,
    warnings: &mut Vec<String>,
) {
    let mut attempt = |path: PathBuf, r: Result<(), Box<dyn std::error::Error>>| match r {
        Ok(()) => files.push(path),
        Err(e) => warnings.push(format!("{}: {e}", path.display())),
    };
    let p = dir.join("hysteresis.png");
    let r = hil_sim::plot::hysteresis(&p, "x_LS - x_PE against x_PE (calibration moves)", traces);
    attempt(p, r);
    let coeffs = match params.build(rig) {
        Ok(c) => c,
        Err(e) => {
            warnings.push(format!("model plots: {e}"));
            return;
        }
    };
    let Some(t) = traces
        .iter()
        .find(|t| t.scenario == "reversals")
        .or(traces.first())
    else {
        return;
    };
    let est = hil_sim::eval::estimates(t, &coeffs);
    let ys: Vec<&[f64]> = est.iter().map(|(_, y)| y.as_slice()).collect();
    let scales = hil_sim::plot::estimate_scales(t, &ys);
    for (name, title) in [("model1", "Model 1"), ("model3", "Model 3")] {
        if let Some((_, y)) = est.iter().find(|(n, _)| *n == name) {
            let p = dir.join(format!("{}_{name}.png", t.scenario));
            let r = hil_sim::plot::estimate(
                &p,
                &format!("{title} along the {} recording", t.scenario),
                t,
                y,
                scales,
            );
            attempt(p, r);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use belt_link::{RecordSample, ScaleCounts};

    #[test]
    fn the_plan_fits_the_drive() {
        let seed = hil_sim::eval::CALIBRATION_PLAN_SEED;
        let same = plan(&Settings::PAPER, None, None, seed, &[]).unwrap();
        assert_eq!(same.position_scale, 1.0);
        assert_eq!(same.clipped_moves, 0);
        let names: Vec<_> = same.scenarios.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names[..3], *hil_sim::eval::CALIBRATION_SCENARIOS);
        assert!(names[3].starts_with("calibration-plan"), "{names:?}");
        // Another seed draws other moves over the same drive.
        let other = plan(&Settings::PAPER, None, None, seed + 1, &[]).unwrap();
        for (a, b) in other.scenarios.iter().zip(&same.scenarios).take(3) {
            assert_eq!(a.moves, b.moves);
        }
        assert_ne!(other.scenarios[3].moves, same.scenarios[3].moves);
        for s in &same.scenarios[..3] {
            let orig = Scenario::load(&s.name).unwrap();
            assert_eq!(s.moves, orig.moves);
        }

        let mut short = Settings::PAPER;
        short.travel_max_mm = 150.0;
        short.max_velocity_mm_s = 30.0;
        let p = plan(&short, None, Some(600.0), seed, &[]).unwrap();
        assert_eq!(p.position_scale, 0.5);
        assert!(p.clipped_moves > 0);
        for s in &p.scenarios {
            assert!((0.0..=150.0).contains(&s.start_mm));
            for m in &s.moves {
                assert!((0.0..=150.0).contains(&m.to_mm), "{}", m.to_mm);
                assert!(m.velocity_mm_s <= 30.0 && m.accel_mm_s2 <= 600.0);
            }
            // Every move still fits the drive's own checks.
            let drive =
                short.drive_config(estimator_core::drive::Models::Params(&ModelParams::PAPER));
            let d = estimator_core::drive::Drive::new(&drive).unwrap();
            for m in &s.moves {
                let (t, v, a) = m.drive_units();
                d.check_move(t, v, a).unwrap();
            }
        }
    }

    /// Caps and drive limits below the plan's own floors (0.5 mm/s, 10 mm/s²) hold every move
    /// under them; they once made the plan panic (`clamp` with its floor above its limit).
    #[test]
    fn caps_below_the_plan_s_floors_hold_every_move() {
        let seed = hil_sim::eval::CALIBRATION_PLAN_SEED;
        let mut slow = Settings::PAPER;
        slow.max_velocity_mm_s = 0.45;
        for (settings, v_cap, a_cap, v_max, a_max) in [
            (Settings::PAPER, Some(0.3), Some(5.0), 0.3, 5.0),
            (slow, None, None, 0.45, slow.max_accel_mm_s2),
        ] {
            let p = plan(&settings, v_cap, a_cap, seed, &[]).unwrap();
            assert!(p.clipped_moves > 0);
            for m in p.scenarios.iter().flat_map(|s| &s.moves) {
                assert!(m.velocity_mm_s > 0.0 && m.velocity_mm_s <= v_max, "{m:?}");
                assert!(m.accel_mm_s2 > 0.0 && m.accel_mm_s2 <= a_max, "{m:?}");
            }
        }
    }

    /// The user's scenarios follow the default set in the drive's own coordinates, held to
    /// the caps; one that leaves the travel is refused by file and move.
    #[test]
    fn user_scenarios_follow_the_default_set_or_are_refused_by_name() {
        let seed = hil_sim::eval::CALIBRATION_PLAN_SEED;
        let mine = Scenario::from_toml_str(
            "name = \"mine\"\nstart_mm = 20.0\n[[move]]\nto_mm = 40.0\nvelocity_mm_s = 200.0\n\
             accel_mm_s2 = 4000.0\n[[move]]\nto_mm = 21.0\nvelocity_mm_s = 5.0\n\
             accel_mm_s2 = 300.0\n",
        )
        .unwrap();
        let user = vec![("mine.toml".to_string(), mine.clone())];
        let base = plan(&Settings::PAPER, None, Some(1000.0), seed, &[]).unwrap();
        let p = plan(&Settings::PAPER, None, Some(1000.0), seed, &user).unwrap();
        assert_eq!(p.scenarios.len(), base.scenarios.len() + 1);
        let last = p.scenarios.last().unwrap();
        assert_eq!(last.name, "mine");
        assert_eq!((last.start_mm, last.moves[0].to_mm), (20.0, 40.0));
        assert_eq!(last.moves[0].accel_mm_s2, 1000.0);
        assert_eq!(last.moves[1], mine.moves[1]);
        assert_eq!(p.clipped_moves, base.clipped_moves + 1);

        let mut far = mine.clone();
        far.moves[1].to_mm = 900.0;
        let e = plan(
            &Settings::PAPER,
            None,
            None,
            seed,
            &[("far.toml".into(), far)],
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("far.toml: move 2: to_mm = 900"), "{e}");
    }

    /// Every recording starts after a forward stroke of SEAT_MM (or the whole travel) onto its
    /// beginning, within the travel, at or above the scenario's start.
    #[test]
    fn every_recording_starts_seated_forward() {
        for travel_mm in [(0.0, 250.0), (0.0, 60.0), (-10.0, 400.0)] {
            let a = Approach {
                travel_mm,
                limits: SEAT_LIMITS,
            };
            let (lo, hi) = travel_mm;
            let seat = SEAT_MM.min(hi - lo);
            for i in 0..=20 {
                for j in 0..=20 {
                    let here = lo + (hi - lo) * i as f64 / 20.0;
                    let start = lo + (hi - lo) * j as f64 / 20.0;
                    let (path, begin) = a.path(here, start);
                    let from = if path.len() > 1 {
                        path[path.len() - 2]
                    } else {
                        here
                    };
                    assert_eq!(path.last(), Some(&begin));
                    assert!(
                        begin - from >= seat - 1e-3,
                        "{travel_mm:?} {here} {start}: {path:?}"
                    );
                    assert!(
                        begin >= start && begin <= hi,
                        "{travel_mm:?} {start}: {begin}"
                    );
                    assert!(path.iter().all(|&p| (lo..=hi).contains(&p)), "{path:?}");
                }
            }
        }
    }

    /// A retarget's wait polls the drive: a wait of 0.5 s or more without a request would trip
    /// its link watchdog (faults.link_timeout_s) in the middle of a recording.
    #[test]
    fn a_retarget_s_wait_keeps_the_drive_s_link_watchdog_fed() {
        use belt_link::{status_flags, Message, WireStatus};
        use std::sync::{Arc, Mutex};
        use std::time::Instant;
        let times = Arc::new(Mutex::new(Vec::<Instant>::new()));
        let seen = times.clone();
        let mut at_um = 20_000;
        let mut link = crate::testing::Fake::link(move |seq, req| {
            seen.lock().unwrap().push(Instant::now());
            let reply = match req {
                Request::Status => Reply::Status(WireStatus {
                    flags: status_flags::ENABLED | status_flags::HOMED,
                    carriage_estimate_um: at_um,
                    ..WireStatus::default()
                }),
                Request::Command(Command::MoveMotorTo { target_um, .. })
                | Request::Command(Command::MoveTo { target_um, .. }) => {
                    at_um = target_um;
                    Reply::Ack { of: req.kind() }
                }
                _ => Reply::Ack { of: req.kind() },
            };
            crate::testing::wire(seq, &reply)
        });
        let s = Scenario::from_toml_str(
            "name = \"cut\"\nstart_mm = 20.0\n[[move]]\nto_mm = 120.0\nvelocity_mm_s = 20.0\n\
             accel_mm_s2 = 500.0\nretarget_after_ms = 1200\n[[move]]\nto_mm = 30.0\n\
             velocity_mm_s = 20.0\naccel_mm_s2 = 500.0\n",
        )
        .unwrap();
        let approach = Approach {
            travel_mm: (0.0, 250.0),
            limits: SEAT_LIMITS,
        };
        let mut progress = Progress::named("test");
        let begin = Instant::now();
        run_scenario(&mut link, &s, &approach, &mut progress).unwrap();
        let times = times.lock().unwrap();
        let gap = times
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or_default();
        assert!(gap < Duration::from_millis(300), "{gap:?}");
        assert!(begin.elapsed() > Duration::from_millis(1200));
    }

    #[test]
    fn recordings_become_traces() {
        let rig = Rig::PAPER;
        let sp = [0, 0, 5, 9, 9, 9, 4, 4];
        let samples: Vec<TickSample> = sp
            .iter()
            .enumerate()
            .map(|(i, &s)| TickSample {
                tick: 1000 + 2 * i as u32,
                sample: RecordSample {
                    motor_counts: MotorCounts(s),
                    scale_counts: ScaleCounts(2000 * i as i32),
                    setpoint_counts: MotorCounts(s),
                    current_ma: -1500,
                },
            })
            .collect();
        let t = to_trace(
            "x",
            &samples,
            2000.0,
            &rig,
            &[1003, 1010],
            &Polarity::NORMAL,
        );
        let dirs: Vec<i8> = t.records.iter().map(|r| r.cmd_dir).collect();
        assert_eq!(dirs, [1, 1, 1, 1, 1, 1, -1, -1]);
        assert_eq!(t.records[3].t_s, 0.003);
        assert_eq!(t.records[2].x_ls_mm, 2.0);
        assert_eq!(t.records[0].out.current_a, I16F16::from_num(-1.5));
        assert_eq!(t.move_starts, [2, 5]);
        // Inverted amplifier wiring: the recorded command is the drive's current negated.
        let inverted = Polarity {
            current_inverted: true,
            ..Polarity::NORMAL
        };
        let inv = to_trace("x", &samples, 2000.0, &rig, &[1003, 1010], &inverted);
        assert_eq!(inv.records[0].out.current_a, I16F16::from_num(1.5));
        assert_eq!(
            inv.records[0].out.telemetry.current_a,
            I16F16::from_num(1.5)
        );
        assert_eq!(t.counts_per_mm, rig.counts_per_mm());
    }

    #[test]
    fn the_scale_must_follow_the_motor() {
        let rig = Rig::PAPER;
        let trace = |scale_per_count: f64| {
            let samples: Vec<TickSample> = (0..100)
                .map(|i| TickSample {
                    tick: i,
                    sample: RecordSample {
                        motor_counts: MotorCounts(i as i32 * 100),
                        scale_counts: ScaleCounts((i as f64 * 100.0 * scale_per_count) as i32),
                        setpoint_counts: MotorCounts(0),
                        current_ma: 0,
                    },
                })
                .collect();
            to_trace("s", &samples, 2000.0, &rig, &[], &Polarity::NORMAL)
        };
        // 2000 scale counts per mm, 1867.9 motor counts per mm.
        let right = 2000.0 / rig.counts_per_mm();
        check_scale(&trace(right)).unwrap();
        let e = check_scale(&trace(-right)).unwrap_err().to_string();
        assert!(e.contains("polarity.scale_inverted"), "{e}");
        let e = check_scale(&trace(0.0)).unwrap_err().to_string();
        assert!(e.contains("linear scale fitted"), "{e}");
    }

    fn paper_image() -> Vec<u8> {
        estimator_core::image::of_params(&ModelParams::PAPER, &Rig::PAPER).unwrap()
    }

    #[test]
    fn a_blob_uploads_to_the_drive_endpoint_and_reads_back() {
        let blob = paper_image();
        let mut link = crate::testing::endpoint_drive(|_| false);
        upload(&mut link, &blob).unwrap();
        assert_eq!(read_back(&mut link, blob.len()).unwrap(), blob);
        link.command(Command::SelectModel(ModelKind::Table))
            .unwrap();
    }

    #[test]
    fn a_lost_chunk_ack_restarts_the_transfer() {
        let blob = paper_image();
        let mut lost = false;
        // The drive takes chunk 2 but its ack is lost: the retry is refused as out of order.
        let mut link = crate::testing::endpoint_drive(move |req| {
            let hit =
                matches!(req, Request::CalChunk { offset, .. } if *offset == 2 * CHUNK_MAX as u32);
            hit && !std::mem::replace(&mut lost, true)
        });
        upload(&mut link, &blob).unwrap();
        assert_eq!(read_back(&mut link, blob.len()).unwrap(), blob);
        assert!(link.stats().resent >= 1);
    }

    #[test]
    fn a_rejected_blob_is_not_retried() {
        let mut blob = paper_image();
        blob[0] ^= 0xff; // bad magic
        let mut link = crate::testing::endpoint_drive(|_| false);
        let e = upload(&mut link, &blob).unwrap_err().to_string();
        assert!(e.contains("bad magic"), "{e}");
    }

    #[test]
    fn an_upload_to_an_enabled_drive_is_refused_by_name_once() {
        let blob = paper_image();
        let begins = std::sync::Arc::new(std::sync::atomic::AtomicU32::new(0));
        let seen = std::sync::Arc::clone(&begins);
        let mut link = crate::testing::endpoint_drive(move |req| {
            if matches!(req, Request::CalBegin { .. }) {
                seen.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
            false
        });
        link.command(Command::Enable).unwrap();
        let e = upload(&mut link, &blob).unwrap_err().to_string();
        assert!(e.contains("needs the drive disabled"), "{e}");
        assert_eq!(begins.load(std::sync::atomic::Ordering::Relaxed), 1);
        link.command(Command::Disable).unwrap();
        upload(&mut link, &blob).unwrap();
    }

    #[test]
    fn a_recorded_run_becomes_the_simulators_trace() {
        // What the drive records of a simulated calibration run, turned back into a trace, is
        // the trace hil-sim fits: every field the fit reads, bit for bit.
        let plant = hil_sim::plant::PlantParams::paper_rig();
        let scenario = Scenario::load("reversals").unwrap();
        let sim = hil_sim::eval::run_in_process(
            &scenario,
            &plant,
            &ModelParams::PAPER,
            ModelKind::None,
            1,
            &mut |_| {},
        )
        .unwrap();
        let samples: Vec<TickSample> = sim
            .records
            .iter()
            .map(|r| TickSample {
                tick: r.out.telemetry.tick,
                sample: RecordSample {
                    motor_counts: r.motor_counts,
                    scale_counts: ScaleCounts((r.x_ls_mm * 2000.0).round() as i32),
                    setpoint_counts: r.setpoint_counts,
                    current_ma: (r.out.current_a.to_num::<f64>() * 1000.0).round() as i16,
                },
            })
            .collect();
        let ticks: Vec<u32> = sim
            .move_starts
            .iter()
            .map(|&i| sim.records[i].out.telemetry.tick)
            .collect();
        let t = to_trace(
            "reversals",
            &samples,
            2000.0,
            &plant.rig(),
            &ticks,
            &Polarity::NORMAL,
        );
        assert_eq!(t.records.len(), sim.records.len());
        assert_eq!(t.counts_per_mm, sim.counts_per_mm);
        assert_eq!(t.move_starts, sim.move_starts);
        for (i, (a, b)) in t.records.iter().zip(&sim.records).enumerate() {
            assert_eq!(a.motor_counts, b.motor_counts, "{i}");
            assert_eq!(a.x_ls_mm.to_bits(), b.x_ls_mm.to_bits(), "{i}");
            assert_eq!(a.cmd_dir, b.cmd_dir, "{i}");
            assert!((a.t_s - b.t_s).abs() < 1e-9, "{i}");
        }
        check_scale(&t).unwrap();
    }
}
