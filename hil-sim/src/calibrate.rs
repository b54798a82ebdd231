//! Calibration from recorded (x_PE, x_LS) samples only, never from the plant's parameters, the way
//! the paper does it (section 6):
//! 1. Delta x = x_LS - x_PE, low-pass filtered (a centred moving average that removes the scale's
//!    quantisation and noise but keeps the fast transition after a reversal);
//! 2. a straight-line start for the band (slope m, offset c, height h) from approached samples;
//! 3. least-squares fits of Model 1 (m, c, h, h_g, a, b) and Model 2 (m, c, h, h_g, a, b, A, B),
//!    each simulated along the recorded motor positions with the drive's own reversal rule
//!    (f64 reference models, Nelder-Mead on the sum of squares);
//! 4. Model 3: band tables = Model 1's edges plus the mean residual of settled samples per bin of
//!    one belt pitch (which averages the tooth ripple out, as the paper's filter did), and 2-D
//!    transition tables fitted by regularised least squares (see [`crate::tables`]), with the jump
//!    h_g of the linear model at the reversal (the paper: Model 3's parameters "are inherited
//!    from those of the linear model");
//! 5. the two baselines of today's controllers from the same data.

use estimator_core::blob::{self, BlobError};
use estimator_core::model::belt::TRACK_DISCOUNTS;
use estimator_core::model::operator::{N_KNOTS, N_OPS};
use estimator_core::model::slip::{SlipParams, MAX_SLIP_UM};
use estimator_core::model::{
    BandParams, BeltTerm, Model1Params, Model2Params, Model3Params, Model4Params, ModelKind,
    ModelParams, TransitionParams, MAX_BAND_POINTS, MAX_TRANSITION_D, MAX_TRANSITION_G0,
};
use estimator_core::reference::{Model4Terms, RefSlip, Reference};
use estimator_core::rig::Rig;
use estimator_core::ConfigError;

use crate::baseline::{Backlash, BidirTable};
use crate::belt_observer::{self, BeltPhysics, FitRun, Param};
use crate::fit::nelder_mead;
use crate::run::Trace;
use crate::tables::{fit_gap_table, strokes, GapSample};

/// Reversal dead bands tried by the calibration (counts; 1 count = 0.535 um on the paper's rig).
pub const DEADBAND_CANDIDATES_COUNTS: [u32; 7] = [2, 8, 24, 48, 96, 160, 240];

/// Smoothing weights tried for Model 3's transition tables.
pub const SMOOTHING_CANDIDATES: [f64; 6] = [0.1, 1.0, 10.0, 100.0, 1e3, 1e4];

/// Half-width of the centred moving average applied to Delta x, in ticks (5 ms at 2 kHz).
pub const FILTER_HALF_WIDTH: usize = 5;

/// Why the recordings could not be turned into a parameter set. Each names what the data lacks
/// or which fit failed, so that a machine builder knows which motions to add.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// No recording holds a sample.
    #[error("no calibration samples")]
    NoSamples,
    /// The recordings cover too little travel for the band tables and harmonics.
    #[error(
        "calibration data covers less than two belt pitches of travel ({span_mm:.2} mm, \
         {pitches_mm:.2} mm needed)"
    )]
    TooLittleTravel {
        /// Travel covered, mm (NaN: no finite position).
        span_mm: f64,
        /// Two belt pitches, mm.
        pitches_mm: f64,
    },
    /// A band table came out unusable (fewer than two points, or not increasing).
    #[error("{direction} band table rejected")]
    BandRejected {
        /// `"forward"` or `"reverse"`.
        direction: &'static str,
    },
    /// Too few reversals in one direction for Model 3's transition table.
    #[error(
        "calibration data has too few reversals for Model 3's transition tables \
         ({samples} samples after {direction} reversals, 100 needed)"
    )]
    TooFewReversals {
        /// `"forward"` or `"reverse"`.
        direction: &'static str,
        /// Samples recorded after such reversals.
        samples: usize,
    },
    /// A linear least-squares fit had no unique solution.
    #[error("{fit}: the least-squares fit is singular")]
    Singular {
        /// `"Model 3's transition table"` or `"Model 4"`.
        fit: &'static str,
    },
    /// No samples approached in both directions (the constant-backlash baseline).
    #[error("no approached samples in both directions")]
    NoApproachedSamples,
    /// No approached samples for the bidirectional table.
    #[error("no approached samples for the table")]
    NoTableSamples,
    /// A fitted parameter set the blob's formats or the builders refuse, naming the field.
    #[error("calibrated parameters rejected: {0}")]
    Rejected(BlobError),
    /// Model 4's features could not be built from the fitted Models 1-3.
    #[error("Model 4's features: {0}")]
    Features(ConfigError),
}

/// What calibration produced, with the fit quality on its own data.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// Every compensator's parameters, the baselines' included (what the firmware loads).
    pub params: ModelParams,
    /// RMS residual of each model on the calibration data, um.
    pub fit_rms_um: [(ModelKind, f64); 4],
    /// Samples used.
    pub samples: usize,
    /// The region of motion the recordings cover, where the caller knows their scenarios (a
    /// fit from traces alone does not; older calibration files hold none).
    pub coverage: Option<crate::coverage::Coverage>,
}

/// One calibration run prepared for fitting.
struct Prepared {
    x_counts: Vec<i32>,
    /// The motor current the drive commanded on each tick, amperes.
    current_a: Vec<f64>,
    x_mm: Vec<f64>,
    dx_um: Vec<f64>,
}

