//! `beltctl`: the command line; everything else is in the library.
// Output only through `stdout` (`out!`, `outln!`, `errln!`): the std macros panic on a closed pipe.
#![deny(clippy::print_stdout, clippy::print_stderr)]

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = belt_tool::cli::Cli::parse();
    hil_sim::stdout::exit_code(match belt_tool::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            hil_sim::errln!("beltctl: {e}");
            ExitCode::FAILURE
        }
    })
}
