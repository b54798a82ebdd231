//! The messages: kinds, [`Request`], [`Reply`], their fixed-size payloads and the hand codec.

use crate::bytes::{Fields, Reader, Short, Writer};
use crate::command::{Command, ModelKind};
use crate::faults::Faults;
use crate::units::{MotorCounts, ScaleCounts};
use fixed::types::I16F16;

/// Largest payload of any message (a calibration read-back: offset, total length and
/// [`CHUNK_MAX`] bytes).
pub const MAX_PAYLOAD: usize = 8 + CHUNK_MAX;
/// Largest raw (un-stuffed) frame: kind, seq, payload, CRC.
pub const MAX_RAW: usize = 2 + MAX_PAYLOAD + 4;
/// Largest COBS-encoded frame, without the delimiter.
pub const MAX_ENCODED: usize = MAX_RAW + MAX_RAW.div_ceil(254);
/// Largest frame on the wire, delimiter included: the size of an encode buffer.
pub const MAX_FRAME: usize = MAX_ENCODED + 1;
/// Largest data part of one calibration chunk.
pub const CHUNK_MAX: usize = 64;
/// Raw bytes around a payload: kind, seq and CRC.
pub(crate) const OVERHEAD: usize = 6;

/// Message kinds (the first raw byte).
pub mod kind {
    /// [`crate::Command::MoveMotorTo`]
    pub const MOVE_MOTOR: u8 = 0x01;
    /// [`crate::Command::Stop`]
    pub const STOP: u8 = 0x02;
    /// [`crate::Command::Enable`]
    pub const ENABLE: u8 = 0x03;
    /// [`crate::Command::Disable`]
    pub const DISABLE: u8 = 0x04;
    /// [`crate::Command::ClearFaults`]
    pub const CLEAR_FAULTS: u8 = 0x05;
    /// [`crate::Command::SelectModel`]
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
    /// [`crate::Command::Home`]
    pub const HOME: u8 = 0x0e;
    /// [`crate::Command::MoveTo`]
    pub const MOVE: u8 = 0x0f;
    /// [`super::Request::ConfigSet`]
    pub const CONFIG_SET: u8 = 0x10;
    /// [`super::Request::ConfigGet`]
    pub const CONFIG_GET: u8 = 0x11;
    /// [`super::Request::ConfigApply`]
    pub const CONFIG_APPLY: u8 = 0x12;
    /// [`super::Request::Save`]
    pub const SAVE: u8 = 0x13;
    /// [`crate::Command::Homing`]
    pub const HOMING: u8 = 0x14;
    /// [`super::Request::Record`]
    pub const RECORD: u8 = 0x15;
    /// [`super::Request::CalRead`]
    pub const CAL_READ: u8 = 0x16;
    /// [`super::Request::ConfigParts`]
    pub const CONFIG_PARTS: u8 = 0x17;
    /// The highest request kind: the kinds after it up to 0x7f are unused.
    pub const LAST_REQUEST: u8 = CONFIG_PARTS;

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
    /// [`super::Reply::ConfigValue`]
    pub const CONFIG_VALUE: u8 = 0x85;
    /// [`super::Reply::Saved`]
    pub const SAVED: u8 = 0x86;
    /// [`super::Reply::Records`]
    pub const RECORDS: u8 = 0x87;
    /// [`super::Reply::CalData`]
    pub const CAL_DATA: u8 = 0x88;

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
    /// A configuration value was refused; `detail` is the key of the offending field.
    Config = 11,
    /// Persistent storage failed or was refused; `detail` names the reason.
    Storage = 12,
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
            11 => LinkError::Config,
            12 => LinkError::Storage,
            _ => return None,
        })
    }
}

/// Highest compensator number a `SelectModel` command, a status or a telemetry frame may carry
/// (0 none, 1-3 Models 1-3, 4 constant backlash, 5 bidirectional table, 6 Model 4; see
/// [`ModelKind`]).
pub const MODEL_MAX: u8 = ModelKind::ALL.len() as u8 - 1;

