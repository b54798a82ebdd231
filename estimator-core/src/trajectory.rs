//! Trapezoidal velocity profile in motor encoder counts, one step per control tick.
//!
//! Position, velocity and acceleration share one fixed-point grid, [`I40F24`]: counts,
//! counts/tick and counts/tick² with 24 fractional bits. Sharing the grid makes `velocity += dv`
//! and `position += velocity` exact integer additions, so the setpoint lands on the target count
//! with no residual and no drift, however long the move. 24 bits resolve 0.013 mm/s²
//! of acceleration at 20 kHz on [`crate::rig::Rig::PAPER`]. The position never passes its target, so it stays
//! between the start and the targets: within `i32` counts, and differences never overflow.
//!
//! # Algorithm
//! Each tick picks the fastest speed `w` that (a) changes the speed by at most one tick of
//! acceleration (speeding up) or deceleration `d` (slowing down), (b) does not exceed the velocity
//! limit, and (c) still lets the carriage stop exactly on the target: the distance covered by `w`
//! and then full braking, `w + (w - d) + (w - 2d) + ...` (the run-out `S(w)`), must fit in the
//! distance left. Writing `w = (n - 1) d + r` with `0 < r <= d`, `S(w) = n r + d n (n - 1) / 2`:
//! one 32x32->64 and one 32x64 multiply, no division and no square root. `n` and `r` are kept up
//! to date by additions as the speed changes, because the decomposition would otherwise need a
//! division.
//!
//! Once `S(w) <= remaining` holds it holds forever (braking by exactly `d` from `w` leaves
//! `S(w - d) = S(w) - w`), so the profile always arrives, and within one deceleration of rest
//! `S(w) = w`, so the last step takes exactly what is left. Per tick:
//! - far from the target (beyond the run-out from the velocity limit): accelerate or cruise, no
//!   run-out needed;
//! - braking: one run-out, `S(speed - d)`; the speed is set above `speed - d` by the largest
//!   `k` with `S(speed - d + k) <= remaining`, one hardware division while the sums fit 32 bits
//!   (else `slack >> ceil(log2(n + 1))`, which never overshoots and absorbs at least half the
//!   slack each tick); the ticks after it that brake by exactly `d` are counted;
//! - far from the target, the ticks that accelerate by exactly `accel` or cruise are counted
//!   too: a counted tick adds a stored step;
//! - the tick(s) where a short move stops accelerating below the limit (the peak of a triangle):
//!   a bisection over whole decelerations, at most 29 run-outs and usually one or two.
//!
//! If the carriage cannot stop at a new target (behind it, or too close ahead) it brakes at full
//! deceleration to rest, then starts a fresh move back: a reversal passes through zero velocity
//! for exactly one tick and never steps the velocity.

use crate::ConfigField;
use core::num::NonZeroU32;
use fixed::types::I40F24;

#[cfg(test)]
use crate::rig::Rig;
use crate::{BuildContext, ConfigError};

/// Fractional bits of the counts grid shared by position, velocity and acceleration.
const FRAC_BITS: u32 = 24;
// The setpoint accessors hand out Q8 and Q16 positions and velocities and a Q24 acceleration.
const _: () = assert!(FRAC_BITS >= 24);
const ONE_COUNT: i64 = 1 << FRAC_BITS;
/// Fastest profile: 2048 counts/tick (2.2 m/s at 2 kHz, 548 mm/s at 500 Hz on the paper's rig).
const MAX_VELOCITY_BITS: u64 = 1 << (11 + FRAC_BITS);
/// Steepest ramp: just under 64 counts/tick² (8.5 m/s² at 500 Hz); keeps `r + k < 2^31`.
const MAX_ACCEL_BITS: u64 = (1 << 30) - 1;
/// Longest braking distance from full speed: 2^31 counts (1150 m). Bounds every run-out, so the
/// run-out arithmetic fits `u64` with room to spare.
const MAX_RUN_OUT_BITS: u128 = 1 << (31 + FRAC_BITS);

/// `ceil(n / d)` for a divisor of 1 ..= 2^31 (0 reads as 1), with the hardware's 32-bit division
/// and a 32-step long division: the compiler's `u64` division routine costs the drive ~0.9 KB of
/// flash for the two divisions a configuration or a retarget needs (never per tick).
fn div_ceil_u64(n: u64, d: u32) -> u64 {
    let d = d.clamp(1, 1 << 31);
    let hi = (n >> 32) as u32;
    // Remainder below `d <= 2^31`: shifted left once it still fits a `u64`, and compared with `d`.
    let mut rem = (hi % d) as u64;
    let mut lo_q = 0u32;
    let lo = n as u32;
    for bit in (0..32).rev() {
        rem = (rem << 1) | ((lo >> bit) & 1) as u64;
        lo_q <<= 1;
        if rem >= d as u64 {
            rem -= d as u64;
            lo_q |= 1;
        }
    }
    let q = ((hi / d) as u64) << 32 | lo_q as u64;
    q + (rem != 0) as u64
}

/// Motion limits in SI units, converted by [`Config::build`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Config {
    /// Cruise speed (velocity limit).
    pub velocity_mm_s: f64,
    /// Acceleration limit while speeding up.
    pub acceleration_mm_s2: f64,
    /// Deceleration limit while slowing down (a positive number).
    pub deceleration_mm_s2: f64,
}

impl Config {
    /// Moderate moves for the paper's rig at 2 kHz: 100 mm/s (within the 5-250 mm/s the stage
    /// typically runs) and 2000 mm/s² both ways, which the 150 W motor through 23.7:1 delivers
    /// with about 2 A of the 8 A limit (≈33 kg effective mass, mostly reflected rotor inertia).
    pub const PAPER_RIG: Config = Config {
        velocity_mm_s: 100.0,
        acceleration_mm_s2: 2000.0,
        deceleration_mm_s2: 2000.0,
    };

    /// Converts to per-tick limits in counts (one profile step per control tick of `ctx`),
    /// rounding every limit down so the profile never exceeds what was asked for.
    pub fn build(&self, ctx: &BuildContext) -> Result<Coeffs, ConfigError> {
        let rate_hz = ctx.rate_hz();
        let counts_per_mm = ctx.rig().counts_per_mm();
        let velocity = grid_floor(
            self.velocity_mm_s,
            counts_per_mm / rate_hz,
            MAX_VELOCITY_BITS,
            ConfigField::TrajectoryVelocityMmS,
        )?;
        let per_tick2 = counts_per_mm / (rate_hz * rate_hz);
        let acceleration = grid_floor(
            self.acceleration_mm_s2,
            per_tick2,
            MAX_ACCEL_BITS,
            ConfigField::TrajectoryAccelerationMmS2,
        )?;
        let deceleration = grid_floor(
            self.deceleration_mm_s2,
            per_tick2,
            MAX_ACCEL_BITS,
            ConfigField::TrajectoryDecelerationMmS2,
        )?;
        Coeffs::new(
            I40F24::from_bits(velocity as i64),
            I40F24::from_bits(acceleration as i64),
            I40F24::from_bits(deceleration as i64),
        )
    }
}

