//! Opening the drive's serial port: 8N1, no flow control, the given baud rate.

use std::time::Duration;

use serialport::{ClearBuffer, DataBits, FlowControl, Parity, StopBits};

use crate::error::ToolError;
use crate::link::{Link, LinkOptions, Port};

/// The drive's baud rate.
pub const DEFAULT_BAUD: u32 = 460_800;

/// How long one read waits for bytes: short, so that the link's own deadlines stay accurate.
const READ_SLICE: Duration = Duration::from_millis(5);

/// Opens `path` as the drive's serial port (8N1, no flow control), input buffer emptied.
pub fn open(path: &str, baud: u32) -> Result<Box<dyn Port>, ToolError> {
    let port = serialport::new(path, baud)
        .data_bits(DataBits::Eight)
        .parity(Parity::None)
        .stop_bits(StopBits::One)
        .flow_control(FlowControl::None)
        .timeout(READ_SLICE)
        .open()
        .map_err(|e| not_a_tty(path).unwrap_or_else(|| ToolError::open(path, &e)))?;
    // Whatever waited in the adapter is from before us (a boot message, an old stream).
    port.clear(ClearBuffer::Input)
        .map_err(|e| ToolError::open(path, &e))?;
    Ok(Box::new(port))
}

/// A link to the drive on `path`.
pub fn connect(path: &str, baud: u32, opts: LinkOptions) -> Result<Link, ToolError> {
    Ok(Link::new(open(path, baud)?, path, opts))
}

/// The error for a path that exists but is no character device (a file, a directory).
fn not_a_tty(path: &str) -> Option<ToolError> {
    use std::os::unix::fs::FileTypeExt;
    let t = std::fs::metadata(path).ok()?.file_type();
    (!t.is_char_device()).then(|| ToolError::Open {
        port: path.to_string(),
        reason: format!(
            "not a serial port (a {})",
            if t.is_dir() { "directory" } else { "file" }
        ),
    })
}
