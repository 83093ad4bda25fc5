//! Small PNG line plots: axes, grid, numeric tick labels and polylines.
//!
//! Hand-written on top of the `image` crate so that the benchmark needs no
//! font or system library. Tick labels use a built-in 3×5 pixel digit font;
//! series names and axis titles belong in the caption of the document that
//! shows the plot (colours are fixed per series, see [`PALETTE`]).

use dpslam::{Error, Result};
use image::{Rgb, RgbImage};
use std::path::Path;

/// Background colour of every plot.
pub const BACKGROUND: [u8; 3] = [255, 255, 255];

/// Series colours, in the order the benchmark uses them: blue (estimate),
/// red (truth), grey (odometry), green (extra).
pub const PALETTE: [[u8; 3]; 4] = [[31, 90, 200], [214, 39, 40], [140, 140, 140], [30, 150, 60]];

const GRID: [u8; 3] = [228, 228, 228];
const AXIS: [u8; 3] = [60, 60, 60];

/// Pixels left of, right of, above and below the plotting area.
const MARGIN_LEFT: u32 = 64;
const MARGIN_RIGHT: u32 = 12;
const MARGIN_TOP: u32 = 12;
const MARGIN_BOTTOM: u32 = 28;

/// Scale of the 3×5 digit font (each font pixel becomes `GLYPH_SCALE`²).
const GLYPH_SCALE: u32 = 2;

/// One polyline (and optionally its vertices as square markers).
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Name for logs; not drawn (no text font beyond digits).
    pub label: String,
    /// Data points in plot units, drawn in order; non-finite points break the line.
    pub points: Vec<[f64; 2]>,
    /// Line colour (RGB).
    pub color: [u8; 3],
    /// Draw a square marker at every point (for sparse measurements).
    pub markers: bool,
}

/// A plot: size in pixels and the series to draw.
#[derive(Debug, Clone, PartialEq)]
pub struct Plot {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// One data unit is as long on x as on y (maps and trajectories).
    pub equal_aspect: bool,
    /// Start both axes at zero when all data are positive (timings).
    pub include_origin: bool,
    /// Series, drawn in order (later ones on top).
    pub series: Vec<Series>,
    /// A point cloud drawn under the series as grey density (darker where
    /// more points fall in a pixel): maps seen from above. Counts in the
    /// data range like the series.
    pub cloud: Vec<[f64; 2]>,
}

/// The mapping from data units to pixel coordinates of a rendered plot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Data range shown on x: `[min, max]`.
    pub x: [f64; 2],
    /// Data range shown on y: `[min, max]`.
    pub y: [f64; 2],
    /// Plotting area in pixels: left, top, right, bottom (inclusive).
    pub area: [u32; 4],
}

impl Frame {
    /// Pixel position (column, row; may lie outside the image) of a data point.
    pub fn to_pixel(&self, p: [f64; 2]) -> [f64; 2] {
        let [l, t, r, b] = self.area.map(f64::from);
        let u = (p[0] - self.x[0]) / (self.x[1] - self.x[0]);
        let v = (p[1] - self.y[0]) / (self.y[1] - self.y[0]);
        [l + u * (r - l), b - v * (b - t)]
    }
}

