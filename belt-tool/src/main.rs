//! `beltctl`: the command line; everything else is in the library.

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = belt_tool::cli::Cli::parse();
    hil_sim::stdout::exit_code(match belt_tool::cli::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("beltctl: {e}");
            ExitCode::FAILURE
        }
    })
}
