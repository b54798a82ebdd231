//! Transmission-error models of the timing belt (paper sections 5 and 6: Models 1, 2, 3;
//! eqs. 14-18; Table 2), in fixed point for the control tick.
//!
//! The models estimate `y = x_LS - x_PE`, the carriage position measured by the linear scale minus
//! the position the motor encoder implies, from the motor position alone.
//!
//! # Units (our reading of Table 2)
//! `x` is the primary (motor) encoder position in mm, `y` the position error in mm:
//! - `m = 0.0010594`: slope of the band along travel (mm of error per mm of travel);
//! - `h = 0.34 mm`: band height; forward motion (x increasing) rides the lower edge `m x - h`,
//!   reverse motion the upper edge `m x`;
//! - `h_g = 0.11 mm`: the fast jump right after a reversal (eq. 16);
//! - Model 1: `a = b = 0.0012`, slopes of the straight transition (mm of error per mm of travel);
//! - Model 2: `a = -0.05 /mm`, `b = -0.03 /mm` rates and `A = 0.07 mm`, `B = 0.09 mm` amplitudes of
//!   the exponential transition.
//!
//! Eq. 14 reduces to `y = max(u, m x - h)` forward and `y = min(u, m x)` reverse. We bound the
//! transition by the band on both sides (`y = clamp(u, m x - h, m x)`): with the paper's sign
//! conventions the far side is never reached, so this changes nothing for Table 2, but it keeps the
//! output inside the band after a run-time model switch or with unusual fitted parameters.
//!
//! # Interface
//! Parameters are SI-ish `f64` ([`ModelParams`]), turned once by [`ModelParams::build`] into
//! fixed-point [`ModelCoeffs`]; the mutable [`ModelState`] is separate; [`estimate`] runs per
//! tick on integers only. Input: the unwrapped motor position in encoder counts (`i32`); counts
//! are converted with [`Rig::counts_per_mm`] at build time. Output: `y` in micrometres as
//! [`I16F16`]. All three models are compiled in and selected per call by [`ModelKind`].
//!
//! # Reversal detection (eqs. 15, 16) with a dead band
//! The state tracks the extreme position reached in the current direction. A reversal is
//! registered only when `x` moves more than `reversal_deadband_counts` back from that extreme;
//! then `x_d` is the extreme (the turning point) and `y_d` the output at the turning point, minus
//! `h_g` (reversal to forward) or plus `h_g` (to reverse). With a dead band of 0 any move back is a
//! reversal, as in the paper. Standing still keeps the direction: this deviates from the literal
//! `x(k) >= x(k-1)`, which would turn a reverse motion into a forward one at every standstill and
//! fake a reversal at the next reverse step. Encoder jitter of up to the dead band is not a
//! reversal; the jump `h_g` appears when the reversal is registered.
//!
//! The detector is shared by all models and updated on every call whatever the model; the output
//! at the turning point is whichever model was active when the carriage was last at the extreme
//! ([`ModelKind::None`] records no output: a reversal after an extreme reached with no model
//! starts on the new band edge). Switching models mid-transition therefore continues the
//! transition from the same turning point with the new model's shape; the output stays inside the
//! band of the new model.
//!
//! Start state ([`ModelState::new`]): moving forward, on the lower band edge, no transition.
//!
//! # Fixed-point formats
//! - positions `i32` counts; differences in `i64` (then saturated), so a jump across the whole
//!   `i32` range neither wraps nor panics;
//! - errors, band heights, amplitudes: [`I16F16`] um (+-32767 um, step 1.5e-5 um);
//! - slopes `m, a, b`: [`I1F31`](fixed::types::I1F31) um per count (+-1 um/count; 1.87 mm/mm on
//!   the paper's rig);
//! - Model 2 rates: a 32-bit-mantissa [`Scale`] from counts to the exponent of `2^-t` (Q32.32);
//!   `2^-t` in Q2.30 within 2e-9 (see [`fixmath::exp2_neg_q30`]);
//! - Model 3: see [`table`].
//!
//! # Range and accuracy
//! Over the whole `i32` input range nothing panics or overflows (outputs saturate). Within
//! `|x| <= ACCURATE_RANGE_COUNTS` (2^24 counts, +-8.98 m on the paper's rig) and with outputs
//! inside +-16 mm, every model stays within 0.05 um of its `f64` reference
//! ([`crate::reference`]) at every step. Property-tested (`tests/model_props.rs`); the worst
//! differences measured are 0.004 um (Models 1, 2: the Q1.31 slope `m` times 2^24 counts) and
//! 0.0001 um (Model 3). For Model 3 this holds for tables whose gap grows no faster than the
//! initial gap (`|dG/dg0| <= 1`, as measured transitions do): a steeper table amplifies any
//! difference in `y` at a turning point by that slope at every reversal, in `f64` as in fixed
//! point.
//!
//! Model 2 meets the band edge where the paper has it meet (see [`exponential`]'s docs: the
//! asymptote stops short of the far edge, the sloped edge still reaches the curve);
//! [`ModelCoeffs::closing`] reports the closing distances (151.1 mm forward, 133.7 mm reverse
//! with Table 2) and `None` where a transition can never close.
//!
//! # Cost (Cortex-M4, instructions per call, measured under QEMU on the release build)
//! | model | on the band edge | in a transition | reversal tick |
//! |-------|------------------|-----------------|---------------|
//! | 1     | 72               | 102             | 115           |
//! | 2     | 66               | 145..153        | 158..166      |
//! | 3     | 116              | 178..181        | 368..384      |
//!
//! (These are the figures of the first fixed-point models; the drive's whole tick per model is in
//! the README's tick table, measured by `tools/bench-target.sh`.) Model 3's worst case is a
//! reversal tick: the band edge at the turning point, the `g0` cell and two interpolated
//! transition rows. Its bands lie on an even axis, so every lookup is a multiply: no search and
//! no division. The per-tick path calls no runtime library (no software division: Model 4's slip
//! observer divides once with the hardware `UDIV`; multiplies are
//! `UMULL`/`SMULL`/`SMLAL`). See the size guards below for `ModelCoeffs` and `ModelState`.

