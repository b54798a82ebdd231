//! The fault catalogue: what latches the drive into its safe state (zero current, amplifier
//! disabled), each detector with a threshold in SI units.
//!
//! The detectors follow what trusted drives check (ODrive, moteus, VESC, LinuxCNC, Klipper; see
//! `shared/ANCHORS.md`): following error scaled by speed (LinuxCNC `MIN_FERROR`/`FERROR`),
//! effort without response (stall or a lost encoder), motion against the effort (wires reversed,
//! ODrive's spinout), overspeed, the amplifier held at its limit, a silent link and late ticks.
//!
//! [`Monitor`] is per-tick integer code like the rest of the core: `Config -> build() ->
//! Coeffs`, state in [`State`]. It sees the motor position measured this tick and the current
//! commanded on the previous tick (the current that produced this tick's motion).

pub use belt_link::Faults;

use crate::ConfigField;
use fixed::types::I16F16;

use crate::{BuildContext, ConfigError};

/// Detector thresholds in SI units. A time of zero switches its detector off.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Config {
    /// Following-error limit at rest, mm (LinuxCNC `MIN_FERROR`).
    pub following_error_at_rest_mm: f64,
    /// Following-error limit at the configured maximum velocity, mm (LinuxCNC `FERROR`); the
    /// limit grows linearly with the set-point speed in between.
    pub following_error_at_max_velocity_mm: f64,
    /// Stall: current magnitude at or above this, amperes...
    pub stall_current_a: f64,
    /// ... while the motor moves less than this, mm ...
    pub stall_motion_mm: f64,
    /// ... for this long, seconds.
    pub stall_time_s: f64,
    /// Runaway: current magnitude at or above this, amperes...
    pub runaway_current_a: f64,
    /// ... while the motor moves against it at or above this speed, not decelerating, mm/s ...
    pub runaway_speed_mm_s: f64,
    /// ... for this long, seconds.
    pub runaway_time_s: f64,
    /// Overspeed: measured speed above this multiple of the configured maximum velocity ...
    pub overspeed_ratio: f64,
    /// ... for this long, seconds.
    pub overspeed_time_s: f64,
    /// The current command at the drive's limit for this long (net of unsaturated ticks),
    /// seconds.
    pub saturation_time_s: f64,
    /// No valid frame from the host for this long while enabled, seconds; 0 = no link watchdog
    /// (a host keeps it alive with any frame, e.g. a status request every 100 ms).
    pub link_timeout_s: f64,
}

impl Config {
    /// Thresholds for the paper's rig, with margins over what every scenario preset of
    /// `hil-sim` needs (`hil-sim faults` counts false trips on them; the presets lag by at most
    /// 0.05 mm and draw at most 5.5 A):
    /// - following error 1 mm at rest to 3 mm at 250 mm/s: twenty times the worst lag, so that
    ///   the detectors below, which name the cause, speak first (measured by `hil-sim faults`:
    ///   at 0.5-1.5 mm the following error pre-empts stall, runaway and saturation);
    /// - stall: 2 A beyond the acceleration feed-forward with less than 20 µm of motion for
    ///   15 ms (2 A accelerates the free stage, 67 kg with the rotor reflected, by about 300 µm
    ///   in that time; the feed-forward of a few-um move is not stall effort);
    /// - runaway: 1.5 A against a motion of ≥ 5 mm/s that is not slowing, for 15 ms;
    /// - overspeed: 1.2 × the maximum velocity (ODrive's margin) for 2 ms;
    /// - saturation: 30 ms at the 8 A limit;
    /// - link: 0.5 s of silence (Klipper's figure).
    pub const PAPER_RIG: Config = Config {
        following_error_at_rest_mm: 1.0,
        following_error_at_max_velocity_mm: 3.0,
        stall_current_a: 2.0,
        stall_motion_mm: 0.02,
        stall_time_s: 0.015,
        runaway_current_a: 1.5,
        runaway_speed_mm_s: 5.0,
        runaway_time_s: 0.015,
        overspeed_ratio: 1.2,
        overspeed_time_s: 0.002,
        saturation_time_s: 0.03,
        link_timeout_s: 0.5,
    };

