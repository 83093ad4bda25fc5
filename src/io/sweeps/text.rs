//! Plain-text sweeps (`.xyz`, `.txt`): `x y z` per line. 3DTK's `.3d`
//! scans share the line syntax.

use super::collector::{Collector, identity};
use crate::error::{Error, Location, Result};
use crate::io::ply::lines_from;
use std::path::Path;

/// Reads a text sweep (metres, sensor frame).
pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>> {
    let mut c = Collector::new(path, identity);
    parse_xyz_lines(path, bytes, false, &mut c)?;
    c.finish()
}

/// Parses `x y z [more columns]` lines. Blank lines and lines starting with
/// `#` or `//` are skipped, as is anything after a `#`; fields are separated
/// by whitespace or commas. With `uos_header`, a first line `<W> x <H>` (the
/// optional header of 3DTK "uos" files) is skipped.
pub(super) fn parse_xyz_lines(
    path: &Path,
    bytes: &[u8],
    uos_header: bool,
    c: &mut Collector,
) -> Result<()> {
    let start = if bytes.starts_with(b"\xEF\xBB\xBF") {
        3
    } else {
        0
    };
    for (no, _, raw) in lines_from(bytes, start, 1) {
        let text = std::str::from_utf8(raw)
            .map_err(|_| Error::at_line(path, no, "line is not text (binary file?)"))?;
        let text = text.split('#').next().unwrap_or("").trim();
        if text.is_empty() || text.starts_with("//") {
            continue;
        }
        if uos_header && no == 1 && is_uos_header(text) {
            continue;
        }
        let mut tok = text
            .split(|ch: char| ch.is_ascii_whitespace() || ch == ',')
            .filter(|t| !t.is_empty());
        let mut p = [0.0f64; 3];
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            let t = tok.next().ok_or_else(|| {
                Error::at_line(
                    path,
                    no,
                    format!("missing {axis}: expected 'x y z' per line"),
                )
            })?;
            p[k] = t
                .parse()
                .map_err(|_| Error::at_line(path, no, format!("{axis}: '{t}' is not a number")))?;
        }
        c.push(p, Location::Line(no))?;
    }
    Ok(())
}

/// 3DTK's `uosHeaderTest`: digits, one space, `x`, one space, digits.
fn is_uos_header(line: &str) -> bool {
    let Some((a, b)) = line.split_once(" x ") else {
        return false;
    };
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|c| c.is_ascii_digit());
    digits(a) && digits(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uos_header_detection() {
        assert!(is_uos_header("361 x 226"));
        assert!(!is_uos_header("361 x 226 1"));
        assert!(!is_uos_header("10.1 0 0"));
    }
}
