//! Simulators that write logs with known ground truth, and the perturbation of
//! corrected logs into SLAM benchmarks.

mod path;
pub mod perturb;
pub mod sim2d;
pub mod sim3d;
