//! Point Cloud Library sweeps (`.pcd`), version 0.5–0.7, `DATA ascii` or
//! `binary`.

use super::collector::{Collector, identity};
use crate::error::{Error, Location, Result};
use crate::geometry::Pose3;
use crate::io::ply::lines_from;
use nalgebra::{Point3, Quaternion, Translation3, UnitQuaternion};
use std::path::Path;

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
pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<(Vec<[f32; 3]>, Option<Pose3>)> {
    let header = Header::parse(path, bytes)?;
    let layout = Layout::of(path, &header)?;
    let mut c = Collector::new(path, identity);
    match header.data.as_str() {
        "binary" => read_binary(path, bytes, &header, &layout, &mut c)?,
        "ascii" => read_ascii(path, bytes, &header, &layout, &mut c)?,
        "binary_compressed" => {
            return Err(Error::at_line(
                path,
                header.data_line,
                "DATA binary_compressed is not supported: convert to binary first, \
                 e.g. `pcl_convert_pcd_ascii_binary in.pcd out.pcd 1`",
            ));
        }
        other => {
            return Err(Error::at_line(
                path,
                header.data_line,
                format!("unknown DATA kind '{other}' (expected ascii or binary)"),
            ));
        }
    }
    let mut points = c.finish()?;
    if let Some(v) = header.viewpoint {
        let inv = v.inverse();
        for p in &mut points {
            let q = inv * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            *p = [q.x as f32, q.y as f32, q.z as f32];
        }
    }
    Ok((points, header.viewpoint))
}

/// A header line's values with the (1-based) line they came from.
type AtLine<T> = Option<(usize, T)>;

/// The PCD header as written, up to and including the `DATA` line.
#[derive(Default)]
struct Header {
    names: AtLine<Vec<String>>,
    sizes: AtLine<Vec<usize>>,
    types: AtLine<Vec<PcdType>>,
    counts: AtLine<Vec<usize>>,
    width: Option<usize>,
    height: Option<usize>,
    points: AtLine<usize>,
    /// The sensor pose in the cloud's frame, when not the identity.
    viewpoint: Option<Pose3>,
    /// The `DATA` kind, lower case.
    data: String,
    data_line: usize,
    /// Byte offset of the body (after the `DATA` line's terminator).
    body: usize,
}

