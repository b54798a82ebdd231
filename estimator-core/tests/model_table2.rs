//! Behaviour of the three models with the paper's Table 2 parameters, the dead band, run-time
//! model switching, Model 3 built from Model 1, and configuration errors.

use estimator_core::fixed::types::I16F16;
use estimator_core::model::{
    estimate, BandParams, Direction, Model1Params, Model2Params, Model3Params, ModelCoeffs,
    ModelKind, ModelParams, ModelState, MAX_BAND_POINTS, MAX_TRANSITION_D, MAX_TRANSITION_G0,
};
use estimator_core::reference::Reference;
use estimator_core::rig::Rig;
use estimator_core::{ConfigError, ConfigField};

const RIG: Rig = Rig::PAPER;

fn cpm() -> f64 {
    RIG.counts_per_mm()
}

fn counts(mm: f64) -> i32 {
    (mm * cpm()).round() as i32
}

fn um(y: I16F16) -> f64 {
    y.to_num::<f64>()
}

fn paper() -> (ModelParams, ModelCoeffs) {
    let p = ModelParams::PAPER;
    let c = p.build(&RIG).expect("paper parameters build");
    (p, c)
}

/// Runs `kind` along `path` (counts) from `path[0]`, returning the outputs in um.
fn run(c: &ModelCoeffs, kind: ModelKind, path: &[i32]) -> Vec<f64> {
    let mut s = ModelState::new(path[0]);
    path.iter()
        .map(|&x| um(estimate(c, kind, &mut s, x)))
        .collect()
}

/// `from` to `to` (mm) in steps of `step` counts, both ends included.
fn ramp(from_mm: f64, to_mm: f64, step: i32) -> Vec<i32> {
    let (a, b) = (counts(from_mm), counts(to_mm));
    let mut v = Vec::new();
    let mut x = a;
    if b >= a {
        while x < b {
            v.push(x);
            x += step;
        }
    } else {
        while x > b {
            v.push(x);
            x -= step;
        }
    }
    v.push(b);
    v
}

fn lower_um(x: i32) -> f64 {
    let p = Model1Params::PAPER;
    (p.m_mm_per_mm * x as f64 / cpm() - p.h_mm) * 1000.0
}

fn upper_um(x: i32) -> f64 {
    Model1Params::PAPER.m_mm_per_mm * x as f64 / cpm() * 1000.0
}

#[test]
fn coeffs_size_and_layout() {
    let size = core::mem::size_of::<ModelCoeffs>();
    let m3 = core::mem::size_of::<estimator_core::model::Model3Coeffs>();
    println!(
        "size_of::<ModelCoeffs>() = {size} bytes (Model 3: {m3}); ModelState = {} bytes; \
         ModelParams = {} bytes",
        core::mem::size_of::<ModelState>(),
        core::mem::size_of::<ModelParams>(),
    );
    // What is used today (host build, closing distances included): growth must be deliberate.
    assert!(m3 <= 2608, "Model 3 storage {m3} B");
    // Model 4 with its belt observer (520 B: 64 guide points, 13 factors, the tracking gains,
    // the rest prediction, the control rate it was built for) and its offset as an `i64` in
    // Q31 (8 B more, 6 instructions a tick fewer: it starts the slope's sum).
    let m4 = core::mem::size_of::<estimator_core::model::Model4Coeffs>();
    assert!(m4 <= 688, "Model 4 storage {m4} B");
    assert!(size <= 5016, "ModelCoeffs {size} B");
    // Model 4 adds its plays, its slip observer, its low-passed current, its belt observer (128
    // B: 8 more for the carried slip's bound in counts, which took 10 instructions off the
    // tick) and the placement's prediction of it (16 B) to the state; Model 3 its line over
    // the current stretch and its half-drawn successor (40 B).
    assert!(core::mem::size_of::<ModelState>() <= 272);
}