/// Host -> drive messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Request {
    /// A drive command, one kind per variant: `MoveMotorTo` 0x01, `MoveTo` 0x0f, `Stop` 0x02,
    /// `Enable` 0x03, `Disable` 0x04, `ClearFaults` 0x05, `SelectModel` 0x06, `Home` 0x0e
    /// (payloads: moves 12 bytes, `SelectModel` 1, `Home` 8, the others 0). Answered with
    /// [`Reply::Ack`], or [`Reply::Error`] with [`LinkError::Refused`] and the
    /// [`CommandError::code`] of the refusal.
    Command(Command),
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
    /// QEMU only: log the run's statistics and end the emulator with exit status `code`
    /// (payload 1).
    Shutdown {
        /// Exit status.
        code: u8,
    },
    /// Stage one configuration value (payload 9: key, `f64` little endian); nothing changes
    /// until [`Request::ConfigApply`]. Answered with [`Reply::Ack`].
    ConfigSet {
        /// Field key (the drive's settings table names it).
        key: u8,
        /// Value in the field's SI unit: the bits of an `f64` (`f64::to_bits`), so that
        /// messages keep `Eq` and a NaN reaches the drive's check as sent.
        value_bits: u64,
    },
    /// Read one configuration value (payload 1); answered with [`Reply::ConfigValue`].
    ConfigGet {
        /// Field key.
        key: u8,
    },
    /// One piece of the configuration image the host built from the staged values (payload
    /// 2 + `len`): the drive converts no units itself. Pieces arrive in order from offset 0.
    ConfigParts {
        /// Offset of `data[0]` in the image.
        offset: u16,
        /// Valid bytes in `data`, `1..=CHUNK_MAX`.
        len: u8,
        /// The bytes; only `data[..len]` is meaningful (the rest is zero).
        data: [u8; CHUNK_MAX],
    },
    /// Check the configuration image ([`Request::ConfigParts`]) against the staged values and
    /// make both the drive's (payload 0); only while disabled. Refused with
    /// [`LinkError::Config`] and the key of the offending field.
    ConfigApply,
    /// Store the configuration and the calibration in persistent storage (payload 0); only
    /// while disabled. Answered with [`Reply::Saved`].
    Save,
    /// Stream [`Reply::Records`] with one sample every `every_n_ticks` ticks; 0 stops it
    /// (payload 2).
    Record {
        /// Decimation; 0 = off.
        every_n_ticks: u16,
    },
    /// Read back [`CHUNK_MAX`] bytes of the installed calibration blob from `offset` (payload 4);
    /// answered with [`Reply::CalData`].
    CalRead {
        /// Offset of the first byte.
        offset: u32,
    },
}

/// One recorded sample in wire form ([`RECORD_SAMPLE_LEN`] bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RecordSample {
    /// Unwrapped motor position.
    pub motor_counts: MotorCounts,
    /// Unwrapped linear-scale position.
    pub scale_counts: ScaleCounts,
    /// Trajectory set-point.
    pub setpoint_counts: MotorCounts,
    /// Current command, milliamperes (saturating).
    pub current_ma: i16,
}

/// Wire size of a [`RecordSample`].
pub const RECORD_SAMPLE_LEN: usize = 14;
/// Samples in one [`Reply::Records`] frame.
pub const RECORD_BATCH: usize = 4;

/// Everything a control tick reports, in integer units: the drive keeps one per tick (the
/// drive's `Telemetry` is this type) and the link carries it as is ([`TELEMETRY_LEN`] bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Telemetry {
    /// Tick counter since start.
    pub tick: u32,
    /// Unwrapped motor position (x_PE).
    pub motor_counts: MotorCounts,
    /// Unwrapped linear-scale position (x_LS).
    pub scale_counts: ScaleCounts,
    /// Trajectory set-point, whole motor counts.
    pub setpoint_counts: MotorCounts,
    /// Set-point minus measured position, whole motor counts.
    pub following_error_counts: MotorCounts,
    /// Estimated transmission error y = x_LS - x_PE, micrometres.
    pub est_error_um: I16F16,
    /// Current command sent to the amplifier, amperes.
    pub current_a: I16F16,
    /// Latched fault bits.
    pub faults: Faults,
    /// Active error model (an unknown number on the wire is refused as out of range).
    pub model: ModelKind,
    /// A move is in progress.
    pub moving: bool,
    /// The amplifier's enable line: high only while the drive is enabled and no fault is
    /// latched.
    pub amplifier_enabled: bool,
    /// The position has been homed since start (moves are refused before).
    pub homed: bool,
}