impl Default for Config {
    fn default() -> Self {
        Self::PAPER_RIG
    }
}

/// `value * scale` on the counts grid, rounded down; `1 ..= max_bits` LSBs.
fn grid_floor(
    value: f64,
    scale: f64,
    max_bits: u64,
    field: ConfigField,
) -> Result<u64, ConfigError> {
    if !value.is_finite() {
        return Err(ConfigError::NotFinite(field));
    }
    let bits = value * scale * ONE_COUNT as f64;
    if !(bits >= 1.0 && bits <= max_bits as f64) {
        return Err(ConfigError::OutOfRange(field));
    }
    // Truncation is floor for a positive value (`f64::floor` is not in `core`).
    Ok(bits as u64)
}

/// Per-tick limits on the counts grid, with the constants the per-tick step needs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Coeffs {
    /// Velocity limit, LSBs of counts/tick.
    velocity: u64,
    /// Acceleration limit, LSBs of counts/tick².
    accel: u32,
    /// Deceleration limit, LSBs of counts/tick².
    decel: u32,
    /// `accel = accel_decels * decel + accel_rem`, `accel_rem < decel`.
    accel_decels: u32,
    accel_rem: u32,
    /// `velocity = (velocity_n - 1) * decel + velocity_r`, `0 < velocity_r <= decel`.
    velocity_n: u32,
    velocity_r: u32,
    /// Run-out from the velocity limit: beyond it the brake check is skipped.
    velocity_run_out: u64,
}

impl Coeffs {
    /// Coefficients from limits already on the counts grid (no floats): velocity in counts/tick,
    /// acceleration and deceleration in counts/tick², all positive. Velocity up to 2048
    /// counts/tick, acceleration and deceleration below 64 counts/tick², braking distance from
    /// full speed up to 2^31 counts (else the deceleration is named as out of range).
    pub fn new(
        velocity_counts_per_tick: I40F24,
        acceleration_counts_per_tick2: I40F24,
        deceleration_counts_per_tick2: I40F24,
    ) -> Result<Self, ConfigError> {
        let in_range = |x: I40F24, max: u64, field| {
            let bits = x.to_bits();
            if bits >= 1 && bits as u64 <= max {
                Ok(bits as u64)
            } else {
                Err(ConfigError::OutOfRange(field))
            }
        };
        let velocity = in_range(
            velocity_counts_per_tick,
            MAX_VELOCITY_BITS,
            ConfigField::TrajectoryVelocityMmS,
        )?;
        let accel = in_range(
            acceleration_counts_per_tick2,
            MAX_ACCEL_BITS,
            ConfigField::TrajectoryAccelerationMmS2,
        )? as u32;
        let decel = in_range(
            deceleration_counts_per_tick2,
            MAX_ACCEL_BITS,
            ConfigField::TrajectoryDecelerationMmS2,
        )? as u32;
        // Divisions are fine here: once per configuration, never per tick.
        let velocity_n = div_ceil_u64(velocity, decel);
        let run_out = velocity_n as u128 * (velocity_n as u128 - 1) / 2 * decel as u128
            + velocity_n as u128 * decel as u128;
        // Upper bound (r <= d) of the run-out; rejects before `velocity_n` can overflow a u32.
        if run_out > MAX_RUN_OUT_BITS {
            return Err(ConfigError::OutOfRange(
                ConfigField::TrajectoryDecelerationMmS2,
            ));
        }
        let velocity_n = velocity_n as u32;
        let velocity_r = (velocity - (velocity_n as u64 - 1) * decel as u64) as u32;
        Ok(Self {
            velocity,
            accel,
            decel,
            accel_decels: accel / decel,
            accel_rem: accel % decel,
            velocity_n,
            velocity_r,
            velocity_run_out: run_out_bits(decel, velocity_n, velocity_r),
        })
    }

    /// Velocity limit.
    pub fn velocity_counts_per_tick(&self) -> I40F24 {
        I40F24::from_bits(self.velocity as i64)
    }

    /// Acceleration limit.
    pub fn acceleration_counts_per_tick2(&self) -> I40F24 {
        I40F24::from_bits(self.accel as i64)
    }

    /// Deceleration limit.
    pub fn deceleration_counts_per_tick2(&self) -> I40F24 {
        I40F24::from_bits(self.decel as i64)
    }

    /// Distance needed to stop from the velocity limit, counting the current tick.
    pub fn run_out_counts(&self) -> I40F24 {
        I40F24::from_bits(self.velocity_run_out as i64)
    }
}

impl Default for Coeffs {
    fn default() -> Self {
        match Config::PAPER_RIG.build(&BuildContext::PAPER) {
            Ok(c) => c,
            // Unreachable: the default configuration is valid (tested). A slow fallback rather
            // than a panic path.
            Err(_) => Self {
                velocity: 1,
                accel: 1,
                decel: 1,
                accel_decels: 1,
                accel_rem: 0,
                velocity_n: 1,
                velocity_r: 1,
                velocity_run_out: 1,
            },
        }
    }
}

/// Distance in LSBs covered by speed `w = (n - 1) d + r` this tick and by full braking after:
/// `w + (w - d) + ... + r = n r + d n (n - 1) / 2`. Exact: `n <= 2^28` and the result is at most
/// the run-out from the velocity limit (< 2^55) for every speed the profile can reach.
#[inline(always)]
fn run_out_bits(d: u32, n: u32, r: u32) -> u64 {
    let n = n as u64;
    // 32x32->64: n < 2^32.
    let triangle = n.wrapping_mul(n.saturating_sub(1)) >> 1;
    (d as u64)
        .wrapping_mul(triangle)
        .wrapping_add(n.wrapping_mul(r as u64))
}

