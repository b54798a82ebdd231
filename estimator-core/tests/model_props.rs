//! Property tests: every fixed-point model against its `f64` reference over random trajectories
//! and random valid parameters, and freedom from panics and overflow over the whole `i32` range.
//!
//! Trajectories are random walks with reversals (steps up to 400 counts per tick), standstills,
//! single-count jitter and huge jumps, starting anywhere in `+-ACCURATE_RANGE_COUNTS`. The
//! accuracy tests use a fixed seed and print the worst difference they saw.

use std::cell::Cell;

use estimator_core::fixed::types::I16F16;
use estimator_core::model::belt::{BeltParams, MAX_GUIDE_BINS, TRACK_DISCOUNT_RANGE};
use estimator_core::model::slip::SlipParams;
use estimator_core::model::BeltTerm;
use estimator_core::model::{
    estimate, estimate_with_current, BacklashParams, BandParams, BidirParams, Model1Params,
    Model2Params, Model3Params, Model4Params, ModelKind, ModelParams, ModelState, TransitionParams,
    ACCURATE_RANGE_COUNTS, MAX_BAND_POINTS, MAX_BIDIR_ROWS, MAX_TRANSITION_D, MAX_TRANSITION_G0,
};
use estimator_core::reference::Reference;
use estimator_core::rig::Rig;
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

/// The accuracy every model must hold against its reference, in um.
const TOLERANCE_UM: f64 = 0.05;

/// One move of the trajectory generator.
#[derive(Clone, Debug)]
enum Move {
    /// `n` ticks of `step` counts (negative: reverse).
    Run { step: i32, n: u16 },
    /// Stand still with +-1 count of jitter for `n` ticks.
    Jitter { n: u8 },
    /// Jump to a position given as a fraction of the range.
    Jump(f64),
}

fn moves() -> impl Strategy<Value = Vec<Move>> {
    let mv = prop_oneof![
        8 => (-400i32..=400, 1u16..200).prop_map(|(step, n)| Move::Run { step, n }),
        // Long runs: far enough to close transitions.
        2 => (-400i32..=400, 200u16..2000).prop_map(|(step, n)| Move::Run { step, n }),
        1 => (1u8..20).prop_map(|n| Move::Jitter { n }),
        1 => (-1.0f64..1.0).prop_map(Move::Jump),
    ];
    prop::collection::vec(mv, 1..40)
}

/// Expands moves into positions inside `+-limit`.
fn positions(x0: i32, moves: &[Move], limit: i32) -> Vec<i32> {
    let mut out = Vec::new();
    let mut x = x0;
    for (k, m) in moves.iter().enumerate() {
        match *m {
            Move::Run { step, n } => {
                for _ in 0..n {
                    x = (x + step).clamp(-limit, limit);
                    out.push(x);
                }
            }
            Move::Jitter { n } => {
                for i in 0..n {
                    let j = [0, 1, 0, -1][(i as usize + k) % 4];
                    out.push((x + j).clamp(-limit, limit));
                }
            }
            Move::Jump(f) => {
                x = (f * limit as f64) as i32;
                out.push(x);
            }
        }
    }
    out
}

/// A rig with 300..4700 counts per mm.
fn rigs() -> impl Strategy<Value = Rig> {
    (2.0f64..60.0, prop::sample::select(vec![12u32, 20, 36])).prop_map(|(gear_ratio, teeth)| Rig {
        gear_ratio,
        pulley_teeth: teeth,
        ..Rig::PAPER
    })
}

