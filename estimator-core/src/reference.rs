//! `f64` reference of the transmission-error models, written straight from the paper's equations
//! (eqs. 14-18) in the paper's units (mm), for tests and the host simulator.
//!
//! Same semantics as [`crate::model`]: the same reversal detector (integer counts, dead band,
//! direction kept at standstill), the same start state, the same parameters converted with the
//! same `counts_per_mm`. Models 1 and 2 use the SI parameters as given. Model 3 uses the table
//! values of the *quantised* coefficients converted back to `f64`, so that only the arithmetic is
//! compared, not the quantisation of calibration data.

use crate::model::belt::{BeltCoeffs, BeltState};
use crate::model::operator::{FORWARD, N_KNOTS, N_OPS, REVERSE};
use crate::model::slip::{self, SlipCoeffs};
use crate::model::{BandCoeffs, Direction, ModelKind, ModelParams, TransitionCoeffs};
use crate::model::{Model1Params, Model2Params};
use crate::rig::Rig;
use crate::ConfigError;
use fixed::types::I16F16;

/// A Model 3 band table as `f64`: `(x_counts, y_mm)` on the coefficients' even axis.
#[derive(Clone, Debug)]
struct RefBand(Vec<(f64, f64)>);

impl RefBand {
    fn from_coeffs(b: &BandCoeffs) -> RefBand {
        RefBand(
            b.points()
                .map(|(x, y)| (x, y.to_num::<f64>() / 1000.0))
                .collect(),
        )
    }

    /// Linear interpolation, clamped outside the axis.
    fn at(&self, x: f64) -> f64 {
        let p = &self.0;
        if x <= p[0].0 {
            return p[0].1;
        }
        for w in p.windows(2) {
            let ((x0, y0), (x1, y1)) = (w[0], w[1]);
            if x < x1 {
                return y0 + (y1 - y0) * (x - x0) / (x1 - x0);
            }
        }
        p[p.len() - 1].1
    }
}

/// A Model 3 transition table as `f64` (gaps in mm).
#[derive(Clone, Debug)]
struct RefTransition {
    rows_per_count: f64,
    cols_per_mm: f64,
    gap_mm: Vec<Vec<f64>>,
}

impl RefTransition {
    fn from_coeffs(t: &TransitionCoeffs) -> RefTransition {
        RefTransition {
            rows_per_count: t.rows_per_count(),
            cols_per_mm: t.columns_per_um() * 1000.0,
            gap_mm: (0..t.n_d())
                .map(|i| {
                    (0..t.n_g0())
                        .map(|j| t.gap_um(i, j).unwrap().to_num::<f64>() / 1000.0)
                        .collect()
                })
                .collect(),
        }
    }

    /// Cell along a uniform axis: (lower, upper, fraction); held at the last index.
    fn cell(pos: f64, n: usize) -> (usize, usize, f64) {
        let last = n - 1;
        let i = pos.floor();
        if i >= last as f64 {
            (last, last, 0.0)
        } else {
            (i as usize, i as usize + 1, pos - i)
        }
    }

    /// Bilinear `G(d, g0)` (mm) at `d` counts of travel and `g0` mm of initial gap.
    fn at(&self, d_counts: f64, g0_mm: f64) -> f64 {
        let (i0, i1, s) = Self::cell(d_counts * self.rows_per_count, self.gap_mm.len());
        let (j0, j1, t) = Self::cell(g0_mm * self.cols_per_mm, self.gap_mm[0].len());
        let g = &self.gap_mm;
        (1.0 - s) * ((1.0 - t) * g[i0][j0] + t * g[i0][j1])
            + s * ((1.0 - t) * g[i1][j0] + t * g[i1][j1])
    }
}

