//! The link decoder on the Cortex-M4: known wire bytes, round trips, and bad frames.
//! Run with `cargo test-target` (QEMU).
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {}

#[cfg(target_os = "none")]
use belt_drive as _;

#[cfg(target_os = "none")]
use belt_link::{
    cobs_encode, crc32, encode, kind, Command, Faults, Frame, LinkError, Message, ModelKind,
    MotorCounts, Receiver, Reply, Request, ScaleCounts, Telemetry, WireStatus, CHUNK_MAX,
    MAX_ENCODED, MAX_FRAME, MAX_RAW, MODEL_MAX,
};
#[cfg(target_os = "none")]
use estimator_core::fixed::types::I16F16;

/// The same bytes as the host test `known_wire_bytes` (computed independently in Python).
#[cfg(target_os = "none")]
const KNOWN_MOVE_MOTOR: [u8; 20] = [
    9, 1, 9, 112, 47, 252, 255, 80, 195, 1, 4, 64, 13, 3, 5, 157, 230, 2, 169, 0,
];

#[cfg(target_os = "none")]
fn feed(rx: &mut Receiver, bytes: &[u8]) -> Option<Result<Frame<Request>, u8>> {
    let mut last = None;
    for &b in bytes {
        if let Some(r) = rx.push::<Request>(b) {
            last = Some(r.map_err(|e| e.error as u8));
        }
    }
    last
}

/// A wire frame with a correct CRC around arbitrary raw content.
#[cfg(target_os = "none")]
fn with_crc(body: &[u8], out: &mut [u8; MAX_FRAME + 8]) -> usize {
    let mut raw = [0u8; MAX_RAW + 8];
    raw[..body.len()].copy_from_slice(body);
    raw[body.len()..body.len() + 4].copy_from_slice(&crc32(body).to_le_bytes());
    let n = cobs_encode(&raw[..body.len() + 4], &mut out[..]).unwrap();
    out[n] = 0;
    n + 1
}

#[cfg(target_os = "none")]
#[defmt_test::tests]
mod tests {
    use super::*;

    #[test]
    fn crc_check_value() {
        defmt::assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn known_move_bytes() {
        let mut out = [0u8; MAX_FRAME];
        let req = Request::Command(Command::MoveMotorTo {
            target_um: -250_000,
            velocity_um_s: 50_000,
            accel_um_s2: 200_000,
        });
        let n = encode(9, &req, &mut out);
        defmt::assert_eq!(&out[..n], &KNOWN_MOVE_MOTOR[..]);
        let mut rx = Receiver::new();
        defmt::assert!(feed(&mut rx, &KNOWN_MOVE_MOTOR) == Some(Ok(Frame { seq: 9, msg: req })));
    }

    #[test]
    fn replies_round_trip() {
        let t = Telemetry {
            tick: 7,
            motor_counts: MotorCounts(-1),
            scale_counts: ScaleCounts(i32::MIN),
            setpoint_counts: MotorCounts(i32::MAX),
            following_error_counts: MotorCounts(3),
            est_error_um: I16F16::from_bits(-65536),
            current_a: I16F16::from_bits(32768),
            faults: Faults(0x0212),
            model: ModelKind::Table,
            moving: true,
            amplifier_enabled: false,
            homed: true,
        };
        let replies = [
            Reply::Ack { of: kind::STOP },
            Reply::Error {
                of: kind::UNKNOWN,
                reason: LinkError::Crc,
                detail: 0,
            },
            Reply::Status(WireStatus {
                frames_ok: 5,
                ..WireStatus::default()
            }),
            Reply::Telemetry(t),
            Reply::Answer {
                current_a: I16F16::from_bits(-5),
                telemetry: t,
                step_instructions: 300,
            },
        ];
        for (i, r) in replies.iter().enumerate() {
            let mut out = [0u8; MAX_FRAME];
            let n = encode(i as u8, r, &mut out);
            let mut rx = Receiver::new();
            let mut got = None;
            for &b in &out[..n] {
                if let Some(x) = rx.push::<Reply>(b) {
                    got = Some(x);
                }
            }
            defmt::assert!(
                got == Some(Ok(Frame {
                    seq: i as u8,
                    msg: *r
                }))
            );
        }
    }

    #[test]
    fn bad_frames_rejected_with_their_reason() {
        let mut rx = Receiver::new();
        // COBS code byte past the end.
        defmt::assert!(feed(&mut rx, &[5, 1, 2, 0]) == Some(Err(LinkError::Framing as u8)));
        // Too short for kind + seq + CRC.
        defmt::assert!(feed(&mut rx, &[3, 1, 2, 0]) == Some(Err(LinkError::TooShort as u8)));
        // Longer than any frame.
        let mut long = [0x55u8; MAX_ENCODED + 3];
        long[MAX_ENCODED + 2] = 0;
        defmt::assert!(feed(&mut rx, &long) == Some(Err(LinkError::Oversize as u8)));
        // One flipped bit.
        let mut bad = KNOWN_MOVE_MOTOR;
        bad[5] ^= 0x10;
        defmt::assert!(feed(&mut rx, &bad) == Some(Err(LinkError::Crc as u8)));

        let mut out = [0u8; MAX_FRAME + 8];
        let cases: [(&[u8], LinkError); 6] = [
            (&[0x7e, 1], LinkError::UnknownKind),
            (&[kind::STOP, 1, 0], LinkError::BadLength),
            (
                &[kind::MOVE_MOTOR, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0],
                LinkError::OutOfRange,
            ),
            (
                &[kind::MOVE_MOTOR, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0],
                LinkError::OutOfRange,
            ),
            (
                &[kind::SELECT_MODEL, 1, MODEL_MAX + 1],
                LinkError::OutOfRange,
            ),
            (&[kind::CAL_CHUNK, 1, 0, 0, 0, 0], LinkError::BadLength),
        ];
        for (body, error) in cases {
            let n = with_crc(body, &mut out);
            defmt::assert!(feed(&mut rx, &out[..n]) == Some(Err(error as u8)));
        }
        defmt::assert_eq!(rx.frames_ok, 0);
        defmt::assert_eq!(rx.frames_bad, 10);
    }

    #[test]
    fn full_chunk_round_trips() {
        let mut data = [0u8; CHUNK_MAX];
        for (i, d) in data.iter_mut().enumerate() {
            *d = (i * 37) as u8;
        }
        let req = Request::CalChunk {
            offset: 1234,
            len: CHUNK_MAX as u8,
            data,
        };
        let mut out = [0u8; MAX_FRAME];
        let n = encode(200, &req, &mut out);
        defmt::assert_eq!(req.kind(), kind::CAL_CHUNK);
        let mut rx = Receiver::new();
        defmt::assert!(feed(&mut rx, &out[..n]) == Some(Ok(Frame { seq: 200, msg: req })));
    }
}
