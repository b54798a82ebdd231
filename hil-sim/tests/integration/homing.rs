//! The drive's homing routine on the simulated plant: a slow, current-limited jog into the end
//! stop, found by the following error; the stop becomes the homing position for the motor and
//! the scale, and the drive backs off. A stop that is not there fails by name, at zero current.

use estimator_core::drive::{Command, CommandError, Drive, DriveConfig, Faults, Parts};
use estimator_core::settings::{HomingConfig, Settings};
use hil_sim::plant::{Plant, PlantParams};
use hil_sim::run::sample;

/// The paper rig homing onto the plant's lower stop (-10 mm), backing off into the travel
/// (to 5 mm).
fn settings() -> Settings {
    let mut s = Settings::PAPER;
    s.travel_margin_mm = 12.0;
    s.homing = HomingConfig {
        position_mm: -10.0,
        backoff_mm: 15.0,
        ..HomingConfig::DEFAULT
    };
    s
}

fn drive(s: &Settings) -> Drive {
    let mut d = Drive::new(&DriveConfig::paper_rig()).unwrap();
    d.reconfigure(Parts::build(s).unwrap()).unwrap();
    d
}

/// Runs until `done` or `max_s` of plant time; returns the time taken.
fn run(d: &mut Drive, p: &mut Plant, max_s: f64, done: impl Fn(&Drive) -> bool) -> f64 {
    let dt = 1.0 / 2000.0;
    let mut t = 0.0;
    while t < max_s && !done(d) {
        // A host that keeps the link alive.
        d.link_alive();
        let out = d.step(sample(p));
        p.step(out.current_a.to_num::<f64>(), dt);
        t += dt;
    }
    t
}

#[test]
fn homing_finds_the_stop_and_ties_motor_and_scale_to_it() {
    let s = settings();
    let plant = PlantParams::paper_rig();
    let mut p = Plant::new(&plant, 120.0, 3).unwrap();
    let mut d = drive(&s);
    // Refused before enabling; enabling needs no homing.
    assert_eq!(d.command(Command::Homing), Err(CommandError::NotEnabled));
    let _ = d.step(sample(&p));
    d.command(Command::Enable).unwrap();
    d.command(Command::Homing).unwrap();
    assert!(d.is_homing());
    // Moves are refused until homed.
    let mv = Command::MoveTo {
        target_um: 50_000,
        velocity_um_s: 50_000,
        accel_um_s2: 500_000,
    };
    assert_eq!(d.command(mv), Err(CommandError::NotHomed));
    // 130 mm at 10 mm/s.
    let t = run(&mut d, &mut p, 20.0, |d| !d.is_homing());
    assert!(d.faults().is_clear(), "{:?}", d.faults());
    assert!(d.is_homed(), "homed after {t:.2} s");
    assert!((12.0..15.0).contains(&t), "{t} s to the stop");
    // The carriage presses into the stop (the plant's stop is compliant): the scale reads the
    // homing position there, a fixed offset from the true carriage.
    let tel = d.telemetry();
    assert_eq!(tel.scale_counts.0, -20_000);
    let pressed_um = p.carriage_mm() * 1000.0 - -10_000.0;
    assert!((-300.0..0.0).contains(&pressed_um), "{pressed_um} um");
    // Back off to 5 mm, then a move works.
    run(&mut d, &mut p, 3.0, |d| !d.telemetry().moving);
    run(&mut d, &mut p, 0.3, |_| false);
    let c = p.carriage_mm();
    assert!((c - 5.0).abs() < 0.5, "backed off to {c} mm");
    d.command(mv).unwrap();
    run(&mut d, &mut p, 2.0, |_| false);
    assert!(d.faults().is_clear(), "{:?}", d.faults());
    assert!((p.carriage_mm() - 50.0).abs() < 0.5, "{}", p.carriage_mm());

    // Homing again from there finds the stop at the same carriage position: repeatable to
    // micrometres, so a calibration made after homing holds after the next.
    d.command(Command::Homing).unwrap();
    run(&mut d, &mut p, 20.0, |d| !d.is_homing());
    assert!(d.is_homed() && d.faults().is_clear());
    let again_um = p.carriage_mm() * 1000.0 - -10_000.0;
    assert!(
        (again_um - pressed_um).abs() < 5.0,
        "{pressed_um} then {again_um} um"
    );
}

#[test]
fn a_missing_stop_fails_by_name_at_zero_current() {
    // A drive configured for 50 mm of travel on a stage whose stop is 160 mm away: the search
    // (travel, both margins, backoff: 89 mm) ends without finding it.
    let mut s = settings();
    s.travel_max_mm = 50.0;
    let plant = PlantParams::paper_rig();
    let mut p = Plant::new(&plant, 150.0, 3).unwrap();
    let mut d = drive(&s);
    let _ = d.step(sample(&p));
    d.command(Command::Enable).unwrap();
    d.command(Command::Homing).unwrap();
    let t = run(&mut d, &mut p, 40.0, |d| !d.is_homing());
    assert!(
        (8.8..9.5).contains(&t),
        "{t} s, {:?}, carriage {} mm",
        d.faults(),
        p.carriage_mm()
    );
    assert_eq!(d.faults().0, Faults::HOMING_FAILED, "{:?}", d.faults());
    assert!(!d.is_homed());
    let out = d.step(sample(&p));
    assert_eq!(out.current_a.to_num::<f64>(), 0.0);
    assert!(!out.telemetry.amplifier_enabled);
}

#[test]
fn an_unconfigured_drive_refuses_to_enable_and_bad_homing_is_refused_by_name() {
    let mut d = Drive::new(&DriveConfig::paper_rig()).unwrap();
    d.forget_configuration();
    assert_eq!(d.command(Command::Enable), Err(CommandError::Unconfigured));
    let settings = |homing| Settings {
        homing,
        ..Settings::PAPER
    };
    for (h, field) in [
        (
            HomingConfig {
                position_mm: -50.0,
                ..HomingConfig::DEFAULT
            },
            "homing.position_mm",
        ),
        (
            HomingConfig {
                detect_error_mm: 2.0,
                ..HomingConfig::DEFAULT
            },
            "homing.detect_error_mm",
        ),
        (
            HomingConfig {
                current_a: 20.0,
                ..HomingConfig::DEFAULT
            },
            "homing.current_a",
        ),
        (
            HomingConfig {
                velocity_mm_s: f64::NAN,
                ..HomingConfig::DEFAULT
            },
            "homing.velocity_mm_s",
        ),
    ] {
        assert_eq!(Parts::build(&settings(h)).unwrap_err().field(), field);
    }
    d.reconfigure(Parts::build(&settings(HomingConfig::DEFAULT)).unwrap())
        .unwrap();
    assert_eq!(d.command(Command::Enable), Ok(()));
}
