//! The simulated rig: section 2 of the paper as a lumped-parameter plant.
//!
//! Nobody has the paper's rig; this is it. The transmission-error models (the paper's Models
//! 1-3) are calibrated and judged on this plant, so it is built from the physics of section 2 and
//! never from those models: hysteresis, fast jump and slow transition come out of tooth backlash,
//! elasticity and friction.
//!
//! # Bodies and states
//!
//! | body | state | equation |
//! |---|---|---|
//! | amplifier | current `i` | `i' = (clamp(i_cmd) - i) / tau_i` |
//! | motor | `theta_m`, `omega_m` | `J_m omega_m' = kt i - b_m omega_m - T_cm sgn(omega_m) - T_g / N` |
//! | gearbox output + pulley | `theta`, `omega` | `J_p omega' = T_g - P'(theta) (F_t + F_f)` |
//! | belt at the pulley | `b`, `v_b` | `m_b v_b' = F_t + F_f - (F2 - F1) - c_s (v_b - x')` |
//! | carriage (eq. 2) | `x`, `x'` | `m x'' + f_c(x) sgn(x') = F2 - F1 + c_s (v_b - x')` |
//! | bristles (eq. 11) | `z` | `z' = u - sigma0 abs(u) z / g(u) - kappa abs(P' omega) z` |
//!
//! * Gearbox: `T_g = k_g dz(theta_m / N - theta, beta / 2)` plus contact damping, where
//!   `dz(d, h)` is eq. 3's dead zone (`d - h` above `h`, `d + h` below `-h`, else 0).
//! * Mesh position of the pulley, eq. 12 integrated and extended by the tooth-mesh form error:
//!   `P(theta) = R theta - rho (sin(theta + theta_0) - sin theta_0) + e (sin(n theta + phi) - sin phi)`.
//!   `R` is the effective radius: the belt is conveyed one belt pitch per pulley tooth and its pitch
//!   under preload is `(1 + pitch_error + F-bar / AE)` times nominal, which is the band's slope.
//! * Teeth, eq. 3: `F_t = k dz(P - b, h)` plus contact damping.
//! * Slip velocity, eq. 12: `u = P'(theta) omega - v_b`. The paper writes `x'` for the belt
//!   velocity; here the spans are elastic and the belt at the pulley is its own body.
//! * Friction, eqs. 5 and 10-11: `mu = sigma0 z + sigma1 z' + sigma2 u`, `gamma = exp(mu alpha)`,
//!   `F_f = F-bar (gamma - 1) L / (L1 + gamma L2)`, spans `L1 = L0 + x`, `L2 = L - L0 - x`.
//! * Spans, eqs. 4 and 6: with `delta = b - x`, `F1 = F-bar - AE delta / L1`,
//!   `F2 = F-bar + AE delta / L2` (never below 0: a slack span carries nothing).
//! * Scale (eq. 13): `x_LS = x + A_z eps_y(x) - A_y eps_z(x)` plus white reading noise.
//!
//! # Why the belt creeps: bristle renewal
//!
//! Eq. 11 alone has no steady sliding below the friction limit: once the bristles carry the load
//! the belt stops slipping, and after a reversal the belt would stay wherever the fast transient
//! left it inside the tooth gap (the `creep_needs_bristle_renewal` test shows it). The rig shows
//! instead that "the belt slowly slides until the next set of teeth pairs engage". The missing
//! physics is that a belt is not a block: belt material enters the wrap unstrained and leaves it
//! strained, so the mean deflection of the contact decays with the distance the pulley surface
//! travels. Averaging the distributed LuGre model over the wrap (as Canudas de Wit et al. did for
//! the tyre's contact patch) adds `-kappa abs(P' omega) z`, `kappa = renewal_factor / (alpha R)`;
//! 2 is exact for a uniform contact pressure (the deflection grows linearly along the wrap).
//! Under a constant load (the carriage's Coulomb friction f_c) the steady state is a creep
//! `u / (P' omega) ~ kappa z / (1 - sigma0 z / g)` with `sigma0 z ~ mu` carrying f_c: slip in
//! proportion to travel and load, independent of speed (the same law as Reynolds' elastic creep
//! of flat belts). It lasts until the other flank meets, so crossing the tooth gap takes tens of
//! millimetres; the load, and so the creep rate, varies along the travel through eq. 10's span
//! lengths and the guide's friction ripple. With the teeth engaged the same term hands the
//! friction share of the load over to the teeth within `1 / kappa` (~25 mm) of travel.
//!
//! After a reversal from a band edge, dx first changes one to one with the motor (gear backlash,
//! unloading and reloading of gear, spans and teeth, and the bristles' pre-sliding up to
//! `z ~ mu / sigma0`: the fast jump, ~0.12 mm), then creeps. A reversal in mid-creep must also
//! swing the bristles from `+z` to `-z`, so its jump is larger: the plant keeps that memory.
//!
//! # Measurement chain
//!
//! The motor encoder counts `floor(theta_m * 4 lines / 2 pi)`; the scale counts
//! `floor((x_LS + noise) / 0.5 um)`, sampled at the end of each tick; the raw registers are the
//! low 16 bits. Run to run (per seed) the plant redraws mu_k and mu_s, sigma_0, f_c, F-bar and the
//! belt pitch (`[variation]`); with the scale noise that is the non-repeatable part.
//!
//! # Integration
//!
//! Symplectic (semi-implicit) Euler on fixed substeps of at most `integration.max_substep_s`:
//! forces from positions, then velocities, then positions from the new velocities. Coulomb
//! friction of motor and carriage is set-valued and solved implicitly per substep (a velocity
//! that would change sign sticks at 0), so stiction is exact and needs no smoothing. The bristle
//! state is advanced with the exact exponential of its linear ODE over the substep, so the LuGre
//! part is unconditionally stable whatever sigma_0; the current lag uses its exact discretisation
//! too. What is left explicit are the contact springs (teeth, gear, spans against the 25 g of
//! lumped belt and the pulley) and dampers: `paper-rig` has `omega_max ~ 16000 rad/s`, and
//! `PlantParams::validate` enforces `omega_max h < 0.5` and `c h / m < 1`. The default 20 us
//! (25 substeps per 2 kHz tick) stays within 0.5 um of a 5 us run (`substep_convergence`) and
//! runs ~300 times faster than real time (`cargo bench -p hil-sim --bench sim_speed`).

