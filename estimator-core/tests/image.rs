//! The calibration image: the host's coefficients arrive exactly, and every way an image can be
//! wrong is refused with a reason; whatever decodes evaluates without a panic.

use estimator_core::blob::{self, crc32, BlobError};
use estimator_core::image::{self, MAX_BYTES};
use estimator_core::model::belt::BeltParams;
use estimator_core::model::operator::{N_KNOTS, N_OPS};
use estimator_core::model::BeltTerm;
use estimator_core::model::Direction::{Forward, Reverse};
use estimator_core::model::{estimate_with_current, ModelKind, ModelParams, ModelState};
use estimator_core::rig::Rig;
use fixed::types::I16F16;
use proptest::prelude::*;

fn params() -> ModelParams {
    // Offsets and a Model 4 with weights, so that every section carries non-zero values.
    let mut p = ModelParams::PAPER;
    p.model1.offset_mm = -0.0423;
    p.model2.offset_mm = 0.0117;
    p.model4.offset_um = -12.5;
    p.model4.play_um_per_mm[0] = 900.0;
    p.model4.play_forward_um_per_mm[2] = -40.0;
    p.model4.knot_um[2] = 7.25;
    p.model4.slip = estimator_core::model::slip::SlipParams {
        load_um: [61.5, 70.25],
        um_per_a: [22.0, -3.5],
        creep_per_mm: 0.03,
        limit_um: 150.0,
        half_gap_um: 140.0,
        weight: -0.75,
    };
    p.backlash.backlash_um = 120.0;
    let mut physics = BeltParams::PAPER;
    physics.guide_bins = GUIDE_BINS;
    physics.guide_delta_n[3] = 0.75;
    p.model4.belt = Some(BeltTerm {
        physics,
        tick_s: 1.0 / 2000.0,
        step_ticks: 6,
        weight: -0.875,
        rest_um: [-131.5, 140.25],
        half_travel_mm: [0.25, 12.5],
        fast_share: 0.625,
    });
    p
}

/// The belt observer's guide profile in the test's parameters.
const GUIDE_BINS: usize = 30;

fn paper_image() -> Vec<u8> {
    image::of_params(&params(), &Rig::PAPER).unwrap()
}

/// Re-signs a modified payload so that only the field checks can catch it.
fn reseal(b: &mut [u8]) {
    let crc = crc32(&[&b[..12], &b[16..]]);
    b[12..16].copy_from_slice(&crc.to_le_bytes());
}

/// Where fields sit: header 16, geometry 24, deadband 4, Model 1 (m, offset, h, h_g, a, b),
/// Model 2 (m, offset, h, h_g, A, B, two rates of 8 bytes), then Model 3's bands.
const MODEL1: usize = 16 + 24 + 4;
const MODEL2: usize = MODEL1 + 24;
const MODEL3: usize = MODEL2 + 40;
/// Model 4's section: widths and two weight sets, five words, the knots, eight words, the slip
/// observer's nine, then the belt observer's (252 bytes and its guide points).
const MODEL4_BYTES: usize = 4 * (3 * N_OPS + 5 + N_KNOTS + 8 + 9) + 252 + 4 * GUIDE_BINS;

#[test]
fn coefficients_arrive_exactly_and_re_encode_to_the_same_bytes() {
    let rig = Rig::PAPER;
    for p in [ModelParams::PAPER, params()] {
        // What the drive gets is the build of the parameters as a blob holds them.
        let mut buf = vec![0u8; blob::MAX_BYTES];
        let n = blob::encode(&p, &rig, &mut buf).unwrap();
        let built = blob::decode(&buf[..n], &rig).unwrap().build(&rig).unwrap();
        let bytes = image::of_params(&p, &rig).unwrap();
        assert!(bytes.len() <= MAX_BYTES);
        let c = image::decode(&bytes, &rig).unwrap();
        // Closing distances included (the host's diagnostics travel with the image).
        assert_eq!(c, built);
        let mut again = vec![0u8; MAX_BYTES];
        let n = image::encode(&c, &rig, &mut again).unwrap();
        assert_eq!(&again[..n], &bytes[..]);
    }
    // A blob's image is its parameters' image; quantising twice changes nothing.
    let mut buf = vec![0u8; blob::MAX_BYTES];
    let n = blob::encode(&params(), &rig, &mut buf).unwrap();
    let quantised = blob::decode(&buf[..n], &rig).unwrap();
    assert_eq!(
        image::from_blob(&buf[..n]).unwrap(),
        image::of_params(&quantised, &rig).unwrap()
    );
    assert_eq!(
        image::from_blob(&buf[..n]).unwrap(),
        image::of_params(&params(), &rig).unwrap()
    );
    // The backlash's per-direction values may exceed the range of its parameters.
    let mut wide = params();
    wide.backlash.offset_um = -15_000.0;
    wide.backlash.backlash_um = 10_000.0;
    let bytes = image::of_params(&wide, &rig).unwrap();
    assert_eq!(
        image::decode(&bytes, &rig)
            .unwrap()
            .backlash()
            .at(Forward)
            .to_num::<f64>(),
        -20_000.0
    );
    // The largest tables fit the drive's buffer.
    let mut big = params();
    big.bidir_table.rows = estimator_core::model::MAX_BIDIR_ROWS;
    big.bidir_table.step_mm = 1.0;
    assert!(image::of_params(&big, &rig).unwrap().len() <= MAX_BYTES);
}