/// Model 1 and 2 parameters around Table 2, with the band slope limited so that the outputs stay
/// within +-16 mm over `+-ACCURATE_RANGE_COUNTS`.
fn band_and_models(cpm: f64) -> impl Strategy<Value = (Model1Params, Model2Params)> {
    let range_mm = ACCURATE_RANGE_COUNTS as f64 / cpm;
    let m_max = 12.0 / range_mm;
    (
        prop_oneof![Just(0.0), -m_max..m_max],
        0.0f64..1.0,
        0.0f64..1.0,
        1e-4f64..0.01,
        1e-4f64..0.01,
        -1.0f64..-1e-3,
        -1.0f64..-1e-3,
        0.0f64..1.0,
        0.0f64..1.0,
    )
        .prop_map(|(m, h, hg, a, b, ra, rb, aa, ab)| {
            let m1 = Model1Params {
                m_mm_per_mm: m,
                offset_mm: (a - b) * 40.0,
                h_mm: h,
                h_g_mm: hg * h,
                slope_a_mm_per_mm: a,
                slope_b_mm_per_mm: b,
            };
            let m2 = Model2Params {
                m_mm_per_mm: m,
                offset_mm: (b - a) * 40.0,
                h_mm: h,
                h_g_mm: hg * h,
                rate_a_per_mm: ra,
                rate_b_per_mm: rb,
                amplitude_a_mm: aa * h,
                amplitude_b_mm: ab * h,
            };
            (m1, m2)
        })
}

/// Table sizes: often the largest, otherwise random.
fn size(max: usize) -> impl Strategy<Value = usize> {
    prop_oneof![1 => Just(max), 2 => 2..=max]
}

/// Random band tables on a shared, evenly spaced axis of random start and step inside the
/// accurate range; the reverse band lies a random non-negative height above the forward band.
fn bands(cpm: f64) -> impl Strategy<Value = (BandParams, BandParams)> {
    let range_mm = ACCURATE_RANGE_COUNTS as f64 / cpm;
    (
        size(MAX_BAND_POINTS),
        prop::collection::vec((0.01f64..1.0, -1.0f64..1.0, 0.0f64..1.0), MAX_BAND_POINTS),
        -1.0f64..0.5,
        -12_000.0f64..12_000.0,
    )
        .prop_map(move |(n, pts, start, y0)| {
            let start_mm = start * range_mm;
            // n points over a random part of the rest of the range.
            let step = (range_mm - start_mm) * 0.999 * pts[0].0 / (n - 1) as f64;
            let mut f = BandParams::EMPTY;
            let mut r = BandParams::EMPTY;
            f.len = n;
            r.len = n;
            let (mut x, mut y) = (start_mm, y0);
            for (i, &(_, dy, hgt)) in pts.iter().take(n).enumerate() {
                f.x_mm[i] = x;
                r.x_mm[i] = x;
                f.y_um[i] = y;
                r.y_um[i] = y + 1500.0 * hgt;
                x += step;
                y = (y + 400.0 * dy).clamp(-13_000.0, 13_000.0);
            }
            (f, r)
        })
}

/// A random transition table whose gap changes by at most one step per `g0` step
/// (`|dG/dg0| <= 1`, like a measured transition).
fn transition() -> impl Strategy<Value = TransitionParams> {
    (
        size(MAX_TRANSITION_D),
        size(MAX_TRANSITION_G0),
        0.5f64..50.0,
        1.0f64..80.0,
        prop::collection::vec(0.0f64..100.0, MAX_TRANSITION_D),
        prop::collection::vec(-1.0f64..1.0, MAX_TRANSITION_D * MAX_TRANSITION_G0),
    )
        .prop_map(|(n_d, n_g0, d_step, g0_step, first, slopes)| {
            let mut t = TransitionParams::EMPTY;
            t.n_d = n_d;
            t.n_g0 = n_g0;
            t.d_step_mm = d_step;
            t.g0_step_um = g0_step;
            for i in 0..n_d {
                let mut g = first[i];
                for j in 0..n_g0 {
                    t.gap_um[i][j] = g;
                    g = (g + slopes[i * MAX_TRANSITION_G0 + j] * g0_step).clamp(0.0, 2000.0);
                }
            }
            t
        })
}

/// Random baselines: a backlash, and a bidirectional table of 2..=256 rows somewhere within the
/// accurate range.
fn baselines(cpm: f64) -> impl Strategy<Value = (BacklashParams, BidirParams)> {
    let range_mm = 0.9 * ACCURATE_RANGE_COUNTS as f64 / cpm;
    (
        -2_000.0f64..2_000.0,
        -500.0f64..2_000.0,
        2usize..=MAX_BIDIR_ROWS,
        -1.0f64..0.5,
        0.0f64..1.0,
        // The table's values span its format (I13F3: +-4095 um).
        prop::collection::vec(-4_095.0f64..4_095.0, 2 * MAX_BIDIR_ROWS),
    )
        .prop_map(move |(offset, backlash, rows, start, span, values)| {
            let mut t = BidirParams::ZERO;
            t.rows = rows;
            t.x0_mm = start * range_mm;
            t.step_mm = ((range_mm - t.x0_mm) * span / (rows - 1) as f64).max(2.0 / cpm);
            for i in 0..rows {
                t.forward_um[i] = values[2 * i];
                t.reverse_um[i] = values[2 * i + 1];
            }
            (
                BacklashParams {
                    offset_um: offset,
                    backlash_um: backlash,
                },
                t,
            )
        })
}

