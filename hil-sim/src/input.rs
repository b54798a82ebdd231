//! Reading input files: TOML errors as one line (`line L, column C: message`), so that every
//! refusal is one line naming the file, the place and the reason.

/// Largest input file read, bytes: far above any real scenario, plant, calibration or ELF, low
/// enough that a wrong path (a device, a disk image) is refused instead of filling memory.
pub const MAX_INPUT_BYTES: u64 = 256 << 20;

/// Largest text input (TOML, JSON), bytes. Parsing takes about 35 times a scenario's size in
/// memory, so this bounds a parse to about 0.6 GB; 16 MiB holds some 200,000 moves.
pub const MAX_TEXT_BYTES: u64 = 16 << 20;

/// The bytes of the file at `path`, at most [`MAX_INPUT_BYTES`]: a larger one, or a device
/// that never ends (`/dev/zero` was read until memory ran out), is an error. A pipe or
/// `/dev/stdin` is read like a file; a directory is an error.
pub fn read_file(path: impl AsRef<std::path::Path>) -> std::io::Result<Vec<u8>> {
    read_at_most(path, MAX_INPUT_BYTES)
}

fn read_at_most(path: impl AsRef<std::path::Path>, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    use std::io::{Error, ErrorKind, Read};
    // Asked before opening: what it is decides nothing else, and a directory needs no open.
    if std::fs::metadata(&path)?.is_dir() {
        return Err(Error::new(ErrorKind::IsADirectory, "is a directory"));
    }
    let file = std::fs::File::open(path)?;
    let mut bytes = Vec::new();
    // The limit holds whatever the file claims to be and if it grows while it is read.
    file.take(max_bytes + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(Error::new(
            ErrorKind::InvalidData,
            format!("larger than {} MiB: not an input file", max_bytes >> 20),
        ));
    }
    Ok(bytes)
}

/// [`read_file`] as UTF-8 text, at most [`MAX_TEXT_BYTES`].
pub fn read_text(path: impl AsRef<std::path::Path>) -> std::io::Result<String> {
    String::from_utf8(read_at_most(path, MAX_TEXT_BYTES)?).map_err(|_| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "stream did not contain valid UTF-8",
        )
    })
}

/// A number as a person reads it in a message: plain, or in scientific notation when very
/// large or small (`1e300`, not three hundred digits).
pub fn show(v: f64) -> String {
    if v == 0.0 || (1e-4..1e9).contains(&v.abs()) || !v.is_finite() {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// A computed figure for a message: four significant digits, in exponent form outside
/// 1e-3..1e6 (an input is echoed exactly by [`show`]).
pub fn approx(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        format!("{v}")
    } else if (1e-3..1e6).contains(&v.abs()) {
        let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.digits$}")
    } else {
        format!("{v:.3e}")
    }
}

/// A TOML input that does not parse (a syntax error, a missing, unknown or mistyped key).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{}{message}", place(*at))]
pub struct TomlError {
    /// Line and column, from 1, where the parser stopped (when it knows).
    pub at: Option<(usize, usize)>,
    /// The parser's message, on one line.
    pub message: String,
}

fn place(at: Option<(usize, usize)>) -> String {
    at.map_or(String::new(), |(line, column)| {
        format!("line {line}, column {column}: ")
    })
}

/// Parses `text` as TOML into `T`; the error prints on one line.
pub fn from_toml<T: serde::de::DeserializeOwned>(text: &str) -> Result<T, TomlError> {
    toml::from_str(text).map_err(|e| located(text, &e))
}

/// The place (line and column in `text`) and the one-line message of a TOML error.
pub fn located(text: &str, e: &toml::de::Error) -> TomlError {
    let message = e.message().trim().replace('\n', " ");
    let at = e.span().map(|span| {
        let at = span.start.min(text.len());
        let before = text.get(..at).unwrap_or("");
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        (line, column)
    });
    TomlError { at, message }
}

#[cfg(test)]
mod tests {
    #[test]
    fn errors_are_one_line_with_the_place() {
        let e = super::from_toml::<toml::Table>("a = 1\nb = = 2\n").unwrap_err();
        assert_eq!(e.at.map(|(line, _)| line), Some(2), "{e}");
        let shown = e.to_string();
        assert!(shown.starts_with("line 2, column "), "{shown}");
        assert!(!shown.contains('\n'), "{shown}");
    }

    /// A device that never ends, a directory, and a file that is not text are errors that
    /// say so; an empty device reads as an empty file.
    #[test]
    fn endless_devices_and_directories_are_not_read() {
        let e = super::read_file("/dev/zero").unwrap_err();
        assert!(e.to_string().contains("larger than 256 MiB"), "{e}");
        let e = super::read_text("/dev/zero").unwrap_err();
        assert!(e.to_string().contains("larger than 16 MiB"), "{e}");
        assert_eq!(super::read_file("/dev/null").unwrap(), b"");
        let e = super::read_file(std::env::temp_dir()).unwrap_err();
        assert!(e.to_string().contains("directory"), "{e}");
        let p = std::env::temp_dir().join(format!("belt-input-{}.bin", std::process::id()));
        std::fs::write(&p, [b'a', 0xff, b'b']).unwrap();
        assert_eq!(super::read_file(&p).unwrap(), [b'a', 0xff, b'b']);
        let e = super::read_text(&p).unwrap_err();
        assert!(e.to_string().contains("UTF-8"), "{e}");
        let _ = std::fs::remove_file(&p);
    }

    #[test]
    fn numbers_in_messages_stay_short() {
        assert_eq!(super::show(1e300), "1e300");
        assert_eq!(super::show(0.25), "0.25");
        assert_eq!(super::show(f64::NAN), "NaN");
        assert_eq!(super::show(-2e-9), "-2e-9");
    }
}