/// Wire size of [`Telemetry`].
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
    /// Unwrapped motor position.
    pub motor_counts: MotorCounts,
    /// Latched fault bits.
    pub faults: Faults,
    /// Active error model.
    pub model: ModelKind,
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
    /// Unwrapped linear-scale position (0 without a scale).
    pub scale_counts: ScaleCounts,
    /// CRC-32 of the stored record the drive booted from or last saved (0 = none).
    pub record_crc: u32,
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
    /// The drive holds a valid configuration (otherwise it refuses to enable).
    pub const CONFIGURED: u8 = 1 << 6;
    /// The homing routine is running.
    pub const HOMING: u8 = 1 << 7;
    /// All defined bits.
    pub const ALL: u8 =
        MOVING | ENABLED | CALIBRATED | STREAMING | HOMED | AMPLIFIER_ENABLED | CONFIGURED | HOMING;
}

/// Wire size of [`WireStatus`].
pub const STATUS_LEN: usize = 50;

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
    Telemetry(Telemetry),
    /// PIL: answer to [`Request::Sample`] (payload 4 + [`TELEMETRY_LEN`] + 4).
    Answer {
        /// Current command, amperes.
        current_a: I16F16,
        /// The tick's telemetry.
        telemetry: Telemetry,
        /// Instructions `Drive::control` took (QEMU instruction counter; 0 where not measured).
        step_instructions: u32,
    },
    /// Answer to [`Request::ConfigGet`] (payload 17).
    ConfigValue {
        /// Field key.
        key: u8,
        /// The value the drive runs with (`f64` bits).
        active_bits: u64,
        /// The staged value (`f64` bits; equal to `active_bits` unless changed since the last
        /// apply).
        staged_bits: u64,
    },
    /// Answer to [`Request::Save`] (payload 8).
    Saved {
        /// Sequence number of the new record.
        seq: u32,
        /// Its CRC-32.
        crc32: u32,
    },
    /// Recorded samples (payload 11 + `count` x [`RECORD_SAMPLE_LEN`]).
    Records {
        /// Frame sequence number, +1 per frame since the recording started: a gap is a loss.
        seq: u32,
        /// Control tick of `samples[0]`.
        first_tick: u32,
        /// Ticks between two samples.
        every: u16,
        /// Valid samples, `1..=RECORD_BATCH`.
        count: u8,
        /// The samples; only `samples[..count]` are meaningful.
        samples: [RecordSample; RECORD_BATCH],
    },
    /// Answer to [`Request::CalRead`] (payload 8 + `len`).
    CalData {
        /// Offset of `data[0]`.
        offset: u32,
        /// Length of the installed blob (0 = none).
        total_len: u32,
        /// Valid bytes in `data`, `0..=CHUNK_MAX`.
        len: u8,
        /// The bytes; only `data[..len]` is meaningful.
        data: [u8; CHUNK_MAX],
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

impl From<Short> for LinkError {
    fn from(_: Short) -> Self {
        LinkError::BadLength
    }
}

/// The bytes after a `head`-byte header: `min..=CHUNK_MAX` of them, zero-padded to
/// [`CHUNK_MAX`], with their count (the chunked transfers' pieces).
#[inline(always)]
fn piece(payload: &[u8], head: usize, min: usize) -> Result<(u8, [u8; CHUNK_MAX]), LinkError> {
    if payload.len() < head + min || payload.len() > head + CHUNK_MAX {
        return Err(LinkError::BadLength);
    }
    let n = payload.len() - head;
    let mut data = [0u8; CHUNK_MAX];
    data[..n].copy_from_slice(&payload[head..]);
    Ok((n as u8, data))
}

fn expect_len(payload: &[u8], len: usize) -> Result<Reader<'_>, LinkError> {
    if payload.len() == len {
        Ok(Reader::new(payload))
    } else {
        Err(LinkError::BadLength)
    }
}

/// A model number the drive defines; any other is out of range.
fn read_model(r: &mut Reader<'_>) -> Result<ModelKind, LinkError> {
    ModelKind::from_u8(r.u8()?).ok_or(LinkError::OutOfRange)
}