/// The reference models with their own reversal detector.
#[derive(Clone, Debug)]
pub struct Reference {
    counts_per_mm: f64,
    deadband_counts: u32,
    m1: Model1Params,
    m2: Model2Params,
    band_f: RefBand,
    band_r: RefBand,
    trans_f: RefTransition,
    trans_r: RefTransition,
    /// Backlash baseline per direction (forward, reverse), mm.
    backlash_mm: (f64, f64),
    /// Bidirectional table: row 0 and spacing in counts, rows per direction in mm.
    bidir_x0: f64,
    bidir_step: f64,
    bidir_mm: [Vec<f64>; 2],
    // Detector and turning point (errors in mm).
    dir: Direction,
    x_ext: i32,
    y_ext_mm: f64,
    y_ext_valid: bool,
    x_d: i32,
    y_d_mm: f64,
    transition: bool,
    g0_mm: f64,
    m4: RefModel4,
    plays: [f64; N_OPS],
    plays_valid: bool,
    /// Model 4's low-passed current, I16F16 bits (restarted with the plays).
    current_lp_bits: i32,
    slip: RefSlip,
    /// Model 4's belt observer, where the calibration has one: the drive's fixed-point port is
    /// its definition (hil-sim holds it to the `f64` observer within 0.3 um).
    belt: Option<(BeltCoeffs, BeltState)>,
}

/// Model 4's quantised coefficients as `f64` (um, counts).
#[derive(Clone, Debug)]
struct RefModel4 {
    widths: [f64; N_OPS],
    /// Play weights moving in reverse and forward, um per count.
    weight_um_per_count: [[f64; N_OPS]; 2],
    x_ref: i32,
    offset_um: f64,
    slope_um_per_count: f64,
    hat_start: f64,
    hat_recip: f64,
    knot_um: [f64; N_KNOTS],
    rates: [u32; 2],
    harmonic_um: [[f64; 2]; 2],
    current_um_per_a: f64,
    current_lp_um_per_a: f64,
    slip_weight: f64,
}

/// Model 4's terms at one tick before their weights (see [`crate::model::operator`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Model4Terms {
    /// The mesh offset, um: the belt observer's where the calibration has one, else the slip
    /// observer's `g`.
    pub slip_um: f64,
    /// Each play's output `x - p`, counts.
    pub plays_counts: [f64; N_OPS],
    /// The forward play weights apply (the registered direction is forward).
    pub forward: bool,
    /// `x - x_ref`, counts.
    pub from_ref_counts: f64,
    /// Each interior knot's hat at `x`, 0..=1.
    pub hats: [f64; N_KNOTS],
    /// Sine and cosine at the belt pitch, then at one pulley turn.
    pub harmonics: [[f64; 2]; 2],
    /// The motor current, A.
    pub current_a: f64,
    /// The motor current through the drive's low pass (the same integer filter), A.
    pub current_lp_a: f64,
}

/// Model 4's slip observer ([`crate::model::slip`]), written out plainly in `i64`.
///
/// The observer is a discrete-time state machine defined in integers (its contact and slip
/// decisions compare states to the bit): an `f64` copy would take the other branch whenever a
/// comparison falls within a rounding, and the two would part by a whole pre-slide. So the
/// reference runs the definition itself, every product in `i64` with its rounding spelled out
/// and no shortcut of the drive's code, and the rest of Model 4 in `f64` on its output.
#[derive(Clone, Debug)]
pub struct RefSlip {
    c: SlipCoeffs,
    /// Mesh offset and friction deflection, I16F16 um.
    g: i64,
    z: i64,
    lp_bits: i32,
    x_prev: i64,
}

impl RefSlip {
    /// The observer of `c`, to be started.
    pub fn new(c: &SlipCoeffs) -> RefSlip {
        RefSlip {
            c: *c,
            g: 0,
            z: 0,
            lp_bits: 0,
            x_prev: 0,
        }
    }

    /// Against the teeth on the side of `forward`, unloaded (as the drive starts it).
    pub fn start(&mut self, forward: bool, x: i32, current_a: f64) {
        let h = self.c.half_gap_bits as i64;
        self.g = if forward { h } else { -h };
        self.z = 0;
        self.lp_bits = current_bits(current_a);
        self.x_prev = x as i64;
    }