/// Model 4's slip observer: loads beyond the limit (gross slip) and within it, gaps from a few
/// um to 400 um, renewal up to 0.2 per mm.
fn slip() -> impl Strategy<Value = SlipParams> {
    (
        prop::array::uniform2(0.0f64..200.0),
        prop::array::uniform2(-60.0f64..60.0),
        0.0f64..0.2,
        5.0f64..300.0,
        2.0f64..400.0,
        -1.5f64..1.5,
    )
        .prop_map(
            |(load_um, um_per_a, creep_per_mm, limit_um, half_gap_um, weight)| SlipParams {
                load_um,
                um_per_a,
                creep_per_mm,
                limit_um,
                half_gap_um,
                weight,
            },
        )
}

/// Model 4 with random weights of plausible size: plays carrying up to 300 um each.
fn model4(cpm: f64) -> impl Strategy<Value = Model4Params> {
    (
        prop::array::uniform3((0.3f64..3.0, -300.0f64..300.0, -300.0f64..300.0)),
        (-0.5f64..0.5, -500.0f64..500.0, -1.0f64..1.0),
        (
            -0.5f64..0.5,
            1.0f64..100.0,
            prop::array::uniform8(-150.0f64..150.0),
        ),
        (
            1.0f64..25.0,
            -30.0f64..30.0,
            -30.0f64..30.0,
            8u32..80,
            -30.0f64..30.0,
            -30.0f64..30.0,
        ),
        (-40.0f64..40.0, -40.0f64..40.0, slip(), belt(cpm)),
    )
        .prop_map(
            move |(plays, (xr, off, slope), (ks, step, knots), h, (cur, cur_lp, slip, belt))| {
                let range_mm = ACCURATE_RANGE_COUNTS as f64 / cpm;
                let mut m = Model4Params::zero(h.0, h.0 * h.3 as f64);
                for (j, (scale, w, f)) in plays.into_iter().enumerate() {
                    // Strictly increasing, at least 1.5 counts apart, as the builder requires.
                    let narrower = if j == 0 { 0.0 } else { m.widths_mm[j - 1] };
                    m.widths_mm[j] = (Model4Params::WIDTHS_MM[j] * scale).max(narrower + 1.5 / cpm);
                    // Within the format's 128 um per count with both weights added.
                    let cap = 60.0 * m.widths_mm[j] * cpm;
                    m.play_um_per_mm[j] = w.clamp(-cap, cap) / m.widths_mm[j];
                    m.play_forward_um_per_mm[j] = f.clamp(-cap, cap) / m.widths_mm[j];
                }
                m.x_ref_mm = xr * range_mm;
                m.offset_um = off;
                // Outputs stay within +-16 mm (where the accuracy holds) over the whole range.
                m.slope_um_per_mm = slope * 4000.0 / range_mm;
                m.knot_start_mm = ks * range_mm;
                m.knot_step_mm = step;
                m.knot_um = knots;
                m.pitch_um = [h.1, h.2];
                m.turn_um = [h.4, h.5];
                m.current_um_per_a = cur;
                m.current_lp_um_per_a = cur_lp;
                m.slip = slip;
                m.belt = belt;
                m
            },
        )
}

