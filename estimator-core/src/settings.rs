//! What a machine builder configures, as one record: the drive train's geometry, the travel and
//! the limits, polarity, gains, fault thresholds, the control rate and homing. Every field has a
//! key (its number on the link: its place among the [`ConfigField`]s, which is its place in
//! [`FIELDS`]), a name (the same name a refusal gives, e.g. `"pid.kp_a_per_mm"`) and a unit; values travel and are stored as `f64` in SI-like units.
//!
//! The model parameters are not here: they come with the calibration blob, which records the
//! geometry it was made for.

use crate::ConfigField;
use belt_link::bytes::{Fields, Reader, Short, Writer};
use belt_link::ModelKind;

use crate::drive::{
    DriveConfig, Models, Parts, PartsImage, Polarity, IMAGE_FIELD, PARTS_IMAGE_LEN,
};
use crate::rig::Rig;
use crate::{fault, pid, ConfigError};

/// The homing routine: a slow jog at reduced current towards a hard stop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HomingConfig {
    /// Towards the stop at negative travel (`false`) or positive travel (`true`).
    pub towards_positive: bool,
    /// Jog speed, mm/s.
    pub velocity_mm_s: f64,
    /// Current limit while jogging, amperes: enough to beat friction, small enough that pressing
    /// on the stop harms nothing.
    pub current_a: f64,
    /// The stop is found when the following error exceeds this, mm.
    pub detect_error_mm: f64,
    /// Position the stop is given, mm of travel.
    pub position_mm: f64,
    /// Distance to back off the stop after homing, mm (0 = stay).
    pub backoff_mm: f64,
}

impl HomingConfig {
    /// Towards negative travel at 10 mm/s and 1.5 A, found at 0.3 mm of following error (below
    /// the 1 mm fault limit), the stop at 0 mm, backing off 5 mm.
    pub const DEFAULT: HomingConfig = HomingConfig {
        towards_positive: false,
        velocity_mm_s: 10.0,
        current_a: 1.5,
        detect_error_mm: 0.3,
        position_mm: 0.0,
        backoff_mm: 5.0,
    };
}

/// The drive's whole configuration except the model parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Settings {
    /// Drive-train geometry.
    pub rig: Rig,
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// Lowest target, mm.
    pub travel_min_mm: f64,
    /// Highest target, mm.
    pub travel_max_mm: f64,
    /// Overshoot allowed before `TRAVEL_LIMIT`, mm.
    pub travel_margin_mm: f64,
    /// Fastest move, mm/s.
    pub max_velocity_mm_s: f64,
    /// Steepest acceleration, mm/s².
    pub max_accel_mm_s2: f64,
    /// Fastest believable motion between two samples, mm/s.
    pub encoder_max_speed_mm_s: f64,
    /// Wiring polarity.
    pub polarity: Polarity,
    /// Position-loop gains.
    pub pid: pid::Config,
    /// Fault thresholds.
    pub faults: fault::Config,
    /// Model active after boot.
    pub initial_model: ModelKind,
    /// Homing routine.
    pub homing: HomingConfig,
}

impl Settings {
    /// The paper's rig (Table 1) at 2 kHz, 0-300 mm of travel, Model 1 active, the default
    /// homing.
    pub const PAPER: Settings = Settings {
        rig: Rig::PAPER,
        rate_hz: 2000.0,
        travel_min_mm: 0.0,
        travel_max_mm: 300.0,
        travel_margin_mm: 5.0,
        max_velocity_mm_s: 250.0,
        max_accel_mm_s2: 5000.0,
        encoder_max_speed_mm_s: 1000.0,
        polarity: Polarity::NORMAL,
        pid: pid::Config::PAPER_RIG,
        faults: fault::Config::PAPER_RIG,
        initial_model: ModelKind::Linear,
        homing: HomingConfig::DEFAULT,
    };