    /// Converts the thresholds into per-tick integers for a drive whose maximum velocity is
    /// `max_velocity_mm_s`, ticking at `rate_hz`.
    pub fn build(&self, ctx: &BuildContext, max_velocity_mm_s: f64) -> Result<Coeffs, ConfigError> {
        use ConfigError as E;
        let (rig, rate_hz) = (ctx.rig(), ctx.rate_hz());
        let cpm = rig.counts_per_mm();
        let fin = |v: f64, f: ConfigField| {
            if v.is_finite() {
                Ok(v)
            } else {
                Err(E::NotFinite(f))
            }
        };
        let rest = fin(
            self.following_error_at_rest_mm,
            ConfigField::FaultsFollowingErrorAtRestMm,
        )?;
        let at_max = fin(
            self.following_error_at_max_velocity_mm,
            ConfigField::FaultsFollowingErrorAtMaxVelocityMm,
        )?;
        if !(rest > 0.0 && rest * cpm <= 1e9) {
            return Err(E::OutOfRange(ConfigField::FaultsFollowingErrorAtRestMm));
        }
        if !(at_max >= rest && at_max * cpm <= 1e9) {
            return Err(E::OutOfRange(
                ConfigField::FaultsFollowingErrorAtMaxVelocityMm,
            ));
        }
        // Extra counts of allowed error per count/tick of set-point speed, Q16.
        let vmax_counts_per_tick = max_velocity_mm_s * cpm / rate_hz;
        let slope = (at_max - rest) * cpm / vmax_counts_per_tick;
        let ticks = |s: f64, f: ConfigField| -> Result<u16, ConfigError> {
            let s = fin(s, f)?;
            let t = s * rate_hz;
            if !(s >= 0.0 && t <= u16::MAX as f64) {
                return Err(E::OutOfRange(f));
            }
            // Round to nearest; a non-zero time is at least one tick.
            let n = (t + 0.5) as u16;
            Ok(if s > 0.0 { n.max(1) } else { 0 })
        };
        let amps = |a: f64, f: ConfigField| -> Result<u32, ConfigError> {
            let a = fin(a, f)?;
            if !(a > 0.0 && a < 32_000.0) {
                return Err(E::OutOfRange(f));
            }
            Ok((a * 65_536.0) as u32)
        };
        // Speeds as counts per WINDOW ticks.
        let per_window = |mm_s: f64, f: ConfigField| -> Result<i32, ConfigError> {
            let c = mm_s * cpm / rate_hz * WINDOW as f64;
            if !(c > 0.0 && c < 1e9) {
                return Err(E::OutOfRange(f));
            }
            Ok(c as i32)
        };
        let ratio = fin(self.overspeed_ratio, ConfigField::FaultsOverspeedRatio)?;
        if !(1.0..=10.0).contains(&ratio) {
            return Err(E::OutOfRange(ConfigField::FaultsOverspeedRatio));
        }
        let link = fin(self.link_timeout_s, ConfigField::FaultsLinkTimeoutS)?;
        let link_ticks = link * rate_hz;
        if !(link >= 0.0 && link_ticks <= u32::MAX as f64 / 2.0) {
            return Err(E::OutOfRange(ConfigField::FaultsLinkTimeoutS));
        }
        let motion = fin(self.stall_motion_mm, ConfigField::FaultsStallMotionMm)?;
        if !(motion >= 0.0 && motion * cpm <= 1e9) {
            return Err(E::OutOfRange(ConfigField::FaultsStallMotionMm));
        }
        // A detector switched off gets a threshold it can never reach: no per-tick check of
        // "is it on".
        let ticks_or_never = |t: u16| if t == 0 { u32::MAX } else { t as u32 };
        Ok(Coeffs {
            fe_rest_counts: (rest * cpm) as u32,
            // Q8, capped at 2^16 (256 extra counts per count/tick): the product with a Q4 speed
            // of at most 2^15 then fits a u32.
            fe_slope_q8: (slope * 256.0).clamp(0.0, 65_536.0) as u32,
            stall_current: amps(self.stall_current_a, ConfigField::FaultsStallCurrentA)?,
            stall_motion_counts: (motion * cpm) as u32,
            stall_ticks: ticks_or_never(ticks(self.stall_time_s, ConfigField::FaultsStallTimeS)?),
            runaway_current: amps(self.runaway_current_a, ConfigField::FaultsRunawayCurrentA)?,
            runaway_window_counts: per_window(
                fin(self.runaway_speed_mm_s, ConfigField::FaultsRunawaySpeedMmS)?,
                ConfigField::FaultsRunawaySpeedMmS,
            )? as u32,
            runaway_ticks: ticks_or_never(ticks(
                self.runaway_time_s,
                ConfigField::FaultsRunawayTimeS,
            )?),
            overspeed_window_counts: per_window(
                max_velocity_mm_s * ratio,
                ConfigField::FaultsOverspeedRatio,
            )? as u32,
            overspeed_ticks: ticks_or_never(ticks(
                self.overspeed_time_s,
                ConfigField::FaultsOverspeedTimeS,
            )?),
            saturation_ticks: ticks_or_never(ticks(
                self.saturation_time_s,
                ConfigField::FaultsSaturationTimeS,
            )?),
            link_timeout_ticks: if link > 0.0 {
                (link_ticks as u32).max(1)
            } else {
                0
            },
        })
    }
}

