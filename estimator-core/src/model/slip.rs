//! Model 4's slip observer: where the belt sits in the tooth gap of the pulley, as a state.
//!
//! Section 2 of the paper: between the fast jump and the band the belt "slowly slides until the
//! next set of teeth pairs engage". What slides is the belt on the pulley's tooth tips, against
//! friction. The observer carries the two states of that contact, in micrometres of belt:
//! - `g`, the mesh offset (pulley minus belt) in `[-h, h]`: at `+h` the teeth drive the belt
//!   forward, at `-h` backward, in between only friction does;
//! - `z`, the friction's deflection (the bristles of eq. 11), which carries the belt's load.
//!
//! Each tick, with the pulley's travel `ds` (motor counts) and the load (a deflection per
//! direction of motion plus one per ampere of the current through a short low pass):
//! 1. **Pre-sliding.** Out of contact, `z` follows the load and `g` moves with it (the belt
//!    slides by what the bristles deflect), by at most the pulley's own travel. In contact the
//!    teeth take a load that grows.
//! 2. **Gross slip.** While the load is beyond the friction limit `z_max` in the direction of
//!    motion, the belt stands and the pulley runs under it: `g` moves by the pulley's whole
//!    travel each tick until the flank meets (at 3000-5000 mm/s² on the paper rig the gap is
//!    crossed within the acceleration). A current spike of a few ticks moves the belt part of
//!    the way: the belt cannot cross faster than the pulley moves. Crossing at once made Model
//!    4 114 um wrong for a whole stroke on a light carriage behind a high ratio, where the
//!    plant's belt crossed a third of the gap (`hil-sim generalise --drawn 3`, machine 3).
//! 3. **Creep.** Out of contact, belt material entering the wrap unstrained lets it slip by
//!    `kappa z / (1 - |z| / z_max)` per unit of travel (the renewal term of the plant's
//!    friction, `u ~ kappa z / (1 - sigma0 z / g)`): slip in proportion to travel and load,
//!    independent of speed. In contact the same renewal hands the load to the teeth (`z`
//!    decays by `kappa` per unit of travel).
//!
//! Why (measured on the simulated rig, `hil-sim` generalisation workloads): with the plant's
//! true mesh offset as one more least-squares term, Model 4's residual on Fig. 18 falls from
//! 20.7 to 2.4 um; the offset is what the paper's models and the plays leave out. The plays
//! model the creep as a function of the distance since each turning point; the real creep
//! depends on the load on the way (acceleration, braking, stops), which only a state carries.
//!
//! # Fixed point
//! `g`, `z` and the limits are I16F16 um in `i32`. The low pass is `l += (i - l) >> 2` on the
//! I16F16 current bits. The step `kappa |ds|` is a Q32 fraction (`kappa` at most 1/16 per
//! count), capped at 128 for the creep (`z` times the factor in Q8 um times the step) and at 1
//! for the hand-over in contact. The creep
//! factor `z_max / (z_max - |z|)` is a Q12 integer from Q8 um operands, rounded: one 32-bit
//! division. Products round to nearest, so the state does not drift against the `f64`
//! reference ([`crate::reference`]), which runs the same definitions.

use crate::ConfigField;
use fixed::types::I16F16;

use super::convert::finite;
use super::operator::lowpass_bits;
use crate::ConfigError;

/// The current's low pass inside the observer: `1 / 2^SLIP_LP_SHIFT` per tick (2 ms at 2 kHz).
pub const SLIP_LP_SHIFT: u32 = 2;
/// Largest `kappa` per count, Q32 (1/16).
pub const MAX_KAPPA_Q32: u64 = 1 << 28;
/// Largest `kappa |ds|` per step for the creep, Q32 (128; the drive's placement predicts a
/// whole move in one step), and for the hand-over in contact (1: all of the load).
pub const MAX_CREEP_Q32: u64 = 1 << 39;
/// See [`MAX_CREEP_Q32`].
pub const MAX_DECAY_Q32: u64 = 1 << 32;
/// Largest limit, half gap and load, um.
pub const MAX_SLIP_UM: f64 = 2048.0;

