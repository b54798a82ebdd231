//! Reading input files: TOML errors as one line (`line L, column C: message`), so that every
//! refusal is one line naming the file, the place and the reason.

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
}
