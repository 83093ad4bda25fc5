//! KITTI Velodyne sweeps (`.bin`): little-endian float32 `x y z intensity`
//! records.

use super::collector::{Collector, identity};
use crate::error::{Error, Location, Result};
use std::path::Path;

/// Bytes per KITTI Velodyne point: float32 x y z intensity.
const KITTI_RECORD: usize = 16;

pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>> {
    let rem = bytes.len() % KITTI_RECORD;
    if rem != 0 {
        return Err(Error::at_byte(
            path,
            (bytes.len() - rem) as u64,
            format!(
                "size {} is not a multiple of {KITTI_RECORD} bytes (float32 x y z intensity): \
                 {rem} trailing bytes; truncated or not a KITTI scan",
                bytes.len()
            ),
        ));
    }
    let mut c = Collector::new(path, identity);
    c.points.reserve(bytes.len() / KITTI_RECORD);
    for (i, rec) in bytes.chunks_exact(KITTI_RECORD).enumerate() {
        let f = |k: usize| f32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().expect("4 bytes"));
        c.push(
            [f(0) as f64, f(1) as f64, f(2) as f64],
            Location::Byte((i * KITTI_RECORD) as u64),
        )?;
    }
    c.finish()
}