    /// Mesh offset `g` now, um.
    pub fn offset_um(&self) -> f64 {
        self.g as f64 / 65536.0
    }

    /// One tick (see [`crate::model::slip`]).
    pub fn step(&mut self, forward: bool, x: i32, current_a: f64) {
        let c = &self.c;
        // The travel is the difference of two `i32` positions modulo 2^32 (a position that
        // wraps around `i32` moves by one count), as the drive defines it.
        let ds = (x as i64 - self.x_prev).rem_euclid(1 << 32);
        let ds = if ds >= 1 << 31 { ds - (1 << 32) } else { ds };
        self.x_prev = x as i64;
        let ads = ds.unsigned_abs();
        // The low pass is part of the definition, as for Model 4's current term: run as is.
        self.lp_bits = crate::model::operator::lowpass_bits(
            self.lp_bits,
            current_bits(current_a),
            slip::SLIP_LP_SHIFT,
        );
        let k = forward as usize;
        let raw = c.load_bits[k] as i64
            + (c.per_a_bits[k] as i64 * self.lp_bits as i64).div_euclid(1 << 16);
        let (cap, limit, h) = (
            c.cap_bits as i64,
            c.limit_bits as i64,
            c.half_gap_bits as i64,
        );
        let req = raw.clamp(-cap, cap);
        let lim = (ads as u128 * c.um_per_count_bits as u128).min(i32::MAX as u128) as i64;
        if raw.abs() > limit && ds != 0 && (ds > 0) == (raw > 0) {
            self.g = (self.g + raw.signum() * lim).clamp(-h, h);
            self.z = req;
            return;
        }
        if !((self.g >= h && req > self.z) || (self.g <= -h && req < self.z)) {
            let dz = (req - self.z).clamp(-lim, lim);
            self.g += dz;
            self.z += dz;
            if self.g > h {
                self.z -= self.g - h;
                self.g = h;
            } else if self.g < -h {
                self.z += -h - self.g;
                self.g = -h;
            }
        }
        let step = ads as u128 * c.kappa_q32 as u128;
        let (g, z) = (self.g, self.z);
        if (g >= h && z > 0) || (g <= -h && z < 0) {
            let step = step.min(slip::MAX_DECAY_Q32 as u128) as i64;
            self.z = z - (z * step + (1 << 31)).div_euclid(1 << 32);
        } else {
            let f = slip::creep_factor_q12(c.limit_bits, z as i32) as i64;
            let r = (z * f + (1 << 19)).div_euclid(1 << 20);
            let step = step.min(slip::MAX_CREEP_Q32 as u128) as i64;
            self.g = (g + (r * step + (1 << 23)).div_euclid(1 << 24)).clamp(-h, h);
        }
    }
}

/// The current as the drive holds it: I16F16 bits, saturated, 0 for a non-finite value.
fn current_bits(current_a: f64) -> i32 {
    if current_a.is_finite() {
        I16F16::saturating_from_num(current_a).to_bits()
    } else {
        0
    }
}

impl RefModel4 {
    /// The weighted sum of `t`, um, saturated like every output of the fixed-point models.
    fn combine(&self, t: &Model4Terms) -> f64 {
        let weights = &self.weight_um_per_count[t.forward as usize];
        let y = self.slip_weight * t.slip_um
            + self.offset_um
            + self.slope_um_per_count * t.from_ref_counts
            + weights
                .iter()
                .zip(&t.plays_counts)
                .map(|(w, f)| w * f)
                .sum::<f64>()
            + self
                .knot_um
                .iter()
                .zip(&t.hats)
                .map(|(v, h)| v * h)
                .sum::<f64>()
            + self
                .harmonic_um
                .iter()
                .zip(&t.harmonics)
                .map(|(w, h)| w[0] * h[0] + w[1] * h[1])
                .sum::<f64>()
            + self.current_um_per_a * t.current_a
            + self.current_lp_um_per_a * t.current_lp_a;
        let (lo, hi) = crate::model::operator::OUT_BITS;
        y.clamp(lo as f64 / 65536.0, hi as f64 / 65536.0)
    }