/// The fastest speed in `[lo, hi]` whose run-out fits in `ahead`, given
/// `S(lo) = lo_run_out <= ahead < S(hi)`; each speed as `(w, n, r)`. Never overshoots; may fall
/// short of the optimum by less than half the remaining slack, which the next tick takes up.
///
/// Only the tick(s) where a move stops accelerating short of the velocity limit come here (the
/// peak of a triangle), so it is kept out of line.
#[inline(never)]
fn fit(
    d: u32,
    (lo, lo_n, lo_r): (u64, u32, u32),
    lo_run_out: u64,
    hi: (u64, u32, u32),
    ahead: u64,
) -> (u64, u32, u32) {
    // 1. Whole decelerations above `lo`: `lo + j d` is `(lo_n + j, lo_r)`, so its run-out needs no
    // division. Bisect for the largest `j` that fits. `j_max` counts the whole steps below `hi`:
    // 0 or 1 when acceleration <= deceleration. At most 29 probes (`n < 2^28`).
    //
    // Arithmetic here and in `tick` cannot wrap (speeds <= the velocity limit, `n < 2^28`,
    // `r + k < 2^31`, run-outs < 2^55); it is spelled `wrapping_*` so that debug and release
    // builds compile to the same panic-free code.
    let j_max = hi.1.wrapping_sub(lo_n).wrapping_sub((hi.2 < lo_r) as u32);
    let (mut j_fit, mut run_fit) = (0u32, lo_run_out);
    let mut j_over = j_max.wrapping_add(1);
    while j_over.wrapping_sub(j_fit) > 1 {
        let j = j_fit.wrapping_add(j_over.wrapping_sub(j_fit) >> 1);
        let run = run_out_bits(d, lo_n.wrapping_add(j), lo_r);
        if run <= ahead {
            (j_fit, run_fit) = (j, run);
        } else {
            j_over = j;
        }
    }
    let base = lo.wrapping_add((j_fit as u64).wrapping_mul(d as u64));
    let n = lo_n.wrapping_add(j_fit);
    // 2. Within one deceleration above `base` the slope of `S` is at most `n + 1`, so
    // `k = slack >> ceil(log2(n + 1)) <= slack / (n + 1)` keeps `S(base + k) <= ahead`, and takes
    // at least half the slack.
    let slack = ahead.wrapping_sub(run_fit);
    let k = core::cmp::min(slack.wrapping_shr(ceil_log2_plus1(n)), d as u64) as u32;
    let w = base.wrapping_add(k as u64);
    if w >= hi.0 {
        return hi;
    }
    let (mut n, mut r) = (n, lo_r.wrapping_add(k));
    if r > d {
        r = r.wrapping_sub(d);
        n = n.wrapping_add(1);
    }
    (w, n, r)
}

/// A lower bound of `slack / speed` (LSBs over LSBs per tick, `speed <= 2^35` as every profile
/// speed): whole ticks of cruising before the target is near. One 32-bit division, rounding
/// the slack down and the speed up to 1/256 count per tick; a cap at 2^32 - 1 only shortens it.
#[inline(always)]
fn cruise_ticks(slack: u64, speed: u64) -> u32 {
    let num = (slack >> 16).min(u32::MAX as u64) as u32;
    let den = NonZeroU32::MIN.saturating_add((speed >> 16).min(u32::MAX as u64) as u32);
    num / den
}

/// After a braking tick that leaves speed `(n, r)` and `slack` (the run-out to spare, at most
/// one deceleration), the ticks that brake fully (`k = 0`): tick `j` starts from `n - j + 1`
/// terms and brakes from `lo_n = n - j` with the same `r` and slack. It brakes fully while
/// `lo_n >= 1` (its speed less `d` is a speed of the profile) and `slack < lo_n + z`, `z = 1`
/// when `r = d` (no room: `k = slack / (lo_n + 1)`), else 0 (`k = slack / lo_n`). So
/// `n - max(1, slack + 1 - z)`.
#[inline(always)]
fn brake_ticks(n: u32, slack: u32, no_room: bool) -> u32 {
    n.saturating_sub(slack.wrapping_add(1).wrapping_sub(no_room as u32).max(1))
}

/// `ceil(log2(n + 1))`: the shift that divides by at least `n + 1` (0 for `n = 0`).
#[inline(always)]
fn ceil_log2_plus1(n: u32) -> u32 {
    u32::BITS.wrapping_sub(n.leading_zeros())
}

/// One tick of the profile: where the carriage should be at the end of the tick.
///
/// Every `Setpoint` is within the ranges the PID's 32-bit datapath relies on: position within the
/// `i32` count range, |velocity| <= 2048 counts/tick, |acceleration| < 64 counts/tick². The
/// profile stays within them by construction (it never passes its target, so the position stays
/// between the start and the targets); [`Setpoint::new`] saturates anything else.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Setpoint {
    /// LSBs of I40F24 counts, counts/tick and counts/tick² (read through the accessors).
    position: i64,
    velocity: i64,
    acceleration: i64,
    done: bool,
}

impl Setpoint {
    /// A setpoint from arbitrary values, saturated to the ranges above; `done` if not moving.
    pub fn new(
        position_counts: I40F24,
        velocity_counts_per_tick: I40F24,
        acceleration_counts_per_tick2: I40F24,
    ) -> Self {
        let velocity = velocity_counts_per_tick
            .to_bits()
            .clamp(-(MAX_VELOCITY_BITS as i64), MAX_VELOCITY_BITS as i64);
        Self {
            position: position_counts.to_bits().clamp(
                (i32::MIN as i64) << FRAC_BITS,
                ((i32::MAX as i64) << FRAC_BITS) | (ONE_COUNT - 1),
            ),
            velocity,
            acceleration: acceleration_counts_per_tick2
                .to_bits()
                .clamp(-(MAX_ACCEL_BITS as i64), MAX_ACCEL_BITS as i64),
            done: velocity == 0,
        }
    }

    /// A setpoint standing still at `position_counts`.
    pub fn at_rest(position_counts: i32) -> Self {
        Self {
            position: (position_counts as i64) << FRAC_BITS,
            velocity: 0,
            acceleration: 0,
            done: true,
        }
    }

    /// Setpoint position.
    pub fn position_counts(&self) -> I40F24 {
        I40F24::from_bits(self.position)
    }

    /// Whole counts of the position, its floor (within `i32` by the invariant above): the
    /// grid's format stays here, the PID and the drive read counts.
    #[inline]
    pub fn position_floor_counts(&self) -> i32 {
        (self.position >> FRAC_BITS) as i32
    }

    /// The position's fraction of a count in 1/256 (`0..=255`, the top 8 fractional bits).
    #[inline]
    pub fn position_frac_q8(&self) -> i32 {
        ((self.position >> (FRAC_BITS - 8)) & 0xff) as i32
    }

    /// The feed-forward velocity in counts per tick, Q16.16 bits (within ±2^27 by the invariant).
    #[inline]
    pub fn velocity_q16(&self) -> i32 {
        (self.velocity >> (FRAC_BITS - 16)) as i32
    }

    /// The feed-forward acceleration in counts per tick², Q8.24 bits (below 64 counts/tick²).
    #[inline]
    pub fn acceleration_q24(&self) -> i32 {
        (self.acceleration >> (FRAC_BITS - 24)) as i32
    }

    /// Step taken this tick (`position - previous position`): the feed-forward velocity.
    pub fn velocity_counts_per_tick(&self) -> I40F24 {
        I40F24::from_bits(self.velocity)
    }

    /// Velocity change this tick: the feed-forward acceleration.
    pub fn acceleration_counts_per_tick2(&self) -> I40F24 {
        I40F24::from_bits(self.acceleration)
    }

    /// At rest on the target.
    pub fn is_done(&self) -> bool {
        self.done
    }
}

/// [`Trajectory::set_coeffs`] refused: braking from the present speed at the new deceleration
/// would take longer than the profile's arithmetic allows (over 2^31 counts).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CannotBrake;

