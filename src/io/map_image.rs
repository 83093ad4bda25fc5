//! 2-D occupancy map images: `map.pgm` + `map.yaml` (ROS map_server
//! convention) and `map.png`.
//!
//! Pixels: free = 254, unknown = 205, occupied towards 0, with
//! `p = (255 − pixel) / 255` as map_server reads it (`negate: 0`). Row 0 of
//! the image is the top (largest y); `origin` in the YAML is the map-frame
//! pose of the lower-left pixel's corner.

use crate::io::atomic::write_atomic;
use crate::{Error, Result};
use std::io::Write;
use std::path::Path;

/// A raster of occupancy probabilities.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyRaster {
    /// Width in cells.
    pub width: usize,
    /// Height in cells.
    pub height: usize,
    /// Cell size, m.
    pub resolution: f64,
    /// Map-frame position (m) of the lower-left corner of cell (0, 0).
    pub origin: [f64; 2],
    /// Occupancy probability per cell, row-major from the bottom row
    /// (y = origin) up; NaN = unknown. (4 bytes a cell: a building-sized
    /// raster is tens of millions of cells, made while the map is held.)
    pub cells: Vec<f32>,
}

impl OccupancyRaster {
    /// 8-bit grey value of a cell in map_server's convention (NaN: unknown).
    pub fn pixel(p: f32) -> u8 {
        if p.is_nan() {
            205
        } else {
            (254.0 - 254.0 * p.clamp(0.0, 1.0)).round() as u8
        }
    }

    /// Rows top to bottom as grey pixels.
    pub fn grey_top_down(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.width * self.height);
        self.extend_grey_top_down(&mut out);
        out
    }

    fn extend_grey_top_down(&self, out: &mut Vec<u8>) {
        for row in (0..self.height).rev() {
            out.extend(
                self.cells[row * self.width..(row + 1) * self.width]
                    .iter()
                    .map(|&p| Self::pixel(p)),
            );
        }
    }
}

/// Writes `<dir>/<stem>.pgm`, `<stem>.yaml` and `<stem>.png`.
pub fn write_map(dir: &Path, stem: &str, raster: &OccupancyRaster) -> Result<()> {
    if raster.width == 0 || raster.height == 0 {
        return Err(Error::Invalid("the map is empty: nothing to draw".into()));
    }
    // One buffer: the PGM's pixels are the PNG's too.
    let mut pgm = Vec::with_capacity(raster.width * raster.height + 64);
    write!(pgm, "P5\n{} {}\n255\n", raster.width, raster.height).expect("write to Vec");
    let header = pgm.len();
    raster.extend_grey_top_down(&mut pgm);
    write_atomic(&dir.join(format!("{stem}.pgm")), &pgm)?;
    let yaml = format!(
        "image: {stem}.pgm\nresolution: {:.6}\norigin: [{:.6}, {:.6}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
        raster.resolution, raster.origin[0], raster.origin[1]
    );
    write_atomic(&dir.join(format!("{stem}.yaml")), yaml.as_bytes())?;
    let mut png = Vec::new();
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut png),
        &pgm[header..],
        raster.width as u32,
        raster.height as u32,
        image::ExtendedColorType::L8,
    )
    .map_err(|e| Error::Invalid(format!("PNG encoding failed: {e}")))?;
    write_atomic(&dir.join(format!("{stem}.png")), &png)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_ros_map_with_bottom_row_last() {
        let dir = tempfile::tempdir().unwrap();
        let r = OccupancyRaster {
            width: 2,
            height: 2,
            resolution: 0.05,
            origin: [-1.0, 2.0],
            cells: vec![1.0, f32::NAN, 0.0, 0.5],
        };
        write_map(dir.path(), "map", &r).unwrap();
        let pgm = std::fs::read(dir.path().join("map.pgm")).unwrap();
        assert!(pgm.starts_with(b"P5\n2 2\n255\n"));
        // top row = cells of row 1 (free, half), bottom row = row 0 (occupied, unknown)
        assert_eq!(&pgm[pgm.len() - 4..], &[254, 127, 0, 205]);
        let yaml = std::fs::read_to_string(dir.path().join("map.yaml")).unwrap();
        assert!(yaml.contains("origin: [-1.000000, 2.000000, 0.0]"));
        assert!(yaml.contains("resolution: 0.050000"));
        let png = image::open(dir.path().join("map.png")).unwrap().to_luma8();
        assert_eq!(png.get_pixel(0, 1).0[0], 0);
        assert!(!dir.path().join("map.png.tmp").exists());
    }
}