#[test]
fn damaged_images_are_refused_with_the_reason() {
    let rig = Rig::PAPER;
    let good = paper_image();
    assert_eq!(image::decode(&good[..8], &rig), Err(BlobError::Truncated));
    for cut in [16, 100, good.len() - 1] {
        assert_eq!(image::decode(&good[..cut], &rig), Err(BlobError::Truncated));
    }
    let mut long = good.clone();
    long.push(0);
    assert_eq!(image::decode(&long, &rig), Err(BlobError::TooLong));
    assert_eq!(
        image::decode(&vec![0u8; MAX_BYTES + 1], &rig),
        Err(BlobError::TooLong)
    );
    let mut b = good.clone();
    b[good.len() / 2] ^= 0x10;
    assert_eq!(image::decode(&b, &rig), Err(BlobError::BadChecksum));
    let mut b = good.clone();
    b[0] = b'X';
    assert_eq!(image::decode(&b, &rig), Err(BlobError::BadMagic));
    let mut b = good.clone();
    b[4] = 9;
    reseal(&mut b);
    assert_eq!(
        image::decode(&b, &rig),
        Err(BlobError::UnsupportedVersion(9))
    );
    // A version 1 image (Model 4 weighted Model 1, no low-passed current) is refused by its
    // version, not misread.
    let mut b = good.clone();
    b[4] = 1;
    reseal(&mut b);
    assert_eq!(
        image::decode(&b, &rig),
        Err(BlobError::UnsupportedVersion(1))
    );
    // A calibration blob is not an image (host tools convert it with `image::from_blob`).
    let mut buf = vec![0u8; blob::MAX_BYTES];
    let n = blob::encode(&params(), &rig, &mut buf).unwrap();
    assert_eq!(image::decode(&buf[..n], &rig), Err(BlobError::BadMagic));
    // Built for another geometry.
    let other = Rig {
        pulley_teeth: 15,
        ..Rig::PAPER
    };
    assert_eq!(image::decode(&good, &other), Err(BlobError::RigMismatch));
}

/// Writes `bytes` at `at`, reseals, and returns the refusal's field.
fn refused_field(at: usize, bytes: &[u8]) -> &'static str {
    let mut b = paper_image();
    b[at..at + bytes.len()].copy_from_slice(bytes);
    reseal(&mut b);
    match image::decode(&b, &Rig::PAPER) {
        Err(BlobError::Invalid(e)) => e.field().name(),
        other => panic!("at {at}: {other:?}"),
    }
}

/// Each `(offset, bytes, field)`: written at the offset and re-signed, refused naming the field.
fn assert_refusals(cases: &[(usize, &[u8], &str)]) {
    for &(at, bytes, field) in cases {
        assert_eq!(refused_field(at, bytes), field, "bytes {bytes:?} at {at}");
    }
}

#[test]
fn well_signed_nonsense_is_refused_naming_the_field() {
    let neg = (-5i32 << 16).to_le_bytes();
    assert_refusals(&[
        (MODEL1 + 8, &neg, "model1.h_mm"),
        (MODEL1 + 12, &neg, "model1.h_g_mm"),
        (
            MODEL1 + 16,
            &(-1i32).to_le_bytes(),
            "model1.slope_a_mm_per_mm",
        ),
        (
            MODEL1 + 4,
            &(20_000i32 << 16).to_le_bytes(),
            "model1.offset_mm",
        ),
        (MODEL2 + 16, &neg, "model2.amplitude_a_mm"),
        // A rate's shift beyond 63.
        (MODEL2 + 28, &64u16.to_le_bytes(), "model2.rate_a_per_mm"),
        // Band: too many points, an axis step under two counts or of none, a value beyond the
        // format's range.
        (MODEL3, &65u16.to_le_bytes(), "model3.forward_band.len"),
        (
            MODEL3 + 8,
            &((1u32 << 31) + 1).to_le_bytes(),
            "model3.forward_band.x_mm",
        ),
        (MODEL3 + 8, &0u32.to_le_bytes(), "model3.forward_band.x_mm"),
        (
            MODEL3 + 12,
            &i32::MAX.to_le_bytes(),
            "model3.forward_band.y_um",
        ),
    ]);
}