    fn from_coeffs(c: &crate::model::Model4Coeffs) -> RefModel4 {
        let q24 = |v: i32| v as f64 / (1u64 << 24) as f64;
        RefModel4 {
            widths: c.widths_counts.map(|w| w as f64),
            // Reverse, forward (by the flag `forward`).
            weight_um_per_count: [REVERSE, FORWARD].map(|k| c.weight_q24[k].map(q24)),
            x_ref: c.x_ref_counts,
            offset_um: c.offset_q31 as f64 / (1u64 << 31) as f64,
            slope_um_per_count: c.slope_q31 as f64 / (1u64 << 31) as f64,
            hat_start: c.hat_start_counts as f64,
            hat_recip: c.hat_recip_q32 as f64 / (1u64 << 32) as f64,
            knot_um: c.knot_um.map(|k| k.to_num()),
            rates: [c.pitch_rate, c.turn_rate],
            harmonic_um: [c.pitch.sin_cos_um(), c.turn.sin_cos_um()],
            current_um_per_a: c.current_um_per_a.to_num(),
            current_lp_um_per_a: c.current_lp_um_per_a.to_num(),
            slip_weight: c.belt.map_or(c.slip.weight_q16, |b| b.weight_q16) as f64 / 65536.0,
        }
    }
}

impl Reference {
    /// The reference for `params` on `rig`, starting at `x0_counts` like
    /// [`ModelState::new`](crate::model::ModelState::new). Fails where `params.build(rig)` fails.
    pub fn new(params: &ModelParams, rig: &Rig, x0_counts: i32) -> Result<Reference, ConfigError> {
        let c = params.build(rig)?;
        let m3 = c.model3();
        Ok(Reference {
            counts_per_mm: rig.counts_per_mm(),
            deadband_counts: params.reversal_deadband_counts,
            m1: params.model1,
            m2: params.model2,
            band_f: RefBand::from_coeffs(m3.band(Direction::Forward)),
            band_r: RefBand::from_coeffs(m3.band(Direction::Reverse)),
            trans_f: RefTransition::from_coeffs(m3.transition(Direction::Forward)),
            trans_r: RefTransition::from_coeffs(m3.transition(Direction::Reverse)),
            backlash_mm: (
                c.backlash().at(Direction::Forward).to_num::<f64>() / 1000.0,
                c.backlash().at(Direction::Reverse).to_num::<f64>() / 1000.0,
            ),
            bidir_x0: c.bidir().grid_counts().0 as f64,
            bidir_step: c.bidir().grid_counts().1 as f64,
            bidir_mm: [Direction::Forward, Direction::Reverse].map(|d| {
                (0..c.bidir().rows())
                    .filter_map(|i| c.bidir().value_um(d, i))
                    .map(|v| v.to_num::<f64>() / 1000.0)
                    .collect()
            }),
            dir: Direction::Forward,
            x_ext: x0_counts,
            y_ext_mm: 0.0,
            y_ext_valid: false,
            x_d: x0_counts,
            y_d_mm: 0.0,
            transition: false,
            g0_mm: 0.0,
            m4: RefModel4::from_coeffs(c.model4()),
            plays: [0.0; N_OPS],
            plays_valid: false,
            current_lp_bits: 0,
            slip: RefSlip::new(&c.model4().slip),
            belt: c.model4().belt.map(|b| (b.c, BeltState::ZERO)),
        })
    }

    /// Back to the start state at `x0_counts`.
    pub fn reset(&mut self, x0_counts: i32) {
        self.dir = Direction::Forward;
        self.x_ext = x0_counts;
        self.y_ext_mm = 0.0;
        self.y_ext_valid = false;
        self.x_d = x0_counts;
        self.y_d_mm = 0.0;
        self.transition = false;
        self.g0_mm = 0.0;
        self.plays_valid = false;
    }

