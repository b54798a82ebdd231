//! The serial link between a host (operator tool, `hil-sim`) and the drive firmware.
//!
//! One `no_std`, allocation-free definition used by both ends, so the firmware and the simulator
//! cannot disagree about a byte.
//!
//! # Frame layout
//!
//! ```text
//! raw frame  = kind: u8 | seq: u8 | payload (fixed size per kind, little-endian) | crc: u32 LE
//! on the wire = COBS(raw frame) | 0x00
//! ```
//!
//! - `crc` is CRC-32/ISO-HDLC (the zlib / Ethernet CRC) over `kind | seq | payload`.
//! - COBS removes every zero byte from the frame, so `0x00` only ever delimits frames: a receiver
//!   resynchronises at the next zero after any garbage. An empty frame (two zeros in a row) is
//!   idle filler and is ignored.
//! - `seq` is chosen by the sender of a request and echoed in its reply.
//! - Kinds `0x01..=0x7f` travel host -> drive ([`Request`]), `0x80..=0xff` drive -> host
//!   ([`Reply`]).
//! - Every payload has one exact length, except [`Request::CalChunk`], whose data length is the
//!   payload length minus 4 (1 to [`CHUNK_MAX`] bytes).
//! - Fixed-point values (`I16F16`) travel as the `i32` of their bits.
//!
//! A frame that fails any check (COBS, size, CRC, kind, length, value range) is rejected whole:
//! the decoder returns [`Rejected`] naming the reason, and the receiver counts it and answers
//! with [`Reply::Error`] where it can. Decoding never panics and never allocates.

/// Largest payload of any message (a calibration chunk: offset + [`CHUNK_MAX`] bytes).
pub const MAX_PAYLOAD: usize = 4 + CHUNK_MAX;
/// Largest raw (un-stuffed) frame: kind, seq, payload, CRC.
pub const MAX_RAW: usize = 2 + MAX_PAYLOAD + 4;
/// Largest COBS-encoded frame, without the delimiter.
pub const MAX_ENCODED: usize = MAX_RAW + MAX_RAW.div_ceil(254);
/// Largest frame on the wire, delimiter included: the size of an encode buffer.
pub const MAX_FRAME: usize = MAX_ENCODED + 1;
/// Largest data part of one calibration chunk.
pub const CHUNK_MAX: usize = 64;
/// Raw bytes around a payload: kind, seq and CRC.
const OVERHEAD: usize = 6;

/// Message kinds (the first raw byte).
pub mod kind {
    /// [`super::Request::MoveMotor`]
    pub const MOVE_MOTOR: u8 = 0x01;
    /// [`super::Request::Stop`]
    pub const STOP: u8 = 0x02;
    /// [`super::Request::Enable`]
    pub const ENABLE: u8 = 0x03;
    /// [`super::Request::Disable`]
    pub const DISABLE: u8 = 0x04;
    /// [`super::Request::ClearFaults`]
    pub const CLEAR_FAULTS: u8 = 0x05;
    /// [`super::Request::SelectModel`]
    pub const SELECT_MODEL: u8 = 0x06;
    /// [`super::Request::CalBegin`]
    pub const CAL_BEGIN: u8 = 0x07;
    /// [`super::Request::CalChunk`]
    pub const CAL_CHUNK: u8 = 0x08;
    /// [`super::Request::CalCommit`]
    pub const CAL_COMMIT: u8 = 0x09;
    /// [`super::Request::Status`]
    pub const STATUS: u8 = 0x0a;
    /// [`super::Request::Telemetry`]
    pub const TELEMETRY: u8 = 0x0b;
    /// [`super::Request::Sample`]
    pub const SAMPLE: u8 = 0x0c;
    /// [`super::Request::Shutdown`]
    pub const SHUTDOWN: u8 = 0x0d;
    /// [`super::Request::Home`]
    pub const HOME: u8 = 0x0e;
    /// [`super::Request::Move`]
    pub const MOVE: u8 = 0x0f;

    /// [`super::Reply::Ack`]
    pub const ACK: u8 = 0x80;
    /// [`super::Reply::Error`]
    pub const ERROR: u8 = 0x81;
    /// [`super::Reply::Status`]
    pub const STATUS_REPLY: u8 = 0x82;
    /// [`super::Reply::Telemetry`]
    pub const TELEMETRY_FRAME: u8 = 0x83;
    /// [`super::Reply::Answer`]
    pub const ANSWER: u8 = 0x84;

    /// Stands for "kind unknown" in an error reply (the frame was too damaged to read it).
    pub const UNKNOWN: u8 = 0xff;
}

/// Why a frame was rejected; the `u8` is its code in [`Reply::Error`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum LinkError {
    /// The COBS stuffing is invalid (a code byte points past the frame end).
    Framing = 1,
    /// More bytes than [`MAX_ENCODED`] arrived before a delimiter.
    Oversize = 2,
    /// Fewer bytes than kind, seq and CRC need.
    TooShort = 3,
    /// The CRC does not match.
    Crc = 4,
    /// The kind is not one this receiver knows.
    UnknownKind = 5,
    /// The payload length does not match the kind.
    BadLength = 6,
    /// A field is outside its valid range (zero speed, unknown model, bad flag...).
    OutOfRange = 7,
    /// The drive refused a well-formed command; `detail` names the reason.
    Refused = 8,
    /// A calibration transfer step was refused; `detail` names the reason.
    Calibration = 9,
    /// The message is valid but this build does not accept it (e.g. a PIL sample on the board).
    NotSupported = 10,
}

impl LinkError {
    /// Decodes an error code; `None` for codes this version does not know.
    pub fn from_code(code: u8) -> Option<Self> {
        Some(match code {
            1 => LinkError::Framing,
            2 => LinkError::Oversize,
            3 => LinkError::TooShort,
            4 => LinkError::Crc,
            5 => LinkError::UnknownKind,
            6 => LinkError::BadLength,
            7 => LinkError::OutOfRange,
            8 => LinkError::Refused,
            9 => LinkError::Calibration,
            10 => LinkError::NotSupported,
            _ => return None,
        })
    }
}

/// Highest compensator number [`Request::SelectModel`] may carry (0 none, 1-3 Models 1-3, 4
/// constant backlash, 5 bidirectional table; see [`crate::model::ModelKind`]).
pub const MODEL_MAX: u8 = 5;

/// Host -> drive messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Request {
    /// Move the motor to `target_um` of nominal travel, no compensation (payload 12 bytes):
    /// calibration records raw motor trajectories with it.
    MoveMotor {
        /// Target, micrometres of nominal travel.
        target_um: i32,
        /// Cruise speed, micrometres per second; must be > 0.
        velocity_um_s: u32,
        /// Acceleration, micrometres per second squared; must be > 0.
        accel_um_s2: u32,
    },
    /// Move the carriage to `target_um` (payload 12, as [`Request::MoveMotor`]): the drive places
    /// the carriage with its active compensator.
    Move {
        /// Carriage target, micrometres of travel.
        target_um: i32,
        /// Cruise speed, micrometres per second; must be > 0.
        velocity_um_s: u32,
        /// Acceleration, micrometres per second squared; must be > 0.
        accel_um_s2: u32,
    },
    /// Decelerate to rest (payload 0).
    Stop,
    /// Enable the current output (payload 0).
    Enable,
    /// Zero current and stay disabled (payload 0).
    Disable,
    /// Clear latched faults (payload 0).
    ClearFaults,
    /// Select the error model, `0..=MODEL_MAX` (payload 1).
    SelectModel(u8),
    /// Start a calibration transfer of `total_len` bytes whose CRC-32 is `crc32` (payload 8).
    CalBegin {
        /// Blob length, bytes (> 0).
        total_len: u32,
        /// CRC-32/ISO-HDLC of the whole blob.
        crc32: u32,
    },
    /// One piece of the calibration blob (payload 4 + `len`).
    CalChunk {
        /// Offset of `data[0]` in the blob.
        offset: u32,
        /// Valid bytes in `data`, `1..=CHUNK_MAX`.
        len: u8,
        /// The bytes; only `data[..len]` is meaningful (the rest is zero).
        data: [u8; CHUNK_MAX],
    },
    /// Check the transfer's length and CRC and hand the blob to the drive (payload 0).
    CalCommit,
    /// Ask for a [`Reply::Status`] (payload 0).
    Status,
    /// Stream [`Reply::Telemetry`] every `every_n_ticks` ticks; 0 stops it (payload 2).
    Telemetry {
        /// Decimation; 0 = off.
        every_n_ticks: u16,
    },
    /// PIL only: the raw counters for one control tick (payload 4); answered with
    /// [`Reply::Answer`].
    Sample {
        /// Raw 16-bit motor encoder counter.
        motor_counter: u16,
        /// Raw 16-bit linear-scale counter.
        scale_counter: u16,
    },
    /// Declare the current motor and scale positions (payload 8); refused while moving.
    Home {
        /// Motor position to assign, micrometres of nominal travel.
        position_um: i32,
        /// Linear-scale position to assign, micrometres.
        scale_um: i32,
    },
    /// QEMU only: log the run's statistics and end the emulator with exit status `code`
    /// (payload 1).
    Shutdown {
        /// Exit status.
        code: u8,
    },
}

