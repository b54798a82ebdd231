//! The configuration image: a [`Parts`] as bytes. The host builds it from the SI settings
//! ([`Parts::build`], `f64`); the drive reads it back with integer checks only, so no
//! soft-float configuration code is linked into the firmware.
//!
//! Layout (little endian, [`PARTS_IMAGE_LEN`] bytes): magic `BDPI`, version, the CRC-32 of the
//! settings record it was built from (the drive refuses an image built from other settings), the
//! geometry, the rate, the integer limits, the encoders' step limits, the profile's limits, the
//! move scale, the loop gains, the fault thresholds, polarity, homing, the status scale, the
//! initial model, then the CRC-32 of everything before it.

use crate::ConfigField;
use belt_link::bytes::{Fields, Reader, Short, Writer};
use belt_link::ModelKind;
use fixed::types::{I16F16, I40F24};

use super::{um_to_counts_q32, HomingCoeffs, Limits, MoveScale, Parts, Polarity};
use crate::rig::Rig;
use crate::trajectory::{self, Trajectory};
use crate::{encoder, fault, pid, ConfigError};

const MAGIC: [u8; 4] = *b"BDPI";
/// Bump when a field changes meaning.
pub const PARTS_IMAGE_VERSION: u16 = 1;
/// Length of a configuration image, bytes.
pub const PARTS_IMAGE_LEN: usize = 229;
/// A configuration image.
pub type PartsImage = [u8; PARTS_IMAGE_LEN];

/// The image as a whole: its length, magic, version or CRC (not a field of it).
pub const IMAGE_FIELD: ConfigField = ConfigField::ConfigImage;

/// Slack where the image's integer checks meet values the host rounded differently (travel ends
/// and homing positions truncated to whole micrometres, then to counts): 2 um and 2 counts.
const ROUNDING_SLACK_UM: i32 = 2;
const ROUNDING_SLACK_COUNTS: i64 = 2;

impl Parts {
    /// The control rate, whole hertz.
    pub fn rate_hz(&self) -> u32 {
        self.rate_hz
    }

    /// The loop's current limit.
    pub fn max_current_a(&self) -> I16F16 {
        self.pid.max_current_a()
    }

    /// The model selected after the configuration is installed.
    pub fn initial_model(&self) -> ModelKind {
        self.initial_model
    }

    /// The image of these parts, tied to the settings record whose CRC-32 is `settings_crc`.
    pub fn encode(&self, settings_crc: u32) -> PartsImage {
        let mut out = [0u8; PARTS_IMAGE_LEN];
        let mut w = Writer::new(&mut out);
        w.put(&MAGIC);
        w.u16(PARTS_IMAGE_VERSION);
        w.u32(settings_crc);
        w.u32(self.rig.encoder_lines);
        w.u64(self.rig.gear_ratio.to_bits());
        w.u64(self.rig.belt_pitch_mm.to_bits());
        w.u32(self.rig.pulley_teeth);
        w.u32(self.rate_hz);
        let l = &self.limits;
        w.u64(l.counts_per_um_q32 as u64);
        w.i32(l.target_min_counts);
        w.i32(l.target_max_counts);
        w.i32(l.fault_min_counts);
        w.i32(l.fault_max_counts);
        w.u32(l.max_velocity_um_s);
        w.u32(l.max_accel_um_s2);
        w.u32(self.motor.max_delta_counts());
        w.u32(self.scale.max_delta_counts());
        let t = self.trajectory.coeffs();
        w.u64(t.velocity_counts_per_tick().to_bits() as u64);
        w.u32(t.acceleration_counts_per_tick2().to_bits() as u32);
        w.u32(t.deceleration_counts_per_tick2().to_bits() as u32);
        w.u64(self.move_scale.velocity_bits_per_um_s_q32);
        w.u64(self.move_scale.accel_bits_per_um_s2_q32);
        for b in self.pid.to_bits() {
            w.i32(b);
        }
        for v in self.monitor.to_words() {
            w.u32(v);
        }
        let p = &self.polarity;
        w.u8(p.motor_encoder_inverted as u8
            | (p.scale_inverted as u8) << 1
            | (p.current_inverted as u8) << 2);
        let h = &self.homing;
        w.u8(h.towards_positive as u8);
        w.u32(h.velocity_um_s);
        w.u32(h.accel_um_s2);
        w.i32(h.current_limit_a.to_bits());
        w.u32(h.detect_counts);
        w.i32(h.position_um);
        w.i32(h.backoff_um);
        w.i32(h.search_counts);
        w.u64(self.um_per_count_q32 as u64);
        w.u8(self.initial_model as u8);
        let n = w.len();
        let crc = belt_link::crc32(&out[..n]);
        Writer::at(&mut out, n).u32(crc);
        out
    }