#[test]
fn forward_start_rides_lower_edge_then_reverse_jumps_and_closes_linearly() {
    let (_, c) = paper();
    let p = Model1Params::PAPER;
    let mut path = ramp(0.0, 300.0, 97);
    let turn = path.len() - 1;
    path.extend(ramp(300.0, 0.0, 97).into_iter().skip(1));
    for kind in [ModelKind::Linear, ModelKind::Exponential, ModelKind::Table] {
        let y = run(&c, kind, &path);
        for k in 0..=turn {
            assert!((y[k] - lower_um(path[k])).abs() < 0.01, "{kind} k={k}");
        }
        // First reverse step: the fast jump h_g, plus the transition over one step.
        let jump = y[turn + 1] - y[turn];
        let step_mm = 97.0 / cpm();
        assert!(
            jump > p.h_g_mm * 1000.0 - 0.01
                && jump < p.h_g_mm * 1000.0 + 4.0 * step_mm * 1000.0 * 0.003,
            "{kind}: jump {jump} um"
        );
        // Far back: on the upper edge.
        let last = path.len() - 1;
        assert!((y[last] - upper_um(path[last])).abs() < 0.01, "{kind}");
    }
    // Model 1: in the reverse transition, y = y_d + h_g + b (x_d - x) exactly.
    let y = run(&c, ModelKind::Linear, &path);
    let x_d = path[turn];
    let y_d = y[turn];
    for k in turn + 1..path.len() {
        let d_mm = (x_d - path[k]) as f64 / cpm();
        let u = y_d + (p.h_g_mm + p.slope_b_mm_per_mm * d_mm) * 1000.0;
        let expect = u.min(upper_um(path[k]));
        assert!((y[k] - expect).abs() < 0.01, "k={k}: {} vs {expect}", y[k]);
    }
    // Closing distance (h - h_g) / (b + m) = 101.8 mm: last transition point and first edge point.
    let closing = (p.h_mm - p.h_g_mm) / (p.slope_b_mm_per_mm + p.m_mm_per_mm);
    assert!((closing - 101.80).abs() < 0.01);
    let first_edge = (turn + 1..path.len())
        .find(|&k| (y[k] - upper_um(path[k])).abs() < 1e-3)
        .unwrap();
    let d_edge = (x_d - path[first_edge]) as f64 / cpm();
    assert!(d_edge >= closing && d_edge < closing + 0.06, "{d_edge}");
    let c1 = c.closing(ModelKind::Linear);
    let f = c1.forward_mm.unwrap().to_num::<f64>();
    let r = c1.reverse_mm.unwrap().to_num::<f64>();
    assert!(
        (f - closing).abs() < 1e-3 && (r - closing).abs() < 1e-3,
        "{f} {r}"
    );
}

#[test]
fn model1_forward_slope_a_after_reverse_run() {
    let (_, c) = paper();
    let p = Model1Params::PAPER;
    // Reverse first (from 0 down to -200 mm), then forward: jump -h_g, slope -a.
    let mut path = ramp(0.0, -200.0, 131);
    let turn = path.len() - 1;
    path.extend(ramp(-200.0, 0.0, 131).into_iter().skip(1));
    let y = run(&c, ModelKind::Linear, &path);
    assert!((y[turn] - upper_um(path[turn])).abs() < 0.01);
    for k in turn + 1..path.len() {
        let d_mm = (path[k] - path[turn]) as f64 / cpm();
        let u = y[turn] - (p.h_g_mm + p.slope_a_mm_per_mm * d_mm) * 1000.0;
        let expect = u.max(lower_um(path[k]));
        assert!((y[k] - expect).abs() < 0.01, "k={k}");
    }
}

