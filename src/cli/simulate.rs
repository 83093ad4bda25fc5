#[derive(clap::Args, Debug)]
pub struct Simulate2dArgs {}
#[derive(clap::Args, Debug)]
pub struct Simulate3dArgs {}

pub fn run2d(_a: Simulate2dArgs) -> dpslam::Result<()> {
    Err(dpslam::Error::Invalid("in progress".into()))
}
pub fn run3d(_a: Simulate3dArgs) -> dpslam::Result<()> {
    Err(dpslam::Error::Invalid("in progress".into()))
}