    /// Direction as last registered.
    pub fn direction(&self) -> Direction {
        self.dir
    }

    /// One step: the error estimate of `kind` at `x_counts`, in micrometres. A prediction at
    /// rest like [`crate::model::estimate`]: Model 4's low passes settled at zero.
    pub fn estimate_um(&mut self, kind: ModelKind, x_counts: i32) -> f64 {
        if kind == ModelKind::Operator {
            self.current_lp_bits = 0;
            self.slip.lp_bits = 0;
        }
        self.estimate_with_current_um(kind, x_counts, 0.0)
    }

    /// [`Reference::estimate_um`] with the motor current (amperes), which only Model 4 uses.
    pub fn estimate_with_current_um(
        &mut self,
        kind: ModelKind,
        x_counts: i32,
        current_a: f64,
    ) -> f64 {
        if kind == ModelKind::Operator {
            return self.model4_step(x_counts, current_a).0;
        }
        self.track(x_counts);
        // Model 4's plays and observer only follow x while Model 4 runs.
        self.plays_valid = false;
        let y_mm = match kind {
            ModelKind::Operator | ModelKind::None => 0.0,
            ModelKind::Linear => self.model1(x_counts),
            ModelKind::Exponential => self.model2(x_counts),
            ModelKind::Table => self.model3(x_counts),
            ModelKind::Backlash => match self.dir {
                Direction::Forward => self.backlash_mm.0,
                Direction::Reverse => self.backlash_mm.1,
            },
            ModelKind::BidirTable => self.bidir(x_counts),
        };
        if x_counts == self.x_ext {
            self.y_ext_mm = y_mm;
            self.y_ext_valid = kind != ModelKind::None;
        }
        y_mm * 1000.0
    }

    /// Eqs. 15, 16: a reversal when `x` is more than the dead band back from the extreme.
    fn track(&mut self, x: i32) {
        let back = match self.dir {
            Direction::Forward => self.x_ext as i64 - x as i64,
            Direction::Reverse => x as i64 - self.x_ext as i64,
        };
        if back < 0 {
            self.x_ext = x;
        } else if back > self.deadband_counts as i64 {
            self.dir = match self.dir {
                Direction::Forward => Direction::Reverse,
                Direction::Reverse => Direction::Forward,
            };
            self.x_d = self.x_ext;
            self.y_d_mm = self.y_ext_mm;
            self.transition = self.y_ext_valid;
            self.x_ext = x;
            let x_d = self.x_d as f64;
            self.g0_mm = match self.dir {
                Direction::Forward => self.y_d_mm - self.band_f.at(x_d),
                Direction::Reverse => self.band_r.at(x_d) - self.y_d_mm,
            }
            .max(0.0);
        }
    }

    /// One step of Model 4 like [`Reference::estimate_with_current_um`], returning its terms
    /// before their weights as well: the estimate is their weighted sum (saturated), and
    /// calibration fits the weights to them.
    pub fn model4_step(&mut self, x_counts: i32, current_a: f64) -> (f64, Model4Terms) {
        self.track(x_counts);
        let t = self.model4_terms(x_counts, current_a);
        let y_um = self.m4.combine(&t);
        if x_counts == self.x_ext {
            self.y_ext_mm = y_um / 1000.0;
            self.y_ext_valid = true;
        }
        (y_um, t)
    }

