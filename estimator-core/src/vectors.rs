//! The closed-loop run behind the on-target core vectors (feature `vectors`): `build.rs` runs it
//! on the host for the expected digests and `tests/core_vectors.rs` on the Cortex-M4, with an
//! integer stand-in for the plant so that the only arithmetic that could differ is the core's.

/// Ticks digested per block.
pub const BLOCK_TICKS: usize = 256;
/// Longest run, ticks.
pub const MAX_TICKS: usize = 16 * BLOCK_TICKS;

/// Digest of one closed-loop run: CRC-32 of every tick's PIL answer, per block of ticks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RunDigest {
    /// Ticks run.
    pub ticks: u32,
    /// Block CRCs (unused blocks 0).
    pub blocks: [u32; MAX_TICKS / BLOCK_TICKS],
    /// Final motor position, counts.
    pub final_counts: i32,
    /// Sum of |estimated error| bits over the run (shows that the model ran).
    pub est_abs_sum: u64,
}

/// Runs the paper rig through three moves (out, back, and a short reversal) with `model`.
/// Never inlined: its frame (drive and configuration) must not stay on the caller's stack.
#[inline(never)]
pub fn closed_loop(model: crate::model::ModelKind) -> RunDigest {
    use crate::drive::{Command, Drive, DriveConfig, Sample};
    use crate::endpoint::answer;
    use belt_link::{Crc32, Message, MAX_PAYLOAD};

    let mut drive = match Drive::new(&DriveConfig::paper_rig()) {
        Ok(d) => d,
        Err(_) => panic!("paper rig refused"),
    };
    // The integer plant: the motor lands on the set-point, pushed off it by the current.
    // `pos` is the raw counter's unwrapped value (the drive's zero is set by homing).
    let mut pos: i64 = 0;
    let sample = |pos: i64| Sample {
        motor_counter: pos as u16,
        scale_counter: (pos * 1070 / 1000) as u16,
    };
    let _ = drive.step(sample(pos));
    let setup = [
        Command::Home {
            position_um: 10_000,
            scale_um: 10_000,
        },
        Command::Enable,
        Command::SelectModel(model),
    ];
    for c in setup {
        if drive.command(c).is_err() {
            panic!("setup command refused");
        }
    }
    let moves = [
        (60_000, 100_000, 2_000_000),
        (30_000, 150_000, 3_000_000),
        (30_500, 20_000, 500_000),
    ];
    let mut digest = RunDigest {
        ticks: 0,
        blocks: [0; MAX_TICKS / BLOCK_TICKS],
        final_counts: 0,
        est_abs_sum: 0,
    };
    let mut crc = Crc32::new();
    let mut next_move = 0;
    let mut rest_ticks = 0;
    for tick in 0..MAX_TICKS {
        if rest_ticks == 20 && next_move < moves.len() {
            let (target_um, velocity_um_s, accel_um_s2) = moves[next_move];
            if let Err(e) = drive.command(Command::MoveMotorTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }) {
                panic!(
                    "move {} refused: {:?}, faults {:?}",
                    next_move,
                    e,
                    drive.telemetry().faults
                );
            }
            next_move += 1;
            rest_ticks = 0;
        }
        // A host is connected: it keeps the link watchdog fed.
        drive.link_alive();
        let out = drive.step(sample(pos));
        let t = out.telemetry;
        let mut bytes = [0u8; MAX_PAYLOAD];
        let n = answer(&out, 0).write_payload(&mut bytes);
        crc.update(&bytes[..n]);
        digest.est_abs_sum += t.est_error_um.to_bits().unsigned_abs() as u64;
        let push = ((out.current_a.to_bits() as i64) * 3) >> 16;
        // The raw counter moves by what takes the motor to the set-point, plus the push.
        pos += (t.setpoint_counts.0 as i64 - t.motor_counts.0 as i64) + push.clamp(-100, 100);
        rest_ticks = if t.moving { 0 } else { rest_ticks + 1 };
        digest.ticks += 1;
        if (tick + 1) % BLOCK_TICKS == 0 {
            digest.blocks[tick / BLOCK_TICKS] = crc.finish();
            crc = Crc32::new();
        }
        if next_move == moves.len() && rest_ticks > 20 {
            digest.blocks[tick / BLOCK_TICKS] = crc.finish();
            break;
        }
    }
    digest.final_counts = drive.telemetry().motor_counts.0;
    digest
}
