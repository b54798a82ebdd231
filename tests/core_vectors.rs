//! The core's vectors on the Cortex-M4: the expected values come from the same code run on the
//! host (`build.rs`), so every comparison here is bit for bit. Run with `cargo test-target`.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
mod vectors {
    include!("common/closed_loop.rs");
    include!(concat!(env!("OUT_DIR"), "/core_vectors.rs"));
}

#[cfg(target_os = "none")]
#[defmt_test::tests]
mod tests {
    use super::vectors;
    use estimator_core::encoder;
    use estimator_core::model::ModelKind;

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

    /// Every model through three moves, compared block by block with the host's run.
    #[test]
    fn closed_loop_runs_match_the_host() {
        for &(model, want) in vectors::CLOSED_LOOP {
            let Some(kind) = ModelKind::from_u8(model) else { defmt::panic!("model {=u8}", model) };
            let got = vectors::closed_loop(kind);
            for (i, (g, w)) in got.blocks.iter().zip(want.blocks.iter()).enumerate() {
                defmt::assert_eq!(g, w, "model {=u8}: block {=usize} of {=usize} ticks differs", model, i, vectors::BLOCK_TICKS);
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
}
