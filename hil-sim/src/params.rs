//! Plant parameters: every physical constant of the simulated rig, in SI units with the unit in
//! the field name, loaded from TOML.
//!
//! The default preset, `presets/paper-rig.toml`, is embedded in the binary ([`PlantParams::paper_rig`]);
//! its comments say where each value comes from. Symbols in the doc comments are those of the
//! paper's section 2 (eqs. 2-12) and eq. 13.

use estimator_core::rig::Rig;
use serde::{Deserialize, Serialize};

use crate::input::{approx, show};

/// The embedded default preset (the paper's rig, Table 1, tuned to section 4's observations).
pub const PAPER_RIG_TOML: &str = include_str!("../presets/paper-rig.toml");

/// Everything the plant needs; see the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlantParams {
    /// Brushed DC motor.
    pub motor: Motor,
    /// Transconductance (current-mode) amplifier.
    pub amplifier: Amplifier,
    /// Built-in two-stage gearbox.
    pub gearbox: Gearbox,
    /// Driving pulley (pinion).
    pub pulley: Pulley,
    /// Timing belt: spans, teeth, form error.
    pub belt: Belt,
    /// LuGre friction between pulley and belt (eq. 11).
    pub friction: Friction,
    /// Carriage on its guide (eq. 2).
    pub carriage: Carriage,
    /// Primary encoder on the motor shaft.
    pub encoder: Encoder,
    /// Linear scale on the carriage.
    pub scale: Scale,
    /// Guide-way angular errors seen through the Abbe offsets (eq. 13).
    pub abbe: Abbe,
    /// Run-to-run (non-repeatable) variation drawn from the seed.
    pub variation: Variation,
    /// Numerical integration.
    pub integration: Integration,
    /// The file these came from, for messages (empty: the built-in preset).
    #[serde(skip)]
    pub source: String,
}

/// Brushed DC motor: torque `kt * i`, rotor inertia, viscous and brush/bearing Coulomb loss.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Motor {
    /// Torque constant kt.
    pub torque_constant_nm_per_a: f64,
    /// Rotor (and encoder, first gear) inertia.
    pub rotor_inertia_kg_m2: f64,
    /// Viscous loss.
    pub viscous_nm_s_per_rad: f64,
    /// Coulomb torque of brushes, bearings and the gear train, referred to the motor shaft.
    pub coulomb_nm: f64,
}

/// Current-mode amplifier: the command is a current; the current loop is a first-order lag.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Amplifier {
    /// Time constant of the current loop.
    pub current_lag_s: f64,
    /// Commands are clamped to +-this.
    pub current_limit_a: f64,
}

/// Gearbox between motor and pulley, with backlash and stiffness at the output shaft.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gearbox {
    /// Motor revolutions per output revolution.
    pub ratio: f64,
    /// Total backlash at the output shaft.
    pub backlash_rad: f64,
    /// Torsional stiffness at the output shaft, once the backlash is closed.
    pub stiffness_nm_per_rad: f64,
    /// Contact damping at the output shaft, only while the backlash is closed.
    pub damping_nm_s_per_rad: f64,
    /// Inertia of the output gear, shaft and pulley.
    pub output_inertia_kg_m2: f64,
}

/// Driving pulley: tooth count, eccentricity rho and initial angle theta_0 (eq. 12), wrap angle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Pulley {
    /// Number of teeth.
    pub teeth: u32,
    /// Eccentricity rho of the pitch circle.
    pub eccentricity_m: f64,
    /// Initial angle theta_0 of the eccentricity.
    pub eccentricity_angle_rad: f64,
    /// Wrap (engagement) angle alpha of the belt on the pulley (eq. 5).
    pub wrap_angle_rad: f64,
}