/// One tick's telemetry in wire form ([`TELEMETRY_LEN`] bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WireTelemetry {
    /// Tick counter since start.
    pub tick: u32,
    /// Unwrapped motor position, counts.
    pub motor_counts: i32,
    /// Unwrapped linear-scale position, scale counts.
    pub scale_counts: i32,
    /// Trajectory set-point, counts.
    pub setpoint_counts: i32,
    /// Following error, counts.
    pub following_error_counts: i32,
    /// Estimated transmission error, micrometres, bits of an `I16F16`.
    pub est_error_um_bits: i32,
    /// Current command, amperes, bits of an `I16F16`.
    pub current_a_bits: i32,
    /// Fault bits ([`Faults`] names them).
    pub faults: u16,
    /// Active model number.
    pub model: u8,
    /// A move is in progress.
    pub moving: bool,
    /// The amplifier enable line is high.
    pub amplifier_enabled: bool,
    /// The drive is homed.
    pub homed: bool,
}

/// Wire size of [`WireTelemetry`].
pub const TELEMETRY_LEN: usize = 32;

/// Bits of the last telemetry byte.
mod telemetry_flags {
    pub const MOVING: u8 = 1 << 0;
    pub const AMPLIFIER_ENABLED: u8 = 1 << 1;
    pub const HOMED: u8 = 1 << 2;
    pub const ALL: u8 = MOVING | AMPLIFIER_ENABLED | HOMED;
}

/// Bits of [`WireStatus::reset_cause`]: why the microcontroller last started (RCC_CSR on the
/// STM32F405; 0 where the board cannot tell, e.g. under QEMU).
pub mod reset_cause {
    /// Low-power management reset.
    pub const LOW_POWER: u8 = 1 << 0;
    /// Window watchdog.
    pub const WINDOW_WATCHDOG: u8 = 1 << 1;
    /// Independent watchdog: the control loop stopped completing ticks.
    pub const INDEPENDENT_WATCHDOG: u8 = 1 << 2;
    /// Software reset (SYSRESETREQ).
    pub const SOFTWARE: u8 = 1 << 3;
    /// Power-on / power-down reset.
    pub const POWER_ON: u8 = 1 << 4;
    /// The NRST pin.
    pub const PIN: u8 = 1 << 5;
    /// Brown-out reset.
    pub const BROWNOUT: u8 = 1 << 6;
    /// The previous run left a panic or HardFault record.
    pub const PANIC_RECORD: u8 = 1 << 7;
    /// Every bit with its name.
    pub const NAMES: [(u8, &str); 8] = [
        (LOW_POWER, "low_power"),
        (WINDOW_WATCHDOG, "window_watchdog"),
        (INDEPENDENT_WATCHDOG, "independent_watchdog"),
        (SOFTWARE, "software"),
        (POWER_ON, "power_on"),
        (PIN, "pin"),
        (BROWNOUT, "brownout"),
        (PANIC_RECORD, "panic_record"),
    ];
}

/// Snapshot of the drive and the link ([`STATUS_LEN`] bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WireStatus {
    /// Control ticks since start.
    pub tick: u32,
    /// Unwrapped motor position, counts.
    pub motor_counts: i32,
    /// Fault bits ([`Faults`] names them).
    pub faults: u16,
    /// Active model number.
    pub model: u8,
    /// [`status_flags`] bits.
    pub flags: u8,
    /// Code of the last [`LinkError`] (0 = none yet).
    pub last_error: u8,
    /// [`reset_cause`] bits of this boot.
    pub reset_cause: u8,
    /// Late or missed control ticks since boot.
    pub missed_ticks: u32,
    /// Linear-scale samples refused as implausible since boot.
    pub scale_glitches: u32,
    /// Frames accepted.
    pub frames_ok: u32,
    /// Frames rejected.
    pub frames_bad: u32,
    /// Deepest stack use seen so far, bytes (0 where not measured).
    pub stack_peak_bytes: u32,
    /// Where the last move sends the carriage, micrometres of travel.
    pub carriage_target_um: i32,
    /// Estimated carriage position (motor position plus the active compensator's estimate),
    /// micrometres of travel.
    pub carriage_estimate_um: i32,
}

/// Bits of [`WireStatus::flags`].
pub mod status_flags {
    /// A move is in progress.
    pub const MOVING: u8 = 1 << 0;
    /// Current output enabled.
    pub const ENABLED: u8 = 1 << 1;
    /// A calibration blob is loaded.
    pub const CALIBRATED: u8 = 1 << 2;
    /// Telemetry streaming is on.
    pub const STREAMING: u8 = 1 << 3;
    /// The drive is homed (moves are refused before).
    pub const HOMED: u8 = 1 << 4;
    /// The amplifier enable line is high.
    pub const AMPLIFIER_ENABLED: u8 = 1 << 5;
    /// All defined bits.
    pub const ALL: u8 = MOVING | ENABLED | CALIBRATED | STREAMING | HOMED | AMPLIFIER_ENABLED;
}

/// Wire size of [`WireStatus`].
pub const STATUS_LEN: usize = 42;

/// Drive -> host messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reply {
    /// Request `of` (a kind) was accepted (payload 1).
    Ack {
        /// Kind of the accepted request.
        of: u8,
    },
    /// Request `of` was rejected (payload 3).
    Error {
        /// Kind of the rejected request, [`kind::UNKNOWN`] if unreadable.
        of: u8,
        /// Why.
        reason: LinkError,
        /// Reason-specific detail (e.g. the drive's refusal code), 0 if none.
        detail: u8,
    },
    /// Answer to [`Request::Status`] (payload [`STATUS_LEN`]).
    Status(WireStatus),
    /// Streamed telemetry (payload [`TELEMETRY_LEN`]).
    Telemetry(WireTelemetry),
    /// PIL: answer to [`Request::Sample`] (payload 4 + [`TELEMETRY_LEN`] + 4).
    Answer {
        /// Current command, amperes, bits of an `I16F16`.
        current_a_bits: i32,
        /// The tick's telemetry.
        telemetry: WireTelemetry,
        /// Instructions `Drive::step` took (QEMU instruction counter; 0 where not measured).
        step_instructions: u32,
    },
}

/// A message type with a wire form.
pub trait Message: Sized {
    /// Its kind byte.
    fn kind(&self) -> u8;
    /// Writes the payload into `out` (at least [`MAX_PAYLOAD`] long) and returns its length.
    fn write_payload(&self, out: &mut [u8]) -> usize;
    /// Parses a payload of kind `kind`.
    fn parse(kind: u8, payload: &[u8]) -> Result<Self, LinkError>;
}

/// A decoded frame: the sender's sequence number and the message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frame<M> {
    /// Sequence number (echoed in replies).
    pub seq: u8,
    /// The message.
    pub msg: M,
}

/// A rejected frame: what could be read of it, and why it was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rejected {
    /// Kind byte if the frame was readable far enough, else [`kind::UNKNOWN`].
    pub kind: u8,
    /// Sequence number if readable, else 0.
    pub seq: u8,
    /// Why.
    pub error: LinkError,
}

// ---- little-endian field access --------------------------------------------------------------