    /// The drive configuration with these settings and `model`.
    pub fn drive_config<'a>(self, model: Models<'a>) -> DriveConfig<'a> {
        DriveConfig {
            settings: self,
            model,
        }
    }

    /// CRC-32 of the encoded record: what a configuration image is tied to.
    pub fn crc32(&self) -> u32 {
        RawSettings::of(self).crc32()
    }

    /// The configuration image of these settings for the drive ([`Parts::encode`]): built
    /// with `f64` arithmetic, so on the host; a refusal names the field.
    pub fn parts_image(&self) -> Result<PartsImage, ConfigError> {
        let parts = Parts::build(self)?;
        Ok(parts.encode(self.crc32()))
    }

    /// The value of field `key`, or `None` for an unknown key.
    pub fn get(&self, key: u8) -> Option<f64> {
        field(key).map(|f| (f.get)(self))
    }

    /// Sets field `key`; a value the field cannot hold (not finite, not a whole number where one
    /// is needed, out of its type's range) is refused by name and changes nothing. Whether the
    /// configuration as a whole makes sense is `Drive`'s check.
    pub fn set(&mut self, key: u8, value: f64) -> Result<(), SettingsError> {
        let f = field(key).ok_or(SettingsError::UnknownKey(key))?;
        if !value.is_finite() {
            return Err(SettingsError::Invalid(ConfigError::NotFinite(f.field)));
        }
        if !(value >= f.min && value <= f.max) || (f.whole && value != (value as i64) as f64) {
            return Err(SettingsError::Invalid(ConfigError::OutOfRange(f.field)));
        }
        (f.set)(self, value);
        Ok(())
    }

    /// The record's bytes: magic, version, field count, then `key, f64` pairs in key order.
    /// Returns the length ([`ENCODED_LEN`]).
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, Short> {
        RawSettings::of(self).encode(out)
    }

    /// Parses a record; every field must be present once and hold a valid value.
    pub fn decode(bytes: &[u8]) -> Result<Settings, SettingsError> {
        RawSettings::decode(bytes)?.settings()
    }
}

/// Fields in the record; their keys are `0..FIELD_COUNT` (tested).
pub const FIELD_COUNT: usize = FIELDS.len();

/// The settings as the drive holds them: each field's `f64` bits by key, stored and reported
/// but never interpreted. The drive runs on the configuration image built from them on the host
/// (no unit conversion, no float compare, no field table on the MCU); the host checks the
/// values ([`RawSettings::settings`]) when it builds the image, naming the field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RawSettings {
    bits: [u64; FIELD_COUNT],
}

impl RawSettings {
    /// The bits of `s`.
    pub fn of(s: &Settings) -> RawSettings {
        let mut bits = [0u64; FIELD_COUNT];
        for (b, f) in bits.iter_mut().zip(&FIELDS) {
            *b = (f.get)(s).to_bits();
        }
        RawSettings { bits }
    }

    /// The bits of field `key`, or `None` for an unknown key.
    pub fn get(&self, key: u8) -> Option<u64> {
        self.bits.get(key as usize).copied()
    }

    /// Stores the bits of field `key`, unchecked (see the type); an unknown key is refused and
    /// changes nothing.
    pub fn set(&mut self, key: u8, bits: u64) -> Result<(), SettingsError> {
        let b = self
            .bits
            .get_mut(key as usize)
            .ok_or(SettingsError::UnknownKey(key))?;
        *b = bits;
        Ok(())
    }

    /// The values as [`Settings`], each checked by its field (the first refused is named).
    pub fn settings(&self) -> Result<Settings, SettingsError> {
        let mut s = Settings::PAPER;
        for f in &FIELDS {
            s.set(f.key(), f64::from_bits(self.bits[f.key() as usize]))?;
        }
        Ok(s)
    }

    /// The record's bytes: magic, version, field count, then `key, f64` pairs in key order.
    /// Returns the length ([`ENCODED_LEN`]).
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, Short> {
        let mut w = Writer::new(out);
        w.put(&MAGIC);
        w.u16(VERSION);
        w.u16(FIELD_COUNT as u16);
        for (key, b) in self.bits.iter().enumerate() {
            w.u8(key as u8);
            w.u64(*b);
        }
        w.finish()
    }