impl Default for Config {
    fn default() -> Self {
        Self::PAPER_RIG
    }
}

/// Ticks over which speed (and acceleration, over two halves) is measured: 4 ms at 2 kHz, long
/// enough that one count of quantisation is under 0.2 mm/s on the paper rig.
pub const WINDOW: usize = 8;
const MASK: usize = WINDOW - 1;

/// Second differences within this many counts count as no acceleration (quantisation).
const ACCEL_DEAD_BAND: i32 = 2;

/// The detectors' thresholds in counts and ticks (`u32::MAX` ticks: switched off).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Coeffs {
    fe_rest_counts: u32,
    fe_slope_q8: u32,
    stall_current: u32,
    stall_motion_counts: u32,
    stall_ticks: u32,
    runaway_current: u32,
    runaway_window_counts: u32,
    runaway_ticks: u32,
    overspeed_window_counts: u32,
    overspeed_ticks: u32,
    saturation_ticks: u32,
    link_timeout_ticks: u32,
}

/// The largest count threshold [`Config::build`] gives (1e9 counts).
const MAX_THRESHOLD_COUNTS: u32 = 1_000_000_000;

impl Coeffs {
    /// The thresholds as words, in the order [`Coeffs::from_words`] reads them: for the
    /// configuration image the host builds (`drive::Parts::encode`).
    pub(crate) fn to_words(self) -> [u32; 12] {
        [
            self.fe_rest_counts,
            self.fe_slope_q8,
            self.stall_current,
            self.stall_motion_counts,
            self.stall_ticks,
            self.runaway_current,
            self.runaway_window_counts,
            self.runaway_ticks,
            self.overspeed_window_counts,
            self.overspeed_ticks,
            self.saturation_ticks,
            self.link_timeout_ticks,
        ]
    }

    /// Thresholds from words, checked in integers against the ranges [`Config::build`] gives;
    /// a refusal names the SI field.
    pub(crate) fn from_words(w: [u32; 12]) -> Result<Coeffs, ConfigError> {
        let check = |ok: bool, v: u32, field| {
            if ok {
                Ok(v)
            } else {
                Err(ConfigError::OutOfRange(field))
            }
        };
        let counts = |v: u32, field| check(v <= MAX_THRESHOLD_COUNTS, v, field);
        // Below 32,000 A in I16F16.
        let amps = |v: u32, field| check(v < 32_000 << 16, v, field);
        // Whole ticks up to `u16::MAX`, or never.
        let ticks = |v: u32, field| {
            check(
                v == u32::MAX || (1..=u16::MAX as u32).contains(&v),
                v,
                field,
            )
        };
        let [rest, slope, stall_a, motion, stall_t, runaway_a, runaway_w, runaway_t, over_w, over_t, sat_t, link] =
            w;
        Ok(Coeffs {
            fe_rest_counts: counts(rest, ConfigField::FaultsFollowingErrorAtRestMm)?,
            fe_slope_q8: check(
                slope <= 1 << 16,
                slope,
                ConfigField::FaultsFollowingErrorAtMaxVelocityMm,
            )?,
            stall_current: amps(stall_a, ConfigField::FaultsStallCurrentA)?,
            stall_motion_counts: counts(motion, ConfigField::FaultsStallMotionMm)?,
            stall_ticks: ticks(stall_t, ConfigField::FaultsStallTimeS)?,
            runaway_current: amps(runaway_a, ConfigField::FaultsRunawayCurrentA)?,
            runaway_window_counts: counts(runaway_w, ConfigField::FaultsRunawaySpeedMmS)?,
            runaway_ticks: ticks(runaway_t, ConfigField::FaultsRunawayTimeS)?,
            overspeed_window_counts: counts(over_w, ConfigField::FaultsOverspeedRatio)?,
            overspeed_ticks: ticks(over_t, ConfigField::FaultsOverspeedTimeS)?,
            saturation_ticks: ticks(sat_t, ConfigField::FaultsSaturationTimeS)?,
            link_timeout_ticks: check(link <= u32::MAX / 2, link, ConfigField::FaultsLinkTimeoutS)?,
        })
    }

