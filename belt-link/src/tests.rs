//! The protocol's own tests: layouts, known bytes, every rejection, round trips, fuzz.

use super::*;
use crate::command::*;
use fixed::types::I16F16;
use proptest::prelude::*;

fn wire<M: Message>(seq: u8, m: &M) -> ([u8; MAX_FRAME], usize) {
    let mut out = [0u8; MAX_FRAME];
    let n = encode(seq, m, &mut out);
    (out, n)
}

fn feed<M: Message>(rx: &mut Receiver, bytes: &[u8]) -> Vec<Result<Frame<M>, Rejected>> {
    bytes.iter().filter_map(|&b| rx.push(b)).collect()
}

fn telemetry() -> Telemetry {
    Telemetry {
        tick: 0xDEAD_BEEF,
        motor_counts: MotorCounts(-123_456),
        scale_counts: ScaleCounts(7_654_321),
        setpoint_counts: MotorCounts(i32::MIN),
        following_error_counts: MotorCounts(i32::MAX),
        est_error_um: I16F16::from_bits(-(3 << 16) - 0x8000),
        current_a: I16F16::from_bits(0x0001_8000),
        faults: Faults(0b10_0000_1010),
        model: ModelKind::Table,
        moving: true,
        amplifier_enabled: false,
        homed: true,
    }
}

fn all_requests() -> Vec<Request> {
    let mut data = [0u8; CHUNK_MAX];
    for (i, d) in data.iter_mut().enumerate() {
        *d = i as u8; // includes a zero byte: COBS must carry it
    }
    vec![
        Request::Command(Command::MoveMotorTo {
            target_um: -250_000,
            velocity_um_s: 50_000,
            accel_um_s2: 1,
        }),
        Request::Command(Command::MoveMotorTo {
            target_um: i32::MAX,
            velocity_um_s: u32::MAX,
            accel_um_s2: u32::MAX,
        }),
        Request::Command(Command::MoveTo {
            target_um: -7,
            velocity_um_s: 3,
            accel_um_s2: 0x00ff_0000,
        }),
        Request::Command(Command::Stop),
        Request::Command(Command::Enable),
        Request::Command(Command::Disable),
        Request::Command(Command::ClearFaults),
        Request::Command(Command::SelectModel(ModelKind::None)),
        Request::Command(Command::SelectModel(ModelKind::BidirTable)),
        Request::CalBegin {
            total_len: 1234,
            crc32: 0,
        },
        Request::CalChunk {
            offset: 0,
            len: 1,
            data: [0; CHUNK_MAX],
        },
        Request::CalChunk {
            offset: 4096,
            len: CHUNK_MAX as u8,
            data,
        },
        Request::CalCommit,
        Request::Status,
        Request::Telemetry { every_n_ticks: 0 },
        Request::Telemetry {
            every_n_ticks: 65535,
        },
        Request::Sample {
            motor_counter: 0,
            scale_counter: 0xffff,
        },
        Request::Shutdown { code: 0 },
        Request::Shutdown { code: 255 },
        Request::Command(Command::Home {
            position_um: -5,
            scale_um: i32::MIN,
        }),
        Request::Command(Command::Homing),
        Request::ConfigSet {
            key: 0,
            value_bits: (-1.5e-9f64).to_bits(),
        },
        Request::ConfigGet { key: 255 },
        Request::ConfigParts {
            offset: 0,
            len: 1,
            data: [0; CHUNK_MAX],
        },
        Request::ConfigParts {
            offset: 192,
            len: CHUNK_MAX as u8,
            data,
        },
        Request::ConfigApply,
        Request::Save,
        Request::Record { every_n_ticks: 2 },
        Request::CalRead { offset: 128 },
    ]
}