pub(crate) mod rng;

pub use crate::params::PlantParams;
use core::f64::consts::TAU;
use rng::Rng;

/// Forces and friction state of the belt at one instant (for plots and checks).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BeltForces {
    /// Tooth force F_t on the belt, positive pushing it forward (eq. 3).
    pub tooth_n: f64,
    /// Friction force F_f on the belt (eq. 10), positive forward.
    pub friction_n: f64,
    /// Tension F1 of span 1 (`L0 + x`, slack when driving forward).
    pub span1_n: f64,
    /// Tension F2 of span 2 (`L - L0 - x`, tight when driving forward).
    pub span2_n: f64,
    /// Friction coefficient mu of eq. 11.
    pub mu: f64,
    /// Mean bristle deflection z.
    pub bristle_m: f64,
    /// Mesh offset `P(theta) - b`: inside `(-h, h)` the teeth are out of contact.
    pub mesh_offset_m: f64,
    /// Slip velocity u of eq. 12.
    pub slip_m_per_s: f64,
}

/// Per-run constants, built once from the parameters and the seed.
#[derive(Clone, Debug)]
struct Coeffs {
    // Amplifier and motor.
    kt: f64,
    tau_i: f64,
    i_limit: f64,
    jm_inv: f64,
    b_m: f64,
    t_cm: f64,
    // Gearbox and pulley.
    n: f64,
    gear_half_backlash: f64,
    k_g: f64,
    c_g: f64,
    jp_inv: f64,
    r_eff: f64,
    rho: f64,
    theta0: f64,
    sin_theta0: f64,
    teeth: f64,
    form: f64,
    form_phase: f64,
    sin_form_phase: f64,
    // Belt.
    ae: f64,
    preload: f64,
    l_total: f64,
    l0: f64,
    mb_inv: f64,
    c_s: f64,
    half_gap: f64,
    k_t: f64,
    c_t: f64,
    // Friction.
    friction: bool,
    alpha: f64,
    sigma0: f64,
    sigma1: f64,
    sigma2: f64,
    mu_k: f64,
    mu_s: f64,
    v_s_inv: f64,
    stribeck_exp: f64,
    kappa: f64,
    // Carriage.
    m_inv: f64,
    f_c: f64,
    f_c_ripple: f64,
    ripple_k: f64,
    ripple_phase: f64,
    travel_min: f64,
    travel_max: f64,
    // Measurement.
    motor_counts_per_rad: f64,
    scale_counts_per_m: f64,
    scale_noise: f64,
    abbe_y: f64,
    abbe_z: f64,
    eps_y: Vec<[f64; 3]>,
    eps_z: Vec<[f64; 3]>,
    counts_per_mm: f64,
    max_substep: f64,
}