/// Reads fields front to back; all reads are bounds-checked by the caller's exact length check.
struct Reader<'a> {
    buf: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn new(buf: &'a [u8]) -> Self {
        Reader { buf, at: 0 }
    }
    fn bytes<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        // `get` keeps this panic-free even if a caller's length check were wrong.
        if let Some(src) = self.buf.get(self.at..self.at + N) {
            out.copy_from_slice(src);
        }
        self.at += N;
        out
    }
    fn u8(&mut self) -> u8 {
        self.bytes::<1>()[0]
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.bytes())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.bytes())
    }
    fn i32(&mut self) -> i32 {
        i32::from_le_bytes(self.bytes())
    }
}

struct Writer<'a> {
    buf: &'a mut [u8],
    at: usize,
}

impl<'a> Writer<'a> {
    fn new(buf: &'a mut [u8]) -> Self {
        Writer { buf, at: 0 }
    }
    fn put(&mut self, bytes: &[u8]) {
        if let Some(dst) = self.buf.get_mut(self.at..self.at + bytes.len()) {
            dst.copy_from_slice(bytes);
        }
        self.at += bytes.len();
    }
    fn u8(&mut self, v: u8) {
        self.put(&[v]);
    }
    fn u16(&mut self, v: u16) {
        self.put(&v.to_le_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.put(&v.to_le_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.put(&v.to_le_bytes());
    }
}

fn expect_len(payload: &[u8], len: usize) -> Result<Reader<'_>, LinkError> {
    if payload.len() == len {
        Ok(Reader::new(payload))
    } else {
        Err(LinkError::BadLength)
    }
}

impl WireTelemetry {
    fn write(&self, w: &mut Writer<'_>) {
        w.u32(self.tick);
        w.i32(self.motor_counts);
        w.i32(self.scale_counts);
        w.i32(self.setpoint_counts);
        w.i32(self.following_error_counts);
        w.i32(self.est_error_um_bits);
        w.i32(self.current_a_bits);
        w.u16(self.faults);
        w.u8(self.model);
        let mut flags = 0;
        if self.moving {
            flags |= telemetry_flags::MOVING;
        }
        if self.amplifier_enabled {
            flags |= telemetry_flags::AMPLIFIER_ENABLED;
        }
        if self.homed {
            flags |= telemetry_flags::HOMED;
        }
        w.u8(flags);
    }
    fn read(r: &mut Reader<'_>) -> Result<Self, LinkError> {
        Ok(WireTelemetry {
            tick: r.u32(),
            motor_counts: r.i32(),
            scale_counts: r.i32(),
            setpoint_counts: r.i32(),
            following_error_counts: r.i32(),
            est_error_um_bits: r.i32(),
            current_a_bits: r.i32(),
            faults: r.u16(),
            model: r.u8(),
            moving: false,
            amplifier_enabled: false,
            homed: false,
        })
        .and_then(|mut t| {
            let flags = r.u8();
            if flags & !telemetry_flags::ALL != 0 {
                return Err(LinkError::OutOfRange);
            }
            t.moving = flags & telemetry_flags::MOVING != 0;
            t.amplifier_enabled = flags & telemetry_flags::AMPLIFIER_ENABLED != 0;
            t.homed = flags & telemetry_flags::HOMED != 0;
            Ok(t)
        })
    }
}

impl Message for Request {
    fn kind(&self) -> u8 {
        match self {
            Request::MoveMotor { .. } => kind::MOVE_MOTOR,
            Request::Move { .. } => kind::MOVE,
            Request::Stop => kind::STOP,
            Request::Enable => kind::ENABLE,
            Request::Disable => kind::DISABLE,
            Request::ClearFaults => kind::CLEAR_FAULTS,
            Request::SelectModel(_) => kind::SELECT_MODEL,
            Request::CalBegin { .. } => kind::CAL_BEGIN,
            Request::CalChunk { .. } => kind::CAL_CHUNK,
            Request::CalCommit => kind::CAL_COMMIT,
            Request::Status => kind::STATUS,
            Request::Telemetry { .. } => kind::TELEMETRY,
            Request::Sample { .. } => kind::SAMPLE,
            Request::Shutdown { .. } => kind::SHUTDOWN,
            Request::Home { .. } => kind::HOME,
        }
    }

    fn write_payload(&self, out: &mut [u8]) -> usize {
        let mut w = Writer::new(out);
        match *self {
            Request::MoveMotor {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }
            | Request::Move {
                target_um,
                velocity_um_s,
                accel_um_s2,
            } => {
                w.i32(target_um);
                w.u32(velocity_um_s);
                w.u32(accel_um_s2);
            }
            Request::Stop
            | Request::Enable
            | Request::Disable
            | Request::ClearFaults
            | Request::CalCommit
            | Request::Status => {}
            Request::SelectModel(m) => w.u8(m),
            Request::CalBegin { total_len, crc32 } => {
                w.u32(total_len);
                w.u32(crc32);
            }
            Request::CalChunk {
                offset,
                len,
                ref data,
            } => {
                w.u32(offset);
                w.put(&data[..(len as usize).min(CHUNK_MAX)]);
            }
            Request::Telemetry { every_n_ticks } => w.u16(every_n_ticks),
            Request::Sample {
                motor_counter,
                scale_counter,
            } => {
                w.u16(motor_counter);
                w.u16(scale_counter);
            }
            Request::Shutdown { code } => w.u8(code),
            Request::Home {
                position_um,
                scale_um,
            } => {
                w.i32(position_um);
                w.i32(scale_um);
            }
        }
        w.at
    }

    fn parse(k: u8, payload: &[u8]) -> Result<Self, LinkError> {
        Ok(match k {
            kind::MOVE_MOTOR | kind::MOVE => {
                let mut r = expect_len(payload, 12)?;
                let (target_um, velocity_um_s, accel_um_s2) = (r.i32(), r.u32(), r.u32());
                if velocity_um_s == 0 || accel_um_s2 == 0 {
                    return Err(LinkError::OutOfRange);
                }
                if k == kind::MOVE_MOTOR {
                    Request::MoveMotor {
                        target_um,
                        velocity_um_s,
                        accel_um_s2,
                    }
                } else {
                    Request::Move {
                        target_um,
                        velocity_um_s,
                        accel_um_s2,
                    }
                }
            }
            kind::STOP => expect_len(payload, 0).map(|_| Request::Stop)?,
            kind::ENABLE => expect_len(payload, 0).map(|_| Request::Enable)?,
            kind::DISABLE => expect_len(payload, 0).map(|_| Request::Disable)?,
            kind::CLEAR_FAULTS => expect_len(payload, 0).map(|_| Request::ClearFaults)?,
            kind::CAL_COMMIT => expect_len(payload, 0).map(|_| Request::CalCommit)?,
            kind::STATUS => expect_len(payload, 0).map(|_| Request::Status)?,
            kind::SELECT_MODEL => {
                let m = expect_len(payload, 1)?.u8();
                if m > MODEL_MAX {
                    return Err(LinkError::OutOfRange);
                }
                Request::SelectModel(m)
            }
            kind::CAL_BEGIN => {
                let mut r = expect_len(payload, 8)?;
                let (total_len, crc32) = (r.u32(), r.u32());
                if total_len == 0 {
                    return Err(LinkError::OutOfRange);
                }
                Request::CalBegin { total_len, crc32 }
            }
            kind::CAL_CHUNK => {
                if payload.len() < 4 + 1 || payload.len() > 4 + CHUNK_MAX {
                    return Err(LinkError::BadLength);
                }
                let mut r = Reader::new(payload);
                let offset = r.u32();
                let mut data = [0u8; CHUNK_MAX];
                let n = payload.len() - 4;
                data[..n].copy_from_slice(&payload[4..]);
                Request::CalChunk {
                    offset,
                    len: n as u8,
                    data,
                }
            }
            kind::TELEMETRY => Request::Telemetry {
                every_n_ticks: expect_len(payload, 2)?.u16(),
            },
            kind::SAMPLE => {
                let mut r = expect_len(payload, 4)?;
                Request::Sample {
                    motor_counter: r.u16(),
                    scale_counter: r.u16(),
                }
            }
            kind::SHUTDOWN => Request::Shutdown {
                code: expect_len(payload, 1)?.u8(),
            },
            kind::HOME => {
                let mut r = expect_len(payload, 8)?;
                Request::Home {
                    position_um: r.i32(),
                    scale_um: r.i32(),
                }
            }
            _ => return Err(LinkError::UnknownKind),
        })
    }
}

impl Message for Reply {
    fn kind(&self) -> u8 {
        match self {
            Reply::Ack { .. } => kind::ACK,
            Reply::Error { .. } => kind::ERROR,
            Reply::Status(_) => kind::STATUS_REPLY,
            Reply::Telemetry(_) => kind::TELEMETRY_FRAME,
            Reply::Answer { .. } => kind::ANSWER,
        }
    }

