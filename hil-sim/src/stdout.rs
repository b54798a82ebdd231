//! Standard output for the command-line tools (`hil-sim`, `qemu-run`, `beltctl`).
//!
//! `println!` panics when the reader has gone (`qemu-run --bench | head`). These writes instead
//! note it and drop the rest of the output; the tool ends its work normally (so a running QEMU is
//! still killed by its guard) and long loops stop early on [`closed`]. Any other write error (a
//! full disk) is reported once on stderr and makes the exit status a failure ([`exit_code`]).
//! [`Sink`] is the same for code that takes an [`io::Write`].
//!
//! Standard error goes through [`errln!`](crate::errln), which drops a failed write: `eprintln!`
//! panics when stderr is a closed pipe (`2>&1 | head`), and there is no channel left to report
//! on; the exit status still says how the tool ended.

use std::fmt;
use std::io::{self, Write};
use std::process::ExitCode;
use std::sync::atomic::{AtomicU8, Ordering};

const OPEN: u8 = 0;
const READER_GONE: u8 = 1;
const FAILED: u8 = 2;

static STATE: AtomicU8 = AtomicU8::new(OPEN);

/// Writes `args` to standard output unless an earlier write failed. Use [`out!`](crate::out) and
/// [`outln!`](crate::outln).
pub fn write(args: fmt::Arguments<'_>) {
    if STATE.load(Ordering::Relaxed) != OPEN {
        return;
    }
    if let Err(e) = io::stdout().lock().write_fmt(args) {
        note_error(&e);
    }
}

/// Records a failed write to standard output (from [`write`] or a writer of the caller's).
pub fn note_error(e: &io::Error) {
    if is_reader_gone(e) {
        let _ = STATE.compare_exchange(OPEN, READER_GONE, Ordering::Relaxed, Ordering::Relaxed);
    } else if STATE.swap(FAILED, Ordering::Relaxed) != FAILED {
        write_err(format_args!("standard output: {e}\n"));
    }
}

/// Writes `args` to standard error; a failure there is dropped (see the
/// [module](crate::stdout)). Use [`errln!`](crate::errln).
pub fn write_err(args: fmt::Arguments<'_>) {
    let _ = io::stderr().lock().write_fmt(args);
}

/// The reader of standard output has gone (a closed pipe).
fn is_reader_gone(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::BrokenPipe
}

/// Asks, without writing, whether the reader of standard output has gone: the write end of a
/// pipe whose read end is closed reports an error condition to `poll` (a file or a terminal
/// never does). Marks it like a failed write, so [`closed`] says so too. For a tool that may sit
/// silent for long (`qemu-run ELF | head` waits for the firmware's next line otherwise).
pub fn reader_gone() -> bool {
    use rustix::event::{poll, PollFd, PollFlags, Timespec};
    let out = io::stdout();
    let mut fds = [PollFd::new(&out, PollFlags::empty())];
    let now = Timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    if matches!(poll(&mut fds, Some(&now)), Ok(n) if n > 0)
        && fds[0].revents().contains(PollFlags::ERR)
    {
        let _ = STATE.compare_exchange(OPEN, READER_GONE, Ordering::Relaxed, Ordering::Relaxed);
    }
    STATE.load(Ordering::Relaxed) == READER_GONE
}

/// Nothing more reaches standard output: the caller may stop producing it.
pub fn closed() -> bool {
    STATE.load(Ordering::Relaxed) != OPEN
}

/// Standard output as an [`io::Write`] for code that takes a writer (a CSV, the firmware's
/// log): the same rules as [`write`]. It never returns an error; [`exit_code`] reports one.
pub struct Sink;

impl Write for Sink {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        if !closed() {
            if let Err(e) = io::stdout().lock().write_all(buf) {
                note_error(&e);
            }
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        if !closed() {
            if let Err(e) = io::stdout().lock().flush() {
                note_error(&e);
            }
        }
        Ok(())
    }
}

/// The tool's exit status: `code`, or a failure if standard output failed for another reason
/// than its reader going away. Flushes first: what is still buffered counts too.
pub fn exit_code(code: ExitCode) -> ExitCode {
    let _ = Sink.flush();
    if STATE.load(Ordering::Relaxed) == FAILED {
        ExitCode::FAILURE
    } else {
        code
    }
}

/// `print!` that never panics (see the [module](crate::stdout)).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::stdout::write(::std::format_args!($($arg)*))
    };
}

/// `println!` that never panics (see the [module](crate::stdout)).
#[macro_export]
macro_rules! outln {
    () => {
        $crate::stdout::write(::std::format_args!("\n"))
    };
    ($($arg:tt)*) => {
        $crate::stdout::write(::std::format_args!("{}\n", ::std::format_args!($($arg)*)))
    };
}

/// `eprintln!` that never panics (see the [module](crate::stdout)).
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {
        $crate::stdout::write_err(::std::format_args!("{}\n", ::std::format_args!($($arg)*)))
    };
}
