//! One control tick of the drive: raw counter in, current command and telemetry out.
//!
//! `Drive::step` is the only per-tick entry point. The firmware's `control` task and `hil-sim`'s
//! in-process loop both call exactly this, so the same samples give bit-identical outputs on the
//! host and on the Cortex-M4.
//!
//! Order inside a tick (sampling first, as ODrive's `sampling_cb`): unwrap the motor counter,
//! advance the trajectory, run the PID, run the error model, check faults, saturate.

use crate::ConfigField;
use core::mem::MaybeUninit;

use fixed::types::{I16F16, I40F24};

use crate::blob::BlobError;
use crate::fault;
pub use crate::fault::Faults;
use crate::model::{self, ModelCoeffs, ModelKind, ModelParams, ModelState};
use crate::rig::Rig;
pub use crate::settings::HomingConfig;
use crate::settings::Settings;
use crate::staging::Source;
use crate::trajectory::{self, Trajectory};
use crate::units::{MotorCounts, ScaleCounts};
use crate::BuildContext;
use crate::{encoder, pid, ConfigError};

mod parts_image;
pub use parts_image::{PartsImage, IMAGE_FIELD, PARTS_IMAGE_LEN, PARTS_IMAGE_VERSION};

/// What the board samples at the start of every tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Sample {
    /// Raw 16-bit motor encoder timer counter (x4 quadrature), wrapping.
    pub motor_counter: u16,
    /// Raw 16-bit linear-scale timer counter (x4, 0.5 um), wrapping; only calibration and
    /// evaluation read it, the control law never does.
    pub scale_counter: u16,
}

/// Everything a tick reports: the link's type, so the drive and the wire cannot disagree.
pub use belt_link::wire::Telemetry;

/// Result of one tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Output {
    /// Current command for the amplifier, amperes (zero while faulted or disabled), polarity
    /// applied: exactly what the board writes.
    pub current_a: I16F16,
    /// What happened this tick.
    pub telemetry: Telemetry,
}

pub use belt_link::{Command, CommandError};

/// Where the error models' parameters come from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Models<'a> {
    /// `f64` parameters (presets, host tools).
    Params(&'a ModelParams),
    /// A calibration image (see [`crate::image`]): coefficients the host built, read and
    /// checked in integers; the firmware carries no `f64` on its calibration path. Empty: no
    /// calibration, uncompensated until one loads (the firmware's boot).
    Image(&'a [u8]),
}

/// The whole drive in SI units; `Drive::new` checks it and converts it once: the machine
/// builder's [`Settings`] (one list of fields, the same on the link and in storage) and the
/// error models' parameters.
///
/// The model parameters are borrowed: they are large, and the firmware keeps them in flash.
#[derive(Clone, Debug, PartialEq)]
pub struct DriveConfig<'a> {
    /// Geometry, rate, travel and limits, polarity, gains, fault thresholds, the model at start
    /// and homing.
    pub settings: Settings,
    /// Error-model parameters (Table 2 presets or a calibration).
    pub model: Models<'a>,
}

impl DriveConfig<'static> {
    /// The paper's rig (Table 1) at 2 kHz, 0-300 mm of travel, Table 2 models, Model 1 active
    /// ([`Settings::PAPER`]).
    pub fn paper_rig() -> DriveConfig<'static> {
        DriveConfig {
            settings: Settings::PAPER,
            model: Models::Params(&ModelParams::PAPER),
        }
    }
}

/// Wiring polarity: which way the counters count and the current pushes. Inverting a counter
/// negates its raw register before unwrapping; inverting the current negates the command after
/// the loop, so the loop, the models and the detectors all work in the drive's own frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Polarity {
    /// The motor encoder counts down for positive carriage travel.
    pub motor_encoder_inverted: bool,
    /// The linear scale counts down for positive carriage travel.
    pub scale_inverted: bool,
    /// Positive amplifier current moves the carriage towards negative travel.
    pub current_inverted: bool,
}

impl Polarity {
    /// Everything counts and pushes towards positive travel.
    pub const NORMAL: Polarity = Polarity {
        motor_encoder_inverted: false,
        scale_inverted: false,
        current_inverted: false,
    };

    /// A current between the drive's frame (positive pushes towards positive travel) and the
    /// amplifier's: negated when the current is inverted. The same map both ways.
    #[inline]
    pub fn current_frame(&self, current_a: I16F16) -> I16F16 {
        if self.current_inverted {
            current_a.saturating_neg()
        } else {
            current_a
        }
    }
}

/// Scale counts per micrometre: the linear scale is 500 lines/mm, x4.
pub const SCALE_COUNTS_PER_UM: i32 = 2;

/// Integer limits derived once from the configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Limits {
    /// Counts per micrometre of nominal travel, Q32.
    counts_per_um_q32: i64,
    target_min_counts: i32,
    target_max_counts: i32,
    fault_min_counts: i32,
    fault_max_counts: i32,
    max_velocity_um_s: u32,
    max_accel_um_s2: u32,
}

/// A move's limits to the profile's grid (I40F24 counts per tick, per tick²) per um/s and
/// um/s², Q32: built in integers when a command arrives. Cold: kept apart from [`Limits`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct MoveScale {
    velocity_bits_per_um_s_q32: u64,
    accel_bits_per_um_s2_q32: u64,
}

/// The tick's measurements and results, kept for [`Drive::telemetry`]; the flags there are the
/// drive's state, read when it is reported. Six words: building the whole telemetry every tick
/// cost more than the firmware's one copy of it when it reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct LastTick {
    motor_counts: i32,
    scale_counts: i32,
    setpoint_counts: i32,
    following_error_counts: i32,
    est_error_um: I16F16,
    current_a: I16F16,
}

