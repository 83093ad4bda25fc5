//! PLY point clouds: export of voxel maps and of registered points, and a fast
//! reader for the `x y z` of the `vertex` element of any PLY file.
//!
//! Exports are binary little-endian. The header is written with ply-rs-bw's
//! [`Writer`] (so its types describe the layout and its parser reads our files
//! back); the body is written directly, because ply-rs-bw's generic element is
//! a string-keyed map, far too slow for millions of voxels.
//!
//! The reader parses the header itself and reads the body straight into
//! `[f32; 3]`, for ascii, binary little-endian and binary big-endian files with
//! any other elements (faces, ...) and properties (colours, normals, ...) before
//! or after the vertices. Byte offsets in its errors count bytes of the
//! decompressed file when the input is gzip-compressed.

use crate::error::{Error, Location, Result};
use crate::io::source::read_bytes;
use ply_rs_bw::ply::{
    Addable, DefaultElement, ElementDef, Encoding, Header, PropertyDef, PropertyType, ScalarType,
};
use ply_rs_bw::writer::Writer;
use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// One occupied voxel of an exported 3-D map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelPoint {
    /// Voxel centre in the map frame: metres, right-handed, z up.
    pub position: [f32; 3],
    /// Penetration density ρ of the voxel, in stops per metre of beam path
    /// (hits / distance travelled inside the voxel).
    pub density: f32,
    /// Number of beam endpoints (hits) recorded in the voxel.
    pub hits: u32,
}

/// Bytes per vertex of a voxel export: x y z density (4 × f32) + hits (u32).
const VOXEL_RECORD: usize = 20;
/// Bytes per vertex of a point export: x y z (3 × f32).
const POINT_RECORD: usize = 12;

/// Writes `voxels` to `path` as a binary little-endian PLY with one `vertex`
/// element of properties `x y z` (float, metres, map frame), `density` (float,
/// 1/m) and `hits` (uint).
///
/// The file is written under a temporary name beside `path` and renamed when
/// complete, so a reader never sees a half-written map. A non-finite position
/// or density is refused (`Error::Invalid`), because viewers and our own
/// reader would treat it as a point at infinity.
pub fn write_voxel_ply(path: &Path, voxels: &[VoxelPoint]) -> Result<()> {
    if let Some(i) = voxels
        .iter()
        .position(|v| !v.position.iter().all(|c| c.is_finite()) || !v.density.is_finite())
    {
        return Err(Error::Invalid(format!(
            "{}: voxel {i} has a non-finite position or density ({:?}); nothing written",
            path.display(),
            voxels[i]
        )));
    }
    let header = vertex_header(
        voxels.len(),
        &[
            ("x", ScalarType::Float),
            ("y", ScalarType::Float),
            ("z", ScalarType::Float),
            ("density", ScalarType::Float),
            ("hits", ScalarType::UInt),
        ],
        &[
            "dpslam voxel map: x y z = voxel centre, map frame, metres, right-handed, z up",
            "density = stops per metre of beam path (1/m); hits = beam endpoints in the voxel",
        ],
    );
    write_atomic(path, |w| {
        write_header(w, &header)?;
        for v in voxels {
            let mut rec = [0u8; VOXEL_RECORD];
            rec[0..4].copy_from_slice(&v.position[0].to_le_bytes());
            rec[4..8].copy_from_slice(&v.position[1].to_le_bytes());
            rec[8..12].copy_from_slice(&v.position[2].to_le_bytes());
            rec[12..16].copy_from_slice(&v.density.to_le_bytes());
            rec[16..20].copy_from_slice(&v.hits.to_le_bytes());
            w.write_all(&rec)?;
        }
        Ok(())
    })
}