fn all_replies() -> Vec<Reply> {
    vec![
        Reply::Ack {
            of: kind::MOVE_MOTOR,
        },
        Reply::Error {
            of: kind::UNKNOWN,
            reason: LinkError::Crc,
            detail: 0,
        },
        Reply::Error {
            of: kind::MOVE_MOTOR,
            reason: LinkError::Refused,
            detail: 3,
        },
        Reply::Status(WireStatus {
            tick: 1,
            motor_counts: MotorCounts(-2),
            faults: Faults(0x0204),
            model: ModelKind::Exponential,
            flags: status_flags::ALL,
            last_error: LinkError::NotSupported as u8,
            reset_cause: reset_cause::INDEPENDENT_WATCHDOG | reset_cause::PANIC_RECORD,
            missed_ticks: 7,
            scale_glitches: 70_000,
            frames_ok: u32::MAX,
            frames_bad: 0,
            stack_peak_bytes: 1500,
            carriage_target_um: -300_000,
            carriage_estimate_um: i32::MAX,
            scale_counts: ScaleCounts(-7),
            record_crc: 0xdead_beef,
        }),
        Reply::Telemetry(telemetry()),
        Reply::Telemetry(Telemetry::default()),
        Reply::Answer {
            current_a: I16F16::from_bits(-1),
            telemetry: telemetry(),
            step_instructions: 321,
        },
        Reply::ConfigValue {
            key: 7,
            active_bits: 23.7222f64.to_bits(),
            staged_bits: f64::NAN.to_bits(),
        },
        Reply::Saved {
            seq: 3,
            crc32: 0x0102_0304,
        },
        Reply::Records {
            seq: u32::MAX,
            first_tick: 9,
            every: 2,
            count: 3,
            samples: [
                RecordSample {
                    motor_counts: MotorCounts(-1),
                    scale_counts: ScaleCounts(2),
                    setpoint_counts: MotorCounts(i32::MIN),
                    current_ma: -8000,
                },
                RecordSample::default(),
                RecordSample {
                    motor_counts: MotorCounts(0x7f00_0000),
                    scale_counts: ScaleCounts(0),
                    setpoint_counts: MotorCounts(5),
                    current_ma: i16::MAX,
                },
                RecordSample::default(),
            ],
        },
        Reply::CalData {
            offset: 64,
            total_len: 1000,
            len: 2,
            data: {
                let mut d = [0u8; CHUNK_MAX];
                d[..2].copy_from_slice(&[0, 9]);
                d
            },
        },
    ]
}

#[test]
fn crc_matches_the_standard_check_value() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    let mut c = Crc32::new();
    c.update(b"1234");
    c.update(b"56789");
    assert_eq!(c.finish(), 0xCBF4_3926);
}

#[test]
fn cobs_known_vectors() {
    let cases: &[(&[u8], &[u8])] = &[
        (&[], &[1]),
        (&[0], &[1, 1]),
        (&[0, 0], &[1, 1, 1]),
        (&[0x11, 0x22, 0x00, 0x33], &[3, 0x11, 0x22, 2, 0x33]),
        (&[0x11, 0x00, 0x00, 0x00], &[2, 0x11, 1, 1, 1]),
    ];
    for (raw, enc) in cases {
        let mut out = [0u8; 16];
        let n = cobs_encode(raw, &mut out).unwrap();
        assert_eq!(&out[..n], *enc);
        let mut back = out;
        let m = cobs_decode_in_place(&mut back[..n]).unwrap();
        assert_eq!(&back[..m], *raw);
    }
    // 254 non-zero bytes: one full block and a final empty block.
    let raw = [0x42u8; 254];
    let mut out = [0u8; 300];
    let n = cobs_encode(&raw, &mut out).unwrap();
    assert_eq!(n, 256);
    assert_eq!(out[0], 0xff);
    let m = cobs_decode_in_place(&mut out[..n]).unwrap();
    assert_eq!(&out[..m], &raw[..]);
}

#[test]
fn every_request_round_trips() {
    for (i, req) in all_requests().into_iter().enumerate() {
        let (bytes, n) = wire(i as u8, &req);
        assert!(n <= MAX_FRAME);
        assert_eq!(bytes[n - 1], 0);
        assert!(!bytes[..n - 1].contains(&0), "{req:?}");
        let mut rx = Receiver::new();
        let got = feed::<Request>(&mut rx, &bytes[..n]);
        assert_eq!(
            got,
            vec![Ok(Frame {
                seq: i as u8,
                msg: req
            })]
        );
        assert_eq!((rx.frames_ok, rx.frames_bad), (1, 0));
    }
}

#[test]
fn every_reply_round_trips() {
    for (i, rep) in all_replies().into_iter().enumerate() {
        let (bytes, n) = wire(200 + i as u8, &rep);
        let mut rx = Receiver::new();
        let got = feed::<Reply>(&mut rx, &bytes[..n]);
        assert_eq!(
            got,
            vec![Ok(Frame {
                seq: 200 + i as u8,
                msg: rep
            })]
        );
    }
}

