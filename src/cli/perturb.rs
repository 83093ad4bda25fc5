#[derive(clap::Args, Debug)]
pub struct PerturbArgs {}

pub fn run(_a: PerturbArgs) -> dpslam::Result<()> {
    Err(dpslam::Error::Invalid("in progress".into()))
}