pub mod baseline;
pub mod belt;
pub mod fixmath;

mod convert;
pub mod exponential;
mod linear;
pub mod operator;
pub mod slip;
pub mod table;

use fixed::types::I16F16;

pub use baseline::{
    BacklashCoeffs, BacklashParams, BidirCoeffs, BidirParams, BidirSource, MAX_BIDIR_ROWS,
};
pub use convert::MAX_ABS_UM;
pub use exponential::{Model2Coeffs, Model2Params};
pub use fixmath::Scale;
pub use linear::{LinearBand, Model1Coeffs, Model1Params};
pub use operator::{BeltTerm, BeltTermCoeffs, Model4Coeffs, Model4Params};
pub use table::{
    BandCoeffs, BandParams, Model3Coeffs, Model3Params, Model3Source, TransitionCoeffs,
    TransitionParams, MAX_BAND_POINTS, MAX_TRANSITION_D, MAX_TRANSITION_G0,
};

use crate::rig::Rig;
use crate::ConfigError;

/// Positions within +-2^24 counts are covered by the accuracy guarantee (see the module docs).
pub const ACCURATE_RANGE_COUNTS: i32 = 1 << 24;

/// Which model [`estimate`] evaluates: the compensator numbers of the link.
pub use belt_link::ModelKind;

/// Direction of motion as registered by the reversal detector.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Direction {
    /// `x` increasing: lower band edge.
    Forward,
    /// `x` decreasing: upper band edge.
    Reverse,
}

/// Travel after a full-band reversal (from the far edge) until a transition meets the new band
/// edge, per direction, in mm. `None`: it does not within [`Closing::LIMIT_MM`] of travel, so the
/// estimate would stay inside the band; the firmware should warn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Closing {
    /// After a reversal to forward.
    pub forward_mm: Option<I16F16>,
    /// After a reversal to reverse.
    pub reverse_mm: Option<I16F16>,
}

