//! Legacy VTK sweeps (`.vtk`), ASCII: the `POINTS` of a `POLYDATA` or
//! `UNSTRUCTURED_GRID` data set.

use super::collector::{Collector, identity};
use crate::error::{Error, Location, Result};
use crate::io::ply::lines_from;
use std::path::Path;

/// Reads the `POINTS` of a legacy ASCII VTK file; other sections (VERTICES,
/// POINT_DATA, ...) are ignored.
pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>> {
    let mut lines = lines_from(bytes, 0, 1).map(|(no, _, raw)| {
        std::str::from_utf8(raw)
            .map(|t| (no, t))
            .map_err(|_| Error::at_line(path, no, "line is not text"))
    });
    let mut next_line = |what: &str| -> Result<(usize, &str)> {
        lines
            .next()
            .unwrap_or_else(|| Err(Error::in_file(path, format!("file ends before {what}"))))
    };
    let (_, magic) = next_line("the '# vtk DataFile' line")?;
    if !magic
        .trim_start()
        .to_ascii_lowercase()
        .starts_with("# vtk datafile")
    {
        return Err(Error::at_line(
            path,
            1,
            "not a legacy VTK file: no '# vtk DataFile' line",
        ));
    }
    next_line("the title line")?;
    let (no, enc) = next_line("the ASCII/BINARY line")?;
    match enc.trim().to_ascii_uppercase().as_str() {
        "ASCII" => {}
        "BINARY" => {
            return Err(Error::at_line(
                path,
                no,
                "binary legacy VTK is not supported: save as ASCII",
            ));
        }
        other => {
            return Err(Error::at_line(
                path,
                no,
                format!("expected ASCII or BINARY, found '{other}'"),
            ));
        }
    }
    let (no, n) = loop {
        let (no, text) = next_line("a POINTS section")?;
        let mut tok = text.split_ascii_whitespace();
        match tok.next().map(|k| k.to_ascii_uppercase()).as_deref() {
            Some("DATASET") => {
                let ds = tok.next().unwrap_or("").to_ascii_uppercase();
                if ds != "POLYDATA" && ds != "UNSTRUCTURED_GRID" {
                    return Err(Error::at_line(
                        path,
                        no,
                        format!("DATASET {ds} not supported (POLYDATA or UNSTRUCTURED_GRID)"),
                    ));
                }
            }
            Some("POINTS") => {
                let n = tok
                    .next()
                    .and_then(|t| t.parse::<usize>().ok())
                    .ok_or_else(|| Error::at_line(path, no, "POINTS needs a point count"))?;
                let ty = tok.next().unwrap_or("").to_ascii_lowercase();
                let known = [
                    "float",
                    "double",
                    "int",
                    "unsigned_int",
                    "short",
                    "unsigned_short",
                    "long",
                    "unsigned_long",
                    "char",
                    "unsigned_char",
                ];
                if !known.contains(&ty.as_str()) {
                    return Err(Error::at_line(
                        path,
                        no,
                        format!("POINTS data type '{ty}' unknown"),
                    ));
                }
                break (no, n);
            }
            // Field data or comments before the points: not ours to read.
            _ => {}
        }
    };
    if n == 0 {
        return Err(Error::at_line(path, no, "POINTS 0: no points"));
    }
    let mut c = Collector::new(path, identity);
    c.points.reserve(n.min(bytes.len() / 6));
    let mut p = [0.0f64; 3];
    let mut k = 0usize; // coordinates read
    let mut last = no;
    while k < 3 * n {
        let (no, text) = match lines.next() {
            Some(r) => r?,
            None => {
                return Err(Error::at_line(
                    path,
                    last,
                    format!("file ends after {} of the {n} declared points", k / 3),
                ));
            }
        };
        last = no;
        for t in text.split_ascii_whitespace() {
            if k == 3 * n {
                return Err(Error::at_line(
                    path,
                    no,
                    format!("more than the 3 × {n} declared coordinates on the last POINTS line"),
                ));
            }
            p[k % 3] = t.parse().map_err(|_| {
                Error::at_line(
                    path,
                    no,
                    format!(
                        "'{t}' is not a number (after {} of the {n} declared points)",
                        k / 3
                    ),
                )
            })?;
            k += 1;
            if k.is_multiple_of(3) {
                c.push(p, Location::Line(no))?;
            }
        }
    }
    c.finish()
}
