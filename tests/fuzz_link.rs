//! 10,000 random and corrupted frames into the firmware's link path (receiver, endpoint, drive)
//! on the Cortex-M4: no panic, every frame rejected and counted, and the drive, enabled and at
//! rest, never moves. Run with `cargo test-target` (QEMU).
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
use {
    belt_drive::drive::{Drive, DriveConfig, Sample},
    belt_link::{encode, Command, Message, Receiver, Request, MAX_FRAME},
    estimator_core::endpoint::Endpoint,
};

/// Frames fed to the link.
#[cfg(target_os = "none")]
const FRAMES: u32 = 10_000;

#[cfg(target_os = "none")]
use belt_link::testing::{bad_frame, Rng};

#[cfg(target_os = "none")]
#[defmt_test::tests]
mod tests {
    use super::*;

    #[test]
    fn ten_thousand_bad_frames_change_nothing() {
        let mut drive = match Drive::new(&DriveConfig::paper_rig()) {
            Ok(d) => d,
            Err(_) => defmt::panic!("paper rig refused"),
        };
        let mut endpoint = Endpoint::new();
        let mut rx = Receiver::new();
        let rest = Sample {
            motor_counter: 1000,
            scale_counter: 2000,
        };

        // Enable through the link itself, so the drive could move if a frame got through.
        let mut wire = [0u8; MAX_FRAME];
        let n = encode(1, &Request::Command(Command::Enable), &mut wire);
        for &b in &wire[..n] {
            if let Some(Ok(f)) = rx.push::<Request>(b) {
                let _ = endpoint.handle_inline(&f.msg, &mut drive);
            }
        }
        defmt::assert_eq!(rx.frames_ok, 1);
        let before = drive.step(rest);

        let mut rng = Rng(0x1234_5678);
        let mut out = [0u8; MAX_FRAME + 16];
        for i in 0..FRAMES {
            let n = bad_frame(&mut rng, &mut out);
            let mut frames = 0;
            for &b in &out[..n] {
                match rx.push::<Request>(b) {
                    None => {}
                    Some(Err(_)) => frames += 1,
                    Some(Ok(f)) => {
                        defmt::panic!("frame {=u32} accepted: kind {=u8:#04x}", i, f.msg.kind())
                    }
                }
            }
            defmt::assert_eq!(frames, 1, "frame {=u32} split", i);
            let o = drive.step(rest);
            defmt::assert!(!o.telemetry.moving, "moving after frame {=u32}", i);
            defmt::assert_eq!(
                o.telemetry.setpoint_counts.0,
                before.telemetry.setpoint_counts.0
            );
            defmt::assert_eq!(o.current_a.to_bits(), before.current_a.to_bits());
        }
        defmt::assert_eq!(rx.frames_ok, 1);
        defmt::assert_eq!(rx.frames_bad, FRAMES);
        defmt::info!(
            "{=u32} bad frames rejected and counted, drive unmoved",
            rx.frames_bad
        );
    }
}
