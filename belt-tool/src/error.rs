//! Everything that can go wrong, each with a message that names the port or file and says what
//! happened, in the words a machine builder at the bench would use.

use std::io;

use belt_link::{kind, CommandError, LinkError};
use estimator_core::endpoint::{cal_error, storage_detail, CONFIG_IMAGE_REFUSED};
use estimator_core::settings;

/// Why a `beltctl` command failed.
#[derive(Debug, thiserror::Error)]
pub enum ToolError {
    /// The port does not exist (unplugged adapter, mistyped path).
    #[error("cannot open {port}: No such file or directory")]
    NoSuchPort {
        /// The path given with `--port`.
        port: String,
    },
    /// The port exists but this user may not open it.
    #[error("cannot open {port}: Permission denied (is your user in the `dialout` group?)")]
    PermissionDenied {
        /// The path given with `--port`.
        port: String,
    },
    /// The port exists but could not be opened for another reason (busy, not a terminal...).
    #[error("cannot open {port}: {reason}")]
    Open {
        /// The path given with `--port`.
        port: String,
        /// What the system said.
        reason: String,
    },
    /// Reading or writing failed after the port was open (e.g. the adapter was unplugged).
    #[error("{port}: {op} failed: {source} (adapter unplugged, or the drive gone?)")]
    Io {
        /// The port.
        port: String,
        /// `"write"` or `"read"`.
        op: &'static str,
        /// What the system said.
        source: io::Error,
    },
    /// Bytes arrive, but never one valid belt-link frame: another device, or a wrong baud rate.
    #[error(
        "{port} answers, but not with belt-drive frames: {bytes} bytes of garbage and no valid \
         frame in reply to {request} (another device, or the wrong baud rate?)"
    )]
    WrongDevice {
        /// The port.
        port: String,
        /// The request that went unanswered.
        request: String,
        /// Bytes received that belonged to no valid frame.
        bytes: u64,
    },
    /// The drive's answer arrived intact but could not be read: another protocol version.
    #[error(
        "{port}: the drive answered {request}, but beltctl cannot read the answer (reply kind \
         {kind:#04x}: {reason}); are the firmware and beltctl from the same release?"
    )]
    Unreadable {
        /// The port.
        port: String,
        /// The request.
        request: String,
        /// The reply's kind byte.
        kind: u8,
        /// Why it was refused (a field out of range, a wrong payload length, a kind unknown).
        reason: &'static str,
    },
    /// Every request comes straight back: TX is wired to RX.
    #[error(
        "{port} echoes every request back instead of answering (a loopback plug, or the \
         adapter's TX tied to its RX?)"
    )]
    Echo {
        /// The port.
        port: String,
    },
    /// No reply at all within the time allowed, on every try.
    #[error("{port}: no reply to {request} within {timeout_ms} ms after {tries} tries{note}")]
    Timeout {
        /// The port.
        port: String,
        /// The request.
        request: String,
        /// Time allowed per try.
        timeout_ms: u64,
        /// Tries made.
        tries: u32,
        /// What else arrived meanwhile, if anything (", 12 bytes of garbage received").
        note: String,
    },
    /// The drive received the request damaged on every try.
    #[error(
        "{port}: {request} reached the drive damaged on every one of {tries} tries ({reason}): \
         noise on the line or a wrong baud rate"
    )]
    Damaged {
        /// The port.
        port: String,
        /// The request.
        request: String,
        /// Tries made.
        tries: u32,
        /// The drive's reason for the last rejection.
        reason: &'static str,
    },
    /// The drive understood the request and said no.
    #[error("the drive refused {request}: {why}")]
    Refused {
        /// The request.
        request: String,
        /// The decoded reason.
        why: String,
        /// The reply's reason code, for callers that handle some refusals.
        reason: LinkError,
        /// The reply's detail byte.
        detail: u8,
    },
    /// Record frames went missing.
    #[error(
        "lost {lost_frames} of {expected_frames} record frames ({detail}): the link cannot carry \
         this rate; record with a larger --every"
    )]
    LostRecords {
        /// Frames missing by sequence number.
        lost_frames: u64,
        /// Frames the drive sent (received plus lost).
        expected_frames: u64,
        /// The gaps, for people.
        detail: String,
    },
    /// A reply that answers the request but makes no sense (a protocol mismatch).
    #[error("{port}: unexpected reply to {request}: {got}")]
    Unexpected {
        /// The port.
        port: String,
        /// The request.
        request: String,
        /// What came.
        got: String,
    },
    /// A file could not be read, parsed or written; the message names it.
    #[error("{path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// What went wrong, naming the field where there is one.
        reason: String,
    },
    /// A bad argument.
    #[error("{0}")]
    Usage(String),
    /// The drive is not in the state the command needs, or did not do what it was asked.
    #[error("{0}")]
    Drive(String),
    /// The recordings could not be fitted; says what they lack.
    #[error("calibration fit: {0}")]
    Fit(#[from] hil_sim::calibrate::CalibrationError),
    /// The calibration files could not be written (names the file).
    #[error("{0}")]
    CalFile(#[from] hil_sim::calfile::CalFileError),
}

impl ToolError {
    /// The error for opening `port` failed with `e`.
    pub fn open(port: &str, e: &serialport::Error) -> ToolError {
        use serialport::ErrorKind as K;
        match e.kind() {
            K::Io(io::ErrorKind::NotFound) => ToolError::NoSuchPort { port: port.into() },
            K::Io(io::ErrorKind::PermissionDenied) => {
                ToolError::PermissionDenied { port: port.into() }
            }
            K::NoDevice => ToolError::Open {
                port: port.into(),
                reason: format!("{} (another program has it open?)", e.description),
            },
            _ => ToolError::Open {
                port: port.into(),
                reason: e.description.clone(),
            },
        }
    }

    /// A file error.
    pub fn file(path: impl std::fmt::Display, reason: impl std::fmt::Display) -> ToolError {
        ToolError::File {
            path: path.to_string(),
            reason: reason.to_string(),
        }
    }
}

/// A link error code's name, for people.
pub fn link_error_name(e: LinkError) -> &'static str {
    match e {
        LinkError::Framing => "COBS framing error",
        LinkError::Oversize => "frame too long",
        LinkError::TooShort => "frame too short",
        LinkError::Crc => "CRC mismatch",
        LinkError::UnknownKind => "unknown request kind",
        LinkError::BadLength => "wrong payload length",
        LinkError::OutOfRange => "a field out of range",
        LinkError::Refused => "refused",
        LinkError::Calibration => "calibration transfer refused",
        LinkError::NotSupported => "not supported on this board",
        LinkError::Config => "configuration refused",
        LinkError::Storage => "storage failed",
    }
}