/// Timing belt: pitch, spans (eqs. 4-10), teeth (eq. 3) and the tooth-mesh form error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Belt {
    /// Nominal pitch.
    pub pitch_m: f64,
    /// Relative pitch error of the unloaded belt (manufacturing); the preload strain adds to it.
    pub pitch_error: f64,
    /// Axial rigidity AE of the belt (cords), in newtons per unit strain.
    pub axial_rigidity_n: f64,
    /// Preload (installation tension) F-bar.
    pub preload_n: f64,
    /// Total free length L of the two spans.
    pub free_length_m: f64,
    /// Span length L0 between pulley and carriage clamp at x = 0 (span 1 is L0 + x).
    pub span_offset_m: f64,
    /// Belt mass lumped at the pulley (wrapped belt plus a share of the spans).
    pub lumped_mass_kg: f64,
    /// Visco-elastic damping of the spans (belt piece against carriage).
    pub span_damping_n_s_per_m: f64,
    /// Half gap h between belt and pulley teeth (eq. 3): the dead zone is |r theta - x| < h.
    pub tooth_half_gap_m: f64,
    /// Overall tooth rigidity k of the teeth in mesh (eq. 3).
    pub tooth_stiffness_n_per_m: f64,
    /// Tooth contact damping, only while a flank is in contact.
    pub tooth_damping_n_s_per_m: f64,
    /// Amplitude of the mesh form error, one period per tooth pitch.
    pub form_error_m: f64,
    /// Phase of the mesh form error at pulley angle 0.
    pub form_error_phase_rad: f64,
}

/// LuGre friction coefficient mu(u) between pulley and belt (eq. 11) plus bristle renewal.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Friction {
    /// false removes all pulley-belt friction (the paper's undamped Fig. 4 case).
    pub enabled: bool,
    /// Bristle stiffness sigma_0 (mu per metre of mean bristle deflection).
    pub sigma0_per_m: f64,
    /// Bristle damping sigma_1.
    pub sigma1_s_per_m: f64,
    /// Viscous term sigma_2.
    pub sigma2_s_per_m: f64,
    /// Kinetic coefficient mu_k.
    pub mu_kinetic: f64,
    /// Static coefficient mu_s.
    pub mu_static: f64,
    /// Stribeck velocity v_s.
    pub stribeck_velocity_m_per_s: f64,
    /// Stribeck exponent a.
    pub stribeck_exponent: f64,
    /// Bristle renewal: belt enters the wrap unstrained and leaves it carrying its deflection, so
    /// the mean deflection relaxes by `renewal_factor / (alpha R)` per metre of pulley travel.
    /// 2 is the value for a uniform contact pressure; 0 gives eq. 11 exactly.
    pub renewal_factor: f64,
}

/// Carriage: mass m and Coulomb friction f_c (eq. 2), travel limits with end stops.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Carriage {
    /// Moving mass m.
    pub mass_kg: f64,
    /// Mean Coulomb friction f_c of the guide bearings.
    pub coulomb_n: f64,
    /// Relative variation of f_c along the guide (bearing preload), repeatable.
    pub coulomb_ripple: f64,
    /// Wavelength of that variation.
    pub coulomb_ripple_wavelength_m: f64,
    /// Phase of that variation at x = 0.
    pub coulomb_ripple_phase_rad: f64,
    /// Lower end stop.
    pub travel_min_m: f64,
    /// Upper end stop.
    pub travel_max_m: f64,
}

/// Quadrature encoder on the motor shaft; counted x4 by a 16-bit timer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Encoder {
    /// Lines per revolution on each channel.
    pub lines: u32,
}

/// Linear scale on the carriage; counted x4 by a 16-bit timer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scale {
    /// Signal periods per millimetre on each channel (Table 1: 500).
    pub lines_per_mm: u32,
    /// Standard deviation of the white reading noise, per control tick.
    pub noise_sd_m: f64,
}

/// One sinusoidal component of a guide-way angular error profile.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Wave {
    /// Amplitude.
    pub amplitude_rad: f64,
    /// Wavelength along the travel.
    pub wavelength_m: f64,
    /// Phase at x = 0.
    pub phase_rad: f64,
}

/// Abbe terms of eq. 13: the scale reads `x + A_z eps_y(x) - A_y eps_z(x)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Abbe {
    /// Abbe offset A_y.
    pub offset_y_m: f64,
    /// Abbe offset A_z.
    pub offset_z_m: f64,
    /// Angular error eps_y(x) (pitch), a sum of waves.
    pub eps_y: Vec<Wave>,
    /// Angular error eps_z(x) (yaw), a sum of waves.
    pub eps_z: Vec<Wave>,
}

/// Relative standard deviations of the parameters redrawn for every run (seed).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variation {
    /// mu_k and mu_s (one common factor).
    pub belt_friction_rel_sd: f64,
    /// sigma_0.
    pub bristle_stiffness_rel_sd: f64,
    /// f_c.
    pub carriage_friction_rel_sd: f64,
    /// F-bar.
    pub preload_rel_sd: f64,
    /// Belt pitch (effective radius): temperature from run to run.
    pub belt_pitch_rel_sd: f64,
}

