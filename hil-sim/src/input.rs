//! Reading input files: TOML errors as one line (`line L, column C: message`), so that every
//! refusal is one line naming the file, the place and the reason.

/// Parses `text` as TOML into `T`; the error is one line.
pub fn from_toml<T: serde::de::DeserializeOwned>(text: &str) -> Result<T, String> {
    toml::from_str(text).map_err(|e| one_line(text, &e))
}

/// `line L, column C: message` for a TOML error in `text`.
pub fn one_line(text: &str, e: &toml::de::Error) -> String {
    let message = e.message().trim().replace('\n', " ");
    match e.span() {
        Some(span) => {
            let at = span.start.min(text.len());
            let before = text.get(..at).unwrap_or("");
            let line = before.matches('\n').count() + 1;
            let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
            format!("line {line}, column {column}: {message}")
        }
        None => message,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn errors_are_one_line_with_the_place() {
        let e = super::from_toml::<toml::Table>("a = 1\nb = = 2\n").unwrap_err();
        assert!(e.starts_with("line 2, column "), "{e}");
        assert!(!e.contains('\n'), "{e}");
    }
}