/// End stops: stiff, well damped springs beyond the travel.
const STOP_STIFFNESS_N_PER_M: f64 = 1.0e6;
const STOP_DAMPING_N_S_PER_M: f64 = 500.0;

/// Dead zone of eq. 3 with contact damping; the damper never pulls a flank that is in contact.
#[inline(always)]
fn contact(d: f64, d_rate: f64, half_gap: f64, k: f64, c: f64) -> f64 {
    if d > half_gap {
        (k * (d - half_gap) + c * d_rate).max(0.0)
    } else if d < -half_gap {
        (k * (d + half_gap) + c * d_rate).min(0.0)
    } else {
        0.0
    }
}

/// Backward-Euler Coulomb friction: `v_trial` is the velocity without friction, `dv` the change
/// friction can make in one substep. A velocity that would cross zero sticks there.
#[inline(always)]
pub fn coulomb(v_trial: f64, dv: f64) -> f64 {
    if v_trial > dv {
        v_trial - dv
    } else if v_trial < -dv {
        v_trial + dv
    } else {
        0.0
    }
}

impl Coeffs {
    fn new(p: &PlantParams, rng: &mut Rng) -> Coeffs {
        // Run-to-run factors, clamped to +-4 sd so a wild draw cannot break the plant.
        let mut draw = |sd: f64| 1.0 + sd * rng.normal().clamp(-4.0, 4.0);
        let v = &p.variation;
        let k_mu = draw(v.belt_friction_rel_sd);
        let k_sigma0 = draw(v.bristle_stiffness_rel_sd);
        let k_fc = draw(v.carriage_friction_rel_sd);
        let k_preload = draw(v.preload_rel_sd);
        let k_pitch = draw(v.belt_pitch_rel_sd);

        let wave = |w: &crate::params::Wave| [w.amplitude_rad, TAU / w.wavelength_m, w.phase_rad];
        let r_eff = p.effective_radius_m() * k_pitch;
        Coeffs {
            kt: p.motor.torque_constant_nm_per_a,
            tau_i: p.amplifier.current_lag_s,
            i_limit: p.amplifier.current_limit_a,
            jm_inv: 1.0 / p.motor.rotor_inertia_kg_m2,
            b_m: p.motor.viscous_nm_s_per_rad,
            t_cm: p.motor.coulomb_nm,
            n: p.gearbox.ratio,
            gear_half_backlash: 0.5 * p.gearbox.backlash_rad,
            k_g: p.gearbox.stiffness_nm_per_rad,
            c_g: p.gearbox.damping_nm_s_per_rad,
            jp_inv: 1.0 / p.gearbox.output_inertia_kg_m2,
            r_eff,
            rho: p.pulley.eccentricity_m,
            theta0: p.pulley.eccentricity_angle_rad,
            sin_theta0: p.pulley.eccentricity_angle_rad.sin(),
            teeth: p.pulley.teeth as f64,
            form: p.belt.form_error_m,
            form_phase: p.belt.form_error_phase_rad,
            sin_form_phase: p.belt.form_error_phase_rad.sin(),
            ae: p.belt.axial_rigidity_n,
            preload: p.belt.preload_n * k_preload,
            l_total: p.belt.free_length_m,
            l0: p.belt.span_offset_m,
            mb_inv: 1.0 / p.belt.lumped_mass_kg,
            c_s: p.belt.span_damping_n_s_per_m,
            half_gap: p.belt.tooth_half_gap_m,
            k_t: p.belt.tooth_stiffness_n_per_m,
            c_t: p.belt.tooth_damping_n_s_per_m,
            friction: p.friction.enabled,
            alpha: p.pulley.wrap_angle_rad,
            sigma0: p.friction.sigma0_per_m * k_sigma0,
            sigma1: p.friction.sigma1_s_per_m,
            sigma2: p.friction.sigma2_s_per_m,
            mu_k: p.friction.mu_kinetic * k_mu,
            mu_s: p.friction.mu_static * k_mu,
            v_s_inv: 1.0 / p.friction.stribeck_velocity_m_per_s,
            stribeck_exp: p.friction.stribeck_exponent,
            kappa: p.friction.renewal_factor / (p.pulley.wrap_angle_rad * r_eff),
            m_inv: 1.0 / p.carriage.mass_kg,
            f_c: p.carriage.coulomb_n * k_fc,
            f_c_ripple: p.carriage.coulomb_ripple,
            ripple_k: TAU / p.carriage.coulomb_ripple_wavelength_m,
            ripple_phase: p.carriage.coulomb_ripple_phase_rad,
            travel_min: p.carriage.travel_min_m,
            travel_max: p.carriage.travel_max_m,
            motor_counts_per_rad: 4.0 * p.encoder.lines as f64 / TAU,
            scale_counts_per_m: 4.0 * p.scale.lines_per_mm as f64 * 1e3,
            scale_noise: p.scale.noise_sd_m,
            abbe_y: p.abbe.offset_y_m,
            abbe_z: p.abbe.offset_z_m,
            eps_y: p.abbe.eps_y.iter().map(wave).collect(),
            eps_z: p.abbe.eps_z.iter().map(wave).collect(),
            counts_per_mm: p.rig().counts_per_mm(),
            max_substep: p.integration.max_substep_s,
        }
    }