impl Closing {
    /// Distances beyond this (mm) count as never.
    pub const LIMIT_MM: f64 = 30_000.0;

    /// Both transitions close.
    pub fn always_closes(&self) -> bool {
        self.forward_mm.is_some() && self.reverse_mm.is_some()
    }

    pub(crate) fn from_mm(forward: Option<f64>, reverse: Option<f64>) -> Closing {
        let conv = |d: Option<f64>| {
            d.filter(|d| d.is_finite() && *d >= 0.0 && *d <= Closing::LIMIT_MM)
                .and_then(I16F16::checked_from_num)
        };
        Closing {
            forward_mm: conv(forward),
            reverse_mm: conv(reverse),
        }
    }
}

/// All model parameters, in SI-ish units (see the module docs for the units of Table 2).
#[derive(Clone, Debug, PartialEq)]
pub struct ModelParams {
    /// Model 1 (linear transition).
    pub model1: Model1Params,
    /// Model 2 (exponential transition).
    pub model2: Model2Params,
    /// Model 3 (lookup tables).
    pub model3: Model3Params,
    /// Model 4 (play operators; see [`operator`]).
    pub model4: Model4Params,
    /// Baseline: constant backlash.
    pub backlash: BacklashParams,
    /// Baseline: bidirectional table.
    pub bidir_table: BidirParams,
    /// A reversal is registered only when `x` moves back more than this from its extreme.
    pub reversal_deadband_counts: u32,
}

impl ModelParams {
    /// Dead band of the presets: 2 counts (about 1 um of belt on the paper's rig), above the
    /// +-1 count jitter of a quadrature encoder at standstill.
    pub const DEFAULT_DEADBAND_COUNTS: u32 = 2;

    /// Travel covered by the Model 3 band tables of [`ModelParams::PAPER`] (+-mm).
    pub const PAPER_TRAVEL_MM: f64 = 2500.0;

    /// Table 2 for Models 1 and 2; Model 3 sampled from Model 1 (no calibration yet).
    pub const PAPER: ModelParams = ModelParams {
        model1: Model1Params::PAPER,
        model2: Model2Params::PAPER,
        model3: Model3Params::from_model1(&Model1Params::PAPER, ModelParams::PAPER_TRAVEL_MM),
        model4: Model4Params::zero(5.08, 101.6),
        backlash: BacklashParams::PAPER,
        bidir_table: BidirParams::from_model1(&Model1Params::PAPER, ModelParams::PAPER_TRAVEL_MM),
        reversal_deadband_counts: ModelParams::DEFAULT_DEADBAND_COUNTS,
    };

    /// Checks every field and converts to fixed-point coefficients for `rig`. The error names
    /// the first offending field, e.g. `"model1.h_mm"` or `"model3.forward_band.x_mm"`.
    pub fn build(&self, rig: &Rig) -> Result<ModelCoeffs, ConfigError> {
        build_coeffs(
            &self.model1,
            &self.model2,
            &self.model3,
            &self.model4,
            (&self.backlash, &self.bidir_table),
            self.reversal_deadband_counts,
            rig,
        )
    }
}

/// Checks and converts every model's parameters, the tables read from any [`Model3Source`] and
/// [`BidirSource`] (the `f64` tables of [`ModelParams`], or a calibration blob in place).
pub fn build_coeffs(
    model1: &Model1Params,
    model2: &Model2Params,
    model3: &impl Model3Source,
    model4: &Model4Params,
    baselines: (&BacklashParams, &impl BidirSource),
    reversal_deadband_counts: u32,
    rig: &Rig,
) -> Result<ModelCoeffs, ConfigError> {
    rig.validate()?;
    let cpm = rig.counts_per_mm();
    Ok(ModelCoeffs {
        model1: model1.build(cpm)?,
        model2: model2.build(cpm)?,
        model3: table::build_model3(model3, cpm)?,
        model4: model4.build(cpm)?,
        backlash: baselines.0.build()?,
        bidir: BidirCoeffs::build(baselines.1, cpm)?,
        deadband_counts: reversal_deadband_counts,
    })
}