/// The drive: configuration, coefficients and state of one axis.
///
/// `repr(C)` in this order: the per-tick fields come first, within reach of the Cortex-M4's
/// short load/store offsets; the large model tables (about 3 KiB) and the cold fields last.
/// Measured with `tools/bench-target.sh`: 7 instructions per tick fewer than the default layout,
/// which put the fault detectors' fields behind the tables.
#[derive(Clone, Debug)]
#[repr(C)]
pub struct Drive {
    tick: u32,
    faults: Faults,
    enabled: bool,
    homed: bool,
    /// The homing routine is searching for its stop.
    homing: bool,
    prev_saturated: bool,
    model: ModelKind,
    polarity: Polarity,
    /// `polarity`'s counter inversions as masks for [`counting_up`].
    counter_flips: CounterFlips,
    /// The previous tick's command in the drive's frame.
    prev_current_a: I16F16,
    /// Its acceleration feed-forward, which the stall detector does not count as effort.
    prev_accel_ff_a: I16F16,
    /// Ticks without a valid frame left before `LINK_TIMEOUT` (link watchdog): the timeout at
    /// every frame and every stop, counted down while enabled; 0 when off or tripped.
    link_ticks_left: u32,
    motor: encoder::Coeffs<u16>,
    motor_state: encoder::State<u16>,
    scale: encoder::Coeffs<u16>,
    scale_state: encoder::State<u16>,
    limits: Limits,
    monitor: fault::Coeffs,
    monitor_state: fault::State,
    trajectory: Trajectory,
    pid: pid::Coeffs,
    pid_state: pid::State,
    model_state: ModelState,
    last: LastTick,
    models: ModelCoeffs,
    /// Limits the trajectory was last built with (velocity um/s, accel um/s^2).
    move_limits: (u32, u32),
    move_scale: MoveScale,
    /// Late or missed ticks reported by the board, since start.
    missed_ticks: u32,
    /// Scale samples refused by its plausibility check, since start.
    scale_glitches: u32,
    /// Where the last move sends the carriage, um.
    carriage_target_um: i32,
    /// Micrometres per count, Q32 (status only).
    um_per_count_q32: i64,
    rig: Rig,
    homing_cfg: HomingCoeffs,
    /// A configuration was given (boot: stored, or over the link); otherwise enabling is refused.
    configured: bool,
    /// The configuration's control rate and the rate the tick runs at (the firmware's timer,
    /// set at boot: [`Drive::set_tick_rate_hz`]), whole hertz. While they differ enabling is
    /// refused ([`CommandError::RestartNeeded`]): every per-tick coefficient is the
    /// configuration's.
    rate_hz: u32,
    tick_rate_hz: u32,
    /// `models` hold coefficients for `rig`; otherwise only `ModelKind::None` may be selected.
    models_valid: bool,
}

/// The counters' and the current's inversions as masks: all ones for an inverted one, else 0.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct CounterFlips {
    motor: u16,
    scale: u16,
    /// Applied by [`flip_current`]: [`Polarity::current_frame`] without a branch.
    current: i32,
}

impl CounterFlips {
    fn of(p: &Polarity) -> CounterFlips {
        let mask = |inverted: bool| (inverted as u16).wrapping_neg();
        CounterFlips {
            motor: mask(p.motor_encoder_inverted),
            scale: mask(p.scale_inverted),
            current: (p.current_inverted as i32).wrapping_neg(),
        }
    }
}

/// A raw counter that counts up for positive travel: negated (`!raw + 1`) under a flip mask of
/// `0xffff`, unchanged under 0; no branch.
#[inline(always)]
fn counting_up(raw: u16, flip: u16) -> u16 {
    (raw ^ flip).wrapping_sub(flip)
}

/// A current command in the amplifier's frame: negated under a flip mask of all ones. The
/// same as [`Polarity::current_frame`] for every command the tick makes: the loop and the
/// homing clamp to `±limit`, so `i32::MIN` (the one value `saturating_neg` treats apart)
/// never occurs.
#[inline(always)]
fn flip_current(current_a: I16F16, flip: i32) -> I16F16 {
    I16F16::from_bits((current_a.to_bits() ^ flip).wrapping_sub(flip))
}

fn finite(v: f64, field: ConfigField) -> Result<f64, ConfigError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(ConfigError::NotFinite(field))
    }
}

/// `v` (already finite) as `i32`, or the named range error.
/// Micrometres with `frac_bits` fractional bits to counts at `counts_per_um_q32` (Q32.32),
/// rounded to nearest, saturating: |um| * 2^33 can exceed i64, and a target out of range is then
/// refused by its range check.
// Not inlined: commands only, and one copy of the 64-bit saturating arithmetic (flash).
#[inline(never)]
fn um_to_counts_q32(um: i32, frac_bits: u32, counts_per_um_q32: i64) -> i32 {
    let shift = 32 + frac_bits;
    let q = (um as i64)
        .saturating_mul(counts_per_um_q32)
        .saturating_add(1 << (shift - 1));
    (q >> shift).clamp(i32::MIN as i64, i32::MAX as i64) as i32
}

fn to_i32(v: f64, field: ConfigField) -> Result<i32, ConfigError> {
    if v >= i32::MIN as f64 && v <= i32::MAX as f64 {
        Ok(v as i32)
    } else {
        Err(ConfigError::OutOfRange(field))
    }
}

/// A checked configuration in the drive's integer units, everything but the model
/// coefficients: built with f64 arithmetic by [`Parts::build`] on the host, carried to the
/// drive as a configuration image ([`Parts::encode`], [`Parts::decode`]: integer checks only),
/// installed by [`Drive::reconfigure`].
#[derive(Clone, Debug, PartialEq)]
pub struct Parts {
    rig: Rig,
    /// The control rate, whole hertz (the firmware's tick timer).
    rate_hz: u32,
    limits: Limits,
    motor: encoder::Coeffs<u16>,
    scale: encoder::Coeffs<u16>,
    trajectory: Trajectory,
    move_scale: MoveScale,
    pid: pid::Coeffs,
    monitor: fault::Coeffs,
    polarity: Polarity,
    homing: HomingCoeffs,
    um_per_count_q32: i64,
    initial_model: ModelKind,
}

/// The homing routine in counts, ticks and amperes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct HomingCoeffs {
    towards_positive: bool,
    velocity_um_s: u32,
    accel_um_s2: u32,
    current_limit_a: I16F16,
    detect_counts: u32,
    position_um: i32,
    backoff_um: i32,
    /// How far the search goes before it gives up: the travel, both margins and the backoff.
    search_counts: i32,
}

