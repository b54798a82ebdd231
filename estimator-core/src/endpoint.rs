//! The drive's end of the link: what each [`Request`] does to the [`Drive`] (commands,
//! calibration transfer, status, the PIL tick), kept beside the drive. The protocol itself
//! (wire types, codec, framing) is the `belt-link` crate, which knows nothing of the drive.

use belt_link::{
    kind, status_flags, Command, CommandError, Crc32, LinkError, Message, Receiver, Reply, Request,
    WireStatus,
};

use crate::blob::BlobError;
use crate::drive::{Drive, Output, Parts, PartsImage, Sample, IMAGE_FIELD, PARTS_IMAGE_LEN};
use crate::image;
use crate::settings::{self, RawSettings, Settings};
pub use crate::staging::BlobBuffer;
use crate::staging::{Staged, Staging};
use crate::ConfigError;

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
    /// A transfer needs the drive disabled: it erases the staging flash, which stalls the CPU.
    pub const ENABLED: u8 = 6;
    /// The staging flash failed to erase, write or read, or this build has none.
    pub const STAGING: u8 = 7;
    /// The drive rejected the blob's contents: this bit plus [`super::blob_error_code`].
    pub const REJECTED: u8 = 0x10;
}

/// `detail` codes of [`LinkError::Storage`] that the endpoint gives; the storage's own errors
/// use codes below 0x40 (see `crate::storage`).
pub mod storage_detail {
    /// This build has no persistent storage (QEMU without `--storage`).
    pub const NO_STORAGE: u8 = 0x40;
    /// The installed calibration's bytes were overwritten by a later, unfinished transfer:
    /// upload the calibration again before saving.
    pub const CALIBRATION_BYTES_GONE: u8 = 0x41;
    /// Saving needs the drive disabled (an erase stalls the CPU).
    pub const ENABLED: u8 = 0x42;
    /// No configuration was applied or stored: nothing to save.
    pub const NOT_CONFIGURED: u8 = 0x43;
    /// The active configuration's image was overwritten by a later image transfer that was not
    /// applied: apply a configuration again before saving.
    pub const CONFIG_BYTES_GONE: u8 = 0x44;
}

/// The [`LinkError::Config`] detail of a configuration image refused as a whole (incomplete,
/// damaged, of another version, or built from other values than the staged ones); other
/// details are the key of the refused field, or 0xff.
pub const CONFIG_IMAGE_REFUSED: u8 = 0xfe;

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
        BlobError::Unreadable => 12,
        BlobError::RateMismatch => 13,
    }
}

/// The PIL answer for one tick's output.
pub fn answer(out: &Output, step_instructions: u32) -> Reply {
    Reply::Answer {
        current_a: out.current_a,
        telemetry: out.telemetry,
        step_instructions,
    }
}

