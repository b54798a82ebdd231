//! The core's vectors on the Cortex-M4: the expected values come from the same code run on the
//! host (`build.rs`), so every comparison here is bit for bit. Run with `cargo test-target`.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
mod vectors {
    pub use estimator_core::vectors::*;
    include!(concat!(env!("OUT_DIR"), "/core_vectors.rs"));
}

/// A paper-rig drive in a static (`Drive::new` and its configuration take a lot of stack).
#[cfg(target_os = "none")]
#[inline(never)]
fn static_drive() -> &'static mut estimator_core::drive::Drive {
    use estimator_core::drive::{Drive, DriveConfig};
    let Some(slot) = cortex_m::singleton!(: Option<Drive> = None) else {
        defmt::panic!("twice")
    };
    let Ok(d) = Drive::new(&DriveConfig::paper_rig()) else {
        defmt::panic!("paper rig refused")
    };
    slot.insert(d)
}

/// `Drive::load_calibration`, kept out of the caller's frame (it needs tens of KiB of stack).
#[cfg(target_os = "none")]
#[inline(never)]
fn load(
    drive: &mut estimator_core::drive::Drive,
    blob: &[u8],
) -> Result<(), estimator_core::blob::BlobError> {
    drive.load_calibration(blob)
}

/// Sends `blob` through a link endpoint (begin, chunks, commit); true if every step was acked.
#[cfg(target_os = "none")]
#[inline(never)]
fn endpoint_transfer(drive: &mut estimator_core::drive::Drive, blob: &[u8]) -> bool {
    use belt_link::{crc32, Reply, Request, CHUNK_MAX};
    use estimator_core::endpoint::{Effect, Endpoint};
    let Some(endpoint) = cortex_m::singleton!(: Endpoint = Endpoint::new()) else {
        defmt::panic!("twice")
    };
    let ack = |e: Effect| matches!(e, Effect::Reply(Reply::Ack { .. }));
    let begin = Request::CalBegin {
        total_len: blob.len() as u32,
        crc32: crc32(blob),
    };
    let mut ok = ack(endpoint.handle_inline(&begin, drive).0);
    for (i, piece) in blob.chunks(CHUNK_MAX).enumerate() {
        let mut data = [0u8; CHUNK_MAX];
        data[..piece.len()].copy_from_slice(piece);
        let chunk = Request::CalChunk {
            offset: (i * CHUNK_MAX) as u32,
            len: piece.len() as u8,
            data,
        };
        ok &= ack(endpoint.handle_inline(&chunk, drive).0);
    }
    ok && ack(endpoint.handle_inline(&Request::CalCommit, drive).0)
}

/// Decodes the host's blob and encodes it again: the bytes must not change.
#[cfg(target_os = "none")]
#[inline(never)]
fn blob_round_trips(good: &[u8]) {
    use estimator_core::{blob, drive::DriveConfig};
    let rig = DriveConfig::paper_rig().settings.rig;
    let Ok(params) = blob::decode(good, &rig) else {
        defmt::panic!("host blob refused on target")
    };
    let Some(again) = cortex_m::singleton!(: [u8; blob::MAX_BYTES] = [0; blob::MAX_BYTES]) else {
        defmt::panic!("twice")
    };
    let Ok(n) = blob::encode(&params, &rig, again) else {
        defmt::panic!("re-encoding failed")
    };
    defmt::assert_eq!(&again[..n], good, "blob re-encoded on target differs");
}

#[cfg(target_os = "none")]
#[defmt_test::tests]
mod tests {
    use super::vectors;
    use estimator_core::encoder;
    use estimator_core::model::belt::STEP_PARTS;
    use estimator_core::model::ModelKind;

    #[init]
    fn init() {
        belt_drive::stack::paint();
    }

    #[test]
    fn encoder_unwrapping_edge_cases() {
        for (case, &(start, limit, reads)) in vectors::ENCODER_CASES.iter().enumerate() {
            let coeffs = match encoder::Coeffs::<u16>::from_max_delta_counts(limit) {
                Ok(c) => c,
                Err(_) => defmt::panic!("case {=usize}: limit refused", case),
            };
            let mut state = encoder::State::<u16>::new(start);
            for (i, &(raw, kind, value)) in reads.iter().enumerate() {
                let got = match coeffs.update(&mut state, raw) {
                    Ok(p) => (0u8, p),
                    Err(encoder::Error::Jump { delta_counts }) => (1, delta_counts),
                    Err(encoder::Error::Overflow) => (2, 0),
                };
                defmt::assert_eq!(got, (kind, value), "case {=usize} read {=usize}", case, i);
            }
        }
    }