    /// The following-error limit, counts, at a set-point velocity of `velocity_q16` (counts per
    /// tick in Q16.16, any sign: [`Setpoint::velocity_q16`](crate::trajectory::Setpoint::velocity_q16),
    /// which the loop reads too). 32-bit arithmetic: the speed to 1/16 count per tick.
    #[inline]
    pub fn following_error_limit_counts(&self, velocity_q16: i32) -> u32 {
        let v_q4 = (velocity_q16.unsigned_abs() >> 12).min(1 << 15);
        self.fe_rest_counts
            .saturating_add(v_q4.wrapping_mul(self.fe_slope_q8) >> 12)
    }

    /// The following-error limit at rest, counts.
    pub fn following_error_at_rest_counts(&self) -> u32 {
        self.fe_rest_counts
    }

    /// Ticks of silence before `LINK_TIMEOUT` (0 = off).
    pub fn link_timeout_ticks(&self) -> u32 {
        self.link_timeout_ticks
    }
}

/// What the detectors see each tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Inputs {
    /// Motor position measured this tick, counts.
    pub position_counts: i32,
    /// Current commanded on the previous tick (the drive's frame, before polarity), amperes.
    pub prev_current_a: I16F16,
    /// Its acceleration feed-forward, amperes (0 when the drive held). The current the
    /// set-point's acceleration asks for is not stall effort: a reversal of a move of a few um
    /// asks 4.6 A for a tick at 5000 mm/s² (the paper rig's tuning) and rightly moves the motor
    /// less than the stall's dead band.
    pub prev_accel_ff_a: I16F16,
    /// The previous tick's command sat at the limit.
    pub prev_saturated: bool,
}

/// The detectors' memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct State {
    /// The last [`WINDOW`] positions; all set to the first position after a reset.
    history: [i32; WINDOW],
    next: usize,
    primed: bool,
    stall_anchor: i32,
    stall_ticks: u32,
    runaway_ticks: u32,
    overspeed_ticks: u32,
    saturation_ticks: u32,
}

impl Default for State {
    fn default() -> Self {
        Self::new()
    }
}

impl State {
    /// Fresh state: the first tick fills the window with its position (no motion yet).
    pub const fn new() -> Self {
        State {
            history: [0; WINDOW],
            next: 0,
            primed: false,
            stall_anchor: 0,
            stall_ticks: 0,
            runaway_ticks: 0,
            overspeed_ticks: 0,
            saturation_ticks: 0,
        }
    }

    /// Forgets everything.
    pub fn reset(&mut self) {
        *self = Self::new();
    }

    /// Forgets everything and starts at `x_counts` as if the motor had stood there for the whole
    /// window: what the drive does when it holds (enable, homing, a fault latching), so that the
    /// first tick after has no window to fill (40 instructions).
    pub fn restart_at(&mut self, x_counts: i32) {
        *self = State {
            history: [x_counts; WINDOW],
            stall_anchor: x_counts,
            primed: true,
            ..Self::new()
        };
    }
}