#[test]
fn every_section_is_checked() {
    // The later sections' offsets follow from the table sizes of the coefficients.
    let rig = Rig::PAPER;
    let p = params();
    let good = image::of_params(&p, &rig).unwrap();
    let c = p.build(&rig).unwrap();
    let m3 = c.model3();
    let bands = 24 + 4 * (m3.band(Forward).len() + m3.band(Reverse).len());
    let trans = |t: &estimator_core::model::TransitionCoeffs| 12 + 2 * t.n_d() * t.n_g0();
    let transition = MODEL3 + bands;
    let backlash = transition + trans(m3.transition(Forward)) + trans(m3.transition(Reverse));
    let bidir = backlash + 8;
    let model4 = bidir + 12 + 4 * c.bidir().rows();
    assert_eq!(
        model4 + MODEL4_BYTES + 24,
        good.len(),
        "the layout this test assumes"
    );
    let pitch_rate = model4 + 4 * (3 * N_OPS + 5 + N_KNOTS);
    let slip = pitch_rate + 4 * 8;
    // The belt observer's section, its factors, words and lengths.
    let belt = slip + 4 * 9;
    let gains = belt + 40;
    let words = gains + 8 * 13;
    let lengths = words + 28 + 28;
    assert_refusals(&[
        (
            transition,
            &17u16.to_le_bytes(),
            "model3.forward_transition.n_d",
        ),
        (
            transition + 4,
            &0u32.to_le_bytes(),
            "model3.forward_transition.d_step_mm",
        ),
        (bidir, &1u16.to_le_bytes(), "bidir_table.rows"),
        (bidir + 8, &0u32.to_le_bytes(), "bidir_table.step_mm"),
        // Model 4: widths out of order, a zero width, a period under 16 counts, a harmonic's
        // amplitude below zero, the low-passed current's weight, the slip observer's load
        // acting the wrong way, renewal, limit, half gap and weight.
        (model4 + 4, &1i32.to_le_bytes(), "model4.widths_mm"),
        (model4, &0i32.to_le_bytes(), "model4.widths_mm"),
        (pitch_rate, &(1u32 << 29).to_le_bytes(), "model4.pitch_mm"),
        // A harmonic's amplitude below zero (its phase takes any turn).
        (pitch_rate + 4, &(-1i32).to_le_bytes(), "model4.pitch_um"),
        (pitch_rate + 16, &(-1i32).to_le_bytes(), "model4.turn_um"),
        (
            slip - 4,
            &i32::MAX.to_le_bytes(),
            "model4.current_lp_um_per_a",
        ),
        (slip + 4, &(-1i32).to_le_bytes(), "model4.slip.load_um"),
        (
            slip + 16,
            &((1u32 << 28) + 1).to_le_bytes(),
            "model4.slip.creep_per_mm",
        ),
        (slip + 24, &0i32.to_le_bytes(), "model4.slip.limit_um"),
        (
            slip + 28,
            &((2049i32) << 16).to_le_bytes(),
            "model4.slip.half_gap_um",
        ),
        (
            slip + 32,
            &((8i32 << 16) + 1).to_le_bytes(),
            "model4.slip.weight",
        ),
        // The belt observer: its presence word, control rate, weight, a factor's shift and sign, the
        // friction coefficients beyond 1, the guide profile's length, the span from the pulley
        // beyond the belt, a length, a tracking gain and the step.
        (belt, &2u32.to_le_bytes(), "model4.belt.step_ticks"),
        (belt + 4, &0u32.to_le_bytes(), "drive.rate_hz"),
        (belt + 4, &100_001u32.to_le_bytes(), "drive.rate_hz"),
        (
            belt + 8,
            &((8i32 << 16) + 1).to_le_bytes(),
            "model4.belt.weight",
        ),
        (
            belt + 24,
            &64u16.to_le_bytes(),
            "model4.belt.half_travel_mm",
        ),
        (gains + 4, &0u32.to_le_bytes(), "model4.belt.m_per_count"),
        (
            gains + 8 * 12,
            &(-1i32).to_le_bytes(),
            "model4.belt.guide_profile_step_m",
        ),
        (
            gains + 8 * 12 + 4,
            &32u32.to_le_bytes(),
            "model4.belt.guide_profile_step_m",
        ),
        (words, &0i32.to_le_bytes(), "model4.belt.mu_kinetic"),
        (
            words + 4,
            &(1i32 << 30).to_le_bytes(),
            "model4.belt.mu_static",
        ),
        (
            words + 16,
            &(8i32 << 28).to_le_bytes(),
            "model4.belt.wrap_rad",
        ),
        // Preload times wrap beyond 4 kN times 7 rad, and a `1 / L` that is not the belt's.
        (
            words + 24,
            &(28_001i32 << 16).to_le_bytes(),
            "model4.belt.preload_n",
        ),
        (gains + 8 * 11, &1i32.to_le_bytes(), "model4.belt.length_m"),
        (
            words + 28 + 20,
            &65u32.to_le_bytes(),
            "model4.belt.guide_profile_n",
        ),
        (lengths, &0i32.to_le_bytes(), "model4.belt.half_gap_m"),
        (lengths + 8, &100i32.to_le_bytes(), "model4.belt.length_m"),
        (
            lengths + 12,
            &(50i32 << 16).to_le_bytes(),
            "model4.belt.span_offset_m",
        ),
        (
            lengths + 24 + 4 * GUIDE_BINS,
            &u64::MAX.to_le_bytes(),
            "model4.belt.step_ticks",
        ),
        (
            lengths + 48 + 4 * GUIDE_BINS,
            &17u32.to_le_bytes(),
            "model4.belt.step_ticks",
        ),
    ]);
}