/// The profile generator: limits plus state.
///
/// Unlike the encoder and the PID, limits and state live together: the state carries a
/// decomposition of the speed in units of the deceleration, rebuilt (one division) whenever the
/// limits change ([`Trajectory::set_coeffs`]), also in mid-move.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Trajectory {
    coeffs: Coeffs,
    /// LSBs of counts.
    position: i64,
    target: i64,
    /// LSBs of counts/tick, signed.
    velocity: i64,
    /// `|velocity| = (n - 1) * decel + r`, `0 < r <= decel`; at rest `n = 0, r = decel`.
    n: u32,
    r: u32,
    /// Ticks whose step is known without looking at the target (0 after any change):
    /// accelerating or cruising far from it, or braking by exactly `decel` towards it. Each adds
    /// `shortcut_dv` to the velocity and takes `shortcut_dn` from `n` (see [`Trajectory::tick`]).
    /// While accelerating (the count with `shortcut_dn` 0 and a velocity step), `(n, r)`
    /// already hold the decomposition of the count's last speed: [`Trajectory::sync`] recovers
    /// the present one when a command cuts the count short.
    shortcut_ticks: u32,
    shortcut_dn: u32,
    shortcut_dv: i64,
}

impl Trajectory {
    /// At rest on `position_counts`.
    pub fn new(coeffs: Coeffs, position_counts: i32) -> Self {
        let position = (position_counts as i64) << FRAC_BITS;
        Self {
            coeffs,
            position,
            target: position,
            velocity: 0,
            n: 0,
            r: coeffs.decel,
            shortcut_ticks: 0,
            shortcut_dn: 0,
            shortcut_dv: 0,
        }
    }

    /// Jumps to rest on `position_counts` (e.g. the measured position when re-enabling the
    /// drive), dropping the target. Not inlined: called from many commands, and on the tick
    /// only when a fault stops the drive (flash size).
    #[inline(never)]
    pub fn reset(&mut self, position_counts: i32) {
        *self = Self::new(self.coeffs, position_counts);
    }

    /// Moves to `target_counts`, starting from the current state: a target behind the carriage (or
    /// too close to stop for) is reached by braking to rest and coming back.
    pub fn set_target(&mut self, target_counts: i32) {
        self.target = (target_counts as i64) << FRAC_BITS;
        self.sync();
    }

    /// Decelerates to rest at the deceleration limit; the stopping point (generally between two
    /// counts) becomes the target.
    pub fn stop(&mut self) {
        self.sync();
        // Distance of full braking after this tick: S(speed - d).
        let run_out = run_out_bits(self.coeffs.decel, self.n.saturating_sub(1), self.r) as i64;
        self.target = if self.velocity >= 0 {
            self.position.wrapping_add(run_out)
        } else {
            self.position.wrapping_sub(run_out)
        };
    }

