//! `dpslam` command-line interface: a thin layer over the library.

mod cli;

use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = cli::Cli::parse();
    match cli::run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("dpslam: error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