/// True for the rejections of a frame damaged on the way: worth sending again.
pub fn is_damage(e: LinkError) -> bool {
    matches!(
        e,
        LinkError::Framing | LinkError::Oversize | LinkError::TooShort | LinkError::Crc
    )
}

/// Names of the drive's calibration-blob refusals (the low bits of a
/// [`cal_error::REJECTED`] detail, `endpoint::blob_error_code`).
const BLOB_ERRORS: [(u8, &str); 13] = [
    (1, "the blob is truncated"),
    (2, "the blob is too long"),
    (3, "not a calibration blob (bad magic)"),
    (4, "unsupported blob version"),
    (5, "bad blob checksum"),
    (
        6,
        "the blob was made for another drive-train geometry than the drive's configuration",
    ),
    (7, "a table has a bad point count"),
    (8, "a model parameter is invalid"),
    (9, "the drive is busy (moving)"),
    (10, "the drive's buffer is too small"),
    (
        11,
        "a parameter cannot be represented in the drive's fixed-point formats",
    ),
    (12, "the drive could not read its staging flash back"),
    (
        13,
        "its belt observer was built for another control rate than the drive's (drive.rate_hz): calibrate at the drive's rate",
    ),
];

/// Storage failures by code (`storage::StorageError::code`).
const STORAGE_ERRORS: [(u8, &str); 7] = [
    (1, "flash error"),
    (2, "flash geometry not supported"),
    (3, "configuration and calibration do not fit a storage slot"),
    (4, "the drive's settings buffer is too small"),
    (5, "the drive's calibration buffer is too small"),
    (
        6,
        "the record read back after writing is not the one written",
    ),
    (
        7,
        "the record changed between check and copy (unstable flash)",
    ),
];

