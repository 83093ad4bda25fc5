#[derive(clap::Args, Debug)]
pub struct Map2dArgs {}

pub fn run(_a: Map2dArgs) -> dpslam::Result<()> {
    Err(dpslam::Error::Invalid("in progress".into()))
}