/// Model 4's belt observer in half the cases: the paper rig's physics with its mass, preload,
/// gap, friction and renewal scaled by up to 2 either way, a guide profile, a step of 1 to 16
/// ticks, any weight within the format and a prediction of rest.
fn belt(cpm: f64) -> impl Strategy<Value = Option<BeltTerm>> {
    let term = (
        prop::array::uniform5(-1.0f64..1.0),
        0usize..=MAX_GUIDE_BINS,
        1u32..=16,
        -1.5f64..1.5,
        prop::array::uniform2(-200.0f64..200.0),
        0.01f64..100.0,
        0.0f64..1.0,
    )
        .prop_map(
            move |(scale, bins, step_ticks, weight, rest_um, half, track)| {
                let f = |k: usize| 2f64.powf(scale[k]);
                let mut physics = BeltParams::PAPER;
                physics.mass_kg *= f(0);
                physics.preload_n *= f(1);
                physics.half_gap_m *= f(2);
                physics.mu_kinetic *= f(3).min(2.0);
                physics.mu_static = physics.mu_kinetic * 1.3;
                physics.kappa_per_m *= f(4);
                physics.m_per_count = 1e-3 / cpm;
                // Any tracking discount the builder accepts.
                let (lo, hi) = (*TRACK_DISCOUNT_RANGE.start(), *TRACK_DISCOUNT_RANGE.end());
                physics.track_discount = lo + track * (hi - lo);
                physics.guide_bins = bins;
                for (k, d) in physics.guide_delta_n.iter_mut().enumerate() {
                    *d = (k as f64).sin();
                }
                BeltTerm {
                    physics,
                    tick_s: 1.0 / 2000.0,
                    step_ticks,
                    weight,
                    rest_um,
                    half_travel_mm: [half.max(2.0 / cpm) / 20.0, half.max(2.0 / cpm)]
                        .map(|h| h.max(2.0 / cpm)),
                    fast_share: (weight.abs() / 1.5).min(1.0),
                }
            },
        );
    prop_oneof![Just(None), term.prop_map(Some)]
}

/// A random valid parameter set and rig.
fn params() -> impl Strategy<Value = (Rig, ModelParams)> {
    rigs().prop_flat_map(|rig| {
        let cpm = rig.counts_per_mm();
        (
            Just(rig),
            band_and_models(cpm),
            bands(cpm),
            transition(),
            transition(),
            prop_oneof![Just(0u32), 0u32..6],
            any::<bool>(),
            baselines(cpm),
            model4(cpm),
        )
            .prop_map(
                |(rig, (m1, m2), (bf, br), tf, tr, db, from_m1, (bl, bt), m4)| {
                    let model3 = if from_m1 {
                        Model3Params::from_model1(
                            &m1,
                            0.99 * ACCURATE_RANGE_COUNTS as f64 / rig.counts_per_mm(),
                        )
                    } else {
                        Model3Params {
                            forward_band: bf,
                            reverse_band: br,
                            forward_transition: tf,
                            reverse_transition: tr,
                        }
                    };
                    (
                        rig,
                        ModelParams {
                            model1: m1,
                            model2: m2,
                            model3,
                            model4: m4,
                            backlash: bl,
                            bidir_table: bt,
                            reversal_deadband_counts: db,
                        },
                    )
                },
            )
    })
}

fn case() -> impl Strategy<Value = ((Rig, ModelParams), i32, Vec<Move>)> {
    (
        params(),
        -ACCURATE_RANGE_COUNTS..=ACCURATE_RANGE_COUNTS,
        moves(),
    )
}

/// Runs `kinds(k)` along the case's trajectory in fixed point and in the reference; returns the
/// worst difference in um, or an error at the first step that exceeds the tolerance.
fn compare(
    rig: &Rig,
    p: &ModelParams,
    x0: i32,
    moves: &[Move],
    kinds: impl Fn(usize) -> ModelKind,
) -> Result<f64, TestCaseError> {
    let c = p
        .build(rig)
        .map_err(|e| TestCaseError::fail(format!("build: {e}")))?;
    let mut s = ModelState::new(x0);
    let mut r = Reference::new(p, rig, x0).unwrap();
    let mut worst = 0.0f64;
    for (k, &x) in positions(x0, moves, ACCURATE_RANGE_COUNTS)
        .iter()
        .enumerate()
    {
        let kind = kinds(k);
        // A current that sweeps +-10 A (only Model 4 reads it).
        let current = I16F16::from_num(((k * 37) % 2000) as f64 / 100.0 - 10.0);
        let y = estimate_with_current(&c, kind, &mut s, x, current).to_num::<f64>();
        let yr = r.estimate_with_current_um(kind, x, current.to_num());
        let diff = (y - yr).abs();
        worst = worst.max(diff);
        prop_assert!(
            diff <= TOLERANCE_UM,
            "{kind} step {k} x={x}: fixed {y} um, reference {yr} um"
        );
        prop_assert_eq!(s.direction(), r.direction());
    }
    Ok(worst)
}

