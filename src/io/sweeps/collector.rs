//! The points every sweep format yields: the no-return policy and the
//! unit/frame conversion, applied alike whatever the file.

use crate::error::{Error, Location, Result};
use crate::io::ply::VertexSink;
use std::path::Path;

/// The conversion of formats already in metres, right-handed, z up: none.
pub(super) fn identity(p: [f64; 3]) -> [f64; 3] {
    p
}

/// Applies the no-return policy and the unit/frame conversion to raw points.
pub(super) struct Collector<'a> {
    path: &'a Path,
    map: fn([f64; 3]) -> [f64; 3],
    pub(super) points: Vec<[f32; 3]>,
    /// Points found in the file, "no return" ones included.
    seen: usize,
}

impl<'a> Collector<'a> {
    pub(super) fn new(path: &'a Path, map: fn([f64; 3]) -> [f64; 3]) -> Self {
        Self {
            path,
            map,
            points: Vec::new(),
            seen: 0,
        }
    }

    /// Takes a point as stored in the file, found at `at`.
    pub(super) fn push(&mut self, raw: [f64; 3], at: Location) -> Result<()> {
        self.seen += 1;
        if raw.iter().any(|v| v.is_nan()) || raw == [0.0; 3] {
            return Ok(());
        }
        if raw.iter().any(|v| v.is_infinite()) {
            return Err(self.error(at, format!("infinite coordinate in point {raw:?}")));
        }
        let m = (self.map)(raw);
        let p = [m[0] as f32, m[1] as f32, m[2] as f32];
        if p.iter().any(|v| v.is_infinite()) {
            return Err(self.error(at, format!("coordinate out of f32 range in point {raw:?}")));
        }
        self.points.push(p);
        Ok(())
    }

    fn error(&self, location: Location, reason: String) -> Error {
        Error::Parse {
            path: self.path.to_path_buf(),
            location,
            reason,
        }
    }

    /// The kept points; an error if the file held no point at all.
    pub(super) fn finish(self) -> Result<Vec<[f32; 3]>> {
        if self.seen == 0 {
            return Err(Error::in_file(self.path, "no points in the file"));
        }
        Ok(self.points)
    }
}

impl VertexSink for Collector<'_> {
    fn reserve(&mut self, n: usize) {
        self.points.reserve(n);
    }
    fn vertex(&mut self, p: [f64; 3], at: Location) -> Result<()> {
        self.push(p, at)
    }
}