    /// Mesh position `P(theta)` and its slope `P'(theta)` (eq. 12 integrated, plus form error).
    #[inline(always)]
    fn mesh(&self, theta: f64) -> (f64, f64) {
        self.mesh_from(theta, &MeshTrig::new(self, theta))
    }

    /// As [`Coeffs::mesh`], with the trigonometric terms given.
    #[inline(always)]
    fn mesh_from(&self, theta: f64, t: &MeshTrig) -> (f64, f64) {
        let p = self.r_eff * theta - self.rho * (t.ecc[0] - self.sin_theta0)
            + self.form * (t.form[0] - self.sin_form_phase);
        let dp = self.r_eff - self.rho * t.ecc[1] + self.form * self.teeth * t.form[1];
        (p, dp)
    }

    /// Stribeck curve g(u) of eq. 11.
    #[inline(always)]
    fn stribeck(&self, u: f64) -> f64 {
        let r = (u * self.v_s_inv).abs();
        let e = if self.stribeck_exp == 2.0 {
            r * r
        } else {
            r.powf(self.stribeck_exp)
        };
        if e > 40.0 {
            self.mu_k
        } else {
            self.mu_k + (self.mu_s - self.mu_k) * (-e).exp()
        }
    }

    /// Friction coefficient of eq. 11 for slip `u`, bristle state `z` and pulley surface speed,
    /// with the bristles' relaxation rate `lambda` (`z' = u - lambda z`).
    #[inline(always)]
    fn mu(&self, u: f64, z: f64, surface_speed: f64) -> (f64, f64) {
        let lambda = self.bristle_rate(u, surface_speed);
        let z_rate = u - lambda * z;
        (
            self.sigma0 * z + self.sigma1 * z_rate + self.sigma2 * u,
            lambda,
        )
    }

    /// Relaxation rate of the bristles: `z' = u - lambda z`.
    #[inline(always)]
    fn bristle_rate(&self, u: f64, surface_speed: f64) -> f64 {
        self.sigma0 * u.abs() / self.stribeck(u) + self.kappa * surface_speed.abs()
    }

    /// Friction force on the belt for coefficient `mu` (eqs. 5-10) at carriage position `x`.
    #[inline(always)]
    fn capstan(&self, mu: f64, x: f64) -> f64 {
        let l1 = self.l0 + x;
        let l2 = self.l_total - l1;
        let gamma = (mu * self.alpha).exp();
        self.preload * (gamma - 1.0) * self.l_total / (l1 + gamma * l2)
    }

    /// Span tensions (F1, F2) for belt stretch `delta = b - x` (eqs. 4 and 6).
    #[inline(always)]
    fn spans(&self, delta: f64, x: f64) -> (f64, f64) {
        let l1 = self.l0 + x;
        let l2 = self.l_total - l1;
        let f1 = (self.preload - self.ae * delta / l1).max(0.0);
        let f2 = (self.preload + self.ae * delta / l2).max(0.0);
        (f1, f2)
    }

