//! The fields a refusal names: one list, each with its dotted name as the host spells it
//! (`"pid.kp_a_per_mm"`). Errors carry the one-byte [`ConfigField`] rather than a string, so
//! the firmware holds no name table: its logs name the field through defmt's interned strings
//! (feature `defmt`), which stay on the host. The first [`crate::settings::FIELD_COUNT`]
//! fields are the settings record's, in key order: their discriminant is the key on the link
//! and in the record, so new fields go after them.

macro_rules! config_fields {
    ($($variant:ident = $name:literal,)*) => {
        /// A configuration or calibration field, as refusals name it.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        #[repr(u8)]
        pub enum ConfigField {
            $(
                #[doc = concat!("`", $name, "`")]
                $variant,
            )*
        }

        impl ConfigField {
            /// Every field, by discriminant.
            pub const ALL: &'static [ConfigField] = &[$(ConfigField::$variant,)*];

            /// The dotted name, e.g. `"pid.kp_a_per_mm"`.
            pub const fn name(self) -> &'static str {
                match self {
                    $(ConfigField::$variant => $name,)*
                }
            }

            /// The name as a defmt interned string: an index into the log's table on the host,
            /// two bytes on the drive.
            #[cfg(feature = "defmt")]
            pub fn istr(self) -> defmt::Str {
                match self {
                    $(ConfigField::$variant => defmt::intern!($name),)*
                }
            }
        }
    };
}