    fn write_payload(&self, out: &mut [u8]) -> usize {
        let mut w = Writer::new(out);
        match *self {
            Reply::Ack { of } => w.u8(of),
            Reply::Error { of, reason, detail } => {
                w.u8(of);
                w.u8(reason as u8);
                w.u8(detail);
            }
            Reply::Status(s) => {
                w.u32(s.tick);
                w.i32(s.motor_counts);
                w.u16(s.faults);
                w.u8(s.model);
                w.u8(s.flags);
                w.u8(s.last_error);
                w.u8(s.reset_cause);
                w.u32(s.missed_ticks);
                w.u32(s.scale_glitches);
                w.u32(s.frames_ok);
                w.u32(s.frames_bad);
                w.u32(s.stack_peak_bytes);
                w.i32(s.carriage_target_um);
                w.i32(s.carriage_estimate_um);
            }
            Reply::Telemetry(t) => t.write(&mut w),
            Reply::Answer {
                current_a_bits,
                telemetry,
                step_instructions,
            } => {
                w.i32(current_a_bits);
                telemetry.write(&mut w);
                w.u32(step_instructions);
            }
        }
        w.at
    }

    fn parse(k: u8, payload: &[u8]) -> Result<Self, LinkError> {
        Ok(match k {
            kind::ACK => Reply::Ack {
                of: expect_len(payload, 1)?.u8(),
            },
            kind::ERROR => {
                let mut r = expect_len(payload, 3)?;
                let of = r.u8();
                let reason = LinkError::from_code(r.u8()).ok_or(LinkError::OutOfRange)?;
                Reply::Error {
                    of,
                    reason,
                    detail: r.u8(),
                }
            }
            kind::STATUS_REPLY => {
                let mut r = expect_len(payload, STATUS_LEN)?;
                let s = WireStatus {
                    tick: r.u32(),
                    motor_counts: r.i32(),
                    faults: r.u16(),
                    model: r.u8(),
                    flags: r.u8(),
                    last_error: r.u8(),
                    reset_cause: r.u8(),
                    missed_ticks: r.u32(),
                    scale_glitches: r.u32(),
                    frames_ok: r.u32(),
                    frames_bad: r.u32(),
                    stack_peak_bytes: r.u32(),
                    carriage_target_um: r.i32(),
                    carriage_estimate_um: r.i32(),
                };
                if s.flags & !status_flags::ALL != 0 {
                    return Err(LinkError::OutOfRange);
                }
                Reply::Status(s)
            }
            kind::TELEMETRY_FRAME => Reply::Telemetry(WireTelemetry::read(&mut expect_len(
                payload,
                TELEMETRY_LEN,
            )?)?),
            kind::ANSWER => {
                let mut r = expect_len(payload, 4 + TELEMETRY_LEN + 4)?;
                let current_a_bits = r.i32();
                let telemetry = WireTelemetry::read(&mut r)?;
                Reply::Answer {
                    current_a_bits,
                    telemetry,
                    step_instructions: r.u32(),
                }
            }
            _ => return Err(LinkError::UnknownKind),
        })
    }
}

// ---- CRC-32 -----------------------------------------------------------------------------------

/// CRC-32/ISO-HDLC, nibble-table form: 64 bytes of table, two lookups per byte.
const CRC_NIBBLES: [u32; 16] = {
    let mut t = [0u32; 16];
    let mut i = 0;
    while i < 16 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 4 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
};

/// A running CRC-32/ISO-HDLC (the zlib CRC), for data that arrives in pieces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crc32(u32);

impl Default for Crc32 {
    fn default() -> Self {
        Self::new()
    }
}

impl Crc32 {
    /// A fresh CRC.
    pub const fn new() -> Self {
        Crc32(0xFFFF_FFFF)
    }
    /// Feeds `data`.
    pub fn update(&mut self, data: &[u8]) {
        let mut c = self.0;
        for &b in data {
            c ^= b as u32;
            c = (c >> 4) ^ CRC_NIBBLES[(c & 0xf) as usize];
            c = (c >> 4) ^ CRC_NIBBLES[(c & 0xf) as usize];
        }
        self.0 = c;
    }
    /// The CRC of everything fed so far.
    pub fn finish(&self) -> u32 {
        !self.0
    }
}

/// CRC-32/ISO-HDLC of `data`.
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = Crc32::new();
    c.update(data);
    c.finish()
}

// ---- COBS -------------------------------------------------------------------------------------

/// COBS-encodes `src` into `dst` (no delimiter); returns the length, or `None` if `dst` is short.
pub fn cobs_encode(src: &[u8], dst: &mut [u8]) -> Option<usize> {
    let mut code_at = 0usize;
    let mut out = 1usize;
    let mut code = 1u8;
    for &b in src {
        if b == 0 {
            *dst.get_mut(code_at)? = code;
            code_at = out;
            out += 1;
            code = 1;
        } else {
            *dst.get_mut(out)? = b;
            out += 1;
            code += 1;
            if code == 0xff {
                *dst.get_mut(code_at)? = code;
                code_at = out;
                out += 1;
                code = 1;
            }
        }
    }
    *dst.get_mut(code_at)? = code;
    Some(out)
}

/// Decodes a COBS block (no delimiter) in place; returns the decoded length.
pub fn cobs_decode_in_place(buf: &mut [u8]) -> Result<usize, LinkError> {
    let mut read = 0usize;
    let mut write = 0usize;
    while read < buf.len() {
        let code = buf[read] as usize;
        if code == 0 {
            return Err(LinkError::Framing);
        }
        let end = read + code;
        if end > buf.len() {
            return Err(LinkError::Framing);
        }
        read += 1;
        while read < end {
            let b = buf[read];
            if b == 0 {
                return Err(LinkError::Framing);
            }
            buf[write] = b;
            write += 1;
            read += 1;
        }
        // A short block stands for a zero byte, except at the very end of the frame.
        if code < 0xff && read < buf.len() {
            buf[write] = 0;
            write += 1;
        }
    }
    Ok(write)
}

// ---- framing ----------------------------------------------------------------------------------

/// Encodes `msg` with sequence number `seq` into `out`; returns the bytes to send (delimiter
/// included).
pub fn encode<M: Message>(seq: u8, msg: &M, out: &mut [u8; MAX_FRAME]) -> usize {
    let mut raw = [0u8; MAX_RAW];
    raw[0] = msg.kind();
    raw[1] = seq;
    let n = msg.write_payload(&mut raw[2..2 + MAX_PAYLOAD]);
    let crc = crc32(&raw[..2 + n]);
    raw[2 + n..6 + n].copy_from_slice(&crc.to_le_bytes());
    // Cannot fail: `out` holds the worst case of the largest raw frame.
    let len = cobs_encode(&raw[..OVERHEAD + n], &mut out[..MAX_ENCODED]).unwrap_or(0);
    out[len] = 0;
    len + 1
}

/// Checks a raw (un-stuffed) frame and parses it.
pub fn decode_raw<M: Message>(raw: &[u8]) -> Result<Frame<M>, Rejected> {
    if raw.len() < OVERHEAD {
        let (k, seq) = (kind::UNKNOWN, 0);
        return Err(Rejected {
            kind: k,
            seq,
            error: LinkError::TooShort,
        });
    }
    let (body, crc) = raw.split_at(raw.len() - 4);
    let mut crc_bytes = [0u8; 4];
    crc_bytes.copy_from_slice(crc);
    if crc32(body) != u32::from_le_bytes(crc_bytes) {
        return Err(Rejected {
            kind: kind::UNKNOWN,
            seq: 0,
            error: LinkError::Crc,
        });
    }
    let (k, seq) = (body[0], body[1]);
    M::parse(k, &body[2..])
        .map(|msg| Frame { seq, msg })
        .map_err(|error| Rejected {
            kind: k,
            seq,
            error,
        })
}