#[test]
fn model2_shape_closing_and_continuity() {
    let (_, c) = paper();
    let p = Model2Params::PAPER;
    let cl = c.closing(ModelKind::Exponential);
    let f = cl.forward_mm.unwrap().to_num::<f64>();
    let r = cl.reverse_mm.unwrap().to_num::<f64>();
    println!("Model 2 closing distances with Table 2: forward {f:.3} mm, reverse {r:.3} mm");
    // (h - h_g - A) / m = 151.0 mm and (h - h_g - B) / m = 132.2 mm, plus the exponential's tail.
    assert!((f - 151.0).abs() < 0.5, "{f}");
    assert!((r - 132.2).abs() < 2.0, "{r}");
    assert!(cl.always_closes());

    for (dir_fwd, closing) in [(true, f), (false, r)] {
        // Long run one way, then back: full-band transition.
        let (a, b) = if dir_fwd { (0.0, -300.0) } else { (0.0, 300.0) };
        let mut path = ramp(a, b, 53);
        let turn = path.len() - 1;
        path.extend(ramp(b, a, 53).into_iter().skip(1));
        let y = run(&c, ModelKind::Exponential, &path);
        let x_d = path[turn];
        let y_d = y[turn];
        let step_mm = 53.0 / cpm();
        let mut reached = None;
        for k in turn + 1..path.len() {
            let d_mm = ((path[k] - x_d) as f64 / cpm()).abs();
            let (u, edge) = if dir_fwd {
                let u = y_d
                    - (p.h_g_mm + p.amplitude_a_mm * (1.0 - (p.rate_a_per_mm * d_mm).exp()))
                        * 1000.0;
                (u, lower_um(path[k]))
            } else {
                let u = y_d
                    + (p.h_g_mm + p.amplitude_b_mm * (1.0 - (p.rate_b_per_mm * d_mm).exp()))
                        * 1000.0;
                (u, upper_um(path[k]))
            };
            let expect = if dir_fwd { u.max(edge) } else { u.min(edge) };
            assert!((y[k] - expect).abs() < 0.01, "k={k}: {} vs {expect}", y[k]);
            if reached.is_none() && (y[k] - edge).abs() < 1e-3 {
                reached = Some(d_mm);
            }
            if k > turn + 1 {
                // No step larger than the curve's steepest slope (A|a| or B|b|) or the band's m.
                let slope = (p.amplitude_a_mm * p.rate_a_per_mm.abs())
                    .max(p.amplitude_b_mm * p.rate_b_per_mm.abs())
                    .max(p.m_mm_per_mm);
                let dy = (y[k] - y[k - 1]).abs();
                assert!(dy <= slope * step_mm * 1000.0 + 1e-3, "k={k}: step {dy} um");
            }
        }
        let reached = reached.expect("meets the edge");
        assert!(
            (reached - closing).abs() < step_mm + 0.01,
            "{reached} vs {closing}"
        );
    }
}

#[test]
fn model2_never_closing_is_flagged() {
    let rig = RIG;
    let mut p = ModelParams::PAPER;
    p.model2.m_mm_per_mm = 0.0;
    let c = p.build(&rig).unwrap();
    assert_eq!(c.closing(ModelKind::Exponential).forward_mm, None);
    assert!(!c.closing(ModelKind::Exponential).always_closes());
    // Still well-behaved: the output settles on the asymptote inside the band and stays there.
    let mut path = ramp(0.0, -300.0, 211);
    path.extend(ramp(-300.0, 500.0, 211).into_iter().skip(1));
    let y = run(&c, ModelKind::Exponential, &path);
    // Reverse first: from the lower edge (-h) up by h_g + B, short of the upper edge (0) ...
    let turn = ramp(0.0, -300.0, 211).len() - 1;
    let m2 = p.model2;
    let rev_end = (-m2.h_mm + m2.h_g_mm + m2.amplitude_b_mm) * 1000.0;
    assert!((y[turn] - rev_end).abs() < 0.02, "{} vs {rev_end}", y[turn]);
    // ... then forward: down by h_g + A from there, short of the lower edge.
    let last = *y.last().unwrap();
    let expect = y[turn] - (m2.h_g_mm + m2.amplitude_a_mm) * 1000.0;
    assert!((last - expect).abs() < 0.01, "{last} vs {expect}");
    assert!(last > -m2.h_mm * 1000.0);
    p.model2.m_mm_per_mm = -0.001;
    assert_eq!(
        p.build(&rig)
            .unwrap()
            .closing(ModelKind::Exponential)
            .reverse_mm,
        None
    );
    // A large amplitude closes even without slope.
    p.model2.m_mm_per_mm = 0.0;
    p.model2.amplitude_a_mm = 0.3;
    assert!(p
        .build(&rig)
        .unwrap()
        .closing(ModelKind::Exponential)
        .forward_mm
        .is_some());
    // Model 1 whose slopes cannot close.
    let mut p = ModelParams::PAPER;
    p.model1.m_mm_per_mm = -0.002;
    assert!(!p
        .build(&rig)
        .unwrap()
        .closing(ModelKind::Linear)
        .always_closes());
}