    /// Parses a record's structure: magic, version, every key present once (the values are the
    /// host's to check, [`RawSettings::settings`]).
    pub fn decode(bytes: &[u8]) -> Result<RawSettings, SettingsError> {
        let mut r = Reader::new(bytes);
        let short = |_: Short| SettingsError::Truncated;
        if r.take::<4>().map_err(short)? != MAGIC {
            return Err(SettingsError::BadMagic);
        }
        let version = r.u16().map_err(short)?;
        if version != VERSION {
            return Err(SettingsError::UnsupportedVersion(version));
        }
        let n = r.u16().map_err(short)? as usize;
        if n != FIELD_COUNT || r.remaining() != n * 9 {
            return Err(SettingsError::Truncated);
        }
        let mut out = RawSettings {
            bits: [0; FIELD_COUNT],
        };
        let mut seen = [false; FIELD_COUNT];
        for _ in 0..n {
            let key = r.u8().map_err(short)?;
            let bits = r.u64().map_err(short)?;
            match seen.get_mut(key as usize) {
                Some(s) if !*s => *s = true,
                _ => return Err(SettingsError::UnknownKey(key)),
            }
            out.set(key, bits)?;
        }
        Ok(out)
    }

    /// CRC-32 of the encoded record: what a configuration image is tied to.
    pub fn crc32(&self) -> u32 {
        let mut buf = [0u8; ENCODED_LEN];
        match self.encode(&mut buf) {
            Ok(n) => belt_link::crc32(buf.get(..n).unwrap_or(&buf)),
            // Cannot happen: the buffer holds a record.
            Err(Short) => 0,
        }
    }
}

impl Default for Settings {
    fn default() -> Self {
        Settings::PAPER
    }
}

/// Record magic.
const MAGIC: [u8; 4] = *b"BDCF";
/// Record version: bump when a field changes meaning.
pub const VERSION: u16 = 1;
/// Length of an encoded record.
pub const ENCODED_LEN: usize = 8 + FIELDS.len() * 9;

/// The configuration part of a stored record: the settings record, then the configuration
/// image built from it (the drive boots from the image: no unit conversion on the MCU).
pub const STORED_LEN: usize = ENCODED_LEN + PARTS_IMAGE_LEN;

/// The stored form of `s` with its configuration image.
pub fn encode_stored(s: &RawSettings, parts: &PartsImage) -> [u8; STORED_LEN] {
    let mut out = [0u8; STORED_LEN];
    // Cannot be short: the buffer holds a record.
    let _ = s.encode(&mut out[..ENCODED_LEN]);
    out[ENCODED_LEN..].copy_from_slice(parts);
    out
}

/// Reads a stored configuration ([`encode_stored`]): the settings and the parts of the image,
/// which must have been built from exactly these settings (else [`IMAGE_FIELD`] is named). The
/// image itself is `bytes[ENCODED_LEN..]`.
pub fn decode_stored(bytes: &[u8]) -> Result<(RawSettings, Parts), SettingsError> {
    if bytes.len() != STORED_LEN {
        return Err(SettingsError::Truncated);
    }
    let (record, image) = bytes.split_at(ENCODED_LEN);
    let settings = RawSettings::decode(record)?;
    let (parts, settings_crc) = Parts::decode(image).map_err(SettingsError::Invalid)?;
    if settings_crc != belt_link::crc32(record) {
        return Err(SettingsError::Invalid(ConfigError::OutOfRange(IMAGE_FIELD)));
    }
    Ok((settings, parts))
}

/// Why a value or a record was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SettingsError {
    /// No field has this key.
    UnknownKey(u8),
    /// The value does not fit the field (named).
    Invalid(ConfigError),
    /// The record is shorter or longer than its field count says.
    Truncated,
    /// Not a settings record.
    BadMagic,
    /// A record of another version.
    UnsupportedVersion(u16),
}

impl core::fmt::Display for SettingsError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            SettingsError::UnknownKey(k) => write!(f, "no configuration field has key {k}"),
            SettingsError::Invalid(e) => write!(f, "{e}"),
            SettingsError::Truncated => f.write_str("settings record truncated or too long"),
            SettingsError::BadMagic => f.write_str("not a settings record (bad magic)"),
            SettingsError::UnsupportedVersion(v) => write!(f, "settings record version {v}"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for SettingsError {}

/// One configuration field.
pub struct Field {
    /// The field, as refusals name it.
    pub field: ConfigField,
    /// Its unit, for people.
    pub unit: &'static str,
    /// Smallest value the field's type holds.
    pub min: f64,
    /// Largest value the field's type holds.
    pub max: f64,
    /// The field holds a whole number (counts, flags, a model number).
    pub whole: bool,
    get: fn(&Settings) -> f64,
    set: fn(&mut Settings, f64),
}

impl Field {
    /// Its key on the link and in the record: the field's place among the `ConfigField`s.
    pub const fn key(&self) -> u8 {
        self.field as u8
    }

    /// Its name, as refusals give it.
    pub const fn name(&self) -> &'static str {
        self.field.name()
    }
}

