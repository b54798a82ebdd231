//! belt-link: the serial link between a host (operator tool, `hil-sim`) and the drive firmware.
//!
//! One `no_std`, allocation-free definition used by both ends, so the firmware, the simulator and
//! the host tools cannot disagree about a byte. It depends on nothing of the drive: the drive
//! (`estimator-core`) depends on it for [`Command`], [`ModelKind`] and the count units, and its
//! endpoint (what a request does to the drive) lives beside `Drive`.
//!
//! - [`command`]: [`Command`], [`CommandError`], [`ModelKind`];
//! - [`faults`]: the fault bits and their names ([`Faults`]);
//! - [`wire`]: message kinds, [`Request`], [`Reply`], their payloads and the codec;
//! - [`frame`]: CRC-32 over the raw frame, COBS, [`encode`], [`decode_raw`] and the streaming
//!   [`Receiver`];
//! - [`crc`] (also the calibration blob's checksum) and [`bytes`] (the one little-endian reader
//!   and writer, also the blob's);
//! - [`units`]: motor and scale counts as types, the drive's too.
//!
//! The codec is written by hand: `postcard` with `serde` measured +2 to +5 KB of firmware flash,
//! and the payloads are few and fixed-size.
//!
//! # Frame layout
//!
//! ```text
//! raw frame  = kind: u8 | seq: u8 | payload (fixed size per kind, little-endian) | crc: u32 LE
//! on the wire = COBS(raw frame) | 0x00
//! ```
//!
//! - `crc` is CRC-32/ISO-HDLC (the zlib / Ethernet CRC) over `kind | seq | payload`.
//! - COBS removes every zero byte from the frame, so `0x00` only ever delimits frames: a receiver
//!   resynchronises at the next zero after any garbage. An empty frame (two zeros in a row) is
//!   idle filler and is ignored.
//! - `seq` is chosen by the sender of a request and echoed in its reply.
//! - Kinds `0x01..=0x7f` travel host -> drive ([`Request`]), `0x80..=0xff` drive -> host
//!   ([`Reply`]).
//! - Every payload has one exact length, except [`Request::CalChunk`], whose data length is the
//!   payload length minus 4 (1 to [`CHUNK_MAX`] bytes).
//! - Fixed-point values travel as the `i32` of their bits and are typed (`fixed::types::I16F16`)
//!   on both sides; counts are [`MotorCounts`] or [`ScaleCounts`] (micrometres stay `i32` with
//!   `_um` in the name).
//!
//! A frame that fails any check (COBS, size, CRC, kind, length, value range) is rejected whole:
//! the decoder returns [`Rejected`] naming the reason, and the receiver counts it and answers
//! with [`Reply::Error`] where it can. Decoding never panics and never allocates.
#![cfg_attr(not(test), no_std)]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod bytes;
pub mod cobs;
pub mod command;
pub mod crc;
pub mod faults;
pub mod frame;
#[cfg(feature = "testing")]
pub mod testing;
pub mod units;
pub mod wire;

pub use cobs::{cobs_decode_in_place, cobs_encode};
pub use command::{Command, CommandError, ModelKind, UnknownModel};
pub use crc::{crc32, Crc32};
pub use faults::Faults;
pub use frame::{decode_raw, encode, Frame, Receiver, Rejected};
pub use units::{MotorCounts, ScaleCounts};
pub use wire::*;

#[cfg(test)]
mod tests;