#[test]
fn dead_band_ignores_jitter() {
    let mut p = ModelParams::PAPER;
    p.reversal_deadband_counts = 2;
    let c = p.build(&RIG).unwrap();
    for kind in [ModelKind::Linear, ModelKind::Exponential, ModelKind::Table] {
        let mut s = ModelState::new(0);
        let x0 = counts(50.0);
        let mut x = 0;
        while x < x0 {
            estimate(&c, kind, &mut s, x);
            x += 100;
        }
        let y0 = um(estimate(&c, kind, &mut s, x0));
        // Jitter of up to 2 counts back from the extreme (x0 + 1): still forward, on the edge.
        for j in [-1, 0, 1, 0, -1, 0, 1, -1, 0] {
            let y = um(estimate(&c, kind, &mut s, x0 + j));
            assert_eq!(s.direction(), Direction::Forward, "{kind}");
            assert!(!s.in_transition());
            assert!((y - lower_um(x0 + j)).abs() < 0.01, "{kind}");
            assert!((y - y0).abs() < 0.01);
        }
        // Three counts back from the extreme (x0 + 1): a reversal at the extreme.
        let y = um(estimate(&c, kind, &mut s, x0 - 2));
        assert_eq!(s.direction(), Direction::Reverse, "{kind}");
        assert_eq!(s.turning_point_counts(), x0 + 1);
        assert!(y - y0 > 100.0, "{kind}: jump {}", y - y0);
    }
    // With no dead band, one count back is a reversal (the paper's literal detector) ...
    p.reversal_deadband_counts = 0;
    let c = p.build(&RIG).unwrap();
    let mut s = ModelState::new(0);
    for x in [0, 100, 200, 199] {
        estimate(&c, ModelKind::Linear, &mut s, x);
    }
    assert_eq!(s.direction(), Direction::Reverse);
    // ... but standing still is not.
    for _ in 0..5 {
        estimate(&c, ModelKind::Linear, &mut s, 199);
        assert_eq!(s.direction(), Direction::Reverse);
    }
}

#[test]
fn model3_from_model1_reproduces_model1() {
    let (p, c) = paper();
    // A Figure 18-like scenario: abrupt reversals at full band and mid-transition.
    let legs_mm = [
        0.0, 250.0, 120.0, 180.0, 175.0, 300.0, -100.0, -40.0, -60.0, -20.0, -300.0, 100.0, 95.0,
        97.0, 0.0,
    ];
    let mut path = vec![0];
    for w in legs_mm.windows(2) {
        path.extend(ramp(w[0], w[1], 37).into_iter().skip(1));
    }
    let y1 = run(&c, ModelKind::Linear, &path);
    let y3 = run(&c, ModelKind::Table, &path);
    let worst = y1
        .iter()
        .zip(&y3)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    // Bilinear interpolation of the kink max(0, g0 - h_g - (a + m) d) errs by at most a quarter
    // of the change across one cell: ((a + m) d_step + g0_step) / 4 (5.6 um with Table 2).
    let t = &p.model3.forward_transition;
    let m1 = &p.model1;
    let bound =
        ((m1.slope_a_mm_per_mm + m1.m_mm_per_mm) * t.d_step_mm * 1000.0 + t.g0_step_um) / 4.0;
    println!(
        "Model 3 from Model 1 vs Model 1 over {} ticks: max |dy| = {worst:.3} um (bound {bound:.2})",
        path.len()
    );
    assert!(worst < bound, "{worst}");
    // The tables close where Model 1 does.
    let c3 = c.closing(ModelKind::Table);
    let c1 = p.model1.closing();
    let (f3, f1) = (
        c3.forward_mm.unwrap().to_num::<f64>(),
        c1.forward_mm.unwrap().to_num::<f64>(),
    );
    assert!(f3 >= f1 && f3 < f1 + 5.0, "{f3} {f1}");
}

#[test]
fn switching_models_at_run_time_is_bounded() {
    let (p, c) = paper();
    let mut r = Reference::new(&p, &RIG, 0).unwrap();
    let mut s = ModelState::new(0);
    let mut path = ramp(0.0, 200.0, 71);
    path.extend(ramp(200.0, 150.0, 71).into_iter().skip(1));
    path.extend(ramp(150.0, 170.0, 71).into_iter().skip(1));
    path.extend(ramp(170.0, -50.0, 71).into_iter().skip(1));
    let band_um = p.model1.h_mm * 1000.0;
    let mut prev: Option<f64> = None;
    for (k, &x) in path.iter().enumerate() {
        let kind = ModelKind::ALL[(k / 97) % 4];
        let y = um(estimate(&c, kind, &mut s, x));
        let yr = r.estimate_um(kind, x);
        assert!((y - yr).abs() < 0.05, "k={k} {kind}: {y} vs {yr}");
        if let (Some(py), true) = (prev, kind != ModelKind::None) {
            assert!((y - py).abs() <= band_um + 1.0, "k={k}: jump {}", y - py);
        }
        prev = (kind != ModelKind::None).then_some(y);
    }
}