impl Default for ModelParams {
    fn default() -> Self {
        ModelParams::PAPER
    }
}

/// Fixed-point coefficients of every model and baseline; immutable per tick. 3896 bytes on the
/// drive (3944 on the host, with the closing distances), of which Model 3's tables take 2112
/// and the bidirectional table 1 KiB.
///
/// In this order, so that Model 3's band headers sit within reach of one `LDRD` from the drive's
/// base (measured: the default layout put them past it, a few instructions a tick).
#[derive(Clone, Debug, PartialEq, Eq)]
#[repr(C)]
pub struct ModelCoeffs {
    pub(crate) model3: Model3Coeffs,
    pub(crate) model1: Model1Coeffs,
    pub(crate) model2: Model2Coeffs,
    pub(crate) model4: Model4Coeffs,
    pub(crate) backlash: BacklashCoeffs,
    pub(crate) bidir: BidirCoeffs,
    pub(crate) deadband_counts: u32,
}

// The firmware keeps one `ModelCoeffs` in static RAM (budget 8 KiB) and moves it when a
// calibration loads: any growth must be deliberate (3960 B with the host's closing distances,
// the 256-row bidirectional table 1 KiB in I13F3, Model 3's even-axis bands 528 B and Model 4
// 688 B of it, 520 B its belt observer's with the control rate it was built for, 8 B its offset
// as an `i64`; ModelState 272 B, Model 4's plays and its slip observer 32 B of it, its belt
// observer and the placement's prediction of it 144 B, Model 3's line over the current
// stretch and its half-drawn successor 40 B). Exact: a shrink shows here too.
#[cfg(feature = "std")]
const _: () = assert!(core::mem::size_of::<ModelCoeffs>() == 3960);
// On the drive (no closing distances): what the static RAM figures count.
#[cfg(not(feature = "std"))]
const _: () = assert!(core::mem::size_of::<ModelCoeffs>() == 3912);
const _: () = assert!(core::mem::size_of::<ModelState>() == 272);

impl ModelCoeffs {
    /// Everything zero and no tables: a value to decode a calibration image into
    /// ([`crate::image::decode_into`]), not a model to run.
    pub const ZERO: ModelCoeffs = {
        use fixed::types::{I1F31, U11F5};
        #[cfg(feature = "std")]
        const NEVER: Closing = Closing {
            forward_mm: None,
            reverse_mm: None,
        };
        const BAND: LinearBand = LinearBand {
            m_um_per_count: I1F31::ZERO,
            offset_um: I16F16::ZERO,
            h_um: I16F16::ZERO,
        };
        const TABLE: BandCoeffs = BandCoeffs {
            len: 0,
            x0_counts: 0,
            points_q32: 0,
            y_um: [I16F16::ZERO; MAX_BAND_POINTS],
        };
        const TRANSITION: TransitionCoeffs = TransitionCoeffs {
            n_d: 0,
            n_g0: 0,
            rows_q32: 0,
            cols_q32: 0,
            gap_um: [[U11F5::ZERO; MAX_TRANSITION_G0]; MAX_TRANSITION_D],
        };
        ModelCoeffs {
            model1: Model1Coeffs {
                band: BAND,
                h_g_um: I16F16::ZERO,
                slope_a_um_per_count: I1F31::ZERO,
                slope_b_um_per_count: I1F31::ZERO,
                #[cfg(feature = "std")]
                closing: NEVER,
            },
            model2: Model2Coeffs {
                band: BAND,
                h_g_um: I16F16::ZERO,
                amp_a_um: I16F16::ZERO,
                amp_b_um: I16F16::ZERO,
                rate_a: Scale::ZERO,
                rate_b: Scale::ZERO,
                #[cfg(feature = "std")]
                closing: NEVER,
            },
            model3: Model3Coeffs {
                forward_band: TABLE,
                reverse_band: TABLE,
                forward_transition: TRANSITION,
                reverse_transition: TRANSITION,
                #[cfg(feature = "std")]
                closing: NEVER,
            },
            model4: Model4Coeffs {
                widths_counts: [0; operator::N_OPS],
                weight_q24: [[0; operator::N_OPS]; 2],
                x_ref_counts: 0,
                offset_q31: 0,
                slope_q31: 0,
                hat_start_counts: 0,
                hat_recip_q32: 0,
                knot_um: [I16F16::ZERO; operator::N_KNOTS],
                pitch_rate: 0,
                pitch: operator::Harmonic::ZERO,
                turn_rate: 0,
                turn: operator::Harmonic::ZERO,
                current_um_per_a: I16F16::ZERO,
                current_lp_um_per_a: I16F16::ZERO,
                slip: slip::SlipCoeffs::ZERO,
                belt: None,
            },
            backlash: BacklashCoeffs {
                forward_um: I16F16::ZERO,
                reverse_um: I16F16::ZERO,
            },
            bidir: BidirCoeffs {
                x0_counts: 0,
                step_counts: 0,
                span_counts: 0,
                step_recip: fixmath::Recip::ZERO,
                rows: 0,
                values: [[fixed::types::I13F3::ZERO; MAX_BIDIR_ROWS]; 2],
            },
            deadband_counts: 0,
        }
    };