/// Positions anywhere in `i32`, with walks around them.
fn wild_positions() -> impl Strategy<Value = Vec<i32>> {
    let x = prop_oneof![
        4 => any::<i32>(),
        1 => Just(i32::MIN),
        1 => Just(i32::MAX),
        2 => -100_000i32..100_000,
    ];
    (x, prop::collection::vec(-3000i32..=3000, 0..60)).prop_map(|(x0, steps)| {
        let mut v = vec![x0];
        let mut x = x0;
        for s in steps {
            x = x.saturating_add(s);
            v.push(x);
        }
        v
    })
}

/// Any well-signed image with changed words either is refused or evaluates every model
/// everywhere without a panic; enough of them decode for that to mean something.
#[test]
fn whatever_decodes_evaluates_safely() {
    use proptest::test_runner::{Config, TestRunner};
    let decoded = std::cell::Cell::new(0u32);
    let mut runner = TestRunner::new(Config {
        cases: 3000,
        failure_persistence: None,
        ..Config::default()
    });
    let case = (
        prop::collection::vec((0usize..5000, any::<u32>()), 1..6),
        wild_positions(),
        any::<i32>(),
    );
    runner
        .run(&case, |(edits, xs, current)| {
            let mut b = paper_image();
            for (at, word) in edits {
                let at = 16 + at % (b.len() - 20);
                b[at..at + 4].copy_from_slice(&word.to_le_bytes());
            }
            reseal(&mut b);
            if let Ok(c) = image::decode(&b, &Rig::PAPER) {
                decoded.set(decoded.get() + 1);
                for kind in ModelKind::ALL {
                    let mut s = ModelState::new(xs[0]);
                    for &x in &xs {
                        estimate_with_current(&c, kind, &mut s, x, I16F16::from_bits(current));
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    assert!(
        decoded.get() >= 300,
        "only {} of 3000 decoded",
        decoded.get()
    );
}

/// The belt observer is built for one control rate: a drive at another refuses the image by
/// that reason before it reads anything in (checking and decoding alike), one at the rate takes
/// it, and host tools read it whatever the rate (the coefficients say which).
#[test]
fn a_belt_observer_for_another_control_rate_is_refused() {
    let rig = Rig::PAPER;
    let good = paper_image();
    assert_eq!(image::check(&good, &rig, 2000), Ok(()));
    assert_eq!(
        image::check(&good, &rig, 4000),
        Err(BlobError::RateMismatch)
    );
    let mut c = estimator_core::model::ModelCoeffs::ZERO;
    assert_eq!(
        image::decode_into(&good, &rig, 1000, &mut c),
        Err(BlobError::RateMismatch)
    );
    let c = image::decode(&good, &rig).unwrap();
    assert_eq!(c.model4().belt().map(|b| b.rate_hz()), Some(2000));
    assert!(BlobError::RateMismatch
        .to_string()
        .contains("drive.rate_hz"));
    // Without a belt observer the image holds no rate: any drive's takes it.
    let mut p = params();
    p.model4.belt = None;
    let plain = image::of_params(&p, &rig).unwrap();
    assert_eq!(image::check(&plain, &rig, 4000), Ok(()));
}
