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

use crate::error::{Error, Location, Result};
use crate::geometry::Pose3;
use crate::io::ply::{VertexSink, lines_from, parse_ply_xyz};
use crate::io::source::read_bytes;
use nalgebra::{Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
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
    let mut prior = None;
    let points = match format {
        SweepFormat::Pcd => {
            let (points, viewpoint) = read_pcd(path, &bytes)?;
            prior = viewpoint;
            points
        }
        SweepFormat::Ply => {
            let mut c = Collector::new(path, identity);
            parse_ply_xyz(path, &bytes, &mut c)?;
            c.finish()?
        }
        SweepFormat::KittiBin => read_kitti(path, &bytes)?,
        SweepFormat::Text => {
            let mut c = Collector::new(path, identity);
            parse_xyz_lines(path, &bytes, false, &mut c)?;
            c.finish()?
        }
        SweepFormat::Vtk => read_vtk(path, &bytes)?,
        SweepFormat::ThreeDtk => {
            let mut c = Collector::new(path, threedtk_point);
            parse_xyz_lines(path, &bytes, true, &mut c)?;
            prior = threedtk_pose_file(path)?;
            c.finish()?
        }
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

// ------------------------------------------------------------------ 3DTK ---

/// Converts a 3DTK point (centimetres, left-handed, y up, z forward) into
/// metres, right-handed, z up, x forward: `(x, y, z) → (z, −x, y) / 100`.
///
/// This is the inverse of 3DTK's own `ScanDataTransform_xyz`
/// (`src/scanio/helper.cc`), which maps right-handed z-up metres into its
/// convention as `(x, y, z) → (−100·y, 100·z, 100·x)`.
pub fn threedtk_point(p: [f64; 3]) -> [f64; 3] {
    [p[2] / 100.0, -p[0] / 100.0, p[1] / 100.0]
}

/// Converts a 3DTK `.pose` (position `t` in centimetres, Euler angles
/// `rx ry rz` in degrees, both in 3DTK's left-handed y-up frame) into a pose in
/// the converted frame of [`threedtk_point`].
///
/// 3DTK builds the scan-to-world matrix with `EulerToMatrix4`
/// (`include/slam6d/globals.icc`): `M = Rx(rx)·Ry(ry)·Rz(rz)` with the usual
/// right-hand-rule rotation matrices written in 3DTK's coordinates, and maps a
/// point as `w = M·p + t`. With `C` the linear part of [`threedtk_point`]
/// (`C·p = (z, −x, y)`, a reflection, det −1), the converted world point is
/// `C·w/100 = (C·M·Cᵀ)(C·p/100) + C·t/100`. So the converted pose has
/// rotation `C·M·Cᵀ` (a proper rotation) and translation `C·t/100`.
/// Conjugating by the reflection `C` turns a rotation by θ about axis `a` into
/// a rotation by θ about `−C·a`, hence
/// `C·M·Cᵀ = Ry(rx)·Rz(−ry)·Rx(−rz)` in the converted frame: 3DTK's yaw about
/// its up axis `ry` becomes a yaw of `−ry` about z.
pub fn threedtk_pose(t_cm: [f64; 3], angles_deg: [f64; 3]) -> Pose3 {
    let [rx, ry, rz] = angles_deg.map(f64::to_radians);
    let q = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), rx)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -ry)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -rz);
    let t = threedtk_point(t_cm);
    Pose3::from_parts(Translation3::new(t[0], t[1], t[2]), q)
}

/// The path of the `.pose` file of a `.3d` scan, if one exists.
fn threedtk_pose_path(scan: &Path) -> Option<PathBuf> {
    let name = scan.file_name()?.to_string_lossy().into_owned();
    let lower = name.to_ascii_lowercase();
    let stem_len = lower
        .strip_suffix(".gz")
        .unwrap_or(&lower)
        .strip_suffix(".3d")?
        .len();
    let stem = &name[..stem_len];
    [".pose", ".pose.gz"]
        .iter()
        .map(|s| scan.with_file_name(format!("{stem}{s}")))
        .find(|p| p.is_file())
}