    /// Reads an image with integer checks only: the CRC, then every field against the ranges
    /// [`Parts::build`] gives (a refusal names the SI field, or [`IMAGE_FIELD`]). Returns the
    /// parts and the CRC-32 of the settings record they were built from.
    pub fn decode(bytes: &[u8]) -> Result<(Parts, u32), ConfigError> {
        let whole = ConfigError::OutOfRange(IMAGE_FIELD);
        if bytes.len() != PARTS_IMAGE_LEN {
            return Err(whole);
        }
        let (body, crc) = bytes.split_at(PARTS_IMAGE_LEN - 4);
        if belt_link::crc32(body).to_le_bytes() != crc {
            return Err(whole);
        }
        Self::read(&mut Reader::new(body)).map_err(|e| e.unwrap_or(whole))
    }

    /// The fields of a CRC-checked image; `Err(None)` for the image as a whole.
    fn read(r: &mut Reader) -> Result<(Parts, u32), Option<ConfigError>> {
        use ConfigError::OutOfRange as Bad;
        let short = |_: Short| None;
        let check = |ok: bool, field: ConfigField| if ok { Ok(()) } else { Err(Some(Bad(field))) };
        if r.take::<4>().map_err(short)? != MAGIC || r.u16().map_err(short)? != PARTS_IMAGE_VERSION
        {
            return Err(None);
        }
        let settings_crc = r.u32().map_err(short)?;
        let rig = Rig {
            encoder_lines: r.u32().map_err(short)?,
            gear_ratio: f64::from_bits(r.u64().map_err(short)?),
            belt_pitch_mm: f64::from_bits(r.u64().map_err(short)?),
            pulley_teeth: r.u32().map_err(short)?,
        };
        // The geometry's own check, float-free (its doubles on their bits).
        rig.validate().map_err(Some)?;
        let rate_hz = r.u32().map_err(short)?;
        check(crate::RATE_HZ.contains(&rate_hz), ConfigField::DriveRateHz)?;

        let limits = Limits {
            counts_per_um_q32: r.u64().map_err(short)? as i64,
            target_min_counts: r.i32().map_err(short)?,
            target_max_counts: r.i32().map_err(short)?,
            fault_min_counts: r.i32().map_err(short)?,
            fault_max_counts: r.i32().map_err(short)?,
            max_velocity_um_s: r.u32().map_err(short)?,
            max_accel_um_s2: r.u32().map_err(short)?,
        };
        check(limits.counts_per_um_q32 > 0, ConfigField::RigGearRatio)?;
        check(
            limits.target_min_counts < limits.target_max_counts,
            ConfigField::DriveTravelMaxMm,
        )?;
        // `a <= b` but for rounding.
        let tol = um_to_counts_q32(ROUNDING_SLACK_UM, 0, limits.counts_per_um_q32) as i64
            + ROUNDING_SLACK_COUNTS;
        let slack = |a: i32, b: i32| a as i64 <= b as i64 + tol;
        // The margin is not negative: the fault band holds the targets, and is a band (strictly,
        // not within the rounding slack: an inverted band would trip `travel_limit` everywhere).
        check(
            slack(limits.fault_min_counts, limits.target_min_counts)
                && slack(limits.target_max_counts, limits.fault_max_counts)
                && limits.fault_min_counts <= limits.fault_max_counts,
            ConfigField::DriveTravelMarginMm,
        )?;
        check(
            limits.max_velocity_um_s > 0,
            ConfigField::DriveMaxVelocityMmS,
        )?;
        check(limits.max_accel_um_s2 > 0, ConfigField::DriveMaxAccelMmS2)?;

        let step = |v: u32| {
            encoder::Coeffs::<u16>::from_max_delta_counts(v)
                .map_err(|_| Some(Bad(ConfigField::EncoderMaxSpeedMmS)))
        };
        let motor = step(r.u32().map_err(short)?)?;
        let scale = step(r.u32().map_err(short)?)?;

        let (v, a, d) = (
            r.u64().map_err(short)?,
            r.u32().map_err(short)?,
            r.u32().map_err(short)?,
        );
        let grid = |bits: u64| I40F24::from_bits(bits.min(i64::MAX as u64) as i64);
        let coeffs = trajectory::Coeffs::new(grid(v), grid(a as u64), grid(d as u64))
            .map_err(|e| Some(remap_trajectory(e)))?;
        let move_scale = MoveScale {
            velocity_bits_per_um_s_q32: r.u64().map_err(short)?,
            accel_bits_per_um_s2_q32: r.u64().map_err(short)?,
        };
        check(
            move_scale.velocity_bits_per_um_s_q32 > 0,
            ConfigField::DriveMaxVelocityMmS,
        )?;
        check(
            move_scale.accel_bits_per_um_s2_q32 > 0,
            ConfigField::DriveMaxAccelMmS2,
        )?;

        let mut gains = [0i32; 7];
        for g in &mut gains {
            *g = r.i32().map_err(short)?;
        }
        let pid = pid::Coeffs::from_bits(gains).map_err(Some)?;
        let mut words = [0u32; 12];
        for w in &mut words {
            *w = r.u32().map_err(short)?;
        }
        let monitor = fault::Coeffs::from_words(words).map_err(Some)?;

        let flags = r.u8().map_err(short)?;
        check(flags < 8, ConfigField::Polarity)?;
        let polarity = Polarity {
            motor_encoder_inverted: flags & 1 != 0,
            scale_inverted: flags & 2 != 0,
            current_inverted: flags & 4 != 0,
        };

        let towards = r.u8().map_err(short)?;
        check(towards < 2, ConfigField::HomingTowardsPositive)?;
        let homing = HomingCoeffs {
            towards_positive: towards == 1,
            velocity_um_s: r.u32().map_err(short)?,
            accel_um_s2: r.u32().map_err(short)?,
            current_limit_a: I16F16::from_bits(r.i32().map_err(short)?),
            detect_counts: r.u32().map_err(short)?,
            position_um: r.i32().map_err(short)?,
            backoff_um: r.i32().map_err(short)?,
            search_counts: r.i32().map_err(short)?,
        };
        check(
            (1..=limits.max_velocity_um_s).contains(&homing.velocity_um_s),
            ConfigField::HomingVelocityMmS,
        )?;
        check(
            (1..=limits.max_accel_um_s2).contains(&homing.accel_um_s2),
            ConfigField::HomingVelocityMmS,
        )?;
        check(
            homing.current_limit_a > 0 && homing.current_limit_a <= pid.max_current_a(),
            ConfigField::HomingCurrentA,
        )?;
        check(
            homing.detect_counts <= monitor.following_error_at_rest_counts(),
            ConfigField::HomingDetectErrorMm,
        )?;
        let counts = |um: i32| um_to_counts_q32(um, 0, limits.counts_per_um_q32);
        let within = |c: i32, lo: i32, hi: i32| slack(lo, c) && slack(c, hi);
        let home = counts(homing.position_um);
        check(
            within(home, limits.fault_min_counts, limits.fault_max_counts),
            ConfigField::HomingPositionMm,
        )?;
        let away = if homing.towards_positive {
            homing.position_um as i64 - homing.backoff_um as i64
        } else {
            homing.position_um as i64 + homing.backoff_um as i64
        };
        check(
            homing.backoff_um >= 0
                && i32::try_from(away).is_ok_and(|um| {
                    within(
                        counts(um),
                        limits.target_min_counts,
                        limits.target_max_counts,
                    )
                }),
            ConfigField::HomingBackoffMm,
        )?;
        check(homing.search_counts > 0, ConfigField::DriveTravelMaxMm)?;

        let um_per_count_q32 = r.u64().map_err(short)? as i64;
        check(um_per_count_q32 > 0, ConfigField::RigGearRatio)?;
        let initial_model = ModelKind::from_u8(r.u8().map_err(short)?)
            .ok_or(Some(Bad(ConfigField::DriveInitialModel)))?;
        if r.remaining() != 0 {
            return Err(None);
        }
        Ok((
            Parts {
                rig,
                rate_hz,
                limits,
                motor,
                scale,
                trajectory: Trajectory::new(coeffs, 0),
                move_scale,
                pid,
                monitor,
                polarity,
                homing,
                um_per_count_q32,
                initial_model,
            },
            settings_crc,
        ))
    }
}