    /// Carriage Coulomb friction f_c at `x`.
    #[inline(always)]
    fn carriage_friction(&self, x: f64) -> f64 {
        self.f_c * (1.0 + self.f_c_ripple * (self.ripple_k * x + self.ripple_phase).sin())
    }

    /// What the scale sees: eq. 13's Abbe terms on top of the carriage position.
    fn scale_position(&self, x: f64) -> f64 {
        let eps = |waves: &[[f64; 3]]| {
            waves
                .iter()
                .map(|w| w[0] * (w[1] * x + w[2]).sin())
                .sum::<f64>()
        };
        x + self.abbe_z * eps(&self.eps_y) - self.abbe_y * eps(&self.eps_z)
    }
}

/// `(sin, cos)` of the eccentricity angle `theta + theta_0` and of the tooth-mesh angle
/// `n theta + phi`, carried from substep to substep by rotation instead of recomputed.
#[derive(Clone, Copy, Debug, Default)]
struct MeshTrig {
    ecc: [f64; 2],
    form: [f64; 2],
}

impl MeshTrig {
    fn new(c: &Coeffs, theta: f64) -> MeshTrig {
        let (s1, c1) = (theta + c.theta0).sin_cos();
        let (s2, c2) = (c.teeth * theta + c.form_phase).sin_cos();
        MeshTrig {
            ecc: [s1, c1],
            form: [s2, c2],
        }
    }

    /// Advances by `d_theta`; exact to rounding for steps below 0.05 rad of mesh angle, else
    /// recomputed.
    #[inline(always)]
    fn rotate(&mut self, c: &Coeffs, theta: f64, d_theta: f64) {
        let d2 = c.teeth * d_theta;
        if d2.abs() >= 0.05 {
            *self = MeshTrig::new(c, theta);
            return;
        }
        #[inline(always)]
        fn rot(sc: &mut [f64; 2], d: f64) {
            // Taylor series of sin and cos to d^6: error below 2e-13 for |d| < 0.05.
            let q = d * d;
            let sd = d * (1.0 - q / 6.0 * (1.0 - q / 20.0));
            let cd = 1.0 - q / 2.0 * (1.0 - q / 12.0 * (1.0 - q / 30.0));
            *sc = [sc[0] * cd + sc[1] * sd, sc[1] * cd - sc[0] * sd];
        }
        rot(&mut self.ecc, d_theta);
        rot(&mut self.form, d2);
    }
}

#[derive(Clone, Copy, Debug, Default)]
struct State {
    t: f64,
    i: f64,
    theta_m: f64,
    omega_m: f64,
    theta: f64,
    omega: f64,
    b: f64,
    v_b: f64,
    x: f64,
    v: f64,
    z: f64,
}

/// The simulated rig. Construct with [`Plant::new`], advance with [`Plant::step`] once per
/// control tick, read the two encoder counters like the firmware does.
///
/// Counter zero: motor angle 0 is the pulley angle at which, with centred gear backlash, a
/// centred tooth gap and no load, the carriage is at 0 mm; the scale reads 0 at carriage 0 mm
/// (plus its Abbe term). The raw registers are the low 16 bits of these absolute counts.
#[derive(Clone, Debug)]
pub struct Plant {
    c: Coeffs,
    s: State,
    noise: Rng,
    scale_counts: i64,
}

impl Plant {
    /// A plant at rest with zero current, carriage at `start_mm`, on the forward band edge but
    /// unloaded: gear backlash and tooth gap closed on their forward-driving flanks with zero
    /// force, spans at preload, bristles relaxed. The first forward move only loads the drive
    /// (dx drops by the elastic share, ~15 um); the first reverse move sees the full reversal.
    ///
    /// `seed` draws the run-to-run variation (`[variation]`) and the scale noise.
    ///
    /// Refused (with the field named) if `params` fails [`PlantParams::validate`] or `start_mm`
    /// is outside the travel.
    pub fn new(
        params: &PlantParams,
        start_mm: f64,
        seed: u64,
    ) -> Result<Plant, crate::error::Error> {
        use crate::error::Context;
        params.validate().context(|| params.name().to_string())?;
        let x = start_mm * 1e-3;
        if !(params.carriage.travel_min_m..=params.carriage.travel_max_m).contains(&x) {
            return Err(crate::error::Error::StartOutsideTravel {
                start_mm,
                min_mm: params.carriage.travel_min_m * 1e3,
                max_mm: params.carriage.travel_max_m * 1e3,
                plant: params.name().to_string(),
            });
        }
        let mut draws = Rng::new(seed, 0);
        let c = Coeffs::new(params, &mut draws);
        // Pulley angle with the forward flank touching: P(theta) = x + h (P is monotonic).
        let target = x + c.half_gap;
        let mut theta = target / c.r_eff;
        for _ in 0..50 {
            let (p, dp) = c.mesh(theta);
            let step = (p - target) / dp;
            theta -= step;
            if step.abs() < 1e-15 {
                break;
            }
        }
        let theta_m = c.n * (theta + c.gear_half_backlash);
        let s = State {
            theta_m,
            theta,
            b: x,
            x,
            ..State::default()
        };
        let mut plant = Plant {
            c,
            s,
            noise: Rng::new(seed, 1),
            scale_counts: 0,
        };
        plant.sample_scale();
        Ok(plant)
    }