/// Numerical integration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Integration {
    /// Longest internal step; `Plant::step` splits a tick into equal substeps no longer than this.
    pub max_substep_s: f64,
}

/// Why plant parameters were refused: the file (when read from one), the place in the TOML, or
/// the first field out of its range or inconsistent with another.
#[derive(Debug, thiserror::Error)]
pub enum ParamsError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The plant file.
        path: std::path::PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// Not a plant in TOML (a syntax error, a missing or unknown key), with line and column.
    #[error("{0}")]
    Toml(crate::input::TomlError),
    /// A field out of its range or inconsistent with another (the first found).
    #[error("{field}: {reason}")]
    Field {
        /// The field, e.g. `carriage.mass_kg`.
        field: &'static str,
        /// Its value and the rule it breaks.
        reason: String,
    },
    /// A geometry hil-sim's drive configuration cannot take (the paper rig's gains and limits
    /// in counts go out of their ranges; [`PlantParams::check_default_drive`]).
    #[error(
        "encoder.lines {lines}, gearbox.ratio {ratio}, pulley.teeth {teeth}, belt.pitch_m \
         {pitch_m} ({counts_per_mm:.4} counts/mm): hil-sim's drive (the paper rig's tuning and \
         limits with this geometry) cannot run it, its configuration refuses {refused}"
    )]
    Geometry {
        /// `encoder.lines`.
        lines: u32,
        /// `gearbox.ratio`.
        ratio: f64,
        /// `pulley.teeth`.
        teeth: u32,
        /// `belt.pitch_m`.
        pitch_m: f64,
        /// What that makes of one millimetre.
        counts_per_mm: f64,
        /// The drive's refusal (its field and rule).
        refused: estimator_core::ConfigError,
    },
    /// One of the above, in a file.
    #[error("{}: {source}", path.display())]
    InFile {
        /// The plant file.
        path: std::path::PathBuf,
        /// What is wrong in it.
        source: Box<ParamsError>,
    },
}

impl PlantParams {
    /// The embedded `paper-rig` preset.
    pub fn paper_rig() -> Self {
        Self::from_toml_str(PAPER_RIG_TOML).expect("embedded preset paper-rig.toml is valid")
    }

    /// Parses and validates a TOML preset.
    pub fn from_toml_str(s: &str) -> Result<Self, ParamsError> {
        let p: PlantParams = crate::input::from_toml(s).map_err(ParamsError::Toml)?;
        p.validate()?;
        Ok(p)
    }