/// Runs the detectors for one tick and returns the fault bits they raise (0 = none).
///
/// The amplifier's saturation is counted every tick (a limit cycle at half the tick rate must
/// not hide from it), and the position history is kept every tick. The window detectors run on
/// alternate ticks, like a drive's supervision below its loop rate: stall and overspeed on the
/// ticks that write an even slot of the history, runaway on the odd ones, each look counting
/// the two ticks since the last. A condition that holds trips its detector within one tick of
/// its configured time (which side depends on the tick it begins), for about half the
/// instructions; they measure over a window of 4 ms and time out after milliseconds to tens of
/// them. Every trip the full-rate detectors make is made; a condition that comes and goes
/// faster than every other tick can also trip when it is there at each look (a limit cycle at
/// stall current or against the current is itself a fault).
#[inline]
pub fn check(c: &Coeffs, s: &mut State, input: Inputs) -> u16 {
    let x = input.position_counts;
    if !s.primed {
        s.history = [x; WINDOW];
        s.stall_anchor = x;
        s.primed = true;
    }
    let i = input.prev_current_a.to_bits();
    let i_abs = i.unsigned_abs();
    let mut raised = 0;

    // Amplifier at its limit: up while saturated, down while not (chatter does not hide it).
    if input.prev_saturated {
        s.saturation_ticks = s.saturation_ticks.saturating_add(1);
        if s.saturation_ticks >= c.saturation_ticks {
            raised |= Faults::CURRENT_SATURATION;
        }
    } else {
        s.saturation_ticks = s.saturation_ticks.saturating_sub(1);
    }

    let slot = s.next & MASK;
    let oldest = s.history[slot];
    s.history[slot] = x;
    s.next = (slot + 1) & MASK;

    // Speed over the window: v = x - x[-W]. `wrapping_sub` is exact: the encoder refuses any
    // step above its plausibility limit, so positions W ticks apart differ by far less than 2^31.
    let v = x.wrapping_sub(oldest);
    let speed = v.unsigned_abs();

    if slot & 1 == 0 {
        // Stall / encoder loss: effort without response, the feed-forward taken off only when
        // the current alone would count (the cheap test first).
        if i_abs >= c.stall_current
            && i.saturating_sub(input.prev_accel_ff_a.to_bits())
                .unsigned_abs()
                >= c.stall_current
            && x.abs_diff(s.stall_anchor) <= c.stall_motion_counts
        {
            s.stall_ticks = s.stall_ticks.saturating_add(2);
            if s.stall_ticks >= c.stall_ticks {
                raised |= Faults::STALL;
            }
        } else {
            s.stall_anchor = x;
            s.stall_ticks = 0;
        }
        if speed > c.overspeed_window_counts {
            s.overspeed_ticks = s.overspeed_ticks.saturating_add(2);
            if s.overspeed_ticks >= c.overspeed_ticks {
                raised |= Faults::OVERSPEED;
            }
        } else {
            s.overspeed_ticks = 0;
        }
        return raised;
    }

    // Runaway: moving against the current and not slowing down (a = x - 2 x[-W/2] + x[-W]).
    // Braking, motion against the current while decelerating, is normal and excluded.
    let mut runaway = false;
    if i_abs >= c.runaway_current && speed >= c.runaway_window_counts && (v ^ i) < 0 {
        let mid = s.history[(slot + WINDOW / 2) & MASK];
        let a = x.wrapping_sub(mid).wrapping_sub(mid.wrapping_sub(oldest));
        // Slowing by more than the counts' quantisation (two counts over half windows): moving
        // forwards `a >= -ACCEL_DEAD_BAND`, else `a <= ACCEL_DEAD_BAND`, i.e. `-a >=
        // -ACCEL_DEAD_BAND` with the negation saturating (`!a - (-1)`), so exact for every `a`.
        let back = ((v <= 0) as i32).wrapping_neg();
        runaway = (a ^ back).saturating_sub(back) >= -ACCEL_DEAD_BAND;
    }
    if runaway {
        s.runaway_ticks = s.runaway_ticks.saturating_add(2);
        if s.runaway_ticks >= c.runaway_ticks {
            raised |= Faults::RUNAWAY;
        }
    } else {
        s.runaway_ticks = 0;
    }
    raised
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn build_refuses_bad_values_by_name() {
        let ctx = BuildContext::PAPER;
        let bad = [
            (
                Config {
                    stall_current_a: f64::NAN,
                    ..Config::PAPER_RIG
                },
                ConfigField::FaultsStallCurrentA,
            ),
            (
                Config {
                    following_error_at_max_velocity_mm: 0.5,
                    ..Config::PAPER_RIG
                },
                ConfigField::FaultsFollowingErrorAtMaxVelocityMm,
            ),
            (
                Config {
                    overspeed_ratio: 0.9,
                    ..Config::PAPER_RIG
                },
                ConfigField::FaultsOverspeedRatio,
            ),
            (
                Config {
                    stall_time_s: -1.0,
                    ..Config::PAPER_RIG
                },
                ConfigField::FaultsStallTimeS,
            ),
            (
                Config {
                    link_timeout_s: f64::INFINITY,
                    ..Config::PAPER_RIG
                },
                ConfigField::FaultsLinkTimeoutS,
            ),
        ];
        for (cfg, field) in bad {
            assert_eq!(cfg.build(&ctx, 250.0).unwrap_err().field(), field);
        }
        assert!(Config::PAPER_RIG.build(&ctx, 250.0).is_ok());
    }
}