    /// Integrates one control tick of `dt_s` with the amplifier commanded to `current_cmd_a`
    /// (clamped to the amplifier's limit), in equal substeps no longer than the configured one.
    /// The scale is sampled (with its noise) at the end of the tick.
    pub fn step(&mut self, current_cmd_a: f64, dt_s: f64) {
        assert!(
            dt_s.is_finite() && dt_s >= 0.0,
            "dt_s must be finite and >= 0"
        );
        if dt_s == 0.0 {
            return;
        }
        let n = (dt_s / self.c.max_substep * (1.0 - 1e-9)).ceil().max(1.0);
        let h = dt_s / n;
        let i_cmd = if current_cmd_a.is_finite() {
            current_cmd_a.clamp(-self.c.i_limit, self.c.i_limit)
        } else {
            0.0
        };
        let lag = 1.0 - (-h / self.c.tau_i).exp();
        // Slow terms, fixed over a tick: the trigonometry is resynchronised and the guide
        // friction (a 130 mm wave) moves by well under 1e-3 of itself.
        let mut trig = MeshTrig::new(&self.c, self.s.theta);
        let f_c = self.c.carriage_friction(self.s.x);
        for _ in 0..n as u64 {
            self.substep(i_cmd, h, lag, f_c, &mut trig);
        }
        self.sample_scale();
    }

    #[inline(always)]
    fn substep(&mut self, i_cmd: f64, h: f64, lag: f64, f_c: f64, trig: &mut MeshTrig) {
        let c = &self.c;
        let s = &mut self.s;
        s.i += (i_cmd - s.i) * lag;

        // Forces from the present state.
        let t_g = contact(
            s.theta_m / c.n - s.theta,
            s.omega_m / c.n - s.omega,
            c.gear_half_backlash,
            c.k_g,
            c.c_g,
        );
        let (p, dp) = c.mesh_from(s.theta, trig);
        let surface = dp * s.omega;
        let f_t = contact(p - s.b, surface - s.v_b, c.half_gap, c.k_t, c.c_t);
        let (f_f, lambda) = if c.friction {
            let (mu, lambda) = c.mu(surface - s.v_b, s.z, surface);
            (c.capstan(mu, s.x), lambda)
        } else {
            (0.0, 0.0)
        };
        let (f1, f2) = c.spans(s.b - s.x, s.x);
        let f_span = f2 - f1 + c.c_s * (s.v_b - s.v);
        let f_stop = if s.x > c.travel_max {
            -STOP_STIFFNESS_N_PER_M * (s.x - c.travel_max) - STOP_DAMPING_N_S_PER_M * s.v
        } else if s.x < c.travel_min {
            STOP_STIFFNESS_N_PER_M * (c.travel_min - s.x) - STOP_DAMPING_N_S_PER_M * s.v
        } else {
            0.0
        };

        // Velocities (Coulomb friction implicit), then positions.
        let t_motor = c.kt * s.i - c.b_m * s.omega_m - t_g / c.n;
        s.omega_m = coulomb(s.omega_m + h * t_motor * c.jm_inv, h * c.t_cm * c.jm_inv);
        s.omega += h * (t_g - dp * (f_t + f_f)) * c.jp_inv;
        s.v_b += h * (f_t + f_f - f_span) * c.mb_inv;
        s.v = coulomb(s.v + h * (f_span + f_stop) * c.m_inv, h * f_c * c.m_inv);
        s.theta_m += h * s.omega_m;
        s.theta += h * s.omega;
        trig.rotate(c, s.theta, h * s.omega);
        s.b += h * s.v_b;
        s.x += h * s.v;

        // Bristles: exact solution of z' = u - lambda z over the substep, with the new slip and
        // the relaxation rate from the force evaluation (the Stribeck term varies slowly).
        if c.friction {
            let u = dp * s.omega - s.v_b;
            let e = lambda * h;
            if e < 1e-3 {
                // exp(-e) to O(e^4); avoids the transcendental in the common slow case.
                s.z += (u - lambda * s.z) * h * (1.0 - e * (0.5 - e / 6.0));
            } else {
                let z_inf = u / lambda;
                s.z = z_inf + (s.z - z_inf) * (-e).exp();
            }
        }
        s.t += h;
    }