fn prepare(trace: &Trace) -> Prepared {
    let n = trace.records.len();
    let raw: Vec<f64> = (0..n).map(|i| trace.dx_um(i)).collect();
    let mut prefix = vec![0.0; n + 1];
    for i in 0..n {
        prefix[i + 1] = prefix[i] + raw[i];
    }
    let dx_um = (0..n)
        .map(|i| {
            let (a, b) = (
                i.saturating_sub(FILTER_HALF_WIDTH),
                (i + FILTER_HALF_WIDTH + 1).min(n),
            );
            (prefix[b] - prefix[a]) / (b - a) as f64
        })
        .collect();
    Prepared {
        x_counts: trace.records.iter().map(|r| r.motor_counts.0).collect(),
        // The drive-frame current Model 4 is fitted on: the simulated drives run the paper rig's
        // polarity (not inverted), and recordings of an inverted drive are turned back into the
        // drive's frame by `belt-tool`'s `to_trace`.
        current_a: trace
            .records
            .iter()
            .map(|r| r.out.current_a.to_num::<f64>())
            .collect(),
        x_mm: (0..n).map(|i| trace.x_pe_mm(i)).collect(),
        dx_um,
    }
}

/// Sum of squared residuals of `kind` with `params` over all runs, and the sample count.
fn sse(params: &ModelParams, rig: &Rig, kind: ModelKind, runs: &[Prepared]) -> (f64, usize) {
    let mut s = 0.0;
    let mut n = 0;
    for r in runs {
        let Some(&x0) = r.x_counts.first() else {
            continue;
        };
        let Ok(mut m) = Reference::new(params, rig, x0) else {
            return (f64::INFINITY, 1);
        };
        for ((x, dx), i) in r.x_counts.iter().zip(&r.dx_um).zip(&r.current_a) {
            let e = dx - m.estimate_with_current_um(kind, *x, *i);
            s += e * e;
            n += 1;
        }
    }
    (s, n)
}

fn model1(v: &[f64]) -> Model1Params {
    Model1Params {
        m_mm_per_mm: v[0],
        offset_mm: v[1],
        h_mm: v[2].max(0.0),
        h_g_mm: v[3].max(0.0),
        slope_a_mm_per_mm: v[4].max(0.0),
        slope_b_mm_per_mm: v[5].max(0.0),
    }
}

fn model2(v: &[f64]) -> Model2Params {
    Model2Params {
        m_mm_per_mm: v[0],
        offset_mm: v[1],
        h_mm: v[2].max(0.0),
        h_g_mm: v[3].max(0.0),
        rate_a_per_mm: v[4].min(0.0),
        rate_b_per_mm: v[5].min(0.0),
        amplitude_a_mm: v[6].max(0.0),
        amplitude_b_mm: v[7].max(0.0),
    }
}

/// Least-squares line through the approached samples of each direction with a shared slope:
/// forward dx = m x + c - h, reverse dx = m x + c (all mm). Returns (m, c, h).
fn band_line(runs: &[Prepared], deadband: u32) -> (f64, f64, f64) {
    // Normal equations for unknowns (m, c, h) with rows [x, 1, -f] where f = 1 forward.
    let mut ata = [[0.0f64; 3]; 3];
    let mut atb = [0.0f64; 3];
    for r in runs {
        for s in strokes(&r.x_counts, deadband) {
            let x_turn = r.x_mm[s.turn_index];
            for i in s.start..s.end {
                if (r.x_mm[i] - x_turn).abs() < 20.0 {
                    continue;
                }
                let row = [r.x_mm[i], 1.0, if s.dir > 0 { -1.0 } else { 0.0 }];
                for a in 0..3 {
                    atb[a] += row[a] * r.dx_um[i] / 1000.0;
                    for b in 0..3 {
                        ata[a][b] += row[a] * row[b];
                    }
                }
            }
        }
    }
    let flat: Vec<f64> = ata.iter().flatten().copied().collect();
    match crate::tables::solve_spd(flat, atb.to_vec()) {
        Some(v) => (v[0], v[1], v[2]),
        None => (0.0, 0.0, 0.3),
    }
}