/// The field with key `key` (the table is in key order, tested).
pub fn field(key: u8) -> Option<&'static Field> {
    FIELDS.get(key as usize)
}

/// The field named `name`.
pub fn field_named(name: &str) -> Option<&'static Field> {
    FIELDS.iter().find(|f| f.field.name() == name)
}

/// The key of the field a [`ConfigError`] names (0xff if none does).
pub fn key_of(e: &ConfigError) -> u8 {
    // The settings fields come first among the `ConfigField`s, in key order (tested).
    let k = e.field() as u8;
    if (k as usize) < FIELD_COUNT {
        k
    } else {
        0xff
    }
}

const INF: f64 = f64::INFINITY;

macro_rules! real {
    ($field:expr, $unit:expr, $($path:ident).+) => {
        Field {
            field: $field,
            unit: $unit,
            min: -INF,
            max: INF,
            whole: false,
            get: |s| s.$($path).+,
            set: |s, v| s.$($path).+ = v,
        }
    };
}

macro_rules! flag {
    ($field:expr, $($path:ident).+) => {
        Field {
            field: $field,
            unit: "0 or 1",
            min: 0.0,
            max: 1.0,
            whole: true,
            get: |s| s.$($path).+ as u8 as f64,
            set: |s, v| s.$($path).+ = v != 0.0,
        }
    };
}

/// Every field, in key order.
pub static FIELDS: [Field; 40] = TABLE;

