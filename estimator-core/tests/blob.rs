//! The calibration blob: round trip, and every way a blob can be wrong is refused with a reason.

use estimator_core::blob::{
    crc32, decode, encode, BlobError, MAX_BYTES, MODEL4_NO_BELT_BYTES as MODEL4_BYTES,
};
use estimator_core::drive::{Command, Drive, DriveConfig, Sample};
use estimator_core::model::{ModelKind, ModelParams};
use estimator_core::rig::Rig;
use estimator_core::ConfigField;
use proptest::prelude::*;

fn paper_blob() -> Vec<u8> {
    let mut p = ModelParams::PAPER;
    p.model1.offset_mm = -0.0423;
    p.model2.offset_mm = 0.0117;
    let mut buf = vec![0u8; MAX_BYTES];
    let n = encode(&p, &Rig::PAPER, &mut buf).unwrap();
    buf.truncate(n);
    buf
}

#[test]
fn crc32_matches_the_ieee_check_value() {
    assert_eq!(crc32(&[b"123456789"]), 0xCBF4_3926);
    assert_eq!(crc32(&[b"1234", b"56789"]), 0xCBF4_3926);
}

#[test]
fn round_trip_quantises_within_the_format() {
    let blob = paper_blob();
    assert!(blob.len() <= MAX_BYTES);
    let p = decode(&blob, &Rig::PAPER).unwrap();
    let q = ModelParams::PAPER;
    assert!((p.model1.m_mm_per_mm - q.model1.m_mm_per_mm).abs() < 1e-8);
    assert!((p.model1.offset_mm + 0.0423).abs() < 1e-7);
    assert!((p.model2.offset_mm - 0.0117).abs() < 1e-7);
    assert!((p.model2.rate_b_per_mm - q.model2.rate_b_per_mm).abs() < 1e-7);
    assert_eq!(p.model3.forward_band.len, q.model3.forward_band.len);
    for i in 0..q.model3.forward_transition.n_d {
        for j in 0..q.model3.forward_transition.n_g0 {
            let (a, b) = (
                p.model3.forward_transition.gap_um[i][j],
                q.model3.forward_transition.gap_um[i][j],
            );
            assert!((a - b).abs() <= 1.0 / 64.0, "{a} vs {b}");
        }
    }
    // Encoding the decoded parameters again gives the same bytes: the format is a fixed point.
    let mut again = vec![0u8; MAX_BYTES];
    let n = encode(&p, &Rig::PAPER, &mut again).unwrap();
    assert_eq!(&again[..n], &blob[..]);
}

#[test]
fn each_defect_has_its_reason() {
    let good = paper_blob();
    let rig = Rig::PAPER;
    assert_eq!(decode(&good[..10], &rig), Err(BlobError::Truncated));
    assert_eq!(
        decode(&good[..good.len() - 1], &rig),
        Err(BlobError::Truncated)
    );
    let mut long = good.clone();
    long.push(0);
    assert_eq!(decode(&long, &rig), Err(BlobError::TooLong));
    let mut b = good.clone();
    b[0] = b'X';
    assert_eq!(decode(&b, &rig), Err(BlobError::BadMagic));
    // A version 1 blob (no baselines) is refused by its version, not misread.
    let mut b = good.clone();
    b[4] = 1;
    assert_eq!(decode(&b, &rig), Err(BlobError::UnsupportedVersion(1)));
    // Nor is version 3, where Model 4 weighted Model 1 and had no low-passed current.
    let mut b = good.clone();
    b[4] = 3;
    assert_eq!(decode(&b, &rig), Err(BlobError::UnsupportedVersion(3)));
    let mut b = good.clone();
    b[40] ^= 0x10;
    assert_eq!(decode(&b, &rig), Err(BlobError::BadChecksum));
    let other = Rig {
        pulley_teeth: 18,
        ..Rig::PAPER
    };
    assert_eq!(decode(&good, &other), Err(BlobError::RigMismatch));
    assert_eq!(decode(&[], &rig), Err(BlobError::Truncated));
    assert_eq!(
        decode(&vec![0u8; MAX_BYTES + 1], &rig),
        Err(BlobError::TooLong)
    );
    let mut small = [0u8; 64];
    assert_eq!(
        encode(&ModelParams::PAPER, &rig, &mut small),
        Err(BlobError::BufferTooSmall)
    );
}

