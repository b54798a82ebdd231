//! Frames: kind, seq, payload and CRC, COBS-stuffed and zero-delimited; the streaming receiver.

use crate::cobs::{cobs_decode_in_place, cobs_encode};
use crate::crc::crc32;
use crate::wire::{
    kind, LinkError, Message, MAX_ENCODED, MAX_FRAME, MAX_PAYLOAD, MAX_RAW, OVERHEAD,
};

/// A decoded frame: the sender's sequence number and the message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frame<M> {
    /// Sequence number (echoed in replies).
    pub seq: u8,
    /// The message.
    pub msg: M,
}

/// A rejected frame: what could be read of it, and why it was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rejected {
    /// Kind byte if the frame was readable far enough, else [`kind::UNKNOWN`].
    pub kind: u8,
    /// Sequence number if readable, else 0.
    pub seq: u8,
    /// Why.
    pub error: LinkError,
}

/// Encodes `msg` with sequence number `seq` into `out`; returns the bytes to send (delimiter
/// included).
pub fn encode<M: Message>(seq: u8, msg: &M, out: &mut [u8; MAX_FRAME]) -> usize {
    let mut raw = [0u8; MAX_RAW];
    raw[0] = msg.kind();
    raw[1] = seq;
    // `min`: a payload never exceeds its buffer, and the compiler then sees the slices below in
    // bounds (no slice panic, whose `core::fmt` costs the drive ~1 KB of flash).
    let n = msg
        .write_payload(&mut raw[2..2 + MAX_PAYLOAD])
        .min(MAX_PAYLOAD);
    let crc = crc32(&raw[..2 + n]);
    raw[2 + n..6 + n].copy_from_slice(&crc.to_le_bytes());
    // Cannot fail: `out` holds the worst case of the largest raw frame.
    let len = cobs_encode(&raw[..OVERHEAD + n], &mut out[..MAX_ENCODED]).unwrap_or(0);
    // `len <= MAX_ENCODED < MAX_FRAME`; `min` lets the compiler see it (no panic path).
    let len = len.min(MAX_FRAME - 1);
    out[len] = 0;
    len + 1
}

/// Checks a raw (un-stuffed) frame and parses it.
pub fn decode_raw<M: Message>(raw: &[u8]) -> Result<Frame<M>, Rejected> {
    if raw.len() < OVERHEAD {
        let (k, seq) = (kind::UNKNOWN, 0);
        return Err(Rejected {
            kind: k,
            seq,
            error: LinkError::TooShort,
        });
    }
    let (body, crc) = raw.split_at(raw.len() - 4);
    let mut crc_bytes = [0u8; 4];
    crc_bytes.copy_from_slice(crc);
    if crc32(body) != u32::from_le_bytes(crc_bytes) {
        return Err(Rejected {
            kind: kind::UNKNOWN,
            seq: 0,
            error: LinkError::Crc,
        });
    }
    let (k, seq) = (body[0], body[1]);
    M::parse(k, &body[2..])
        .map(|msg| Frame { seq, msg })
        .map_err(|error| Rejected {
            kind: k,
            seq,
            error,
        })
}

/// Streaming receiver: feed it every byte from the wire; it returns a result per frame.
///
/// It keeps one encoded frame (at most [`MAX_ENCODED`] bytes) and the link counters. Garbage
/// longer than that is rejected as [`LinkError::Oversize`] once its delimiter arrives.
#[derive(Clone, Debug)]
pub struct Receiver {
    buf: [u8; MAX_ENCODED],
    len: usize,
    overflow: bool,
    /// Frames accepted.
    pub frames_ok: u32,
    /// Frames rejected.
    pub frames_bad: u32,
    /// The last rejection's reason, if any.
    pub last_error: Option<LinkError>,
}

impl Default for Receiver {
    fn default() -> Self {
        Self::new()
    }
}

impl Receiver {
    /// An empty receiver.
    pub const fn new() -> Self {
        Receiver {
            buf: [0; MAX_ENCODED],
            len: 0,
            overflow: false,
            frames_ok: 0,
            frames_bad: 0,
            last_error: None,
        }
    }

    /// Feeds one byte; returns `Some` when it completed a (non-empty) frame.
    pub fn push<M: Message>(&mut self, byte: u8) -> Option<Result<Frame<M>, Rejected>> {
        if byte != 0 {
            if self.len < MAX_ENCODED {
                self.buf[self.len] = byte;
                self.len += 1;
            } else {
                self.overflow = true;
            }
            return None;
        }
        let (len, overflow) = (self.len, self.overflow);
        self.len = 0;
        self.overflow = false;
        if len == 0 && !overflow {
            return None; // idle filler
        }
        let result = if overflow {
            Err(Rejected {
                kind: kind::UNKNOWN,
                seq: 0,
                error: LinkError::Oversize,
            })
        } else {
            // `len <= MAX_ENCODED` and `n <= len`; `get` keeps the slice panic (and its
            // `core::fmt`, ~1 KB of the drive's flash) out.
            match cobs_decode_in_place(self.buf.get_mut(..len).unwrap_or_default()) {
                Ok(n) => decode_raw(self.buf.get(..n).unwrap_or_default()),
                Err(error) => Err(Rejected {
                    kind: kind::UNKNOWN,
                    seq: 0,
                    error,
                }),
            }
        };
        match &result {
            Ok(_) => self.frames_ok = self.frames_ok.wrapping_add(1),
            Err(r) => self.reject(r.error),
        }
        Some(result)
    }

    /// Counts a frame that decoded but was refused later (by the drive or the transfer logic).
    pub fn reject(&mut self, error: LinkError) {
        self.frames_bad = self.frames_bad.wrapping_add(1);
        self.last_error = Some(error);
    }
}
