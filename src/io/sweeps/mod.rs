//! 3-D laser sweeps: one point cloud per file, in the sensor frame.
//!
//! Formats, chosen by file extension (a trailing `.gz` is allowed; gzip is
//! also recognised by its magic bytes whatever the name):
//!
//! | extension | format |
//! |---|---|
//! | `.pcd` | PCD 0.5–0.7, `DATA ascii` or `binary` (`binary_compressed` is refused) |
//! | `.ply` | PLY ascii / binary little- or big-endian, `vertex` `x y z` |
//! | `.bin` | KITTI Velodyne: little-endian float32 `x y z intensity` records |
//! | `.xyz`, `.txt` | text, `x y z` per line, extra columns ignored |
//! | `.vtk` | legacy VTK, ASCII, `DATASET POLYDATA` (or `UNSTRUCTURED_GRID`) `POINTS` |
//! | `.3d` | 3DTK "uos" scan, with the pose from the `.pose` file beside it |
//!
//! Units and frames of [`Sweep::points`]: metres, sensor frame, right-handed,
//! z up. 3DTK files (centimetres, left-handed, y up) are converted, see
//! [`threedtk_point`] and [`threedtk_pose`].
//!
//! **No-return points are dropped**, in every format alike: a point with a NaN
//! coordinate, or exactly `(0, 0, 0)` as stored in the file. Organised clouds
//! use NaN for missing returns; Velodyne drivers write zeros (5 032 of the
//! 69 088 points of each fast_gicp sweep), and a laser cannot measure a return
//! at its own origin. An infinite coordinate is not a known "no return"
//! convention and is reported as an error. A file whose points are all "no
//! return" gives a sweep with no points; a file with no points at all (empty
//! file, zero declared points) is an error.
//!
//! Errors name the file and the 1-based line (text formats) or the 0-based
//! byte offset (binary formats; counted in the decompressed data of a gzip
//! file). bzip2 files are refused with a message saying to decompress them.

mod collector;
mod kitti;
mod pcd;
mod text;
mod threedtk;
mod vtk;

pub use threedtk::{threedtk_point, threedtk_pose};

use crate::error::{Error, Result};
use crate::geometry::Pose3;
use crate::io::ply::parse_ply_xyz;
use crate::io::source::read_bytes;
use collector::{Collector, identity};
use std::cmp::Ordering;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// One 3-D laser sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct Sweep {
    /// Measured points in the sensor frame: metres, right-handed, z up.
    /// "No return" points (NaN, or exactly zero) are already dropped.
    pub points: Vec<[f32; 3]>,
    /// The file the sweep was read from.
    pub source: PathBuf,
    /// A pose estimate from the file, if it carries one: maps sensor-frame
    /// points into the dataset's world frame (metres, right-handed, z up).
    /// From a 3DTK `.pose` file, or from a non-identity PCD `VIEWPOINT`.
    pub prior: Option<Pose3>,
}

/// File formats [`read_sweep`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SweepFormat {
    /// Point Cloud Library `.pcd`.
    Pcd,
    /// Stanford `.ply`.
    Ply,
    /// KITTI Velodyne `.bin` (float32 x y z intensity).
    KittiBin,
    /// Plain text `.xyz` / `.txt`.
    Text,
    /// Legacy VTK `.vtk` (ASCII).
    Vtk,
    /// 3DTK `.3d` (+ `.pose`).
    ThreeDtk,
}

/// What a file name says about its content.
enum Kind {
    Sweep(SweepFormat),
    Bzip2,
    Other,
}

fn classify(path: &Path) -> Kind {
    let Some(name) = path.file_name() else {
        return Kind::Other;
    };
    let name = name.to_string_lossy().to_ascii_lowercase();
    if name.ends_with(".bz2") {
        return Kind::Bzip2;
    }
    let name = name.strip_suffix(".gz").unwrap_or(&name);
    let Some((_, ext)) = name.rsplit_once('.') else {
        return Kind::Other;
    };
    Kind::Sweep(match ext {
        "pcd" => SweepFormat::Pcd,
        "ply" => SweepFormat::Ply,
        "bin" => SweepFormat::KittiBin,
        "xyz" | "txt" => SweepFormat::Text,
        "vtk" => SweepFormat::Vtk,
        "3d" => SweepFormat::ThreeDtk,
        _ => return Kind::Other,
    })
}

const BZIP2_REASON: &str =
    "bzip2-compressed: bzip2 not supported, decompress first (bunzip2 -k FILE)";

/// The format of `path`, from its extension (a trailing `.gz` ignored).
/// A `.bz2` file or an unknown extension is an error saying so.
pub fn sweep_format(path: &Path) -> Result<SweepFormat> {
    match classify(path) {
        Kind::Sweep(f) => Ok(f),
        Kind::Bzip2 => Err(Error::in_file(path, BZIP2_REASON)),
        Kind::Other => Err(Error::in_file(
            path,
            "unknown sweep format: expected .pcd, .ply, .bin, .xyz, .txt, .vtk or .3d \
             (optionally .gz)",
        )),
    }
}