/// Why the drive refused, from an error reply's reason and detail.
pub fn refusal(reason: LinkError, detail: u8) -> String {
    match reason {
        LinkError::Refused => match CommandError::from_code(detail) {
            Some(e) => e.to_string(),
            None => format!("refused with code {detail} (unknown to this beltctl)"),
        },
        LinkError::Config => match settings::field(detail) {
            Some(f) => format!(
                "configuration field {} ({}) is invalid or does not fit the rest of the \
                 configuration",
                f.name(), f.unit
            ),
            None if detail == 0xff => "the configuration as a whole is invalid".into(),
            None if detail == CONFIG_IMAGE_REFUSED => "the drive refused the configuration image \
                 (incomplete, damaged, of another version, or built from other values than the \
                 staged ones): apply again"
                .into(),
            None => format!("configuration refused (field key {detail}, unknown to this beltctl)"),
        },
        LinkError::Storage => match detail {
            storage_detail::ENABLED => {
                "saving needs the drive disabled (`beltctl disable` first)".into()
            }
            storage_detail::NO_STORAGE => "this drive has no persistent storage".into(),
            storage_detail::CONFIG_BYTES_GONE => "the active configuration's image was \
                 overwritten by a transfer that was not applied: apply the configuration again, \
                 then save"
                .into(),
            storage_detail::NOT_CONFIGURED => "the drive holds no configuration to save: set \
                 one first (`beltctl config set` or `config load`)"
                .into(),
            storage_detail::CALIBRATION_BYTES_GONE => "the installed calibration's bytes were \
                 overwritten by an unfinished transfer: upload the calibration again, then save"
                .into(),
            d => match STORAGE_ERRORS.iter().find(|(c, _)| *c == d) {
                Some((_, why)) => format!("saving failed: {why}"),
                None => format!("saving failed (storage detail {d})"),
            },
        },
        LinkError::Calibration => match detail {
            cal_error::NOT_STARTED => {
                "no calibration transfer in progress (or none installed to read back)".into()
            }
            cal_error::OFFSET => "a chunk arrived out of order".into(),
            cal_error::TOO_LONG => "the calibration is longer than the drive accepts".into(),
            cal_error::INCOMPLETE => "committed before every byte arrived".into(),
            cal_error::CRC => "the received bytes do not match the announced CRC".into(),
            cal_error::ENABLED => {
                "a calibration transfer needs the drive disabled (it erases flash): disable it first"
                    .into()
            }
            cal_error::STAGING => {
                "the drive's staging flash failed (or this build has none: QEMU needs --staging)"
                    .into()
            }
            d if d & cal_error::REJECTED != 0 => {
                let code = d & !cal_error::REJECTED;
                match BLOB_ERRORS.iter().find(|(c, _)| *c == code) {
                    Some((_, why)) => format!("the drive rejected the calibration: {why}"),
                    None => format!("the drive rejected the calibration (code {code})"),
                }
            }
            d => format!("calibration transfer refused (detail {d})"),
        },
        LinkError::UnknownKind => {
            "the drive does not know this request (firmware older than beltctl?)".into()
        }
        LinkError::NotSupported => "not supported on this board".into(),
        LinkError::OutOfRange => "a field is outside the range the drive accepts".into(),
        LinkError::BadLength => {
            "wrong payload length (firmware of another protocol version?)".into()
        }
        e => link_error_name(e).into(),
    }
}

/// The request kind's name, for messages about frames that name only the kind.
pub fn kind_name(k: u8) -> &'static str {
    match k {
        kind::MOVE_MOTOR => "move-motor",
        kind::MOVE => "move",
        kind::STOP => "stop",
        kind::ENABLE => "enable",
        kind::DISABLE => "disable",
        kind::CLEAR_FAULTS => "clear-faults",
        kind::SELECT_MODEL => "select-model",
        kind::HOME => "home (declared)",
        kind::HOMING => "home",
        kind::CAL_BEGIN => "calibration begin",
        kind::CAL_CHUNK => "calibration chunk",
        kind::CAL_COMMIT => "calibration commit",
        kind::CAL_READ => "calibration read-back",
        kind::STATUS => "status",
        kind::TELEMETRY => "telemetry",
        kind::SAMPLE => "sample",
        kind::SHUTDOWN => "shutdown",
        kind::CONFIG_SET => "config set",
        kind::CONFIG_GET => "config get",
        kind::CONFIG_APPLY => "config apply",
        kind::CONFIG_PARTS => "configuration image",
        kind::SAVE => "save",
        kind::RECORD => "record",
        _ => "an unknown request",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use estimator_core::blob::BlobError;
    use estimator_core::endpoint::blob_error_code;

    #[test]
    fn blob_error_names_follow_the_drive_codes() {
        for (e, name) in [
            (BlobError::Truncated, "truncated"),
            (BlobError::TooLong, "too long"),
            (BlobError::BadMagic, "magic"),
            (BlobError::BadChecksum, "checksum"),
            (BlobError::RigMismatch, "geometry"),
            (BlobError::RateMismatch, "control rate"),
            (BlobError::Busy, "busy"),
            (BlobError::BufferTooSmall, "buffer"),
        ] {
            let why = refusal(
                LinkError::Calibration,
                cal_error::REJECTED | blob_error_code(e),
            );
            assert!(why.contains(name), "{e:?}: {why}");
        }
    }

    #[test]
    fn storage_error_names_follow_the_drive_codes() {
        use estimator_core::storage::StorageError;
        type E = StorageError<()>;
        for (e, name) in [
            (E::Flash(()), "flash error"),
            (E::Geometry, "geometry"),
            (E::TooLarge { needed: 1, room: 0 }, "fit"),
            (E::Verify, "read back"),
            (E::Changed, "unstable"),
        ] {
            let why = refusal(LinkError::Storage, e.code());
            assert!(why.contains(name), "{e:?}: {why}");
        }
        assert!(refusal(LinkError::Storage, storage_detail::ENABLED).contains("disable"));
    }

    #[test]
    fn refusals_name_the_command_error_and_the_field() {
        for e in CommandError::ALL {
            assert_eq!(refusal(LinkError::Refused, e.code()), e.to_string());
        }
        let f = settings::field_named("rig.gear_ratio").unwrap();
        assert!(refusal(LinkError::Config, f.key()).contains("rig.gear_ratio"));
        assert!(refusal(LinkError::Config, 200).contains("200"));
        assert!(refusal(LinkError::Refused, 200).contains("200"));
    }
}