impl Telemetry {
    fn write(&self, w: &mut Writer<'_>) {
        w.u32(self.tick);
        w.i32(self.motor_counts.0);
        w.i32(self.scale_counts.0);
        w.i32(self.setpoint_counts.0);
        w.i32(self.following_error_counts.0);
        w.i32(self.est_error_um.to_bits());
        w.i32(self.current_a.to_bits());
        w.u16(self.faults.0);
        w.u8(self.model as u8);
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
        Ok(Telemetry {
            tick: r.u32()?,
            motor_counts: MotorCounts(r.i32()?),
            scale_counts: ScaleCounts(r.i32()?),
            setpoint_counts: MotorCounts(r.i32()?),
            following_error_counts: MotorCounts(r.i32()?),
            est_error_um: I16F16::from_bits(r.i32()?),
            current_a: I16F16::from_bits(r.i32()?),
            faults: Faults(r.u16()?),
            model: read_model(r)?,
            moving: false,
            amplifier_enabled: false,
            homed: false,
        })
        .and_then(|mut t| {
            let flags = r.u8()?;
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
            Request::Command(c) => match c {
                Command::MoveMotorTo { .. } => kind::MOVE_MOTOR,
                Command::MoveTo { .. } => kind::MOVE,
                Command::Stop => kind::STOP,
                Command::Enable => kind::ENABLE,
                Command::Disable => kind::DISABLE,
                Command::ClearFaults => kind::CLEAR_FAULTS,
                Command::SelectModel(_) => kind::SELECT_MODEL,
                Command::Home { .. } => kind::HOME,
                Command::Homing => kind::HOMING,
            },
            Request::CalBegin { .. } => kind::CAL_BEGIN,
            Request::CalChunk { .. } => kind::CAL_CHUNK,
            Request::CalCommit => kind::CAL_COMMIT,
            Request::Status => kind::STATUS,
            Request::Telemetry { .. } => kind::TELEMETRY,
            Request::Sample { .. } => kind::SAMPLE,
            Request::Shutdown { .. } => kind::SHUTDOWN,
            Request::ConfigSet { .. } => kind::CONFIG_SET,
            Request::ConfigGet { .. } => kind::CONFIG_GET,
            Request::ConfigApply => kind::CONFIG_APPLY,
            Request::Save => kind::SAVE,
            Request::Record { .. } => kind::RECORD,
            Request::CalRead { .. } => kind::CAL_READ,
            Request::ConfigParts { .. } => kind::CONFIG_PARTS,
        }
    }

    fn write_payload(&self, out: &mut [u8]) -> usize {
        let mut w = Writer::new(out);
        match *self {
            Request::Command(
                Command::MoveMotorTo {
                    target_um,
                    velocity_um_s,
                    accel_um_s2,
                }
                | Command::MoveTo {
                    target_um,
                    velocity_um_s,
                    accel_um_s2,
                },
            ) => {
                w.i32(target_um);
                w.u32(velocity_um_s);
                w.u32(accel_um_s2);
            }
            Request::Command(
                Command::Stop
                | Command::Enable
                | Command::Disable
                | Command::ClearFaults
                | Command::Homing,
            )
            | Request::CalCommit
            | Request::Status
            | Request::ConfigApply
            | Request::Save => {}
            Request::Command(Command::SelectModel(m)) => w.u8(m as u8),
            Request::Command(Command::Home {
                position_um,
                scale_um,
            }) => {
                w.i32(position_um);
                w.i32(scale_um);
            }
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
            Request::ConfigSet { key, value_bits } => {
                w.u8(key);
                w.u64(value_bits);
            }
            Request::ConfigGet { key } => w.u8(key),
            Request::Record { every_n_ticks } => w.u16(every_n_ticks),
            Request::CalRead { offset } => w.u32(offset),
            Request::ConfigParts {
                offset,
                len,
                ref data,
            } => {
                w.u16(offset);
                w.put(&data[..(len as usize).min(CHUNK_MAX)]);
            }
        }
        // Cannot overflow: every payload fits MAX_PAYLOAD.
        w.len()
    }

    fn parse(k: u8, payload: &[u8]) -> Result<Self, LinkError> {
        let command = |c| Ok(Request::Command(c));
        match k {
            kind::MOVE_MOTOR | kind::MOVE => {
                let mut r = expect_len(payload, 12)?;
                let (target_um, velocity_um_s, accel_um_s2) = (r.i32()?, r.u32()?, r.u32()?);
                if velocity_um_s == 0 || accel_um_s2 == 0 {
                    return Err(LinkError::OutOfRange);
                }
                command(Command::move_to(
                    k == kind::MOVE,
                    target_um,
                    velocity_um_s,
                    accel_um_s2,
                ))
            }
            kind::STOP => expect_len(payload, 0).and_then(|_| command(Command::Stop)),
            kind::ENABLE => expect_len(payload, 0).and_then(|_| command(Command::Enable)),
            kind::DISABLE => expect_len(payload, 0).and_then(|_| command(Command::Disable)),
            kind::CLEAR_FAULTS => {
                expect_len(payload, 0).and_then(|_| command(Command::ClearFaults))
            }
            kind::SELECT_MODEL => {
                let m = expect_len(payload, 1)?.u8()?;
                command(Command::SelectModel(
                    ModelKind::from_u8(m).ok_or(LinkError::OutOfRange)?,
                ))
            }
            kind::HOME => {
                let mut r = expect_len(payload, 8)?;
                command(Command::Home {
                    position_um: r.i32()?,
                    scale_um: r.i32()?,
                })
            }
            kind::CAL_COMMIT => expect_len(payload, 0).map(|_| Request::CalCommit),
            kind::STATUS => expect_len(payload, 0).map(|_| Request::Status),
            kind::CAL_BEGIN => {
                let mut r = expect_len(payload, 8)?;
                let (total_len, crc32) = (r.u32()?, r.u32()?);
                if total_len == 0 {
                    return Err(LinkError::OutOfRange);
                }
                Ok(Request::CalBegin { total_len, crc32 })
            }
            kind::CAL_CHUNK => {
                let (len, data) = piece(payload, 4, 1)?;
                Ok(Request::CalChunk {
                    offset: Reader::new(payload).u32()?,
                    len,
                    data,
                })
            }
            kind::TELEMETRY => Ok(Request::Telemetry {
                every_n_ticks: expect_len(payload, 2)?.u16()?,
            }),
            kind::SAMPLE => {
                let mut r = expect_len(payload, 4)?;
                Ok(Request::Sample {
                    motor_counter: r.u16()?,
                    scale_counter: r.u16()?,
                })
            }
            kind::SHUTDOWN => Ok(Request::Shutdown {
                code: expect_len(payload, 1)?.u8()?,
            }),
            kind::HOMING => expect_len(payload, 0).and_then(|_| command(Command::Homing)),
            kind::CONFIG_SET => {
                let mut r = expect_len(payload, 9)?;
                Ok(Request::ConfigSet {
                    key: r.u8()?,
                    value_bits: r.u64()?,
                })
            }
            kind::CONFIG_GET => Ok(Request::ConfigGet {
                key: expect_len(payload, 1)?.u8()?,
            }),
            kind::CONFIG_APPLY => expect_len(payload, 0).map(|_| Request::ConfigApply),
            kind::SAVE => expect_len(payload, 0).map(|_| Request::Save),
            kind::RECORD => Ok(Request::Record {
                every_n_ticks: expect_len(payload, 2)?.u16()?,
            }),
            kind::CAL_READ => Ok(Request::CalRead {
                offset: expect_len(payload, 4)?.u32()?,
            }),
            kind::CONFIG_PARTS => {
                let (len, data) = piece(payload, 2, 1)?;
                Ok(Request::ConfigParts {
                    offset: Reader::new(payload).u16()?,
                    len,
                    data,
                })
            }
            _ => Err(LinkError::UnknownKind),
        }
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
            Reply::ConfigValue { .. } => kind::CONFIG_VALUE,
            Reply::Saved { .. } => kind::SAVED,
            Reply::Records { .. } => kind::RECORDS,
            Reply::CalData { .. } => kind::CAL_DATA,
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
                w.i32(s.motor_counts.0);
                w.u16(s.faults.0);
                w.u8(s.model as u8);
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
                w.i32(s.scale_counts.0);
                w.u32(s.record_crc);
            }
            Reply::Telemetry(t) => t.write(&mut w),
            Reply::Answer {
                current_a,
                telemetry,
                step_instructions,
            } => {
                w.i32(current_a.to_bits());
                telemetry.write(&mut w);
                w.u32(step_instructions);
            }
            Reply::ConfigValue {
                key,
                active_bits,
                staged_bits,
            } => {
                w.u8(key);
                w.u64(active_bits);
                w.u64(staged_bits);
            }
            Reply::Saved { seq, crc32 } => {
                w.u32(seq);
                w.u32(crc32);
            }
            Reply::Records {
                seq,
                first_tick,
                every,
                count,
                ref samples,
            } => {
                w.u32(seq);
                w.u32(first_tick);
                w.u16(every);
                let n = (count as usize).min(RECORD_BATCH);
                w.u8(n as u8);
                for s in &samples[..n] {
                    w.i32(s.motor_counts.0);
                    w.i32(s.scale_counts.0);
                    w.i32(s.setpoint_counts.0);
                    w.u16(s.current_ma as u16);
                }
            }
            Reply::CalData {
                offset,
                total_len,
                len,
                ref data,
            } => {
                w.u32(offset);
                w.u32(total_len);
                w.put(&data[..(len as usize).min(CHUNK_MAX)]);
            }
        }
        w.len()
    }

    fn parse(k: u8, payload: &[u8]) -> Result<Self, LinkError> {
        Ok(match k {
            kind::ACK => Reply::Ack {
                of: expect_len(payload, 1)?.u8()?,
            },
            kind::ERROR => {
                let mut r = expect_len(payload, 3)?;
                let of = r.u8()?;
                let reason = LinkError::from_code(r.u8()?).ok_or(LinkError::OutOfRange)?;
                Reply::Error {
                    of,
                    reason,
                    detail: r.u8()?,
                }
            }
            kind::STATUS_REPLY => {
                let mut r = expect_len(payload, STATUS_LEN)?;
                let s = WireStatus {
                    tick: r.u32()?,
                    motor_counts: MotorCounts(r.i32()?),
                    faults: Faults(r.u16()?),
                    model: read_model(&mut r)?,
                    flags: r.u8()?,
                    last_error: r.u8()?,
                    reset_cause: r.u8()?,
                    missed_ticks: r.u32()?,
                    scale_glitches: r.u32()?,
                    frames_ok: r.u32()?,
                    frames_bad: r.u32()?,
                    stack_peak_bytes: r.u32()?,
                    carriage_target_um: r.i32()?,
                    carriage_estimate_um: r.i32()?,
                    scale_counts: ScaleCounts(r.i32()?),
                    record_crc: r.u32()?,
                };
                // Every bit of `flags` is defined (`status_flags::ALL` is 0xff).
                Reply::Status(s)
            }
            kind::TELEMETRY_FRAME => {
                Reply::Telemetry(Telemetry::read(&mut expect_len(payload, TELEMETRY_LEN)?)?)
            }
            kind::ANSWER => {
                let mut r = expect_len(payload, 4 + TELEMETRY_LEN + 4)?;
                let current_a = I16F16::from_bits(r.i32()?);
                let telemetry = Telemetry::read(&mut r)?;
                Reply::Answer {
                    current_a,
                    telemetry,
                    step_instructions: r.u32()?,
                }
            }
            kind::CONFIG_VALUE => {
                let mut r = expect_len(payload, 17)?;
                Reply::ConfigValue {
                    key: r.u8()?,
                    active_bits: r.u64()?,
                    staged_bits: r.u64()?,
                }
            }
            kind::SAVED => {
                let mut r = expect_len(payload, 8)?;
                Reply::Saved {
                    seq: r.u32()?,
                    crc32: r.u32()?,
                }
            }
            kind::RECORDS => {
                if payload.len() < 11 {
                    return Err(LinkError::BadLength);
                }
                let mut r = Reader::new(payload);
                let (seq, first_tick, every, count) = (r.u32()?, r.u32()?, r.u16()?, r.u8()?);
                let n = count as usize;
                if n == 0 || n > RECORD_BATCH {
                    return Err(LinkError::OutOfRange);
                }
                if payload.len() != 11 + n * RECORD_SAMPLE_LEN {
                    return Err(LinkError::BadLength);
                }
                let mut samples = [RecordSample::default(); RECORD_BATCH];
                for s in &mut samples[..n] {
                    *s = RecordSample {
                        motor_counts: MotorCounts(r.i32()?),
                        scale_counts: ScaleCounts(r.i32()?),
                        setpoint_counts: MotorCounts(r.i32()?),
                        current_ma: r.u16()? as i16,
                    };
                }
                Reply::Records {
                    seq,
                    first_tick,
                    every,
                    count,
                    samples,
                }
            }
            kind::CAL_DATA => {
                let (len, data) = piece(payload, 8, 0)?;
                let mut r = Reader::new(payload);
                Reply::CalData {
                    offset: r.u32()?,
                    total_len: r.u32()?,
                    len,
                    data,
                }
            }
            _ => return Err(LinkError::UnknownKind),
        })
    }
}