const TABLE: [Field; 40] = [
    Field {
        field: ConfigField::RigEncoderLines,
        unit: "lines/rev",
        min: 1.0,
        max: (1u32 << 20) as f64,
        whole: true,
        get: |s| s.rig.encoder_lines as f64,
        set: |s, v| s.rig.encoder_lines = v as u32,
    },
    real!(
        ConfigField::RigGearRatio,
        "motor rev/pulley rev",
        rig.gear_ratio
    ),
    real!(ConfigField::RigBeltPitchMm, "mm", rig.belt_pitch_mm),
    Field {
        field: ConfigField::RigPulleyTeeth,
        unit: "teeth",
        min: 1.0,
        max: 1000.0,
        whole: true,
        get: |s| s.rig.pulley_teeth as f64,
        set: |s, v| s.rig.pulley_teeth = v as u32,
    },
    real!(ConfigField::DriveRateHz, "Hz", rate_hz),
    real!(ConfigField::DriveTravelMinMm, "mm", travel_min_mm),
    real!(ConfigField::DriveTravelMaxMm, "mm", travel_max_mm),
    real!(ConfigField::DriveTravelMarginMm, "mm", travel_margin_mm),
    real!(ConfigField::DriveMaxVelocityMmS, "mm/s", max_velocity_mm_s),
    real!(ConfigField::DriveMaxAccelMmS2, "mm/s^2", max_accel_mm_s2),
    real!(
        ConfigField::EncoderMaxSpeedMmS,
        "mm/s",
        encoder_max_speed_mm_s
    ),
    flag!(
        ConfigField::PolarityMotorEncoderInverted,
        polarity.motor_encoder_inverted
    ),
    flag!(ConfigField::PolarityScaleInverted, polarity.scale_inverted),
    flag!(
        ConfigField::PolarityCurrentInverted,
        polarity.current_inverted
    ),
    real!(ConfigField::PidKpAPerMm, "A/mm", pid.kp_a_per_mm),
    real!(ConfigField::PidKiAPerMmS, "A/(mm s)", pid.ki_a_per_mm_s),
    real!(ConfigField::PidKdASPerMm, "A s/mm", pid.kd_a_s_per_mm),
    real!(
        ConfigField::PidDerivativeCutoffHz,
        "Hz",
        pid.derivative_cutoff_hz
    ),
    real!(
        ConfigField::PidKffVelASPerMm,
        "A s/mm",
        pid.kff_vel_a_s_per_mm
    ),
    real!(
        ConfigField::PidKffAccAS2PerMm,
        "A s^2/mm",
        pid.kff_acc_a_s2_per_mm
    ),
    real!(ConfigField::PidMaxCurrentA, "A", pid.max_current_a),
    real!(
        ConfigField::FaultsFollowingErrorAtRestMm,
        "mm",
        faults.following_error_at_rest_mm
    ),
    real!(
        ConfigField::FaultsFollowingErrorAtMaxVelocityMm,
        "mm",
        faults.following_error_at_max_velocity_mm
    ),
    real!(
        ConfigField::FaultsStallCurrentA,
        "A",
        faults.stall_current_a
    ),
    real!(
        ConfigField::FaultsStallMotionMm,
        "mm",
        faults.stall_motion_mm
    ),
    real!(ConfigField::FaultsStallTimeS, "s", faults.stall_time_s),
    real!(
        ConfigField::FaultsRunawayCurrentA,
        "A",
        faults.runaway_current_a
    ),
    real!(
        ConfigField::FaultsRunawaySpeedMmS,
        "mm/s",
        faults.runaway_speed_mm_s
    ),
    real!(ConfigField::FaultsRunawayTimeS, "s", faults.runaway_time_s),
    real!(
        ConfigField::FaultsOverspeedRatio,
        "x max velocity",
        faults.overspeed_ratio
    ),
    real!(
        ConfigField::FaultsOverspeedTimeS,
        "s",
        faults.overspeed_time_s
    ),
    real!(
        ConfigField::FaultsSaturationTimeS,
        "s",
        faults.saturation_time_s
    ),
    real!(
        ConfigField::FaultsLinkTimeoutS,
        "s (0 = off)",
        faults.link_timeout_s
    ),
    Field {
        field: ConfigField::DriveInitialModel,
        unit: "0 none, 1-3 Models 1-3, 4 backlash, 5 bidirectional table, 6 Model 4",
        min: 0.0,
        max: (ModelKind::ALL.len() - 1) as f64,
        whole: true,
        get: |s| s.initial_model as u8 as f64,
        set: |s, v| s.initial_model = ModelKind::from_u8(v as u8).unwrap_or_default(),
    },
    flag!(ConfigField::HomingTowardsPositive, homing.towards_positive),
    real!(ConfigField::HomingVelocityMmS, "mm/s", homing.velocity_mm_s),
    real!(ConfigField::HomingCurrentA, "A", homing.current_a),
    real!(
        ConfigField::HomingDetectErrorMm,
        "mm",
        homing.detect_error_mm
    ),
    real!(ConfigField::HomingPositionMm, "mm", homing.position_mm),
    real!(ConfigField::HomingBackoffMm, "mm", homing.backoff_mm),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_their_index_and_names_unique() {
        for (i, f) in FIELDS.iter().enumerate() {
            // The table in `ConfigField` order: a field's key is its index here.
            assert_eq!(f.key() as usize, i, "{}", f.name());
            assert_eq!(key_of(&ConfigError::OutOfRange(f.field)), f.key());
            assert_eq!(field_named(f.name()).map(|g| g.key()), Some(f.key()));
        }
        // Every other field is no settings key.
        for f in &ConfigField::ALL[FIELD_COUNT..] {
            assert_eq!(key_of(&ConfigError::OutOfRange(*f)), 0xff, "{f}");
        }
    }

    #[test]
    fn the_paper_drive_keeps_its_defaults() {
        // What every simulation and test built on `DriveConfig::paper_rig` had before the
        // settings became its field list: the default homing, Model 1 at start, 2 kHz.
        let s = DriveConfig::paper_rig().settings;
        assert_eq!(s.homing, HomingConfig::DEFAULT);
        assert_eq!(s.initial_model, ModelKind::Linear);
        assert_eq!(s.rate_hz, 2000.0);
        assert_eq!(s.rig, Rig::PAPER);
    }

    #[test]
    fn every_field_round_trips_through_get_set_and_the_record() {
        let mut s = Settings::PAPER;
        for f in &FIELDS {
            let v = s.get(f.key()).unwrap();
            let new = if f.whole {
                if v + 1.0 <= f.max {
                    v + 1.0
                } else {
                    v - 1.0
                }
            } else {
                v * 1.5 + 0.25
            };
            s.set(f.key(), new).unwrap();
            assert_eq!(s.get(f.key()), Some(new), "{}", f.name());
        }
        let mut buf = [0u8; ENCODED_LEN];
        assert_eq!(s.encode(&mut buf), Ok(ENCODED_LEN));
        assert_eq!(Settings::decode(&buf), Ok(s));
    }

    #[test]
    fn raw_settings_hold_any_bits_and_the_host_names_the_bad_field() {
        let mut raw = RawSettings::of(&Settings::PAPER);
        assert_eq!(raw.settings(), Ok(Settings::PAPER));
        // The drive stores what it is sent (it runs on the image, not on these)...
        raw.set(1, f64::NAN.to_bits()).unwrap();
        assert_eq!(raw.get(1), Some(f64::NAN.to_bits()));
        assert_eq!(
            raw.set(FIELD_COUNT as u8, 0),
            Err(SettingsError::UnknownKey(40))
        );
        assert_eq!(raw.get(FIELD_COUNT as u8), None);
        // ...the record keeps the bits exactly...
        let mut buf = [0u8; ENCODED_LEN];
        assert_eq!(raw.encode(&mut buf), Ok(ENCODED_LEN));
        assert_eq!(RawSettings::decode(&buf), Ok(raw));
        // ...and the host's check names the field.
        assert_eq!(
            raw.settings(),
            Err(SettingsError::Invalid(ConfigError::NotFinite(
                ConfigField::RigGearRatio
            )))
        );
        // The same bytes as the checked record.
        let mut checked = [0u8; ENCODED_LEN];
        Settings::PAPER.encode(&mut checked).unwrap();
        let mut raw_bytes = [0u8; ENCODED_LEN];
        RawSettings::of(&Settings::PAPER)
            .encode(&mut raw_bytes)
            .unwrap();
        assert_eq!(checked, raw_bytes);
        // Structure refusals: a key out of range, a key twice.
        let mut bad = raw_bytes;
        bad[8] = FIELD_COUNT as u8;
        assert_eq!(
            RawSettings::decode(&bad),
            Err(SettingsError::UnknownKey(40))
        );
        let mut bad = raw_bytes;
        bad[8 + 9] = 0;
        assert_eq!(RawSettings::decode(&bad), Err(SettingsError::UnknownKey(0)));
    }

    #[test]
    fn bad_values_and_records_are_refused_by_name() {
        let mut s = Settings::PAPER;
        let e = |r: Result<(), SettingsError>| match r {
            Err(SettingsError::Invalid(e)) => e.field(),
            other => panic!("{other:?}"),
        };
        assert_eq!(e(s.set(0, 0.0)), ConfigField::RigEncoderLines);
        assert_eq!(e(s.set(0, 1.5)), ConfigField::RigEncoderLines);
        assert_eq!(e(s.set(1, f64::NAN)), ConfigField::RigGearRatio);
        assert_eq!(e(s.set(11, 2.0)), ConfigField::PolarityMotorEncoderInverted);
        assert_eq!(e(s.set(33, 7.0)), ConfigField::DriveInitialModel);
        assert_eq!(s.set(200, 1.0), Err(SettingsError::UnknownKey(200)));
        assert_eq!(s, Settings::PAPER, "refused values change nothing");

        let mut buf = [0u8; ENCODED_LEN];
        Settings::PAPER.encode(&mut buf).unwrap();
        assert_eq!(
            Settings::decode(&buf[..ENCODED_LEN - 1]),
            Err(SettingsError::Truncated)
        );
        let mut bad = buf;
        bad[0] ^= 1;
        assert_eq!(Settings::decode(&bad), Err(SettingsError::BadMagic));
        let mut bad = buf;
        bad[8 + 9] = 0; // the second pair's key repeats the first's
        assert_eq!(Settings::decode(&bad), Err(SettingsError::UnknownKey(0)));
        let mut bad = buf;
        bad[9..17].copy_from_slice(&f64::NAN.to_bits().to_le_bytes());
        assert!(matches!(
            Settings::decode(&bad),
            Err(SettingsError::Invalid(ConfigError::NotFinite(
                ConfigField::RigEncoderLines
            )))
        ));
    }
}