/// Reads the `.pose` beside a `.3d` scan: six numbers `x y z` (cm) and
/// `rx ry rz` (degrees), normally on two lines.
fn threedtk_pose_file(scan: &Path) -> Result<Option<Pose3>> {
    let Some(path) = threedtk_pose_path(scan) else {
        return Ok(None);
    };
    let bytes = read_bytes(&path)?;
    let mut vals = Vec::with_capacity(6);
    let mut last = 0;
    for (no, _, raw) in lines_from(&bytes, 0, 1) {
        last = no;
        let text =
            std::str::from_utf8(raw).map_err(|_| Error::at_line(&path, no, "line is not text"))?;
        for t in text.split_ascii_whitespace() {
            let v: f64 = t
                .parse()
                .map_err(|_| Error::at_line(&path, no, format!("'{t}' is not a number")))?;
            if !v.is_finite() {
                return Err(Error::at_line(
                    &path,
                    no,
                    format!("non-finite pose value '{t}'"),
                ));
            }
            if vals.len() == 6 {
                return Err(Error::at_line(
                    &path,
                    no,
                    "more than 6 numbers: expected 'x y z' (cm) and 'rx ry rz' (degrees)",
                ));
            }
            vals.push(v);
        }
    }
    if vals.len() != 6 {
        return Err(Error::at_line(
            &path,
            last.max(1),
            format!(
                "found {} numbers, expected 6: 'x y z' (cm) and 'rx ry rz' (degrees)",
                vals.len()
            ),
        ));
    }
    Ok(Some(threedtk_pose(
        [vals[0], vals[1], vals[2]],
        [vals[3], vals[4], vals[5]],
    )))
}

// ------------------------------------------------------- point collection ---

fn identity(p: [f64; 3]) -> [f64; 3] {
    p
}

/// Applies the no-return policy and the unit/frame conversion to raw points.
struct Collector<'a> {
    path: &'a Path,
    map: fn([f64; 3]) -> [f64; 3],
    points: Vec<[f32; 3]>,
    /// Points found in the file, "no return" ones included.
    seen: usize,
}

impl<'a> Collector<'a> {
    fn new(path: &'a Path, map: fn([f64; 3]) -> [f64; 3]) -> Self {
        Self {
            path,
            map,
            points: Vec::new(),
            seen: 0,
        }
    }