/// The observer's parameters (calibration fits them on the whole motion, see `hil-sim`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlipParams {
    /// Friction deflection carrying the load at constant speed, reverse `[0]` and forward `[1]`,
    /// um (both >= 0; the reverse one acts backward).
    pub load_um: [f64; 2],
    /// Deflection per ampere of the low-passed motor current, reverse and forward, um/A.
    pub um_per_a: [f64; 2],
    /// Renewal of the contact per mm of pulley travel (`kappa`), 1/mm, from 0 to a sixteenth of
    /// the counts per mm.
    pub creep_per_mm: f64,
    /// Friction limit as a deflection (`z_max`), um, in `[1, 2048]`.
    pub limit_um: f64,
    /// Half the tooth gap (`h`), um, in `[1, 2048]`.
    pub half_gap_um: f64,
    /// Weight of `g` in Model 4's sum (um of error per um of offset; `|w| < 8`).
    pub weight: f64,
}

impl SlipParams {
    /// An observer that adds nothing (weight 0) with a plausible shape.
    pub const ZERO: SlipParams = SlipParams {
        load_um: [0.0; 2],
        um_per_a: [0.0; 2],
        creep_per_mm: 0.0,
        limit_um: 100.0,
        half_gap_um: 100.0,
        weight: 0.0,
    };

    /// Checks every field and converts for `counts_per_mm`; errors name the field.
    pub fn build(&self, counts_per_mm: f64) -> Result<SlipCoeffs, ConfigError> {
        let bounded = |v: f64, lo: f64, field: ConfigField| -> Result<f64, ConfigError> {
            let v = finite(v, field)?;
            if !(lo..=MAX_SLIP_UM).contains(&v) {
                return Err(ConfigError::OutOfRange(field));
            }
            Ok(v)
        };
        let limit = bounded(self.limit_um, 1.0, ConfigField::Model4SlipLimitUm)?;
        let half_gap = bounded(self.half_gap_um, 1.0, ConfigField::Model4SlipHalfGapUm)?;
        let mut load_bits = [0i32; 2];
        let mut per_a_bits = [0i32; 2];
        for k in 0..2 {
            let l = bounded(self.load_um[k], 0.0, ConfigField::Model4SlipLoadUm)?;
            // Reverse acts backward.
            load_bits[k] = I16F16::from_num(if k == 0 { -l } else { l }).to_bits();
            let a = finite(self.um_per_a[k], ConfigField::Model4SlipUmPerA)?;
            if a.abs() > MAX_SLIP_UM {
                return Err(ConfigError::OutOfRange(ConfigField::Model4SlipUmPerA));
            }
            per_a_bits[k] = I16F16::from_num(a).to_bits();
        }
        let kappa = finite(self.creep_per_mm, ConfigField::Model4SlipCreepPerMm)?;
        let kappa_q32 = kappa / counts_per_mm * (1u64 << 32) as f64;
        // At most 1/16 per count (the hand-over's cap of 1 is then reached at 16 counts per
        // tick, the creep's of 128 at 2048).
        if !(0.0..=MAX_KAPPA_Q32 as f64).contains(&kappa_q32) {
            return Err(ConfigError::OutOfRange(ConfigField::Model4SlipCreepPerMm));
        }
        let um_per_count = 1000.0 / counts_per_mm * 65536.0;
        let weight = finite(self.weight, ConfigField::Model4SlipWeight)?;
        if weight.abs() >= 8.0 {
            return Err(ConfigError::OutOfRange(ConfigField::Model4SlipWeight));
        }
        let limit_bits = I16F16::from_num(limit).to_bits();
        Ok(SlipCoeffs {
            load_bits,
            per_a_bits,
            kappa_q32: (kappa_q32 + 0.5) as u32,
            um_per_count_bits: (um_per_count + 0.5).min(u32::MAX as f64) as u32,
            limit_bits,
            cap_bits: SlipCoeffs::cap_bits_of(limit_bits),
            half_gap_bits: I16F16::from_num(half_gap).to_bits(),
            // Half away from zero (`core` has no `f64::round`).
            weight_q16: (if weight >= 0.0 {
                weight * 65536.0 + 0.5
            } else {
                weight * 65536.0 - 0.5
            }) as i32,
        })
    }
}