/// Reads one sweep from `path` (format by extension, see the module docs).
///
/// For a 3DTK `.3d` file, the pose is read from `<stem>.pose` (or
/// `<stem>.pose.gz`) in the same directory; without one, `prior` is `None`.
pub fn read_sweep(path: &Path) -> Result<Sweep> {
    let format = sweep_format(path)?;
    let bytes = read_bytes(path)?;
    if bytes.is_empty() {
        return Err(Error::in_file(path, "empty file"));
    }
    if is_bzip2(&bytes) {
        return Err(Error::in_file(path, BZIP2_REASON));
    }
    let (points, prior) = match format {
        SweepFormat::Pcd => pcd::read(path, &bytes)?,
        SweepFormat::Ply => {
            // The PLY parser is the one the map reader uses (`io::ply`).
            let mut c = Collector::new(path, identity);
            parse_ply_xyz(path, &bytes, &mut c)?;
            (c.finish()?, None)
        }
        SweepFormat::KittiBin => (kitti::read(path, &bytes)?, None),
        SweepFormat::Text => (text::read(path, &bytes)?, None),
        SweepFormat::Vtk => (vtk::read(path, &bytes)?, None),
        SweepFormat::ThreeDtk => threedtk::read(path, &bytes)?,
    };
    Ok(Sweep {
        points,
        source: path.to_path_buf(),
        prior,
    })
}

/// The sweep files of `dir`, in file-name order (runs of digits compared by
/// value, so `scan2` comes before `scan10`; equal to plain byte order for
/// zero-padded names).
///
/// A sequence has one format: when `dir` holds supported files of several
/// formats, the most frequent one is taken (so the `relative.txt` beside the
/// `.pcd` sweeps of fast_gicp is not a sweep) and a tie is an error. For 3DTK
/// the `.3d` files are listed; their `.pose` files are read by [`read_sweep`].
/// Hidden files and subdirectories are ignored. A directory with no supported
/// file is an error (mentioning `.bz2` files, which must be decompressed).
pub fn list_sweeps(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut by_format: BTreeMap<SweepFormat, Vec<PathBuf>> = BTreeMap::new();
    let mut bzip2 = 0usize;
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let path = entry.path();
        if entry.file_name().to_string_lossy().starts_with('.') || !path.is_file() {
            continue;
        }
        match classify(&path) {
            Kind::Sweep(f) => by_format.entry(f).or_default().push(path),
            Kind::Bzip2 => bzip2 += 1,
            Kind::Other => {}
        }
    }
    let best = by_format.values().map(Vec::len).max().unwrap_or(0);
    if best == 0 {
        let hint = if bzip2 > 0 {
            format!(" ({bzip2} .bz2 file(s): bzip2 not supported, decompress first)")
        } else {
            String::new()
        };
        return Err(Error::Invalid(format!(
            "{}: no sweep files (.pcd, .ply, .bin, .xyz, .txt, .vtk, .3d, optionally .gz){hint}",
            dir.display()
        )));
    }
    let winners: Vec<SweepFormat> = by_format
        .iter()
        .filter(|(_, v)| v.len() == best)
        .map(|(f, _)| *f)
        .collect();
    if winners.len() > 1 {
        return Err(Error::Invalid(format!(
            "{}: as many sweep files of formats {winners:?} ({best} each): \
             cannot tell which form the sequence; put one format per directory",
            dir.display()
        )));
    }
    let mut files = by_format.remove(&winners[0]).unwrap_or_default();
    files.sort_by(|a, b| natural_cmp(&file_name(a), &file_name(b)));
    Ok(files)
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Compares names with runs of ASCII digits ordered by numeric value; ties
/// (e.g. `scan01` vs `scan1`) fall back to byte order so the order is total.
fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (ab, bb) = (a.as_bytes(), b.as_bytes());
    let (mut i, mut j) = (0, 0);
    while i < ab.len() && j < bb.len() {
        if ab[i].is_ascii_digit() && bb[j].is_ascii_digit() {
            let si = i;
            while i < ab.len() && ab[i].is_ascii_digit() {
                i += 1;
            }
            let sj = j;
            while j < bb.len() && bb[j].is_ascii_digit() {
                j += 1;
            }
            let da = trim_zeros(&ab[si..i]);
            let db = trim_zeros(&bb[sj..j]);
            let ord = da.len().cmp(&db.len()).then_with(|| da.cmp(db));
            if ord != Ordering::Equal {
                return ord;
            }
        } else {
            let ord = ab[i].cmp(&bb[j]);
            if ord != Ordering::Equal {
                return ord;
            }
            i += 1;
            j += 1;
        }
    }
    (ab.len() - i).cmp(&(bb.len() - j)).then_with(|| a.cmp(b))
}

fn trim_zeros(d: &[u8]) -> &[u8] {
    let k = d.iter().position(|&c| c != b'0').unwrap_or(d.len());
    &d[k..]
}

fn is_bzip2(bytes: &[u8]) -> bool {
    bytes.len() >= 10
        && bytes.starts_with(b"BZh")
        && (b'1'..=b'9').contains(&bytes[3])
        && bytes[4..10] == [0x31, 0x41, 0x59, 0x26, 0x53, 0x59]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order() {
        let mut v = vec!["scan10.3d", "scan2.3d", "scan002.3d", "a.pcd", "scan1.3d"];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            v,
            ["a.pcd", "scan1.3d", "scan002.3d", "scan2.3d", "scan10.3d"]
        );
    }

    #[test]
    fn classify_by_extension() {
        assert!(matches!(
            classify(Path::new("a/x.PCD.gz")),
            Kind::Sweep(SweepFormat::Pcd)
        ));
        assert!(matches!(classify(Path::new("scan.dat.bz2")), Kind::Bzip2));
        assert!(matches!(classify(Path::new("scan000.pose")), Kind::Other));
        assert!(matches!(classify(Path::new("noext")), Kind::Other));
    }
}