config_fields! {
    RigEncoderLines = "rig.encoder_lines",
    RigGearRatio = "rig.gear_ratio",
    RigBeltPitchMm = "rig.belt_pitch_mm",
    RigPulleyTeeth = "rig.pulley_teeth",
    DriveRateHz = "drive.rate_hz",
    DriveTravelMinMm = "drive.travel_min_mm",
    DriveTravelMaxMm = "drive.travel_max_mm",
    DriveTravelMarginMm = "drive.travel_margin_mm",
    DriveMaxVelocityMmS = "drive.max_velocity_mm_s",
    DriveMaxAccelMmS2 = "drive.max_accel_mm_s2",
    EncoderMaxSpeedMmS = "encoder.max_speed_mm_s",
    PolarityMotorEncoderInverted = "polarity.motor_encoder_inverted",
    PolarityScaleInverted = "polarity.scale_inverted",
    PolarityCurrentInverted = "polarity.current_inverted",
    PidKpAPerMm = "pid.kp_a_per_mm",
    PidKiAPerMmS = "pid.ki_a_per_mm_s",
    PidKdASPerMm = "pid.kd_a_s_per_mm",
    PidDerivativeCutoffHz = "pid.derivative_cutoff_hz",
    PidKffVelASPerMm = "pid.kff_vel_a_s_per_mm",
    PidKffAccAS2PerMm = "pid.kff_acc_a_s2_per_mm",
    PidMaxCurrentA = "pid.max_current_a",
    FaultsFollowingErrorAtRestMm = "faults.following_error_at_rest_mm",
    FaultsFollowingErrorAtMaxVelocityMm = "faults.following_error_at_max_velocity_mm",
    FaultsStallCurrentA = "faults.stall_current_a",
    FaultsStallMotionMm = "faults.stall_motion_mm",
    FaultsStallTimeS = "faults.stall_time_s",
    FaultsRunawayCurrentA = "faults.runaway_current_a",
    FaultsRunawaySpeedMmS = "faults.runaway_speed_mm_s",
    FaultsRunawayTimeS = "faults.runaway_time_s",
    FaultsOverspeedRatio = "faults.overspeed_ratio",
    FaultsOverspeedTimeS = "faults.overspeed_time_s",
    FaultsSaturationTimeS = "faults.saturation_time_s",
    FaultsLinkTimeoutS = "faults.link_timeout_s",
    DriveInitialModel = "drive.initial_model",
    HomingTowardsPositive = "homing.towards_positive",
    HomingVelocityMmS = "homing.velocity_mm_s",
    HomingCurrentA = "homing.current_a",
    HomingDetectErrorMm = "homing.detect_error_mm",
    HomingPositionMm = "homing.position_mm",
    HomingBackoffMm = "homing.backoff_mm",
    BacklashBacklashUm = "backlash.backlash_um",
    BacklashOffsetUm = "backlash.offset_um",
    BidirTableForwardUm = "bidir_table.forward_um",
    BidirTableReverseUm = "bidir_table.reverse_um",
    BidirTableRows = "bidir_table.rows",
    BidirTableStepMm = "bidir_table.step_mm",
    BidirTableX0Mm = "bidir_table.x0_mm",
    CalibrationImage = "calibration_image",
    ConfigImage = "config_image",
    EncoderMaxDeltaCounts = "encoder.max_delta_counts",
    Polarity = "polarity",
    Model1HGMm = "model1.h_g_mm",
    Model1HMm = "model1.h_mm",
    Model1MMmPerMm = "model1.m_mm_per_mm",
    Model1OffsetMm = "model1.offset_mm",
    Model1SlopeAMmPerMm = "model1.slope_a_mm_per_mm",
    Model1SlopeBMmPerMm = "model1.slope_b_mm_per_mm",
    Model2AmplitudeAMm = "model2.amplitude_a_mm",
    Model2AmplitudeBMm = "model2.amplitude_b_mm",
    Model2HGMm = "model2.h_g_mm",
    Model2HMm = "model2.h_mm",
    Model2MMmPerMm = "model2.m_mm_per_mm",
    Model2OffsetMm = "model2.offset_mm",
    Model2RateAPerMm = "model2.rate_a_per_mm",
    Model2RateBPerMm = "model2.rate_b_per_mm",
    Model3ForwardBand = "model3.forward_band",
    Model3ForwardBandLen = "model3.forward_band.len",
    Model3ForwardBandXMm = "model3.forward_band.x_mm",
    Model3ForwardBandYUm = "model3.forward_band.y_um",
    Model3ForwardTransition = "model3.forward_transition",
    Model3ForwardTransitionDStepMm = "model3.forward_transition.d_step_mm",
    Model3ForwardTransitionG0StepUm = "model3.forward_transition.g0_step_um",
    Model3ForwardTransitionGapUm = "model3.forward_transition.gap_um",
    Model3ForwardTransitionND = "model3.forward_transition.n_d",
    Model3ForwardTransitionNG0 = "model3.forward_transition.n_g0",
    Model3ReverseBand = "model3.reverse_band",
    Model3ReverseBandLen = "model3.reverse_band.len",
    Model3ReverseBandXMm = "model3.reverse_band.x_mm",
    Model3ReverseBandYUm = "model3.reverse_band.y_um",
    Model3ReverseTransition = "model3.reverse_transition",
    Model3ReverseTransitionDStepMm = "model3.reverse_transition.d_step_mm",
    Model3ReverseTransitionG0StepUm = "model3.reverse_transition.g0_step_um",
    Model3ReverseTransitionGapUm = "model3.reverse_transition.gap_um",
    Model3ReverseTransitionND = "model3.reverse_transition.n_d",
    Model3ReverseTransitionNG0 = "model3.reverse_transition.n_g0",
    Model4BeltAccelPerA = "model4.belt.accel_per_a",
    Model4BeltAxialRigidityN = "model4.belt.axial_rigidity_n",
    Model4BeltGearHalfM = "model4.belt.gear_half_m",
    Model4BeltGearNPerM = "model4.belt.gear_n_per_m",
    Model4BeltGuideN = "model4.belt.guide_n",
    Model4BeltGuideProfileN = "model4.belt.guide_profile_n",
    Model4BeltGuideProfileStartM = "model4.belt.guide_profile_start_m",
    Model4BeltGuideProfileStepM = "model4.belt.guide_profile_step_m",
    Model4BeltHalfGapM = "model4.belt.half_gap_m",
    Model4BeltKappaPerM = "model4.belt.kappa_per_m",
    Model4BeltLengthM = "model4.belt.length_m",
    Model4BeltMPerCount = "model4.belt.m_per_count",
    Model4BeltMassKg = "model4.belt.mass_kg",
    Model4BeltMuKinetic = "model4.belt.mu_kinetic",
    Model4BeltMuStatic = "model4.belt.mu_static",
    Model4BeltPreloadN = "model4.belt.preload_n",
    Model4BeltSigma0PerM = "model4.belt.sigma0_per_m",
    Model4BeltSigma1SPerM = "model4.belt.sigma1_s_per_m",
    Model4BeltSigma2SPerM = "model4.belt.sigma2_s_per_m",
    Model4BeltSpanDampingNSPerM = "model4.belt.span_damping_n_s_per_m",
    Model4BeltSpanOffsetM = "model4.belt.span_offset_m",
    Model4BeltStepTicks = "model4.belt.step_ticks",
    Model4BeltStribeckMPerS = "model4.belt.stribeck_m_per_s",
    Model4BeltToothNPerM = "model4.belt.tooth_n_per_m",
    Model4BeltTrackDiscount = "model4.belt.track_discount",
    Model4BeltFastShare = "model4.belt.fast_share",
    Model4BeltHalfTravelMm = "model4.belt.half_travel_mm",
    Model4BeltRestUm = "model4.belt.rest_um",
    Model4BeltWeight = "model4.belt.weight",
    Model4BeltWrapRad = "model4.belt.wrap_rad",
    Model4CurrentLpUmPerA = "model4.current_lp_um_per_a",
    Model4CurrentUmPerA = "model4.current_um_per_a",
    Model4KnotStartMm = "model4.knot_start_mm",
    Model4KnotStepMm = "model4.knot_step_mm",
    Model4KnotUm = "model4.knot_um",
    Model4OffsetUm = "model4.offset_um",
    Model4PitchMm = "model4.pitch_mm",
    Model4PitchUm = "model4.pitch_um",
    Model4PlayForwardUmPerMm = "model4.play_forward_um_per_mm",
    Model4PlayUmPerMm = "model4.play_um_per_mm",
    Model4SlipCreepPerMm = "model4.slip.creep_per_mm",
    Model4SlipHalfGapUm = "model4.slip.half_gap_um",
    Model4SlipLimitUm = "model4.slip.limit_um",
    Model4SlipLoadUm = "model4.slip.load_um",
    Model4SlipUmPerA = "model4.slip.um_per_a",
    Model4SlipWeight = "model4.slip.weight",
    Model4SlopeUmPerMm = "model4.slope_um_per_mm",
    Model4TurnMm = "model4.turn_mm",
    Model4TurnUm = "model4.turn_um",
    Model4WidthsMm = "model4.widths_mm",
    Model4XRefMm = "model4.x_ref_mm",
    TrajectoryAccelerationMmS2 = "trajectory.acceleration_mm_s2",
    TrajectoryDecelerationMmS2 = "trajectory.deceleration_mm_s2",
    TrajectoryVelocityMmS = "trajectory.velocity_mm_s",
}

impl core::fmt::Display for ConfigField {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// Compares with the dotted name: `e.field() == "drive.rate_hz"`.
impl PartialEq<&str> for ConfigField {
    fn eq(&self, other: &&str) -> bool {
        self.name() == *other
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_distinct_dotted_and_in_discriminant_order() {
        for (i, f) in ConfigField::ALL.iter().enumerate() {
            assert_eq!(*f as usize, i, "{f:?}");
            let n = f.name();
            assert!(
                n.bytes().all(|b| b.is_ascii_lowercase()
                    || b.is_ascii_digit()
                    || b == b'.'
                    || b == b'_'),
                "{n}"
            );
            for g in &ConfigField::ALL[..i] {
                assert_ne!(g.name(), n);
            }
        }
    }
}
