// ---- the drive's side of the link -------------------------------------------------------------

#![allow(missing_docs)]
use crate::drive::{blob, BlobError, Command, CommandError, Drive, Faults, Output, Sample, Telemetry};
use estimator_core::model::ModelKind;
use estimator_core::link::*;
use estimator_core::fixed::types::I16F16;

/// Wire code (`detail` of [`LinkError::Refused`]) of a drive refusal.
pub fn command_error_code(e: CommandError) -> u8 {
    match e {
        CommandError::TargetOutOfTravel => 1,
        CommandError::VelocityOutOfRange => 2,
        CommandError::AccelOutOfRange => 3,
        CommandError::NotEnabled => 4,
        CommandError::ModelNotCalibrated => 5,
        CommandError::Busy => 6,
    }
}

/// The refusal with wire code `code`.
pub fn command_error_from_code(code: u8) -> Option<CommandError> {
    Some(match code {
        1 => CommandError::TargetOutOfTravel,
        2 => CommandError::VelocityOutOfRange,
        3 => CommandError::AccelOutOfRange,
        4 => CommandError::NotEnabled,
        5 => CommandError::ModelNotCalibrated,
        6 => CommandError::Busy,
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
    /// The drive rejected the blob's contents.
    pub const REJECTED: u8 = 6;
}

/// The request for a drive command, if `req` is one.
pub fn to_command(req: &Request) -> Option<Command> {
    Some(match *req {
        Request::Move { target_um, velocity_um_s, accel_um_s2 } => {
            Command::MoveTo { target_um, velocity_um_s, accel_um_s2 }
        }
        Request::Stop => Command::Stop,
        Request::Enable => Command::Enable,
        Request::Disable => Command::Disable,
        Request::ClearFaults => Command::ClearFaults,
        // Range-checked by the decoder, so `from_u8` cannot fail here; stay total anyway.
        Request::SelectModel(m) => Command::SelectModel(ModelKind::from_u8(m)?),
        Request::Home { position_um, scale_um } => Command::Home { position_um, scale_um },
        _ => return None,
    })
}

/// The request that carries `cmd`.
pub fn from_command(cmd: &Command) -> Request {
    match *cmd {
        Command::MoveTo { target_um, velocity_um_s, accel_um_s2 } => {
            Request::Move { target_um, velocity_um_s, accel_um_s2 }
        }
        Command::Stop => Request::Stop,
        Command::Enable => Request::Enable,
        Command::Disable => Request::Disable,
        Command::ClearFaults => Request::ClearFaults,
        Command::SelectModel(m) => Request::SelectModel(m as u8),
        Command::Home { position_um, scale_um } => Request::Home { position_um, scale_um },
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
        Reply::Answer { current_a_bits, telemetry, step_instructions } => Some((
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
    enabled: bool,
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
            enabled: false,
            streaming: false,
        }
    }

    /// Acts on one decoded request. Drive commands are applied here; what the firmware must
    /// still do (send a reply, run a tick, ...) comes back as an [`Effect`], and anything worth
    /// logging as an [`Event`].
    pub fn handle(&mut self, req: &Request, drive: &mut Drive) -> (Effect, Event) {
        let k = req.kind();
        let ack = Effect::Reply(Reply::Ack { of: k });
        let refuse = |reason: LinkError, detail: u8| Effect::Reply(Reply::Error { of: k, reason, detail });
        if let Some(cmd) = to_command(req) {
            return match drive.command(cmd) {
                Ok(()) => {
                    match cmd {
                        Command::Enable => self.enabled = true,
                        Command::Disable => self.enabled = false,
                        _ => {}
                    }
                    (ack, Event::Applied(cmd))
                }
                Err(e) => (refuse(LinkError::Refused, command_error_code(e)), Event::Refused(cmd, e)),
            };
        }
        match *req {
            Request::Sample { motor_counter, scale_counter } => {
                (Effect::Tick(Sample { motor_counter, scale_counter }), Event::None)
            }
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
                    return (refuse(LinkError::Calibration, d), Event::CalibrationRefused(d));
                }
                self.transfer = Some((total_len as usize, crc32, 0, Crc32::new()));
                (ack, Event::CalibrationBegun { total_len })
            }
            Request::CalChunk { offset, len, ref data } => {
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
                (refuse(LinkError::Calibration, d), Event::CalibrationRefused(d))
            }
            Request::CalCommit => {
                let d = match self.transfer {
                    None => cal_error::NOT_STARTED,
                    Some((total, _, got, _)) if got != total => cal_error::INCOMPLETE,
                    Some((_, want, _, crc)) if crc.finish() != want => cal_error::CRC,
                    Some((total, ..)) => {
                        self.transfer = None;
                        return match drive.load_calibration(&self.blob[..total]) {
                            Ok(()) => {
                                self.calibrated = true;
                                (ack, Event::CalibrationLoaded { len: total as u32 })
                            }
                            Err(e) => (
                                refuse(LinkError::Calibration, cal_error::REJECTED),
                                Event::CalibrationRejected(e),
                            ),
                        };
                    }
                };
                if d == cal_error::CRC {
                    self.transfer = None;
                }
                (refuse(LinkError::Calibration, d), Event::CalibrationRefused(d))
            }
            // Every command kind was handled above.
            _ => (refuse(LinkError::NotSupported, 0), Event::None),
        }
    }

    /// The status reply for the drive's latest telemetry and the link counters.
    pub fn status(&self, last: &Telemetry, rx: &Receiver, stack_peak_bytes: u32) -> WireStatus {
        let mut flags = 0;
        if last.moving {
            flags |= status_flags::MOVING;
        }
        if self.enabled && last.faults.is_clear() {
            flags |= status_flags::ENABLED;
        }
        if self.calibrated {
            flags |= status_flags::CALIBRATED;
        }
        if self.streaming {
            flags |= status_flags::STREAMING;
        }
        WireStatus {
            tick: last.tick,
            motor_counts: last.motor_counts,
            faults: last.faults.0,
            model: last.model as u8,
            flags,
            last_error: rx.last_error.map_or(0, |e| e as u8),
            frames_ok: rx.frames_ok,
            frames_bad: rx.frames_bad,
            stack_peak_bytes,
        }
    }
}