    fn sample_scale(&mut self) {
        let noise = if self.c.scale_noise > 0.0 {
            self.c.scale_noise * self.noise.normal()
        } else {
            0.0
        };
        let reading = self.c.scale_position(self.s.x) + noise;
        self.scale_counts = (reading * self.c.scale_counts_per_m).floor() as i64;
    }

    /// Fault injection: moves the end stops, millimetres of carriage travel (a jam is a stop
    /// just ahead of the carriage). The physics is unchanged; only where the stops stand.
    pub fn set_end_stops_mm(&mut self, min_mm: f64, max_mm: f64) {
        self.c.travel_min = min_mm * 1e-3;
        self.c.travel_max = max_mm * 1e-3;
    }

    /// The amplifier's current limit, amperes.
    pub fn current_limit_a(&self) -> f64 {
        self.c.i_limit
    }

    /// Raw motor encoder timer register (x4 quadrature, wraps at 16 bits).
    pub fn motor_counter(&self) -> u16 {
        self.motor_counts() as u16
    }

    /// Raw linear scale timer register (x4 quadrature, 0.5 um counts, wraps at 16 bits).
    pub fn scale_counter(&self) -> u16 {
        self.scale_counts as u16
    }

    /// Unwrapped motor encoder counts (the truth behind [`Plant::motor_counter`]).
    pub fn motor_counts(&self) -> i64 {
        (self.s.theta_m * self.c.motor_counts_per_rad).floor() as i64
    }

    /// Unwrapped scale counts (the truth behind [`Plant::scale_counter`], noise included).
    pub fn scale_counts(&self) -> i64 {
        self.scale_counts
    }

    /// Nominal motor counts per millimetre of carriage travel (`Rig::counts_per_mm`).
    pub fn counts_per_mm(&self) -> f64 {
        self.c.counts_per_mm
    }

    /// Scale counts per millimetre.
    pub fn scale_counts_per_mm(&self) -> f64 {
        self.c.scale_counts_per_m * 1e-3
    }

    /// x_PE: the motor encoder reading in nominal millimetres (quantised, as the firmware sees it).
    pub fn motor_mm(&self) -> f64 {
        self.motor_counts() as f64 / self.c.counts_per_mm
    }

    /// x_PE without quantisation: the motor angle in nominal millimetres.
    pub fn motor_true_mm(&self) -> f64 {
        self.s.theta_m * self.c.motor_counts_per_rad / self.c.counts_per_mm
    }

    /// x_LS: the scale reading in millimetres (quantised, with noise, as the firmware sees it).
    pub fn scale_mm(&self) -> f64 {
        self.scale_counts as f64 / self.scale_counts_per_mm()
    }

    /// The paper's `dx = x_LS - x_PE` from the two readings, in millimetres.
    pub fn delta_x_mm(&self) -> f64 {
        self.scale_mm() - self.motor_mm()
    }

    /// True carriage position (belt clamp), millimetres.
    pub fn carriage_mm(&self) -> f64 {
        self.s.x * 1e3
    }

    /// True position the scale would read without noise and quantisation (eq. 13), millimetres.
    pub fn scale_true_mm(&self) -> f64 {
        self.c.scale_position(self.s.x) * 1e3
    }

    /// True carriage velocity, mm/s.
    pub fn carriage_velocity_mm_s(&self) -> f64 {
        self.s.v * 1e3
    }

    /// Motor shaft angle (continuous truth), radians.
    pub fn motor_angle_rad(&self) -> f64 {
        self.s.theta_m
    }

    /// Motor shaft velocity, rad/s.
    pub fn motor_velocity_rad_s(&self) -> f64 {
        self.s.omega_m
    }