/// Streaming receiver: feed it every byte from the wire; it returns a result per frame.
///
/// It keeps one encoded frame (at most [`MAX_ENCODED`] bytes) and the link counters. Garbage
/// longer than that is rejected as [`LinkError::Oversize`] once its delimiter arrives.
#[derive(Clone, Debug)]
pub struct Receiver {
    buf: [u8; MAX_ENCODED],
    len: usize,
    overflow: bool,
    /// Frames accepted.
    pub frames_ok: u32,
    /// Frames rejected.
    pub frames_bad: u32,
    /// The last rejection's reason, if any.
    pub last_error: Option<LinkError>,
}

impl Default for Receiver {
    fn default() -> Self {
        Self::new()
    }
}

impl Receiver {
    /// An empty receiver.
    pub const fn new() -> Self {
        Receiver {
            buf: [0; MAX_ENCODED],
            len: 0,
            overflow: false,
            frames_ok: 0,
            frames_bad: 0,
            last_error: None,
        }
    }

    /// Feeds one byte; returns `Some` when it completed a (non-empty) frame.
    pub fn push<M: Message>(&mut self, byte: u8) -> Option<Result<Frame<M>, Rejected>> {
        if byte != 0 {
            if self.len < MAX_ENCODED {
                self.buf[self.len] = byte;
                self.len += 1;
            } else {
                self.overflow = true;
            }
            return None;
        }
        let (len, overflow) = (self.len, self.overflow);
        self.len = 0;
        self.overflow = false;
        if len == 0 && !overflow {
            return None; // idle filler
        }
        let result = if overflow {
            Err(Rejected {
                kind: kind::UNKNOWN,
                seq: 0,
                error: LinkError::Oversize,
            })
        } else {
            match cobs_decode_in_place(&mut self.buf[..len]) {
                Ok(n) => decode_raw(&self.buf[..n]),
                Err(error) => Err(Rejected {
                    kind: kind::UNKNOWN,
                    seq: 0,
                    error,
                }),
            }
        };
        match &result {
            Ok(_) => self.frames_ok = self.frames_ok.wrapping_add(1),
            Err(r) => self.reject(r.error),
        }
        Some(result)
    }

    /// Counts a frame that decoded but was refused later (by the drive or the transfer logic).
    pub fn reject(&mut self, error: LinkError) {
        self.frames_bad = self.frames_bad.wrapping_add(1);
        self.last_error = Some(error);
    }
}

// ---- the drive's side of the link -------------------------------------------------------------

use crate::blob::{self, BlobError};
use crate::drive::{Command, CommandError, Drive, Faults, Output, Sample, Telemetry};
use crate::model::ModelKind;
use fixed::types::I16F16;

/// Wire code (`detail` of [`LinkError::Refused`]) of a drive refusal.
pub fn command_error_code(e: CommandError) -> u8 {
    match e {
        CommandError::TargetOutOfTravel => 1,
        CommandError::VelocityOutOfRange => 2,
        CommandError::AccelOutOfRange => 3,
        CommandError::NotEnabled => 4,
        CommandError::Busy => 6,
        CommandError::NotHomed => 7,
    }
}

/// The refusal with wire code `code`.
pub fn command_error_from_code(code: u8) -> Option<CommandError> {
    Some(match code {
        1 => CommandError::TargetOutOfTravel,
        2 => CommandError::VelocityOutOfRange,
        3 => CommandError::AccelOutOfRange,
        4 => CommandError::NotEnabled,
        6 => CommandError::Busy,
        7 => CommandError::NotHomed,
        _ => return None,
    })
}

/// `detail` codes of [`LinkError::Calibration`].
pub mod cal_error {
    /// A chunk or commit without a transfer in progress.
    pub const NOT_STARTED: u8 = 1;
    /// A chunk not at the next expected offset.
    pub const OFFSET: u8 = 2;
    /// The blob (or a chunk's end) is longer than the drive accepts.
    pub const TOO_LONG: u8 = 3;
    /// Commit before all bytes arrived.
    pub const INCOMPLETE: u8 = 4;
    /// The received bytes do not match the announced CRC.
    pub const CRC: u8 = 5;
    /// The drive rejected the blob's contents: this bit plus [`super::blob_error_code`].
    pub const REJECTED: u8 = 0x10;
}

/// Wire code of a blob refusal (low bits of a [`cal_error::REJECTED`] detail).
pub fn blob_error_code(e: BlobError) -> u8 {
    match e {
        BlobError::Truncated => 1,
        BlobError::TooLong => 2,
        BlobError::BadMagic => 3,
        BlobError::UnsupportedVersion(_) => 4,
        BlobError::BadChecksum => 5,
        BlobError::RigMismatch => 6,
        BlobError::BadCount(_) => 7,
        BlobError::Invalid(_) => 8,
        BlobError::Busy => 9,
        BlobError::BufferTooSmall => 10,
        BlobError::Unrepresentable(_) => 11,
    }
}

/// The request for a drive command, if `req` is one.
pub fn to_command(req: &Request) -> Option<Command> {
    Some(match *req {
        Request::MoveMotor {
            target_um,
            velocity_um_s,
            accel_um_s2,
        } => Command::MoveMotorTo {
            target_um,
            velocity_um_s,
            accel_um_s2,
        },
        Request::Move {
            target_um,
            velocity_um_s,
            accel_um_s2,
        } => Command::MoveTo {
            target_um,
            velocity_um_s,
            accel_um_s2,
        },
        Request::Stop => Command::Stop,
        Request::Enable => Command::Enable,
        Request::Disable => Command::Disable,
        Request::ClearFaults => Command::ClearFaults,
        // Range-checked by the decoder, so `from_u8` cannot fail here; stay total anyway.
        Request::SelectModel(m) => Command::SelectModel(ModelKind::from_u8(m)?),
        Request::Home {
            position_um,
            scale_um,
        } => Command::Home {
            position_um,
            scale_um,
        },
        _ => return None,
    })
}

/// The request that carries `cmd`.
pub fn from_command(cmd: &Command) -> Request {
    match *cmd {
        Command::MoveMotorTo {
            target_um,
            velocity_um_s,
            accel_um_s2,
        } => Request::MoveMotor {
            target_um,
            velocity_um_s,
            accel_um_s2,
        },
        Command::MoveTo {
            target_um,
            velocity_um_s,
            accel_um_s2,
        } => Request::Move {
            target_um,
            velocity_um_s,
            accel_um_s2,
        },
        Command::Stop => Request::Stop,
        Command::Enable => Request::Enable,
        Command::Disable => Request::Disable,
        Command::ClearFaults => Request::ClearFaults,
        Command::SelectModel(m) => Request::SelectModel(m as u8),
        Command::Home {
            position_um,
            scale_um,
        } => Request::Home {
            position_um,
            scale_um,
        },
    }
}

impl From<&Telemetry> for WireTelemetry {
    fn from(t: &Telemetry) -> Self {
        WireTelemetry {
            tick: t.tick,
            motor_counts: t.motor_counts,
            scale_counts: t.scale_counts,
            setpoint_counts: t.setpoint_counts,
            following_error_counts: t.following_error_counts,
            est_error_um_bits: t.est_error_um.to_bits(),
            current_a_bits: t.current_a.to_bits(),
            faults: t.faults.0,
            model: t.model as u8,
            moving: t.moving,
            amplifier_enabled: t.amplifier_enabled,
            homed: t.homed,
        }
    }
}

impl TryFrom<WireTelemetry> for Telemetry {
    type Error = LinkError;
    fn try_from(w: WireTelemetry) -> Result<Self, LinkError> {
        Ok(Telemetry {
            tick: w.tick,
            motor_counts: w.motor_counts,
            scale_counts: w.scale_counts,
            setpoint_counts: w.setpoint_counts,
            following_error_counts: w.following_error_counts,
            est_error_um: I16F16::from_bits(w.est_error_um_bits),
            current_a: I16F16::from_bits(w.current_a_bits),
            faults: Faults(w.faults),
            model: ModelKind::from_u8(w.model).ok_or(LinkError::OutOfRange)?,
            moving: w.moving,
            amplifier_enabled: w.amplifier_enabled,
            homed: w.homed,
        })
    }
}