#[test]
fn layout_is_fixed() {
    // A Move, byte by byte: kind, seq, target (LE), velocity, accel, CRC.
    let m = Request::Command(Command::MoveMotorTo {
        target_um: 0x0403_0201,
        velocity_um_s: 5,
        accel_um_s2: 6,
    });
    let mut raw = [0u8; MAX_RAW];
    raw[0] = m.kind();
    raw[1] = 9;
    let n = m.write_payload(&mut raw[2..]);
    assert_eq!(n, 12);
    assert_eq!(&raw[..14], &[1, 9, 1, 2, 3, 4, 5, 0, 0, 0, 6, 0, 0, 0]);
    let sizes = [
        (Reply::Ack { of: 1 }.write_payload(&mut [0; MAX_PAYLOAD]), 1),
        (
            Reply::Status(WireStatus::default()).write_payload(&mut [0; MAX_PAYLOAD]),
            STATUS_LEN,
        ),
        (
            Reply::Telemetry(telemetry()).write_payload(&mut [0; MAX_PAYLOAD]),
            TELEMETRY_LEN,
        ),
        (
            Reply::Answer {
                current_a: I16F16::ZERO,
                telemetry: telemetry(),
                step_instructions: 0,
            }
            .write_payload(&mut [0; MAX_PAYLOAD]),
            40,
        ),
    ];
    for (got, want) in sizes {
        assert_eq!(got, want);
    }
}

/// Wire bytes computed independently (Python: zlib.crc32 and a separate COBS encoder).
const KNOWN_MOVE_MOTOR: [u8; 20] = [
    9, 1, 9, 112, 47, 252, 255, 80, 195, 1, 4, 64, 13, 3, 5, 157, 230, 2, 169, 0,
];
const KNOWN_SAMPLE: [u8; 12] = [2, 12, 3, 52, 18, 1, 5, 48, 121, 235, 166, 0];

#[test]
fn known_wire_bytes() {
    let (b, n) = wire(
        9,
        &Request::Command(Command::MoveMotorTo {
            target_um: -250_000,
            velocity_um_s: 50_000,
            accel_um_s2: 200_000,
        }),
    );
    assert_eq!(&b[..n], &KNOWN_MOVE_MOTOR);
    let (b, n) = wire(
        0,
        &Request::Sample {
            motor_counter: 0x1234,
            scale_counter: 0,
        },
    );
    assert_eq!(&b[..n], &KNOWN_SAMPLE);
}

/// Builds a wire frame from arbitrary raw content with a correct CRC.
fn frame_with_crc(body: &[u8]) -> Vec<u8> {
    let mut raw = body.to_vec();
    raw.extend_from_slice(&crc32(body).to_le_bytes());
    let mut out = vec![0u8; raw.len() + raw.len() / 254 + 2];
    let n = cobs_encode(&raw, &mut out).unwrap();
    out.truncate(n);
    out.push(0);
    out
}

