use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum EvalCommand {}

pub fn run(c: EvalCommand) -> dpslam::Result<()> {
    match c {}
}
