//! Consistent overhead byte stuffing: no zero byte inside a frame, so `0x00` only delimits.

use crate::LinkError;

/// COBS-encodes `src` into `dst` (no delimiter); returns the length, or `None` if `dst` is short.
pub fn cobs_encode(src: &[u8], dst: &mut [u8]) -> Option<usize> {
    let mut code_at = 0usize;
    let mut out = 1usize;
    let mut code = 1u8;
    for &b in src {
        if b == 0 {
            *dst.get_mut(code_at)? = code;
            code_at = out;
            out += 1;
            code = 1;
        } else {
            *dst.get_mut(out)? = b;
            out += 1;
            code += 1;
            if code == 0xff {
                *dst.get_mut(code_at)? = code;
                code_at = out;
                out += 1;
                code = 1;
            }
        }
    }
    *dst.get_mut(code_at)? = code;
    Some(out)
}

/// Decodes a COBS block (no delimiter) in place; returns the decoded length.
///
/// `write <= read` throughout (a block of `code` bytes decodes to at most `code`), so every
/// store lands in bytes already read; the accesses are checked (`get`) all the same, so the
/// firmware carries no panic path for any input.
pub fn cobs_decode_in_place(buf: &mut [u8]) -> Result<usize, LinkError> {
    let mut read = 0usize;
    let mut write = 0usize;
    while let Some(&code) = buf.get(read) {
        let code = code as usize;
        if code == 0 {
            return Err(LinkError::Framing);
        }
        let end = read + code;
        if end > buf.len() {
            return Err(LinkError::Framing);
        }
        read += 1;
        while read < end {
            let b = buf.get(read).copied().unwrap_or(0);
            if b == 0 {
                return Err(LinkError::Framing);
            }
            *buf.get_mut(write).ok_or(LinkError::Framing)? = b;
            write += 1;
            read += 1;
        }
        // A short block stands for a zero byte, except at the very end of the frame.
        if code < 0xff && read < buf.len() {
            *buf.get_mut(write).ok_or(LinkError::Framing)? = 0;
            write += 1;
        }
    }
    Ok(write)
}