impl Plot {
    /// An empty plot of `width` × `height` pixels.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            equal_aspect: false,
            include_origin: false,
            series: Vec::new(),
            cloud: Vec::new(),
        }
    }

    /// The data-to-pixel mapping this plot will use. Errors when the image is
    /// too small for the margins or no series has a finite point.
    pub fn frame(&self) -> Result<Frame> {
        if self.width < MARGIN_LEFT + MARGIN_RIGHT + 16
            || self.height < MARGIN_TOP + MARGIN_BOTTOM + 16
        {
            return Err(Error::Config(format!(
                "plot of {}×{} pixels is too small for its axes",
                self.width, self.height
            )));
        }
        let finite = self
            .series
            .iter()
            .flat_map(|s| s.points.iter())
            .chain(self.cloud.iter())
            .filter(|p| p[0].is_finite() && p[1].is_finite());
        let mut x = [f64::INFINITY, f64::NEG_INFINITY];
        let mut y = x;
        for p in finite {
            x = [x[0].min(p[0]), x[1].max(p[0])];
            y = [y[0].min(p[1]), y[1].max(p[1])];
        }
        if !x[0].is_finite() {
            return Err(Error::Invalid(
                "nothing to plot: no finite data point".into(),
            ));
        }
        if self.include_origin {
            x[0] = x[0].min(0.0);
            y[0] = y[0].min(0.0);
        }
        let area = [
            MARGIN_LEFT,
            MARGIN_TOP,
            self.width - 1 - MARGIN_RIGHT,
            self.height - 1 - MARGIN_BOTTOM,
        ];
        let (pw, ph) = (f64::from(area[2] - area[0]), f64::from(area[3] - area[1]));
        // A zero span (one point, a straight line) still needs a scale.
        let widen = |r: [f64; 2]| {
            let span = r[1] - r[0];
            let pad = if span > 0.0 {
                0.04 * span
            } else {
                0.5 * r[0].abs().max(1.0)
            };
            [r[0] - pad, r[1] + pad]
        };
        let (mut x, mut y) = (widen(x), widen(y));
        if self.include_origin {
            x[0] = x[0].max(0.0).min(x[0] + (x[1] - x[0]) * 0.04);
            y[0] = y[0].max(0.0).min(y[0] + (y[1] - y[0]) * 0.04);
        }
        if self.equal_aspect {
            // Grow the axis with fewer units per pixel around its centre.
            let upp = ((x[1] - x[0]) / pw).max((y[1] - y[0]) / ph);
            let grow = |r: [f64; 2], pixels: f64| {
                let c = 0.5 * (r[0] + r[1]);
                [c - 0.5 * upp * pixels, c + 0.5 * upp * pixels]
            };
            x = grow(x, pw);
            y = grow(y, ph);
        }
        Ok(Frame { x, y, area })
    }

    /// Draws the plot.
    pub fn render(&self) -> Result<RgbImage> {
        let frame = self.frame()?;
        let mut img = RgbImage::from_pixel(self.width, self.height, Rgb(BACKGROUND));
        let [l, t, r, b] = frame.area;
        let (xs, xstep) = ticks(frame.x, 8);
        let (ys, ystep) = ticks(frame.y, 8);
        for &v in &xs {
            let px = frame.to_pixel([v, frame.y[0]])[0].round() as u32;
            for row in t..=b {
                put(&mut img, px, row, GRID);
            }
            for row in b..b + 4 {
                put(&mut img, px, row, AXIS);
            }
            let text = tick_label(v, xstep);
            let w = text_width(&text);
            draw_text(&mut img, px.saturating_sub(w / 2), b + 7, &text, AXIS);
        }
        for &v in &ys {
            let py = frame.to_pixel([frame.x[0], v])[1].round() as u32;
            for col in l..=r {
                put(&mut img, col, py, GRID);
            }
            for col in l.saturating_sub(4)..l {
                put(&mut img, col, py, AXIS);
            }
            let text = tick_label(v, ystep);
            let w = text_width(&text);
            let h = 5 * GLYPH_SCALE;
            draw_text(
                &mut img,
                l.saturating_sub(7 + w),
                py.saturating_sub(h / 2),
                &text,
                AXIS,
            );
        }
        for col in l..=r {
            put(&mut img, col, t, AXIS);
            put(&mut img, col, b, AXIS);
        }
        for row in t..=b {
            put(&mut img, l, row, AXIS);
            put(&mut img, r, row, AXIS);
        }
        if !self.cloud.is_empty() {
            let (w, h) = (img.width() as usize, img.height() as usize);
            let mut count = vec![0u32; w * h];
            for p in self
                .cloud
                .iter()
                .filter(|p| p[0].is_finite() && p[1].is_finite())
            {
                let q = frame.to_pixel(*p);
                let (x, y) = (q[0].round() as i64, q[1].round() as i64);
                if (i64::from(l)..=i64::from(r)).contains(&x)
                    && (i64::from(t)..=i64::from(b)).contains(&y)
                {
                    count[y as usize * w + x as usize] += 1;
                }
            }
            for (i, &c) in count.iter().enumerate().filter(|(_, c)| **c > 0) {
                // One point: light grey; ten or more: dark grey.
                let v = (200.0 - 140.0 * (f64::from(c).log10().min(1.0))) as u8;
                img.put_pixel((i % w) as u32, (i / w) as u32, Rgb([v, v, v]));
            }
        }
        for s in &self.series {
            let pts: Vec<Option<[f64; 2]>> = s
                .points
                .iter()
                .map(|p| (p[0].is_finite() && p[1].is_finite()).then(|| frame.to_pixel(*p)))
                .collect();
            for w in pts.windows(2) {
                if let (Some(a), Some(c)) = (w[0], w[1]) {
                    draw_line(&mut img, &frame, a, c, s.color);
                }
            }
            if s.markers || s.points.len() == 1 {
                for p in pts.iter().flatten() {
                    let (cx, cy) = (p[0].round() as i64, p[1].round() as i64);
                    for dy in -3..=3 {
                        for dx in -3..=3 {
                            put_clipped(&mut img, &frame, cx + dx, cy + dy, s.color);
                        }
                    }
                }
            }
        }
        Ok(img)
    }

    /// Renders the plot and writes it as a PNG file.
    pub fn write_png(&self, path: &Path) -> Result<()> {
        let img = self.render()?;
        let mut png = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|e| Error::Invalid(format!("PNG encoding failed: {e}")))?;
        dpslam::pipeline::write_atomic(path, &png)
    }
}