impl Header {
    /// Reads the header lines up to `DATA`; an error on unknown keywords,
    /// malformed values or a missing `DATA` line.
    fn parse(path: &Path, bytes: &[u8]) -> Result<Self> {
        let mut h = Header::default();
        let mut data_end = None;
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
            if key == "DATA" {
                h.data = vals
                    .first()
                    .map(|s| s.to_ascii_lowercase())
                    .unwrap_or_default();
                h.data_line = no;
                data_end = Some(begin + raw.len());
                break;
            }
            h.line(path, no, &key, &vals)?;
        }
        let data_end = data_end.ok_or_else(|| {
            Error::in_file(
                path,
                "no DATA line: not a PCD file, or the header is truncated",
            )
        })?;
        h.body = bytes[data_end..]
            .iter()
            .position(|&c| c == b'\n')
            .map_or(bytes.len(), |i| data_end + i + 1);
        Ok(h)
    }

    /// Takes header line `no`: keyword `key` (upper case) with `vals`.
    fn line(&mut self, path: &Path, no: usize, key: &str, vals: &[&str]) -> Result<()> {
        let num = |t: &str, what: &str| {
            t.parse::<usize>().map_err(|_| {
                Error::at_line(
                    path,
                    no,
                    format!("{what}: '{t}' is not a non-negative integer"),
                )
            })
        };
        match key {
            "VERSION" => {}
            "FIELDS" | "COLUMNS" => {
                self.names = Some((no, vals.iter().map(|s| s.to_string()).collect()));
            }
            "SIZE" => {
                self.sizes = Some((
                    no,
                    vals.iter().map(|t| num(t, "SIZE")).collect::<Result<_>>()?,
                ));
            }
            "COUNT" => {
                self.counts = Some((
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
                self.types = Some((no, ts));
            }
            "WIDTH" | "HEIGHT" | "POINTS" => {
                let [v] = vals else {
                    return Err(Error::at_line(path, no, format!("{key} takes one value")));
                };
                let v = num(v, key)?;
                match key {
                    "WIDTH" => self.width = Some(v),
                    "HEIGHT" => self.height = Some(v),
                    _ => self.points = Some((no, v)),
                }
            }
            "VIEWPOINT" => self.viewpoint = viewpoint(path, no, vals)?,
            other => {
                return Err(Error::at_line(
                    path,
                    no,
                    format!("unknown PCD header keyword '{other}' (not a PCD file?)"),
                ));
            }
        }
        Ok(())
    }
}

/// The pose of a `VIEWPOINT tx ty tz qw qx qy qz` line (`None`: identity).
fn viewpoint(path: &Path, no: usize, vals: &[&str]) -> Result<Option<Pose3>> {
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
    let is_identity = pose.translation.vector.norm() < 1e-12 && pose.rotation.angle() < 1e-12;
    Ok((!is_identity).then_some(pose))
}

/// What the body holds, from a checked header: the fields, which of them
/// are x, y and z, and how many points.
struct Layout {
    fields: Vec<PcdField>,
    /// Indices into `fields` of x, y and z.
    xyz: [usize; 3],
    /// Points declared.
    n: usize,
}

impl Layout {
    /// Checks that the header's field lines agree and name x, y and z, and
    /// that it declares a point count.
    fn of(path: &Path, h: &Header) -> Result<Self> {
        let (names_line, names) = h
            .names
            .as_ref()
            .ok_or_else(|| Error::in_file(path, "header has no FIELDS line"))?;
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
        let (sl, sizes) = h
            .sizes
            .as_ref()
            .ok_or_else(|| Error::in_file(path, "header has no SIZE line"))?;
        check_len("SIZE", *sl, sizes.len())?;
        let (tl, types) = h
            .types
            .as_ref()
            .ok_or_else(|| Error::in_file(path, "header has no TYPE line"))?;
        check_len("TYPE", *tl, types.len())?;
        let (cl, counts) = h.counts.clone().unwrap_or((*names_line, vec![1; nf]));
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
                    *sl,
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
            let i = fields.iter().position(|f| f.name == *axis).ok_or_else(|| {
                Error::at_line(path, *names_line, format!("FIELDS has no '{axis}'"))
            })?;
            if fields[i].count != 1 {
                return Err(Error::at_line(
                    path,
                    cl,
                    format!("field '{axis}' must have COUNT 1"),
                ));
            }
            xyz[k] = i;
        }
        let n = point_count(path, h)?;
        Ok(Self { fields, xyz, n })
    }
}

/// The points declared: `POINTS`, else `WIDTH × HEIGHT` (which must agree
/// with `POINTS` when both are given); an error when none.
fn point_count(path: &Path, h: &Header) -> Result<usize> {
    let wh = match (h.width, h.height) {
        (Some(w), Some(h)) => w.checked_mul(h),
        (Some(w), None) => Some(w),
        _ => None,
    };
    let n = match (h.points, wh) {
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
    Ok(n)
}

/// Reads a `DATA binary` body: `n` packed little-endian records, exactly.
fn read_binary(path: &Path, bytes: &[u8], h: &Header, l: &Layout, c: &mut Collector) -> Result<()> {
    let (fields, xyz, n, body) = (&l.fields, l.xyz, l.n, h.body);
    let record: usize = fields.iter().map(|f| f.size * f.count).sum();
    let offset = |i: usize| -> usize { fields[..i].iter().map(|f| f.size * f.count).sum() };
    let offs = xyz.map(offset);
    let need = n
        .checked_mul(record)
        .ok_or_else(|| Error::in_file(path, format!("POINTS {n} × {record} bytes overflows")))?;
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
    Ok(())
}

/// Reads a `DATA ascii` body: one point per non-blank line, `n` exactly.
fn read_ascii(path: &Path, bytes: &[u8], h: &Header, l: &Layout, c: &mut Collector) -> Result<()> {
    let (fields, n) = (&l.fields, l.n);
    let columns: usize = fields.iter().map(|f| f.count).sum();
    let col = l
        .xyz
        .map(|i| fields[..i].iter().map(|f| f.count).sum::<usize>());
    let mut k = 0usize;
    let mut last = h.data_line;
    for (no, _, raw) in lines_from(bytes, h.body, h.data_line + 1) {
        last = no;
        let text =
            std::str::from_utf8(raw).map_err(|_| Error::at_line(path, no, "line is not text"))?;
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
    Ok(())
}
