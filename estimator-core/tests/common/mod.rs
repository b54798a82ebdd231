//! What the drive-level tests share: a rigid stage to close the loop on, homing, a move.
#![allow(dead_code)]

use estimator_core::drive::{Command, Drive, DriveConfig, Sample};

/// Rigid stage: 1.09 m/s^2 per ampere (the PID defaults' design point), light viscous loss.
pub struct Mass {
    pub x_counts: f64,
    pub v_counts_s: f64,
    pub cpm: f64,
    /// -1: the motor wires are reversed.
    pub sign: f64,
}

impl Mass {
    pub fn new(x_mm: f64) -> Mass {
        let cpm = estimator_core::rig::Rig::PAPER.counts_per_mm();
        Mass {
            x_counts: x_mm * cpm,
            v_counts_s: 0.0,
            cpm,
            sign: 1.0,
        }
    }
    pub fn sample(&self) -> Sample {
        Sample {
            motor_counter: (self.x_counts.floor() as i64) as u16,
            scale_counter: 0,
        }
    }
    pub fn step(&mut self, current_a: f64, dt: f64) {
        let a_counts_s2 = self.sign * current_a * 1.09e3 * self.cpm - 2.0 * self.v_counts_s;
        self.v_counts_s += a_counts_s2 * dt;
        self.x_counts += self.v_counts_s * dt;
    }
}

/// A drive built from `cfg`, homed with the stage at `x_mm`.
pub fn homed_with(cfg: &DriveConfig, x_mm: f64) -> (Drive, Mass) {
    let mut d = Drive::new(cfg).unwrap();
    let m = Mass::new(x_mm);
    d.step(m.sample());
    d.command(Command::Home {
        position_um: (x_mm * 1000.0) as i32,
        scale_um: 0,
    })
    .unwrap();
    (d, m)
}

/// A motor move at 80 mm/s and 1000 mm/s^2.
pub fn mv(target_mm: f64) -> Command {
    Command::MoveMotorTo {
        target_um: (target_mm * 1000.0) as i32,
        velocity_um_s: 80_000,
        accel_um_s2: 1_000_000,
    }
}