/// The PIL answer for one tick's output.
pub fn answer(out: &Output, step_instructions: u32) -> Reply {
    Reply::Answer {
        current_a_bits: out.current_a.to_bits(),
        telemetry: WireTelemetry::from(&out.telemetry),
        step_instructions,
    }
}

/// The output a PIL answer carries, or `None` if the reply is not an answer or is invalid.
pub fn output_of(reply: &Reply) -> Option<(Output, u32)> {
    match *reply {
        Reply::Answer {
            current_a_bits,
            telemetry,
            step_instructions,
        } => Some((
            Output {
                current_a: I16F16::from_bits(current_a_bits),
                telemetry: Telemetry::try_from(telemetry).ok()?,
            },
            step_instructions,
        )),
        _ => None,
    }
}

/// What the firmware must do after [`Endpoint::handle`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Effect {
    /// Send this reply.
    Reply(Reply),
    /// PIL: run one control tick on this sample (the control task sends the answer).
    Tick(Sample),
    /// Send a [`Reply::Status`] (built with [`Endpoint::status`]).
    Status,
    /// Stream telemetry every `n` ticks (0 = off); then acknowledge.
    Stream(u16),
    /// QEMU: log the statistics and exit with this status.
    Shutdown(u8),
    /// A complete, CRC-checked calibration of this many bytes awaits: decode it
    /// ([`Endpoint::calibration`], [`crate::blob::decode_coeffs`]) outside any lock the control
    /// task needs, install it with [`Drive::set_models`], then report with
    /// [`Endpoint::calibration_done`].
    Calibrate(usize),
}

/// An event worth a log line, reported by [`Endpoint::handle`] (the core has no logger).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Event {
    /// Nothing to report.
    None,
    /// A command was applied.
    Applied(Command),
    /// A command was refused.
    Refused(Command, CommandError),
    /// A calibration transfer began.
    CalibrationBegun {
        /// Announced length, bytes.
        total_len: u32,
    },
    /// A calibration step was refused (see [`cal_error`]).
    CalibrationRefused(u8),
    /// A calibration blob was loaded.
    CalibrationLoaded {
        /// Its length, bytes.
        len: u32,
    },
    /// The drive rejected a blob.
    CalibrationRejected(BlobError),
}

/// The drive's end of the link: turns requests into drive commands, assembles calibration
/// blobs, and says what to answer. Frame decoding stays in [`Receiver`].
pub struct Endpoint {
    blob: [u8; blob::MAX_BYTES],
    /// Transfer in progress: announced length and CRC, bytes received, running CRC.
    transfer: Option<(usize, u32, usize, Crc32)>,
    calibrated: bool,
    streaming: bool,
}

impl Default for Endpoint {
    fn default() -> Self {
        Self::new()
    }
}

impl Endpoint {
    /// A fresh endpoint (drive disabled, nothing loaded).
    pub const fn new() -> Self {
        Endpoint {
            blob: [0; blob::MAX_BYTES],
            transfer: None,
            calibrated: false,
            streaming: false,
        }
    }

    /// The assembled calibration blob of an [`Effect::Calibrate`] (`len` bytes).
    pub fn calibration(&self, len: usize) -> &[u8] {
        &self.blob[..len.min(self.blob.len())]
    }

    /// Reports the outcome of installing a calibration of `len` bytes.
    pub fn calibration_done(
        &mut self,
        len: usize,
        result: Result<(), BlobError>,
    ) -> (Reply, Event) {
        match result {
            Ok(()) => {
                self.calibrated = true;
                (
                    Reply::Ack {
                        of: kind::CAL_COMMIT,
                    },
                    Event::CalibrationLoaded { len: len as u32 },
                )
            }
            Err(e) => (
                Reply::Error {
                    of: kind::CAL_COMMIT,
                    reason: LinkError::Calibration,
                    detail: cal_error::REJECTED | blob_error_code(e),
                },
                Event::CalibrationRejected(e),
            ),
        }
    }

    /// [`Endpoint::handle`] with a calibration decoded and installed in line: for hosts and
    /// tests, where no control task waits on the drive.
    pub fn handle_inline(&mut self, req: &Request, drive: &mut Drive) -> (Effect, Event) {
        match self.handle(req, drive) {
            (Effect::Calibrate(len), _) => {
                let result = crate::blob::decode_coeffs(self.calibration(len), drive.rig())
                    .and_then(|c| drive.set_models(c));
                let (reply, event) = self.calibration_done(len, result);
                (Effect::Reply(reply), event)
            }
            other => other,
        }
    }

    /// Acts on one decoded request. Drive commands are applied here; what the firmware must
    /// still do (send a reply, run a tick, ...) comes back as an [`Effect`], and anything worth
    /// logging as an [`Event`].
    pub fn handle(&mut self, req: &Request, drive: &mut Drive) -> (Effect, Event) {
        // Any valid frame keeps the link watchdog fed.
        drive.link_alive();
        let k = req.kind();
        let ack = Effect::Reply(Reply::Ack { of: k });
        let refuse = |reason: LinkError, detail: u8| {
            Effect::Reply(Reply::Error {
                of: k,
                reason,
                detail,
            })
        };
        if let Some(cmd) = to_command(req) {
            return match drive.command(cmd) {
                Ok(()) => (ack, Event::Applied(cmd)),
                Err(e) => (
                    refuse(LinkError::Refused, command_error_code(e)),
                    Event::Refused(cmd, e),
                ),
            };
        }
        match *req {
            Request::Sample {
                motor_counter,
                scale_counter,
            } => (
                Effect::Tick(Sample {
                    motor_counter,
                    scale_counter,
                }),
                Event::None,
            ),
            Request::Status => (Effect::Status, Event::None),
            Request::Telemetry { every_n_ticks } => {
                self.streaming = every_n_ticks != 0;
                (Effect::Stream(every_n_ticks), Event::None)
            }
            Request::Shutdown { code } => (Effect::Shutdown(code), Event::None),
            Request::CalBegin { total_len, crc32 } => {
                if total_len as usize > blob::MAX_BYTES {
                    self.transfer = None;
                    let d = cal_error::TOO_LONG;
                    return (
                        refuse(LinkError::Calibration, d),
                        Event::CalibrationRefused(d),
                    );
                }
                self.transfer = Some((total_len as usize, crc32, 0, Crc32::new()));
                (ack, Event::CalibrationBegun { total_len })
            }
            Request::CalChunk {
                offset,
                len,
                ref data,
            } => {
                let d = match &mut self.transfer {
                    None => cal_error::NOT_STARTED,
                    Some((_, _, got, _)) if offset as usize != *got => cal_error::OFFSET,
                    Some((total, _, got, _)) if *got + len as usize > *total => cal_error::TOO_LONG,
                    Some((_, _, got, crc)) => {
                        let piece = &data[..len as usize];
                        self.blob[*got..*got + piece.len()].copy_from_slice(piece);
                        crc.update(piece);
                        *got += piece.len();
                        return (ack, Event::None);
                    }
                };
                (
                    refuse(LinkError::Calibration, d),
                    Event::CalibrationRefused(d),
                )
            }
            Request::CalCommit => {
                let d = match self.transfer {
                    None => cal_error::NOT_STARTED,
                    Some((total, _, got, _)) if got != total => cal_error::INCOMPLETE,
                    Some((_, want, _, crc)) if crc.finish() != want => cal_error::CRC,
                    Some((total, ..)) => {
                        self.transfer = None;
                        // Decoding takes milliseconds of soft-float: the caller does it outside
                        // the drive's lock (see `Effect::Calibrate`).
                        return (Effect::Calibrate(total), Event::None);
                    }
                };
                if d == cal_error::CRC {
                    self.transfer = None;
                }
                (
                    refuse(LinkError::Calibration, d),
                    Event::CalibrationRefused(d),
                )
            }
            // Every command kind was handled above.
            _ => (refuse(LinkError::NotSupported, 0), Event::None),
        }
    }