/// Model 3's tables built on the fitted Model 1, with smoothing weight `smooth` (see
/// [`fit_gap_table`]).
fn model3(
    m1: &Model1Params,
    runs: &[Prepared],
    rig: &Rig,
    deadband: u32,
    smooth: f64,
) -> Result<Model3Params, CalibrationError> {
    let edge = |x_mm: f64, dir: i8| {
        1000.0 * (m1.m_mm_per_mm * x_mm + m1.offset_mm - if dir > 0 { m1.h_mm } else { 0.0 })
    };
    let closing = m1.closing();
    let settle_mm = |dir: i8| {
        let c = if dir > 0 {
            closing.forward_mm
        } else {
            closing.reverse_mm
        };
        c.map_or(150.0, |v| v.to_num::<f64>()).clamp(5.0, 150.0)
    };

    // Band tables: bins of one belt pitch over the travel seen.
    let (lo, hi) = travel_span_mm(runs, rig)?;
    let n_bins = (((hi - lo) / rig.belt_pitch_mm).ceil() as usize).clamp(2, MAX_BAND_POINTS);
    let bin_w = (hi - lo) / n_bins as f64;
    let band = |dir: i8| -> Vec<(f64, f64)> {
        let (mut sum, mut cnt) = (vec![0.0; n_bins], vec![0usize; n_bins]);
        for r in runs {
            for s in strokes(&r.x_counts, deadband)
                .into_iter()
                .filter(|s| s.dir == dir)
            {
                let x_turn = r.x_mm[s.turn_index];
                for i in s.start..s.end {
                    if (r.x_mm[i] - x_turn).abs() >= settle_mm(dir) {
                        let b = (((r.x_mm[i] - lo) / bin_w) as usize).min(n_bins - 1);
                        sum[b] += r.dx_um[i] - edge(r.x_mm[i], dir);
                        cnt[b] += 1;
                    }
                }
            }
        }
        let pts: Vec<(f64, f64)> = (0..n_bins)
            .map(|b| {
                let x = lo + (b as f64 + 0.5) * bin_w;
                let corr = if cnt[b] >= 20 {
                    sum[b] / cnt[b] as f64
                } else {
                    0.0
                };
                (x, edge(x, dir) + corr)
            })
            .collect();
        pts
    };
    let (mut fwd, mut rev) = (band(1), band(-1));
    // The reverse edge lies above the forward one (the model's invariant). With almost no
    // hysteresis (a frictionless guide) the two averages can cross by noise: they meet at their
    // mean there.
    for (f, r) in fwd.iter_mut().zip(rev.iter_mut()) {
        if r.1 < f.1 {
            let mid = 0.5 * (f.1 + r.1);
            (f.1, r.1) = (mid, mid);
        }
    }
    let forward_band = BandParams::from_points(&fwd).ok_or(CalibrationError::BandRejected {
        direction: "forward",
    })?;
    let reverse_band = BandParams::from_points(&rev).ok_or(CalibrationError::BandRejected {
        direction: "reverse",
    })?;

    // Transition tables: gap to the new band edge after each reversal.
    let band_at =
        |b: &BandParams, x: f64| crate::tables::interp(&b.x_mm[..b.len], &b.y_um[..b.len], x);
    let mut samples: [Vec<GapSample>; 2] = [Vec::new(), Vec::new()];
    let mut d_max = [0.0f64; 2];
    for r in runs {
        let ss = strokes(&r.x_counts, deadband);
        for s in ss.iter().skip(1) {
            let k = if s.dir > 0 { 0 } else { 1 };
            let b = if s.dir > 0 {
                &forward_band
            } else {
                &reverse_band
            };
            let x_d = r.x_mm[s.turn_index];
            // Error at the turning point: the filtered Delta x there.
            let g0 = (r.dx_um[s.turn_index] - band_at(b, x_d)) * s.dir as f64;
            if !(g0.is_finite()) || g0 < 0.0 {
                continue;
            }
            for i in s.start..s.end {
                let d = (r.x_mm[i] - x_d).abs();
                let gap = (r.dx_um[i] - band_at(b, r.x_mm[i])) * s.dir as f64;
                samples[k].push(GapSample {
                    d_mm: d,
                    g0_um: g0,
                    gap_um: gap,
                });
                d_max[k] = d_max[k].max(d);
            }
        }
    }
    let transition = |k: usize, hg_um: f64| -> Result<TransitionParams, CalibrationError> {
        let s = &samples[k];
        if s.len() < 100 {
            return Err(CalibrationError::TooFewReversals {
                direction: if k == 0 { "forward" } else { "reverse" },
                samples: s.len(),
            });
        }
        let g_max = s.iter().map(|g| g.g0_um).fold(0.0, f64::max).max(1.0);
        let d_len = settle_mm(if k == 0 { 1 } else { -1 })
            .min(d_max[k])
            .max(1.0);
        let (nd, ng) = (MAX_TRANSITION_D, MAX_TRANSITION_G0);
        let d_axis: Vec<f64> = (0..nd)
            .map(|i| d_len * i as f64 / (nd - 1) as f64)
            .collect();
        let g_axis: Vec<f64> = (0..ng)
            .map(|j| g_max * j as f64 / (ng - 1) as f64)
            .collect();
        let used: Vec<GapSample> = s.iter().copied().filter(|g| g.d_mm <= d_len).collect();
        let anchor: Vec<f64> = g_axis.iter().map(|g| (g - hg_um).max(0.0)).collect();
        let vals = fit_gap_table(&used, &d_axis, &g_axis, smooth, &anchor).ok_or(
            CalibrationError::Singular {
                fit: "Model 3's transition table",
            },
        )?;
        let mut t = TransitionParams::EMPTY;
        t.n_d = nd;
        t.n_g0 = ng;
        t.d_step_mm = d_axis[1];
        t.g0_step_um = g_axis[1];
        for i in 0..nd {
            for j in 0..ng {
                t.gap_um[i][j] = vals[i * ng + j].clamp(0.0, 2000.0);
            }
        }
        Ok(t)
    };
    let hg_um = m1.h_g_mm * 1000.0;
    Ok(Model3Params {
        forward_band,
        reverse_band,
        forward_transition: transition(0, hg_um)?,
        reverse_transition: transition(1, hg_um)?,
    })
}