    /// Takes a point as stored in the file, found at `at`.
    fn push(&mut self, raw: [f64; 3], at: Location) -> Result<()> {
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
    fn finish(self) -> Result<Vec<[f32; 3]>> {
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

// ------------------------------------------------------------------- text ---

/// Parses `x y z [more columns]` lines. Blank lines and lines starting with
/// `#` or `//` are skipped, as is anything after a `#`; fields are separated
/// by whitespace or commas. With `uos_header`, a first line `<W> x <H>` (the
/// optional header of 3DTK "uos" files) is skipped.
fn parse_xyz_lines(path: &Path, bytes: &[u8], uos_header: bool, c: &mut Collector) -> Result<()> {
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

// ------------------------------------------------------------------ KITTI ---

/// Bytes per KITTI Velodyne point: float32 x y z intensity.
const KITTI_RECORD: usize = 16;

fn read_kitti(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>> {
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

// -------------------------------------------------------------------- PCD ---

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PcdType {
    I,
    U,
    F,
}

struct PcdField {
    name: String,
    size: usize,
    ty: PcdType,
    count: usize,
}

/// Decodes a little-endian PCD scalar (size and type validated by the header parser).
fn pcd_decode(b: &[u8], ty: PcdType, size: usize) -> f64 {
    macro_rules! get {
        ($t:ty, $n:expr) => {
            <$t>::from_le_bytes(b[..$n].try_into().expect("checked length")) as f64
        };
    }
    match (ty, size) {
        (PcdType::F, 4) => get!(f32, 4),
        (PcdType::F, _) => get!(f64, 8),
        (PcdType::I, 1) => b[0] as i8 as f64,
        (PcdType::I, 2) => get!(i16, 2),
        (PcdType::I, 4) => get!(i32, 4),
        (PcdType::I, _) => get!(i64, 8),
        (PcdType::U, 1) => b[0] as f64,
        (PcdType::U, 2) => get!(u16, 2),
        (PcdType::U, 4) => get!(u32, 4),
        (PcdType::U, _) => get!(u64, 8),
    }
}

/// Reads a PCD file: the points (sensor frame) and, for a non-identity
/// `VIEWPOINT`, the sensor pose in the cloud's frame.
///
/// PCD stores points in the cloud's frame with the sensor at `VIEWPOINT`
/// (`tx ty tz qw qx qy qz`); the points are mapped into the sensor frame by
/// the inverse viewpoint so that `prior` maps them back.
fn read_pcd(path: &Path, bytes: &[u8]) -> Result<(Vec<[f32; 3]>, Option<Pose3>)> {
    let mut names: Option<(usize, Vec<String>)> = None;
    let mut sizes: Option<(usize, Vec<usize>)> = None;
    let mut types: Option<(usize, Vec<PcdType>)> = None;
    let mut counts: Option<(usize, Vec<usize>)> = None;
    let mut width: Option<usize> = None;
    let mut height: Option<usize> = None;
    let mut npoints: Option<(usize, usize)> = None;
    let mut viewpoint: Option<Pose3> = None;
    let mut data: Option<(usize, String, usize)> = None; // line, kind, body start
    for (no, begin, raw) in lines_from(bytes, 0, 1) {
        let text = std::str::from_utf8(raw)
            .map_err(|_| Error::at_line(path, no, "header line is not text"))?;
        let text = text.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let mut tok = text.split_ascii_whitespace();
        let key = tok.next().unwrap_or("").to_ascii_uppercase();
        let vals: Vec<&str> = tok.collect();
        let num = |t: &str, what: &str| {
            t.parse::<usize>().map_err(|_| {
                Error::at_line(
                    path,
                    no,
                    format!("{what}: '{t}' is not a non-negative integer"),
                )
            })
        };
        match key.as_str() {
            "VERSION" => {}
            "FIELDS" | "COLUMNS" => {
                names = Some((no, vals.iter().map(|s| s.to_string()).collect()));
            }
            "SIZE" => {
                sizes = Some((
                    no,
                    vals.iter().map(|t| num(t, "SIZE")).collect::<Result<_>>()?,
                ));
            }
            "COUNT" => {
                counts = Some((
                    no,
                    vals.iter()
                        .map(|t| num(t, "COUNT"))
                        .collect::<Result<_>>()?,
                ));
            }
            "TYPE" => {
                let ts = vals
                    .iter()
                    .map(|t| match *t {
                        "I" | "i" => Ok(PcdType::I),
                        "U" | "u" => Ok(PcdType::U),
                        "F" | "f" => Ok(PcdType::F),
                        other => Err(Error::at_line(
                            path,
                            no,
                            format!("TYPE '{other}' is not I, U or F"),
                        )),
                    })
                    .collect::<Result<_>>()?;
                types = Some((no, ts));
            }
            "WIDTH" | "HEIGHT" | "POINTS" => {
                let [v] = vals.as_slice() else {
                    return Err(Error::at_line(path, no, format!("{key} takes one value")));
                };
                let v = num(v, &key)?;
                match key.as_str() {
                    "WIDTH" => width = Some(v),
                    "HEIGHT" => height = Some(v),
                    _ => npoints = Some((no, v)),
                }
            }
            "VIEWPOINT" => {
                let v: Vec<f64> = vals
                    .iter()
                    .map(|t| t.parse::<f64>())
                    .collect::<std::result::Result<_, _>>()
                    .ok()
                    .filter(|v: &Vec<f64>| v.len() == 7 && v.iter().all(|x| x.is_finite()))
                    .ok_or_else(|| {
                        Error::at_line(
                            path,
                            no,
                            "VIEWPOINT needs 7 finite numbers: tx ty tz qw qx qy qz",
                        )
                    })?;
                let q = Quaternion::new(v[3], v[4], v[5], v[6]);
                if q.norm() < 1e-9 {
                    return Err(Error::at_line(
                        path,
                        no,
                        "VIEWPOINT quaternion has zero norm",
                    ));
                }
                let pose = Pose3::from_parts(
                    Translation3::new(v[0], v[1], v[2]),
                    UnitQuaternion::from_quaternion(q),
                );
                let is_identity =
                    pose.translation.vector.norm() < 1e-12 && pose.rotation.angle() < 1e-12;
                viewpoint = (!is_identity).then_some(pose);
            }
            "DATA" => {
                let kind = vals
                    .first()
                    .map(|s| s.to_ascii_lowercase())
                    .unwrap_or_default();
                data = Some((no, kind, begin + raw.len()));
                break;
            }
            other => {
                return Err(Error::at_line(
                    path,
                    no,
                    format!("unknown PCD header keyword '{other}' (not a PCD file?)"),
                ));
            }
        }
    }
    let (data_line, kind, data_end) = data.ok_or_else(|| {
        Error::in_file(
            path,
            "no DATA line: not a PCD file, or the header is truncated",
        )
    })?;
    // The body starts after the DATA line's terminator.
    let body = bytes[data_end..]
        .iter()
        .position(|&c| c == b'\n')
        .map_or(bytes.len(), |i| data_end + i + 1);

    let (names_line, names) =
        names.ok_or_else(|| Error::in_file(path, "header has no FIELDS line"))?;
    let nf = names.len();
    let check_len = |what: &str, line: usize, n: usize| {
        if n == nf {
            Ok(())
        } else {
            Err(Error::at_line(
                path,
                line,
                format!("{what} has {n} entries but FIELDS has {nf}"),
            ))
        }
    };
    let (sl, sizes) = sizes.ok_or_else(|| Error::in_file(path, "header has no SIZE line"))?;
    check_len("SIZE", sl, sizes.len())?;
    let (tl, types) = types.ok_or_else(|| Error::in_file(path, "header has no TYPE line"))?;
    check_len("TYPE", tl, types.len())?;
    let (cl, counts) = counts.unwrap_or((names_line, vec![1; nf]));
    check_len("COUNT", cl, counts.len())?;
    let mut fields = Vec::with_capacity(nf);
    for i in 0..nf {
        let ok = match types[i] {
            PcdType::F => matches!(sizes[i], 4 | 8),
            _ => matches!(sizes[i], 1 | 2 | 4 | 8),
        };
        if !ok {
            return Err(Error::at_line(
                path,
                sl,
                format!(
                    "field '{}': SIZE {} is invalid for its TYPE",
                    names[i], sizes[i]
                ),
            ));
        }
        if counts[i] == 0 {
            return Err(Error::at_line(
                path,
                cl,
                format!("field '{}': COUNT 0", names[i]),
            ));
        }
        fields.push(PcdField {
            name: names[i].clone(),
            size: sizes[i],
            ty: types[i],
            count: counts[i],
        });
    }
    let mut xyz = [0usize; 3];
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        let i = fields
            .iter()
            .position(|f| f.name == *axis)
            .ok_or_else(|| Error::at_line(path, names_line, format!("FIELDS has no '{axis}'")))?;
        if fields[i].count != 1 {
            return Err(Error::at_line(
                path,
                cl,
                format!("field '{axis}' must have COUNT 1"),
            ));
        }
        xyz[k] = i;
    }
    let wh = match (width, height) {
        (Some(w), Some(h)) => w.checked_mul(h),
        (Some(w), None) => Some(w),
        _ => None,
    };
    let n = match (npoints, wh) {
        (Some((line, p)), Some(wh)) if p != wh => {
            return Err(Error::at_line(
                path,
                line,
                format!("POINTS {p} differs from WIDTH × HEIGHT = {wh}"),
            ));
        }
        (Some((_, p)), _) => p,
        (None, Some(wh)) => wh,
        (None, None) => {
            return Err(Error::in_file(path, "header has neither POINTS nor WIDTH"));
        }
    };
    if n == 0 {
        return Err(Error::in_file(path, "header declares no points"));
    }

    let mut c = Collector::new(path, identity);
    match kind.as_str() {
        "binary" => {
            let record: usize = fields.iter().map(|f| f.size * f.count).sum();
            let offset = |i: usize| -> usize { fields[..i].iter().map(|f| f.size * f.count).sum() };
            let offs = xyz.map(offset);
            let need = n.checked_mul(record).ok_or_else(|| {
                Error::in_file(path, format!("POINTS {n} × {record} bytes overflows"))
            })?;
            let avail = bytes.len() - body;
            if avail < need {
                let k = avail / record;
                return Err(Error::at_byte(
                    path,
                    (body + k * record) as u64,
                    format!(
                        "binary data truncated: file ends at byte {} inside point {k} of {n} \
                         ({record} bytes per point)",
                        bytes.len()
                    ),
                ));
            }
            if avail > need {
                return Err(Error::at_byte(
                    path,
                    (body + need) as u64,
                    format!(
                        "{} bytes after the last of the {n} declared points \
                         (POINTS/SIZE/COUNT wrong?)",
                        avail - need
                    ),
                ));
            }
            c.points.reserve(n);
            for i in 0..n {
                let base = body + i * record;
                let get = |k: usize| {
                    let f = &fields[xyz[k]];
                    pcd_decode(&bytes[base + offs[k]..], f.ty, f.size)
                };
                c.push([get(0), get(1), get(2)], Location::Byte(base as u64))?;
            }
        }
        "ascii" => {
            let columns: usize = fields.iter().map(|f| f.count).sum();
            let col = xyz.map(|i| fields[..i].iter().map(|f| f.count).sum::<usize>());
            let mut k = 0usize;
            let mut last = data_line;
            for (no, _, raw) in lines_from(bytes, body, data_line + 1) {
                last = no;
                let text = std::str::from_utf8(raw)
                    .map_err(|_| Error::at_line(path, no, "line is not text"))?;
                if text.trim().is_empty() {
                    continue;
                }
                if k == n {
                    return Err(Error::at_line(
                        path,
                        no,
                        format!("more data lines than the {n} declared points"),
                    ));
                }
                let toks: Vec<&str> = text.split_ascii_whitespace().collect();
                if toks.len() != columns {
                    return Err(Error::at_line(
                        path,
                        no,
                        format!("{} values, expected {columns} (FIELDS × COUNT)", toks.len()),
                    ));
                }
                let mut p = [0.0f64; 3];
                for a in 0..3 {
                    let t = toks[col[a]];
                    p[a] = t.parse().map_err(|_| {
                        Error::at_line(
                            path,
                            no,
                            format!("{}: '{t}' is not a number", ["x", "y", "z"][a]),
                        )
                    })?;
                }
                c.push(p, Location::Line(no))?;
                k += 1;
            }
            if k < n {
                return Err(Error::at_line(
                    path,
                    last,
                    format!("file ends after {k} of the {n} declared points"),
                ));
            }
        }
        "binary_compressed" => {
            return Err(Error::at_line(
                path,
                data_line,
                "DATA binary_compressed is not supported: convert to binary first, \
                 e.g. `pcl_convert_pcd_ascii_binary in.pcd out.pcd 1`",
            ));
        }
        other => {
            return Err(Error::at_line(
                path,
                data_line,
                format!("unknown DATA kind '{other}' (expected ascii or binary)"),
            ));
        }
    }
    let mut points = c.finish()?;
    if let Some(v) = viewpoint {
        let inv = v.inverse();
        for p in &mut points {
            let q = inv * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            *p = [q.x as f32, q.y as f32, q.z as f32];
        }
    }
    Ok((points, viewpoint))
}

// -------------------------------------------------------------------- VTK ---

/// Reads the `POINTS` of a legacy ASCII VTK file; other sections (VERTICES,
/// POINT_DATA, ...) are ignored.
fn read_vtk(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    /// 3DTK's `EulerToMatrix4` rotation, transcribed element by element from
    /// its column-major `alignxf` (angles in radians).
    fn threedtk_matrix(rx: f64, ry: f64, rz: f64) -> Matrix3<f64> {
        let (sx, cx) = rx.sin_cos();
        let (sy, cy) = ry.sin_cos();
        let (sz, cz) = rz.sin_cos();
        let a = [
            cy * cz,
            sx * sy * cz + cx * sz,
            -cx * sy * cz + sx * sz,
            -cy * sz,
            -sx * sy * sz + cx * cz,
            cx * sy * sz + sx * cz,
            sy,
            -sx * cy,
            cx * cy,
        ];
        Matrix3::from_column_slice(&a)
    }

    #[test]
    fn threedtk_pose_matches_conjugated_euler_matrix_of_3dtk() {
        let c = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, 1.0, 0.0);
        for (rx, ry, rz) in [
            (10.0, 0.0, 0.0),
            (0.0, 25.0, 0.0),
            (0.0, 0.0, -40.0),
            (1.3569, -0.8524, -0.5622),
            (30.0, -70.0, 120.0),
        ] {
            let m = threedtk_matrix(
                f64::to_radians(rx),
                f64::to_radians(ry),
                f64::to_radians(rz),
            );
            let want = c * m * c.transpose();
            let got = threedtk_pose([1.0, 2.0, 3.0], [rx, ry, rz]);
            let r = got.rotation.to_rotation_matrix();
            assert!((r.matrix() - want).norm() < 1e-12, "angles {rx} {ry} {rz}");
            // And the whole map agrees on a point: C(M p + t)/100 == pose(C p/100).
            let p = [37.0, -12.0, 250.0];
            let w = m * Vector3::new(p[0], p[1], p[2]) + Vector3::new(1.0, 2.0, 3.0);
            let want_w = threedtk_point([w.x, w.y, w.z]);
            let q = threedtk_point(p);
            let got_w = got * Point3::new(q[0], q[1], q[2]);
            for k in 0..3 {
                assert!((got_w[k] - want_w[k]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn threedtk_point_is_rh_z_up_metres() {
        // 3DTK: x right, y up, z forward (cm) -> x forward, y left, z up (m).
        assert_eq!(threedtk_point([0.0, 0.0, 100.0]), [1.0, 0.0, 0.0]);
        assert_eq!(threedtk_point([100.0, 0.0, 0.0]), [0.0, -1.0, 0.0]);
        assert_eq!(threedtk_point([0.0, 100.0, 0.0]), [0.0, 0.0, 1.0]);
    }

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

    #[test]
    fn uos_header_detection() {
        assert!(is_uos_header("361 x 226"));
        assert!(!is_uos_header("361 x 226 1"));
        assert!(!is_uos_header("10.1 0 0"));
    }
}