#[test]
fn bad_frames_are_rejected_with_a_reason() {
    let cases: Vec<(Vec<u8>, LinkError, u8)> = vec![
        // a code byte pointing past the end
        (vec![5, 1, 2, 0], LinkError::Framing, kind::UNKNOWN),
        // valid COBS, too short for kind + seq + CRC
        (vec![3, 1, 2, 0], LinkError::TooShort, kind::UNKNOWN),
        // longer than any frame
        (
            vec![0x55; MAX_ENCODED + 10]
                .into_iter()
                .chain([0])
                .collect(),
            LinkError::Oversize,
            kind::UNKNOWN,
        ),
        (frame_with_crc(&[0x7e, 1]), LinkError::UnknownKind, 0x7e),
        (
            frame_with_crc(&[kind::ACK, 1, 1]),
            LinkError::UnknownKind,
            kind::ACK,
        ),
        (
            frame_with_crc(&[kind::STOP, 1, 0]),
            LinkError::BadLength,
            kind::STOP,
        ),
        (
            frame_with_crc(&[kind::MOVE_MOTOR, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0]),
            LinkError::OutOfRange,
            kind::MOVE_MOTOR,
        ),
        (
            frame_with_crc(&[kind::MOVE_MOTOR, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]),
            LinkError::OutOfRange,
            kind::MOVE_MOTOR,
        ),
        (
            frame_with_crc(&[kind::MOVE_MOTOR, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0]),
            LinkError::BadLength,
            kind::MOVE_MOTOR,
        ),
        (
            frame_with_crc(&[kind::SELECT_MODEL, 1, MODEL_MAX + 1]),
            LinkError::OutOfRange,
            kind::SELECT_MODEL,
        ),
        (
            frame_with_crc(&[kind::CAL_BEGIN, 1, 0, 0, 0, 0, 1, 2, 3, 4]),
            LinkError::OutOfRange,
            kind::CAL_BEGIN,
        ),
        (
            frame_with_crc(&[kind::CAL_CHUNK, 1, 0, 0, 0, 0]),
            LinkError::BadLength,
            kind::CAL_CHUNK,
        ),
    ];
    for (bytes, error, k) in cases {
        let mut rx = Receiver::new();
        let got = feed::<Request>(&mut rx, &bytes);
        assert_eq!(got.len(), 1, "{bytes:?}");
        let r = got[0].unwrap_err();
        assert_eq!((r.error, r.kind), (error, k), "{bytes:?}");
        assert_eq!(
            (rx.frames_ok, rx.frames_bad, rx.last_error),
            (0, 1, Some(error))
        );
    }
    // A chunk with one byte too many has a bad length; one past the largest payload is longer
    // than any frame.
    let mut body = vec![kind::CAL_CHUNK, 1, 0, 0, 0, 0];
    body.extend([1u8; CHUNK_MAX + 1]);
    let mut rx = Receiver::new();
    let got = feed::<Request>(&mut rx, &frame_with_crc(&body));
    assert_eq!(got[0].unwrap_err().error, LinkError::BadLength);
    let mut body = vec![kind::CAL_CHUNK, 1, 0, 0, 0, 0];
    body.extend([1u8; MAX_PAYLOAD - 4 + 1]);
    let mut rx = Receiver::new();
    let got = feed::<Request>(&mut rx, &frame_with_crc(&body));
    assert_eq!(got[0].unwrap_err().error, LinkError::Oversize);
    // A reply kind of the right length, but with a bad flag byte.
    let mut body = vec![kind::TELEMETRY_FRAME, 1];
    body.extend([0u8; TELEMETRY_LEN - 1]);
    body.push(0x80);
    let mut rx = Receiver::new();
    let got = feed::<Reply>(&mut rx, &frame_with_crc(&body));
    assert_eq!(got[0].unwrap_err().error, LinkError::OutOfRange);
    // Telemetry, an answer and a status naming a model the drive does not have. The model
    // byte sits after the tick, four counts, estimate, current and fault bits (30 bytes in);
    // in a status after the tick, position and fault bits.
    for (k, len, at) in [
        (kind::TELEMETRY_FRAME, TELEMETRY_LEN, 30),
        (kind::ANSWER, 4 + TELEMETRY_LEN + 4, 4 + 30),
        (kind::STATUS_REPLY, STATUS_LEN, 10),
    ] {
        let mut body = vec![k, 1];
        body.extend(vec![0u8; len]);
        let mut rx = Receiver::new();
        assert!(feed::<Reply>(&mut rx, &frame_with_crc(&body))[0].is_ok());
        body[2 + at] = MODEL_MAX + 1;
        let mut rx = Receiver::new();
        let got = feed::<Reply>(&mut rx, &frame_with_crc(&body));
        assert_eq!(
            got[0].unwrap_err().error,
            LinkError::OutOfRange,
            "kind {k:#04x}"
        );
    }
}

#[test]
fn any_single_bit_flip_is_caught() {
    for req in all_requests() {
        let (bytes, n) = wire(1, &req);
        let mut raw = bytes[..n - 1].to_vec();
        let m = cobs_decode_in_place(&mut raw).unwrap();
        raw.truncate(m);
        for bit in 0..raw.len() * 8 {
            let mut bad = raw.clone();
            bad[bit / 8] ^= 1 << (bit % 8);
            assert!(decode_raw::<Request>(&bad).is_err(), "{req:?} bit {bit}");
        }
    }
}

#[test]
fn receiver_resynchronises_after_garbage() {
    let mut rx = Receiver::new();
    let (good, n) = wire(7, &Request::Status);
    let mut stream = vec![0, 0, 0x13, 0x37, 0x99, 0];
    stream.extend_from_slice(&good[..n]);
    stream.extend([0xff; 200]);
    stream.push(0);
    stream.extend_from_slice(&good[..n]);
    let got = feed::<Request>(&mut rx, &stream);
    assert_eq!(got.len(), 4);
    assert!(got[0].is_err() && got[2].is_err());
    assert_eq!(
        got[1],
        Ok(Frame {
            seq: 7,
            msg: Request::Status
        })
    );
    assert_eq!(got[3], got[1]);
    assert_eq!((rx.frames_ok, rx.frames_bad), (2, 2));
    assert_eq!(rx.last_error, Some(LinkError::Oversize));
}

/// A transfer's piece: 1..=CHUNK_MAX random bytes, zero-padded, with their count.
fn piece() -> impl Strategy<Value = (u8, [u8; CHUNK_MAX])> {
    proptest::collection::vec(any::<u8>(), 1..=CHUNK_MAX).prop_map(|d| {
        let mut data = [0u8; CHUNK_MAX];
        data[..d.len()].copy_from_slice(&d);
        (d.len() as u8, data)
    })
}

