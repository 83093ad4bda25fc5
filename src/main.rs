//! `dpslam` command-line interface: a thin layer over the library.

mod cli;

use clap::Parser;

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

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