impl Parts {
    /// Checks `cfg` as [`Drive::new`] does and converts it; a refusal names the field.
    pub fn build(cfg: &Settings) -> Result<Parts, ConfigError> {
        use ConfigError as E;
        let homing = &cfg.homing;
        // The geometry and the rate, checked once; every builder below takes them from here.
        let ctx = BuildContext::new(cfg.rig, cfg.rate_hz)?;
        let rate_hz = ctx.rate_hz();
        let cpm = cfg.rig.counts_per_mm();
        let lo = finite(cfg.travel_min_mm, ConfigField::DriveTravelMinMm)?;
        let hi = finite(cfg.travel_max_mm, ConfigField::DriveTravelMaxMm)?;
        let margin = finite(cfg.travel_margin_mm, ConfigField::DriveTravelMarginMm)?;
        if hi <= lo {
            return Err(E::OutOfRange(ConfigField::DriveTravelMaxMm));
        }
        if margin < 0.0 {
            return Err(E::OutOfRange(ConfigField::DriveTravelMarginMm));
        }
        let vmax = finite(cfg.max_velocity_mm_s, ConfigField::DriveMaxVelocityMmS)?;
        let amax = finite(cfg.max_accel_mm_s2, ConfigField::DriveMaxAccelMmS2)?;
        if !(vmax > 0.0 && vmax * 1000.0 <= u32::MAX as f64) {
            return Err(E::OutOfRange(ConfigField::DriveMaxVelocityMmS));
        }
        if !(amax > 0.0 && amax * 1000.0 <= u32::MAX as f64) {
            return Err(E::OutOfRange(ConfigField::DriveMaxAccelMmS2));
        }
        if vmax * 1000.0 < 1.0 {
            return Err(E::OutOfRange(ConfigField::DriveMaxVelocityMmS));
        }
        if amax * 1000.0 < 1.0 {
            return Err(E::OutOfRange(ConfigField::DriveMaxAccelMmS2));
        }
        let counts_per_um_q32 = (cpm / 1000.0 * 4_294_967_296.0) as i64;
        // The travel's ends through the very conversion a move's target takes (whole um, then
        // counts rounded to nearest), so that a move to either end is accepted.
        let end_counts = |mm: f64, field| -> Result<i32, ConfigError> {
            let um = to_i32(mm * 1000.0 + if mm < 0.0 { -0.5 } else { 0.5 }, field)?;
            Ok(um_to_counts_q32(um, 0, counts_per_um_q32))
        };
        let limits = Limits {
            counts_per_um_q32,
            target_min_counts: end_counts(lo, ConfigField::DriveTravelMinMm)?,
            target_max_counts: end_counts(hi, ConfigField::DriveTravelMaxMm)?,
            fault_min_counts: to_i32((lo - margin) * cpm, ConfigField::DriveTravelMarginMm)?,
            fault_max_counts: to_i32((hi + margin) * cpm, ConfigField::DriveTravelMarginMm)?,
            max_velocity_um_s: (vmax * 1000.0) as u32,
            max_accel_um_s2: (amax * 1000.0) as u32,
        };
        let move_scale = MoveScale {
            velocity_bits_per_um_s_q32: (cpm / 1000.0 / rate_hz * 72_057_594_037_927_936.0) as u64,
            accel_bits_per_um_s2_q32: (cpm / 1000.0 / (rate_hz * rate_hz)
                * 72_057_594_037_927_936.0) as u64,
        };
        let monitor = cfg.faults.build(&ctx, vmax)?;
        let enc = encoder::Config {
            max_speed_mm_s: cfg.encoder_max_speed_mm_s,
        };
        let motor = enc.build::<u16>(&ctx)?;
        let scale_per_tick = finite(cfg.encoder_max_speed_mm_s, ConfigField::EncoderMaxSpeedMmS)?
            * 1000.0
            * SCALE_COUNTS_PER_UM as f64
            / rate_hz;
        let scale = encoder::Coeffs::<u16>::from_max_delta_counts(scale_per_tick as u32 + 1)
            .map_err(|_| E::OutOfRange(ConfigField::EncoderMaxSpeedMmS))?;
        let pid = cfg.pid.build(&ctx)?;
        let start = trajectory::Config {
            velocity_mm_s: vmax,
            acceleration_mm_s2: amax,
            deceleration_mm_s2: amax,
        };
        let trajectory = Trajectory::new(start.build(&ctx)?, 0);

        // Homing: slow and gentle, found before the following-error fault.
        let hv = finite(homing.velocity_mm_s, ConfigField::HomingVelocityMmS)?;
        if !(hv > 0.0 && hv <= vmax) {
            return Err(E::OutOfRange(ConfigField::HomingVelocityMmS));
        }
        let hi_a = finite(homing.current_a, ConfigField::HomingCurrentA)?;
        if !(hi_a > 0.0 && hi_a <= cfg.pid.max_current_a) {
            return Err(E::OutOfRange(ConfigField::HomingCurrentA));
        }
        let detect = finite(homing.detect_error_mm, ConfigField::HomingDetectErrorMm)?;
        if !(detect > 0.0 && detect < cfg.faults.following_error_at_rest_mm) {
            return Err(E::OutOfRange(ConfigField::HomingDetectErrorMm));
        }
        let hpos = finite(homing.position_mm, ConfigField::HomingPositionMm)?;
        if !(hpos >= lo - margin && hpos <= hi + margin) {
            return Err(E::OutOfRange(ConfigField::HomingPositionMm));
        }
        let backoff = finite(homing.backoff_mm, ConfigField::HomingBackoffMm)?;
        let after = if homing.towards_positive {
            hpos - backoff
        } else {
            hpos + backoff
        };
        if !(backoff >= 0.0 && after >= lo && after <= hi) {
            return Err(E::OutOfRange(ConfigField::HomingBackoffMm));
        }
        // Whole um/s: a speed that rounds to none would never move (the image refuses it too).
        if hv * 1000.0 < 1.0 {
            return Err(E::OutOfRange(ConfigField::HomingVelocityMmS));
        }
        let homing = HomingCoeffs {
            towards_positive: homing.towards_positive,
            velocity_um_s: (hv * 1000.0) as u32,
            // Reaches the jog speed within 0.1 s.
            accel_um_s2: ((hv * 10_000.0) as u32).clamp(1, limits.max_accel_um_s2),
            current_limit_a: I16F16::checked_from_num(hi_a)
                .ok_or(E::OutOfRange(ConfigField::HomingCurrentA))?,
            detect_counts: (detect * cpm) as u32,
            position_um: to_i32(hpos * 1000.0, ConfigField::HomingPositionMm)?,
            backoff_um: to_i32(backoff * 1000.0, ConfigField::HomingBackoffMm)?,
            search_counts: to_i32(
                (hi - lo + 2.0 * margin + backoff) * cpm,
                ConfigField::DriveTravelMaxMm,
            )?,
        };
        Ok(Parts {
            rig: cfg.rig,
            // Whole hertz: `Settings` holds the rate so; a fraction only in host simulations.
            rate_hz: rate_hz as u32,
            limits,
            motor,
            scale,
            trajectory,
            move_scale,
            pid,
            monitor,
            polarity: cfg.polarity,
            homing,
            um_per_count_q32: (1000.0 / cpm * 4_294_967_296.0) as i64,
            initial_model: cfg.initial_model,
        })
    }
}