/// "Nice" tick values (1, 2 or 5 × 10ᵏ apart) inside `range`, about `target` of them,
/// and their spacing.
pub fn ticks(range: [f64; 2], target: usize) -> (Vec<f64>, f64) {
    let span = range[1] - range[0];
    if !(span > 0.0 && span.is_finite()) {
        return (vec![range[0]], 1.0);
    }
    let raw = span / target.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let first = (range[0] / step).ceil() as i64;
    let last = (range[1] / step).floor() as i64;
    ((first..=last).map(|i| i as f64 * step).collect(), step)
}

/// Tick text with as many decimals as the spacing needs.
fn tick_label(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10()).ceil() as usize
    };
    let s = format!("{v:.decimals$}");
    // "-0" and "-0.0" read as noise on an axis.
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

/// 3×5 glyphs, one row per `u8` (bits 2..0 = columns left to right).
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 2, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        _ => return None,
    })
}

fn text_width(text: &str) -> u32 {
    (text.chars().count() as u32 * 4).saturating_sub(1) * GLYPH_SCALE
}

fn draw_text(img: &mut RgbImage, x: u32, y: u32, text: &str, color: [u8; 3]) {
    for (i, c) in text.chars().enumerate() {
        let Some(rows) = glyph(c) else { continue };
        let x0 = x + i as u32 * 4 * GLYPH_SCALE;
        for (row, bits) in rows.iter().enumerate() {
            for col in 0..3u32 {
                if bits & (4 >> col) != 0 {
                    for dy in 0..GLYPH_SCALE {
                        for dx in 0..GLYPH_SCALE {
                            put(
                                img,
                                x0 + col * GLYPH_SCALE + dx,
                                y + row as u32 * GLYPH_SCALE + dy,
                                color,
                            );
                        }
                    }
                }
            }
        }
    }
}

fn put(img: &mut RgbImage, x: u32, y: u32, color: [u8; 3]) {
    if x < img.width() && y < img.height() {
        img.put_pixel(x, y, Rgb(color));
    }
}

/// Sets a pixel only inside the plotting area, so lines never cross the labels.
fn put_clipped(img: &mut RgbImage, frame: &Frame, x: i64, y: i64, color: [u8; 3]) {
    let [l, t, r, b] = frame.area.map(i64::from);
    if (l..=r).contains(&x) && (t..=b).contains(&y) {
        img.put_pixel(x as u32, y as u32, Rgb(color));
    }
}

/// A 2-pixel-wide line from `a` to `c` (pixel coordinates), clipped to the area.
fn draw_line(img: &mut RgbImage, frame: &Frame, a: [f64; 2], c: [f64; 2], color: [u8; 3]) {
    let (dx, dy) = (c[0] - a[0], c[1] - a[1]);
    let n = dx.abs().max(dy.abs()).ceil().clamp(1.0, 1e6) as usize * 2;
    for i in 0..=n {
        let s = i as f64 / n as f64;
        let (x, y) = (a[0] + s * dx, a[1] + s * dy);
        let (xi, yi) = (x.round() as i64, y.round() as i64);
        put_clipped(img, frame, xi, yi, color);
        put_clipped(img, frame, xi + 1, yi, color);
        put_clipped(img, frame, xi, yi + 1, color);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_inside() {
        let (t, step) = ticks([-0.3, 9.7], 8);
        assert_eq!(step, 2.0);
        assert_eq!(t, vec![0.0, 2.0, 4.0, 6.0, 8.0]);
        let (t, step) = ticks([0.013, 0.049], 4);
        assert!((step - 0.01).abs() < 1e-12);
        assert_eq!(t.len(), 3);
    }

    #[test]
    fn labels_have_the_decimals_of_the_step() {
        assert_eq!(tick_label(2.0, 1.0), "2");
        assert_eq!(tick_label(0.25, 0.05), "0.25");
        assert_eq!(tick_label(-0.0, 0.5), "0.0");
    }

    #[test]
    fn equal_aspect_keeps_units_square() {
        let mut p = Plot::new(400, 300);
        p.equal_aspect = true;
        p.series.push(Series {
            label: "l".into(),
            points: vec![[0.0, 0.0], [10.0, 1.0]],
            color: PALETTE[0],
            markers: false,
        });
        let f = p.frame().unwrap();
        let a = f.to_pixel([0.0, 0.0]);
        let b = f.to_pixel([1.0, 1.0]);
        assert!(((b[0] - a[0]) + (b[1] - a[1])).abs() < 1e-9, "{a:?} {b:?}");
    }
}
