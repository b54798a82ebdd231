//! beltctl: the machine builder's host tool for a belt-drive controller.
//!
//! It speaks the drive's own protocol code (`belt-link`), reads the configuration table of the
//! drive's core (`estimator_core::settings`), and calibrates with the simulator's code
//! (`hil_sim::calibrate`, `calfile`, `plot`), so that the tool, the drive and the simulator
//! cannot disagree.
//!
//! - [`link`]: requests with retries and reply matching, the recording stream;
//! - [`port`]: opening the serial adapter;
//! - [`error`]: [`ToolError`], the messages;
//! - [`status`], [`config`], [`ops`], [`record`], [`calibrate`], [`validate`]: what the
//!   commands do;
//! - [`cli`]: the command line.
#![forbid(unsafe_code)]
// Output only through `stdout` (`out!`, `outln!`, `errln!`): the std macros panic on a closed pipe.
#![deny(clippy::print_stdout, clippy::print_stderr)]
#![warn(missing_docs)]

pub mod calibrate;
pub mod cli;
pub mod config;
pub mod error;
pub mod link;
pub mod ops;
pub mod port;
pub mod record;
pub mod status;
#[cfg(test)]
mod testing;
pub mod validate;

pub use error::ToolError;
pub use link::{Link, LinkOptions};