    /// Model 1's coefficients.
    pub fn model1(&self) -> &Model1Coeffs {
        &self.model1
    }

    /// Model 2's coefficients.
    pub fn model2(&self) -> &Model2Coeffs {
        &self.model2
    }

    /// Model 3's coefficients (tables).
    pub fn model3(&self) -> &Model3Coeffs {
        &self.model3
    }

    /// Model 4's coefficients.
    pub fn model4(&self) -> &Model4Coeffs {
        &self.model4
    }

    /// The constant-backlash baseline.
    pub fn backlash(&self) -> &BacklashCoeffs {
        &self.backlash
    }

    /// The bidirectional-table baseline.
    pub fn bidir(&self) -> &BidirCoeffs {
        &self.bidir
    }

    /// The reversal dead band.
    pub fn deadband_counts(&self) -> u32 {
        self.deadband_counts
    }

    /// Closing distances of `kind` (both `Some(0)` for [`ModelKind::None`]); `None` in either
    /// direction is worth a warning (`hil-sim calibrate` gives it). Host only: the firmware has
    /// no use for them, and Model 2's bisection through `exp` is 4 KB of soft-float.
    #[cfg(feature = "std")]
    pub fn closing(&self, kind: ModelKind) -> Closing {
        match kind {
            ModelKind::None | ModelKind::Backlash | ModelKind::BidirTable | ModelKind::Operator => {
                Closing::from_mm(Some(0.0), Some(0.0))
            }
            ModelKind::Linear => self.model1.closing(),
            ModelKind::Exponential => self.model2.closing(),
            ModelKind::Table => self.model3.closing(),
        }
    }
}