/// The observer's fixed-point coefficients (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SlipCoeffs {
    /// Load at constant speed, reverse (negative) and forward, I16F16 um.
    pub(crate) load_bits: [i32; 2],
    /// Per ampere, I16F16 um/A.
    pub(crate) per_a_bits: [i32; 2],
    /// `kappa` per count, Q32.
    pub(crate) kappa_q32: u32,
    /// Travel per count, I16F16 um.
    pub(crate) um_per_count_bits: u32,
    /// `z_max` and the cap on the load (`0.95 z_max`), I16F16 um.
    pub(crate) limit_bits: i32,
    pub(crate) cap_bits: i32,
    /// `h`, I16F16 um.
    pub(crate) half_gap_bits: i32,
    /// Weight of `g`, Q16.
    pub(crate) weight_q16: i32,
}

impl SlipCoeffs {
    /// The cap on the load, `0.95 z_max`, kept with the coefficients so that the tick does not
    /// derive it.
    pub(crate) const fn cap_bits_of(limit_bits: i32) -> i32 {
        limit_bits - limit_bits / 20
    }

    /// Adds nothing; all bits zero (so that `ModelCoeffs::ZERO` stays in `.bss`, not a copy
    /// in flash). A zero limit and gap are total: the factor is 0 and `g` stays at 0.
    pub const ZERO: SlipCoeffs = SlipCoeffs {
        load_bits: [0; 2],
        per_a_bits: [0; 2],
        kappa_q32: 0,
        um_per_count_bits: 0,
        limit_bits: 0,
        cap_bits: 0,
        half_gap_bits: 0,
        weight_q16: 0,
    };
}

/// The observer's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Slip {
    /// Mesh offset and friction deflection, I16F16 um.
    pub(crate) g_bits: i32,
    pub(crate) z_bits: i32,
    /// Low-passed current, I16F16 A.
    pub(crate) lp_bits: i32,
    pub(crate) x_prev: i32,
}

impl Slip {
    pub(crate) const NEW: Slip = Slip {
        g_bits: 0,
        z_bits: 0,
        lp_bits: 0,
        x_prev: 0,
    };

    /// Against the teeth on the side that moving `forward` puts the belt, the load with the
    /// teeth (as after a long move: the plays start on the same side).
    pub(crate) fn start(&mut self, c: &SlipCoeffs, forward: bool, x: i32, current_bits: i32) {
        *self = Slip {
            g_bits: if forward {
                c.half_gap_bits
            } else {
                -c.half_gap_bits
            },
            z_bits: 0,
            lp_bits: current_bits,
            x_prev: x,
        };
    }

