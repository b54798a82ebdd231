//! `cargo bench -p estimator-core --bench step`: host time of one `Drive::step` per model, on a
//! move with reversals (the Fig. 18 pattern) against a lumped-mass motor. Host numbers only rank
//! the models; the Cortex-M4 budget is counted in instructions under QEMU (see README).

use std::hint::black_box;
use std::time::Instant;

use estimator_core::drive::{Command, Drive, DriveConfig, Sample};
use estimator_core::model::ModelKind;
use estimator_core::rig::Rig;

/// A drive homed at 150 mm, enabled, with `kind` selected.
fn ready(kind: ModelKind) -> Drive {
    let mut d = Drive::new(&DriveConfig::paper_rig()).expect("paper rig");
    d.step(Sample::default());
    let home = Command::Home {
        position_um: 150_000,
        scale_um: 0,
    };
    d.command(home).expect("home");
    d.command(Command::Enable).expect("enable");
    d.command(Command::SelectModel(kind)).expect("model");
    d
}

fn main() {
    let cpm = Rig::PAPER.counts_per_mm();
    const TICKS: usize = 400_000;
    println!("Drive::step on the host, {TICKS} ticks per model (moves with reversals)");
    for kind in ModelKind::ALL {
        let mut d = ready(kind);
        // Ideal motor following the set-point: the per-tick path sees real motion.
        let (mut x, mut v) = (150.0 * cpm, 0.0f64);
        let targets = [200_000, 120_000, 180_000, 90_000, 160_000];
        let mut samples = Vec::with_capacity(TICKS);
        let mut outs = Vec::with_capacity(TICKS);
        for k in 0..TICKS {
            if k % 40_000 == 0 {
                let t = targets[(k / 40_000) % targets.len()];
                let _ = d.command(Command::MoveMotorTo {
                    target_um: t,
                    velocity_um_s: 80_000,
                    accel_um_s2: 1_500_000,
                });
            }
            let s = Sample {
                motor_counter: (x as i64) as u16,
                scale_counter: 0,
            };
            samples.push(s);
            // A frame each tick, as the firmware's sample frames feed it: without it the link
            // watchdog trips and the rest of the run is a faulted drive's.
            d.link_alive();
            let o = d.step(s);
            v += (o.current_a.to_num::<f64>() * 1.09e3 * cpm - 2.0 * v) / 2000.0;
            x += v / 2000.0;
            outs.push(o);
        }
        // Timed pass: replay the recorded samples through a fresh drive in the same state.
        let mut d2 = ready(kind);
        let start = Instant::now();
        for (k, s) in samples.iter().enumerate() {
            if k % 40_000 == 0 {
                let t = targets[(k / 40_000) % targets.len()];
                let _ = d2.command(Command::MoveMotorTo {
                    target_um: t,
                    velocity_um_s: 80_000,
                    accel_um_s2: 1_500_000,
                });
            }
            d2.link_alive();
            black_box(d2.step(black_box(*s)));
        }
        let ns = start.elapsed().as_nanos() as f64 / TICKS as f64;
        assert_eq!(d2.telemetry(), outs[TICKS - 1].telemetry, "replay diverged");
        assert!(d2.faults().is_clear(), "{kind:?}: {:?}", d2.faults());
        println!("  {:<7} {:6.1} ns/step", kind.as_str(), ns);
    }
}
