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
    estimator_core::link::Endpoint,
    estimator_core::link::{
        cobs_encode, cobs_decode_in_place, crc32, encode, kind, Message, Receiver, Request,
        CHUNK_MAX, MAX_ENCODED, MAX_FRAME, MAX_RAW,
    },
};

/// Frames fed to the link.
#[cfg(target_os = "none")]
const FRAMES: u32 = 10_000;

/// xorshift32: deterministic, so a failure reproduces.
#[cfg(target_os = "none")]
struct Rng(u32);

#[cfg(target_os = "none")]
impl Rng {
    fn next(&mut self) -> u32 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        self.0 = x;
        x
    }
    fn below(&mut self, n: u32) -> u32 {
        self.next() % n
    }
    fn nonzero_byte(&mut self) -> u8 {
        1 + self.below(255) as u8
    }
}

/// A well-formed request of a random kind.
#[cfg(target_os = "none")]
fn valid_request(rng: &mut Rng) -> Request {
    match rng.below(6) {
        0 => Request::Move {
            target_um: rng.next() as i32,
            velocity_um_s: 1 + rng.below(100_000),
            accel_um_s2: 1 + rng.below(1_000_000),
        },
        1 => Request::SelectModel(rng.below(4) as u8),
        2 => Request::Stop,
        3 => Request::Home { position_um: rng.next() as i32, scale_um: rng.next() as i32 },
        4 => Request::CalBegin { total_len: 1 + rng.below(4096), crc32: rng.next() },
        _ => Request::Sample { motor_counter: rng.next() as u16, scale_counter: rng.next() as u16 },
    }
}

/// COBS-wraps `raw` with a delimiter; returns the wire length.
#[cfg(target_os = "none")]
fn wrap(raw: &[u8], out: &mut [u8; MAX_FRAME + 16]) -> usize {
    let n = cobs_encode(raw, &mut out[..]).unwrap_or(0);
    out[n] = 0;
    n + 1
}

/// Raw frame (kind, seq, payload) with a correct CRC appended; returns its length.
#[cfg(target_os = "none")]
fn seal(raw: &mut [u8; MAX_RAW + 8], body_len: usize) -> usize {
    let crc = crc32(&raw[..body_len]);
    raw[body_len..body_len + 4].copy_from_slice(&crc.to_le_bytes());
    body_len + 4
}

/// One bad frame on the wire (exactly one delimiter, at the end).
#[cfg(target_os = "none")]
fn bad_frame(rng: &mut Rng, out: &mut [u8; MAX_FRAME + 16]) -> usize {
    let mut raw = [0u8; MAX_RAW + 8];
    match rng.below(6) {
        // Random non-zero bytes, sometimes longer than any frame.
        0 => {
            let n = 1 + rng.below(MAX_ENCODED as u32 + 12) as usize;
            for b in out[..n].iter_mut() {
                *b = rng.nonzero_byte();
            }
            out[n] = 0;
            n + 1
        }
        // A valid frame with 1 to 3 bits flipped under the CRC.
        1 => {
            let mut wire = [0u8; MAX_FRAME];
            let n = encode(rng.next() as u8, &valid_request(rng), &mut wire);
            let m = cobs_decode_in_place(&mut wire[..n - 1]).unwrap_or(0);
            raw[..m].copy_from_slice(&wire[..m]);
            // Distinct bits: flipping one bit twice would give the valid frame back.
            let first = rng.below(m as u32 * 8) as usize;
            for k in 0..1 + rng.below(3) as usize {
                let bit = (first + 7 * k) % (m * 8);
                raw[bit / 8] ^= 1 << (bit % 8);
            }
            wrap(&raw[..m], out)
        }
        // Correct CRC, wrong payload length for the kind.
        2 => {
            let req = valid_request(rng);
            raw[0] = req.kind();
            raw[1] = rng.next() as u8;
            let good = req.write_payload(&mut raw[2..2 + MAX_RAW - 6]);
            let mut len = rng.below(CHUNK_MAX as u32) as usize;
            if len == good {
                len += 1;
            }
            for b in raw[2 + good.min(len)..2 + len].iter_mut() {
                *b = rng.next() as u8;
            }
            let n = seal(&mut raw, 2 + len);
            wrap(&raw[..n], out)
        }
        // Correct CRC, a kind the drive does not accept (unused or a reply kind).
        3 => {
            raw[0] = if rng.below(2) == 0 { 0x0f + rng.below(0x70) as u8 } else { kind::ACK + rng.below(0x7f) as u8 };
            raw[1] = rng.next() as u8;
            let len = rng.below(20) as usize;
            for b in raw[2..2 + len].iter_mut() {
                *b = rng.next() as u8;
            }
            let n = seal(&mut raw, 2 + len);
            wrap(&raw[..n], out)
        }
        // Correct CRC and length, a value out of range.
        4 => {
            let req = match rng.below(4) {
                0 => Request::Move { target_um: rng.next() as i32, velocity_um_s: 0, accel_um_s2: 1 + rng.below(1000) },
                1 => Request::Move { target_um: rng.next() as i32, velocity_um_s: 1 + rng.below(1000), accel_um_s2: 0 },
                2 => Request::SelectModel(4 + rng.below(252) as u8),
                _ => Request::CalBegin { total_len: 0, crc32: rng.next() },
            };
            raw[0] = req.kind();
            raw[1] = rng.next() as u8;
            let len = req.write_payload(&mut raw[2..2 + MAX_RAW - 6]);
            let n = seal(&mut raw, 2 + len);
            wrap(&raw[..n], out)
        }
        // A valid frame whose first COBS code points past the end.
        _ => {
            let mut wire = [0u8; MAX_FRAME];
            let n = encode(rng.next() as u8, &valid_request(rng), &mut wire);
            out[..n].copy_from_slice(&wire[..n]);
            out[0] = (n as u8).saturating_add(1 + rng.below(100) as u8).max(n as u8 + 1);
            n
        }
    }
}

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
        let rest = Sample { motor_counter: 1000, scale_counter: 2000 };

        // Enable through the link itself, so the drive could move if a frame got through.
        let mut wire = [0u8; MAX_FRAME];
        let n = encode(1, &Request::Enable, &mut wire);
        for &b in &wire[..n] {
            if let Some(Ok(f)) = rx.push::<Request>(b) {
                let _ = endpoint.handle(&f.msg, &mut drive);
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
                    Some(Ok(f)) => defmt::panic!("frame {=u32} accepted: kind {=u8:#04x}", i, f.msg.kind()),
                }
            }
            defmt::assert_eq!(frames, 1, "frame {=u32} split", i);
            let o = drive.step(rest);
            defmt::assert!(!o.telemetry.moving, "moving after frame {=u32}", i);
            defmt::assert_eq!(o.telemetry.setpoint_counts, before.telemetry.setpoint_counts);
            defmt::assert_eq!(o.current_a.to_bits(), before.current_a.to_bits());
        }
        defmt::assert_eq!(rx.frames_ok, 1);
        defmt::assert_eq!(rx.frames_bad, FRAMES);
        defmt::info!("{=u32} bad frames rejected and counted, drive unmoved", rx.frames_bad);
    }
}