    /// One tick at motor position `x` with the current's I16F16 bits, moving `forward` as the
    /// reversal detector registered it.
    #[inline(always)]
    pub(crate) fn step(&mut self, c: &SlipCoeffs, forward: bool, x: i32, current_bits: i32) {
        let ds = x.wrapping_sub(self.x_prev);
        self.x_prev = x;
        self.lp_bits = lowpass_bits(self.lp_bits, current_bits, SLIP_LP_SHIFT);
        if ds == 0 {
            // Standing still moves neither `g` nor `z`: no slip without travel, the load's
            // swing and the creep are bounded by the travel, and the state is in the gap
            // (`|g| <= h`, the drive restarts it with new coefficients). Most ticks of a
            // positioning job are at rest.
            return;
        }
        let ads = ds.unsigned_abs();
        let k = forward as usize;
        // |per_a| <= 2^27, |lp| <= 2^31: the load fits 2^58.
        let raw = c.load_bits[k] as i64 + ((c.per_a_bits[k] as i64 * self.lp_bits as i64) >> 16);
        let h = c.half_gap_bits;
        let lim = (ads as u64 * c.um_per_count_bits as u64).min(i32::MAX as u64) as i32;
        // Beyond the limit (>= 0) the load is the cap (<= the limit); within it, it fits an
        // `i32`, so the load and the pre-slide are 32-bit.
        let limit = c.limit_bits as i64;
        let req = if raw > limit {
            if ds > 0 {
                // The belt stands while the pulley runs under it, towards the flank.
                self.g_bits = self.g_bits.saturating_add(lim).min(h);
                self.z_bits = c.cap_bits;
                return;
            }
            c.cap_bits
        } else if raw < -limit {
            if ds < 0 {
                self.g_bits = self.g_bits.saturating_sub(lim).max(-h);
                self.z_bits = -c.cap_bits;
                return;
            }
            -c.cap_bits
        } else {
            // max/min, not clamp: the bounds come from coefficients, and clamp asserts their
            // order.
            (raw as i32).max(-c.cap_bits).min(c.cap_bits)
        };
        let (g, z) = (self.g_bits, self.z_bits);
        let hold = (g >= h && req > z) || (g <= -h && req < z);
        if !hold {
            // |req| <= cap < 2^27 and |z| < 2^27 (|g - z| <= 2^27 even after new coefficients):
            // no overflow.
            let dz = (req - z).max(-lim).min(lim);
            let (mut g, mut z) = (g + dz, z + dz);
            if g > h {
                z -= g - h;
                g = h;
            } else if g < -h {
                z += -h - g;
                g = -h;
            }
            self.g_bits = g;
            self.z_bits = z;
        }
        let step = ads as u64 * c.kappa_q32 as u64;
        let (g, z) = (self.g_bits, self.z_bits);
        if (g >= h && z > 0) || (g <= -h && z < 0) {
            let step = step.min(MAX_DECAY_Q32) as i64;
            self.z_bits = z - ((z as i64 * step + (1 << 31)) >> 32) as i32;
        } else {
            // |z| < 2^27 and the factor <= 2^17: r (Q8 um) < 2^24, times a step <= 2^39
            // fits an i64 (the drive resets the state with new coefficients; a state kept
            // across them stays within these bounds too).
            let r = (z as i64 * creep_factor_q12(c.limit_bits, z) as i64 + (1 << 19)) >> 20;
            let dg = (r * step.min(MAX_CREEP_Q32) as i64 + (1 << 23)) >> 24;
            self.g_bits = (g as i64 + dg).max(-(h as i64)).min(h as i64) as i32;
        }
    }

    /// The output term: `weight g`, Q24 um.
    #[inline(always)]
    pub(crate) fn term(&self, c: &SlipCoeffs) -> i64 {
        (self.g_bits as i64 * c.weight_q16 as i64) >> 8
    }
}

/// `z_max / (z_max - |z|)` in Q12, rounded, from Q8 operands, at most 32. The observer keeps
/// `|z| <= 0.95 z_max` (a factor of 20); the cap bounds it for any state.
#[inline(always)]
pub fn creep_factor_q12(limit_bits: i32, z_bits: i32) -> u32 {
    // limit <= 2048 um: limit_q8 <= 2^19, shifted by 12 it fits a u32.
    let limit_q8 = ((limit_bits.max(0) >> 8) as u32).min(1 << 19);
    let den = limit_q8.saturating_sub(z_bits.unsigned_abs() >> 8).max(1);
    (((limit_q8 << 12) + den / 2) / den).min(MAX_FACTOR_Q12)
}

