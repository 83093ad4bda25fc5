//! Reading and writing files: laser logs, sweeps, trajectories, maps.
//!
//! Every reader reports problems as [`crate::Error::Parse`] naming the file,
//! the line (or byte offset) and the reason. Gzip-compressed inputs are
//! recognised by their magic bytes, whatever their name.

pub mod atomic;
pub mod bag;
pub mod carmen;
pub mod dpslam_log;
pub mod log2d;
pub mod map_image;
pub mod odometry;
pub mod ply;
pub mod source;
pub mod sweeps;
pub mod tum;
