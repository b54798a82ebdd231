//! One generator of bad link frames, for the on-target link fuzz (`tests/fuzz_link.rs`) and
//! hil-sim's PIL fuzzer (feature `testing`). Each call yields exactly one frame (one delimiter,
//! at the end) that the drive must reject: random bytes, bit flips under the CRC, wrong lengths,
//! unknown kinds, out-of-range values, broken COBS. Frames that carry a sequence number use 0,
//! which the PIL controller never uses for its own requests.

/// xorshift32: deterministic, so a failure reproduces.
pub struct Rng(pub u32);

impl Rng {
    /// The next 32 random bits.
    pub fn next_u32(&mut self) -> u32 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        self.0 = x;
        x
    }
    /// Uniform-ish in `0..n` (`n > 0`).
    pub fn below(&mut self, n: u32) -> u32 {
        self.next_u32() % n
    }
    /// A byte in `1..=255`.
    pub fn nonzero_byte(&mut self) -> u8 {
        1 + self.below(255) as u8
    }
}

/// A well-formed request of a random kind.
pub fn valid_request(rng: &mut Rng) -> crate::Request {
    use crate::{Command, Request};
    match rng.below(6) {
        0 => Request::Command(Command::MoveMotorTo {
            target_um: rng.next_u32() as i32,
            velocity_um_s: 1 + rng.below(100_000),
            accel_um_s2: 1 + rng.below(1_000_000),
        }),
        1 => Request::Command(Command::SelectModel(
            crate::ModelKind::ALL[rng.below(crate::ModelKind::ALL.len() as u32) as usize],
        )),
        2 => Request::Command(Command::Stop),
        3 => Request::Command(Command::Home {
            position_um: rng.next_u32() as i32,
            scale_um: rng.next_u32() as i32,
        }),
        4 => Request::CalBegin {
            total_len: 1 + rng.below(4096),
            crc32: rng.next_u32(),
        },
        _ => Request::Sample {
            motor_counter: rng.next_u32() as u16,
            scale_counter: rng.next_u32() as u16,
        },
    }
}

/// COBS-wraps `raw` with a delimiter; returns the wire length.
fn wrap(raw: &[u8], out: &mut [u8; crate::MAX_FRAME + 16]) -> usize {
    use crate::cobs_encode;
    let n = cobs_encode(raw, &mut out[..]).unwrap_or(0);
    out[n] = 0;
    n + 1
}

/// Raw frame (kind, seq, payload) with a correct CRC appended; returns its length.
fn seal(raw: &mut [u8; crate::MAX_RAW + 8], body_len: usize) -> usize {
    use crate::crc32;
    let crc = crc32(&raw[..body_len]);
    raw[body_len..body_len + 4].copy_from_slice(&crc.to_le_bytes());
    body_len + 4
}

/// The frame on the wire for the raw body `raw[..body_len]` (kind, seq, payload): CRC appended,
/// COBS, one delimiter; returns the wire length. Also for a host test that needs a frame the
/// typed encoder cannot write (a reply with a field out of range).
pub fn sealed_frame(
    raw: &mut [u8; crate::MAX_RAW + 8],
    body_len: usize,
    out: &mut [u8; crate::MAX_FRAME + 16],
) -> usize {
    let n = seal(raw, body_len);
    wrap(&raw[..n], out)
}

/// One bad frame on the wire (exactly one delimiter, at the end).
pub fn bad_frame(rng: &mut Rng, out: &mut [u8; crate::MAX_FRAME + 16]) -> usize {
    use crate::{
        cobs_decode_in_place, encode, kind, Command, Message, Request, CHUNK_MAX, MAX_ENCODED,
        MAX_FRAME, MAX_RAW,
    };
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
            let n = encode(0, &valid_request(rng), &mut wire);
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
            raw[1] = 0;
            let good = req.write_payload(&mut raw[2..2 + MAX_RAW - 6]);
            let mut len = rng.below(CHUNK_MAX as u32) as usize;
            if len == good {
                len += 1;
            }
            for b in raw[2 + good.min(len)..2 + len].iter_mut() {
                *b = rng.next_u32() as u8;
            }
            sealed_frame(&mut raw, 2 + len, out)
        }
        // Correct CRC, a kind the drive does not accept (unused or a reply kind).
        3 => {
            raw[0] = if rng.below(2) == 0 {
                // The first kind after the last request kind, up to 0x7f.
                kind::LAST_REQUEST + 1 + rng.below(0x7f - kind::LAST_REQUEST as u32) as u8
            } else {
                kind::ACK + rng.below(0x7f) as u8
            };
            raw[1] = 0;
            let len = rng.below(20) as usize;
            for b in raw[2..2 + len].iter_mut() {
                *b = rng.next_u32() as u8;
            }
            sealed_frame(&mut raw, 2 + len, out)
        }
        // Correct CRC and length, a value out of range.
        4 => {
            let k = rng.below(4);
            let len = if k == 2 {
                // A compensator number past the last (no `ModelKind` carries it): raw bytes.
                raw[0] = crate::kind::SELECT_MODEL;
                raw[1] = 0;
                raw[2] = crate::MODEL_MAX + 1 + rng.below(255 - crate::MODEL_MAX as u32) as u8;
                1
            } else {
                let req = match k {
                    0 => Request::Command(Command::MoveMotorTo {
                        target_um: rng.next_u32() as i32,
                        velocity_um_s: 0,
                        accel_um_s2: 1 + rng.below(1000),
                    }),
                    1 => Request::Command(Command::MoveMotorTo {
                        target_um: rng.next_u32() as i32,
                        velocity_um_s: 1 + rng.below(1000),
                        accel_um_s2: 0,
                    }),
                    _ => Request::CalBegin {
                        total_len: 0,
                        crc32: rng.next_u32(),
                    },
                };
                raw[0] = req.kind();
                raw[1] = 0;
                req.write_payload(&mut raw[2..2 + MAX_RAW - 6])
            };
            sealed_frame(&mut raw, 2 + len, out)
        }
        // A valid frame whose first COBS code points past the end.
        _ => {
            let mut wire = [0u8; MAX_FRAME];
            let n = encode(0, &valid_request(rng), &mut wire);
            out[..n].copy_from_slice(&wire[..n]);
            out[0] = (n as u8)
                .saturating_add(1 + rng.below(100) as u8)
                .max(n as u8 + 1);
            n
        }
    }
}