/// The profile's refusals name the drive's limits, which the start profile is built from.
fn remap_trajectory(e: ConfigError) -> ConfigError {
    ConfigError::OutOfRange(match e.field() {
        ConfigField::TrajectoryVelocityMmS => ConfigField::DriveMaxVelocityMmS,
        _ => ConfigField::DriveMaxAccelMmS2,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::DriveConfig;
    use crate::settings::Settings;

    fn paper() -> Parts {
        Parts::build(&Settings::PAPER).unwrap()
    }

    /// The image with `edit` applied to its body and the CRC made valid again: what a buggy
    /// or hostile host could send.
    fn edited(image: &PartsImage, at: usize, bytes: &[u8]) -> PartsImage {
        let mut out = *image;
        out[at..at + bytes.len()].copy_from_slice(bytes);
        let crc = belt_link::crc32(&out[..PARTS_IMAGE_LEN - 4]);
        out[PARTS_IMAGE_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
        out
    }

    #[test]
    fn round_trip_is_exact() {
        let p = paper();
        let image = p.encode(0x1234_5678);
        let (back, crc) = Parts::decode(&image).unwrap();
        assert_eq!(crc, 0x1234_5678);
        assert_eq!(back, p);
    }

    #[test]
    fn paper_settings_image_matches_the_drive_config() {
        let image = Settings::PAPER.parts_image().unwrap();
        let (p, crc) = Parts::decode(&image).unwrap();
        assert_eq!(crc, Settings::PAPER.crc32());
        assert_eq!(p, Parts::build(&DriveConfig::paper_rig().settings).unwrap());
    }

    #[test]
    fn damage_and_wrong_lengths_are_refused_as_a_whole() {
        let image = paper().encode(7);
        for i in 0..PARTS_IMAGE_LEN {
            let mut bad = image;
            bad[i] ^= 0x10;
            assert_eq!(
                Parts::decode(&bad).unwrap_err(),
                ConfigError::OutOfRange(IMAGE_FIELD),
                "byte {i}"
            );
        }
        assert!(Parts::decode(&image[..PARTS_IMAGE_LEN - 1]).is_err());
        assert!(Parts::decode(&[]).is_err());
        // Another version, CRC intact.
        let v = edited(&image, 4, &(PARTS_IMAGE_VERSION + 1).to_le_bytes());
        assert_eq!(
            Parts::decode(&v).unwrap_err(),
            ConfigError::OutOfRange(IMAGE_FIELD)
        );
    }

    /// Offsets of a few fields in the layout (see the module's doc).
    const RATE: usize = 10 + 24;
    const LIMITS: usize = RATE + 4;
    const PID: usize = LIMITS + 32 + 8 + 16 + 16;
    const FAULTS: usize = PID + 28;
    const HOMING: usize = FAULTS + 48 + 1;

    #[test]
    fn fields_out_of_range_are_refused_by_name() {
        let image = paper().encode(7);
        let cases: &[(usize, &[u8], ConfigField)] = &[
            (10, &0u32.to_le_bytes(), ConfigField::RigEncoderLines),
            (
                14,
                &f64::NAN.to_bits().to_le_bytes(),
                ConfigField::RigGearRatio,
            ),
            (
                14,
                &(-2.0f64).to_bits().to_le_bytes(),
                ConfigField::RigGearRatio,
            ),
            (
                22,
                &f64::INFINITY.to_bits().to_le_bytes(),
                ConfigField::RigBeltPitchMm,
            ),
            (RATE, &99u32.to_le_bytes(), ConfigField::DriveRateHz),
            // Target max below target min.
            (
                LIMITS + 12,
                &i32::MIN.to_le_bytes(),
                ConfigField::DriveTravelMaxMm,
            ),
            // A fault band turned inside out by less than the rounding slack: min and max of
            // travel 0..1 count, fault band 1..0.
            (
                LIMITS + 8,
                &[0i32, 1, 1, 0]
                    .iter()
                    .flat_map(|v| v.to_le_bytes())
                    .collect::<Vec<u8>>(),
                ConfigField::DriveTravelMarginMm,
            ),
            (
                LIMITS + 24,
                &0u32.to_le_bytes(),
                ConfigField::DriveMaxVelocityMmS,
            ),
            (
                LIMITS + 28,
                &0u32.to_le_bytes(),
                ConfigField::DriveMaxAccelMmS2,
            ),
            (
                LIMITS + 32,
                &0u32.to_le_bytes(),
                ConfigField::EncoderMaxSpeedMmS,
            ),
            (
                LIMITS + 32,
                &40_000u32.to_le_bytes(),
                ConfigField::EncoderMaxSpeedMmS,
            ),
            (
                LIMITS + 40,
                &0u64.to_le_bytes(),
                ConfigField::DriveMaxVelocityMmS,
            ),
            (
                LIMITS + 48,
                &0u32.to_le_bytes(),
                ConfigField::DriveMaxAccelMmS2,
            ),
            (
                LIMITS + 56,
                &0u64.to_le_bytes(),
                ConfigField::DriveMaxVelocityMmS,
            ),
            (PID, &(1i32 << 24).to_le_bytes(), ConfigField::PidKpAPerMm),
            (PID, &(-1i32).to_le_bytes(), ConfigField::PidKpAPerMm),
            (
                PID + 12,
                &0i32.to_le_bytes(),
                ConfigField::PidDerivativeCutoffHz,
            ),
            (
                PID + 24,
                &(128i32 << 16).to_le_bytes(),
                ConfigField::PidMaxCurrentA,
            ),
            (
                FAULTS + 4,
                &(1u32 << 17).to_le_bytes(),
                ConfigField::FaultsFollowingErrorAtMaxVelocityMm,
            ),
            (
                FAULTS + 16,
                &0u32.to_le_bytes(),
                ConfigField::FaultsStallTimeS,
            ),
            (
                FAULTS + 44,
                &u32::MAX.to_le_bytes(),
                ConfigField::FaultsLinkTimeoutS,
            ),
            (HOMING - 1, &[8], ConfigField::Polarity),
            (HOMING, &[2], ConfigField::HomingTowardsPositive),
            (
                HOMING + 1,
                &0u32.to_le_bytes(),
                ConfigField::HomingVelocityMmS,
            ),
            (
                HOMING + 1,
                &u32::MAX.to_le_bytes(),
                ConfigField::HomingVelocityMmS,
            ),
            (
                HOMING + 9,
                &(100i32 << 16).to_le_bytes(),
                ConfigField::HomingCurrentA,
            ),
            (
                HOMING + 17,
                &i32::MAX.to_le_bytes(),
                ConfigField::HomingPositionMm,
            ),
            (
                HOMING + 21,
                &(-1i32).to_le_bytes(),
                ConfigField::HomingBackoffMm,
            ),
            (
                HOMING + 21,
                &400_000i32.to_le_bytes(),
                ConfigField::HomingBackoffMm,
            ),
            (
                HOMING + 25,
                &0i32.to_le_bytes(),
                ConfigField::DriveTravelMaxMm,
            ),
            (PARTS_IMAGE_LEN - 5, &[200], ConfigField::DriveInitialModel),
        ];
        for &(at, bytes, field) in cases {
            let bad = edited(&image, at, bytes);
            assert_eq!(
                Parts::decode(&bad).map(|_| ()).unwrap_err().field(),
                field,
                "at {at}"
            );
        }
    }

    use proptest::prelude::*;

    /// Settings around the paper rig's, across geometries, rates, limits, gains and homing.
    fn settings() -> impl Strategy<Value = Settings> {
        (
            (100u32..20_000, 1.0f64..60.0, 2.0f64..12.0, 10u32..80),
            (500u32..20_000, 50.0f64..600.0, 0.0f64..20.0),
            (10.0f64..800.0, 100.0f64..20_000.0),
            (0.1f64..4.0, 0.0f64..3.0, 0.5f64..20.0),
            (0.05f64..3.0, 0.0f64..0.5, any::<bool>(), 0.0f64..20.0),
            (0u8..3, 0.0f64..2.0, 0.0f64..5.0),
        )
            .prop_map(|(rig, rate, lim, gains, homing, misc)| {
                let mut s = Settings::PAPER;
                s.rig.encoder_lines = rig.0;
                s.rig.gear_ratio = rig.1;
                s.rig.belt_pitch_mm = rig.2;
                s.rig.pulley_teeth = rig.3;
                s.rate_hz = rate.0 as f64;
                s.travel_max_mm = rate.1;
                s.travel_margin_mm = rate.2;
                s.max_velocity_mm_s = lim.0;
                s.max_accel_mm_s2 = lim.1;
                s.pid.kp_a_per_mm *= gains.0;
                s.pid.kd_a_s_per_mm *= gains.1;
                s.pid.max_current_a = gains.2;
                s.homing.velocity_mm_s = homing.0 * 10.0;
                s.homing.current_a = homing.1 + 0.1;
                s.homing.towards_positive = homing.2;
                s.homing.backoff_mm = homing.3;
                if homing.2 {
                    s.homing.position_mm = s.travel_max_mm;
                }
                s.initial_model = crate::model::ModelKind::from_u8(misc.0).unwrap();
                s.faults.link_timeout_s = misc.1;
                s.faults.stall_time_s = misc.2;
                s
            })
    }

    // Measured once with counters: about 80 % of these settings build (the rest are refused
    // by `build`, e.g. a rate too slow for the speed), and about 30 % of the edited images are
    // accepted and driven.
    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        /// What the host builds, the drive accepts, bit for bit.
        #[test]
        fn every_built_image_is_accepted_unchanged(s in settings()) {
            if let Ok(p) = Parts::build(&s) {
                let image = s.parts_image().unwrap();
                let (back, crc) = Parts::decode(&image).unwrap();
                prop_assert_eq!(crc, s.crc32());
                prop_assert_eq!(back, p);
            }
        }

        /// Any edited image (CRC made valid again) is refused or accepted, never a panic; an
        /// accepted one drives without panicking either.
        #[test]
        fn edited_images_never_panic(
            at in 10usize..PARTS_IMAGE_LEN - 4,
            bytes in proptest::collection::vec(any::<u8>(), 1..9),
            samples in proptest::collection::vec(any::<(u16, u16)>(), 1..40),
            target_um in any::<i32>(),
        ) {
            let image = paper().encode(0);
            let n = bytes.len().min(PARTS_IMAGE_LEN - 4 - at);
            let bad = edited(&image, at, &bytes[..n]);
            if let Ok((p, _)) = Parts::decode(&bad) {
                let mut slot = core::mem::MaybeUninit::uninit();
                let d = crate::drive::Drive::from_parts_in(&mut slot, p, &[]);
                if let Ok(d) = d {
                    let _ = d.command(crate::drive::Command::Enable);
                    let _ = d.command(crate::drive::Command::Homing);
                    let _ = d.command(crate::drive::Command::MoveTo {
                        target_um,
                        velocity_um_s: 100_000,
                        accel_um_s2: 1_000_000,
                    });
                    for (m, sc) in samples {
                        d.step(crate::drive::Sample {
                            motor_counter: m,
                            scale_counter: sc,
                        });
                    }
                }
            }
        }
    }
}