    /// Where the profile would come to rest braking from now at the deceleration limit, whole
    /// counts (the present position at rest).
    pub fn stopping_point_counts(&self) -> i32 {
        let mut now = *self;
        now.sync();
        let run_out = run_out_bits(now.coeffs.decel, now.n.saturating_sub(1), now.r) as i64;
        let stop = if self.velocity >= 0 {
            self.position.wrapping_add(run_out)
        } else {
            self.position.wrapping_sub(run_out)
        };
        (stop >> FRAC_BITS).clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    /// Replaces the limits, at rest or in mid-move (a feed override, a blended retarget).
    /// Position and velocity carry over unchanged, so the set-point never steps; a speed above
    /// the new velocity limit is braked down to it at the new deceleration. One division: call
    /// it when a command arrives, not every tick.
    pub fn set_coeffs(&mut self, coeffs: Coeffs) -> Result<(), CannotBrake> {
        let speed = self.velocity.unsigned_abs();
        // `Coeffs` hold a deceleration of one LSB at least; `max(1)` lets the compiler see it
        // (no division-by-zero panic path below).
        let d = (coeffs.decel as u64).max(1);
        let (n, r) = if speed == 0 {
            (0, coeffs.decel)
        } else {
            // speed = (n - 1) d + r, 0 < r <= d.
            let n = div_ceil_u64(speed, d as u32);
            let run_out = n as u128 * (n as u128 - 1) / 2 * d as u128 + n as u128 * d as u128;
            if run_out > MAX_RUN_OUT_BITS {
                return Err(CannotBrake);
            }
            (n as u32, (speed - (n - 1) * d) as u32)
        };
        self.coeffs = coeffs;
        self.n = n;
        self.r = r;
        self.shortcut_ticks = 0;
        Ok(())
    }

    /// The limits in use.
    pub fn coeffs(&self) -> &Coeffs {
        &self.coeffs
    }

    /// Setpoint position after the last tick.
    pub fn position_counts(&self) -> I40F24 {
        I40F24::from_bits(self.position)
    }

    /// Whole counts of the position after the last tick (its floor, saturated to `i32`).
    #[inline]
    pub fn position_floor_counts(&self) -> i32 {
        (self.position >> FRAC_BITS).clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    /// Velocity of the last tick.
    pub fn velocity_counts_per_tick(&self) -> I40F24 {
        I40F24::from_bits(self.velocity)
    }

    /// Where the profile is going: a whole count, or the stopping point after [`stop`](Self::stop).
    pub fn target_counts(&self) -> I40F24 {
        I40F24::from_bits(self.target)
    }

    /// At rest on the target.
    pub fn is_done(&self) -> bool {
        self.velocity == 0 && self.position == self.target
    }

    /// The fastest admissible speed after `speed`: one acceleration faster, capped at the
    /// velocity limit; with its decomposition. Above the limit (after the limits were lowered in
    /// mid-move) it brakes towards the limit, by at most one deceleration per tick.
    #[inline(always)]
    fn faster(&self, speed: u64) -> (u64, u32, u32) {
        let c = &self.coeffs;
        if speed > c.velocity {
            let d = c.decel as u64;
            return if speed.wrapping_sub(c.velocity) > d {
                // n >= 2 here: speed > d.
                (speed.wrapping_sub(d), self.n.wrapping_sub(1), self.r)
            } else {
                (c.velocity, c.velocity_n, c.velocity_r)
            };
        }
        let up = speed.wrapping_add(c.accel as u64);
        if up >= c.velocity {
            (c.velocity, c.velocity_n, c.velocity_r)
        } else {
            let mut n = self.n.wrapping_add(c.accel_decels);
            let mut r = self.r.wrapping_add(c.accel_rem);
            if r > c.decel {
                r = r.wrapping_sub(c.decel);
                n = n.wrapping_add(1);
            }
            (up, n, r)
        }
    }

    /// The step when the target is within the run-out from the velocity limit.
    ///
    /// One run-out is computed, `S(lo)` for the slowest admissible speed `lo = speed - d`; holding
    /// the speed then needs `S(speed) = S(lo) + speed` (one more step before the same braking),
    /// so a braking tick costs one run-out and a shift.
    ///
    /// The fourth value counts the ticks after this one that brake by exactly `d` (0: none
    /// known): see [`brake_ticks`].
    #[inline(always)]
    fn near(&self, speed: u64, within_limit: bool, ahead: i64) -> (u64, u32, u32, u32) {
        let d = self.coeffs.decel;
        let (lo, lo_n, lo_r) = if self.n >= 2 {
            (speed.wrapping_sub(d as u64), self.n.wrapping_sub(1), self.r)
        } else {
            (0, 0, d)
        };
        let lo_run_out = run_out_bits(d, lo_n, lo_r);
        if ahead < lo_run_out as i64 {
            // Cannot stop at the target: brake fully, come back from rest.
            return (lo, lo_n, lo_r, 0);
        }
        let slack = (ahead as u64).wrapping_sub(lo_run_out);
        if slack < speed {
            // Must slow down, by less than `d`: the largest `k` with `S(lo + k) <= ahead`. Up
            // to `room = d - lo_r` each unit of `k` adds `lo_n` to `S` (the same terms, each
            // faster); past it the speed gains a term and `S(lo + k) = S(lo) + (lo_n + 1) k -
            // room`. So `k = slack / lo_n` short of the room, else `(slack + room) / (lo_n + 1)`;
            // `k < d` as `slack < speed = lo_n d + lo_r`. One hardware division while the slack
            // and the room fit 32 bits together (speeds up to about 256 counts/tick); past that
            // `k = slack >> ceil(log2(lo_n + 1))`, at least half of it (the slope of `S` is at
            // most `lo_n + 1`), and the next tick takes up the rest.
            let room = d.wrapping_sub(lo_r);
            let (k, rest) = if slack.wrapping_add(room as u64) >> 32 == 0 {
                let slack = slack as u32;
                let k = if lo_n as u64 * room as u64 <= slack as u64 {
                    slack.wrapping_add(room) / NonZeroU32::MIN.saturating_add(lo_n)
                } else {
                    // `lo_n > 0` here (`lo_n room > slack >= 0`).
                    slack / NonZeroU32::new(lo_n).unwrap_or(NonZeroU32::MIN)
                };
                // What `S` gains, at most the slack: what is left stays for the ticks after.
                let gained = lo_n
                    .wrapping_mul(k)
                    .wrapping_add(lo_r.wrapping_add(k).saturating_sub(d));
                (k, slack.wrapping_sub(gained))
            } else {
                (slack.wrapping_shr(ceil_log2_plus1(lo_n)) as u32, u32::MAX)
            };
            let (mut n, mut r) = (lo_n, lo_r.wrapping_add(k));
            if r > d {
                r = r.wrapping_sub(d);
                n = n.wrapping_add(1);
            }
            // The ticks after this one that brake fully, keeping the slack left as it is
            // (`S(w) = w + S(w - d)`): see [`brake_ticks`]. With the slack within one
            // deceleration and the speed within the limit, their speeds stay above it.
            let brake = if rest <= d && within_limit {
                brake_ticks(n, rest, r == d)
            } else {
                0
            };
            return (lo.wrapping_add(k as u64), n, r, brake);
        }
        // Holding the speed fits; accelerating may not.
        let hi = self.faster(speed);
        if run_out_bits(d, hi.1, hi.2) <= ahead as u64 {
            return (hi.0, hi.1, hi.2, 0);
        }
        // From rest `(n, r)` is `(0, d)`, the decomposition of zero.
        let held = (speed, self.n, self.r);
        let (w, n, r) = fit(d, held, lo_run_out.wrapping_add(speed), hi, ahead as u64);
        (w, n, r, 0)
    }

    /// A far tick below the velocity limit that reaches speed `next = (w, n, r)`: counts the
    /// ticks after it that accelerate by exactly `accel` (`w + k accel < vmax`, and at most
    /// `far`), and returns the decomposition of the count's last speed `w + k accel` in place
    /// of `(n, r)` (`r` gains `k accel_rem` and wraps into `n`). `k` is capped so that the sum
    /// fits 32 bits: one hardware division finds the wraps.
    #[inline(always)]
    fn accelerate(&mut self, next: (u64, u32, u32), far: u64, backwards: bool) -> (u64, u32, u32) {
        let c = &self.coeffs;
        let (w, n, r) = next;
        let below = c.velocity.wrapping_sub(1).wrapping_sub(w);
        let mut k = cruise_ticks(far, c.velocity).min(cruise_ticks(below, c.accel as u64));
        if c.accel_rem != 0 {
            // `r - 1 < 2^31` (decel <= 2^30) and `k accel_rem < 2^31`.
            let cap = (1u32 << 31) >> (u32::BITS - c.accel_rem.leading_zeros());
            k = k.min(cap.wrapping_sub(1));
        }
        self.shortcut_ticks = k;
        self.shortcut_dv = if backwards {
            (c.accel as i64).wrapping_neg()
        } else {
            c.accel as i64
        };
        let d = NonZeroU32::new(c.decel).unwrap_or(NonZeroU32::MIN);
        let t = r.wrapping_sub(1).wrapping_add(k.wrapping_mul(c.accel_rem));
        let wraps = t / d;
        let n_end = n
            .wrapping_add(k.wrapping_mul(c.accel_decels))
            .wrapping_add(wraps);
        let r_end = t.wrapping_sub(wraps.wrapping_mul(d.get())).wrapping_add(1);
        (w, n_end, r_end)
    }

    /// Makes `(n, r)` describe the present speed again when a command cuts a count short: only
    /// an acceleration count keeps them ahead (by a division, outside the tick).
    fn sync(&mut self) {
        // An acceleration count: no step of `n` (braking takes 1), a step of velocity (cruising
        // has none).
        if self.shortcut_ticks != 0 && self.shortcut_dn == 0 && self.shortcut_dv != 0 {
            let speed = self.velocity.unsigned_abs();
            let n = div_ceil_u64(speed, self.coeffs.decel);
            self.n = n as u32;
            self.r = (speed - (n - 1) * self.coeffs.decel as u64) as u32;
        }
        self.shortcut_ticks = 0;
    }

    /// Advances one tick. Bounded integer arithmetic (a few 32-bit divisions on the ticks that
    /// start a count or take up slack). Always inlined: the control tick is its one caller on
    /// the drive (17 instructions per tick fewer, measured; out of line, the full step alone
    /// costs 7 more on the mean).
    #[inline(always)]
    pub fn tick(&mut self) -> Setpoint {
        if self.shortcut_ticks != 0 {
            // A step counted when it began (acceleration, cruise or full braking): the full
            // step below would take the same, and the velocity stays away from zero.
            self.shortcut_ticks = self.shortcut_ticks.wrapping_sub(1);
            self.n = self.n.wrapping_sub(self.shortcut_dn);
            self.velocity = self.velocity.wrapping_add(self.shortcut_dv);
            self.position = self.position.wrapping_add(self.velocity);
            return Setpoint {
                position: self.position,
                velocity: self.velocity,
                acceleration: self.shortcut_dv,
                done: false,
            };
        }
        let to_go = self.target.wrapping_sub(self.position);
        let v = self.velocity;
        if v == 0 && to_go == 0 {
            return self.setpoint(0);
        }
        // Work along the direction of travel (or of the target, from rest); `ahead` is negative
        // if the target is behind.
        let backwards = if v != 0 { v < 0 } else { to_go < 0 };
        let ahead = if backwards {
            to_go.wrapping_neg()
        } else {
            to_go
        };
        let speed = v.unsigned_abs();
        let within_limit = speed <= self.coeffs.velocity;
        let (w, n, r) = if within_limit && ahead >= self.coeffs.velocity_run_out as i64 {
            // Far away: no speed up to the limit can need braking yet.
            let next = self.faster(speed);
            // The next `k` ticks are far too while they cover at most `ahead - S(vmax)`: at
            // most `vmax` each.
            let far = (ahead as u64).wrapping_sub(self.coeffs.velocity_run_out);
            self.shortcut_dn = 0;
            if next.0 == self.coeffs.velocity {
                // At the limit: cruising.
                self.shortcut_ticks = cruise_ticks(far, next.0);
                self.shortcut_dv = 0;
                next
            } else {
                self.accelerate(next, far, backwards)
            }
        } else {
            let (w, n, r, brake) = self.near(speed, within_limit, ahead);
            if brake != 0 {
                let d = self.coeffs.decel as i64;
                self.shortcut_ticks = brake;
                self.shortcut_dn = 1;
                self.shortcut_dv = if backwards { d } else { d.wrapping_neg() };
            }
            (w, n, r)
        };
        let velocity = if backwards {
            (w as i64).wrapping_neg()
        } else {
            w as i64
        };
        self.position = self.position.wrapping_add(velocity);
        self.velocity = velocity;
        self.n = n;
        self.r = r;
        self.setpoint(velocity.wrapping_sub(v))
    }

    #[inline(always)]
    fn setpoint(&self, acceleration: i64) -> Setpoint {
        Setpoint {
            position: self.position,
            velocity: self.velocity,
            acceleration,
            done: self.is_done(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn long_division_rounds_up_like_div_ceil(n: u64, d in 1u32..=(1 << 31)) {
            prop_assert_eq!(div_ceil_u64(n, d), n.div_ceil(d as u64));
        }
    }

    #[test]
    fn long_division_at_the_edges() {
        for (n, d) in [
            (0, 1),
            (u64::MAX, 1),
            (u64::MAX, 1 << 31),
            (1 << 35, 3),
            (5, 5),
            (6, 5),
        ] {
            assert_eq!(div_ceil_u64(n, d), n.div_ceil(d as u64), "{n} / {d}");
        }
    }

    fn bits(x: I40F24) -> i64 {
        x.to_bits()
    }

    /// Runs to rest on the target, checking the limits every tick; returns (ticks, peak speed).
    fn run(t: &mut Trajectory, max_ticks: u64) -> (u64, i64) {
        let c = *t.coeffs();
        let (vmax, a, d) = (c.velocity as i64, c.accel as i64, c.decel as i64);
        let mut prev = t.tick();
        let mut peak = 0;
        let mut ticks = 1;
        while !prev.is_done() {
            let s = t.tick();
            let (v0, v1) = (
                bits(prev.velocity_counts_per_tick()),
                bits(s.velocity_counts_per_tick()),
            );
            assert!(v1.abs() <= vmax);
            assert_eq!(bits(s.position_counts()) - bits(prev.position_counts()), v1);
            assert_eq!(bits(s.acceleration_counts_per_tick2()), v1 - v0);
            assert!(v0.signum() * v1.signum() >= 0, "sign flip without rest");
            if v1.abs() > v0.abs() {
                assert!(v1.abs() - v0.abs() <= a);
            } else {
                assert!(v0.abs() - v1.abs() <= d);
            }
            peak = peak.max(v1.abs());
            prev = s;
            ticks += 1;
            assert!(ticks <= max_ticks, "no arrival within {max_ticks} ticks");
        }
        assert_eq!(bits(prev.position_counts()), t.target);
        assert_eq!(prev.velocity_counts_per_tick(), 0);
        (ticks, peak)
    }

    fn coeffs(v: f64, a: f64, d: f64) -> Coeffs {
        Coeffs::new(
            I40F24::from_num(v),
            I40F24::from_num(a),
            I40F24::from_num(d),
        )
        .unwrap()
    }

    #[test]
    fn paper_rig_defaults() {
        let c = Config::PAPER_RIG.build(&BuildContext::PAPER).unwrap();
        assert_eq!(c, Coeffs::default());
        // 100 mm/s at 2 kHz: 93.39 counts/tick; 2000 mm/s²: 0.934 counts/tick².
        let v: f64 = c.velocity_counts_per_tick().to_num();
        assert!((v - 93.39449).abs() < 1e-5, "{v}");
        let a: f64 = c.acceleration_counts_per_tick2().to_num();
        assert!((a - 0.933945).abs() < 1e-6, "{a}");
        assert!(
            c.velocity_counts_per_tick()
                <= I40F24::from_num(100.0 * Rig::PAPER.counts_per_mm() / 2000.0)
        );
    }

    #[test]
    fn config_errors_name_the_field() {
        let rig = BuildContext::PAPER;
        let ok = Config::PAPER_RIG;
        let field = |c: Config| c.build(&rig).unwrap_err().field();
        assert_eq!(
            field(Config {
                velocity_mm_s: f64::NAN,
                ..ok
            }),
            ConfigField::TrajectoryVelocityMmS
        );
        assert_eq!(
            field(Config {
                velocity_mm_s: 0.0,
                ..ok
            }),
            ConfigField::TrajectoryVelocityMmS
        );
        assert_eq!(
            field(Config {
                velocity_mm_s: -5.0,
                ..ok
            }),
            ConfigField::TrajectoryVelocityMmS
        );
        assert_eq!(
            field(Config {
                velocity_mm_s: 1e9,
                ..ok
            }),
            ConfigField::TrajectoryVelocityMmS
        );
        assert_eq!(
            field(Config {
                acceleration_mm_s2: f64::INFINITY,
                ..ok
            }),
            ConfigField::TrajectoryAccelerationMmS2
        );
        assert_eq!(
            field(Config {
                acceleration_mm_s2: 0.0,
                ..ok
            }),
            ConfigField::TrajectoryAccelerationMmS2
        );
        assert_eq!(
            field(Config {
                acceleration_mm_s2: 1e12,
                ..ok
            }),
            ConfigField::TrajectoryAccelerationMmS2
        );
        assert_eq!(
            field(Config {
                deceleration_mm_s2: -1.0,
                ..ok
            }),
            ConfigField::TrajectoryDecelerationMmS2
        );
        // Stopping from 100 mm/s at 1e-6 mm/s² would take far more than 2^31 counts.
        assert_eq!(
            field(Config {
                deceleration_mm_s2: 1e-6,
                ..ok
            }),
            ConfigField::TrajectoryDecelerationMmS2
        );
        assert!(Coeffs::new(I40F24::ZERO, I40F24::ONE, I40F24::ONE).is_err());
        assert!(Coeffs::new(I40F24::ONE, I40F24::from_num(64), I40F24::ONE).is_err());
        assert!(Coeffs::new(I40F24::from_num(2049), I40F24::ONE, I40F24::ONE).is_err());
    }

    #[test]
    fn zero_length_move_is_done_at_once() {
        let mut t = Trajectory::new(Coeffs::default(), 42);
        assert!(t.is_done());
        t.set_target(42);
        let s = t.tick();
        assert!(s.is_done());
        assert_eq!(s.position_counts(), 42);
        assert_eq!(s.velocity_counts_per_tick(), 0);
        assert_eq!(s.acceleration_counts_per_tick2(), 0);
    }

    #[test]
    fn trapezoid_reaches_cruise_and_lands_exactly() {
        let c = coeffs(10.0, 0.5, 0.25);
        let mut t = Trajectory::new(c, -1000);
        t.set_target(1000);
        let (ticks, peak) = run(&mut t, 10_000);
        assert_eq!(peak, c.velocity as i64);
        // Continuous optimum: 2000/10 + 10/2 (1/0.5 + 1/0.25) = 230 ticks.
        assert!((230..=233).contains(&ticks), "{ticks}");
        assert_eq!(t.position_counts(), 1000);
    }

    #[test]
    fn short_move_is_triangular() {
        let c = coeffs(10.0, 0.5, 0.5);
        let mut t = Trajectory::new(c, 0);
        t.set_target(-50);
        let (ticks, peak) = run(&mut t, 1000);
        // Peak of a symmetric triangle: sqrt(a L) = 5 counts/tick, 20 ticks.
        let peak = peak as f64 / ONE_COUNT as f64;
        assert!(peak < 10.0 && (peak - 5.0).abs() < 0.6, "{peak}");
        assert!((20..=23).contains(&ticks), "{ticks}");
    }

    #[test]
    fn one_count_move_with_tiny_velocity() {
        let c = coeffs(0.001, 1e-5, 1e-5);
        let mut t = Trajectory::new(c, 7);
        t.set_target(8);
        let (ticks, _) = run(&mut t, 2000);
        assert!(ticks >= 1000, "{ticks}");
        assert_eq!(t.position_counts(), 8);
    }

    #[test]
    fn reversal_mid_move_is_continuous() {
        let c = Coeffs::default();
        let mut t = Trajectory::new(c, 0);
        t.set_target(200_000);
        for _ in 0..500 {
            t.tick();
        }
        let v = t.velocity_counts_per_tick();
        assert!(v > 0);
        t.set_target(-100);
        let s = t.tick();
        assert_eq!(
            bits(s.acceleration_counts_per_tick2()),
            -(c.decel as i64),
            "full braking, one deceleration"
        );
        run(&mut t, 100_000);
        assert_eq!(t.position_counts(), -100);
    }

    #[test]
    fn stop_decelerates_at_the_limit() {
        let c = Coeffs::default();
        let mut t = Trajectory::new(c, 0);
        t.set_target(-1_000_000);
        for _ in 0..1000 {
            t.tick();
        }
        let p0 = t.position_counts();
        let v0: f64 = -t.velocity_counts_per_tick().to_num::<f64>();
        assert!(v0 > 90.0, "cruising backwards");
        t.stop();
        let (ticks, _) = run(&mut t, 100_000);
        let d: f64 = c.deceleration_counts_per_tick2().to_num();
        let brake = v0 * v0 / (2.0 * d);
        let travelled: f64 = (p0 - t.position_counts()).to_num();
        // Discrete braking covers v0²/2d - v0/2.
        assert!(
            (travelled - (brake - v0 / 2.0)).abs() <= 0.01,
            "{travelled} vs {brake}"
        );
        assert!((ticks as f64 - v0 / d).abs() <= 1.0, "{ticks}");
        // Stopping at rest stays put.
        t.stop();
        assert!(t.tick().is_done());
    }

    #[test]
    fn huge_move_end_to_end() {
        let c = coeffs(2000.0, 40.0, 50.0);
        let mut t = Trajectory::new(c, i32::MIN);
        t.set_target(i32::MAX);
        let (ticks, _) = run(&mut t, 2_200_000);
        assert!(ticks > 2 * (i32::MAX as u64) / 2000);
        assert_eq!(t.position_counts(), i32::MAX);
        t.set_target(i32::MIN);
        run(&mut t, 2_200_000);
        assert_eq!(t.position_counts(), i32::MIN);
    }

    /// New limits in mid-move (faster, slower, with a target behind): position and velocity
    /// continue without a step, each tick changes the speed by at most the larger of the old and
    /// new acceleration limits, a speed above the new limit only falls, and the profile lands
    /// exactly on the new target.
    #[test]
    fn limits_change_in_mid_move_without_a_step() {
        let slow = coeffs(20.0, 0.5, 0.5);
        let fast = coeffs(60.0, 2.0, 1.5);
        let cases = [
            (slow, fast, 200, 60_000i32),
            (fast, slow, 200, 60_000),
            (fast, slow, 200, -20_000),
            (slow, fast, 100, -5_000),
            (fast, coeffs(10.0, 0.2, 0.1), 150, 40_000),
            (fast, slow, 60, 100),
        ];
        for (k, &(c0, c1, at, target)) in cases.iter().enumerate() {
            let mut t = Trajectory::new(c0, 0);
            t.set_target(50_000);
            let mut prev = t.tick();
            for _ in 1..at {
                prev = t.tick();
            }
            t.set_coeffs(c1).unwrap();
            t.set_target(target);
            let dv_max = [c0.accel, c0.decel, c1.accel, c1.decel]
                .into_iter()
                .max()
                .unwrap() as i64;
            let vmax = c1.velocity as i64;
            let mut over = bits(prev.velocity_counts_per_tick()).abs() > vmax;
            for tick in 0..2_000_000 {
                let s = t.tick();
                let (v0, v1) = (
                    bits(prev.velocity_counts_per_tick()),
                    bits(s.velocity_counts_per_tick()),
                );
                assert_eq!(
                    bits(s.position_counts()) - bits(prev.position_counts()),
                    v1,
                    "case {k} tick {tick}"
                );
                assert!(
                    (v1 - v0).abs() <= dv_max,
                    "case {k} tick {tick}: {v0} -> {v1}"
                );
                assert!(
                    v0.signum() * v1.signum() >= 0,
                    "case {k}: sign flip without rest"
                );
                if over {
                    assert!(
                        v1.abs() <= v0.abs(),
                        "case {k} tick {tick}: speeds up above the limit"
                    );
                    over = v1.abs() > vmax;
                } else {
                    assert!(v1.abs() <= vmax, "case {k} tick {tick}");
                }
                prev = s;
                if s.is_done() {
                    break;
                }
            }
            assert!(prev.is_done(), "case {k} never arrived");
            assert_eq!(t.position_counts(), target, "case {k}");
        }
    }

    /// What the profile does to the trajectory between ticks in [`the_counted_steps_are_exact`].
    #[derive(Clone, Copy, Debug)]
    enum Op {
        Tick(u16),
        Target(i32),
        Stop,
        Coeffs(u32, u32, u32),
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            4 => (1u16..3000).prop_map(Op::Tick),
            2 => (-2_000_000i32..2_000_000).prop_map(Op::Target),
            1 => Just(Op::Stop),
            1 => (1u32..1 << 29, 1u32..1 << 26, 1u32..1 << 26)
                .prop_map(|(v, a, d)| Op::Coeffs(v, a, d)),
        ]
    }

    proptest! {
        /// Ticks taken through the cruise and braking counts give the set-points and the state
        /// (`n`, `r`) of the full step, bit for bit, through retargets, stops and new limits in
        /// mid-move.
        #[test]
        fn the_counted_steps_are_exact(
            (v, a, d) in (1u32..1 << 29, 1u32..1 << 26, 1u32..1 << 26),
            ops in prop::collection::vec(op(), 1..12),
        ) {
            let c = |v: u32, a: u32, d: u32| Coeffs::new(
                I40F24::from_bits(v as i64 * 64),
                I40F24::from_bits(a as i64),
                I40F24::from_bits(d as i64),
            );
            let Ok(c0) = c(v, a, d) else { return Ok(()) };
            let mut fast = Trajectory::new(c0, 0);
            let mut full = fast;
            for op in ops {
                match op {
                    Op::Tick(n) => {
                        for _ in 0..n {
                            // The full step from the present state, as after a command.
                            full.sync();
                            prop_assert_eq!(fast.tick(), full.tick());
                        }
                    }
                    Op::Target(t) => {
                        fast.set_target(t);
                        full.set_target(t);
                    }
                    Op::Stop => {
                        fast.stop();
                        full.stop();
                    }
                    Op::Coeffs(v, a, d) => {
                        if let Ok(c1) = c(v, a, d) {
                            prop_assert_eq!(fast.set_coeffs(c1), full.set_coeffs(c1));
                        }
                    }
                }
                prop_assert_eq!(fast.position, full.position);
                prop_assert_eq!(fast.velocity, full.velocity);
                // Mid-count an acceleration holds its last speed's decomposition: the present
                // one is what a command would see.
                let (mut now, mut full_now) = (fast, full);
                now.sync();
                full_now.sync();
                prop_assert_eq!((now.n, now.r), (full_now.n, full_now.r));
                prop_assert_eq!(fast.stopping_point_counts(), full.stopping_point_counts());
            }
        }
    }

    /// A long cruise is mostly shortcut ticks, and lands exactly.
    #[test]
    fn a_long_cruise_takes_the_shortcut() {
        let mut t = Trajectory::new(coeffs(20.0, 0.5, 0.5), 0);
        t.set_target(200_000);
        let mut shortcuts = 0;
        let mut ticks = 0;
        while ticks < 20_000 {
            let took = t.shortcut_ticks != 0;
            if t.tick().is_done() {
                break;
            }
            shortcuts += took as u32;
            ticks += 1;
        }
        assert_eq!(t.position_counts(), 200_000);
        // 10,000 ticks at 20 counts/tick, 40 ramping each way (braking is shortcut too).
        assert!(shortcuts > 9_000, "{shortcuts} of {ticks}");
    }

    /// The bench's second move (150 mm/s, 3000 mm/s^2 on the paper rig at 2 kHz, 40 mm) from
    /// rest: the profile and its target.
    fn bench_move() -> (Trajectory, i32) {
        let per_mm = Rig::PAPER.counts_per_mm();
        let (v, a) = (150.0 * per_mm / 2000.0, 3000.0 * per_mm / 4e6);
        let mut t = Trajectory::new(coeffs(v, a, a), 0);
        let target = (40.0 * per_mm) as i32;
        t.set_target(target);
        (t, target)
    }

    /// Braking to the target is mostly shortcut ticks (the bench's
    /// second move: 150 mm/s, 3000 mm/s^2 on the paper rig at 2 kHz, 40 mm).
    #[test]
    fn braking_takes_the_shortcut() {
        let (mut t, target) = bench_move();
        let (mut braking, mut shortcuts) = (0, 0);
        let mut prev = t.tick();
        for _ in 0..10_000 {
            if prev.is_done() {
                break;
            }
            let took = t.shortcut_ticks != 0;
            let s = t.tick();
            if s.acceleration_counts_per_tick2() < 0 {
                braking += 1;
                shortcuts += took as u32;
            }
            prev = s;
        }
        assert_eq!(t.position_counts(), target);
        assert!(braking >= 95, "{braking}");
        // 96 of 102: the tick that takes up the slack left by the cruise (one division; the
        // count starts on it), and the few at the end that take up what is left as `n` falls
        // to the slack. (With a shift in place of the division: 79.)
        assert!(braking - shortcuts <= 8, "{shortcuts} of {braking}");
    }

    /// Accelerating far from the target is counted too (the same move): the tick that starts
    /// the count works out where it ends; a command in mid-count (see
    /// [`the_counted_steps_are_exact`]) recovers the present decomposition.
    #[test]
    fn acceleration_takes_the_shortcut() {
        let (mut t, _) = bench_move();
        let (mut accelerating, mut shortcuts) = (0, 0);
        for _ in 0..10_000 {
            let took = t.shortcut_ticks != 0;
            let s = t.tick();
            if s.acceleration_counts_per_tick2() <= 0 {
                break;
            }
            accelerating += 1;
            shortcuts += took as u32;
        }
        assert!(accelerating >= 95, "{accelerating}");
        // The first tick counts the rest; the count stops short of the limit by the rounding
        // of its bound, and the last tick or two are full steps.
        assert!(
            accelerating - shortcuts <= 4,
            "{shortcuts} of {accelerating}"
        );
    }

    #[test]
    fn coeffs_change_at_rest() {
        let mut t = Trajectory::new(Coeffs::default(), 0);
        t.set_target(10_000);
        run(&mut t, 100_000);
        let fast = coeffs(200.0, 1.0, 1.0);
        assert_eq!(t.set_coeffs(fast), Ok(()));
        t.set_target(0);
        // 10000 counts at 1 count/tick² never reaches 200 counts/tick: a 2 x 100 tick triangle.
        let (ticks, peak) = run(&mut t, 1000);
        assert!((200..=203).contains(&ticks), "{ticks}");
        assert!(peak <= 100 * ONE_COUNT);
    }
}
