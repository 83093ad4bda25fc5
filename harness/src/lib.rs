//! dpslam's development harness, out of the library's public API:
//! benchmarks of accuracy against references and of speed against particle
//! count, and the test fixtures of the GPU path.
//!
//! - [`accuracy`]: `map2d` on every dataset with a reference (relations,
//!   truth trajectories, the simulator), scored and written up as
//!   `docs/RESULTS.md` with map images and trajectory plots.
//! - [`bench3d`]: `map3d`, KISS-ICP and odometry on long simulated 3-D
//!   sequences, scored and written up as `docs/RESULTS-3D.md`.
//! - [`scaling`]: time per filter iteration against the number of particles.
//! - [`rig`]: a filter warmed up on a real log and the pieces of one step, for
//!   timing (shared with `benches/iteration.rs`).
//! - [`plot`], [`report`]: the PNG plots and the Markdown tables.
//! - [`fixtures`]: maps and filters for the GPU tests and the likelihood
//!   benchmark.

pub mod accuracy;
pub mod bench3d;
pub mod fixtures;
pub mod plot;
pub mod report;
pub mod rig;
pub mod scaling;