#[test]
fn settle_keeps_direction_and_drops_the_transition() {
    let (_, c) = paper();
    let mut s = ModelState::new(0);
    for x in [0, 1000, 2000, 1500, 1000] {
        estimate(&c, ModelKind::Linear, &mut s, x);
    }
    assert_eq!(s.direction(), Direction::Reverse);
    assert!(s.in_transition());
    s.settle(1000);
    assert_eq!(s.direction(), Direction::Reverse);
    assert!(!s.in_transition());
    let y = um(estimate(&c, ModelKind::Linear, &mut s, 900));
    assert!((y - upper_um(900)).abs() < 0.01);
    s.reset(900);
    assert_eq!(s.direction(), Direction::Forward);
}

#[test]
fn model_kind_numbers_and_names() {
    for (i, k) in ModelKind::ALL.into_iter().enumerate() {
        assert_eq!(k as u8, i as u8);
        assert_eq!(ModelKind::from_u8(i as u8), Some(k));
        assert_eq!(ModelKind::parse(k.as_str()), Some(k));
    }
    assert_eq!(ModelKind::from_u8(ModelKind::ALL.len() as u8), None);
    assert_eq!(ModelKind::parse("model4"), Some(ModelKind::Operator));
    assert_eq!(ModelKind::parse("model5"), None);
    assert_eq!(ModelKind::BidirTable.as_str(), "bidir_table");
    assert_eq!(ModelKind::Exponential.as_str(), "model2");
}

fn build_err(f: impl FnOnce(&mut ModelParams)) -> ConfigError {
    let mut p = ModelParams::PAPER;
    f(&mut p);
    p.build(&RIG).expect_err("must be refused")
}

#[test]
fn config_errors_name_the_field() {
    use ConfigError::*;
    assert_eq!(
        build_err(|p| p.model1.h_mm = f64::NAN),
        NotFinite(ConfigField::Model1HMm)
    );
    assert_eq!(
        build_err(|p| p.model1.h_mm = -0.1),
        OutOfRange(ConfigField::Model1HMm)
    );
    assert_eq!(
        build_err(|p| p.model1.m_mm_per_mm = 5.0),
        OutOfRange(ConfigField::Model1MMmPerMm)
    );
    assert_eq!(
        build_err(|p| p.model1.slope_a_mm_per_mm = -0.1),
        OutOfRange(ConfigField::Model1SlopeAMmPerMm)
    );
    assert_eq!(
        build_err(|p| p.model1.slope_b_mm_per_mm = f64::INFINITY),
        NotFinite(ConfigField::Model1SlopeBMmPerMm)
    );
    assert_eq!(
        build_err(|p| p.model1.h_g_mm = 20.0),
        OutOfRange(ConfigField::Model1HGMm)
    );
    assert_eq!(
        build_err(|p| p.model2.rate_a_per_mm = 0.1),
        OutOfRange(ConfigField::Model2RateAPerMm)
    );
    assert_eq!(
        build_err(|p| p.model2.rate_b_per_mm = -1e9),
        OutOfRange(ConfigField::Model2RateBPerMm)
    );
    assert_eq!(
        build_err(|p| p.model2.amplitude_b_mm = -0.01),
        OutOfRange(ConfigField::Model2AmplitudeBMm)
    );
    assert_eq!(
        build_err(|p| p.model2.h_mm = f64::NAN),
        NotFinite(ConfigField::Model2HMm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_band.x_mm[3] = p.model3.forward_band.x_mm[2]),
        NotMonotonic(ConfigField::Model3ForwardBandXMm)
    );
    // Distinct in mm, identical after rounding to counts.
    assert_eq!(
        build_err(|p| p.model3.reverse_band.x_mm[3] = p.model3.reverse_band.x_mm[2] + 1e-5),
        NotMonotonic(ConfigField::Model3ReverseBandXMm)
    );
    // Increasing but not evenly spaced: off the even axis by 2 um (the tolerance is 1.5 um);
    // within it, accepted.
    assert_eq!(
        build_err(|p| p.model3.forward_band.x_mm[4] += 0.002),
        NotUniform(ConfigField::Model3ForwardBandXMm)
    );
    let mut p = ModelParams::PAPER;
    p.model3.reverse_band.x_mm[4] += 0.001;
    assert!(p.build(&Rig::PAPER).is_ok());
    // The ends set the axis: a moved end point moves the axis, and the inner points are off it.
    assert_eq!(
        build_err(|p| {
            let n = p.model3.reverse_band.len;
            p.model3.reverse_band.x_mm[n - 1] += 1.0;
        }),
        NotUniform(ConfigField::Model3ReverseBandXMm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_band.x_mm[0] = f64::NAN),
        NotFinite(ConfigField::Model3ForwardBandXMm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_band.x_mm[0] = -2e6),
        OutOfRange(ConfigField::Model3ForwardBandXMm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_band.len = 1),
        TableSize(ConfigField::Model3ForwardBandLen)
    );
    assert_eq!(
        build_err(|p| p.model3.reverse_band.len = MAX_BAND_POINTS + 1),
        TableSize(ConfigField::Model3ReverseBandLen)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_band.y_um[1] = 1e6),
        OutOfRange(ConfigField::Model3ForwardBandYUm)
    );
    // A reverse band below the forward band: negative band.
    assert_eq!(
        build_err(|p| p.model3.reverse_band.y_um[4] = p.model3.forward_band.y_um[4] - 1.0),
        OutOfRange(ConfigField::Model3ReverseBandYUm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_transition.gap_um[2][3] = -1.0),
        OutOfRange(ConfigField::Model3ForwardTransitionGapUm)
    );
    assert_eq!(
        build_err(|p| p.model3.reverse_transition.gap_um[0][0] = f64::NAN),
        NotFinite(ConfigField::Model3ReverseTransitionGapUm)
    );
    assert_eq!(
        build_err(|p| p.model3.reverse_transition.gap_um[0][0] = 3000.0),
        OutOfRange(ConfigField::Model3ReverseTransitionGapUm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_transition.n_d = MAX_TRANSITION_D + 1),
        TableSize(ConfigField::Model3ForwardTransitionND)
    );
    assert_eq!(
        build_err(|p| p.model3.reverse_transition.n_g0 = MAX_TRANSITION_G0 + 1),
        TableSize(ConfigField::Model3ReverseTransitionNG0)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_transition.d_step_mm = 1e-5),
        OutOfRange(ConfigField::Model3ForwardTransitionDStepMm)
    );
    assert_eq!(
        build_err(|p| p.model3.forward_transition.g0_step_um = 0.0),
        OutOfRange(ConfigField::Model3ForwardTransitionG0StepUm)
    );
    let mut p = ModelParams::PAPER;
    p.model1.h_mm = f64::NAN;
    assert_eq!(p.build(&RIG).unwrap_err().field(), "model1.h_mm");
    let bad_rig = Rig {
        gear_ratio: 0.0,
        ..Rig::PAPER
    };
    assert_eq!(
        ModelParams::PAPER.build(&bad_rig),
        Err(OutOfRange(ConfigField::RigGearRatio))
    );
}