/// Writes `points` (metres; in whatever frame the caller registered them,
/// normally the map frame) to `path` as a binary little-endian PLY with one
/// `vertex` element of float properties `x y z`.
///
/// Written under a temporary name and renamed when complete. Non-finite
/// coordinates are refused (`Error::Invalid`): drop "no return" points first.
pub fn write_points_ply(path: &Path, points: &[[f32; 3]]) -> Result<()> {
    if let Some(i) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(Error::Invalid(format!(
            "{}: point {i} has a non-finite coordinate ({:?}); nothing written",
            path.display(),
            points[i]
        )));
    }
    let header = vertex_header(
        points.len(),
        &[
            ("x", ScalarType::Float),
            ("y", ScalarType::Float),
            ("z", ScalarType::Float),
        ],
        &["dpslam registered points: x y z in metres, right-handed, z up"],
    );
    write_atomic(path, |w| {
        write_header(w, &header)?;
        for p in points {
            let mut rec = [0u8; POINT_RECORD];
            rec[0..4].copy_from_slice(&p[0].to_le_bytes());
            rec[4..8].copy_from_slice(&p[1].to_le_bytes());
            rec[8..12].copy_from_slice(&p[2].to_le_bytes());
            w.write_all(&rec)?;
        }
        Ok(())
    })
}

/// Reads the `x y z` properties of the `vertex` element of the PLY file at
/// `path` (plain or gzip), in file order and as stored: no point is dropped or
/// transformed, doubles are narrowed to `f32`, NaN stays NaN.
///
/// Supports ascii, binary little- and big-endian, any scalar type for `x y z`
/// and any other elements or properties, which are skipped. A header or body
/// that does not match (truncated data, wrong counts, non-numbers, data past
/// the last declared element) is an error naming the line or byte offset.
pub fn read_ply_points(path: &Path) -> Result<Vec<[f32; 3]>> {
    struct Raw(Vec<[f32; 3]>);
    impl VertexSink for Raw {
        fn reserve(&mut self, n: usize) {
            self.0.reserve(n);
        }
        fn vertex(&mut self, p: [f64; 3], _: Location) -> Result<()> {
            self.0.push([p[0] as f32, p[1] as f32, p[2] as f32]);
            Ok(())
        }
    }
    let bytes = read_bytes(path)?;
    let mut out = Raw(Vec::new());
    parse_ply_xyz(path, &bytes, &mut out)?;
    Ok(out.0)
}

/// Receives the vertices found by [`parse_ply_xyz`].
pub(crate) trait VertexSink {
    /// Called once before the first vertex with the number of vertices the
    /// header declares (capped by what the file's size could hold, so that a
    /// corrupt count cannot trigger a huge allocation).
    fn reserve(&mut self, _n: usize) {}
    /// One vertex's `x y z` as stored, and where it was found.
    fn vertex(&mut self, p: [f64; 3], at: Location) -> Result<()>;
}

/// Parses the PLY file `bytes` (already decompressed) read from `path`, and
/// gives `sink` the `x y z` of every vertex, in file order, with where the
/// vertex was found (its line for ascii, the byte offset of its record for
/// binary). Returns the number of vertices.
pub(crate) fn parse_ply_xyz<S: VertexSink>(
    path: &Path,
    bytes: &[u8],
    sink: &mut S,
) -> Result<usize> {
    if bytes.is_empty() {
        return Err(Error::in_file(path, "empty file"));
    }
    let header = parse_header(path, bytes)?;
    let vertex = header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| Error::in_file(path, "no 'vertex' element in the header"))?;
    let el = &header.elements[vertex];
    let mut xyz_idx = [0usize; 3];
    for (k, name) in ["x", "y", "z"].iter().enumerate() {
        let i = el
            .props
            .iter()
            .position(|(n, _)| n == name)
            .ok_or_else(|| {
                Error::at_line(
                    path,
                    el.line,
                    format!("element 'vertex' has no property '{name}'"),
                )
            })?;
        if matches!(el.props[i].1, Prop::List(..)) {
            return Err(Error::at_line(
                path,
                el.line,
                format!("vertex property '{name}' is a list, not a scalar"),
            ));
        }
        xyz_idx[k] = i;
    }
    // Binary vertices take at least 3 bytes, ascii ones at least 6.
    sink.reserve(el.count.min(bytes.len() / 3));
    match header.format {
        Format::Ascii => parse_ascii_body(path, bytes, &header, vertex, xyz_idx, sink),
        Format::BinaryLe => parse_binary_body(path, bytes, &header, vertex, xyz_idx, false, sink),
        Format::BinaryBe => parse_binary_body(path, bytes, &header, vertex, xyz_idx, true, sink),
    }
}

