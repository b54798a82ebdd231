//! Geometry of the drive train: motor encoder counts <-> carriage millimetres.
//!
//! Defaults follow the paper's Table 1: a 2000-line quadrature encoder on the motor shaft
//! (x4 = 8000 counts per motor revolution), a 23.7222:1 gearbox and a 5.08 mm (0.2 in) pitch belt.
//! The paper does not give the pulley's tooth count; we take 20 teeth (101.6 mm of belt per pulley
//! revolution), a common XL pulley, which puts one motor count at 0.535 um of belt, close to the
//! 0.5 um resolution of the rig's linear scale.

use crate::ConfigField;

/// Mechanical constants that convert motor encoder counts into nominal carriage travel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rig {
    /// Encoder lines per motor revolution (one quadrature channel); counts are 4x this.
    pub encoder_lines: u32,
    /// Gearbox reduction, motor revolutions per pulley revolution.
    pub gear_ratio: f64,
    /// Belt pitch in millimetres.
    pub belt_pitch_mm: f64,
    /// Teeth on the driving pulley.
    pub pulley_teeth: u32,
}

/// `2000 encoder lines, gear 23.7222:1, 20-tooth pulley, 5.08 mm pitch (1867.9 counts/mm)`.
impl core::fmt::Display for Rig {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "{} encoder lines, gear {}:1, {}-tooth pulley, {} mm pitch ({:.1} counts/mm)",
            self.encoder_lines,
            self.gear_ratio,
            self.pulley_teeth,
            self.belt_pitch_mm,
            self.counts_per_mm()
        )
    }
}

impl Rig {
    /// The paper's rig (Table 1) with a 20-tooth pulley.
    pub const PAPER: Rig = Rig {
        encoder_lines: 2000,
        gear_ratio: 23.7222,
        belt_pitch_mm: 5.08,
        pulley_teeth: 20,
    };

    /// Encoder counts per motor revolution (x4 quadrature decoding).
    pub fn counts_per_motor_rev(&self) -> f64 {
        4.0 * self.encoder_lines as f64
    }

    /// Belt travel per pulley revolution, in millimetres.
    pub fn mm_per_pulley_rev(&self) -> f64 {
        self.belt_pitch_mm * self.pulley_teeth as f64
    }

    /// Motor encoder counts per millimetre of nominal carriage travel.
    pub fn counts_per_mm(&self) -> f64 {
        self.counts_per_motor_rev() * self.gear_ratio / self.mm_per_pulley_rev()
    }

    /// Nominal carriage travel per motor encoder count, in micrometres.
    pub fn um_per_count(&self) -> f64 {
        1000.0 / self.counts_per_mm()
    }

    /// Pulley pitch radius in millimetres.
    pub fn pulley_radius_mm(&self) -> f64 {
        self.mm_per_pulley_rev() / (2.0 * core::f64::consts::PI)
    }

    /// The same geometry bit for bit: what a calibration made for `other` needs, with no float
    /// compare (no soft float on the drive).
    pub fn same_bits(&self, other: &Rig) -> bool {
        (self.encoder_lines, self.pulley_teeth) == (other.encoder_lines, other.pulley_teeth)
            && self.gear_ratio.to_bits() == other.gear_ratio.to_bits()
            && self.belt_pitch_mm.to_bits() == other.belt_pitch_mm.to_bits()
    }

    /// Checks that every field is finite and positive.
    pub fn validate(&self) -> Result<(), crate::ConfigError> {
        use crate::ConfigError as E;
        if self.encoder_lines == 0 || self.encoder_lines > 1 << 20 {
            return Err(E::OutOfRange(ConfigField::RigEncoderLines));
        }
        if !positive_below(self.gear_ratio, 1e4) {
            return Err(E::OutOfRange(ConfigField::RigGearRatio));
        }
        if !positive_below(self.belt_pitch_mm, 1e3) {
            return Err(E::OutOfRange(ConfigField::RigBeltPitchMm));
        }
        if self.pulley_teeth == 0 || self.pulley_teeth > 1000 {
            return Err(E::OutOfRange(ConfigField::RigPulleyTeeth));
        }
        Ok(())
    }
}

/// `0 < x < max` and finite, on the bits (positive doubles order like their bits; NaN, the
/// infinities and negative values fall outside): no float compare, so the drive can check a
/// geometry it receives without soft float.
fn positive_below(x: f64, max: f64) -> bool {
    let b = x.to_bits();
    b > 0 && b < max.to_bits()
}

impl Default for Rig {
    fn default() -> Self {
        Self::PAPER
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_rig_scale() {
        let r = Rig::PAPER;
        assert_eq!(r.counts_per_motor_rev(), 8000.0);
        assert!(
            (r.counts_per_mm() - 1867.89).abs() < 0.01,
            "{}",
            r.counts_per_mm()
        );
        assert!((r.um_per_count() - 0.53536).abs() < 1e-4);
    }
}