/// Per-tick state: the reversal detector, the turning point and Model 3's caches and Model 4's plays.
///
/// Model 3's caches (the `g0` cell, the interpolated transition rows and the line over the
/// current stretch) are refreshed at every reversal. After replacing the coefficients call [`ModelState::reset`]: a
/// stale cache costs accuracy until the next reversal, never safety.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelState {
    pub(crate) dir: Direction,
    /// Extreme position reached in the current direction.
    pub(crate) x_ext_counts: i32,
    /// Output when the carriage was last at `x_ext` (valid if a model was active then).
    pub(crate) y_ext_um: I16F16,
    pub(crate) y_ext_valid: bool,
    /// Turning point of the last reversal and the output there (before `h_g`).
    pub(crate) x_d_counts: i32,
    pub(crate) y_d_um: I16F16,
    /// A transition from `(x_d, y_d)` is in progress (false at start-up).
    pub(crate) transition: bool,
    /// Model 3: the `g0` cell of the current transition, and whether it is still to be found
    /// (a transition in progress whose first Model 3 tick has not come yet).
    pub(crate) g0_cell: table::Cell,
    pub(crate) needs_g0: bool,
    /// Model 3: the band segment and the transition's row pair in use (empty after a
    /// reversal, new coefficients and a new `g0`).
    pub(crate) band: table::SegmentCache,
    pub(crate) rows: table::SegmentCache,
    /// Model 3: its estimate as a line over the current stretch of travel (emptied at a
    /// reversal).
    pub(crate) piece: table::Piece,
    /// Model 4: the plays, valid while Model 4 has run every tick.
    pub(crate) plays: operator::Plays,
    /// Model 4's belt-slip observer (restarted with the plays).
    pub(crate) slip: slip::Slip,
    /// Model 4's belt observer, where the calibration has one (restarted with the plays).
    pub(crate) belt: belt::BeltState,
    /// The placement's predicted rest of its offset (a copy's, [`estimate`]).
    pub(crate) belt_rest: operator::BeltRest,
    /// Set by [`estimate`] (a prediction's copy): Model 4's belt observer predicts its rest
    /// instead of stepping.
    pub(crate) predicting: bool,
    /// Model 4's low-passed current, I16F16 amperes (restarted with the plays).
    pub(crate) current_lp_bits: i32,
}

impl ModelState {
    /// Start at `x0_counts`, moving forward, on the lower band edge.
    pub const fn new(x0_counts: i32) -> ModelState {
        ModelState {
            dir: Direction::Forward,
            x_ext_counts: x0_counts,
            y_ext_um: I16F16::ZERO,
            y_ext_valid: false,
            x_d_counts: x0_counts,
            y_d_um: I16F16::ZERO,
            transition: false,
            g0_cell: table::Cell { lo: 0, hi: 0, t: 0 },
            needs_g0: false,
            band: table::SegmentCache::EMPTY,
            rows: table::SegmentCache::EMPTY,
            piece: table::Piece::NONE,
            plays: operator::Plays::NEW,
            slip: slip::Slip::NEW,
            belt: belt::BeltState::ZERO,
            belt_rest: operator::BeltRest::NONE,
            predicting: false,
            current_lp_bits: 0,
        }
    }

    /// Back to the start state at `x0_counts` (e.g. after homing or new coefficients).
    // Not inlined: commands only (flash size).
    #[inline(never)]
    pub fn reset(&mut self, x0_counts: i32) {
        *self = ModelState::new(x0_counts);
    }

    /// Forgets the transition but keeps the direction: the estimate continues on the band edge of
    /// the current direction from `x_counts` (e.g. after new coefficients while standing still).
    // Not inlined: commands only (flash size).
    #[inline(never)]
    pub fn settle(&mut self, x_counts: i32) {
        let dir = self.dir;
        *self = ModelState::new(x_counts);
        self.dir = dir;
    }

    /// Direction of motion as last registered.
    pub fn direction(&self) -> Direction {
        self.dir
    }

    /// Position of the last turning point `x_d` (the start position before any reversal).
    pub fn turning_point_counts(&self) -> i32 {
        self.x_d_counts
    }

    /// Error at the last turning point, before the jump `h_g`.
    pub fn turning_point_error_um(&self) -> I16F16 {
        self.y_d_um
    }

    /// Whether a transition is in progress (a reversal was registered with a model active).
    pub fn in_transition(&self) -> bool {
        self.transition
    }