    /// The fixed-point belt observer (`model::belt`, not yet in the drive) through moves out
    /// and back, bit for bit as on the host's `tick`: a step every tick, run here part by part
    /// (`begin`, then `advance`), and a step every 2, 4 and 6 ticks spread over them. The cost of
    /// each part, of the step and of the ticks is logged: TIM2 counts instructions exactly only
    /// under `--icount 0` (see README, "A reduced plant observer").
    #[test]
    fn belt_observer_matches_the_host() {
        // SAFETY: TIM2 as an instruction counter, as `hardware::qemu` sets it up (PSC = 0,
        // ARR = 0, no interrupt); nothing else in this test uses it.
        let tim2 = unsafe { &*stm32f4xx_hal::pac::TIM2::ptr() };
        unsafe {
            (*stm32f4xx_hal::pac::RCC::ptr())
                .apb1enr()
                .modify(|_, w| w.tim2en().set_bit());
            tim2.psc().write(|w| w.bits(0));
            tim2.arr().write(|w| w.bits(0));
        }
        tim2.cr1().write(|w| w.cen().set_bit());
        for (&every, &(crc, last, range)) in vectors::BELT_EVERY.iter().zip(vectors::BELT.iter()) {
            let d = vectors::belt_observer(every, |s, c, counts, current| {
                let mut parts = [0u32; STEP_PARTS as usize];
                cortex_m::interrupt::free(|_| {
                    if every > 1 {
                        let t0 = tim2.cnt().read().bits();
                        s.tick(c, counts, current);
                        let t1 = tim2.cnt().read().bits();
                        parts[0] = t1.wrapping_sub(t0).wrapping_sub(5);
                        return;
                    }
                    let t0 = tim2.cnt().read().bits();
                    s.begin(c, counts, current);
                    let t1 = tim2.cnt().read().bits();
                    parts[0] = t1.wrapping_sub(t0).wrapping_sub(5);
                    for (k, part) in parts.iter_mut().enumerate().skip(1) {
                        let t0 = tim2.cnt().read().bits();
                        let done = s.advance(c);
                        let t1 = tim2.cnt().read().bits();
                        *part = t1.wrapping_sub(t0).wrapping_sub(5);
                        // The last part ends the step.
                        defmt::assert_eq!(done, k + 1 == STEP_PARTS as usize);
                    }
                });
                parts
            });
            defmt::assert_eq!(d.offset_range_bits, range);
            defmt::assert_eq!(d.final_offset_bits, last);
            defmt::assert_eq!(d.crc, crc);
            defmt::info!(
                "belt observer, a step every {=u32} ticks: {=u32} ticks bit-identical, offset {=i32}..{=i32} um/65536; TIM2 per tick mean {=u64}/10, max {=u32}",
                every,
                vectors::BELT_TICKS,
                range.0,
                range.1,
                d.measured_sum * 10 / vectors::BELT_TICKS as u64,
                d.measured_max
            );
            if every == 1 {
                for k in 0..STEP_PARTS as usize {
                    defmt::info!(
                        "belt observer part {=usize}: TIM2 mean {=u64}/10, max {=u32}",
                        k,
                        d.part_sum[k] * 10 / vectors::BELT_TICKS as u64,
                        d.part_max[k]
                    );
                }
            }
        }
    }

    /// Every model through three moves, compared block by block with the host's run.
    #[test]
    fn closed_loop_runs_match_the_host() {
        for &(model, want) in vectors::CLOSED_LOOP {
            let Some(kind) = ModelKind::from_u8(model) else {
                defmt::panic!("model {=u8}", model)
            };
            let got = vectors::closed_loop(kind);
            for (i, (g, w)) in got.blocks.iter().zip(want.blocks.iter()).enumerate() {
                defmt::assert_eq!(
                    g,
                    w,
                    "model {=u8}: block {=usize} of {=usize} ticks differs",
                    model,
                    i,
                    vectors::BLOCK_TICKS
                );
            }
            defmt::assert_eq!(got.ticks, want.ticks);
            defmt::assert_eq!(got.final_counts, want.final_counts);
            defmt::assert_eq!(got.est_abs_sum, want.est_abs_sum);
            defmt::info!(
                "model {=u8}: {=u32} ticks bit-identical, final {=i32} counts",
                model,
                got.ticks,
                got.final_counts
            );
        }
    }

    /// The host's blob decodes on the target, re-encodes to the same bytes, loads into a drive,
    /// and travels through the link endpoint in chunks; damaged blobs are refused.
    #[test]
    fn calibration_blob_checks() {
        use estimator_core::blob::BlobError;
        use estimator_core::image;
        belt_drive::stack::paint();
        super::blob_round_trips(&vectors::PAPER_BLOB[..]);

        // The image built from it on the host loads into a drive. The large objects live in
        // statics.
        let good = &vectors::PAPER_IMAGE[..];
        let drive = super::static_drive();
        defmt::assert!(super::load(drive, good).is_ok());

        // Damaged copies: every check must refuse them (and change nothing).
        let Some(bad) = cortex_m::singleton!(: [u8; image::MAX_BYTES] = [0; image::MAX_BYTES])
        else {
            defmt::panic!("twice")
        };
        let bad = &mut bad[..good.len()];
        bad.copy_from_slice(good);
        bad[good.len() / 2] ^= 0x40;
        defmt::assert!(super::load(drive, bad) == Err(BlobError::BadChecksum));
        defmt::assert!(super::load(drive, &good[..good.len() - 1]).is_err());
        defmt::assert!(super::load(drive, &good[..8]) == Err(BlobError::Truncated));
        bad.copy_from_slice(good);
        bad[0] = b'X';
        defmt::assert!(super::load(drive, bad) == Err(BlobError::BadMagic));

        // Through the endpoint: begin, chunks, commit.
        defmt::assert!(super::endpoint_transfer(drive, good));
        defmt::info!(
            "calibration image: {=usize} bytes, checks pass on target; stack peak so far {=u32} bytes",
            good.len(),
            belt_drive::stack::peak_bytes()
        );
    }
}
