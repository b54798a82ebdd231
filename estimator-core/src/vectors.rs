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

/// Ticks of the belt observer's run.
pub const BELT_TICKS: u32 = 3000;

/// Digest of the belt observer's run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BeltDigest {
    /// CRC-32 of every tick's offset and error bits.
    pub crc: u32,
    /// Final mesh offset, I16F16 um.
    pub final_offset_bits: i32,
    /// Smallest and largest offset over the run (shows the belt crossed the gap).
    pub offset_range_bits: (i32, i32),
    /// What `measure` returned: sum and largest of the whole step (instructions on the
    /// target).
    pub measured_sum: u64,
    /// See [`BeltDigest::measured_sum`].
    pub measured_max: u32,
    /// The same per part of the step ([`crate::model::belt::BeltState::advance`]).
    pub part_sum: [u64; crate::model::belt::STEP_PARTS as usize],
    /// See [`BeltDigest::part_sum`].
    pub part_max: [u32; crate::model::belt::STEP_PARTS as usize],
}

/// Step lengths of the belt observer's runs, ticks ([`belt_observer`]).
pub const BELT_EVERY: [u32; 4] = [1, 2, 4, 6];

/// The fixed-point belt observer (`model::belt`) on the paper rig's physics with a guide
/// profile, a step every `every` ticks, through moves out and back (trapezoids, 25 um per tick
/// at most, with the current a drive would draw). `measure` runs one tick
/// ([`crate::model::belt::BeltState::tick`] or its equivalent) and returns the cost of each
/// part, or of the tick in the first (0 on the host).
#[inline(never)]
pub fn belt_observer(
    every: u32,
    mut measure: impl FnMut(
        &mut crate::model::belt::BeltState,
        &crate::model::belt::BeltCoeffs,
        i32,
        i32,
    ) -> [u32; crate::model::belt::STEP_PARTS as usize],
) -> BeltDigest {
    use crate::model::belt::{BeltParams, BeltState, STEP_PARTS};
    use belt_link::Crc32;
    // A guide profile of 40 points, 10 mm apart, -0.8..0.8 N.
    let mut p = BeltParams::PAPER;
    p.guide_bins = 40;
    for (k, d) in p.guide_delta_n.iter_mut().take(40).enumerate() {
        *d = ((k * 37) % 17) as f64 * 0.1 - 0.8;
    }
    let Ok(c) = p.build_every(1.0 / 2000.0, every) else {
        panic!("paper physics refused")
    };
    let mut s = BeltState::new(&c, 0);
    let mut crc = Crc32::new();
    let mut digest = BeltDigest {
        crc: 0,
        final_offset_bits: 0,
        offset_range_bits: (i32::MAX, i32::MIN),
        measured_sum: 0,
        measured_max: 0,
        part_sum: [0; STEP_PARTS as usize],
        part_max: [0; STEP_PARTS as usize],
    };
    // Velocity in Q8 counts per tick, acceleration 1/8 count per tick² (~0.27 m/s²).
    let (mut pos_q8, mut vel_q8) = (0i64, 0i64);
    let targets = [60_000i64, 10_000, 40_000, 38_000];
    let mut next = 0;
    for _ in 0..BELT_TICKS {
        let target = targets[next.min(targets.len() - 1)] << 8;
        let to_go = target - pos_q8;
        // Brake when the distance to stop reaches what is left.
        let stop_q8 = vel_q8 * vel_q8 / (2 * 32) + vel_q8.abs();
        let want = if to_go.abs() <= stop_q8 {
            0
        } else {
            to_go.signum() * 47 * 256
        };
        let accel = (want - vel_q8).clamp(-32, 32);
        vel_q8 += accel;
        pos_q8 += vel_q8;
        if to_go.abs() < 256 && vel_q8.abs() < 64 && next < targets.len() {
            next += 1;
        }
        // Current: 0.2 A per 1/8 count per tick², 0.15 A against the motion.
        let current_bits = (accel * 13_107 / 32 + vel_q8.signum() * 9_830) as i32;
        let counts = (pos_q8 >> 8) as i32;
        let parts = measure(&mut s, &c, counts, current_bits);
        let cost = parts.iter().sum::<u32>();
        for (k, &part) in parts.iter().enumerate() {
            digest.part_sum[k] += part as u64;
            digest.part_max[k] = digest.part_max[k].max(part);
        }
        digest.measured_sum += cost as u64;
        digest.measured_max = digest.measured_max.max(cost);
        let (o, e) = (s.offset_um_bits(), s.error_um_bits());
        crc.update(&o.to_le_bytes());
        crc.update(&e.to_le_bytes());
        let (lo, hi) = digest.offset_range_bits;
        digest.offset_range_bits = (lo.min(o), hi.max(o));
    }
    digest.crc = crc.finish();
    digest.final_offset_bits = s.offset_um_bits();
    digest
}