    /// Loads a plant file; errors name it.
    pub fn load(path: &std::path::Path) -> Result<Self, ParamsError> {
        let text = crate::input::read_text(path).map_err(|source| ParamsError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut p = Self::from_toml_str(&text).map_err(|e| ParamsError::InFile {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
        p.source = path.display().to_string();
        Ok(p)
    }

    /// The plant file's name, or `the built-in paper-rig plant`.
    pub fn name(&self) -> &str {
        if self.source.is_empty() {
            "the built-in paper-rig plant"
        } else {
            &self.source
        }
    }

    /// Serialises to TOML (loses the preset's comments).
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).expect("plant parameters serialise")
    }

    /// The nominal drive-train geometry the controller assumes (encoder counts <-> millimetres).
    pub fn rig(&self) -> Rig {
        Rig {
            encoder_lines: self.encoder.lines,
            gear_ratio: self.gearbox.ratio,
            belt_pitch_mm: self.belt.pitch_m * 1e3,
            pulley_teeth: self.pulley.teeth,
        }
    }

    /// Nominal pitch radius of the pulley (pitch times teeth over 2 pi).
    pub fn nominal_radius_m(&self) -> f64 {
        self.belt.pitch_m * self.pulley.teeth as f64 / core::f64::consts::TAU
    }

    /// Effective radius: the belt is conveyed one belt pitch per pulley tooth, and the belt pitch
    /// under preload is the nominal one times `(1 + pitch_error + F-bar / AE)`.
    pub fn effective_radius_m(&self) -> f64 {
        self.nominal_radius_m()
            * (1.0 + self.belt.pitch_error + self.belt.preload_n / self.belt.axial_rigidity_n)
    }

    /// Span stiffness (both spans in parallel, eq. 6) at carriage position `x_m`.
    pub fn span_stiffness_n_per_m(&self, x_m: f64) -> f64 {
        let l1 = self.belt.span_offset_m + x_m;
        let l2 = self.belt.free_length_m - l1;
        self.belt.axial_rigidity_n * self.belt.free_length_m / (l1 * l2)
    }

    /// Checks every field; the error names the first offending one.
    pub fn validate(&self) -> Result<(), ParamsError> {
        let mut c = Check::default();
        let m = &self.motor;
        c.pos("motor.torque_constant_nm_per_a", m.torque_constant_nm_per_a);
        c.pos("motor.rotor_inertia_kg_m2", m.rotor_inertia_kg_m2);
        c.nonneg("motor.viscous_nm_s_per_rad", m.viscous_nm_s_per_rad);
        c.nonneg("motor.coulomb_nm", m.coulomb_nm);
        let a = &self.amplifier;
        // A current loop slower than 0.1 s is not a servo amplifier.
        c.range("amplifier.current_lag_s", a.current_lag_s, 1e-9, 0.1);
        c.pos("amplifier.current_limit_a", a.current_limit_a);
        let g = &self.gearbox;
        c.range("gearbox.ratio", g.ratio, 1e-3, 1e4);
        c.range("gearbox.backlash_rad", g.backlash_rad, 0.0, 0.1);
        c.pos("gearbox.stiffness_nm_per_rad", g.stiffness_nm_per_rad);
        c.nonneg("gearbox.damping_nm_s_per_rad", g.damping_nm_s_per_rad);
        c.pos("gearbox.output_inertia_kg_m2", g.output_inertia_kg_m2);
        let p = &self.pulley;
        c.test(
            "pulley.teeth",
            (3..=1000).contains(&p.teeth),
            "must be in 3..=1000",
        );
        c.finite("pulley.eccentricity_angle_rad", p.eccentricity_angle_rad);
        c.range(
            "pulley.wrap_angle_rad",
            p.wrap_angle_rad,
            0.1,
            2.0 * core::f64::consts::TAU,
        );
        let b = &self.belt;
        c.range("belt.pitch_m", b.pitch_m, 1e-4, 0.1);
        // Run-out is a small fraction of the pulley (the paper rig's is 6 um on 16 mm); after
        // the pitch, which the radius comes from.
        c.range(
            "pulley.eccentricity_m",
            p.eccentricity_m,
            0.0,
            0.1 * self.nominal_radius_m(),
        );
        c.range("belt.pitch_error", b.pitch_error, -0.05, 0.05);
        c.pos("belt.axial_rigidity_n", b.axial_rigidity_n);
        c.pos("belt.preload_n", b.preload_n);
        c.pos("belt.free_length_m", b.free_length_m);
        c.pos("belt.span_offset_m", b.span_offset_m);
        c.pos("belt.lumped_mass_kg", b.lumped_mass_kg);
        c.nonneg("belt.span_damping_n_s_per_m", b.span_damping_n_s_per_m);
        c.range(
            "belt.tooth_half_gap_m",
            b.tooth_half_gap_m,
            0.0,
            b.pitch_m / 2.0,
        );
        c.pos("belt.tooth_stiffness_n_per_m", b.tooth_stiffness_n_per_m);
        c.nonneg("belt.tooth_damping_n_s_per_m", b.tooth_damping_n_s_per_m);
        c.range("belt.form_error_m", b.form_error_m, 0.0, b.pitch_m / 10.0);
        c.finite("belt.form_error_phase_rad", b.form_error_phase_rad);
        let f = &self.friction;
        c.pos("friction.sigma0_per_m", f.sigma0_per_m);
        c.nonneg("friction.sigma1_s_per_m", f.sigma1_s_per_m);
        c.nonneg("friction.sigma2_s_per_m", f.sigma2_s_per_m);
        c.range("friction.mu_kinetic", f.mu_kinetic, 1e-6, 5.0);
        c.range("friction.mu_static", f.mu_static, f.mu_kinetic, 5.0);
        c.pos(
            "friction.stribeck_velocity_m_per_s",
            f.stribeck_velocity_m_per_s,
        );
        c.range("friction.stribeck_exponent", f.stribeck_exponent, 0.1, 10.0);
        c.range("friction.renewal_factor", f.renewal_factor, 0.0, 10.0);
        let k = &self.carriage;
        c.range("carriage.mass_kg", k.mass_kg, 1e-3, 1e4);
        c.nonneg("carriage.coulomb_n", k.coulomb_n);
        c.range("carriage.coulomb_ripple", k.coulomb_ripple, 0.0, 0.9);
        c.pos(
            "carriage.coulomb_ripple_wavelength_m",
            k.coulomb_ripple_wavelength_m,
        );
        c.finite(
            "carriage.coulomb_ripple_phase_rad",
            k.coulomb_ripple_phase_rad,
        );
        c.finite("carriage.travel_min_m", k.travel_min_m);
        c.finite("carriage.travel_max_m", k.travel_max_m);
        c.test(
            "carriage.travel_max_m",
            k.travel_max_m > k.travel_min_m,
            "must exceed travel_min_m",
        );
        // Both spans must stay longer than a tenth of L0 anywhere between the end stops.
        c.test(
            "belt.span_offset_m",
            b.span_offset_m + k.travel_min_m > 0.1 * b.span_offset_m,
            "span 1 (L0 + x) must stay positive down to carriage.travel_min_m",
        );
        c.test(
            "belt.free_length_m",
            b.free_length_m - b.span_offset_m - k.travel_max_m > 0.1 * b.span_offset_m,
            "span 2 (L - L0 - x) must stay positive up to carriage.travel_max_m",
        );
        c.test(
            "friction.sigma0_per_m",
            f.mu_static / f.sigma0_per_m < b.pitch_m,
            "bristle pre-sliding (mu_s / sigma0) must be shorter than a pitch",
        );
        c.test(
            "encoder.lines",
            (1..=1 << 20).contains(&self.encoder.lines),
            "must be in 1..=2^20",
        );
        c.test(
            "scale.lines_per_mm",
            (1..=100_000).contains(&self.scale.lines_per_mm),
            "must be in 1..=100000",
        );
        // Beyond these the scale's reading leaves the range its counter represents.
        c.range("scale.noise_sd_m", self.scale.noise_sd_m, 0.0, 1e-3);
        let ab = &self.abbe;
        c.range("abbe.offset_y_m", ab.offset_y_m, -1.0, 1.0);
        c.range("abbe.offset_z_m", ab.offset_z_m, -1.0, 1.0);
        for (name, waves) in [("abbe.eps_y", &ab.eps_y), ("abbe.eps_z", &ab.eps_z)] {
            for w in waves.iter() {
                c.range(name, w.amplitude_rad, 0.0, 1e-2);
                // Guide waviness: shorter waves than a millimetre are the scale's noise, and
                // x / wavelength must stay a number the sine can take.
                c.range(name, w.wavelength_m, 1e-3, 1e3);
                c.finite(name, w.phase_rad);
            }
            // The pitch or yaw all waves add up to, not only each.
            let sum: f64 = waves.iter().map(|w| w.amplitude_rad).sum();
            c.test(
                name,
                sum <= 1e-2,
                &format!("the amplitudes add up to {} rad: at most 0.01", approx(sum)),
            );
        }
        let v = &self.variation;
        c.range(
            "variation.belt_friction_rel_sd",
            v.belt_friction_rel_sd,
            0.0,
            0.2,
        );
        c.range(
            "variation.bristle_stiffness_rel_sd",
            v.bristle_stiffness_rel_sd,
            0.0,
            0.2,
        );
        c.range(
            "variation.carriage_friction_rel_sd",
            v.carriage_friction_rel_sd,
            0.0,
            0.2,
        );
        c.range("variation.preload_rel_sd", v.preload_rel_sd, 0.0, 0.2);
        c.range(
            "variation.belt_pitch_rel_sd",
            v.belt_pitch_rel_sd,
            0.0,
            1e-3,
        );
        let h = self.integration.max_substep_s;
        c.range("integration.max_substep_s", h, 1e-7, 1e-3);
        if c.err.is_none() {
            // The drive must be able to move the carriage at all: at the amplifier's limit the
            // motor pushes the belt with more than the friction of guide and motor.
            let r = self.nominal_radius_m();
            let n = self.gearbox.ratio;
            let push_n = m.torque_constant_nm_per_a * a.current_limit_a * n / r;
            let guide_n = k.coulomb_n * (1.0 + k.coulomb_ripple);
            let friction_n = guide_n + m.coulomb_nm * n / r;
            c.test(
                "motor.torque_constant_nm_per_a",
                push_n > friction_n,
                &format!(
                    "with amplifier.current_limit_a the motor pushes the carriage with at most {} \
                     N, not more than the friction of guide and motor ({} N): the drive cannot \
                     move it",
                    approx(push_n),
                    approx(friction_n)
                ),
            );
            // The gearbox must carry the guide's friction without winding up by a large angle.
            let windup_rad = guide_n * r / g.stiffness_nm_per_rad;
            c.test(
                "gearbox.stiffness_nm_per_rad",
                windup_rad < 0.1,
                &format!(
                    "winds up {} rad under the carriage's friction: at most 0.1",
                    approx(windup_rad)
                ),
            );
        }
        if c.err.is_none() {
            // Explicit (symplectic) update of the stiffest contact: keep omega * h well below 2.
            // Each value in range can still overflow the span's stiffness to NaN.
            let spans_finite = [self.carriage.travel_min_m, self.carriage.travel_max_m]
                .iter()
                .all(|&x| self.span_stiffness_n_per_m(x).is_finite());
            c.test(
                "belt.axial_rigidity_n",
                spans_finite,
                "with belt.free_length_m and belt.span_offset_m the span stiffness AE L / (l1 \
                 l2) is not a finite number (values too large to compute with)",
            );
            let w = self.stiffest_mode_rad_s();
            c.test(
                "integration.max_substep_s",
                w * h < 0.5,
                &format!(
                    "too long for the stiffest mode ({} rad/s): need omega * h < 0.5",
                    approx(w)
                ),
            );
            let d = self.fastest_damping_rate_per_s();
            c.test(
                "integration.max_substep_s",
                d * h < 1.0,
                &format!(
                    "too long for the fastest damping ({} /s): need c h / m < 1",
                    approx(d)
                ),
            );
        }
        c.err.map_or(Ok(()), Err)
    }

    /// Whether hil-sim's own drive (the paper rig's tuning and limits with this plant's
    /// geometry, [`crate::drive_setup::drive_limits`]) takes this geometry: every in-process
    /// run and calibration uses it. A virtual drive is configured by its host and is not
    /// bound by it. The error names the plant file.
    pub fn check_default_drive(&self) -> Result<(), ParamsError> {
        let rig = self.rig();
        match estimator_core::drive::Drive::new(&crate::drive_setup::drive_limits(rig)) {
            Ok(_) => Ok(()),
            Err(refused) => {
                let e = ParamsError::Geometry {
                    lines: self.encoder.lines,
                    ratio: self.gearbox.ratio,
                    teeth: self.pulley.teeth,
                    pitch_m: self.belt.pitch_m,
                    counts_per_mm: rig.counts_per_mm(),
                    refused,
                };
                Err(match self.source.is_empty() {
                    true => e,
                    false => ParamsError::InFile {
                        path: self.source.clone().into(),
                        source: Box::new(e),
                    },
                })
            }
        }
    }

    /// Highest natural frequency of the contact springs (tooth and gear against the lightest
    /// masses), the explicit integrator's stability bound.
    pub fn stiffest_mode_rad_s(&self) -> f64 {
        let r = self.nominal_radius_m();
        let m_pulley = self.gearbox.output_inertia_kg_m2 / (r * r);
        let m_belt = self.belt.lumped_mass_kg;
        let tooth = self.belt.tooth_stiffness_n_per_m * (1.0 / m_pulley + 1.0 / m_belt);
        let k_span = max_or_nan(&[
            self.span_stiffness_n_per_m(self.carriage.travel_min_m),
            self.span_stiffness_n_per_m(self.carriage.travel_max_m),
        ]);
        let belt = (self.belt.tooth_stiffness_n_per_m + k_span) / m_belt;
        let rotor_at_output =
            self.motor.rotor_inertia_kg_m2 * self.gearbox.ratio * self.gearbox.ratio;
        let gear = self.gearbox.stiffness_nm_per_rad
            * (1.0 / self.gearbox.output_inertia_kg_m2 + 1.0 / rotor_at_output)
            + self.belt.tooth_stiffness_n_per_m / m_pulley;
        // The spans between the belt and the carriage (only a light carriage makes it the
        // stiffest).
        let carriage = k_span * (1.0 / m_belt + 1.0 / self.carriage.mass_kg);
        // The bristles between pulley and belt: their force is explicit although their state
        // is advanced exactly; stiffness F-bar alpha sigma_0 near mu = 0 (eq. 10). The paper
        // rig's is 3,400 rad/s; at about 2 / h the run goes wrong (sigma_0 1e6 /m at 20 us).
        let bristles = if self.friction.enabled {
            self.belt.preload_n
                * self.pulley.wrap_angle_rad
                * self.friction.sigma0_per_m
                * (1.0 / m_pulley + 1.0 / m_belt)
        } else {
            0.0
        };
        max_or_nan(&[tooth, belt, gear, carriage, bristles]).sqrt()
    }

    /// Largest `c / m` of the explicit dampers on the lumped belt and the pulley; the friction's
    /// is `dF_f / du ~ F-bar alpha (sigma_1 + sigma_2)` near sticking (eq. 10 for small mu).
    pub fn fastest_damping_rate_per_s(&self) -> f64 {
        let r = self.nominal_radius_m();
        let m_pulley = self.gearbox.output_inertia_kg_m2 / (r * r);
        let f = &self.friction;
        let c_friction = if f.enabled {
            self.belt.preload_n * self.pulley.wrap_angle_rad * (f.sigma1_s_per_m + f.sigma2_s_per_m)
        } else {
            0.0
        };
        let c_contact = self.belt.tooth_damping_n_s_per_m + c_friction;
        let belt = (c_contact + self.belt.span_damping_n_s_per_m) / self.belt.lumped_mass_kg;
        let pulley = c_contact / m_pulley
            + self.gearbox.damping_nm_s_per_rad / self.gearbox.output_inertia_kg_m2;
        let carriage = self.belt.span_damping_n_s_per_m / self.carriage.mass_kg;
        // The motor's own viscous friction and the gearbox's damping on the rotor side.
        let n2 = self.gearbox.ratio * self.gearbox.ratio;
        let motor = (self.motor.viscous_nm_s_per_rad + self.gearbox.damping_nm_s_per_rad / n2)
            / self.motor.rotor_inertia_kg_m2;
        belt.max(pulley).max(carriage).max(motor)
    }
}

/// The largest of `xs`, or NaN if any is: `f64::max` drops a NaN, so a figure that overflowed
/// would pass a stability check on the others.
fn max_or_nan(xs: &[f64]) -> f64 {
    xs.iter().fold(f64::NEG_INFINITY, |m, &x| {
        if m.is_nan() || x.is_nan() {
            f64::NAN
        } else {
            m.max(x)
        }
    })
}

/// Collects the first validation failure.
#[derive(Default)]
struct Check {
    err: Option<ParamsError>,
}

impl Check {
    fn test(&mut self, field: &'static str, ok: bool, why: &str) {
        if !ok && self.err.is_none() {
            self.err = Some(ParamsError::Field {
                field,
                reason: why.to_string(),
            });
        }
    }
    fn finite(&mut self, field: &'static str, v: f64) {
        self.test(
            field,
            v.is_finite(),
            &format!("{} is not a finite number", show(v)),
        );
    }
    fn pos(&mut self, field: &'static str, v: f64) {
        self.finite(field, v);
        self.test(field, v > 0.0, &format!("{} must be > 0", show(v)));
    }
    fn nonneg(&mut self, field: &'static str, v: f64) {
        self.finite(field, v);
        self.test(field, v >= 0.0, &format!("{} must be >= 0", show(v)));
    }
    fn range(&mut self, field: &'static str, v: f64, lo: f64, hi: f64) {
        self.finite(field, v);
        self.test(
            field,
            (lo..=hi).contains(&v),
            &format!("{} must be in [{}, {}]", show(v), show(lo), show(hi)),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_rig_loads_and_matches_the_firmware_geometry() {
        let p = PlantParams::paper_rig();
        assert_eq!(p.rig(), Rig::PAPER);
        assert!((p.nominal_radius_m() * 1e3 - Rig::PAPER.pulley_radius_mm()).abs() < 1e-12);
    }

    #[test]
    fn paper_rig_integration_margins() {
        let p = PlantParams::paper_rig();
        let h = p.integration.max_substep_s;
        let (w, d) = (p.stiffest_mode_rad_s(), p.fastest_damping_rate_per_s());
        assert!((10_000.0..20_000.0).contains(&w), "{w}");
        assert!(
            w * h < 0.4 && d * h < 0.7,
            "omega h {}, c h / m {}",
            w * h,
            d * h
        );
    }

    #[test]
    fn toml_round_trip() {
        let p = PlantParams::paper_rig();
        let q = PlantParams::from_toml_str(&p.to_toml_string()).unwrap();
        assert_eq!(p, q);
    }

    #[test]
    fn errors_name_the_field() {
        let bad = PAPER_RIG_TOML.replace("mass_kg = 2.5", "mass_kg = -2.5");
        let e = PlantParams::from_toml_str(&bad).unwrap_err();
        assert!(
            matches!(&e, ParamsError::Field { field: "carriage.mass_kg", reason } if reason.contains("-2.5")),
            "{e:?}"
        );
        let e = e.to_string();
        assert!(e.starts_with("carriage.mass_kg:"), "{e}");

        let bad = PAPER_RIG_TOML.replace("max_substep_s = 2.0e-5", "max_substep_s = 5.0e-4");
        let e = PlantParams::from_toml_str(&bad).unwrap_err().to_string();
        assert!(e.starts_with("integration.max_substep_s:"), "{e}");

        // Each value in range, but the span stiffness overflows to NaN: refused, not integrated.
        let bad = PAPER_RIG_TOML
            .replace("free_length_m = 0.94", "free_length_m = 3e160")
            .replace("span_offset_m = 0.12", "span_offset_m = 1e160")
            .replace("axial_rigidity_n = 2.0e5", "axial_rigidity_n = 1e171");
        let e = PlantParams::from_toml_str(&bad).unwrap_err().to_string();
        assert!(
            e.starts_with("belt.axial_rigidity_n:") && e.contains("finite"),
            "{e}"
        );

        let bad = PAPER_RIG_TOML.replace("sigma1_s_per_m = 5.0", "sigma1_s_per_m = 50.0");
        let e = PlantParams::from_toml_str(&bad).unwrap_err().to_string();
        assert!(
            e.starts_with("integration.max_substep_s:") && e.contains("damping"),
            "{e}"
        );

        let bad = PAPER_RIG_TOML.replace("[carriage]", "[carriage]\ncolour = 3");
        let e = PlantParams::from_toml_str(&bad).unwrap_err();
        assert!(
            matches!(&e, ParamsError::Toml(m) if m.message.contains("colour")),
            "{e:?}"
        );

        let mut p = PlantParams::paper_rig();
        p.friction.mu_static = 0.5 * p.friction.mu_kinetic;
        assert!(p
            .validate()
            .unwrap_err()
            .to_string()
            .starts_with("friction.mu_static:"));
        // Plants the simulator cannot run, or the drive cannot move, are refused by the field
        // at fault (each of these once exited 0 with a frozen carriage or ended in a drive
        // fault blamed on the scenario).
        let refused = |edit: &dyn Fn(&mut PlantParams), field: &str, why: &str| {
            let mut p = PlantParams::paper_rig();
            edit(&mut p);
            let e = p.validate().unwrap_err().to_string();
            assert!(
                e.starts_with(&format!("{field}:")) && e.contains(why),
                "{e}"
            );
        };
        // Stiff bristles: sigma_0 1e6 /m went 0.28 mm wrong at 20 us and is right at 5 us.
        refused(
            &|p| p.friction.sigma0_per_m = 1e6,
            "integration.max_substep_s",
            "stiffest mode",
        );
        let mut p = PlantParams::paper_rig();
        p.friction.sigma0_per_m = 1e6;
        p.integration.max_substep_s = 5e-6;
        p.validate().unwrap();
        refused(
            &|p| p.motor.viscous_nm_s_per_rad = 4.0,
            "integration.max_substep_s",
            "fastest damping",
        );
        refused(
            &|p| p.motor.torque_constant_nm_per_a = 1e-6,
            "motor.torque_constant_nm_per_a",
            "the drive cannot move it",
        );
        refused(
            &|p| p.amplifier.current_limit_a = 1e-3,
            "motor.torque_constant_nm_per_a",
            "the drive cannot move it",
        );
        refused(
            &|p| p.gearbox.stiffness_nm_per_rad = 1e-3,
            "gearbox.stiffness_nm_per_rad",
            "winds up",
        );
        refused(
            &|p| p.abbe.eps_y[0].wavelength_m = 5e-324,
            "abbe.eps_y",
            "must be in [0.001, 1000]",
        );
        refused(
            &|p| {
                let w = p.abbe.eps_y[0].clone();
                p.abbe.eps_y = vec![w; 4];
                for w in &mut p.abbe.eps_y {
                    w.amplitude_rad = 4e-3;
                }
            },
            "abbe.eps_y",
            "add up to 0.016",
        );
        refused(
            &|p| p.amplifier.current_lag_s = 1.0,
            "amplifier.current_lag_s",
            "must be in",
        );
        // A file's errors name it.
        let e = PlantParams::load(std::path::Path::new("/nonexistent/plant.toml")).unwrap_err();
        assert!(matches!(e, ParamsError::Io { .. }), "{e:?}");
        assert!(
            e.to_string().starts_with("/nonexistent/plant.toml: "),
            "{e}"
        );
    }
}