    /// Moves Model 4's plays and slip observer with `x` (see [`crate::model::operator`]).
    fn model4_terms(&mut self, x: i32, current_a: f64) -> Model4Terms {
        let m = &self.m4;
        let xf = x as f64;
        let forward = self.dir == Direction::Forward;
        // The filter is integer on the drive and part of the feature's definition: run it as is.
        let bits = current_bits(current_a);
        self.current_lp_bits = if self.plays_valid {
            crate::model::operator::current_lowpass(self.current_lp_bits, bits)
        } else {
            bits
        };
        let belt_offset_um = match &mut self.belt {
            Some((c, s)) => {
                if self.plays_valid {
                    s.tick(c, x, bits);
                } else {
                    *s = BeltState::start(c, x, forward);
                }
                Some(s.offset_um_bits() as f64 / 65536.0)
            }
            None => {
                if self.plays_valid {
                    self.slip.step(forward, x, current_a);
                } else {
                    self.slip.start(forward, x, current_a);
                }
                None
            }
        };
        if !self.plays_valid {
            for (p, w) in self.plays.iter_mut().zip(&m.widths) {
                *p = match self.dir {
                    Direction::Forward => xf - w,
                    Direction::Reverse => xf + w,
                };
            }
            self.plays_valid = true;
        }
        let mut t = Model4Terms {
            forward: self.dir == Direction::Forward,
            from_ref_counts: xf - m.x_ref as f64,
            current_a,
            current_lp_a: I16F16::from_bits(self.current_lp_bits).to_num(),
            ..Model4Terms::default()
        };
        for ((p, w), f) in self
            .plays
            .iter_mut()
            .zip(&m.widths)
            .zip(&mut t.plays_counts)
        {
            *p = p.clamp(xf - w, xf + w);
            *f = xf - *p;
        }
        let pos = (xf - m.hat_start) * m.hat_recip;
        for (k, h) in t.hats.iter_mut().enumerate() {
            *h = (1.0 - (pos - (k + 1) as f64).abs()).max(0.0);
        }
        for (rate, h) in m.rates.iter().zip(&mut t.harmonics) {
            let turns = (x as i64)
                .wrapping_sub(m.x_ref as i64)
                .wrapping_mul(*rate as i64) as u32;
            let a = turns as f64 / (1u64 << 32) as f64 * core::f64::consts::TAU;
            *h = [a.sin(), a.cos()];
        }
        t.slip_um = belt_offset_um.unwrap_or_else(|| self.slip.offset_um());
        t
    }

    /// The bidirectional table of the current direction, interpolated, held flat outside.
    fn bidir(&self, x: i32) -> f64 {
        let t = match self.dir {
            Direction::Forward => &self.bidir_mm[0],
            Direction::Reverse => &self.bidir_mm[1],
        };
        let last = (t.len() - 1) as f64;
        let f = ((x as f64 - self.bidir_x0) / self.bidir_step).clamp(0.0, last);
        let i = (f.floor() as usize).min(t.len() - 2);
        let w = f - i as f64;
        t[i] + (t[i + 1] - t[i]) * w
    }

    fn mm(&self, counts: f64) -> f64 {
        counts / self.counts_per_mm
    }

    /// `x(k) - x_d(k)` in mm.
    fn since_turn_mm(&self, x: i32) -> f64 {
        self.mm(x as f64 - self.x_d as f64)
    }

    /// Eq. 14, bounded by the band on both sides.
    fn model1(&self, x: i32) -> f64 {
        let (transition, y_d_mm) = (self.transition, self.y_d_mm);
        let p = &self.m1;
        let xm = self.mm(x as f64);
        let (lower, upper) = (
            p.m_mm_per_mm * xm + p.offset_mm - p.h_mm,
            p.m_mm_per_mm * xm + p.offset_mm,
        );
        if !transition {
            return match self.dir {
                Direction::Forward => lower,
                Direction::Reverse => upper,
            };
        }
        let u = match self.dir {
            Direction::Forward => (y_d_mm - p.h_g_mm) - p.slope_a_mm_per_mm * self.since_turn_mm(x),
            Direction::Reverse => (y_d_mm + p.h_g_mm) - p.slope_b_mm_per_mm * self.since_turn_mm(x),
        };
        u.max(lower).min(upper)
    }

