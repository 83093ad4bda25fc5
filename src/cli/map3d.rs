#[derive(clap::Args, Debug)]
pub struct Map3dArgs {}

pub fn run(_a: Map3dArgs) -> dpslam::Result<()> {
    Err(dpslam::Error::Invalid("in progress".into()))
}