/// The output a PIL answer carries, or `None` if the reply is not an answer (the decoder
/// already refused an answer with an unknown model or flag).
pub fn output_of(reply: &Reply) -> Option<(Output, u32)> {
    match *reply {
        Reply::Answer {
            current_a,
            telemetry,
            step_instructions,
        } => Some((
            Output {
                current_a,
                telemetry,
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
    /// A complete, CRC-checked calibration image of this many bytes awaits: check it
    /// ([`Endpoint::calibration`], [`crate::image::check`]) outside any lock the control task
    /// needs, read it in with [`Drive::load_checked_calibration`], then report with
    /// [`Endpoint::calibration_done`].
    Calibrate(usize),
    /// The staged configuration ([`Endpoint::staged`]) is to be applied: read its image with
    /// [`Endpoint::staged_parts`] (integer checks), install it with [`Drive::reconfigure`],
    /// report with [`Endpoint::configure_done`].
    Configure,
    /// Store [`Endpoint::active`] and [`Endpoint::installed_calibration`] (the drive is
    /// disabled), then report with [`Endpoint::save_done`].
    Save,
    /// Stream recorded samples every `n` ticks (0 = off); then acknowledge.
    Record(u16),
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
    /// A configuration value or the staged configuration was refused (the field).
    ConfigRefused(ConfigError),
    /// A new configuration is in force.
    Configured,
    /// The configuration and calibration were stored.
    Saved {
        /// Record sequence number.
        seq: u32,
        /// Record CRC-32.
        crc32: u32,
    },
    /// Storing failed (the storage detail code).
    SaveFailed(u8),
}

/// `bytes` in link-sized pieces, in order: offset, length, the bytes zero-padded.
fn pieces(bytes: &[u8]) -> impl Iterator<Item = (usize, u8, [u8; belt_link::CHUNK_MAX])> + '_ {
    bytes
        .chunks(belt_link::CHUNK_MAX)
        .enumerate()
        .map(|(i, piece)| {
            let mut data = [0u8; belt_link::CHUNK_MAX];
            data[..piece.len()].copy_from_slice(piece);
            (i * belt_link::CHUNK_MAX, piece.len() as u8, data)
        })
}

/// The whole calibration transfer of `image`, in order: `CalBegin` with its length and CRC,
/// the `CalChunk` pieces, `CalCommit` (the host's side of the endpoint's transfer).
pub fn calibration_requests(image: &[u8]) -> impl Iterator<Item = Request> + '_ {
    let begin = Request::CalBegin {
        total_len: image.len() as u32,
        crc32: belt_link::crc32(image),
    };
    core::iter::once(begin)
        .chain(pieces(image).map(|(offset, len, data)| Request::CalChunk {
            offset: offset as u32,
            len,
            data,
        }))
        .chain(core::iter::once(Request::CalCommit))
}

/// The [`Request::ConfigParts`] pieces that carry `image` to the drive, in order (the host's
/// side of [`Endpoint::staged_parts`]).
pub fn config_parts_requests(image: &PartsImage) -> impl Iterator<Item = Request> + '_ {
    pieces(image).map(|(offset, len, data)| Request::ConfigParts {
        offset: offset as u16,
        len,
        data,
    })
}

/// The drive's end of the link: turns requests into drive commands, assembles calibration
/// images in its [`Staging`] area, and says what to answer. Frame decoding stays in
/// [`Receiver`].
pub struct Endpoint<B = BlobBuffer> {
    /// Where a calibration image is written as it arrives and read from (the firmware's flash
    /// sector: no RAM copy; a RAM buffer on hosts).
    staging: B,
    /// Transfer in progress: announced length and CRC, bytes received, running CRC.
    transfer: Option<(usize, u32, usize, Crc32)>,
    /// Length of the installed calibration while its bytes are in `staging` (a new transfer
    /// overwrites them).
    installed: Option<usize>,
    calibrated: bool,
    streaming: bool,
    /// The configuration in force and the one being edited over the link, as bits (the drive
    /// runs on the image built from them: see [`RawSettings`]).
    active: RawSettings,
    staged: RawSettings,
    /// A configuration image and its bytes received so far: the one arriving for `staged`,
    /// or, while `parts_active`, the image of `active` (one buffer: 229 bytes of RAM less).
    parts: PartsImage,
    parts_got: usize,
    parts_active: bool,
    /// A configuration was applied or stored (otherwise there is nothing to save).
    configured: bool,
    /// CRC of the stored record booted from or last saved (0 = none).
    record_crc: u32,
}

impl Default for Endpoint {
    fn default() -> Self {
        Self::new()
    }
}

impl Endpoint {
    /// A fresh endpoint owning its blob buffer (drive disabled, nothing loaded, the paper rig's
    /// values staged).
    pub fn new() -> Self {
        Self::with_staging([0; image::MAX_BYTES], RawSettings::of(&Settings::PAPER))
    }
}

impl<B: Staging> Endpoint<B> {
    /// A fresh endpoint assembling calibrations in `staging` (drive disabled, nothing loaded),
    /// with `defaults` active and staged until a configuration is applied or booted.
    pub fn with_staging(staging: B, defaults: RawSettings) -> Self {
        Endpoint {
            staging,
            transfer: None,
            installed: None,
            calibrated: false,
            streaming: false,
            active: defaults,
            staged: defaults,
            parts: [0; PARTS_IMAGE_LEN],
            parts_got: 0,
            parts_active: false,
            configured: false,
            record_crc: 0,
        }
    }

    /// Boot: the configuration the drive was built with, its image, and the stored record it
    /// came from (CRC, 0 if none).
    pub fn boot_with(&mut self, active: RawSettings, parts: &PartsImage, record_crc: u32) {
        self.active = active;
        self.staged = active;
        self.parts = *parts;
        self.parts_got = PARTS_IMAGE_LEN;
        self.parts_active = true;
        self.configured = true;
        self.record_crc = record_crc;
    }

    /// The image of the configuration in force, if one was applied or stored and no later
    /// transfer overwrote it.
    pub fn active_parts(&self) -> Option<&PartsImage> {
        self.parts_active.then_some(&self.parts)
    }

    /// The configuration image received for the staged values, checked in integers: complete,
    /// intact, and built from exactly [`Endpoint::staged`] (else [`IMAGE_FIELD`] is named).
    pub fn staged_parts(&self) -> Result<Parts, ConfigError> {
        if self.parts_got != PARTS_IMAGE_LEN {
            return Err(ConfigError::OutOfRange(IMAGE_FIELD));
        }
        let (parts, settings_crc) = Parts::decode(&self.parts)?;
        if settings_crc != self.staged.crc32() {
            return Err(ConfigError::OutOfRange(IMAGE_FIELD));
        }
        Ok(parts)
    }

    /// Boot: a stored calibration of `len` bytes was staged (see
    /// [`crate::storage::stage_blob`]) and installed.
    pub fn boot_calibration(&mut self, len: usize) {
        self.installed = Some(len.min(image::MAX_BYTES));
        self.calibrated = true;
    }

    /// The staging area (where a stored calibration is staged at boot).
    pub fn staging(&mut self) -> &mut B {
        &mut self.staging
    }

    /// The configuration in force.
    pub fn active(&self) -> &RawSettings {
        &self.active
    }

    /// The configuration being edited (what [`Effect::Configure`] applies).
    pub fn staged(&self) -> &RawSettings {
        &self.staged
    }

    /// The installed calibration's bytes, if still staged (empty: none loaded), or `None` if
    /// a later transfer overwrote them.
    pub fn installed_calibration(&mut self) -> Option<Staged<'_, B>> {
        let len = self.installed_len()?;
        Some(Staged::new(&mut self.staging, len))
    }

    /// The installed calibration's length, if still staged (0: none loaded).
    pub fn installed_len(&self) -> Option<usize> {
        match self.installed {
            Some(len) => Some(len),
            None if !self.calibrated => Some(0),
            None => None,
        }
    }

    /// Reports the outcome of an [`Effect::Configure`].
    pub fn configure_done(
        &mut self,
        result: Result<(), Result<ConfigError, CommandError>>,
    ) -> (Reply, Event) {
        let of = kind::CONFIG_APPLY;
        match result {
            Ok(()) => {
                self.active = self.staged;
                self.parts_active = true;
                self.configured = true;
                (Reply::Ack { of }, Event::Configured)
            }
            Err(Ok(e)) => (
                Reply::Error {
                    of,
                    reason: LinkError::Config,
                    detail: if e.field() == IMAGE_FIELD {
                        CONFIG_IMAGE_REFUSED
                    } else {
                        settings::key_of(&e)
                    },
                },
                Event::ConfigRefused(e),
            ),
            Err(Err(e)) => (
                Reply::Error {
                    of,
                    reason: LinkError::Refused,
                    detail: e.code(),
                },
                Event::None,
            ),
        }
    }

    /// Reports the outcome of an [`Effect::Save`]: the record's sequence number and CRC, or the
    /// storage detail code.
    pub fn save_done(&mut self, result: Result<(u32, u32), u8>) -> (Reply, Event) {
        match result {
            Ok((seq, crc32)) => {
                self.record_crc = crc32;
                (Reply::Saved { seq, crc32 }, Event::Saved { seq, crc32 })
            }
            Err(d) => (
                Reply::Error {
                    of: kind::SAVE,
                    reason: LinkError::Storage,
                    detail: d,
                },
                Event::SaveFailed(d),
            ),
        }
    }

    /// The assembled calibration image of an [`Effect::Calibrate`] (`len` bytes), read from
    /// the staging area.
    pub fn calibration(&mut self, len: usize) -> Staged<'_, B> {
        Staged::new(&mut self.staging, len)
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
                let len = len.min(image::MAX_BYTES);
                self.installed = Some(len);
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
                let result = drive.load_calibration_from(&mut self.calibration(len));
                let (reply, event) = self.calibration_done(len, result);
                (Effect::Reply(reply), event)
            }
            (Effect::Configure, _) => {
                let result = self
                    .staged_parts()
                    .map_err(Ok)
                    .and_then(|p| drive.reconfigure(p).map_err(Err));
                let (reply, event) = self.configure_done(result);
                (Effect::Reply(reply), event)
            }
            other => other,
        }
    }

    /// Acts on one decoded request. Drive commands are applied here; what the firmware must
    /// still do (send a reply, run a tick, ...) comes back as an [`Effect`], and anything worth
    /// logging as an [`Event`].
    pub fn handle(&mut self, req: &Request, drive: &mut Drive) -> (Effect, Event) {
        // Any valid frame from the host keeps the link watchdog fed. A PIL sample does not: it
        // is the simulated machine's sensors, and a virtual drive fed by its own plant could
        // not show a host that went silent.
        if !matches!(req, Request::Sample { .. }) {
            drive.link_alive();
        }
        let k = req.kind();
        let ack = Effect::Reply(Reply::Ack { of: k });
        let refuse = |reason: LinkError, detail: u8| {
            Effect::Reply(Reply::Error {
                of: k,
                reason,
                detail,
            })
        };
        match *req {
            Request::Command(cmd) => match drive.command(cmd) {
                Ok(()) => (ack, Event::Applied(cmd)),
                Err(e) => (refuse(LinkError::Refused, e.code()), Event::Refused(cmd, e)),
            },
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
            // Values are staged as sent: the host checks them when it builds the image, and
            // the drive checks the image.
            Request::ConfigSet { key, value_bits } => match self.staged.set(key, value_bits) {
                Ok(()) => (ack, Event::None),
                Err(_) => (refuse(LinkError::OutOfRange, key), Event::None),
            },
            Request::ConfigGet { key } => match (self.active.get(key), self.staged.get(key)) {
                (Some(active_bits), Some(staged_bits)) => (
                    Effect::Reply(Reply::ConfigValue {
                        key,
                        active_bits,
                        staged_bits,
                    }),
                    Event::None,
                ),
                _ => (refuse(LinkError::OutOfRange, key), Event::None),
            },
            Request::ConfigApply => {
                if drive.is_enabled() {
                    let e = CommandError::Busy;
                    return (refuse(LinkError::Refused, e.code()), Event::None);
                }
                (Effect::Configure, Event::None)
            }
            Request::Save => {
                if drive.is_enabled() {
                    return (
                        refuse(LinkError::Storage, storage_detail::ENABLED),
                        Event::SaveFailed(storage_detail::ENABLED),
                    );
                }
                if !self.configured {
                    let d = storage_detail::NOT_CONFIGURED;
                    return (refuse(LinkError::Storage, d), Event::SaveFailed(d));
                }
                if !self.parts_active {
                    let d = storage_detail::CONFIG_BYTES_GONE;
                    return (refuse(LinkError::Storage, d), Event::SaveFailed(d));
                }
                if self.installed_len().is_none() {
                    let d = storage_detail::CALIBRATION_BYTES_GONE;
                    return (refuse(LinkError::Storage, d), Event::SaveFailed(d));
                }
                (Effect::Save, Event::None)
            }
            Request::Record { every_n_ticks } => (Effect::Record(every_n_ticks), Event::None),
            Request::ConfigParts {
                offset,
                len,
                ref data,
            } => {
                // In order from 0; offset 0 starts over.
                let at = if offset == 0 { 0 } else { self.parts_got };
                let piece = &data[..(len as usize).min(belt_link::CHUNK_MAX)];
                // The buffer no longer holds the active image.
                self.parts_active = false;
                match self.parts.get_mut(at..at + piece.len()) {
                    Some(dst) if offset as usize == at => {
                        dst.copy_from_slice(piece);
                        self.parts_got = at + piece.len();
                        (ack, Event::None)
                    }
                    _ => {
                        self.parts_got = 0;
                        (refuse(LinkError::OutOfRange, 0), Event::None)
                    }
                }
            }
            Request::CalRead { offset } => {
                let Some(total) = self.installed_len() else {
                    let d = cal_error::NOT_STARTED;
                    return (refuse(LinkError::Calibration, d), Event::None);
                };
                let start = (offset as usize).min(total);
                let n = (total - start).min(belt_link::CHUNK_MAX);
                let mut data = [0u8; belt_link::CHUNK_MAX];
                if self.staging.read(start, &mut data[..n]).is_err() {
                    let d = cal_error::STAGING;
                    return (refuse(LinkError::Calibration, d), Event::None);
                }
                (
                    Effect::Reply(Reply::CalData {
                        offset,
                        total_len: total as u32,
                        len: n as u8,
                        data,
                    }),
                    Event::None,
                )
            }
            Request::CalBegin { total_len, crc32 } => {
                if total_len as usize > image::MAX_BYTES {
                    self.transfer = None;
                    let d = cal_error::TOO_LONG;
                    return (
                        refuse(LinkError::Calibration, d),
                        Event::CalibrationRefused(d),
                    );
                }
                // Erasing stalls a single-bank MCU for up to 2 s: never under a live motor.
                if drive.is_enabled() {
                    self.transfer = None;
                    let d = cal_error::ENABLED;
                    return (
                        refuse(LinkError::Calibration, d),
                        Event::CalibrationRefused(d),
                    );
                }
                // The staged bytes are about to be overwritten.
                self.installed = None;
                if self.staging.erase().is_err() {
                    self.transfer = None;
                    let d = cal_error::STAGING;
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
                        let piece = &data[..(len as usize).min(belt_link::CHUNK_MAX)];
                        match self.staging.write(*got, piece) {
                            Ok(()) => {
                                crc.update(piece);
                                *got += piece.len();
                                return (ack, Event::None);
                            }
                            // A failed write leaves the area unknown: the transfer starts over.
                            Err(_) => {
                                self.transfer = None;
                                cal_error::STAGING
                            }
                        }
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
                        // Checking the whole image takes a while: the caller does it outside
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
        let flags = [
            (last.moving, status_flags::MOVING),
            (drive.is_enabled(), status_flags::ENABLED),
            (self.calibrated, status_flags::CALIBRATED),
            (self.streaming, status_flags::STREAMING),
            (drive.is_homed(), status_flags::HOMED),
            (last.amplifier_enabled, status_flags::AMPLIFIER_ENABLED),
            (drive.is_configured(), status_flags::CONFIGURED),
            (drive.is_homing(), status_flags::HOMING),
        ]
        .iter()
        .filter(|(set, _)| *set)
        .fold(0, |acc, (_, bit)| acc | bit);
        WireStatus {
            tick: last.tick,
            motor_counts: last.motor_counts,
            faults: last.faults,
            model: last.model,
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
            scale_counts: last.scale_counts,
            record_crc: self.record_crc,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // ---- the endpoint, against the real drive ----

    use crate::drive::{DriveConfig, Output as DriveOutput};
    use crate::fault::Faults;
    use belt_link::{crc32, CHUNK_MAX};

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
    fn refusal_codes_round_trip() {
        for e in CommandError::ALL {
            assert_eq!(CommandError::from_code(e.code()), Some(e));
        }
        assert_eq!(CommandError::from_code(0), None);
        for code in 0..=255u8 {
            if let Some(e) = CommandError::from_code(code) {
                assert_eq!(e.code(), code);
            }
        }
    }

    #[test]
    fn answers_carry_the_output() {
        let mut d = drive();
        let out = d.step(Sample {
            motor_counter: 7,
            scale_counter: 9,
        });
        let reply = answer(&out, 42);
        assert_eq!(output_of(&reply), Some((out, 42)));
        assert_eq!(output_of(&Reply::Ack { of: 1 }), None::<(DriveOutput, u32)>);
    }

    #[test]
    fn a_host_s_frames_feed_the_link_watchdog_and_pil_samples_do_not() {
        let mut d = drive();
        let mut ep = Endpoint::new();
        for c in [
            Command::Home {
                position_um: 0,
                scale_um: 0,
            },
            Command::Enable,
        ] {
            assert!(matches!(
                ep.handle_inline(&Request::Command(c), &mut d).0,
                Effect::Reply(Reply::Ack { .. })
            ));
        }
        let n = d.monitor().link_timeout_ticks();
        assert!(n > 1);
        // The firmware's tick: the sample arrives as a frame, then the control runs on it.
        let tick = |ep: &mut Endpoint, d: &mut Drive| {
            let sample = Request::Sample {
                motor_counter: 0,
                scale_counter: 0,
            };
            match ep.handle_inline(&sample, d).0 {
                Effect::Tick(s) => d.step(s).telemetry.faults,
                other => panic!("a sample runs a tick, not {other:?}"),
            }
        };
        for _ in 0..n - 1 {
            assert!(tick(&mut ep, &mut d).is_clear());
        }
        // A status request is the host's: the count starts again.
        assert!(matches!(
            ep.handle_inline(&Request::Status, &mut d).0,
            Effect::Status
        ));
        for _ in 0..n - 1 {
            assert!(tick(&mut ep, &mut d).is_clear());
        }
        assert_eq!(tick(&mut ep, &mut d), Faults(Faults::LINK_TIMEOUT));
    }

    #[test]
    fn endpoint_applies_commands_and_reports_refusals() {
        let mut d = drive();
        let mut ep = Endpoint::new();
        let mv = Request::Command(Command::MoveMotorTo {
            target_um: 10_000,
            velocity_um_s: 50_000,
            accel_um_s2: 500_000,
        });
        let (e, ev) = ep.handle_inline(&mv, &mut d);
        assert_eq!(
            refused(e),
            Some((LinkError::Refused, CommandError::NotEnabled.code()))
        );
        assert!(matches!(ev, Event::Refused(_, CommandError::NotEnabled)));
        assert_eq!(
            ep.handle_inline(&Request::Command(Command::Enable), &mut d)
                .0,
            ACK_ENABLE
        );
        assert!(d.is_enabled());
        let (e, ev) = ep.handle_inline(&mv, &mut d);
        assert_eq!(
            refused(e),
            Some((LinkError::Refused, CommandError::NotHomed.code()))
        );
        assert!(matches!(ev, Event::Refused(_, CommandError::NotHomed)));
        let home = Request::Command(Command::Home {
            position_um: 0,
            scale_um: 0,
        });
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
        let far = Request::Command(Command::MoveMotorTo {
            target_um: 10_000_000,
            velocity_um_s: 1,
            accel_um_s2: 1,
        });
        let code = CommandError::TargetOutOfTravel.code();
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

    fn paper_image() -> Vec<u8> {
        crate::image::of_params(
            &crate::model::ModelParams::PAPER,
            &DriveConfig::paper_rig().settings.rig,
        )
        .unwrap()
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
        let blob = paper_image();
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
            total_len: image::MAX_BYTES as u32 + 1,
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
        // The host's side is `calibration_requests`: begin, every piece, commit.
        let before = d.models().clone();
        let reqs: Vec<Request> = calibration_requests(&blob).collect();
        assert_eq!(reqs.len(), blob.len().div_ceil(CHUNK_MAX) + 2);
        let (commit, rest) = reqs.split_last().unwrap();
        for req in rest {
            assert!(matches!(
                ep.handle(req, &mut d).0,
                Effect::Reply(Reply::Ack { .. })
            ));
        }
        assert_eq!(ep.handle(commit, &mut d).0, Effect::Calibrate(blob.len()));
        assert_eq!(
            crate::staging::read_all(&mut ep.calibration(blob.len())).unwrap(),
            blob
        );
        assert_eq!(d.models(), &before);
    }

    /// Staging that fails its writes after `ok_writes` of them (and can fail erases).
    struct Flaky {
        buf: BlobBuffer,
        ok_writes: usize,
        erase_ok: bool,
    }

    impl Staging for Flaky {
        fn erase(&mut self) -> Result<(), crate::staging::StagingError> {
            if !self.erase_ok {
                return Err(crate::staging::StagingError::Flash);
            }
            self.buf.erase()
        }
        fn write(
            &mut self,
            offset: usize,
            data: &[u8],
        ) -> Result<(), crate::staging::StagingError> {
            if self.ok_writes == 0 {
                return Err(crate::staging::StagingError::Flash);
            }
            self.ok_writes -= 1;
            self.buf.write(offset, data)
        }
        fn read(
            &mut self,
            offset: usize,
            buf: &mut [u8],
        ) -> Result<(), crate::staging::StagingError> {
            self.buf.read(offset, buf)
        }
    }

    #[test]
    fn calibration_transfer_needs_the_drive_disabled_and_a_working_staging_area() {
        let blob = paper_image();
        let cal = |d: u8| Some((LinkError::Calibration, d));
        let begin = Request::CalBegin {
            total_len: blob.len() as u32,
            crc32: crc32(&blob),
        };
        // Enabled: refused before anything is erased; the installed calibration stays.
        let mut d = drive();
        let mut ep = Endpoint::new();
        for req in calibration_requests(&blob) {
            assert!(matches!(
                ep.handle_inline(&req, &mut d).0,
                Effect::Reply(Reply::Ack { .. })
            ));
        }
        assert!(ack(&ep
            .handle_inline(&Request::Command(Command::Enable), &mut d)
            .0));
        let (e, ev) = ep.handle_inline(&begin, &mut d);
        assert_eq!(refused(e), cal(cal_error::ENABLED));
        assert_eq!(ev, Event::CalibrationRefused(cal_error::ENABLED));
        assert_eq!(ep.installed_len(), Some(blob.len()));
        assert_eq!(
            refused(ep.handle_inline(&chunk(0, &blob[..8]), &mut d).0),
            cal(cal_error::NOT_STARTED)
        );

        // An erase that fails: refused by name, no transfer.
        let mut d = drive();
        let flaky = Flaky {
            buf: [0; image::MAX_BYTES],
            ok_writes: 3,
            erase_ok: false,
        };
        let mut ep = Endpoint::with_staging(flaky, RawSettings::of(&Settings::PAPER));
        assert_eq!(
            refused(ep.handle_inline(&begin, &mut d).0),
            cal(cal_error::STAGING)
        );
        assert_eq!(
            refused(ep.handle_inline(&chunk(0, &blob[..8]), &mut d).0),
            cal(cal_error::NOT_STARTED)
        );
        // A write that fails on the fourth chunk: refused, and the transfer must start over.
        ep.staging().erase_ok = true;
        assert!(ack(&ep.handle_inline(&begin, &mut d).0));
        for (i, piece) in blob.chunks(CHUNK_MAX).take(3).enumerate() {
            assert!(ack(&ep
                .handle_inline(&chunk(i * CHUNK_MAX, piece), &mut d)
                .0));
        }
        let fourth = chunk(3 * CHUNK_MAX, &blob[3 * CHUNK_MAX..4 * CHUNK_MAX]);
        assert_eq!(
            refused(ep.handle_inline(&fourth, &mut d).0),
            cal(cal_error::STAGING)
        );
        assert_eq!(
            refused(ep.handle_inline(&Request::CalCommit, &mut d).0),
            cal(cal_error::NOT_STARTED)
        );
        // Nothing was installed: the drive still runs without a calibration of this link.
        assert_eq!(ep.installed_len(), Some(0));
    }

    // ---- the configuration: values staged, the host's image applied ----

    fn ack(e: &Effect) -> bool {
        matches!(e, Effect::Reply(Reply::Ack { .. }))
    }

    fn send_image(ep: &mut Endpoint, d: &mut Drive, image: &PartsImage) {
        for req in config_parts_requests(image) {
            assert!(ack(&ep.handle(&req, d).0));
        }
    }

    #[test]
    fn configuration_applies_only_the_image_of_the_staged_values() {
        use crate::settings::{self, Settings};
        let mut d = drive();
        let mut ep = Endpoint::new();
        let image_refused = Some((LinkError::Config, CONFIG_IMAGE_REFUSED));

        // Nothing applied yet: nothing to save, and no image to apply.
        assert_eq!(
            refused(ep.handle(&Request::Save, &mut d).0),
            Some((LinkError::Storage, storage_detail::NOT_CONFIGURED))
        );
        assert_eq!(
            refused(ep.handle_inline(&Request::ConfigApply, &mut d).0),
            image_refused
        );

        // A new travel: staged, its image sent, applied.
        let key = settings::field_named("drive.travel_max_mm").unwrap().key();
        let set = |v: f64| Request::ConfigSet {
            key,
            value_bits: v.to_bits(),
        };
        assert!(ack(&ep.handle(&set(250.0), &mut d).0));
        let mut want = Settings::PAPER;
        want.travel_max_mm = 250.0;
        assert_eq!(ep.staged(), &RawSettings::of(&want));
        send_image(&mut ep, &mut d, &want.parts_image().unwrap());
        let (e, ev) = ep.handle_inline(&Request::ConfigApply, &mut d);
        assert!(ack(&e), "{e:?}");
        assert_eq!(ev, Event::Configured);
        assert_eq!(ep.active(), &RawSettings::of(&want));
        assert_eq!(ep.active_parts(), Some(&want.parts_image().unwrap()));
        assert_eq!(ep.handle(&Request::Save, &mut d).0, Effect::Save);

        // An image of other values than the staged ones (a value staged after it was built).
        let mut other = want;
        other.travel_max_mm = 200.0;
        send_image(&mut ep, &mut d, &other.parts_image().unwrap());
        assert!(ack(&ep.handle(&set(210.0), &mut d).0));
        assert_eq!(
            refused(ep.handle_inline(&Request::ConfigApply, &mut d).0),
            image_refused
        );
        assert_eq!(
            ep.active(),
            &RawSettings::of(&want),
            "a refused apply changes nothing"
        );
        assert_eq!(
            refused(ep.handle(&Request::Save, &mut d).0),
            Some((LinkError::Storage, storage_detail::CONFIG_BYTES_GONE))
        );

        // Pieces out of order are refused, and the image must be sent again from 0.
        let image = ep.staged().settings().unwrap().parts_image().unwrap();
        let pieces: Vec<Request> = config_parts_requests(&image).collect();
        assert!(ack(&ep.handle(&pieces[0], &mut d).0));
        assert_eq!(
            refused(ep.handle(&pieces[2], &mut d).0),
            Some((LinkError::OutOfRange, 0))
        );
        assert!(!ack(&ep.handle(&pieces[1], &mut d).0));
        assert_eq!(
            refused(ep.handle_inline(&Request::ConfigApply, &mut d).0),
            image_refused
        );
        send_image(&mut ep, &mut d, &image);
        assert!(ack(&ep.handle_inline(&Request::ConfigApply, &mut d).0));
        assert_eq!(ep.active().settings().unwrap().travel_max_mm, 210.0);

        // Refused while enabled, as every configuration change.
        assert!(ack(&ep
            .handle(&Request::Command(Command::Enable), &mut d)
            .0));
        send_image(&mut ep, &mut d, &image);
        assert_eq!(
            refused(ep.handle_inline(&Request::ConfigApply, &mut d).0),
            Some((LinkError::Refused, CommandError::Busy.code()))
        );
    }

    #[test]
    fn stored_configuration_round_trips_and_refuses_a_mismatch() {
        use crate::settings::{decode_stored, encode_stored, Settings, SettingsError};
        let s = Settings::PAPER;
        let image = s.parts_image().unwrap();
        let bytes = encode_stored(&RawSettings::of(&s), &image);
        let (back, parts) = decode_stored(&bytes).unwrap();
        assert_eq!(back.settings().unwrap(), s);
        assert_eq!(&bytes[settings::ENCODED_LEN..], &image[..]);
        assert_eq!(parts, Parts::decode(&image).unwrap().0);
        // The image of other settings beside these.
        let mut other = s;
        other.max_velocity_mm_s = 100.0;
        let mixed = encode_stored(&RawSettings::of(&s), &other.parts_image().unwrap());
        assert_eq!(
            decode_stored(&mixed).unwrap_err(),
            SettingsError::Invalid(ConfigError::OutOfRange(IMAGE_FIELD))
        );
        // A record of the firmware before the image (settings only).
        assert_eq!(
            decode_stored(&bytes[..settings::ENCODED_LEN]).unwrap_err(),
            SettingsError::Truncated
        );
    }
}