/// Least squares of Model 1 (`Linear`) or Model 2 (`Exponential`) over all runs, from `x0`.
fn fit(
    params: &mut ModelParams,
    rig: &Rig,
    runs: &[Prepared],
    kind: ModelKind,
    x0: &[f64],
    step: &[f64],
    progress: &mut dyn FnMut(&str, f64),
) -> Vec<f64> {
    const MAX_EVALS: usize = 600;
    let stage = format!("fit {}", kind.as_str());
    let mut evals = 0usize;
    nelder_mead(
        |v| {
            evals += 1;
            progress(&stage, evals as f64 / MAX_EVALS as f64);
            match kind {
                ModelKind::Exponential => params.model2 = model2(v),
                _ => params.model1 = model1(v),
            }
            sse(params, rig, kind, runs).0
        },
        x0,
        step,
        1e-9,
        MAX_EVALS,
    )
    .x
}

/// Calibrates every model and both baselines from `traces`. `progress(stage, fraction)` reports.
pub fn calibrate(
    traces: &[Trace],
    rig: &Rig,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Calibration, CalibrationError> {
    calibrate_with(traces, rig, None, progress)
}

/// [`calibrate`], and where `belt` gives the machine's configured geometry and motor (with
/// default physics for the rest), Model 4 with the belt observer: its physics identified on the
/// recordings ([`belt_observer::identify_with`]), kept in place of the slip observer when it
/// fits the recordings better.
pub fn calibrate_with(
    traces: &[Trace],
    rig: &Rig,
    belt: Option<&BeltPhysics>,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Calibration, CalibrationError> {
    let runs: Vec<Prepared> = traces
        .iter()
        .filter(|t| !t.records.is_empty())
        .map(prepare)
        .collect();
    if runs.is_empty() {
        return Err(CalibrationError::NoSamples);
    }
    let mut params = ModelParams::PAPER;

    // Start: the band line, Table 2 for the transition shapes.
    let (m, c, h) = band_line(&runs, ModelParams::DEFAULT_DEADBAND_COUNTS);
    let p = Model1Params::PAPER;
    let x1 = [m, c, h, p.h_g_mm, p.slope_a_mm_per_mm, p.slope_b_mm_per_mm];
    let step1 = [2e-4, 0.02, 0.03, 0.02, 5e-4, 5e-4];

    // The reversal dead band, by measurement: a dead band of a count or two takes the creep of a
    // settling motor (a few um back) for a reversal and applies the whole fast jump h_g although
    // the carriage has not moved; too wide a band registers real reversals late.
    let mut best = (f64::INFINITY, ModelParams::DEFAULT_DEADBAND_COUNTS);
    for (k, &db) in DEADBAND_CANDIDATES_COUNTS.iter().enumerate() {
        progress(
            "choose dead band",
            k as f64 / DEADBAND_CANDIDATES_COUNTS.len() as f64,
        );
        params.reversal_deadband_counts = db;
        let trial = nelder_mead(
            |v| {
                params.model1 = model1(v);
                sse(&params, rig, ModelKind::Linear, &runs).0
            },
            &x1,
            &step1,
            1e-6,
            150,
        );
        if trial.value < best.0 {
            best = (trial.value, db);
        }
    }
    let deadband = best.1;
    params.reversal_deadband_counts = deadband;
    let fit1 = fit(
        &mut params,
        rig,
        &runs,
        ModelKind::Linear,
        &x1,
        &step1,
        progress,
    );
    params.model1 = model1(&fit1);

    let p2 = Model2Params::PAPER;
    let f = &fit1;
    let x2 = [
        f[0],
        f[1],
        f[2],
        f[3],
        p2.rate_a_per_mm,
        p2.rate_b_per_mm,
        p2.amplitude_a_mm,
        p2.amplitude_b_mm,
    ];
    let step2 = [2e-4, 0.02, 0.03, 0.02, 0.02, 0.02, 0.03, 0.03];
    let fit2 = fit(
        &mut params,
        rig,
        &runs,
        ModelKind::Exponential,
        &x2,
        &step2,
        progress,
    );
    params.model2 = model2(&fit2);

    // Model 3's smoothing, by measurement on the calibration data: sparse (d, g0) cells and the
    // tooth ripple make a lightly smoothed table oscillate between cells.
    let mut best = (f64::INFINITY, SMOOTHING_CANDIDATES[0]);
    for (k, &smooth) in SMOOTHING_CANDIDATES.iter().enumerate() {
        progress(
            "Model 3 tables",
            k as f64 / SMOOTHING_CANDIDATES.len() as f64,
        );
        params.model3 = model3(&params.model1, &runs, rig, deadband, smooth)?;
        let v = sse(&params, rig, ModelKind::Table, &runs).0;
        if v < best.0 {
            best = (v, smooth);
        }
    }
    params.model3 = model3(&params.model1, &runs, rig, deadband, best.1)?;
    progress("Model 4", 0.0);
    params.model4 = model4(&runs, rig, &params, belt, progress)?;
    params.backlash = Backlash::calibrate(traces)
        .ok_or(CalibrationError::NoApproachedSamples)?
        .to_params();
    params.bidir_table = BidirTable::calibrate(traces, crate::baseline::MAX_ROWS)
        .ok_or(CalibrationError::NoTableSamples)?
        .to_params();
    // From here on, exactly what the firmware will hold: the blob's fixed-point formats.
    let params = quantised(&params, rig).map_err(CalibrationError::Rejected)?;
    progress("Model 3 tables", 1.0);

    let rms = |kind| {
        let (s, n) = sse(&params, rig, kind, &runs);
        (s / n.max(1) as f64).sqrt()
    };
    let fit_rms_um = [
        (ModelKind::Linear, rms(ModelKind::Linear)),
        (ModelKind::Exponential, rms(ModelKind::Exponential)),
        (ModelKind::Table, rms(ModelKind::Table)),
        (ModelKind::Operator, rms(ModelKind::Operator)),
    ];
    Ok(Calibration {
        params,
        fit_rms_um,
        samples: runs.iter().map(|r| r.x_counts.len()).sum(),
        coverage: None,
    })
}

/// The travel the calibration data covers, mm; at least two belt pitches.
fn travel_span_mm(runs: &[Prepared], rig: &Rig) -> Result<(f64, f64), CalibrationError> {
    let (lo, hi) = runs
        .iter()
        .flat_map(|r| r.x_mm.iter())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &x| {
            (l.min(x), h.max(x))
        });
    if (hi - lo).is_nan() || hi - lo <= 2.0 * rig.belt_pitch_mm {
        return Err(CalibrationError::TooLittleTravel {
            span_mm: hi - lo,
            pitches_mm: 2.0 * rig.belt_pitch_mm,
        });
    }
    Ok((lo, hi))
}

/// Model 4: the slip observer's own parameters by Nelder-Mead around one linear least-squares
/// fit of all the weights (the three plays with and without the forward share, band line and
/// hats, both harmonics, the current and its low pass, and the observer's mesh offset) to Delta
/// x on every calibration sample, lightly regularised (ridge 1e-6 of each column's energy) so
/// that terms the data never move get no weight. The terms are [`Reference::model4_step`]'s,
/// the definitions the drive's Model 4 evaluates; the observer is the quantised one the blob
/// will hold.
fn model4(
    runs: &[Prepared],
    rig: &Rig,
    base: &ModelParams,
    belt: Option<&BeltPhysics>,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Model4Params, CalibrationError> {
    let (lo, hi) = travel_span_mm(runs, rig)?;
    let mut m = Model4Params::zero(rig.belt_pitch_mm, rig.mm_per_pulley_rev());
    m.x_ref_mm = ((lo + hi) / 2.0).round();
    m.knot_step_mm = (hi - lo) / (N_KNOTS + 1) as f64;
    m.knot_start_mm = lo + m.knot_step_mm;
    // The geometry as the blob holds it and the dead band as the drive will hold it: the terms
    // are those the drive's Model 4 computes (its reference evaluates the same definitions).
    let probe = ModelParams {
        model4: blob::quantise_model4(&m).map_err(CalibrationError::Rejected)?,
        ..quantised(base, rig).map_err(CalibrationError::Rejected)?
    };
    let cpm = rig.counts_per_mm();
    // Every term but the observer's, per sample, and the direction the observer sees.
    let mut cols: Vec<[f64; NB]> = Vec::new();
    let mut forward: Vec<bool> = Vec::new();
    let mut y: Vec<f64> = Vec::new();
    for r in runs {
        let Some(&x0) = r.x_counts.first() else {
            continue;
        };
        let mut model4 = Reference::new(&probe, rig, x0).map_err(CalibrationError::Features)?;
        for (i, &x) in r.x_counts.iter().enumerate() {
            let (_, t) = model4.model4_step(x, r.current_a[i]);
            cols.push(model4_row(&t, cpm));
            forward.push(t.forward);
            y.push(r.dx_um[i]);
        }
    }
    let mut fixed = crate::tables::Bordered::new(NB);
    for (row, &v) in cols.iter().zip(&y) {
        fixed.add(row, v);
    }
    // The observer's offset along every run, for candidate parameters (quantised as the blob
    // holds them); None where they are refused.
    let shape = m.clone();
    let offsets = |slip: &SlipParams| -> Option<Vec<f64>> {
        let mut q = shape.clone();
        q.slip = *slip;
        let q = blob::quantise_model4(&q).ok()?;
        let c = q.slip.build(cpm).ok()?;
        let mut out = Vec::with_capacity(y.len());
        let mut k = 0;
        for r in runs {
            let mut obs = RefSlip::new(&c);
            for (i, (&x, &a)) in r.x_counts.iter().zip(&r.current_a).enumerate() {
                if i == 0 {
                    obs.start(forward[k], x, a);
                } else {
                    obs.step(forward[k], x, a);
                }
                out.push(obs.offset_um());
                k += 1;
            }
        }
        Some(out)
    };
    // The joint least squares with the offset `g` as the last column: (weights, residual sum).
    let solve = |g: &[f64]| -> Option<(Vec<f64>, f64)> {
        fixed.solve_with(
            cols.iter()
                .zip(&y)
                .zip(g)
                .map(|((row, &v), &gv)| (&row[..], v, gv)),
        )
    };
    const MAX_EVALS: usize = 500;
    let mut evals = 0usize;
    let best = nelder_mead(
        |v| {
            evals += 1;
            progress("Model 4 slip observer", evals as f64 / MAX_EVALS as f64);
            offsets(&slip_params(v))
                .and_then(|g| solve(&g))
                .map_or(f64::INFINITY, |(_, sse)| sse)
        },
        &SLIP_START,
        &SLIP_STEP,
        1e-9,
        MAX_EVALS,
    );
    m.slip = slip_params(&best.x);
    let mut m = blob::quantise_model4(&m).map_err(CalibrationError::Rejected)?;
    let (mut v, slip_sse) = offsets(&m.slip)
        .and_then(|g| solve(&g))
        .ok_or(CalibrationError::Singular { fit: "Model 4" })?;
    if let Some(start) = belt {
        if let Some((term, bv, sse)) =
            belt_term(runs, &cols, &y, start, &m, base, rig, &solve, progress)?
        {
            // Kept only where it fits the recordings better than the slip observer.
            if sse < slip_sse {
                m.belt = Some(term);
                v = bv;
            }
        }
    }
    for j in 0..N_OPS {
        m.play_um_per_mm[j] = v[2 * j];
        m.play_forward_um_per_mm[j] = v[2 * j + 1];
    }
    let k = 2 * N_OPS;
    m.offset_um = v[k];
    m.slope_um_per_mm = v[k + 1];
    m.knot_um.copy_from_slice(&v[k + 2..k + 2 + N_KNOTS]);
    let h = k + 2 + N_KNOTS;
    m.pitch_um = [v[h], v[h + 1]];
    m.turn_um = [v[h + 2], v[h + 3]];
    m.current_um_per_a = v[NB - 2];
    m.current_lp_um_per_a = v[NB - 1];
    // The blob holds |w| < 8 (Q16); a fit at the bound is clamped, not refused.
    let weight = v[NB].clamp(-7.99, 7.99);
    match &mut m.belt {
        // The slip observer is not run beside the belt observer.
        Some(b) => {
            b.weight = weight;
            m.slip.weight = 0.0;
        }
        None => m.slip.weight = weight,
    }
    Ok(m)
}

/// Model 4's joint least squares with an offset column: the weights and the residual sum.
type Solve<'a> = dyn Fn(&[f64]) -> Option<(Vec<f64>, f64)> + 'a;

/// Ticks per step of Model 4's belt observer: its cost within the tick's budget (README: about
/// 234 instructions a tick at a step every 6 ticks, 338 at every 4th) at the accuracy measured.
pub const BELT_STEP_TICKS: u32 = 6;
/// The identification's search: carriage-mass starts (the fit has local minima in the mass),
/// evaluations a round and further rounds (README, "A reduced plant observer").
const BELT_MASS_STARTS: [f64; 4] = [0.5, 1.0, 2.0, 4.0];
const BELT_EVALS: usize = 150;
const BELT_ROUNDS: usize = 1;

/// Model 4's belt observer on these recordings: the guide's friction along the travel, the
/// physics identified from `start`, and the weights refitted with its offset exactly as the
/// drive computes it (the blob's physics through [`Reference::model4_step`]). `None` where the
/// identification or the fit find nothing. Identified at each of the tracking filter's
/// discounts ([`TRACK_DISCOUNTS`]), the one whose fit is best kept: the filter's bandwidth
/// against the counts' quantisation is the machine's (README, "Model 4 with the belt
/// observer").
#[allow(clippy::too_many_arguments)]
fn belt_term(
    runs: &[Prepared],
    cols: &[[f64; NB]],
    y: &[f64],
    start: &BeltPhysics,
    m: &Model4Params,
    base: &ModelParams,
    rig: &Rig,
    solve: &Solve,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Option<(BeltTerm, Vec<f64>, f64)>, CalibrationError> {
    let mut fit_runs = Vec::with_capacity(runs.len());
    let mut at = 0;
    for r in runs {
        let n = r.x_counts.len();
        fit_runs.push(FitRun {
            inputs: r
                .x_counts
                .iter()
                .zip(&r.current_a)
                .map(|(&x, &a)| (i64::from(x), a))
                .collect(),
            terms: cols[at..at + n].iter().map(|c| c.to_vec()).collect(),
            dx_um: y[at..at + n].to_vec(),
        });
        at += n;
    }
    let mut physics = start.clone();
    physics.drive_port = true;
    physics.capstan_taylor = true;
    physics.decimation = BELT_STEP_TICKS;
    physics.guide_profile = belt_observer::guide_profile(&fit_runs, &physics);
    let fields: Vec<Param> = Param::ALL.iter().map(|(p, _)| *p).collect();
    let mut best: Option<(BeltTerm, Vec<f64>, f64)> = None;
    let discounts = TRACK_DISCOUNTS.len() as f64;
    for (i, &discount) in TRACK_DISCOUNTS.iter().enumerate() {
        physics.belt.track_discount = discount;
        let starts: Vec<BeltPhysics> = BELT_MASS_STARTS
            .iter()
            .map(|&f| {
                let mut p = physics.clone();
                p.scale(Param::Mass, f);
                p
            })
            .collect();
        let Some(found) = belt_observer::identify_with(
            &fit_runs,
            &starts,
            &fields,
            BELT_EVALS,
            BELT_ROUNDS,
            &mut |f| progress("Model 4 belt observer", (i as f64 + f) / discounts),
        ) else {
            continue;
        };
        let mut term = BeltTerm {
            physics: found.physics.core_params(),
            tick_s: belt_observer::TICK_S,
            step_ticks: BELT_STEP_TICKS,
            weight: 0.0,
            rest_um: [0.0; 2],
            half_travel_mm: [0.3, 10.0],
            fast_share: 0.5,
        };
        // Physics the drive's builder refuses are not a calibration (the search keeps to them).
        if term.build(rig.counts_per_mm()).is_err() {
            continue;
        }
        let mut probe_m4 = m.clone();
        probe_m4.belt = Some(term);
        let probe = ModelParams {
            model4: blob::quantise_model4(&probe_m4).map_err(CalibrationError::Rejected)?,
            ..quantised(base, rig).map_err(CalibrationError::Rejected)?
        };
        let mut offset = Vec::with_capacity(y.len());
        for r in runs {
            let Some(&x0) = r.x_counts.first() else {
                continue;
            };
            let mut model4 = Reference::new(&probe, rig, x0).map_err(CalibrationError::Features)?;
            for (&x, &a) in r.x_counts.iter().zip(&r.current_a) {
                offset.push(model4.model4_step(x, a).1.slip_um);
            }
        }
        if let Some((rest_um, half_travel_mm, fast_share)) =
            rest_of(runs, &offset, rig.counts_per_mm())
        {
            let fitted = BeltTerm {
                rest_um,
                half_travel_mm,
                fast_share,
                ..term
            };
            // A fit the drive's formats refuse (a rest beyond their range) keeps the defaults.
            if fitted.build(rig.counts_per_mm()).is_ok() {
                term = fitted;
            }
        }
        if let Some((v, sse)) = solve(&offset) {
            if best.as_ref().is_none_or(|b| sse < b.2) {
                best = Some((term, v, sse));
            }
        }
    }
    Ok(best)
}

/// Ticks the motor must stand (within 2 counts) before and after a sample for it to be at rest:
/// 20 ms at 2 kHz.
const REST_TICKS: usize = 40;

/// The placement's model of the belt observer's rest ([`BeltTerm::rest_um`],
/// [`BeltTerm::half_travel_mm`], [`BeltTerm::fast_share`]) from its own offsets along the
/// recordings: between two rests with one-way travel `L` between them, the offset goes from
/// `o0` to `r_d + (o0 - r_d) (a 2^(-L / H1) + (1 - a) 2^(-L / H2))`, a fast part (the gap
/// crossed) and a slow one (the creep). `H1`, `H2` and `a` by a search over a grid, `r_d` per
/// direction by least squares for each. `None` without two pairs of rests each way.
fn rest_of(
    runs: &[Prepared],
    offset_um: &[f64],
    counts_per_mm: f64,
) -> Option<([f64; 2], [f64; 2], f64)> {
    // (one-way travel in mm, forward, offset at the first rest, at the second).
    let mut pairs: Vec<(f64, bool, f64, f64)> = Vec::new();
    let mut at = 0;
    for r in runs {
        let x = &r.x_counts;
        let o = &offset_um[at..at + x.len()];
        at += x.len();
        let still = |k: usize| {
            k >= REST_TICKS
                && k + REST_TICKS < x.len()
                && x[k - REST_TICKS..=k + REST_TICKS]
                    .iter()
                    .all(|&v| (i64::from(v) - i64::from(x[k])).abs() <= 2)
        };
        // The last tick of each rest, then the pair with the next rest when the way between
        // is one-way.
        let mut last: Option<usize> = None;
        let mut k = 0;
        while k < x.len() {
            if !still(k) {
                k += 1;
                continue;
            }
            let mut end = k;
            while end + 1 < x.len() && still(end + 1) {
                end += 1;
            }
            if let Some(p) = last {
                let way = &x[p..=k];
                let d = i64::from(x[k]) - i64::from(x[p]);
                let (lo, hi) = way
                    .iter()
                    .fold((i32::MAX, i32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
                let one_way = d != 0 && i64::from(hi) - i64::from(lo) <= d.abs() + 4;
                if one_way {
                    pairs.push((d.abs() as f64 / counts_per_mm, d > 0, o[p], o[end]));
                }
            }
            last = Some(end);
            k = end + 1;
        }
    }
    // Two pairs each way at least: with one, every shape fits it exactly.
    if pairs.iter().filter(|p| p.1).count() < 2 || pairs.iter().filter(|p| !p.1).count() < 2 {
        return None;
    }
    // The share of the way still to go after `l` mm: `a 2^(-l / h1) + (1 - a) 2^(-l / h2)`.
    let left =
        |l: f64, (h1, h2, a): (f64, f64, f64)| a * (-l / h1).exp2() + (1.0 - a) * (-l / h2).exp2();
    let fit = |shape: (f64, f64, f64)| -> ([f64; 2], f64) {
        let mut rest = [0.0; 2];
        for (dir, r) in rest.iter_mut().enumerate() {
            let (mut num, mut den) = (0.0, 0.0);
            for &(l, _, o0, o1) in pairs.iter().filter(|p| p.1 == (dir == 1)) {
                let e = left(l, shape);
                num += (1.0 - e) * (o1 - o0 * e);
                den += (1.0 - e) * (1.0 - e);
            }
            *r = if den > 0.0 { num / den } else { 0.0 };
        }
        let sse = pairs
            .iter()
            .map(|&(l, fwd, o0, o1)| {
                let r = rest[fwd as usize];
                (o1 - (r + (o0 - r) * left(l, shape))).powi(2)
            })
            .sum();
        (rest, sse)
    };
    // The fast part 20 um to 2 mm, the slow one 1 mm to 1 m (8 a decade, at least two counts),
    // the share in twentieths.
    let count2 = 2.0 / counts_per_mm;
    let h = |from: f64, i: i32| (from * 10f64.powf(f64::from(i) / 8.0)).max(count2);
    let mut best = ([0.0; 2], (1.0, 10.0, 0.0), f64::INFINITY);
    for i in 0..=16 {
        for j in 0..=24 {
            for k in 0..=20 {
                let shape = (h(0.02, i), h(1.0, j), f64::from(k) / 20.0);
                let (rest, sse) = fit(shape);
                if sse < best.2 {
                    best = (rest, shape, sse);
                }
            }
        }
    }
    let (rest, (h1, h2, a), _) = best;
    Some((rest, [h1, h2], a))
}

/// Model 4's terms besides the observer: two per play, the band line, the hats, the harmonics,
/// the current and its low pass.
pub const NB: usize = 2 * N_OPS + 2 + N_KNOTS + 4 + 2;

/// Model 4's terms at one tick as a row of the fit, every weight's column in its unit (um per mm
/// of play output, um, um per mm of travel, um per hat, per sine, per ampere); the observer's
/// offset is not in it (the fit adds it as the last column).
pub fn model4_row(t: &Model4Terms, counts_per_mm: f64) -> [f64; NB] {
    let mut row = [0.0; NB];
    for (j, f) in t.plays_counts.iter().enumerate() {
        row[2 * j] = f / counts_per_mm;
        row[2 * j + 1] = if t.forward { f / counts_per_mm } else { 0.0 };
    }
    let k = 2 * N_OPS;
    row[k] = 1.0;
    row[k + 1] = t.from_ref_counts / counts_per_mm;
    row[k + 2..k + 2 + N_KNOTS].copy_from_slice(&t.hats);
    let h = k + 2 + N_KNOTS;
    row[h..h + 4].copy_from_slice(t.harmonics.as_flattened());
    row[NB - 2] = t.current_a;
    row[NB - 1] = t.current_lp_a;
    row
}

/// Where the observer's fit starts (`slip_params`' coordinates): a load of 60 um at constant
/// speed, 5 % more forward, 25 um per ampere, a renewal of 0.03 per mm, limit and half gap
/// 150 um. Measured on the simulated plants (paper rig and four variants) the fits land within
/// a factor of two of these.
const SLIP_START: [f64; 6] = [60.0, 0.05, 25.0, 0.03, 150.0, 150.0];
const SLIP_STEP: [f64; 6] = [20.0, 0.05, 10.0, 0.01, 40.0, 30.0];

/// The observer of the fit's coordinates: load, its forward asymmetry, um per ampere, renewal
/// per mm, limit and half gap. Out-of-range coordinates fold back into range (the simplex
/// explores freely).
fn slip_params(v: &[f64]) -> SlipParams {
    let asym = v[1].clamp(-0.9, 0.9);
    let load = v[0].abs().min(MAX_SLIP_UM);
    SlipParams {
        load_um: [load * (1.0 - asym), load * (1.0 + asym)].map(|l| l.min(MAX_SLIP_UM)),
        um_per_a: [v[2] * (1.0 - asym), v[2] * (1.0 + asym)]
            .map(|a| a.clamp(-MAX_SLIP_UM, MAX_SLIP_UM)),
        creep_per_mm: v[3].abs().min(1.0),
        limit_um: v[4].abs().clamp(1.0, MAX_SLIP_UM),
        half_gap_um: v[5].abs().clamp(1.0, MAX_SLIP_UM),
        weight: 0.0,
    }
}

/// The parameters exactly as the firmware will hold them (through the blob's formats).
pub fn quantised(params: &ModelParams, rig: &Rig) -> Result<ModelParams, BlobError> {
    let mut buf = vec![0u8; blob::MAX_BYTES];
    let n = blob::encode(params, rig, &mut buf)?;
    blob::decode(&buf[..n], rig)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::Record;
    use estimator_core::units::MotorCounts;

    /// A recording of the motor at `xs` (counts) with the carriage exactly on it.
    fn trace(xs: impl Iterator<Item = i32>, rig: &Rig) -> Trace {
        let cpm = rig.counts_per_mm();
        let records = xs
            .enumerate()
            .map(|(i, x)| Record {
                t_s: i as f64 / 2000.0,
                motor_counts: MotorCounts(x),
                x_ls_mm: x as f64 / cpm,
                setpoint_counts: MotorCounts(x),
                cmd_dir: 1,
                out: Default::default(),
            })
            .collect();
        Trace {
            scenario: "test".into(),
            seed: 0,
            counts_per_mm: cpm,
            records,
            move_starts: vec![0],
        }
    }

    #[test]
    fn refusals_name_what_the_data_lacks() {
        let rig = Rig::PAPER;
        let none = |t: &[Trace]| calibrate(t, &rig, &mut |_, _| {}).unwrap_err();
        assert_eq!(none(&[]), CalibrationError::NoSamples);
        assert_eq!(
            none(&[trace(std::iter::empty(), &rig)]),
            CalibrationError::NoSamples
        );
        // Strokes of 1 mm back and forth: less than two belt pitches of travel.
        let mm = rig.counts_per_mm();
        let zigzag = (0..8000).map(|i: i32| {
            let p = i % 4000;
            (if p < 2000 { p } else { 4000 - p } as f64 * mm / 2000.0) as i32
        });
        let e = none(&[trace(zigzag, &rig)]);
        match e {
            CalibrationError::TooLittleTravel {
                span_mm,
                pitches_mm,
            } => {
                assert!((span_mm - 1.0).abs() < 0.01, "{span_mm}");
                assert!((pitches_mm - 2.0 * rig.belt_pitch_mm).abs() < 1e-12);
            }
            other => panic!("{other:?}"),
        }
        assert!(e.to_string().contains("(1.00 mm, 10.16 mm needed)"), "{e}");
    }
}