    /// The status reply: the drive's latest telemetry and state, and the link counters.
    pub fn status(
        &self,
        drive: &Drive,
        rx: &Receiver,
        stack_peak_bytes: u32,
        reset_cause: u8,
    ) -> WireStatus {
        let last = drive.telemetry();
        let mut flags = 0;
        if last.moving {
            flags |= status_flags::MOVING;
        }
        if drive.is_enabled() {
            flags |= status_flags::ENABLED;
        }
        if self.calibrated {
            flags |= status_flags::CALIBRATED;
        }
        if self.streaming {
            flags |= status_flags::STREAMING;
        }
        if drive.is_homed() {
            flags |= status_flags::HOMED;
        }
        if last.amplifier_enabled {
            flags |= status_flags::AMPLIFIER_ENABLED;
        }
        WireStatus {
            tick: last.tick,
            motor_counts: last.motor_counts,
            faults: last.faults.0,
            model: last.model as u8,
            flags,
            last_error: rx.last_error.map_or(0, |e| e as u8),
            reset_cause,
            missed_ticks: drive.missed_tick_count(),
            scale_glitches: drive.scale_glitch_count(),
            frames_ok: rx.frames_ok,
            frames_bad: rx.frames_bad,
            stack_peak_bytes,
            carriage_target_um: drive.carriage_target_um(),
            carriage_estimate_um: drive.carriage_estimate_um(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn wire<M: Message>(seq: u8, m: &M) -> ([u8; MAX_FRAME], usize) {
        let mut out = [0u8; MAX_FRAME];
        let n = encode(seq, m, &mut out);
        (out, n)
    }

    fn feed<M: Message>(rx: &mut Receiver, bytes: &[u8]) -> Vec<Result<Frame<M>, Rejected>> {
        bytes.iter().filter_map(|&b| rx.push(b)).collect()
    }

    fn telemetry() -> WireTelemetry {
        WireTelemetry {
            tick: 0xDEAD_BEEF,
            motor_counts: -123_456,
            scale_counts: 7_654_321,
            setpoint_counts: i32::MIN,
            following_error_counts: i32::MAX,
            est_error_um_bits: -(3 << 16) - 0x8000,
            current_a_bits: 0x0001_8000,
            faults: 0b10_0000_1010,
            model: 3,
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
            Request::MoveMotor {
                target_um: -250_000,
                velocity_um_s: 50_000,
                accel_um_s2: 1,
            },
            Request::MoveMotor {
                target_um: i32::MAX,
                velocity_um_s: u32::MAX,
                accel_um_s2: u32::MAX,
            },
            Request::Move {
                target_um: -7,
                velocity_um_s: 3,
                accel_um_s2: 0x00ff_0000,
            },
            Request::Stop,
            Request::Enable,
            Request::Disable,
            Request::ClearFaults,
            Request::SelectModel(0),
            Request::SelectModel(MODEL_MAX),
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
            Request::Home {
                position_um: -5,
                scale_um: i32::MIN,
            },
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
                motor_counts: -2,
                faults: 0x0204,
                model: 2,
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
            }),
            Reply::Telemetry(telemetry()),
            Reply::Telemetry(WireTelemetry::default()),
            Reply::Answer {
                current_a_bits: -1,
                telemetry: telemetry(),
                step_instructions: 321,
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
        let m = Request::MoveMotor {
            target_um: 0x0403_0201,
            velocity_um_s: 5,
            accel_um_s2: 6,
        };
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
                42,
            ),
            (
                Reply::Telemetry(telemetry()).write_payload(&mut [0; MAX_PAYLOAD]),
                TELEMETRY_LEN,
            ),
            (
                Reply::Answer {
                    current_a_bits: 0,
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
    pub(crate) const KNOWN_MOVE_MOTOR: [u8; 20] = [
        9, 1, 9, 112, 47, 252, 255, 80, 195, 1, 4, 64, 13, 3, 5, 157, 230, 2, 169, 0,
    ];
    pub(crate) const KNOWN_SAMPLE: [u8; 12] = [2, 12, 3, 52, 18, 1, 5, 48, 121, 235, 166, 0];

    #[test]
    fn known_wire_bytes() {
        let (b, n) = wire(
            9,
            &Request::MoveMotor {
                target_um: -250_000,
                velocity_um_s: 50_000,
                accel_um_s2: 200_000,
            },
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
        // A chunk with one byte too many is longer than any frame.
        let mut body = vec![kind::CAL_CHUNK, 1, 0, 0, 0, 0];
        body.extend([1u8; CHUNK_MAX + 1]);
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

    // ---- the endpoint, against the real drive ----

    use crate::drive::{DriveConfig, Output as DriveOutput};

    fn drive() -> Drive {
        Drive::new(&DriveConfig::paper_rig()).unwrap()
    }

    fn refused(e: Effect) -> Option<(LinkError, u8)> {
        match e {
            Effect::Reply(Reply::Error { reason, detail, .. }) => Some((reason, detail)),
            _ => None,
        }
    }

    const ACK_ENABLE: Effect = Effect::Reply(Reply::Ack { of: kind::ENABLE });

    #[test]
    fn commands_map_both_ways() {
        let cmds = [
            Command::MoveMotorTo {
                target_um: 1,
                velocity_um_s: 2,
                accel_um_s2: 3,
            },
            Command::Stop,
            Command::Enable,
            Command::Disable,
            Command::ClearFaults,
            Command::SelectModel(ModelKind::Exponential),
            Command::Home {
                position_um: -4,
                scale_um: 5,
            },
        ];
        for c in cmds {
            assert_eq!(to_command(&from_command(&c)), Some(c));
        }
        assert_eq!(to_command(&Request::Status), None);
        for code in 0..=255u8 {
            if let Some(e) = command_error_from_code(code) {
                assert_eq!(command_error_code(e), code);
            }
        }
        assert_eq!(command_error_from_code(0), None);
    }

    #[test]
    fn telemetry_and_answers_convert_exactly() {
        let mut d = drive();
        let out = d.step(Sample {
            motor_counter: 7,
            scale_counter: 9,
        });
        let reply = answer(&out, 42);
        assert_eq!(output_of(&reply), Some((out, 42)));
        let mut w = WireTelemetry::from(&out.telemetry);
        w.model = MODEL_MAX + 1;
        assert_eq!(Telemetry::try_from(w), Err(LinkError::OutOfRange));
        assert_eq!(output_of(&Reply::Ack { of: 1 }), None::<(DriveOutput, u32)>);
    }

    #[test]
    fn endpoint_applies_commands_and_reports_refusals() {
        let mut d = drive();
        let mut ep = Endpoint::new();
        let mv = Request::MoveMotor {
            target_um: 10_000,
            velocity_um_s: 50_000,
            accel_um_s2: 500_000,
        };
        let (e, ev) = ep.handle_inline(&mv, &mut d);
        assert_eq!(
            refused(e),
            Some((
                LinkError::Refused,
                command_error_code(CommandError::NotEnabled)
            ))
        );
        assert!(matches!(ev, Event::Refused(_, CommandError::NotEnabled)));
        assert_eq!(ep.handle_inline(&Request::Enable, &mut d).0, ACK_ENABLE);
        assert!(d.is_enabled());
        let (e, ev) = ep.handle_inline(&mv, &mut d);
        assert_eq!(
            refused(e),
            Some((
                LinkError::Refused,
                command_error_code(CommandError::NotHomed)
            ))
        );
        assert!(matches!(ev, Event::Refused(_, CommandError::NotHomed)));
        let home = Request::Home {
            position_um: 0,
            scale_um: 0,
        };
        assert_eq!(
            ep.handle_inline(&home, &mut d).0,
            Effect::Reply(Reply::Ack { of: kind::HOME })
        );
        let (e, ev) = ep.handle_inline(&mv, &mut d);
        assert_eq!(
            e,
            Effect::Reply(Reply::Ack {
                of: kind::MOVE_MOTOR
            })
        );
        assert!(matches!(ev, Event::Applied(Command::MoveMotorTo { .. })));
        let far = Request::MoveMotor {
            target_um: 10_000_000,
            velocity_um_s: 1,
            accel_um_s2: 1,
        };
        let code = command_error_code(CommandError::TargetOutOfTravel);
        assert_eq!(
            refused(ep.handle_inline(&far, &mut d).0),
            Some((LinkError::Refused, code))
        );

        let s = Request::Sample {
            motor_counter: 3,
            scale_counter: 4,
        };
        let tick = Effect::Tick(Sample {
            motor_counter: 3,
            scale_counter: 4,
        });
        assert_eq!(ep.handle_inline(&s, &mut d).0, tick);
        assert_eq!(ep.handle_inline(&Request::Status, &mut d).0, Effect::Status);
        assert_eq!(
            ep.handle_inline(&Request::Telemetry { every_n_ticks: 20 }, &mut d)
                .0,
            Effect::Stream(20)
        );
        assert_eq!(
            ep.handle_inline(&Request::Shutdown { code: 3 }, &mut d).0,
            Effect::Shutdown(3)
        );

        let _ = d.step(Sample::default());
        let mut rx = Receiver::new();
        rx.reject(LinkError::Crc);
        let st = ep.status(&d, &rx, 1234, 0);
        assert_eq!(st.flags & status_flags::ENABLED, status_flags::ENABLED);
        assert_eq!(st.flags & status_flags::STREAMING, status_flags::STREAMING);
        assert_eq!(st.flags & status_flags::CALIBRATED, 0);
        assert_eq!(
            (st.frames_bad, st.last_error, st.stack_peak_bytes),
            (1, LinkError::Crc as u8, 1234)
        );
        assert_eq!(st.tick, d.telemetry().tick);
    }

    fn paper_blob() -> Vec<u8> {
        let mut buf = vec![0u8; blob::MAX_BYTES];
        let n = blob::encode(
            &crate::model::ModelParams::PAPER,
            &DriveConfig::paper_rig().rig,
            &mut buf,
        )
        .unwrap();
        buf.truncate(n);
        buf
    }

    fn chunk(offset: usize, piece: &[u8]) -> Request {
        let mut data = [0u8; CHUNK_MAX];
        data[..piece.len()].copy_from_slice(piece);
        Request::CalChunk {
            offset: offset as u32,
            len: piece.len() as u8,
            data,
        }
    }

    #[test]
    fn calibration_transfer_checks_every_step() {
        let blob = paper_blob();
        let mut d = drive();
        let mut ep = Endpoint::new();
        let cal = |d: u8| Some((LinkError::Calibration, d));
        // Nothing started.
        assert_eq!(
            refused(ep.handle_inline(&chunk(0, &blob[..8]), &mut d).0),
            cal(cal_error::NOT_STARTED)
        );
        assert_eq!(
            refused(ep.handle_inline(&Request::CalCommit, &mut d).0),
            cal(cal_error::NOT_STARTED)
        );
        // Too long for the drive.
        let huge = Request::CalBegin {
            total_len: blob::MAX_BYTES as u32 + 1,
            crc32: 0,
        };
        assert_eq!(
            refused(ep.handle_inline(&huge, &mut d).0),
            cal(cal_error::TOO_LONG)
        );
        // A good transfer with one out-of-order chunk refused on the way (and then resent).
        let begin = Request::CalBegin {
            total_len: blob.len() as u32,
            crc32: crc32(&blob),
        };
        assert!(matches!(
            ep.handle_inline(&begin, &mut d).0,
            Effect::Reply(Reply::Ack { .. })
        ));
        assert_eq!(
            refused(ep.handle_inline(&chunk(64, &blob[64..128]), &mut d).0),
            cal(cal_error::OFFSET)
        );
        for (i, piece) in blob.chunks(CHUNK_MAX).enumerate() {
            if i == 2 {
                // Commit before the end.
                assert_eq!(
                    refused(ep.handle_inline(&Request::CalCommit, &mut d).0),
                    cal(cal_error::INCOMPLETE)
                );
            }
            assert!(matches!(
                ep.handle_inline(&chunk(i * CHUNK_MAX, piece), &mut d).0,
                Effect::Reply(Reply::Ack { .. })
            ));
        }
        // Past the announced end.
        assert_eq!(
            refused(ep.handle_inline(&chunk(blob.len(), &[1]), &mut d).0),
            cal(cal_error::TOO_LONG)
        );
        let (e, ev) = ep.handle_inline(&Request::CalCommit, &mut d);
        assert!(matches!(e, Effect::Reply(Reply::Ack { .. })), "{e:?}");
        assert_eq!(
            ev,
            Event::CalibrationLoaded {
                len: blob.len() as u32
            }
        );
        assert_ne!(
            ep.status(&d, &Receiver::new(), 0, 0).flags & status_flags::CALIBRATED,
            0
        );

        // Bytes that do not match the announced CRC.
        let begin = Request::CalBegin {
            total_len: 8,
            crc32: crc32(&blob[..8]) ^ 1,
        };
        assert!(matches!(
            ep.handle_inline(&begin, &mut d).0,
            Effect::Reply(Reply::Ack { .. })
        ));
        assert!(matches!(
            ep.handle_inline(&chunk(0, &blob[..8]), &mut d).0,
            Effect::Reply(Reply::Ack { .. })
        ));
        assert_eq!(
            refused(ep.handle_inline(&Request::CalCommit, &mut d).0),
            cal(cal_error::CRC)
        );
        // A transfer that arrives intact but holds no valid blob: the drive refuses it.
        let begin = Request::CalBegin {
            total_len: 8,
            crc32: crc32(&blob[..8]),
        };
        assert!(matches!(
            ep.handle_inline(&begin, &mut d).0,
            Effect::Reply(Reply::Ack { .. })
        ));
        assert!(matches!(
            ep.handle_inline(&chunk(0, &blob[..8]), &mut d).0,
            Effect::Reply(Reply::Ack { .. })
        ));
        let (e, ev) = ep.handle_inline(&Request::CalCommit, &mut d);
        let code = cal_error::REJECTED | blob_error_code(BlobError::Truncated);
        assert_eq!(refused(e), cal(code));
        assert_eq!(ev, Event::CalibrationRejected(BlobError::Truncated));

        // Without the inline helper, a complete transfer is handed back for decoding outside
        // the drive's lock, with exactly the bytes that arrived; the drive is untouched.
        let before = d.models().clone();
        let begin = Request::CalBegin {
            total_len: blob.len() as u32,
            crc32: crc32(&blob),
        };
        assert!(matches!(
            ep.handle(&begin, &mut d).0,
            Effect::Reply(Reply::Ack { .. })
        ));
        for (i, piece) in blob.chunks(CHUNK_MAX).enumerate() {
            assert!(matches!(
                ep.handle(&chunk(i * CHUNK_MAX, piece), &mut d).0,
                Effect::Reply(Reply::Ack { .. })
            ));
        }
        assert_eq!(
            ep.handle(&Request::CalCommit, &mut d).0,
            Effect::Calibrate(blob.len())
        );
        assert_eq!(ep.calibration(blob.len()), &blob[..]);
        assert_eq!(d.models(), &before);
    }

    fn arb_request() -> impl Strategy<Value = Request> {
        prop_oneof![
            (any::<i32>(), 1..=u32::MAX, 1..=u32::MAX).prop_map(|(t, v, a)| Request::MoveMotor {
                target_um: t,
                velocity_um_s: v,
                accel_um_s2: a
            }),
            (any::<i32>(), 1..=u32::MAX, 1..=u32::MAX).prop_map(|(t, v, a)| {
                Request::Move {
                    target_um: t,
                    velocity_um_s: v,
                    accel_um_s2: a,
                }
            }),
            Just(Request::Stop),
            Just(Request::Enable),
            Just(Request::Disable),
            Just(Request::ClearFaults),
            (0..=MODEL_MAX).prop_map(Request::SelectModel),
            (1..=u32::MAX, any::<u32>()).prop_map(|(l, c)| Request::CalBegin {
                total_len: l,
                crc32: c
            }),
            (
                any::<u32>(),
                proptest::collection::vec(any::<u8>(), 1..=CHUNK_MAX)
            )
                .prop_map(|(o, d)| {
                    let mut data = [0u8; CHUNK_MAX];
                    data[..d.len()].copy_from_slice(&d);
                    Request::CalChunk {
                        offset: o,
                        len: d.len() as u8,
                        data,
                    }
                }),
            Just(Request::CalCommit),
            Just(Request::Status),
            any::<u16>().prop_map(|n| Request::Telemetry { every_n_ticks: n }),
            (any::<u16>(), any::<u16>()).prop_map(|(m, s)| Request::Sample {
                motor_counter: m,
                scale_counter: s
            }),
            any::<u8>().prop_map(|code| Request::Shutdown { code }),
            (any::<i32>(), any::<i32>()).prop_map(|(p, s)| Request::Home {
                position_um: p,
                scale_um: s
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
}
