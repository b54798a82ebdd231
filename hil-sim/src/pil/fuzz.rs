//! Bad frames through the firmware's real link path under QEMU (USART2 RX interrupt, receiver,
//! endpoint), interleaved with PIL ticks: every frame must be rejected and counted, and the
//! drive, enabled and at rest, must answer every tick exactly like an in-process core that never
//! saw the garbage.

use belt_link::MAX_FRAME;
use estimator_core::drive::{Command, Drive, DriveConfig, Sample};

use super::{PilController, PilError, PilOptions};
use crate::run::keepalive_ticks;

use belt_link::testing as gen;

/// Bad frames between two ticks (keeps the error replies flowing back in small batches).
const FRAMES_PER_TICK: u32 = 10;
/// The first frames go out in one write (about 3 KB, many times the firmware's 128-byte
/// receive queue): the queue fills and the receive path must pause and resume without losing
/// a byte or its wake-up.
const BURST_FRAMES: u32 = 60;

/// Outcome of [`run`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FuzzReport {
    /// Rejected frames the firmware counted during the run.
    pub frames_bad: u32,
    /// Frames the firmware accepted beyond our own requests (must be 0).
    pub frames_ok_extra: u32,
    /// Ticks run.
    pub ticks: u32,
    /// Every tick's output equalled the undisturbed core's, at rest.
    pub unmoved: bool,
    /// QEMU's exit status.
    pub exit_status: i32,
}

/// Sends `n` bad frames to the firmware.
pub fn run(opts: &PilOptions, n: u32) -> Result<FuzzReport, PilError> {
    // The firmware boots uncalibrated; so does its host twin.
    let cfg = DriveConfig {
        model: estimator_core::drive::Models::Image(&[]),
        ..DriveConfig::paper_rig()
    };
    let mut host = Drive::new(&cfg)?;
    let mut fw = PilController::start(opts)?;
    let rest = Sample {
        motor_counter: 1234,
        scale_counter: 4321,
    };
    let mut unmoved = host.step(rest) == fw.step_sample(rest)?;
    for c in [
        Command::Home {
            position_um: 100_000,
            scale_um: 100_000,
        },
        Command::Enable,
    ] {
        host.command(c).map_err(PilError::Refused)?;
        fw.send_command(c)?;
    }
    let before = fw.status()?;
    let mut rng = gen::Rng(0x5eed_f00d);
    let mut buf = [0u8; MAX_FRAME + 16];
    let mut burst = Vec::new();
    let mut ticks = 0u32;
    let mut keepalives = 0u32;
    let keepalive = keepalive_ticks(1.0 / cfg.settings.rate_hz);
    for i in 0..n {
        let len = gen::bad_frame(&mut rng, &mut buf);
        if i < BURST_FRAMES {
            burst.extend_from_slice(&buf[..len]);
            if i + 1 < BURST_FRAMES.min(n) {
                continue;
            }
            fw.send_raw(&std::mem::take(&mut burst))?;
        } else {
            fw.send_raw(&buf[..len])?;
        }
        if (i + 1) % FRAMES_PER_TICK == 0 || i + 1 == n {
            let a = host.step(rest);
            let b = match fw.step_sample(rest) {
                Ok(b) => b,
                Err(e) => {
                    // Whether the firmware still answers at all tells a hang from a lost
                    // frame.
                    let then = match fw.status() {
                        Ok(st) => format!(
                            "answered: tick {}, frames ok {}, bad {}",
                            st.tick, st.frames_ok, st.frames_bad
                        ),
                        Err(e2) => format!("{e2} either: the firmware hangs"),
                    };
                    crate::errln!(
                        "PIL fuzz: tick {} after {} bad frames got no answer; a status request \
                         then: {then}",
                        ticks + 1,
                        i + 1
                    );
                    return Err(e);
                }
            };
            unmoved &= a == b && !b.telemetry.moving;
            ticks += 1;
            // A host keeps both link watchdogs fed, as a run's does: here, right after an
            // answer, no bad frame is in flight.
            if u64::from(ticks).is_multiple_of(keepalive) {
                host.link_alive();
                fw.status()?;
                keepalives += 1;
            }
        }
    }
    let after = fw.status()?;
    // Our own accepted frames since `before`: one sample per tick, the keepalives and this
    // status request.
    let ours = ticks + keepalives + 1;
    let exit_status = fw.shutdown(0)?;
    Ok(FuzzReport {
        frames_bad: after.frames_bad - before.frames_bad,
        frames_ok_extra: (after.frames_ok - before.frames_ok).saturating_sub(ours),
        ticks,
        unmoved,
        exit_status,
    })
}