#[test]
fn band_params_from_points() {
    let pts: Vec<(f64, f64)> = (0..MAX_BAND_POINTS).map(|i| (i as f64, 0.0)).collect();
    assert!(BandParams::from_points(&pts).is_some());
    let pts: Vec<(f64, f64)> = (0..=MAX_BAND_POINTS).map(|i| (i as f64, 0.0)).collect();
    assert!(BandParams::from_points(&pts).is_none());
    let m3 = Model3Params::from_model1(&Model1Params::PAPER, 100.0);
    assert!(m3.build(cpm()).is_ok());
}

/// Model 4 with the narrowest knot grid `build` accepts (one count, the reciprocal at
/// `u32::MAX`) and its knots as far below zero as allowed, run over the whole `i32` range: no
/// overflow or index panic in the hat lookup, and beyond the knots the hats contribute nothing.
#[test]
fn model4_extreme_knot_grid_never_panics() {
    let rig = Rig::PAPER;
    let cpm = rig.counts_per_mm();
    let mut p = ModelParams::PAPER;
    p.model4.knot_step_mm = 1.0 / cpm;
    p.model4.knot_start_mm = -((1u32 << 30) as f64 - 2.0) / cpm;
    p.model4.knot_um = [100.0; estimator_core::model::operator::N_KNOTS];
    let c = p.build(&rig).unwrap();
    let mut s = ModelState::new(0);
    for x in [
        0,
        -(1 << 30),
        -(1 << 30) + 3,
        1 << 30,
        i32::MAX - 1,
        i32::MAX,
        i32::MIN,
        i32::MIN + 1,
        0,
    ] {
        let y = estimate(&c, ModelKind::Operator, &mut s, x);
        if x > -(1 << 29) {
            // Far past the knots: only the (zero) other terms.
            assert_eq!(y, I16F16::ZERO, "x = {x}");
        }
    }
}
