//! # dpslam
//!
//! Laser SLAM with particle filters and distributed-particle maps (DP-SLAM,
//! Eliazar & Parr), in 2-D and 3-D from one implementation.
//!
//! The pipeline, per laser scan: [`filter::ParticleFilter::step`] calls
//! predict (motion model), weigh (laser model on each particle's view of the
//! DP-map), resample, update (add the scan to the DP-map under new ancestry
//! nodes) and prune (drop dead ancestry branches, collapse only-children).
//!
//! Frames and units, everywhere unless a doc comment says otherwise: metres,
//! radians, right-handed; 2-D poses are `x, y, θ` in the map frame (θ
//! counter-clockwise from +x); 3-D poses are `nalgebra::Isometry3<f64>` with z up.

#![warn(missing_docs)]

pub mod ancestry;
pub mod backend;
pub mod config;
pub mod dpmap;
pub mod error;
pub mod eval;
pub mod filter;
pub mod geometry;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod hierarchy;
pub mod icp;
pub mod io;
pub mod laser_model;
pub mod motion_learning;
pub mod motion_model;
mod particle;
pub mod pipeline;
pub mod points;
pub mod proposal;
pub mod raycast;
pub mod refine;
pub mod scan;
pub mod scan_match;
pub mod scorer;
pub mod sim;
pub mod slam;

pub use error::{Error, Result};
