//! The link against an in-memory fake drive: matching, retries, the error classes, records.

use belt_link::{CommandError, MotorCounts, RECORD_BATCH};

use super::*;
use crate::testing::{wire, Fake};

fn status(tick: u32) -> Reply {
    Reply::Status(WireStatus {
        tick,
        ..WireStatus::default()
    })
}

fn records(seq: u32, first_tick: u32, every: u16, count: u8) -> Reply {
    let mut samples = [RecordSample::default(); RECORD_BATCH];
    for (i, s) in samples.iter_mut().enumerate() {
        s.motor_counts = MotorCounts((first_tick + i as u32 * every as u32) as i32);
    }
    Reply::Records {
        seq,
        first_tick,
        every,
        count,
        samples,
    }
}

#[test]
fn unsolicited_and_stale_frames_do_not_confuse_the_matching() {
    let mut link = Fake::link(|seq, req| {
        assert_eq!(req, Request::Status);
        let mut out = wire(0, &status(1)); // boot status
        out.extend(wire(0, &records(7, 0, 1, 4))); // nobody records
        out.extend(wire(seq.wrapping_add(100), &status(2))); // a stale reply
        out.extend(wire(seq, &Reply::Ack { of: kind::STATUS })); // implausible for a status
        out.extend([0, 0]); // idle filler
        out.extend(wire(seq, &status(42)));
        out
    });
    assert_eq!(link.status().unwrap().tick, 42);
    let s = link.stats();
    assert_eq!((s.boots, s.unsolicited, s.stale), (1, 1, 2), "{s:?}");
    assert_eq!((s.garbage_bytes, s.resent), (0, 0));
}

#[test]
fn a_damaged_request_is_sent_again() {
    let mut tries = 0;
    let mut link = Fake::link(move |seq, req| {
        tries += 1;
        if tries == 1 {
            // As the drive answers a frame it could not read: seq and kind unknown.
            wire(
                0,
                &Reply::Error {
                    of: kind::UNKNOWN,
                    reason: LinkError::Crc,
                    detail: 0,
                },
            )
        } else {
            wire(seq, &Reply::Ack { of: req.kind() })
        }
    });
    link.command(Command::Enable).unwrap();
    assert_eq!(link.stats().resent, 1);
}

#[test]
fn damage_on_every_try_is_reported_as_such() {
    let mut link = Fake::link(|seq, req| {
        wire(
            seq,
            &Reply::Error {
                of: req.kind(),
                reason: LinkError::Crc,
                detail: 0,
            },
        )
    });
    let e = link.command(Command::Stop).unwrap_err().to_string();
    assert!(
        e.contains("damaged on every one of 3 tries (CRC mismatch)"),
        "{e}"
    );
}

#[test]
fn silence_times_out_after_every_try() {
    let mut link = Fake::link(|_, _| Vec::new());
    let t0 = Instant::now();
    let e = link.status().unwrap_err();
    let took = t0.elapsed();
    assert_eq!(
        e.to_string(),
        "fake: no reply to status within 30 ms after 3 tries (nothing received at all: is the \
         drive powered and connected?)"
    );
    assert!(took >= Duration::from_millis(90) && took < Duration::from_millis(600));
    assert_eq!(link.stats().resent, 2);
}

#[test]
fn garbage_is_a_wrong_device() {
    let mut n = 0u32;
    let mut link = Fake::link(move |_, _| {
        n += 1;
        // Text with a zero now and then: frames that never decode.
        let mut v = format!("ERROR {n}\r\n").into_bytes();
        v.push(0);
        v
    });
    let e = link.status().unwrap_err();
    assert!(matches!(e, ToolError::WrongDevice { .. }), "{e}");
    assert!(
        e.to_string()
            .starts_with("fake answers, but not with belt-drive frames: 30 bytes of garbage"),
        "{e}"
    );
}

#[test]
fn garbage_after_valid_frames_is_a_timeout_that_mentions_it() {
    let mut first = true;
    let mut link = Fake::link(move |seq, _| {
        if std::mem::take(&mut first) {
            wire(seq, &status(1))
        } else {
            vec![1, 2, 3, 0]
        }
    });
    link.status().unwrap();
    let e = link.status().unwrap_err().to_string();
    assert!(
        e.contains("after 3 tries (received 12 bytes of garbage)"),
        "{e}"
    );
}

#[test]
fn an_echo_is_recognised() {
    let mut link = Fake::link(|seq, req| {
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(seq, &req, &mut buf);
        buf[..n].to_vec()
    });
    let e = link.status().unwrap_err();
    assert!(matches!(e, ToolError::Echo { .. }), "{e}");
}