    /// Pulley angle theta, radians.
    pub fn pulley_angle_rad(&self) -> f64 {
        self.s.theta
    }

    /// Motor current (after the amplifier's lag), amperes.
    pub fn current_a(&self) -> f64 {
        self.s.i
    }

    /// Simulated time since construction, seconds.
    pub fn time_s(&self) -> f64 {
        self.s.t
    }

    /// Carriage Coulomb friction drawn for this run at the present position, newtons.
    pub fn carriage_friction_n(&self) -> f64 {
        self.c.carriage_friction(self.s.x)
    }

    /// Belt forces and friction state now.
    pub fn belt(&self) -> BeltForces {
        let c = &self.c;
        let s = &self.s;
        let (p, dp) = c.mesh(s.theta);
        let surface = dp * s.omega;
        let u = surface - s.v_b;
        let f_t = contact(p - s.b, u, c.half_gap, c.k_t, c.c_t);
        let (mu, f_f) = if c.friction {
            let mu = c.mu(u, s.z, surface).0;
            (mu, c.capstan(mu, s.x))
        } else {
            (0.0, 0.0)
        };
        let (f1, f2) = c.spans(s.b - s.x, s.x);
        BeltForces {
            tooth_n: f_t,
            friction_n: f_f,
            span1_n: f1,
            span2_n: f2,
            mu,
            bristle_m: s.z,
            mesh_offset_m: p - s.b,
            slip_m_per_s: u,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet() -> PlantParams {
        let mut p = PlantParams::paper_rig();
        p.scale.noise_sd_m = 0.0;
        p
    }

    #[test]
    fn starts_at_rest_and_stays_there() {
        let mut plant = Plant::new(&quiet(), 100.0, 3).unwrap();
        let (m0, s0) = (plant.motor_counts(), plant.scale_counts());
        assert!((plant.carriage_mm() - 100.0).abs() < 1e-12);
        let f = plant.belt();
        assert!(f.tooth_n.abs() < 1e-9 && f.friction_n.abs() < 1e-9, "{f:?}");
        for _ in 0..2000 {
            plant.step(0.0, 5e-4);
        }
        assert_eq!(plant.motor_counts(), m0);
        assert_eq!(plant.scale_counts(), s0);
        assert!(plant.carriage_velocity_mm_s().abs() < 1e-9);
    }

    #[test]
    fn counters_wrap_like_16_bit_timers() {
        // Drive the motor backwards through zero and the scale across a 16-bit boundary.
        let mut plant = Plant::new(&quiet(), 0.05, 1).unwrap();
        let mut prev = (plant.motor_counter(), plant.motor_counts());
        let mut wrapped = false;
        for _ in 0..4000 {
            plant.step(-0.6, 5e-4);
            let now = (plant.motor_counter(), plant.motor_counts());
            assert_eq!(now.0, now.1 as u16);
            // The register difference, read as i16, is the true difference.
            assert_eq!(now.0.wrapping_sub(prev.0) as i16 as i64, now.1 - prev.1);
            wrapped |= now.0 > prev.0 && now.1 < prev.1;
            prev = now;
            assert_eq!(plant.scale_counter(), plant.scale_counts() as u16);
        }
        assert!(
            plant.motor_counts() < 0 && wrapped,
            "{}",
            plant.motor_counts()
        );
        assert!(plant.scale_counts() < 0);
    }

    #[test]
    fn current_is_clamped_and_lags() {
        let mut plant = Plant::new(&quiet(), 100.0, 1).unwrap();
        plant.step(1e6, 2e-4);
        let i = plant.current_a();
        // One time constant: 63 % of the 10 A limit.
        assert!((i - 10.0 * (1.0 - (-1.0f64).exp())).abs() < 0.05, "{i}");
        plant.step(f64::NAN, 1e-2);
        assert!(plant.current_a().abs() < 0.01);
    }

    #[test]
    fn seeds_change_the_run_but_not_the_geometry() {
        let p = quiet();
        let a = Plant::new(&p, 50.0, 1).unwrap();
        let b = Plant::new(&p, 50.0, 2).unwrap();
        assert_ne!(a.carriage_friction_n(), b.carriage_friction_n());
        assert!((a.motor_counts() - b.motor_counts()).abs() <= 1);
        let c = Plant::new(&p, 50.0, 1).unwrap();
        assert_eq!(a.carriage_friction_n(), c.carriage_friction_n());
    }
}