    /// Eq. 17, bounded by the band on both sides.
    fn model2(&self, x: i32) -> f64 {
        self.model2_at(self.transition, self.y_d_mm, x)
    }

    /// Model 2 from an explicit transition state (Model 4's own, or the drive's).
    fn model2_at(&self, transition: bool, y_d_mm: f64, x: i32) -> f64 {
        let p = &self.m2;
        let xm = self.mm(x as f64);
        let (lower, upper) = (
            p.m_mm_per_mm * xm + p.offset_mm - p.h_mm,
            p.m_mm_per_mm * xm + p.offset_mm,
        );
        if !transition {
            return match self.dir {
                Direction::Forward => lower,
                Direction::Reverse => upper,
            };
        }
        let dx = self.since_turn_mm(x);
        let u = match self.dir {
            Direction::Forward => {
                let e = (p.rate_a_per_mm * dx.max(0.0)).exp();
                (y_d_mm - p.h_g_mm) - p.amplitude_a_mm * (1.0 - e)
            }
            Direction::Reverse => {
                let e = (-p.rate_b_per_mm * dx.min(0.0)).exp();
                (y_d_mm + p.h_g_mm) + p.amplitude_b_mm * (1.0 - e)
            }
        };
        u.max(lower).min(upper)
    }

    /// Eq. 18 in our parametrisation (see [`crate::model::table`]).
    fn model3(&self, x: i32) -> f64 {
        let xf = x as f64;
        // Travel since the turning point in the current direction (>= 1 count in a transition).
        let dx = xf - self.x_d as f64;
        let d = match self.dir {
            Direction::Forward => dx.max(0.0),
            Direction::Reverse => (-dx).max(0.0),
        };
        match self.dir {
            Direction::Forward => {
                let edge = self.band_f.at(xf);
                if self.transition {
                    edge + self.trans_f.at(d, self.g0_mm)
                } else {
                    edge
                }
            }
            Direction::Reverse => {
                let edge = self.band_r.at(xf);
                if self.transition {
                    edge - self.trans_r.at(d, self.g0_mm)
                } else {
                    edge
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::slip::{Slip, SlipParams};
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig { cases: 512, failure_persistence: None, ..ProptestConfig::default() })]

        /// The plain `i64` observer is the drive's, bit for bit, on wild input: positions
        /// anywhere in `i32` (jumps across its wrap and of more than 2^31), currents anywhere
        /// in I16F16 (steps of the whole range), loads beyond the limit and within it.
        #[test]
        fn the_slip_reference_is_the_drive_s(
            load in prop::array::uniform2(0.0f64..2048.0),
            per_a in prop::array::uniform2(-2048.0f64..2048.0),
            creep_per_mm in 0.0f64..10.0,
            limit_um in 1.0f64..2048.0,
            half_gap_um in 1.0f64..2048.0,
            x0 in any::<i32>(),
            walk in prop::collection::vec((any::<i32>(), -2000i32..2000, any::<i32>(), any::<bool>(), 0u8..3), 1..100),
        ) {
            let c = SlipParams {
                load_um: load,
                um_per_a: per_a,
                creep_per_mm,
                limit_um,
                half_gap_um,
                weight: 1.0,
            }
            .build(500.0)
            .expect("observer builds");
            let (mut drive, mut reference) = (Slip::NEW, RefSlip::new(&c));
            drive.start(&c, true, x0, 0);
            reference.start(true, x0, 0.0);
            let mut x = x0;
            for (jump, step, current_bits, forward, kind) in walk {
                x = match kind {
                    0 => jump,
                    _ => x.wrapping_add(step),
                };
                let amps = I16F16::from_bits(current_bits);
                drive.step(&c, forward, x, current_bits);
                reference.step(forward, x, amps.to_num());
                prop_assert_eq!(drive.g_bits as i64, reference.g);
                prop_assert_eq!(drive.z_bits as i64, reference.z);
            }
        }
    }
}