fn runner(cases: u32, seed: u8) -> TestRunner {
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    TestRunner::new_with_rng(
        config,
        TestRng::from_seed(RngAlgorithm::ChaCha, &[seed; 32]),
    )
}

fn accuracy(kind: ModelKind, seed: u8) {
    let worst = Cell::new(0.0f64);
    runner(1024, seed)
        .run(&case(), |((rig, p), x0, mv)| {
            let w = compare(&rig, &p, x0, &mv, |_| kind)?;
            worst.set(worst.get().max(w));
            Ok(())
        })
        .unwrap();
    println!("{kind}: max |fixed - f64| = {:.3e} um", worst.get());
}

#[test]
fn model1_matches_reference() {
    accuracy(ModelKind::Linear, 1);
}

#[test]
fn model2_matches_reference() {
    accuracy(ModelKind::Exponential, 2);
}

#[test]
fn model3_matches_reference() {
    accuracy(ModelKind::Table, 3);
}

#[test]
fn model4_matches_reference() {
    accuracy(ModelKind::Operator, 5);
}

#[test]
fn switching_models_matches_reference() {
    let worst = Cell::new(0.0f64);
    runner(512, 4)
        .run(
            &(case(), prop::collection::vec(0u8..7, 1..20)),
            |(((rig, p), x0, mv), sw)| {
                let every = 1 + 997 / sw.len();
                let kind = |k: usize| ModelKind::from_u8(sw[(k / every) % sw.len()]).unwrap();
                let w = compare(&rig, &p, x0, &mv, kind)?;
                worst.set(worst.get().max(w));
                Ok(())
            },
        )
        .unwrap();
    println!("switching: max |fixed - f64| = {:.3e} um", worst.get());
}

/// Extreme but valid parameters: slopes and rates near their format limits, large bands and
/// tables, any dead band.
fn extreme_params() -> impl Strategy<Value = (Rig, ModelParams)> {
    (
        params(),
        prop_oneof![Just(1.8f64), Just(-1.8), -1.8f64..1.8],
        prop_oneof![Just(16.0f64), 0.0f64..16.0],
        prop_oneof![Just(1.8f64), 0.0f64..1.8],
        prop_oneof![Just(-1000.0f64), -1000.0f64..0.0],
        any::<u32>(),
    )
        .prop_map(|((_, mut p), m, h, a, rate, db)| {
            let rig = Rig::PAPER;
            // Model 4's widths were spaced for another rig: keep them 1.5 counts apart on this one.
            let w = &mut p.model4.widths_mm;
            for j in 1..w.len() {
                w[j] = w[j].max(w[j - 1] + 1.5 / rig.counts_per_mm());
            }
            p.model1.m_mm_per_mm = m;
            p.model1.h_mm = h;
            p.model1.h_g_mm = h;
            p.model1.slope_a_mm_per_mm = a;
            p.model1.slope_b_mm_per_mm = 1.8 - a;
            p.model2.m_mm_per_mm = m;
            p.model2.h_mm = h;
            p.model2.h_g_mm = h / 2.0;
            p.model2.rate_a_per_mm = rate;
            p.model2.rate_b_per_mm = -1000.0 - rate;
            p.model2.amplitude_a_mm = 16.0 - h;
            p.model2.amplitude_b_mm = h;
            p.reversal_deadband_counts = db % 4 * (db >> 30);
            (rig, p)
        })
}

/// Positions anywhere in `i32`, including the extremes and steps across them.
fn wild_positions() -> impl Strategy<Value = Vec<i32>> {
    let x = prop_oneof![
        4 => any::<i32>(),
        1 => Just(i32::MIN),
        1 => Just(i32::MAX),
        1 => Just(0),
        1 => i32::MIN..i32::MIN + 500,
        1 => i32::MAX - 500..=i32::MAX,
    ];
    let walk = (x, prop::collection::vec(-400i32..=400, 0..50)).prop_map(|(x0, steps)| {
        let mut v = vec![x0];
        let mut x = x0;
        for s in steps {
            x = x.saturating_add(s);
            v.push(x);
        }
        v
    });
    prop::collection::vec(walk, 1..20).prop_map(|w| w.concat())
}