/// A ply-rs-bw header with one binary little-endian `vertex` element.
fn vertex_header(count: usize, props: &[(&str, ScalarType)], comments: &[&str]) -> Header {
    let mut header = Header::new();
    header.encoding = Encoding::BinaryLittleEndian;
    header.comments = comments.iter().map(|c| c.to_string()).collect();
    let mut el = ElementDef::new("vertex".to_string());
    el.count = count;
    for (name, ty) in props {
        el.properties.add(PropertyDef::new(
            name.to_string(),
            PropertyType::Scalar(ty.clone()),
        ));
    }
    header.elements.add(el);
    header
}

fn write_header<W: Write>(w: &mut W, header: &Header) -> std::io::Result<()> {
    Writer::<DefaultElement>::new()
        .write_header(w, header)
        .map(|_| ())
}

/// Distinguishes temporary files of concurrent writers in one process.
static TMP_SEQ: AtomicU64 = AtomicU64::new(0);

/// Writes a file through `body` under a temporary name in the target's
/// directory, then renames it over `path` (atomic on POSIX file systems).
fn write_atomic(
    path: &Path,
    body: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::Invalid(format!("{}: not a file path", path.display())))?;
    let tmp: PathBuf = path.with_file_name(format!(
        ".{}.tmp{}-{}",
        name.to_string_lossy(),
        std::process::id(),
        TMP_SEQ.fetch_add(1, Ordering::Relaxed)
    ));
    let written = (|| -> std::io::Result<()> {
        let mut w = BufWriter::with_capacity(1 << 20, File::create(&tmp)?);
        body(&mut w)?;
        let f = w.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()
    })();
    let renamed = written.and_then(|()| fs::rename(&tmp, path));
    renamed.map_err(|e| {
        // Best effort: a leftover temporary file is only litter, the error
        // that matters is the one reported.
        let _ = fs::remove_file(&tmp);
        Error::io(path, e)
    })
}

// ---------------------------------------------------------------- reading ---

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn from_name(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// Decodes a value from exactly `self.size()` bytes.
    fn decode(self, b: &[u8], big: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().expect("caller checked the length");
                if big {
                    <$t>::from_be_bytes(a) as f64
                } else {
                    <$t>::from_le_bytes(a) as f64
                }
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => get!(i16, 2),
            Scalar::U16 => get!(u16, 2),
            Scalar::I32 => get!(i32, 4),
            Scalar::U32 => get!(u32, 4),
            Scalar::F32 => get!(f32, 4),
            Scalar::F64 => get!(f64, 8),
        }
    }
}

#[derive(Debug, Clone, Copy)]
enum Prop {
    Scalar(Scalar),
    /// Count type, item type.
    List(Scalar, Scalar),
}

#[derive(Debug)]
struct ElementSpec {
    name: String,
    count: usize,
    props: Vec<(String, Prop)>,
    /// Header line that declared the element.
    line: usize,
}

#[derive(Debug)]
struct PlyHeader {
    format: Format,
    elements: Vec<ElementSpec>,
    /// Byte offset of the first body byte.
    body_start: usize,
    /// Line number of the first body line (ascii bodies).
    body_line: usize,
}

