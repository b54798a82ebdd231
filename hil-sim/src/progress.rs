//! Progress for long runs: a bar on a terminal, one line per stage otherwise.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

/// Stage-by-stage progress on standard error.
pub struct Progress {
    bar: Option<ProgressBar>,
    stage: String,
    tty: bool,
    /// The program named on stage lines without a terminal.
    program: &'static str,
}

impl Default for Progress {
    fn default() -> Self {
        Self::new()
    }
}

impl Progress {
    /// A reporter for `hil-sim`; draws a bar only when standard error is a terminal.
    pub fn new() -> Progress {
        Progress::named("hil-sim")
    }

    /// A reporter for another program (its name starts the stage lines).
    pub fn named(program: &'static str) -> Progress {
        Progress {
            bar: None,
            stage: String::new(),
            tty: std::io::stderr().is_terminal(),
            program,
        }
    }

    /// Reports `fraction` (0..=1) of `stage`.
    pub fn stage(&mut self, stage: &str, fraction: f64) {
        if stage != self.stage {
            if let Some(b) = self.bar.take() {
                b.finish_and_clear();
            }
            self.stage = stage.to_string();
            if self.tty {
                let b = ProgressBar::new(1000);
                b.set_style(
                    ProgressStyle::with_template("{msg:>28} [{bar:40}] {percent:>3}% {elapsed}")
                        .unwrap_or_else(|_| ProgressStyle::default_bar())
                        .progress_chars("=> "),
                );
                b.set_message(stage.to_string());
                self.bar = Some(b);
            } else {
                crate::errln!("{}: {stage}", self.program);
            }
        }
        if let Some(b) = &self.bar {
            b.set_position((fraction.clamp(0.0, 1.0) * 1000.0) as u64);
        }
    }

    /// Prints a line without tearing the bar.
    pub fn println(&self, line: &str) {
        match &self.bar {
            Some(b) => b.suspend(|| crate::errln!("{line}")),
            None => crate::errln!("{line}"),
        }
    }

    /// Clears the bar.
    pub fn finish(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
        self.stage.clear();
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish();
    }
}