    /// Eqs. 15-16 with the dead band: update the extreme, or register a reversal.
    #[inline]
    fn track(&mut self, deadband_counts: u32, x: i32) {
        // Ahead of the extreme: a new extreme. Behind it, the distance back (two `i32` apart:
        // exact in `u32`) against the dead band.
        let (ahead, back) = match self.dir {
            Direction::Forward => (x > self.x_ext_counts, self.x_ext_counts.wrapping_sub(x)),
            Direction::Reverse => (x < self.x_ext_counts, x.wrapping_sub(self.x_ext_counts)),
        };
        if ahead {
            self.x_ext_counts = x;
        } else if back as u32 > deadband_counts {
            self.dir = match self.dir {
                Direction::Forward => Direction::Reverse,
                Direction::Reverse => Direction::Forward,
            };
            self.x_d_counts = self.x_ext_counts;
            self.y_d_um = self.y_ext_um;
            self.transition = self.y_ext_valid;
            self.x_ext_counts = x;
            // Model 3's g0 cell is recomputed on its next tick, on the other band.
            self.needs_g0 = self.y_ext_valid;
            self.band.invalidate();
            self.piece.invalidate();
        }
    }
}

/// One tick: update the reversal detector with `x_counts` (unwrapped motor encoder counts) and
/// return the estimated error `y = x_LS - x_PE` of model `kind`, in micrometres. A prediction
/// at rest: Model 4 sees no current, its low passes settled at zero (as after the move that
/// brings the motor to `x_counts`, whatever its length). See [`estimate_with_current`].
///
/// The state becomes a prediction's: run it on a copy of the drive's (the placement does). It
/// zeroes Model 4's low passes, and from then on its belt observer predicts its rest on every
/// call instead of stepping, each prediction going on from the last (so the tick's path never
/// has to mark a prediction stale).
///
/// Integer-only, bounded time, no panics for any input.
pub fn estimate(
    coeffs: &ModelCoeffs,
    kind: ModelKind,
    state: &mut ModelState,
    x_counts: i32,
) -> I16F16 {
    if kind == ModelKind::Operator {
        state.current_lp_bits = 0;
        state.slip.lp_bits = 0;
    }
    // The flag lives in the state, not in an argument, so that the per-tick call is the same
    // as before the belt observer (an argument cost every compensator 2-3 instructions a tick).
    state.predicting = true;
    estimate_with_current(coeffs, kind, state, x_counts, I16F16::ZERO)
}

/// [`estimate`] with the motor current commanded this tick (amperes in the drive's frame,
/// positive pushing towards positive travel), which only Model 4 uses.
pub fn estimate_with_current(
    coeffs: &ModelCoeffs,
    kind: ModelKind,
    state: &mut ModelState,
    x_counts: i32,
    current_a: I16F16,
) -> I16F16 {
    state.track(coeffs.deadband_counts, x_counts);
    if kind != ModelKind::Operator {
        // The plays and the slip observer only follow x while Model 4 runs; they restart on
        // the band edge after.
        state.plays.valid = false;
    }
    let y = match kind {
        ModelKind::None => I16F16::ZERO,
        ModelKind::Linear => linear::eval(&coeffs.model1, state, x_counts),
        ModelKind::Exponential => exponential::eval(&coeffs.model2, state, x_counts),
        ModelKind::Table => table::eval(&coeffs.model3, state, x_counts),
        ModelKind::Backlash => baseline::eval_backlash(&coeffs.backlash, state),
        ModelKind::BidirTable => baseline::eval_bidir(&coeffs.bidir, state, x_counts),
        ModelKind::Operator => operator::eval(&coeffs.model4, state, x_counts, current_a),
    };
    if x_counts == state.x_ext_counts {
        state.y_ext_um = y;
        state.y_ext_valid = kind != ModelKind::None;
    }
    y
}