/// Where fields sit in a blob: header 16, geometry 24 (lines, teeth, gear f64, pitch f64),
/// deadband 4; then Model 1 (m, offset, h, ..) and Model 2 (8 words) before Model 3's bands.
const PAYLOAD: usize = 16 + 24 + 4;
const MODEL1_H: usize = PAYLOAD + 8;
const MODEL3_BANDS: usize = PAYLOAD + 24 + 32;

/// Re-signs a modified payload so that only the semantic checks can catch it.
fn resign(b: &mut [u8]) {
    let crc = crc32(&[&b[..12], &b[16..]]);
    b[12..16].copy_from_slice(&crc.to_le_bytes());
}

#[test]
fn well_signed_nonsense_is_refused_by_the_model_checks() {
    let rig = Rig::PAPER;
    let mut b = paper_blob();
    // model1.h (payload offset: geometry, deadband, then m and offset) negative.
    b[MODEL1_H..MODEL1_H + 4].copy_from_slice(&(-5i32 << 16).to_le_bytes());
    resign(&mut b);
    assert!(matches!(decode(&b, &rig), Err(BlobError::Invalid(e)) if e.field() == "model1.h_mm"));
    // forward band count beyond the table.
    let mut b = paper_blob();
    let band_at = MODEL3_BANDS;
    b[band_at..band_at + 2].copy_from_slice(&500u16.to_le_bytes());
    resign(&mut b);
    assert_eq!(
        decode(&b, &rig),
        Err(BlobError::BadCount(ConfigField::Model3ForwardBand))
    );
    // The bidirectional table (before Model 4: rows, 0, x0, step, 2 rows of 2 values) with
    // one row, with too many, and with a step of zero.
    for (rows, want) in [
        (1u16, Err(BlobError::BadCount(ConfigField::BidirTableRows))),
        (257, Err(BlobError::BadCount(ConfigField::BidirTableRows))),
        (3, Err(BlobError::Truncated)),
    ] {
        let mut b = paper_blob();
        let at = b.len() - MODEL4_BYTES - 28;
        b[at..at + 2].copy_from_slice(&rows.to_le_bytes());
        resign(&mut b);
        assert_eq!(decode(&b, &rig), want, "{rows} rows");
    }
    let mut b = paper_blob();
    let at = b.len() - MODEL4_BYTES - 20;
    b[at..at + 4].copy_from_slice(&0i32.to_le_bytes());
    resign(&mut b);
    assert!(
        matches!(decode(&b, &rig), Err(BlobError::Invalid(e)) if e.field() == "bidir_table.step_mm")
    );
}

#[test]
fn drive_loads_good_images_and_refuses_bad_ones_unchanged() {
    let mut d = Drive::new(&DriveConfig::paper_rig()).unwrap();
    d.step(Sample::default());
    d.command(Command::SelectModel(ModelKind::Linear)).unwrap();
    let before = d.models().clone();
    let good = estimator_core::image::from_blob(&paper_blob()).unwrap();
    // A blob is a file for tools; the drive loads the image built from it.
    assert_eq!(d.load_calibration(&paper_blob()), Err(BlobError::BadMagic));
    let mut bad = good.clone();
    bad[30] ^= 1;
    assert_eq!(d.load_calibration(&bad), Err(BlobError::BadChecksum));
    assert_eq!(d.models(), &before);
    // Well signed, a bad value in the last section: refused before anything is read in (the
    // slip observer's weight, before the belt observer's presence word and the closing
    // distances).
    let mut bad = good.clone();
    let at = bad.len() - 24 - 4 - 4;
    bad[at..at + 4].copy_from_slice(&(9i32 << 16).to_le_bytes());
    resign(&mut bad);
    assert!(
        matches!(d.load_calibration(&bad), Err(BlobError::Invalid(e)) if e.field() == "model4.slip.weight")
    );
    assert_eq!(d.models(), &before);
    d.load_calibration(&good).unwrap();
    assert_ne!(d.models(), &before);
    // The offset shows in the estimate at rest on the forward edge: m*0 + c - h.
    let y = d
        .step(Sample::default())
        .telemetry
        .est_error_um
        .to_num::<f64>();
    assert!((y - (-42.3 - 340.0)).abs() < 0.01, "{y}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]
    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..6000)) {
        let _ = decode(&bytes, &Rig::PAPER);
    }

    #[test]
    fn corrupted_blobs_never_decode_silently(pos in 0usize..5000, bit in 0u8..8) {
        let mut b = paper_blob();
        let pos = pos % b.len();
        b[pos] ^= 1 << bit;
        prop_assert!(decode(&b, &Rig::PAPER).is_err());
    }
}
