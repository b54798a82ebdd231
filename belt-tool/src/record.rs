//! `beltctl record`: the drive's recording stream into a CSV file.

use std::io::{IsTerminal, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use hil_sim::input::show;
use indicatif::{ProgressBar, ProgressStyle};

use crate::error::ToolError;
use crate::link::{Link, RecordingStats, TickSample};

/// The CSV header.
pub const CSV_HEADER: &str = "tick,motor_counts,scale_counts,setpoint_counts,current_ma";

/// Writes samples as CSV rows.
pub fn write_rows(w: &mut impl Write, samples: &[TickSample]) -> std::io::Result<()> {
    for s in samples {
        let r = &s.sample;
        writeln!(
            w,
            "{},{},{},{},{}",
            s.tick, r.motor_counts, r.scale_counts, r.setpoint_counts, r.current_ma
        )?;
    }
    Ok(())
}

/// Records for `seconds`, one sample every `every` ticks, into `out`; returns the samples
/// written and the recording's counters (losses are the caller's to report).
pub fn record(
    link: &mut Link,
    seconds: f64,
    every: u16,
    out: &Path,
) -> Result<(u64, RecordingStats), ToolError> {
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= 86_400.0) {
        return Err(ToolError::Usage(format!(
            "--seconds {}: give a duration of up to a day",
            show(seconds)
        )));
    }
    let io_err = |e: std::io::Error| ToolError::file(out.display(), e);
    // Written beside `out` and renamed over it once samples arrived: a refused or empty
    // recording leaves an existing file as it was.
    let partial = partial_path(out);
    let file = std::fs::File::create(&partial).map_err(io_err)?;
    let mut w = std::io::BufWriter::new(file);
    let mut written = 0u64;
    let result = stream(link, seconds, every, &mut w, &mut written, out).and_then(|stats| {
        w.flush().map_err(io_err)?;
        if written == 0 {
            return Err(ToolError::Drive(format!(
                "the drive sent no samples in {} s (one every {every} ticks asked); {} not \
                 written",
                show(seconds),
                out.display()
            )));
        }
        Ok(stats)
    });
    drop(w);
    // What arrived before a failure is kept, as the caller reports.
    if written > 0 {
        std::fs::rename(&partial, out).map_err(io_err)?;
    } else {
        let _ = std::fs::remove_file(&partial);
    }
    result.map(|stats| (written, stats))
}

/// `dir/.name.partial`, beside `out` (so the rename stays on one file system).
fn partial_path(out: &Path) -> std::path::PathBuf {
    let name = out
        .file_name()
        .map_or_else(|| "recording".into(), |n| n.to_string_lossy().into_owned());
    out.with_file_name(format!(".{name}.partial-{}", std::process::id()))
}

/// The recording itself: header and rows into `w`, `written` counting the rows.
fn stream(
    link: &mut Link,
    seconds: f64,
    every: u16,
    w: &mut impl Write,
    written: &mut u64,
    out: &Path,
) -> Result<RecordingStats, ToolError> {
    let io_err = |e: std::io::Error| ToolError::file(out.display(), e);
    writeln!(w, "{CSV_HEADER}").map_err(io_err)?;
    let bar = std::io::stderr().is_terminal().then(|| {
        let b = ProgressBar::new((seconds * 10.0).ceil() as u64);
        b.set_style(
            ProgressStyle::with_template("recording [{bar:40}] {msg} {elapsed}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        b
    });
    link.start_recording(every)?;
    let start = Instant::now();
    let result: Result<(), ToolError> = (|| {
        while start.elapsed().as_secs_f64() < seconds {
            let left = Duration::from_secs_f64(seconds).saturating_sub(start.elapsed());
            link.pump(crate::ops::KEEPALIVE.min(left))?;
            link.status()?;
            let batch = link.take_samples();
            *written += batch.len() as u64;
            write_rows(w, &batch).map_err(io_err)?;
            if let (Some(b), Some(st)) = (&bar, link.recording_stats()) {
                b.set_position((start.elapsed().as_secs_f64() * 10.0) as u64);
                b.set_message(format!(
                    "{} samples{}",
                    written,
                    if st.lost_frames > 0 {
                        format!(", {} frames lost", st.lost_frames)
                    } else {
                        String::new()
                    }
                ));
            }
        }
        Ok(())
    })();
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    // Stop the stream whatever happened: a drive left streaming floods the next user.
    let stopped = link.stop_recording();
    result?;
    let (rest, stats) = stopped?;
    *written += rest.len() as u64;
    write_rows(w, &rest).map_err(io_err)?;
    Ok(stats)
}