#[cfg(test)]
mod tests {
    use super::table::tests::{band_in, transition_in};
    use super::table::Model3Coeffs;
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Model 3 on its lines ([`table::Piece`]) gives what the two interpolations give within
        /// 4 LSB of Q16.16 (6e-5 um), along walks that creep, jump, dither across segment ends,
        /// turn within and beyond the dead band and run past both tables' ends.
        #[test]
        fn the_line_is_the_interpolation(
            // Segments and rows of at most 2^16 counts near the walk: crossed often.
            forward_band in band_in(-200_000..200_000, 1 << 16),
            reverse_band in band_in(-200_000..200_000, 1 << 16),
            forward_transition in transition_in(1 << 16),
            reverse_transition in transition_in(1 << 16),
            deadband in 0u32..64,
            x0 in -300_000i32..300_000,
            steps in prop::collection::vec((-900i32..900, 1u16..400, any::<bool>()), 1..30),
        ) {
            let mut c = ModelCoeffs::ZERO;
            c.model3 = Model3Coeffs {
                forward_band,
                reverse_band,
                forward_transition,
                reverse_transition,
                closing: Closing::default(),
            };
            c.deadband_counts = deadband;
            let (mut lines, mut lerps) = (ModelState::new(x0), ModelState::new(x0));
            let mut x = x0;
            for (step, n, dither) in steps {
                for i in 0..n {
                    // A steady step, or a dither that crosses back and forth (a line must not
                    // outlive a half-drawn successor).
                    let dx = if dither && i % 2 == 1 { -(step / 8) } else { step / 8 };
                    x = x.saturating_add(dx);
                    lerps.piece.invalidate();
                    let a = estimate(&c, ModelKind::Table, &mut lines, x).to_bits();
                    let b = estimate(&c, ModelKind::Table, &mut lerps, x).to_bits();
                    prop_assert!(a.abs_diff(b) <= 4, "x = {}: line {} lerps {}", x, a, b);
                }
            }
        }
    }

    /// A dither across a band segment's end in mid-transition: back on the old line after its
    /// successor was half drawn (the old line must be gone, not read with the new slope).
    #[test]
    fn a_dither_across_a_segment_end_stays_on_the_interpolation() {
        let c = ModelParams::PAPER.build(&crate::rig::Rig::PAPER).unwrap();
        let band = c.model3.band(Direction::Reverse);
        let segment = |x: i32| (band.position_q32(x) >> 32) as u32;
        // The first three ends of the reverse band's segments above 1 mm: `x0 + ceil(i 2^32 /
        // points_q32)`, where the segment index steps.
        let end = |i: i64| {
            band.x0_counts as i64
                + ((i << 32) + band.points_q32 as i64 - 1) / band.points_q32 as i64
        };
        let ends: Vec<i32> = (1..band.len as i64)
            .map(end)
            .filter(|&x| x > 2_000)
            .take(3)
            .map(|x| x as i32)
            .collect();
        assert_eq!(ends.len(), 3);
        for &e in &ends {
            assert_ne!(segment(e - 1), segment(e));
        }
        // Out forward past them, then back: a transition in reverse, moving down.
        let top = ends[2] + 20_000;
        let mut path: Vec<i32> = (0..top).step_by(37).collect();
        for x in (1_000..top).rev() {
            path.push(x);
            if ends.contains(&x) {
                // One count either side of the end, within the dead band (2 counts).
                for _ in 0..4 {
                    path.push(x - 1);
                    path.push(x);
                }
            }
        }
        let (mut lines, mut lerps) = (ModelState::new(0), ModelState::new(0));
        for &x in &path {
            lerps.piece.invalidate();
            let a = estimate(&c, ModelKind::Table, &mut lines, x).to_bits();
            let b = estimate(&c, ModelKind::Table, &mut lerps, x).to_bits();
            assert!(a.abs_diff(b) <= 4, "x = {x}: line {a} lerps {b}");
        }
        assert!(lines.in_transition());
    }

    /// The lines are taken: on a steady walk through a transition most ticks are on one.
    #[test]
    fn a_steady_walk_is_mostly_on_lines() {
        let c = ModelParams::PAPER.build(&crate::rig::Rig::PAPER).unwrap();
        let mut s = ModelState::new(0);
        let (mut on_lines, mut ticks) = (0, 0);
        for x in (0..40_000).step_by(37).chain((0..80_000).rev().step_by(41)) {
            on_lines += (s.piece.span != 0) as u32;
            ticks += 1;
            estimate(&c, ModelKind::Table, &mut s, x);
        }
        assert!(on_lines * 10 > ticks * 9, "{on_lines} of {ticks}");
    }
}