fn arb_request() -> impl Strategy<Value = Request> {
    prop_oneof![
        (any::<i32>(), 1..=u32::MAX, 1..=u32::MAX).prop_map(|(t, v, a)| Request::Command(
            Command::MoveMotorTo {
                target_um: t,
                velocity_um_s: v,
                accel_um_s2: a
            }
        )),
        (any::<i32>(), 1..=u32::MAX, 1..=u32::MAX).prop_map(|(t, v, a)| {
            Request::Command(Command::MoveTo {
                target_um: t,
                velocity_um_s: v,
                accel_um_s2: a,
            })
        }),
        Just(Request::Command(Command::Stop)),
        Just(Request::Command(Command::Enable)),
        Just(Request::Command(Command::Disable)),
        Just(Request::Command(Command::ClearFaults)),
        proptest::sample::select(ModelKind::ALL.to_vec())
            .prop_map(|m| Request::Command(Command::SelectModel(m))),
        (1..=u32::MAX, any::<u32>()).prop_map(|(l, c)| Request::CalBegin {
            total_len: l,
            crc32: c
        }),
        (any::<u32>(), piece()).prop_map(|(offset, (len, data))| Request::CalChunk {
            offset,
            len,
            data
        }),
        Just(Request::CalCommit),
        Just(Request::Status),
        any::<u16>().prop_map(|n| Request::Telemetry { every_n_ticks: n }),
        (any::<u16>(), any::<u16>()).prop_map(|(m, s)| Request::Sample {
            motor_counter: m,
            scale_counter: s
        }),
        any::<u8>().prop_map(|code| Request::Shutdown { code }),
        (any::<i32>(), any::<i32>()).prop_map(|(p, s)| Request::Command(Command::Home {
            position_um: p,
            scale_um: s
        })),
        Just(Request::Command(Command::Homing)),
        (any::<u8>(), any::<u64>())
            .prop_map(|(key, value_bits)| Request::ConfigSet { key, value_bits }),
        any::<u8>().prop_map(|key| Request::ConfigGet { key }),
        Just(Request::ConfigApply),
        Just(Request::Save),
        any::<u16>().prop_map(|n| Request::Record { every_n_ticks: n }),
        any::<u32>().prop_map(|offset| Request::CalRead { offset }),
        (any::<u16>(), piece()).prop_map(|(offset, (len, data))| Request::ConfigParts {
            offset,
            len,
            data
        }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Arbitrary bytes never panic the receiver, and every frame is accounted for.
    #[test]
    fn receiver_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        let mut rx = Receiver::new();
        let results = feed::<Request>(&mut rx, &bytes);
        prop_assert_eq!(results.len() as u32, rx.frames_ok + rx.frames_bad);
        let mut rx = Receiver::new();
        let _ = feed::<Reply>(&mut rx, &bytes);
    }

    /// Random requests round-trip, through a stream with garbage in front.
    #[test]
    fn requests_round_trip(req in arb_request(), seq in any::<u8>(),
                           junk in proptest::collection::vec(1u8..=255, 0..100)) {
        let mut rx = Receiver::new();
        let mut stream = junk.clone();
        stream.push(0);
        let (bytes, n) = wire(seq, &req);
        stream.extend_from_slice(&bytes[..n]);
        let got = feed::<Request>(&mut rx, &stream);
        prop_assert_eq!(got.last().copied(), Some(Ok(Frame { seq, msg: req })));
    }

    /// Corrupting any byte of a valid frame makes it rejected (or splits it into rejects).
    #[test]
    fn corrupted_frames_are_rejected(req in arb_request(), pos in any::<usize>(), x in 1u8..=255) {
        let (mut bytes, n) = wire(3, &req);
        let i = pos % (n - 1);
        bytes[i] ^= x;
        let mut rx = Receiver::new();
        let got = feed::<Request>(&mut rx, &bytes[..n]);
        prop_assert!(got.iter().all(|r| r.is_err()), "{:?}", got);
        prop_assert_eq!(rx.frames_ok, 0);
    }

    /// Random raw content with a valid CRC either parses to a message that re-encodes
    /// identically, or is rejected.
    #[test]
    fn parse_is_canonical(body in proptest::collection::vec(any::<u8>(), 2..MAX_RAW - 4)) {
        let bytes = frame_with_crc(&body);
        let mut rx = Receiver::new();
        let got = feed::<Request>(&mut rx, &bytes);
        prop_assert_eq!(got.len(), 1);
        if let Ok(f) = got[0] {
            let (again, n) = wire(f.seq, &f.msg);
            prop_assert_eq!(&again[..n], &bytes[..]);
        }
    }
}