impl Drive {
    /// Checks `cfg` and builds a disabled, configured drive at position 0 (home it with
    /// `Command::Home` or `Command::Homing`).
    pub fn new(cfg: &DriveConfig) -> Result<Drive, ConfigError> {
        let mut drive = Drive::assemble(Parts::build(&cfg.settings)?);
        drive.install_models(cfg)?;
        Ok(drive)
    }

    /// [`Drive::new`] built in place in `slot` (the firmware's static): the 5.6 KB drive never
    /// passes through the caller's stack. On a refusal `slot` may hold a drive; do not use it.
    pub fn new_in<'a>(
        slot: &'a mut MaybeUninit<Drive>,
        cfg: &DriveConfig,
    ) -> Result<&'a mut Drive, ConfigError> {
        let parts = Parts::build(&cfg.settings)?;
        let drive = slot.write(Drive::assemble(parts));
        drive.install_models(cfg)?;
        Ok(drive)
    }

    /// A disabled drive from a configuration image's `parts` (see [`Parts::decode`]) and a
    /// calibration image (empty: none, no compensation until one loads), built in place in `slot` as [`Drive::new_in`] does but without any
    /// `f64`: the firmware's boot. On a refusal `slot` may hold a drive; do not use it.
    pub fn from_parts_in<'a>(
        slot: &'a mut MaybeUninit<Drive>,
        parts: Parts,
        calibration: &[u8],
    ) -> Result<&'a mut Drive, BlobError> {
        let rig = parts.rig;
        let drive = slot.write(Drive::assemble(parts));
        if calibration.is_empty() {
            drive.uncalibrated();
        } else {
            crate::image::decode_into(calibration, &rig, drive.rate_hz, &mut drive.models)?;
        }
        Ok(drive)
    }

    /// No calibration: uncompensated (`ModelKind::None`) until one loads.
    fn uncalibrated(&mut self) {
        self.models_valid = false;
        self.model = ModelKind::None;
    }

    /// The models of `cfg`, into the drive's coefficients in place (an empty image: none, as
    /// the firmware boots).
    fn install_models(&mut self, cfg: &DriveConfig) -> Result<(), ConfigError> {
        match cfg.model {
            Models::Params(p) => {
                self.models = p.build(&cfg.settings.rig)?;
                // A belt observer is built for one control rate, as the image check holds it.
                let rate = self.models.model4.belt.as_ref().map(|b| b.rate_hz());
                if rate.is_some_and(|hz| hz != self.rate_hz) {
                    return Err(ConfigError::OutOfRange(ConfigField::DriveRateHz));
                }
            }
            Models::Image([]) => self.uncalibrated(),
            Models::Image(b) => {
                crate::image::decode_into(b, &cfg.settings.rig, self.rate_hz, &mut self.models)
                    .map_err(|e| match e {
                        BlobError::Invalid(e) => e,
                        _ => ConfigError::OutOfRange(ConfigField::CalibrationImage),
                    })?
            }
        }
        Ok(())
    }

    /// A disabled drive with `parts` and no models yet (every table empty).
    #[inline(always)]
    fn assemble(p: Parts) -> Drive {
        Drive {
            rig: p.rig,
            limits: p.limits,
            motor: p.motor,
            motor_state: encoder::State::new(0),
            scale: p.scale,
            scale_state: encoder::State::new(0),
            trajectory: p.trajectory,
            move_limits: (p.limits.max_velocity_um_s, p.limits.max_accel_um_s2),
            move_scale: p.move_scale,
            pid: p.pid,
            pid_state: pid::State::new(),
            // Read in place by `install_models`: no second 5 KiB copy on the stack.
            models: ModelCoeffs::ZERO,
            models_valid: true,
            model_state: ModelState::new(0),
            model: p.initial_model,
            monitor: p.monitor,
            monitor_state: fault::State::new(),
            polarity: p.polarity,
            counter_flips: CounterFlips::of(&p.polarity),
            homing_cfg: p.homing,
            homing: false,
            configured: true,
            rate_hz: p.rate_hz,
            tick_rate_hz: p.rate_hz,
            enabled: false,
            homed: false,
            faults: Faults::NONE,
            prev_current_a: I16F16::ZERO,
            prev_accel_ff_a: I16F16::ZERO,
            prev_saturated: false,
            link_ticks_left: p.monitor.link_timeout_ticks(),
            missed_ticks: 0,
            scale_glitches: 0,
            carriage_target_um: 0,
            um_per_count_q32: p.um_per_count_q32,
            tick: 0,
            last: LastTick::default(),
        }
    }

    /// Marks the drive unconfigured: it refuses to enable until [`Drive::reconfigure`] (the
    /// firmware boots so when no valid configuration is stored, never silently on defaults).
    pub fn forget_configuration(&mut self) {
        self.configured = false;
        self.enabled = false;
        self.hold_here();
    }

    /// Whether the drive holds a configuration it may run with.
    pub fn is_configured(&self) -> bool {
        self.configured
    }

    /// The rate the control tick runs at, whole hertz: the firmware sets its timer's at boot,
    /// before it installs the stored configuration. A configuration of another rate is
    /// installed but not run ([`Drive::restart_needed`]).
    pub fn set_tick_rate_hz(&mut self, rate_hz: u32) {
        self.tick_rate_hz = rate_hz;
    }

    /// The configuration's control rate, whole hertz.
    pub fn rate_hz(&self) -> u32 {
        self.rate_hz
    }

    /// The configuration's control rate is not the tick's: enabling is refused until the drive
    /// restarts with it stored (the timer is set at boot).
    pub fn restart_needed(&self) -> bool {
        self.rate_hz != self.tick_rate_hz
    }

    /// Whether the error models hold coefficients for this drive's geometry (a calibration, or
    /// the presets of the geometry they were made for).
    pub fn is_calibrated(&self) -> bool {
        self.models_valid
    }

    /// Whether the homing routine is running.
    pub fn is_homing(&self) -> bool {
        self.homing
    }

    /// Installs a configuration ([`Parts::build`] on the host, [`Parts::decode`] on the drive).
    /// Only while disabled. The drive must be homed again; with another geometry the models no
    /// longer apply, so compensation is off (`ModelKind::None`) until a calibration loads.
    pub fn reconfigure(&mut self, p: Parts) -> Result<(), CommandError> {
        if self.enabled || !self.trajectory.is_done() {
            return Err(CommandError::Busy);
        }
        // Another geometry, or another rate (Model 4's observer and low pass are built for
        // one): the calibration no longer applies.
        if !p.rig.same_bits(&self.rig) || p.rate_hz != self.rate_hz {
            self.models_valid = false;
        }
        let here = self.motor_state.position_counts();
        self.rig = p.rig;
        self.rate_hz = p.rate_hz;
        self.limits = p.limits;
        self.motor = p.motor;
        self.scale = p.scale;
        self.trajectory = p.trajectory;
        self.trajectory.reset(here);
        self.move_limits = (p.limits.max_velocity_um_s, p.limits.max_accel_um_s2);
        self.move_scale = p.move_scale;
        self.pid = p.pid;
        self.monitor = p.monitor;
        self.polarity = p.polarity;
        self.counter_flips = CounterFlips::of(&p.polarity);
        self.homing_cfg = p.homing;
        self.um_per_count_q32 = p.um_per_count_q32;
        self.model = if self.models_valid {
            p.initial_model
        } else {
            ModelKind::None
        };
        self.model_state.settle(here);
        self.configured = true;
        self.homed = false;
        self.homing = false;
        self.hold_here();
        Ok(())
    }

    /// Checks and loads a calibration image (see [`crate::image`]). Refused while a move is in
    /// progress; a refused image changes nothing.
    pub fn load_calibration(&mut self, image: &[u8]) -> Result<(), BlobError> {
        self.load_calibration_from(&mut { image })
    }

    /// [`Drive::load_calibration`] from an image read in small windows (the staging flash).
    pub fn load_calibration_from(&mut self, image: &mut dyn Source) -> Result<(), BlobError> {
        if !self.trajectory.is_done() {
            return Err(BlobError::Busy);
        }
        crate::image::check_from(image, &self.rig, self.rate_hz)?;
        self.load_checked_calibration_from(image)
    }

    /// Loads an image that [`crate::image::check`] accepted for this drive's geometry, reading
    /// it straight into the coefficients (no 5 KiB staging copy): the firmware checks outside
    /// the control task's lock and holds the lock only for this read (tens of microseconds, at
    /// rest). Refused while a move is in progress. Should the bytes fail after all, the drive
    /// is left with no compensation (every table empty, model `None`), never with a mix.
    pub fn load_checked_calibration(&mut self, image: &[u8]) -> Result<(), BlobError> {
        self.load_checked_calibration_from(&mut { image })
    }

    /// [`Drive::load_checked_calibration`] from an image read in small windows.
    pub fn load_checked_calibration_from(
        &mut self,
        image: &mut dyn Source,
    ) -> Result<(), BlobError> {
        if !self.trajectory.is_done() {
            return Err(BlobError::Busy);
        }
        if let Err(e) = crate::image::decode_from(image, &self.rig, self.rate_hz, &mut self.models)
        {
            self.models = ModelCoeffs::ZERO;
            self.models_valid = false;
            self.model = ModelKind::None;
            self.model_state.settle(self.motor_state.position_counts());
            return Err(e);
        }
        self.models_valid = true;
        self.model_state.settle(self.motor_state.position_counts());
        Ok(())
    }

    /// The drive-train geometry this drive was built for.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The coefficients of the error models in use.
    pub fn models(&self) -> &ModelCoeffs {
        &self.models
    }

    /// Telemetry of the last tick: its positions, set-point, following error, estimate and
    /// current, with the drive's faults, model and flags as they are now. The control task reads
    /// it right after the tick, where they are the tick's; a status reply between ticks shows a
    /// command's effect at once (a move is `moving`, a disable drops `amplifier_enabled`,
    /// which the amplifier's line follows at the next tick).
    pub fn telemetry(&self) -> Telemetry {
        let last = &self.last;
        Telemetry {
            tick: self.tick,
            motor_counts: MotorCounts(last.motor_counts),
            scale_counts: ScaleCounts(last.scale_counts),
            setpoint_counts: MotorCounts(last.setpoint_counts),
            following_error_counts: MotorCounts(last.following_error_counts),
            est_error_um: last.est_error_um,
            current_a: last.current_a,
            faults: self.faults,
            model: self.model,
            moving: self.enabled && !self.trajectory.is_done(),
            amplifier_enabled: self.amplifier_enabled(),
            homed: self.homed,
        }
    }

    /// Latches `bits` (e.g. `Faults::CLOCK_FAILURE` from the board): zero current and a low
    /// amplifier enable from the next tick until `ClearFaults` and `Enable`.
    pub fn raise_fault(&mut self, bits: u16) {
        if bits == 0 {
            return;
        }
        self.faults.0 |= bits;
        self.enabled = false;
        self.hold_here();
    }

    /// The board (or a runner) reports `n` control ticks that ran late or never ran. They are
    /// counted; while the drive is enabled any of them latches `DEADLINE_MISSED`, because the
    /// loop's timing (and so its gains) no longer holds.
    pub fn missed_ticks(&mut self, n: u32) {
        if n == 0 {
            return;
        }
        self.missed_ticks = self.missed_ticks.saturating_add(n);
        if self.enabled {
            self.raise_fault(Faults::DEADLINE_MISSED);
        }
    }

    /// A valid frame arrived from the host: feeds the link watchdog.
    pub fn link_alive(&mut self) {
        self.link_ticks_left = self.monitor.link_timeout_ticks();
    }

    /// Whether the current output is enabled.
    pub fn is_enabled(&self) -> bool {
        self.enabled
    }

    /// Whether the drive wants the amplifier's enable line high: enabled and no fault latched
    /// (the telemetry's `amplifier_enabled`, without building the telemetry); the control task
    /// writes it right after each tick.
    pub fn amplifier_enabled(&self) -> bool {
        self.enabled && self.faults.is_clear()
    }

    /// Whether the drive has been homed since start.
    pub fn is_homed(&self) -> bool {
        self.homed
    }

    /// Latched fault bits.
    pub fn faults(&self) -> Faults {
        self.faults
    }

    /// Late or missed ticks reported since start.
    pub fn missed_tick_count(&self) -> u32 {
        self.missed_ticks
    }

    /// Scale samples refused as implausible since start (a glitch of the temporary calibration
    /// scale is counted, never a motor fault).
    pub fn scale_glitch_count(&self) -> u32 {
        self.scale_glitches
    }

    /// Where the last move sends the carriage, um of travel (the motor target of a motor move;
    /// the home position after homing).
    pub fn carriage_target_um(&self) -> i32 {
        self.carriage_target_um
    }

    /// The estimated carriage position of the last tick: motor position plus the active
    /// compensator's estimate, um of travel (rounded, saturating).
    pub fn carriage_estimate_um(&self) -> i32 {
        let motor_q32 = (self.last.motor_counts as i64).saturating_mul(self.um_per_count_q32);
        let est_q32 = (self.last.est_error_um.to_bits() as i64) << 16;
        let um = motor_q32.saturating_add(est_q32).saturating_add(1 << 31) >> 32;
        um.clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    /// The fault detectors' thresholds in counts and ticks.
    pub fn monitor(&self) -> &fault::Coeffs {
        &self.monitor
    }

    /// Micrometres of nominal travel to counts (round to nearest), saturating.
    fn um_to_counts(&self, um: i32) -> i32 {
        self.fixed_um_to_counts(um, 0)
    }

    /// Micrometres with `frac_bits` fractional bits to counts, rounded to nearest, saturating:
    /// |um| * 2^33 can exceed i64, and a target out of range is then refused by its range check.
    fn fixed_um_to_counts(&self, um: i32, frac_bits: u32) -> i32 {
        um_to_counts_q32(um, frac_bits, self.limits.counts_per_um_q32)
    }

    /// The range checks of a move (travel, velocity, acceleration), as a command makes them, for
    /// a host that checks a plan before sending it. A carriage move is also refused when the
    /// motor would have to stand beyond the travel's fault limits, which depends on the model's
    /// state at the time.
    pub fn check_move(
        &self,
        target_um: i32,
        velocity_um_s: u32,
        accel_um_s2: u32,
    ) -> Result<(), CommandError> {
        self.move_target_counts(target_um, velocity_um_s, accel_um_s2)
            .map(|_| ())
    }

    /// [`Drive::check_move`]; the target in counts.
    fn move_target_counts(
        &self,
        target_um: i32,
        velocity_um_s: u32,
        accel_um_s2: u32,
    ) -> Result<i32, CommandError> {
        let target = self.um_to_counts(target_um);
        if target < self.limits.target_min_counts || target > self.limits.target_max_counts {
            return Err(CommandError::TargetOutOfTravel);
        }
        if velocity_um_s == 0 || velocity_um_s > self.limits.max_velocity_um_s {
            return Err(CommandError::VelocityOutOfRange);
        }
        if accel_um_s2 == 0 || accel_um_s2 > self.limits.max_accel_um_s2 {
            return Err(CommandError::AccelOutOfRange);
        }
        Ok(target)
    }

    /// Checks and starts a move; `carriage`: `target_um` is where the carriage must arrive. All
    /// work happens on a copy of the profile, committed only when every check passed.
    fn start_move(
        &mut self,
        target_um: i32,
        velocity_um_s: u32,
        accel_um_s2: u32,
        carriage: bool,
    ) -> Result<(), CommandError> {
        if !self.enabled {
            return Err(CommandError::NotEnabled);
        }
        if !self.homed {
            return Err(CommandError::NotHomed);
        }
        let target = self.move_target_counts(target_um, velocity_um_s, accel_um_s2)?;
        let mut profile = self.trajectory;
        if (velocity_um_s, accel_um_s2) != self.move_limits {
            // New limits, also in mid-move (feed override, blending): integers only, so nothing
            // of f64 runs while the control task waits for the lock.
            let coeffs = self.move_coeffs(velocity_um_s, accel_um_s2)?;
            profile
                .set_coeffs(coeffs)
                .map_err(|_| CommandError::AccelOutOfRange)?;
        }
        let motor_target = if carriage {
            let m = self.motor_target_for(target, &profile);
            // The motor may stand outside the carriage's travel by the error, not beyond the
            // fault limits.
            if m < self.limits.fault_min_counts || m > self.limits.fault_max_counts {
                return Err(CommandError::TargetOutOfTravel);
            }
            m
        } else {
            target
        };
        profile.set_target(motor_target);
        self.trajectory = profile;
        self.move_limits = (velocity_um_s, accel_um_s2);
        self.carriage_target_um = target_um;
        Ok(())
    }

    /// The motor position at which the active model puts the carriage on `carriage_counts`,
    /// following the planned path: from the present state, through the stopping point if the
    /// target lies behind it (where the motor will turn), to the target. The model's error
    /// changes by about 0.1 % of the travel along a band edge, so three fixed-point iterations of
    /// `m = c - y(m)` settle to the count. Bounded: at most six model evaluations, on a copy of
    /// the model's state.
    fn motor_target_for(&self, carriage_counts: i32, profile: &Trajectory) -> i32 {
        if self.model == ModelKind::None {
            return carriage_counts;
        }
        // Every compensator goes through the same inverse: the baselines' estimates are the
        // LinuxCNC corrections, applied to the move's end point so that the motor's trapezoid
        // takes up the backlash within the move's limits.
        let here = profile.position_floor_counts();
        let stop = profile.stopping_point_counts();
        let moving_up = stop >= here;
        let mut m = carriage_counts;
        for _ in 0..3 {
            let mut state = self.model_state.clone();
            // The motor turns at the stopping point when the target lies behind it.
            if stop != here && (m >= stop) != moving_up {
                model::estimate(&self.models, self.model, &mut state, stop);
            }
            let y_um = model::estimate(&self.models, self.model, &mut state, m);
            m = carriage_counts.saturating_sub(self.fixed_um_to_counts(y_um.to_bits(), 16));
        }
        m
    }

    /// A move's profile limits on the counts grid, from integer um/s and um/s² (rounded down).
    fn move_coeffs(
        &self,
        velocity_um_s: u32,
        accel_um_s2: u32,
    ) -> Result<trajectory::Coeffs, CommandError> {
        let grid = |x: u32, per_q32: u64| {
            let bits = (x as u128 * per_q32 as u128) >> 32;
            I40F24::from_bits(bits.min(i64::MAX as u128) as i64)
        };
        let v = grid(velocity_um_s, self.move_scale.velocity_bits_per_um_s_q32);
        let a = grid(accel_um_s2, self.move_scale.accel_bits_per_um_s2_q32);
        trajectory::Coeffs::new(v, a, a).map_err(|e| match e.field() {
            ConfigField::TrajectoryVelocityMmS => CommandError::VelocityOutOfRange,
            _ => CommandError::AccelOutOfRange,
        })
    }

    /// Applies a command. A refused command changes nothing; any command, applied or not, shows
    /// that the host is alive (link watchdog).
    pub fn command(&mut self, cmd: Command) -> Result<(), CommandError> {
        self.link_alive();
        match cmd {
            Command::MoveMotorTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            } => self.start_move(target_um, velocity_um_s, accel_um_s2, false)?,
            Command::MoveTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            } => self.start_move(target_um, velocity_um_s, accel_um_s2, true)?,
            Command::Stop => {
                self.trajectory.stop();
                self.homing = false;
            }
            Command::Enable => {
                if !self.configured {
                    return Err(CommandError::Unconfigured);
                }
                if self.restart_needed() {
                    return Err(CommandError::RestartNeeded);
                }
                if !self.faults.is_clear() {
                    return Err(CommandError::NotEnabled);
                }
                if !self.enabled {
                    self.hold_here();
                    self.enabled = true;
                }
            }
            Command::Disable => {
                self.enabled = false;
                self.homing = false;
            }
            Command::ClearFaults => self.faults = Faults::NONE,
            Command::SelectModel(kind) => {
                if kind != ModelKind::None && !self.models_valid {
                    return Err(CommandError::NotCalibrated);
                }
                self.model = kind;
            }
            Command::Homing => self.start_homing()?,
            Command::Home {
                position_um,
                scale_um,
            } => {
                if !self.trajectory.is_done() {
                    return Err(CommandError::Busy);
                }
                let x = self.um_to_counts(position_um);
                self.motor_state.reset(x);
                let scale = (scale_um as i64 * SCALE_COUNTS_PER_UM as i64)
                    .clamp(i32::MIN as i64, i32::MAX as i64) as i32;
                self.scale_state.reset(scale);
                self.model_state.reset(x);
                self.carriage_target_um = position_um;
                self.homed = true;
                self.homing = false;
                self.hold_here();
            }
        }
        Ok(())
    }

    /// Starts the homing search: a motor move towards the stop, far enough to cross the whole
    /// travel from anywhere in it, at the homing speed; [`Drive::step`] watches for the stop.
    fn start_homing(&mut self) -> Result<(), CommandError> {
        if !self.enabled {
            return Err(CommandError::NotEnabled);
        }
        if !self.trajectory.is_done() {
            return Err(CommandError::Busy);
        }
        let h = self.homing_cfg;
        let coeffs = self.move_coeffs(h.velocity_um_s, h.accel_um_s2)?;
        let here = self.motor_state.position_counts();
        let target = if h.towards_positive {
            here.saturating_add(h.search_counts)
        } else {
            here.saturating_sub(h.search_counts)
        };
        let mut profile = self.trajectory;
        profile
            .set_coeffs(coeffs)
            .map_err(|_| CommandError::AccelOutOfRange)?;
        profile.set_target(target);
        self.trajectory = profile;
        self.move_limits = (h.velocity_um_s, h.accel_um_s2);
        self.homed = false;
        self.homing = true;
        Ok(())
    }

    /// The homing search's tick, instead of the fault detectors (pressing on the stop is what it
    /// looks for): the current limited to the homing current, the stop found when the following
    /// error passes the detection threshold. Then the stop is the homing position, the scale
    /// reads it too (the carriage touches the stop), the models start on the band edge of the
    /// approach direction, and the drive backs off. Runs after the profile's and the loop's
    /// tick, which the control tick shares with normal motion (one inlined copy of each);
    /// kept out of line: the per-tick path of a homed drive does not pay for it.
    #[cold]
    #[inline(never)]
    fn homing_tick(&mut self, sp: &trajectory::Setpoint, out: &pid::Output) -> (I16F16, i32, i32) {
        let h = self.homing_cfg;
        let fe = out.following_error_counts.to_num::<i32>();
        let setpoint = sp.position_floor_counts();
        if fe.unsigned_abs() > h.detect_counts {
            let home = self.um_to_counts(h.position_um);
            self.motor_state.reset(home);
            let scale = (h.position_um as i64 * SCALE_COUNTS_PER_UM as i64)
                .clamp(i32::MIN as i64, i32::MAX as i64) as i32;
            self.scale_state.reset(scale);
            self.model_state.reset(home);
            if !h.towards_positive {
                self.model_state.dir = model::Direction::Reverse;
            }
            self.homing = false;
            self.homed = true;
            self.hold_here();
            let away = if h.towards_positive {
                h.position_um.saturating_sub(h.backoff_um)
            } else {
                h.position_um.saturating_add(h.backoff_um)
            };
            self.carriage_target_um = h.position_um;
            if h.backoff_um != 0 {
                // Checked at configuration: the backoff ends inside the travel.
                let _ = self.start_move(away, h.velocity_um_s, h.accel_um_s2, false);
            }
            return (I16F16::ZERO, 0, home);
        }
        if self.trajectory.is_done() {
            self.homing = false;
            self.faults.0 |= Faults::HOMING_FAILED;
        }
        // `max`/`min`, not `clamp`: the same for the positive limit the configuration
        // guarantees, without `clamp`'s panic path for `min > max`.
        let limit = h.current_limit_a;
        (out.current_a.max(-limit).min(limit), fe, setpoint)
    }

    /// Counts a tick without a frame from the host; latches `LINK_TIMEOUT` when too many pass.
    #[inline(always)]
    fn link_watchdog(&mut self) {
        // Counted down from the timeout: the tick that reaches 0 is the timeout-th without a
        // frame. The fault then latches, and the stop it causes re-arms the count.
        if self.link_ticks_left != 0 {
            self.link_ticks_left = self.link_ticks_left.wrapping_sub(1);
            if self.link_ticks_left == 0 {
                self.faults.0 |= Faults::LINK_TIMEOUT;
            }
        }
    }

    /// Set-point at the measured position, loop and detector state cleared: enabling never jerks
    /// the motor, and no detector carries history across a stop.
    // Not inlined: commands, and the ticks while a fault is latched.
    #[inline(never)]
    fn hold_here(&mut self) {
        let x = self.motor_state.position_counts();
        self.trajectory.reset(x);
        self.pid_state.reset();
        self.monitor_state.restart_at(x);
        self.prev_current_a = I16F16::ZERO;
        self.prev_accel_ff_a = I16F16::ZERO;
        self.prev_saturated = false;
        self.link_ticks_left = self.monitor.link_timeout_ticks();
    }

    /// One control tick and its telemetry: [`Drive::control`], then [`Drive::telemetry`].
    pub fn step(&mut self, sample: Sample) -> Output {
        let current_a = self.control(sample);
        Output {
            current_a,
            telemetry: self.telemetry(),
        }
    }

    /// One control tick: the amplifier's current command (polarity applied); what only the tick
    /// knows is kept for [`Drive::telemetry`], which the firmware builds after writing the current.
    /// Integer-only, allocation-free, bounded time; never panics.
    pub fn control(&mut self, sample: Sample) -> I16F16 {
        self.tick = self.tick.wrapping_add(1);
        let motor_raw = counting_up(sample.motor_counter, self.counter_flips.motor);
        let mut x = match self.motor.update(&mut self.motor_state, motor_raw) {
            Ok(x) => x,
            Err(_) => {
                // The position can no longer be trusted: the drive must be homed again.
                self.faults.0 |= Faults::ENCODER_JUMP;
                self.homed = false;
                self.motor_state.position_counts()
            }
        };
        let scale_raw = counting_up(sample.scale_counter, self.counter_flips.scale);
        // The scale only informs calibration; a glitch there is counted and keeps the last good
        // reading.
        if self.scale.update(&mut self.scale_state, scale_raw).is_err() {
            self.scale_glitches = self.scale_glitches.saturating_add(1);
        }
        // Before homing the position means nothing: the travel is checked once homed.
        if self.homed && (x < self.limits.fault_min_counts || x > self.limits.fault_max_counts) {
            self.faults.0 |= Faults::TRAVEL_LIMIT;
        }

        let mut current_a = I16F16::ZERO;
        let mut accel_ff_a = I16F16::ZERO;
        let mut saturated = false;
        let mut following_error_counts = 0;
        let mut setpoint_counts = x;
        if self.enabled && self.faults.is_clear() {
            let sp = self.trajectory.tick();
            let out = self.pid.update(&mut self.pid_state, &sp, x);
            if self.homing {
                (current_a, following_error_counts, setpoint_counts) = self.homing_tick(&sp, &out);
                if self.homed {
                    // Found this tick: the model starts from the position it assigned.
                    x = self.motor_state.position_counts();
                }
                self.link_watchdog();
            } else {
                // The floor of the I24F8 error (always within i32).
                following_error_counts = out.following_error_counts.to_num::<i32>();
                setpoint_counts = sp.position_floor_counts();
                let limit = self.monitor.following_error_limit_counts(sp.velocity_q16());
                if following_error_counts.unsigned_abs() > limit {
                    self.faults.0 |= Faults::FOLLOWING_ERROR;
                } else {
                    current_a = out.current_a;
                    accel_ff_a = out.accel_feedforward_a;
                    saturated = out.saturated;
                }
                self.faults.0 |= fault::check(
                    &self.monitor,
                    &mut self.monitor_state,
                    fault::Inputs {
                        position_counts: x,
                        prev_current_a: self.prev_current_a,
                        prev_accel_ff_a: self.prev_accel_ff_a,
                        prev_saturated: self.prev_saturated,
                    },
                );
                self.link_watchdog();
            }
        }
        if !self.faults.is_clear() {
            // Safe state: zero current, disabled until the host clears the fault and re-enables.
            self.enabled = false;
            self.homing = false;
            current_a = I16F16::ZERO;
            accel_ff_a = I16F16::ZERO;
            saturated = false;
            self.hold_here();
        }
        self.prev_current_a = current_a;
        self.prev_accel_ff_a = accel_ff_a;
        self.prev_saturated = saturated;

        let est_error_um = model::estimate_with_current(
            &self.models,
            self.model,
            &mut self.model_state,
            x,
            current_a,
        );
        // Polarity last: everything above works in the drive's own frame.
        let command_a = flip_current(current_a, self.counter_flips.current);
        self.last = LastTick {
            motor_counts: x,
            scale_counts: self.scale_state.position_counts(),
            setpoint_counts,
            following_error_counts,
            est_error_um,
            current_a: command_a,
        };
        command_a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counting_up_negates_exactly_under_the_flip() {
        let normal = CounterFlips::of(&Polarity::NORMAL);
        let inverted = CounterFlips::of(&Polarity {
            motor_encoder_inverted: true,
            scale_inverted: true,
            current_inverted: false,
        });
        assert_eq!((normal.motor, normal.scale), (0, 0));
        for raw in 0..=u16::MAX {
            assert_eq!(counting_up(raw, normal.motor), raw);
            assert_eq!(counting_up(raw, inverted.motor), raw.wrapping_neg());
            assert_eq!(counting_up(raw, inverted.scale), raw.wrapping_neg());
        }
    }

    #[test]
    fn the_current_flip_is_the_frame_change() {
        for current_inverted in [false, true] {
            let p = Polarity {
                current_inverted,
                ..Polarity::NORMAL
            };
            let flip = CounterFlips::of(&p).current;
            // Every command the tick can make: within +-(2^31 - 1) bits.
            for bits in [
                i32::MIN + 1,
                -(1 << 23),
                -65536,
                -1,
                0,
                1,
                12345,
                1 << 23,
                i32::MAX,
            ]
            .into_iter()
            .chain((-70_000..70_000).step_by(7))
            {
                let a = I16F16::from_bits(bits);
                assert_eq!(flip_current(a, flip), p.current_frame(a), "{bits}");
            }
        }
    }
}