#[test]
fn refusals_are_decoded() {
    let mut link = Fake::link(|seq, req| {
        let (reason, detail) = match req {
            Request::Command(_) => (LinkError::Refused, CommandError::NotHomed.code()),
            Request::ConfigApply => (LinkError::Config, 1),
            _ => (LinkError::NotSupported, 0),
        };
        wire(
            seq,
            &Reply::Error {
                of: req.kind(),
                reason,
                detail,
            },
        )
    });
    let e = link
        .command(Command::MoveTo {
            target_um: 12_500,
            velocity_um_s: 1,
            accel_um_s2: 1,
        })
        .unwrap_err();
    assert_eq!(
        e.to_string(),
        "the drive refused move to 12.500 mm: not homed: home the drive before moving"
    );
    let e = link.acked(&Request::ConfigApply).unwrap_err().to_string();
    assert!(e.contains("rig.gear_ratio"), "{e}");
    let e = link.acked(&Request::Save).unwrap_err().to_string();
    assert!(e.contains("not supported"), "{e}");
}

#[test]
fn requests_never_use_seq_0() {
    let mut seen = Vec::new();
    let (tx, rx) = std::sync::mpsc::channel();
    let mut link = Fake::link(move |seq, req| {
        tx.send(seq).unwrap();
        wire(seq, &Reply::Ack { of: req.kind() })
    });
    for _ in 0..600 {
        link.command(Command::Stop).unwrap();
    }
    seen.extend(rx.try_iter());
    assert_eq!(seen.len(), 600);
    assert!(!seen.contains(&0));
    assert!(seen.contains(&255) && seen.contains(&1));
}

#[test]
fn records_are_collected_while_other_requests_wait() {
    let mut frame = 0u32;
    let mut link = Fake::link(move |seq, req| {
        let mut out = Vec::new();
        if matches!(req, Request::Status) {
            // Two frames per status poll, 4 samples each, every 2 ticks.
            for _ in 0..2 {
                out.extend(wire(0, &records(frame, frame * 8, 2, 4)));
                frame += 1;
            }
            out.extend(wire(seq, &status(frame)));
        } else {
            if req == (Request::Record { every_n_ticks: 2 }) {
                // An earlier recording still in flight, then the ack.
                out.extend(wire(0, &records(5000, 0, 2, 4)));
            }
            out.extend(wire(seq, &Reply::Ack { of: req.kind() }));
        }
        out
    });
    link.start_recording(2).unwrap();
    for _ in 0..3 {
        link.status().unwrap();
    }
    let (samples, stats) = link.stop_recording().unwrap();
    assert_eq!(samples.len(), 24);
    assert!(samples
        .iter()
        .enumerate()
        .all(|(i, s)| s.tick == 2 * i as u32 && s.sample.motor_counts.0 == s.tick as i32));
    assert_eq!((stats.frames, stats.lost_frames, stats.foreign), (6, 0, 1));
    stats.check().unwrap();
}

#[test]
fn sequence_gaps_and_tick_jumps_are_losses() {
    let mut c = Collector::new(1);
    let s = [RecordSample::default(); 4];
    c.push(0, 100, 1, &s);
    c.push(1, 104, 1, &s);
    c.push(4, 116, 1, &s); // frames 2 and 3 lost
    c.push(3, 112, 1, &s); // late: dropped
    c.push(5, 124, 1, &s); // whole sequence, 4 ticks skipped
    let st = &c.stats;
    assert_eq!(
        (
            st.frames,
            st.lost_frames,
            st.out_of_order,
            st.missing_samples
        ),
        (4, 2, 1, 4)
    );
    assert_eq!(st.gaps, vec![(2, 2)]);
    let e = st.check().unwrap_err().to_string();
    assert!(e.starts_with("lost 2 of 6 record frames (2 at seq 2, 4 samples missing by tick, 1 frames out of order)"), "{e}");

    // Frames lost before the first that arrived count too.
    let mut c = Collector::new(1);
    c.push(3, 0, 1, &s);
    assert_eq!(c.stats.lost_frames, 3);

    // The last sequence number a drive can send is counted once; its repeat is out of order.
    let mut c = Collector::new(1);
    c.push(0, 0, 1, &s);
    c.push(u32::MAX, 4, 1, &s);
    c.push(u32::MAX, 8, 1, &s);
    assert_eq!(
        (c.stats.frames, c.stats.lost_frames, c.stats.out_of_order),
        (2, u64::from(u32::MAX) - 1, 1)
    );
}

#[test]
fn an_answer_from_another_protocol_version_is_named_at_once() {
    // A status that names a model this beltctl does not know (a newer firmware): intact on the
    // wire, refused by the decoder. Said at the first answer, not after every try as garbage.
    let mut link = Fake::link(|seq, _| {
        let mut raw = [0; belt_link::MAX_RAW + 8];
        raw[..2].copy_from_slice(&[kind::STATUS_REPLY, seq]);
        let len = status(5).write_payload(&mut raw[2..]);
        raw[2 + 10] = belt_link::MODEL_MAX + 1; // the status's model byte
        let mut out = [0; MAX_FRAME + 16];
        let n = belt_link::testing::sealed_frame(&mut raw, 2 + len, &mut out);
        out[..n].to_vec()
    });
    let e = link.status().unwrap_err();
    assert!(matches!(e, ToolError::Unreadable { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("the drive answered status, but beltctl cannot read")
            && e.to_string().contains("a field out of range"),
        "{e}"
    );
    assert_eq!(link.stats().resent, 0);
}