/// Splits `bytes[start..]` into lines: (1-based number, offset of the line,
/// content without `\r\n`), numbering from `first_line`.
pub(crate) fn lines_from(
    bytes: &[u8],
    start: usize,
    first_line: usize,
) -> impl Iterator<Item = (usize, usize, &[u8])> {
    let mut pos = start;
    let mut no = first_line;
    std::iter::from_fn(move || {
        if pos >= bytes.len() {
            return None;
        }
        let begin = pos;
        let end = match bytes[pos..].iter().position(|&c| c == b'\n') {
            Some(i) => pos + i,
            None => bytes.len(),
        };
        pos = end + 1;
        let line = no;
        no += 1;
        let mut content = &bytes[begin..end];
        if let Some(stripped) = content.strip_suffix(b"\r") {
            content = stripped;
        }
        Some((line, begin, content))
    })
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<PlyHeader> {
    let mut format = None;
    let mut elements: Vec<ElementSpec> = Vec::new();
    for (no, begin, raw) in lines_from(bytes, 0, 1) {
        let text = std::str::from_utf8(raw)
            .map_err(|_| Error::at_line(path, no, "header line is not text"))?;
        let mut tok = text.split_ascii_whitespace();
        let key = tok.next().unwrap_or("");
        if no == 1 {
            if key != "ply" {
                return Err(Error::at_line(
                    path,
                    1,
                    "not a PLY file: first line is not 'ply'",
                ));
            }
            continue;
        }
        match key {
            "" | "comment" | "obj_info" => {}
            "format" => {
                format = Some(match tok.next() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::BinaryLe,
                    Some("binary_big_endian") => Format::BinaryBe,
                    other => {
                        return Err(Error::at_line(
                            path,
                            no,
                            format!("unknown PLY format {:?}", other.unwrap_or("")),
                        ));
                    }
                });
            }
            "element" => {
                let name = tok
                    .next()
                    .ok_or_else(|| Error::at_line(path, no, "element without a name"))?;
                let count = tok
                    .next()
                    .and_then(|c| c.parse::<usize>().ok())
                    .ok_or_else(|| {
                        Error::at_line(path, no, format!("element '{name}' has no valid count"))
                    })?;
                elements.push(ElementSpec {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                    line: no,
                });
            }
            "property" => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| Error::at_line(path, no, "property before any element"))?;
                let words: Vec<&str> = tok.collect();
                let bad = || Error::at_line(path, no, format!("malformed property line '{text}'"));
                let ty = |s: &str| {
                    Scalar::from_name(s).ok_or_else(|| {
                        Error::at_line(path, no, format!("unknown property type '{s}'"))
                    })
                };
                let (name, prop) = match words.as_slice() {
                    ["list", ct, it, name] => {
                        let ct = ty(ct)?;
                        if !ct.is_integer() {
                            return Err(Error::at_line(
                                path,
                                no,
                                "list count type must be an integer type",
                            ));
                        }
                        (*name, Prop::List(ct, ty(it)?))
                    }
                    [t, name] => (*name, Prop::Scalar(ty(t)?)),
                    _ => return Err(bad()),
                };
                el.props.push((name.to_string(), prop));
            }
            "end_header" => {
                let end = begin + raw.len();
                // The body starts after the line terminator (`\n` or `\r\n`).
                let body_start = bytes[end..]
                    .iter()
                    .position(|&c| c == b'\n')
                    .map_or(bytes.len(), |i| end + i + 1);
                let format =
                    format.ok_or_else(|| Error::in_file(path, "header has no 'format' line"))?;
                return Ok(PlyHeader {
                    format,
                    elements,
                    body_start,
                    body_line: no + 1,
                });
            }
            other => {
                return Err(Error::at_line(
                    path,
                    no,
                    format!("unknown PLY header keyword '{other}'"),
                ));
            }
        }
    }
    Err(Error::in_file(
        path,
        "header has no 'end_header' line (truncated or not a PLY file)",
    ))
}