/// Cap of [`creep_factor_q12`]: 32 in Q12.
pub const MAX_FACTOR_Q12: u32 = 32 << 12;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const CPM: f64 = 1868.0;

    fn coeffs(load_um: f64, um_per_a: f64, limit_um: f64, half_gap_um: f64) -> SlipCoeffs {
        SlipParams {
            load_um: [load_um; 2],
            um_per_a: [um_per_a; 2],
            creep_per_mm: 0.03,
            limit_um,
            half_gap_um,
            weight: -1.0,
        }
        .build(CPM)
        .expect("observer builds")
    }

    fn um(bits: i32) -> f64 {
        bits as f64 / 65536.0
    }

    /// A stroke after a reversal: the pre-slide swings the load's deflection over at once, then
    /// the belt creeps at `kappa z / (1 - z / z_max)` per mm until the other flank meets.
    #[test]
    fn a_reversal_pre_slides_then_creeps_to_the_other_flank() {
        let c = coeffs(60.0, 0.0, 150.0, 140.0);
        let mut s = Slip::NEW;
        s.start(&c, true, 0, 0);
        // Forward 1 mm: against the forward flank, the load handed to the teeth.
        let mut x = 0;
        for _ in 0..100 {
            x += 19;
            s.step(&c, true, x, 0);
        }
        assert_eq!(s.g_bits, c.half_gap_bits);
        // Back in 10-count ticks (5.4 um each): 60 um of pre-slide within 12 ticks, then creep.
        let g_before = um(s.g_bits);
        for _ in 0..12 {
            x -= 10;
            s.step(&c, false, x, 0);
        }
        let after_slide = um(s.g_bits);
        assert!(
            (g_before - after_slide - 60.0).abs() < 1.0,
            "{g_before} -> {after_slide}"
        );
        let (g0, x0) = (um(s.g_bits), x);
        for _ in 0..300 {
            x -= 10;
            s.step(&c, false, x, 0);
        }
        let per_mm = (g0 - um(s.g_bits)) / ((x0 - x) as f64 / CPM);
        let want = 0.03 * 60.0 / (1.0 - 60.0 / 150.0);
        assert!(
            (per_mm - want).abs() < 0.01 * want,
            "{per_mm} um/mm, want {want}"
        );
        // Far enough and the reverse flank meets.
        for _ in 0..20_000 {
            x -= 10;
            s.step(&c, false, x, 0);
        }
        assert_eq!(s.g_bits, -c.half_gap_bits);
    }

    /// A load beyond the limit in the direction of motion slips the belt across the gap by the
    /// pulley's whole travel each tick (the belt stands while the pulley runs under it), onto
    /// the flank and no further.
    #[test]
    fn a_load_beyond_the_limit_slips_across_the_gap() {
        let c = coeffs(60.0, 50.0, 150.0, 140.0);
        let mut s = Slip::NEW;
        s.start(&c, false, 0, 0);
        let amps = I16F16::from_num(2.5).to_bits();
        let travel_bits = 5 * c.um_per_count_bits as i32;
        let mut x = 0;
        // The low pass reaches the limit (60 + 50 x 2.5 um > 150 um) within a few ticks.
        for _ in 0..8 {
            x += 5;
            s.step(&c, true, x, amps);
        }
        assert!(s.g_bits > -c.half_gap_bits);
        let mut slipped = 0;
        while s.g_bits < c.half_gap_bits {
            let before = s.g_bits;
            x += 5;
            s.step(&c, true, x, amps);
            assert_eq!(s.g_bits - before, travel_bits.min(c.half_gap_bits - before));
            slipped += 1;
            assert!(slipped < 200, "the flank never met");
        }
        // 280 um at 2.7 um a tick.
        assert!(slipped > 90, "{slipped}");
        for _ in 0..10 {
            x += 5;
            s.step(&c, true, x, amps);
            assert_eq!(s.g_bits, c.half_gap_bits);
        }
    }

    proptest! {
        /// On any walk, any current: `g` stays in the gap and `|z|` within the limit; standing
        /// still changes nothing whatever the current does; and the step is the same whether
        /// `x` wraps around `i32` or not.
        #[test]
        fn the_state_stays_physical(
            load in 0.0f64..300.0,
            per_a in -100.0f64..100.0,
            limit in 1.0f64..500.0,
            half_gap in 1.0f64..500.0,
            x0 in any::<i32>(),
            walk in prop::collection::vec((-3000i32..3000, -20.0f64..20.0, 0u8..4), 1..200),
        ) {
            let c = coeffs(load, per_a, limit, half_gap);
            let mut s = Slip::NEW;
            s.start(&c, true, x0, 0);
            let mut x = x0;
            for (dx, amps, hold) in walk {
                let bits = I16F16::from_num(amps).to_bits();
                if hold == 0 {
                    let before = (s.g_bits, s.z_bits);
                    s.step(&c, dx > 0, x, bits);
                    prop_assert_eq!((s.g_bits, s.z_bits), before);
                    continue;
                }
                x = x.wrapping_add(dx);
                s.step(&c, dx > 0, x, bits);
                prop_assert!(s.g_bits.abs() <= c.half_gap_bits);
                prop_assert!(s.z_bits.abs() <= c.limit_bits);
            }
        }
    }
}