#[test]
fn no_panics_over_the_whole_i32_range() {
    runner(1024, 5)
        .run(
            &(
                extreme_params(),
                wild_positions(),
                prop::collection::vec(0u8..4, 1..8),
            ),
            |((rig, p), xs, kinds)| {
                let c = p
                    .build(&rig)
                    .map_err(|e| TestCaseError::fail(format!("{e}")))?;
                let mut s = ModelState::new(xs[0]);
                for (k, &x) in xs.iter().enumerate() {
                    let kind = ModelKind::from_u8(kinds[k % kinds.len()]).unwrap();
                    let y: I16F16 = estimate(&c, kind, &mut s, x);
                    // Defined, and in the band for Models 1 and 2 wherever the band fits.
                    let m = (p.model1.m_mm_per_mm * x as f64 / rig.counts_per_mm()
                        + p.model1.offset_mm)
                        * 1000.0;
                    let h = p.model1.h_mm * 1000.0;
                    // The slope's Q31 um per count is exact to half an LSB, 2^-32 um per count
                    // of |x|: up to 0.5 um at the ends of the i32 range.
                    let tol = 0.01 + (x as f64).abs() / (1u64 << 32) as f64;
                    if kind == ModelKind::Linear && m.abs() + h < 32_000.0 {
                        let yf = y.to_num::<f64>();
                        prop_assert!(
                            yf <= m + tol && yf >= m - h - tol,
                            "{} not in [{}, {}]",
                            yf,
                            m - h,
                            m
                        );
                    }
                }
                Ok(())
            },
        )
        .unwrap();
}

#[test]
fn largest_tables_and_extremes_do_not_panic() {
    // Every table at its size limit, spanning the whole i32 range of counts.
    let rig = Rig::PAPER;
    let cpm = rig.counts_per_mm();
    let mut p = ModelParams::PAPER;
    let span_mm = (i32::MAX as f64 - 1.0) / cpm;
    for band in [&mut p.model3.forward_band, &mut p.model3.reverse_band] {
        band.len = MAX_BAND_POINTS;
        for i in 0..MAX_BAND_POINTS {
            band.x_mm[i] = -span_mm + 2.0 * span_mm * i as f64 / (MAX_BAND_POINTS - 1) as f64;
            band.y_um[i] = if i % 2 == 0 { -15_000.0 } else { 15_000.0 };
        }
    }
    p.model3.reverse_band.y_um = p.model3.forward_band.y_um;
    for t in [
        &mut p.model3.forward_transition,
        &mut p.model3.reverse_transition,
    ] {
        t.n_d = MAX_TRANSITION_D;
        t.n_g0 = MAX_TRANSITION_G0;
        t.d_step_mm = 2.5 / cpm;
        t.g0_step_um = 2.5 / 65536.0;
        for row in t.gap_um.iter_mut() {
            for g in row.iter_mut() {
                *g = 2047.96875;
            }
        }
    }
    let c = p.build(&rig).expect("largest tables build");
    let mut s = ModelState::new(0);
    let xs = [
        0,
        i32::MAX,
        i32::MIN,
        i32::MAX,
        -1,
        1,
        i32::MIN + 1,
        i32::MAX - 1,
        0,
        -100,
        100,
        i32::MIN,
    ];
    for kind in ModelKind::ALL {
        for &x in &xs {
            let _ = estimate(&c, kind, &mut s, x);
        }
    }
    // Long steps through every segment both ways.
    for kind in ModelKind::ALL {
        let mut x = i32::MIN;
        while x < i32::MAX - (1 << 24) {
            let _ = estimate(&c, kind, &mut s, x);
            x += 1 << 24;
        }
        while x > i32::MIN + (1 << 24) {
            let _ = estimate(&c, kind, &mut s, x);
            x -= 3 << 22;
        }
    }
}