fn parse_binary_body(
    path: &Path,
    bytes: &[u8],
    header: &PlyHeader,
    vertex: usize,
    xyz_idx: [usize; 3],
    big: bool,
    sink: &mut impl VertexSink,
) -> Result<usize> {
    let mut pos = header.body_start;
    let len = bytes.len();
    for (ei, el) in header.elements.iter().enumerate() {
        let is_vertex = ei == vertex;
        let fixed: Option<Vec<usize>> = el
            .props
            .iter()
            .map(|(_, p)| match p {
                Prop::Scalar(s) => Some(s.size()),
                Prop::List(..) => None,
            })
            .collect();
        if let Some(sizes) = fixed {
            // Fast path: every instance has the same size; check the whole
            // element fits before touching it.
            let stride: usize = sizes.iter().sum();
            let need = el.count.checked_mul(stride).ok_or_else(|| {
                Error::at_line(
                    path,
                    el.line,
                    format!("element '{}' count too large", el.name),
                )
            })?;
            if len - pos < need {
                let k = (len - pos) / stride.max(1);
                return Err(Error::at_byte(
                    path,
                    (pos + k * stride) as u64,
                    format!(
                        "binary data truncated: file ends at byte {len} inside {} {k} of {} \
                         ({stride} bytes each)",
                        el.name, el.count
                    ),
                ));
            }
            if is_vertex {
                let mut offs = [0usize; 3];
                let mut tys = [Scalar::F32; 3];
                for k in 0..3 {
                    offs[k] = sizes[..xyz_idx[k]].iter().sum();
                    if let Prop::Scalar(s) = el.props[xyz_idx[k]].1 {
                        tys[k] = s;
                    }
                }
                for i in 0..el.count {
                    let base = pos + i * stride;
                    let rec = &bytes[base..base + stride];
                    let p = [
                        tys[0].decode(&rec[offs[0]..], big),
                        tys[1].decode(&rec[offs[1]..], big),
                        tys[2].decode(&rec[offs[2]..], big),
                    ];
                    sink.vertex(p, Location::Byte(base as u64))?;
                }
            }
            pos += need;
        } else {
            // Elements with list properties: walk every instance.
            for i in 0..el.count {
                let base = pos;
                let mut p = [0.0f64; 3];
                for (pi, (pname, prop)) in el.props.iter().enumerate() {
                    let truncated = |at: usize| {
                        Error::at_byte(
                            path,
                            at as u64,
                            format!(
                                "binary data truncated: file ends at byte {len} inside {} {i} \
                                 of {} (property '{pname}')",
                                el.name, el.count
                            ),
                        )
                    };
                    match *prop {
                        Prop::Scalar(s) => {
                            if len - pos < s.size() {
                                return Err(truncated(base));
                            }
                            if is_vertex && let Some(k) = xyz_idx.iter().position(|&x| x == pi) {
                                p[k] = s.decode(&bytes[pos..], big);
                            }
                            pos += s.size();
                        }
                        Prop::List(ct, it) => {
                            if len - pos < ct.size() {
                                return Err(truncated(base));
                            }
                            let n = ct.decode(&bytes[pos..], big);
                            if n < 0.0 {
                                return Err(Error::at_byte(
                                    path,
                                    pos as u64,
                                    format!("negative list length {n} in '{pname}'"),
                                ));
                            }
                            pos += ct.size();
                            let body = (n as usize) * it.size();
                            if len - pos < body {
                                return Err(truncated(base));
                            }
                            pos += body;
                        }
                    }
                }
                if is_vertex {
                    sink.vertex(p, Location::Byte(base as u64))?;
                }
            }
        }
    }
    if pos < len {
        return Err(Error::at_byte(
            path,
            pos as u64,
            format!(
                "{} bytes after the last declared element (header counts too small?)",
                len - pos
            ),
        ));
    }
    Ok(header.elements[vertex].count)
}

fn parse_ascii_body(
    path: &Path,
    bytes: &[u8],
    header: &PlyHeader,
    vertex: usize,
    xyz_idx: [usize; 3],
    sink: &mut impl VertexSink,
) -> Result<usize> {
    let mut lines = lines_from(bytes, header.body_start, header.body_line)
        .filter(|(_, _, l)| !l.iter().all(|c| c.is_ascii_whitespace()));
    let mut last_line = header.body_line.saturating_sub(1);
    for (ei, el) in header.elements.iter().enumerate() {
        let is_vertex = ei == vertex;
        for i in 0..el.count {
            let (no, _, raw) = lines.next().ok_or_else(|| {
                Error::at_line(
                    path,
                    last_line,
                    format!("file ends after {i} of {} '{}' elements", el.count, el.name),
                )
            })?;
            last_line = no;
            let text = std::str::from_utf8(raw)
                .map_err(|_| Error::at_line(path, no, "line is not text"))?;
            let mut tok = text.split_ascii_whitespace();
            let mut p = [0.0f64; 3];
            for (pi, (pname, prop)) in el.props.iter().enumerate() {
                let mut next = || {
                    tok.next().ok_or_else(|| {
                        Error::at_line(
                            path,
                            no,
                            format!("too few values for {} {i}: missing '{pname}'", el.name),
                        )
                    })
                };
                match *prop {
                    Prop::Scalar(_) => {
                        let t = next()?;
                        if is_vertex && let Some(k) = xyz_idx.iter().position(|&x| x == pi) {
                            p[k] = t.parse::<f64>().map_err(|_| {
                                Error::at_line(path, no, format!("{pname}: '{t}' is not a number"))
                            })?;
                        }
                    }
                    Prop::List(..) => {
                        let t = next()?;
                        let n = t.parse::<usize>().map_err(|_| {
                            Error::at_line(
                                path,
                                no,
                                format!("list length of '{pname}': '{t}' is not a count"),
                            )
                        })?;
                        for _ in 0..n {
                            next()?;
                        }
                    }
                }
            }
            if tok.next().is_some() {
                return Err(Error::at_line(
                    path,
                    no,
                    format!("more values than the properties of '{}'", el.name),
                ));
            }
            if is_vertex {
                sink.vertex(p, Location::Line(no))?;
            }
        }
    }
    if let Some((no, _, _)) = lines.next() {
        return Err(Error::at_line(
            path,
            no,
            "data after the last declared element (header counts too small?)",
        ));
    }
    Ok(header.elements[vertex].count)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(bytes: &[u8]) -> Result<Vec<[f64; 3]>> {
        struct All(Vec<[f64; 3]>);
        impl VertexSink for All {
            fn vertex(&mut self, p: [f64; 3], _: Location) -> Result<()> {
                self.0.push(p);
                Ok(())
            }
        }
        let mut v = All(Vec::new());
        parse_ply_xyz(Path::new("t.ply"), bytes, &mut v)?;
        Ok(v.0)
    }

    #[test]
    fn ascii_with_faces_before_vertices_and_extra_properties() {
        let text = b"ply\r\nformat ascii 1.0\r\ncomment x\r\nelement face 2\r\n\
property list uchar int vertex_indices\r\nelement vertex 2\r\nproperty uchar red\r\n\
property double z\r\nproperty float x\r\nproperty float y\r\nend_header\r\n\
3 0 1 2\r\n0\r\n7 3.5 1 2\r\n8 -1e3 4 5\r\n";
        assert_eq!(
            parse(text).unwrap(),
            vec![[1.0, 2.0, 3.5], [4.0, 5.0, -1000.0]]
        );
    }

    #[test]
    fn binary_big_endian_with_list_element_and_double() {
        let mut b = b"ply\nformat binary_big_endian 1.0\nelement vertex 2\n\
property double x\nproperty double y\nproperty double z\nelement face 1\n\
property list uchar uint idx\nend_header\n"
            .to_vec();
        for v in [1.5f64, -2.0, 3.25, 4.0, 5.0, 6.0] {
            b.extend_from_slice(&v.to_be_bytes());
        }
        b.push(2);
        b.extend_from_slice(&0u32.to_be_bytes());
        b.extend_from_slice(&1u32.to_be_bytes());
        assert_eq!(parse(&b).unwrap(), vec![[1.5, -2.0, 3.25], [4.0, 5.0, 6.0]]);
        // Cut inside the face list: still an error although the vertices are whole.
        let err = parse(&b[..b.len() - 2]).unwrap_err().to_string();
        assert!(err.contains("truncated") && err.contains("face 0"), "{err}");
        // One byte too many.
        let mut long = b.clone();
        long.push(0);
        let err = parse(&long).unwrap_err().to_string();
        assert!(err.contains(&format!("byte {}", b.len())), "{err}");
    }

    #[test]
    fn truncated_binary_vertex_names_byte_offset_of_the_cut_record() {
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n\
property float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
        let start = b.len();
        for v in 0..8 {
            b.extend_from_slice(&(v as f32).to_le_bytes());
        }
        let err = parse(&b).unwrap_err().to_string();
        assert!(err.contains(&format!("byte {}", start + 24)), "{err}");
        assert!(err.contains("vertex 2 of 3"), "{err}");
    }

    #[test]
    fn header_errors_name_lines() {
        let e = parse(b"plx\n").unwrap_err().to_string();
        assert!(e.contains("line 1"), "{e}");
        let e = parse(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty flt x\nend_header\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 4") && e.contains("flt"), "{e}");
        let e = parse(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("end_header"), "{e}");
        let e = parse(
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("line 3") && e.contains("'z'"), "{e}");
    }

    #[test]
    fn ascii_count_mismatches_are_errors_with_lines() {
        let h = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n\
property float y\nproperty float z\nend_header\n";
        let short = format!("{h}1 2 3\n");
        let e = parse(short.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("1 of 2"), "{e}");
        let long = format!("{h}1 2 3\n4 5 6\n7 8 9\n");
        let e = parse(long.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("line 10"), "{e}");
        let bad = format!("{h}1 2 3\n4 five 6\n");
        let e = parse(bad.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("line 9") && e.contains("five"), "{e}");
    }

    #[test]
    fn export_refuses_non_finite_and_leaves_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.ply");
        assert!(write_points_ply(&p, &[[0.0, f32::NAN, 0.0]]).is_err());
        let v = VoxelPoint {
            position: [0.0; 3],
            density: f32::INFINITY,
            hits: 1,
        };
        assert!(write_voxel_ply(&p, &[v]).is_err());
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn export_into_missing_directory_is_an_io_error_naming_the_path() {
        let p = Path::new("/nonexistent-dpslam-dir/x.ply");
        let e = write_points_ply(p, &[[1.0, 2.0, 3.0]])
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent-dpslam-dir/x.ply"), "{e}");
    }

    #[test]
    fn voxel_export_round_trips_through_our_reader_with_exact_layout() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.ply");
        let vox: Vec<VoxelPoint> = (0..1000)
            .map(|i| VoxelPoint {
                position: [i as f32 * 0.05, -(i as f32), 1.0 / (i as f32 + 1.0)],
                density: i as f32 * 0.5,
                hits: i * 3,
            })
            .collect();
        write_voxel_ply(&p, &vox).unwrap();
        let bytes = fs::read(&p).unwrap();
        let body = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        assert_eq!(bytes.len() - body, vox.len() * VOXEL_RECORD);
        let last = &bytes[bytes.len() - 4..];
        assert_eq!(u32::from_le_bytes(last.try_into().unwrap()), 999 * 3);
        let pts = read_ply_points(&p).unwrap();
        assert_eq!(pts.len(), vox.len());
        for (a, b) in pts.iter().zip(&vox) {
            assert_eq!(*a, b.position);
        }
    }
}
